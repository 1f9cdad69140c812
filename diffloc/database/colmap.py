"""Export a visual database as a COLMAP model in TEXT format (for hloc / COLMAP users).

Files written into one folder (atomically, as a whole)::

    cameras.txt   CAMERA_ID PINHOLE WIDTH HEIGHT fx fy cx cy   (one per distinct intrinsics)
    images.txt    IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME
                  POINTS2D[] as (X, Y, POINT3D_ID), one entry per keypoint, -1 where none
    points3D.txt  POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX)

Conventions:

- COLMAP stores world-to-camera poses: ``(qw, qx, qy, qz)`` and ``t`` of ``T_cw = T_wc^-1``
  (same OpenCV camera frame as diffloc), the quaternion with ``qw >= 0``.
- COLMAP puts the origin at the top-left *corner* of the image, so the centre of the top-left
  pixel is (0.5, 0.5); diffloc puts it at the centre. Keypoints and principal points are
  shifted by +0.5 px (as hloc does), which leaves every reprojection error unchanged.
- Ids are 1-based: keyframe ``k`` is image ``k + 1`` and map point ``p`` is point ``p + 1``
  (ids of unobserved points are skipped: COLMAP models hold only points with a track).
  ``POINT2D_IDX`` is the keypoint's index within its keyframe.
- ``ERROR`` is the mean reprojection error (pixels) of the point over its track, computed in
  float64 from the database's poses and intrinsics.
- Numbers are written with Python's shortest round-trip ``repr``.

Example (one keyframe observing one map point):
    >>> import torch
    >>> from diffloc.geometry.camera import PinholeCamera
    >>> db = VisualDatabase(descriptor_dim=2)
    >>> cam = PinholeCamera.from_fov(64, 48, 1.0)  # principal point (31.5, 23.5)
    >>> k = db.add_keyframe(torch.eye(4), cam, torch.tensor([[31.5, 23.5]]), torch.ones(1, 2),
    ...                     torch.ones(1))
    >>> X = torch.tensor([[0.0, 0.0, 2.0]])  # 2 m ahead, seen at the image centre
    >>> ids = db.add_points(X, torch.ones(1, 2), torch.tensor([-1]))
    >>> db.add_observations(k, torch.tensor([0]), ids)
    >>> write_colmap_text(db, "export/sparse/0")
    PosixPath('export/sparse/0')
    >>> open("export/sparse/0/points3D.txt").read().splitlines()[-1]  # id xyz rgb error track
    '1 0.0 0.0 2.0 128 128 128 0.0 1 0'
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from diffloc.checks import check_shape
from diffloc.database.database import VisualDatabase
from diffloc.geometry.se3 import invert, translation_quaternion_from_pose
from diffloc.io.atomic import atomic_directory

__all__ = ["COLMAP_PIXEL_OFFSET", "GREY", "reprojection_errors", "write_colmap_text"]

COLMAP_PIXEL_OFFSET = 0.5
"""Added to diffloc pixel coordinates (centre origin) to get COLMAP's (corner origin)."""
GREY = 128
"""The colour of map points without one."""


def reprojection_errors(db: VisualDatabase) -> torch.Tensor:
    """Reprojection error of every observation of a database.

    Args:
        db: the database.

    Returns:
        (O,) float64 pixel distances between each observing keypoint and the projection of
        its map point, in the order of :meth:`VisualDatabase.observations`.

    Example:
        >>> from diffloc.geometry.camera import PinholeCamera
        >>> db = VisualDatabase(descriptor_dim=2)
        >>> cam = PinholeCamera.from_fov(64, 48, 1.0)  # principal point (31.5, 23.5)
        >>> k = db.add_keyframe(torch.eye(4), cam, torch.tensor([[31.5, 23.5]]), torch.ones(1, 2),
        ...                     torch.ones(1))
        >>> X = torch.tensor([[0.0, 0.0, 2.0]])  # 2 m ahead, seen at the image centre
        >>> ids = db.add_points(X, torch.ones(1, 2), torch.tensor([-1]))
        >>> db.add_observations(k, torch.tensor([0]), ids)
        >>> reprojection_errors(db)
        tensor([0.], dtype=torch.float64)
    """
    observations = db.observations()
    keyframes, keypoints, points = observations.unbind(dim=1)
    T_cw = invert(db.T_wc.double())[keyframes]
    points_cam = (T_cw[:, :3, :3] @ db.point_positions.double()[points, :, None])[..., 0]
    points_cam = points_cam + T_cw[:, :3, 3]
    fx, fy, cx, cy = db.intrinsics.double()[keyframes].unbind(dim=1)
    u = fx * points_cam[:, 0] / points_cam[:, 2] + cx
    v = fy * points_cam[:, 1] / points_cam[:, 2] + cy
    return torch.hypot(
        u - db.keypoints.double()[keypoints, 0], v - db.keypoints.double()[keypoints, 1]
    )


def _check_folder(folder: Path, overwrite: bool) -> None:
    if folder.exists() and not folder.is_dir():
        raise FileExistsError(f"{folder} exists and is not a folder")
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise FileExistsError(
            f"{folder} exists and is not empty; pass overwrite=True to replace it as a whole"
        )


def _cameras(db: VisualDatabase) -> tuple[list[str], np.ndarray]:
    """``cameras.txt`` rows (one per distinct size + intrinsics) and each keyframe's id."""
    table = np.concatenate(
        [db.image_sizes.numpy().astype(np.float64), db.intrinsics.double().numpy()], axis=1
    )
    distinct, camera_of = np.unique(table, axis=0, return_inverse=True)
    rows = []
    for camera_id, (width, height, fx, fy, cx, cy) in enumerate(distinct.tolist(), start=1):
        params = (fx, fy, cx + COLMAP_PIXEL_OFFSET, cy + COLMAP_PIXEL_OFFSET)
        rows.append(
            f"{camera_id} PINHOLE {int(width)} {int(height)} " + " ".join(map(repr, params))
        )
    return rows, camera_of.reshape(-1) + 1


def _images(db: VisualDatabase, camera_of: np.ndarray, names: Sequence[str]) -> list[str]:
    """``images.txt`` rows: pose line and 2D points line of every keyframe."""
    t_cw, q_xyzw = translation_quaternion_from_pose(invert(db.T_wc.double()))
    q_wxyz = torch.cat([q_xyzw[:, 3:], q_xyzw[:, :3]], dim=1).tolist()
    offsets = db.keypoint_offsets.tolist()
    xy = (db.keypoints.double() + COLMAP_PIXEL_OFFSET).tolist()
    ids = torch.where(db.keypoint_points >= 0, db.keypoint_points + 1, -1).tolist()
    rows = []
    for k in range(db.num_keyframes):
        pose = " ".join(map(repr, q_wxyz[k] + t_cw[k].tolist()))
        rows.append(f"{k + 1} {pose} {int(camera_of[k])} {names[k]}")
        rows.append(
            " ".join(
                f"{xy[i][0]!r} {xy[i][1]!r} {ids[i]}" for i in range(offsets[k], offsets[k + 1])
            )
        )
    return rows


def _points(db: VisualDatabase, colors: np.ndarray) -> list[str]:
    """``points3D.txt`` rows of the observed map points."""
    observations = db.observations()
    errors = reprojection_errors(db)
    keyframes, keypoints, points = observations.unbind(dim=1)
    local = keypoints - db.keypoint_offsets[keyframes]
    order = torch.argsort(points, stable=True)
    counts = torch.bincount(points, minlength=db.num_points)
    mean_error = torch.zeros(db.num_points, dtype=torch.float64).index_add_(0, points, errors)
    mean_error = mean_error / counts.clamp_min(1)
    track_images = (keyframes[order] + 1).tolist()
    track_points2d = local[order].tolist()
    positions = db.point_positions.double().tolist()
    rows, start = [], 0
    for p, count in enumerate(counts.tolist()):
        if count == 0:
            continue
        track = " ".join(
            f"{track_images[j]} {track_points2d[j]}" for j in range(start, start + count)
        )
        start += count
        x, y, z = positions[p]
        r, g, b = colors[p].tolist()
        rows.append(f"{p + 1} {x!r} {y!r} {z!r} {r} {g} {b} {float(mean_error[p])!r} {track}")
    return rows


def write_colmap_text(
    db: VisualDatabase,
    folder: str | os.PathLike,
    image_names: Sequence[str] | None = None,
    point_colors: np.ndarray | None = None,
    overwrite: bool = False,
) -> Path:
    """Write ``db`` as a COLMAP TEXT model (module docstring) into ``folder``, atomically.

    Args:
        db: the visual database (keyframes with ``T_wc``, intrinsics, keypoints, map points).
        folder: the model folder; created, or replaced as a whole when ``overwrite``.
        image_names: (K,) image file names, e.g. relative paths under the image root hloc
            and COLMAP are given; default ``keyframe_<k>.png``. No spaces (COLMAP splits on
            them).
        point_colors: (P, 3) uint8 RGB per map point; default grey (:data:`GREY`).
        overwrite: replace an existing non-empty ``folder``.

    Returns:
        ``folder``.

    Raises:
        FileExistsError: ``folder`` exists and is not empty (and not ``overwrite``), or is a
            file.
        ValueError: wrong counts of names or colours, names with whitespace, non-finite poses,
            intrinsics or points, or a map point behind a camera that observes it.

    Example: see the module docstring.
    """
    folder = Path(folder)
    _check_folder(folder, overwrite)
    k, p = db.num_keyframes, db.num_points
    names = (
        list(image_names)
        if image_names is not None
        else [f"keyframe_{i:06d}.png" for i in range(k)]
    )
    if len(names) != k:
        raise ValueError(f"got {len(names)} image names for {k} keyframes")
    if any(not name or any(c.isspace() for c in name) for name in names):
        raise ValueError("COLMAP image names must be non-empty and hold no whitespace")
    if len(set(names)) != k:
        raise ValueError("COLMAP image names must be distinct")
    colors = np.full((p, 3), GREY, np.uint8) if point_colors is None else np.asarray(point_colors)
    check_shape(colors, f"{p},3", "point_colors")
    if colors.dtype != np.uint8:
        raise ValueError(f"point_colors must be uint8, got {colors.dtype}")
    for name, values in (
        ("T_wc", db.T_wc),
        ("intrinsics", db.intrinsics),
        ("point_positions", db.point_positions),
    ):
        if not bool(torch.isfinite(values).all()):
            raise ValueError(f"cannot export a database with non-finite {name}")
    observations = db.observations()
    T_cw = invert(db.T_wc.double())[observations[:, 0]]
    depth = (T_cw[:, 2, :3] * db.point_positions.double()[observations[:, 2]]).sum(1)
    if bool((depth + T_cw[:, 2, 3] <= 0).any()):
        raise ValueError("a map point lies behind a keyframe that observes it")
    cameras, camera_of = _cameras(db)
    files = {
        "cameras.txt": ["# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]", *cameras],
        "images.txt": [
            "# Image list: IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
            "#   POINTS2D[] as (X, Y, POINT3D_ID)",
            *_images(db, camera_of, names),
        ],
        "points3D.txt": [
            "# 3D point list: POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as "
            "(IMAGE_ID, POINT2D_IDX)",
            *_points(db, colors),
        ],
    }
    with atomic_directory(folder, overwrite=folder.exists()) as tmp:
        for file_name, lines in files.items():
            (tmp / file_name).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return folder
