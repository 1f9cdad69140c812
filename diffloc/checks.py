"""Input checks used at public API boundaries.

These raise typed exceptions with messages that say what to fix; they are never ``assert``
statements (which ``python -O`` strips). Shapes are described by strings such as ``"*,4,4"``
or ``"B,N,3"``: ``*`` matches any number of leading dimensions, a letter matches any size and
a number must match exactly.
"""

from __future__ import annotations

import numpy as np
import torch

ArrayLike = torch.Tensor | np.ndarray


class ShapeError(ValueError):
    """A tensor or array does not have the documented shape."""


def _shape_matches(shape: tuple[int, ...], spec: list[str]) -> bool:
    if spec and spec[0] == "*":
        tail = spec[1:]
        return len(shape) >= len(tail) and _shape_matches(shape[len(shape) - len(tail) :], tail)
    if len(shape) != len(spec):
        return False
    return all(not s.isdigit() or int(s) == d for s, d in zip(spec, shape, strict=True))


def check_shape(x: ArrayLike, spec: str, name: str = "input") -> None:
    """Raise :class:`ShapeError` unless ``x.shape`` matches ``spec``.

    Args:
        x: a tensor or array.
        spec: comma-separated dimensions, e.g. ``"*,4,4"``, ``"N,3"``, ``"B,3,H,W"``.
        name: the argument name used in the error message.

    Example:
        >>> check_shape(torch.eye(4), "*,4,4", "T_wc")
    """
    if not isinstance(x, torch.Tensor | np.ndarray):
        raise TypeError(f"{name} must be a torch.Tensor or numpy array, got {type(x).__name__}")
    parts = [p.strip() for p in spec.split(",")]
    if not _shape_matches(tuple(x.shape), parts):
        raise ShapeError(f"{name} must have shape ({spec}), got {tuple(x.shape)}")


def check_finite(x: ArrayLike, name: str = "input") -> None:
    """Raise ``ValueError`` if ``x`` holds NaN or infinite values."""
    finite = torch.isfinite(x).all() if isinstance(x, torch.Tensor) else np.isfinite(x).all()
    if not bool(finite):
        raise ValueError(f"{name} contains NaN or infinite values")


def check_positive_int(value: object, name: str) -> int:
    """Return ``value`` as ``int`` if it is a positive integer, else raise ``ValueError``."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value <= 0:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)
