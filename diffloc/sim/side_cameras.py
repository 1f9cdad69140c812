"""Side cameras of the simulated rig: the front camera turned about the body's up axis.

A real multi-camera rig (seed 2's Frontier: front, left and right cameras) records each
camera as a sequence of its own. ``scene.rig.side_camera_yaw_deg`` gives the simulated mapping
run such cameras: each yaw (degrees, counter-clockwise seen from above, so 90 looks to the
body's left) makes a camera with the front camera's intrinsics and extrinsic
``T_body_side = Rz(yaw) T_body_camera`` (position and orientation turned together), written as
the sequence ``<mapping>_<suffix>`` of the standard dataset layout: images, depth, poses at
the mapping run's timestamps and a calibration with its own ``T_body_camera``; no lidar (the
rig's lidar is the mapping sequence's).

Example:
    >>> side_sequence_names("mapping", [90.0, -90.0, 180.0, 45.0])
    {'mapping_left': 90.0, 'mapping_right': -90.0, 'mapping_back': 180.0, 'mapping_yaw45': 45.0}
    >>> T = side_camera_extrinsic(torch.eye(4, dtype=torch.float64), 90.0)
    >>> T[:3, 0].round(decimals=12)  # body x turned to body y
    tensor([0., 1., 0.], dtype=torch.float64)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from diffloc.checks import check_shape

__all__ = ["side_camera_extrinsic", "side_sequence_names", "validate_side_camera_yaws"]

KEY = "scene.rig.side_camera_yaw_deg"
NAMED_YAWS = {90.0: "left", -90.0: "right", 180.0: "back"}
"""Sequence-name suffixes of the usual side cameras; other yaws are ``yaw<degrees>``."""


def validate_side_camera_yaws(yaws: Sequence[float]) -> list[float]:
    """The yaws as floats, or a ``ValueError`` naming the setting.

    Each yaw must be a finite number in (-180, 180], not 0 (the front camera itself), and no
    yaw may repeat.

    Example:
        >>> validate_side_camera_yaws([90, -90])
        [90.0, -90.0]
    """
    out: list[float] = []
    for index, yaw in enumerate(yaws):
        if isinstance(yaw, bool) or not isinstance(yaw, int | float) or not math.isfinite(yaw):
            raise ValueError(f"{KEY}[{index}] must be a finite number of degrees, got {yaw!r}")
        if not -180.0 < yaw <= 180.0:
            raise ValueError(f"{KEY}[{index}] must be in (-180, 180] degrees, got {yaw}")
        if yaw == 0.0:
            raise ValueError(f"{KEY}[{index}] is 0: that is the front camera, already simulated")
        if float(yaw) in out:
            raise ValueError(f"{KEY} repeats the yaw {yaw} (got {list(yaws)})")
        out.append(float(yaw))
    return out


def _suffix(yaw: float) -> str:
    if yaw in NAMED_YAWS:
        return NAMED_YAWS[yaw]
    return "yaw" + f"{yaw:g}".replace(".", "p")


def side_sequence_names(base: str, yaws: Sequence[float]) -> dict[str, float]:
    """``{sequence name: yaw}`` of the side cameras of sequence ``base`` (order kept).

    Raises:
        ValueError: a bad yaw list (:func:`validate_side_camera_yaws`).
    """
    return {f"{base}_{_suffix(yaw)}": yaw for yaw in validate_side_camera_yaws(yaws)}


def side_camera_extrinsic(T_body_camera: torch.Tensor, yaw_deg: float) -> torch.Tensor:
    """The (4, 4) extrinsic ``Rz(yaw) @ T_body_camera`` of a camera turned by ``yaw_deg``
    about the body's z (up) axis, in ``T_body_camera``'s dtype."""
    check_shape(T_body_camera, "4,4", "T_body_camera")
    yaw = math.radians(yaw_deg)
    c, s = math.cos(yaw), math.sin(yaw)
    turn = torch.eye(4, dtype=T_body_camera.dtype)
    turn[:2, :2] = torch.tensor([[c, -s], [s, c]], dtype=T_body_camera.dtype)
    return turn @ T_body_camera
