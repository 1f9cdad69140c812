"""Screen-space sizes of point splats: fixed, inverse depth (seed 2 Eq. 2) or multi-pass."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

__all__ = ["PointSizes"]


@dataclass(frozen=True)
class PointSizes:
    """Screen-space splat sizes (side of the square, in pixels) for :func:`render_points`.

    Each point first gets the inverse-depth size of seed 2 Eq. 2,
    ``rho = clamp(rho_max / z, rho_min, rho_max)`` (``z`` in metres, so ``rho_max`` is the
    size at 1 m and closer). It is then snapped to the nearest of the integer ``levels``
    (ties round up); points of one level form one rendering pass and passes are merged by
    nearest depth (seed 2 Fig. 5). ``levels=None`` uses every integer in
    ``[round(rho_min), round(rho_max)]`` (at least 1), which renders Eq. 2 per point with the
    size rounded to whole pixels as OpenGL does. A fixed size ``k`` is ``levels=(k,)``.

    Attributes:
        rho_min: smallest size (pixels, > 0).
        rho_max: largest size (pixels, >= rho_min).
        levels: optional sorted tuple of distinct positive integer sizes, the passes.

    Raises:
        ValueError: non-finite or non-positive sizes, ``rho_max < rho_min``, bad levels.

    Example:
        >>> PointSizes.inverse_depth(1.0, 4.0).pass_sizes()
        (1, 2, 3, 4)
        >>> PointSizes.fixed(2).pass_sizes()
        (2,)
    """

    rho_min: float = 1.0
    rho_max: float = 1.0
    levels: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("rho_min", "rho_max"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"PointSizes.{name} must be a positive number, got {value!r}")
        if self.rho_max < self.rho_min:
            raise ValueError(f"PointSizes.rho_max ({self.rho_max}) < rho_min ({self.rho_min})")
        if self.levels is not None:
            levels = tuple(self.levels)
            valid = all(isinstance(k, int) and not isinstance(k, bool) and k > 0 for k in levels)
            if not levels or not valid or list(levels) != sorted(set(levels)):
                raise ValueError(
                    f"PointSizes.levels must be increasing positive integers, got {self.levels!r}"
                )
            object.__setattr__(self, "levels", levels)

    @classmethod
    def fixed(cls, size: int) -> PointSizes:
        """Every point drawn as a ``size x size`` square (a single pass)."""
        return cls(rho_min=float(size), rho_max=float(size), levels=(size,))

    @classmethod
    def inverse_depth(cls, rho_min: float, rho_max: float) -> PointSizes:
        """Eq. 2 per point, rounded to whole pixels."""
        return cls(rho_min=rho_min, rho_max=rho_max)

    @classmethod
    def multi_pass(cls, rho_min: float, rho_max: float, levels: tuple[int, ...]) -> PointSizes:
        """Eq. 2 snapped to a few fixed sizes, one pass each, merged by nearest depth."""
        return cls(rho_min=rho_min, rho_max=rho_max, levels=levels)

    def pass_sizes(self) -> tuple[int, ...]:
        """The integer splat sizes, one rendering pass each."""
        if self.levels is not None:
            return self.levels
        low = max(1, math.floor(self.rho_min + 0.5))
        return tuple(range(low, max(low, math.floor(self.rho_max + 0.5)) + 1))

    def level_index(self, depth: torch.Tensor) -> torch.Tensor:
        """Pass index of points at camera-frame z-depths ``depth`` (any shape, > 0).

        Args:
            depth: (...) z-depths in metres.

        Returns:
            (...) int64 indices into :meth:`pass_sizes`.
        """
        sizes = self.pass_sizes()
        rho = (self.rho_max / depth).clamp(self.rho_min, self.rho_max)
        midpoints = torch.tensor(
            [0.5 * (a + b) for a, b in zip(sizes[:-1], sizes[1:], strict=True)],
            dtype=rho.dtype,
            device=rho.device,
        )
        return torch.bucketize(rho, midpoints, right=True)
