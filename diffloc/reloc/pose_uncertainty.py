"""How precisely a refined pose's inliers fix the camera position (first-order covariance).

A pose can be backed by hundreds of consistent inliers and still be loose: when its map points
all lie far away or in one narrow direction (the end of an avenue seen from its far side), the
reprojection errors hardly change as the camera slides along the viewing direction. The
validation can ask how far the camera could move for the same residuals.

For the inliers' map points ``X_i`` (camera frame ``x_i``), keypoints ``u_i`` and keypoint
scales ``s_i``, the pose is perturbed by a left twist ``delta = (v, w)`` of ``T_cw``
(:meth:`PinholeCamera.project_jacobian_pose`, distortion included). With ``J`` (2N, 6) the
Jacobian of the scaled projections ``pi(x_i) / s_i`` at ``delta = 0`` and the residual variance
estimated from the inliers, ``s^2 = sum ||(pi(x_i) - u_i) / s_i||^2 / (2N - 6)``, the covariance
of ``delta`` is ``Sigma = s^2 (J^T J)^-1``. To first order the camera centre moves by
``-R_wc v``, so its covariance is ``R_wc Sigma_vv R_wc^T`` (metres^2, world frame), and the
reported figure is the standard deviation along its worst direction, ``sqrt(lambda_max)``.
First order, and only as good as the residuals are independent: map point errors shared by many
inliers are not in it.

Example (eight points 4 m in front of a camera; one pixel of noise):
    >>> import math
    >>> from diffloc.geometry.camera import PinholeCamera
    >>> camera = PinholeCamera.from_fov(640, 480, math.pi / 2)
    >>> g = torch.Generator().manual_seed(0)
    >>> X = torch.cat([torch.rand(8, 2, generator=g, dtype=torch.float64) * 4 - 2,
    ...                torch.full((8, 1), 4.0, dtype=torch.float64)], dim=1)
    >>> T = torch.eye(4, dtype=torch.float64)
    >>> uv = camera.project(X)[0] + torch.randn(8, 2, generator=g, dtype=torch.float64)
    >>> 0.0 < position_sigma_m(camera, T, X, uv, torch.ones(8, dtype=torch.float64)) < 0.1
    True
"""

from __future__ import annotations

import math

import torch

from diffloc.checks import check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import invert, transform_points

__all__ = ["position_covariance", "position_sigma_m"]


def position_covariance(
    camera: PinholeCamera,
    T_wc: torch.Tensor,
    points_world: torch.Tensor,
    keypoints: torch.Tensor,
    sigmas: torch.Tensor,
) -> torch.Tensor:
    """First-order covariance of the camera centre of a refined pose (module docstring).

    Args:
        camera: the query camera.
        T_wc: (4, 4) refined camera-to-world pose.
        points_world: (N, 3) the inliers' map points.
        keypoints: (N, 2) their query keypoints (pixels).
        sigmas: (N,) their keypoint scales (the refinement's residual weights are ``1/s_i``).

    Returns:
        (3, 3) float64 covariance of the camera centre, metres^2, in the world frame; every
        entry ``inf`` with fewer than 4 inliers or a degenerate geometry (``J^T J`` singular).

    Raises:
        ShapeError: mismatched shapes.
    """
    check_shape(T_wc, "4,4", "T_wc")
    check_shape(points_world, "N,3", "points_world")
    n = points_world.shape[0]
    check_shape(keypoints, f"{n},2", "keypoints")
    check_shape(sigmas, f"{n}", "sigmas")
    unbounded = torch.full((3, 3), math.inf, dtype=torch.float64)
    if n < 4:
        return unbounded
    T_wc = T_wc.double()
    camera = camera.to(torch.float64)
    points_cam = transform_points(invert(T_wc), points_world.double())
    scale = sigmas.double()[:, None]
    residuals = (camera.project(points_cam)[0] - keypoints.double()) / scale  # (N, 2)
    J = (camera.project_jacobian_pose(points_cam) / scale[..., None]).reshape(2 * n, 6)
    variance = (residuals * residuals).sum() / (2 * n - 6)
    information = J.T @ J
    if not torch.isfinite(information).all() or torch.linalg.matrix_rank(information) < 6:
        return unbounded
    R_wc = T_wc[:3, :3]
    return variance * R_wc @ torch.linalg.inv(information)[:3, :3] @ R_wc.T


def position_sigma_m(
    camera: PinholeCamera,
    T_wc: torch.Tensor,
    points_world: torch.Tensor,
    keypoints: torch.Tensor,
    sigmas: torch.Tensor,
) -> float:
    """Standard deviation (metres) of the camera centre along its worst direction,
    ``sqrt`` of the largest eigenvalue of :func:`position_covariance` (``inf`` when the
    inliers do not fix the pose)."""
    covariance = position_covariance(camera, T_wc, points_world, keypoints, sigmas)
    if not torch.isfinite(covariance).all():
        return math.inf
    return math.sqrt(max(float(torch.linalg.eigvalsh(covariance)[-1]), 0.0))
