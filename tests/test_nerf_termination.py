"""Early ray termination (``SamplerConfig.stop_transmittance`` / ``grad_stop_transmittance``):
on a small field trained to hold an opaque slab, the render with termination equals the full
render within the threshold, fewer samples are evaluated, and lidar-window samples behind the
termination point are still evaluated."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from diffloc.geometry.camera import PinholeCamera
from diffloc.maps.nerf.field import FieldConfig, RadianceField
from diffloc.maps.nerf.renderer import render_image, render_rays
from diffloc.maps.nerf.sampler import DensityGrid, SamplerConfig

SLAB_X = 0.3  # the slab fills x > SLAB_X of the [-2, 2]^3 box


@pytest.fixture(scope="module")
def trained() -> tuple[RadianceField, DensityGrid]:
    """A tiny field fitted (density only, 150 Adam steps) to 40 / m in the slab and 0
    elsewhere, with its density grid refreshed."""
    torch.manual_seed(0)
    cfg = FieldConfig(
        triplane_resolutions=[16], triplane_channels=4, hidden=16, appearance_dim=4, init_std=0.1
    )
    field = RadianceField(cfg, -2 * torch.ones(3), 2 * torch.ones(3), 2)
    with torch.no_grad():
        field.colour_mlp[0].weight.normal_(0, 1.0)
    optimiser = torch.optim.Adam(field.parameters(), lr=0.05)
    g = torch.Generator().manual_seed(1)
    for _ in range(150):
        points = torch.rand(1024, 3, generator=g) * 4 - 2
        target = torch.where(points[:, 0] > SLAB_X, 40.0, 0.0)
        loss = (field.density(points) - target).abs().mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    sampler = SamplerConfig(
        grid_resolution=16, coarse_samples=64, importance_samples=16, min_weight=-1.0
    )
    grid = DensityGrid(sampler)
    grid.refresh(field.density, field.normalise, torch.Generator().manual_seed(0))
    return field, grid


def _with(grid: DensityGrid, **settings) -> DensityGrid:
    other = DensityGrid(dataclasses.replace(grid.config, **settings))
    other.load_state_dict(grid.state_dict())
    return other


def _rays(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays from x = -1.5 towards +x (spread 0.1), all hitting the slab."""
    g = torch.Generator().manual_seed(3)
    origins = torch.cat((torch.full((n, 1), -1.5), torch.rand(n, 2, generator=g) - 0.5), 1)
    directions = torch.nn.functional.normalize(
        torch.cat((torch.ones(n, 1), 0.1 * torch.randn(n, 2, generator=g)), 1), dim=-1
    )
    return origins, directions


def _count_evaluations(field: RadianceField, monkeypatch) -> list[torch.Tensor]:
    """Record the points of every density evaluation the renderer makes (world points, or
    cube points when it evaluates normalised points)."""
    seen: list[torch.Tensor] = []
    for name in ("geometry", "geometry_and_normals", "geometry_in_cube"):
        original = getattr(field, name)

        def wrapper(points, *rest, original=original):
            seen.append(points.detach())
            return original(points, *rest)

        monkeypatch.setattr(field, name, wrapper)
    return seen


@pytest.mark.parametrize("stop", [1e-4, 1e-3])
def test_termination_keeps_the_render_within_the_threshold(trained, monkeypatch, stop) -> None:
    field, grid = trained
    origins, directions = _rays(256)
    codes = torch.randn(256, 4, generator=torch.Generator().manual_seed(4))
    seen = _count_evaluations(field, monkeypatch)
    with torch.no_grad():
        full = render_rays(
            field, _with(grid, stop_transmittance=0.0), origins, directions, None, codes
        )
        n_full = sum(len(p) for p in seen)
        seen.clear()
        cut = render_rays(
            field, _with(grid, stop_transmittance=stop), origins, directions, None, codes
        )
        n_cut = sum(len(p) for p in seen)
    assert float(full.opacity.min()) > 1 - 1e-4  # every ray ends in the slab
    assert n_cut < 0.97 * n_full  # samples behind the slab's front are dropped
    assert float((cut.rgb - full.rgb).abs().max()) <= stop
    assert float((cut.opacity - full.opacity).abs().max()) <= stop
    assert float((cut.range - full.range).abs().max()) <= stop * float(full.t.max())


def test_terminated_image_matches_the_full_image(trained) -> None:
    field, grid = trained
    cam = PinholeCamera.from_fov(16, 12, 1.0)
    pose = torch.tensor(
        [[0.0, 0.0, 1.0, -1.5], [1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
    )  # looking along +x
    code = torch.randn(4)
    full = render_image(field, _with(grid, stop_transmittance=0.0), cam, pose, code)
    cut = render_image(field, _with(grid, stop_transmittance=1e-4), cam, pose, code)
    assert float(full["opacity"].min()) > 0.999
    for key in ("rgb", "opacity"):
        torch.testing.assert_close(cut[key], full[key], rtol=0, atol=1e-4)
    torch.testing.assert_close(cut["depth"], full["depth"], rtol=0, atol=1e-3)


def test_training_termination_keeps_the_lidar_window_and_the_gradient(trained, monkeypatch) -> None:
    field, grid = trained
    origins, directions = _rays(128)
    depth = torch.full((128,), 3.0)  # behind the slab's front: past the termination point
    seen = _count_evaluations(field, monkeypatch)
    outs, grads = [], []
    for stop in (0.0, 1e-3):
        seen.clear()
        g = torch.Generator().manual_seed(5)
        out = render_rays(
            field,
            _with(grid, grad_stop_transmittance=stop),
            origins,
            directions,
            g,
            depth=depth,
            depth_sigma=0.05,
            with_normals=True,
        )
        loss = out.range.sum() + out.opacity.sum() + out.normal.sum()
        grads.append(
            torch.cat(
                [
                    p.flatten()
                    for p in torch.autograd.grad(loss, field.parameters(), allow_unused=True)
                    if p is not None
                ]
            )
        )
        outs.append((out, torch.cat(seen)))
    (full, points_full), (cut, points_cut) = outs
    window = ((full.t - depth[:, None]).abs() <= 0.15) & (full.t > 0)
    assert len(points_cut) < len(points_full)
    # every window sample of the full evaluation is evaluated with termination too
    key = lambda p: set(map(tuple, (p * 1e4).round().long().tolist()))  # noqa: E731
    window_points = (origins[:, None] + full.t[..., None] * directions[:, None])[window]
    assert key(window_points) <= key(points_cut)
    assert float((cut.range - full.range).abs().max().detach()) <= 1e-3 * float(full.t.max())
    torch.testing.assert_close(
        grads[1], grads[0], rtol=0.05, atol=0.05 * float(grads[0].abs().max())
    )
