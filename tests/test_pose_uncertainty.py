"""First-order position uncertainty of a refined pose (diffloc/reloc/pose_uncertainty.py)."""

from __future__ import annotations

import math

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import so3_exp, transform_points
from diffloc.optim.motion_cost import refine_pose
from diffloc.reloc.pose_uncertainty import position_covariance, position_sigma_m

CAMERA = PinholeCamera.from_fov(640, 480, math.pi / 2)


def scene(depth_m: float, n: int = 60, seed: int = 0) -> torch.Tensor:
    """(n, 3) points spread over the view at about ``depth_m`` in front of the identity pose."""
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(n, 2, generator=g, dtype=torch.float64) * 2 - 1) * depth_m * 0.8
    z = depth_m * (1 + 0.1 * torch.rand(n, 1, generator=g, dtype=torch.float64))
    return torch.cat([xy, z], dim=1)


def test_the_covariance_matches_the_spread_of_refined_poses():
    """Monte Carlo: 1 px noise on the keypoints, 300 refinements; the predicted standard
    deviation of the camera centre along its worst direction is within 15 % of the spread."""
    T = torch.eye(4, dtype=torch.float64)  # a turned camera: the covariance is in the world
    T[:3, :3] = so3_exp(torch.tensor([0.3, -1.1, 0.4], dtype=torch.float64))
    T[:3, 3] = torch.tensor([2.0, -1.0, 0.5], dtype=torch.float64)
    X = transform_points(T, scene(depth_m=8.0))
    clean = CAMERA.project_world(X, T)[0]
    g = torch.Generator().manual_seed(1)
    noisy = clean + torch.randn(300, *clean.shape, generator=g, dtype=torch.float64)
    refined = refine_pose(CAMERA, T.expand(300, 4, 4), X.expand(300, -1, -1), noisy)
    centres = refined.T_wc[:, :3, 3]
    worst = torch.linalg.eigh(torch.cov(centres.T))
    empirical = math.sqrt(float(worst.eigenvalues[-1]))
    # the prediction from one noisy draw, whose residuals estimate the 1 px noise
    predicted = position_sigma_m(CAMERA, refined.T_wc[0], X, noisy[0], torch.ones(len(X)))
    assert predicted == pytest.approx(empirical, rel=0.15)
    # ... along the same worst direction
    covariance = position_covariance(CAMERA, refined.T_wc[0], X, noisy[0], torch.ones(len(X)))
    direction = torch.linalg.eigh(covariance).eigenvectors[:, -1]
    assert abs(float(direction @ worst.eigenvectors[:, -1])) > 0.95


def test_farther_points_fix_the_camera_worse():
    T = torch.eye(4, dtype=torch.float64)
    sigma = []
    for depth in (4.0, 16.0):
        X = scene(depth)
        g = torch.Generator().manual_seed(2)
        uv = CAMERA.project(X)[0] + torch.randn(len(X), 2, generator=g, dtype=torch.float64)
        sigma.append(position_sigma_m(CAMERA, T, X, uv, torch.ones(len(X))))
    assert sigma[1] > 3 * sigma[0]


def test_larger_keypoint_scales_mean_smaller_weighted_residuals_not_a_smaller_sigma():
    """Scaling every s_i by 2 halves the weighted residuals and doubles the weighted Jacobian's
    inverse: the covariance is unchanged (the residual variance is estimated, not assumed)."""
    X = scene(6.0)
    T = torch.eye(4, dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    uv = CAMERA.project(X)[0] + torch.randn(len(X), 2, generator=g, dtype=torch.float64)
    one = position_covariance(CAMERA, T, X, uv, torch.ones(len(X)))
    two = position_covariance(CAMERA, T, X, uv, torch.full((len(X),), 2.0))
    assert torch.allclose(one, two)


def test_too_few_or_degenerate_inliers_give_an_unbounded_sigma():
    T = torch.eye(4, dtype=torch.float64)
    X = scene(4.0, n=3)
    assert position_sigma_m(CAMERA, T, X, CAMERA.project(X)[0], torch.ones(3)) == math.inf
    same = scene(4.0, n=1).expand(6, 3)  # six copies of one point: J^T J has rank 2
    uv = CAMERA.project(same)[0]
    assert position_sigma_m(CAMERA, T, same, uv, torch.ones(6)) == math.inf


def test_mismatched_shapes_are_clear_errors():
    X = scene(4.0, n=8)
    with pytest.raises(ShapeError):
        position_sigma_m(CAMERA, torch.eye(4), X, torch.zeros(7, 2), torch.ones(8))
    with pytest.raises(ShapeError):
        position_sigma_m(CAMERA, torch.eye(3), X, torch.zeros(8, 2), torch.ones(8))
