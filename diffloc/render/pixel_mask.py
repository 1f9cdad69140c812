"""The pixels to render of a masked surfel render: summed-area tables and box tests."""

from __future__ import annotations

import math

import torch

from diffloc.geometry.camera import MIN_DEPTH
from diffloc.render.view import _View

_PREFILTER_MARGIN_PX = 0.05
"""Slack of the disk-box test of masked renders: far above the float32 rounding of a pixel
coordinate (~1e-4 px) and of the ray-disk test (~1e-6 of the disk)."""


def _summed_area(pixels: torch.Tensor) -> torch.Tensor:
    """((H + 1) * (W + 1),) int32 flat summed-area table of an (H, W) bool image: entry
    ``(v, u)`` counts the true pixels above row ``v`` and left of column ``u``."""
    height, width = pixels.shape
    table = torch.zeros((height + 1, width + 1), dtype=torch.int32, device=pixels.device)
    torch.cumsum(pixels.to(torch.int32).cumsum(0, dtype=torch.int32), 1, out=table[1:, 1:])
    return table.view(-1)


def _box_sums(sums: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, width: int) -> torch.Tensor:
    """(M,) int32 counts of the true pixels in the boxes ``[lo, hi]`` ((2, M) int32 ``(u, v)``,
    inclusive, in the image as :func:`_surfel_boxes` clips them; empty boxes count <= 0), from
    a flat :func:`_summed_area` table of a ``width``-wide image: four lookups per box (int32
    indices: the table is image-sized)."""
    last = hi + 1
    top, bottom = lo[1] * (width + 1), last[1] * (width + 1)
    corners = torch.stack((bottom + last[0], top + lo[0], top + last[0], bottom + lo[0]))
    value = sums.index_select(0, corners.view(-1)).view(4, -1)
    return value[0] + value[1] - value[2] - value[3]


def _box_touches(
    centres: torch.Tensor, extents: torch.Tensor, view: _View, pixel_sums: torch.Tensor
) -> torch.Tensor:
    """(m,) bool: the camera-frame boxes ``centres +- extents`` ((3, m) each) that may be seen
    at a pixel of ``pixel_sums``.

    The ``u = fx x / z + cx`` of a box's points lies between the extremes of ``x / z`` over
    its ``x`` and ``z`` ranges (at its corners); only the pixel centres in that range, widened
    by :data:`_PREFILTER_MARGIN_PX` against rounding, can see the box. Boxes reaching the near
    plane (or with NaN entries) may be seen anywhere.
    """
    z_near, z_far = centres[2] - extents[2], centres[2] + extents[2]
    low, high = centres[:2] - extents[:2], centres[:2] + extents[:2]
    low.div_(torch.where(low < 0, z_near, z_far))  # smallest x / z, y / z
    high.div_(torch.where(high < 0, z_far, z_near))
    unbounded = (z_near > MIN_DEPTH).logical_not_()
    low.masked_fill_(unbounded, -math.inf)
    high.masked_fill_(unbounded, math.inf)
    width, height = view.camera.width, view.camera.height
    for row, f, principal, size in ((0, view.fx, view.cx, width), (1, view.fy, view.cy, height)):
        low[row].mul_(f).add_(principal - _PREFILTER_MARGIN_PX).ceil_().clamp_(0, size)
        high[row].mul_(f).add_(principal + _PREFILTER_MARGIN_PX).floor_().clamp_(-1, size - 1)
    return _box_sums(pixel_sums, low.to(torch.int32), high.to(torch.int32), width) > 0
