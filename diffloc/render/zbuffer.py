"""Z-buffer keys of the hard splatting renderers (surfels and points).

A candidate (pixel, primitive) is an int64 key whose high 32 bits are the bits of its float32
depth (positive floats order like their bit patterns) and whose low 32 bits are the primitive
index. ``scatter_reduce(..., reduce="amin")`` over the flattened pixels keeps, per pixel, the
nearest depth and its id in one pass; equal depths go to the lower index, so renders are
deterministic and independent of the input order (:mod:`~diffloc.render.point_render`).
Surfel keys instead hold the float32 *inverse* depth (high word) and a tie-breaker decreasing
with the surfel's number (low word) and are max-reduced (:mod:`~diffloc.render.surfel_raster`).
Cameras are rendered one after the other; everything per camera is vectorised over primitives
and pixels, in chunks that bound the memory.
"""

from __future__ import annotations

import sys

import torch

_EMPTY_KEY = torch.iinfo(torch.int64).max
"""Depth z-buffer key of an empty pixel (keys are min-reduced)."""
_LOW32 = 0xFFFFFFFF
_CHUNK = 1 << 18
"""Elements per chunk of vectorised work: bounds temporaries to a few MB each."""
_HIGH_WORD = 1 if sys.byteorder == "little" else 0
"""Which of the two 32-bit words of an int64 in memory holds its high half."""
_NO_KEY = torch.iinfo(torch.int64).min
"""Surfel z-buffer key of an empty pixel (keys are max-reduced)."""
_TIE_TOP = 0x7F7FFFFF
"""Bits of the largest finite float32; tie-breakers count down from it."""
_MAX_SURFELS = _TIE_TOP - 0x00800000 + 1
"""Surfels per render, so that every tie-breaker is a positive normal float32."""


def _pack_keys(depth: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
    """int64 keys ordering by float32 ``depth > 0`` first, then by ``ids`` in [0, 2^31)."""
    bits = depth.to(torch.float32).contiguous().view(torch.int32).to(torch.int64)
    return torch.add(ids, bits, alpha=1 << 32)


def _unpack_keys(keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(ids, depth)`` of z-buffer keys: -1 and 0 where the key is empty."""
    empty = keys == _EMPTY_KEY
    ids = torch.bitwise_and(keys, _LOW32).masked_fill_(empty, -1)
    depth_bits = torch.bitwise_right_shift(keys, 32).to(torch.int32)
    depth = depth_bits.view(torch.float32).masked_fill_(empty, 0.0)
    return ids, depth


def _key_words(keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(low, high)`` int32 halves of (P,) int64 keys, (P,) strided views each (no copy)."""
    words = keys.view(torch.int32)  # (2 P,)
    return words[1 - _HIGH_WORD :: 2], words[_HIGH_WORD::2]


def _empty_keys(shape: tuple[int, ...], device: torch.device) -> torch.Tensor:
    return torch.full(shape, _EMPTY_KEY, dtype=torch.int64, device=device)


def _tie_breakers(ids: torch.Tensor) -> torch.Tensor:
    """(K,) float32 z-buffer tie-breakers of (K,) int64 map indices (below :data:`_MAX_SURFELS`).

    Their bits are ``_TIE_TOP - ids``: positive normal floats, so a matrix product with one
    non-zero (unit) term reproduces them bit for bit, decreasing with the map index, so the
    max-reduced key of equal inverse depths holds the lowest.
    """
    return (_TIE_TOP - ids).to(torch.int32).view(torch.float32)
