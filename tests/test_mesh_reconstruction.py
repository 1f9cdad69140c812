"""Mesh reconstruction from a point map and the UV atlas / texel map of it."""

import numpy as np
import pytest
import torch

from diffloc.maps.mesh import MeshReconstructionConfig, reconstruct_mesh
from diffloc.maps.uv_atlas import compute_uv_atlas, rasterize_atlas
from diffloc.o3d import open3d

RADIUS = 1.0


def sphere_points(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points on a unit sphere (with 2 mm noise) and their outward normals."""
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(count, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return RADIUS * normals + rng.normal(scale=0.002, size=(count, 3)), normals


def half_sphere_points(count: int) -> tuple[np.ndarray, np.ndarray]:
    """The upper half of the sphere: an open surface Poisson would close below."""
    points, normals = sphere_points(2 * count)
    keep = points[:, 2] > 0.0
    return points[keep], normals[keep]


CFG = MeshReconstructionConfig(voxel_size_m=0.02, poisson_depth=6, max_distance_m=0.08)


@pytest.fixture(scope="module")
def sphere_mesh():
    return reconstruct_mesh(*sphere_points(20_000), CFG)


def test_sphere_is_reconstructed_on_its_surface(sphere_mesh):
    radii = np.linalg.norm(sphere_mesh.vertices, axis=1)
    assert np.abs(radii - RADIUS).max() < 0.03
    # The density quantile trims its share of the lowest-density vertices even on a closed,
    # fully supported surface: a few per cent of the area go.
    assert 0.88 * 4 * np.pi * RADIUS**2 < sphere_mesh.area < 1.01 * 4 * np.pi * RADIUS**2


def test_reconstructed_mesh_is_edge_and_vertex_manifold(sphere_mesh):
    o3d = open3d()
    legacy = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(sphere_mesh.vertices),
        o3d.utility.Vector3iVector(sphere_mesh.faces),
    )
    assert legacy.is_edge_manifold(allow_boundary_edges=True)
    assert legacy.is_vertex_manifold()


def test_normals_point_out_of_the_surface(sphere_mesh):
    outward = (sphere_mesh.face_normals * sphere_mesh.triangles_center).sum(axis=1)
    assert (outward > 0).mean() > 0.99


def test_a_room_seen_from_inside_keeps_its_normals_towards_the_sensor():
    points, normals = sphere_points(20_000)
    mesh = reconstruct_mesh(points, -normals, CFG)  # scanned from the centre: normals inward
    inward = (mesh.face_normals * mesh.triangles_center).sum(axis=1)
    assert (inward < 0).mean() > 0.99


def test_surface_no_point_supports_is_trimmed():
    mesh = reconstruct_mesh(*half_sphere_points(20_000), CFG)
    assert mesh.vertices[:, 2].min() > -0.1  # Poisson's closing of the lower half is gone
    # What is left of the closing surface lies within max_distance_m of the rim.
    assert 0.85 * 2 * np.pi * RADIUS**2 < mesh.area < 1.1 * 2 * np.pi * RADIUS**2


def test_decimation_keeps_the_face_budget():
    cfg = MeshReconstructionConfig(
        voxel_size_m=0.02, poisson_depth=6, max_distance_m=0.08, target_faces=2000
    )
    mesh = reconstruct_mesh(*sphere_points(20_000), cfg)
    assert len(mesh.faces) <= 2000
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - RADIUS).max() < 0.05


def test_too_few_points_are_refused():
    points, normals = sphere_points(50)
    with pytest.raises(ValueError, match="at least 100"):
        reconstruct_mesh(points, normals, CFG)


def test_zero_normals_are_refused():
    points, normals = sphere_points(500)
    normals[3] = 0.0
    with pytest.raises(ValueError, match="non-zero"):
        reconstruct_mesh(points, normals, CFG)


def test_mismatched_normals_are_refused():
    points, normals = sphere_points(500)
    with pytest.raises(ValueError, match="normals"):
        reconstruct_mesh(points, normals[:-1], CFG)


def test_non_finite_points_are_refused():
    points, normals = sphere_points(500)
    points[0, 0] = np.nan
    with pytest.raises(ValueError, match="points"):
        reconstruct_mesh(points, normals, CFG)


def test_bad_config_is_refused():
    with pytest.raises(ValueError, match="density_quantile"):
        MeshReconstructionConfig(density_quantile=1.0)


def test_atlas_charts_the_mesh_without_overlap(sphere_mesh):
    size = 256
    uvs = compute_uv_atlas(sphere_mesh.vertices, sphere_mesh.faces, size)
    assert uvs.shape == (len(sphere_mesh.faces), 3, 2)
    assert uvs.min() >= 0.0 and uvs.max() <= 1.0
    assert uvs.reshape(-1, 2).max(axis=0).max() > 0.9  # the layout fills the atlas's side
    texels = rasterize_atlas(uvs, size, margin=0)
    # Every texel centre belongs to one triangle, so covered texels are distinct and the
    # surface points they map to lie on their triangles (on the sphere).
    flat = texels.rows * size + texels.cols
    assert len(torch.unique(flat)) == len(flat) and bool(texels.covered.all())
    points = texels.points(sphere_mesh.vertices, sphere_mesh.faces).numpy()
    assert np.abs(np.linalg.norm(points, axis=1) - RADIUS).max() < 0.03
    assert bool((texels.barycentric >= -1e-9).all())


def test_the_same_mesh_gets_the_same_atlas(sphere_mesh):
    """A mesh map built twice from the same inputs must be the same map (content-keyed
    stages assume it): the atlas is a function of the mesh and the settings."""
    first = compute_uv_atlas(sphere_mesh.vertices, sphere_mesh.faces, 256)
    np.testing.assert_array_equal(
        first, compute_uv_atlas(sphere_mesh.vertices, sphere_mesh.faces, 256)
    )
    finer = compute_uv_atlas(sphere_mesh.vertices, sphere_mesh.faces, 256, max_cost=0.5)
    assert not np.array_equal(first, finer)  # the settings reach xatlas


def test_texel_map_inverts_a_known_affine_layout():
    # One triangle, world (x, y, 0) = 2 * (u, v): texel centres map to known points.
    vertices = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    faces = np.array([[0, 1, 2]])
    uvs = np.array([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]], dtype=np.float32)
    texels = rasterize_atlas(uvs, 8, margin=1)
    points = texels.points(vertices, faces)
    centre_u = (texels.cols.to(torch.float64) + 0.5) / 8
    centre_v = (texels.rows.to(torch.float64) + 0.5) / 8
    torch.testing.assert_close(points[:, 0], 2 * centre_u)
    torch.testing.assert_close(points[:, 1], 2 * centre_v)
    inside = (centre_u + centre_v) <= 1.0
    assert bool((texels.covered == inside).all())
    assert int((~texels.covered).sum()) > 0  # the gutter along the hypotenuse


def test_atlas_of_an_empty_mesh_is_refused():
    with pytest.raises(ValueError, match="without faces"):
        compute_uv_atlas(np.zeros((3, 3)), np.zeros((0, 3), dtype=np.int64), 64)


def test_atlas_that_covers_no_texel_is_refused():
    tiny = np.array([[[0.1, 0.1], [0.1001, 0.1], [0.1, 0.1001]]], dtype=np.float32)
    with pytest.raises(ValueError, match="no texel"):
        rasterize_atlas(tiny, 4)
