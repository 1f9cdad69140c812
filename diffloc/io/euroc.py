"""EuRoC MAV dataset (ASL folder layout) reader and writer.

Layout of a ``mav0`` folder (only the parts used here)::

    mav0/cam0/data.csv                         #timestamp [ns],filename
    mav0/cam0/data/<timestamp_ns>.png
    mav0/cam0/sensor.yaml                      T_BS, resolution, intrinsics, distortion
    mav0/state_groundtruth_estimate0/data.csv  #timestamp, p_RS_R_x [m], p_RS_R_y [m],
                                               p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [],
                                               q_RS_z [], v_RS_R (3), b_w_RS_S (3),
                                               b_a_RS_S (3)          -- 17 columns
    mav0/pointcloud0/data.ply                  prior map (only in the Vicon-room sequences)

Ground truth gives body poses ``T_wb`` (``R`` = world, ``S`` = body IMU frame; quaternion
order w, x, y, z). ``T_BS`` of ``cam0/sensor.yaml`` maps camera points to the body frame, so
camera poses are ``T_wc = T_wb(t_image) @ T_BS``, with ``T_wb`` interpolated at the image
timestamps (linear translation, slerp rotation). Images outside the ground-truth time range
are dropped; their count is logged and stored in ``SequenceData.info["dropped_images"]``.
Timestamps are integer nanoseconds in the files and float64 seconds in :class:`SequenceData`
(the exact integers are in ``info["timestamps_ns"]``).

A camera whose four distortion coefficients are all zero is read as ``distortion=None``.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from diffloc.checks import check_finite, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import (
    invert,
    pose_from_translation_quaternion,
    translation_quaternion_from_pose,
)
from diffloc.io.atomic import atomic_write_text
from diffloc.io.calib import camera_to_dict
from diffloc.io.images import write_rgb
from diffloc.io.ply import write_point_cloud
from diffloc.io.sequence import SequenceData
from diffloc.io.trajectory import interpolate_poses, rotation_error_of_rigid

__all__ = ["read_euroc", "write_euroc"]

logger = logging.getLogger(__name__)

GT_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
    "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
    "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
    "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)
_RIGID_TOLERANCE = 1e-6


def _resolve_mav0(mav0_dir: str | os.PathLike) -> Path:
    path = Path(mav0_dir)
    if not path.is_dir():
        raise FileNotFoundError(f"EuRoC folder not found: {path}")
    if not (path / "cam0").exists() and (path / "mav0").is_dir():
        path = path / "mav0"
    return path


def _seconds_to_ns(seconds: np.ndarray) -> np.ndarray:
    """Integer nanoseconds nearest to float64 seconds (exact split: ``t * 1e9`` would round to
    256 ns at EuRoC's 1.4e9 s epoch times)."""
    whole = np.floor(seconds)
    return whole.astype(np.int64) * 1_000_000_000 + np.rint((seconds - whole) * 1e9).astype(
        np.int64
    )


def _ns_to_seconds(ns: np.ndarray) -> np.ndarray:
    """float64 seconds of integer nanoseconds, rounded once (``ns / 1e9`` would round twice)."""
    return (ns // 1_000_000_000).astype(np.float64) + (ns % 1_000_000_000) / 1e9


def _data_rows(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, comma-separated fields) of the non-comment lines of a CSV file."""
    if not path.is_file():
        raise FileNotFoundError(f"EuRoC file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a text file") from exc
    rows = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if line and not line.startswith("#"):
            rows.append((number, [f.strip() for f in line.split(",")]))
    return rows


def _nanoseconds(path: Path, number: int, field: str) -> int:
    if not field.isdigit():
        raise ValueError(
            f"{path}, line {number}: timestamp {field!r} is not an integer number of nanoseconds"
        )
    return int(field)


def _increasing(path: Path, ns: list[int], numbers: list[int]) -> None:
    for k in range(1, len(ns)):
        if ns[k] <= ns[k - 1]:
            raise ValueError(
                f"{path}, line {numbers[k]}: timestamp {ns[k]} is not greater than the previous one"
            )


def _float(value: Any, path: Path, key: str) -> float:
    if isinstance(value, bool):
        raise ValueError(f"{path}: key '{key}' must be a number, got {value!r}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: key '{key}' must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise ValueError(f"{path}: key '{key}' must be finite, got {value!r}")
    return number


def _read_sensor_yaml(path: Path) -> tuple[PinholeCamera, torch.Tensor, Any]:
    if not path.is_file():
        raise FileNotFoundError(f"EuRoC camera description not found: {path}")
    text = path.read_text(encoding="utf-8")
    lines = text.splitlines()
    if lines and lines[0].startswith("%YAML"):
        text = "\n".join(lines[1:])
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a YAML mapping")
    for key in ("T_BS", "resolution", "camera_model", "intrinsics"):
        if key not in data:
            raise ValueError(f"{path}: key '{key}' is missing")
    if data["camera_model"] != "pinhole":
        raise ValueError(
            f"{path}: key 'camera_model' must be 'pinhole', got {data['camera_model']!r}"
        )
    t_bs = data["T_BS"]
    if not isinstance(t_bs, dict) or "data" not in t_bs:
        raise ValueError(f"{path}: key 'T_BS' must be a mapping with 'data'")
    if t_bs.get("rows", 4) != 4 or t_bs.get("cols", 4) != 4:
        raise ValueError(f"{path}: key 'T_BS' must be 4x4")
    values = t_bs["data"]
    if not isinstance(values, list) or len(values) != 16:
        raise ValueError(f"{path}: key 'T_BS.data' must hold 16 numbers")
    T_BS = torch.tensor(
        [_float(v, path, "T_BS.data") for v in values], dtype=torch.float64
    ).reshape(4, 4)
    if float(rotation_error_of_rigid(T_BS)) > _RIGID_TOLERANCE:
        raise ValueError(f"{path}: key 'T_BS' is not a rigid transform")
    resolution = data["resolution"]
    if (
        not isinstance(resolution, list)
        or len(resolution) != 2
        or not all(isinstance(r, int) and not isinstance(r, bool) and r > 0 for r in resolution)
    ):
        raise ValueError(f"{path}: key 'resolution' must be [width, height] positive integers")
    intrinsics = data["intrinsics"]
    if not isinstance(intrinsics, list) or len(intrinsics) != 4:
        raise ValueError(f"{path}: key 'intrinsics' must be [fu, fv, cu, cv]")
    fu, fv, cu, cv = (_float(v, path, "intrinsics") for v in intrinsics)
    if fu <= 0 or fv <= 0:
        raise ValueError(f"{path}: key 'intrinsics' must have positive focal lengths")
    distortion = None
    model = data.get("distortion_model", "radial-tangential")
    coefficients = data.get("distortion_coefficients", [0.0, 0.0, 0.0, 0.0])
    if model not in ("radial-tangential", "radtan"):
        raise ValueError(
            f"{path}: key 'distortion_model' {model!r} is not supported (only radial-tangential)"
        )
    if not isinstance(coefficients, list) or len(coefficients) != 4:
        raise ValueError(f"{path}: key 'distortion_coefficients' must hold [k1, k2, p1, p2]")
    k = [_float(v, path, "distortion_coefficients") for v in coefficients]
    if any(k):
        distortion = torch.tensor(k, dtype=torch.float64)
    camera = PinholeCamera(
        fx=torch.tensor(fu, dtype=torch.float64),
        fy=torch.tensor(fv, dtype=torch.float64),
        cx=torch.tensor(cu, dtype=torch.float64),
        cy=torch.tensor(cv, dtype=torch.float64),
        width=resolution[0],
        height=resolution[1],
        distortion=distortion,
    )
    return camera, T_BS, data.get("rate_hz")


def _read_groundtruth(path: Path) -> tuple[np.ndarray, torch.Tensor]:
    """Ground-truth timestamps (N,) int64 ns and body poses T_wb (N, 4, 4) float64."""
    rows = _data_rows(path)
    ns, numbers, values = [], [], []
    for number, fields in rows:
        if len(fields) < 8:
            raise ValueError(
                f"{path}, line {number}: expected at least 8 columns (timestamp, "
                f"p xyz, q wxyz), got {len(fields)}"
            )
        ns.append(_nanoseconds(path, number, fields[0]))
        try:
            row = [float(f) for f in fields[1:8]]
        except ValueError as exc:
            raise ValueError(f"{path}, line {number}: not a number") from exc
        if not all(math.isfinite(v) for v in row):
            raise ValueError(f"{path}, line {number}: NaN or infinite value")
        if math.sqrt(sum(v * v for v in row[3:7])) < 1e-12:
            raise ValueError(f"{path}, line {number}: zero quaternion")
        numbers.append(number)
        values.append(row)
    if not values:
        raise ValueError(f"{path}: no ground-truth rows")
    _increasing(path, ns, numbers)
    array = torch.tensor(values, dtype=torch.float64)
    q_xyzw = torch.cat([array[:, 4:7], array[:, 3:4]], dim=1)
    return np.array(ns, dtype=np.int64), pose_from_translation_quaternion(array[:, :3], q_xyzw)


def read_euroc(
    mav0_dir: str | os.PathLike, name: str | None = None, camera_name: str = "cam0"
) -> SequenceData:
    """Read a EuRoC ASL ``mav0`` folder as a :class:`SequenceData` of camera ``camera_name``.

    Args:
        mav0_dir: the ``mav0`` folder (or the sequence folder that contains it).
        name: sequence name (default: the folder holding ``mav0``).
        camera_name: ``"cam0"`` or ``"cam1"``.

    Returns:
        The sequence: camera poses ``T_wc = T_wb @ T_BS`` at the image times inside the
        ground-truth range, ``T_body_camera = T_BS``, no depth, no lidar sweeps,
        ``pointcloud_path`` = ``pointcloud0/data.ply`` if present.

    Raises:
        FileNotFoundError: a missing folder, CSV, ``sensor.yaml`` or image.
        ValueError: malformed CSV rows (with line numbers) or ``sensor.yaml`` keys, or no image
            inside the ground-truth time range.

    Example:
        See :func:`write_euroc` (a round trip through a written ``mav0`` folder).
    """
    mav0 = _resolve_mav0(mav0_dir)
    cam_dir = mav0 / camera_name
    camera, T_BS, rate_hz = _read_sensor_yaml(cam_dir / "sensor.yaml")
    csv_path = cam_dir / "data.csv"
    rows = _data_rows(csv_path)
    image_ns, numbers, files = [], [], []
    for number, fields in rows:
        if len(fields) != 2 or not fields[1]:
            raise ValueError(
                f"{csv_path}, line {number}: expected 'timestamp,filename', got "
                f"{len(fields)} columns"
            )
        image_ns.append(_nanoseconds(csv_path, number, fields[0]))
        numbers.append(number)
        files.append(cam_dir / "data" / fields[1])
    _increasing(csv_path, image_ns, numbers)
    gt_ns, T_wb = _read_groundtruth(mav0 / "state_groundtruth_estimate0" / "data.csv")
    image_ns_arr = np.array(image_ns, dtype=np.int64).reshape(-1)
    inside = (image_ns_arr >= gt_ns[0]) & (image_ns_arr <= gt_ns[-1])
    dropped = int((~inside).sum())
    if dropped:
        logger.warning(
            "%s: dropped %d of %d images outside the ground-truth time range",
            mav0,
            dropped,
            len(image_ns_arr),
        )
    if not inside.any():
        raise ValueError(f"{csv_path}: no image lies inside the ground-truth time range")
    kept_ns = image_ns_arr[inside]
    kept_files = [f for f, keep in zip(files, inside.tolist(), strict=True) if keep]
    missing = next((f for f in kept_files if not f.is_file()), None)
    if missing is not None:
        raise FileNotFoundError(f"EuRoC image listed in {csv_path} not found: {missing}")
    origin = int(gt_ns[0])
    T_wb_images = interpolate_poses((gt_ns - origin) * 1e-9, T_wb, (kept_ns - origin) * 1e-9)
    T_wc = T_wb_images @ T_BS
    pointcloud = mav0 / "pointcloud0" / "data.ply"
    if name is None:
        name = mav0.parent.name if mav0.name == "mav0" else mav0.name
    return SequenceData(
        name=name,
        timestamps=_ns_to_seconds(kept_ns),
        T_wc=T_wc,
        camera=camera,
        rgb_paths=kept_files,
        depth_paths=None,
        T_body_camera=T_BS,
        pointcloud_path=pointcloud if pointcloud.is_file() else None,
        info={"dropped_images": dropped, "timestamps_ns": kept_ns, "rate_hz": rate_hz},
    )


def _yaml_number(x: float) -> str:
    """Shortest round-trip float text that YAML 1.1 (PyYAML) also reads as a float."""
    text = repr(float(x))
    if "e" in text:
        mantissa, exponent = text.split("e")
        if "." not in mantissa:
            mantissa += ".0"
        text = f"{mantissa}e{exponent if exponent[0] in '+-' else '+' + exponent}"
    return text


def _sensor_yaml(camera: PinholeCamera, T_BS: torch.Tensor, rate_hz: float) -> str:
    cam = camera_to_dict(camera)
    d = cam["distortion"] or {"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0}
    data = [_yaml_number(v) for v in T_BS.reshape(-1).tolist()]
    rows = [", ".join(data[4 * r : 4 * r + 4]) for r in range(4)]
    rate = int(rate_hz) if float(rate_hz).is_integer() else _yaml_number(rate_hz)
    intrinsics = ", ".join(_yaml_number(cam[k]) for k in ("fx", "fy", "cx", "cy"))
    coefficients = ", ".join(_yaml_number(d[k]) for k in ("k1", "k2", "p1", "p2"))
    return (
        "# General sensor definitions.\n"
        "sensor_type: camera\n"
        "comment: diffloc simulated camera\n"
        "\n"
        "# Sensor extrinsics wrt. the body-frame.\n"
        "T_BS:\n"
        "  cols: 4\n"
        "  rows: 4\n"
        f"  data: [{rows[0]},\n"
        f"         {rows[1]},\n"
        f"         {rows[2]},\n"
        f"         {rows[3]}]\n"
        "\n"
        "# Camera specific definitions.\n"
        f"rate_hz: {rate}\n"
        f"resolution: [{cam['width']}, {cam['height']}]\n"
        "camera_model: pinhole\n"
        f"intrinsics: [{intrinsics}] #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        f"distortion_coefficients: [{coefficients}]\n"
    )


def write_euroc(
    mav0_dir: str | os.PathLike,
    timestamps: np.ndarray | torch.Tensor,
    T_wc: torch.Tensor | np.ndarray,
    camera: PinholeCamera,
    images: Sequence[torch.Tensor | np.ndarray],
    T_body_camera: torch.Tensor | np.ndarray | None = None,
    rate_hz: float | None = None,
    points_world: np.ndarray | torch.Tensor | None = None,
) -> Path:
    """Write camera frames and ground truth in the EuRoC ASL layout (for tests and export).

    Ground truth body poses ``T_wb = T_wc @ inv(T_body_camera)`` are written at the image
    times (velocities by finite differences, biases zero). Each file is written atomically.

    Args:
        mav0_dir: the ``mav0`` folder to create (must not hold a ``cam0`` folder yet).
        timestamps: (N,) seconds, stored as ``round(t * 1e9)`` nanoseconds; must stay strictly
            increasing after rounding.
        T_wc: (N, 4, 4) camera-to-world poses.
        camera: the unbatched camera (``cam0``).
        images: N images, (3, H, W) float in [0, 1] or (H, W, 3) uint8.
        T_body_camera: (4, 4) camera-to-body ``T_BS`` (default identity).
        rate_hz: ``rate_hz`` of ``sensor.yaml`` (default: from the median frame interval).
        points_world: optional (P, 3) prior map written to ``pointcloud0/data.ply``.

    Returns:
        ``mav0_dir``.

    Raises:
        FileExistsError: ``mav0_dir/cam0`` exists.
        ValueError: mismatched lengths, non-increasing timestamps, non-rigid poses.

    Example:
        >>> camera = PinholeCamera(fx=40.0, fy=40.0, cx=15.5, cy=11.5, width=32, height=24)
        >>> T_wc = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
        >>> T_wc[:, 0, 3] = torch.tensor([0.0, 0.1, 0.2])
        >>> images = [torch.zeros(3, 24, 32)] * 3
        >>> _ = write_euroc("MH_tiny/mav0", [0.0, 0.05, 0.1], T_wc, camera, images)
        >>> seq = read_euroc("MH_tiny/mav0")
        >>> seq.name, len(seq), seq.T_wc[:, 0, 3]
        ('MH_tiny', 3, tensor([0.0000, 0.1000, 0.2000], dtype=torch.float64))
    """
    mav0 = Path(mav0_dir)
    if (mav0 / "cam0").exists():
        raise FileExistsError(f"{mav0 / 'cam0'} already exists")
    times = np.asarray(
        timestamps.detach().cpu().numpy() if isinstance(timestamps, torch.Tensor) else timestamps,
        dtype=np.float64,
    )
    check_shape(times, "N", "timestamps")
    check_finite(times, "timestamps")
    n = len(times)
    if n == 0:
        raise ValueError("write_euroc needs at least one frame")
    T = torch.as_tensor(T_wc).detach().cpu().to(torch.float64)
    check_shape(T, f"{n},4,4", "T_wc")
    check_finite(T, "T_wc")
    if float(rotation_error_of_rigid(T).max()) > _RIGID_TOLERANCE:
        raise ValueError("T_wc holds matrices that are not rigid transforms")
    if len(images) != n:
        raise ValueError(f"{n} timestamps but {len(images)} images")
    T_BS = (
        torch.eye(4, dtype=torch.float64)
        if T_body_camera is None
        else torch.as_tensor(T_body_camera).detach().cpu().to(torch.float64)
    )
    check_shape(T_BS, "4,4", "T_body_camera")
    if float(rotation_error_of_rigid(T_BS)) > _RIGID_TOLERANCE:
        raise ValueError("T_body_camera is not a rigid transform")
    ns = _seconds_to_ns(times)
    if n > 1 and not (np.diff(ns) > 0).all():
        raise ValueError("timestamps must be strictly increasing (after rounding to ns)")
    if rate_hz is None:
        rate_hz = float(round(1.0 / float(np.median(np.diff(times))))) if n > 1 else 20.0

    cam_dir = mav0 / "cam0"
    for stamp, image in zip(ns.tolist(), images, strict=True):
        write_rgb(cam_dir / "data" / f"{stamp}.png", image)
    csv = "#timestamp [ns],filename\n" + "".join(f"{s},{s}.png\n" for s in ns.tolist())
    atomic_write_text(cam_dir / "data.csv", csv)
    atomic_write_text(cam_dir / "sensor.yaml", _sensor_yaml(camera, T_BS, rate_hz))

    T_wb = T @ invert(T_BS)
    p, q_xyzw = translation_quaternion_from_pose(T_wb)
    p_np = p.numpy()
    seconds = (ns - ns[0]) * 1e-9
    velocity = np.gradient(p_np, seconds, axis=0) if n > 1 else np.zeros((n, 3))
    table = (
        np.concatenate(
            [p_np, q_xyzw[:, 3:4].numpy(), q_xyzw[:, :3].numpy(), velocity, np.zeros((n, 6))],
            axis=1,
        )
        + 0.0
    )
    line = "%d" + ",%.17g" * 16 + "\n"
    flat = [
        v for stamp, row in zip(ns.tolist(), table.tolist(), strict=True) for v in (stamp, *row)
    ]
    atomic_write_text(
        mav0 / "state_groundtruth_estimate0" / "data.csv",
        GT_HEADER + "\n" + (line * n) % tuple(flat),
    )
    if points_world is not None:
        write_point_cloud(mav0 / "pointcloud0" / "data.ply", points_world)
    return mav0
