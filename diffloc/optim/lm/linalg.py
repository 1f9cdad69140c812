"""Batched solvers of symmetric positive (semi-)definite systems: dense Cholesky, PCG."""

from __future__ import annotations

from collections.abc import Callable

import torch

from diffloc.checks import check_shape

__all__ = ["solve_spd"]


def solve_spd(H: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Solve symmetric positive (semi-)definite systems ``H x = b``, batched.

    Cholesky where it succeeds; the batch entries where it fails (not positive definite)
    fall back to a least-squares solve, which gives the minimum-norm solution for singular
    ``H`` (zero for ``H = 0``).

    Args:
        H: (..., D, D) symmetric matrices.
        b: (..., D) right-hand sides.

    Returns:
        (..., D) solutions.

    Example:
        >>> solve_spd(torch.diag(torch.tensor([2.0, 4.0])), torch.tensor([2.0, 2.0]))
        tensor([1.0000, 0.5000])
    """
    check_shape(H, "*,D,D", "H")
    check_shape(b, "*,D", "b")
    L, info = torch.linalg.cholesky_ex(H)
    y = torch.linalg.solve_triangular(L, b[..., None], upper=False)
    x = torch.linalg.solve_triangular(L.mT, y, upper=True)[..., 0]
    failed = info != 0
    if bool(failed.any()):
        fallback = torch.linalg.lstsq(H[failed], b[failed][..., None], driver="gelsd")
        x[failed] = fallback.solution[..., 0]
    return x


def _pcg(
    matvec: Callable[[torch.Tensor], torch.Tensor],
    precondition: Callable[[torch.Tensor], torch.Tensor],
    b: torch.Tensor,
    max_iterations: int,
    tolerance: float,
) -> torch.Tensor:
    """Batched preconditioned conjugate gradients for SPD systems, ``b``: (B, D)."""

    def dot(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return (x * y).sum(-1)

    def safe_ratio(num: torch.Tensor, den: torch.Tensor) -> torch.Tensor:
        return torch.where(den > 0, num / torch.where(den > 0, den, 1.0), 0.0)

    x = torch.zeros_like(b)
    r = b.clone()
    z = precondition(r)
    p = z.clone()
    rz = dot(r, z)
    threshold = tolerance * torch.linalg.vector_norm(b, dim=-1)
    for _ in range(max_iterations):
        if bool((torch.linalg.vector_norm(r, dim=-1) <= threshold).all()):
            break
        Ap = matvec(p)
        alpha = safe_ratio(rz, dot(p, Ap))
        x = x + alpha[:, None] * p
        r = r - alpha[:, None] * Ap
        z = precondition(r)
        rz_new = dot(r, z)
        p = z + safe_ratio(rz_new, rz)[:, None] * p
        rz = rz_new
    return x
