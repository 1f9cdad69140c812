"""Surfel reprojection constraints (seed 1 Sec. III-B, Eq. 1-4): lift, cost, database pairs."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.database.database import VisualDatabase
from diffloc.geometry.camera import MIN_DEPTH, PinholeCamera
from diffloc.geometry.se3 import invert, se3_exp, se3_log
from diffloc.optim.lm import autodiff_linearize, levenberg_marquardt
from diffloc.optim.surfel_cost import (
    SurfelOptimConfig,
    SurfelReprojectionCost,
    lift_to_surfel,
    optimize_keyframe_poses,
    pairs_from_database,
    replace_map_points,
)
from diffloc.testing import assert_close, gradcheck, random_se3

# torch's forward-mode AD loads its decompositions with the deprecated torch.jit.script.
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated")

F64 = torch.float64
CAM = PinholeCamera.from_fov(640, 480, math.radians(70), dtype=F64)
INTRINSICS = torch.stack([CAM.fx, CAM.fy, CAM.cx, CAM.cy])


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)


def _look_at(eye: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """OpenCV camera-to-world pose at ``eye`` looking at ``target`` (y down ~ world -z)."""
    z = _unit(target - eye)
    x = _unit(torch.linalg.cross(z, torch.tensor([0.0, 0.0, -1.0], dtype=F64)))
    y = torch.linalg.cross(z, x)
    T = torch.eye(4, dtype=F64)
    T[:3, :3] = torch.stack([x, y, z], dim=1)
    T[:3, 3] = eye
    return T


def _lift(keypoints: torch.Tensor, T_wc: torch.Tensor, centers, normals):
    M = keypoints.shape[0]
    fx, fy, cx, cy = (v.expand(M) for v in INTRINSICS)
    return lift_to_surfel(keypoints, T_wc.expand(M, 4, 4), fx, fy, cx, cy, centers, normals)


def _project(points_world: torch.Tensor, T_wc: torch.Tensor) -> torch.Tensor:
    return CAM.project_world(points_world, T_wc)[0]


def _perturb(T: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Move by exactly 0.2 m and rotate by exactly 2 degrees, random directions."""
    shape = T.shape[:-2]
    v = 0.2 * _unit(torch.randn(*shape, 3, generator=generator, dtype=F64))
    w = math.radians(2.0) * _unit(torch.randn(*shape, 3, generator=generator, dtype=F64))
    T_new = T.clone()
    T_new[..., :3, :3] = (
        se3_exp(torch.cat([torch.zeros_like(w), w], -1))[..., :3, :3] @ T[..., :3, :3]
    )
    T_new[..., :3, 3] = T[..., :3, 3] + v
    return T_new


def _pose_errors(T: torch.Tensor, T_true: torch.Tensor) -> tuple[float, float]:
    """Largest translation (m) and rotation (rad) error."""
    delta = invert(T_true) @ T
    angle = torch.linalg.vector_norm(se3_log(delta)[..., 3:], dim=-1)
    return float(delta[..., :3, 3].norm(dim=-1).max()), float(angle.max())


# ---------------------------------------------------------------------------- lift


def test_lift_fronto_parallel_plane_gives_constant_depth() -> None:
    g = torch.Generator().manual_seed(0)
    T_wc = random_se3(generator=g)
    d = 3.5
    centre_cam = torch.tensor([0.3, -0.2, d], dtype=F64)
    centers = (T_wc[:3, :3] @ centre_cam + T_wc[:3, 3]).expand(50, 3)
    normals = (T_wc[:3, :3] @ torch.tensor([0.0, 0.0, -1.0], dtype=F64)).expand(50, 3)
    keypoints = torch.rand(50, 2, generator=g, dtype=F64) * torch.tensor([640.0, 480.0])
    points_world, valid = _lift(keypoints, T_wc, centers, normals)
    points_cam = (invert(T_wc)[:3, :3] @ points_world.T).T + invert(T_wc)[:3, 3]
    assert bool(valid.all())
    assert_close(points_cam[:, 2], torch.full((50,), d, dtype=F64))
    assert_close(_project(points_world, T_wc), keypoints)


def test_lift_tilted_plane_is_the_ray_plane_point() -> None:
    g = torch.Generator().manual_seed(1)
    T_wc = _look_at(torch.tensor([0.0, -4.0, 1.0], dtype=F64), torch.zeros(3, dtype=F64))
    normal = _unit(torch.tensor([0.3, -1.0, 0.5], dtype=F64))
    tangent = _unit(torch.linalg.cross(normal, torch.tensor([1.0, 0.0, 0.0], dtype=F64)))
    bitangent = torch.linalg.cross(normal, tangent)
    centre = torch.tensor([0.2, 0.1, -0.1], dtype=F64)
    ab = torch.rand(40, 2, generator=g, dtype=F64) - 0.5
    truth = centre + ab[:, :1] * tangent + ab[:, 1:] * bitangent
    points_world, valid = _lift(
        _project(truth, T_wc), T_wc, centre.expand(40, 3), (2.5 * normal).expand(40, 3)
    )
    assert bool(valid.all())
    assert_close(points_world, truth)


def test_lift_parallel_ray_and_plane_behind_are_invalid_not_nan() -> None:
    T_wc = torch.eye(4, dtype=F64)
    keypoints = torch.stack([INTRINSICS[2:], INTRINSICS[2:] + 10.0])  # optical axis, off axis
    centers = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -2.0]], dtype=F64)
    normals = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)  # parallel; behind
    points_world, valid = _lift(keypoints, T_wc, centers, normals)
    assert valid.tolist() == [False, False]
    assert bool(torch.isfinite(points_world).all())
    cost = SurfelReprojectionCost(
        keypoints, keypoints, centers, normals, INTRINSICS.expand(2, 4), INTRINSICS.expand(2, 4)
    )
    T = T_wc.expand(2, 4, 4).clone().requires_grad_(True)
    residuals = cost(T, T)
    residuals.sum().backward()
    assert residuals.abs().max() == 0
    assert bool(torch.isfinite(T.grad).all())


@pytest.mark.parametrize(
    "shapes",
    [
        {"keypoints": (3, 2), "T_wc": (4, 4, 4)},
        {"keypoints": (3, 3), "T_wc": (3, 4, 4)},
        {"keypoints": (3, 2), "T_wc": (3, 4, 4), "fx": (2,)},
        {"keypoints": (3, 2), "T_wc": (3, 4, 4), "normals": (3, 2)},
    ],
)
def test_lift_bad_shapes_raise(shapes: dict) -> None:
    sizes = {"keypoints": (3, 2), "T_wc": (3, 4, 4), "fx": (3,), "normals": (3, 3)}
    sizes.update(shapes)
    ones = {k: torch.ones(v, dtype=F64) for k, v in sizes.items()}
    with pytest.raises(ShapeError):
        lift_to_surfel(
            ones["keypoints"],
            ones["T_wc"],
            ones["fx"],
            ones["fx"],
            ones["fx"],
            ones["fx"],
            torch.ones(3, 3, dtype=F64),
            ones["normals"],
        )


def test_cost_bad_inputs_raise() -> None:
    kp, c, K = torch.ones(3, 2, dtype=F64), torch.ones(3, 3, dtype=F64), INTRINSICS.expand(3, 4)
    with pytest.raises(ShapeError):
        SurfelReprojectionCost(kp, kp[:2], c, c, K, K)
    with pytest.raises(ShapeError):
        SurfelReprojectionCost(kp, kp, c, c, K[:, :3], K)
    with pytest.raises(ValueError, match="sigma"):
        SurfelReprojectionCost(kp, kp, c, c, K, K, torch.zeros(3, dtype=F64))
    cost = SurfelReprojectionCost(kp, kp, c, c, K, K)
    with pytest.raises(ShapeError):
        cost(torch.eye(4, dtype=F64).expand(2, 4, 4), torch.eye(4, dtype=F64).expand(3, 4, 4))


# ---------------------------------------------------------------------------- synthetic scene


@dataclass
class Scene:
    T_true: torch.Tensor  # (K, 4, 4)
    centers: torch.Tensor  # (S, 3)
    normals: torch.Tensor  # (S, 3)
    points: torch.Tensor  # (S, 3) true map points (one per surfel)
    observers: list[list[int]]  # sorted keyframes observing each point
    keypoints: torch.Tensor  # (K, S, 2) projections (alpha's exact in float32)


def _scene(num_keyframes: int = 6, num_surfels: int = 200, seed: int = 0) -> Scene:
    """Keyframes on an arc looking at surfels on random planes facing the cameras.

    Each surfel holds one map point off its centre. Every point's first observer sees it at a
    keypoint exactly representable in float32 (the database stores float32 keypoints), and
    the point is the lift of that keypoint, so Eq. 1 re-places it exactly.
    """
    g = torch.Generator().manual_seed(seed)
    angles = torch.linspace(-0.6, 0.6, num_keyframes, dtype=F64)
    eyes = torch.stack([5 * torch.sin(angles), -5 * torch.cos(angles), 0.3 * angles], -1)
    T_true = torch.stack([_look_at(eye, torch.zeros(3, dtype=F64)) for eye in eyes])
    centers = (torch.rand(num_surfels, 3, generator=g, dtype=F64) - 0.5) * 2.0
    towards_cameras = torch.tensor([0.0, -1.0, 0.0], dtype=F64)
    normals = _unit(towards_cameras + 0.8 * torch.randn(num_surfels, 3, generator=g, dtype=F64))
    normals = torch.where(normals[:, 1:2] < 0, normals, -normals)
    offsets = 0.3 * torch.randn(num_surfels, 3, generator=g, dtype=F64)
    offsets = offsets - (offsets * normals).sum(-1, keepdim=True) * normals
    points = centers + offsets
    observers = []
    for _ in range(num_surfels):
        seen = torch.rand(num_keyframes, generator=g) < 0.6
        seen[torch.randperm(num_keyframes, generator=g)[:2]] = True
        observers.append(torch.nonzero(seen).flatten().tolist())
    alpha = torch.tensor([obs[0] for obs in observers])
    keypoints_alpha = _project(points[:, None], T_true[alpha])[:, 0].float().double()
    points = _lift(keypoints_alpha, T_true[alpha], centers, normals)[0]
    keypoints = torch.stack([_project(points, T) for T in T_true])
    keypoints[alpha, torch.arange(num_surfels)] = keypoints_alpha
    return Scene(T_true, centers, normals, points, observers, keypoints)


def _database(scene: Scene, T_wc: torch.Tensor) -> VisualDatabase:
    """A database of the scene with keyframe poses ``T_wc`` and points at surfel centres."""
    db = VisualDatabase(descriptor_dim=2)
    num_surfels = scene.centers.shape[0]
    seen_by = [[s for s in range(num_surfels) if k in scene.observers[s]] for k in range(len(T_wc))]
    for k, surfels in enumerate(seen_by):
        ids = torch.tensor(surfels, dtype=torch.int64)
        n = len(surfels)
        db.add_keyframe(
            T_wc[k], CAM, scene.keypoints[k, ids], torch.zeros(n, 2), torch.ones(n), ids
        )
    point_ids = db.add_points(scene.centers, torch.zeros(num_surfels, 2), torch.arange(num_surfels))
    for k, surfels in enumerate(seen_by):
        ids = torch.tensor(surfels, dtype=torch.int64)
        db.add_observations(k, torch.arange(len(surfels)), point_ids[ids])
    return db


@pytest.fixture(scope="module")
def scene() -> Scene:
    return _scene()


def test_scene_keypoints_are_exact(scene: Scene) -> None:
    for s, obs in enumerate(scene.observers):
        for k in obs:
            assert_close(
                _project(scene.points[s : s + 1], scene.T_true[k])[0],
                scene.keypoints[k, s],
                atol=1e-4,
                rtol=0,
            )


def test_pairs_from_database(scene: Scene) -> None:
    db = _database(scene, scene.T_true)
    pairs = pairs_from_database(db, scene.centers, scene.normals)
    expected = [(s, obs[0], b) for s, obs in enumerate(scene.observers) for b in obs[1:]]
    got = list(zip(pairs.points.tolist(), pairs.alpha.tolist(), pairs.beta.tolist(), strict=True))
    assert got == expected
    assert_close(pairs.keypoints_alpha, scene.keypoints[pairs.alpha, pairs.points].float())
    assert_close(pairs.keypoints_beta, scene.keypoints[pairs.beta, pairs.points].float())
    assert_close(pairs.centers, scene.centers[pairs.points])
    assert_close(pairs.normals, scene.normals[pairs.points])
    assert_close(pairs.intrinsics_beta, INTRINSICS.expand(len(pairs), 4))
    residuals = SurfelReprojectionCost.from_pairs(pairs)(
        scene.T_true[pairs.alpha], scene.T_true[pairs.beta]
    )
    assert residuals.abs().max() < 1e-3  # float32 keypoints in beta


def test_points_without_surfel_give_no_pairs_and_keep_position(scene: Scene) -> None:
    db = _database(scene, scene.T_true)
    db.point_surfels[:10] = -1
    pairs = pairs_from_database(db, scene.centers, scene.normals)
    assert bool((pairs.points >= 10).all())
    positions = replace_map_points(db, scene.centers, scene.normals)
    assert_close(positions[:10], scene.centers[:10])


def test_replace_map_points_lands_on_true_surface_points(scene: Scene) -> None:
    db = _database(scene, scene.T_true)
    positions = replace_map_points(db, scene.centers, scene.normals)
    assert_close(positions, scene.points, atol=1e-12, rtol=0)
    on_plane = ((positions - scene.centers) * scene.normals).sum(-1)
    assert on_plane.abs().max() < 1e-12


def test_database_functions_reject_bad_surfels(scene: Scene) -> None:
    db = _database(scene, scene.T_true)
    with pytest.raises(ShapeError):
        pairs_from_database(db, scene.centers, scene.normals[:5])
    with pytest.raises(ValueError, match="surfels beyond"):
        replace_map_points(db, scene.centers[:5], scene.normals[:5])
    nan = torch.full((1, 3), float("nan"), dtype=F64)
    bad = scene.centers.clone()
    bad[int(db.point_surfels.max())] = nan  # a surfel map points use
    with pytest.raises(ValueError, match="surfel_centers"):
        pairs_from_database(db, bad, scene.normals)
    with pytest.raises(ValueError, match="surfel_normals"):
        replace_map_points(db, scene.centers, torch.where(bad.isnan(), bad, scene.normals))
    # A bad surfel no map point uses does not matter.
    unused = pairs_from_database(
        db, torch.cat((scene.centers, nan)), torch.cat((scene.normals, nan))
    )
    assert len(unused) == len(pairs_from_database(db, scene.centers, scene.normals))


@pytest.mark.parametrize("fix_first", [True, False])
def test_optimize_recovers_perturbed_poses(scene: Scene, fix_first: bool) -> None:
    T_init = _perturb(scene.T_true, torch.Generator().manual_seed(3))
    if fix_first:  # the gauge keyframe starts right; otherwise the surfel planes anchor it
        T_init[0] = scene.T_true[0]
    db = _database(scene, T_init)
    config = SurfelOptimConfig(fix_first_keyframe=fix_first)
    T_wc, result = optimize_keyframe_poses(db, scene.centers, scene.normals, config)
    assert bool(result.converged), result.reason
    translation, rotation = _pose_errors(T_wc, scene.T_true)
    assert translation < 1e-6 and rotation < 1e-6
    if fix_first:
        assert torch.equal(T_wc[0], scene.T_true[0])
    db.T_wc = T_wc
    assert_close(replace_map_points(db, scene.centers, scene.normals), scene.points, atol=1e-6)


def test_keyframes_in_fewer_than_min_pairs_pairs_are_held_constant(scene: Scene) -> None:
    """A keyframe in fewer than ``min_pairs`` valid pairs keeps its initial pose; the others
    are optimised (here they recover the truth, the held keyframe starting at its own)."""
    db = _database(scene, scene.T_true)
    pairs = pairs_from_database(db, scene.centers, scene.normals)
    counts = torch.bincount(torch.cat([pairs.alpha, pairs.beta]), minlength=db.num_keyframes)
    weakest = int(counts.argmin())
    assert int((counts <= counts[weakest]).sum()) == 1
    T_init = _perturb(scene.T_true, torch.Generator().manual_seed(3))
    T_init[weakest] = scene.T_true[weakest]
    db.T_wc = T_init
    config = SurfelOptimConfig(fix_first_keyframe=False, min_pairs=int(counts[weakest]) + 1)
    T_wc, _ = optimize_keyframe_poses(db, scene.centers, scene.normals, config)
    assert torch.equal(T_wc[weakest], T_init[weakest])
    translation, rotation = _pose_errors(T_wc, scene.T_true)
    assert translation < 1e-6 and rotation < 1e-6
    with pytest.raises(ValueError, match="min_pairs"):
        optimize_keyframe_poses(
            db, scene.centers, scene.normals, SurfelOptimConfig(min_pairs=int(counts.max()) + 1)
        )


def test_optimize_without_pairs_raises(scene: Scene) -> None:
    db = _database(scene, scene.T_true)
    db.point_surfels[:] = -1
    with pytest.raises(ValueError, match="no valid surfel pairs"):
        optimize_keyframe_poses(db, scene.centers, scene.normals)


def test_optimize_uses_only_the_pairs_of_the_given_points(scene: Scene) -> None:
    """Keyframe 3's keypoints of the first half of the points are wrong: the optimisation on
    the second half recovers the truth, on all points it does not."""
    keypoints = scene.keypoints.clone()
    half = scene.centers.shape[0] // 2
    keypoints[3, :half] += 25.0
    wrong = Scene(
        scene.T_true, scene.centers, scene.normals, scene.points, scene.observers, keypoints
    )
    T_init = _perturb(scene.T_true, torch.Generator().manual_seed(3))
    db = _database(wrong, T_init)
    points = torch.arange(db.num_points) >= half
    config = SurfelOptimConfig(fix_first_keyframe=False, min_pairs=0)
    T_wc, _ = optimize_keyframe_poses(db, scene.centers, scene.normals, config, points=points)
    assert _pose_errors(T_wc, scene.T_true)[0] < 1e-6
    T_all, _ = optimize_keyframe_poses(db, scene.centers, scene.normals, config)
    assert _pose_errors(T_all, scene.T_true)[0] > 1e-3
    with pytest.raises(ValueError, match="no valid surfel pairs"):
        optimize_keyframe_poses(
            db, scene.centers, scene.normals, config, points=torch.zeros_like(points)
        )
    with pytest.raises(ShapeError, match="points"):
        optimize_keyframe_poses(db, scene.centers, scene.normals, config, points=points[:-1])


def test_bad_config_raises() -> None:
    with pytest.raises(ValueError):
        SurfelOptimConfig(sigma_px=0.0)
    with pytest.raises(ValueError, match="min_pairs"):
        SurfelOptimConfig(min_pairs=-1)


# ---------------------------------------------------------------------------- gradients


def _small_problem(M: int = 4):
    scene = _scene(num_keyframes=2, num_surfels=M, seed=5)
    kp_a = torch.stack([scene.keypoints[obs[0], s] for s, obs in enumerate(scene.observers)])
    kp_b = kp_a + 1.5  # non-zero residuals
    K = INTRINSICS.expand(M, 4)
    sigma = torch.linspace(0.5, 2.0, M, dtype=F64)
    cost = SurfelReprojectionCost(kp_a, kp_b, scene.centers, scene.normals, K, K, sigma)
    T_a = scene.T_true[0].expand(M, 4, 4)
    T_b = scene.T_true[1].expand(M, 4, 4)
    return cost, T_a, T_b


def test_cost_gradcheck_wrt_both_poses() -> None:
    cost, T_a, T_b = _small_problem()
    assert bool(cost.residuals_and_valid(T_a, T_b)[1].all())

    def fn(xi_a: torch.Tensor, xi_b: torch.Tensor) -> torch.Tensor:
        return cost(T_a @ se3_exp(xi_a), T_b @ se3_exp(xi_b))

    zero = torch.zeros(4, 6, dtype=F64)
    assert gradcheck(fn, [zero + 1e-3, zero - 1e-3])


def test_lift_gradcheck_wrt_keypoints_poses_and_surfels() -> None:
    scene = _scene(num_keyframes=2, num_surfels=3, seed=6)
    kp = scene.keypoints[0]
    T = scene.T_true[0].expand(3, 4, 4)
    fx, fy, cx, cy = (v.expand(3) for v in INTRINSICS)

    def fn(keypoints, xi, centers, normals):
        return lift_to_surfel(keypoints, T @ se3_exp(xi), fx, fy, cx, cy, centers, normals)[0]

    assert gradcheck(fn, [kp, torch.full((3, 6), 1e-3), scene.centers, scene.normals])


def test_cost_batched_poses_match_unbatched() -> None:
    cost, T_a, T_b = _small_problem()
    g = torch.Generator().manual_seed(7)
    delta = random_se3((2, 4), generator=g, max_angle=0.02, max_translation=0.05)
    batched = cost(T_a @ delta, T_b @ delta.flip(0))
    for i in range(2):
        assert_close(batched[i], cost(T_a @ delta[i], T_b @ delta[1 - i]))


# ---------------------------------------------------------------------------- analytic Jacobians

DEGENERATE = ("parallel ray", "plane behind alpha", "alpha on the plane", "behind beta")


def _random_pairs(M: int, batch: tuple[int, ...], seed: int):
    """A cost of ``M`` random pairs and (*batch, M) poses; the first pairs are degenerate.

    Keypoints lie on the image, the surfel plane through the keypoint's point at a depth of
    1-5 m in ``alpha`` has a random tilt, ``beta`` is ``alpha`` moved by up to 0.3 rad and
    0.5 m. Pairs ``0 .. 3`` (when ``M > 4``) are made invalid as named in ``DEGENERATE``;
    batch entries differ by small pose changes that keep them so.
    """
    g = torch.Generator().manual_seed(seed)
    T_a = random_se3((M,), generator=g, max_translation=3.0)
    T_b = T_a @ random_se3((M,), generator=g, max_angle=0.3, max_translation=0.5)
    K = (INTRINSICS * (1.0 + 0.2 * torch.rand(M, 4, generator=g, dtype=F64))).contiguous()
    kp_a = torch.rand(M, 2, generator=g, dtype=F64) * torch.tensor([640.0, 480.0])
    kp_b = torch.rand(M, 2, generator=g, dtype=F64) * torch.tensor([640.0, 480.0])
    rays = torch.stack([(kp_a[:, 0] - K[:, 2]) / K[:, 0], (kp_a[:, 1] - K[:, 3]) / K[:, 1]], -1)
    rays_world = (T_a[:, :3, :3] @ torch.cat([rays, torch.ones(M, 1, dtype=F64)], -1)[..., None])[
        ..., 0
    ]
    depth = 1.0 + 4.0 * torch.rand(M, 1, generator=g, dtype=F64)
    normals = -_unit(rays_world) + 0.7 * torch.randn(M, 3, generator=g, dtype=F64)
    normals = normals * (0.5 + torch.rand(M, 1, generator=g, dtype=F64))  # any length
    in_plane = torch.linalg.cross(normals, torch.randn(M, 3, generator=g, dtype=F64))
    centers = T_a[:, :3, 3] + depth * rays_world + 0.3 * _unit(in_plane)
    sigma = 0.5 + torch.rand(M, generator=g, dtype=F64)
    keep = torch.ones(M, dtype=torch.bool)  # pairs whose poses may be perturbed in the batch
    if M > len(DEGENERATE):
        normals[0] = torch.linalg.cross(rays_world[0], torch.tensor([1.0, 2.0, 3.0], dtype=F64))
        centers[1] = T_a[1, :3, 3] - 2.0 * rays_world[1]
        centers[2] = T_a[2, :3, 3]
        T_b[3] = T_a[3] @ torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0], dtype=F64))
        keep[: len(DEGENERATE)] = False
    cost = SurfelReprojectionCost(kp_a, kp_b, centers, normals, K, K.flip(0), sigma)
    delta_a = random_se3((*batch, M), generator=g, max_angle=0.05, max_translation=0.05)
    delta_b = random_se3((*batch, M), generator=g, max_angle=0.05, max_translation=0.05)
    identity = torch.eye(4, dtype=F64)
    delta_a = torch.where(keep[:, None, None], delta_a, identity)
    delta_b = torch.where(keep[:, None, None], delta_b, identity)
    return cost, T_a @ delta_a, T_b @ delta_b


def _assert_jacobian_close(J: torch.Tensor, J_ref: torch.Tensor, rtol: float = 1e-8) -> None:
    """Entries within ``rtol`` of the largest entry of their block (..., M, 2, 6)."""
    scale = J_ref.abs().amax(dim=(-2, -1), keepdim=True)
    error = (J - J_ref).abs()
    assert bool((error <= rtol * scale).all()), float((error / scale.clamp(min=1e-300)).max())


@pytest.mark.parametrize(
    ("M", "batch"), [(1, ()), (5, ()), (64, ()), (300, ()), (64, (2,)), (40, (1, 2))]
)
def test_linearize_matches_autodiff(M: int, batch: tuple[int, ...]) -> None:
    cost, T_a, T_b = _random_pairs(M, batch, seed=M + len(batch))
    lin = cost.linearize(T_a, T_b)
    ref = autodiff_linearize(lambda Ta, Tb, e: cost(Ta, Tb), T_a, T_b)
    residuals, valid = cost.residuals_and_valid(T_a, T_b)
    assert lin.residuals.shape == (*batch, M, 2)
    assert lin.jac_a.shape == lin.jac_b.shape == (*batch, M, 2, 6)
    assert lin.jac_a.dtype == lin.jac_b.dtype == F64
    assert_close(lin.residuals, residuals, rtol=1e-12, atol=0)
    assert_close(lin.residuals, ref.residuals, rtol=1e-12, atol=0)
    _assert_jacobian_close(lin.jac_a, ref.jac_a)
    _assert_jacobian_close(lin.jac_b, ref.jac_b)
    if M > len(DEGENERATE):
        assert not bool(valid[..., : len(DEGENERATE)].any()), "degenerate pairs must be invalid"
        random_valid = valid[..., len(DEGENERATE) :].double().mean()
        assert float(random_valid) >= 0.5, "most random pairs should be valid"
    invalid = ~valid[..., None, None]
    for J in (lin.jac_a, lin.jac_b, lin.residuals[..., None]):
        assert bool(torch.where(invalid, J, 0.0).eq(0).all())
        assert bool(torch.isfinite(J).all())


@pytest.mark.parametrize(("M", "batch"), [(64, ()), (40, (1, 2))])
def test_residuals_match_lift_and_projection_reference(M: int, batch: tuple[int, ...]) -> None:
    """The component-major residuals against :func:`lift_to_surfel` and a row-wise pinhole
    projection (the obviously-correct reference)."""
    cost, T_a, T_b = _random_pairs(M, batch, seed=100 + M)
    residuals, valid = cost.residuals_and_valid(T_a, T_b)
    K_a, K_b = cost.intrinsics_alpha, cost.intrinsics_beta
    points_world, lifted = lift_to_surfel(
        cost.keypoints_alpha, T_a, *K_a.unbind(-1), cost.centers, cost.normals
    )
    points_b = (T_b[..., :3, :3].mT @ (points_world - T_b[..., :3, 3])[..., None])[..., 0]
    in_front = points_b[..., 2] > MIN_DEPTH
    xy = points_b[..., :2] / torch.where(in_front, points_b[..., 2], 1.0)[..., None]
    expected = (xy * K_b[:, :2] + K_b[:, 2:] - cost.keypoints_beta) / cost.sigma[:, None]
    assert torch.equal(valid, lifted & in_front)
    assert_close(residuals, torch.where(valid[..., None], expected, 0.0), rtol=1e-12, atol=1e-9)
    assert_close(cost(T_a, T_b), residuals, rtol=0.0, atol=0.0)


def test_linearize_bad_shapes_raise() -> None:
    cost, T_a, T_b = _random_pairs(6, (), seed=12)
    with pytest.raises(ShapeError):
        cost.linearize(T_a[:5], T_b[:5])
    with pytest.raises(ShapeError):
        cost.linearize(T_a, T_b[..., :3, :])


def test_optimize_analytic_matches_autodiff_lm(scene: Scene) -> None:
    """optimize_keyframe_poses (analytic Jacobians) takes the steps of the autodiff solver."""
    T_init = _perturb(scene.T_true, torch.Generator().manual_seed(4))
    db = _database(scene, T_init)
    config = SurfelOptimConfig(fix_first_keyframe=False)
    T_wc, result = optimize_keyframe_poses(db, scene.centers, scene.normals, config)
    pairs = pairs_from_database(db, scene.centers, scene.normals)
    cost = SurfelReprojectionCost.from_pairs(pairs)
    T0 = db.T_wc.to(F64)
    reference = levenberg_marquardt(
        T0,
        lambda T_a, T_b, extra: cost(T_a, T_b),
        pairs.alpha,
        pairs.beta,
        mask=cost.residuals_and_valid(T0[pairs.alpha], T0[pairs.beta])[1],
        kernel=config.kernel,
        config=config.lm,
    )
    assert_close(T_wc, reference.T_wc, atol=1e-9, rtol=0)
    assert_close(result.cost_history[:5], reference.cost_history[:5], rtol=1e-9, atol=1e-12)
