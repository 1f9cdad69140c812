"""Culling of redundant keyframes and unconfirmed map points (seed 1 Sec. III-A).

Two rules bound the database when the camera revisits a place:

* a keyframe at least ``redundant_fraction`` (90%) of whose map points are observed by at least
  ``min_other_observers`` (3) other keyframes is a duplicate and is removed;
* a map point created by a keyframe and not observed by any of the next ``new_point_window``
  (2) keyframes is removed.

Example (four keyframes of two keypoints each; two map points, both created by keyframe 0):
    >>> import torch
    >>> from diffloc.geometry.camera import PinholeCamera
    >>> db = VisualDatabase(descriptor_dim=2)
    >>> cam = PinholeCamera.from_fov(64, 48, 1.0)
    >>> for _ in range(4):
    ...     _ = db.add_keyframe(torch.eye(4), cam, torch.full((2, 2), 20.0), torch.ones(2, 2),
    ...                         torch.ones(2))
    >>> ids = db.add_points(torch.zeros(2, 3), torch.ones(2, 2), torch.tensor([-1, -1]))
    >>> for keyframe in range(4):  # every keyframe sees point 0; only keyframe 0 sees point 1
    ...     db.add_observations(keyframe, torch.tensor([0]), ids[:1])
    >>> db.add_observations(0, torch.tensor([1]), ids[1:])
    >>> cull_unconfirmed_points(db, CullingConfig())  # point 1: not seen in keyframes 1-2
    tensor([1])
    >>> redundancy(db, CullingConfig())  # point 0 is seen by 3 other keyframes
    tensor([1., 1., 1., 1.], dtype=torch.float64)
    >>> cull_redundant_keyframes(db, CullingConfig()), db.num_keyframes
    (tensor([0]), 3)
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from diffloc.checks import check_positive_int
from diffloc.database.database import VisualDatabase, member_mask

__all__ = ["CullingConfig", "cull_redundant_keyframes", "cull_unconfirmed_points"]


@dataclass
class CullingConfig:
    """Thresholds of the two culling rules (seed 1 Sec. III-A).

    Attributes:
        redundant_fraction: a keyframe is redundant when at least this fraction of its map
            points is observed by ``min_other_observers`` other keyframes (seed 1: 0.9).
        min_other_observers: other keyframes that must observe a point (seed 1: 3).
        new_point_window: a new point must be observed again within this many following
            keyframes (seed 1: 2).
    """

    redundant_fraction: float = 0.9
    min_other_observers: int = 3
    new_point_window: int = 2

    def __post_init__(self) -> None:
        if not 0.0 < self.redundant_fraction <= 1.0:
            raise ValueError(f"redundant_fraction must be in (0, 1], got {self.redundant_fraction}")
        check_positive_int(self.min_other_observers, "min_other_observers")
        check_positive_int(self.new_point_window, "new_point_window")


def redundancy(db: VisualDatabase, config: CullingConfig) -> torch.Tensor:
    """Fraction of each keyframe's map points seen by ``min_other_observers`` other keyframes.

    Args:
        db: the database.
        config: culling thresholds.

    Returns:
        (K,) float64 fractions; 0 for keyframes without map points.

    Example: see the module docstring.
    """
    observed = db.keypoint_points >= 0
    point, keyframe = db.keypoint_points[observed], db.keypoint_keyframes()[observed]
    others = torch.bincount(point, minlength=db.num_points)[point] - 1
    well_seen = (others >= config.min_other_observers).double()
    total = torch.bincount(keyframe, minlength=db.num_keyframes).double()
    seen = torch.bincount(keyframe, weights=well_seen, minlength=db.num_keyframes)
    return seen / total.clamp(min=1.0)


def cull_redundant_keyframes(
    db: VisualDatabase, config: CullingConfig, candidates: torch.Tensor | None = None
) -> torch.Tensor:
    """Remove redundant keyframes, most redundant first, re-scoring after every removal.

    Removing a keyframe lowers the observation counts of its points, so two keyframes that
    make each other redundant are not both removed. Map points left without observations are
    removed with the keyframe (:meth:`VisualDatabase.remove_keyframes`).

    Args:
        db: the database, modified in place.
        config: culling thresholds.
        candidates: (M,) int64 keyframes that may be removed (default: all).

    Returns:
        (R,) int64 indices (before culling) of the removed keyframes, in removal order.

    Example: see the module docstring.
    """
    original = torch.arange(db.num_keyframes)
    allowed = torch.ones(db.num_keyframes, dtype=torch.bool)
    if candidates is not None:
        allowed = torch.isin(original, candidates.long())
    removed = []
    while True:
        score = torch.where(allowed, redundancy(db, config), -1.0)
        if db.num_keyframes == 0 or float(score.max()) < config.redundant_fraction:
            break
        worst = int(torch.argmax(score))
        removed.append(int(original[worst]))
        keep = torch.arange(db.num_keyframes) != worst
        original, allowed = original[keep], allowed[keep]
        db.remove_keyframes(torch.tensor([worst]))
    return torch.tensor(removed, dtype=torch.int64)


def cull_unconfirmed_points(
    db: VisualDatabase, config: CullingConfig, first_keyframes: torch.Tensor | None = None
) -> torch.Tensor:
    """Remove map points not observed again in the keyframes after the one that created them.

    A point's creating keyframe is its first (lowest-index) observer. Only points whose
    window of ``new_point_window`` following keyframes exists completely are judged.

    Args:
        db: the database, modified in place.
        config: culling thresholds.
        first_keyframes: (M,) int64 judge only points created by these keyframes (default:
            every keyframe with a complete window).

    Returns:
        (R,) int64 ids (before culling) of the removed points.

    Example: see the module docstring.
    """
    observed = db.keypoint_points >= 0
    if first_keyframes is not None:
        # Only points the given keyframes observe can have one of them as creator.
        candidates = db.points_observed_by(first_keyframes)
        observed = member_mask(db.keypoint_points, candidates, db.num_points)
    point, keyframe = db.keypoint_points[observed], db.keypoint_keyframes()[observed]
    big = torch.full((db.num_points,), db.num_keyframes, dtype=torch.int64)
    first = big.scatter_reduce(0, point, keyframe, reduce="amin")
    in_window = (keyframe > first[point]) & (keyframe <= first[point] + config.new_point_window)
    confirmed = torch.zeros(db.num_points, dtype=torch.bool)
    confirmed[point[in_window]] = True
    judged = first + config.new_point_window < db.num_keyframes
    if first_keyframes is not None:
        judged &= member_mask(first, first_keyframes, db.num_keyframes + 1)
    removed = torch.nonzero(judged & ~confirmed).flatten()
    db.remove_points(removed)
    return removed
