"""``diffloc task=train_nerf``: config composition, a tiny run, bad submaps."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from diffloc.config import compose_config, to_object
from diffloc.maps.nerf.export import load_field
from diffloc.maps.nerf.field import FieldConfig
from diffloc.maps.nerf.sampler import SamplerConfig
from diffloc.maps.nerf.submaps import load_submaps
from diffloc.pipeline import nerf_stage
from diffloc.pipeline.nerf_config import TrainNerfConfig
from diffloc.pipeline.nerf_stage import train_nerf_submap


def test_task_config_composes_with_overrides() -> None:
    cfg = to_object(
        compose_config(["task=train_nerf", "nerf.submap=3", "nerf.train.field.encoding=hashgrid"])
    )
    assert isinstance(cfg.nerf, TrainNerfConfig) and cfg.task.name == "train_nerf"
    assert cfg.nerf.submap == 3 and cfg.nerf.train.field.encoding == "hashgrid"
    assert cfg.nerf.train.loss.depth_sigma_m == 0.01


def _tiny(tmp_path: Path, **changes) -> TrainNerfConfig:
    cfg = TrainNerfConfig(out_dir=str(tmp_path / "nerf"), epochs=1)
    cfg.submaps.num_submaps = 2
    cfg.data.holdout_every = 0
    cfg.data.lidar_stride = 8
    cfg.train = dataclasses.replace(
        cfg.train,
        field=FieldConfig(triplane_resolutions=[16], triplane_channels=4, hidden=16),
        sampler=SamplerConfig(grid_resolution=16, coarse_samples=16, importance_samples=8),
        ray_batch=64,
        lidar_batch=32,
        normal_batch=8,
        steps_per_epoch=2,
    )
    return dataclasses.replace(cfg, **changes)


def test_train_nerf_writes_submaps_logs_and_a_loadable_field(
    tiny_indoor_dataset: Path, tmp_path: Path
) -> None:
    summary = train_nerf_submap(tiny_indoor_dataset, _tiny(tmp_path, submap=1), False)
    assert summary.submaps == 2 and summary.steps == 2
    out = tmp_path / "nerf"
    submaps, _ = load_submaps(out / "submaps.json")
    assert len(submaps) == 2 and (out / "submaps.png").is_file()
    assert (out / "submap_1" / "checkpoints" / "last.ckpt").is_file()
    field, _ = load_field(out / "submap_1" / "field")
    assert field.config.triplane_resolutions == [16]


def test_a_second_run_reuses_the_committed_field_and_a_failed_one_keeps_it(
    tiny_indoor_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = _tiny(tmp_path, submap=0)
    first = train_nerf_submap(tiny_indoor_dataset, cfg, False)
    field = tmp_path / "nerf" / "submap_0" / "field"
    before = {p.name: p.read_bytes() for p in field.iterdir()}

    def no_training(*args, **kwargs):
        raise AssertionError("trained again although the settings and data are unchanged")

    monkeypatch.setattr(nerf_stage, "fit_submap", no_training)
    assert train_nerf_submap(tiny_indoor_dataset, cfg, False) == first
    with pytest.raises(AssertionError, match="trained again"):  # other settings: trains
        train_nerf_submap(tiny_indoor_dataset, dataclasses.replace(cfg, epochs=2), False)
    assert {p.name: p.read_bytes() for p in field.iterdir()} == before
    assert not list(field.parent.glob(".tmp-*"))


def test_bad_submaps_are_clear_errors(tiny_indoor_dataset: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="nerf.submap=5"):
        train_nerf_submap(tiny_indoor_dataset, _tiny(tmp_path, submap=5), False)
    single = _tiny(tmp_path)
    single.submaps.num_submaps = 5
    single.submaps.overlap_m = 0.0
    with pytest.raises(ValueError, match="at least 2 training frames"):
        train_nerf_submap(tiny_indoor_dataset, single, False)
