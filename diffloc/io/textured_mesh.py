"""The textured triangle mesh shared by the simulator, mesh IO and mesh maps."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diffloc.checks import check_finite, check_shape


@dataclass
class TexturedMesh:
    """A triangle mesh with per-corner texture coordinates, materials and object ids.

    Triangles are counter-clockwise seen from outside, so ``cross(v1 - v0, v2 - v0)`` points out
    of the solid. Texture coordinates wrap: ``(u, v)`` and ``(u + 1, v)`` sample the same texel,
    so one unit of ``u`` is one repeat of the material's texture. ``v = 0`` is the top row of the
    texture image.

    Attributes:
        vertices: (V, 3) float32 positions in metres.
        triangles: (F, 3) int32 vertex indices.
        corner_uvs: (F, 3, 2) float32 texture coordinates of each triangle corner.
        material_ids: (F,) int32 index into ``textures``.
        object_ids: (F,) int32; 0 is fixed structure, k > 0 is movable object k.
        textures: one (S_m, S_m, 3) float32 albedo image in [0, 1] per material.
        material_names: one name per material (used for file names, so ``[A-Za-z0-9_-]``).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    corner_uvs: np.ndarray
    material_ids: np.ndarray
    object_ids: np.ndarray
    textures: list[np.ndarray]
    material_names: list[str]

    def __post_init__(self) -> None:
        check_shape(self.vertices, "V,3", "vertices")
        check_shape(self.triangles, "F,3", "triangles")
        faces = self.triangles.shape[0]
        check_shape(self.corner_uvs, f"{faces},3,2", "corner_uvs")
        check_shape(self.material_ids, f"{faces}", "material_ids")
        check_shape(self.object_ids, f"{faces}", "object_ids")
        check_finite(self.vertices, "vertices")
        check_finite(self.corner_uvs, "corner_uvs")
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float32)
        self.triangles = np.ascontiguousarray(self.triangles, dtype=np.int32)
        self.corner_uvs = np.ascontiguousarray(self.corner_uvs, dtype=np.float32)
        self.material_ids = np.ascontiguousarray(self.material_ids, dtype=np.int32)
        self.object_ids = np.ascontiguousarray(self.object_ids, dtype=np.int32)
        if len(self.textures) != len(self.material_names):
            raise ValueError(
                f"got {len(self.textures)} textures but {len(self.material_names)} material names"
            )
        for name, texture in zip(self.material_names, self.textures, strict=True):
            check_shape(texture, "S,T,3", f"texture of material {name!r}")
        if faces and (self.triangles.min() < 0 or self.triangles.max() >= len(self.vertices)):
            raise ValueError("triangles index vertices that do not exist")
        if faces and (self.material_ids.min() < 0 or self.material_ids.max() >= len(self.textures)):
            raise ValueError("material_ids index materials that do not exist")

    @property
    def num_faces(self) -> int:
        return int(self.triangles.shape[0])

    def face_normals(self) -> np.ndarray:
        """Unit outward normals, (F, 3) float32."""
        corners = self.vertices[self.triangles]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)

    def select_faces(self, keep: np.ndarray) -> TexturedMesh:
        """A mesh with only the faces where ``keep`` (F,) bool is true; vertices are compacted."""
        check_shape(keep, f"{self.num_faces}", "keep")
        triangles = self.triangles[keep]
        used, inverse = np.unique(triangles.ravel(), return_inverse=True)
        return TexturedMesh(
            vertices=self.vertices[used],
            triangles=inverse.reshape(-1, 3).astype(np.int32),
            corner_uvs=self.corner_uvs[keep],
            material_ids=self.material_ids[keep],
            object_ids=self.object_ids[keep],
            textures=self.textures,
            material_names=self.material_names,
        )

    @staticmethod
    def concatenate(meshes: list[TexturedMesh]) -> TexturedMesh:
        """Join meshes that share the same material list (same names, same textures)."""
        if not meshes:
            raise ValueError("cannot concatenate an empty list of meshes")
        names = meshes[0].material_names
        if any(m.material_names != names for m in meshes):
            raise ValueError("meshes to concatenate must share one material list")
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return TexturedMesh(
            vertices=np.concatenate([m.vertices for m in meshes]),
            triangles=np.concatenate(
                [m.triangles + o for m, o in zip(meshes, offsets, strict=True)]
            ),
            corner_uvs=np.concatenate([m.corner_uvs for m in meshes]),
            material_ids=np.concatenate([m.material_ids for m in meshes]),
            object_ids=np.concatenate([m.object_ids for m in meshes]),
            textures=meshes[0].textures,
            material_names=names,
        )
