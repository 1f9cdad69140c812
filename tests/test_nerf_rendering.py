"""Rays, Eq. 5 volume rendering, sampling, and the Eq. 6 / Eq. 7 losses."""

from __future__ import annotations

import math

import pytest
import torch

from diffloc.geometry.camera import PinholeCamera
from diffloc.maps.nerf.contraction import SceneNormalisation
from diffloc.maps.nerf.losses import depth_kl_loss, normal_loss, photometric_loss
from diffloc.maps.nerf.rays import camera_rays, ray_box_bounds
from diffloc.maps.nerf.rendering import composite, render_weights
from diffloc.maps.nerf.sampler import DensityGrid, SamplerConfig, interval_lengths, spacing
from diffloc.testing import assert_close, gradcheck, random_se3


def test_camera_rays_pass_through_their_pixels() -> None:
    cam = PinholeCamera.from_fov(16, 12, 1.2, dtype=torch.float64)
    T_wc = random_se3((), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    uv = torch.tensor([[0.0, 0.0], [7.5, 5.5], [15.0, 3.0]], dtype=torch.float64)
    o, d, z = camera_rays(cam, T_wc, uv)
    assert_close(d.norm(dim=-1), torch.ones(3, dtype=torch.float64))
    points_world = o + 2.0 * d
    T_cw = torch.linalg.inv(T_wc)
    points_cam = points_world @ T_cw[:3, :3].T + T_cw[:3, 3]
    uv_back, _ = cam.project(points_cam)
    assert_close(uv_back, uv)
    assert_close(points_cam[:, 2], 2.0 * z)


def test_ray_box_bounds_enter_and_leave_the_box() -> None:
    o = torch.tensor([[0.0, 0, 0], [-3.0, 0, 0], [-3.0, 5, 0]])
    d = torch.tensor([[1.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0]])
    near, far = ray_box_bounds(o, d, -torch.ones(3), torch.ones(3), 0.01)
    assert_close(near[:2], torch.tensor([0.01, 2.0]))
    assert_close(far[:2], torch.tensor([1.0, 4.0]))
    assert bool(far[2] <= near[2])


def _dense_weights(density: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """Eq. 5 term by term (reference)."""
    out = torch.zeros_like(density)
    for r in range(density.shape[0]):
        for i in range(density.shape[1]):
            before = sum(float(deltas[r, j] * density[r, j]) for j in range(i))
            out[r, i] = math.exp(-before) * (1 - torch.exp(-deltas[r, i] * density[r, i]))
    return out


def test_render_weights_match_eq5_term_by_term_and_gradcheck() -> None:
    g = torch.Generator().manual_seed(0)
    density = torch.rand(3, 7, generator=g, dtype=torch.float64) * 4
    deltas = torch.rand(3, 7, generator=g, dtype=torch.float64) * 0.3
    assert_close(render_weights(density, deltas), _dense_weights(density, deltas))
    gradcheck(render_weights, [density, deltas])
    values = torch.rand(3, 7, 3, generator=g, dtype=torch.float64)
    gradcheck(composite, [render_weights(density, deltas), values])


def test_opaque_wall_puts_all_weight_at_the_wall() -> None:
    t = torch.linspace(0.0, 4.0, 401)[None]
    density = torch.where(t >= 2.0, 1e4, 0.0)
    deltas = interval_lengths(t, torch.tensor([0.0]), torch.tensor([4.0]))
    w = render_weights(density, deltas)
    assert abs(float(composite(w, t)) - 2.0) < 0.01
    assert abs(float(w.sum()) - 1.0) < 1e-5


def test_spacing_is_linear_bounded_and_inverse_beyond_the_box() -> None:
    s = torch.tensor([[0.0, 0.25, 0.5, 0.75, 1.0]])
    near, far = torch.tensor([1.0]), torch.tensor([3.0])
    assert_close(spacing(s, near, far, None), torch.tensor([[1.0, 1.5, 2.0, 2.5, 3.0]]))
    contracted = spacing(s, near, far, 100.0)
    assert_close(contracted[0, [0, 1, 2, 4]], torch.tensor([1.0, 2.0, 3.0, 100.0]))
    assert float(1 / contracted[0, 3]) == pytest.approx((1 / 3.0 + 1 / 100.0) / 2)


def test_a_ray_meeting_the_box_beyond_the_outer_far_distance_samples_nothing() -> None:
    """A camera far outside a contracted field's box: a ray that misses the box gets a slab
    entry beyond ``far_m``; its distances collapse onto ``far_m`` (no interval, no NaN) through
    the uniform and the importance samples alike."""
    s = torch.tensor([[0.0, 0.25, 0.5, 0.75, 1.0]])
    collapsed = spacing(s, torch.tensor([449.0]), torch.tensor([449.001]), 200.0)
    assert_close(collapsed, torch.full((1, 5), 200.0))
    cfg = SamplerConfig(grid_resolution=8, uniform_samples=8, importance_samples=16, far_m=200.0)
    grid = DensityGrid(cfg)
    norm = SceneNormalisation(-torch.ones(3), torch.ones(3), True)
    grid.refresh(lambda x: torch.full((len(x),), 10.0), norm, torch.Generator().manual_seed(0))
    o = torch.tensor([[0.0, -300.0, 0.0]])
    d = torch.nn.functional.normalize(torch.tensor([[1.0, 0.01, 0.0]]), dim=1)
    near, far = ray_box_bounds(o, d, -torch.ones(3), torch.ones(3), cfg.near_m)
    assert float(near) > cfg.far_m > float(far)
    t = grid.sample(o, d, near, far.maximum(near + 1e-3), norm, None)
    assert bool(torch.isfinite(t).all())
    assert_close(t, torch.full_like(t, 200.0))


def test_importance_samples_concentrate_at_the_surface_of_the_grid() -> None:
    """A grid with one opaque slab at x = 0.5 draws most importance samples next to it."""
    cfg = SamplerConfig(grid_resolution=16, uniform_samples=4, importance_samples=64)
    grid = DensityGrid(cfg)
    norm = SceneNormalisation(-torch.ones(3), torch.ones(3), False)

    def density(points: torch.Tensor) -> torch.Tensor:
        return torch.where((points[:, 0] - 0.5).abs() < 0.1, 1e3, 0.0)

    gen = torch.Generator().manual_seed(0)
    grid.refresh(density, norm, gen)
    o = torch.tensor([[-0.9, 0.1, 0.2]]).expand(8, 3)
    d = torch.tensor([[1.0, 0.0, 0.0]]).expand(8, 3)
    t = grid.sample(o, d, torch.full((8,), 0.0), torch.full((8,), 1.9), norm, gen)
    assert t.shape == (8, 68)
    assert bool((t[:, 1:] >= t[:, :-1]).all())
    near_wall = ((o[:, :1] + t - 0.5).abs() < 0.2).float().mean()
    assert float(near_wall) > 0.8


def test_importance_samples_cover_the_occupied_cell_not_only_its_entry() -> None:
    """A thin opaque surface in the middle of a cell (the grid stores only the cell's maximum
    density): the importance weights fall by exp(-cell_optical_depth) over the cell, so a
    known share of the samples lies behind the cell's middle. Uncapped, the whole cell was
    opaque at its entry and every sample sat in front of the surface."""
    cfg = SamplerConfig(grid_resolution=4, uniform_samples=0, importance_samples=64)
    grid = DensityGrid(cfg)
    grid.density[2] = 1e4  # cells x in [0, 0.5): the surface at x = 0.25
    grid.refreshed.fill_(True)
    norm = SceneNormalisation(-torch.ones(3), torch.ones(3), False)
    o, d = torch.tensor([[-0.9, 0.1, 0.2]]), torch.tensor([[1.0, 0.0, 0.0]])
    t = grid.sample(o, d, torch.zeros(1), torch.full((1,), 1.9), norm, None)
    x = o[:, 0] + t[0]
    assert float(((x >= 0.0) & (x < 0.5)).float().mean()) > 0.95
    # rate 0.5 per half-unit cell: share of [0.25, 0.5) = (e^-0.25 - e^-0.5) / (1 - e^-0.5)
    expected = (math.exp(-0.25) - math.exp(-0.5)) / (1 - math.exp(-0.5))
    assert abs(float((x >= 0.25).float().mean()) - expected) < 0.05


def test_a_negative_cell_optical_depth_is_refused() -> None:
    with pytest.raises(ValueError, match="cell_optical_depth"):
        SamplerConfig(cell_optical_depth=-1.0)


def test_guided_samples_surround_the_lidar_range() -> None:
    cfg = SamplerConfig(uniform_samples=2, importance_samples=0, guided_samples=32)
    grid = DensityGrid(cfg)
    norm = SceneNormalisation(-5 * torch.ones(3), 5 * torch.ones(3), False)
    o, d = torch.zeros(4, 3), torch.tensor([[0.0, 0, 1]]).expand(4, 3)
    gen = torch.Generator().manual_seed(0)
    depth = torch.tensor([1.0, 2.0, 3.0, 4.0])
    t = grid.sample(o, d, torch.zeros(4), torch.full((4,), 5.0), norm, gen, depth, 0.05)
    assert t.shape == (4, 34)
    close = ((t - depth[:, None]).abs() < 0.2).sum(dim=1)
    assert bool((close >= 30).all())


def test_photometric_loss_and_gradcheck() -> None:
    a = torch.rand(5, 3, dtype=torch.float64)
    assert float(photometric_loss(a, a)) == 0.0
    gradcheck(photometric_loss, [a, torch.rand(5, 3, dtype=torch.float64)])


def _gaussian_weights(t: torch.Tensor, mean: float, std: float) -> torch.Tensor:
    w = torch.exp(-0.5 * ((t - mean) / std) ** 2)
    return w / w.sum(dim=-1, keepdim=True)


def test_depth_kl_is_zero_at_the_target_and_grows_with_the_offset() -> None:
    t = torch.linspace(0.0, 4.0, 2001, dtype=torch.float64)[None]
    deltas = interval_lengths(t, t[:, 0], t[:, -1])
    depth = torch.tensor([2.0], dtype=torch.float64)
    losses = [
        float(depth_kl_loss(_gaussian_weights(t, 2.0 + off, 0.05), t, deltas, depth, 0.05))
        for off in (0.0, 0.02, 0.05)
    ]
    assert abs(losses[0]) < 1e-3
    # KL of two normals with equal std: offset^2 / (2 std^2)
    assert losses[1] == pytest.approx(0.02**2 / (2 * 0.05**2), abs=2e-3)
    assert losses[0] < losses[1] < losses[2]


def test_depth_kl_gradcheck_float64() -> None:
    g = torch.Generator().manual_seed(1)
    t = torch.sort(torch.rand(3, 9, generator=g, dtype=torch.float64) * 2 + 1).values
    deltas = interval_lengths(t, t[:, 0] - 0.05, t[:, -1] + 0.05)
    w = torch.rand(3, 9, generator=g, dtype=torch.float64) * 0.2 + 0.01
    depth = torch.tensor([1.5, 2.0, 2.5], dtype=torch.float64)
    gradcheck(lambda w, t: depth_kl_loss(w, t, deltas, depth, 0.3), [w, t])


def test_depth_kl_rejects_a_non_positive_sigma() -> None:
    with pytest.raises(ValueError, match="sigma"):
        depth_kl_loss(torch.ones(1, 2), torch.ones(1, 2), torch.ones(1, 2), torch.ones(1), 0.0)


def test_normal_loss_eq7_values_and_gradcheck() -> None:
    n = torch.tensor([[0.0, 0, 1], [1.0, 0, 0]], dtype=torch.float64)
    assert float(normal_loss(n, n)) == 0.0
    flipped = normal_loss(-n, n)  # |2n|_1 = 2 and |1 - (-1)| = 2 per ray
    assert float(flipped) == pytest.approx(4.0)
    g = torch.Generator().manual_seed(2)
    a = torch.nn.functional.normalize(torch.randn(4, 3, generator=g, dtype=torch.float64), dim=-1)
    b = torch.nn.functional.normalize(torch.randn(4, 3, generator=g, dtype=torch.float64), dim=-1)
    gradcheck(normal_loss, [a, b])
