"""Front end for poses coupled by residual blocks: :func:`levenberg_marquardt`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from diffloc.checks import ShapeError, check_finite, check_shape
from diffloc.optim.lm.block_assembly import _assemble
from diffloc.optim.lm.block_system import _System
from diffloc.optim.lm.config import LMConfig
from diffloc.optim.lm.cost import _robust_cost
from diffloc.optim.lm.inputs import _batched_mask, _check_index, _check_poses, _fixed_mask
from diffloc.optim.lm.linearize import (
    BlockJacobianFn,
    BlockResidualFn,
    _check_linearization,
    autodiff_linearize,
)
from diffloc.optim.lm.loop import minimize
from diffloc.optim.lm.result import LMResult, _lm_result
from diffloc.optim.lm.retraction import _retract
from diffloc.optim.lm.structure import _Structure
from diffloc.optim.robust import KernelFn, RobustKernel, make_robust_kernel

__all__ = ["levenberg_marquardt"]


@dataclass
class _BlockProblem:
    """The :class:`LMProblem` of :func:`levenberg_marquardt`: parameters ``(T, extra)``."""

    residual_fn: BlockResidualFn
    jacobian_fn: BlockJacobianFn | None
    index_a: torch.Tensor
    index_b: torch.Tensor | None
    mask: torch.Tensor  # (B, M)
    kernel: KernelFn
    structure: _Structure

    @property
    def analytic(self) -> bool:
        return self.jacobian_fn is not None

    def gather(self, T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The poses of every block, (B, M, 4, 4) views of (4, 4, B, M) tensors whose 16
        entries are each contiguous over the blocks (a cheap gather, and what component-wise
        residual functions such as SurfelReprojectionCost read without a transposing copy)."""
        B, P = T.shape[:2]
        M = self.index_a.shape[0]
        T_cm = T.permute(2, 3, 0, 1).reshape(16 * B, P)  # a small copy

        def take(index: torch.Tensor) -> torch.Tensor:
            rows = torch.gather(T_cm, 1, index.expand(16 * B, M))
            return rows.view(4, 4, B, M).permute(2, 3, 0, 1)

        return take(self.index_a), None if self.index_b is None else take(self.index_b)

    def linearize(self, params: tuple[torch.Tensor, torch.Tensor | None]) -> _System:
        T, extra = params
        if self.jacobian_fn is not None:
            lin = self.jacobian_fn(*self.gather(T), extra)
        else:
            lin = autodiff_linearize(self.residual_fn, *self.gather(T), extra)
        _check_linearization(lin, *self.mask.shape)
        return _assemble(lin, self.mask, self.kernel, self.structure)

    def evaluate(self, params: tuple[torch.Tensor, torch.Tensor | None]) -> torch.Tensor:
        T, extra = params
        return _robust_cost(self.residual_fn(*self.gather(T), extra), self.mask, self.kernel)

    def retract(
        self, params: tuple[torch.Tensor, torch.Tensor | None], delta: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        return _retract(*params, delta, self.structure)


def levenberg_marquardt(
    T_wc: torch.Tensor,
    residual_fn: BlockResidualFn,
    index_a: torch.Tensor,
    index_b: torch.Tensor | None = None,
    *,
    extra: torch.Tensor | None = None,
    jacobian_fn: BlockJacobianFn | None = None,
    mask: torch.Tensor | None = None,
    fixed: torch.Tensor | Sequence[int] | None = None,
    kernel: RobustKernel | None = None,
    config: LMConfig | None = None,
) -> LMResult:
    """Minimise a robust sum of residual blocks over poses (and extra parameters).

    See :mod:`diffloc.optim.lm` for the cost, the pose update and the stopping rules. The
    residual functions receive the poses gathered per block, ``T_a = T_wc[:, index_a]``, and
    must return whitened residuals; their Jacobians follow the right-perturbation convention.

    Args:
        T_wc: (P, 4, 4) or (B, P, 4, 4) initial camera-to-world poses (float64 advised).
        residual_fn: ``(T_a (B, M, 4, 4), T_b (B, M, 4, 4) | None, extra (B, E) | None)
            -> (B, M, R)``: cost evaluations and autodiff Jacobians
            (:func:`autodiff_linearize`); with ``jacobian_fn`` given, called only to evaluate
            candidate steps when ``config.step_expansions > 0``.
        index_a: (M,) int64 pose index of every block's first pose.
        index_b: (M,) int64 pose index of every block's second pose, or ``None``.
        extra: (E,) or (B, E) initial extra parameters, or ``None``.
        jacobian_fn: same inputs, returns a :class:`BlockLinearization` with analytic
            Jacobians; then each candidate step is linearized directly (which saves a
            residual pass after each accepted step), unless step expansions evaluate several
            candidates per iteration: then only the chosen one is linearized.
        mask: (M,) or (B, M) bool, blocks to use (padding, outliers); default all.
        fixed: indices of poses held constant (the gauge), default none.
        kernel: robust kernel (default trivial: least squares).
        config: solver settings (default :class:`LMConfig`).

    Returns:
        :class:`LMResult` with ``T_wc`` of the input's shape.

    Raises:
        ShapeError: inputs or residual-function outputs of the wrong shape.
        TypeError: non-float poses or non-integer indices.
        ValueError: non-finite poses or initial residuals, empty or out-of-range indices, or
            nothing left to optimise (all poses fixed and no extra parameters).

    Example:
        >>> T0 = torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
        >>> goal = torch.tensor([[0.0, 0, 0], [1.0, 0, 0]], dtype=torch.float64)
        >>> fn = lambda Ta, Tb, e: Ta[..., :3, 3] - goal   # one block per pose
        >>> out = levenberg_marquardt(T0, fn, torch.tensor([0, 1]), fixed=[0])
        >>> out.T_wc[1, :3, 3].round(decimals=9), out.converged
        (tensor([1., 0., 0.], dtype=torch.float64), tensor(True))
    """
    _check_poses(T_wc, "*,P,4,4", "T_wc")
    if T_wc.dim() not in (3, 4):
        raise ShapeError(f"T_wc must have shape (P, 4, 4) or (B, P, 4, 4), got {T_wc.shape}")
    batched = T_wc.dim() == 4
    T = T_wc if batched else T_wc[None]
    B, P = T.shape[:2]
    _check_index(index_a, P, "index_a")
    M = index_a.shape[0]
    if index_b is not None:
        _check_index(index_b, P, "index_b")
        if index_b.shape != index_a.shape:
            raise ShapeError(f"index_b must have shape ({M},), got {tuple(index_b.shape)}")
    if extra is not None:
        check_shape(extra, "*,E", "extra")
        if extra.shape[:-1] not in ((), (B,) if batched else ()):
            raise ShapeError(f"extra must have shape (E,) or (B, E), got {tuple(extra.shape)}")
        check_finite(extra, "extra")
        extra = extra.to(T.dtype).expand(B, extra.shape[-1]).detach()
    is_fixed = _fixed_mask(fixed, P)
    if bool(is_fixed.all()) and extra is None:
        raise ValueError("every pose is fixed and there are no extra parameters to optimise")
    num_extra = 0 if extra is None else extra.shape[-1]
    index_a, index_b = index_a.long(), None if index_b is None else index_b.long()
    mask_b = _batched_mask(mask, B, M)
    problem = _BlockProblem(
        residual_fn,
        jacobian_fn,
        index_a,
        index_b,
        torch.ones(B, M, dtype=torch.bool) if mask_b is None else mask_b,
        make_robust_kernel(kernel or RobustKernel()),
        _Structure.from_blocks(P, index_a, index_b, is_fixed, num_extra),
    )
    with torch.no_grad():
        run = minimize(problem, (T.detach(), extra), config or LMConfig())
    T_out, extra_out = run.params
    return _lm_result(run, T_out, extra_out, batched)
