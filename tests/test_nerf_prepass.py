"""The no-grad pre-pass (``SamplerConfig.grad_min_weight``): the render is that of the full
evaluation, and the gradients are the full ones minus those through the densities of samples
at or below the weight threshold (outside the lidar window), which are small."""

from __future__ import annotations

import torch

from diffloc.maps.nerf.field import FieldConfig, RadianceField
from diffloc.maps.nerf.losses import depth_kl_loss, photometric_loss
from diffloc.maps.nerf.renderer import render_rays
from diffloc.maps.nerf.rendering import composite, render_weights
from diffloc.maps.nerf.sampler import DensityGrid, SamplerConfig

THRESHOLD = 1e-3


def _scene(grad_min_weight: float) -> tuple[RadianceField, DensityGrid]:
    torch.manual_seed(0)
    cfg = FieldConfig(
        triplane_resolutions=[8], triplane_channels=4, hidden=16, appearance_dim=4, init_std=1.0
    )
    field = RadianceField(cfg, -2 * torch.ones(3), 2 * torch.ones(3), 3).double()
    with torch.no_grad():
        field.colour_mlp[0].weight.normal_(0, 1.0)
        field.density_mlp[2].bias[0] = 4.0  # dense enough that rays saturate
    sampler = SamplerConfig(
        grid_resolution=8,
        coarse_samples=16,
        importance_samples=8,
        skip_density=0.0,
        min_weight=THRESHOLD,
        grad_min_weight=grad_min_weight,
    )
    grid = DensityGrid(sampler)
    grid.refresh(field.density, field.normalise, torch.Generator().manual_seed(0))
    return field, grid


def _batch(n: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    return {
        "origins": (torch.rand(n, 3, generator=g) * 2 - 1).double(),
        "directions": torch.nn.functional.normalize(
            torch.randn(n, 3, generator=g), dim=-1
        ).double(),
        "codes": torch.randn(n, 4, generator=g).double(),
        "target": torch.rand(n, 3, generator=g).double(),
        "depth": (0.3 + torch.rand(n, generator=g)).double(),
    }


def _render(field: RadianceField, grid: DensityGrid, b: dict[str, torch.Tensor]):
    """Camera and lidar renders of one batch (same sample positions for any grid config)."""
    gen = lambda: torch.Generator().manual_seed(5)  # noqa: E731
    cam = render_rays(field, grid, b["origins"], b["directions"], gen(), b["codes"])
    lid = render_rays(
        field, grid, b["origins"], b["directions"], gen(), depth=b["depth"], depth_sigma=0.05
    )
    return cam, lid


def _grads(loss: torch.Tensor, field: RadianceField) -> torch.Tensor:
    grads = torch.autograd.grad(
        loss, list(field.parameters()), allow_unused=True, retain_graph=True
    )
    return torch.cat([g.reshape(-1) for g in grads if g is not None])


def _reference_rgb(field: RadianceField, b: dict[str, torch.Tensor], cam) -> torch.Tensor:
    """Every sample evaluated with autograd; samples whose weight is at or below the threshold
    have their density detached and their colour zeroed (``min_weight``)."""
    r, s = cam.t.shape
    points = (b["origins"][:, None] + cam.t[..., None] * b["directions"][:, None]).reshape(-1, 3)
    density, geo = field.geometry(points)
    live = (render_weights(density.detach().reshape(r, s), cam.deltas) > THRESHOLD).reshape(-1)
    weights = render_weights(torch.where(live, density, density.detach()).reshape(r, s), cam.deltas)
    dirs = b["directions"][:, None].expand(r, s, 3).reshape(-1, 3)
    codes = b["codes"][:, None].expand(r, s, 4).reshape(-1, 4)
    colour = field.colour(geo, dirs, codes) * live[:, None]
    return composite(weights, colour.reshape(r, s, 3))


def test_prepass_renders_the_same_and_drops_only_the_low_weight_gradients() -> None:
    field, full_grid = _scene(-1.0)
    _, grid = _scene(THRESHOLD)
    b = _batch(48)
    cam_full, lid_full = _render(field, full_grid, b)
    cam, lid = _render(field, grid, b)
    for ours, ref in ((cam, cam_full), (lid, lid_full)):
        for key in ("weights", "range", "opacity"):
            torch.testing.assert_close(getattr(ours, key), getattr(ref, key), rtol=1e-12, atol=0)
    torch.testing.assert_close(cam.rgb, cam_full.rgb, rtol=1e-12, atol=1e-14)
    dropped = float((cam_full.weights <= THRESHOLD).double().mean())
    assert 0.1 < dropped < 0.9  # otherwise the test would not see a wrong pre-pass
    # the photometric gradient is exactly the one with the dropped densities held constant
    torch.testing.assert_close(
        _grads(photometric_loss(cam.rgb, b["target"]), field),
        _grads(photometric_loss(_reference_rgb(field, b, cam), b["target"]), field),
        rtol=1e-9,
        atol=1e-12,
    )
    # and the part dropped from the full (photometric + Eq. 6) gradient is small
    loss, loss_full = (
        photometric_loss(c.rgb, b["target"])
        + depth_kl_loss(ld.weights, ld.t, ld.deltas, b["depth"], 0.05)
        for c, ld in ((cam, lid), (cam_full, lid_full))
    )
    torch.testing.assert_close(loss, loss_full, rtol=1e-12, atol=0)
    full = _grads(loss_full, field)
    difference = float((_grads(loss, field) - full).norm() / full.norm())
    assert 0 < difference < 0.25  # 0.107 measured: behind-surface samples of a dense toy field


def test_lidar_window_samples_keep_their_gradient_below_the_threshold() -> None:
    """Eq. 6 reads log(w) in the window, whose gradient is largest where w is small."""
    field, grid = _scene(1.0)  # above every weight: only the window stays differentiable
    _, full_grid = _scene(-1.0)
    b = _batch(16)
    gen = lambda: torch.Generator().manual_seed(5)  # noqa: E731
    kw = {"depth": b["depth"], "depth_sigma": 0.05}
    lid = render_rays(field, grid, b["origins"], b["directions"], gen(), **kw)
    ref = render_rays(field, full_grid, b["origins"], b["directions"], gen(), **kw)
    window = (lid.t - b["depth"][:, None]).abs() <= 0.15
    assert bool(window.any()) and not bool(window.all())
    (g,) = torch.autograd.grad(lid.weights[window].log().sum(), field.density_mlp[2].bias)
    (g_ref,) = torch.autograd.grad(ref.weights[window].log().sum(), field.density_mlp[2].bias)
    assert float(g.abs().sum()) > 0
    assert not torch.allclose(g, g_ref)  # samples outside the window lost theirs
