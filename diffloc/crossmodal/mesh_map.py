"""A textured mesh map from a point map and the mapping images (seed 2 III-D, Eq. 3-4).

Reconstruction (:mod:`diffloc.maps.mesh`) -> UV atlas and texel surface points
(:mod:`diffloc.maps.uv_atlas`) -> exposure-compensated blend of the nearest unoccluded
mapping views per texel (:mod:`diffloc.render.mesh_texturing`) -> one
:class:`~diffloc.io.textured_mesh.TexturedMesh` with a single atlas material. Texels no view
sees (and atlas texels between charts) take the colour of the nearest textured texel, so
mip-mapped lookups stay on texture.

:func:`textured_mesh_from_dataset` reads only what a user with real data has: the point map
(``map/lidar_map.ply`` or ``map/tls_map.ply``), and the mapping sequence's images, poses and
calibration. It never opens the simulator's ground-truth mesh (``map/mesh*``) nor its
recorded exposures (``<sequence>/exposure.txt``).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy import ndimage

from diffloc.geometry.camera import PinholeCamera
from diffloc.io.dataset import MAP_FILES, read_sequence
from diffloc.io.ply import read_point_cloud
from diffloc.io.textured_mesh import TexturedMesh
from diffloc.maps.mesh import MeshReconstructionConfig, reconstruct_mesh
from diffloc.maps.uv_atlas import compute_uv_atlas, rasterize_atlas
from diffloc.render.exposure import ExposureEstimate
from diffloc.render.mesh_texturing import TextureBlendConfig, texture_texels
from diffloc.render.raycast import MeshRaycaster

__all__ = [
    "POINT_MAPS",
    "TexturedMeshConfig",
    "TexturedMeshMap",
    "build_textured_mesh",
    "texture_mesh",
    "textured_mesh_from_dataset",
]

POINT_MAPS = ("lidar_map", "tls_map")
"""The point maps a mesh may be reconstructed from."""


@dataclass
class TexturedMeshConfig:
    """Settings of the textured mesh map.

    Attributes:
        reconstruction: surface reconstruction.
        atlas_size: side of the square texture atlas in texels.
        atlas_gutter: texels between charts.
        atlas_max_cost: xatlas's chart cost limit (see :func:`compute_uv_atlas`).
        atlas_margin: gutter texels given surface points (see :func:`rasterize_atlas`).
        blend: the Eq. 3-4 blend.
    """

    reconstruction: MeshReconstructionConfig = field(default_factory=MeshReconstructionConfig)
    atlas_size: int = 1024
    atlas_gutter: float = 2.0
    atlas_max_cost: float = 2.0
    atlas_margin: int = 2
    blend: TextureBlendConfig = field(default_factory=TextureBlendConfig)


@dataclass
class TexturedMeshMap:
    """A textured mesh map and how it was made.

    Attributes:
        mesh: the mesh, one material ``"atlas"`` holding the (S, S, 3) texture.
        exposures: (V,) exposures used for the V mapping images (geometric mean 1).
        estimate: the exposure estimate, or ``None`` when exposures were given or switched off.
        textured_fraction: share of surface texels seen by at least one view.
        seconds: wall time per step (``reconstruct``, ``atlas``, ``texture``).
    """

    mesh: TexturedMesh
    exposures: torch.Tensor
    estimate: ExposureEstimate | None
    textured_fraction: float
    seconds: dict[str, float]


def _atlas_mesh(geometry: trimesh.Trimesh, corner_uvs: np.ndarray, texture: np.ndarray):
    faces = len(geometry.faces)
    return TexturedMesh(
        vertices=np.asarray(geometry.vertices, dtype=np.float32),
        triangles=np.asarray(geometry.faces, dtype=np.int32),
        corner_uvs=corner_uvs,
        material_ids=np.zeros(faces, dtype=np.int32),
        object_ids=np.zeros(faces, dtype=np.int32),
        textures=[texture],
        material_names=["atlas"],
    )


def texture_mesh(
    geometry: trimesh.Trimesh,
    images: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    cfg: TexturedMeshConfig,
    exposures: str | torch.Tensor = "estimated",
    show_progress: bool = False,
) -> TexturedMeshMap:
    """UV-atlas and texture a reconstructed mesh from mapping images.

    Args:
        geometry: a manifold mesh (:func:`~diffloc.maps.mesh.reconstruct_mesh`).
        images: (V, 3, H, W) float32 mapping images in [0, 1].
        T_wc: (V, 4, 4) camera-to-world poses of the images.
        camera: the unbatched camera.
        cfg: the settings.
        exposures: ``"estimated"``, ``"none"`` or known (V,) exposures (an oracle if they
            come from ground truth).
        show_progress: progress bars.

    Returns:
        The :class:`TexturedMeshMap` (``seconds`` without ``reconstruct``).
    """
    size = cfg.atlas_size
    start = time.perf_counter()
    corner_uvs = compute_uv_atlas(
        geometry.vertices, geometry.faces, size, cfg.atlas_gutter, cfg.atlas_max_cost
    )
    texels = rasterize_atlas(corner_uvs, size, cfg.atlas_margin)
    points = texels.points(geometry.vertices, geometry.faces)
    normals = torch.from_numpy(np.array(geometry.face_normals))[texels.triangle_ids]
    atlas_s = time.perf_counter() - start
    start = time.perf_counter()
    blank = np.zeros((size, size, 3), dtype=np.float32)
    raycaster = MeshRaycaster(_atlas_mesh(geometry, corner_uvs, blank))
    blended = texture_texels(
        points, normals, raycaster, images, T_wc, camera, cfg.blend, exposures, show_progress
    )
    seen = blended.view_count > 0
    textured = np.zeros((size, size), dtype=bool)
    image = np.zeros((size, size, 3), dtype=np.float32)
    rows, cols = texels.rows[seen].numpy(), texels.cols[seen].numpy()
    textured[rows, cols] = True
    image[rows, cols] = blended.colors[seen].numpy()
    if not textured.any():
        raise ValueError("no mapping image sees the mesh; check the poses and the map frame")
    _, (near_row, near_col) = ndimage.distance_transform_edt(~textured, return_indices=True)
    image = image[near_row, near_col]
    texture_s = time.perf_counter() - start
    surface = texels.covered
    fraction = float((seen & surface).sum()) / max(int(surface.sum()), 1)
    return TexturedMeshMap(
        mesh=_atlas_mesh(geometry, corner_uvs, image),
        exposures=blended.exposures,
        estimate=blended.estimate,
        textured_fraction=fraction,
        seconds={"atlas": atlas_s, "texture": texture_s},
    )


def build_textured_mesh(
    points: np.ndarray,
    normals: np.ndarray,
    images: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    cfg: TexturedMeshConfig,
    exposures: str | torch.Tensor = "estimated",
    show_progress: bool = False,
) -> TexturedMeshMap:
    """Reconstruct a mesh from a point map and texture it (see :func:`texture_mesh`).

    Args:
        points: (N, 3) point map, world frame.
        normals: (N, 3) its outward normals.
        images, T_wc, camera, cfg, exposures, show_progress: as in :func:`texture_mesh`.

    Returns:
        The :class:`TexturedMeshMap`.
    """
    start = time.perf_counter()
    geometry = reconstruct_mesh(points, normals, cfg.reconstruction)
    reconstruct_s = time.perf_counter() - start
    result = texture_mesh(geometry, images, T_wc, camera, cfg, exposures, show_progress)
    result.seconds = {"reconstruct": reconstruct_s, **result.seconds}
    return result


def textured_mesh_from_dataset(
    root: str | os.PathLike,
    point_map: str,
    cfg: TexturedMeshConfig,
    sequence: str = "mapping",
    frames: np.ndarray | None = None,
    exposures: str | torch.Tensor = "estimated",
    show_progress: bool = False,
) -> TexturedMeshMap:
    """The textured mesh map of a dataset folder from one of its point maps.

    Args:
        root: the dataset folder (:mod:`diffloc.io.dataset`).
        point_map: ``"lidar_map"`` or ``"tls_map"``; the map must have normals.
        cfg: the settings.
        sequence: the mapping sequence whose images texture the mesh.
        frames: (K,) indices of the frames to use (all by default; leave held-out ones out).
        exposures: as in :func:`texture_mesh`.
        show_progress: progress bars.

    Returns:
        The :class:`TexturedMeshMap`.

    Raises:
        ValueError: an unknown point map, a map without normals.
        FileNotFoundError: the point map or the sequence is missing.
    """
    if point_map not in POINT_MAPS:
        raise ValueError(f"point_map must be one of {POINT_MAPS}, got {point_map!r}")
    path = Path(root) / MAP_FILES[point_map]
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no {point_map}; simulate or build the map first")
    cloud = read_point_cloud(path)
    if cloud.normals is None:
        raise ValueError(f"{path}: the point map has no normals (nx, ny, nz); mesh needs them")
    seq = read_sequence(Path(root), sequence)
    ids = np.arange(len(seq)) if frames is None else np.asarray(frames, dtype=np.int64)
    if ids.ndim != 1 or len(ids) == 0 or ids.min() < 0 or ids.max() >= len(seq):
        raise ValueError(f"frames must be indices into the {len(seq)} frames of {sequence!r}")
    images = torch.stack([seq.load_rgb(int(i)) for i in ids])
    return build_textured_mesh(
        cloud.points,
        cloud.normals,
        images,
        seq.T_wc[ids],
        seq.camera,
        cfg,
        exposures,
        show_progress,
    )
