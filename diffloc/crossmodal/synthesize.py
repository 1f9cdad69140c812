"""Maps that render RGB-D images at a pose: one interface for point clouds, meshes, ...

Seed 2 (Sec. III-D) synthesises a database of RGB-D images from a map that has no images of
its own. Every map type implements :class:`RGBDMap`: ``render(T_wc, camera)`` returns an
:class:`RGBD` batch, colours in [0, 1] and z-depth in metres with 0 where the map shows
nothing (a *hole*). The database builder (:mod:`diffloc.crossmodal.database`) and the
localiser only see this interface, so a radiance field plugs in by implementing it too.

- :class:`PointCloudMap`: a coloured point cloud drawn as square splats
  (:func:`~diffloc.render.point_render.render_points`), with the inverse-depth sizes of seed 2
  Eq. 2 either per point (``PointSizes.inverse_depth``, every point its own rounded size, as
  a single OpenGL pass cannot do) or snapped to a few sizes rendered in passes and merged by
  nearest depth (``PointSizes.multi_pass``, seed 2 Fig. 5).
- :class:`MeshMap`: a textured triangle mesh, ray cast
  (:class:`~diffloc.render.raycast.MeshRenderer`); the colour is the texture albedo.

Example:
    One red point 2 m in front of two cameras, drawn 3 px wide (Eq. 2: 6 px at 1 m):

    >>> import torch
    >>> from diffloc.geometry.camera import PinholeCamera
    >>> from diffloc.render.point_sizes import PointSizes
    >>> cloud = PointCloudMap(
    ...     torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0.0, 0.0]]),
    ...     PointSizes.inverse_depth(1.0, 6.0))
    >>> camera = PinholeCamera(fx=10.0, fy=10.0, cx=4.0, cy=4.0, width=9, height=9)
    >>> views = render_views(cloud, torch.eye(4).expand(2, 4, 4), camera)
    >>> views.rgb.shape, float(views.depth.max()), hole_fraction(views.depth)
    (torch.Size([2, 3, 9, 9]), 2.0, tensor([0.8889, 0.8889]))
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch

from diffloc.checks import ShapeError, check_finite, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.textured_mesh import TexturedMesh
from diffloc.progress import progress
from diffloc.render.point_render import render_points
from diffloc.render.point_sizes import PointSizes
from diffloc.render.raycast import MeshRenderer
from diffloc.render.screen_space import ScreenSpaceVisibility

__all__ = [
    "RGBD",
    "MeshMap",
    "PointCloudMap",
    "RGBDMap",
    "hole_fraction",
    "render_views",
]


@dataclass(frozen=True, eq=False)
class RGBD:
    """A batch of RGB-D images.

    Attributes:
        rgb: (B, 3, H, W) float32 colours in [0, 1].
        depth: (B, 1, H, W) float32 z-depth in metres, 0 where there is no measurement.
    """

    rgb: torch.Tensor
    depth: torch.Tensor

    def __post_init__(self) -> None:
        check_shape(self.rgb, "B,3,H,W", "rgb")
        b, _, h, w = self.rgb.shape
        check_shape(self.depth, f"{b},1,{h},{w}", "depth")

    def __len__(self) -> int:
        return int(self.rgb.shape[0])


class RGBDMap(Protocol):
    """A map that renders RGB-D images at camera poses."""

    def render(self, T_wc: torch.Tensor, camera: PinholeCamera) -> RGBD:
        """RGB-D images (B, 3, H, W) and (B, 1, H, W) seen from ``T_wc`` (B, 4, 4)."""


@dataclass(frozen=True, eq=False)
class PointCloudMap:
    """A coloured point cloud rendered as square splats of Eq. 2 sizes.

    Attributes:
        points: (N, 3) float32 world points, metres.
        colors: (N, 3) float32 RGB in [0, 1].
        sizes: splat sizes in pixels: ``PointSizes.inverse_depth(rho_min, rho_max)`` (Eq. 2
            per point) or ``PointSizes.multi_pass(rho_min, rho_max, levels)`` (a few passes
            merged by nearest depth); sizes are for the camera it is rendered with.
        visibility: optional screen-space visibility filter
            (:mod:`~diffloc.render.screen_space`): pixels that nearer splats enclose take
            their point (see-through gaps and small holes closed).

    Raises:
        ShapeError: wrong shapes.
        ValueError: an empty cloud, NaN/inf values or colours outside [0, 1].
    """

    points: torch.Tensor
    colors: torch.Tensor
    sizes: PointSizes
    visibility: ScreenSpaceVisibility | None = None

    def __post_init__(self) -> None:
        check_shape(self.points, "N,3", "points")
        check_shape(self.colors, f"{self.points.shape[0]},3", "colors")
        if self.points.shape[0] == 0:
            raise ValueError("the point cloud is empty: there is nothing to render")
        check_finite(self.points, "points")
        check_finite(self.colors, "colors")
        if bool((self.colors < 0).any() or (self.colors > 1).any()):
            raise ValueError("colors must lie in [0, 1]")
        object.__setattr__(self, "points", self.points.to(torch.float32))
        object.__setattr__(self, "colors", self.colors.to(torch.float32))

    def render(self, T_wc: torch.Tensor, camera: PinholeCamera) -> RGBD:
        """Splat the cloud into ``B`` cameras.

        Args:
            T_wc: (B, 4, 4) camera-to-world poses.
            camera: one camera of size W x H.

        Returns:
            :class:`RGBD` with rgb (B, 3, H, W) and depth (B, 1, H, W).
        """
        out = render_points(self.points, self.colors, T_wc, camera, self.sizes, self.visibility)
        return RGBD(out.rgb, out.depth)


class MeshMap:
    """A textured triangle mesh rendered by ray casting; colour = texture albedo.

    Args:
        mesh: the mesh (at least one triangle).

    Raises:
        ValueError: a mesh without triangles.
    """

    def __init__(self, mesh: TexturedMesh) -> None:
        self.renderer = MeshRenderer(mesh)

    def render(self, T_wc: torch.Tensor, camera: PinholeCamera) -> RGBD:
        """Ray cast ``B`` cameras.

        Args:
            T_wc: (B, 4, 4) camera-to-world poses.
            camera: one camera of size W x H.

        Returns:
            :class:`RGBD` with rgb (B, 3, H, W) and depth (B, 1, H, W).
        """
        check_shape(T_wc, "B,4,4", "T_wc")
        if T_wc.shape[0] == 0:
            raise ShapeError("T_wc must hold at least one pose, got shape (0, 4, 4)")
        albedo, depth = self.renderer.render_rgbd(T_wc, camera)
        return RGBD(albedo.clamp_(0.0, 1.0), depth)  # the render's own buffer


def render_views(
    rgbd_map: RGBDMap,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    batch_size: int = 8,
    show_progress: bool = False,
) -> RGBD:
    """Render a map at many poses, ``batch_size`` at a time.

    Args:
        rgbd_map: any :class:`RGBDMap`.
        T_wc: (M, 4, 4) camera-to-world poses, M >= 1.
        camera: one camera (batch shape ``()``).
        batch_size: poses per ``render`` call.
        show_progress: progress bar over the batches (quiet when ``CI=true``).

    Returns:
        :class:`RGBD` with rgb (M, 3, H, W) and depth (M, 1, H, W).

    Raises:
        ShapeError: ``T_wc`` not (M, 4, 4) or empty.
        ValueError: NaN/inf poses or a non-positive ``batch_size``.
    """
    check_shape(T_wc, "M,4,4", "T_wc")
    if T_wc.shape[0] == 0:
        raise ShapeError("T_wc must hold at least one pose, got shape (0, 4, 4)")
    check_finite(T_wc, "T_wc")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    batches = T_wc.split(batch_size)
    parts = [rgbd_map.render(T, camera) for T in progress(batches, "render", show_progress)]
    return RGBD(torch.cat([p.rgb for p in parts]), torch.cat([p.depth for p in parts]))


def hole_fraction(depth: torch.Tensor) -> torch.Tensor:
    """Share of pixels without depth (holes) per image.

    Args:
        depth: (B, 1, H, W) z-depth, 0 where there is no measurement.

    Returns:
        (B,) float32 fractions in [0, 1].

    Example:
        >>> hole_fraction(torch.tensor([[[[0.0, 2.0], [1.0, 0.0]]]]))
        tensor([0.5000])
    """
    check_shape(depth, "B,1,H,W", "depth")
    return (depth <= 0).flatten(1).float().mean(1)
