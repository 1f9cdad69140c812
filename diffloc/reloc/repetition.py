"""Repeated structure under a relocalised pose: the inliers' twins at one common shift.

Where the scene repeats (a tiled floor, a row of identical windows, a facade of one module), a
pose one period away explains the query as well as the right one: its inliers are the same
keypoints matched to the copies of the same structure, and the content around them may repeat
too. Neither inlier tests nor a photometric comparison can then tell the two poses apart; the
map itself can. For the inliers ``(k, i)`` (query keypoint ``k``, map point ``i`` at ``X_i``) of
a pose:

1. the *twins* of ``i`` are the ``max_twins`` map points whose descriptors are nearest to
   ``i``'s own (the map's descriptors compared with each other: the query keypoint's is biased
   towards ``i``, since it was matched for being nearest to it) and that lie at least
   ``min_shift_m`` from ``X_i`` (a second point of the same spot is no repetition);
2. every twin votes for the shift ``t = X_j - X_i``;
3. the shifts are voted on a grid of step ``tolerance_m / 2``: the *support* of a grid shift
   is the number of inliers with a twin within ``tolerance_m / 2`` of it along every axis (so
   two supporting twins agree to ``tolerance_m``); the best-supported shift is the repetition
   of the pose.

A camera moved by ``t`` sees each supporting twin where the query sees its inlier, with the
same appearance: a pose that many of its inliers are repeated for is ambiguous, and the
validation (:class:`~diffloc.reloc.validation.ValidationConfig`, ``max_repeated``) refuses it.

Example (three posts 2 m apart, each looking most like the next one; the query matched the
first two):
    >>> positions = torch.tensor([[0.0, 0, 5], [2.0, 0, 5], [4.0, 0, 5]])
    >>> descriptors = torch.tensor([[1.0, 0], [0.8, 0.2], [0.7, 0.3]])
    >>> shift = repeated_shift(
    ...     torch.tensor([0, 1]), positions, descriptors, "l2", RepetitionConfig(max_twins=1))
    >>> shift.support, round(shift.shift_m, 2)
    (2, 2.0)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from diffloc.checks import check_shape
from diffloc.features.matching import Metric, descriptor_distances

__all__ = ["RepeatedShift", "RepetitionConfig", "repeated_shift", "repeated_shifts"]

_CORNERS = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
"""(8, 3) the grid shifts around an offset, from the cell below it."""


@dataclass(frozen=True)
class RepetitionConfig:
    """Settings of :func:`repeated_shift` (module docstring).

    Attributes:
        min_shift_m: nearest a twin may lie to its inlier's point (metres).
        tolerance_m: twins whose shifts differ by at most this (per axis) support the same
            shift.
        max_twins: most twins per inlier (the nearest in descriptor space; a structure that
            repeats more often than this votes for fewer of its shifts).
    """

    min_shift_m: float = 0.5
    tolerance_m: float = 0.1
    max_twins: int = 16

    def __post_init__(self) -> None:
        for name in ("min_shift_m", "tolerance_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"repetition.{name} must be > 0, got {value}")
        if self.max_twins < 1:
            raise ValueError(f"repetition.max_twins must be >= 1, got {self.max_twins}")


@dataclass(frozen=True)
class RepeatedShift:
    """The best-supported shift of a pose's inliers onto their twins.

    Attributes:
        support: inliers with a twin at the shift (0: no inlier has a twin).
        shift_m: length of the shift in metres (0 when ``support`` is 0).
    """

    support: int
    shift_m: float


def repeated_shift(
    points: torch.Tensor,
    point_positions: torch.Tensor,
    point_descriptors: torch.Tensor,
    metric: Metric,
    config: RepetitionConfig,
) -> RepeatedShift:
    """The repetition of a pose's inliers (module docstring).

    Args:
        points: (N,) int64 map point of each inlier.
        point_positions: (P, 3) positions of all map points (world frame, metres).
        point_descriptors: (P, D) descriptors of all map points.
        metric: the descriptor metric of the database (``"l2"``, ``"cosine"``, ``"hamming"``).
        config: settings.

    Returns:
        The best-supported shift (support 0 without inliers or twins).

    Raises:
        ShapeError: inconsistent shapes.
        IndexError: a point id outside the map.
    """
    shifts, support = repeated_shifts(
        points, point_positions, point_descriptors, metric, config, count=1
    )
    if len(support) == 0:
        return RepeatedShift(0, 0.0)
    return RepeatedShift(int(support[0]), float(torch.linalg.vector_norm(shifts[0])))


def repeated_shifts(
    points: torch.Tensor,
    point_positions: torch.Tensor,
    point_descriptors: torch.Tensor,
    metric: Metric,
    config: RepetitionConfig,
    count: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``count`` best-supported shifts of a pose's inliers onto their twins (module
    docstring), as vectors: the candidate moves of a pose to a repeated place.

    Args:
        points: (N,) int64 map point of each inlier.
        point_positions: (P, 3) positions of all map points (world frame, metres).
        point_descriptors: (P, D) descriptors of all map points.
        metric: the descriptor metric of the database.
        config: settings.
        count: most shifts returned (>= 1).

    Returns:
        ``(shifts, support)``: (S, 3) float64 shifts in metres (grid cell corners, the best
        supported first) and (S,) int64 their support, ``S <= count`` (0 without inliers or
        twins).

    Raises:
        ShapeError: inconsistent shapes.
        IndexError: a point id outside the map.
        ValueError: ``count < 1``.
    """
    check_shape(points, "N", "points")
    check_shape(point_positions, "P,3", "point_positions")
    check_shape(point_descriptors, "P,D", "point_descriptors")
    if len(point_descriptors) != len(point_positions):
        raise ValueError(
            f"{len(point_descriptors)} point descriptors for {len(point_positions)} positions"
        )
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    none = torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, dtype=torch.int64)
    if len(points) == 0:
        return none
    if int(points.min()) < 0 or int(points.max()) >= len(point_positions):
        raise IndexError(f"inlier points must be map points in [0, {len(point_positions)})")
    distances = descriptor_distances(point_descriptors[points], point_descriptors, metric)
    distances.scatter_(1, points[:, None], math.inf)  # (N, P), a point is not its own twin
    k = min(config.max_twins, distances.shape[1] - 1)
    if k < 1:
        return none
    twins = torch.topk(distances, k, dim=1, largest=False).indices  # (N, k)
    positions = point_positions.to(torch.float64)
    offsets = positions[twins] - positions[points][:, None]  # (N, k, 3)
    is_twin = torch.linalg.vector_norm(offsets, dim=-1) >= config.min_shift_m
    owner = torch.arange(len(points))[:, None].expand_as(is_twin)[is_twin]  # (M,)
    offsets = offsets[is_twin]  # (M, 3)
    if len(offsets) == 0:
        return none
    # Vote on a grid of step tolerance / 2: an offset supports the 8 grid shifts within
    # tolerance / 2 of it per axis; each inlier counts once per shift.
    step = config.tolerance_m / 2
    cells = (torch.floor(offsets / step).long()[:, None] + _CORNERS).reshape(-1, 3)  # (8M, 3)
    low = cells.min(0).values
    extent = cells.max(0).values - low + 1
    index = cells - low
    key = (index[:, 0] * extent[1] + index[:, 1]) * extent[2] + index[:, 2]  # (8M,)
    pairs = torch.unique(key * len(points) + owner.repeat_interleave(8))
    keys, support = torch.unique(pairs // len(points), return_counts=True)
    cell = (
        torch.stack(
            [keys // (extent[1] * extent[2]), keys // extent[2] % extent[1], keys % extent[2]], 1
        )
        + low
    )
    corner = cell.double() * step
    # Best support first, the shortest shift of equal support first (the period before its
    # multiples); a shift within tolerance of a better one is the same repetition.
    order = torch.from_numpy(
        np.lexsort((torch.linalg.vector_norm(corner, dim=1).numpy(), -support.numpy()))
    )
    corner, cell, support = corner[order], cell[order], support[order]
    kept = []
    free = torch.ones(len(order), dtype=torch.bool)
    while len(kept) < count and bool(free.any()):  # at most `count` rounds
        i = int(torch.nonzero(free)[0])
        kept.append(i)
        free &= (corner - corner[i]).abs().amax(1) > config.tolerance_m
    # Each shift is the mean of the offsets that voted for its grid cell.
    below = torch.floor(offsets / step).long()  # (M, 3)
    votes = ((cell[kept][:, None] - below) // 2 == 0).all(-1).double()  # (S, M), 0 or 1 below
    return (votes @ offsets) / votes.sum(1, keepdim=True), support[kept]
