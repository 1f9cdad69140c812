"""Wavefront OBJ + MTL + PNG textures for :class:`TexturedMesh`.

Written layout for ``<dir>/scene.obj``::

    <dir>/scene.obj             v / vt / f lines, ``g object_<id>`` groups, ``usemtl <name>``
    <dir>/scene.mtl             one ``newmtl <name>`` with ``map_Kd textures/<name>.png`` each
    <dir>/textures/<name>.png   the material's albedo as an 8-bit RGB PNG

Conventions:

- Faces are written in the mesh's order. A ``g object_<id>`` line starts every run of faces
  with a new object id (followed by ``usemtl``), a ``usemtl`` line every run with a new
  material, so object ids, material ids and face order round trip.
- OBJ ``vt`` has ``v = 0`` at the bottom of the image; :class:`TexturedMesh` has ``v = 0`` at
  the top row. The file stores ``v_obj = 1 - v`` (computed in float64). UVs may lie outside
  [0, 1] (textures wrap).
- Numbers: vertices and ``u`` with ``%.9g`` (exact for float32), ``v_obj`` with Python's
  shortest float64 ``repr`` so that ``float32(1 - v_obj)`` gives back the float32 ``v``
  exactly (for ``|v|`` between 2^-29 and 2^24, or 0). Identical ``(u, v)`` pairs share one
  ``vt`` line.
- Textures are stored as ``round(255 * albedo)``; they round trip exactly when the albedo
  values are ``k / 255`` (as read from 8-bit images).

The reader also accepts OBJ files from other tools: ``v``, ``vt``, ``f`` (``v``, ``v/vt``,
``v/vt/vn``, ``v//vn``, negative indices, polygons fan-triangulated), ``g``/``o`` groups
(``object_<id>`` gives the id, other names give 0), ``usemtl``, ``mtllib``; other statements
are ignored. Faces without ``vt`` get UV (0, 0); faces before any ``usemtl`` and materials
without ``map_Kd`` get a 1x1 texture of their ``Kd`` colour (white by default).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from diffloc.io.atomic import atomic_write_text
from diffloc.io.images import read_rgb, write_rgb
from diffloc.io.textured_mesh import TexturedMesh

__all__ = ["read_textured_mesh_obj", "write_textured_mesh_obj"]

_MATERIAL_NAME = re.compile(r"^[A-Za-z0-9_-]+$")
_OBJECT_GROUP = re.compile(r"^object_(\d+)$")
_DEFAULT_MATERIAL = "default"


def _texture_uint8(texture: np.ndarray) -> np.ndarray:
    array = np.asarray(texture, dtype=np.float64)
    return np.rint(np.clip(array, 0.0, 1.0) * 255.0).astype(np.uint8)


def _unique_uvs(corner_uvs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct (u, v) pairs in order of first use, and each corner's index into them."""
    flat = np.ascontiguousarray(corner_uvs.reshape(-1, 2), dtype=np.float32)
    if len(flat) == 0:
        return flat, np.zeros(0, dtype=np.int64)
    keys = flat.view(np.uint64).reshape(-1)  # bit patterns: -0.0 and 0.0 stay distinct
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return flat[first[order]], rank[inverse.reshape(-1)]


def write_textured_mesh_obj(path: str | os.PathLike, mesh: TexturedMesh) -> Path:
    """Write ``mesh`` as OBJ + MTL + textures (each file atomically; deterministic bytes).

    Args:
        path: the ``.obj`` file; the ``.mtl`` file gets the same stem and the textures go to
            ``textures/`` next to it.
        mesh: the mesh; material names must be ``[A-Za-z0-9_-]+`` and distinct.

    Returns:
        ``path``.

    Raises:
        ValueError: a bad or repeated material name, a path not ending in ``.obj``.

    Example:
        >>> write_textured_mesh_obj(root / "map" / "mesh" / "scene.obj", mesh)
    """
    path = Path(path)
    if path.suffix.lower() != ".obj":
        raise ValueError(f"{path}: the mesh file must end in .obj")
    names = list(mesh.material_names)
    for name in names:
        if not isinstance(name, str) or not _MATERIAL_NAME.match(name):
            raise ValueError(f"{path}: material name {name!r} must match [A-Za-z0-9_-]+")
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: material names repeat: {names}")
    mtl_path = path.with_suffix(".mtl")
    for name, texture in zip(names, mesh.textures, strict=True):
        write_rgb(path.parent / "textures" / f"{name}.png", _texture_uint8(texture))
    mtl = ["# diffloc materials"]
    for name in names:
        mtl += [
            "",
            f"newmtl {name}",
            "Ka 0 0 0",
            "Kd 1 1 1",
            "Ks 0 0 0",
            "d 1",
            "illum 1",
            f"map_Kd textures/{name}.png",
        ]
    atomic_write_text(mtl_path, "\n".join(mtl) + "\n")

    vertices = mesh.vertices
    uvs, corner_vt = _unique_uvs(mesh.corner_uvs)
    parts = [
        f"# diffloc textured mesh: {len(vertices)} vertices, {mesh.num_faces} faces\n",
        f"mtllib {mtl_path.name}\n",
    ]
    if len(vertices):
        parts.append(("v %.9g %.9g %.9g\n" * len(vertices)) % tuple(vertices.ravel().tolist()))
    if len(uvs):
        u = uvs[:, 0].astype(np.float64)
        v_obj = 1.0 - uvs[:, 1].astype(np.float64)
        interleaved = np.empty(2 * len(uvs), dtype=object)
        interleaved[0::2] = u.tolist()
        interleaved[1::2] = v_obj.tolist()
        parts.append(("vt %.9g %r\n" * len(uvs)) % tuple(interleaved))
    faces = mesh.num_faces
    if faces:
        table = np.empty((faces, 6), dtype=np.int64)
        table[:, 0::2] = mesh.triangles.astype(np.int64) + 1
        table[:, 1::2] = corner_vt.reshape(faces, 3) + 1
        obj_ids, mat_ids = mesh.object_ids, mesh.material_ids
        change = np.flatnonzero((obj_ids[1:] != obj_ids[:-1]) | (mat_ids[1:] != mat_ids[:-1])) + 1
        starts = np.concatenate([[0], change, [faces]])
        previous_obj = previous_mat = None
        for start, stop in zip(starts[:-1].tolist(), starts[1:].tolist(), strict=True):
            obj, mat = int(obj_ids[start]), int(mat_ids[start])
            if obj != previous_obj:
                parts.append(f"g object_{obj}\n")
                previous_mat = None
            if mat != previous_mat:
                parts.append(f"usemtl {names[mat]}\n")
            previous_obj, previous_mat = obj, mat
            block = table[start:stop]
            parts.append(("f %d/%d %d/%d %d/%d\n" * len(block)) % tuple(block.ravel().tolist()))
    atomic_write_text(path, "".join(parts))
    return path


def _floats(path: Path, rows: list[str], width: int, what: str) -> np.ndarray:
    """(len(rows), width) float64 from the arguments of ``v``/``vt`` statements.

    Extra columns (``w``, vertex colours) are dropped.
    """
    if not rows:
        return np.zeros((0, width))
    try:
        tokens = " ".join(rows).split()
        if len(tokens) == width * len(rows):
            return np.array(tokens, dtype=np.float64).reshape(-1, width)
        values = []
        for row in rows:
            numbers = row.split()[:width]
            if len(numbers) < width:
                raise ValueError(f"{path}: '{what} {row}' has fewer than {width} numbers")
            values.append([float(x) for x in numbers])
        return np.array(values, dtype=np.float64)
    except ValueError as exc:
        if str(path) in str(exc):
            raise
        raise ValueError(f"{path}: a {what} line holds something that is not a number") from exc


# Patterns start with a literal "\n" so the regex engine can skip ahead quickly; the text is
# prefixed with "\n" so the first line is found too.
_V = re.compile(r"\nv[ \t]+([^\n]*)")
_VT = re.compile(r"\nvt[ \t]+([^\n]*)")
_MTLLIB = re.compile(r"\nmtllib[ \t]+([^\n]*)")
_ORDERED = re.compile(r"\n(f|g|o|usemtl)(?=[ \t\n]|$)(?:[ \t]+([^\n]*))?")

# (v args, vt args, f args, (#v, #vt) before each face or None, runs, mtllibs)
_Scan = tuple[list[str], list[str], list[str], list[tuple[int, int]] | None, list[tuple], list[str]]


def _group_object_id(args: str) -> int:
    match = next((m for w in args.split() if (m := _OBJECT_GROUP.match(w))), None)
    return int(match.group(1)) if match else 0


def _scan_fast(text: str) -> _Scan | None:
    """Statements by C-level regex scans.

    Returns ``None`` (use :func:`_scan_slow`) if a line starts with whitespace or faces use
    relative (negative) indices.
    """
    if text.startswith((" ", "\t")) or "\n " in text or "\n\t" in text:
        return None
    text = "\n" + text
    v_rows = _V.findall(text)
    vt_rows = _VT.findall(text)
    mtllibs = [m.strip() for m in _MTLLIB.findall(text)]
    face_rows: list[str] = []
    runs: list[tuple[int, int, str | None]] = [(0, 0, None)]
    for key, args in _ORDERED.findall(text):
        if key == "f":
            face_rows.append(args)
        elif key == "usemtl":
            runs.append((len(face_rows), runs[-1][1], args))
        else:
            runs.append((len(face_rows), _group_object_id(args), runs[-1][2]))
    if any("-" in row for row in face_rows):
        return None
    return v_rows, vt_rows, face_rows, None, runs, mtllibs


def _scan_slow(text: str) -> _Scan:
    """Line-by-line scan that records how many v/vt precede each face (negative indices)."""
    v_rows: list[str] = []
    vt_rows: list[str] = []
    face_rows: list[str] = []
    counts: list[tuple[int, int]] = []
    runs: list[tuple[int, int, str | None]] = [(0, 0, None)]
    mtllibs: list[str] = []
    for raw in text.split("\n"):
        key, _, args = raw.strip().partition(" ")
        args = args.strip()
        if key == "v":
            v_rows.append(args)
        elif key == "vt":
            vt_rows.append(args)
        elif key == "f":
            face_rows.append(args)
            counts.append((len(v_rows), len(vt_rows)))
        elif key in ("g", "o"):
            runs.append((len(face_rows), _group_object_id(args), runs[-1][2]))
        elif key == "usemtl":
            runs.append((len(face_rows), runs[-1][1], args))
        elif key == "mtllib":
            mtllibs.append(args)
    return v_rows, vt_rows, face_rows, counts, runs, mtllibs


def _read_mtl(path: Path) -> tuple[list[str], list[np.ndarray]]:
    if not path.is_file():
        raise FileNotFoundError(f"material library not found: {path}")
    names: list[str] = []
    textures: list[np.ndarray | None] = []
    colors: list[list[float]] = []
    for number, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        words = raw.split()
        if not words or words[0].startswith("#"):
            continue
        if words[0] == "newmtl":
            if len(words) < 2:
                raise ValueError(f"{path}, line {number}: 'newmtl' without a name")
            names.append(" ".join(words[1:]))
            textures.append(None)
            colors.append([1.0, 1.0, 1.0])
        elif not names:
            continue
        elif words[0] == "map_Kd" and len(words) >= 2:
            texture = read_rgb(path.parent / words[-1])
            textures[-1] = texture.permute(1, 2, 0).contiguous().numpy()
        elif words[0] == "Kd" and len(words) >= 4:
            try:
                colors[-1] = [float(x) for x in words[1:4]]
            except ValueError as exc:
                raise ValueError(f"{path}, line {number}: bad Kd colour") from exc
    out = [
        t if t is not None else np.array(c, dtype=np.float32).reshape(1, 1, 3)
        for t, c in zip(textures, colors, strict=True)
    ]
    return names, out


def _corner(token: str) -> tuple[int, int | None]:
    parts = token.split("/")
    vt = int(parts[1]) if len(parts) > 1 and parts[1] else None
    return int(parts[0]), vt


def read_textured_mesh_obj(path: str | os.PathLike) -> TexturedMesh:
    """Read an OBJ (+ MTL + textures) into a :class:`TexturedMesh`.

    Args:
        path: the ``.obj`` file.

    Returns:
        The mesh (see the module docstring for conventions).

    Raises:
        FileNotFoundError: the OBJ, its MTL or a texture is missing.
        ValueError: malformed numbers, indices out of range, unknown materials; the message
            names the file.

    Example:
        >>> mesh = read_textured_mesh_obj(root / "map" / "mesh" / "scene.obj")
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"OBJ file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a text file") from exc
    if "\r" in text:
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    scan = _scan_fast(text)
    if scan is None:
        scan = _scan_slow(text)
    v_lines, vt_lines, face_lines, face_counts, runs, mtllibs = scan

    vertices = _floats(path, v_lines, 3, "v").astype(np.float32)
    uv_file = _floats(path, vt_lines, 2, "vt")
    uvs = np.empty_like(uv_file, dtype=np.float32)
    uvs[:, 0] = uv_file[:, 0].astype(np.float32)
    uvs[:, 1] = (1.0 - uv_file[:, 1]).astype(np.float32)

    names: list[str] = []
    textures: list[np.ndarray] = []
    for lib in mtllibs:
        lib_names, lib_textures = _read_mtl(path.parent / lib)
        for name, texture in zip(lib_names, lib_textures, strict=True):
            if name not in names:
                names.append(name)
                textures.append(texture)

    n_faces_lines = len(face_lines)
    simple = all(
        line.count("/") == 3 and line.count(" ") == 2 and "//" not in line for line in face_lines
    )
    corner_v: np.ndarray
    corner_t: np.ndarray
    face_of_line: np.ndarray
    try:
        if simple:
            table = np.array(
                " ".join(face_lines).replace("/", " ").split(), dtype=np.int64
            ).reshape(-1, 6)
            simple = bool((table > 0).all())
        if simple:
            corner_v = table[:, 0::2] - 1
            corner_t = table[:, 1::2] - 1
            face_of_line = np.arange(n_faces_lines)
        else:
            tris_v, tris_t, owners = [], [], []
            counts = face_counts or [(0, 0)] * n_faces_lines  # no negative indices then
            for line_index, (line, (nv, nvt)) in enumerate(zip(face_lines, counts, strict=True)):
                corners = [_corner(tok) for tok in line.split()]
                if len(corners) < 3:
                    raise ValueError(f"{path}: face 'f {line}' has fewer than 3 corners")
                if any(v == 0 or t == 0 for v, t in corners):
                    raise ValueError(f"{path}: face 'f {line}' uses index 0 (OBJ counts from 1)")
                vs = [v - 1 if v > 0 else nv + v for v, _ in corners]
                ts = [(-1 if t is None else (t - 1 if t > 0 else nvt + t)) for _, t in corners]
                for j in range(1, len(corners) - 1):
                    tris_v.append((vs[0], vs[j], vs[j + 1]))
                    tris_t.append((ts[0], ts[j], ts[j + 1]))
                    owners.append(line_index)
            corner_v = np.array(tris_v, dtype=np.int64).reshape(-1, 3)
            corner_t = np.array(tris_t, dtype=np.int64).reshape(-1, 3)
            face_of_line = np.array(owners, dtype=np.int64)
    except ValueError as exc:
        if str(path) in str(exc):
            raise
        raise ValueError(f"{path}: a face line holds an index that is not an integer") from exc
    if corner_v.size and (corner_v.min() < 0 or corner_v.max() >= len(vertices)):
        raise ValueError(f"{path}: faces index vertices that do not exist")
    if corner_t.size and corner_t.max() >= len(uvs):
        raise ValueError(f"{path}: faces index texture coordinates that do not exist")
    if (corner_t < -1).any():
        raise ValueError(f"{path}: faces index texture coordinates that do not exist")
    padded_uvs = np.concatenate([uvs, np.zeros((1, 2), dtype=np.float32)])
    corner_uvs = padded_uvs[corner_t]  # index -1 -> the (0, 0) pad row

    run_starts = np.array([r[0] for r in runs], dtype=np.int64)
    run_of_line = np.searchsorted(run_starts, np.arange(n_faces_lines), side="right") - 1
    line_objects = np.array([r[1] for r in runs], dtype=np.int32)[run_of_line]
    run_materials = [r[2] for r in runs]
    if any(m is None for m in (run_materials[i] for i in np.unique(run_of_line).tolist())):
        if _DEFAULT_MATERIAL not in names:
            names.append(_DEFAULT_MATERIAL)
            textures.append(np.ones((1, 1, 3), dtype=np.float32))
    index_of = {name: i for i, name in enumerate(names)}
    run_material_ids = []
    for material in run_materials:
        key = _DEFAULT_MATERIAL if material is None else material
        if key not in index_of:
            run_material_ids.append(-1)
        else:
            run_material_ids.append(index_of[key])
    line_materials = np.array(run_material_ids, dtype=np.int32)[run_of_line]
    if (line_materials < 0).any():
        missing = sorted({run_materials[r] for r in run_of_line[line_materials < 0].tolist()})
        raise ValueError(f"{path}: faces use materials not defined in {mtllibs}: {missing}")
    return TexturedMesh(
        vertices=vertices.reshape(-1, 3),
        triangles=corner_v.astype(np.int32),
        corner_uvs=corner_uvs.reshape(-1, 3, 2),
        material_ids=line_materials[face_of_line],
        object_ids=line_objects[face_of_line],
        textures=textures,
        material_names=names,
    )
