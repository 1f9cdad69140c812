"""``diffloc task=train_nerf``: config composition, a tiny run, bad submaps."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from diffloc.config import compose_config
from diffloc.maps.nerf.export import load_field
from diffloc.maps.nerf.field import FieldConfig
from diffloc.maps.nerf.sampler import SamplerConfig
from diffloc.maps.nerf.submaps import load_submaps
from diffloc.pipeline.nerf_config import TrainNerfTaskConfig
from diffloc.pipeline.nerf_stage import train_nerf_submap


def test_task_config_composes_with_overrides() -> None:
    cfg = OmegaConf.to_object(
        compose_config(["task=train_nerf", "task.submap=3", "task.train.field.encoding=hashgrid"])
    )
    assert isinstance(cfg.task, TrainNerfTaskConfig)
    assert cfg.task.submap == 3 and cfg.task.train.field.encoding == "hashgrid"
    assert cfg.task.train.loss.depth_sigma_m == 0.01


def _tiny(tmp_path: Path, **changes) -> TrainNerfTaskConfig:
    cfg = TrainNerfTaskConfig(out_dir=str(tmp_path / "nerf"), epochs=1)
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
    assert summary["submaps"] == 2 and summary["steps"] == 2
    out = tmp_path / "nerf"
    submaps, _ = load_submaps(out / "submaps.json")
    assert len(submaps) == 2 and (out / "submaps.png").is_file()
    assert (out / "submap_1" / "checkpoints" / "last.ckpt").is_file()
    field, _ = load_field(out / "submap_1" / "field")
    assert field.config.triplane_resolutions == [16]


def test_bad_submaps_are_clear_errors(tiny_indoor_dataset: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="task.submap=5"):
        train_nerf_submap(tiny_indoor_dataset, _tiny(tmp_path, submap=5), False)
    single = _tiny(tmp_path)
    single.submaps.num_submaps = 5
    single.submaps.overlap_m = 0.0
    with pytest.raises(ValueError, match="at least 2 training frames"):
        train_nerf_submap(tiny_indoor_dataset, single, False)
