"""Configuration is checked before work starts, and what is recorded is what is used.

Issue 17, findings 5 (a typo in a list of cloud names is ignored and stale point maps stay),
7 (``dataset.json`` records a frame rate that is not the one used) and 8 (range errors surface
only after the work), and ``task.render_batch=0`` of finding 1.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from diffloc.cli import run
from diffloc.io.dataset import read_sequence
from diffloc.pipeline.build_map import BuildMapConfig, build_maps
from tests.conftest import FINE_SURFELS, TINY, compose_config, copy_dataset, run_task


def _map_files(root: Path) -> dict[str, bytes]:
    """Every file of ``<root>/map`` (top level) and its bytes."""
    return {p.name: p.read_bytes() for p in sorted((root / "map").iterdir()) if p.is_file()}


@pytest.mark.parametrize("setting", ["task.clouds=[tls_mapp]", "task.point_maps=[lidar_mapp]"])
def test_an_unknown_cloud_name_is_refused_before_any_work(
    tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory, setting: str
):
    """Finding 5: a typo in a list of cloud names was skipped like an absent cloud, and the
    map was built from fewer sources."""
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "typo")
    before = _map_files(root)
    key = setting.split("=")[0]
    with pytest.raises(ValueError, match=rf"{key}.*unknown map clouds.*mapp.*tls_map"):
        run_task("build_map", root, setting)
    assert _map_files(root) == before


def test_point_maps_no_longer_asked_for_are_removed(
    tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory
):
    """Finding 5: a point map of a cloud dropped from ``task.point_maps`` stayed in ``map/``
    beside the new maps, as if it belonged to them."""
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "stale")
    cfg = BuildMapConfig(point_maps=["tls_map"], preview_frames=1)
    summary = build_maps(root, cfg, FINE_SURFELS, show_progress=False)
    assert (root / "map" / "tls_point_map.ply").is_file() and "tls_point_map" in summary.point_maps
    build_maps(root, BuildMapConfig(point_maps=[], preview_frames=1), FINE_SURFELS, False)
    assert not (root / "map" / "tls_point_map.ply").exists()


def test_render_batch_zero_is_refused_before_the_map_is_written(
    tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory
):
    """Finding 1: ``task.render_batch=0`` failed only after ``surfel_map.ply`` of the new
    configuration had replaced the old one under the old record."""
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "batch")
    before = _map_files(root)
    with pytest.raises(ValueError, match=r"task\.render_batch"):
        run_task("build_map", root, "task.render_batch=0", "map.voxel_size_m=0.05")
    assert _map_files(root) == before


def test_dataset_json_records_the_frame_rate_each_sequence_was_simulated_at(
    tiny_indoor_dataset: Path,
):
    """Finding 7: a sequence's ``frame_rate_hz`` of 0 (or a bad one) was recorded while the
    scene's rate was used; the record now holds the rate the timestamps follow."""
    info = json.loads((tiny_indoor_dataset / "dataset.json").read_text())
    for name in info["sequences"]:
        used = info["sequence_trajectories"][name]["frame_rate_hz"]
        timestamps = np.asarray(read_sequence(tiny_indoor_dataset, name).timestamps)
        assert used == pytest.approx(1.0 / float(np.median(np.diff(timestamps))))


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("scene.map.voxel_size_m=-0.1", r"scene\.map\.voxel_size_m"),
        ("scene.map.normal_radius_m=0", r"scene\.map\.normal_radius_m"),
        ("scene.sequences.0.speed_variation_mps=5", r"scene\.sequences\.0 .*speed_variation"),
    ],
)
def test_scene_ranges_are_refused_before_anything_is_simulated(
    tmp_path: Path, setting: str, message: str
):
    """Finding 8: ``scene.map.voxel_size_m<0`` surfaced only after every sequence was
    simulated (and a sequence's bad speed variation after the sequences before it)."""
    out = tmp_path / "scene"
    with pytest.raises(ValueError, match=message):
        run(compose_config(TINY + ["task=simulate", f"out_dir={out}", setting]))
    assert not out.exists()


@pytest.mark.parametrize(
    ("task", "setting"),
    [
        ("relocalize", "reloc.max_trans_m=-0.3"),
        ("relocalize", "reloc.max_rot_deg=nan"),
        ("main", "reloc.max_trans_m=0"),
    ],
)
def test_reloc_ranges_are_refused_before_any_stage_runs(
    tiny_indoor_dataset: Path, tmp_path_factory: pytest.TempPathFactory, task: str, setting: str
):
    """Finding 8: ``reloc.max_trans_m<0`` surfaced only after the stages before it ran (or
    never: it was used as given)."""
    root = copy_dataset(tiny_indoor_dataset, tmp_path_factory, "ranges")
    key = setting.split("=")[0].replace(".", r"\.")
    with pytest.raises(ValueError, match=key):
        run_task(task, root, setting, f"task.out_dir={root / 'reloc'}")
    assert not (root / "db").exists() and not (root / "map" / "build_map.json").exists()


def test_a_misspelt_sequence_is_refused_before_relocalisation(tiny_indoor_dataset: Path):
    with pytest.raises(FileNotFoundError, match=r"query_sam.*query_same"):
        run_task("relocalize", tiny_indoor_dataset, "reloc.sequences=[query_sam]")


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("db.features.max_keypoints=0", r"^db\.features\.max_keypoints must be a positive int"),
        ("db.optim.min_pairs=-1", r"^db\.optim\.min_pairs must be >= 0"),
        ("map.voxel_size_m=-1", r"^map\.voxel_size_m must be a positive finite number"),
        ("db.noise_sigma=-0.1", r"^db\.noise_sigma must be a finite number >= 0"),
        ("db.noise_sigma=nan", r"^db\.noise_sigma must be a finite number >= 0"),
        ("db.radius_px_per_prior_m=-1", r"^db\.radius_px_per_prior_m must be a finite number"),
        ("db.point_gate_m_per_prior_m=-1", r"^db\.point_gate_m_per_prior_m must be a finite"),
    ],
)
def test_a_bad_nested_value_is_named_by_its_full_key_before_any_work(
    tiny_indoor_mapped: Path, setting: str, message: str
):
    """A nested schema's check does not know where it sits (``max_keypoints must be ...``):
    the error names the full key, so the user can find the setting; nothing is written."""
    before = sorted(p.relative_to(tiny_indoor_mapped) for p in tiny_indoor_mapped.rglob("*"))
    with pytest.raises(ValueError, match=message):
        run_task("build_db", tiny_indoor_mapped, setting)
    assert (
        sorted(p.relative_to(tiny_indoor_mapped) for p in tiny_indoor_mapped.rglob("*")) == before
    )


@pytest.mark.parametrize(
    ("task", "setting", "message"),
    [
        ("relocalize", "retriever=bow reloc.retriever.words=0", r"^reloc\.retriever\.words must"),
        ("relocalize", "reloc.retriever.clusters=0", r"^reloc\.retriever\.clusters must be a p"),
        ("train_nerf", "nerf.epochs=0", r"^nerf\.epochs must be an integer >= 1"),
        ("train_nerf", "nerf.submap=-1", r"^nerf\.submap must be an integer >= 0"),
        ("simulate", "scene.camera.width=0", r"^scene\.camera\.width must be a positive int"),
        ("simulate", "scene.camera.hfov_deg=200", r"^scene\.camera\.hfov_deg must be in"),
        ("simulate", "scene.lidar.rate_hz=0", r"^scene\.lidar\.rate_hz must be a finite number"),
    ],
)
def test_task_ranges_are_refused_before_anything_is_written(
    tiny_indoor_mapped: Path, tmp_path: Path, task: str, setting: str, message: str
):
    """Until now these surfaced only in the middle of the task (an empty vocabulary, a
    training of no epochs that wrote its run folder, a simulation that had taken its lock)."""
    before = sorted(p.relative_to(tiny_indoor_mapped) for p in tiny_indoor_mapped.rglob("*"))
    out = tmp_path / "out"
    where = {"simulate": f"out_dir={out}", "relocalize": f"task.out_dir={out}"}
    with pytest.raises(ValueError, match=message):
        run_task(
            task, tiny_indoor_mapped, *setting.split(), *([where[task]] if task in where else [])
        )
    assert (
        sorted(p.relative_to(tiny_indoor_mapped) for p in tiny_indoor_mapped.rglob("*")) == before
    )
    assert list(tmp_path.iterdir()) == []


def test_a_cloud_named_twice_is_refused(tiny_indoor_mapped: Path):
    """It was accepted and the cloud's points went into the surfel input twice."""
    with pytest.raises(ValueError, match=r"task\.clouds names \['tls_map'\] more than once"):
        run_task("build_map", tiny_indoor_mapped, "task.clouds=[lidar_map,tls_map,tls_map]")
