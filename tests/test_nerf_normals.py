"""Analytic normals (one evaluation, first-order autograd) against the autograd density
gradient with double backward, in float64: values, normal-loss gradients, gradcheck."""

from __future__ import annotations

import pytest
import torch

from diffloc.maps.nerf.contraction import SceneNormalisation
from diffloc.maps.nerf.encodings import (
    HashGridEncoding,
    TriplaneEncoding,
    multilinear,
    multilinear_with_gradient,
)
from diffloc.maps.nerf.field import FieldConfig, RadianceField
from diffloc.maps.nerf.losses import normal_loss
from diffloc.maps.nerf.renderer import render_rays
from diffloc.maps.nerf.rendering import composite
from diffloc.maps.nerf.sampler import DensityGrid, SamplerConfig
from diffloc.testing import assert_close, gradcheck


def _points(n: int, seed: int, spread: float = 2.2) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * spread


def _field(kind: str, contracted: bool) -> RadianceField:
    torch.manual_seed(0)
    cfg = FieldConfig(
        encoding=kind,
        triplane_resolutions=[5, 9],
        triplane_channels=3,
        hash_levels=3,
        hash_log2_table_size=6,
        hash_base_resolution=3,
        hash_max_resolution=9,
        hidden=16,
        geo_features=4,
        appearance_dim=2,
        contracted=contracted,
        init_std=0.5,
    )
    box = torch.tensor([1.0, 1.5, 0.8])
    return RadianceField(cfg, -box, box, 3).double()


def _autograd_normals(field: RadianceField, x: torch.Tensor) -> torch.Tensor:
    """The reference: ``-grad(density)`` by autograd, graph kept (double backward)."""
    x = x.detach().requires_grad_(True)
    (grad,) = torch.autograd.grad(field.density(x).sum(), x, create_graph=True)
    return -grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-9)


def test_multilinear_gradient_of_a_bilinear_cell() -> None:
    # corners (0,0)=0, (1,0)=1, (0,1)=2, (1,1)=4: f = a + 2 b + a b on the unit cell
    rows = torch.tensor([[0.0], [1.0], [2.0], [4.0]], dtype=torch.float64)
    frac = torch.tensor([[0.25], [0.5]], dtype=torch.float64)
    expected = torch.tensor([0.25 + 1.0 + 0.125], dtype=torch.float64)
    assert_close(multilinear(rows, frac), expected)
    coords = torch.zeros(2, 1, dtype=torch.float64)
    # resolution 3: one cell spans 1 coordinate unit, so d/dcoord = d/dfrac
    value, slope = multilinear_with_gradient(rows, frac, coords, 3)
    assert_close(value, expected)
    assert_close(slope, torch.tensor([[1.5], [2.25]], dtype=torch.float64))
    outside = torch.tensor([[1.5], [0.0]], dtype=torch.float64)
    _, clamped = multilinear_with_gradient(rows, frac, outside, 3)
    assert_close(clamped, torch.tensor([[0.0], [2.25]], dtype=torch.float64))


@pytest.mark.parametrize("kind", ["triplane", "hashgrid"])
def test_encoding_jacobian_matches_autograd_to_second_order(kind: str) -> None:
    torch.manual_seed(2)
    enc = (
        TriplaneEncoding((5, 8), 3, 0.3)
        if kind == "triplane"
        else HashGridEncoding(4, 2, 8, 3, 16, 0.5)
    ).double()
    x = _points(60, 1).requires_grad_(True)
    features = enc(x)
    w = torch.randn_like(features)
    (reference,) = torch.autograd.grad((features * w).sum(), x, create_graph=True)
    analytic_features, jacobian = enc.forward_with_jacobian(x)
    analytic = torch.einsum("nf,nfk->nk", w, jacobian)
    assert_close(analytic_features, features)
    assert_close(analytic, reference)
    params = [x, *enc.parameters()]
    g_ref = torch.autograd.grad(reference.pow(2).sum() + features.sum(), params)
    g_new = torch.autograd.grad(analytic.pow(2).sum() + analytic_features.sum(), params)
    for a, b in zip(g_new, g_ref, strict=True):
        assert_close(a, b)


@pytest.mark.parametrize("contracted", [False, True])
def test_normalisation_pullback_is_the_transposed_jacobian(contracted: bool) -> None:
    box_min, box_max = torch.tensor([-1.0, -2.0, 0.0]), torch.tensor([3.0, 2.0, 1.0])
    norm = SceneNormalisation(box_min, box_max, contracted).double()
    p = torch.randn(200, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 4
    p.requires_grad_(True)
    v = torch.randn(200, 3, dtype=torch.float64)
    (reference,) = torch.autograd.grad(norm(p)[0], p, v)
    assert_close(norm.pullback(p, v), reference)


@pytest.mark.parametrize("kind", ["triplane", "hashgrid"])
@pytest.mark.parametrize("contracted", [False, True])
def test_normals_and_normal_loss_gradients_match_double_backward(
    kind: str, contracted: bool
) -> None:
    field = _field(kind, contracted)
    x = _points(50, 3, spread=2.6 if contracted else 2.0)
    density, _, normals = field.geometry_and_normals(x)
    reference = _autograd_normals(field, x)
    assert_close(density, field.density(x))
    assert_close(normals, reference)
    target = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1)
    params = list(field.parameters())
    g_new = torch.autograd.grad(normal_loss(normals, target), params, allow_unused=True)
    g_ref = torch.autograd.grad(normal_loss(reference, target), params, allow_unused=True)
    assert any(g is not None and float(g.abs().max()) > 0 for g in g_new)
    for a, b in zip(g_new, g_ref, strict=True):
        assert (a is None) == (b is None)
        if a is not None:
            assert_close(a, b)


def test_normals_are_zero_outside_a_bounded_field() -> None:
    field = _field("triplane", False)
    _, _, normals = field.geometry_and_normals(torch.tensor([[1.5, 0.0, 0.0]], dtype=torch.float64))
    assert float(normals.detach().abs().max()) == 0.0


class _Normals(torch.nn.Module):
    def __init__(self, field: RadianceField) -> None:
        super().__init__()
        self.field = field

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.field.geometry_and_normals(points)[2]


def test_normals_gradcheck_in_the_encoding_and_mlp_parameters() -> None:
    module = _Normals(_field("triplane", False))
    x = _points(6, 5, spread=1.6)
    names = ["field.encoding.planes.0", "field.density_mlp.0.weight", "field.density_mlp.2.weight"]
    base = dict(module.named_parameters())

    def fn(*values: torch.Tensor) -> torch.Tensor:
        return torch.func.functional_call(module, dict(zip(names, values, strict=True)), (x,))

    gradcheck(fn, [base[name].detach() for name in names])


def test_render_rays_with_grad_evaluates_each_sample_once_and_matches_autograd_normals() -> None:
    field = _field("triplane", False)
    # one evaluation call per pass: no early termination (which evaluates in chunks)
    sampler = SamplerConfig(
        grid_resolution=6, coarse_samples=16, importance_samples=8, stop_transmittance=0.0
    )
    grid = DensityGrid(sampler)
    grid.refresh(field.density, field.normalise, torch.Generator().manual_seed(0))
    g = torch.Generator().manual_seed(4)
    origins = (torch.rand(12, 3, generator=g, dtype=torch.float64) - 0.5) * 0.5
    directions = torch.nn.functional.normalize(torch.randn(12, 3, generator=g), dim=-1).double()
    calls = {"forward": 0, "forward_with_jacobian": 0}
    for name in calls:
        method = getattr(field.encoding, name)

        def counted(xyz: torch.Tensor, _method=method, _name=name) -> object:
            calls[_name] += 1
            return _method(xyz)

        setattr(field.encoding, name, counted)
    with torch.no_grad():
        rendered = render_rays(field, grid, origins, directions, None, with_normals=True)
    assert calls == {"forward": 2, "forward_with_jacobian": 0}  # no grad: again if visible
    calls.update(forward=0, forward_with_jacobian=0)
    assert_close(
        render_rays(field, grid, origins, directions, None, with_normals=True).normal,
        rendered.normal,
    )
    calls.update(forward=0, forward_with_jacobian=0)
    out = render_rays(field, grid, origins, directions, g, with_normals=True)
    assert calls == {"forward": 0, "forward_with_jacobian": 1}
    r, s = out.t.shape
    points = (origins[:, None] + out.t[..., None] * directions[:, None]).reshape(-1, 3)
    seen = (out.weights.detach() > grid.config.min_weight)[..., None]
    reference = composite(out.weights, _autograd_normals(field, points).reshape(r, s, 3) * seen)
    reference = reference / reference.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    assert_close(out.normal, reference)
    target = torch.nn.functional.normalize(torch.randn(r, 3, dtype=torch.float64), dim=-1)
    params = list(field.encoding.parameters()) + list(field.density_mlp.parameters())
    g_new = torch.autograd.grad(normal_loss(out.normal, target), params, retain_graph=True)
    g_ref = torch.autograd.grad(normal_loss(reference, target), params)
    for a, b in zip(g_new, g_ref, strict=True):
        assert_close(a, b)


def test_normals_on_the_box_face_are_the_limit_from_inside() -> None:
    """Guided lidar samples clamped to the far bound lie on the box face (cube coordinate 1):
    the normal there is the last cell's, not autograd's through ``grid_sample``'s border
    (which treats the vertex beyond the face as zero)."""
    field = _field("triplane", False)
    face = torch.tensor([[1.0, 0.3, -0.2], [-0.4, 1.5, 0.1]], dtype=torch.float64)
    inside = face * (1 - 1e-9)
    assert_close(field.normals(face), field.normals(inside), rtol=1e-6, atol=1e-6)
