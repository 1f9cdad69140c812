"""PLY reading (through trimesh) and writing: dtypes, custom properties, faces, bad files."""

import re
from pathlib import Path

import numpy as np
import pytest
import trimesh

from diffloc.io.ply import read_ply, read_point_cloud, write_ply, write_point_cloud
from diffloc.o3d import open3d

DTYPES = ["i1", "u1", "i2", "u2", "i4", "u4", "f4", "f8"]
XYZ_HEADER = "property float x\nproperty float y\nproperty float z\n"


def all_types_vertex(n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    vertex = {axis: rng.standard_normal(n).astype(np.float32) for axis in "xyz"}
    for code in DTYPES:
        dtype = np.dtype(code)
        if dtype.kind == "f":
            values = (rng.standard_normal(n) * 10 ** rng.uniform(-8, 8, n)).astype(dtype)
        else:
            info = np.iinfo(dtype)
            values = rng.integers(info.min, info.max, n, endpoint=True, dtype=np.int64)
            values = values.astype(dtype)
        vertex[f"p_{code}"] = values
    vertex["radius"] = rng.uniform(0, 1, n).astype(np.float32)
    vertex["confidence"] = rng.uniform(0, 1, n)
    return vertex


def cloud(n: int = 40, seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    points = rng.standard_normal((n, 3)).astype(np.float32)
    normals = rng.standard_normal((n, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    colors = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    return points, normals, colors


@pytest.mark.parametrize("binary", [True, False])
def test_round_trip_is_exact_with_dtypes(tmp_path: Path, binary: bool):
    rng = np.random.default_rng(0)
    vertex = all_types_vertex(50, rng)
    faces = rng.integers(0, 50, (20, 3)).astype(np.int32)
    path = tmp_path / "a.ply"
    write_ply(path, vertex, faces, binary=binary, comments=["made by a test"])
    got, got_faces = read_ply(path)
    assert list(got) == list(vertex)
    for name, values in vertex.items():
        assert got[name].dtype == values.dtype, name
        np.testing.assert_array_equal(got[name], values, err_msg=name)
    assert got_faces.dtype == np.int64
    np.testing.assert_array_equal(got_faces, faces)
    before = path.read_bytes()
    write_ply(path, vertex, faces, binary=binary, comments=["made by a test"])
    assert path.read_bytes() == before, "bytes must be deterministic"


def test_no_faces_gives_none_and_empty_cloud(tmp_path: Path):
    write_ply(tmp_path / "a.ply", {a: np.zeros(0, np.float32) for a in "xyz"})
    vertex, faces = read_ply(tmp_path / "a.ply")
    assert faces is None and vertex["x"].shape == (0,) and vertex["x"].dtype == np.float32
    assert read_point_cloud(tmp_path / "a.ply").points.shape == (0, 3)


def test_big_endian_other_elements_comments_and_alias(tmp_path: Path):
    header = (
        b"ply\nformat binary_big_endian 1.0\ncomment hello\nobj_info scanner 3\n"
        b"element camera 1\nproperty float32 fov\nproperty list uint8 int32 misc\n"
        b"element vertex 3\nproperty float32 x\nproperty float32 y\nproperty float32 z\n"
        b"property uint16 label\n"
        b"element face 1\nproperty list uint8 uint32 vertex_index\nend_header\n"
    )
    camera = np.array([1.5], ">f4").tobytes() + bytes([2]) + np.array([7, 8], ">i4").tobytes()
    xyz = np.arange(9, dtype=np.float32).reshape(3, 3)
    rows = np.empty(3, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("label", ">u2")])
    rows["x"], rows["y"], rows["z"], rows["label"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], [1, 2, 300]
    face = bytes([3]) + np.array([0, 1, 2], ">u4").tobytes()
    path = tmp_path / "be.ply"
    path.write_bytes(header + camera + rows.tobytes() + face)
    vertex, faces = read_ply(path)
    np.testing.assert_array_equal(np.stack([vertex[a] for a in "xyz"], 1), xyz)
    np.testing.assert_array_equal(vertex["label"], [1, 2, 300])
    assert vertex["label"].dtype == np.uint16 and vertex["label"].dtype.isnative
    np.testing.assert_array_equal(faces, [[0, 1, 2]])


def test_ascii_mixed_polygons_are_triangulated(tmp_path: Path):
    body = "".join(f"{i} {i + 1} {i + 2}\n" for i in range(5))
    (tmp_path / "p.ply").write_bytes(
        (
            "ply\r\nformat ascii 1.0\r\nelement vertex 5\r\n"
            + XYZ_HEADER.replace("\n", "\r\n")
            + "element face 2\r\nproperty list uchar int vertex_indices\r\nend_header\r\n"
            + body
            + "4 0 1 2 3\r\n3 1 2 4\r\n"
        ).encode()
    )
    vertex, faces = read_ply(tmp_path / "p.ply")
    assert sorted(map(tuple, faces.tolist())) == [(0, 1, 2), (1, 2, 4), (2, 3, 0)]
    np.testing.assert_array_equal(vertex["z"], np.arange(2, 7, dtype=np.float32))


@pytest.mark.parametrize("binary", [True, False])
def test_point_cloud_round_trip(tmp_path: Path, binary: bool):
    points, normals, colors = cloud()
    rng = np.random.default_rng(2)
    extra = {
        "radius": rng.uniform(0, 1, 40).astype(np.float32),
        "confidence": rng.integers(0, 9, 40).astype(np.uint8),
        "intensity": rng.integers(0, 60000, 40).astype(np.uint16),
    }
    write_point_cloud(tmp_path / "c.ply", points, normals, colors, extra, binary=binary)
    got = read_point_cloud(tmp_path / "c.ply")
    np.testing.assert_array_equal(got.points, points)
    np.testing.assert_array_equal(got.normals, normals)
    np.testing.assert_array_equal(got.colors, colors.astype(np.float32) / np.float32(255))
    assert got.colors.dtype == np.float32
    assert list(got.extra) == list(extra)
    for name, values in extra.items():
        np.testing.assert_array_equal(got.extra[name], values)
        assert got.extra[name].dtype == values.dtype
    # Float colours in [0, 1] are stored to 1/255.
    write_point_cloud(tmp_path / "f.ply", points, colors=colors / 255.0)
    plain = read_point_cloud(tmp_path / "f.ply")
    np.testing.assert_array_equal(plain.colors, got.colors)
    assert plain.normals is None and plain.extra == {}


# ---------------------------------------------------------------- round trips with the libraries


@pytest.mark.parametrize("binary", [True, False])
def test_diffloc_cloud_opens_in_trimesh_and_open3d(tmp_path: Path, binary: bool):
    points, normals, colors = cloud()
    radius = np.linspace(0.01, 0.4, 40, dtype=np.float32)
    path = tmp_path / "c.ply"
    write_point_cloud(path, points, normals, colors, {"radius": radius}, binary=binary)

    in_trimesh = trimesh.load(path, process=False)
    assert isinstance(in_trimesh, trimesh.PointCloud)
    np.testing.assert_array_equal(in_trimesh.vertices, points.astype(np.float64))
    np.testing.assert_array_equal(in_trimesh.colors[:, :3], colors)

    o3d = open3d()
    legacy = o3d.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(np.asarray(legacy.points).astype(np.float32), points)
    np.testing.assert_array_equal(np.asarray(legacy.normals).astype(np.float32), normals)
    np.testing.assert_allclose(np.asarray(legacy.colors) * 255.0, colors, atol=1e-9)
    tensor = o3d.t.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(tensor.point.positions.numpy(), points)
    np.testing.assert_array_equal(tensor.point.normals.numpy(), normals)
    np.testing.assert_array_equal(tensor.point.colors.numpy(), colors)
    np.testing.assert_array_equal(tensor.point["radius"].numpy()[:, 0], radius)


@pytest.mark.parametrize("binary", [True, False])
def test_diffloc_mesh_opens_in_trimesh_and_open3d(tmp_path: Path, binary: bool):
    points, normals, colors = cloud(6)
    faces = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 0], [1, 3, 5]], dtype=np.int32)
    vertex = {axis: points[:, i] for i, axis in enumerate("xyz")}
    vertex |= {axis: normals[:, i] for i, axis in enumerate(("nx", "ny", "nz"))}
    vertex |= {channel: colors[:, i] for i, channel in enumerate(("red", "green", "blue"))}
    path = tmp_path / "m.ply"
    write_ply(path, vertex, faces, binary=binary)

    mesh = trimesh.load(path, process=False)
    np.testing.assert_array_equal(mesh.vertices, points.astype(np.float64))
    np.testing.assert_array_equal(mesh.faces, faces)
    np.testing.assert_array_equal(mesh.vertex_normals, normals.astype(np.float64))
    np.testing.assert_array_equal(mesh.visual.vertex_colors[:, :3], colors)

    o3d_mesh = open3d().io.read_triangle_mesh(str(path))
    np.testing.assert_array_equal(np.asarray(o3d_mesh.vertices).astype(np.float32), points)
    np.testing.assert_array_equal(np.asarray(o3d_mesh.triangles), faces)
    np.testing.assert_array_equal(np.asarray(o3d_mesh.vertex_normals).astype(np.float32), normals)
    np.testing.assert_allclose(np.asarray(o3d_mesh.vertex_colors) * 255.0, colors, atol=1e-9)


@pytest.mark.parametrize("encoding", ["binary", "ascii"])
def test_trimesh_files_are_read_with_the_same_values(tmp_path: Path, encoding: str):
    points, normals, colors = cloud(6)
    faces = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 0], [1, 3, 5]])
    rgba = np.concatenate([colors, np.full((6, 1), 255, np.uint8)], axis=1)
    mesh = trimesh.Trimesh(points, faces, vertex_normals=normals, vertex_colors=rgba, process=False)
    path = tmp_path / "m.ply"
    path.write_bytes(mesh.export(file_type="ply", encoding=encoding, include_attributes=True))
    vertex, got_faces = read_ply(path)
    np.testing.assert_array_equal(got_faces, faces)
    got = read_point_cloud(path)
    digits = 1e-7 if encoding == "ascii" else 0.0  # trimesh's ASCII writer prints 8 decimals
    np.testing.assert_allclose(got.points, points, rtol=0, atol=digits)
    np.testing.assert_allclose(got.normals, normals, rtol=0, atol=digits)
    np.testing.assert_array_equal(got.colors, colors / np.float32(255))
    np.testing.assert_array_equal(vertex["alpha"], np.full(6, 255, np.uint8))

    points_only = tmp_path / "c.ply"
    points_only.write_bytes(trimesh.PointCloud(points, colors=rgba).export(file_type="ply"))
    got = read_point_cloud(points_only)
    np.testing.assert_array_equal(got.points, points)
    np.testing.assert_array_equal(got.colors, colors / np.float32(255))


@pytest.mark.parametrize("ascii_format", [False, True])
def test_open3d_files_are_read_with_the_same_values(tmp_path: Path, ascii_format: bool):
    o3d = open3d()
    points, normals, colors = cloud()
    legacy = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    legacy.normals = o3d.utility.Vector3dVector(normals.astype(np.float64))
    legacy.colors = o3d.utility.Vector3dVector(colors / 255.0)
    path = tmp_path / "legacy.ply"
    assert o3d.io.write_point_cloud(str(path), legacy, write_ascii=ascii_format)
    got = read_point_cloud(path)
    tolerance = 1e-5 if ascii_format else 0.0  # open3d's ASCII writer prints 6 digits
    np.testing.assert_allclose(got.points, points, rtol=tolerance, atol=tolerance)
    np.testing.assert_allclose(got.normals, normals, rtol=tolerance, atol=tolerance)
    np.testing.assert_array_equal(got.colors, colors / np.float32(255))

    tensor = o3d.t.geometry.PointCloud(o3d.core.Tensor(points))
    tensor.point.normals = o3d.core.Tensor(normals)
    radius = np.linspace(0.01, 0.4, 40, dtype=np.float32)[:, None]
    tensor.point["radius"] = o3d.core.Tensor(radius)
    path = tmp_path / "tensor.ply"
    assert o3d.t.io.write_point_cloud(str(path), tensor, write_ascii=ascii_format)
    got = read_point_cloud(path)
    np.testing.assert_allclose(got.points, points, rtol=tolerance, atol=tolerance)
    np.testing.assert_allclose(got.extra["radius"], radius[:, 0], rtol=tolerance, atol=tolerance)


# ---------------------------------------------------------------- one test per bad-input rule


def test_missing_file(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="nothing.ply"):
        read_ply(tmp_path / "nothing.ply")


def test_foreign_file_is_not_a_ply(tmp_path: Path):
    (tmp_path / "bad.ply").write_bytes(b"\x89PNG\r\n\x1a\n not a point cloud")
    with pytest.raises(ValueError, match=r"bad\.ply: not a PLY file"):
        read_ply(tmp_path / "bad.ply")


def test_header_without_end_header(tmp_path: Path):
    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\n" + XYZ_HEADER)
    with pytest.raises(ValueError, match=r"bad\.ply: not a PLY file trimesh can read"):
        read_ply(tmp_path / "bad.ply")


def test_unknown_property_type(tmp_path: Path):
    (tmp_path / "bad.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n1\n"
    )
    with pytest.raises(ValueError, match=r"bad\.ply.*float128"):
        read_ply(tmp_path / "bad.ply")


def test_truncated_binary_body(tmp_path: Path):
    path = tmp_path / "t.ply"
    write_point_cloud(path, np.zeros((100, 3)))
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(ValueError, match=r"t\.ply.*unexpected length"):
        read_ply(path)


def test_binary_body_longer_than_the_header_says(tmp_path: Path):
    path = tmp_path / "t.ply"
    write_point_cloud(path, np.zeros((100, 3)))
    path.write_bytes(path.read_bytes() + b"more")
    with pytest.raises(ValueError, match=r"t\.ply.*unexpected length"):
        read_ply(path)


def test_truncated_ascii_vertices(tmp_path: Path):
    path = tmp_path / "t.ply"
    write_point_cloud(path, np.ones((10, 3)), binary=False)
    path.write_text(path.read_text().rsplit("\n", 3)[0] + "\n")
    with pytest.raises(ValueError, match=r"t\.ply: truncated PLY.*declares 10.*holds 8"):
        read_ply(path)


def test_truncated_ascii_faces(tmp_path: Path):
    path = tmp_path / "m.ply"
    xyz = {a: np.zeros(3, np.float32) for a in "xyz"}
    write_ply(path, xyz, np.array([[0, 1, 2]] * 4), binary=False)
    path.write_text(path.read_text().rsplit("\n", 2)[0] + "\n")
    with pytest.raises(ValueError, match=r"m\.ply: truncated PLY.*declares 4 faces.*holds 3"):
        read_ply(path)


def test_binary_polygons_of_mixed_sizes_are_refused(tmp_path: Path):
    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 5\n" + XYZ_HEADER + "element face 2\n"
        "property list uchar int vertex_indices\nend_header\n"
    ).encode()
    faces = bytes([4]) + np.array([0, 1, 2, 3], "<i4").tobytes()
    faces += bytes([3]) + np.array([1, 2, 4], "<i4").tobytes()
    (tmp_path / "p.ply").write_bytes(header + np.zeros(15, "<f4").tobytes() + faces)
    with pytest.raises(ValueError, match=r"p\.ply.*unexpected length"):
        read_ply(tmp_path / "p.ply")


def test_ascii_value_that_is_not_a_number(tmp_path: Path):
    (tmp_path / "bad.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 1\n" + XYZ_HEADER + "end_header\n0 abc 1\n"
    )
    with pytest.raises(ValueError, match=r"bad\.ply: not a PLY file trimesh can read"):
        read_ply(tmp_path / "bad.ply")


def test_no_vertex_element(tmp_path: Path):
    (tmp_path / "bad.ply").write_text(
        "ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\n"
        "end_header\n"
    )
    with pytest.raises(ValueError, match=r"bad\.ply: PLY file has no 'vertex' element"):
        read_ply(tmp_path / "bad.ply")


def test_missing_coordinate_property(tmp_path: Path):
    (tmp_path / "bad.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nend_header\n"
    )
    with pytest.raises(ValueError, match=r"bad\.ply: PLY vertex element has no z property"):
        read_point_cloud(tmp_path / "bad.ply")
    (tmp_path / "bad2.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
        "end_header\n1 2\n"
    )
    with pytest.raises(ValueError, match=r"bad2\.ply: not a PLY file trimesh can read.*'z'"):
        read_point_cloud(tmp_path / "bad2.ply")


BAD_ASCII_PLY = {
    "list property on vertices": (
        "property list uchar float weights\nend_header\n0 0 0 2 0.5 0.5\n",
        "list properties on the vertex element",
    ),
    "face element without vertex_indices": (
        "element face 0\nproperty uchar flags\nend_header\n0 0 0\n",
        "PLY face element has no 'vertex_indices'",
    ),
    "face index out of range": (
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n3 0 0 5\n",
        "PLY faces index vertices that do not exist",
    ),
}


@pytest.mark.parametrize("case", list(BAD_ASCII_PLY))
def test_bad_one_vertex_ply_is_refused_naming_the_file(tmp_path: Path, case: str):
    tail, message = BAD_ASCII_PLY[case]
    (tmp_path / "bad.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 1\n" + XYZ_HEADER + tail
    )
    with pytest.raises(ValueError, match=r"bad\.ply: " + re.escape(message)):
        read_ply(tmp_path / "bad.ply")


@pytest.mark.parametrize(("column", "what"), [("x", "positions"), ("nx", "normals")])
def test_non_finite_values(tmp_path: Path, column: str, what: str):
    points, normals, _ = cloud(4)
    path = tmp_path / "bad.ply"
    write_point_cloud(path, points, normals)
    vertex, _ = read_ply(path)
    vertex[column][2] = np.nan
    write_ply(path, vertex)
    with pytest.raises(ValueError, match=rf"bad\.ply: 1 points have NaN or infinite {what}"):
        read_point_cloud(path)


def test_write_rejects_bad_input_and_writes_nothing(tmp_path: Path):
    with pytest.raises(ValueError, match="int64"):
        write_ply(tmp_path / "a.ply", {"x": np.zeros(3, np.int64)})
    with pytest.raises(ValueError, match="expected 3"):
        write_ply(tmp_path / "a.ply", {"x": np.zeros(3, np.float32), "y": np.zeros(2, np.float32)})
    with pytest.raises(ValueError, match="name"):
        write_ply(tmp_path / "a.ply", {"bad name": np.zeros(3, np.float32)})
    with pytest.raises(ValueError, match="clashes"):
        write_point_cloud(tmp_path / "a.ply", np.zeros((2, 3)), extra={"x": np.zeros(2)})
    with pytest.raises(ValueError, match="NaN"):
        write_point_cloud(tmp_path / "a.ply", np.full((2, 3), np.nan))
    assert list(tmp_path.iterdir()) == []
