"""``diffloc task=train_nerf``: config composition, a tiny run, bad submaps, checkpoints that
must not be resumed, a spoilt field, a diverged training, bad ``nerf.*`` values."""

from __future__ import annotations

import dataclasses
import math
import re
import shutil
import warnings
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from diffloc.cli import check_values
from diffloc.config import compose_config, to_object
from diffloc.maps.nerf.export import load_field
from diffloc.maps.nerf.field import FieldConfig
from diffloc.maps.nerf.sampler import SamplerConfig
from diffloc.maps.nerf.submaps import load_submaps
from diffloc.maps.nerf.train import fit_submap
from diffloc.pipeline import nerf_stage
from diffloc.pipeline.nerf_config import TrainNerfConfig
from diffloc.pipeline.nerf_stage import submap_training_data, train_nerf_submap


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


def test_the_empty_space_loss_in_a_closed_room_is_a_clear_error(
    tiny_indoor_dataset: Path, tmp_path: Path
) -> None:
    # the task builds the no-return rays; the tiny room returns in every direction
    cfg = _tiny(tmp_path, submap=1)
    loss = dataclasses.replace(cfg.train.loss, empty_weight=0.1)
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, loss=loss))
    with pytest.raises(ValueError, match="every direction of the lidar's grid has a return"):
        train_nerf_submap(tiny_indoor_dataset, cfg, False)


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


def test_scripts_get_the_submap_and_rays_the_task_trains_on(
    tiny_indoor_dataset: Path, tmp_path: Path
) -> None:
    """``submap_training_data`` (the experiment scripts' entry) is the task's own clustering
    and ray building: the same frames, held-out frames and lidar rays as the record reports."""
    cfg = _tiny(tmp_path, submap=1)
    summary = train_nerf_submap(tiny_indoor_dataset, cfg, False)
    seq, submap, rays = submap_training_data(tiny_indoor_dataset, cfg)
    assert len(seq) > 0 and len(submap.frames) == summary.frames
    assert (len(rays.frames), len(rays.heldout)) == (summary.train_frames, summary.heldout_frames)
    assert rays.no_return is None  # the empty-space loss is off
    loss = dataclasses.replace(cfg.train.loss, empty_weight=0.1)
    with_empty = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, loss=loss))
    assert submap_training_data(tiny_indoor_dataset, with_empty)[2].no_return is not None
    with pytest.raises(ValueError, match=r"nerf.submap=2 but the clustering made 2 submaps"):
        submap_training_data(tiny_indoor_dataset, dataclasses.replace(cfg, submap=2))


def _field_bytes(out: Path, submap: int = 0) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in (out / f"submap_{submap}" / "field").iterdir()}


def _trained(dataset: Path, cfg: TrainNerfConfig) -> dict[str, bytes]:
    """The field of a training from scratch with ``cfg`` (in its own folder)."""
    train_nerf_submap(dataset, cfg, False)
    return _field_bytes(Path(cfg.out_dir), cfg.submap)


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])


def _nan_weight(path: Path) -> None:
    state = torch.load(path, map_location="cpu", weights_only=True)
    next(iter(state["state_dict"].values())).view(-1)[0] = math.nan
    torch.save(state, path)


def _without_identity(path: Path) -> None:
    """A checkpoint as diffloc wrote it before checkpoints named their training."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    del state[nerf_stage.TRAINING_KEY]
    torch.save(state, path)


@pytest.mark.parametrize(
    ("spoil", "reason"),
    [
        (_truncate, "cannot be read"),
        (_nan_weight, "non-finite weights"),
        (_without_identity, "does not say which training"),
    ],
)
def test_a_spoilt_checkpoint_is_not_resumed_and_the_run_trains_from_scratch(
    tiny_indoor_dataset: Path, tmp_path: Path, spoil: Callable[[Path], None], reason: str
) -> None:
    expected = _trained(tiny_indoor_dataset, _tiny(tmp_path / "scratch", epochs=2))
    cfg = _tiny(tmp_path)
    train_nerf_submap(tiny_indoor_dataset, cfg, False)  # epoch 1 of 2: a checkpoint to resume
    checkpoint = tmp_path / "nerf" / "submap_0" / "checkpoints" / "last.ckpt"
    spoil(checkpoint)
    with pytest.warns(UserWarning, match=rf"last\.ckpt is not resumed.*{reason}"):
        summary = train_nerf_submap(tiny_indoor_dataset, dataclasses.replace(cfg, epochs=2), False)
    assert summary.steps == 4
    assert _field_bytes(tmp_path / "nerf") == expected


def test_an_intact_checkpoint_is_resumed_to_the_uninterrupted_field(
    tiny_indoor_dataset: Path, tmp_path: Path
) -> None:
    expected = _trained(tiny_indoor_dataset, _tiny(tmp_path / "scratch", epochs=2))
    cfg = _tiny(tmp_path)
    train_nerf_submap(tiny_indoor_dataset, cfg, False)
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*is not resumed")
        train_nerf_submap(tiny_indoor_dataset, dataclasses.replace(cfg, epochs=2), False)
    assert _field_bytes(tmp_path / "nerf") == expected


def test_the_checkpoint_of_other_settings_is_not_resumed(
    tiny_indoor_dataset: Path, tmp_path: Path
) -> None:
    """It holds as many steps as asked for: resumed, it would be exported as is."""
    expected = _trained(tiny_indoor_dataset, _tiny(tmp_path / "scratch"))
    cfg = _tiny(tmp_path)
    other = dataclasses.replace(cfg.train, lr_network=cfg.train.lr_network / 5)
    train_nerf_submap(tiny_indoor_dataset, dataclasses.replace(cfg, train=other), False)
    with pytest.warns(UserWarning, match="belongs to a training of other settings"):
        train_nerf_submap(tiny_indoor_dataset, cfg, False)
    assert _field_bytes(tmp_path / "nerf") == expected


def test_a_checkpoint_beside_another_trainings_files_is_not_resumed(
    tiny_indoor_dataset: Path, tmp_path: Path
) -> None:
    """A checkpoint of another learning rate in this training's folder (a copied checkpoints
    folder, or one whose removal failed) is told apart by what it holds, not by its folder
    (trained from scratch then, as the test of other settings above checks byte for byte)."""
    cfg = _tiny(tmp_path)
    other = _tiny(tmp_path / "other")
    other.train = dataclasses.replace(cfg.train, lr_network=cfg.train.lr_network / 5)
    train_nerf_submap(tiny_indoor_dataset, other, False)
    train_nerf_submap(tiny_indoor_dataset, cfg, False)
    checkpoints = Path(cfg.out_dir) / "submap_0" / "checkpoints"
    shutil.rmtree(checkpoints)
    shutil.copytree(Path(other.out_dir) / "submap_0" / "checkpoints", checkpoints)
    with pytest.warns(UserWarning, match="belongs to a training of other settings"):
        train_nerf_submap(tiny_indoor_dataset, dataclasses.replace(cfg, epochs=2), False)


def test_a_checkpoint_past_the_epochs_asked_for_is_not_resumed(
    tiny_indoor_dataset: Path, tmp_path: Path
) -> None:
    expected = _trained(tiny_indoor_dataset, _tiny(tmp_path / "scratch"))
    cfg = _tiny(tmp_path)
    train_nerf_submap(tiny_indoor_dataset, dataclasses.replace(cfg, epochs=2), False)
    with pytest.warns(UserWarning, match=r"past nerf\.epochs \(4 steps, 2 asked for\)"):
        assert train_nerf_submap(tiny_indoor_dataset, cfg, False).steps == 2
    assert _field_bytes(tmp_path / "nerf") == expected


def test_a_field_spoilt_since_its_record_is_made_again(
    tiny_indoor_dataset: Path, tmp_path: Path
) -> None:
    cfg = _tiny(tmp_path)
    train_nerf_submap(tiny_indoor_dataset, cfg, False)
    expected = _field_bytes(tmp_path / "nerf")
    _truncate(tmp_path / "nerf" / "submap_0" / "field" / "field.safetensors")
    train_nerf_submap(tiny_indoor_dataset, cfg, False)
    assert _field_bytes(tmp_path / "nerf") == expected


def test_a_diverged_training_is_refused_and_nothing_is_committed(
    tiny_indoor_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def diverging(*args, **kwargs):
        module = fit_submap(*args, **kwargs)
        with torch.no_grad():
            next(module.field.parameters()).view(-1)[0] = math.inf
        return module

    monkeypatch.setattr(nerf_stage, "fit_submap", diverging)
    with pytest.raises(ValueError, match=r"diverged .* lower nerf\.train\.lr_encoding"):
        train_nerf_submap(tiny_indoor_dataset, _tiny(tmp_path), False)
    run_dir = tmp_path / "nerf" / "submap_0"
    assert not (run_dir / "field").exists() and not (run_dir / "train_nerf.json").exists()


@pytest.mark.parametrize(
    "override",
    [
        "nerf.train.lr_network=-0.01",
        "nerf.train.lr_encoding=nan",
        "nerf.train.ray_batch=0",
        "nerf.train.normal_batch=2000",
        "nerf.train.seed=-1",
        "nerf.train.field.encoding=voxels",
        "nerf.train.field.triplane_resolutions=[]",
        "nerf.train.field.hidden=0",
        "nerf.train.field.hash_max_resolution=8",
        "nerf.train.field.init_std=0",
        "nerf.train.sampler.near_m=-1",
        "nerf.train.sampler.far_m=0.01",
        "nerf.train.sampler.grid_decay=2",
        "nerf.train.sampler.coarse_samples=0",
        "nerf.train.sampler.skip_density=-1",
        "nerf.train.sampler.min_weight=2",
        "nerf.train.sampler.grad_min_weight=-2",
        "nerf.train.loss.depth_weight=-1",
        "nerf.train.loss.empty_weight=-1",
        "nerf.train.empty_batch=0",
        "nerf.train.loss.depth_sigma_m=0",
        "nerf.train.loss.depth_sigma_start_m=0.001",
        "nerf.data.image_scale=0",
        "nerf.data.lidar_stride=0",
        "nerf.data.box_percentile=50",
        "nerf.submaps.num_submaps=-1",
        "nerf.submaps.position_sigma_m=0",
        "nerf.submaps.overlap_m=-1",
    ],
)
def test_bad_nerf_values_are_refused_naming_the_key(override: str) -> None:
    key = override.split("=")[0]
    with pytest.raises(ValueError, match=rf"^{re.escape(key)} must be"):
        check_values(compose_config(["task=train_nerf", override]))
