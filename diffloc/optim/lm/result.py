"""What the front ends of :mod:`diffloc.optim.lm` return (:class:`LMResult`)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from diffloc.optim.lm.loop import LMRun

__all__ = ["LMResult"]


@dataclass
class LMResult:
    """Outcome of a Levenberg-Marquardt run.

    Leading dimensions ``(...)`` are ``(B,)`` for a batched call and ``()`` otherwise.

    Attributes:
        T_wc: optimised poses, (..., P, 4, 4) (multi-pose) or (..., 4, 4) (single-pose).
        extra: (..., E) optimised extra parameters, or ``None``.
        cost_history: (..., I + 1) cost before the first and after every iteration (costs of
            problems that stopped early are repeated), ``I`` the most iterations run.
        iterations: (...) int64 linear solves per problem.
        converged: (...) bool, stopped by a gradient, step or cost tolerance.
        reason: per problem (flattened batch order) one of ``"gradient"``, ``"step"``,
            ``"cost"`` (converged), ``"max_iterations"``, ``"damping"``.
    """

    T_wc: torch.Tensor
    extra: torch.Tensor | None
    cost_history: torch.Tensor
    iterations: torch.Tensor
    converged: torch.Tensor
    reason: tuple[str, ...]

    @property
    def cost(self) -> torch.Tensor:
        """(...) final cost."""
        return self.cost_history[..., -1]


def _lm_result(run: LMRun, T: torch.Tensor, extra: torch.Tensor | None, batched: bool) -> LMResult:
    """The :class:`LMResult` of a run (batch dimension removed unless ``batched``)."""
    device = T.device
    result = LMResult(
        T_wc=T,
        extra=extra,
        cost_history=torch.tensor(run.cost_history, dtype=T.dtype, device=device).T.contiguous(),
        iterations=torch.tensor(run.iterations, dtype=torch.long, device=device),
        converged=torch.tensor(run.converged, device=device),
        reason=run.reason,
    )
    if batched:
        return result
    return LMResult(
        T_wc=result.T_wc[0],
        extra=None if extra is None else extra[0],
        cost_history=result.cost_history[0],
        iterations=result.iterations[0],
        converged=result.converged[0],
        reason=result.reason,
    )
