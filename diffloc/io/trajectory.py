"""Trajectories in the TUM format, pose interpolation and timestamp association.

A TUM trajectory file has one pose per line, ``timestamp tx ty tz qx qy qz qw``: seconds,
metres, and a unit quaternion (scalar last) of the rotation of ``T_wc`` (camera-to-world,
or generally sensor-to-world). Lines starting with ``#`` are comments.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np
import torch

from diffloc.checks import check_finite, check_shape
from diffloc.geometry.se3 import pose_from_translation_quaternion, translation_quaternion_from_pose
from diffloc.io.atomic import atomic_write_text

__all__ = [
    "associate_timestamps",
    "interpolate_poses",
    "read_tum",
    "rotation_error_of_rigid",
    "write_tum",
]

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"
_SPLIT = re.compile(r"[,\s]+")
_RIGID_TOLERANCE = 1e-6


def _as_tensor64(x: np.ndarray | torch.Tensor) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.detach().to(device="cpu", dtype=torch.float64)
    return torch.as_tensor(np.asarray(x, dtype=np.float64))


def _as_timestamps(x: np.ndarray | torch.Tensor | list, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    array = np.asarray(x, dtype=np.float64)
    check_shape(array, "N", name)
    check_finite(array, name)
    return array


def rotation_error_of_rigid(T: torch.Tensor) -> torch.Tensor:
    """How far (..., 4, 4) matrices are from rigid transforms.

    Returns:
        (...) the max of ``|R^T R - I|``, ``|det R - 1|`` and ``|last row - (0, 0, 0, 1)|``.
    """
    R = T[..., :3, :3]
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    ortho = (R.transpose(-1, -2) @ R - eye).abs().amax(dim=(-1, -2))
    det = (torch.linalg.det(R) - 1).abs()
    last = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype, device=T.device)
    bottom = (T[..., 3, :] - last).abs().amax(dim=-1)
    return torch.maximum(torch.maximum(ortho, det), bottom)


def write_tum(
    path: str | os.PathLike,
    timestamps: np.ndarray | torch.Tensor,
    T_wc: np.ndarray | torch.Tensor,
) -> None:
    """Write a trajectory as a TUM file (atomically, deterministic bytes).

    Timestamps are written with ``%.9f``, translations with ``%.12f`` and quaternions
    (canonical sign ``qw >= 0``) with ``%.15f``, so :func:`read_tum` returns the input to better
    than 1e-9 for translations below 1e3 km.

    Args:
        path: the file to write.
        timestamps: (N,) seconds, strictly increasing.
        T_wc: (N, 4, 4) rigid sensor-to-world transforms.

    Raises:
        ShapeError: wrong shapes or lengths.
        ValueError: non-finite values, non-increasing timestamps, non-rigid matrices.

    Example:
        >>> write_tum("poses.txt", np.array([0.0, 0.1]), torch.eye(4).expand(2, 4, 4))
        >>> row = open("poses.txt").read().splitlines()[-1].split()  # t tx ty tz qx qy qz qw
        >>> row[0], row[1], row[7]
        ('0.100000000', '0.000000000000', '1.000000000000000')
    """
    times = _as_timestamps(timestamps, "timestamps")
    T = _as_tensor64(T_wc)
    check_shape(T, f"{len(times)},4,4", "T_wc")
    check_finite(T, "T_wc")
    if len(times) > 1 and not (np.diff(times) > 0).all():
        raise ValueError(f"{path}: timestamps must be strictly increasing")
    if len(times) and float(rotation_error_of_rigid(T).max()) > _RIGID_TOLERANCE:
        raise ValueError(f"{path}: T_wc holds matrices that are not rigid transforms")
    t, q = translation_quaternion_from_pose(T)
    rows = np.concatenate([times[:, None], t.numpy(), q.numpy()], axis=1) + 0.0  # no -0.0
    line = "%.9f" + " %.12f" * 3 + " %.15f" * 4 + "\n"
    body = (line * len(rows)) % tuple(rows.ravel().tolist()) if len(rows) else ""
    atomic_write_text(path, TUM_HEADER + "\n" + body)


def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, torch.Tensor]:
    """Read a TUM trajectory file.

    Comments (``#``) and blank lines are skipped; columns may be separated by spaces, tabs or
    commas. Quaternions are normalised.

    Args:
        path: the file.

    Returns:
        ``(timestamps, T_wc)``: (N,) float64 seconds and (N, 4, 4) float64 transforms.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: a row with a column count other than 8, a non-number, NaN/inf, a zero
            quaternion, or a timestamp not greater than the previous one; the message names
            the file and the line number.

    Example:
        >>> _ = Path("poses.txt").write_text("0.5 1 2 3 0 0 0 1")  # t tx ty tz qx qy qz qw
        >>> timestamps, T_wc = read_tum("poses.txt")
        >>> timestamps, T_wc[0, :3, 3]
        (array([0.5]), tensor([1., 2., 3.], dtype=torch.float64))
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a text file") from exc
    rows: list[list[float]] = []
    previous = -math.inf
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path}, line {number}"
        fields = [f for f in _SPLIT.split(line) if f]
        if len(fields) != 8:
            raise ValueError(
                f"{where}: expected 8 columns (timestamp tx ty tz qx qy qz qw), got {len(fields)}"
            )
        try:
            values = [float(f) for f in fields]
        except ValueError as exc:
            raise ValueError(f"{where}: not a number in {line!r}") from exc
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"{where}: NaN or infinite value in {line!r}")
        if math.sqrt(sum(v * v for v in values[4:])) < 1e-12:
            raise ValueError(f"{where}: zero quaternion")
        if values[0] <= previous:
            raise ValueError(
                f"{where}: timestamp {fields[0]} is not greater than the previous "
                "one (timestamps must be strictly increasing)"
            )
        previous = values[0]
        rows.append(values)
    if not rows:
        return np.zeros(0), torch.zeros(0, 4, 4, dtype=torch.float64)
    array = torch.tensor(rows, dtype=torch.float64)
    T = pose_from_translation_quaternion(array[:, 1:4], array[:, 4:8])
    return array[:, 0].numpy().copy(), T


def _slerp(q0: torch.Tensor, q1: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Spherical interpolation of unit quaternions (..., 4) along the shorter arc."""
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    theta = torch.acos(dot)
    sin_theta = torch.sin(theta)
    small = sin_theta < 1e-9
    safe = torch.where(small, torch.ones_like(sin_theta), sin_theta)
    w0 = torch.where(small, 1 - alpha, torch.sin((1 - alpha) * theta) / safe)
    w1 = torch.where(small, alpha, torch.sin(alpha * theta) / safe)
    q = w0 * q0 + w1 * q1
    return q / q.norm(dim=-1, keepdim=True)


def interpolate_poses(
    timestamps_src: np.ndarray | torch.Tensor,
    T_src: np.ndarray | torch.Tensor,
    timestamps_query: np.ndarray | torch.Tensor,
) -> torch.Tensor:
    """Poses at query times: linear in translation, slerp in rotation between neighbours.

    A query equal to a source timestamp returns that source pose exactly. Queries outside
    ``[timestamps_src[0], timestamps_src[-1]]`` are an error; select the queries inside first
    with ``(q >= t[0]) & (q <= t[-1])``.

    Args:
        timestamps_src: (N,) strictly increasing seconds, N >= 1.
        T_src: (N, 4, 4) rigid transforms at those times.
        timestamps_query: (M,) seconds.

    Returns:
        (M, 4, 4) float64 transforms.

    Raises:
        ValueError: empty source, non-increasing source times, queries out of range.

    Example:
        >>> T_src = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
        >>> T_src[1, 0, 3] = 2.0  # 2 m along x in one second
        >>> interpolate_poses(np.array([0.0, 1.0]), T_src, np.array([0.5]))[0, :3, 3]
        tensor([1., 0., 0.], dtype=torch.float64)
    """
    times = _as_timestamps(timestamps_src, "timestamps_src")
    query = _as_timestamps(timestamps_query, "timestamps_query")
    T = _as_tensor64(T_src)
    check_shape(T, f"{len(times)},4,4", "T_src")
    check_finite(T, "T_src")
    if len(times) == 0:
        raise ValueError("interpolate_poses needs at least one source pose")
    if len(times) > 1 and not (np.diff(times) > 0).all():
        raise ValueError("timestamps_src must be strictly increasing")
    outside = (query < times[0]) | (query > times[-1])
    if outside.any():
        raise ValueError(
            f"{int(outside.sum())} of {len(query)} query times lie outside the source range "
            f"[{times[0]:.9f}, {times[-1]:.9f}] (first: {query[outside][0]:.9f})"
        )
    if len(query) == 0:
        return torch.zeros(0, 4, 4, dtype=torch.float64)
    if len(times) == 1:
        return T.expand(len(query), 4, 4).clone()
    i0 = np.clip(np.searchsorted(times, query, side="right") - 1, 0, len(times) - 2)
    alpha_np = (query - times[i0]) / (times[i0 + 1] - times[i0])
    i0_t = torch.from_numpy(i0)
    alpha = torch.from_numpy(alpha_np)[:, None]
    t_src, q_src = translation_quaternion_from_pose(T)
    t = (1 - alpha) * t_src[i0_t] + alpha * t_src[i0_t + 1]
    q = _slerp(q_src[i0_t], q_src[i0_t + 1], alpha)
    out = pose_from_translation_quaternion(t, q)
    exact0 = torch.from_numpy(alpha_np == 0.0)[:, None, None]
    exact1 = torch.from_numpy(alpha_np == 1.0)[:, None, None]
    out = torch.where(exact0, T[i0_t], out)
    return torch.where(exact1, T[i0_t + 1], out)


def associate_timestamps(
    a: np.ndarray | torch.Tensor, b: np.ndarray | torch.Tensor, max_dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one nearest-timestamp association, like TUM's ``associate.py``.

    All pairs with ``|a[i] - b[j]| <= max_dt`` are candidates; they are taken greedily in
    order of increasing time difference (ties by ``i`` then ``j``), skipping pairs whose ``i``
    or ``j`` is already used.

    Args:
        a: (N,) seconds.
        b: (M,) seconds.
        max_dt: largest accepted time difference in seconds (>= 0).

    Returns:
        ``(idx_a, idx_b)``: (K,) int64 indices of matched pairs, sorted by ``idx_a``.

    Example:
        >>> associate_timestamps(np.array([0.0, 1.0]), np.array([1.01, 0.02]), 0.05)
        (array([0, 1]), array([1, 0]))
    """
    ta = _as_timestamps(a, "a")
    tb = _as_timestamps(b, "b")
    if not (math.isfinite(max_dt) and max_dt >= 0):
        raise ValueError(f"max_dt must be a finite number >= 0, got {max_dt}")
    order_b = np.argsort(tb, kind="stable")
    sorted_b = tb[order_b]
    lo = np.searchsorted(sorted_b, ta - max_dt, side="left")
    hi = np.searchsorted(sorted_b, ta + max_dt, side="right")
    counts = hi - lo
    cand_a = np.repeat(np.arange(len(ta)), counts)
    starts = np.repeat(lo - np.cumsum(np.concatenate([[0], counts[:-1]])), counts)
    cand_b = order_b[starts + np.arange(len(cand_a))] if len(cand_a) else cand_a
    diff = np.abs(ta[cand_a] - tb[cand_b])
    keep = diff <= max_dt
    cand_a, cand_b, diff = cand_a[keep], cand_b[keep], diff[keep]
    order = np.lexsort((cand_b, cand_a, diff))
    used_a = np.zeros(len(ta), dtype=bool)
    used_b = np.zeros(len(tb), dtype=bool)
    pairs = []
    for i, j in zip(cand_a[order].tolist(), cand_b[order].tolist(), strict=True):
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            pairs.append((i, j))
    pairs.sort()
    idx = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    return idx[:, 0].copy(), idx[:, 1].copy()
