"""UV atlas of a triangle mesh and the texel -> surface point map ``A^-1`` of seed 2 Eq. 4.

The atlas comes from open3d's ``t.geometry.TriangleMesh.compute_uvatlas`` (Microsoft's UVAtlas:
charts cut so that their stretch stays below ``max_stretch``, packed into one square texture
with ``gutter`` texels between charts). The mesh is first split into partitions of about
``faces_per_partition`` faces that are charted separately: UVAtlas's cost grows faster than
linearly with the faces (a 20k-face mesh: 79 s in one partition, 3 s in eight). With several
partitions the packing order of the charts varies from run to run, so the layout is not
bitwise reproducible (the surface each chart maps is). Corner UVs
follow :class:`TexturedMesh`: ``v = 0`` is the top row, texel ``(row, col)`` of an ``S x S``
texture has its centre at ``((col + 0.5) / S, (row + 0.5) / S)``.

:func:`rasterize_atlas` inverts the atlas: every texel whose centre lies in a triangle's UV
footprint gets that triangle and its barycentric coordinates, hence a surface point. Texels
within ``margin`` texels of a chart (the gutter) take the nearest covered texel's triangle
and extrapolate on its plane, so bilinear and mip-mapped lookups at chart borders read
texture, not background.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from diffloc.checks import check_shape
from diffloc.o3d import open3d

__all__ = ["AtlasTexels", "compute_uv_atlas", "rasterize_atlas"]


def compute_uv_atlas(
    vertices: np.ndarray,
    faces: np.ndarray,
    size: int,
    gutter: float = 2.0,
    max_stretch: float = 0.16,
    faces_per_partition: int = 2500,
) -> np.ndarray:
    """Chart and pack a manifold triangle mesh into one square UV atlas.

    Args:
        vertices: (V, 3) positions.
        faces: (F, 3) vertex indices of a manifold mesh (see :mod:`diffloc.maps.mesh`).
        size: atlas side in texels (the gutter is measured at this size).
        gutter: texels between charts.
        max_stretch: UVAtlas's stretch limit in [0, 1] (0: no stretch, many charts).
        faces_per_partition: about this many faces are charted together.

    Returns:
        (F, 3, 2) float32 corner UVs in [0, 1].

    Raises:
        ValueError: empty mesh or bad sizes; RuntimeError from open3d for a non-manifold mesh.
    """
    check_shape(vertices, "V,3", "vertices")
    check_shape(faces, "F,3", "faces")
    if len(faces) == 0:
        raise ValueError("cannot build a UV atlas for a mesh without faces")
    if size < 16 or gutter < 0 or not 0.0 <= max_stretch <= 1.0 or faces_per_partition < 1:
        raise ValueError(
            "atlas needs size >= 16, gutter >= 0, max_stretch in [0, 1], faces_per_partition "
            f">= 1; got {size}, {gutter}, {max_stretch}, {faces_per_partition}"
        )
    partitions = -(-len(faces) // faces_per_partition)
    o3d = open3d()
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(np.asarray(vertices, dtype=np.float32))
    mesh.triangle.indices = o3d.core.Tensor(np.asarray(faces, dtype=np.int64))
    mesh.compute_uvatlas(
        size=size,
        gutter=gutter,
        max_stretch=max_stretch,
        parallel_partitions=partitions,
        nthreads=1,
    )
    return mesh.triangle.texture_uvs.numpy().astype(np.float32).reshape(-1, 3, 2)


@dataclass
class AtlasTexels:
    """The texels of an ``S x S`` atlas that map to the surface.

    Attributes:
        size: S.
        rows: (T,) int64 texel rows.
        cols: (T,) int64 texel columns.
        triangle_ids: (T,) int64 triangle of each texel.
        barycentric: (T, 3) float64 weights of the triangle's corners (may leave [0, 1] in the
            gutter).
        covered: (T,) bool, true where the texel centre lies in its triangle (false: gutter).
    """

    size: int
    rows: torch.Tensor
    cols: torch.Tensor
    triangle_ids: torch.Tensor
    barycentric: torch.Tensor
    covered: torch.Tensor

    def points(self, vertices: np.ndarray, faces: np.ndarray) -> torch.Tensor:
        """(T, 3) float64 surface points ``A^-1(u, v)`` of the texels."""
        corners = torch.from_numpy(np.asarray(vertices, dtype=np.float64)[faces])
        return torch.einsum("tk,tkc->tc", self.barycentric, corners[self.triangle_ids])


def _barycentric(uv: torch.Tensor, corner_uvs: torch.Tensor) -> torch.Tensor:
    """Barycentric weights (N, 3) of points uv (N, 2) in triangles corner_uvs (N, 3, 2)."""
    a, b, c = corner_uvs[:, 0], corner_uvs[:, 1], corner_uvs[:, 2]
    e1, e2, d = b - a, c - a, uv - a
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    det = torch.where(det.abs() < 1e-18, torch.full_like(det, 1e-18), det)
    w1 = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / det
    w2 = (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / det
    return torch.stack([1 - w1 - w2, w1, w2], dim=1)


def rasterize_atlas(corner_uvs: np.ndarray, size: int, margin: int = 2) -> AtlasTexels:
    """Find the triangle and barycentric coordinates of every surface texel of an atlas.

    Args:
        corner_uvs: (F, 3, 2) corner UVs in [0, 1] (``v = 0`` top row).
        size: atlas side S in texels.
        margin: gutter texels around charts that are filled from the nearest covered texel.

    Returns:
        The :class:`AtlasTexels` (covered texels first, then the gutter).

    Usage (``tests/test_mesh_reconstruction.py`` runs it on atlases of small meshes)::

        texels = rasterize_atlas(corner_uvs, 1024)
        points = texels.points(mesh.vertices, mesh.faces)  # (T, 3)
    """
    check_shape(corner_uvs, "F,3,2", "corner_uvs")
    if size < 1 or margin < 0:
        raise ValueError(f"size must be >= 1 and margin >= 0, got {size}, {margin}")
    uvs = torch.from_numpy(np.asarray(corner_uvs, dtype=np.float64)) * size  # texel units
    low = torch.floor(uvs.amin(dim=1) - 0.5).long().clamp(0, size - 1)
    high = torch.ceil(uvs.amax(dim=1) - 0.5).long().clamp(0, size - 1)
    extent = high - low + 1  # (F, 2) columns, rows of each triangle's texel box
    counts = extent[:, 0] * extent[:, 1]
    triangle = torch.repeat_interleave(torch.arange(len(uvs)), counts)
    start = torch.cumsum(counts, 0) - counts
    local = torch.arange(int(counts.sum())) - start[triangle]
    col = low[triangle, 0] + local % extent[triangle, 0]
    row = low[triangle, 1] + local // extent[triangle, 0]
    centre = torch.stack([col, row], dim=1).to(torch.float64) + 0.5
    weights = _barycentric(centre, uvs[triangle])
    inside = (weights >= -1e-9).all(dim=1)
    owner = torch.full((size * size,), -1, dtype=torch.int64)
    owner[row[inside] * size + col[inside]] = triangle[inside]
    owner_image = owner.reshape(size, size).numpy()
    covered_image = owner_image >= 0
    if not covered_image.any():
        raise ValueError("the atlas covers no texel centre; is the atlas size too small?")
    distance, (near_row, near_col) = ndimage.distance_transform_edt(
        ~covered_image, return_indices=True
    )
    take = distance <= margin
    rows, cols = np.nonzero(take)
    covered = covered_image[rows, cols]
    order = np.argsort(~covered, kind="stable")
    rows, cols, covered = rows[order], cols[order], covered[order]
    triangle_ids = torch.from_numpy(owner_image[near_row[rows, cols], near_col[rows, cols]])
    rows_t, cols_t = torch.from_numpy(rows), torch.from_numpy(cols)
    centre = torch.stack([cols_t, rows_t], dim=1).to(torch.float64) + 0.5
    return AtlasTexels(
        size=size,
        rows=rows_t,
        cols=cols_t,
        triangle_ids=triangle_ids,
        barycentric=_barycentric(centre, uvs[triangle_ids]),
        covered=torch.from_numpy(covered),
    )
