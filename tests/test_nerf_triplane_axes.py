"""Tri-plane levels with their own vertex count per axis (``FieldConfig.triplane_aspect``):
non-square planes against known answers and the gather reference, gradcheck, export / load,
fields saved before the setting, bad values."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from hydra.errors import ConfigCompositionException
from safetensors.torch import load_file, save_file

from diffloc.config import compose_config, to_object
from diffloc.maps.nerf.encodings import (
    TriplaneEncoding,
    bilinear_gather,
    triplane_axis_resolutions,
)
from diffloc.maps.nerf.export import export_field, load_field
from diffloc.maps.nerf.field import FieldConfig, RadianceField
from diffloc.maps.nerf.sampler import DensityGrid, SamplerConfig
from diffloc.testing import assert_close, gradcheck
from tests.encoding_checks import assert_matches_reference, encoding_points

AXES = (5, 3, 4)  # vertices along x, y, z: every plane is non-square


def test_bilinear_gather_on_a_non_square_plane_hits_vertices_and_interpolates() -> None:
    table = torch.arange(12.0)[:, None]  # 4 x 3 vertices (i, j): value 4 j + i
    uv = torch.tensor([[-1.0, -1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [0.0, 0.0]])
    # i = 1.5 (u + 1), j = v + 1
    expected = torch.tensor([0.0, 11.0, 3.0, 8.0, 4.0 + 1.5])
    assert_close(bilinear_gather(table, uv, (4, 3))[:, 0], expected)
    with pytest.raises(ValueError, match="a 3 x 3 plane needs 9"):
        bilinear_gather(table, uv, 3)


def test_non_square_level_reproduces_affine_planes_exactly() -> None:
    """Planes holding ``1 + 0.1 u + 0.2 v`` at their vertices (u, v the plane's coordinates)
    interpolate to exactly that, so the feature is the product of the three affine values."""
    enc = TriplaneEncoding([AXES], 1, 0.1).double()
    with torch.no_grad():
        for plane, (a, b) in zip(enc.planes, enc.PAIRS, strict=True):
            assert plane.shape == (1, AXES[b], AXES[a])
            u = torch.linspace(-1, 1, AXES[a], dtype=torch.float64)
            v = torch.linspace(-1, 1, AXES[b], dtype=torch.float64)
            plane.copy_((1 + 0.1 * u[None, :] + 0.2 * v[:, None])[None])
    x = encoding_points(50, 2).double().clamp(-1, 1)
    expected = 1.0
    for a, b in enc.PAIRS:
        expected = expected * (1 + 0.1 * x[:, a] + 0.2 * x[:, b])
    assert_close(enc(x)[:, 0], expected)
    assert_close(enc.forward_reference(x)[:, 0], expected)
    assert_close(enc.forward_with_jacobian(x)[0][:, 0], expected)


def test_non_square_levels_match_the_gather_reference_values_and_gradients() -> None:
    torch.manual_seed(0)
    enc = TriplaneEncoding([AXES, (9, 6, 2)], 3, 0.3).double()
    x = encoding_points(40).double().requires_grad_(True)
    assert_matches_reference(enc, x)


def test_jacobian_of_a_non_square_level_is_the_autograd_derivative() -> None:
    torch.manual_seed(3)
    enc = TriplaneEncoding([AXES, (7, 2, 3)], 2, 0.3).double()
    x = (encoding_points(12, 4) * 0.85).double().requires_grad_(True)
    features, jacobian = enc.forward_with_jacobian(x)
    assert_close(features, enc(x))
    rows = [torch.autograd.grad(enc(x)[:, k].sum(), x)[0] for k in range(enc.out_dim)]
    assert_close(jacobian, torch.stack(rows, dim=1))


def test_non_square_encoding_gradcheck_float64() -> None:
    torch.manual_seed(1)
    enc = TriplaneEncoding([(4, 3, 2)], 2, 0.3).double()
    names = [name for name, _ in enc.named_parameters()]
    x = torch.rand(6, 3, dtype=torch.float64) * 1.8 - 0.9

    def fn(x: torch.Tensor, *tables: torch.Tensor) -> torch.Tensor:
        return torch.func.functional_call(enc, dict(zip(names, tables, strict=True)), (x,))

    gradcheck(fn, [x, *[p.detach() for p in enc.parameters()]])


def test_axis_resolutions_keep_the_vertices_per_level_and_follow_the_box() -> None:
    extent = [27.87, 48.26, 5.32]  # the outdoor seed-0 submap's box, metres
    assert triplane_axis_resolutions([64, 256], extent, 0.0) == [(64, 64, 64), (256, 256, 256)]
    ((rx, ry, rz),) = triplane_axis_resolutions([256], extent, 1.0)
    assert abs(rx * ry + rx * rz + ry * rz - 3 * 256**2) < 0.01 * 3 * 256**2
    cells_m = [e / (r - 1) for e, r in zip(extent, (rx, ry, rz), strict=True)]
    assert max(cells_m) / min(cells_m) < 1.05  # cubic cells
    assert triplane_axis_resolutions([4], [100.0, 1.0, 1.0], 1.0)[0][1:] == (2, 2)


@pytest.mark.parametrize("aspect", [-0.1, 1.5, float("nan"), "box"])
def test_a_bad_aspect_is_a_clear_error(aspect: object) -> None:
    with pytest.raises(ValueError, match="triplane_aspect must be a finite number in"):
        FieldConfig(triplane_aspect=aspect)
    # Hydra refuses a string for the float key itself, naming the override
    with pytest.raises((ValueError, ConfigCompositionException), match="triplane_aspect"):
        to_object(compose_config(["task=train_nerf", f"nerf.train.field.triplane_aspect={aspect}"]))


def test_a_level_with_fewer_than_two_vertices_on_an_axis_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match=r"needs >= 2 vertices on 3 axes, got \(4, 1, 4\)"):
        TriplaneEncoding([(4, 1, 4)], 2, 0.1)


def _field(aspect: float, contracted: bool = True) -> tuple[RadianceField, DensityGrid]:
    torch.manual_seed(0)
    cfg = FieldConfig(
        triplane_resolutions=[6, 10],
        triplane_aspect=aspect,
        triplane_channels=3,
        hidden=8,
        geo_features=3,
        appearance_dim=2,
        contracted=contracted,
        init_std=0.5,
        density_bias=0.0,
    )
    box = torch.tensor([-3.0, 1.0, -0.2]), torch.tensor([5.0, 9.5, 1.3])
    grid = DensityGrid(SamplerConfig(grid_resolution=8))
    return RadianceField(cfg, *box, 3), grid


def _outputs(field: RadianceField) -> tuple[torch.Tensor, ...]:
    x = encoding_points(30, 5) * torch.tensor([6.0, 6.0, 1.0]) + torch.tensor([1.0, 5.0, 0.5])
    d = torch.nn.functional.normalize(torch.randn(30, 3, generator=torch.Generator()), dim=-1)
    with torch.no_grad():
        out = field(x, d, torch.zeros(30, 2))
    return out.density, out.rgb


def test_the_field_gets_box_shaped_planes_and_export_keeps_their_shapes(tmp_path: Path) -> None:
    field, grid = _field(1.0)
    expected = triplane_axis_resolutions([6, 10], [8.0, 8.5, 1.5], 1.0)
    assert field.encoding.resolutions == tuple(expected)
    assert expected[1][2] < expected[1][0] < expected[1][1]  # z < x < y, as the box
    loaded, _ = load_field(export_field(tmp_path / "field", field, grid))
    assert loaded.config.triplane_aspect == 1.0
    shapes = [p.shape for p in field.encoding.planes]
    assert [p.shape for p in loaded.encoding.planes] == shapes
    for a, b in zip(_outputs(loaded), _outputs(field), strict=True):
        assert torch.equal(a, b)


def test_a_field_exported_before_the_setting_still_loads(tmp_path: Path) -> None:
    """The earlier format: a level's three planes stacked in one (3, C, R, R) tensor
    ``field.encoding.planes.{level}`` and no ``triplane_aspect`` in ``field.json``."""
    field, grid = _field(0.0)
    out = export_field(tmp_path / "field", field, grid)
    tensors = load_file(out / "field.safetensors")
    planes = [tensors.pop(f"field.encoding.planes.{i}") for i in range(6)]
    for level in range(2):
        tensors[f"field.encoding.planes.{level}"] = torch.stack(planes[3 * level : 3 * level + 3])
    save_file(tensors, out / "field.safetensors")
    record = json.loads((out / "field.json").read_text())
    del record["field"]["triplane_aspect"]
    (out / "field.json").write_text(json.dumps(record))
    loaded, _ = load_field(out)
    assert loaded.config.triplane_aspect == 0.0
    assert loaded.encoding.resolutions == ((6, 6, 6), (10, 10, 10))
    for a, b in zip(_outputs(loaded), _outputs(field), strict=True):
        assert torch.equal(a, b)


def test_a_field_file_without_its_box_is_a_clear_error(tmp_path: Path) -> None:
    field, grid = _field(1.0)
    out = export_field(tmp_path / "field", field, grid)
    tensors = load_file(out / "field.safetensors")
    del tensors["field.normalise.half_extent"]
    save_file(tensors, out / "field.safetensors")
    with pytest.raises(ValueError, match="no field box"):
        load_field(out)
