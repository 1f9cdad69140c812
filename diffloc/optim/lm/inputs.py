"""Checks of the front ends' inputs: poses, block indices, masks and fixed poses."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from diffloc.checks import ShapeError, check_finite, check_shape


def _check_poses(T_wc: torch.Tensor, spec: str, name: str) -> None:
    check_shape(T_wc, spec, name)
    if not T_wc.is_floating_point():
        raise TypeError(f"{name} must be a floating point tensor, got {T_wc.dtype}")
    check_finite(T_wc, name)


def _check_index(index: torch.Tensor, num_poses: int, name: str) -> None:
    check_shape(index, "M", name)
    if index.dtype not in (torch.int32, torch.int64):
        raise TypeError(f"{name} must be an integer tensor, got {index.dtype}")
    if index.numel() == 0:
        raise ValueError(f"{name} is empty: the problem has no residual blocks")
    if bool((index < 0).any() | (index >= num_poses).any()):
        raise ValueError(f"{name} must hold pose indices in [0, {num_poses}), got out-of-range")


def _batched_mask(mask: torch.Tensor | None, batch: int, size: int) -> torch.Tensor | None:
    if mask is None:
        return None
    if mask.dtype != torch.bool:
        raise TypeError(f"mask must be a bool tensor, got {mask.dtype}")
    if mask.shape not in ((size,), (batch, size)):
        raise ShapeError(f"mask must have shape ({size},) or ({batch}, {size}), got {mask.shape}")
    return mask.expand(batch, size)


def _fixed_mask(fixed: torch.Tensor | Sequence[int] | None, num_poses: int) -> torch.Tensor:
    is_fixed = torch.zeros(num_poses, dtype=torch.bool)
    if fixed is None:
        return is_fixed
    index = torch.as_tensor(fixed, dtype=torch.long).reshape(-1)
    if bool((index < 0).any() | (index >= num_poses).any()):
        raise ValueError(f"fixed pose indices must be in [0, {num_poses}), got {index.tolist()}")
    is_fixed[index] = True
    return is_fixed
