"""A radiance-field submap as an RGB-D map (:class:`~diffloc.crossmodal.synthesize.RGBDMap`).

Seed 2 (III-D3) renders its database images from the NeRF map at the selected poses; here a
trained field (:func:`diffloc.maps.nerf.export.load_field`) renders them by volume rendering
(:func:`diffloc.maps.nerf.renderer.render_image`, deterministic samples). The rendered depth
is the camera z of the expected termination; pixels whose opacity is below ``min_opacity``
look into empty space (or out of the submap) and become holes (depth 0), as the other maps'
empty pixels are.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch

from diffloc.checks import check_shape
from diffloc.crossmodal.synthesize import RGBD
from diffloc.geometry.camera import PinholeCamera
from diffloc.maps.nerf.export import load_field
from diffloc.maps.nerf.field import RadianceField
from diffloc.maps.nerf.renderer import render_image
from diffloc.maps.nerf.sampler import DensityGrid

__all__ = ["RadianceFieldMap"]


@dataclass(frozen=True, eq=False)
class RadianceFieldMap:
    """A radiance field rendered into RGB-D images.

    Attributes:
        field: the trained field.
        grid: its density grid.
        appearance: (A,) appearance code of the rendered images (the mean of the training
            codes by default, see :meth:`from_folder`).
        min_opacity: pixels of lower opacity are holes (depth 0).
        chunk: rays rendered per batch.

    Raises:
        ShapeError: an appearance code of the wrong length.
        ValueError: ``min_opacity`` outside (0, 1].
    """

    field: RadianceField
    grid: DensityGrid
    appearance: torch.Tensor
    min_opacity: float = 0.5
    chunk: int = 8192

    def __post_init__(self) -> None:
        check_shape(self.appearance, str(self.field.config.appearance_dim), "appearance")
        if not 0 < self.min_opacity <= 1:
            raise ValueError(f"min_opacity must be in (0, 1], got {self.min_opacity}")

    @classmethod
    def from_folder(cls, path: str | os.PathLike, min_opacity: float = 0.5) -> RadianceFieldMap:
        """The field exported to ``path`` (:func:`~diffloc.maps.nerf.export.export_field`),
        rendered with the mean of its training appearance codes."""
        field, grid = load_field(path)
        field.eval()
        code = field.appearance.weight.detach().mean(0)
        return cls(field, grid, code, min_opacity)

    def render(self, T_wc: torch.Tensor, camera: PinholeCamera) -> RGBD:
        """RGB-D images (B, 3, H, W) and (B, 1, H, W) seen from ``T_wc`` (B, 4, 4)."""
        check_shape(T_wc, "B,4,4", "T_wc")
        views = [
            render_image(self.field, self.grid, camera, pose, self.appearance, chunk=self.chunk)
            for pose in T_wc
        ]
        rgb = torch.stack([v["rgb"] for v in views]).clamp(0.0, 1.0)
        depth = torch.stack([v["depth"] * (v["opacity"] >= self.min_opacity) for v in views])
        return RGBD(rgb.float(), depth.float())
