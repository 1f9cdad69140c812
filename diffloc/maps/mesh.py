"""Triangle mesh reconstruction from a point map with normals (screened Poisson, trimmed).

The surface is reconstructed from the lidar or terrestrial-scanner map alone (points and
normals oriented towards the sensors), never from the simulator's ground-truth mesh:

1. voxel downsampling (``voxel_size_m``; open3d averages points and normals per voxel);
2. screened Poisson reconstruction (open3d, octree ``poisson_depth``);
3. density trimming: Poisson closes the surface through space no scan saw; those vertices
   have a low density (few samples supported them), so vertices below the
   ``density_quantile`` are dropped, and so are vertices farther than ``max_distance_m`` from
   every input point;
4. quadric decimation to at most ``target_faces`` faces (open3d): Poisson tessellates flat
   walls as finely as corners, and the UV atlas and the texturing cost grow with the faces;
5. cleaning with trimesh (merged duplicate vertices, no degenerate or duplicate faces,
   connected components of fewer than ``min_component_faces`` faces dropped, unreferenced
   vertices removed);
6. a manifold fix-up (open3d): faces on edges shared by more than two faces and around
   non-manifold (bow-tie) vertices are removed, as UV atlas charting needs a manifold mesh.

Ball pivoting is not offered: Poisson with density trimming gives closed, hole-free walls from
a noisy lidar map at a fraction of the cost.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from diffloc.checks import check_finite, check_shape
from diffloc.o3d import open3d

__all__ = ["MeshReconstructionConfig", "reconstruct_mesh"]

MIN_POINTS = 100
"""Fewest map points a surface is reconstructed from."""


@dataclass
class MeshReconstructionConfig:
    """Settings of :func:`reconstruct_mesh`.

    Attributes:
        voxel_size_m: voxel of the downsampling before Poisson, metres (> 0).
        poisson_depth: octree depth of the Poisson solver (cells ``~ extent / 2^depth``).
        poisson_scale: ratio of the reconstruction cube to the points' bounding cube.
        density_quantile: vertices whose Poisson density is below this quantile are dropped.
        max_distance_m: vertices farther than this from every map point are dropped, metres.
        target_faces: quadric decimation target (0 keeps every face).
        min_component_faces: connected components with fewer faces are dropped.
        manifold_passes: rounds of removing faces at non-manifold edges and vertices.
    """

    voxel_size_m: float = 0.05
    poisson_depth: int = 8
    poisson_scale: float = 1.1
    density_quantile: float = 0.05
    max_distance_m: float = 0.12
    target_faces: int = 80_000
    min_component_faces: int = 50
    manifold_passes: int = 4

    def __post_init__(self) -> None:
        for key in ("voxel_size_m", "poisson_scale", "max_distance_m"):
            if not getattr(self, key) > 0:
                raise ValueError(f"mesh.{key} must be > 0, got {getattr(self, key)}")
        if not 0.0 <= self.density_quantile < 1.0:
            raise ValueError(
                f"mesh.density_quantile must be in [0, 1), got {self.density_quantile}"
            )
        if self.target_faces < 0:
            raise ValueError(f"mesh.target_faces must be >= 0, got {self.target_faces}")
        if not 1 <= self.poisson_depth <= 16:
            raise ValueError(f"mesh.poisson_depth must be in [1, 16], got {self.poisson_depth}")


def _poisson(points: np.ndarray, normals: np.ndarray, cfg: MeshReconstructionConfig):
    """Voxel-downsampled screened Poisson; returns the legacy open3d mesh and its densities."""
    o3d = open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    cloud.normals = o3d.utility.Vector3dVector(normals.astype(np.float64))
    cloud = cloud.voxel_down_sample(cfg.voxel_size_m)
    cloud.normalize_normals()
    mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        cloud, depth=cfg.poisson_depth, scale=cfg.poisson_scale, n_threads=1
    )
    return mesh, np.asarray(densities)


def _clean(vertices: np.ndarray, faces: np.ndarray, min_faces: int) -> trimesh.Trimesh:
    """trimesh cleaning: merge, drop degenerate / duplicate faces and small components.

    Not ``validate=True``: that also runs ``fix_normals``, which turns closed components to a
    positive volume, i.e. flips a room seen from inside (normals towards the sensor) inside out.
    """
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    mesh.update_faces(mesh.unique_faces() & mesh.nondegenerate_faces())
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, len(mesh.faces))
    sizes = np.bincount(labels)
    mesh.update_faces(sizes[labels] >= min_faces)
    mesh.remove_unreferenced_vertices()
    return mesh


def _make_manifold(mesh: trimesh.Trimesh, passes: int) -> trimesh.Trimesh:
    """Remove faces at non-manifold edges and bow-tie vertices (open3d's checks)."""
    o3d = open3d()
    legacy = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(mesh.vertices), o3d.utility.Vector3iVector(mesh.faces)
    )
    for _ in range(passes):
        legacy.remove_non_manifold_edges()
        bad = np.asarray(legacy.get_non_manifold_vertices())
        if len(bad) == 0:
            break
        legacy.remove_vertices_by_index(bad)
    legacy.remove_unreferenced_vertices()
    return trimesh.Trimesh(np.asarray(legacy.vertices), np.asarray(legacy.triangles), process=False)


def reconstruct_mesh(
    points: np.ndarray, normals: np.ndarray, cfg: MeshReconstructionConfig
) -> trimesh.Trimesh:
    """Reconstruct a trimmed, cleaned, manifold triangle mesh from a point map.

    Args:
        points: (N, 3) map points in the world frame, metres.
        normals: (N, 3) unit normals oriented out of the surface (towards the sensors).
        cfg: the reconstruction settings.

    Returns:
        A ``trimesh.Trimesh`` (float64 vertices, int64 faces) in the world frame.

    Raises:
        ValueError: shapes differ, values are not finite, fewer than ``MIN_POINTS`` points,
            zero-length normals, or nothing of the surface survives the trimming.

    Usage (a Poisson solve; ``tests/test_mesh_reconstruction.py`` runs it on small clouds)::

        mesh = reconstruct_mesh(cloud.points, cloud.normals, MeshReconstructionConfig())
    """
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    check_shape(points, "N,3", "points")
    check_shape(normals, f"{points.shape[0]},3", "normals")
    check_finite(points, "points")
    check_finite(normals, "normals")
    if len(points) < MIN_POINTS:
        raise ValueError(
            f"a mesh needs at least {MIN_POINTS} map points, got {len(points)}; "
            "is the map empty or cropped away?"
        )
    if (np.linalg.norm(normals, axis=1) < 1e-6).any():
        raise ValueError("normals must be non-zero (estimate them before meshing)")
    legacy, densities = _poisson(points, normals, cfg)
    vertices = np.asarray(legacy.vertices)
    distance, _ = cKDTree(points).query(vertices, k=1)
    drop = (densities < np.quantile(densities, cfg.density_quantile)) | (
        distance > cfg.max_distance_m
    )
    legacy.remove_vertices_by_mask(drop)
    if len(legacy.triangles) == 0:
        raise ValueError("no surface is left after density trimming; check the map's normals")
    if 0 < cfg.target_faces < len(legacy.triangles):
        legacy = legacy.simplify_quadric_decimation(cfg.target_faces)
    vertices, faces = np.asarray(legacy.vertices), np.asarray(legacy.triangles)
    mesh = _make_manifold(_clean(vertices, faces, cfg.min_component_faces), cfg.manifold_passes)
    if len(mesh.faces) == 0:
        raise ValueError("no surface is left after cleaning; the map may be too sparse")
    return mesh
