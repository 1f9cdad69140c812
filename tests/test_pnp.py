"""PnP: EPnP known answers, LM refinement, LO-RANSAC accuracy and inliers, poselib agreement,
determinism, distortion and bad inputs."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import invert, se3_exp, transform_points
from diffloc.reloc.epnp import solve_epnp
from diffloc.reloc.pnp import PnPRansacConfig, refine_pnp, solve_pnp, solve_pnp_ransac
from diffloc.testing import random_points, random_se3

# Measured worst cases over 30 seeds (500 points, 50 % outliers, 1 px noise): 0.036 deg and
# 5.2 mm (0.042 deg, 5.6 mm with distortion); the floors below keep a 2-3x margin at 1000 points.
MAX_ROTATION_DEG = 0.1
MAX_TRANSLATION_M = 0.01
EUROC_DISTORTION = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)


def _camera(distortion: tuple[float, ...] | None = None) -> PinholeCamera:
    dist = None if distortion is None else torch.tensor(distortion, dtype=torch.float64)
    return PinholeCamera(
        fx=torch.tensor(500.0, dtype=torch.float64),
        fy=torch.tensor(500.0, dtype=torch.float64),
        cx=torch.tensor(319.5, dtype=torch.float64),
        cy=torch.tensor(239.5, dtype=torch.float64),
        width=640,
        height=480,
        distortion=dist,
    )


def _scene(
    n: int, outlier_ratio: float, seed: int, camera: PinholeCamera, noise_px: float = 1.0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Points 2-20 m in front of ``camera`` at a random pose, noisy keypoints, outliers.

    Returns:
        points_world (n, 3), keypoints (n, 2), true T_wc (4, 4), true inlier mask (n,).
    """
    g = torch.Generator().manual_seed(seed)
    size = torch.tensor([camera.width, camera.height], dtype=torch.float64)
    uv = torch.rand(n, 2, generator=g, dtype=torch.float64) * size - 0.5
    depth = 2.0 + 18.0 * torch.rand(n, generator=g, dtype=torch.float64)
    points_cam = camera.unproject(uv, depth)
    T_wc = random_se3((), generator=g, max_translation=10.0)
    keypoints = camera.project(points_cam)[0]
    keypoints = keypoints + noise_px * torch.randn(n, 2, generator=g, dtype=torch.float64)
    outlier = torch.rand(n, generator=g) < outlier_ratio
    random_uv = torch.rand(n, 2, generator=g, dtype=torch.float64) * size - 0.5
    keypoints = torch.where(outlier[:, None], random_uv, keypoints)
    return transform_points(T_wc, points_cam), keypoints, T_wc, ~outlier


def _pose_errors(T_est: torch.Tensor, T_true: torch.Tensor) -> tuple[float, float]:
    """Rotation error (deg) and camera-centre error (m) between two T_wc.

    The angle comes from ``||R_est - R_true||_F = 2 sqrt(2) sin(angle / 2)``, accurate down to
    rounding level (``acos`` of the trace cannot resolve angles below ~2e-8 rad).
    """
    chord = float(torch.linalg.matrix_norm(T_est[:3, :3] - T_true[:3, :3])) / math.sqrt(8.0)
    angle = 2.0 * math.asin(min(1.0, chord))
    return math.degrees(angle), float((T_est[:3, 3] - T_true[:3, 3]).norm())


def _generator(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# ---------------------------------------------------------------------------- EPnP / LM


@pytest.mark.parametrize("planar", [False, True])
def test_epnp_exact_on_noise_free_data(planar):
    g = _generator(1)
    T_cw = random_se3((5,), generator=g, max_translation=1.0)
    points_cam = random_points((5, 20), generator=g, low=(-2.0, -2.0, 4.0), high=(2.0, 2.0, 8.0))
    points_world = transform_points(invert(T_cw), points_cam)
    if planar:  # points on a tilted plane in the world
        points_world[..., 2] = 0.3 * points_world[..., 0] - 0.2 * points_world[..., 1]
        points_cam = transform_points(T_cw, points_world)
    xy = points_cam[..., :2] / points_cam[..., 2:]
    assert torch.allclose(solve_epnp(points_world, xy), T_cw, atol=1e-8)


@pytest.mark.parametrize("n", [4, 5, 30])
def test_solve_pnp_exact_and_batched(n):
    camera = _camera()
    g = _generator(2)
    T_wc = random_se3((2, 3), generator=g, max_translation=2.0)
    points_cam = random_points((2, 3, n), generator=g, low=(-3.0, -2.0, 3.0), high=(3.0, 2.0, 9.0))
    points_world = transform_points(T_wc, points_cam)
    keypoints = camera.project(points_cam)[0]
    T_est = solve_pnp(points_world, keypoints, camera)
    assert T_est.shape == (2, 3, 4, 4)
    assert torch.allclose(T_est, T_wc, atol=1e-8)


@pytest.mark.parametrize("seed", [0, 1])
def test_solve_pnp_with_noise(seed):
    # Worst over 30 seeds (200 points, 1 px noise): 0.05 deg, 5.6 mm.
    camera = _camera()
    points_world, keypoints, T_wc, _ = _scene(200, 0.0, seed, camera)
    rot, trans = _pose_errors(solve_pnp(points_world, keypoints, camera), T_wc)
    assert rot < 0.15 and trans < 0.02


def test_solve_pnp_weights_ignore_points():
    camera = _camera()
    g = _generator(3)
    T_wc = random_se3((2,), generator=g, max_translation=2.0)
    points_cam = random_points((2, 30), generator=g, low=(-3.0, -2.0, 3.0), high=(3.0, 2.0, 9.0))
    points_world = transform_points(T_wc, points_cam)
    keypoints = camera.project(points_cam)[0]
    weights = torch.ones(2, 30, dtype=torch.float64)
    weights[:, :10] = 0.0  # ignored points may be anything
    keypoints[:, :10] += 50.0
    assert torch.allclose(solve_pnp(points_world, keypoints, camera, weights), T_wc, atol=1e-8)


def test_refine_pnp_converges_from_a_perturbed_pose():
    camera = _camera(EUROC_DISTORTION)
    points_world, keypoints, T_wc, _ = _scene(200, 0.0, seed=3, camera=camera, noise_px=0.0)
    twist = torch.tensor([0.05, -0.03, 0.04, 0.01, -0.02, 0.015], dtype=torch.float64)
    T_start = T_wc @ se3_exp(twist)
    T_est = refine_pnp(T_start, points_world, keypoints, camera)
    assert torch.allclose(T_est, T_wc, atol=1e-8)


def test_solve_pnp_bad_inputs():
    camera = _camera()
    X = torch.rand(3, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="at least 4"):
        solve_pnp(X, torch.rand(3, 2, dtype=torch.float64), camera)
    with pytest.raises(ShapeError):
        solve_pnp(torch.rand(6, 3), torch.rand(5, 2), camera)
    with pytest.raises(ShapeError):
        solve_pnp(torch.rand(6, 3), torch.rand(6, 2), camera, weights=torch.ones(5))
    with pytest.raises(ValueError, match="non-negative"):
        solve_pnp(torch.rand(6, 3), torch.rand(6, 2), camera, weights=-torch.ones(6))


# ---------------------------------------------------------------------------- RANSAC


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ransac_half_outliers(seed):
    camera = _camera()
    points_world, keypoints, T_wc, true_inliers = _scene(1000, 0.5, seed, camera)
    result = solve_pnp_ransac(points_world, keypoints, camera, PnPRansacConfig(), _generator())
    assert result.success
    rot, trans = _pose_errors(result.T_wc, T_wc)
    assert rot < MAX_ROTATION_DEG and trans < MAX_TRANSLATION_M
    hits = int((result.inliers & true_inliers).sum())
    assert hits / int(result.inliers.sum()) > 0.95  # precision
    assert hits / int(true_inliers.sum()) > 0.95  # recall
    assert result.num_inliers == int(result.inliers.sum())
    assert result.iterations >= PnPRansacConfig().min_iterations
    assert torch.equal(result.inliers, result.reprojection_errors < 4.0)


@pytest.mark.parametrize("ratio", [0.25, 0.75])
def test_ransac_pose_is_the_least_squares_optimum_on_its_inliers(ratio):
    camera = _camera()
    points_world, keypoints, _, _ = _scene(1000, ratio, 3, camera)
    result = solve_pnp_ransac(points_world, keypoints, camera, PnPRansacConfig(), _generator())
    weights = result.inliers.to(torch.float64)
    optimum = refine_pnp(result.T_wc, points_world, keypoints, camera, weights, iterations=50)
    rot, trans = _pose_errors(result.T_wc, optimum)
    # measured worst over 30 scenes (0.25 / 0.5 / 0.75 outliers): 1e-7 rad, 1.1e-6 m
    assert math.radians(rot) < 1e-6 and trans < 1e-5


def test_ransac_agrees_with_poselib():
    poselib = pytest.importorskip("poselib")
    camera = _camera()
    points_world, keypoints, T_wc, _ = _scene(1000, 0.5, 4, camera)
    ours = solve_pnp_ransac(points_world, keypoints, camera, PnPRansacConfig(), _generator())
    cam = {"model": "PINHOLE", "width": 640, "height": 480, "params": [500, 500, 319.5, 239.5]}
    pose, info = poselib.estimate_absolute_pose(
        keypoints.numpy(), points_world.numpy(), cam, {"max_reproj_error": 4.0}, {}
    )
    T_cw = torch.eye(4, dtype=torch.float64)
    T_cw[:3, :3] = torch.tensor(pose.R)
    T_cw[:3, 3] = torch.tensor(pose.t)
    rot, trans = _pose_errors(ours.T_wc, invert(T_cw))
    assert rot < 0.02 and trans < 0.003  # different robust losses: measured <= 0.008 deg, 1.2 mm
    assert abs(ours.num_inliers - info["num_inliers"]) <= 5


def test_ransac_is_deterministic_for_a_seed():
    camera = _camera()
    points_world, keypoints, _, _ = _scene(400, 0.6, 5, camera)
    config = PnPRansacConfig(batch_size=64)
    a = solve_pnp_ransac(points_world, keypoints, camera, config, _generator(7))
    b = solve_pnp_ransac(points_world, keypoints, camera, config, _generator(7))
    assert torch.equal(a.T_wc, b.T_wc) and torch.equal(a.inliers, b.inliers)
    assert a.iterations == b.iterations


def test_ransac_restores_the_thread_count():
    camera = _camera()
    points_world, keypoints, _, _ = _scene(100, 0.2, 10, camera)
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        solve_pnp_ransac(points_world, keypoints, camera, PnPRansacConfig(), _generator())
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(previous)


def test_ransac_with_distortion():
    camera = _camera(EUROC_DISTORTION)
    points_world, keypoints, T_wc, true_inliers = _scene(1000, 0.5, 6, camera)
    result = solve_pnp_ransac(points_world, keypoints, camera, PnPRansacConfig(), _generator())
    rot, trans = _pose_errors(result.T_wc, T_wc)
    assert result.success and rot < MAX_ROTATION_DEG and trans < MAX_TRANSLATION_M
    hits = int((result.inliers & true_inliers).sum())
    assert hits / int(true_inliers.sum()) > 0.95
    # Ignoring the distortion breaks the fit: most correspondences are then outliers.
    pinhole = dataclasses.replace(camera, distortion=None)
    wrong = solve_pnp_ransac(points_world, keypoints, pinhole, PnPRansacConfig(), _generator())
    assert wrong.num_inliers < 0.8 * result.num_inliers


def test_ransac_small_problem_without_bailout():
    camera = _camera()
    points_world, keypoints, T_wc, _ = _scene(40, 0.3, 8, camera, noise_px=0.0)
    result = solve_pnp_ransac(points_world, keypoints, camera, PnPRansacConfig(), _generator())
    rot, trans = _pose_errors(result.T_wc, T_wc)
    assert result.success and rot < 1e-6 and trans < 1e-6


def test_ransac_reports_failure_without_structure():
    camera = _camera()
    points_world, keypoints, _, _ = _scene(300, 1.0, 9, camera)  # every match is random
    result = solve_pnp_ransac(points_world, keypoints, camera, PnPRansacConfig(), _generator())
    assert not result.success


def test_ransac_without_any_p3p_solution_is_not_an_error():
    # All points at one place: no sample has a P3P solution (this raised OverflowError once).
    camera = _camera()
    points_world = torch.tensor([[0.0, 0.0, 4.0]], dtype=torch.float64).repeat(50, 1)
    keypoints = torch.rand(50, 2, generator=_generator(1), dtype=torch.float64) * 400
    config = PnPRansacConfig(max_iterations=300)
    result = solve_pnp_ransac(points_world, keypoints, camera, config, _generator())
    assert not result.success and result.num_inliers == 0 and result.iterations == 300


@pytest.mark.parametrize("n", [0, 3])
def test_ransac_too_few_points_is_not_an_error(n):
    camera = _camera()
    result = solve_pnp_ransac(
        torch.rand(n, 3, dtype=torch.float64),
        torch.rand(n, 2, dtype=torch.float64),
        camera,
        PnPRansacConfig(),
        _generator(),
    )
    assert not result.success and result.num_inliers == 0 and result.iterations == 0
    assert result.inliers.shape == (n,) and result.reprojection_errors.shape == (n,)


def test_ransac_bad_inputs():
    camera = _camera()
    config = PnPRansacConfig()
    X, uv = torch.rand(20, 3, dtype=torch.float64), torch.rand(20, 2, dtype=torch.float64)
    with pytest.raises(ShapeError):
        solve_pnp_ransac(X[:19], uv, camera, config, _generator())
    with pytest.raises(ShapeError):
        solve_pnp_ransac(X[None], uv[None], camera, config, _generator())
    bad = uv.clone()
    bad[3, 1] = torch.nan
    with pytest.raises(ValueError, match="NaN"):
        solve_pnp_ransac(X, bad, camera, config, _generator())
    batched = PinholeCamera.from_fov(640, 480, torch.tensor([1.0, 1.2]))
    with pytest.raises(ValueError, match="one camera"):
        solve_pnp_ransac(X, uv, batched, config, _generator())


@pytest.mark.parametrize(
    "field, value",
    [
        ("threshold_px", 0.0),
        ("confidence", 1.0),
        ("min_iterations", 20_000),
        ("batch_size", 0),
        ("min_inliers", 3),
        ("lo_rounds", -1),
        ("num_threads", 0),
    ],
)
def test_config_validation(field, value):
    with pytest.raises(ValueError):
        PnPRansacConfig(**{field: value})
