"""Seed 1's neighbouring surfel sets: the distinct surfel ids within a keypoint's radius.

:func:`neighbour_surfels` reads a rendered surfel index map
(:func:`~diffloc.render.surfel_render.render_surfel_index`); :func:`keypoint_disk_mask` gives
the pixels it reads, so that only those are rendered, and :class:`KeypointDisks` makes both
from one set of row segments per image (what the database builder uses).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from diffloc.checks import ShapeError, check_finite, check_shape

__all__ = ["KeypointDisks", "keypoint_disk_mask", "neighbour_surfels"]


def neighbour_surfels(
    ids: torch.Tensor, keypoints: torch.Tensor, radius_px: torch.Tensor | float
) -> torch.Tensor:
    """Distinct surfel ids within each keypoint's radius (seed 1's neighbouring surfel set).

    A pixel belongs to a keypoint when its centre is within ``radius_px`` (Euclidean) of the
    keypoint; -1 entries of the id map are ignored. For OpenCV keypoints whose ``size`` is a
    diameter, pass ``size / 2``.

    Args:
        ids: (H, W) or (B, H, W) int64 surfel index map (-1 where none).
        keypoints: (K, 2) or (B, K, 2) pixel coordinates ``(u, v)``, batched like ``ids``.
        radius_px: scalar, (K,) or (B, K) radii in pixels (>= 0).

    Returns:
        (K, M) or (B, K, M) int64: each row the sorted distinct ids, padded with -1; ``M`` is
        the largest set size (0 when all sets are empty).

    Raises:
        ShapeError: shapes that do not match.
        ValueError: non-finite keypoints or negative / non-finite radii.

    Example:
        >>> ids = torch.tensor([[0, 1, -1], [2, 2, 3]])
        >>> neighbour_surfels(ids, torch.tensor([[0.0, 0.0]]), 1.0)
        tensor([[0, 1, 2]])
    """
    unbatched = ids.dim() == 2
    if unbatched:
        ids, keypoints = ids[None], keypoints[None]
    check_shape(ids, "B,H,W", "ids")
    check_shape(keypoints, "B,K,2", "keypoints")
    if keypoints.shape[0] != ids.shape[0]:
        raise ShapeError(
            f"keypoints batch {keypoints.shape[0]} does not match ids batch {ids.shape[0]}"
        )
    check_finite(keypoints, "keypoints")
    batch, height, width = ids.shape
    count = keypoints.shape[1]
    radius = torch.as_tensor(radius_px, dtype=torch.float32, device=keypoints.device)
    try:
        radius = radius.expand(batch, count) if radius.dim() < 2 else radius
    except RuntimeError as exc:
        raise ShapeError(f"radius_px of shape {tuple(radius.shape)} does not match K") from exc
    if radius.shape != (batch, count):
        raise ShapeError(f"radius_px must be scalar, (K,) or (B, K), got {tuple(radius.shape)}")
    if not bool((torch.isfinite(radius) & (radius >= 0)).all()):
        raise ValueError("radius_px must be finite and non-negative")
    result = _neighbours_flat(ids, keypoints.to(torch.float32), radius)
    result = result.view(batch, count, result.shape[-1])
    return result[0] if unbatched else result


def _inside(pu: torch.Tensor, u: torch.Tensor, dv2: torch.Tensor, r2: torch.Tensor) -> torch.Tensor:
    """Whether float pixel columns ``pu`` lie in the disks, given each row's squared offset
    ``dv2`` and squared radius ``r2`` (all broadcast alike); the one float32 membership test."""
    return (pu - u).square() + dv2 <= r2


def _disk_rows(
    keypoints: torch.Tensor, radius: torch.Tensor, height: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Image rows each keypoint's disk may cover.

    Args:
        keypoints: (N, 2) float32 pixel coordinates ``(u, v)``.
        radius: (N,) float32 radii.
        height: image height.

    Returns:
        owner: (R,) int64 keypoint of every row, ascending.
        rows: (R,) int64 row index in ``[0, height)``: the rows within ``floor(radius) + 1`` of
        the keypoint's nearest pixel row, which hold every pixel of the disk.
    """
    reach = torch.floor(radius) + 1
    centre = torch.floor(keypoints[:, 1] + 0.5)
    first = (centre - reach).clamp(0, height).long()
    last = (centre + reach).clamp(-1, height - 1).long()
    count = (last - first + 1).clamp_min(0)
    owner = torch.repeat_interleave(torch.arange(len(count), device=count.device), count)
    rank = torch.arange(len(owner), device=owner.device) - (count.cumsum(0) - count)[owner]
    return owner, first[owner] + rank


def _segment_end(
    u: torch.Tensor, dv2: torch.Tensor, r2: torch.Tensor, width: int, side: int
) -> torch.Tensor:
    """(R,) int64 last pixel column of each row's disk segment towards ``side`` (-1 left, +1
    right), clamped to ``[-1, width]``.

    At image-scale coordinates the square-root estimate is within one pixel of the float32
    test of :func:`_inside`, which decides: the segment end is the outermost of the estimate's
    neighbours inside the disk (beyond the estimate on an empty row, so that the ends cross).
    """
    half = (r2 - dv2).clamp_min(0).sqrt()
    estimate = torch.ceil(u - half) if side < 0 else torch.floor(u + half)
    estimate = estimate.clamp(-1, width)
    outer, inner = estimate + side, estimate - side
    end = torch.where(_inside(estimate, u, dv2, r2), estimate, inner)
    end = torch.where(_inside(outer, u, dv2, r2), outer, end)
    return end.long().clamp(-1, width)


def _disk_segments(
    keypoints: torch.Tensor, radius: torch.Tensor, height: int, width: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pixels of the keypoint disks as non-empty row segments, clipped to the image.

    Args:
        keypoints: (N, 2) float32 pixel coordinates ``(u, v)``.
        radius: (N,) float32 radii.
        height: image height.
        width: image width.

    Returns:
        ``(owner, rows, left, right)``, each (S,) int64: the keypoint, image row and first and
        last column (inclusive) of every segment, keypoint by keypoint.
    """
    owner, rows = _disk_rows(keypoints, radius, height)
    u, r2 = keypoints[owner, 0], radius[owner].square()
    dv2 = (rows - keypoints[owner, 1]).square()
    left = _segment_end(u, dv2, r2, width, -1).clamp_min(0)
    right = _segment_end(u, dv2, r2, width, 1).clamp_max(width - 1)
    keep = left <= right
    return owner[keep], rows[keep], left[keep], right[keep]


def keypoint_disk_mask(
    keypoints: torch.Tensor, radius_px: torch.Tensor | float, height: int, width: int
) -> torch.Tensor:
    """The pixels :func:`neighbour_surfels` reads: those within each keypoint's radius.

    Pass it as ``pixels`` to :meth:`SurfelIndexRenderer.render` when only the neighbour sets
    are needed.

    Args:
        keypoints: (K, 2) finite pixel coordinates ``(u, v)``.
        radius_px: scalar or (K,) radii in pixels (finite, >= 0).
        height: image height H.
        width: image width W.

    Returns:
        (H, W) bool, true at the pixel centres within ``radius_px`` of a keypoint.

    Raises:
        ShapeError: keypoints not (K, 2), radii neither scalar nor (K,).
        ValueError: non-finite keypoints, negative or non-finite radii.

    Example:
        >>> keypoint_disk_mask(torch.tensor([[1.0, 1.0]]), 1.0, 3, 4).int()
        tensor([[0, 1, 0, 0],
                [1, 1, 1, 0],
                [0, 1, 0, 0]], dtype=torch.int32)
    """
    return KeypointDisks.of(keypoints, radius_px, height, width).mask()


@dataclass(frozen=True)
class KeypointDisks:
    """The pixels within each keypoint's radius in one image, as row segments.

    Made once per image, they give both the pixels :func:`neighbour_surfels` reads
    (:meth:`mask`, as :func:`keypoint_disk_mask`) and, from the rendered index map, the
    neighbouring surfel sets (:meth:`neighbours`, as :func:`neighbour_surfels`).

    Attributes:
        owner: (S,) int64 keypoint of every segment, keypoint by keypoint.
        rows: (S,) int64 image row of every segment.
        left: (S,) int64 first column (inclusive) of every segment.
        right: (S,) int64 last column (inclusive) of every segment.
        count: number of keypoints K.
        height: image height H.
        width: image width W.

    Example:
        >>> disks = KeypointDisks.of(torch.tensor([[0.0, 0.0]]), 1.0, 2, 3)
        >>> disks.neighbours(torch.tensor([[0, 1, -1], [2, 2, 3]]))
        tensor([[0, 1, 2]])
    """

    owner: torch.Tensor
    rows: torch.Tensor
    left: torch.Tensor
    right: torch.Tensor
    count: int
    height: int
    width: int

    @classmethod
    def of(
        cls, keypoints: torch.Tensor, radius_px: torch.Tensor | float, height: int, width: int
    ) -> KeypointDisks:
        """The disks of (K, 2) ``keypoints`` with scalar or (K,) ``radius_px`` in an image.

        Raises:
            ShapeError: keypoints not (K, 2), radii neither scalar nor (K,).
            ValueError: non-finite keypoints, negative or non-finite radii.
        """
        check_shape(keypoints, "K,2", "keypoints")
        check_finite(keypoints, "keypoints")
        keypoints = keypoints.to(torch.float32)
        radius = torch.as_tensor(radius_px, dtype=torch.float32, device=keypoints.device)
        if radius.dim() > 1 or radius.numel() not in (1, keypoints.shape[0]):
            raise ShapeError(f"radius_px must be scalar or (K,), got {tuple(radius.shape)}")
        if not bool((torch.isfinite(radius) & (radius >= 0)).all()):
            raise ValueError("radius_px must be finite and non-negative")
        radius = radius.expand(keypoints.shape[0])
        segments = _disk_segments(keypoints, radius, height, width)
        return cls(*segments, keypoints.shape[0], height, width)

    def mask(self) -> torch.Tensor:
        """(H, W) bool, true at the pixel centres within a keypoint's radius."""
        start = self.rows * self.width
        steps = torch.zeros(self.height * self.width + 1, dtype=torch.int32, device=start.device)
        steps.index_add_(0, start + self.left, torch.ones_like(self.left, dtype=torch.int32))
        ends = torch.full_like(self.right, -1, dtype=torch.int32)
        steps.index_add_(0, start + self.right + 1, ends)
        return steps.cumsum_(0)[:-1].view(self.height, self.width) > 0

    def neighbours(self, ids: torch.Tensor) -> torch.Tensor:
        """(K, M) sorted distinct surfel ids of (H, W) ``ids`` in each disk, padded with -1.

        Raises:
            ShapeError: ``ids`` not (H, W).
        """
        check_shape(ids, f"{self.height},{self.width}", "ids")
        return _segment_sets(ids[None], self.owner, self.rows, self.left, self.right, self.count)


def _run_starts(
    ids: torch.Tensor, first: torch.Tensor, last: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat pixels that start a run of equal ids within each row segment.

    A segment ``[first, last]`` (flat pixel indices within one image row) holds the same ids
    as its first pixel plus the pixels that differ from their left neighbour.

    Args:
        ids: (B, H, W) surfel index map.
        first, last: (S,) int64 flat pixel bounds of non-empty segments.

    Returns:
        count: (S,) int64 number of run starts of every segment.
        pixel: (E,) int64 flat pixel index of every run start, segment by segment.
    """
    change = torch.zeros_like(ids, dtype=torch.bool)
    change[..., 1:] = ids[..., 1:] != ids[..., :-1]
    change = change.reshape(-1)
    before = torch.zeros(change.numel() + 1, dtype=torch.int64, device=ids.device)
    torch.cumsum(change, 0, out=before[1:])  # before[f]: changes at flat pixels < f
    # The changes in (first, last] are positions[skip:skip + count - 1]; a zero sentinel
    # stands in for the segment's first pixel, written afterwards.
    positions = torch.cat([change.nonzero().squeeze(1), before[:1]])
    skip = before[first + 1]
    count = before[last + 1] - skip + 1
    start = count.cumsum(0) - count
    index = torch.arange(int(count.sum()), device=ids.device)
    index += torch.repeat_interleave(skip - 1 - start, count)
    pixel = positions[index.clamp_min_(0)]
    pixel[start] = first
    return count, pixel


def _padded_sets(owner: torch.Tensor, values: torch.Tensor, count: int) -> torch.Tensor:
    """(count, M) sorted distinct non-negative ``values`` of every owner, padded with -1.

    Args:
        owner: (E,) int64 owner of every value in ``[0, count)``.
        values: (E,) int64 values >= -1; -1 ones are ignored.
        count: number of owners.
    """
    base = int(values.max()) + 2 if len(values) else 1
    key = (owner * base + (values + 1)).sort(stable=True).values  # stable: radix sort on CPU
    first = torch.ones_like(key, dtype=torch.bool)
    first[1:] = key[1:] != key[:-1]
    key = key[first & (key % base != 0)]
    owner, values = key // base, key % base - 1
    sizes = torch.bincount(owner, minlength=count)
    width = int(sizes.max()) if count else 0
    rank = torch.arange(len(key), device=key.device) - (sizes.cumsum(0) - sizes)[owner]
    out = torch.full((count * width,), -1, dtype=torch.int64, device=key.device)
    return out.index_put_((owner * width + rank,), values).view(count, width)


def _neighbours_flat(
    ids: torch.Tensor, keypoints: torch.Tensor, radius: torch.Tensor
) -> torch.Tensor:
    """(B * K, M) neighbour sets; see :func:`neighbour_surfels`.

    Every keypoint scans only its own disk, as ragged row segments (no padding to the largest
    radius): the ids of a segment are those of its runs of equal ids, and one sort of
    ``(keypoint, id)`` keys makes the sets distinct.
    """
    batch, height, width = ids.shape
    kp, rad = keypoints.reshape(-1, 2), radius.reshape(-1)
    owner, rows, left, right = _disk_segments(kp, rad, height, width)
    camera = owner // max(keypoints.shape[1], 1)
    return _segment_sets(ids, owner, camera * height + rows, left, right, kp.shape[0])


def _segment_sets(
    ids: torch.Tensor,
    owner: torch.Tensor,
    rows: torch.Tensor,
    left: torch.Tensor,
    right: torch.Tensor,
    count: int,
) -> torch.Tensor:
    """(count, M) distinct ids of (B, H, W) ``ids`` in the (S,) row segments of each owner.

    ``rows`` index the rows of all B images stacked (``b H + row``); see :func:`_disk_segments`
    for the other fields. The ids of a segment are those of its runs of equal ids, and one
    sort of ``(owner, id)`` keys makes the sets distinct.
    """
    row_start = rows * ids.shape[-1]
    runs, pixel = _run_starts(ids, row_start + left, row_start + right)
    found = ids.reshape(-1).index_select(0, pixel)
    return _padded_sets(torch.repeat_interleave(owner, runs), found, count)
