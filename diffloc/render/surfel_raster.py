"""Rasterisation of surfel windows into the z-buffer and reading the surfel keys back.

Surfel z-buffer keys hold the float32 *inverse* depth (high word) and a tie-breaker
decreasing with the surfel's number (low word), max-reduced: the matrix product writes the
keys directly (the tie-breaker is a constant polynomial) and the ray-disk test is one
``copysign`` that makes misses negative. The nearest hit wins; equal inverse depths go to the
lower index. Depths come out as ``1 / inverse depth``, bit for bit what a depth-keyed z-buffer
would store, but two hits whose different inverse depths round to the same depth are ordered
by the inverse depth rather than the index.
"""

from __future__ import annotations

import functools
import math

import torch

from diffloc.geometry.camera import MIN_DEPTH
from diffloc.render.surfel_windows import _SurfelCandidates, _Windows
from diffloc.render.zbuffer import _CHUNK, _HIGH_WORD, _TIE_TOP, _key_words

_GEMM_COLUMNS = 12
"""Fewest windows per matrix product of :func:`_rasterise_surfels`: from 12 columns on, the
CPU sgemm (MKL, AVX2) rounds every output column alike, whatever the other columns; narrower
products take other kernels whose roundings differ."""
_BASIS_CACHE_AREA = 1024
"""Window bases up to this many pixels are memoised (a few MB at most)."""


def _make_window_basis(
    size_u: int, size_v: int, stride: int, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """Monomials and flat pixel offsets of the row-major pixels ``(i, j)`` of a window.

    Returns:
        ``(basis, offsets)``: (A, 6) float32 monomials ``(i^2, i j, j^2, i, j, 1)`` with
        ``A = size_u * size_v`` (a matrix product with (6, m) coefficients evaluates m
        polynomials at every pixel) and (A, 1) int64 offsets ``j stride + i`` in a z-buffer
        with rows of ``stride`` pixels.
    """
    j, i = torch.meshgrid(
        torch.arange(size_v, device=device, dtype=torch.float32),
        torch.arange(size_u, device=device, dtype=torch.float32),
        indexing="ij",
    )
    i, j = i.reshape(-1), j.reshape(-1)
    basis = torch.stack((i * i, i * j, j * j, i, j, torch.ones_like(i)), dim=1)
    offsets = j.to(torch.int64).mul_(stride).add_(i.to(torch.int64))
    return basis, offsets[:, None]


_cached_window_basis = functools.lru_cache(maxsize=256)(_make_window_basis)


def _window_basis(
    size_u: int, size_v: int, stride: int, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_make_window_basis`, memoised for small windows (read-only constants)."""
    if size_u * size_v <= _BASIS_CACHE_AREA:
        return _cached_window_basis(size_u, size_v, stride, device)
    return _make_window_basis(size_u, size_v, stride, device)


def _chunk_shape(area: int) -> tuple[int, int]:
    """``(columns, rows)``: windows of ``area`` pixels per matrix product of
    :func:`_rasterise_surfels` (at least :data:`_GEMM_COLUMNS`) and pixels of each per product
    (all but for windows wider than ``_CHUNK / _GEMM_COLUMNS``)."""
    columns = max(_GEMM_COLUMNS, _CHUNK // area)
    return columns, min(area, _CHUNK // columns)


def _rasterise_surfels(windows: _Windows, keys: torch.Tensor) -> None:
    """Ray-disk test of all candidate pixels, z-buffered into ``keys`` in place.

    A candidate's key is the int64 read from two adjacent float32: the low word is the
    window's tie-breaker and the high word the inverse depth, with the sign of ``1 - q``
    (negative: the ray misses the disk). Positive floats order like their bits, so a
    max-reduction keeps per pixel the largest inverse depth, i.e. the nearest hit, and of equal
    ones the lowest surfel; misses are negative keys and never win. A matrix product per chunk
    of windows writes the keys in place (the tie-breaker is a constant polynomial), a second
    one ``1 - q``, and one ``copysign`` applies the test. Every product has at least
    :data:`_GEMM_COLUMNS` columns (a chunk of fewer windows repeats some, which writes the same
    keys again; wide windows go by blocks of pixel rows), so that every window takes the same
    matrix product kernel, whatever other windows share its chunk.

    Args:
        windows: the candidate windows of one camera.
        keys: (windows.buffer_rows * windows.stride,) int64 flat z-buffer, in place
            (:data:`_NO_KEY` where empty).
    """
    pairs = windows.keys.view(3, -1, 2)
    for size_u, size_v, near, first, count in windows.buckets:
        area = size_u * size_v
        basis, offsets = _window_basis(size_u, size_v, windows.stride, keys.device)
        columns, rows = _chunk_shape(area)
        blocks = [
            (basis[row : row + rows], offsets[row : row + rows]) for row in range(0, area, rows)
        ]
        for start in range(first, first + count, columns):
            stop = min(start + columns, first + count)
            chunk = (
                slice(start, stop)
                if stop - start >= _GEMM_COLUMNS
                else torch.arange(_GEMM_COLUMNS).remainder_(stop - start).add_(start)
            )
            keys_pairs = pairs[:, chunk].reshape(3, -1)
            polynomials, base = windows.inside[:, chunk], windows.base[chunk]
            for block, block_offsets in blocks:
                candidates = torch.mm(block[:, 3:], keys_pairs)  # (rows, 2 m)
                inside = torch.mm(block, polynomials)  # (rows, m)
                inverse_depth = candidates[:, _HIGH_WORD::2]
                if near:  # hits must also be in front of the near plane
                    miss = (inside < 0) | (inverse_depth <= 0) | (inverse_depth >= 1.0 / MIN_DEPTH)
                    inverse_depth.masked_fill_(miss, -1.0)
                else:
                    inverse_depth.copysign_(inside)
                slots = torch.add(base, block_offsets)
                keys.scatter_reduce_(
                    0, slots.view(-1), candidates.view(torch.int64).view(-1), "amax"
                )


def _resolve_surfel_keys(
    keys: torch.Tensor,
    surfels: _SurfelCandidates,
    size: int,
    ids: torch.Tensor,
    depth: torch.Tensor,
    normals: torch.Tensor,
) -> None:
    """Write the surfel ids, depths and normals of a z-buffer into the output images.

    Args:
        keys: (P,) int64 z-buffer (see :func:`_rasterise_surfels`).
        surfels: the camera's candidate surfels.
        size: number of surfels N in the map.
        ids: (P,) int64 output, map index or -1.
        depth: (P,) float32 output, z-depth or 0.
        normals: (3, P) float32 output, unit camera-frame normal or 0.
    """
    count = surfels.ids.shape[0]
    low, high = _key_words(keys)
    inverse_depth = high.view(torch.float32)
    hit = inverse_depth > 0  # empty pixels: _NO_KEY or a miss, high word -0.0 or negative
    torch.reciprocal(torch.where(hit, inverse_depth, math.inf), out=depth)  # empty: 0
    found = torch.sub(_TIE_TOP, torch.where(hit, low, _TIE_TOP - size))  # `size`: none
    ids.copy_(found).masked_fill_(~hit, -1)
    position = torch.empty(size + 1, dtype=torch.int32, device=keys.device)  # map -> candidate
    position[size] = count
    position.index_copy_(0, surfels.ids, torch.arange(count, dtype=torch.int32, device=keys.device))
    local = position.index_select(0, found)
    table = torch.cat((surfels.normals, surfels.normals.new_zeros(3, 1)), dim=1)  # (3, M + 1)
    for row, out in zip(table, normals, strict=True):
        torch.index_select(row, 0, local, out=out)
