"""Frustum culling of surfels: bounding spheres against the view frustum, cell by cell."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from diffloc.render.pixel_mask import _box_touches
from diffloc.render.view import _View

_CULL_SLACK = 1e-5
"""Slack of the frustum cull against float32 rounding, relative to ``1 m + |camera centre|``."""


def _frustum_planes(view: _View, height: int, width: int) -> tuple[list[list[float]], float]:
    """Camera-frame unit normals of the four side planes of the frustum, and the cull slack.

    The planes pass through the camera centre and the outer pixel edges (e.g. ``u = -0.5``,
    ``fx x + (cx + 0.5) z >= 0``); every disk point seen at a pixel centre lies strictly inside
    all four half-spaces, which only meet in front of the camera. The slack (metres) absorbs the
    float32 rounding of the distances.

    Returns:
        ``(planes, slack)``: four ``[a, b, c]`` normals pointing inwards and the slack.
    """
    planes = []
    for a, b, axis in (
        (view.fx, view.cx + 0.5, 0),
        (-view.fx, width - 0.5 - view.cx, 0),
        (view.fy, view.cy + 0.5, 1),
        (-view.fy, height - 0.5 - view.cy, 1),
    ):
        norm = math.hypot(a, b)
        normal = [0.0, 0.0, b / norm]
        normal[axis] = a / norm
        planes.append(normal)
    return planes, _CULL_SLACK * (1.0 + float(view.t_cw.norm()))


def _frustum_candidates(
    centers: torch.Tensor, radii: torch.Tensor, view: _View, height: int, width: int
) -> torch.Tensor:
    """(M,) int64 increasing indices of the surfels whose bounding sphere may be in view.

    One ``(4, 3) x (3, N)`` product gives, straight from the world-frame centres, the signed
    distances to the four side planes of :func:`_frustum_planes`; a surfel is kept when its
    radius (plus the slack) reaches into all four half-spaces. This also drops the surfels
    behind the camera; the centre's ``z > MIN_DEPTH`` is tested on the survivors. Surfels with
    NaN coordinates or radii are dropped.

    Args:
        centers: (N, 3) world-frame centres.
        radii: (N,) radii.
        view: the camera.
        height: image height.
        width: image width.

    Returns:
        (M,) int64 surfel indices, increasing.
    """
    planes, slack = _frustum_planes(view, height, width)
    normals = torch.tensor(planes, dtype=torch.float32, device=centers.device)  # (4, 3)
    distances = torch.addmm(normals @ view.t_cw, normals @ view.R_cw, centers.T)  # (4, N)
    reach = distances.amin(0).add_(radii)
    return (reach >= -slack).nonzero().view(-1)


def _concat_ranges(starts: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """(sum counts,) int64 concatenation of the ranges ``starts[i] + (0 .. counts[i] - 1)``."""
    offsets = torch.cumsum(counts, 0).sub_(counts)
    shift = torch.repeat_interleave(starts - offsets, counts)
    return torch.arange(shift.shape[0], device=starts.device).add_(shift)


def _cell_keys(cells: torch.Tensor) -> torch.Tensor:
    """(N,) int64 keys, equal exactly for equal rows, of (N, 3) int64 cell coordinates."""
    if cells.shape[0] == 0:
        return cells[:, 0]
    cells = cells - cells.amin(0)
    extent = cells.amax(0).add_(1).tolist()
    if extent[0] * extent[1] * extent[2] < 2**62:
        return (cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2]
    return torch.unique(cells, dim=0, return_inverse=True)[1]  # slower, no overflow


@dataclass(frozen=True)
class _SurfelCells:
    """The finite surfels of a map grouped by cubic cells, for frustum culling by cell.

    Cell ``g`` holds the surfels ``ids[starts[g] : starts[g + 1]]`` (increasing map indices),
    whose data are stored cell by cell in ``centers``, ``normals``, ``radii`` and ``extents``;
    its bounding sphere (float64, slightly inflated) holds all their bounding spheres, and its
    box (``box_centres +- box_extents``) all their disks' axis-aligned boxes.
    """

    ids: torch.Tensor  # (N',) int64 map indices, cell by cell
    centers: torch.Tensor  # (N', 3) float32
    normals: torch.Tensor  # (N', 3) float32
    radii: torch.Tensor  # (N',) float32
    extents: torch.Tensor  # (N', 3) float32 half-extents of the disks (:func:`_disk_extents`)
    starts: torch.Tensor  # (G + 1,) int64
    sphere_centres: torch.Tensor  # (G, 3) float64
    sphere_radii: torch.Tensor  # (G,) float64
    box_centres: torch.Tensor  # (G, 3) float64
    box_extents: torch.Tensor  # (G, 3) float64

    @classmethod
    def build(
        cls, centers: torch.Tensor, normals: torch.Tensor, radii: torch.Tensor, size: float
    ) -> _SurfelCells:
        """Group the finite surfels of (N, 3) ``centers``, ``normals``, (N,) ``radii`` by cells of
        ``size`` metres. Non-finite surfels are never drawn and are left out."""
        finite = torch.isfinite(centers).all(1) & torch.isfinite(normals).all(1)
        ids = (finite & torch.isfinite(radii)).nonzero().view(-1)
        cells = torch.floor(centers.index_select(0, ids).double() / size).long()
        _, cell, counts = torch.unique(_cell_keys(cells), return_inverse=True, return_counts=True)
        ids = ids.index_select(0, torch.sort(cell, stable=True).indices)
        starts = torch.cat((counts.new_zeros(1), torch.cumsum(counts, 0)))
        cell = torch.repeat_interleave(torch.arange(counts.shape[0], device=ids.device), counts)
        c = centers.index_select(0, ids).double()
        mean = torch.zeros(counts.shape[0], 3, dtype=torch.float64, device=ids.device)
        mean = mean.index_add_(0, cell, c).div_(counts[:, None])
        reach = (c - mean.index_select(0, cell)).norm(dim=1).add_(radii.index_select(0, ids))
        bound = torch.zeros_like(counts, dtype=torch.float64).scatter_reduce_(
            0, cell, reach, "amax"
        )
        radii, normals = radii.index_select(0, ids), normals.index_select(0, ids)
        extents = _disk_extents(normals, radii)
        corners = (c - extents.double(), c + extents.double())
        index = cell[:, None].expand(-1, 3)
        low = torch.full_like(mean, math.inf).scatter_reduce_(0, index, corners[0], "amin")
        high = torch.full_like(mean, -math.inf).scatter_reduce_(0, index, corners[1], "amax")
        return cls(
            ids,
            centers.index_select(0, ids),
            normals,
            radii,
            extents,
            starts,
            mean,
            bound.mul_(1.0 + 1e-6).add_(1e-6),
            (low + high) / 2,
            (high - low) / 2,
        )

    def cull(
        self, view: _View, height: int, width: int, pixel_sums: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(M,) int64 positions (into the cell-ordered data) of the surfels that may be in view.

        Cells whose bounding sphere is inside all four frustum half-spaces (with a margin far
        above the float32 rounding of :func:`_frustum_candidates`) keep all their surfels,
        cells outside one of them none; the surfels of the others are tested one by one by
        :func:`_frustum_candidates`. The result is the set that it would select on the whole
        map. With ``pixel_sums`` (see :func:`_summed_area`), the cells whose box can reach no
        pixel to render (:meth:`_reach`) are dropped first.
        """
        planes, slack = _frustum_planes(view, height, width)
        planes = torch.tensor(planes, dtype=torch.float64, device=self.starts.device)
        R, t = view.R_cw.double(), view.t_cw.double()
        distances = torch.addmm((planes @ t).T, self.sphere_centres, (planes @ R).T)  # (G, 4)
        nearest = distances.amin(1)
        margin = 100.0 * slack
        inside = nearest - self.sphere_radii >= margin - slack
        cells = torch.nonzero(inside | (nearest + self.sphere_radii >= -slack - margin)).view(-1)
        inside = inside.index_select(0, cells)
        if pixel_sums is not None:
            reach = self._reach(cells, view, slack, pixel_sums)
            cells, inside = cells[reach], inside[reach]
        starts = self.starts.index_select(0, cells)
        counts = self.starts.diff().index_select(0, cells)
        kept = _concat_ranges(starts[inside], counts[inside])
        tested = _concat_ranges(starts[~inside], counts[~inside])
        centers, radii = self.centers.index_select(0, tested), self.radii.index_select(0, tested)
        near = tested.index_select(0, _frustum_candidates(centers, radii, view, height, width))
        return torch.cat((kept, near))

    def _reach(
        self, cells: torch.Tensor, view: _View, slack: float, pixel_sums: torch.Tensor
    ) -> torch.Tensor:
        """(C,) bool: the (C,) ``cells`` whose box may reach a pixel of ``pixel_sums``
        (:func:`_box_touches`; camera-frame boxes that hold the world-frame ones, grown by 1 mm
        plus 100 times the frustum ``slack`` against the float32 rounding of the surfels'
        camera-frame coordinates)."""
        R = view.R_cw.double()
        centres = torch.addmm(view.t_cw.double(), R, self.box_centres.index_select(0, cells).T)
        extents = (R.abs() @ self.box_extents.index_select(0, cells).T).add_(1e-3 + 100 * slack)
        return _box_touches(centres.float(), extents.float(), view, pixel_sums)


def _disk_extents(normals: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
    """(N, 3) half-extents ``r sqrt(1 - n_i^2)`` of the axis-aligned boxes of disks with
    (N, 3) normals (any non-zero length; NaN for non-finite ones) and (N,) radii."""
    unit = normals / normals.norm(dim=1, keepdim=True)
    return torch.rsub(unit * unit, 1.0).clamp_(min=0.0).sqrt_().mul_(radii[:, None])
