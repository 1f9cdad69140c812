"""A radiance field as an RGB-D map of the rendered-database localisation."""

from __future__ import annotations

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.crossmodal.nerf_map import RadianceFieldMap
from diffloc.geometry.camera import PinholeCamera
from diffloc.maps.nerf.export import export_field
from diffloc.maps.nerf.field import FieldConfig, RadianceField
from diffloc.maps.nerf.renderer import render_image
from diffloc.maps.nerf.sampler import DensityGrid, SamplerConfig


def _field() -> tuple[RadianceField, DensityGrid]:
    torch.manual_seed(0)
    cfg = FieldConfig(
        triplane_resolutions=[8], triplane_channels=4, hidden=16, appearance_dim=4, init_std=1.0
    )
    field = RadianceField(cfg, -2 * torch.ones(3), 2 * torch.ones(3), 3)
    with torch.no_grad():
        field.appearance.weight.normal_(0, 1.0)
    grid = DensityGrid(SamplerConfig(grid_resolution=8, coarse_samples=16, importance_samples=8))
    grid.refresh(field.density, field.normalise, torch.Generator().manual_seed(0))
    return field, grid


def _poses() -> torch.Tensor:
    poses = torch.eye(4).repeat(2, 1, 1)
    poses[0, :3, 3] = torch.tensor([0.0, 0.0, -1.5])
    poses[1, :3, 3] = torch.tensor([0.5, -0.3, -1.0])
    return poses


def test_render_is_the_field_render_with_low_opacity_pixels_as_holes() -> None:
    field, grid = _field()
    camera = PinholeCamera.from_fov(10, 8, 1.2)
    code = torch.randn(4)
    refs = [render_image(field, grid, camera, pose, code) for pose in _poses()]
    cut = float(torch.cat([r["opacity"].flatten() for r in refs]).median())
    rgbd = RadianceFieldMap(field, grid, code, min_opacity=cut).render(_poses(), camera)
    assert rgbd.rgb.shape == (2, 3, 8, 10) and rgbd.depth.shape == (2, 1, 8, 10)
    holes = 0
    for b, ref in enumerate(refs):
        torch.testing.assert_close(rgbd.rgb[b], ref["rgb"])
        solid = ref["opacity"] >= cut
        torch.testing.assert_close(rgbd.depth[b][solid], ref["depth"][solid])
        assert bool((rgbd.depth[b][~solid] == 0).all())
        holes += int((~solid).sum())
    assert 0 < holes < 2 * 80


def test_from_folder_renders_the_exported_field_with_the_mean_code(tmp_path) -> None:
    field, grid = _field()
    camera = PinholeCamera.from_fov(6, 4, 1.0)
    loaded = RadianceFieldMap.from_folder(export_field(tmp_path / "f", field, grid))
    torch.testing.assert_close(loaded.appearance, field.appearance.weight.detach().mean(0))
    direct = RadianceFieldMap(field, grid, loaded.appearance).render(_poses(), camera)
    rgbd = loaded.render(_poses(), camera)
    torch.testing.assert_close(rgbd.rgb, direct.rgb)
    torch.testing.assert_close(rgbd.depth, direct.depth)


def test_an_appearance_code_of_the_wrong_length_is_a_shape_error() -> None:
    field, grid = _field()
    with pytest.raises(ShapeError, match="appearance"):
        RadianceFieldMap(field, grid, torch.zeros(5))


def test_min_opacity_outside_the_unit_interval_is_a_clear_error() -> None:
    field, grid = _field()
    with pytest.raises(ValueError, match="min_opacity"):
        RadianceFieldMap(field, grid, torch.zeros(4), min_opacity=0.0)
