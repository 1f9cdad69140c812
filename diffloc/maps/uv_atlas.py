"""UV atlas of a triangle mesh and the texel -> surface point map ``A^-1`` of seed 2 Eq. 4.

The atlas comes from xatlas (the library ``trimesh.Trimesh.unwrap`` calls; here directly, for
the gutter and the atlas size): charts grown over faces whose normals agree, within a chart
cost ``max_cost``, parameterised and packed into one atlas with ``gutter`` texels between
charts. The same mesh always gets the same atlas (``tests/test_mesh_reconstruction.py``), so a
mesh map built twice from the same inputs is the same map; open3d's UVAtlas, used before, packed
its charts in a run-dependent order. Corner UVs follow :class:`TexturedMesh`: ``v = 0`` is the
top row, texel ``(row, col)`` of an ``S x S`` texture has its centre at ``((col + 0.5) / S,
(row + 0.5) / S)``.

:func:`rasterize_atlas` inverts the atlas: every texel whose centre lies in a triangle's UV
footprint gets that triangle and its barycentric coordinates, hence a surface point. Texels
within ``margin`` texels of a chart (the gutter) take the nearest covered texel's triangle
and extrapolate on its plane, so bilinear and mip-mapped lookups at chart borders read
texture, not background.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import xatlas
from scipy import ndimage

from diffloc.checks import check_shape

__all__ = ["AtlasTexels", "compute_uv_atlas", "rasterize_atlas"]


def compute_uv_atlas(
    vertices: np.ndarray,
    faces: np.ndarray,
    size: int,
    gutter: float = 2.0,
    max_cost: float = 2.0,
) -> np.ndarray:
    """Chart and pack a triangle mesh into one square UV atlas (xatlas), deterministically.

    xatlas sizes its layout to about ``size`` texels (its own estimate of the texel density,
    so the layout's longer side may come out some 20 % over or under); the layout is scaled to
    ``size`` keeping its aspect, so the gutter between charts is ``gutter`` texels at xatlas's
    size and about that at ``size``.

    Args:
        vertices: (V, 3) positions.
        faces: (F, 3) vertex indices.
        size: atlas side in texels (the gutter is planned at about this size).
        gutter: texels between charts (rounded up to whole texels).
        max_cost: xatlas's chart cost limit (normal deviation, roundness, straightness):
            lower makes more, flatter charts.

    Returns:
        (F, 3, 2) float32 corner UVs in [0, 1], face ``i``'s corners in the order of
        ``faces[i]``.

    Raises:
        ValueError: empty mesh or bad sizes.
        RuntimeError: xatlas did not pack the mesh into one atlas.

    Example:
        >>> import trimesh
        >>> box = trimesh.creation.box()
        >>> uvs = compute_uv_atlas(box.vertices, box.faces, 64)
        >>> uvs.shape, bool((uvs >= 0).all() and (uvs <= 1).all())
        ((12, 3, 2), True)
        >>> bool((uvs == compute_uv_atlas(box.vertices, box.faces, 64)).all())
        True
    """
    check_shape(vertices, "V,3", "vertices")
    check_shape(faces, "F,3", "faces")
    if len(faces) == 0:
        raise ValueError("cannot build a UV atlas for a mesh without faces")
    if size < 16 or gutter < 0 or max_cost <= 0:
        raise ValueError(
            f"atlas needs size >= 16, gutter >= 0, max_cost > 0; got {size}, {gutter}, {max_cost}"
        )
    atlas = xatlas.Atlas()
    atlas.add_mesh(np.asarray(vertices, dtype=np.float32), np.asarray(faces, dtype=np.uint32))
    charts = xatlas.ChartOptions()
    charts.max_cost = max_cost
    pack = xatlas.PackOptions()
    pack.resolution = size
    pack.padding = math.ceil(gutter)
    atlas.generate(charts, pack)
    if atlas.atlas_count != 1:
        raise RuntimeError(f"xatlas packed the mesh into {atlas.atlas_count} atlases, not one")
    _, corner_vertices, uvs = atlas[0]  # uvs per xatlas vertex, each axis scaled to [0, 1]
    texels = uvs.astype(np.float64) * (atlas.width, atlas.height)
    corner_uvs = texels[corner_vertices] / max(atlas.width, atlas.height)
    return corner_uvs.astype(np.float32)


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
