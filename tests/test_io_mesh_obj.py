"""Wavefront OBJ + MTL + PNG textures for TexturedMesh: exact round trip and foreign files."""

from pathlib import Path

import numpy as np
import pytest

from diffloc.io.mesh_obj import read_textured_mesh_obj, write_textured_mesh_obj
from diffloc.io.textured_mesh import TexturedMesh


def make_mesh(seed: int = 0) -> TexturedMesh:
    rng = np.random.default_rng(seed)
    vertices = (rng.standard_normal((30, 3)) * 10).astype(np.float32)
    faces = 24
    triangles = rng.integers(0, 30, (faces, 3)).astype(np.int32)
    corner_uvs = (rng.standard_normal((faces, 3, 2)) * 3).astype(np.float32)
    corner_uvs[0] = [[0.0, 0.0], [1.0, 1.0], [-0.0, 0.5]]
    corner_uvs[1] = [[1e-7, 3e-6], [0.25, 0.75], [12.5, -4.125]]
    corner_uvs[2] = corner_uvs[0]  # shared vt lines
    # Runs of objects and materials, including an interleaved pattern.
    object_ids = np.array([0] * 8 + [3] * 5 + [0] * 3 + [7] * 8, dtype=np.int32)
    material_ids = np.array(([0, 0, 1] * 8)[:faces], dtype=np.int32)
    textures = [
        rng.integers(0, 256, (8, 8, 3)).astype(np.float32) / np.float32(255),
        rng.integers(0, 256, (4, 6, 3)).astype(np.float32) / np.float32(255),
        np.full((2, 2, 3), np.float32(128) / np.float32(255)),  # unused material
    ]
    return TexturedMesh(
        vertices,
        triangles,
        corner_uvs,
        material_ids,
        object_ids,
        textures,
        ["brick_wall", "floor-1", "unused"],
    )


def assert_meshes_equal(a: TexturedMesh, b: TexturedMesh) -> None:
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.triangles, b.triangles)
    np.testing.assert_array_equal(a.corner_uvs, b.corner_uvs)
    np.testing.assert_array_equal(a.material_ids, b.material_ids)
    np.testing.assert_array_equal(a.object_ids, b.object_ids)
    assert a.material_names == b.material_names
    assert len(a.textures) == len(b.textures)
    for x, y in zip(a.textures, b.textures, strict=True):
        assert x.dtype == y.dtype == np.float32
        np.testing.assert_array_equal(x, y)


def test_round_trip_is_exact_and_deterministic(tmp_path: Path):
    mesh = make_mesh()
    path = write_textured_mesh_obj(tmp_path / "mesh" / "scene.obj", mesh)
    assert sorted(p.name for p in (tmp_path / "mesh").iterdir()) == [
        "scene.mtl",
        "scene.obj",
        "textures",
    ]
    assert sorted(p.name for p in (tmp_path / "mesh" / "textures").iterdir()) == [
        "brick_wall.png",
        "floor-1.png",
        "unused.png",
    ]
    got = read_textured_mesh_obj(path)
    assert_meshes_equal(mesh, got)
    first = {p.name: p.read_bytes() for p in (tmp_path / "mesh").rglob("*") if p.is_file()}
    write_textured_mesh_obj(tmp_path / "again" / "scene.obj", got)
    second = {p.name: p.read_bytes() for p in (tmp_path / "again").rglob("*") if p.is_file()}
    assert first == second


def test_file_structure_groups_materials_and_flipped_v(tmp_path: Path):
    mesh = make_mesh()
    write_textured_mesh_obj(tmp_path / "scene.obj", mesh)
    lines = (tmp_path / "scene.obj").read_text().splitlines()
    assert "mtllib scene.mtl" in lines
    groups = [line for line in lines if line.startswith("g ")]
    assert groups == ["g object_0", "g object_3", "g object_0", "g object_7"]
    vt = [line for line in lines if line.startswith("vt ")]
    assert len(vt) < 3 * mesh.num_faces  # identical UVs share a line
    assert "vt 0 1.0" in vt and "vt 1 0.0" in vt and "vt 0.25 0.25" in vt  # v_obj = 1 - v
    assert "map_Kd textures/brick_wall.png" in (tmp_path / "scene.mtl").read_text()


def test_foreign_obj_quads_normals_negative_indices(tmp_path: Path):
    (tmp_path / "m.obj").write_text(
        "# some other tool\no thing\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0 1.0\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvn 0 0 1\ns off\n"
        "f 1//1 2//1 3//1 4//1\n"
        "g object_4\n  f -4/-3 -3/-2 -2/-1\n"
    )
    mesh = read_textured_mesh_obj(tmp_path / "m.obj")
    np.testing.assert_array_equal(mesh.triangles, [[0, 1, 2], [0, 2, 3], [0, 1, 2]])
    np.testing.assert_array_equal(mesh.object_ids, [0, 0, 4])
    np.testing.assert_array_equal(mesh.corner_uvs[0], np.zeros((3, 2)))
    np.testing.assert_array_equal(mesh.corner_uvs[2], [[0, 1], [1, 1], [1, 0]])
    assert mesh.material_names == ["default"] and mesh.textures[0].shape == (1, 1, 3)


def test_material_without_texture_uses_kd(tmp_path: Path):
    (tmp_path / "m.mtl").write_text("newmtl red\nKd 1 0 0\n")
    (tmp_path / "m.obj").write_text(
        "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl red\nf 1 2 3\n"
    )
    mesh = read_textured_mesh_obj(tmp_path / "m.obj")
    assert mesh.material_names == ["red"]
    np.testing.assert_array_equal(mesh.textures[0], [[[1.0, 0.0, 0.0]]])


def test_missing_texture_and_mtl(tmp_path: Path):
    write_textured_mesh_obj(tmp_path / "scene.obj", make_mesh())
    (tmp_path / "textures" / "floor-1.png").unlink()
    with pytest.raises(FileNotFoundError, match="floor-1.png"):
        read_textured_mesh_obj(tmp_path / "scene.obj")
    (tmp_path / "scene.mtl").unlink()
    with pytest.raises(FileNotFoundError, match="scene.mtl"):
        read_textured_mesh_obj(tmp_path / "scene.obj")
    with pytest.raises(FileNotFoundError, match="nothing.obj"):
        read_textured_mesh_obj(tmp_path / "nothing.obj")


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("v 0 0 0\nv 1 0 0\nf 1 2 3\n", "vertices that do not exist"),
        ("v 0 0 zero\nf 1 1 1\n", "not a number"),
        ("v 0 0 0\nf 1 1 x\n", "not an integer"),
        ("v 0 0 0\nvt 0 0\nf 1/1 1/1 1/2\n", "texture coordinates that do not exist"),
        ("v 0 0 0\nusemtl nowhere\nf 1 1 1\n", "materials not defined"),
        ("v 0 0 0\nvt 0 0\nf 1/1 1/1 0/1\n", "index 0"),
    ],
)
def test_malformed_obj_names_file(tmp_path: Path, body: str, message: str):
    (tmp_path / "bad.obj").write_text(body)
    with pytest.raises(ValueError, match=message) as info:
        read_textured_mesh_obj(tmp_path / "bad.obj")
    assert "bad.obj" in str(info.value)


def test_bad_material_name_is_refused(tmp_path: Path):
    mesh = make_mesh()
    mesh.material_names = ["ok", "has space", "x"]
    with pytest.raises(ValueError, match="has space"):
        write_textured_mesh_obj(tmp_path / "scene.obj", mesh)
    with pytest.raises(ValueError, match=".obj"):
        write_textured_mesh_obj(tmp_path / "scene.ply", make_mesh())
