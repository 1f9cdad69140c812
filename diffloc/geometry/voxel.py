"""Voxel-grid averaging of point clouds on a grid anchored at the world origin."""

from __future__ import annotations

import numpy as np

__all__ = ["voxel_average"]


def voxel_average(
    points: np.ndarray, voxel_size_m: float, *attributes: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Average points and per-point attributes over the occupied cells of a voxel grid.

    A point's cell is ``floor(p / voxel_size_m)``, so clouds averaged separately share one
    grid. Cells come out sorted lexicographically by index, so the result does not depend on
    the input order of whole cells.

    Args:
        points: (P, 3) points, P >= 1 (not checked: callers validate their inputs).
        voxel_size_m: cell edge length, metres (> 0).
        *attributes: (P, C) or (P,) per-point values averaged the same way.

    Returns:
        ``(centers, counts, *means)``: (M, 3) float64 cell means of the points, (M,) int64
        points per cell, then one (M, C) float64 mean per attribute.

    Example:
        >>> voxel_average(np.array([[0.1, 0, 0], [0.3, 0, 0], [1.5, 0, 0]]), 1.0)[1]
        array([2, 1])
    """
    points = np.asarray(points, dtype=np.float64)
    cells = np.floor(points / voxel_size_m).astype(np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) < 2.0**62:
        keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
        _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    else:
        _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)

    def cell_mean(values: np.ndarray) -> np.ndarray:
        values = np.asarray(values, dtype=np.float64).reshape(len(points), -1)
        columns = [
            np.bincount(inverse, weights=values[:, c], minlength=len(counts))
            for c in range(values.shape[1])
        ]
        return np.stack(columns, axis=1) / counts[:, None]

    return (cell_mean(points), counts.astype(np.int64), *(cell_mean(a) for a in attributes))
