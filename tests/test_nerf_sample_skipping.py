"""Which samples the renderer evaluates: occupied grid cells (and the lidar window) for
density, weights above ``min_weight`` for colour and normals; chunk-independent images."""

from __future__ import annotations

import pytest
import torch

from diffloc.geometry.camera import PinholeCamera
from diffloc.maps.nerf.field import FieldConfig, RadianceField
from diffloc.maps.nerf.renderer import render_image, render_rays
from diffloc.maps.nerf.rendering import composite, render_weights
from diffloc.maps.nerf.sampler import DensityGrid, SamplerConfig


def _scene(skip_density: float, min_weight: float) -> tuple[RadianceField, DensityGrid]:
    torch.manual_seed(0)
    cfg = FieldConfig(
        triplane_resolutions=[8], triplane_channels=4, hidden=16, appearance_dim=4, init_std=1.0
    )
    field = RadianceField(cfg, -2 * torch.ones(3), 2 * torch.ones(3), 3)
    with torch.no_grad():
        field.colour_mlp[0].weight.normal_(0, 1.0)
    sampler = SamplerConfig(
        grid_resolution=8,
        coarse_samples=16,
        importance_samples=8,
        skip_density=skip_density,
        min_weight=min_weight,
    )
    grid = DensityGrid(sampler)
    grid.refresh(field.density, field.normalise, torch.Generator().manual_seed(0))
    with torch.no_grad():
        grid.density[:4] = 0.0  # the half x < 0 counts as empty
    return field, grid


def _rays(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    origins = torch.rand(n, 3, generator=g) * 2 - 1
    directions = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return origins, directions


def _reference(
    field, grid, out, origins, directions, codes, normal_min_weight: float = -1.0
) -> dict[str, torch.Tensor]:
    """Every sample evaluated, then those outside occupied cells (tested apart) and their
    colours and normals below ``min_weight`` zeroed (normals also below
    ``normal_min_weight``)."""
    r, s = out.t.shape
    points = (origins[:, None] + out.t[..., None] * directions[:, None]).reshape(-1, 3)
    dirs = directions[:, None].expand(r, s, 3).reshape(-1, 3)
    full = field(points, dirs, codes[:, None].expand(r, s, -1).reshape(r * s, -1), True)
    xyz, _ = field.normalise(points)
    occupied = grid.occupied(xyz)
    weights = render_weights((full.density * occupied).reshape(r, s), out.deltas)
    seen = (weights.detach() > grid.config.min_weight)[..., None]
    shaded = seen & (weights.detach() > normal_min_weight)[..., None]
    normal = composite(weights, full.normal.reshape(r, s, 3) * shaded)
    return {
        "weights": weights,
        "rgb": composite(weights, full.rgb.reshape(r, s, 3) * seen),
        "normal": normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-9),
        "skipped": ~occupied,
    }


@pytest.mark.parametrize(("skip_density", "min_weight"), [(0.0, -1.0), (0.3, 1e-3)])
def test_render_rays_equals_evaluating_every_sample_and_zeroing_the_skipped_ones(
    skip_density: float, min_weight: float
) -> None:
    field, grid = _scene(skip_density, min_weight)
    origins, directions = _rays(64)
    codes = torch.randn(64, 4)
    out = render_rays(field, grid, origins, directions, None, codes, with_normals=True)
    ref = _reference(field, grid, out, origins, directions, codes)
    skipped = ref.pop("skipped")
    assert bool(skipped.any()) == (skip_density > 0) and not bool(skipped.all())
    for key, value in ref.items():
        torch.testing.assert_close(getattr(out, key), value, rtol=1e-5, atol=1e-5)
    # the gradients through the skipped evaluation equal the reference's
    params = [p for p in field.parameters() if p.requires_grad]
    loss_out = (out.rgb**2).sum() + (out.normal * torch.ones(3)).sum() + out.weights.sum()
    loss_ref = (ref["rgb"] ** 2).sum() + (ref["normal"] * torch.ones(3)).sum()
    loss_ref = loss_ref + ref["weights"].sum()
    for a, b in zip(
        torch.autograd.grad(loss_out, params, allow_unused=True),
        torch.autograd.grad(loss_ref, params, allow_unused=True),
        strict=True,
    ):
        if a is not None or b is not None:
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("normal_min_weight", [1e-3, 0.05])
def test_rendered_normals_composite_only_samples_above_normal_min_weight(
    normal_min_weight: float,
) -> None:
    """Without grad (rendering) the normals come from the samples above both thresholds."""
    field, grid = _scene(0.3, 1e-3)
    grid.config.normal_min_weight = normal_min_weight
    origins, directions = _rays(64)
    codes = torch.randn(64, 4)
    with torch.no_grad():
        out = render_rays(field, grid, origins, directions, None, codes, with_normals=True)
    ref = _reference(field, grid, out, origins, directions, codes, normal_min_weight)
    torch.testing.assert_close(out.normal, ref["normal"].detach(), rtol=1e-5, atol=1e-5)
    if normal_min_weight > 0.01:  # the threshold changed some normals
        unthresholded = _reference(field, grid, out, origins, directions, codes)["normal"]
        assert float((out.normal - unthresholded.detach()).abs().max()) > 1e-3


def test_lidar_window_is_evaluated_in_empty_cells() -> None:
    field, grid = _scene(1e9, 1e-4)  # every cell counts as empty
    origins, directions = _rays(32)
    depth = torch.full((32,), 0.5)
    out = render_rays(field, grid, origins, directions, None, depth=depth, depth_sigma=0.05)
    window = (out.t - depth[:, None]).abs() <= 0.15
    assert bool(window.any()) and bool((window | (out.t > 0.5)).any())
    assert bool((out.weights[~window] == 0).all())
    assert bool((out.weights[window] > 0).any())


def test_render_image_does_not_depend_on_the_chunk() -> None:
    field, grid = _scene(0.3, 1e-4)
    cam = PinholeCamera.from_fov(12, 10, 1.2)
    pose = torch.eye(4)
    pose[:3, 3] = torch.tensor([0.1, -0.2, -1.5])
    code = torch.randn(4)
    small = render_image(field, grid, cam, pose, code, chunk=7, with_normals=True)
    whole = render_image(field, grid, cam, pose, code, chunk=4096, with_normals=True)
    assert small.keys() == whole.keys() == {"rgb", "depth", "opacity", "normal"}
    for key in whole:
        torch.testing.assert_close(small[key], whole[key], rtol=1e-5, atol=1e-6)
    assert float(whole["opacity"].max()) > 0.1


def test_a_cell_and_its_neighbours_count_as_occupied() -> None:
    grid = DensityGrid(SamplerConfig(grid_resolution=8, skip_density=0.5))
    centre = lambda i: (torch.tensor(i, dtype=torch.float32) + 0.5) / 8 * 2 - 1  # noqa: E731
    points = torch.stack([centre(i) for i in ([3, 3, 3], [4, 2, 3], [5, 3, 3], [3, 3, 6])])
    assert bool(grid.occupied(points).all())  # not refreshed yet: everything
    with torch.no_grad():
        grid.density[3, 3, 3] = 1.0
        grid.refreshed.fill_(True)
    assert grid.occupied(points).tolist() == [True, True, False, False]


def test_the_grid_is_in_use_only_when_sampling_reads_it() -> None:
    assert DensityGrid(SamplerConfig()).in_use
    assert DensityGrid(SamplerConfig(importance_samples=0)).in_use  # skipping reads it
    assert not DensityGrid(SamplerConfig(importance_samples=0, skip_density=0)).in_use
