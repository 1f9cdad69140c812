"""Pose validation (seed 1 Sec. III-C): inlier count, distance to the previous inlier pose."""

from __future__ import annotations

import math

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.reloc.validation import PoseValidator, ValidationConfig


def pose_at(x: float) -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64)
    T[0, 3] = x
    return T


def test_too_few_inliers_is_rejected_and_does_not_become_the_reference():
    v = PoseValidator(ValidationConfig(theta_in=15, theta_dist_m=0.3))
    assert not v.validate(pose_at(0.0), 20, 0.0)  # first inlier pose: no reference yet
    assert not v.validate(pose_at(5.0), 14, 0.1)  # outlier pose, reference stays at 0
    assert v.validate(pose_at(0.2), 15, 0.2)


def test_distance_to_the_previous_inlier_pose():
    v = PoseValidator(ValidationConfig(theta_in=15, theta_dist_m=0.3))
    v.validate(pose_at(0.0), 30, 0.0)
    assert not v.validate(pose_at(0.5), 30, 0.05)  # too far ...
    assert v.validate(pose_at(0.7), 30, 0.1)  # ... but it is the new reference


def test_speed_allowance_grows_with_the_time_gap():
    v = PoseValidator(ValidationConfig(theta_in=15, theta_dist_m=0.3, max_speed_mps=1.0))
    v.validate(pose_at(0.0), 30, 0.0)
    assert v.validate(pose_at(1.2), 30, 1.0)  # 1.2 <= 0.3 + 1.0 * 1
    assert not v.validate(pose_at(2.1), 30, 1.5)  # 0.9 > 0.3 + 1.0 * 0.5


def test_single_image_mode_checks_inliers_only():
    v = PoseValidator(ValidationConfig(theta_in=15, temporal=False))
    assert v.validate(pose_at(0.0), 15, 0.0)
    assert v.validate(pose_at(100.0), 15, 0.1)
    assert not v.validate(pose_at(0.0), 14, 0.2)


def test_reset_forgets_the_reference():
    v = PoseValidator(ValidationConfig())
    v.validate(pose_at(0.0), 30, 0.0)
    v.reset()
    assert not v.validate(pose_at(0.0), 30, 0.1)


@pytest.mark.parametrize(
    "kwargs", [{"theta_in": -1}, {"theta_dist_m": -0.1}, {"max_speed_mps": math.inf}]
)
def test_bad_thresholds_are_clear_errors(kwargs):
    with pytest.raises(ValueError):
        ValidationConfig(**kwargs)


def test_bad_poses_are_clear_errors():
    v = PoseValidator(ValidationConfig())
    with pytest.raises(ShapeError):
        v.validate(torch.eye(3), 30, 0.0)
    bad = pose_at(0.0)
    bad[0, 3] = math.nan
    with pytest.raises(ValueError, match="T_wc"):
        v.validate(bad, 30, 0.0)
    with pytest.raises(ValueError, match="timestamp"):
        v.validate(pose_at(0.0), 30, math.nan)
