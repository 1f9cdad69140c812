"""Pose validation of relocalised queries (seed 1 Sec. III-C, last paragraph).

A refined query pose with ``n_in >= theta_in`` inlier matches is an *inlier pose*. In
sequence mode it is *verified* only if it also lies within ``theta_dist`` of the previous
inlier pose; every inlier pose (verified or not) becomes the new reference. The first inlier
pose of a sequence has no reference and is not verified. In single-image mode only the inlier
test applies.

Seed 1 evaluates on 20 Hz EuRoC images, where ``theta_dist`` (0.3 m indoors, 0.8 m outdoors)
bounds the motion between consecutive queries. For sparser query streams the threshold grows
with the time since the reference: ``theta_dist + max_speed_mps * dt`` (``max_speed_mps = 0``
gives the paper's test exactly).

Example:
    >>> v = PoseValidator(ValidationConfig(theta_in=15, theta_dist_m=0.3))
    >>> T = torch.eye(4, dtype=torch.float64)
    >>> v.validate(T, 20, 0.0), v.validate(T, 20, 0.05), v.validate(T, 5, 0.1)
    (False, True, False)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from diffloc.checks import check_finite, check_shape

__all__ = ["PoseValidator", "ValidationConfig"]


@dataclass
class ValidationConfig:
    """Thresholds of :class:`PoseValidator`.

    Attributes:
        theta_in: fewest inlier matches of an inlier pose (seed 1: 15).
        theta_dist_m: largest distance to the previous inlier pose (seed 1: 0.3 m indoors,
            0.8 m outdoors).
        max_speed_mps: allowance per second since the previous inlier pose, for query streams
            sparser than seed 1's 20 Hz (0 disables it).
        temporal: apply the distance test (sequence mode); ``False`` is single-image mode.
    """

    theta_in: int = 15
    theta_dist_m: float = 0.3
    max_speed_mps: float = 0.0
    temporal: bool = True

    def __post_init__(self) -> None:
        if self.theta_in < 0:
            raise ValueError(f"theta_in must be >= 0, got {self.theta_in}")
        for name in ("theta_dist_m", "max_speed_mps"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")


class PoseValidator:
    """Stateful pose validation over one query sequence (module docstring).

    Args:
        config: thresholds.
    """

    def __init__(self, config: ValidationConfig) -> None:
        self.config = config
        self.reset()

    def reset(self) -> None:
        """Forget the previous inlier pose (start of a new sequence)."""
        self._last_position: torch.Tensor | None = None
        self._last_time = 0.0

    def validate(self, T_wc: torch.Tensor, num_inliers: int, timestamp: float) -> bool:
        """Whether a refined pose is verified; updates the reference on inlier poses.

        Args:
            T_wc: (4, 4) refined camera-to-world pose.
            num_inliers: its inlier matches ``n_in``.
            timestamp: query time in seconds (increasing over the sequence).

        Returns:
            ``True`` if the pose passes the inlier test and, in sequence mode, the distance
            test against the previous inlier pose.

        Raises:
            ShapeError: ``T_wc`` is not (4, 4).
            ValueError: a non-finite pose or timestamp.
        """
        check_shape(T_wc, "4,4", "T_wc")
        check_finite(T_wc, "T_wc")
        if not math.isfinite(timestamp):
            raise ValueError(f"timestamp must be finite, got {timestamp}")
        if num_inliers < self.config.theta_in:
            return False
        if not self.config.temporal:
            return True
        position = T_wc[:3, 3].to(torch.float64)
        previous, dt = self._last_position, abs(timestamp - self._last_time)
        self._last_position, self._last_time = position, float(timestamp)
        if previous is None:
            return False
        limit = self.config.theta_dist_m + self.config.max_speed_mps * dt
        return bool(torch.linalg.vector_norm(position - previous) <= limit)
