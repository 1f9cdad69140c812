"""The robust cost of masked residual blocks (what a front end's ``evaluate`` returns)."""

from __future__ import annotations

import torch

from diffloc.optim.robust import KernelFn


def _robust_cost(residuals: torch.Tensor, mask: torch.Tensor, kernel: KernelFn) -> torch.Tensor:
    """(B,) robust cost ``0.5 * sum rho(||r||^2)`` of residuals (B, M, R) of the masked (B, M)
    blocks; the other blocks are zeroed first, so NaN in padded blocks cannot leak."""
    masked = torch.where(mask[..., None], residuals, 0.0)
    rho, _ = kernel((masked * masked).sum(-1))
    return 0.5 * torch.where(mask, rho, 0.0).sum(-1)
