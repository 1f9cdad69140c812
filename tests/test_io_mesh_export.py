"""Atlas meshes exported through trimesh open in trimesh and open3d with the same data."""

import numpy as np
import pytest
import trimesh

from diffloc.io.mesh_export import atlas_to_trimesh, write_atlas_obj, write_atlas_ply
from diffloc.io.textured_mesh import TexturedMesh
from diffloc.o3d import open3d


def atlas_mesh(materials: int = 1) -> TexturedMesh:
    """A unit square of two triangles whose shared edge has different UVs on each side."""
    rng = np.random.default_rng(0)
    return TexturedMesh(
        vertices=np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.5]], np.float32),
        triangles=np.array([[0, 1, 2], [0, 2, 3]], np.int32),
        corner_uvs=np.array(
            [[[0.1, 0.9], [0.9, 0.9], [0.9, 0.1]], [[0.05, 0.95], [0.8, 0.2], [0.1, 0.2]]],
            np.float32,
        ),
        material_ids=np.zeros(2, np.int32),
        object_ids=np.zeros(2, np.int32),
        textures=[rng.random((8, 8, 3)).astype(np.float32) for _ in range(materials)],
        material_names=[f"atlas{i}" for i in range(materials)],
    )


def corner_table(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray) -> np.ndarray:
    """Rows (x, y, z, u, v) of every face corner, sorted: independent of vertex order."""
    rows = np.concatenate([vertices[faces].reshape(-1, 3), uvs.reshape(-1, 2)], axis=1)
    return rows[np.lexsort(rows.T[::-1])]


def expected_table(mesh: TexturedMesh) -> np.ndarray:
    uvs = mesh.corner_uvs.astype(np.float64).copy()
    uvs[..., 1] = 1.0 - uvs[..., 1]  # files use the OBJ convention
    return corner_table(mesh.vertices.astype(np.float64), mesh.triangles, uvs)


def test_obj_reads_back_in_trimesh_and_open3d(tmp_path):
    mesh = atlas_mesh()
    path = write_atlas_obj(tmp_path / "map" / "mesh.obj", mesh)
    assert {p.name for p in path.parent.iterdir()} == {"mesh.obj", "mesh.mtl", "atlas0.png"}
    loaded = trimesh.load(path, process=False)
    got = corner_table(loaded.vertices, loaded.faces, loaded.visual.uv[loaded.faces])
    np.testing.assert_allclose(got, expected_table(mesh), atol=1e-6)
    image = np.asarray(loaded.visual.material.image.convert("RGB"))
    np.testing.assert_array_equal(image, np.rint(mesh.textures[0] * 255).astype(np.uint8))
    o3d = open3d()
    legacy = o3d.io.read_triangle_mesh(str(path))
    faces = np.asarray(legacy.triangles)
    uvs = np.asarray(legacy.triangle_uvs).reshape(-1, 3, 2)
    got = corner_table(np.asarray(legacy.vertices), faces, uvs)
    np.testing.assert_allclose(got, expected_table(mesh), atol=1e-6)


def test_ply_reads_back_in_trimesh_and_open3d(tmp_path):
    mesh = atlas_mesh()
    path = write_atlas_ply(tmp_path / "mesh.ply", mesh)
    exported = atlas_to_trimesh(mesh)
    colors = exported.visual.to_color().vertex_colors[:, :3]
    loaded = trimesh.load(path, process=False)
    np.testing.assert_allclose(loaded.vertices, exported.vertices, atol=1e-7)
    np.testing.assert_array_equal(loaded.faces, exported.faces)
    np.testing.assert_allclose(loaded.visual.uv, exported.visual.uv, atol=1e-7)
    o3d = open3d()
    legacy = o3d.io.read_triangle_mesh(str(path))
    np.testing.assert_allclose(np.asarray(legacy.vertices), exported.vertices, atol=1e-7)
    np.testing.assert_array_equal(np.asarray(legacy.triangles), exported.faces)
    np.testing.assert_allclose(np.asarray(legacy.vertex_colors) * 255, colors, atol=1e-4)


def test_seams_split_vertices_by_uv():
    exported = atlas_to_trimesh(atlas_mesh())
    # Vertices 0 and 2 carry different UVs in the two triangles: 4 + 2 vertices.
    assert len(exported.vertices) == 6


def test_multi_material_mesh_is_refused(tmp_path):
    with pytest.raises(ValueError, match="exactly one material"):
        write_atlas_obj(tmp_path / "mesh.obj", atlas_mesh(materials=2))


def test_wrong_suffix_is_refused(tmp_path):
    with pytest.raises(ValueError, match=r"\.ply"):
        write_atlas_ply(tmp_path / "mesh.obj", atlas_mesh())
