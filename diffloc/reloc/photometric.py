"""Photometric consistency of a relocalised pose: the keyframe warped into the query.

A pose that matches the query to a *repeated* place (the neighbouring room, the other end of a
uniform facade) is backed by many consistent inliers, so inlier tests cannot refuse it; what
differs between the two places is everything the inliers do not cover (furniture, a tree, a
parked car). This check compares the whole overlap of the query with the keyframe the pose was
found from:

1. the surfel map is rendered at the keyframe (z-depth ``d(p_k)`` per pixel ``p_k``, the
   images scaled to ``width_px`` pixels wide, never up; once per keyframe, cached);
2. every keyframe pixel with depth is lifted to ``X = T_wk K_k^-1 [p_k, 1] d(p_k)`` and
   projected into the query at the pose, ``p = pi(K T_wc^-1 X)`` (same width);
3. a z-buffer of the warped points keeps, per query pixel, the nearest surface (within
   ``depth_tolerance``, relative): what the keyframe saw behind a nearer surface is hidden;
4. the keyframe's grey values ``k(p_k)`` and the query's ``q(p)`` (bilinear) are compared per
   cell of a ``cells x cells`` grid of the query image by the normalised cross-correlation

       NCC = sum (q - mean q)(k - mean k) / sqrt(sum (q - mean q)^2 sum (k - mean k)^2),

   over cells holding at least ``min_cell_pixels`` such pixels;
5. the score is the median NCC of those cells: NCC is invariant to a gain and offset per
   cell, so exposure and lighting changes between the runs matter little; a cell where the
   place differs (a tree instead of a statue) or the pose is wrong scores low.

Fewer than ``min_cells`` cells give NaN: the pose cannot be confirmed (no overlap with its
keyframe), which :class:`~diffloc.reloc.validation.PoseValidator` treats as a failed test.

Example:
    >>> PhotometricConfig().cells, PhotometricConfig().width_px
    (4, 160)

Usage::

    check = PhotometricCheck(surfel_map, db.T_wc, db.camera, keyframe_image)
    score = check.score(query_image, result.T_wc, camera, result.canonical)   # in [-1, 1]
    # a reference with depth of its own (an RGB-D database image): steps 2-5 alone
    score = warped_ncc(grey, depth, ref_camera, T_w_ref, query_image, camera, T_wc, config)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from diffloc.checks import check_finite, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import invert, transform_points
from diffloc.maps.surfel import SurfelMap
from diffloc.render.surfel_render import SurfelIndexRenderer

__all__ = ["PhotometricCheck", "PhotometricConfig", "cell_ncc", "grey_image", "warped_ncc"]


@dataclass(frozen=True)
class PhotometricConfig:
    """Settings of :class:`PhotometricCheck` (module docstring).

    Attributes:
        width_px: width of the compared images in pixels (a larger image is scaled down to
            it, keeping its aspect; a smaller one is compared as it is).
        cells: the image is split into ``cells x cells`` cells, each scored by NCC.
        min_cell_pixels: fewest compared pixels of a scored cell.
        min_cells: fewest scored cells of a score (fewer: NaN).
        depth_tolerance: largest relative difference between the keyframe's rendered depth and
            the warped point's depth of a pixel the keyframe saw.
    """

    width_px: int = 160
    cells: int = 4
    min_cell_pixels: int = 30
    min_cells: int = 3
    depth_tolerance: float = 0.05

    def __post_init__(self) -> None:
        for name in ("width_px", "cells", "min_cell_pixels", "min_cells"):
            if getattr(self, name) < 1:
                raise ValueError(f"photometric.{name} must be >= 1, got {getattr(self, name)}")
        if self.min_cells > self.cells**2:
            raise ValueError(
                f"photometric.min_cells ({self.min_cells}) exceeds the {self.cells**2} cells"
            )
        if not (math.isfinite(self.depth_tolerance) and self.depth_tolerance > 0):
            raise ValueError(f"photometric.depth_tolerance must be > 0, got {self.depth_tolerance}")


def _compared(camera: PinholeCamera, width_px: int) -> PinholeCamera:
    """``camera`` scaled down to ``width_px`` pixels wide (unchanged if it is not wider)."""
    return camera.scaled(width_px / camera.width) if camera.width > width_px else camera


def grey_image(image: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(H, W) float32 luma of a (3, H0, W0) image, area-resampled to (height, width)."""
    weights = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float32)
    grey = (image.to(torch.float32) * weights[:, None, None]).sum(0)
    return F.interpolate(grey[None, None], size=(height, width), mode="area")[0, 0]


def _bilinear(image: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """(N,) bilinear values of the (H, W) ``image`` at pixel coordinates ``uv`` (N, 2), pixel
    centres at integers."""
    height, width = image.shape
    scale = torch.tensor([2.0 / width, 2.0 / height], dtype=torch.float32)
    grid = (uv.to(torch.float32) + 0.5) * scale - 1.0
    out = F.grid_sample(image[None, None], grid[None, None], mode="bilinear", align_corners=False)
    return out[0, 0, 0]


def cell_ncc(
    a: torch.Tensor, b: torch.Tensor, cell: torch.Tensor, num_cells: int, min_pixels: int
) -> torch.Tensor:
    """Normalised cross-correlation of two signals per cell, all cells at once.

    Args:
        a: (N,) values of the first image at the compared pixels.
        b: (N,) values of the second image at the same pixels.
        cell: (N,) int64 cell of each pixel, in ``[0, num_cells)``.
        num_cells: number of cells.
        min_pixels: cells with fewer pixels get NaN.

    Returns:
        (num_cells,) float64 NCC per cell in [-1, 1]; NaN for cells with fewer than
        ``min_pixels`` pixels or no contrast in either image.

    Example:
        >>> a = torch.tensor([0.0, 1.0, 2.0, 0.0, 1.0, 5.0])
        >>> b = torch.tensor([1.0, 3.0, 5.0, 5.0, 1.0, 0.0])
        >>> cell_ncc(a, b, torch.tensor([0, 0, 0, 1, 1, 1]), 3, 2)
        tensor([ 1.0000, -0.7857,     nan], dtype=torch.float64)
    """
    a, b = a.double(), b.double()

    def per_cell(values: torch.Tensor) -> torch.Tensor:
        return torch.zeros(num_cells, dtype=torch.float64).index_add_(0, cell, values)

    n = per_cell(torch.ones_like(a))
    mean_a, mean_b = per_cell(a) / n, per_cell(b) / n
    da, db = a - mean_a[cell], b - mean_b[cell]
    denominator = (per_cell(da * da) * per_cell(db * db)).sqrt()
    ncc = per_cell(da * db) / denominator
    return torch.where((n >= min_pixels) & (denominator > 1e-12), ncc, math.nan)


class PhotometricCheck:
    """Scores relocalised poses by the photometric consistency of their keyframe
    (module docstring); keyframe images and depth renders are cached as they are used.

    Args:
        surfel_map: the map the database was built on.
        keyframe_poses: (K, 4, 4) camera-to-world poses of the database keyframes.
        keyframe_camera: the camera of keyframe ``k``.
        keyframe_image: the (3, H, W) float image of keyframe ``k`` in [0, 1].
        config: settings.
    """

    def __init__(
        self,
        surfel_map: SurfelMap,
        keyframe_poses: torch.Tensor,
        keyframe_camera: Callable[[int], PinholeCamera],
        keyframe_image: Callable[[int], torch.Tensor],
        config: PhotometricConfig | None = None,
    ) -> None:
        check_shape(keyframe_poses, "K,4,4", "keyframe_poses")
        self.config = config or PhotometricConfig()
        self.renderer = SurfelIndexRenderer(
            surfel_map.centers, surfel_map.normals, surfel_map.radii
        )
        self.keyframe_poses = keyframe_poses.to(torch.float64)
        self.keyframe_camera = keyframe_camera
        self.keyframe_image = keyframe_image
        self._keyframes: dict[int, tuple[PinholeCamera, torch.Tensor, torch.Tensor]] = {}

    def _keyframe(self, k: int) -> tuple[PinholeCamera, torch.Tensor, torch.Tensor]:
        """The scaled camera, grey image (H, W) and surfel depth (H, W) of keyframe ``k``
        (one render per keyframe: the query's pose needs no render of its own)."""
        if k not in self._keyframes:
            camera = _compared(self.keyframe_camera(k), self.config.width_px)
            depth = self.renderer.render(self.keyframe_poses[k][None].float(), camera).depth[0]
            grey = grey_image(self.keyframe_image(k), camera.height, camera.width)
            self._keyframes[k] = (camera.to(torch.float64), grey, depth)
        return self._keyframes[k]

    def score(
        self, image: torch.Tensor, T_wc: torch.Tensor, camera: PinholeCamera, keyframe: int
    ) -> float:
        """Median per-cell NCC between the query and keyframe ``keyframe`` warped to it
        (:func:`warped_ncc` of the keyframe's scaled grey image and surfel depth).

        Args:
            image: (3, H, W) query image in [0, 1].
            T_wc: (4, 4) the query's relocalised camera-to-world pose.
            camera: the query camera (batch shape ``()``).
            keyframe: the database keyframe the pose was found from.

        Returns:
            The score in [-1, 1], NaN with fewer than ``min_cells`` scored cells.

        Raises:
            ShapeError: an image that is not (3, H, W) or a pose that is not (4, 4).
            ValueError: a non-finite pose.
            IndexError: a keyframe the database does not hold.
        """
        if not 0 <= keyframe < len(self.keyframe_poses):
            raise IndexError(
                f"keyframe {keyframe} is not in the database of {len(self.keyframe_poses)}"
            )
        k_camera, k_grey, k_depth = self._keyframe(keyframe)
        return warped_ncc(
            k_grey,
            k_depth,
            k_camera,
            self.keyframe_poses[keyframe],
            image,
            camera,
            T_wc,
            self.config,
        )


def warped_ncc(
    reference_grey: torch.Tensor,
    reference_depth: torch.Tensor,
    reference_camera: PinholeCamera,
    T_w_reference: torch.Tensor,
    image: torch.Tensor,
    camera: PinholeCamera,
    T_wc: torch.Tensor,
    config: PhotometricConfig,
) -> float:
    """Median per-cell NCC between a query and a reference image with depth warped to it
    (module docstring, steps 2-5): the core of :meth:`PhotometricCheck.score`, and the whole
    test where the reference already has depth (a rendered or real-image RGB-D database).

    Every reference pixel is compared at its own resolution; the query is scaled down to
    ``config.width_px`` pixels wide.

    Args:
        reference_grey: (h, w) grey reference image.
        reference_depth: (h, w) its z-depth, 0 = none.
        reference_camera: the reference camera (batch shape ``()``, size w x h).
        T_w_reference: (4, 4) reference camera-to-world pose.
        image: (3, H, W) query image in [0, 1].
        camera: the query camera (batch shape ``()``).
        T_wc: (4, 4) the query's camera-to-world pose to test.
        config: settings.

    Returns:
        The score in [-1, 1], NaN with fewer than ``config.min_cells`` scored cells.

    Raises:
        ShapeError: a reference image or depth not of the reference camera's size, a query
            image that is not (3, H, W) or a pose that is not (4, 4).
        ValueError: a non-finite pose.
    """
    size = f"{reference_camera.height},{reference_camera.width}"
    check_shape(reference_grey, size, "reference_grey")
    check_shape(reference_depth, size, "reference_depth")
    check_shape(image, "3,H,W", "image")
    for name, T in (("T_w_reference", T_w_reference), ("T_wc", T_wc)):
        check_shape(T, "4,4", name)
        check_finite(T, name)
    cfg, k_camera = config, reference_camera.to(torch.float64)
    k_pixels = torch.nonzero(reference_depth > 0).flip(1)  # (N, 2) (u, v) with depth
    z_k = reference_depth[k_pixels[:, 1], k_pixels[:, 0]].double()
    points = transform_points(T_w_reference.double(), k_camera.unproject(k_pixels.double(), z_k))
    query_camera = _compared(camera, cfg.width_px).to(torch.float64)
    in_query = transform_points(invert(T_wc.double()), points)
    uv, in_front = query_camera.project(in_query)
    inside = torch.nonzero(in_front & query_camera.in_image(uv)).squeeze(1)
    uv, z_q, k_pixels = uv[inside], in_query[inside, 2], k_pixels[inside]
    # z-buffer of the warped points: only the nearest surface of a query pixel is seen
    height, width = query_camera.height, query_camera.width
    cols = uv[:, 0].round().long().clamp(0, width - 1)
    rows = uv[:, 1].round().long().clamp(0, height - 1)
    flat = rows * width + cols
    nearest = torch.full((height * width,), math.inf, dtype=torch.float64)
    nearest.scatter_reduce_(0, flat, z_q, "amin")
    seen = z_q <= nearest[flat] * (1 + cfg.depth_tolerance)
    uv, rows, cols, k_pixels = uv[seen], rows[seen], cols[seen], k_pixels[seen]
    cell = (rows * cfg.cells // height) * cfg.cells + cols * cfg.cells // width
    ncc = cell_ncc(
        _bilinear(grey_image(image, height, width), uv),
        reference_grey[k_pixels[:, 1], k_pixels[:, 0]],
        cell,
        cfg.cells**2,
        cfg.min_cell_pixels,
    )
    scored = ncc[~ncc.isnan()]
    if len(scored) < cfg.min_cells:
        return math.nan
    return float(scored.median())
