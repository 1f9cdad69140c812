"""Camera extrinsic and time offset shared by all keyframes (diffloc.optim.rig_calibration)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.database.database import VisualDatabase
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.rig import SensorRig
from diffloc.geometry.se3 import invert, se3_exp, se3_log, vee
from diffloc.optim.lm import LMConfig
from diffloc.optim.rig_calibration import (
    RigCalibrationConfig,
    RigCalibrationCost,
    body_twists,
    calibrate_rig,
    corrected_rig,
)
from diffloc.optim.surfel_cost import SurfelReprojectionCost, lift_to_surfel
from diffloc.testing import assert_close

# torch's forward-mode AD loads its decompositions with the deprecated torch.jit.script.
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated")

F64 = torch.float64
CAM = PinholeCamera.from_fov(640, 480, math.radians(70), dtype=F64)
INTRINSICS = torch.stack([CAM.fx, CAM.fy, CAM.cx, CAM.cy])
# The simulator's default rig: camera 10 cm ahead of the body, looking along body x.
T_BC = torch.tensor(
    [[0.0, 0.0, 1.0, 0.1], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
    dtype=F64,
)
DT_TRUE = 0.03  # seconds


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)


def _extrinsic_error(translation_m: float, rotation_deg: float) -> torch.Tensor:
    """``se3_exp([v, w])`` with ``|v| = translation_m`` and ``|w| = rotation_deg``."""
    v = translation_m * _unit(torch.tensor([0.6, -0.3, 0.74], dtype=F64))
    w = math.radians(rotation_deg) * _unit(torch.tensor([-0.2, 0.7, 0.4], dtype=F64))
    return se3_exp(torch.cat((v, w)))


def _camera_path(t: torch.Tensor) -> torch.Tensor:
    """(N, 4, 4) cameras on an accelerating, bobbing arc, looking at the origin (y ~ down)."""
    a = -0.6 + 0.25 * t + 0.08 * t * t
    eye = torch.stack((5 * torch.sin(a), -5 * torch.cos(a), 0.3 * torch.sin(2 * t)), -1)
    z = _unit(-eye)
    x = _unit(torch.linalg.cross(z, torch.tensor([0.0, 0.0, -1.0], dtype=F64).expand_as(z)))
    y = torch.linalg.cross(z, x)
    T = torch.eye(4, dtype=F64).repeat(len(t), 1, 1)
    T[:, :3, :3] = torch.stack((x, y, z), -1)
    T[:, :3, 3] = eye
    return T


def _body_path(t: torch.Tensor) -> torch.Tensor:
    """(N, 4, 4) body poses whose camera (through :data:`T_BC`) follows :func:`_camera_path`."""
    return _camera_path(t) @ invert(T_BC)


@dataclass
class Scene:
    T_true: torch.Tensor  # (K, 4, 4) true keyframe poses
    centers: torch.Tensor  # (S, 3)
    normals: torch.Tensor  # (S, 3)
    seen: torch.Tensor  # (S, K) bool
    keypoints: torch.Tensor  # (K, S, 2)


def _scene(T_true: torch.Tensor, num_surfels: int = 300, seed: int = 0) -> Scene:
    """Surfels on random planes near the origin, each seen by at least two keyframes.

    The first observer's keypoint is exactly representable in float32 (the database stores
    float32) and the surfel's point is its lift, so the true poses give residuals of float32
    rounding only.
    """
    g = torch.Generator().manual_seed(seed)
    K = T_true.shape[0]
    centers = (torch.rand(num_surfels, 3, generator=g, dtype=F64) - 0.5) * 2.0
    normals = _unit(torch.randn(num_surfels, 3, generator=g, dtype=F64))
    towards = _unit(T_true[:, :3, 3].mean(0) - centers)  # face the cameras
    normals = torch.where((normals * towards).sum(-1, keepdim=True) < 0, -normals, normals)
    normals = _unit(normals + towards)
    seen = torch.rand(num_surfels, K, generator=g) < 0.5
    pair = torch.argsort(torch.rand(num_surfels, K, generator=g), dim=1)[:, :2]
    seen[torch.arange(num_surfels)[:, None], pair] = True
    alpha = seen.to(torch.int64).argmax(1)  # first observer
    offsets = 0.2 * torch.randn(num_surfels, 3, generator=g, dtype=F64)
    offsets = offsets - (offsets * normals).sum(-1, keepdim=True) * normals
    keypoints_alpha = CAM.project_world((centers + offsets)[:, None], T_true[alpha])[0][:, 0]
    keypoints_alpha = keypoints_alpha.float().double()
    points = lift_to_surfel(
        keypoints_alpha,
        T_true[alpha],
        *INTRINSICS[:, None].expand(4, num_surfels),
        centers,
        normals,
    )[0]
    keypoints = CAM.project_world(points, T_true)[0]  # (K, S, 2)
    keypoints[alpha, torch.arange(num_surfels)] = keypoints_alpha
    return Scene(T_true, centers, normals, seen, keypoints)


def _database(scene: Scene, T_wc: torch.Tensor) -> VisualDatabase:
    """A database of the scene with keyframe poses ``T_wc``, one map point per surfel."""
    db = VisualDatabase(descriptor_dim=2)
    S = scene.centers.shape[0]
    for k in range(len(T_wc)):
        ids = torch.nonzero(scene.seen[:, k])[:, 0]
        n = len(ids)
        db.add_keyframe(
            T_wc[k], CAM, scene.keypoints[k, ids], torch.zeros(n, 2), torch.ones(n), ids
        )
    point_ids = db.add_points(scene.centers, torch.zeros(S, 2), torch.arange(S))
    for k in range(len(T_wc)):
        ids = torch.nonzero(scene.seen[:, k])[:, 0]
        db.add_observations(k, torch.arange(len(ids)), point_ids[ids])
    return db


def _errors(T: torch.Tensor, T_ref: torch.Tensor) -> tuple[float, float]:
    """Largest translation (m) and rotation (rad) difference."""
    delta = se3_log(invert(T_ref) @ T)
    return float(delta[..., :3].norm(dim=-1).max()), float(delta[..., 3:].norm(dim=-1).max())


@dataclass
class Problem:
    scene: Scene
    T_wb: torch.Tensor  # (N, 4, 4) trajectory samples
    times: torch.Tensor  # (N,)
    keyframes: torch.Tensor  # (K,) sample of each keyframe
    db: VisualDatabase  # poses through the wrong extrinsic, no time offset
    E: torch.Tensor  # (4, 4) expected correction


def _problem(model_exact: bool, dt: float = DT_TRUE, seed: int = 0) -> Problem:
    """Keyframes at every third sample of a 31-sample trajectory (jittered times).

    The database poses are ``T_wb(t_k) T_BC E^-1``; the images (keypoints) are taken at
    ``T_wb(t_k) Exp(dt v_k) T_BC`` with the finite-difference twist of the samples
    (``model_exact``: the calibration model itself) or at ``T_wb(t_k + dt) T_BC`` of the
    continuous trajectory (the model is then first order in ``dt``).
    """
    g = torch.Generator().manual_seed(seed)
    times = torch.linspace(0.0, 3.0, 31, dtype=F64)
    times[1:-1] += 0.02 * (torch.rand(29, generator=g, dtype=F64) - 0.5)
    T_wb = _body_path(times)
    keyframes = torch.arange(0, 31, 3)
    if model_exact:
        v = body_twists(T_wb, times)[keyframes]
        T_true = T_wb[keyframes] @ se3_exp(dt * v) @ T_BC
    else:
        T_true = _body_path(times[keyframes] + dt) @ T_BC
    scene = _scene(T_true, seed=seed)
    E = _extrinsic_error(0.03, 1.0)
    db = _database(scene, T_wb[keyframes] @ T_BC @ invert(E))
    return Problem(scene, T_wb, times, keyframes, db, E)


@pytest.fixture(scope="module")
def exact() -> Problem:
    return _problem(model_exact=True)


# ---------------------------------------------------------------------------- twists


def test_body_twists_are_exact_for_a_constant_twist() -> None:
    xi = torch.tensor([0.4, -0.1, 0.2, 0.3, -0.5, 0.8], dtype=F64)
    times = torch.tensor([0.0, 0.1, 0.35, 0.4, 0.9], dtype=F64)
    T = se3_exp(torch.tensor([1.0, 2.0, 3.0, 0.1, 0.2, 0.3], dtype=F64)) @ se3_exp(
        times[:, None] * xi
    )
    assert_close(body_twists(T, times), xi.expand(5, 6), atol=1e-12, rtol=0)


def test_body_twists_are_second_order_inside_first_order_at_the_ends() -> None:
    def twist(t: float) -> torch.Tensor:  # vee(T^-1 dT/dt) by central differences, h tiny
        h = 1e-6
        T0, T1, T2 = _body_path(torch.tensor([t - h, t, t + h], dtype=F64))
        dT = (T2 - T0) / (2 * h)
        M = invert(T1) @ dT
        return torch.cat((M[:3, 3], vee(M[:3, :3])))

    errors = {}
    for h in (0.1, 0.05):
        times = torch.arange(0.5, 2.5 + h / 2, h, dtype=F64)
        estimate = body_twists(_body_path(times), times)
        middle = len(times) // 2
        errors[h] = [float((estimate[i] - twist(float(times[i]))).norm()) for i in (middle, 0)]
    inner = errors[0.1][0] / errors[0.05][0]
    end = errors[0.1][1] / errors[0.05][1]
    assert 3.0 < inner < 5.0  # O(h^2)
    assert 1.5 < end < 2.5  # O(h)
    assert errors[0.05][0] < 2e-3  # twists of ~3 m/s


def test_body_twists_bad_inputs_raise() -> None:
    T = torch.eye(4, dtype=F64).repeat(3, 1, 1)
    with pytest.raises(ValueError, match="strictly increasing"):
        body_twists(T, torch.tensor([0.0, 1.0, 1.0], dtype=F64))
    with pytest.raises(ValueError, match="at least 2"):
        body_twists(T[:1], torch.zeros(1, dtype=F64))
    with pytest.raises(ShapeError):
        body_twists(T, torch.zeros(2, dtype=F64))
    bad = T.clone()
    bad[1, 0, 3] = math.nan
    with pytest.raises(ValueError, match="NaN"):
        body_twists(bad, torch.arange(3, dtype=F64))


# ---------------------------------------------------------------------------- Jacobians


def _random_rig(batch: tuple[int, ...], seed: int = 0):
    """A rig cost of 5 keyframes and 12 pairs with non-zero residuals, and a random point."""
    g = torch.Generator().manual_seed(seed)
    T_wc = _camera_path(torch.linspace(0.0, 2.0, 5, dtype=F64))
    scene = _scene(T_wc, num_surfels=12, seed=seed)
    count = scene.seen.to(torch.int64).cumsum(1)
    alpha, beta = ((count == 1) & scene.seen).int().argmax(1), (count == 2).int().argmax(1)
    index = torch.arange(12)
    K = INTRINSICS.expand(12, 4)
    cost = SurfelReprojectionCost(
        scene.keypoints[alpha, index],
        scene.keypoints[beta, index] + 2.0 * torch.randn(12, 2, generator=g, dtype=F64),
        scene.centers,
        scene.normals,
        K,
        K,
        torch.linspace(0.5, 2.0, 12, dtype=F64),
    )
    twists = torch.randn(5, 6, generator=g, dtype=F64)
    rig = RigCalibrationCost(cost, alpha, beta, T_wc, twists)
    xi = 0.05 * torch.randn(*batch, 6, generator=g, dtype=F64)
    dt = 0.03 * torch.randn(batch, generator=g, dtype=F64)
    return rig, se3_exp(xi), dt


@pytest.mark.parametrize("batch", [(), (2,)])
def test_linearize_matches_autodiff(batch: tuple[int, ...]) -> None:
    rig, C, dt = _random_rig(batch)
    lin = rig.linearize(C, dt)

    def residuals(delta: torch.Tensor) -> torch.Tensor:  # delta: (..., 7)
        return rig(C @ se3_exp(delta[..., :6]), dt + delta[..., 6])

    zero = torch.zeros(*batch, 7, dtype=F64)
    J = torch.func.jacfwd(residuals)(zero)  # (..., M, 2, ..., 7)
    if batch:
        J = J.diagonal(dim1=0, dim2=3).movedim(-1, 0)  # (B, M, 2, 7)
    assert bool((lin.residuals.abs() > 0.1).any())
    assert_close(lin.residuals, residuals(zero))
    assert_close(lin.jac_a, J[..., :6], rtol=1e-8, atol=1e-8)
    assert_close(lin.jac_extra, J[..., 6:], rtol=1e-8, atol=1e-8)
    assert lin.jac_b is None


def test_dt_jacobian_matches_finite_differences() -> None:
    rig, C, dt = _random_rig(())
    h = 1e-6
    numeric = (rig(C, dt + h) - rig(C, dt - h)) / (2 * h)
    assert_close(rig.linearize(C, dt).jac_extra[..., 0], numeric, rtol=1e-6, atol=1e-6)


def test_keyframe_poses_follow_the_model() -> None:
    rig, C, dt = _random_rig(())
    expected = rig.T_wc @ se3_exp(dt * rig.twists) @ C
    assert_close(rig.keyframe_poses(C, dt), expected)
    with pytest.raises(ShapeError):
        rig.keyframe_poses(C, dt.expand(2))


# ---------------------------------------------------------------------------- calibration


def test_recovers_extrinsic_and_time_offset_exactly(exact: Problem) -> None:
    result = calibrate_rig(
        exact.db,
        exact.scene.centers,
        exact.scene.normals,
        exact.T_wb,
        exact.times,
        exact.keyframes,
    )
    assert result.converged, result.reason
    translation, rotation = _errors(result.T_correction, exact.E)
    assert translation < 1e-6 and rotation < 1e-6
    assert abs(result.dt - DT_TRUE) < 1e-6
    translation, rotation = _errors(result.T_wc, exact.scene.T_true)
    assert translation < 1e-6 and rotation < 1e-6
    assert result.cost < 1e-6 * result.initial_cost
    assert result.num_pairs == int(exact.scene.seen.sum() - exact.scene.seen.shape[0])
    assert result.std.shape == (7,) and bool((result.std > 0).all())
    assert bool((result.dt_correlation.abs() < 1).all())


def test_extrinsic_only_recovers_the_correction() -> None:
    problem = _problem(model_exact=True, dt=0.0)
    result = calibrate_rig(
        problem.db,
        problem.scene.centers,
        problem.scene.normals,
        config=RigCalibrationConfig(estimate_time_offset=False),
    )
    assert result.converged, result.reason
    translation, rotation = _errors(result.T_correction, problem.E)
    assert translation < 1e-6 and rotation < 1e-6
    assert result.dt == 0.0 and result.std.shape == (6,)
    assert bool((result.dt_correlation == 0).all())


def test_first_order_model_on_the_continuous_trajectory() -> None:
    """Images at ``T_wb(t_k + dt)``: only the O(dt^2) model error remains."""
    problem = _problem(model_exact=False)
    result = calibrate_rig(
        problem.db,
        problem.scene.centers,
        problem.scene.normals,
        problem.T_wb,
        problem.times,
        problem.keyframes,
    )
    translation, rotation = _errors(result.T_correction, problem.E)
    assert translation < 2e-3 and rotation < math.radians(0.05)
    assert abs(result.dt - DT_TRUE) < 2e-3
    before = _errors(problem.db.T_wc, problem.scene.T_true)[0]
    after = _errors(result.T_wc, problem.scene.T_true)[0]
    assert after < 0.05 * before


def test_trajectory_of_exactly_the_keyframes(exact: Problem) -> None:
    """``keyframe_indices=None``: ``T_wb`` holds one sample per keyframe."""
    rig_samples = exact.T_wb[exact.keyframes], exact.times[exact.keyframes]
    result = calibrate_rig(exact.db, exact.scene.centers, exact.scene.normals, *rig_samples)
    assert result.converged
    # Keyframe-only differences are coarser than the model's twists: close, not exact.
    assert abs(result.dt - DT_TRUE) < 5e-3


def test_bad_inputs_raise(exact: Problem) -> None:
    db, centers, normals = exact.db, exact.scene.centers, exact.scene.normals
    T_wb, times, index = exact.T_wb, exact.times, exact.keyframes
    single = _database(
        Scene(
            exact.scene.T_true[:1], centers, normals, exact.scene.seen[:, :1], exact.scene.keypoints
        ),
        exact.scene.T_true[:1],
    )
    with pytest.raises(ValueError, match="at least 2 keyframes"):
        calibrate_rig(single, centers, normals, T_wb, times, index[:1])
    with pytest.raises(ValueError, match="strictly increasing"):
        calibrate_rig(db, centers, normals, T_wb, times.flip(0), index)
    bad = T_wb.clone()
    bad[3, 1, 3] = math.inf
    with pytest.raises(ValueError, match="T_wb contains NaN"):
        calibrate_rig(db, centers, normals, bad, times, index)
    nan_db = _database(exact.scene, db.T_wc)
    nan_db.T_wc[2, 0, 0] = math.nan
    with pytest.raises(ValueError, match="db.T_wc contains NaN"):
        calibrate_rig(nan_db, centers, normals, T_wb, times, index)
    with pytest.raises(ValueError, match="needs the body trajectory"):
        calibrate_rig(db, centers, normals)
    with pytest.raises(ShapeError, match="keyframe_indices"):
        calibrate_rig(db, centers, normals, T_wb, times)
    with pytest.raises(ValueError, match=r"keyframe_indices must be in \[0, 31\)"):
        calibrate_rig(db, centers, normals, T_wb, times, index + 10)
    with pytest.raises(TypeError):
        calibrate_rig(db, centers, normals, T_wb, times, index.double())
    with pytest.raises(ShapeError):
        calibrate_rig(db, centers, normals, T_wb[:, :3], times, index)
    with pytest.raises(ShapeError):
        calibrate_rig(db, centers, normals[:5], T_wb, times, index)
    no_surfels = _database(exact.scene, db.T_wc)
    no_surfels.point_surfels[:] = -1
    with pytest.raises(ValueError, match="no valid surfel pairs"):
        calibrate_rig(no_surfels, centers, normals, T_wb, times, index)
    with pytest.raises(ValueError, match="sigma_px"):
        RigCalibrationConfig(sigma_px=0.0)


def test_lm_settings_are_used(exact: Problem) -> None:
    config = RigCalibrationConfig(lm=LMConfig(max_iterations=1))
    result = calibrate_rig(
        exact.db,
        exact.scene.centers,
        exact.scene.normals,
        exact.T_wb,
        exact.times,
        exact.keyframes,
        config,
    )
    assert result.iterations == 1 and result.reason == "max_iterations"
    assert result.cost < result.initial_cost


def test_corrected_rig_applies_the_correction() -> None:
    rig = SensorRig.from_transforms({"camera": T_BC, "lidar": se3_exp(torch.ones(6, dtype=F64))})
    C = _extrinsic_error(0.05, 1.0)
    fixed = corrected_rig(rig, C)
    with torch.no_grad():
        assert_close(fixed.T_body_sensor("camera"), T_BC @ C)
        assert_close(fixed.T_body_sensor("lidar"), rig.T_body_sensor("lidar"))
    assert SensorRig.from_urdf(fixed.to_urdf()).to_urdf() == fixed.to_urdf()
    with pytest.raises(ValueError, match="no sensor 'cam'"):
        corrected_rig(rig, C, camera="cam")
    with pytest.raises(ShapeError):
        corrected_rig(rig, C[:3])


def test_rig_cost_bad_inputs_raise() -> None:
    rig, _, _ = _random_rig(())
    with pytest.raises(ShapeError):
        RigCalibrationCost(rig.cost, rig.alpha[:3], rig.beta, rig.T_wc, rig.twists)
    with pytest.raises(ShapeError):
        RigCalibrationCost(rig.cost, rig.alpha, rig.beta, rig.T_wc, rig.twists[:3])
    with pytest.raises(ValueError, match="keyframe indices"):
        RigCalibrationCost(rig.cost, rig.alpha + 5, rig.beta, rig.T_wc, rig.twists)
