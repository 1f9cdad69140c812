"""PLY (Stanford polygon format) point clouds and meshes: trimesh reads, diffloc writes.

Reading goes through trimesh's PLY reader (``trimesh.exchange.ply.load_ply``): ``ascii``,
``binary_little_endian`` and ``binary_big_endian`` bodies, every scalar type, any other
elements, ``face`` lists. trimesh keeps every vertex property of the file with its dtype (in
the ``_ply_raw`` entry of its metadata), so diffloc's own per-point fields (``radius``,
``confidence``, ``red_f32 green_f32 blue_f32``) and those of other tools (``intensity``, ...)
come back without a reader of diffloc's own. open3d is not used for reading: its legacy reader
drops custom properties, its tensor reader drops ``char short ushort uint`` ones, and on a
truncated or malformed body both print a warning and return partly filled arrays that cannot be
told from a good file.

On top of trimesh, diffloc checks what a loader must (any failure is a ``ValueError`` naming
the file): a file trimesh cannot decode (its reason is quoted: a bad header, a binary body of
the wrong length, text that is not a number), a missing vertex element or ``x, y, z``, fewer
rows than the header declares (a truncated ASCII file) or more (a header that undercounts),
list properties on the vertex element,
faces that index missing vertices, and in :func:`read_point_cloud` non-finite positions,
normals or colours. Known limits of trimesh's reader: binary faces must all have the same
corner count, and ASCII integers out of range for their declared type wrap silently.

Writing stays diffloc's own (:func:`write_ply`): deterministic bytes, exact dtypes, atomic.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import trimesh

from diffloc.checks import check_finite, check_shape
from diffloc.io.atomic import atomic_write_bytes

__all__ = ["PointCloudData", "read_point_cloud", "read_ply", "write_ply", "write_point_cloud"]

_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
          "f4": "float", "f8": "double"}  # fmt: skip
_FACE_LISTS = ("vertex_indices", "vertex_index")
_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")


def _load_with_trimesh(path: Path) -> tuple[dict, dict]:
    """trimesh's decoded PLY: ``(elements, mesh kwargs)``; any failure names the file."""
    try:
        with open(path, "rb") as handle:
            loaded = trimesh.exchange.ply.load_ply(handle, fix_texture=False, skip_materials=True)
    except Exception as exc:  # trimesh reports bad files with many exception types
        raise ValueError(
            f"{path}: not a PLY file trimesh can read ({type(exc).__name__}: {exc})"
        ) from exc
    return loaded["metadata"]["_ply_raw"], loaded


def _check_ascii_rows(path: Path, elements: dict) -> None:
    """An ASCII body holds no more lines than declared rows (trimesh reads only the declared
    rows and ignores the rest, so a header that undercounts would silently drop data; fewer
    rows are reported per element by :func:`_column` and :func:`_faces`)."""
    data = path.read_bytes()
    end = data.find(b"end_header")
    header = data[:end]
    if end < 0 or b"format ascii" not in header:
        return
    body = data[data.find(b"\n", end) + 1 :]
    rows = sum(1 for line in body.splitlines() if line.strip())
    declared = sum(int(spec["length"]) for spec in elements.values())
    if rows > declared:
        counts = ", ".join(f"{int(spec['length'])} {name!r}" for name, spec in elements.items())
        raise ValueError(
            f"{path}: the PLY header declares {declared} rows ({counts}) but the ASCII body holds "
            f"{rows} lines; the header's element counts do not match the file"
        )


def _column(path: Path, element: str, spec: dict, name: str) -> np.ndarray:
    """One scalar property of a decoded element as a native-order (N,) array."""
    declared = np.dtype(spec["properties"][name])
    data = spec.get("data")
    if spec["length"] == 0 or data is None:
        return np.zeros(0, dtype=declared.newbyteorder("="))
    values = np.asarray(data[name])
    if values.dtype == object:
        raise ValueError(f"{path}: PLY element {element!r} has rows of different lengths")
    values = values.reshape(len(values), -1)
    if values.shape[1] != 1:
        raise ValueError(f"{path}: PLY element {element!r} property {name!r} is not a scalar")
    if len(values) != spec["length"]:
        raise ValueError(
            f"{path}: truncated PLY: the header declares {spec['length']} {element!r} rows "
            f"but the file holds {len(values)}"
        )
    return np.array(values[:, 0], dtype=values.dtype.newbyteorder("="), order="C")


def _faces(path: Path, elements: dict, loaded: dict, num_vertices: int) -> np.ndarray | None:
    """(F, 3) int64 triangles of the ``face`` element (polygons triangulated by trimesh)."""
    if "face" not in elements:
        return None
    spec = elements["face"]
    if not any(key in spec["properties"] for key in _FACE_LISTS):
        raise ValueError(
            f"{path}: PLY face element has no 'vertex_indices' or 'vertex_index' list property"
        )
    if spec["length"] == 0:
        return np.zeros((0, 3), dtype=np.int64)
    polygons = loaded.get("faces")
    if polygons is None:
        raise ValueError(f"{path}: trimesh decoded no faces from the PLY face element")
    faces = trimesh.geometry.triangulate_quads(polygons, dtype=np.int64).reshape(-1, 3)
    data = spec["data"]
    rows = len(data if isinstance(data, np.ndarray) else next(iter(data.values())))
    if rows != spec["length"]:
        raise ValueError(
            f"{path}: truncated PLY: the header declares {spec['length']} faces "
            f"but the file holds {rows}"
        )
    if faces.size and (faces.min() < 0 or faces.max() >= num_vertices):
        raise ValueError(
            f"{path}: PLY faces index vertices that do not exist "
            f"(indices {faces.min()}..{faces.max()}, {num_vertices} vertices)"
        )
    return faces


def read_ply(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    """Read the vertex properties and the triangles of a PLY file (decoded by trimesh).

    Args:
        path: the ``.ply`` file.

    Returns:
        ``(vertex, faces)``: ``vertex`` maps each vertex property name to an (N,) array with
        the file's dtype (native byte order, in header order); ``faces`` is an (F, 3) int64
        array of vertex indices (polygons triangulated by trimesh: triangles first, then the
        split quads, then fans of larger polygons), or ``None`` when the file has no ``face``
        element.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: a file trimesh cannot decode (bad header, truncated or overlong binary
            body, non-numbers), no vertex element or no ``x, y, z``, list properties on the
            vertex element, fewer rows than the header declares, an ASCII body with more
            (trimesh alone drops the surplus rows), a face element without
            ``vertex_indices``/``vertex_index``, out-of-range face indices. The message names
            the file.

    Example:
        >>> write_ply("cloud.ply", {"x": np.zeros(2), "y": np.ones(2), "z": np.arange(2.0)})
        >>> vertex, faces = read_ply("cloud.ply")
        >>> np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1), faces
        (array([[0., 1., 0.],
               [0., 1., 1.]]), None)
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY file not found: {path}")
    elements, loaded = _load_with_trimesh(path)
    _check_ascii_rows(path, elements)
    if "vertex" not in elements:
        raise ValueError(f"{path}: PLY file has no 'vertex' element")
    spec = elements["vertex"]
    lists = [name for name, code in spec["properties"].items() if "(" in code]
    if lists:
        raise ValueError(
            f"{path}: list properties on the vertex element are not supported: {lists}"
        )
    missing = [axis for axis in "xyz" if axis not in spec["properties"]]
    if missing:
        raise ValueError(f"{path}: PLY vertex element has no {', '.join(missing)} property")
    vertex = {name: _column(path, "vertex", spec, name) for name in spec["properties"]}
    return vertex, _faces(path, elements, loaded, spec["length"])


def _as_numpy(x: np.ndarray | torch.Tensor) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def write_ply(
    path: str | os.PathLike,
    vertex: dict[str, np.ndarray],
    faces: np.ndarray | None = None,
    binary: bool = True,
    comments: list[str] | None = None,
) -> None:
    """Write vertex properties and optional triangles as a PLY file (atomically).

    Binary files are little endian. ASCII numbers are written with enough digits to read
    back exactly (``%.9g`` for float, ``%.17g`` for double). The bytes are deterministic.

    Args:
        path: the ``.ply`` file to write.
        vertex: property name -> (N,) array (or tensor) of dtype int8, uint8, int16, uint16,
            int32, uint32, float32 or float64; all of the same length N; written in dict order.
        faces: optional (F, 3) vertex indices, written as ``property list uchar int
            vertex_indices`` (``uint`` if the array is uint32).
        binary: binary little endian (default) or ASCII.
        comments: optional header comment lines.

    Raises:
        ValueError: an unsupported dtype, a bad property name, arrays of different lengths,
            faces out of range.

    Example:
        >>> x = np.array([0.0, 1.0], dtype=np.float32)
        >>> write_ply("cloud.ply", {"x": x, "y": x, "z": x, "radius": np.full(2, 0.02)})
        >>> vertex, _ = read_ply("cloud.ply")
        >>> list(vertex), vertex["radius"].dtype
        (['x', 'y', 'z', 'radius'], dtype('float64'))
    """
    path = Path(path)
    if not vertex:
        raise ValueError(f"{path}: write_ply needs at least one vertex property")
    columns: dict[str, np.ndarray] = {}
    count = None
    for name, values in vertex.items():
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise ValueError(f"{path}: bad PLY property name {name!r}")
        array = _as_numpy(values)
        if array.ndim != 1:
            raise ValueError(f"{path}: vertex property {name!r} must be 1-D, got {array.shape}")
        code = array.dtype.kind + str(array.dtype.itemsize)
        if code not in _NAMES:
            raise ValueError(
                f"{path}: vertex property {name!r} has dtype {array.dtype}, which PLY cannot "
                "store; cast it to one of int8/uint8/int16/uint16/int32/uint32/float32/float64"
            )
        if count is None:
            count = len(array)
        elif len(array) != count:
            raise ValueError(
                f"{path}: vertex property {name!r} has {len(array)} values, expected {count}"
            )
        columns[name] = array
    face_array = None
    if faces is not None:
        face_array = _as_numpy(faces)
        check_shape(face_array, "F,3", "faces")
        if face_array.dtype.kind not in "iu":
            raise ValueError(f"{path}: faces must be integers, got {face_array.dtype}")
        if face_array.size and (face_array.min() < 0 or face_array.max() >= count):
            raise ValueError(f"{path}: faces index vertices that do not exist")
        index_code = "u4" if face_array.dtype == np.uint32 else "i4"
        face_array = face_array.astype(index_code)
    lines = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0"]
    lines += [f"comment {c}" for c in (comments or [])]
    lines.append(f"element vertex {count}")
    for name, array in columns.items():
        lines.append(f"property {_NAMES[array.dtype.kind + str(array.dtype.itemsize)]} {name}")
    if face_array is not None:
        lines.append(f"element face {len(face_array)}")
        lines.append(f"property list uchar {_NAMES[face_array.dtype.str[1:]]} vertex_indices")
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii")
    if binary:
        dtype = np.dtype(
            [(n, "<" + a.dtype.kind + str(a.dtype.itemsize)) for n, a in columns.items()]
        )
        rows = np.empty(count, dtype=dtype)
        for name, array in columns.items():
            rows[name] = array
        parts = [header, rows.tobytes()]
        if face_array is not None:
            face_rows = np.empty(
                len(face_array), dtype=[("n", "u1"), ("idx", "<" + face_array.dtype.str[1:], (3,))]
            )
            face_rows["n"] = 3
            face_rows["idx"] = face_array
            parts.append(face_rows.tobytes())
        atomic_write_bytes(path, b"".join(parts))
        return
    formats = [
        "%d" if a.dtype.kind in "iu" else ("%.9g" if a.dtype.itemsize == 4 else "%.17g")
        for a in columns.values()
    ]
    body = []
    if count:
        line = " ".join(formats) + "\n"
        flat = [v for row in zip(*(a.tolist() for a in columns.values()), strict=True) for v in row]
        body.append((line * count) % tuple(flat))
    if face_array is not None and len(face_array):
        body.append(("3 %d %d %d\n" * len(face_array)) % tuple(face_array.ravel().tolist()))
    atomic_write_bytes(path, header + "".join(body).encode("ascii"))


@dataclass
class PointCloudData:
    """A point cloud read from a PLY file.

    Attributes:
        points: (N, 3) float32 positions (``x, y, z``).
        normals: (N, 3) float32 (``nx, ny, nz``) or ``None``.
        colors: (N, 3) float32 RGB in [0, 1] (``red, green, blue``) or ``None``.
        extra: every other vertex property, name -> (N,) array with the file's dtype.
    """

    points: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)


_RESERVED = ("x", "y", "z", "nx", "ny", "nz", "red", "green", "blue")


def write_point_cloud(
    path: str | os.PathLike,
    points: np.ndarray | torch.Tensor,
    normals: np.ndarray | torch.Tensor | None = None,
    colors: np.ndarray | torch.Tensor | None = None,
    extra: dict[str, np.ndarray] | None = None,
    binary: bool = True,
) -> None:
    """Write a point cloud as PLY: float32 ``x y z``, optional ``nx ny nz``, ``red green blue``.

    Args:
        path: the ``.ply`` file.
        points: (N, 3) positions (stored as float32).
        normals: optional (N, 3) normals (stored as float32).
        colors: optional (N, 3) colours: uint8, or float in [0, 1] (stored as
            ``round(255 * c)`` uchar, so float colours round trip only to 1/255).
        extra: optional name -> (N,) arrays stored as further vertex properties with their
            own dtype (e.g. ``radius``, ``confidence``, ``intensity``).
        binary: binary little endian (default) or ASCII.

    Raises:
        ShapeError: wrong shapes.
        ValueError: non-finite points, colours outside [0, 1], extra names that clash.
    """
    points_np = _as_numpy(points)
    check_shape(points_np, "N,3", "points")
    check_finite(points_np, "points")
    n = len(points_np)
    vertex: dict[str, np.ndarray] = {
        axis: np.ascontiguousarray(points_np[:, i], dtype=np.float32)
        for i, axis in enumerate("xyz")
    }
    if normals is not None:
        normals_np = _as_numpy(normals)
        check_shape(normals_np, f"{n},3", "normals")
        for i, axis in enumerate(("nx", "ny", "nz")):
            vertex[axis] = np.ascontiguousarray(normals_np[:, i], dtype=np.float32)
    if colors is not None:
        colors_np = _as_numpy(colors)
        check_shape(colors_np, f"{n},3", "colors")
        if colors_np.dtype != np.uint8:
            check_finite(colors_np, "colors")
            if colors_np.size and (colors_np.min() < 0 or colors_np.max() > 1):
                raise ValueError("float colors must be in [0, 1]")
            colors_np = np.rint(colors_np.astype(np.float64) * 255.0).astype(np.uint8)
        for i, channel in enumerate(("red", "green", "blue")):
            vertex[channel] = np.ascontiguousarray(colors_np[:, i])
    for name, values in (extra or {}).items():
        if name in _RESERVED:
            raise ValueError(f"extra property {name!r} clashes with a standard property")
        vertex[name] = _as_numpy(values)
    write_ply(path, vertex, binary=binary)


def read_point_cloud(path: str | os.PathLike) -> PointCloudData:
    """Read a point cloud PLY written by :func:`write_point_cloud` or another tool.

    Args:
        path: the ``.ply`` file.

    Returns:
        The :class:`PointCloudData`. Integer colours are divided by their type's maximum
        (255 for uchar); float colours are returned as stored. Every other vertex property
        (``radius``, ``confidence``, ``intensity``, ...) is in ``extra`` with its own dtype.

    Raises:
        FileNotFoundError: missing file.
        ValueError: a malformed file (see :func:`read_ply`), or NaN/infinite positions,
            normals or float colours; the message names the file.

    Example:
        >>> write_ply("map.ply", {a: np.arange(3.0) for a in ("x", "y", "z", "intensity")})
        >>> cloud = read_point_cloud("map.ply")
        >>> cloud.points.shape, cloud.normals, list(cloud.extra)
        ((3, 3), None, ['intensity'])
    """
    vertex, _ = read_ply(path)
    points = np.stack([vertex[a] for a in "xyz"], axis=1).astype(np.float32)
    normals = None
    if all(a in vertex for a in ("nx", "ny", "nz")):
        normals = np.stack([vertex[a] for a in ("nx", "ny", "nz")], axis=1).astype(np.float32)
    colors = None
    if all(c in vertex for c in ("red", "green", "blue")):
        raw = np.stack([vertex[c] for c in ("red", "green", "blue")], axis=1)
        if raw.dtype.kind in "iu":
            colors = raw.astype(np.float32) / np.float32(np.iinfo(raw.dtype).max)
        else:
            colors = raw.astype(np.float32)
    for name, values in (("positions", points), ("normals", normals), ("colours", colors)):
        if values is not None and not np.isfinite(values).all():
            bad = int((~np.isfinite(values).all(axis=1)).sum())
            raise ValueError(f"{path}: {bad} points have NaN or infinite {name}")
    used = {"x", "y", "z"}
    if normals is not None:
        used |= {"nx", "ny", "nz"}
    if colors is not None:
        used |= {"red", "green", "blue"}
    extra = {k: v for k, v in vertex.items() if k not in used}
    return PointCloudData(points=points, normals=normals, colors=colors, extra=extra)
