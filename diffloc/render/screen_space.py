"""Screen-space visibility of point splats: hide what a sparse nearer surface lets through.

Square splats of a sparse cloud leave gaps through which the points behind a surface show
(seed 2 Fig. 4: far walls seen through near ones), and small holes where no splat lands.
Point-based renderers repair both in image space (e.g. Pintus et al., "Real-time rendering of
massive unstructured raw point clouds using screen-space operators", VAST 2011): a pixel is
*hidden* when nearer surface encloses it in the image. Here the disc of ``radius`` pixels
around each pixel is cut into 8 sectors of 45 deg centred on the directions E, SE, S, SW, W,
NW, N, NE, and the nearest z-buffer key of each sector is taken (wedges, not rays: the gaps of
a regular splat grid are lines that a one-pixel ray can follow without meeting the surface);
the pixel is enclosed when at least ``min_sectors`` of those keys have a depth below
``depth_ratio`` times its own (an empty pixel counts as infinitely far, so an enclosed hole is
filled the same way). An enclosed pixel takes the lower median of the 8 sector keys: with
``min_sectors >= 5`` that is one of the enclosing surface's points, so its depth and colour
come from the surface that hides the pixel, and one stray nearer point in a single sector
cannot win. A pixel beside a straight silhouette finds the nearer object in at most 5 sectors
(fewer at its convex corners) and stays; so does the image border, since pixels outside the
image are empty and enclose nothing. One pass, vectorised over the batch and pixels: one
shifted minimum of the key images per offset in the disc (about ``pi radius^2``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from diffloc.checks import check_shape
from diffloc.render.zbuffer import _EMPTY_KEY, _unpack_keys

__all__ = ["DIRECTIONS", "ScreenSpaceVisibility", "hide_enclosed", "sector_offsets"]

DIRECTIONS = ((0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1), (-1, 0), (-1, 1))
"""The 8 sector directions as (row, column) steps: E, SE, S, SW, W, NW, N, NE."""


@dataclass(frozen=True)
class ScreenSpaceVisibility:
    """Settings of :func:`hide_enclosed`.

    Attributes:
        radius: pixels searched along each of the 8 directions (>= 1).
        min_sectors: directions (of 8) that must hold nearer surface to hide a pixel, in
            [5, 8] (so that the lower median of the 8 keys lies on that surface).
        depth_ratio: a key is nearer when its depth is below this times the pixel's depth,
            in (0, 1].

    Raises:
        ValueError: values outside these ranges.
    """

    radius: int = 8
    min_sectors: int = 7
    depth_ratio: float = 0.9

    def __post_init__(self) -> None:
        if isinstance(self.radius, bool) or not isinstance(self.radius, int) or self.radius < 1:
            raise ValueError(f"radius must be an integer >= 1, got {self.radius!r}")
        if self.min_sectors not in range(5, 9):
            raise ValueError(f"min_sectors must be an integer in [5, 8], got {self.min_sectors!r}")
        if not 0.0 < self.depth_ratio <= 1.0:
            raise ValueError(f"depth_ratio must be in (0, 1], got {self.depth_ratio!r}")


def sector_offsets(radius: int) -> list[list[tuple[int, int]]]:
    """The (row, column) offsets of each of the 8 sectors: every offset within ``radius``
    pixels (Euclidean, the pixel itself excluded) whose angle lies within 22.5 deg of the
    sector's direction in :data:`DIRECTIONS` (no integer offset lies on a border).

    Example:
        >>> [len(s) for s in sector_offsets(2)], sector_offsets(2)[0], sector_offsets(2)[1]
        ([2, 1, 2, 1, 2, 1, 2, 1], [(0, 1), (0, 2)], [(1, 1)])
    """
    sectors: list[list[tuple[int, int]]] = [[] for _ in DIRECTIONS]
    for dv in range(-radius, radius + 1):
        for du in range(-radius, radius + 1):
            if 0 < dv * dv + du * du <= radius * radius:
                sector = math.floor(math.atan2(dv, du) / (math.pi / 4) + 0.5) % len(DIRECTIONS)
                sectors[sector].append((dv, du))
    return sectors


def _sector_nearest(keys: torch.Tensor, radius: int) -> torch.Tensor:
    """(8, B, H, W) smallest key in each sector (:func:`sector_offsets`) around every pixel of
    (B, H, W) ``keys``; pixels outside the image are empty."""
    batch, height, width = keys.shape
    padded = torch.full(
        (batch, height + 2 * radius, width + 2 * radius),
        _EMPTY_KEY,
        dtype=keys.dtype,
        device=keys.device,
    )  # F.pad would round the int64 fill through a float
    padded[:, radius : radius + height, radius : radius + width] = keys
    nearest = torch.full(
        (len(DIRECTIONS), *keys.shape), _EMPTY_KEY, dtype=keys.dtype, device=keys.device
    )
    for k, offsets in enumerate(sector_offsets(radius)):
        for dv, du in offsets:
            top, left = radius + dv, radius + du
            window = padded[:, top : top + height, left : left + width]
            torch.minimum(nearest[k], window, out=nearest[k])
    return nearest


@torch.no_grad()
def hide_enclosed(keys: torch.Tensor, visibility: ScreenSpaceVisibility) -> torch.Tensor:
    """Replace every pixel enclosed by nearer surface by that surface (module docstring).

    Args:
        keys: (B, H, W) int64 depth z-buffer keys (:mod:`~diffloc.render.zbuffer`: float32
            depth in the high word, point index in the low word; empty pixels hold the
            largest int64).
        visibility: search radius, sectors and depth ratio.

    Returns:
        (B, H, W) int64 keys: the enclosed pixels hold the lower median of their 8 directional
        nearest keys, the others are unchanged.

    Example:
        A 5 x 5 wall at depth 1 (point 0) with a see-through pixel at depth 4 (point 1) in its
        middle: the far pixel is hidden and takes the wall's key.

        >>> from diffloc.render.zbuffer import _pack_keys
        >>> depth = torch.ones(1, 5, 5)
        >>> depth[0, 2, 2] = 4.0
        >>> ids = (depth > 1).long()
        >>> out = hide_enclosed(_pack_keys(depth, ids), ScreenSpaceVisibility(radius=2))
        >>> bool((out == _pack_keys(torch.ones(1, 5, 5), torch.zeros(1, 5, 5).long())).all())
        True
    """
    check_shape(keys, "B,H,W", "keys")
    if keys.dtype != torch.int64:
        raise TypeError(f"keys must be int64 z-buffer keys, got {keys.dtype}")
    nearest = _sector_nearest(keys, visibility.radius)
    _, depth = _unpack_keys(keys)
    _, near_depth = _unpack_keys(nearest)
    far = depth.masked_fill(keys == _EMPTY_KEY, torch.inf) * visibility.depth_ratio
    nearer = (nearest != _EMPTY_KEY) & (near_depth < far)
    enclosed = nearer.sum(0) >= visibility.min_sectors
    median = nearest.sort(dim=0).values[(len(DIRECTIONS) - 1) // 2]
    return torch.where(enclosed, median, keys)
