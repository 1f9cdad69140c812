"""Candidate pixel windows of surfels, sorted into buckets of a few window sizes.

Candidate windows are the pixels of the analytic bounding box of the projected ellipse
(clipped to the image), grouped in buckets of a few window sizes (sparse buckets merged into
larger ones); a window starts at its box's top-left pixel (reaching into a padded z-buffer past
the image border), so that a surfel's window, and every key it writes, is the same whatever
else is drawn (masked renders skip the surfels that reach no pixel to render).
"""

from __future__ import annotations

import bisect
import functools
import math
from dataclasses import dataclass

import torch

from diffloc.geometry.camera import MIN_DEPTH
from diffloc.render.pixel_mask import _box_sums
from diffloc.render.surfel_conics import (
    _Conics,
    _surfel_boxes,
    _surfel_conics,
    _window_polynomials,
)
from diffloc.render.view import _View
from diffloc.render.zbuffer import _HIGH_WORD, _tie_breakers

_GRAZING_COS = 1e-6
"""Surfels seen exactly edge-on (|cos| of the view angle below this) cover no pixel centre."""
_MERGE_PIXELS = 4096
"""A bucket of windows joins a larger one when that adds at most this many candidate pixels
(about the cost of the few tensor operations that every bucket takes)."""
_PAD_STEP = 32
"""The z-buffer row padding is a multiple of this (few distinct strides for the basis cache)."""


@dataclass(frozen=True)
class _SurfelCandidates:
    """The surfels of one camera that pass the frustum cull (and, in a masked render, the box
    test), in the camera frame.

    They may come in any order: the z-buffer breaks ties with the map index, not the position.
    """

    ids: torch.Tensor  # (M,) int64 distinct map indices
    centers: torch.Tensor  # (3, M) float32 camera-frame centres (coordinates as rows)
    normals: torch.Tensor  # (3, M) float32 unit camera-frame normals
    radii: torch.Tensor  # (M,) float32


@dataclass(frozen=True)
class _Windows:
    """Candidate pixel windows of one camera, sorted into buckets of one window size.

    Window ``w`` tests the ``size_v x size_u`` pixels from flat index ``base[w]`` of a
    z-buffer of ``buffer_rows x stride`` pixels (the image, padded right and below so that every
    window fits from the top-left pixel of its surfel's box), with
    polynomials in the offsets ``(i, j)`` from that top-left pixel: ``inside[:, w]`` holds the
    coefficients of ``1 - q`` (>= 0 on the disk, see :class:`_Conics`) on the monomials
    ``(i^2, i j, j^2, i, j, 1)``, ``keys[:, 2 w + 1]`` those of the inverse depth on
    ``(i, j, 1)`` and ``keys[:, 2 w]`` a constant, the float32 whose bits are the window's
    z-buffer tie-breaker (see :func:`_rasterise_surfels`; the two swap on big-endian
    machines, so that each pair reads as one int64 key). Windows ``start .. start + count - 1``
    of a bucket share the size; ``near`` buckets hold surfels that may reach the near plane.
    """

    inside: torch.Tensor  # (6, K) float32
    keys: torch.Tensor  # (3, 2 K) float32
    base: torch.Tensor  # (K,) int64 flat index of the top-left pixel
    buckets: list[tuple[int, int, bool, int, int]]  # size_u, size_v, near, start, count
    stride: int  # z-buffer row length, >= W
    buffer_rows: int  # z-buffer rows, >= H


def _surfel_windows(
    surfels: _SurfelCandidates,
    view: _View,
    height: int,
    width: int,
    cull_backfaces: bool,
    pixel_sums: torch.Tensor | None = None,
) -> _Windows:
    """Conics and candidate windows of the surfels that may be visible in one camera.

    Args:
        surfels: the frustum-culled surfels.
        view: the camera.
        height: image height.
        width: image width.
        cull_backfaces: drop surfels whose normal points away from the camera.
        pixel_sums: summed-area table of the pixels to render (see :func:`_summed_area`), or
            ``None`` for all pixels.
    """
    layout = _bucket_layout(width, height, surfels.radii.device)
    lo, group, conics = _surfel_groups(surfels, view, layout, cull_backfaces, pixel_sums)
    return _bucket_windows(surfels, layout, lo, group, conics)


def _surfel_groups(
    surfels: _SurfelCandidates,
    view: _View,
    layout: _BucketLayout,
    cull_backfaces: bool,
    pixel_sums: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor, _Conics]:
    """Boxes and buckets of M surfels.

    Args:
        surfels: the frustum-culled surfels.
        view: the camera.
        layout: the image's window buckets.
        cull_backfaces: drop surfels whose normal points away from the camera.
        pixel_sums: summed-area table of the pixels to render (see :func:`_summed_area`), or
            ``None`` for all pixels.

    Returns:
        ``(lo, group, conics)``: (2, M) int32 top-left box corners ``(u, v)`` (see
        :func:`_surfel_boxes`), (M,) int32 bucket before merging (:class:`_BucketLayout`),
        ``len(layout.shapes)`` for the surfels not drawn (not visible, or their box holds no
        pixel of ``pixel_sums``), and the surfels' conics.
    """
    c, n, r = surfels.centers, surfels.normals, surfels.radii
    conics, k, cc = _surfel_conics(c, n, r, view)
    total = c.sum(0) + n.sum(0) + r
    visible = (total - total) == 0  # false for NaN / inf
    visible &= c[2] > MIN_DEPTH
    visible &= k.square() > _GRAZING_COS**2 * cc
    if cull_backfaces:
        visible &= k < 0
    near = c[2] - r <= MIN_DEPTH
    lo, hi = _surfel_boxes(conics, near, r, c, view, layout.height, layout.width)
    extent = hi - lo + 1
    visible &= torch.minimum(*extent) > 0  # (integer amin is slow on CPU)
    level = layout.level.index_select(0, extent.clamp_(0, layout.level.shape[0] - 1).view(-1))
    level = level.view(2, -1)  # (2, m)
    group = level[0].mul_(layout.levels).add_(level[1]).mul_(2).add_(near)
    if pixel_sums is not None:
        visible &= _box_sums(pixel_sums, lo, hi, layout.width) > 0
    return lo, group.masked_fill_(~visible, len(layout.shapes)), conics


def _bucket_sizes(limit: int) -> list[int]:
    """Window sizes used as buckets: 1, 2, 3, 4, 6, 8, then steps of ~40 %, last >= ``limit``."""
    sizes = [1, 2, 3, 4, 6, 8]
    while sizes[-1] < limit:
        sizes.append(math.ceil(sizes[-1] * 1.4))
    return sizes


@dataclass(frozen=True)
class _BucketLayout:
    """The window buckets of one image size.

    Bucket (group) ``g = 2 (levels l_u + l_v) + near`` holds windows of
    ``shapes[g] = (size_u, size_v)`` pixels, the :func:`_bucket_sizes` of levels ``l_u`` and
    ``l_v`` clipped to the image; ``near`` marks surfels that may reach the near plane.
    """

    width: int  # image width W
    height: int  # image height H
    levels: int
    shapes: tuple[tuple[int, int], ...]  # (G,)
    level: torch.Tensor  # (max(W, H) + 1,) int32 level of a box extent
    sizes: torch.Tensor  # (2, G + 1) int32 (size_u, size_v) of each group, then 1 (dropped)


@functools.lru_cache(maxsize=16)
def _bucket_layout(width: int, height: int, device: torch.device) -> _BucketLayout:
    """:class:`_BucketLayout` of a ``width x height`` image (memoised read-only constants)."""
    limit = max(width, height)
    sizes = _bucket_sizes(limit)
    levels = len(sizes)
    shapes = tuple(
        (min(sizes[g // (2 * levels)], width), min(sizes[g // 2 % levels], height))
        for g in range(2 * levels**2)
    )
    table = torch.tensor(sizes, device=device)
    level = torch.bucketize(torch.arange(limit + 1, device=device), table, out_int32=True)
    sizes = torch.tensor([*shapes, (1, 1)], dtype=torch.int32, device=device).T.contiguous()
    return _BucketLayout(width, height, levels, shapes, level, sizes)


def _bucket_windows(
    surfels: _SurfelCandidates,
    layout: _BucketLayout,
    lo: torch.Tensor,
    group: torch.Tensor,
    conics: _Conics,
) -> _Windows:
    """Sort the drawn windows into buckets of one (width, height) and place them in the image.

    Each box widens (right and down, into the z-buffer's padding at the image border) to its
    bucket's size: the extra pixels fail the exact test. Surfels that may reach the near plane
    get buckets of their own, which add a depth test. Sparse buckets join larger ones (see
    :func:`_merge_sparse_buckets`); a window's top-left pixel and polynomials depend on its
    surfel alone, and a larger window evaluates the same pixels the same way
    (:func:`_rasterise_surfels`), so a surfel is drawn bit for bit alike whatever else is
    drawn with it. Only the drawn windows (group below ``len(layout.shapes)``: visible, and
    their box holds a pixel to render; the full render draws no pixel outside a surfel's box,
    which bounds its disk with a margin against rounding) are placed and given polynomials.

    Args:
        surfels: the frustum-culled surfels (M).
        layout: the image's window buckets.
        lo: (2, M) int32 top-left pixel ``(u, v)`` of each box.
        group: (M,) int32 bucket of each window (see :func:`_surfel_groups`).
        conics: the conics of the M surfels.
    """
    height, width = layout.height, layout.width
    dropped = len(layout.shapes)
    counts = torch.bincount(group, minlength=dropped + 1).tolist()
    target = [*_merge_sparse_buckets(counts[:-1], layout.shapes), dropped]
    # int16 groups: the stable sort below is twice as fast as on int32.
    group = torch.tensor(target, dtype=torch.int16, device=lo.device).index_select(0, group)
    buckets, start = [], 0
    for g, count in enumerate(torch.bincount(group, minlength=dropped + 1)[:-1].tolist()):
        if count:
            buckets.append((*layout.shapes[g], g % 2 == 1, start, count))
            start += count
    # The windows, bucket by bucket: a stable sort of all, or of the drawn ones when few are.
    if 2 * start > group.shape[0]:
        order = torch.argsort(group, stable=True)[:start]
    else:
        drawn = torch.nonzero(group != dropped).view(-1)
        order = drawn.index_select(0, torch.argsort(group.index_select(0, drawn), stable=True))
    corner = lo.index_select(1, order)
    size = layout.sizes.index_select(1, group.index_select(0, order).to(torch.int32))
    pad_u, pad_v = (
        ((corner + size).amax(1) - corner.new_tensor([width, height])).clamp_(min=0).tolist()
        if start
        else (0, 0)
    )
    stride = width + -(-pad_u // _PAD_STEP) * _PAD_STEP  # few distinct strides: basis cache
    inside, inverse_depth = _window_polynomials(conics.select(order), corner)
    keys = inside.new_empty(3, start, 2)  # (tie-breaker, inverse depth) words of int64 keys
    keys[:2, :, 1 - _HIGH_WORD] = 0.0
    keys[2, :, 1 - _HIGH_WORD] = _tie_breakers(surfels.ids.index_select(0, order))
    keys[:, :, _HIGH_WORD] = inverse_depth
    base = corner[1].to(torch.int64).mul_(stride).add_(corner[0])
    return _Windows(inside, keys.view(3, -1), base, buckets, stride, height + pad_v)


def _merge_sparse_buckets(counts: list[int], shapes: tuple[tuple[int, int], ...]) -> list[int]:
    """The bucket each bucket's windows go to: sparse ones join the smallest that holds them.

    Every bucket costs a few tensor operations whatever its size, so a bucket of ``c`` windows
    of ``A`` pixels moves to the smallest-area bucket (same near flag, both sides at least as
    large) when that adds at most :data:`_MERGE_PIXELS` candidate pixels, ``c (A' - A)``.
    Sparsest buckets go first; a bucket that received windows may move on later.

    Args:
        counts: windows per bucket (group index ``g``, near flag ``g % 2``).
        shapes: ``(size_u, size_v)`` of each bucket.

    Returns:
        The target group of every group.
    """
    alive = {g: c for g, c in enumerate(counts) if c}
    by_area = sorted((shapes[g][0] * shapes[g][1], g) for g in alive)
    target = list(range(len(counts)))
    for g in sorted(alive, key=counts.__getitem__):
        area, (size_u, size_v) = shapes[g][0] * shapes[g][1], shapes[g]
        for other_area, h in by_area[bisect.bisect_left(by_area, (area, -1)) :]:
            if alive[g] * (other_area - area) > _MERGE_PIXELS:
                break
            other_u, other_v = shapes[h]
            if h != g and h in alive and h % 2 == g % 2 and other_u >= size_u and other_v >= size_v:
                alive[h] += alive.pop(g)
                target[g] = h
                break
    for g in range(len(target)):  # follow chains of moves
        while target[target[g]] != target[g]:
            target[g] = target[target[g]]
    return target
