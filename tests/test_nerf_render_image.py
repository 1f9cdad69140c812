"""Rendering images at a pose and fitting appearance codes of unseen images."""

from __future__ import annotations

import torch

from diffloc.geometry.camera import PinholeCamera
from diffloc.maps.nerf.appearance import fit_appearance_code
from diffloc.maps.nerf.field import FieldConfig, RadianceField
from diffloc.maps.nerf.losses import photometric_loss
from diffloc.maps.nerf.rays import camera_rays
from diffloc.maps.nerf.renderer import render_image, render_rays
from diffloc.maps.nerf.sampler import DensityGrid, SamplerConfig


def _scene() -> tuple[RadianceField, DensityGrid]:
    torch.manual_seed(0)
    cfg = FieldConfig(triplane_resolutions=[8], triplane_channels=4, hidden=16, appearance_dim=4)
    field = RadianceField(cfg, -2 * torch.ones(3), 2 * torch.ones(3), 3)
    with torch.no_grad():
        field.appearance.weight.normal_(0, 2.0)
        field.colour_mlp[0].weight.normal_(0, 1.0)
    grid = DensityGrid(SamplerConfig(grid_resolution=8, coarse_samples=16, importance_samples=8))
    grid.refresh(field.density, field.normalise, torch.Generator().manual_seed(0))
    return field, grid


def test_render_image_gives_rgb_depth_and_normals_of_the_camera_size() -> None:
    field, grid = _scene()
    cam = PinholeCamera.from_fov(12, 8, 1.0)
    out = render_image(field, grid, cam, torch.eye(4), torch.zeros(4), with_normals=True)
    assert out["rgb"].shape == (3, 8, 12) and out["depth"].shape == (1, 8, 12)
    assert out["normal"].shape == (3, 8, 12)
    assert bool(((out["rgb"] >= 0) & (out["rgb"] <= 1)).all())
    assert bool((out["opacity"] <= 1 + 1e-5).all())
    # depth is camera z: range times the z of a unit ray
    uv = cam.pixel_grid(torch.float32).reshape(-1, 2)
    o, d, z = camera_rays(cam, torch.eye(4), uv)
    rays = render_rays(field, grid, o, d, None, torch.zeros(96, 4))
    torch.testing.assert_close(out["depth"].reshape(-1), rays.range * z, rtol=1e-4, atol=1e-4)


def test_fitted_code_explains_an_image_rendered_with_a_known_code() -> None:
    field, grid = _scene()
    cam = PinholeCamera.from_fov(16, 12, 1.0)
    uv = cam.pixel_grid(torch.float32).reshape(-1, 2)
    o, d, _ = camera_rays(cam, torch.eye(4), uv)
    truth = field.appearance.weight[1].detach()
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        target = render_rays(field, grid, o, d, g, truth.expand(len(uv), -1)).rgb

    def loss(code: torch.Tensor) -> float:
        with torch.no_grad():
            out = render_rays(
                field, grid, o, d, torch.Generator().manual_seed(1), code.expand(len(uv), -1)
            )
        return float(photometric_loss(out.rgb, target))

    start = field.appearance.weight.detach().mean(0)
    code = fit_appearance_code(field, grid, o, d, target, steps=60, batch=128, lr=0.1)
    assert loss(code) < 0.2 * loss(start)
