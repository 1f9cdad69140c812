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
        check_finite(origins, "origins")
        check_finite(directions, "directions")
        o3d = open3d()
        rays = torch.cat([origins, directions], dim=1).to(torch.float32).contiguous().numpy()
        result = self._scene.cast_rays(o3d.core.Tensor(rays))
        distance = torch.from_numpy(result["t_hit"].numpy())
        hit = torch.isfinite(distance)
        triangle_ids = torch.from_numpy(result["primitive_ids"].numpy().astype(np.int64))
        triangle_ids = torch.where(hit, triangle_ids, torch.full_like(triangle_ids, -1))
        barycentric = torch.from_numpy(result["primitive_uvs"].numpy())
        normals = torch.from_numpy(result["primitive_normals"].numpy())
        normals = torch.where(hit[:, None], normals, torch.zeros_like(normals))
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


def camera_rays(camera: PinholeCamera, T_wc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit world-frame rays through every pixel centre of ``camera``.

    Args:
        camera: an unbatched camera (distortion honoured).
        T_wc: (B, 4, 4) camera-to-world poses.

    Returns:
        origins (B, H*W, 3) and directions (B, H*W, 3), float32; pixels in row-major order.
    """
    check_shape(T_wc, "B,4,4", "T_wc")
    pixels = camera.pixel_grid(torch.float64).reshape(-1, 2)
    rays_cam = camera.to(torch.float64).unproject(pixels)
    rays_cam = rays_cam / rays_cam.norm(dim=-1, keepdim=True)
    T = T_wc.to(torch.float64)
    directions = torch.einsum("bij,nj->bni", T[:, :3, :3], rays_cam)
    origins = T[:, None, :3, 3].expand_as(directions)
    return origins.to(torch.float32), directions.to(torch.float32)


class MeshRenderer:
    """Ray-cast renderer of a :class:`TexturedMesh`: albedo, depth, normals and ids per pixel.

    Texture lookups are trilinear on a mip pyramid; the level follows each pixel's footprint on
    the surface (distance / focal length, stretched by the incidence angle), so distant and
    grazing surfaces do not alias.

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
        self._texels_per_metre = texels_per_metre.to(torch.float32)
        self._corner_uvs = torch.from_numpy(mesh.corner_uvs)
        self._material_ids = torch.from_numpy(mesh.material_ids).long()
        self._object_ids = torch.from_numpy(mesh.object_ids)

    def render(self, T_wc: torch.Tensor, camera: PinholeCamera) -> MeshRender:
        """Render B views.

        Args:
            T_wc: (B, 4, 4) camera-to-world poses.
            camera: an unbatched pinhole camera with image size (H, W).

        Returns:
            The per-pixel :class:`MeshRender`.
        """
        check_shape(T_wc, "B,4,4", "T_wc")
        check_finite(T_wc, "T_wc")
        batch, height, width = T_wc.shape[0], camera.height, camera.width
        origins, directions = camera_rays(camera, T_wc)
        hits = self.raycaster.cast(origins.reshape(-1, 3), directions.reshape(-1, 3))
        hit = hits.hit
        tri = hits.triangle_ids.clamp_min(0)
        b1, b2 = hits.barycentric[:, 0:1], hits.barycentric[:, 1:2]
        corner_uv = self._corner_uvs[tri]
        uv = (1 - b1 - b2) * corner_uv[:, 0] + b1 * corner_uv[:, 1] + b2 * corner_uv[:, 2]
        distance = torch.where(hit, hits.distance, torch.zeros_like(hits.distance))
        flat_dirs = directions.reshape(-1, 3)
        cos_incidence = (hits.normals * flat_dirs).sum(-1).abs().clamp_min(0.05)
        focal = float(camera.fx) if camera.fx.ndim == 0 else float(camera.fx.reshape(-1)[0])
        footprint = self._texels_per_metre[tri] * distance / focal / cos_incidence.sqrt()
        seen = hit.nonzero().squeeze(1)  # textures are sampled where a ray hit only
        sampled = self.textures.sample(self._material_ids[tri[seen]], uv[seen], footprint[seen])
        albedo = sampled.new_zeros(len(hit), 3).index_copy_(0, seen, sampled)
        z_axis = T_wc[:, :3, 2].to(torch.float32)
        cos_axis = (directions * z_axis[:, None, :]).sum(-1).reshape(-1)
        depth = distance * cos_axis
        points = origins.reshape(-1, 3) + directions.reshape(-1, 3) * distance[:, None]
        points = torch.where(hit[:, None], points, torch.zeros_like(points))
        object_ids = torch.where(
            hit, self._object_ids[tri], torch.full_like(self._object_ids[tri], -1)
        )

        def image(values: torch.Tensor) -> torch.Tensor:
            return values.reshape(batch, height, width, -1).permute(0, 3, 1, 2).contiguous()

        return MeshRender(
            albedo=image(albedo),
            depth=image(depth),
            normals=image(hits.normals),
            object_ids=image(object_ids),
            triangle_ids=image(hits.triangle_ids),
            points=image(points),
            rays=image(directions),
        )
