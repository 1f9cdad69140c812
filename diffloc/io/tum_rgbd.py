"""TUM RGB-D benchmark folder reader and writer.

Layout::

    <root>/rgb.txt          # comments, then "timestamp rgb/<timestamp>.png" per line
    <root>/depth.txt        # comments, then "timestamp depth/<timestamp>.png" per line
    <root>/groundtruth.txt  TUM trajectory (timestamp tx ty tz qx qy qz qw) of T_world_camera
    <root>/rgb/*.png        8-bit colour images
    <root>/depth/*.png      16-bit depth, 5000 units per metre, 0 = no measurement
    <root>/calib.yaml       optional, diffloc extension: the camera (see diffloc.io.calib)

RGB and depth frames are taken by different clocks; :func:`read_tum_rgbd` pairs them one to
one by nearest timestamp within ``max_dt`` (as TUM's ``associate.py``), keeps the RGB time as
the frame time and interpolates the ground truth there. RGB frames without a depth partner or
outside the ground-truth time range are dropped (counts in ``info``).

Camera: the ``camera`` argument if given, else the camera of ``<root>/calib.yaml`` if present,
else :data:`FREIBURG1_CAMERA`, TUM's published calibration of the "freiburg1" Kinect
(fx 517.3, fy 516.5, cx 318.6, cy 255.3, 640x480, k1 0.2624, k2 -0.9531, p1 -0.0054,
p2 0.0026). TUM also publishes k3 = 1.1633 for that camera, which the 4-coefficient
radial-tangential model of :class:`PinholeCamera` cannot hold: it is left out, so the default
is only approximate near the image border. Pass the right camera for freiburg2/3 sequences.
The depth scale is always 5000 (the format's definition).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from diffloc.checks import check_finite, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.atomic import atomic_write_text
from diffloc.io.calib import Calibration, read_calib, write_calib
from diffloc.io.images import write_depth, write_rgb
from diffloc.io.sequence import SequenceData
from diffloc.io.trajectory import associate_timestamps, interpolate_poses, read_tum, write_tum

__all__ = ["FREIBURG1_CAMERA", "TUM_DEPTH_SCALE", "read_tum_rgbd", "write_tum_rgbd"]

logger = logging.getLogger(__name__)

TUM_DEPTH_SCALE = 5000.0
"""Depth PNG units per metre in the TUM RGB-D format."""


def freiburg1_camera() -> PinholeCamera:
    """TUM's freiburg1 colour camera (k3 = 1.1633 omitted, see the module docstring)."""
    return PinholeCamera(
        fx=torch.tensor(517.3, dtype=torch.float64),
        fy=torch.tensor(516.5, dtype=torch.float64),
        cx=torch.tensor(318.6, dtype=torch.float64),
        cy=torch.tensor(255.3, dtype=torch.float64),
        width=640,
        height=480,
        distortion=torch.tensor([0.2624, -0.9531, -0.0054, 0.0026], dtype=torch.float64),
    )


FREIBURG1_CAMERA = freiburg1_camera()


def _read_file_list(path: Path) -> tuple[np.ndarray, list[Path]]:
    """Timestamps (N,) and file paths of a TUM ``rgb.txt``/``depth.txt``."""
    if not path.is_file():
        raise FileNotFoundError(f"TUM RGB-D file list not found: {path}")
    times: list[float] = []
    files: list[Path] = []
    for number, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) != 2:
            raise ValueError(
                f"{path}, line {number}: expected 'timestamp filename', got {len(fields)} columns"
            )
        try:
            t = float(fields[0])
        except ValueError as exc:
            raise ValueError(
                f"{path}, line {number}: timestamp {fields[0]!r} is not a number"
            ) from exc
        if not math.isfinite(t):
            raise ValueError(f"{path}, line {number}: timestamp is not finite")
        if times and t <= times[-1]:
            raise ValueError(
                f"{path}, line {number}: timestamp {fields[0]} is not greater than the previous one"
            )
        times.append(t)
        files.append(path.parent / fields[1])
    return np.array(times, dtype=np.float64), files


def read_tum_rgbd(
    root: str | os.PathLike,
    camera: PinholeCamera | None = None,
    max_dt: float = 0.02,
    name: str | None = None,
) -> SequenceData:
    """Read a TUM RGB-D sequence folder.

    Args:
        root: the folder with ``rgb.txt``, ``depth.txt`` and ``groundtruth.txt``.
        camera: the camera; default from ``calib.yaml`` if present, else
            :data:`FREIBURG1_CAMERA`.
        max_dt: largest RGB-depth time difference (seconds) for a pair.
        name: sequence name (default: the folder name).

    Returns:
        The :class:`SequenceData` with depth (scale 5000); ``info`` holds
        ``rgb_without_depth`` and ``dropped_images`` (outside the ground truth) counts and
        ``camera_source``.

    Raises:
        FileNotFoundError: a missing list, ground-truth or image file.
        ValueError: malformed lists (with line numbers), no RGB-depth pairs inside the ground
            truth.

    Usage: ``read_tum_rgbd("rgbd_dataset_freiburg1_xyz")`` on a downloaded TUM sequence
    (``tests/test_io_tum_rgbd.py`` writes and reads small ones).
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"TUM RGB-D folder not found: {root}")
    rgb_times, rgb_files = _read_file_list(root / "rgb.txt")
    depth_times, depth_files = _read_file_list(root / "depth.txt")
    gt_times, T_gt = read_tum(root / "groundtruth.txt")
    if len(gt_times) == 0:
        raise ValueError(f"{root / 'groundtruth.txt'}: no ground-truth poses")
    T_body_camera = None
    if camera is not None:
        source = "argument"
    elif (root / "calib.yaml").is_file():
        calib = read_calib(root / "calib.yaml")
        camera, T_body_camera, source = calib.camera, calib.T_body_camera, "calib.yaml"
    else:
        camera, source = freiburg1_camera(), "freiburg1 default"
        logger.warning(
            "%s: no camera given and no calib.yaml: using the freiburg1 calibration", root
        )
    idx_rgb, idx_depth = associate_timestamps(rgb_times, depth_times, max_dt)
    unmatched = len(rgb_times) - len(idx_rgb)
    times = rgb_times[idx_rgb]
    inside = (times >= gt_times[0]) & (times <= gt_times[-1])
    dropped = int((~inside).sum())
    if unmatched or dropped:
        logger.warning(
            "%s: %d RGB frames without depth within %.3f s, %d outside the ground "
            "truth; they are dropped",
            root,
            unmatched,
            max_dt,
            dropped,
        )
    if not inside.any():
        raise ValueError(f"{root}: no RGB-depth pair lies inside the ground-truth time range")
    idx_rgb, idx_depth, times = idx_rgb[inside], idx_depth[inside], times[inside]
    rgb_paths = [rgb_files[i] for i in idx_rgb.tolist()]
    depth_paths = [depth_files[i] for i in idx_depth.tolist()]
    missing = next((p for p in rgb_paths + depth_paths if not p.is_file()), None)
    if missing is not None:
        raise FileNotFoundError(f"TUM RGB-D image not found: {missing}")
    return SequenceData(
        name=name if name is not None else root.name,
        timestamps=times,
        T_wc=interpolate_poses(gt_times, T_gt, times),
        camera=camera,
        rgb_paths=rgb_paths,
        depth_paths=depth_paths,
        depth_scale=TUM_DEPTH_SCALE,
        T_body_camera=T_body_camera,
        info={"rgb_without_depth": unmatched, "dropped_images": dropped, "camera_source": source},
    )


def write_tum_rgbd(
    root: str | os.PathLike,
    timestamps: np.ndarray | torch.Tensor,
    T_wc: torch.Tensor | np.ndarray,
    rgb_images: Sequence[torch.Tensor | np.ndarray],
    depth_images: Sequence[torch.Tensor | np.ndarray],
    camera: PinholeCamera | None = None,
    depth_time_offset: float = 0.004,
) -> Path:
    """Write frames in the TUM RGB-D layout (for tests and export).

    Timestamps are rounded to microseconds (TUM's file names). Depth frames are stamped
    ``depth_time_offset`` seconds after their RGB frame, so reading exercises the RGB-depth
    association; ground truth is written at the RGB times. With ``camera`` a ``calib.yaml``
    (depth scale 5000) is written too.

    Args:
        root: the folder to fill (must not hold an ``rgb.txt`` yet).
        timestamps: (N,) seconds of the RGB frames, strictly increasing at µs resolution.
        T_wc: (N, 4, 4) camera-to-world poses.
        rgb_images: N images, (3, H, W) float in [0, 1] or (H, W, 3) uint8.
        depth_images: N depth maps (H, W) or (1, H, W) in metres (at most 13.107 m; deeper
            values become 0).
        camera: optional camera to store in ``calib.yaml``.
        depth_time_offset: depth minus RGB time in seconds; keep it below the reader's
            ``max_dt`` and half the frame interval.

    Returns:
        ``root``.
    """
    root = Path(root)
    if (root / "rgb.txt").exists():
        raise FileExistsError(f"{root / 'rgb.txt'} already exists")
    times = np.asarray(
        timestamps.detach().cpu().numpy() if isinstance(timestamps, torch.Tensor) else timestamps,
        dtype=np.float64,
    )
    check_shape(times, "N", "timestamps")
    check_finite(times, "timestamps")
    n = len(times)
    if len(rgb_images) != n or len(depth_images) != n:
        raise ValueError(
            f"{n} timestamps but {len(rgb_images)} RGB and {len(depth_images)} depth images"
        )
    if not math.isfinite(depth_time_offset):
        raise ValueError("depth_time_offset must be finite")
    rgb_stamps = [f"{t:.6f}" for t in times.tolist()]
    depth_stamps = [f"{t + depth_time_offset:.6f}" for t in times.tolist()]
    rounded = np.array([float(s) for s in rgb_stamps])
    if n > 1 and not (np.diff(rounded) > 0).all():
        raise ValueError("timestamps must be strictly increasing at microsecond resolution")
    for stamp, image in zip(rgb_stamps, rgb_images, strict=True):
        write_rgb(root / "rgb" / f"{stamp}.png", image)
    for stamp, depth in zip(depth_stamps, depth_images, strict=True):
        write_depth(root / "depth" / f"{stamp}.png", depth, TUM_DEPTH_SCALE)
    header = "# {kind}\n# file: 'diffloc export'\n# timestamp filename\n"
    atomic_write_text(
        root / "rgb.txt",
        header.format(kind="color images") + "".join(f"{s} rgb/{s}.png\n" for s in rgb_stamps),
    )
    atomic_write_text(
        root / "depth.txt",
        header.format(kind="depth maps") + "".join(f"{s} depth/{s}.png\n" for s in depth_stamps),
    )
    write_tum(root / "groundtruth.txt", rounded, T_wc)
    if camera is not None:
        write_calib(root / "calib.yaml", Calibration(camera=camera, depth_scale=TUM_DEPTH_SCALE))
    return root
