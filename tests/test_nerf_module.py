"""Lightning training of a submap: resumption, export without pickle, bad input."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from diffloc.io.dataset import read_sequence
from diffloc.maps.nerf.data import (
    SubmapDataConfig,
    build_submap_rays,
    split_frames,
    training_sweeps,
)
from diffloc.maps.nerf.export import export_field, load_field
from diffloc.maps.nerf.field import FieldConfig
from diffloc.maps.nerf.module import NerfTrainConfig
from diffloc.maps.nerf.sampler import SamplerConfig
from diffloc.maps.nerf.train import fit_submap, load_checkpoint

DATA = SubmapDataConfig(image_scale=0.25, holdout_every=0, lidar_stride=8)


def _config(**changes) -> NerfTrainConfig:
    cfg = NerfTrainConfig(
        field=FieldConfig(triplane_resolutions=[16, 32], triplane_channels=4, hidden=16),
        sampler=SamplerConfig(
            grid_resolution=16,
            grid_update_every=2,
            coarse_samples=32,
            importance_samples=8,
            uniform_samples=8,
            guided_samples=4,
        ),
        ray_batch=128,
        lidar_batch=64,
        normal_batch=16,
        steps_per_epoch=3,
    )
    return dataclasses.replace(cfg, **changes)


@pytest.fixture(scope="module")
def tiny_rays(tiny_indoor_dataset: Path):
    seq = read_sequence(tiny_indoor_dataset, "mapping")
    return build_submap_rays(seq, list(range(len(seq))), DATA)


def test_split_frames_holds_out_every_nth_frame() -> None:
    assert split_frames(list(range(10)), 8) == ([1, 2, 3, 4, 5, 6, 7, 9], [0, 8])
    assert split_frames([3, 4], 0) == ([3, 4], [])


def test_submap_rays_cover_the_images_and_the_box_holds_the_cameras(tiny_rays) -> None:
    rays = tiny_rays
    assert len(rays.rgb) == len(rays.frames) * 40 * 30
    assert len(rays.lidar) > 0
    assert bool(torch.allclose(rays.directions.norm(dim=-1), torch.ones(1)))
    assert bool(((rays.origins >= rays.box_min) & (rays.origins <= rays.box_max)).all())
    valid = rays.lidar.normals.abs().sum(-1) > 0
    assert float(valid.float().mean()) > 0.5
    assert bool(torch.allclose(rays.lidar.normals[valid].norm(dim=-1), torch.ones(1)))


def test_resuming_continues_the_uninterrupted_loss_curve(tiny_rays, tmp_path: Path) -> None:
    cfg = _config()
    straight = fit_submap(tiny_rays, cfg, tmp_path / "a", epochs=2, show_progress=False)
    fit_submap(tiny_rays, cfg, tmp_path / "b", epochs=1, show_progress=False)
    resumed = fit_submap(tiny_rays, cfg, tmp_path / "b", epochs=2, resume=True, show_progress=False)
    assert len(straight.losses) == 6 and len(resumed.losses) == 3
    np.testing.assert_allclose(resumed.losses, straight.losses[3:], rtol=1e-6)
    assert (tmp_path / "b" / "logs" / "version_0" / "metrics.csv").is_file()


def test_training_lowers_the_loss(tiny_rays, tmp_path: Path) -> None:
    cfg = _config(steps_per_epoch=20)
    module = fit_submap(tiny_rays, cfg, tmp_path, epochs=1, show_progress=False)
    assert np.mean(module.losses[-5:]) < np.mean(module.losses[:5])


def test_export_round_trip_without_pickle(tiny_rays, tmp_path: Path) -> None:
    module = fit_submap(tiny_rays, _config(), tmp_path / "run", epochs=1, show_progress=False)
    out = export_field(tmp_path / "field", module.field, module.grid)
    field, grid = load_field(out)
    x = tiny_rays.origins[:50] + tiny_rays.directions[:50]
    with torch.no_grad():
        assert torch.equal(field.density(x), module.field.density(x))
    assert torch.equal(grid.density, module.grid.density)
    assert field.config == module.field.config


def test_a_checkpoint_loads_back_with_its_weights_and_step(tiny_rays, tmp_path: Path) -> None:
    cfg = _config()
    module = fit_submap(tiny_rays, cfg, tmp_path / "run", epochs=2, show_progress=False)
    loaded, step = load_checkpoint(tiny_rays, cfg, tmp_path / "run/checkpoints/last.ckpt")
    assert step == 2 * cfg.steps_per_epoch
    trained = module.state_dict()
    assert loaded.state_dict().keys() == trained.keys()
    assert all(torch.equal(v, trained[k]) for k, v in loaded.state_dict().items())
    assert not torch.equal(
        loaded.field.appearance.weight,
        fit_submap(
            tiny_rays, cfg, tmp_path / "other", 1, show_progress=False
        ).field.appearance.weight,
    )


def test_loading_a_pickle_or_foreign_json_is_a_clear_error(tiny_rays, tmp_path: Path) -> None:
    module = fit_submap(tiny_rays, _config(), tmp_path / "run", epochs=1, show_progress=False)
    out = export_field(tmp_path / "field", module.field, module.grid)
    torch.save(module.field.state_dict(), out / "field.safetensors")
    with pytest.raises(ValueError, match="safetensors"):
        load_field(out)
    (out / "field.json").write_text('{"format_version": 99}')
    with pytest.raises(ValueError, match="format_version"):
        load_field(out)
    with pytest.raises(FileNotFoundError):
        load_field(tmp_path / "missing")


def test_a_nan_loss_skips_the_step_with_a_warning(tiny_rays, tmp_path: Path) -> None:
    from diffloc.maps.nerf import module as module_mod

    original = module_mod.photometric_loss
    module_mod.photometric_loss = lambda a, b: original(a, b) * float("nan")
    try:
        with pytest.warns(UserWarning, match="non-finite loss"):
            module = fit_submap(tiny_rays, _config(), tmp_path, epochs=1, show_progress=False)
    finally:
        module_mod.photometric_loss = original
    assert module.losses == []
    fresh = fit_submap(tiny_rays, _config(), tmp_path / "fresh", epochs=0, show_progress=False)
    for a, b in zip(module.field.parameters(), fresh.field.parameters(), strict=True):
        assert torch.equal(a, b)


def test_a_submap_without_lidar_or_with_one_frame_is_refused(tiny_indoor_dataset: Path) -> None:
    seq = read_sequence(tiny_indoor_dataset, "mapping")
    with pytest.raises(ValueError, match="at least 2 training frames"):
        build_submap_rays(seq, [1], DATA)
    blind = dataclasses.replace(seq, lidar_paths=[], lidar_timestamps=np.zeros(0), T_wl=None)
    with pytest.raises(ValueError, match="no lidar sweeps"):
        build_submap_rays(blind, list(range(len(seq))), DATA)


def test_box_range_shrinks_the_box_to_the_near_returns_and_keeps_every_ray(
    tiny_indoor_dataset: Path,
) -> None:
    seq = read_sequence(tiny_indoor_dataset, "mapping")
    frames = list(range(len(seq)))
    full = build_submap_rays(seq, frames, DATA)
    near = build_submap_rays(seq, frames, dataclasses.replace(DATA, box_range_m=2.0))
    assert len(near.lidar) == len(full.lidar)
    assert bool((near.box_max - near.box_min < full.box_max - full.box_min).any())
    assert bool(((near.origins >= near.box_min) & (near.origins <= near.box_max)).all())
    with pytest.raises(ValueError, match="no lidar return within box_range_m"):
        build_submap_rays(seq, frames, dataclasses.replace(DATA, box_range_m=0.01))


def test_the_sweep_of_a_held_out_frame_is_not_trained_on(tiny_indoor_dataset: Path) -> None:
    """A lidar at half the camera rate (outdoors: 1 Hz against 2 Hz): training frame 1 lies
    as near to the sweep taken at held-out frame 0 as to the next one; the held-out frame's
    sweep must stay out of training, the others must stay in."""
    seq = read_sequence(tiny_indoor_dataset, "mapping")
    slow = dataclasses.replace(
        seq,
        lidar_paths=seq.lidar_paths[::2],
        lidar_timestamps=seq.lidar_timestamps[::2],
        T_wl=seq.T_wl[::2],
    )
    frames = list(range(len(seq)))
    train, heldout = split_frames(frames, 8)
    rays = build_submap_rays(slow, frames, dataclasses.replace(DATA, holdout_every=8))
    gap = np.abs(slow.lidar_timestamps[None] - slow.timestamps[heldout][:, None])
    at_heldout = set(gap.argmin(axis=1).tolist())
    sensors = {tuple(p) for p in rays.lidar.origins.unique(dim=0).tolist()}
    positions = [tuple(p) for p in slow.T_wl[:, :3, 3].float().tolist()]
    used = {i for i, p in enumerate(positions) if p in sensors}
    assert used and not used & at_heldout
    assert used == set(training_sweeps(slow, train, heldout))
    assert len(used) == len(positions) - len(at_heldout)


def test_the_learning_rate_decays_and_resumes_on_schedule(tiny_rays, tmp_path: Path) -> None:
    cfg = _config(lr_decay_steps=4, lr_final_ratio=0.25)
    straight = fit_submap(tiny_rays, cfg, tmp_path / "a", epochs=2, show_progress=False)
    lrs = [group["lr"] for group in straight.optimizers().optimizer.param_groups]
    np.testing.assert_allclose(lrs, [0.25 * cfg.lr_encoding, 0.25 * cfg.lr_network], rtol=1e-6)
    constant = fit_submap(tiny_rays, _config(), tmp_path / "c", epochs=2, show_progress=False)
    assert constant.losses[:2] == straight.losses[:2]  # the first update is at the full rate
    assert constant.losses[-1] != straight.losses[-1]
    fit_submap(tiny_rays, cfg, tmp_path / "b", epochs=1, show_progress=False)
    resumed = fit_submap(tiny_rays, cfg, tmp_path / "b", epochs=2, resume=True, show_progress=False)
    np.testing.assert_allclose(resumed.losses, straight.losses[3:], rtol=1e-6)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"lr_decay_steps": -1}, "lr_decay_steps"),
        ({"lr_final_ratio": 0.0}, "lr_final_ratio"),
        ({"lr_final_ratio": 1.5}, "lr_final_ratio"),
    ],
)
def test_bad_learning_rate_schedules_are_refused(changes: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        NerfTrainConfig(**changes)


def test_the_fused_adam_makes_the_updates_of_the_per_element_adam() -> None:
    """The optimiser (the fused CPU Adam) moves every parameter as ``torch.optim.Adam``'s
    per-element loop with the same groups does, float64, over three steps of fixed gradients."""
    from diffloc.maps.nerf.module import NerfModule

    cfg = _config(field=FieldConfig(encoding="hashgrid", hash_levels=3, hash_log2_table_size=8))
    module = NerfModule(cfg, torch.zeros(3), torch.ones(3), 4).double()
    twin = NerfModule(cfg, torch.zeros(3), torch.ones(3), 4).double()
    twin.load_state_dict(module.state_dict())
    fused = module.configure_optimizers()["optimizer"]
    assert fused.defaults["fused"]
    groups = [
        {**{k: v for k, v in g.items() if k != "params"}, "params": g["params"]}
        for g in twin.configure_optimizers()["optimizer"].param_groups
    ]
    loop = torch.optim.Adam(groups, fused=False, foreach=False)
    generator = torch.Generator().manual_seed(0)
    for _ in range(3):
        for a, b in zip(module.parameters(), twin.parameters(), strict=True):
            a.grad = torch.randn(a.shape, generator=generator, dtype=a.dtype)
            b.grad = a.grad.clone()
        fused.step()
        loop.step()
    for a, b in zip(module.parameters(), twin.parameters(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
