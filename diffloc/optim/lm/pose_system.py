"""Normal equations of batched one-pose problems (6x6 systems) and their damped step."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from diffloc.optim.lm.config import LMConfig
from diffloc.optim.lm.problem import _select
from diffloc.optim.robust import KernelFn

__all__ = ["PoseSystem"]


@dataclass(frozen=True)
class PoseSystem:
    """Normal equations of ``B`` one-pose problems (6 unknowns each) at their current poses.

    What :func:`minimize` needs of a linearization with one pose per problem; a problem may
    subclass it to carry what it computed along (more dataclass fields, tensors with the
    leading dimension ``B``, or dataclasses of those: :meth:`where` picks them too).

    Attributes:
        cost: (B,) cost ``0.5 * sum rho``.
        grad: (B, 6) gradient w.r.t. the pose step.
        hessian: (B, 6, 6) Gauss-Newton matrix ``sum w J^T J``.
        support: (B, 1) robust weights on the pose summed over its residual components (see
            :attr:`LMConfig.expansion_min_support`).
    """

    cost: torch.Tensor
    grad: torch.Tensor
    hessian: torch.Tensor
    support: torch.Tensor

    def where(self, mask: torch.Tensor, other: PoseSystem) -> PoseSystem:
        """Per problem: ``other`` where ``mask`` (B,) is true, else ``self``."""
        return _select(mask, other, self)

    def model_change(self, delta: torch.Tensor) -> torch.Tensor:
        """(B,) change of the quadratic model, ``g.delta + delta.H.delta / 2``, delta (B, 6)."""
        half = torch.baddbmm(self.grad[:, None], delta[:, None], self.hessian, alpha=0.5)
        return half[:, 0].mul_(delta).sum(-1)

    def expandable(self, min_support: float) -> torch.Tensor:
        """(B, 6) bool: poses whose steps may be expanded."""
        return (self.support >= min_support).expand(-1, 6)

    def solve(
        self, damping: torch.Tensor, config: LMConfig, mixed_precision: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, bool]:
        """Step of ``(H + damping * diag(clamp(diag H))) delta = -g`` in float64, damping (B,).

        Returns:
            ``(delta, failed, True)``: the (B, 6) steps and (B,) non-zero where Cholesky could
            not factor the damped matrix (that step is meaningless and counts as failed).
        """
        damped = self.hessian.clone()
        diagonal = damped.diagonal(dim1=-2, dim2=-1)
        diagonal.addcmul_(diagonal.clamp(min=config.min_diagonal), damping[:, None])
        L, info = torch.linalg.cholesky_ex(damped)
        return torch.cholesky_solve(self.grad[..., None], L)[..., 0].neg_(), info, True


def _pose_system(
    residuals: torch.Tensor, jacobian: torch.Tensor, mask: torch.Tensor, kernel: KernelFn
) -> PoseSystem:
    """Normal equations of one-pose problems from residuals (B, M, R) and Jacobians
    (B, M, R, 6) of masked (B, M) blocks.

    Read through permuted views with the blocks innermost (free when the residual function
    produced them in that layout), where torch's element-wise and reduction kernels are
    several times faster than on (..., R) rows. The products are summed over the R residual
    components one by one, so every reduction runs over the blocks in order: padding blocks at
    the end of a batch leave the sums bitwise unchanged.
    """
    R = residuals.shape[2]
    keep, zero = mask[:, None, :], residuals.new_zeros(())  # (B, 1, M)
    r = torch.where(keep, residuals.transpose(1, 2), zero)  # (B, R, M)
    rho, weight = kernel((r * r).sum(1))
    cost = torch.where(mask, rho, zero).sum(-1).mul_(0.5)
    weight = torch.where(mask, weight, zero)
    J = torch.where(keep[:, None], jacobian.permute(0, 3, 2, 1), zero)  # (B, 6, R, M)
    WJ = J * weight[:, None, None]
    H = torch.bmm(WJ[:, :, 0], J[:, :, 0].mT)
    grad = torch.bmm(WJ[:, :, 0], r[:, 0, :, None])
    for i in range(1, R):
        H = torch.baddbmm(H, WJ[:, :, i], J[:, :, i].mT)
        grad = torch.baddbmm(grad, WJ[:, :, i], r[:, i, :, None])
    return PoseSystem(cost, grad[..., 0], H, weight.sum(-1, keepdim=True).mul_(R))
