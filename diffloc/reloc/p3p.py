"""Batched minimal P3P solver (Lambda Twist, Persson & Nordberg, ECCV 2018).

Given three bearing vectors ``y_i`` (unit rays in the camera frame) and their world points
``x_i``, the unknown depths ``lambda_i`` (distances along the rays) satisfy::

    |lambda_i y_i - lambda_j y_j|^2 = |x_i - x_j|^2 = a_ij,   i < j.

With ``b_ij = y_i . y_j`` and ``lambda^T M_ij lambda = a_ij`` these are three quadrics in
``lambda``. Two homogeneous combinations ``D1 = a23 M12 - a12 M23`` and
``D2 = a23 M13 - a13 M23`` (``lambda^T D lambda = 0``) define two conics; a singular member
``D0 = D1 + gamma D2`` of their pencil (``det D0 = 0`` is a cubic in ``gamma``) is a pair of
lines through their intersections. Whenever a real solution exists the cubic has a real root
whose ``D0`` is a *real* line pair (eigenvalues ``sigma1 > 0 > sigma2``), and the largest real
root is always one. Each line ``e1 . lambda = +-s e2 . lambda`` (eigenvectors of ``D0``,
``s = sqrt(-sigma2 / sigma1)``) is intersected with one of the conics (a quadratic), the scale
of ``lambda`` follows from the sum of the three distance equations, and Newton steps on the
distance equations polish the depths (two by default; none inside RANSAC, whose models are
refined on their inliers anyway). The rotation is
``R = [dc12, dc13, dc12 x dc13] [dx12, dx13, dx12 x dx13]^-1`` (camera-frame vs world point
differences) and ``t = lambda_1 y_1 - R x_1``.

The implementation follows the paper's mathematics, written for tensors of ``H`` hypotheses
(no Python loops over hypotheses) with as few torch operations as possible, since for the
hundred-odd hypotheses of a RANSAC batch their fixed cost dominates: symmetric 3x3 matrices
are (H, 6) rows and their adjugates one gather and three element-wise operations, the cubic's
coefficients are the traces ``tr(adj(D_i) D_j)``, the cubic is solved in closed form
(Cardano / trigonometric) and polished by a Newton step, and the eigenvectors of the rank-2
``D0`` come from its adjugate (``adj D0 = sigma1 sigma2 e3 e3^T``) and the rank-1 matrix
``D0 - sigma2 (I - e3 e3^T) = (sigma1 - sigma2) e1 e1^T``.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import torch

from diffloc.checks import ShapeError, check_finite, check_shape

__all__ = ["P3P_MAX_SOLUTIONS", "solve_p3p"]

P3P_MAX_SOLUTIONS = 4
"""Largest number of real P3P solutions per sample."""

# Validity tolerances (dimensionless, float64).
_COLLINEAR_SIN2 = 1e-10  # squared sine of the angle between the world-point differences
_RANK_EPS = 1e-14  # sigma1 * sigma2 must be below -_RANK_EPS |D0|^2 (a proper line pair)
_ORTHONORMAL_TOL = 1e-6  # largest |R R^T - I| of an accepted rotation

# [tr(adj(D1) D1), tr(adj(D1) D2), tr(adj(D2) D1), tr(adj(D2) D2)] times these are the
# coefficients c0..c3 of det(D1 + g D2) (tr(adj(X) X) = 3 det X).
_TRACE_TO_CUBIC = (1.0 / 3.0, 1.0, 1.0, 1.0 / 3.0)
# Symmetric 3x3 matrices are (..., 6) rows [s00, s01, s02, s11, s12, s22].
_SYM_TO_FULL = (0, 1, 2, 1, 3, 4, 2, 4, 5)
_SYM_DIAGONAL = (0, 3, 5)
_SYM_NORM_WEIGHTS = (1.0, 2.0, 2.0, 1.0, 2.0, 1.0)  # sum w s^2 = squared Frobenius norm
# adj_k = s[p] s[q] - s[r] s[u] for (p, q, r, u) in the columns below, k = 00, 01, ..., 22.
_SYM_ADJUGATE = (
    (3, 2, 1, 0, 1, 0),
    (5, 4, 4, 5, 2, 3),
    (4, 1, 2, 2, 0, 1),
    (4, 5, 3, 2, 4, 1),
)
# D1 and D2 (symmetric rows) are linear in v = [n (3), n_i gram_k (27, index 3 + 9 i + k)],
# with b12, b13, b23 at k = 1, 2, 5 of the flat Gram matrix of the bearings:
# D1 = n23 M12 - n12 M23 = [n23, -n23 b12, 0, n23 - n12, n12 b23, -n12] and
# D2 = n23 M13 - n13 M23 = [n23, 0, -n23 b13, -n13, n13 b23, n23 - n13]. Each entry is a list
# of (index in v, coefficient).
_D1_D2_MAP = (
    ((2, 1.0),),
    ((22, -1.0),),
    (),
    ((2, 1.0), (0, -1.0)),
    ((8, 1.0),),
    ((0, -1.0),),
    ((2, 1.0),),
    (),
    ((23, -1.0),),
    ((1, -1.0),),
    ((17, 1.0),),
    ((2, 1.0), (1, -1.0)),
)
_PAIRS = ((0, 0, 1), (1, 2, 2))  # (i, j) of the pairs 12, 13, 23


class _Constants(NamedTuple):
    trace_to_cubic: torch.Tensor  # (4,)
    sym_to_full: torch.Tensor  # (9,) long
    sym_diagonal: torch.Tensor  # (3,) long
    sym_norm_weights: torch.Tensor  # (6,)
    sym_adjugate: torch.Tensor  # (24,) long
    d1_d2_map: torch.Tensor  # (30, 12), v -> [D1, D2]
    pair_i: torch.Tensor  # (3,) long
    pair_j: torch.Tensor  # (3,) long
    gram_pairs: torch.Tensor  # (3,) long, positions of b12, b13, b23 in a flat 3x3 Gram
    eye: torch.Tensor  # (3, 3)
    three_eye: torch.Tensor  # (3, 3)


@functools.lru_cache(maxsize=8)
def _constants(dtype: torch.dtype, device: torch.device) -> _Constants:
    """Constant tensors, made once per dtype and device (never modified in place)."""

    def index(values: tuple[int, ...]) -> torch.Tensor:
        return torch.tensor(values, dtype=torch.long, device=device)

    with torch.inference_mode(False):  # ordinary tensors even if first made in RANSAC
        return _Constants(
            trace_to_cubic=torch.tensor(_TRACE_TO_CUBIC, dtype=dtype, device=device),
            sym_to_full=index(_SYM_TO_FULL),
            sym_diagonal=index(_SYM_DIAGONAL),
            sym_norm_weights=torch.tensor(_SYM_NORM_WEIGHTS, dtype=dtype, device=device),
            sym_adjugate=index(sum(_SYM_ADJUGATE, ())),
            d1_d2_map=_linear_map(_D1_D2_MAP, 30, dtype, device),
            pair_i=index(_PAIRS[0]),
            pair_j=index(_PAIRS[1]),
            gram_pairs=index((1, 2, 5)),
            eye=torch.eye(3, dtype=dtype, device=device),
            three_eye=3.0 * torch.eye(3, dtype=dtype, device=device),
        )


def _linear_map(
    columns: tuple[tuple[tuple[int, float], ...], ...],
    rows: int,
    dtype: torch.dtype,
    device: torch.device,
) -> torch.Tensor:
    """(rows, len(columns)) matrix whose column k has the given (row, value) entries."""
    out = torch.zeros(rows, len(columns), dtype=dtype, device=device)
    for k, entries in enumerate(columns):
        for row, value in entries:
            out[row, k] = value
    return out


def _full(sym: torch.Tensor, const: _Constants) -> torch.Tensor:
    """(..., 3, 3) matrices from (..., 6) symmetric rows."""
    return sym.index_select(-1, const.sym_to_full).view(*sym.shape[:-1], 3, 3)


def _adjugate(sym: torch.Tensor, const: _Constants) -> torch.Tensor:
    """(..., 6) adjugates of (..., 6) symmetric rows."""
    p, q, r, u = sym.index_select(-1, const.sym_adjugate).view(*sym.shape[:-1], 4, 6).unbind(-2)
    return torch.addcmul(p * q, r, u, value=-1.0)


def _largest_real_cubic_root(k2: torch.Tensor, k1: torch.Tensor, k0: torch.Tensor) -> torch.Tensor:
    """Largest real root of ``g^3 + k2 g^2 + k1 g + k0`` (closed form + a Newton step)."""
    a = k2 / 3.0
    p3 = torch.addcmul(k1, k2, a, value=-1.0).div_(3.0)  # p / 3 of t^3 + p t + q, g = t - a
    h = torch.addcmul(k0, a, torch.addcmul(-k1, a, a, value=2.0)).mul_(0.5)  # q / 2
    p3_sq = p3 * p3
    disc = torch.addcmul(h * h, p3_sq, p3)
    # One real root (disc > 0): Cardano with the cancellation-free sign choice.
    big = torch.copysign(disc.clamp(min=0.0).sqrt_(), h).add_(h).neg_()
    u = torch.copysign(big.abs().pow_(1.0 / 3.0), big)
    t_one = torch.addcdiv(u, p3, u, value=-1.0)
    # Three real roots (disc <= 0, so p <= 0): trigonometric form, largest branch.
    r = p3.neg().clamp_(min=0.0).sqrt_()
    r3 = torch.mul(p3, r).neg_().clamp_(min=1e-300)  # r^3 = -p3 r
    cos_arg = torch.div(h, r3).neg_().clamp_(-1.0, 1.0)
    t_three = torch.acos(cos_arg).div_(3.0).cos_().mul_(r).mul_(2.0)
    g = torch.where(disc > 0, t_one, t_three).sub_(a)
    f = torch.addcmul(k0, torch.addcmul(k1, g + k2, g), g)
    df = torch.addcmul(k1, torch.add(g, k2, alpha=2.0 / 3.0), g, value=3.0)
    return torch.where(df != 0, torch.addcdiv(g, f, df, value=-1.0), g)


def _pick_column(M: torch.Tensor, score: torch.Tensor) -> torch.Tensor:
    """Column of (H, 3, 3) ``M`` with the largest ``score`` (H, 3), normalised."""
    col = torch.take_along_dim(M, score.argmax(-1)[:, None, None], dim=-1)[..., 0]
    return col / torch.linalg.vector_norm(col, dim=-1, keepdim=True)


def _intersection_directions(
    D12: torch.Tensor, const: _Constants
) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions (H, 4, 3) of the intersections of the conics D1, D2 (H, 2, 6), validity."""
    # det(A + g B) = det A + g tr(adj(A) B) + g^2 tr(A adj(B)) + g^3 det B for 3x3 matrices,
    # and tr(adj(X) Y) = sum_k w_k adj(X)_k Y_k on symmetric rows (w: off-diagonals twice).
    traces = (_adjugate(D12, const)[:, :, None] * D12[:, None]) @ const.sym_norm_weights
    c = traces.view(-1, 4) * const.trace_to_cubic  # (H, 4) coefficients of det(D1 + g D2)
    # Solve det(A + g B) = 0 with |det B| >= |det A|: the monic constant term is <= 1. If
    # both determinants vanish the result is NaN and the sample invalid (a null set).
    swap = c[:, 3].abs() < c[:, 0].abs()
    c = torch.where(swap[:, None], c.flip(-1), c)
    A, B = torch.where(swap[:, None, None], D12.flip(1), D12).unbind(1)
    k0, k1, k2 = (c[:, :3] / c[:, 3:]).unbind(-1)
    gamma = _largest_real_cubic_root(k2, k1, k0)
    D0 = torch.addcmul(A, gamma[:, None], B)

    adj = _adjugate(D0, const)
    diag_adj = adj.index_select(-1, const.sym_diagonal)
    minors = diag_adj.sum(-1)  # sigma1 * sigma2
    norm2 = (D0 * D0) @ const.sym_norm_weights  # squared Frobenius norm
    ok = minors < norm2.mul_(-_RANK_EPS)
    e3 = _pick_column(_full(adj, const), diag_adj.abs())  # null vector of D0
    D0_full = _full(D0, const)
    half = torch.diagonal(D0_full, dim1=-2, dim2=-1).sum(-1).mul_(0.5)
    root = torch.addcmul(-minors, half, half).clamp_(min=0.0).sqrt_()
    sigma1, sigma2 = half + root, half - root
    # D0 - sigma2 (I - e3 e3^T) = (sigma1 - sigma2) e1 e1^T
    projector = torch.addcmul(const.eye, e3[:, :, None], e3[:, None], value=-1.0)
    rank1 = torch.addcmul(D0_full, sigma2[:, None, None], projector, value=-1.0)
    e1 = _pick_column(rank1, torch.diagonal(rank1, dim1=-2, dim2=-1))
    e2 = torch.linalg.cross(e3, e1, dim=-1)
    se1 = torch.div(sigma2, sigma1).neg_().clamp_(min=0.0).sqrt_()[:, None] * e1
    W = torch.stack((e3, e2 + se1, e2 - se1), dim=1)  # (H, 3, 3) rows u, v+, v-

    # Lines e1.l = +-s e2.l span (e3, e2 +- s e1); restrict the better-conditioned conic
    # (on the lines A = -gamma B) to each of them: qa a^2 + qb a b + qc b^2 = 0.
    conic = _full(torch.where((gamma.abs() > 1.0)[:, None], A, B), const)
    forms = W @ conic @ W.transpose(-1, -2)
    qa = forms[:, 0, :1]
    qb = 2.0 * forms[:, 0, 1:]
    qc = torch.diagonal(forms, dim1=-2, dim2=-1)[:, 1:]
    disc = torch.addcmul(qb * qb, qa, qc, value=-4.0)
    qq = torch.copysign(disc.clamp(min=0.0).sqrt_(), qb).add_(qb).mul_(-0.5)
    alpha = torch.stack((qq, qc), dim=-1)  # two (alpha, beta) roots per line
    beta = torch.stack((qa.expand_as(qq), qq), dim=-1)
    dirs = torch.addcmul(
        alpha[..., None] * e3[:, None, None, :], beta[..., None], W[:, 1:, None, :]
    )
    valid = (ok[:, None] & (disc >= 0))[..., None].expand(-1, 2, 2)
    return dirs.reshape(-1, 4, 3), valid.reshape(-1, 4)


def _refine_depths(
    lam: torch.Tensor, b: tuple[torch.Tensor, ...], a: tuple[torch.Tensor, ...], iterations: int
) -> torch.Tensor:
    """Newton steps on the three distance equations; lam (H, 4, 3), b and a three (H, 1).

    The equations ``l_i^2 + l_j^2 - 2 b_ij l_i l_j = a_ij`` have the Jacobian
    ``2 [[j11, j12, 0], [j21, 0, j23], [0, j32, j33]]`` (``j11 = l1 - b12 l2``, ...), inverted
    by its adjugate. Starting from the closed-form depths each step roughly squares the
    relative error; steps with a vanishing determinant are skipped.
    """
    for _ in range(iterations):
        l1, l2, l3 = lam.unbind(-1)
        j11, j12 = l1 - b[0] * l2, l2 - b[0] * l1
        j21, j23 = l1 - b[1] * l3, l3 - b[1] * l1
        j32, j33 = l2 - b[2] * l3, l3 - b[2] * l2
        f1 = j11 * l1 + j12 * l2 - a[0]
        f2 = j21 * l1 + j23 * l3 - a[1]
        f3 = j32 * l2 + j33 * l3 - a[2]
        det = j11 * j23 * j32 + j12 * j21 * j33  # minus the determinant
        d1 = j12 * (j23 * f3 - j33 * f2) - j23 * j32 * f1
        d2 = j11 * (j33 * f2 - j23 * f3) - j21 * j33 * f1
        d3 = j21 * (j32 * f1 - j12 * f3) - j11 * j32 * f2
        scale = 0.5 / torch.where(det != 0, det, torch.ones_like(det))
        lam = lam + torch.stack((d1, d2, d3), -1) * scale[..., None]
    return lam


def p3p_flat(
    bearings: torch.Tensor, points_world: torch.Tensor, refine_iterations: int = 2
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`solve_p3p` on flat float64 inputs without input checks (the RANSAC fast path).

    Args:
        bearings: (H, 3, 3) *unit* rays, one per row.
        points_world: (H, 3, 3) world points, one per row.
        refine_iterations: Newton steps on the depths.

    Returns:
        ``(R_cw, t_cw, valid)``: (H, 4, 3, 3), (H, 4, 3) and (H, 4) bool. Entries that are
        not valid are unspecified (possibly NaN).
    """
    const = _constants(bearings.dtype, bearings.device)
    y = bearings
    gram = y @ y.transpose(-1, -2)
    diffs = points_world.index_select(1, const.pair_j) - points_world.index_select(1, const.pair_i)
    a = (diffs * diffs).sum(-1)  # a12, a13, a23
    total = a.sum(-1, keepdim=True)
    n = a / total
    products = (n[:, :, None] * gram.view(-1, 1, 9)).flatten(1)  # n_i gram_k
    D12 = (torch.cat((n, products), dim=-1) @ const.d1_d2_map).view(-1, 2, 6)
    dirs, valid = _intersection_directions(D12, const)

    # Scale from the sum of the distance equations: l^T (3 I - gram) l = a12 + a13 + a23.
    dmd = ((dirs @ (const.three_eye - gram)) * dirs).sum(-1)
    lam = torch.copysign(torch.div(total, dmd).sqrt_(), dirs.sum(-1))[..., None] * dirs
    if refine_iterations > 0:
        b = gram.view(-1, 9).index_select(-1, const.gram_pairs)  # b12, b13, b23
        b_cols, a_cols = b[:, None].unbind(-1), a[:, None].unbind(-1)
        lam = _refine_depths(lam, b_cols, a_cols, refine_iterations)
    valid = valid & (lam > 0).all(-1)

    # Pose from the camera-frame points C_i = lambda_i y_i.
    dx12, dx13 = diffs[:, 0], diffs[:, 1]
    normal = torch.linalg.cross(dx12, dx13, dim=-1)
    n2 = (normal * normal).sum(-1, keepdim=True)
    valid = valid & (n2 > _COLLINEAR_SIN2 * a[:, :1] * a[:, 1:2])
    inv_rows = (torch.linalg.cross(dx13, normal, dim=-1), torch.linalg.cross(normal, dx12, dim=-1))
    x_inv = torch.stack((*inv_rows, normal), dim=1) / n2[..., None]  # inverse of [dx12 dx13 n]
    C = lam[..., None] * y[:, None]  # (H, 4, 3, 3)
    dc = C[:, :, 1:] - C[:, :, :1]
    Y = torch.stack((dc[:, :, 0], dc[:, :, 1], torch.linalg.cross(dc[:, :, 0], dc[:, :, 1])), -1)
    H = y.shape[0]
    R = (Y.view(H, 12, 3) @ x_inv).view(H, 4, 3, 3)  # the rows of the 4 solutions at once
    t = C[:, :, 0] - (R.view(H, 12, 3) @ points_world[:, 0, :, None]).view(H, 4, 3)
    ortho = (R @ R.transpose(-1, -2)).sub_(const.eye).abs_().flatten(-2).amax(-1)
    return R, t, valid & (ortho < _ORTHONORMAL_TOL)


def solve_p3p(
    bearings: torch.Tensor, points_world: torch.Tensor, refine_iterations: int = 2
) -> tuple[torch.Tensor, torch.Tensor]:
    """All camera poses consistent with three 2D-3D correspondences (Lambda Twist P3P).

    Computation is in float64 whatever the input dtype. Degenerate samples (collinear or
    coincident world points, rays without a real solution, ill-conditioned solutions whose
    rotation is not orthonormal to 1e-6) give ``valid = False`` and an identity pose, never NaN.

    Args:
        bearings: (..., 3, 3) rays in the OpenCV camera frame, one per row (any positive
            length; normalised internally), e.g. ``[x, y, 1]`` of undistorted normalised
            image coordinates.
        points_world: (..., 3, 3) the matching world points, one per row.
        refine_iterations: Newton steps on the depths (0 disables).

    Returns:
        ``(T_cw, valid)``: (..., 4, 4, 4) world-to-camera transforms (solution index before
        the matrix dimensions) and (..., 4) bool, true for real solutions with all three
        points in front of the camera. Valid solutions are not sorted; use the mask.

    Raises:
        ShapeError: shapes other than (..., 3, 3) or different batch shapes.
        ValueError: non-finite inputs.

    Example:
        >>> X = torch.tensor([[0.0, 0, 4], [1, 0, 5], [0, 1, 6]], dtype=torch.float64)
        >>> T_cw, valid = solve_p3p(X, X)  # camera at the world origin
        >>> eye = torch.eye(4, dtype=torch.float64)
        >>> bool(((T_cw - eye).abs().amax((-1, -2))[valid] < 1e-9).any())
        True
    """
    check_shape(bearings, "*,3,3", "bearings")
    check_shape(points_world, "*,3,3", "points_world")
    if bearings.shape != points_world.shape:
        raise ShapeError(
            f"bearings and points_world must have the same shape (..., 3, 3), got "
            f"{tuple(bearings.shape)} and {tuple(points_world.shape)}"
        )
    check_finite(bearings, "bearings")
    check_finite(points_world, "points_world")
    batch = bearings.shape[:-2]
    y = bearings.to(torch.float64).reshape(-1, 3, 3)
    y = y / torch.linalg.vector_norm(y, dim=-1, keepdim=True)
    x = points_world.to(dtype=torch.float64, device=y.device).reshape(-1, 3, 3)
    R, t, valid = p3p_flat(y, x, refine_iterations)
    valid = valid & torch.isfinite(t).all(-1)
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = torch.where(
        valid[..., None, None], R, torch.eye(3, dtype=R.dtype, device=R.device)
    )
    T[..., :3, 3] = torch.where(valid[..., None], t, torch.zeros_like(t))
    T[..., 3, 3] = 1.0
    return T.reshape(*batch, P3P_MAX_SOLUTIONS, 4, 4), valid.reshape(*batch, P3P_MAX_SOLUTIONS)
