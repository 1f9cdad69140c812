"""Wavefront OBJ + MTL + PNG textures for :class:`TexturedMesh`.

Written layout for ``<dir>/scene.obj``::

    <dir>/scene.obj             v / vt / f lines, ``g object_<id>`` groups, ``usemtl <name>``
    <dir>/scene.mtl             one ``newmtl <name>`` with ``map_Kd textures/<name>.png`` each
    <dir>/textures/<name>.png   the material's albedo as an 8-bit RGB PNG

Conventions:

- Faces are written in the mesh's order. A ``g object_<id>`` line starts every run of faces
  with a new object id (followed by ``usemtl``), a ``usemtl`` line every run with a new
  material, so object ids and material ids round trip.
- OBJ ``vt`` has ``v = 0`` at the bottom of the image; :class:`TexturedMesh` has ``v = 0`` at
  the top row. The file stores ``v_obj = 1 - v`` (computed in float64). UVs may lie outside
  [0, 1] (textures wrap).
- Numbers: vertices and ``u`` with ``%.9g`` (exact for float32), ``v_obj`` with Python's
  shortest float64 ``repr`` so that ``float32(1 - v_obj)`` gives back the float32 ``v``
  exactly (for ``|v|`` between 2^-29 and 2^24, or 0). Identical ``(u, v)`` pairs share one
  ``vt`` line.
- Textures are stored as ``round(255 * albedo)``; they round trip exactly when the albedo
  values are ``k / 255`` (as read from 8-bit images).

Reading goes through trimesh (OBJ, MTL and texture images; see
:func:`read_textured_mesh_obj` for what comes back and what diffloc checks on top). A mesh
written here reads back with the same triangles (corner positions), corner UVs, material and
object ids and textures; the faces come back grouped by object and material, and the vertex
list is rebuilt from the distinct positions.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import trimesh

from diffloc.io.atomic import atomic_write_text
from diffloc.io.images import write_rgb
from diffloc.io.textured_mesh import TexturedMesh

__all__ = ["read_textured_mesh_obj", "write_textured_mesh_obj"]

_MATERIAL_NAME = re.compile(r"^[A-Za-z0-9_-]+$")
_OBJECT_GROUP = re.compile(r"^object_(\d+)(?:_|$)")
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
        >>> mesh = TexturedMesh(
        ...     vertices=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32),
        ...     triangles=np.array([[0, 1, 2]], dtype=np.int32),
        ...     corner_uvs=np.array([[[0, 1], [1, 1], [0, 0]]], dtype=np.float32),
        ...     material_ids=np.zeros(1, dtype=np.int32),
        ...     object_ids=np.zeros(1, dtype=np.int32),
        ...     textures=[np.full((4, 4, 3), 0.5, dtype=np.float32)],
        ...     material_names=["grey"],
        ... )
        >>> write_textured_mesh_obj("mesh/scene.obj", mesh)
        PosixPath('mesh/scene.obj')
        >>> sorted(str(p) for p in Path("mesh").rglob("*"))
        ['mesh/scene.mtl', 'mesh/scene.obj', 'mesh/textures', 'mesh/textures/grey.png']
        >>> read_textured_mesh_obj("mesh/scene.obj").num_faces
        1
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


def _statements(text: str, keyword: str) -> list[str]:
    """Arguments of every ``keyword`` statement (one per line, leading blanks allowed)."""
    return [m.strip() for m in re.findall(rf"(?m)^[ \t]*{keyword}[ \t]+([^\n]*)", text)]


def _material_library(path: Path, text: str) -> tuple[Path | None, dict]:
    """The one ``mtllib`` of an OBJ parsed by trimesh: ``(mtl path or None, name -> kwargs)``."""
    libraries = _statements(text, "mtllib")
    if not libraries:
        return None, {}
    if len(libraries) > 1:
        raise ValueError(f"{path}: several mtllib statements {libraries}; trimesh reads only one")
    mtl_path = path.parent / libraries[0]
    if not mtl_path.is_file():
        raise FileNotFoundError(f"material library not found: {mtl_path}")
    mtl_text = mtl_path.read_text(encoding="utf-8")
    for texture in re.findall(r"(?im)^[ \t]*map_Kd[ \t]+([^\n]*)", mtl_text):
        if not (mtl_path.parent / texture.strip()).is_file():
            raise FileNotFoundError(f"texture not found: {mtl_path.parent / texture.strip()}")
    resolver = trimesh.resolvers.FilePathResolver(mtl_path)
    materials = trimesh.exchange.obj.parse_mtl(mtl_text, resolver=resolver)
    for block in re.split(r"(?m)^[ \t]*newmtl[ \t]+", mtl_text)[1:]:
        name = block.split("\n", 1)[0].strip()
        if re.search(r"(?im)^[ \t]*map_Kd[ \t]", block) and "image" not in materials[name]:
            raise ValueError(f"{mtl_path}: the texture of material {name!r} cannot be decoded")
    return mtl_path, materials


def _texture(material: dict) -> np.ndarray:
    """(S, T, 3) float32 albedo in [0, 1]: the ``map_Kd`` image, else a 1x1 of ``Kd``."""
    if "image" in material:
        rgb = np.asarray(material["image"].convert("RGB"), dtype=np.float32)
        return rgb / np.float32(255)
    color = material.get("kd", [1.0, 1.0, 1.0])
    return np.array(color, dtype=np.float32).reshape(1, 1, 3)


def read_textured_mesh_obj(path: str | os.PathLike) -> TexturedMesh:
    """Read an OBJ (+ MTL + textures) into a :class:`TexturedMesh`, decoded by trimesh.

    trimesh (``trimesh.load`` with ``group_material`` and ``split_groups``) parses the file
    and its material library; it splits the faces into one geometry per (group, material),
    duplicates each vertex per texture coordinate it is used with and drops unused vertices.
    The mesh diffloc builds from that:

    - faces come grouped by object id, then by material index, each group in file order;
    - vertices are the distinct positions in sorted order (shared again by the groups);
    - ``corner_uvs`` are trimesh's texture coordinates with ``v = 1 - v_obj``; faces without
      ``vt`` get (0, 0) (trimesh drops the ``vt`` of a group whose indices it cannot resolve;
      diffloc notices only when no group keeps any);
    - object ids come from the ``object_<id>`` group names (other groups give 0);
    - materials are those of the MTL file in its order (unused ones too), each with its
      ``map_Kd`` texture or a 1x1 texture of its ``Kd`` colour, plus ``default`` (white) for
      faces before any ``usemtl``.

    diffloc checks what trimesh lets pass: a missing MTL or texture file, ``usemtl`` names the
    MTL does not define, face statements trimesh skipped (e.g. indented ones), texture
    coordinates it resolved for no face at all, non-finite positions or UVs.

    Args:
        path: the ``.obj`` file.

    Returns:
        The mesh.

    Raises:
        FileNotFoundError: the OBJ, its MTL or a texture is missing.
        ValueError: a file trimesh cannot decode (its reason is quoted: non-numbers, indices
            out of range), several ``mtllib`` statements, undefined materials, lost faces or
            texture coordinates, non-finite values; the message names the file.

    Example: see :func:`write_textured_mesh_obj` (a round trip).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"OBJ file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a text file") from exc
    mtl_path, materials = _material_library(path, text)
    undefined = sorted(set(_statements(text, "usemtl")) - set(materials))
    if undefined:
        raise ValueError(f"{path}: faces use materials not defined in {mtl_path}: {undefined}")
    try:
        scene = trimesh.load(
            path, file_type="obj", process=False, group_material=True, split_groups=True,
            force="scene",
        )  # fmt: skip
    except Exception as exc:  # trimesh reports bad files with many exception types
        raise ValueError(
            f"{path}: not an OBJ file trimesh can read ({type(exc).__name__}: {exc})"
        ) from exc

    names = list(materials)
    textures = [_texture(materials[name]) for name in names]
    parts = []
    for geometry_name, geometry in scene.geometry.items():
        if not isinstance(geometry, trimesh.Trimesh):
            continue
        material = getattr(getattr(geometry.visual, "material", None), "name", None)
        if material not in materials:
            material = _DEFAULT_MATERIAL
            if material not in names:
                names.append(material)
                textures.append(np.ones((1, 1, 3), dtype=np.float32))
        match = _OBJECT_GROUP.match(geometry_name)
        parts.append((int(match.group(1)) if match else 0, names.index(material), geometry))
    parts.sort(key=lambda part: part[:2])

    corners = sum(max(len(face.split()) - 2, 0) for face in _statements(text, "f"))
    decoded = sum(len(geometry.faces) for *_, geometry in parts)
    if decoded != corners:
        raise ValueError(
            f"{path}: trimesh decoded {decoded} triangles but the face statements hold "
            f"{corners} (a face syntax it skips, e.g. an indented 'f' line)"
        )
    uses_vt = re.search(r"(?m)^[ \t]*f[ \t]+[^\n]*\d/-?\d", text) is not None
    if uses_vt and all(getattr(g.visual, "uv", None) is None for *_, g in parts):
        raise ValueError(f"{path}: faces index texture coordinates that trimesh cannot resolve")

    corner_positions, corner_uvs = [], []
    for _, _, geometry in parts:
        faces = np.asarray(geometry.faces, dtype=np.int64)
        corner_positions.append(np.asarray(geometry.vertices, dtype=np.float32)[faces])
        uv = getattr(geometry.visual, "uv", None)
        if uv is None:
            corner_uvs.append(np.zeros((len(faces), 3, 2), dtype=np.float32))
        else:
            uv = np.asarray(uv, dtype=np.float64)[faces]
            corner_uvs.append(np.stack([uv[..., 0], 1.0 - uv[..., 1]], -1).astype(np.float32))
    positions = np.concatenate(corner_positions or [np.zeros((0, 3, 3), np.float32)])
    vertices, triangles = np.unique(positions.reshape(-1, 3), axis=0, return_inverse=True)
    counts = [len(g.faces) for *_, g in parts]
    try:
        return TexturedMesh(
            vertices=vertices,
            triangles=triangles.reshape(-1, 3),
            corner_uvs=np.concatenate(corner_uvs or [np.zeros((0, 3, 2), np.float32)]),
            material_ids=np.repeat([m for _, m, _ in parts], counts).astype(np.int32),
            object_ids=np.repeat([o for o, _, _ in parts], counts).astype(np.int32),
            textures=textures,
            material_names=names,
        )
    except ValueError as exc:
        raise ValueError(f"{path}: not a valid textured mesh ({exc})") from exc
