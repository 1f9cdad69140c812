"""Wavefront OBJ + MTL + PNG textures for TexturedMesh: exact round trip and foreign files."""

from pathlib import Path

import numpy as np
import PIL.Image
import pytest
import trimesh

from diffloc.io.mesh_obj import read_textured_mesh_obj, write_textured_mesh_obj
from diffloc.io.textured_mesh import TexturedMesh
from diffloc.o3d import open3d


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


def canonical(mesh: TexturedMesh) -> TexturedMesh:
    """The faces grouped by (object id, material id), as the reader returns them."""
    order = np.lexsort((mesh.material_ids, mesh.object_ids))
    return TexturedMesh(
        vertices=mesh.vertices,
        triangles=mesh.triangles[order],
        corner_uvs=mesh.corner_uvs[order],
        material_ids=mesh.material_ids[order],
        object_ids=mesh.object_ids[order],
        textures=mesh.textures,
        material_names=mesh.material_names,
    )


def assert_same_surface(a: TexturedMesh, b: TexturedMesh) -> None:
    """Same triangles (corner positions), corner UVs, ids and textures, in the same order."""
    np.testing.assert_array_equal(a.vertices[a.triangles], b.vertices[b.triangles])
    np.testing.assert_array_equal(a.corner_uvs, b.corner_uvs)
    np.testing.assert_array_equal(a.material_ids, b.material_ids)
    np.testing.assert_array_equal(a.object_ids, b.object_ids)
    assert a.material_names == b.material_names
    assert len(a.textures) == len(b.textures)
    for x, y in zip(a.textures, b.textures, strict=True):
        assert x.dtype == y.dtype == np.float32
        np.testing.assert_array_equal(x, y)


def face_rows(corners: np.ndarray, corner_uvs: np.ndarray) -> np.ndarray:
    """(F, 15) float32 rows of corner positions and UVs, sorted (for order-free comparison)."""
    rows = np.concatenate(
        [corners.reshape(-1, 9).astype(np.float32), corner_uvs.reshape(-1, 6).astype(np.float32)],
        axis=1,
    )
    return rows[np.lexsort(rows.T[::-1])]


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
    assert_same_surface(canonical(mesh), got)
    used = np.unique(mesh.triangles)
    np.testing.assert_array_equal(got.vertices, np.unique(mesh.vertices[used], axis=0))
    first = {p.name: p.read_bytes() for p in (tmp_path / "mesh").rglob("*") if p.is_file()}
    write_textured_mesh_obj(path, mesh)
    second = {p.name: p.read_bytes() for p in (tmp_path / "mesh").rglob("*") if p.is_file()}
    assert first == second
    again = write_textured_mesh_obj(tmp_path / "again" / "scene.obj", got)
    assert_same_surface(got, read_textured_mesh_obj(again))


def test_diffloc_obj_opens_in_trimesh_and_open3d(tmp_path: Path):
    mesh = make_mesh()
    path = write_textured_mesh_obj(tmp_path / "scene.obj", mesh)
    expected = face_rows(mesh.vertices[mesh.triangles], mesh.corner_uvs)

    scene = trimesh.load(path, process=False, group_material=True, split_groups=True)
    corners, uvs, images = [], [], {}
    for geometry in scene.geometry.values():
        corners.append(geometry.vertices[geometry.faces])
        uv = geometry.visual.uv[geometry.faces]
        uvs.append(np.stack([uv[..., 0], 1.0 - uv[..., 1]], axis=-1))
        material = geometry.visual.material
        images[material.name] = np.asarray(material.image.convert("RGB"))
    np.testing.assert_array_equal(face_rows(np.concatenate(corners), np.concatenate(uvs)), expected)
    for name, image in images.items():
        texture = mesh.textures[mesh.material_names.index(name)]
        np.testing.assert_array_equal(image, np.rint(texture * 255).astype(np.uint8))

    # open3d's OBJ reader assigns one material per group; positions, UVs and textures agree
    # (open3d keeps v_obj and holds its texture rows bottom-up: the same texel is sampled).
    o3d_mesh = open3d().io.read_triangle_mesh(str(path), enable_post_processing=False)
    vertices = np.asarray(o3d_mesh.vertices)[np.asarray(o3d_mesh.triangles)]
    uv = np.asarray(o3d_mesh.triangle_uvs).reshape(-1, 3, 2)
    got = face_rows(vertices, np.stack([uv[..., 0], 1.0 - uv[..., 1]], axis=-1))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-6)
    textures = [np.asarray(t) for t in o3d_mesh.textures if not t.is_empty()]
    assert len(textures) == len(mesh.textures)
    for image, texture in zip(textures, mesh.textures, strict=True):
        np.testing.assert_array_equal(image[::-1], np.rint(texture * 255).astype(np.uint8))


def textured_quad_strip(rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    vertices = rng.standard_normal((8, 3))
    faces = np.array([[0, 1, 2], [2, 3, 4], [5, 6, 7]])
    uv = rng.uniform(0, 1, (8, 2))
    image = rng.integers(0, 256, (4, 5, 3)).astype(np.uint8)
    return vertices, faces, uv, image


def test_trimesh_obj_is_read_with_the_same_values(tmp_path: Path):
    vertices, faces, uv, image = textured_quad_strip(np.random.default_rng(0))
    visual = trimesh.visual.TextureVisuals(uv=uv, image=PIL.Image.fromarray(image))
    trimesh.Trimesh(vertices, faces, visual=visual, process=False).export(tmp_path / "m.obj")
    got = read_textured_mesh_obj(tmp_path / "m.obj")
    # trimesh writes 8 decimals.
    np.testing.assert_allclose(got.vertices[got.triangles], vertices[faces], rtol=0, atol=1e-7)
    flipped = np.stack([uv[faces][..., 0], 1.0 - uv[faces][..., 1]], axis=-1)
    np.testing.assert_allclose(got.corner_uvs, flipped, rtol=0, atol=1e-7)
    assert got.material_names == ["material_0"]
    np.testing.assert_array_equal(got.textures[0], image / np.float32(255))
    np.testing.assert_array_equal(got.object_ids, 0)


def test_open3d_obj_is_read_with_the_same_values(tmp_path: Path):
    o3d = open3d()
    vertices, faces, uv, image = textured_quad_strip(np.random.default_rng(1))
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(faces)
    )
    mesh.triangle_uvs = o3d.utility.Vector2dVector(uv[faces].reshape(-1, 2))
    mesh.textures = [o3d.geometry.Image(image)]
    mesh.triangle_material_ids = o3d.utility.IntVector([0, 0, 0])
    assert o3d.io.write_triangle_mesh(str(tmp_path / "m.obj"), mesh)
    got = read_textured_mesh_obj(tmp_path / "m.obj")
    # open3d writes 6 significant digits.
    np.testing.assert_allclose(got.vertices[got.triangles], vertices[faces], rtol=1e-5, atol=1e-6)
    flipped = np.stack([uv[faces][..., 0], 1.0 - uv[faces][..., 1]], axis=-1)
    np.testing.assert_allclose(got.corner_uvs, flipped, rtol=1e-5, atol=1e-6)
    # open3d writes its texture rows bottom-up (its own UVs have v = 0 at the top), so the
    # same texel is sampled.
    assert len(got.textures) == 1
    np.testing.assert_array_equal(got.textures[0], image[::-1] / np.float32(255))


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
        "g object_4\nf -4/-3 -3/-2 -2/-1\nf -3/-3 -2/-2 -1/-1\n"
        "g walls\nf 1//1 2//1 3//1 4//1\n"
    )
    mesh = read_textured_mesh_obj(tmp_path / "m.obj")
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float32)
    np.testing.assert_array_equal(
        mesh.vertices[mesh.triangles], square[[[0, 1, 2], [2, 3, 0], [0, 1, 2], [1, 2, 3]]]
    )
    np.testing.assert_array_equal(mesh.object_ids, [0, 0, 4, 4])
    np.testing.assert_array_equal(mesh.corner_uvs[:2], np.zeros((2, 3, 2)))
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


# ---------------------------------------------------------------- one test per bad-input rule


def test_missing_obj(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="nothing.obj"):
        read_textured_mesh_obj(tmp_path / "nothing.obj")


def test_missing_mtl(tmp_path: Path):
    write_textured_mesh_obj(tmp_path / "scene.obj", make_mesh())
    (tmp_path / "scene.mtl").unlink()
    with pytest.raises(FileNotFoundError, match=r"material library not found: .*scene\.mtl"):
        read_textured_mesh_obj(tmp_path / "scene.obj")


def test_missing_texture(tmp_path: Path):
    write_textured_mesh_obj(tmp_path / "scene.obj", make_mesh())
    (tmp_path / "textures" / "floor-1.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"texture not found: .*floor-1\.png"):
        read_textured_mesh_obj(tmp_path / "scene.obj")


def test_texture_that_is_not_an_image(tmp_path: Path):
    write_textured_mesh_obj(tmp_path / "scene.obj", make_mesh())
    (tmp_path / "textures" / "floor-1.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match=r"scene\.mtl: the texture of material 'floor-1'"):
        read_textured_mesh_obj(tmp_path / "scene.obj")


def test_several_material_libraries(tmp_path: Path):
    (tmp_path / "a.mtl").write_text("newmtl a\n")
    (tmp_path / "m.obj").write_text("mtllib a.mtl\nmtllib a.mtl\nv 0 0 0\nf 1 1 1\n")
    with pytest.raises(ValueError, match=r"m\.obj: several mtllib"):
        read_textured_mesh_obj(tmp_path / "m.obj")


def test_not_a_text_file(tmp_path: Path):
    (tmp_path / "bad.obj").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    with pytest.raises(ValueError, match=r"bad\.obj: not a text file"):
        read_textured_mesh_obj(tmp_path / "bad.obj")


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("v 0 0 0\nv 1 0 0\nf 1 2 3\n", "trimesh can read.*IndexError"),
        ("v 0 0 zero\nf 1 1 1\n", "trimesh can read.*could not be read"),
        ("v 0 0 0\nf 1 1 x\n", "trimesh can read.*could not be read"),
        ("v 0 0 0\nvt 0 0\nf 1/1 1/1 1/2\n", "texture coordinates that trimesh cannot resolve"),
        ("v 0 0 0\nusemtl nowhere\nf 1 1 1\n", "materials not defined"),
        ("v 0 0 0\nf 1 1 1\n  f 1 1 1\n", "decoded 1 triangles but the face statements hold 2"),
        ("v 0 0 inf\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "vertices contains NaN or infinite"),
    ],
    ids=["vertex-index", "vertex-number", "face-number", "vt-index", "material", "lost", "inf"],
)
def test_malformed_obj_names_file(tmp_path: Path, body: str, message: str):
    (tmp_path / "bad.obj").write_text(body)
    with pytest.raises(ValueError, match=message) as info:
        read_textured_mesh_obj(tmp_path / "bad.obj")
    assert "bad.obj" in str(info.value)


def test_bad_material_name_is_refused_and_nothing_written(tmp_path: Path):
    mesh = make_mesh()
    mesh.material_names = ["ok", "has space", "x"]
    with pytest.raises(ValueError, match="has space"):
        write_textured_mesh_obj(tmp_path / "scene.obj", mesh)
    with pytest.raises(ValueError, match=".obj"):
        write_textured_mesh_obj(tmp_path / "scene.ply", make_mesh())
    assert list(tmp_path.iterdir()) == []
