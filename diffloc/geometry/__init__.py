"""Geometry: batched SE(3)/SO(3) maps, the pinhole camera and the sensor rig.

See :mod:`diffloc.geometry.se3` for the pose and twist conventions (``T_ab`` maps frame b to
frame a, twists are ``[v, w]``), :mod:`diffloc.geometry.camera` for the OpenCV camera and pixel
conventions and :mod:`diffloc.geometry.rig` for URDF sensor rigs.
"""

from diffloc.geometry.camera import MIN_DEPTH, PinholeCamera
from diffloc.geometry.rig import SensorRig, rotation_from_rpy, rpy_from_rotation
from diffloc.geometry.se3 import (
    adjoint,
    cayley_rotation,
    compose,
    hat,
    invert,
    pose_from_translation_quaternion,
    se3_exp,
    se3_log,
    so3_exp,
    so3_log,
    transform_points,
    translation_quaternion_from_pose,
    vee,
)

__all__ = [
    "MIN_DEPTH",
    "PinholeCamera",
    "SensorRig",
    "adjoint",
    "cayley_rotation",
    "compose",
    "hat",
    "invert",
    "pose_from_translation_quaternion",
    "rotation_from_rpy",
    "rpy_from_rotation",
    "se3_exp",
    "se3_log",
    "so3_exp",
    "so3_log",
    "transform_points",
    "translation_quaternion_from_pose",
    "vee",
]
