"""PLY (Stanford polygon format) reading and writing, vectorised with numpy structured dtypes.

Supported: ``format ascii 1.0``, ``binary_little_endian 1.0`` and ``binary_big_endian 1.0``;
scalar types ``char uchar short ushort int uint float double`` and their aliases ``int8 uint8
int16 uint16 int32 uint32 float32 float64``; any vertex properties (``x, y, z``, ``nx, ny,
nz``, ``red, green, blue``, ``radius``, ``confidence``, ...); a ``face`` element with a list
property ``vertex_indices`` or ``vertex_index``; other elements are parsed for their size and
skipped; ``comment`` and ``obj_info`` lines are ignored.

Binary elements whose list properties all have the same length in every row (the usual
triangle mesh) are decoded in one ``np.frombuffer`` call. Rows with varying list lengths
(mixed polygons) fall back to a per-row loop over that element only; polygons with more than
three corners are fan-triangulated in the returned ``faces``.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from diffloc.checks import check_finite, check_shape
from diffloc.io.atomic import atomic_write_bytes

__all__ = ["PointCloudData", "read_point_cloud", "read_ply", "write_ply", "write_point_cloud"]

_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}  # fmt: skip
_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
          "f4": "float", "f8": "double"}  # fmt: skip
_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
_FACE_LISTS = ("vertex_indices", "vertex_index")
_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")


@dataclass
class _Property:
    name: str
    dtype: str  # numpy kind+size code, e.g. "f4"; for lists: the item type
    count_dtype: str | None = None  # set for list properties


@dataclass
class _Element:
    name: str
    count: int
    properties: list[_Property] = field(default_factory=list)


def _parse_header(path: Path, data: bytes) -> tuple[str, list[_Element], int]:
    """Return (format, elements, byte offset of the body)."""
    if not (data.startswith(b"ply\n") or data.startswith(b"ply\r\n")):
        raise ValueError(f"{path}: not a PLY file (it does not start with 'ply')")
    match = re.search(rb"(?m)^end_header[ \t]*(\r?\n|$)", data)
    if match is None:
        raise ValueError(f"{path}: PLY header has no 'end_header' line")
    try:
        header = data[: match.start()].decode("ascii")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: PLY header is not ASCII text") from exc
    fmt: str | None = None
    elements: list[_Element] = []
    for number, raw in enumerate(header.splitlines()[1:], start=2):
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        where = f"{path}: PLY header line {number} ({raw.strip()!r})"
        if words[0] == "format":
            if len(words) != 3 or words[1] not in _FORMATS or words[2] != "1.0":
                raise ValueError(
                    f"{where}: expected 'format ascii|binary_little_endian|binary_big_endian 1.0'"
                )
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise ValueError(f"{where}: expected 'element <name> <count>'")
            elements.append(_Element(words[1], int(words[2])))
        elif words[0] == "property":
            if not elements:
                raise ValueError(f"{where}: property before any element")
            if len(words) == 3 and words[1] in _TYPES:
                prop = _Property(words[2], _TYPES[words[1]])
            elif (
                len(words) == 5 and words[1] == "list" and words[2] in _TYPES and words[3] in _TYPES
            ):
                if _TYPES[words[2]][0] == "f":
                    raise ValueError(f"{where}: list count type must be an integer type")
                prop = _Property(words[4], _TYPES[words[3]], count_dtype=_TYPES[words[2]])
            else:
                raise ValueError(
                    f"{where}: expected 'property <type> <name>' or "
                    "'property list <count type> <item type> <name>' with types "
                    f"from {sorted(_TYPES)}"
                )
            if any(p.name == prop.name for p in elements[-1].properties):
                raise ValueError(f"{where}: property {prop.name!r} repeated")
            elements[-1].properties.append(prop)
        else:
            raise ValueError(f"{where}: unknown header keyword {words[0]!r}")
    if fmt is None:
        raise ValueError(f"{path}: PLY header has no 'format' line")
    return fmt, elements, match.end()


def _scalar_dtype(props: list[_Property], order: str) -> np.dtype:
    return np.dtype([(p.name, order + p.dtype) for p in props])


def _native(array: np.ndarray) -> np.ndarray:
    """A C-contiguous copy in native byte order (never a view of the file buffer)."""
    return np.array(array, dtype=array.dtype.newbyteorder("="), order="C")


def _read_binary_element(
    path: Path, data: bytes, offset: int, element: _Element, order: str
) -> tuple[dict[str, np.ndarray | list[np.ndarray]], int]:
    """Decode one element; list properties come back as (N, k) arrays or lists of arrays."""
    count, props = element.count, element.properties

    def truncated(need: int) -> ValueError:
        return ValueError(
            f"{path}: truncated PLY: element {element.name!r} ({count} rows) needs {need} bytes "
            f"at offset {offset}, but the file has only {len(data) - offset} left"
        )

    if count == 0:
        return {p.name: np.zeros(0, dtype=p.dtype) for p in props}, offset
    lists = [p for p in props if p.count_dtype is not None]
    if not lists:
        dtype = _scalar_dtype(props, order)
        need = dtype.itemsize * count
        if offset + need > len(data):
            raise truncated(need)
        rows = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
        return {p.name: _native(rows[p.name]) for p in props}, offset + need
    # Guess fixed list lengths from the first row, then verify every row.
    lengths: dict[str, int] = {}
    cursor = offset
    for p in props:
        if p.count_dtype is None:
            cursor += np.dtype(p.dtype).itemsize
            continue
        if cursor + np.dtype(p.count_dtype).itemsize > len(data):
            raise truncated(cursor - offset + np.dtype(p.count_dtype).itemsize)
        k = int(np.frombuffer(data, dtype=order + p.count_dtype, count=1, offset=cursor)[0])
        lengths[p.name] = k
        cursor += np.dtype(p.count_dtype).itemsize + k * np.dtype(p.dtype).itemsize
    fields: list[tuple] = []
    for p in props:
        if p.count_dtype is None:
            fields.append((p.name, order + p.dtype))
        else:
            fields.append((f"__n_{p.name}", order + p.count_dtype))
            fields.append((p.name, order + p.dtype, (lengths[p.name],)))
    dtype = np.dtype(fields)
    need = dtype.itemsize * count
    if offset + need <= len(data):
        rows = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
        if all((rows[f"__n_{p.name}"] == lengths[p.name]).all() for p in lists):
            out: dict[str, np.ndarray | list[np.ndarray]] = {}
            for p in props:
                values = rows[p.name]
                out[p.name] = _native(values.reshape(count, -1) if p.count_dtype else values)
            return out, offset + need
    # Slow path: list lengths vary between rows.
    columns: dict[str, list] = {p.name: [] for p in props}
    cursor = offset
    for _ in range(count):
        for p in props:
            if p.count_dtype is None:
                size = np.dtype(p.dtype).itemsize
                if cursor + size > len(data):
                    raise truncated(cursor + size - offset)
                columns[p.name].append(np.frombuffer(data, order + p.dtype, 1, cursor)[0])
                cursor += size
            else:
                size = np.dtype(p.count_dtype).itemsize
                if cursor + size > len(data):
                    raise truncated(cursor + size - offset)
                k = int(np.frombuffer(data, order + p.count_dtype, 1, cursor)[0])
                cursor += size
                item = np.dtype(p.dtype).itemsize
                if cursor + k * item > len(data):
                    raise truncated(cursor + k * item - offset)
                columns[p.name].append(_native(np.frombuffer(data, order + p.dtype, k, cursor)))
                cursor += k * item
    result: dict[str, np.ndarray | list[np.ndarray]] = {}
    for p in props:
        if p.count_dtype is None:
            result[p.name] = np.array(columns[p.name], dtype=p.dtype)
        else:
            result[p.name] = columns[p.name]
    return result, cursor


def _to_numbers(path: Path, tokens: np.ndarray, dtype: str, what: str) -> np.ndarray:
    try:
        if dtype[0] == "f":
            return tokens.astype(np.float64).astype(dtype)
        values = tokens.astype(np.int64)
    except ValueError as exc:
        raise ValueError(f"{path}: PLY {what} holds a value that is not a number") from exc
    info = np.iinfo(dtype)
    if values.size and (values.min() < info.min or values.max() > info.max):
        raise ValueError(f"{path}: PLY {what} holds a value out of range for {_NAMES[dtype]}")
    return values.astype(dtype)


def _read_ascii_element(
    path: Path, tokens: np.ndarray, pos: int, element: _Element
) -> tuple[dict[str, np.ndarray | list[np.ndarray]], int]:
    count, props = element.count, element.properties

    def truncated() -> ValueError:
        return ValueError(
            f"{path}: truncated PLY: element {element.name!r} expects {count} rows, "
            "the file ends early"
        )

    if count == 0:
        return {p.name: np.zeros(0, dtype=p.dtype) for p in props}, pos
    width: list[int] = []
    cursor = pos
    for p in props:  # row layout guessed from the first row
        if p.count_dtype is None:
            width.append(1)
            cursor += 1
        else:
            if cursor >= len(tokens):
                raise truncated()
            k = int(_to_numbers(path, tokens[cursor : cursor + 1], "i8", "list count")[0])
            width.append(1 + k)
            cursor += 1 + k
    stride = sum(width)
    if pos + stride * count <= len(tokens):
        block = tokens[pos : pos + stride * count].reshape(count, stride)
        starts = np.cumsum([0] + width[:-1])
        uniform = all(
            p.count_dtype is None
            or (_to_numbers(path, block[:, s], "i8", "list count") == w - 1).all()
            for p, s, w in zip(props, starts, width, strict=True)
        )
        if uniform:
            out: dict[str, np.ndarray | list[np.ndarray]] = {}
            for p, s, w in zip(props, starts, width, strict=True):
                what = f"element {element.name!r} property {p.name!r}"
                if p.count_dtype is None:
                    out[p.name] = _to_numbers(path, block[:, s], p.dtype, what)
                else:
                    out[p.name] = _to_numbers(path, block[:, s + 1 : s + w], p.dtype, what)
            return out, pos + stride * count
    columns: dict[str, list] = {p.name: [] for p in props}
    cursor = pos
    for _ in range(count):
        for p in props:
            what = f"element {element.name!r} property {p.name!r}"
            if cursor >= len(tokens):
                raise truncated()
            if p.count_dtype is None:
                columns[p.name].append(
                    _to_numbers(path, tokens[cursor : cursor + 1], p.dtype, what)[0]
                )
                cursor += 1
            else:
                k = int(_to_numbers(path, tokens[cursor : cursor + 1], "i8", "list count")[0])
                if cursor + 1 + k > len(tokens):
                    raise truncated()
                columns[p.name].append(
                    _to_numbers(path, tokens[cursor + 1 : cursor + 1 + k], p.dtype, what)
                )
                cursor += 1 + k
    result: dict[str, np.ndarray | list[np.ndarray]] = {}
    for p in props:
        if p.count_dtype is None:
            result[p.name] = np.array(columns[p.name], dtype=p.dtype)
        else:
            result[p.name] = columns[p.name]
    return result, cursor


def _triangulate(path: Path, polygons: np.ndarray | list[np.ndarray]) -> np.ndarray:
    """(F, 3) triangles from (F, k) polygons or a list of variable-length polygons (fans)."""
    if isinstance(polygons, np.ndarray):
        if polygons.shape[1] == 3:
            return polygons
        if polygons.shape[1] < 3:
            raise ValueError(f"{path}: PLY faces have fewer than 3 corners")
        polygons = list(polygons)
    dtype = polygons[0].dtype if polygons else np.dtype("i4")
    triangles = []
    for poly in polygons:
        if len(poly) < 3:
            raise ValueError(f"{path}: a PLY face has fewer than 3 corners")
        for j in range(1, len(poly) - 1):
            triangles.append((poly[0], poly[j], poly[j + 1]))
    return np.array(triangles, dtype=dtype).reshape(-1, 3)


def read_ply(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    """Read the vertex properties and the triangles of a PLY file.

    Args:
        path: the ``.ply`` file.

    Returns:
        ``(vertex, faces)``: ``vertex`` maps each vertex property name to an (N,) array with
        the file's dtype (native byte order, in header order); ``faces`` is an (F, 3) array of
        vertex indices with the file's list item dtype (polygons fan-triangulated), or ``None``
        when the file has no ``face`` element.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: malformed header, no vertex element, list properties on the vertex
            element, a face element without ``vertex_indices``/``vertex_index``, out-of-range
            face indices, or truncated data. The message names the file.

    Example:
        >>> vertex, faces = read_ply("cloud.ply")
        >>> points = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1)
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY file not found: {path}")
    data = path.read_bytes()
    fmt, elements, body = _parse_header(path, data)
    order = _FORMATS[fmt]
    parsed: dict[str, dict] = {}
    if fmt == "ascii":
        try:
            text = data[body:].decode("ascii")
        except UnicodeDecodeError as exc:
            raise ValueError(f"{path}: ASCII PLY body contains non-ASCII bytes") from exc
        tokens = np.array(text.split())
        pos = 0
        for element in elements:
            values, pos = _read_ascii_element(path, tokens, pos, element)
            parsed.setdefault(element.name, values)
    else:
        offset = body
        for element in elements:
            values, offset = _read_binary_element(path, data, offset, element, order)
            parsed.setdefault(element.name, values)
    if "vertex" not in parsed:
        raise ValueError(f"{path}: PLY file has no 'vertex' element")
    vertex_element = next(e for e in elements if e.name == "vertex")
    if any(p.count_dtype is not None for p in vertex_element.properties):
        raise ValueError(f"{path}: list properties on the vertex element are not supported")
    vertex = parsed["vertex"]
    faces = None
    if "face" in parsed:
        face_values = parsed["face"]
        key = next((k for k in _FACE_LISTS if k in face_values), None)
        face_element = next(e for e in elements if e.name == "face")
        if key is None:
            if face_element.count:
                raise ValueError(
                    f"{path}: PLY face element has no 'vertex_indices' or "
                    "'vertex_index' list property"
                )
            faces = np.zeros((0, 3), dtype=np.int32)
        else:
            faces = _triangulate(path, face_values[key])
            if faces.size and (faces.min() < 0 or faces.max() >= vertex_element.count):
                raise ValueError(
                    f"{path}: PLY faces index vertices that do not exist "
                    f"(indices {faces.min()}..{faces.max()}, "
                    f"{vertex_element.count} vertices)"
                )
    return vertex, faces


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
        >>> write_ply("cloud.ply", {"x": x, "y": y, "z": z, "radius": r})
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
        (255 for uchar); float colours are returned as stored.

    Raises:
        FileNotFoundError: missing file.
        ValueError: malformed file or no ``x, y, z`` properties.
    """
    vertex, _ = read_ply(path)
    missing = [a for a in "xyz" if a not in vertex]
    if missing:
        raise ValueError(f"{path}: PLY vertex element has no {', '.join(missing)} property")
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
    used = {"x", "y", "z"}
    if normals is not None:
        used |= {"nx", "ny", "nz"}
    if colors is not None:
        used |= {"red", "green", "blue"}
    extra = {k: v for k, v in vertex.items() if k not in used}
    return PointCloudData(points=points, normals=normals, colors=colors, extra=extra)
