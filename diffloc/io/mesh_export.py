"""Export a single-texture :class:`TexturedMesh` (a texture atlas) through trimesh.

- OBJ + MTL + PNG (:func:`write_atlas_obj`): trimesh's OBJ exporter with a
  ``TextureVisuals`` material; the files open in any mesh viewer (MeshLab, Blender, open3d).
- PLY (:func:`write_atlas_ply`): binary, per-vertex ``red green blue alpha`` sampled from the
  texture at each vertex's UV (viewers without texture support show the colours) plus the UVs
  as ``s t`` vertex properties.

A per-corner UV layout has seams: a mesh vertex used with two UVs is written as two
vertices (one per distinct ``(vertex, u, v)``), so both files hold the same vertex list.
UVs follow the OBJ convention in the files (``v = 0`` at the bottom of the image), i.e.
``1 - v`` of :class:`TexturedMesh`. Every file is written atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from diffloc.io.atomic import atomic_write_bytes, atomic_write_text
from diffloc.io.textured_mesh import TexturedMesh

__all__ = ["atlas_to_trimesh", "write_atlas_obj", "write_atlas_ply"]


def _texture_uint8(texture: np.ndarray) -> np.ndarray:
    return np.rint(np.clip(np.asarray(texture, dtype=np.float64), 0, 1) * 255).astype(np.uint8)


def atlas_to_trimesh(mesh: TexturedMesh) -> trimesh.Trimesh:
    """A ``trimesh.Trimesh`` with ``TextureVisuals`` (per-vertex UVs, seams split).

    Args:
        mesh: a mesh with exactly one material (its texture is the atlas).

    Returns:
        The trimesh mesh; ``visual.uv`` in the OBJ convention (``v = 0`` at the bottom).

    Raises:
        ValueError: the mesh has no faces or more than one material.
    """
    if mesh.num_faces == 0:
        raise ValueError("cannot export a mesh without faces")
    if len(mesh.textures) != 1:
        raise ValueError(
            f"atlas export needs exactly one material, got {len(mesh.textures)}; use "
            "diffloc.io.mesh_obj.write_textured_mesh_obj for multi-material meshes"
        )
    keys = np.concatenate(
        [
            mesh.triangles.reshape(-1, 1).astype(np.float64),
            mesh.corner_uvs.reshape(-1, 2).astype(np.float64),
        ],
        axis=1,
    )
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    vertex_ids = unique[:, 0].astype(np.int64)
    uv = np.stack([unique[:, 1], 1.0 - unique[:, 2]], axis=1)
    material = trimesh.visual.material.SimpleMaterial(
        image=Image.fromarray(_texture_uint8(mesh.textures[0])), name=mesh.material_names[0]
    )
    return trimesh.Trimesh(
        vertices=mesh.vertices[vertex_ids].astype(np.float64),
        faces=inverse.reshape(-1, 3),
        visual=trimesh.visual.TextureVisuals(uv=uv, material=material),
        process=False,
    )


def write_atlas_obj(path: str | os.PathLike, mesh: TexturedMesh) -> Path:
    """Write ``<stem>.obj``, ``<stem>.mtl`` and the texture PNG beside it.

    Args:
        path: the ``.obj`` file; its folder is created.
        mesh: a single-material mesh.

    Returns:
        ``path``.
    """
    path = Path(path)
    if path.suffix.lower() != ".obj":
        raise ValueError(f"{path}: an OBJ file name must end in .obj")
    path.parent.mkdir(parents=True, exist_ok=True)
    text, files = trimesh.exchange.obj.export_obj(
        atlas_to_trimesh(mesh),
        include_normals=False,
        include_texture=True,
        return_texture=True,
        mtl_name=f"{path.stem}.mtl",
        header=None,
    )
    for name, data in files.items():
        atomic_write_bytes(path.parent / name, data)
    atomic_write_text(path, text)
    return path


def write_atlas_ply(path: str | os.PathLike, mesh: TexturedMesh) -> Path:
    """Write a binary PLY with per-vertex colours (sampled from the atlas) and ``s t`` UVs.

    Args:
        path: the ``.ply`` file; its folder is created.
        mesh: a single-material mesh.

    Returns:
        ``path``.
    """
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise ValueError(f"{path}: a PLY file name must end in .ply")
    textured = atlas_to_trimesh(mesh)
    colors = textured.visual.to_color().vertex_colors
    colored = trimesh.Trimesh(
        vertices=textured.vertices,
        faces=textured.faces,
        vertex_colors=colors,
        process=False,
    )
    colored.vertex_attributes["s"] = textured.visual.uv[:, 0].astype(np.float32)
    colored.vertex_attributes["t"] = textured.visual.uv[:, 1].astype(np.float32)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, trimesh.exchange.ply.export_ply(colored, encoding="binary"))
    return path
