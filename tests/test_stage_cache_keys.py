"""Stages never reuse stale or half-written results (issue 17, findings 1, 2 and 8).

These tests use only the stages' public entry points, so they run (and fail) on the code
before the stage contract too.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from diffloc.maps.surfel import SurfelMapConfig
from diffloc.pipeline.build_map import BuildMapConfig, MapSummary, build_maps
from diffloc.pipeline.database_select import select_database
from diffloc.pipeline.database_stage import DatabaseConfig, database_dir
from diffloc.pipeline.hints import StaleStageError
from tests.conftest import FINE_SURFELS, copy_dataset, run_task


def test_temporaries_of_killed_runs_are_removed_by_the_next_run(
    tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory
):
    """Finding 8: hidden ``.tmp-*`` folders and files of killed runs stayed forever."""
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "temporaries")
    leftovers = [
        root / "map" / ".tmp-build_map-k1ll3d",
        root / "map" / ".surfel_map.ply.tmp-x",
        root / "map" / ".surfel_preview.png.tmp.png",
        root / "map" / ".build_map.json.abc123.tmp",
    ]
    leftovers[0].mkdir()
    (leftovers[0] / "surfel_map.ply").write_bytes(b"half")
    leftovers[1].mkdir()
    for path in leftovers[2:]:
        path.write_bytes(b"half")
    build_maps(root, BuildMapConfig(point_maps=[], preview_frames=1), FINE_SURFELS, False)
    assert [path for path in leftovers if path.exists()] == []


def test_a_failed_map_run_leaves_the_previous_map_and_record_intact(
    tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory
):
    """Finding 1: a run that failed (here on a corrupt image) after writing
    ``surfel_map.ply`` left the map of its config under the previous run's record; the next
    run with the previous config reused that wrong map."""
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "failed")
    files = {
        name: (root / "map" / name).read_bytes() for name in ("surfel_map.ply", "build_map.json")
    }
    image = root / "mapping" / "rgb" / "000000.png"
    good = image.read_bytes()
    image.write_bytes(b"not a png")
    coarser = SurfelMapConfig(voxel_size_m=0.05, mean_radius_m=0.05, normal_radius_m=0.15)
    with pytest.raises(ValueError, match=r"000000\.png"):
        build_maps(root, BuildMapConfig(point_maps=[], preview_frames=1), coarser, False)
    assert {name: (root / "map" / name).read_bytes() for name in files} == files
    image.write_bytes(good)
    summary = build_maps(root, BuildMapConfig(point_maps=[], preview_frames=1), FINE_SURFELS, False)
    assert (root / "map" / "surfel_map.ply").read_bytes() == files["surfel_map.ply"]
    assert summary == MapSummary.from_record(json.loads(files["build_map.json"]))


@pytest.mark.filterwarnings("ignore::diffloc.pipeline.database_stage.OptimisationRejectedWarning")
def test_an_optimised_database_of_an_older_build_is_refused(
    tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory
):
    """Finding 2: after ``build_db`` ran again (another ``db.noise_seed``, same folder),
    ``relocalize`` and ``optimize_db``'s readers used the old ``optimized/`` without a word."""
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "older")
    noisy = ("db.noise_sigma=0.05", "db.optim.min_pairs=5", "db.optim_check.accept=always")
    run_task("build_db", root, *noisy)
    run_task("optimize_db", root, *noisy)
    run_task("build_db", root, *noisy, "db.noise_seed=1")
    cfg = DatabaseConfig(noise_sigma=0.05, noise_seed=1)
    assert database_dir(root, cfg) == database_dir(root, DatabaseConfig(noise_sigma=0.05))
    with pytest.raises(StaleStageError, match=r"optimize_db\.json was made from another"):
        select_database(root, cfg, "optimized")
    with pytest.raises(ValueError, match=r"optimize_db\.json .*task=optimize_db"):
        run_task("relocalize", root, *noisy, "db.noise_seed=1", f"task.out_dir={root / 'r'}")
    optimized = run_task("optimize_db", root, *noisy, "db.noise_seed=1")
    assert optimized.config["noise_seed"] == 1
    assert select_database(root, cfg, "optimized").path == database_dir(root, cfg) / "optimized"
