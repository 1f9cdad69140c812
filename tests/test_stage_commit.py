"""A stage commits as a whole and is reused only while its config and inputs are unchanged.

Issue 17, findings 1 (a failed run leaves a map of the new config under the old record),
2 (``optimized/`` of an older ``build_db`` is used) and 8 (``.tmp-*`` folders of killed runs
are never cleaned), and the contract of :mod:`diffloc.pipeline.stage` itself.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from diffloc.io.identity import identity
from diffloc.maps.surfel import SurfelMapConfig
from diffloc.pipeline.build_map import BuildMapConfig, build_maps
from diffloc.pipeline.database_select import select_database
from diffloc.pipeline.database_stage import DatabaseConfig, database_dir
from diffloc.pipeline.hints import Command, MissingStageError, StaleStageError
from diffloc.pipeline.stage import open_stage, stage_key, verified_record
from tests.conftest import FINE_SURFELS, copy_dataset, run_task

COMMAND = Command("demo")


def _commit(folder: Path, key: dict, files: dict[str, str], owned=()) -> dict:
    with open_stage(folder, "demo", COMMAND) as stage:
        for name, text in files.items():
            (stage.workdir() / name).write_text(text)
        return stage.commit(key, {"count": len(files)}, list(files), owned)


def test_a_commit_writes_outputs_and_a_record_that_verifies(tmp_path: Path):
    key = stage_key({"a": 1}, {"input": {"kind": "file", "size": 1, "sha256": "x"}})
    record = _commit(tmp_path, key, {"out.txt": "hello"})
    assert (tmp_path / "out.txt").read_text() == "hello"
    assert verified_record(tmp_path, "demo", COMMAND) == record
    assert record["stage"]["outputs"]["out.txt"] == identity(tmp_path / "out.txt")
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".tmp")] == []


def test_a_failed_run_leaves_the_previous_result_and_record_intact(tmp_path: Path):
    key = stage_key({"a": 1}, {})
    record = _commit(tmp_path, key, {"out.txt": "old"})
    with pytest.raises(RuntimeError), open_stage(tmp_path, "demo", COMMAND) as stage:
        (stage.workdir() / "out.txt").write_text("new")
        raise RuntimeError("the stage failed before its commit")
    assert (tmp_path / "out.txt").read_text() == "old"
    assert verified_record(tmp_path, "demo", COMMAND) == record


def test_an_output_changed_after_the_commit_is_not_trusted(tmp_path: Path):
    key = stage_key({"a": 1}, {})
    _commit(tmp_path, key, {"out.txt": "old"})
    (tmp_path / "out.txt").write_text("half-written")
    with pytest.raises(StaleStageError, match=r"out\.txt is not the file .*demo\.json describes"):
        verified_record(tmp_path, "demo", COMMAND)
    with open_stage(tmp_path, "demo", COMMAND) as stage:
        assert stage.reusable(key) is None
    (tmp_path / "demo.json").unlink()
    with pytest.raises(MissingStageError, match="task=demo"):
        verified_record(tmp_path, "demo", COMMAND)


def test_reuse_needs_the_same_config_and_inputs(tmp_path: Path):
    key = stage_key({"a": 1}, {"input": {"sha256": "x"}})
    _commit(tmp_path, key, {"out.txt": "x"})
    with open_stage(tmp_path, "demo", COMMAND) as stage:
        assert stage.reusable(key) is not None
        assert stage.reusable(stage_key({"a": 2}, {"input": {"sha256": "x"}})) is None
        assert stage.reusable(stage_key({"a": 1}, {"input": {"sha256": "y"}})) is None


def test_outputs_the_new_run_does_not_make_are_removed(tmp_path: Path):
    key = stage_key({}, {})
    _commit(tmp_path, key, {"a.txt": "a", "b.txt": "b"})
    (tmp_path / "c.txt").write_text("an output of a run before the records")
    _commit(tmp_path, key, {"a.txt": "a"}, owned=["c.txt"])
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".")) == [
        "a.txt",
        "demo.json",
    ]


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
    assert summary == json.loads(files["build_map.json"])


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
    assert optimized["config"]["noise_seed"] == 1
    assert select_database(root, cfg, "optimized").path == database_dir(root, cfg) / "optimized"
