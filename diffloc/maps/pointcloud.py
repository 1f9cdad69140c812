"""Coloured point-cloud maps (seed 2, Sec. III-D1) and their colourisation from posed images.

A :class:`PointMap` is the map that seed 2 renders RGB-D database images from. A lidar or TLS
cloud gets its colours from posed camera images with :meth:`PointMap.colorize`: every point
takes the colour of the pixel it projects to in the *nearest* view that sees it, where

- it projects inside the image and lies in front of the camera,
- the view's depth image has a measurement at that pixel (depth 0 means none) that agrees
  with the point's camera-frame z within ``occlusion_tolerance_m`` (so the point is neither
  occluded nor floating in front of the observed surface),
- if point normals are given, the angle between the normal and the direction to the camera
  is at most ``max_view_angle_rad``.

"Nearest" is the smallest camera distance, or with normals the smallest
``distance / |cos(view angle)|``: proportional to the length a pixel covers on the surface, so
the view that samples the surface most finely wins. The colour is that of the nearest pixel
(no interpolation, so no colour bleeds across depth edges), the same pixel the depth test used.

Points seen by no view are **dropped**: a made-up colour (grey, or a neighbour's) would put
appearance into rendered database images that no camera observed, and seed 2 matches features
on those images. ``colorize`` returns the kept points with the mask of kept input points, so
callers can keep other per-point data aligned.

This module renders nothing: the depth images come from the caller (the simulator's depth, a
depth camera, or a render of another map).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import torch

from diffloc.checks import ShapeError, check_finite, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import invert, transform_points
from diffloc.io.ply import read_point_cloud, write_point_cloud
from diffloc.maps._storage import (
    colors_from_ply,
    exact_color_columns,
    map_suffix,
    naming_file,
    read_npz,
    write_npz,
)
from diffloc.maps._tensors import PerPointFields, as_float32, check_in_range, check_unit_vectors
from diffloc.progress import progress

__all__ = ["POINT_MAP_FORMAT_VERSION", "ColorizeConfig", "PointMap"]

POINT_MAP_FORMAT_VERSION = 1
"""``format_version`` of point-map ``.npz`` files."""

_KIND = "diffloc-point-map"


@dataclass
class ColorizeConfig:
    """Parameters of :meth:`PointMap.colorize`.

    Attributes:
        occlusion_tolerance_m: largest ``|z_point - depth(pixel)|`` (metres) at which a point
            counts as the surface seen at its pixel.
        max_view_angle_rad: with normals, views seeing the surface more obliquely than this
            (angle between normal and direction to the camera, normal sign ignored) are not
            used; in ``(0, pi/2]``.
        max_pairs_per_chunk: views are processed in chunks of
            ``max(1, max_pairs_per_chunk // N)`` so that about this many point-view pairs
            (roughly 100 bytes each: the default peaks near 200 MB) are in memory at once.
    """

    occlusion_tolerance_m: float = 0.05
    max_view_angle_rad: float = math.radians(80.0)
    max_pairs_per_chunk: int = 2**21

    def __post_init__(self) -> None:
        if not 0 < self.occlusion_tolerance_m < math.inf:
            raise ValueError(
                f"occlusion_tolerance_m must be positive, got {self.occlusion_tolerance_m!r}"
            )
        if not 0 < self.max_view_angle_rad <= math.pi / 2:
            raise ValueError(
                f"max_view_angle_rad must be in (0, pi/2], got {self.max_view_angle_rad!r}"
            )
        if isinstance(self.max_pairs_per_chunk, bool) or not (
            isinstance(self.max_pairs_per_chunk, int) and self.max_pairs_per_chunk > 0
        ):
            raise ValueError(
                f"max_pairs_per_chunk must be a positive integer, got {self.max_pairs_per_chunk!r}"
            )


@dataclass(frozen=True, eq=False)
class PointMap(PerPointFields):
    """A coloured point cloud of N points; all tensors on one device.

    Attributes:
        positions: (N, 3) float32 points, world frame, metres.
        colors: (N, 3) float32 RGB in [0, 1].
        normals: (N, 3) float32 unit normals, or ``None``.

    Floating tensors or numpy arrays are accepted and stored as float32 tensors.

    Raises:
        ShapeError: a field of the wrong shape.
        TypeError: a field that is not a floating tensor or array.
        ValueError: NaN/inf values, colours outside [0, 1], non-unit normals, or fields on
            different devices.

    Example:
        >>> cloud = PointMap(torch.zeros(2, 3), torch.full((2, 3), 0.5))
        >>> len(cloud)
        2
    """

    positions: torch.Tensor
    colors: torch.Tensor
    normals: torch.Tensor | None = None

    def __post_init__(self) -> None:
        positions = as_float32(self.positions, "N,3", "positions")
        n = positions.shape[0]
        colors = as_float32(self.colors, f"{n},3", "colors")
        check_in_range(colors, 0.0, 1.0, "colors")
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "colors", colors)
        if self.normals is not None:
            normals = as_float32(self.normals, f"{n},3", "normals")
            check_unit_vectors(normals, "normals")
            object.__setattr__(self, "normals", normals)
        self._check_same_device()

    # ------------------------------------------------------------------ colourisation

    @classmethod
    def colorize(
        cls,
        points: torch.Tensor,
        images: torch.Tensor,
        T_wc: torch.Tensor,
        camera: PinholeCamera,
        depths: torch.Tensor,
        config: ColorizeConfig | None = None,
        normals: torch.Tensor | None = None,
        show_progress: bool = False,
    ) -> tuple[PointMap, torch.Tensor]:
        """Colour points from the nearest posed image that sees them (module docstring).

        Vectorised over points; views are processed in chunks with a running best score per
        point, so memory is bounded by ``config.max_pairs_per_chunk`` plus O(N).

        Args:
            points: (N, 3) points, world frame, metres.
            images: (V, 3, H, W) float RGB in [0, 1].
            T_wc: (V, 4, 4) camera-to-world poses of the images.
            camera: intrinsics of size W x H, one camera (batch shape ``()``) or one per view
                (batch shape ``(V,)``). Computation runs in float32 on the points' device.
            depths: (V, 1, H, W) z-depth in metres along the optical axis, 0 = no measurement.
            config: tolerances and chunk size (default: :class:`ColorizeConfig`).
            normals: optional (N, 3) unit normals (sign ignored): weight views by viewing
                angle, and keep them in the returned map.
            show_progress: show a progress bar over view chunks (quiet in CI).

        Returns:
            ``(point_map, seen)``: the map of the K points seen by at least one view, in input
            order, and the (N,) bool mask of those points (points seen by no view are
            dropped).

        Raises:
            ShapeError: inputs of the wrong shapes, or images not matching the camera size.
            ValueError: NaN/inf inputs, images outside [0, 1], negative depths.

        Example:
            >>> from diffloc.geometry.camera import PinholeCamera
            >>> camera = PinholeCamera.from_fov(16, 12, 1.2)
            >>> points = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [0.0, 0.0, -2.0]])
            >>> images = torch.tensor([0.2, 0.4, 0.6]).view(1, 3, 1, 1).expand(1, 3, 12, 16)
            >>> depths = torch.full((1, 1, 12, 16), 2.0)  # one view of a wall 2 m ahead
            >>> cloud, seen = PointMap.colorize(points, images, torch.eye(4)[None], camera, depths)
            >>> seen, cloud.colors  # the point behind the wall and the one behind the camera
            (tensor([ True, False, False]), tensor([[0.2000, 0.4000, 0.6000]]))
        """
        config = ColorizeConfig() if config is None else config
        points = as_float32(points, "N,3", "points")
        if normals is not None:
            normals = as_float32(normals, f"{points.shape[0]},3", "normals").to(points.device)
            check_unit_vectors(normals, "normals")
        views = _Views.checked(images, T_wc, camera, depths, points.device)
        best_color, best_score = _colorize(points, normals, views, config, show_progress)
        seen = torch.isfinite(best_score)
        point_map = cls(
            positions=points[seen],
            colors=best_color[seen],
            normals=None if normals is None else normals[seen],
        )
        return point_map, seen

    # ------------------------------------------------------------------ persistence

    def save(self, path: str | os.PathLike) -> None:
        """Write to ``.ply`` (:meth:`save_ply`) or ``.npz`` (:meth:`save_npz`) by suffix."""
        {".ply": self.save_ply, ".npz": self.save_npz}[map_suffix(path)](path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> PointMap:
        """Read a ``.ply`` (:meth:`load_ply`) or ``.npz`` (:meth:`load_npz`) file by suffix."""
        return {".ply": cls.load_ply, ".npz": cls.load_npz}[map_suffix(path)](path)

    def save_ply(self, path: str | os.PathLike) -> None:
        """Write a binary PLY file atomically.

        Vertex properties: float ``x y z``, float ``nx ny nz`` when there are normals, ``uchar
        red green blue`` (for viewers) and float ``red_f32 green_f32 blue_f32`` (exact).

        Args:
            path: the ``.ply`` file.
        """
        extra = exact_color_columns(self.colors)
        write_point_cloud(path, self.positions, self.normals, self.colors, extra=extra)

    @classmethod
    def load_ply(cls, path: str | os.PathLike) -> PointMap:
        """Read a coloured PLY point cloud (e.g. a TLS export or a file from :meth:`save_ply`).

        Colours come from ``red_f32 green_f32 blue_f32`` when present, else from ``red green
        blue`` (integers divided by their maximum). Other vertex properties are ignored.

        Args:
            path: the ``.ply`` file.

        Returns:
            The point map (CPU tensors).

        Raises:
            FileNotFoundError: the file does not exist.
            ValueError: a malformed PLY, no colours, or invalid values; the message names the
                file.
        """
        cloud = read_point_cloud(path)
        colors = colors_from_ply(cloud)
        if colors is None:
            raise ValueError(f"{path}: a point map PLY needs red, green, blue properties")
        with naming_file(path, "point map"):
            return cls(positions=cloud.points, colors=colors, normals=cloud.normals)

    def save_npz(self, path: str | os.PathLike) -> None:
        """Write an uncompressed ``.npz`` (with ``format_version`` and ``kind``) atomically.

        Args:
            path: the ``.npz`` file.
        """
        write_npz(path, _KIND, POINT_MAP_FORMAT_VERSION, self._tensors())

    @classmethod
    def load_npz(cls, path: str | os.PathLike) -> PointMap:
        """Read a file written by :meth:`save_npz` (``allow_pickle=False``).

        Args:
            path: the ``.npz`` file.

        Returns:
            The point map (CPU tensors).

        Raises:
            FileNotFoundError: the file does not exist.
            ValueError: a corrupt or truncated archive, another kind or format version,
                missing/unknown entries, or invalid values; the message names the file.
        """
        arrays = read_npz(
            path,
            _KIND,
            POINT_MAP_FORMAT_VERSION,
            required=("positions", "colors"),
            optional=("normals",),
        )
        with naming_file(path, "point map"):
            return cls(**arrays)


@dataclass(frozen=True)
class _Views:
    """Validated posed RGB-D views, float32 on the points' device."""

    images: torch.Tensor  # (V, 3, H, W)
    depths: torch.Tensor  # (V, 1, H, W)
    T_cw: torch.Tensor  # (V, 4, 4) world-to-camera
    centers: torch.Tensor  # (V, 3) camera centres, world frame
    camera: PinholeCamera

    @classmethod
    def checked(
        cls,
        images: torch.Tensor,
        T_wc: torch.Tensor,
        camera: PinholeCamera,
        depths: torch.Tensor,
        device: torch.device,
    ) -> _Views:
        check_shape(images, "V,3,H,W", "images")
        v, _, h, w = images.shape
        check_shape(T_wc, f"{v},4,4", "T_wc (one pose per image)")
        check_shape(depths, f"{v},1,{h},{w}", "depths (one per image, same size)")
        if (camera.width, camera.height) != (w, h):
            raise ShapeError(f"images are {w}x{h} but the camera is {camera.width}x{camera.height}")
        if camera.batch_shape not in (torch.Size(()), torch.Size((v,))):
            raise ShapeError(
                f"camera must be one camera or one per view (batch shape (), ({v},)), got "
                f"{tuple(camera.batch_shape)}"
            )
        if not (images.is_floating_point() and depths.is_floating_point()):
            raise TypeError(
                f"images and depths must be floating point, got {images.dtype}, {depths.dtype}"
            )
        for tensor, name in ((images, "images"), (T_wc, "T_wc"), (depths, "depths")):
            check_finite(tensor, name)
        check_in_range(images, 0.0, 1.0, "images")
        check_in_range(depths, 0.0, math.inf, "depths")
        T_wc = T_wc.to(device=device, dtype=torch.float64)
        return cls(
            images=images.to(device=device, dtype=torch.float32),
            depths=depths.to(device=device, dtype=torch.float32),
            T_cw=invert(T_wc).to(torch.float32),
            centers=T_wc[:, :3, 3].to(torch.float32),
            camera=camera.to(device=device, dtype=torch.float32),
        )

    def __len__(self) -> int:
        return int(self.images.shape[0])

    def chunk(self, start: int, stop: int) -> _Views:
        camera = self.camera if self.camera.batch_shape == () else self.camera[start:stop]
        return _Views(
            images=self.images[start:stop],
            depths=self.depths[start:stop],
            T_cw=self.T_cw[start:stop],
            centers=self.centers[start:stop],
            camera=camera,
        )


def _colorize(
    points: torch.Tensor,
    normals: torch.Tensor | None,
    views: _Views,
    config: ColorizeConfig,
    show_progress: bool,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Best colour (N, 3) (NaN where unseen) and its score (N,) (inf where unseen)."""
    n = points.shape[0]
    best_score = torch.full((n,), math.inf, dtype=torch.float32, device=points.device)
    best_color = torch.full((n, 3), math.nan, dtype=torch.float32, device=points.device)
    step = max(1, config.max_pairs_per_chunk // max(n, 1))
    starts = range(0, len(views), step)
    for start in progress(starts, "colourising points", show_progress, total=len(starts)):
        chunk = views.chunk(start, start + step)
        score, pixel = _view_scores(points, normals, chunk, config)  # (C, N) each
        chunk_score, chunk_view = score.min(dim=0)
        better = chunk_score < best_score
        best_score = torch.where(better, chunk_score, best_score)
        color = _pixel_colors(chunk.images, chunk_view, pixel.gather(0, chunk_view[None])[0])
        best_color = torch.where(better[:, None], color, best_color)
    return best_color, best_score


def _view_scores(
    points: torch.Tensor, normals: torch.Tensor | None, views: _Views, config: ColorizeConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """Score of every (view, point) pair, inf where not visible, and the flat pixel index.

    Args:
        points: (N, 3) world points.
        normals: (N, 3) unit normals or ``None``.
        views: C views.
        config: tolerances.

    Returns:
        ``(score, pixel)``: (C, N) float32 camera distance (divided by ``|cos|`` of the view
        angle with normals) and (C, N) int64 index ``v * W + u`` of the nearest pixel.
    """
    height, width = views.depths.shape[-2:]
    points_cam = transform_points(views.T_cw, points)  # (C, N, 3)
    uv, in_front = views.camera.project(points_cam)
    visible = in_front & views.camera.in_image(uv)
    u = torch.round(uv[..., 0]).long().clamp(0, width - 1)
    v = torch.round(uv[..., 1]).long().clamp(0, height - 1)
    pixel = v * width + u
    depth = views.depths.reshape(len(views), -1).gather(1, pixel)
    visible &= (depth > 0) & ((points_cam[..., 2] - depth).abs() <= config.occlusion_tolerance_m)
    score = torch.linalg.vector_norm(points_cam, dim=-1)
    if normals is not None:
        to_camera = views.centers[:, None, :] - points[None]  # (C, N, 3)
        cos = (to_camera * normals[None]).sum(-1).abs() / score.clamp_min(1e-12)
        visible &= cos >= math.cos(config.max_view_angle_rad)
        score = score / cos.clamp_min(1e-12)
    return torch.where(visible, score, torch.full_like(score, math.inf)), pixel


def _pixel_colors(images: torch.Tensor, view: torch.Tensor, pixel: torch.Tensor) -> torch.Tensor:
    """(N, 3) colours of pixel ``pixel[i]`` (flat index) in image ``view[i]`` of (C, 3, H, W)."""
    c, channels, height, width = images.shape
    flat = images.permute(1, 0, 2, 3).reshape(channels, c * height * width)
    return flat[:, view * (height * width) + pixel].T
