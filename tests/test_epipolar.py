"""Two-view epipolar geometry: the five-point solver against the truth and kornia, the
decomposition of E, and bad inputs."""

from __future__ import annotations

import math

import pytest
import torch
from kornia.geometry.epipolar import find_essential

from diffloc.checks import ShapeError
from diffloc.geometry.epipolar import decompose_essential, five_point_essential
from diffloc.geometry.se3 import hat, se3_exp
from diffloc.testing import assert_close

F64 = torch.float64


def _sign_free_distance(E: torch.Tensor, E_ref: torch.Tensor) -> torch.Tensor:
    """(..., K, L) sign-free Frobenius distances of unit-norm (..., K, 3, 3), (..., L, 3, 3)."""
    diff = (E[..., :, None, :, :] - E_ref[..., None, :, :, :]).flatten(-2).norm(dim=-1)
    summ = (E[..., :, None, :, :] + E_ref[..., None, :, :, :]).flatten(-2).norm(dim=-1)
    return torch.minimum(diff, summ)


def test_five_point_solver_finds_the_true_e_and_agrees_with_kornia() -> None:
    g = torch.Generator().manual_seed(3)
    B = 200
    points = torch.rand(B, 5, 3, generator=g, dtype=torch.float64) * 4 - 2
    points[..., 2] += 6.0
    xi = torch.cat(
        (
            torch.rand(B, 3, generator=g, dtype=torch.float64) - 0.5,
            0.3 * (torch.rand(B, 3, generator=g, dtype=torch.float64) - 0.5),
        ),
        dim=1,
    )
    T_qk = se3_exp(xi)
    points_q = points @ T_qk[:, :3, :3].mT + T_qk[:, None, :3, 3]
    xy_kf, xy_q = points[..., :2] / points[..., 2:], points_q[..., :2] / points_q[..., 2:]
    E_true = hat(T_qk[:, :3, 3]) @ T_qk[:, :3, :3]
    E_true = E_true / torch.linalg.matrix_norm(E_true)[:, None, None]
    E = five_point_essential(xy_kf, xy_q)
    assert E.shape == (B, 10, 3, 3)
    # As accurate as kornia's solver: median ~1e-13, a few ill-conditioned samples ~1e-6.
    closest = _sign_free_distance(E, E_true[:, None]).nan_to_num(math.inf).amin((-1, -2))
    assert float(closest.median()) < 1e-10 and float(closest.max()) < 1e-4
    # Every real candidate of kornia's solver is one of ours.
    E_kornia = find_essential(xy_kf, xy_q)
    valid_kornia = torch.isfinite(E_kornia).flatten(2).all(-1)
    match = _sign_free_distance(E_kornia, E).nan_to_num(math.inf).amin(-1)
    assert float(match[valid_kornia].quantile(0.98)) < 1e-6
    # A sample of five identical correspondences has no solution.
    same = torch.full((1, 5, 2), 0.1, dtype=torch.float64)
    assert bool(five_point_essential(same, same).isnan().all())


@pytest.mark.parametrize("shape", [(), (2,), (1, 2)])
def test_decomposition_reproduces_e_and_spans_its_manifold(shape: tuple[int, ...]) -> None:
    g = torch.Generator().manual_seed(4)
    xi = torch.cat(
        (
            torch.randn(*shape, 3, generator=g, dtype=F64),
            torch.randn(*shape, 3, generator=g, dtype=F64),
        ),
        dim=-1,
    )
    T = se3_exp(xi)
    t_true = T[..., :3, 3]
    E = 2.5 * hat(t_true) @ T[..., :3, :3]  # any scale
    R, t, basis = decompose_essential(E)
    assert R.shape == (*shape, 3, 3) and t.shape == (*shape, 3) and basis.shape == (*shape, 3, 2)
    eye = torch.eye(3, dtype=F64).expand(*shape, 3, 3)
    assert_close(R @ R.mT, eye)
    assert_close(torch.linalg.det(R), torch.ones(shape, dtype=F64))
    assert_close(t.norm(dim=-1), torch.ones(shape, dtype=F64))
    # t is the true direction up to sign; [t]_x R is E up to its scale and sign.
    direction = t_true / t_true.norm(dim=-1, keepdim=True)
    assert_close((t * direction).sum(-1).abs(), torch.ones(shape, dtype=F64))
    unit = E / torch.linalg.matrix_norm(E)[..., None, None]
    rebuilt = hat(t) @ R
    rebuilt = rebuilt / torch.linalg.matrix_norm(rebuilt)[..., None, None]
    sign = (rebuilt * unit).sum((-1, -2)).sign()[..., None, None]
    assert_close(rebuilt * sign, unit)
    # basis: orthonormal and orthogonal to t.
    assert_close(basis.mT @ basis, torch.eye(2, dtype=F64).expand(*shape, 2, 2))
    assert_close(basis.mT @ t[..., None], torch.zeros(*shape, 2, 1, dtype=F64))


def test_bad_inputs_raise() -> None:
    xy = torch.zeros(3, 5, 2, dtype=F64)
    with pytest.raises(ShapeError, match="xy1"):
        five_point_essential(torch.zeros(3, 4, 2, dtype=F64), xy)
    with pytest.raises(ShapeError, match="same B"):
        five_point_essential(xy, torch.zeros(2, 5, 2, dtype=F64))
    with pytest.raises(TypeError, match="xy2"):
        five_point_essential(xy, xy.float())
    with pytest.raises(ShapeError, match="E"):
        decompose_essential(torch.zeros(3, 4, dtype=F64))
