"""The pose update of the LM: ``T_wc <- T_wc @ [[Cay(w), v], [0, 1]]``, ``delta = [v, w]``.

The Cayley map agrees with ``se3_exp`` to first order (so the Jacobians are the same) and costs
a handful of tensor operations instead of the exponential's trigonometric branches.
"""

from __future__ import annotations

import functools

import torch

from diffloc.checks import check_shape
from diffloc.optim.lm.structure import _Structure

__all__ = ["cayley_rotation"]


@functools.lru_cache(maxsize=8)
def _cayley_coefficients(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(16, 10) map from the outer product ``q q^T`` (flattened) of ``q = (s, x, y, z)`` to
    the nine entries of ``|q|^2 R(q)`` (row-major) and ``|q|^2``. Never modified in place."""
    terms = (
        ((0, 0, 1), (1, 1, 1), (2, 2, -1), (3, 3, -1)),  # R00 = ss + xx - yy - zz
        ((1, 2, 2), (0, 3, -2)),  # R01 = 2 (xy - sz)
        ((1, 3, 2), (0, 2, 2)),  # R02 = 2 (xz + sy)
        ((1, 2, 2), (0, 3, 2)),  # R10 = 2 (xy + sz)
        ((0, 0, 1), (1, 1, -1), (2, 2, 1), (3, 3, -1)),  # R11
        ((2, 3, 2), (0, 1, -2)),  # R12 = 2 (yz - sx)
        ((1, 3, 2), (0, 2, -2)),  # R20 = 2 (xz - sy)
        ((2, 3, 2), (0, 1, 2)),  # R21 = 2 (yz + sx)
        ((0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, 1)),  # R22
        ((0, 0, 1), (1, 1, 1), (2, 2, 1), (3, 3, 1)),  # |q|^2
    )
    with torch.inference_mode(False):  # an ordinary tensor even if first made in one
        coefficients = torch.zeros(16, len(terms), dtype=dtype, device=device)
        for column, entries in enumerate(terms):
            for a, b, value in entries:
                coefficients[4 * a + b, column] = value
    return coefficients


def cayley_rotation(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of the Cayley map, the cheap retraction of the LM pose updates.

    ``Cay(w) = ((1 - |c|^2) I + 2 hat(c) + 2 c c^T) / (1 + |c|^2)`` with ``c = w / 2`` is the
    rotation of the quaternion ``(1, c)``: an exact rotation that agrees with
    ``so3_exp(w)`` up to second order (angle ``2 atan(|w| / 2)`` about ``w``), computed with
    a handful of tensor operations (one outer product and one small matrix product).

    Args:
        w: (..., 3) rotation vectors (radians).

    Returns:
        (..., 3, 3) rotation matrices.

    Example:
        >>> R = cayley_rotation(torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64))
        >>> torch.allclose(R @ R.mT, torch.eye(3, dtype=torch.float64))
        True
        >>> round(float(torch.atan2(R[1, 0], R[0, 0])), 4)  # 2 atan(0.25), not 0.5
        0.49
    """
    if not isinstance(w, torch.Tensor) or w.shape[-1:] != (3,):  # checked only if wrong
        check_shape(w, "*,3", "w")
    q = torch.nn.functional.pad(w, (1, 0), value=2.0)  # 2 (1, w / 2): the scale cancels
    outer = (q[..., :, None] * q[..., None, :]).flatten(-2)
    m = outer @ _cayley_coefficients(w.dtype, w.device)
    return (m[..., :9] / m[..., 9:]).unflatten(-1, (3, 3))


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
