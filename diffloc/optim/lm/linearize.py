"""Residual blocks linearized at the current poses: function types, autodiff Jacobians.

The residual functions of :mod:`diffloc.optim.lm` return whitened residuals of blocks of
poses; their Jacobians are taken w.r.t. a right (body-frame) perturbation of each pose,
``J_a = d r(T_a @ se3_exp(d)) / d d`` at ``d = 0``.

Autodiff Jacobians
    When no analytic ``jacobian_fn`` is given, Jacobians come from :func:`torch.func.jacfwd`
    with respect to a zero tangent shared by all blocks (each block depends only on its own
    gathered poses, so one forward-mode pass per tangent direction gives every block's
    Jacobian). The residual function must then be composable with ``torch.func`` (no Python
    control flow on tensor values, no ``.item()``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from diffloc.checks import ShapeError, check_shape
from diffloc.geometry.se3 import se3_exp

__all__ = [
    "BlockJacobianFn",
    "BlockLinearization",
    "BlockResidualFn",
    "PoseJacobianFn",
    "PoseResidualFn",
    "autodiff_linearize",
]


@dataclass
class BlockLinearization:
    """Residual blocks and their Jacobians at the current parameters.

    Attributes:
        residuals: (B, M, R) whitened residuals.
        jac_a: (B, M, R, 6) Jacobians w.r.t. a right perturbation of pose ``index_a[m]``.
        jac_b: (B, M, R, 6) the same for pose ``index_b[m]``, or ``None`` (one-pose blocks).
        jac_extra: (B, M, R, E) Jacobians w.r.t. the extra parameters, or ``None``.
    """

    residuals: torch.Tensor
    jac_a: torch.Tensor
    jac_b: torch.Tensor | None = None
    jac_extra: torch.Tensor | None = None


BlockResidualFn = Callable[[torch.Tensor, torch.Tensor | None, torch.Tensor | None], torch.Tensor]
"""``(T_a (B, M, 4, 4), T_b (B, M, 4, 4) | None, extra (B, E) | None) -> (B, M, R)``: each
block's residual from the poses gathered at ``index_a`` / ``index_b`` (non-contiguous views:
each of the 16 pose entries is contiguous over the blocks)."""

BlockJacobianFn = Callable[
    [torch.Tensor, torch.Tensor | None, torch.Tensor | None], BlockLinearization
]
"""Same inputs as :data:`BlockResidualFn`, returns residuals and analytic Jacobians."""

PoseResidualFn = Callable[[torch.Tensor], torch.Tensor]
"""``T_wc (B, 4, 4) -> (B, N, R)``: residuals of ``B`` single-pose problems."""

PoseJacobianFn = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""``T_wc (B, 4, 4) -> (residuals (B, N, R), jacobians (B, N, R, 6))``, right perturbation."""


def autodiff_linearize(
    residual_fn: BlockResidualFn,
    T_a: torch.Tensor,
    T_b: torch.Tensor | None = None,
    extra: torch.Tensor | None = None,
) -> BlockLinearization:
    """Residuals and Jacobians of ``residual_fn`` by forward-mode autodiff.

    Differentiates ``residual_fn(T_a @ se3_exp(d_a), T_b @ se3_exp(d_b), extra + d_e)`` at
    ``d = 0`` with one tangent ``(d_a, d_b, d_e)`` shared by all blocks and problems: since a
    block depends only on its own poses and its own problem's extra parameters, this gives
    every block's Jacobian in ``6 (+ 6) + E`` forward-mode passes (``torch.func.jacfwd``).

    Args:
        residual_fn: the block residual function (must be composable with ``torch.func``).
        T_a: (B, M, 4, 4) first pose of every block (``(B, 4, 4)`` for single-pose problems).
        T_b: (B, M, 4, 4) second pose of every block, or ``None``.
        extra: (B, E) extra parameters, or ``None``.

    Returns:
        The linearization: residuals (B, M, R) and Jacobians (B, M, R, 6) / (B, M, R, E).

    Example:
        >>> T = torch.eye(4, dtype=torch.float64).expand(1, 2, 4, 4)
        >>> lin = autodiff_linearize(lambda Ta, Tb, e: Ta[..., :3, 3], T)
        >>> lin.jac_a[0, 0, :, :3]
        tensor([[1., 0., 0.],
                [0., 1., 0.],
                [0., 0., 1.]], dtype=torch.float64)
    """
    n_pose = 6 if T_b is None else 12
    n_extra = 0 if extra is None else extra.shape[-1]

    def perturbed(tangent: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        Ta = T_a @ se3_exp(tangent[:6])
        Tb = None if T_b is None else T_b @ se3_exp(tangent[6:12])
        e = None if extra is None else extra + tangent[n_pose:]
        r = residual_fn(Ta, Tb, e)
        return r, r

    zero = torch.zeros(n_pose + n_extra, dtype=T_a.dtype, device=T_a.device)
    jac, residuals = torch.func.jacfwd(perturbed, has_aux=True)(zero)
    return BlockLinearization(
        residuals=residuals,
        jac_a=jac[..., :6],
        jac_b=None if T_b is None else jac[..., 6:12],
        jac_extra=None if extra is None else jac[..., n_pose:],
    )


def _check_linearization(lin: BlockLinearization, batch: int, num_blocks: int | None) -> None:
    r = lin.residuals
    check_shape(r, "B,M,R", "residuals")
    if r.shape[0] != batch or (num_blocks is not None and r.shape[1] != num_blocks):
        expected = f"({batch}, {'M' if num_blocks is None else num_blocks}, R)"
        raise ShapeError(f"residuals must have shape {expected}, got {tuple(r.shape)}")
    for name in ("jac_a", "jac_b"):
        J = getattr(lin, name)
        if J is not None and J.shape != (*r.shape, 6):
            raise ShapeError(f"{name} must have shape {(*r.shape, 6)}, got {tuple(J.shape)}")
    if lin.jac_extra is not None and lin.jac_extra.shape[:3] != r.shape:
        raise ShapeError(
            f"jac_extra must have shape {(*r.shape, 'E')}, got {tuple(lin.jac_extra.shape)}"
        )
