"""Input checks used at public API boundaries.

These raise typed exceptions with messages that say what to fix; they are never ``assert``
statements (which ``python -O`` strips). Shapes are described by strings such as ``"*,4,4"``
or ``"B,N,3"``: ``*`` matches any number of leading dimensions, a letter matches any size and
a number must match exactly.
"""

from __future__ import annotations

import math

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
        >>> check_shape(torch.eye(4), "*,4,4", "T_wc")  # passes: returns None
        >>> check_shape(torch.eye(3), "*,4,4", "T_wc")
        Traceback (most recent call last):
        ...
        diffloc.checks.ShapeError: T_wc must have shape (*,4,4), got (3, 3)
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


def check_int_at_least(value: object, name: str, low: int) -> int:
    """Return ``value`` if it is an integer ``>= low`` (not a bool), else raise ``ValueError``.

    Example:
        >>> check_int_at_least(3, "steps", 1)
        3
    """
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


def check_number(
    value: object,
    name: str,
    low: float = -math.inf,
    high: float = math.inf,
    *,
    open_low: bool = False,
    open_high: bool = False,
) -> float:
    """Return ``value`` if it is a finite number in the interval, else raise ``ValueError``.

    Args:
        value: the setting.
        name: its name, for the message.
        low, high: the interval's ends.
        open_low, open_high: exclude the end (``open_low=True, low=0``: positive).

    Example:
        >>> check_number(0.5, "scale", 0.0, 1.0, open_low=True)
        0.5
    """
    number = isinstance(value, int | float | np.floating | np.integer) and not isinstance(
        value, bool
    )
    inside = (
        number
        and math.isfinite(value)
        and (value > low if open_low else value >= low)
        and (value < high if open_high else value <= high)
    )
    if not inside:
        if math.isinf(high):
            where = f"{'>' if open_low else '>='} {low:g}"
        else:
            where = f"in {'(' if open_low else '['}{low:g}, {high:g}{')' if open_high else ']'}"
        raise ValueError(f"{name} must be a finite number {where}, got {value!r}")
    return float(value)


def check_ransac_settings(config: object, min_sample: int) -> None:
    """Validate the settings every RANSAC config of diffloc shares (PnP, essential check).

    Reads ``threshold_px``, ``confidence``, ``min_iterations``, ``max_iterations``,
    ``batch_size``, ``min_inliers``, ``lo_rounds``, ``refine_iterations``, ``bailout_points``
    and ``num_threads`` from ``config``.

    Args:
        config: the settings object.
        min_sample: the minimal sample size (``min_inliers`` may not be smaller).

    Raises:
        ValueError: the first out-of-range setting, named.
    """
    c = config
    if not (math.isfinite(c.threshold_px) and c.threshold_px > 0):
        raise ValueError(f"threshold_px must be positive, got {c.threshold_px}")
    if not 0.0 < c.confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {c.confidence}")
    if c.batch_size < 1 or c.max_iterations < 1:
        raise ValueError("batch_size and max_iterations must be positive")
    if not 0 <= c.min_iterations <= c.max_iterations:
        raise ValueError("min_iterations must be in [0, max_iterations]")
    if c.min_inliers < min_sample:
        raise ValueError(f"min_inliers must be at least {min_sample}, got {c.min_inliers}")
    if min(c.lo_rounds, c.refine_iterations, c.bailout_points) < 0:
        raise ValueError("lo_rounds, refine_iterations and bailout_points must be >= 0")
    if c.num_threads is not None and c.num_threads < 1:
        raise ValueError(f"num_threads must be None or positive, got {c.num_threads}")
