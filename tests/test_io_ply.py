"""PLY reading and writing: every scalar type, custom properties, faces, formats, bad files."""

from pathlib import Path

import numpy as np
import pytest

from diffloc.io.ply import read_ply, read_point_cloud, write_ply, write_point_cloud

DTYPES = ["i1", "u1", "i2", "u2", "i4", "u4", "f4", "f8"]


def all_types_vertex(n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    vertex = {}
    for code in DTYPES:
        dtype = np.dtype(code)
        if dtype.kind == "f":
            values = (rng.standard_normal(n) * 10 ** rng.uniform(-8, 8, n)).astype(dtype)
        else:
            info = np.iinfo(dtype)
            values = rng.integers(info.min, info.max, n, endpoint=True, dtype=np.int64)
            values = values.astype(dtype)
        vertex[f"p_{code}"] = values
    vertex["x"] = rng.standard_normal(n).astype(np.float32)
    vertex["radius"] = rng.uniform(0, 1, n).astype(np.float32)
    vertex["confidence"] = rng.uniform(0, 1, n)
    return vertex


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
    assert got_faces.dtype == np.int32
    np.testing.assert_array_equal(got_faces, faces)
    before = path.read_bytes()
    write_ply(path, vertex, faces, binary=binary, comments=["made by a test"])
    assert path.read_bytes() == before, "bytes must be deterministic"


def test_no_faces_gives_none_and_empty_cloud(tmp_path: Path):
    write_ply(tmp_path / "a.ply", {"x": np.zeros(0, np.float32)})
    vertex, faces = read_ply(tmp_path / "a.ply")
    assert faces is None and vertex["x"].shape == (0,)


def test_big_endian_other_elements_comments_and_alias(tmp_path: Path):
    header = (
        b"ply\nformat binary_big_endian 1.0\ncomment hello\nobj_info scanner 3\n"
        b"element camera 1\nproperty float32 fov\nproperty list uint8 int32 misc\n"
        b"element vertex 3\nproperty float32 x\nproperty float32 y\nproperty float32 z\n"
        b"property uint16 label\n"
        b"element face 1\nproperty uint8 flags\nproperty list uint8 uint32 vertex_index\n"
        b"element edge 2\nproperty int vertex1\nproperty int vertex2\nend_header\n"
    )
    camera = np.array([1.5], ">f4").tobytes() + bytes([2]) + np.array([7, 8], ">i4").tobytes()
    xyz = np.arange(9, dtype=np.float32).reshape(3, 3)
    rows = np.empty(3, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("label", ">u2")])
    rows["x"], rows["y"], rows["z"], rows["label"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], [1, 2, 300]
    face = bytes([9, 3]) + np.array([0, 1, 2], ">u4").tobytes()
    edges = np.array([0, 1, 1, 2], ">i4").tobytes()
    path = tmp_path / "be.ply"
    path.write_bytes(header + camera + rows.tobytes() + face + edges)
    vertex, faces = read_ply(path)
    np.testing.assert_array_equal(np.stack([vertex[a] for a in "xyz"], 1), xyz)
    np.testing.assert_array_equal(vertex["label"], [1, 2, 300])
    assert vertex["label"].dtype == np.uint16 and vertex["label"].dtype.isnative
    np.testing.assert_array_equal(faces, [[0, 1, 2]])
    assert faces.dtype == np.uint32


@pytest.mark.parametrize("binary", [True, False])
def test_mixed_polygons_are_fan_triangulated(tmp_path: Path, binary: bool):
    xyz = np.arange(15, dtype=np.float32).reshape(5, 3)
    if binary:
        header = (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\n"
            b"property float y\nproperty float z\nelement face 2\n"
            b"property list uchar int vertex_indices\nend_header\n"
        )
        faces = bytes([4]) + np.array([0, 1, 2, 3], "<i4").tobytes()
        faces += bytes([3]) + np.array([1, 2, 4], "<i4").tobytes()
        data = header + xyz.astype("<f4").tobytes() + faces
    else:
        body = "".join(" ".join(str(v) for v in row) + "\n" for row in xyz)
        data = (
            "ply\r\nformat ascii 1.0\r\nelement vertex 5\r\nproperty float x\r\n"
            "property float y\r\nproperty float z\r\nelement face 2\r\n"
            "property list uchar int vertex_indices\r\nend_header\r\n"
            + body
            + "4 0 1 2 3\r\n3 1 2 4\r\n"
        ).encode()
    (tmp_path / "p.ply").write_bytes(data)
    vertex, faces = read_ply(tmp_path / "p.ply")
    np.testing.assert_array_equal(faces, [[0, 1, 2], [0, 2, 3], [1, 2, 4]])
    np.testing.assert_array_equal(vertex["z"], xyz[:, 2])


@pytest.mark.parametrize("binary", [True, False])
def test_point_cloud_round_trip(tmp_path: Path, binary: bool):
    rng = np.random.default_rng(1)
    points = rng.standard_normal((40, 3)).astype(np.float32)
    normals = rng.standard_normal((40, 3)).astype(np.float32)
    colors = rng.integers(0, 256, (40, 3)).astype(np.uint8)
    extra = {
        "radius": rng.uniform(0, 1, 40).astype(np.float32),
        "confidence": rng.integers(0, 9, 40).astype(np.uint8),
    }
    write_point_cloud(tmp_path / "c.ply", points, normals, colors, extra, binary=binary)
    cloud = read_point_cloud(tmp_path / "c.ply")
    np.testing.assert_array_equal(cloud.points, points)
    np.testing.assert_array_equal(cloud.normals, normals)
    np.testing.assert_array_equal(cloud.colors, colors.astype(np.float32) / np.float32(255))
    assert cloud.colors.dtype == np.float32
    assert list(cloud.extra) == ["radius", "confidence"]
    for name, values in extra.items():
        np.testing.assert_array_equal(cloud.extra[name], values)
        assert cloud.extra[name].dtype == values.dtype
    # Float colours in [0, 1] are stored to 1/255.
    write_point_cloud(tmp_path / "f.ply", points, colors=colors / 255.0)
    np.testing.assert_array_equal(read_point_cloud(tmp_path / "f.ply").colors, cloud.colors)
    plain = read_point_cloud(tmp_path / "f.ply")
    assert plain.normals is None and plain.extra == {}


def test_truncated_binary_names_file(tmp_path: Path):
    path = tmp_path / "t.ply"
    write_point_cloud(path, np.zeros((100, 3)))
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(ValueError, match=r"t\.ply.*truncated"):
        read_ply(path)


def test_truncated_ascii_names_file(tmp_path: Path):
    path = tmp_path / "t.ply"
    write_point_cloud(path, np.ones((10, 3)), binary=False)
    path.write_text(path.read_text().rsplit("\n", 3)[0])
    with pytest.raises(ValueError, match=r"t\.ply.*truncated"):
        read_ply(path)


def test_truncated_faces_names_file(tmp_path: Path):
    path = tmp_path / "m.ply"
    write_ply(path, {"x": np.zeros(3, np.float32)}, np.array([[0, 1, 2]] * 4))
    path.write_bytes(path.read_bytes()[:-3])
    with pytest.raises(ValueError, match=r"m\.ply.*truncated"):
        read_ply(path)


@pytest.mark.parametrize(
    ("header", "message"),
    [
        ("plx\nformat ascii 1.0\nend_header\n", "not a PLY"),
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "end_header"),
        ("ply\nformat binary_middle_endian 1.0\nend_header\n", "format"),
        ("ply\nformat ascii 2.0\nend_header\n", "format"),
        ("ply\nelement vertex 1\nproperty float x\nend_header\n0\n", "no 'format'"),
        ("ply\nformat ascii 1.0\nproperty float x\nend_header\n", "before any element"),
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n", "property"),
        ("ply\nformat ascii 1.0\nelement vertex one\nend_header\n", "element"),
        (
            "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\nabc\n",
            "not a number",
        ),
        ("ply\nformat ascii 1.0\nelement face 0\nend_header\n", "no 'vertex'"),
        (
            "ply\nformat ascii 1.0\nelement vertex 1\nproperty uchar x\nend_header\n300\n",
            "out of range",
        ),
    ],
)
def test_malformed_files_name_the_file(tmp_path: Path, header: str, message: str):
    path = tmp_path / "bad.ply"
    path.write_text(header)
    with pytest.raises(ValueError, match=message) as info:
        read_ply(path)
    assert "bad.ply" in str(info.value)


def test_face_index_out_of_range(tmp_path: Path):
    path = tmp_path / "bad.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n0\n3 0 0 5\n"
    )
    with pytest.raises(ValueError, match="do not exist"):
        read_ply(path)


def test_missing_file(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="nothing.ply"):
        read_ply(tmp_path / "nothing.ply")


def test_write_rejects_bad_input(tmp_path: Path):
    with pytest.raises(ValueError, match="int64"):
        write_ply(tmp_path / "a.ply", {"x": np.zeros(3, np.int64)})
    with pytest.raises(ValueError, match="expected 3"):
        write_ply(tmp_path / "a.ply", {"x": np.zeros(3, np.float32), "y": np.zeros(2, np.float32)})
    with pytest.raises(ValueError, match="name"):
        write_ply(tmp_path / "a.ply", {"bad name": np.zeros(3, np.float32)})
    with pytest.raises(ValueError, match="clashes"):
        write_point_cloud(tmp_path / "a.ply", np.zeros((2, 3)), extra={"x": np.zeros(2)})
    assert not (tmp_path / "a.ply").exists()
