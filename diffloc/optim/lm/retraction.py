"""The pose update of the LM: ``T_wc <- T_wc @ [[Cay(w), v], [0, 1]]``, ``delta = [v, w]``.

The Cayley map agrees with ``se3_exp`` to first order (so the Jacobians are the same) and costs
a handful of tensor operations instead of the exponential's trigonometric branches.
"""

from __future__ import annotations

import torch

from diffloc.geometry.se3 import cayley_rotation
from diffloc.optim.lm.structure import _Structure


def _right_step(T: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """``T @ [[Cay(w), v], [0, 1]]`` for poses (..., 4, 4) and steps ``d = [v, w]`` (..., 6)."""
    top = torch.cat((cayley_rotation(d[..., 3:]), d[..., :3, None]), dim=-1)  # (..., 3, 4)
    return T @ torch.cat((top, T[..., 3:, :]), dim=-2)


def _retract(
    T: torch.Tensor, extra: torch.Tensor | None, delta: torch.Tensor, structure: _Structure
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Apply a step: ``T_p <- T_p @ [[Cay(w_p), v_p], [0, 1]]`` for free poses (the retraction
    of :mod:`diffloc.optim.lm`), ``extra += delta_e``."""
    s = structure
    n6 = 6 * s.num_free
    d = delta[:, :n6].reshape(delta.shape[0], s.num_free, 6)
    T_new = T.index_copy(1, s.free, _right_step(T[:, s.free], d))
    return T_new, None if extra is None else extra + delta[:, n6:]
