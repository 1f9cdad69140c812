"""Lidar rays of a submap: origin, direction and measured range per return, and the normal of
the surface it hit, estimated from the merged sweeps (PCA of the neighbours, oriented towards
the sensor)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from diffloc.io.sequence import SequenceData

__all__ = ["LidarRays", "lidar_rays", "pca_normals"]


@dataclass
class LidarRays:
    """Rays of lidar returns (world frame, float32).

    Attributes:
        origins: (M, 3) sensor positions.
        directions: (M, 3) unit directions.
        ranges: (M,) measured ranges, metres.
        normals: (M, 3) unit surface normals facing the sensor, zero where none was estimated.
    """

    origins: torch.Tensor
    directions: torch.Tensor
    ranges: torch.Tensor
    normals: torch.Tensor

    def __len__(self) -> int:
        return len(self.ranges)


def pca_normals(
    points: np.ndarray, origins: np.ndarray, radius: float, min_neighbours: int, k: int
) -> np.ndarray:
    """Normals of a point cloud by PCA of each point's neighbourhood.

    Args:
        points: (N, 3) world points.
        origins: (N, 3) sensor position that measured each point (normals face it).
        radius: neighbourhood radius, metres.
        min_neighbours: points with fewer neighbours (self included) get a zero normal.
        k: at most this many neighbours.

    Returns:
        (N, 3) float32 unit normals, zero rows where none was estimated.
    """
    tree = cKDTree(points)
    normals = np.zeros(points.shape, dtype=np.float32)
    for start in range(0, len(points), 65536):
        chunk = slice(start, start + 65536)
        dist, idx = tree.query(points[chunk], k=k, distance_upper_bound=radius)
        valid = np.isfinite(dist)
        count = valid.sum(axis=1)
        nb = points[np.where(valid, idx, 0)]
        mean = (nb * valid[..., None]).sum(axis=1) / np.maximum(count, 1)[:, None]
        centred = (nb - mean[:, None]) * valid[..., None]
        _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
        n = vectors[:, :, 0]
        n[np.einsum("ni,ni->n", n, origins[chunk] - points[chunk]) < 0] *= -1
        n[count < min_neighbours] = 0.0
        normals[chunk] = n
    return normals


def lidar_rays(
    seq: SequenceData,
    sweeps: list[int],
    max_range_m: float,
    normal_radius_m: float,
    stride: int,
) -> LidarRays:
    """Rays of the returns of some sweeps of a sequence.

    Args:
        seq: a sequence with lidar sweeps and their poses ``T_wl``.
        sweeps: indices of the sweeps to use.
        max_range_m: returns farther than this are dropped.
        normal_radius_m: neighbourhood radius of the normal estimate (over all used sweeps).
        stride: keep every ``stride``-th return as a ray (normals use all of them).

    Returns:
        The rays.

    Raises:
        ValueError: no sweep given, or no return within range.
    """
    if not sweeps:
        raise ValueError(f"sequence {seq.name!r}: no lidar sweeps for these frames")
    points, origins = [], []
    for i in sweeps:
        T_wl = seq.T_wl[i].numpy()
        sweep = seq.load_lidar(i).numpy().astype(np.float64)
        keep = np.linalg.norm(sweep, axis=1) <= max_range_m
        points.append(sweep[keep] @ T_wl[:3, :3].T + T_wl[:3, 3])
        origins.append(np.broadcast_to(T_wl[:3, 3], points[-1].shape))
    points, origins = np.concatenate(points), np.concatenate(origins)
    if len(points) == 0:
        raise ValueError(f"sequence {seq.name!r}: no lidar return within {max_range_m} m")
    normals = pca_normals(points, origins, normal_radius_m, min_neighbours=6, k=16)
    points, origins, normals = points[::stride], origins[::stride], normals[::stride]
    offsets = points - origins
    ranges = np.linalg.norm(offsets, axis=1)
    return LidarRays(
        origins=torch.from_numpy(origins.astype(np.float32)),
        directions=torch.from_numpy((offsets / ranges[:, None]).astype(np.float32)),
        ranges=torch.from_numpy(ranges.astype(np.float32)),
        normals=torch.from_numpy(normals),
    )
