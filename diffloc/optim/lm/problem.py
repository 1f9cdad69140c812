"""The interface of :func:`~diffloc.optim.lm.loop.minimize`: a problem and its normal equations."""

from __future__ import annotations

import dataclasses
from dataclasses import fields
from typing import Any, Protocol

import torch

from diffloc.optim.lm.config import LMConfig

__all__ = ["LMProblem", "LinearSystem"]


class LinearSystem(Protocol):
    """The normal equations of ``B`` problems at their current parameters, as :func:`minimize`
    uses them (:class:`PoseSystem` for one pose per problem; the block-sparse system of
    :func:`levenberg_marquardt` otherwise)."""

    cost: torch.Tensor  # (B,)
    grad: torch.Tensor  # (B, D)

    def where(self, mask: torch.Tensor, other: Any) -> Any: ...

    def model_change(self, delta: torch.Tensor) -> torch.Tensor: ...

    def expandable(self, min_support: float) -> torch.Tensor: ...

    def solve(
        self, damping: torch.Tensor, config: LMConfig, mixed_precision: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None, bool]: ...


class LMProblem(Protocol):
    """A problem for :func:`minimize`: its parameters (any value: a pose tensor, a tuple of
    tensors) are linearized, evaluated and updated by these.

    Attributes:
        analytic: ``linearize`` is cheap enough to call on every candidate step (analytic
            Jacobians): it then replaces ``evaluate``, which saves a residual pass per
            accepted step (unless step expansions evaluate several candidates).
    """

    analytic: bool

    def linearize(self, params: Any) -> LinearSystem:
        """The normal equations at ``params``."""
        ...

    def evaluate(self, params: Any) -> torch.Tensor:
        """(B,) costs at ``params``."""
        ...

    def retract(self, params: Any, delta: torch.Tensor) -> Any:
        """``params`` moved by the steps ``delta`` (B, D) (zero rows: unchanged)."""
        ...


def _select(mask: torch.Tensor, new: Any, old: Any) -> Any:
    """Per problem: ``new`` where ``mask`` (B,) is true, else ``old``. Values are tensors
    (leading dimension ``B``), ``None``, and tuples or dataclasses (field by field) of those."""
    if new is None:
        return None
    if isinstance(new, tuple):
        return tuple(_select(mask, n, o) for n, o in zip(new, old, strict=True))
    if dataclasses.is_dataclass(new):
        picked = {
            f.name: _select(mask, getattr(new, f.name), getattr(old, f.name)) for f in fields(new)
        }
        return dataclasses.replace(old, **picked)
    return torch.where(mask.view(-1, *[1] * (new.dim() - 1)), new, old)
