"""Lidar points with the sensor position that measured each one, from the sources a dataset has.

Surfel normals are oriented towards the sensor, so a map builder needs, per point, where the
sensor was. Sources:

- ``sweeps``: lidar sweeps with poses (diffloc's own format): every point carries its sweep's
  origin;
- a point cloud file: a terrestrial-scanner map (diffloc's ``map/tls_map.ply``), the prior
  cloud a sequence ships (EuRoC ``pointcloud0/data.ply``) or any PLY. The scanner positions are
  unknown, so the origin of each point is the nearest camera position of the sequence: cameras
  are in free space, which is all that orienting a normal needs.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from diffloc.io.ply import read_point_cloud
from diffloc.io.sequence import SequenceData
from diffloc.progress import progress

__all__ = ["lidar_points_with_origins"]


def _sweeps_in_world(seq: SequenceData, show_progress: bool) -> tuple[np.ndarray, np.ndarray]:
    points, origins = [], []
    for i in progress(range(len(seq.lidar_paths)), f"{seq.name}: lidar sweeps", show_progress):
        T_wl = seq.T_wl[i].numpy()
        sweep = seq.load_lidar(i).numpy().astype(np.float64)
        points.append(sweep @ T_wl[:3, :3].T + T_wl[:3, 3])
        origins.append(np.broadcast_to(T_wl[:3, 3], sweep.shape))
    return np.concatenate(points), np.concatenate(origins)


def _cloud_with_camera_origins(seq: SequenceData, path: Path) -> tuple[np.ndarray, np.ndarray]:
    points = read_point_cloud(path).points.astype(np.float64)
    cameras = seq.T_wc[:, :3, 3].numpy()
    _, nearest = cKDTree(cameras).query(points)
    return points, cameras[nearest]


def lidar_points_with_origins(
    seq: SequenceData,
    use_sweeps: bool = True,
    clouds: list[str | os.PathLike] | tuple = (),
    show_progress: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
    """World-frame lidar points and, per point, the sensor position that saw it.

    Args:
        seq: the mapping sequence (its poses give origins to clouds without scanner poses).
        use_sweeps: include the sequence's lidar sweeps (if it has any).
        clouds: point-cloud PLY files to include; the sequence's own prior cloud
            (``seq.pointcloud_path``) is always included when present.
        show_progress: progress bar while reading sweeps.

    Returns:
        ``(points, origins, sources)``: (N, 3) float64 world points, (N, 3) float64 sensor
        positions and one line per source used.

    Raises:
        FileNotFoundError: a listed cloud does not exist.
        ValueError: no source gave any point.
    """
    parts, sources = [], []
    if use_sweeps and seq.lidar_paths:
        parts.append(_sweeps_in_world(seq, show_progress))
        sources.append(f"{len(seq.lidar_paths)} lidar sweeps of {seq.name!r}")
    paths = [Path(c) for c in clouds]
    if seq.pointcloud_path is not None:
        paths.append(seq.pointcloud_path)
    for path in paths:
        if not path.is_file():
            raise FileNotFoundError(f"point cloud {path} does not exist")
        parts.append(_cloud_with_camera_origins(seq, path))
        sources.append(f"{path.name} ({len(parts[-1][0])} points)")
    if not parts or sum(len(p) for p, _ in parts) == 0:
        raise ValueError(
            f"no lidar points for sequence {seq.name!r}: it has no sweeps and no point cloud; "
            "list a lidar map PLY in the map sources"
        )
    points = np.concatenate([p for p, _ in parts])
    origins = np.ascontiguousarray(np.concatenate([o for _, o in parts]))
    return torch.from_numpy(points), torch.from_numpy(origins), sources
