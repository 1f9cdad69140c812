"""Two-view epipolar geometry of calibrated cameras: the five-point solver and E's decomposition.

Conventions: ``E`` maps the first view to the second, ``x2^T E x1 = 0`` for undistorted
normalised homogeneous coordinates ``x = (X/Z, Y/Z, 1)``, i.e. ``E ~ [t]_x R`` with ``(R, t)``
the rotation and translation of ``T_21`` (first camera to second camera). Essential matrices
are defined up to scale and sign; the solvers return them with unit Frobenius norm. Geometry is
float64.

The five-point solver follows kornia's :func:`kornia.geometry.epipolar.find_essential`
(Nister's elimination, the degree-10 polynomial's roots as companion-matrix eigenvalues), in
about a tenth of its tensor operations: its polynomial products are single matrix products
with constant tables, and it skips what only autograd and accelerators need (a gradient
through the roots, host round trips).

Example:
    >>> from diffloc.geometry.se3 import hat, so3_exp
    >>> R = so3_exp(torch.tensor([0.0, 0.1, 0.0], dtype=torch.float64))
    >>> t = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    >>> R_est, t_est, _ = decompose_essential(hat(t) @ R)
    >>> torch.allclose(hat(t_est) @ R_est, hat(t) @ R) or torch.allclose(
    ...     hat(t_est) @ R_est, -hat(t) @ R)
    True
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import torch

from diffloc.checks import ShapeError, check_shape

__all__ = ["decompose_essential", "five_point_essential"]

# Monomials (exponents of x, y, z) of Nister's five-point method: the linear forms in
# (x, y, z, 1) whose coefficients are the null-space basis, their products, and the twenty
# cubic monomials in the order of the elimination (the first ten are eliminated; rows 4-9 of
# the result are those of x^2 z, x^2, y^2 z, y^2, x y z, x y).
_LINEAR = ((1, 0, 0), (0, 1, 0), (0, 0, 1), (0, 0, 0))
_QUADRATIC = (
    (2, 0, 0), (1, 1, 0), (1, 0, 1), (1, 0, 0), (0, 2, 0), (0, 1, 1), (0, 1, 0), (0, 0, 2),
    (0, 0, 1), (0, 0, 0),
)  # fmt: skip
_CUBIC = (
    (3, 0, 0), (0, 3, 0), (2, 1, 0), (1, 2, 0), (2, 0, 1), (2, 0, 0), (0, 2, 1), (0, 2, 0),
    (1, 1, 1), (1, 1, 0), (1, 0, 2), (1, 0, 1), (1, 0, 0), (0, 1, 2), (0, 1, 1), (0, 1, 0),
    (0, 0, 3), (0, 0, 2), (0, 0, 1), (0, 0, 0),
)  # fmt: skip
_HIDDEN_ROWS = (4, 6, 8, 5, 7, 9)  # <x^2 z>, <y^2 z>, <x y z>, then <x^2>, <y^2>, <x y>
_RANK_EPS = 1e3  # a design whose R factor has a diagonal below this many epsilons is singular
_REAL_ROOT_TOL = 1e-10  # |imag| of a real root, relative to max(1, |root|)


class _Tables(NamedTuple):
    """Constant tables of :func:`five_point_essential` (float64, never modified in place)."""

    linear_products: torch.Tensor  # (16, 10): (a, c) linear x linear -> quadratic
    cubic_products: torch.Tensor  # (40, 20): (q, c) quadratic x linear -> cubic
    cross: torch.Tensor  # (3, 9): (j, k) -> sum of eps_jki a_j b_k, the cross product
    half_eye: torch.Tensor  # (9, 1) flattened I / 2
    hidden: torch.Tensor  # (20, 13) [top | bottom] rows -> three polynomials in z
    cubic_times_cubic: torch.Tensor  # (16, 7) polynomial product (highest degree first)
    sextic_times_quartic: torch.Tensor  # (35, 11)
    subdiagonal: torch.Tensor  # (9, 10) the companion matrix below its first row
    hidden_rows: torch.Tensor  # (6,) long
    degrees: torch.Tensor  # (5,) 4, 3, 2, 1, 0


def _product_table(
    left: tuple[tuple[int, ...], ...], right: tuple[tuple[int, ...], ...], out: tuple
) -> torch.Tensor:
    """(len(left) * len(right), len(out)) table of monomial products."""
    index = {monomial: k for k, monomial in enumerate(out)}
    table = torch.zeros(len(left), len(right), len(out), dtype=torch.float64)
    for a, ma in enumerate(left):
        for b, mb in enumerate(right):
            table[a, b, index[tuple(p + q for p, q in zip(ma, mb, strict=True))]] = 1.0
    return table.flatten(0, 1)


def _convolution_table(m: int, n: int) -> torch.Tensor:
    """(m * n, m + n - 1) table of the product of polynomials of m and n coefficients."""
    table = torch.zeros(m, n, m + n - 1, dtype=torch.float64)
    for i in range(m):
        for j in range(n):
            table[i, j, i + j] = 1.0
    return table.flatten(0, 1)


@functools.lru_cache(maxsize=4)
def _tables(device: torch.device) -> _Tables:
    """The constant tables of :func:`five_point_essential` on ``device``."""
    cross = torch.zeros(3, 3, 3, dtype=torch.float64)
    for j, k, i in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):  # eps_jki = 1, eps_kji = -1
        cross[j, k, i], cross[k, j, i] = 1.0, -1.0
    # <k> = top_k - z bottom_k: the coefficients (highest degree first) of x (a cubic), y (a
    # cubic) and 1 (a quartic) from the ten non-eliminated monomials
    # (x z^2, x z, x, y z^2, y z, y, z^3, z^2, z, 1) of a top and a bottom row.
    hidden = torch.zeros(20, 13, dtype=torch.float64)
    for k in range(10):
        column = (0, 4, 8)[(k >= 3) + (k >= 6)] + k - (0, 3, 6)[(k >= 3) + (k >= 6)]
        hidden[k, column + 1] = 1.0
        hidden[10 + k, column] = -1.0
    with torch.inference_mode(False):
        return _Tables(
            *(
                t.to(device)
                for t in (
                    _product_table(_LINEAR, _LINEAR, _QUADRATIC),
                    _product_table(_QUADRATIC, _LINEAR, _CUBIC),
                    cross.view(9, 3).T.contiguous(),
                    (0.5 * torch.eye(3, dtype=torch.float64)).view(9, 1),
                    hidden,
                    _convolution_table(4, 4),
                    _convolution_table(7, 5),
                    torch.eye(9, 10, dtype=torch.float64),
                    torch.tensor(_HIDDEN_ROWS),
                    torch.arange(4, -1, -1, dtype=torch.float64),
                )
            )
        )


def _check_samples(xy1: torch.Tensor, xy2: torch.Tensor) -> None:
    """Raise unless ``xy1`` and ``xy2`` are float64 (B, 5, 2) tensors of the same shape."""
    for name, xy in (("xy1", xy1), ("xy2", xy2)):
        if not isinstance(xy, torch.Tensor) or xy.dtype != torch.float64:
            raise TypeError(
                f"{name} must be a float64 torch.Tensor, got {getattr(xy, 'dtype', type(xy))}"
            )
        check_shape(xy, "B,5,2", name)
    if xy1.shape != xy2.shape:
        raise ShapeError(
            f"xy1 and xy2 must both be (B, 5, 2) with the same B, got {tuple(xy1.shape)} and "
            f"{tuple(xy2.shape)}"
        )


def five_point_essential(xy1: torch.Tensor, xy2: torch.Tensor) -> torch.Tensor:
    """Essential matrices of minimal samples by Nister's five-point method.

    The null space of the five epipolar constraints ``x2^T E x1 = 0`` is four-dimensional,
    ``E = x X + y Y + z Z + W``; ``det E = 0`` and ``2 E E^T E - tr(E E^T) E = 0`` are ten
    cubics in ``(x, y, z)``, Gauss-Jordan elimination of ten of their monomials leaves three
    equations linear in ``(x, y, 1)`` with polynomial coefficients in ``z``, whose determinant
    (degree ten) has the ``z`` of every solution as a real root; ``x`` and ``y`` follow from
    the cross product of two of the equations.

    Args:
        xy1: (B, 5, 2) float64 undistorted normalised coordinates in the first view.
        xy2: (B, 5, 2) float64 the matching coordinates in the second view.

    Returns:
        (B, 10, 3, 3) float64 candidates with ``x2^T E x1 = 0`` and unit Frobenius norm, NaN
        in the slots without a real solution and in all slots of a rank-deficient sample
        (repeated or degenerate points).

    Raises:
        ShapeError: inputs that are not both (B, 5, 2).
        TypeError: inputs that are not float64 tensors.

    Example:
        >>> from diffloc.geometry.se3 import hat
        >>> X1 = torch.tensor([[[0.1, 0.2, 4.0], [-0.5, 0.3, 5.0], [0.4, -0.3, 6.0],
        ...                     [0.0, 0.6, 4.5], [-0.2, -0.4, 7.0]]], dtype=torch.float64)
        >>> t = torch.tensor([0.3, 0.0, 0.1], dtype=torch.float64)  # T_21 = (I, t)
        >>> X2 = X1 + t
        >>> E = five_point_essential(X1[..., :2] / X1[..., 2:], X2[..., :2] / X2[..., 2:])
        >>> E_true = hat(t) / torch.linalg.matrix_norm(hat(t))
        >>> distance = torch.minimum(torch.linalg.matrix_norm(E - E_true),
        ...                          torch.linalg.matrix_norm(E + E_true))
        >>> E.shape, bool(distance.nan_to_num(1.0).min() < 1e-9)
        (torch.Size([1, 10, 3, 3]), True)
    """
    _check_samples(xy1, xy2)
    const = _tables(xy1.device)
    B = xy1.shape[0]
    h1 = torch.nn.functional.pad(xy1, (0, 1), value=1.0)
    h2 = torch.nn.functional.pad(xy2, (0, 1), value=1.0)
    design = (h2[..., :, None] * h1[..., None, :]).flatten(2)  # (B, 5, 9): rows vec(x2 x1^T)
    Q, R = torch.linalg.qr(design.mT, mode="complete")
    pivots = R.diagonal(dim1=-2, dim2=-1).abs()
    singular = pivots.amin(-1) <= _RANK_EPS * torch.finfo(R.dtype).eps * pivots.amax(-1)
    N = Q[..., 5:]  # (B, 9, 4): entries of E as linear forms in (x, y, z, 1)
    rows = N.view(B, 3, 3, 4)
    # det E: the cross product of rows 0 and 1 (quadratics) dotted with row 2.
    products = (rows[:, 0, :, None, :, None] * rows[:, 1, None, :, None, :]).reshape(B, 9, 16)
    cofactors = const.cross @ (products @ const.linear_products)  # (B, 3, 10)
    determinant = (cofactors.mT @ rows[:, 2]).reshape(B, 1, 40) @ const.cubic_products
    # (E E^T - tr(E E^T) I / 2) E, the nine trace constraints.
    columns = rows.permute(0, 1, 3, 2).reshape(B, 12, 3)  # ((i, a), k)
    EEt = (columns @ columns.view(B, 3, 4, 3).permute(0, 3, 1, 2).reshape(B, 3, 12)).view(
        B, 3, 4, 3, 4
    )
    EEt = EEt.permute(0, 1, 3, 2, 4).reshape(B, 9, 16) @ const.linear_products  # (B, 9, 10)
    EEt = EEt - const.half_eye * EEt[:, ::4].sum(1, keepdim=True)
    trace = EEt.view(B, 3, 3, 10).permute(0, 1, 3, 2).reshape(B, 30, 3) @ rows.reshape(B, 3, 12)
    trace = trace.view(B, 3, 10, 3, 4).permute(0, 1, 3, 2, 4).reshape(B, 9, 40)
    coefficients = torch.cat((trace @ const.cubic_products, determinant), dim=1)  # (B, 10, 20)
    reduced, info = torch.linalg.solve_ex(coefficients[..., :10], coefficients[..., 10:])
    top_bottom = reduced.index_select(1, const.hidden_rows).view(B, 2, 3, 10)
    hidden = top_bottom.transpose(1, 2).reshape(B, 3, 20) @ const.hidden  # (B, 3, 13)
    cubics, quartic = hidden[..., :8].view(B, 3, 2, 4), hidden[..., 8:]
    sextics = (cubics[:, :, None, 0, :, None] * cubics[:, None, :, 1, None, :]).reshape(B, 9, 16)
    minors = const.cross @ (sextics @ const.cubic_times_cubic)  # (B, 3, 7)
    polynomial = (minors.mT @ quartic).reshape(B, 1, 35) @ const.sextic_times_quartic
    first_row = -polynomial[..., 1:] / polynomial[..., :1]  # monic, z^9 first
    usable = torch.isfinite(first_row).all(-1) & ((info == 0) & ~singular)[:, None]
    companion = torch.cat(
        (torch.where(usable[..., None], first_row, 0.0), const.subdiagonal.expand(B, 9, 10)), 1
    )
    roots = torch.linalg.eigvals(companion)  # (B, 10)
    real = (roots.imag.abs() <= _REAL_ROOT_TOL * roots.abs().clamp(min=1.0)) & usable
    z = roots.real
    powers = z[..., None] ** const.degrees  # (B, 10, 5): z^4 ... 1
    xy_terms = (cubics @ powers[:, None, :, 1:].mT).unbind(2)  # two (B, 3, 10)
    equations = torch.stack((*xy_terms, quartic @ powers.mT), dim=-1)  # (B, 3, 10, 3)
    solution = torch.linalg.cross(equations[:, 0], equations[:, 1], dim=-1)  # ~ (x, y, 1)
    weights = torch.cat(
        (solution[..., :2] / solution[..., 2:], z[..., None], torch.ones_like(z)[..., None]), -1
    )
    E = (N @ weights.mT).mT.reshape(B, 10, 3, 3)
    E = E / torch.linalg.matrix_norm(E)[..., None, None]
    valid = real & torch.isfinite(E).flatten(2).all(-1)
    return torch.where(valid[..., None, None], E, math.nan)


def decompose_essential(E: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A rotation and a unit translation of essential matrices, and the translation's normal plane.

    One of the four decompositions: ``[t]_x R = +-E / s`` (``s`` the common singular value);
    the other three are ``(R, -t)`` and ``(R', +-t)`` with ``R' = U W^T V^T``, and telling them
    apart needs points in front of both cameras. ``basis`` spans the plane orthogonal to
    ``t``, so ``R exp([w]_x)`` and ``normalize(t + basis d)`` parametrise the five-dimensional
    essential manifold around ``E``.

    Args:
        E: (..., 3, 3) essential matrices (any scale and sign, rank 2 up to noise).

    Returns:
        ``(R, t, basis)``: (..., 3, 3) rotations ``U W V^T`` (det +1), (..., 3) unit
        translations (the left singular vector of the zero singular value) and (..., 3, 2)
        orthonormal bases of the plane orthogonal to ``t``.

    Raises:
        ShapeError: ``E`` is not (..., 3, 3).

    Example:
        >>> E = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]],
        ...                  dtype=torch.float64)  # [t]_x with t = x, R = I
        >>> R, t, basis = decompose_essential(E)
        >>> t.abs().tolist(), basis.shape
        ([1.0, 0.0, 0.0], torch.Size([3, 2]))
    """
    if not isinstance(E, torch.Tensor) or E.shape[-2:] != (3, 3):  # checked only if wrong
        check_shape(E, "*,3,3", "E")
    U, _, Vh = torch.linalg.svd(E)
    U = U * torch.linalg.det(U).sign()[..., None, None]
    Vh = Vh * torch.linalg.det(Vh).sign()[..., None, None]
    W = E.new_tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return U @ W @ Vh, U[..., 2], U[..., :2]
