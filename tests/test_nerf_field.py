"""Radiance field: encodings against their gather references, contraction, normals."""

from __future__ import annotations

import pytest
import torch

from diffloc.maps.nerf.contraction import SceneNormalisation, contract, uncontract
from diffloc.maps.nerf.encodings import (
    HashGridEncoding,
    TriplaneEncoding,
    _cell_rows,
    _vertex_index,
    bilinear_gather,
    trilinear_gather,
    trilinear_lookup,
)
from diffloc.maps.nerf.field import FieldConfig, RadianceField, build_encoding
from diffloc.testing import assert_close, gradcheck
from tests.encoding_checks import assert_matches_reference, encoding_points


def test_bilinear_gather_hits_vertices_and_interpolates_linearly() -> None:
    table = torch.arange(9.0)[:, None]  # 3x3 plane, value j*3 + i
    uv = torch.tensor([[-1.0, -1.0], [1.0, 1.0], [0.0, -1.0], [-0.5, 0.5]])
    # i = (u+1), j = (v+1): value = 3 j + i
    assert_close(bilinear_gather(table, uv, 3)[:, 0], torch.tensor([0.0, 8.0, 1.0, 0.5 + 4.5]))


def test_hash_levels_use_dense_rows_only_when_the_grid_fits() -> None:
    enc = HashGridEncoding(3, 2, 6, 3, 9, 0.1)
    assert enc.resolutions == (3, 5, 9)
    assert [len(t) for t in enc.tables] == [27, 64, 64]


@pytest.mark.parametrize("table_size", [2**19, 1000])
def test_hashed_rows_are_the_spatial_hash_modulo_the_table_size(table_size: int) -> None:
    """The power-of-two mask and the general remainder give Instant-NGP's hash modulo T."""
    vertex = torch.randint(0, 2048, (500, 3), generator=torch.Generator().manual_seed(0))
    primes = (1, 2654435761, 805459861)
    expected = [
        (int(i) * primes[0] ^ int(j) * primes[1] ^ int(k) * primes[2]) % table_size
        for i, j, k in vertex.tolist()
    ]
    assert _vertex_index(vertex, 2048, table_size).tolist() == expected


@pytest.mark.parametrize(("resolution", "table_size"), [(9, 1000), (2048, 2**19), (2048, 1000)])
def test_cell_rows_are_the_vertex_index_of_each_corner(resolution: int, table_size: int) -> None:
    """Per-axis rows of the eight corners (dense, hashed with a mask, hashed with a remainder)
    are :func:`_vertex_index` of the corner vertices, in the corner order of the gathers."""
    g = torch.Generator().manual_seed(0)
    lower = torch.randint(0, resolution - 1, (300, 3), generator=g)
    corners = torch.tensor([[(c >> a) & 1 for a in range(3)] for c in range(8)])
    vertex = (lower[:, None] + corners).reshape(-1, 3)
    expected = _vertex_index(vertex, resolution, table_size).view(300, 8)
    assert torch.equal(_cell_rows(lower.T, resolution, table_size), expected)


@pytest.mark.parametrize("resolution", [5, 40])
def test_trilinear_lookup_is_the_gather_interpolation_in_float64(resolution: int) -> None:
    """The fused lookup (dense and hashed level) gives the gathers' values, table and
    position gradients, and second derivatives (float64); no points give no rows."""
    torch.manual_seed(2)
    table = torch.randn(2**9, 3, dtype=torch.float64, requires_grad=True)
    x = encoding_points(60, 4).double().requires_grad_(True)
    fast, ref = trilinear_lookup(table, x, resolution), trilinear_gather(table, x, resolution)
    assert_close(fast, ref, rtol=1e-12, atol=1e-12)
    w = torch.randn_like(fast)
    g_fast = torch.autograd.grad((fast * w).sum(), [x, table], create_graph=True)
    g_ref = torch.autograd.grad((ref * w).sum(), [x, table], create_graph=True)
    for a, b in zip(g_fast, g_ref, strict=True):
        assert_close(a, b, rtol=1e-12, atol=1e-12)
    gg_fast = torch.autograd.grad(g_fast[0].square().sum(), [x, table])
    gg_ref = torch.autograd.grad(g_ref[0].square().sum(), [x, table])
    for a, b in zip(gg_fast, gg_ref, strict=True):
        assert_close(a, b, rtol=1e-12, atol=1e-12)
    assert trilinear_lookup(table, x[:0], resolution).shape == (0, 3)


@pytest.mark.parametrize("kind", ["triplane", "hashgrid"])
def test_fast_encoding_matches_gather_reference_values_and_gradients(kind: str) -> None:
    torch.manual_seed(0)
    enc = (
        TriplaneEncoding((5, 8), 3, 0.3)
        if kind == "triplane"
        else HashGridEncoding(4, 2, 8, 3, 16, 0.5)
    ).double()
    x = encoding_points(40).double().requires_grad_(True)
    assert_matches_reference(enc, x)


@pytest.mark.parametrize("kind", ["triplane", "hashgrid"])
def test_encoding_gradcheck_float64(kind: str) -> None:
    torch.manual_seed(1)
    enc = (
        TriplaneEncoding((4,), 2, 0.3)
        if kind == "triplane"
        else HashGridEncoding(2, 2, 5, 3, 6, 0.5)
    ).double()
    names = [name for name, _ in enc.named_parameters()]
    x = torch.rand(6, 3, dtype=torch.float64) * 1.8 - 0.9

    def fn(x: torch.Tensor, *tables: torch.Tensor) -> torch.Tensor:
        return torch.func.functional_call(enc, dict(zip(names, tables, strict=True)), (x,))

    gradcheck(fn, [x, *[p.detach() for p in enc.parameters()]])


@pytest.mark.parametrize("kind", ["triplane", "hashgrid"])
def test_jacobian_of_no_points_is_empty(kind: str) -> None:
    """An empty batch (a termination chunk whose rays have all stopped) has empty outputs."""
    enc = (
        TriplaneEncoding((4, 6), 3, 0.3)
        if kind == "triplane"
        else HashGridEncoding(2, 2, 5, 3, 6, 0.5)
    )
    features, jacobian = enc.forward_with_jacobian(torch.zeros(0, 3))
    assert features.shape == (0, enc.out_dim)
    assert jacobian.shape == (0, enc.out_dim, 3)


def test_contraction_is_identity_inside_and_inverted_by_uncontract() -> None:
    x = torch.tensor([[0.3, -0.9, 0.1], [3.0, 0.0, 0.0], [-10.0, 5.0, 1.0]])
    y = contract(x)
    assert_close(y[0], x[0])
    assert float(y.abs().max()) < 2.0
    assert_close(y[1], torch.tensor([5.0 / 3.0, 0.0, 0.0]))
    assert_close(uncontract(y), x, rtol=1e-5, atol=1e-5)


def test_contraction_is_mip_nerf_360s_formula_in_float64() -> None:
    """The per-point factor gives ``(2 - 1 / n) x / n`` beyond the unit cube (L-infinity n),
    and ``x`` inside, to float64 rounding; so do its gradients."""
    x = (torch.randn(500, 3, generator=torch.Generator().manual_seed(1)) * 3).double()
    x.requires_grad_(True)
    n = x.abs().amax(dim=-1, keepdim=True)
    expected = torch.where(n <= 1.0, x, (2.0 - 1.0 / n) * x / n)
    assert bool((n <= 1.0).any()) and bool((n > 1.0).any())
    assert_close(contract(x), expected, rtol=1e-14, atol=1e-14)
    v = torch.randn_like(x)
    (fast,) = torch.autograd.grad(contract(x), x, v)
    (ref,) = torch.autograd.grad(expected, x, v)
    assert_close(fast, ref, rtol=1e-12, atol=1e-12)


def test_normalisation_maps_the_box_to_the_cube_and_flags_outside() -> None:
    norm = SceneNormalisation(torch.tensor([0.0, 0, 0]), torch.tensor([2.0, 4, 6]), False)
    xyz, inside = norm(torch.tensor([[1.0, 2, 3], [2.0, 4, 6], [3.0, 2, 3]]))
    assert_close(xyz[:2], torch.tensor([[0.0, 0, 0], [1.0, 1, 1]]))
    assert inside.tolist() == [True, True, False]
    assert_close(norm.inverse(xyz), torch.tensor([[1.0, 2, 3], [2.0, 4, 6], [3.0, 2, 3]]))


def test_unknown_encoding_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="unknown encoding"):
        build_encoding(FieldConfig(encoding="voxels"))


def _field(kind: str, contracted: bool = False) -> RadianceField:
    torch.manual_seed(0)
    cfg = FieldConfig(
        encoding=kind,
        triplane_resolutions=[6],
        triplane_channels=4,
        hash_levels=2,
        hash_log2_table_size=6,
        hash_base_resolution=3,
        hash_max_resolution=8,
        hidden=16,
        geo_features=4,
        appearance_dim=2,
        contracted=contracted,
        init_std=0.5,
    )
    return RadianceField(cfg, torch.tensor([-1.0, -1, -1]), torch.tensor([1.0, 1, 1]), 3).double()


@pytest.mark.parametrize("kind", ["triplane", "hashgrid"])
@pytest.mark.parametrize("contracted", [False, True])
def test_normals_are_the_normalised_negative_density_gradient(kind: str, contracted: bool) -> None:
    field = _field(kind, contracted)
    x = encoding_points(8, 3).double() * 0.8
    d = torch.nn.functional.normalize(torch.randn(8, 3, dtype=torch.float64), dim=-1)
    out = field(x, d, torch.zeros(8, 2, dtype=torch.float64), with_normals=True)
    eps = 1e-6
    numeric = torch.stack(
        [
            (field.density(x + eps * e) - field.density(x - eps * e)) / (2 * eps)
            for e in torch.eye(3, dtype=torch.float64)
        ],
        dim=-1,
    )
    assert_close(out.normal, -numeric / numeric.norm(dim=-1, keepdim=True), rtol=1e-5, atol=1e-6)


def test_field_gradcheck_float64_through_the_normals() -> None:
    """The normal loss back-propagates through the density gradient (double backward)."""
    field = _field("triplane")
    x = encoding_points(5, 4).double() * 0.8
    d = torch.nn.functional.normalize(torch.randn(5, 3, dtype=torch.float64), dim=-1)
    codes = torch.zeros(5, 2, dtype=torch.float64)

    def fn(x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = field(x, d, codes, with_normals=True)
        return out.density, out.rgb, out.normal

    gradcheck(fn, [x])


def test_appearance_code_changes_colour_not_density() -> None:
    field = _field("triplane")
    with torch.no_grad():
        field.colour_mlp[0].weight.normal_()
    x, d = encoding_points(4).double() * 0.5, torch.tensor([[0.0, 0, 1.0]] * 4, dtype=torch.float64)
    a = field(x, d, torch.zeros(4, 2, dtype=torch.float64))
    b = field(x, d, torch.ones(4, 2, dtype=torch.float64))
    assert_close(a.density, b.density)
    assert float((a.rgb - b.rgb).abs().max().detach()) > 1e-3


def test_density_is_zero_outside_a_bounded_field() -> None:
    field = _field("triplane")
    with torch.no_grad():
        assert float(field.density(torch.tensor([[1.5, 0.0, 0.0]], dtype=torch.float64))) == 0.0


def test_trilinear_gather_reproduces_a_linear_function() -> None:
    r = 4
    i, j, k = torch.meshgrid(torch.arange(4.0), torch.arange(4.0), torch.arange(4.0), indexing="ij")
    # row (k R + j) R + i holds i + 2 j + 3 k
    table = torch.zeros(r**3, 1)
    table[((k * r + j) * r + i).long().flatten(), 0] = (i + 2 * j + 3 * k).flatten()
    xyz = torch.rand(20, 3) * 2 - 1
    u = (xyz + 1) * (r - 1) / 2
    assert_close(trilinear_gather(table, xyz, r)[:, 0], u[:, 0] + 2 * u[:, 1] + 3 * u[:, 2])
