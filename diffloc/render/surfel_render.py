"""Hard surfel splatting: the global surfel index map of seed 1 Sec. III-A.

:func:`render_surfel_index` (and :class:`SurfelIndexRenderer`, for many renders of one map)
draws oriented disks and returns, per pixel, the nearest surfel's index, the exact depth of
the ray-disk hit and the surfel normal. Surfels are first culled against the view frustum with
their bounding spheres (:mod:`~diffloc.render.surfel_cull`) and the survivors numbered in map
order; each gets a candidate window of pixels (:mod:`~diffloc.render.surfel_windows`) where
its ray-disk conic (:mod:`~diffloc.render.surfel_conics`) is evaluated with small matrix
products into a z-buffer of inverse-depth keys (:mod:`~diffloc.render.surfel_raster`). A
render of a pixel subset (:mod:`~diffloc.render.pixel_mask`) draws only the cells and surfels
that reach a pixel to render. Camera and bad-input rules: :mod:`~diffloc.render.view`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch

from diffloc.checks import ShapeError, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.render.pixel_mask import _box_touches, _summed_area
from diffloc.render.surfel_cull import _disk_extents, _frustum_candidates, _SurfelCells
from diffloc.render.surfel_raster import _rasterise_surfels, _resolve_surfel_keys
from diffloc.render.surfel_windows import _surfel_windows, _SurfelCandidates
from diffloc.render.view import (
    _check_camera,
    _check_map_size,
    _check_poses,
    _rigid_columns,
    _View,
    _views,
)
from diffloc.render.zbuffer import _MAX_SURFELS, _NO_KEY

__all__ = ["SurfelIndexRenderer", "SurfelRender", "render_surfel_index"]


_SURFEL_CHUNK = 1 << 16
"""Surfels per chunk of the box test of masked renders (temporaries stay in the CPU caches)."""
_PROBE_DIRECTION = (1.0, 0.7548776662466927, 0.5698402909980532)
"""A direction orthogonal to no simple normal (powers of the inverse plastic number)."""


@dataclass(frozen=True)
class SurfelRender:
    """Surfel index map of a batch of cameras.

    Attributes:
        ids: (B, H, W) int64 index of the visible surfel, -1 where none.
        depth: (B, H, W) float32 z-depth (metres) of the ray-disk hit, 0 where none.
        normals: (B, 3, H, W) float32 unit normal of the visible surfel in the *camera* frame
            (as stored in the map, not flipped towards the camera), 0 where none.
    """

    ids: torch.Tensor
    depth: torch.Tensor
    normals: torch.Tensor

    @property
    def mask(self) -> torch.Tensor:
        """(B, H, W) bool, true where a surfel is visible."""
        return self.ids >= 0


def _check_surfels(centers: torch.Tensor, normals: torch.Tensor, radii: torch.Tensor) -> None:
    check_shape(centers, "N,3", "centers")
    check_shape(normals, "N,3", "normals")
    check_shape(radii, "N", "radii")
    n = centers.shape[0]
    if normals.shape[0] != n or radii.shape[0] != n:
        raise ShapeError(
            f"centers, normals and radii must have the same length N, got "
            f"{n}, {normals.shape[0]} and {radii.shape[0]}"
        )
    _check_map_size(n, "surfels", _MAX_SURFELS)
    if n == 0:
        return
    # One reduction each decides the common case; the exact (slower) tests run only when it
    # is inconclusive: a NaN entry or a real violation.
    if not bool(radii.min() > 0) and bool((radii <= 0).any()):
        raise ValueError("surfel radii must be positive")
    if normals.dtype in (torch.float32, torch.float64):
        # A zero row has a zero projection on any direction; a non-zero one almost never does.
        direction = torch.tensor(_PROBE_DIRECTION, dtype=normals.dtype, device=normals.device)
        if bool(torch.mv(normals, direction).abs_().min() > 0):
            return
    if bool((normals == 0).all(-1).any()):
        raise ValueError("surfel normals must be non-zero")


class SurfelIndexRenderer:
    """Renders the global surfel index map (seed 1 Sec. III-A) of one surfel map, view by view.

    For many renders of the same map: the map is validated and converted once and, with
    ``cell_size_m``, its surfels are grouped into cubic cells whose bounding spheres are culled
    against each view's frustum first, so only the surfels of the cells that the frustum cuts
    are tested one by one. Renders are bit for bit those of :func:`render_surfel_index` (the
    cells change the work, not the candidate set). The map tensors must not change afterwards.

    Args:
        centers: (N, 3) surfel centres, world frame (metres).
        normals: (N, 3) surfel normals, world frame (any non-zero length).
        radii: (N,) disk radii in metres (> 0).
        cell_size_m: edge of the culling cells in metres, or ``None`` to test every surfel.

    Raises:
        ShapeError: wrong shapes.
        ValueError: radii ``<= 0``, zero normals, a non-positive cell size.

    Example:
        >>> renderer = SurfelIndexRenderer(
        ...     torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[0.0, 0.0, -1.0]]),
        ...     torch.tensor([0.1]))
        >>> out = renderer.render(torch.eye(4)[None], PinholeCamera.from_fov(64, 48, 1.0))
        >>> int(out.ids[0, 24, 32]), float(out.depth[0, 24, 32])
        (0, 2.0)
    """

    def __init__(
        self,
        centers: torch.Tensor,
        normals: torch.Tensor,
        radii: torch.Tensor,
        *,
        cell_size_m: float | None = 0.25,
    ) -> None:
        _check_surfels(centers, normals, radii)
        if cell_size_m is not None and not (math.isfinite(cell_size_m) and cell_size_m > 0):
            raise ValueError(f"cell_size_m must be positive, got {cell_size_m!r}")
        self.centers = centers.to(torch.float32)
        self.normals = normals.to(torch.float32)
        self.radii = radii.to(torch.float32)
        self.cells = (
            None
            if cell_size_m is None
            else _SurfelCells.build(self.centers, self.normals, self.radii, cell_size_m)
        )

    def __len__(self) -> int:
        return self.centers.shape[0]

    @functools.cached_property
    def _extents(self) -> torch.Tensor:
        """(N, 3) half-extents of the disks' boxes (:func:`_disk_extents`), for masked renders
        without cells (made at the first)."""
        return _disk_extents(self.normals, self.radii)

    def _candidates(
        self, view: _View, height: int, width: int, pixel_sums: torch.Tensor | None
    ) -> _SurfelCandidates:
        """The surfels that may be visible in ``view``, in the camera frame.

        With ``pixel_sums`` (see :func:`_summed_area`), only those that may be seen at a pixel
        to render: the cells, then the surfels, whose axis-aligned boxes (world-frame boxes
        rotated into the camera frame) reach one (:func:`_box_touches`). Every transform is
        elementwise (:func:`_rigid_columns`), so a surfel is drawn alike in any subset.
        """
        if self.cells is None:
            positions = _frustum_candidates(self.centers, self.radii, view, height, width)
            ids, data = positions, (self.centers, self.normals, self.radii)
        else:
            positions = self.cells.cull(view, height, width, pixel_sums)
            ids = self.cells.ids.index_select(0, positions)
            data = (self.cells.centers, self.cells.normals, self.cells.radii)
        centers, normals, radii = data
        c = view.to_camera(centers.index_select(0, positions).T, elementwise=True)
        if pixel_sums is not None:
            extents = self._extents if self.cells is None else self.cells.extents
            e = view.R_cw.abs() @ extents.index_select(0, positions).T
            touches = [ids.new_zeros(0, dtype=torch.bool)]  # (no surfels at all)
            for start in range(0, ids.shape[0], _SURFEL_CHUNK):
                chunk = slice(start, start + _SURFEL_CHUNK)
                touches.append(_box_touches(c[:, chunk], e[:, chunk], view, pixel_sums))
            keep = torch.cat(touches).nonzero().view(-1)
            positions, ids, c = positions[keep], ids[keep], c.index_select(1, keep)
        n = _rigid_columns(view.R_cw, normals.index_select(0, positions).T)
        n = n / (n * n).sum(0).sqrt_()
        return _SurfelCandidates(ids, c, n, radii.index_select(0, positions))

    @torch.no_grad()
    def render(
        self,
        T_wc: torch.Tensor,
        camera: PinholeCamera,
        *,
        cull_backfaces: bool = False,
        pixels: torch.Tensor | None = None,
    ) -> SurfelRender:
        """Render the map from a batch of poses; see :func:`render_surfel_index`.

        Args:
            T_wc: (B, 4, 4) camera-to-world poses.
            camera: one ideal pinhole camera or a batch of ``B`` (same image size).
            cull_backfaces: also drop surfels whose normal points away from the camera.
            pixels: (B, H, W) bool, the pixels to render, or ``None`` for all.

        Returns:
            A :class:`SurfelRender` with ids (B, H, W), depth (B, H, W), normals (B, 3, H, W).
        """
        batch = _check_poses(T_wc)
        camera = _check_camera(camera, batch)
        if camera.distortion is not None:
            raise ValueError(
                "render_surfel_index needs an ideal pinhole camera (distortion=None); undistort "
                "the images and keypoints first (PinholeCamera.undistort_points)"
            )
        height, width = camera.height, camera.width
        if pixels is not None:
            check_shape(pixels, f"{batch},{height},{width}", "pixels")
            if pixels.dtype != torch.bool:
                raise ValueError(f"pixels must be a bool mask, got {pixels.dtype}")
        device = self.centers.device
        ids = torch.empty((batch, height * width), dtype=torch.int64, device=device)
        depth = torch.empty((batch, height * width), dtype=torch.float32, device=device)
        normals_cam = torch.empty((batch, 3, height * width), dtype=torch.float32, device=device)
        for b, view in enumerate(_views(T_wc, camera)):
            sums = None if pixels is None else _summed_area(pixels[b])
            surfels = self._candidates(view, height, width, sums)
            windows = _surfel_windows(surfels, view, height, width, cull_backfaces, sums)
            rows, stride = windows.buffer_rows, windows.stride
            keys = torch.full((rows * stride,), _NO_KEY, dtype=torch.int64, device=device)
            _rasterise_surfels(windows, keys)
            if pixels is None:
                if (rows, stride) != (height, width):  # drop the padding
                    keys = keys.view(rows, stride)[:height, :width].reshape(-1)
                _resolve_surfel_keys(keys, surfels, len(self), ids[b], depth[b], normals_cam[b])
                continue
            # The other pixels saw only some of their surfels: -1, 0, 0 there.
            index = torch.nonzero(pixels[b].reshape(-1)).view(-1)
            found_ids, found_depth = ids.new_empty(len(index)), depth.new_empty(len(index))
            found_normals = normals_cam.new_empty(3, len(index))
            keys = keys.index_select(0, index + index // width * (stride - width))
            _resolve_surfel_keys(keys, surfels, len(self), found_ids, found_depth, found_normals)
            ids[b].fill_(-1).index_copy_(0, index, found_ids)
            depth[b].zero_().index_copy_(0, index, found_depth)
            normals_cam[b].zero_().index_copy_(1, index, found_normals)
        return SurfelRender(
            ids.view(batch, height, width),
            depth.view(batch, height, width),
            normals_cam.view(batch, 3, height, width),
        )


def render_surfel_index(
    centers: torch.Tensor,
    normals: torch.Tensor,
    radii: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    *,
    cull_backfaces: bool = False,
    pixels: torch.Tensor | None = None,
) -> SurfelRender:
    """Render the global surfel index map (seed 1 Sec. III-A) of oriented disks.

    A pixel shows the nearest surfel whose disk the ray through the pixel centre hits; its
    depth is the exact z-depth of that hit. Disks are two-sided unless ``cull_backfaces``.

    With ``pixels``, only the surfels whose candidate window holds one of those pixels are
    drawn (each surfel's window is the one it has in the full render, so every surfel that
    covers such a pixel is drawn): ids, depths and normals at those pixels are bit for bit
    those of the full render, and -1, 0, 0 at the other pixels. Use it when only a few
    regions are read (e.g. the keypoint disks of
    :func:`diffloc.database.neighbours.neighbour_surfels`).

    Args:
        centers: (N, 3) surfel centres, world frame (metres).
        normals: (N, 3) surfel normals, world frame (any non-zero length; normalised here).
        radii: (N,) disk radii in metres (> 0).
        T_wc: (B, 4, 4) camera-to-world poses.
        camera: one ideal pinhole camera or a batch of ``B`` (same image size).
        cull_backfaces: also drop surfels whose normal points away from the camera.
        pixels: (B, H, W) bool, the pixels to render, or ``None`` for all.

    Returns:
        A :class:`SurfelRender` with ids (B, H, W), depth (B, H, W), normals (B, 3, H, W).

    Raises:
        ShapeError: wrong shapes, ``B = 0`` or a camera batch that does not match ``T_wc``,
            ``pixels`` not (B, H, W).
        ValueError: non-finite poses, radii ``<= 0``, zero normals, a distorted camera, a
            ``pixels`` mask that is not bool.

    Example:
        >>> cam = PinholeCamera.from_fov(64, 48, 1.0)
        >>> out = render_surfel_index(
        ...     torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[0.0, 0.0, -1.0]]),
        ...     torch.tensor([0.1]), torch.eye(4)[None], cam)
        >>> int(out.ids[0, 24, 32]), float(out.depth[0, 24, 32])
        (0, 2.0)
    """
    _check_poses(T_wc)
    renderer = SurfelIndexRenderer(centers, normals, radii, cell_size_m=None)
    return renderer.render(T_wc, camera, cull_backfaces=cull_backfaces, pixels=pixels)
