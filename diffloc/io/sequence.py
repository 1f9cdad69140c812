"""One recorded (or simulated) sequence: images, ground-truth poses, calibration, lidar sweeps.

All dataset readers (:mod:`diffloc.io.dataset`, :mod:`diffloc.io.euroc`,
:mod:`diffloc.io.tum_rgbd`) return a :class:`SequenceData`. It holds file paths, not pixels;
images and sweeps are loaded on demand.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from diffloc.checks import check_finite, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.images import read_depth, read_rgb
from diffloc.io.ply import read_point_cloud

__all__ = ["SequenceData"]


def _timestamps(x: Any, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    array = np.array(x, dtype=np.float64)
    if array.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {array.shape}")
    check_finite(array, name)
    return array


def _poses(x: Any, name: str) -> torch.Tensor:
    T = x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x))
    T = T.detach().cpu().to(torch.float64)
    check_shape(T, "N,4,4", name)
    check_finite(T, name)
    return T


@dataclass
class SequenceData:
    """A sequence of camera frames with ground truth, and optional lidar sweeps.

    Attributes:
        name: sequence name.
        timestamps: (N,) float64 seconds of the camera frames.
        T_wc: (N, 4, 4) float64 camera-to-world ground-truth poses, row i <-> frame i.
        camera: the (unbatched) camera of every frame.
        rgb_paths: N image files.
        depth_paths: N depth PNG files registered to the images, or ``None``.
        depth_scale: depth PNG units per metre.
        T_body_camera: (4, 4) float64 camera-to-body transform, or ``None``.
        T_body_lidar: (4, 4) float64 lidar-to-body transform, or ``None``.
        lidar_paths: M sweep files (PLY, points in the lidar frame).
        lidar_timestamps: (M,) float64 seconds of the sweeps.
        T_wl: (M, 4, 4) float64 lidar-to-world poses at sweep times, or ``None`` (only when
            there are no sweeps).
        pointcloud_path: a prior map point cloud of the sequence if the dataset ships one
            (EuRoC ``pointcloud0/data.ply``), else ``None``.
        info: reader notes (e.g. ``{"dropped_images": 3}``).

    Raises:
        ValueError: lengths that do not match, non-finite values, a non-positive depth scale.
    """

    name: str
    timestamps: np.ndarray
    T_wc: torch.Tensor
    camera: PinholeCamera
    rgb_paths: list[Path]
    depth_paths: list[Path] | None = None
    depth_scale: float = 1000.0
    T_body_camera: torch.Tensor | None = None
    T_body_lidar: torch.Tensor | None = None
    lidar_paths: list[Path] = field(default_factory=list)
    lidar_timestamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    T_wl: torch.Tensor | None = None
    pointcloud_path: Path | None = None
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        where = f"sequence {self.name!r}"
        if not isinstance(self.camera, PinholeCamera):
            raise TypeError(f"{where}: camera must be a PinholeCamera")
        self.timestamps = _timestamps(self.timestamps, "timestamps")
        n = len(self.timestamps)
        self.T_wc = _poses(self.T_wc, "T_wc")
        if len(self.T_wc) != n:
            raise ValueError(f"{where}: {n} timestamps but {len(self.T_wc)} poses T_wc")
        self.rgb_paths = [Path(p) for p in self.rgb_paths]
        if len(self.rgb_paths) != n:
            raise ValueError(f"{where}: {n} timestamps but {len(self.rgb_paths)} rgb_paths")
        if self.depth_paths is not None:
            self.depth_paths = [Path(p) for p in self.depth_paths]
            if len(self.depth_paths) != n:
                raise ValueError(f"{where}: {n} timestamps but {len(self.depth_paths)} depth_paths")
        if not (math.isfinite(self.depth_scale) and self.depth_scale > 0):
            raise ValueError(f"{where}: depth_scale must be positive, got {self.depth_scale}")
        for key in ("T_body_camera", "T_body_lidar"):
            T = getattr(self, key)
            if T is not None:
                T = _poses(torch.as_tensor(T)[None], key)[0]
                setattr(self, key, T)
        self.lidar_paths = [Path(p) for p in self.lidar_paths]
        self.lidar_timestamps = _timestamps(self.lidar_timestamps, "lidar_timestamps")
        m = len(self.lidar_paths)
        if len(self.lidar_timestamps) != m:
            raise ValueError(
                f"{where}: {m} lidar_paths but {len(self.lidar_timestamps)} lidar_timestamps"
            )
        if self.T_wl is None:
            if m:
                raise ValueError(f"{where}: {m} lidar sweeps but no poses T_wl")
        else:
            self.T_wl = _poses(self.T_wl, "T_wl")
            if len(self.T_wl) != m:
                raise ValueError(f"{where}: {m} lidar sweeps but {len(self.T_wl)} poses T_wl")
        if self.pointcloud_path is not None:
            self.pointcloud_path = Path(self.pointcloud_path)

    def __len__(self) -> int:
        return len(self.timestamps)

    def load_rgb(self, i: int) -> torch.Tensor:
        """Image ``i`` as a (3, H, W) float32 RGB tensor in [0, 1]."""
        return read_rgb(self.rgb_paths[i])

    def load_depth(self, i: int) -> torch.Tensor:
        """Depth of frame ``i`` as a (1, H, W) float32 tensor in metres (0 = no measurement).

        Raises:
            ValueError: the sequence has no depth images.
        """
        if self.depth_paths is None:
            raise ValueError(f"sequence {self.name!r} has no depth images")
        return read_depth(self.depth_paths[i], self.depth_scale)

    def load_lidar(self, i: int) -> torch.Tensor:
        """Sweep ``i`` as (P, 3) float32 points in the lidar frame."""
        return torch.from_numpy(read_point_cloud(self.lidar_paths[i]).points)
