"""Front end for independent one-pose problems: :func:`levenberg_marquardt_single_pose`."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from diffloc.checks import ShapeError
from diffloc.optim.lm.config import LMConfig
from diffloc.optim.lm.cost import _robust_cost
from diffloc.optim.lm.inputs import _batched_mask, _check_poses
from diffloc.optim.lm.linearize import (
    BlockLinearization,
    PoseJacobianFn,
    PoseResidualFn,
    _check_linearization,
    autodiff_linearize,
)
from diffloc.optim.lm.loop import minimize
from diffloc.optim.lm.pose_system import PoseSystem, _pose_system
from diffloc.optim.lm.result import LMResult, _lm_result
from diffloc.optim.lm.retraction import _right_step
from diffloc.optim.robust import KernelFn, RobustKernel, make_robust_kernel

__all__ = ["levenberg_marquardt_single_pose"]


@dataclass
class _PoseProblem:
    """The :class:`LMProblem` of :func:`levenberg_marquardt_single_pose`: poses (B, 4, 4)."""

    residual_fn: PoseResidualFn
    jacobian_fn: PoseJacobianFn | None
    mask: torch.Tensor | None  # (B, N), or None: all
    kernel: KernelFn

    @property
    def analytic(self) -> bool:
        return self.jacobian_fn is not None

    def _mask(self, residuals: torch.Tensor) -> torch.Tensor:
        if self.mask is not None:
            return self.mask
        return torch.ones(residuals.shape[:2], dtype=torch.bool, device=residuals.device)

    def linearize(self, T: torch.Tensor) -> PoseSystem:
        if self.jacobian_fn is not None:
            lin = BlockLinearization(*self.jacobian_fn(T))
        else:
            lin = autodiff_linearize(lambda T_a, _b, _e: self.residual_fn(T_a), T)
        num_blocks = None if self.mask is None else self.mask.shape[1]
        _check_linearization(lin, T.shape[0], num_blocks)
        return _pose_system(lin.residuals, lin.jac_a, self._mask(lin.residuals), self.kernel)

    def evaluate(self, T: torch.Tensor) -> torch.Tensor:
        residuals = self.residual_fn(T)
        return _robust_cost(residuals, self._mask(residuals), self.kernel)

    def retract(self, T: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        return _right_step(T, delta)


def levenberg_marquardt_single_pose(
    T_wc: torch.Tensor,
    residual_fn: PoseResidualFn,
    *,
    jacobian_fn: PoseJacobianFn | None = None,
    mask: torch.Tensor | None = None,
    kernel: RobustKernel | None = None,
    config: LMConfig | None = None,
) -> LMResult:
    """Solve ``B`` independent one-pose problems at once (batched 6x6 systems).

    The loop of :func:`levenberg_marquardt` (:func:`minimize`) on :class:`PoseSystem`
    normal equations, without gathering poses per block.

    Args:
        T_wc: (4, 4) or (B, 4, 4) initial camera-to-world poses (float64 advised).
        residual_fn: ``T_wc (B, 4, 4) -> (B, N, R)`` whitened residuals (always called with a
            leading batch dimension, ``B = 1`` for an unbatched input); with ``jacobian_fn``
            given, called only when ``config.step_expansions > 0``.
        jacobian_fn: ``T_wc (B, 4, 4) -> ((B, N, R), (B, N, R, 6))`` residuals and analytic
            Jacobians w.r.t. ``T_wc <- T_wc @ se3_exp(delta)``; default autodiff.
        mask: (N,) or (B, N) bool, residuals to use (padding, outliers); default all.
        kernel: robust kernel (default trivial).
        config: solver settings (default :class:`LMConfig`).

    Returns:
        :class:`LMResult` with ``T_wc`` of the input's shape.

    Raises:
        ShapeError: inputs or residual-function outputs of the wrong shape.
        ValueError: non-finite poses or initial residuals.

    Example:
        >>> goal = torch.tensor([[[1.0, 2.0, 3.0]]], dtype=torch.float64)
        >>> out = levenberg_marquardt_single_pose(
        ...     torch.eye(4, dtype=torch.float64), lambda T: T[:, None, :3, 3] - goal)
        >>> out.T_wc[:3, 3].round(decimals=9)
        tensor([1., 2., 3.], dtype=torch.float64)
    """
    _check_poses(T_wc, "*,4,4", "T_wc")
    if T_wc.dim() not in (2, 3):
        raise ShapeError(f"T_wc must have shape (4, 4) or (B, 4, 4), got {tuple(T_wc.shape)}")
    batched = T_wc.dim() == 3
    T = T_wc if batched else T_wc[None]
    B = T.shape[0]
    mask_b = None if mask is None else _batched_mask(mask, B, mask.shape[-1])
    kernel_fn = make_robust_kernel(kernel or RobustKernel())
    problem = _PoseProblem(residual_fn, jacobian_fn, mask_b, kernel_fn)
    with torch.no_grad():
        run = minimize(problem, T.detach(), config or LMConfig())
    return _lm_result(run, run.params, None, batched)
