"""Ray casting against a triangle mesh with open3d's ``RaycastingScene``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from diffloc.checks import check_finite, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.textured_mesh import TexturedMesh
from diffloc.o3d import open3d
from diffloc.render.texture import MipmapTextures


@dataclass
class RayHits:
    """First intersections of R rays with a mesh.

    Attributes:
        distance: (R,) float32 ray parameter of the hit (metres for unit directions), inf on miss.
        triangle_ids: (R,) int64 index of the hit triangle, -1 on miss.
        barycentric: (R, 2) float32 barycentric coordinates (b1, b2) of the hit in its triangle;
            the hit is ``(1 - b1 - b2) * v0 + b1 * v1 + b2 * v2``.
        normals: (R, 3) float32 outward unit normal of the hit triangle, zero on miss.
    """

    distance: torch.Tensor
    triangle_ids: torch.Tensor
    barycentric: torch.Tensor
    normals: torch.Tensor

    @property
    def hit(self) -> torch.Tensor:
        """(R,) bool, true where the ray hit the mesh."""
        return self.triangle_ids >= 0


class MeshRaycaster:
    """First-hit ray casting against a :class:`TexturedMesh` (open3d BVH, multi-threaded).

    Args:
        mesh: the mesh to cast against; it must have at least one triangle.

    Example:
        >>> mesh = TexturedMesh(  # a grey 18 x 18 m wall 5 m ahead, facing the origin
        ...     vertices=np.array([[-9, -9, 5], [9, -9, 5], [9, 9, 5], [-9, 9, 5]], np.float32),
        ...     triangles=np.array([[0, 2, 1], [0, 3, 2]], dtype=np.int32),
        ...     corner_uvs=np.zeros((2, 3, 2), dtype=np.float32),
        ...     material_ids=np.zeros(2, dtype=np.int32),
        ...     object_ids=np.zeros(2, dtype=np.int32),
        ...     textures=[np.full((4, 4, 3), 0.5, dtype=np.float32)],
        ...     material_names=["grey"],
        ... )
        >>> caster = MeshRaycaster(mesh)
        >>> hits = caster.cast(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]))
        >>> hits.distance, hits.normals[:, 2]  # 5 m to the wall, whose normal faces the ray
        (tensor([5.]), tensor([-1.]))
    """

    def __init__(self, mesh: TexturedMesh) -> None:
        if mesh.num_faces == 0:
            raise ValueError("cannot ray cast an empty mesh (it has no triangles)")
        o3d = open3d()
        self.mesh = mesh
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(mesh.vertices), o3d.core.Tensor(mesh.triangles.astype(np.uint32))
        )

    def cast(self, origins: torch.Tensor, directions: torch.Tensor) -> RayHits:
        """Cast rays and return their first hits.

        Args:
            origins: (R, 3) ray origins in the mesh frame.
            directions: (R, 3) ray directions (unit length for metric distances).

        Returns:
            The hits of the R rays.
        """
        check_shape(origins, "R,3", "origins")
        check_shape(directions, f"{origins.shape[0]},3", "directions")
        o3d = open3d()
        rays = torch.cat([origins, directions], dim=1).to(torch.float32).contiguous().numpy()
        if not np.isfinite(rays).all():  # one pass over the float32 rays open3d gets
            check_finite(origins, "origins")
            check_finite(directions, "directions")
            raise ValueError("origins or directions overflow float32")
        result = self._scene.cast_rays(o3d.core.Tensor.from_numpy(rays))  # shares, no copy
        distance = torch.from_numpy(result["t_hit"].numpy())
        miss = ~torch.isfinite(distance)
        triangle_ids = torch.from_numpy(result["primitive_ids"].numpy().astype(np.int64))
        triangle_ids.masked_fill_(miss, -1)
        barycentric = torch.from_numpy(result["primitive_uvs"].numpy())
        normals = torch.from_numpy(result["primitive_normals"].numpy())
        normals.masked_fill_(miss[:, None], 0.0)  # open3d's own buffer, not shared elsewhere
        return RayHits(distance, triangle_ids, barycentric, normals)


@dataclass
class MeshRender:
    """Per-pixel outputs of rendering a textured mesh into B cameras.

    Attributes:
        albedo: (B, 3, H, W) float32 texture colour in [0, 1], 0 where nothing was hit.
        depth: (B, 1, H, W) float32 z-depth in metres along the optical axis, 0 where no hit.
        normals: (B, 3, H, W) float32 outward unit surface normals in the world frame.
        object_ids: (B, 1, H, W) int32 object id of the hit triangle, -1 where no hit.
        triangle_ids: (B, 1, H, W) int64 hit triangle, -1 where no hit.
        points: (B, 3, H, W) float32 world coordinates of the hits (zero where no hit).
        rays: (B, 3, H, W) float32 unit ray directions in the world frame.
    """

    albedo: torch.Tensor
    depth: torch.Tensor
    normals: torch.Tensor
    object_ids: torch.Tensor
    triangle_ids: torch.Tensor
    points: torch.Tensor
    rays: torch.Tensor


def camera_frame_rays(camera: PinholeCamera) -> torch.Tensor:
    """Unit camera-frame rays through every pixel centre of ``camera``.

    Args:
        camera: an unbatched camera (distortion honoured).

    Returns:
        (H*W, 3) float64 unit directions, pixels in row-major order.
    """
    pixels = camera.pixel_grid(torch.float64).reshape(-1, 2)
    rays_cam = camera.to(torch.float64).unproject(pixels)
    return rays_cam / rays_cam.norm(dim=-1, keepdim=True)


def world_rays(rays_cam: torch.Tensor, T_wc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-frame rays moved into the world by B poses.

    Args:
        rays_cam: (P, 3) float64 camera-frame directions (:func:`camera_frame_rays`).
        T_wc: (B, 4, 4) camera-to-world poses.

    Returns:
        origins (B, P, 3) (an expanded view of the B camera centres) and directions
        (B, P, 3), float32 (rotated in float64).
    """
    check_shape(T_wc, "B,4,4", "T_wc")
    T = T_wc.to(torch.float64)
    directions = torch.einsum("bij,nj->bni", T[:, :3, :3], rays_cam).to(torch.float32)
    return T[:, None, :3, 3].to(torch.float32).expand_as(directions), directions


def camera_rays(camera: PinholeCamera, T_wc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit world-frame rays through every pixel centre of ``camera``.

    Args:
        camera: an unbatched camera (distortion honoured).
        T_wc: (B, 4, 4) camera-to-world poses.

    Returns:
        origins (B, H*W, 3) and directions (B, H*W, 3), float32; pixels in row-major order.
    """
    check_shape(T_wc, "B,4,4", "T_wc")
    return world_rays(camera_frame_rays(camera), T_wc)


def _camera_key(camera: PinholeCamera) -> tuple:
    """What the rays of an unbatched camera depend on: size, dtype and parameter values."""
    values = [camera.fx, camera.fy, camera.cx, camera.cy]
    if camera.distortion is not None:
        values.append(camera.distortion)
    flat = torch.cat([v.reshape(-1) for v in values]).tolist()
    return camera.width, camera.height, camera.dtype, camera.distortion is None, tuple(flat)


@dataclass
class _Surface:
    """What every render output is made from, for R = B * P rays (P pixels per view).

    Attributes:
        origins: (B, P, 3) float32 ray origins.
        directions: (B, P, 3) float32 unit ray directions, world frame.
        hits: the R first hits.
        distance: (R,) float32 hit distance, 0 where no hit.
        albedo: (3, R) float32 texture colour, 0 where no hit.
        depth: (R,) float32 z-depth, 0 where no hit.
    """

    origins: torch.Tensor
    directions: torch.Tensor
    hits: RayHits
    distance: torch.Tensor
    albedo: torch.Tensor
    depth: torch.Tensor


class MeshRenderer:
    """Ray-cast renderer of a :class:`TexturedMesh`: albedo, depth, normals and ids per pixel.

    Texture lookups are trilinear on a mip pyramid; the level follows each pixel's footprint on
    the surface (distance / focal length, stretched by the incidence angle), so distant and
    grazing surfaces do not alias. The camera-frame rays of the last camera are kept and
    reused while the camera (size and parameter values) stays the same.

    Args:
        mesh: the mesh; it must have at least one triangle.

    Example:
        >>> mesh = TexturedMesh(  # a grey 18 x 18 m wall 5 m ahead, facing the origin
        ...     vertices=np.array([[-9, -9, 5], [9, -9, 5], [9, 9, 5], [-9, 9, 5]], np.float32),
        ...     triangles=np.array([[0, 2, 1], [0, 3, 2]], dtype=np.int32),
        ...     corner_uvs=np.zeros((2, 3, 2), dtype=np.float32),
        ...     material_ids=np.zeros(2, dtype=np.int32),
        ...     object_ids=np.zeros(2, dtype=np.int32),
        ...     textures=[np.full((4, 4, 3), 0.5, dtype=np.float32)],
        ...     material_names=["grey"],
        ... )
        >>> renderer = MeshRenderer(mesh)
        >>> out = renderer.render(torch.eye(4)[None], PinholeCamera.from_fov(16, 12, 1.2))
        >>> out.depth.shape, round(out.depth.min().item(), 4), out.albedo.max().item()
        (torch.Size([1, 1, 12, 16]), 5.0, 0.5)
    """

    def __init__(self, mesh: TexturedMesh) -> None:
        self.raycaster = MeshRaycaster(mesh)
        self.textures = MipmapTextures(mesh.textures)
        corners = torch.from_numpy(mesh.vertices[mesh.triangles]).to(torch.float64)
        uvs = torch.from_numpy(mesh.corner_uvs).to(torch.float64)
        area_world = 0.5 * torch.linalg.cross(
            corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
        ).norm(dim=-1)
        duv1, duv2 = uvs[:, 1] - uvs[:, 0], uvs[:, 2] - uvs[:, 0]
        area_uv = 0.5 * (duv1[:, 0] * duv2[:, 1] - duv1[:, 1] * duv2[:, 0]).abs()
        texels_per_metre = self.textures.size * torch.sqrt(area_uv / area_world.clamp_min(1e-12))
        # Per-triangle rows (u0, v0, u1, v1, u2, v2, texels per metre) as planes (7, F): one
        # gather gives every hit's corner UVs and texel density.
        rows = [torch.from_numpy(mesh.corner_uvs).reshape(-1, 6), texels_per_metre[:, None]]
        self._triangle_planes = torch.cat(rows, 1).to(torch.float32).t().contiguous()
        self._material_ids = torch.from_numpy(mesh.material_ids).to(torch.int32)
        self._object_ids = torch.from_numpy(mesh.object_ids)
        self._rays_cam: tuple[tuple, torch.Tensor] | None = None

    def _camera_frame_rays(self, camera: PinholeCamera) -> torch.Tensor:
        """(H*W, 3) float64 camera-frame rays of ``camera``, reused for the same camera."""
        key = _camera_key(camera)
        if self._rays_cam is None or self._rays_cam[0] != key:
            self._rays_cam = (key, camera_frame_rays(camera))
        return self._rays_cam[1]

    def _surface(self, T_wc: torch.Tensor, camera: PinholeCamera) -> _Surface:
        """Cast the rays of B views and texture their hits (see :class:`_Surface`)."""
        check_shape(T_wc, "B,4,4", "T_wc")
        check_finite(T_wc, "T_wc")
        origins, directions = world_rays(self._camera_frame_rays(camera), T_wc)
        flat_dirs = directions.reshape(-1, 3)
        hits = self.raycaster.cast(origins.reshape(-1, 3), flat_dirs)
        hit = hits.hit
        tri = hits.triangle_ids.clamp_min(0)
        # In place on this call's own buffers (the gathered rows, fresh sums): the same
        # operations in the same order with less fresh memory to fault in.
        u0, v0, u1, v1, u2, v2, texels_per_metre = self._triangle_planes.index_select(1, tri)
        b1, b2 = hits.barycentric.t()
        b0 = (1 - b1).sub_(b2)
        u = u0.mul_(b0).add_(u1.mul_(b1)).add_(u2.mul_(b2))
        v = v0.mul_(b0).add_(v1.mul_(b1)).add_(v2.mul_(b2))
        distance = torch.where(hit, hits.distance, torch.zeros_like(hits.distance))
        cos_incidence = _dot(hits.normals, flat_dirs).abs_().clamp_min_(0.05)
        focal = float(camera.fx) if camera.fx.ndim == 0 else float(camera.fx.reshape(-1)[0])
        footprint = texels_per_metre.mul_(distance).div_(focal).div_(cos_incidence.sqrt_())
        seen = hit.nonzero().squeeze(1)  # textures are sampled where a ray hit only
        material = self._material_ids.index_select(0, tri.index_select(0, seen))
        uv = torch.stack([u.index_select(0, seen), v.index_select(0, seen)])  # (2, N)
        sampled = self.textures.sample(material, uv.t(), footprint.index_select(0, seen))
        albedo = sampled.new_zeros(3, len(hit)).index_copy_(1, seen, sampled.t())
        z_axis = T_wc[:, :3, 2].to(torch.float32)
        cos_axis = _dot(directions, z_axis[:, None, :]).reshape(-1)
        return _Surface(origins, directions, hits, distance, albedo, cos_axis.mul_(distance))

    def render_rgbd(
        self, T_wc: torch.Tensor, camera: PinholeCamera
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Render the albedo and depth of B views only (the same values as :meth:`render`).

        Args:
            T_wc: (B, 4, 4) camera-to-world poses.
            camera: an unbatched pinhole camera with image size (H, W).

        Returns:
            albedo (B, 3, H, W) and depth (B, 1, H, W), as in :class:`MeshRender`.
        """
        surface = self._surface(T_wc, camera)
        shape = (T_wc.shape[0], camera.height, camera.width)
        return _planes_image(surface.albedo, shape), _planes_image(surface.depth[None], shape)

    def render(self, T_wc: torch.Tensor, camera: PinholeCamera) -> MeshRender:
        """Render B views.

        Args:
            T_wc: (B, 4, 4) camera-to-world poses.
            camera: an unbatched pinhole camera with image size (H, W).

        Returns:
            The per-pixel :class:`MeshRender`.
        """
        surface = self._surface(T_wc, camera)
        hits, distance = surface.hits, surface.distance
        hit = hits.hit
        tri = hits.triangle_ids.clamp_min(0)
        origins, directions = surface.origins.reshape(-1, 3), surface.directions.reshape(-1, 3)
        points = origins + directions * distance[:, None]
        points = torch.where(hit[:, None], points, torch.zeros_like(points))
        object_ids = self._object_ids[tri]
        object_ids = torch.where(hit, object_ids, torch.full_like(object_ids, -1))
        shape = (T_wc.shape[0], camera.height, camera.width)

        def image(values: torch.Tensor) -> torch.Tensor:
            return values.reshape(*shape, -1).permute(0, 3, 1, 2).contiguous()

        return MeshRender(
            albedo=_planes_image(surface.albedo, shape),
            depth=_planes_image(surface.depth[None], shape),
            normals=image(hits.normals),
            object_ids=image(object_ids),
            triangle_ids=image(hits.triangle_ids),
            points=image(points),
            rays=image(surface.directions),
        )


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Dot products of (..., 3) vectors (broadcasting) summed left to right, as
    ``(a * b).sum(-1)`` sums three terms, from strided columns without a (..., 3) temporary.

    Example:
        >>> _dot(torch.tensor([[1.0, 2.0, 3.0]]), torch.tensor([0.5, -1.0, 2.0]))
        tensor([4.5000])
    """
    out = a[..., 0] * b[..., 0]
    return out.add_(a[..., 1] * b[..., 1]).add_(a[..., 2] * b[..., 2])


def _planes_image(planes: torch.Tensor, shape: tuple[int, int, int]) -> torch.Tensor:
    """(C, B*H*W) channel planes -> (B, C, H, W) images (a view when B = 1)."""
    batch, height, width = shape
    return planes.reshape(-1, batch, height, width).transpose(0, 1).contiguous()
