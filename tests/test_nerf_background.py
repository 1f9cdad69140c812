"""The learnt background colour of a radiance field (``FieldConfig.background``): compositing,
gradients, the render paths, export and the setting's validation."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch

from diffloc.config import compose_config, to_object
from diffloc.geometry.camera import PinholeCamera
from diffloc.maps.nerf.export import export_field, load_field
from diffloc.maps.nerf.field import FieldConfig, RadianceField
from diffloc.maps.nerf.renderer import render_image, render_rays
from diffloc.maps.nerf.rendering import composite, composite_over
from diffloc.maps.nerf.sampler import DensityGrid, SamplerConfig
from diffloc.testing import assert_close, gradcheck

SKY = torch.tensor([0.2, 0.5, 0.9])


def test_a_ray_through_nothing_returns_the_background() -> None:
    colours = torch.rand(2, 4, 3, generator=torch.Generator().manual_seed(0))
    background = torch.stack((SKY, 1 - SKY))
    assert_close(composite_over(torch.zeros(2, 4), colours, background), background)


def test_a_fully_opaque_ray_ignores_the_background() -> None:
    colours = torch.rand(1, 3, 3, generator=torch.Generator().manual_seed(1))
    weights = torch.tensor([[0.25, 0.75, 0.0]])
    out = composite_over(weights, colours, SKY[None])
    assert_close(out, composite(weights, colours))
    assert_close(out, 0.25 * colours[:, 0] + 0.75 * colours[:, 1])


def test_the_remaining_transmittance_weighs_the_background() -> None:
    colours = torch.ones(1, 2, 3)
    out = composite_over(torch.tensor([[0.1, 0.3]]), colours, SKY[None])
    assert_close(out, 0.4 + 0.6 * SKY[None])


def test_composite_over_gradcheck_float64() -> None:
    g = torch.Generator().manual_seed(2)
    weights = torch.rand(3, 5, generator=g, dtype=torch.float64) / 5
    colours = torch.rand(3, 5, 3, generator=g, dtype=torch.float64)
    background = torch.rand(3, 3, generator=g, dtype=torch.float64)
    gradcheck(composite_over, [weights, colours, background])


def _scene(background: str, density_bias: float) -> tuple[RadianceField, DensityGrid]:
    torch.manual_seed(0)
    cfg = FieldConfig(
        triplane_resolutions=[8],
        triplane_channels=4,
        hidden=16,
        appearance_dim=4,
        density_bias=density_bias,
        background=background,
    )
    field = RadianceField(cfg, -2 * torch.ones(3), 2 * torch.ones(3), 3)
    with torch.no_grad():
        field.appearance.weight.normal_(0, 2.0)
        field.colour_mlp[0].weight.normal_(0, 1.0)
        if field.background_head is not None:
            field.background_head.weight.normal_(0, 1.0)
            field.background_head.bias.normal_(0, 1.0)
    sampler = SamplerConfig(grid_resolution=8, coarse_samples=16, importance_samples=8)
    grid = DensityGrid(dataclasses.replace(sampler, skip_density=0.0))
    grid.refresh(field.density, field.normalise, torch.Generator().manual_seed(0))
    return field, grid


def _rays(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    directions = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return torch.zeros(n, 3), directions


def test_an_empty_field_renders_the_background_of_each_code() -> None:
    field, grid = _scene("learned", density_bias=-40.0)
    origins, directions = _rays(6)
    codes = field.appearance.weight.detach()[torch.tensor([0, 1, 2, 0, 1, 2])]
    out = render_rays(field, grid, origins, directions, None, codes)
    head = field.background_head
    expected = torch.sigmoid(codes @ head.weight.T + head.bias).detach()
    assert_close(out.rgb, expected, atol=1e-6, rtol=0)
    assert float((expected[0] - expected[1]).abs().max()) > 1e-2  # the code changes it
    assert_close(out.opacity, torch.zeros(6), atol=1e-6, rtol=0)


def test_no_background_renders_an_empty_field_black() -> None:
    field, grid = _scene("none", density_bias=-40.0)
    assert field.background(torch.zeros(2, 4)) is None
    origins, directions = _rays(2)
    out = render_rays(field, grid, origins, directions, None, torch.zeros(2, 4))
    assert_close(out.rgb, torch.zeros(2, 3), atol=1e-6, rtol=0)


def test_an_opaque_field_hides_the_background_and_range_ignores_it() -> None:
    with_sky, grid = _scene("learned", density_bias=14.0)
    without, _ = _scene("none", density_bias=14.0)
    shared = {k: v for k, v in with_sky.state_dict().items() if "background" not in k}
    without.load_state_dict(shared)
    origins, directions = _rays(5)
    codes = torch.zeros(5, 4)
    a = render_rays(with_sky, grid, origins, directions, None, codes)
    b = render_rays(without, grid, origins, directions, None, codes)
    assert_close(a.opacity, torch.ones(5), atol=1e-5, rtol=0)
    assert_close(a.rgb, b.rgb, atol=1e-5, rtol=0)
    assert torch.equal(a.range, b.range) and torch.equal(a.opacity, b.opacity)


def test_the_background_code_gradient_reaches_the_head_and_the_code() -> None:
    field, grid = _scene("learned", density_bias=-40.0)
    origins, directions = _rays(3)
    code = torch.zeros(3, 4, requires_grad=True)
    render_rays(field, grid, origins, directions, None, code).rgb.sum().backward()
    assert float(field.background_head.bias.grad.abs().min()) > 0
    assert float(code.grad.abs().max()) > 0


def test_render_image_shows_the_background_where_the_field_is_empty() -> None:
    field, grid = _scene("learned", density_bias=-40.0)
    code = field.appearance.weight.detach()[1]
    out = render_image(field, grid, PinholeCamera.from_fov(6, 4, 1.0), torch.eye(4), code)
    with torch.no_grad():
        sky = field.background(code[None])[0]
    assert_close(out["rgb"], sky[:, None, None].expand(3, 4, 6), atol=1e-6, rtol=0)


def test_export_round_trip_keeps_the_background(tmp_path: Path) -> None:
    field, grid = _scene("learned", density_bias=0.0)
    loaded, _ = load_field(export_field(tmp_path / "field", field, grid))
    assert loaded.config.background == "learned"
    codes = torch.randn(4, 4, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        assert torch.equal(loaded.background(codes), field.background(codes))


def test_a_field_exported_before_the_setting_loads_without_background(tmp_path: Path) -> None:
    field, grid = _scene("none", density_bias=0.0)
    out = export_field(tmp_path / "field", field, grid)
    record = json.loads((out / "field.json").read_text())
    del record["field"]["background"]
    (out / "field.json").write_text(json.dumps(record))
    loaded, _ = load_field(out)
    assert loaded.config.background == "none" and loaded.background_head is None


def test_an_unknown_background_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match=r"background must be one of \['none', 'learned'\]"):
        FieldConfig(background="sky")
    overrides = ["task=train_nerf", "nerf.train.field.background=sky"]
    with pytest.raises(ValueError, match="background must be one of"):
        to_object(compose_config(overrides))


def test_the_outdoor_and_indoor_settings_name_a_known_background() -> None:
    for scene in ("indoor", "outdoor"):
        nerf = to_object(compose_config([f"scene={scene}", "task=train_nerf"])).nerf
        assert nerf.train.field.background in ("none", "learned")
