"""MeshRenderer: the same pixels, bit for bit, as the per-definition render (camera rays in
float64, per-ray UV and footprint, row-wise trilinear lookup); misses, a camera inside the
mesh, batches, distortion, the camera-ray reuse, and refused rays."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import se3_exp
from diffloc.io.textured_mesh import TexturedMesh
from diffloc.render.raycast import MeshRaycaster, MeshRenderer, _dot
from diffloc.render.texture import MipmapTextures

FIELDS = ("albedo", "depth", "normals", "object_ids", "triangle_ids", "points", "rays")


def box_mesh() -> TexturedMesh:
    """A closed 4 x 3 x 2.5 m box (outward triangles), two textured materials, UVs that wrap."""
    low, high = np.array([-2.0, -1.5, -1.25]), np.array([2.0, 1.5, 1.25])
    corners = np.array(
        [[high[i] if (k >> i) & 1 else low[i] for i in range(3)] for k in range(8)],
        dtype=np.float32,
    )
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    triangles = np.array([[a, b, c] for a, b, c, d in quads] + [[a, c, d] for a, b, c, d in quads])
    rng = np.random.default_rng(0)
    faces = len(triangles)
    return TexturedMesh(
        vertices=corners,
        triangles=triangles.astype(np.int32),
        corner_uvs=rng.uniform(-2.0, 3.0, (faces, 3, 2)).astype(np.float32),
        material_ids=(np.arange(faces) % 2).astype(np.int32),
        object_ids=(np.arange(faces) // 4).astype(np.int32),
        textures=[rng.random((16, 16, 3), dtype=np.float32), rng.random((8, 8, 3), np.float32)],
        material_names=["a", "b"],
    )


def look_from(position: list[float], rotation: list[float]) -> torch.Tensor:
    """(4, 4) float64 camera-to-world pose at ``position`` turned by the axis-angle ``rotation``."""
    T = se3_exp(torch.tensor([0.0, 0.0, 0.0, *rotation], dtype=torch.float64))
    T[:3, 3] = torch.tensor(position, dtype=torch.float64)
    return T


OUTSIDE = look_from([0.3, -0.2, -6.0], [0.05, -0.1, 0.02])  # the box fills the middle only
INSIDE = look_from([0.4, 0.1, 0.2], [0.3, 1.2, -0.4])  # every ray hits a wall from inside


def reference_bilinear(
    textures: MipmapTextures, material: torch.Tensor, uv: torch.Tensor, level: torch.Tensor
) -> torch.Tensor:
    """Row-wise (N, 3) bilinear wrapping lookup, read off the definition."""
    rows = textures._pairs[:3].t()  # each pair column starts with its own texel
    sizes = torch.tensor([textures.size >> k for k in range(textures.num_levels)])
    size = sizes[level]
    base = textures._offsets[level] + material * size * size
    xy = (uv - torch.floor(uv)) * size[:, None] - 0.5
    xy0 = torch.floor(xy)
    frac = xy - xy0
    wrap = size - 1
    x0, y0 = xy0[:, 0].long() & wrap, xy0[:, 1].long() & wrap
    x1, y1 = (x0 + 1) & wrap, (y0 + 1) & wrap
    fx, fy = frac[:, 0:1], frac[:, 1:2]
    t00, t01 = rows[base + y0 * size + x0], rows[base + y0 * size + x1]
    t10, t11 = rows[base + y1 * size + x0], rows[base + y1 * size + x1]
    return (t00 * (1 - fx) + t01 * fx) * (1 - fy) + (t10 * (1 - fx) + t11 * fx) * fy


def reference_render(
    mesh: TexturedMesh, T_wc: torch.Tensor, camera: PinholeCamera
) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Every :class:`MeshRender` field per ray, written out plainly; and the mip levels used."""
    caster, textures = MeshRaycaster(mesh), MipmapTextures(mesh.textures)
    batch, height, width = T_wc.shape[0], camera.height, camera.width
    pixels = camera.pixel_grid(torch.float64).reshape(-1, 2)
    rays_cam = camera.to(torch.float64).unproject(pixels)
    rays_cam = rays_cam / rays_cam.norm(dim=-1, keepdim=True)
    T = T_wc.to(torch.float64)
    directions = torch.einsum("bij,nj->bni", T[:, :3, :3], rays_cam).to(torch.float32)
    origins = T[:, None, :3, 3].expand_as(directions).to(torch.float32)
    dirs, starts = directions.reshape(-1, 3), origins.reshape(-1, 3)
    hits = caster.cast(starts, dirs)
    hit, tri = hits.hit, hits.triangle_ids.clamp_min(0)
    corners = torch.from_numpy(mesh.vertices[mesh.triangles]).to(torch.float64)
    uvs = torch.from_numpy(mesh.corner_uvs).to(torch.float64)
    area_world = 0.5 * torch.linalg.cross(
        corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    ).norm(dim=-1)
    duv1, duv2 = uvs[:, 1] - uvs[:, 0], uvs[:, 2] - uvs[:, 0]
    area_uv = 0.5 * (duv1[:, 0] * duv2[:, 1] - duv1[:, 1] * duv2[:, 0]).abs()
    density = (textures.size * torch.sqrt(area_uv / area_world.clamp_min(1e-12))).float()
    b1, b2 = hits.barycentric[:, 0:1], hits.barycentric[:, 1:2]
    corner_uv = torch.from_numpy(mesh.corner_uvs)[tri]
    uv = (1 - b1 - b2) * corner_uv[:, 0] + b1 * corner_uv[:, 1] + b2 * corner_uv[:, 2]
    distance = torch.where(hit, hits.distance, torch.zeros_like(hits.distance))
    cos_incidence = (hits.normals * dirs).sum(-1).abs().clamp_min(0.05)
    footprint = density[tri] * distance / float(camera.fx) / cos_incidence.sqrt()
    level = torch.log2(footprint.clamp_min(1.0)).clamp(max=textures.num_levels - 1)
    lower = torch.floor(level).long()
    upper = (lower + 1).clamp(max=textures.num_levels - 1)
    blend = (level - lower)[:, None]
    material = torch.from_numpy(mesh.material_ids).long()[tri]
    below = reference_bilinear(textures, material, uv, lower)
    above = reference_bilinear(textures, material, uv, upper)
    colour = torch.where(blend > 0, (1 - blend) * below + blend * above, below)
    albedo = torch.where(hit[:, None], colour, torch.zeros_like(colour))
    z_axis = T_wc[:, :3, 2].to(torch.float32)
    depth = distance * (directions * z_axis[:, None, :]).sum(-1).reshape(-1)
    points = torch.where(hit[:, None], starts + dirs * distance[:, None], torch.zeros_like(dirs))
    objects = torch.from_numpy(mesh.object_ids)[tri]
    values = {
        "albedo": albedo,
        "depth": depth,
        "normals": hits.normals,
        "object_ids": torch.where(hit, objects, torch.full_like(objects, -1)),
        "triangle_ids": hits.triangle_ids,
        "points": points,
        "rays": dirs,
    }
    images = {
        k: v.reshape(batch, height, width, -1).permute(0, 3, 1, 2).contiguous()
        for k, v in values.items()
    }
    return images, level[hit]


CAMERAS = {
    "pinhole": PinholeCamera.from_fov(48, 36, math.radians(100), dtype=torch.float64),
    "distorted": PinholeCamera.from_fov(
        40, 30, math.radians(80), distortion=torch.tensor([-0.2, 0.05, 1e-3, -1e-3])
    ),
}


@pytest.mark.parametrize("camera_name", list(CAMERAS))
@pytest.mark.parametrize("poses", ["outside", "inside", "both"])
@pytest.mark.parametrize("chunk_size", [32768, 37])  # one lookup chunk, or many small ones
def test_render_equals_the_definition_bit_for_bit(
    camera_name: str, poses: str, chunk_size: int
) -> None:
    mesh, camera = box_mesh(), CAMERAS[camera_name]
    T_wc = {
        "outside": OUTSIDE[None],
        "inside": INSIDE[None],
        "both": torch.stack([OUTSIDE, INSIDE]),
    }[poses]
    renderer = MeshRenderer(mesh)
    renderer.textures.chunk_size = chunk_size
    got = renderer.render(T_wc, camera)
    expected, levels = reference_render(mesh, T_wc, camera)
    for name in FIELDS:
        assert getattr(got, name).dtype == expected[name].dtype, name
        assert torch.equal(getattr(got, name), expected[name]), name
    albedo, depth = renderer.render_rgbd(T_wc, camera)
    assert torch.equal(albedo, got.albedo) and torch.equal(depth, got.depth)
    assert albedo.is_contiguous() and depth.is_contiguous()
    if poses == "both":  # level 0 (magnified), whole levels and blends between two levels
        assert bool((levels == 0).any()) and bool((levels % 1 > 0).any())


def test_rays_that_miss_everything_leave_empty_pixels() -> None:
    away = look_from([0.0, 0.0, -6.0], [math.pi, 0.0, 0.0])  # looking away from the box
    out = MeshRenderer(box_mesh()).render(away[None], CAMERAS["pinhole"])
    assert bool((out.depth == 0).all()) and bool((out.albedo == 0).all())
    assert bool((out.triangle_ids == -1).all()) and bool((out.object_ids == -1).all())
    assert bool((out.normals == 0).all()) and bool((out.points == 0).all())


def test_a_camera_inside_the_mesh_sees_the_walls_around_it() -> None:
    camera = CAMERAS["pinhole"]
    centre = look_from([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])  # optical axis +z to the lid 1.25 m away
    out = MeshRenderer(box_mesh()).render(centre[None], camera)
    assert bool((out.triangle_ids >= 0).all()) and bool((out.depth > 0).all())
    centre_depth = out.depth[0, 0, camera.height // 2, camera.width // 2]
    assert torch.isclose(centre_depth, torch.tensor(1.25), atol=1e-5)
    inward = (out.normals * out.rays).sum(1)  # outward normals point away from the camera
    assert bool((inward > 0).all())


def test_camera_rays_are_reused_only_for_the_same_camera() -> None:
    mesh, renderer = box_mesh(), MeshRenderer(box_mesh())
    wide = CAMERAS["pinhole"]
    narrow = PinholeCamera.from_fov(48, 36, math.radians(60), dtype=torch.float64)  # same size
    for camera in (wide, narrow, wide, wide.scaled(0.5)):
        got = renderer.render(OUTSIDE[None], camera)
        expected, _ = reference_render(mesh, OUTSIDE[None], camera)
        for name in FIELDS:
            assert torch.equal(getattr(got, name), expected[name]), name


@pytest.mark.parametrize("bad", ["origins", "directions"])
def test_non_finite_rays_are_refused_by_name(bad: str) -> None:
    caster = MeshRaycaster(box_mesh())
    rays = {"origins": torch.zeros(4, 3), "directions": torch.tensor([[0.0, 0.0, 1.0]] * 4)}
    rays[bad][1, 0] = float("nan")
    with pytest.raises(ValueError, match=bad):
        caster.cast(rays["origins"], rays["directions"])


def test_rays_beyond_float32_are_refused() -> None:
    caster = MeshRaycaster(box_mesh())
    far = torch.tensor([[1e300, 0.0, 0.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match="float32"):
        caster.cast(far, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))


def test_dot_sums_like_the_elementwise_product_bit_for_bit() -> None:
    g = torch.Generator().manual_seed(0)
    scale = 10.0 ** torch.randint(-4, 5, (20000, 1), generator=g)  # mixed magnitudes
    a = torch.randn(20000, 3, generator=g) * scale
    b = torch.randn(20000, 3, generator=g)
    axis = torch.randn(3, generator=g)
    for other in (b, axis):  # row by row, and one vector broadcast over the rows
        got, expected = _dot(a, other), (a * other).sum(-1)
        assert torch.equal(got.view(torch.int32), expected.view(torch.int32))
