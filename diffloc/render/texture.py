"""Mip-mapped, wrapping texture sampling for many materials at once."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from diffloc.checks import check_shape


def _neighbour_pairs(level: torch.Tensor) -> torch.Tensor:
    """(M, 3, s, s) mip level -> (6, M*s*s) planes: each texel's colour, then the colour of its
    right-hand neighbour (wrapping), so one column holds one bilinear footprint's top or bottom."""
    return torch.cat([level, level.roll(-1, 3)], 1).permute(1, 0, 2, 3).reshape(6, -1)


def _to_power_of_two(texture: np.ndarray, size: int) -> torch.Tensor:
    """(S, T, 3) array -> (3, size, size) tensor, resized bilinearly when needed."""
    image = torch.from_numpy(np.ascontiguousarray(texture, dtype=np.float32)).permute(2, 0, 1)
    if image.shape[1:] != (size, size):
        image = F.interpolate(image[None], size=(size, size), mode="bilinear", antialias=True)[0]
    return image


class MipmapTextures:
    """A stack of M wrapping textures with mip levels, sampled trilinearly in one batched call.

    Every texture is brought to one power-of-two size S (the largest given). Level l has size
    ``S >> l`` and is the 2x2 box-filtered level ``l - 1``. All levels of all materials live in one
    flat (6, texels) buffer of neighbour pairs (a texel and the one to its right, wrapping), so a
    bilinear lookup is two column gathers (its top and bottom pair) regardless of M, blended as
    whole channel rows; the buffer takes twice the memory of the texels. Samples are looked up
    ``chunk_size`` at a time, so the temporaries of a lookup stay bounded however many samples
    there are: the process reuses their heap memory instead of faulting in fresh pages per call.

    Args:
        textures: M images, each (S_m, T_m, 3) float in [0, 1].
        chunk_size: samples looked up together (a speed setting; results do not depend on it).
    """

    def __init__(self, textures: list[np.ndarray], chunk_size: int = 131072) -> None:
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        if not textures:
            raise ValueError("at least one texture is required")
        for i, texture in enumerate(textures):
            check_shape(texture, "S,T,3", f"textures[{i}]")
        largest = max(max(t.shape[0], t.shape[1]) for t in textures)
        size = 1 << max(0, math.ceil(math.log2(largest)))
        sizes = [size >> k for k in range(size.bit_length())]  # S, S/2, ..., 1
        counts = torch.tensor([len(textures) * s * s for s in sizes], dtype=torch.int64)
        if int(counts.sum()) > torch.iinfo(torch.int32).max:  # texel indices are int32
            raise ValueError(f"{len(textures)} textures of {size}x{size} texels are too many")
        level = torch.stack([_to_power_of_two(t, size) for t in textures])  # (M, 3, S, S)
        levels = [level]
        while len(levels) < len(sizes):
            level = F.avg_pool2d(level, 2)
            levels.append(level)
        self.num_materials = len(textures)
        self.size = size
        self.num_levels = len(levels)
        self._offsets = (torch.cumsum(counts, 0) - counts).to(torch.int32)
        self._size = torch.tensor(size, dtype=torch.int32)
        self._pairs = torch.cat([_neighbour_pairs(lv) for lv in levels], 1)
        self.chunk_size = chunk_size

    def _bilinear(
        self, material: torch.Tensor, uv: torch.Tensor, level: torch.Tensor
    ) -> torch.Tensor:
        """Bilinear, wrapping lookup at one integer mip level per sample.

        Args:
            material: (N,) integer material index.
            uv: (N, 2) float32 texture coordinates.
            level: (N,) integer mip level.

        Returns:
            (3, N) colours, one row per channel.
        """
        # In place wherever the buffer is this call's own: the same operations in the same
        # order, with less fresh memory.
        level, material = level.to(torch.int32), material.to(torch.int32)
        size = torch.bitwise_right_shift(self._size, level)  # S >> level
        base = self._offsets.index_select(0, level).add_((material * size).mul_(size))
        uv = uv.t()  # (2, N): whole rows per coordinate
        xy = torch.floor(uv)
        xy = torch.sub(uv, xy, out=xy).mul_(size).sub_(0.5)
        xy0 = torch.floor(xy)
        fx, fy = xy.sub_(xy0)
        wrap = size - 1  # sizes are powers of two, so "& (size - 1)" is "% size"
        x0, y0 = xy0.to(torch.int32).bitwise_and_(wrap)
        row0 = (y0 * size).add_(base)
        row1 = (y0 + 1).bitwise_and_(wrap).mul_(size).add_(base)
        index = torch.empty(2, len(level), dtype=torch.int32)
        torch.add(row0, x0, out=index[0])
        torch.add(row1, x0, out=index[1])
        pairs = self._pairs.index_select(1, index.view(-1)).view(6, 2, -1)
        top, bottom = pairs[:, 0], pairs[:, 1]  # (6, N) each
        t00, t01, t10, t11 = top[:3], top[3:], bottom[:3], bottom[3:]
        gx = 1 - fx
        top = t00.mul_(gx).add_(t01.mul_(fx))
        bottom = t10.mul_(gx).add_(t11.mul_(fx))
        return top.mul_(1 - fy).add_(bottom.mul_(fy))

    def _trilinear(
        self, material: torch.Tensor, uv: torch.Tensor, footprint_texels: torch.Tensor
    ) -> torch.Tensor:
        """:meth:`sample` of one chunk (the same arguments), as (3, N) channel rows."""
        level = torch.log2(footprint_texels.clamp_min(1.0)).clamp(max=self.num_levels - 1)
        lower = torch.floor(level).to(torch.int32).clamp(max=self.num_levels - 1)
        blend = level - lower.to(level.dtype)
        uv = uv.to(torch.float32)
        colour = self._bilinear(material, uv, lower)
        # The next level only where it is blended in (magnified or clamped samples sit on a
        # whole level: blend 0), the same value with fewer lookups.
        mixed = (blend > 0).nonzero().squeeze(1)
        if len(mixed):
            w = blend[mixed].to(colour.dtype)
            upper = (lower[mixed] + 1).clamp(max=self.num_levels - 1)
            above = self._bilinear(material[mixed], uv[mixed], upper)
            colour[:, mixed] = (1 - w) * colour[:, mixed] + w * above
        return colour

    def sample(
        self, material: torch.Tensor, uv: torch.Tensor, footprint_texels: torch.Tensor
    ) -> torch.Tensor:
        """Sample N points trilinearly.

        Args:
            material: (N,) integer material index.
            uv: (N, 2) texture coordinates (wrapping; v = 0 is the top row).
            footprint_texels: (N,) size of the sample's pixel on the level-0 texture, in texels;
                it selects the mip level (log2 of it, clamped to the pyramid).

        Returns:
            (N, 3) float32 colours (the transpose of contiguous (3, N) channel rows).
        """
        check_shape(uv, "N,2", "uv")
        check_shape(material, f"{uv.shape[0]}", "material")
        check_shape(footprint_texels, f"{uv.shape[0]}", "footprint_texels")
        colours = torch.empty(3, uv.shape[0], dtype=torch.float32)
        for start in range(0, uv.shape[0], self.chunk_size):
            part = slice(start, start + self.chunk_size)
            colours[:, part] = self._trilinear(material[part], uv[part], footprint_texels[part])
        return colours.t()
