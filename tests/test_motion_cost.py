"""Motion-only refinement (seed 1 Eq. 5): cost module, ORB-SLAM rounds, implicit gradients."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import invert, se3_exp, se3_log, transform_points
from diffloc.optim import motion_cost
from diffloc.optim.lm import LMConfig, autodiff_linearize, levenberg_marquardt_single_pose
from diffloc.optim.motion_cost import MotionOnlyCost, MotionRefineConfig, refine_pose
from diffloc.optim.robust import RobustKernel, make_robust_kernel
from diffloc.testing import assert_close, gradcheck, random_points, random_se3

# torch's forward-mode AD loads its decompositions with the deprecated torch.jit.script.
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated")

F64 = torch.float64
CAM = PinholeCamera.from_fov(640, 480, math.radians(70), dtype=F64)
IMAGE_SIZE = torch.tensor([640.0, 480.0], dtype=F64)


def _unit(generator: torch.Generator) -> torch.Tensor:
    v = torch.randn(3, generator=generator, dtype=F64)
    return v / torch.linalg.vector_norm(v)


def _errors(T: torch.Tensor, T_true: torch.Tensor) -> tuple[float, float]:
    """Translation error (m) and rotation error (degrees)."""
    delta = invert(T_true) @ T
    angle = torch.linalg.vector_norm(se3_log(delta)[..., 3:], dim=-1)
    return float(delta[..., :3, 3].norm(dim=-1).max()), math.degrees(float(angle.max()))


@dataclass
class Query:
    T_true: torch.Tensor  # (4, 4)
    T_init: torch.Tensor  # (4, 4)
    points_world: torch.Tensor  # (N, 3)
    keypoints: torch.Tensor  # (N, 2)
    is_outlier: torch.Tensor  # (N,)


def make_query(
    generator: torch.Generator,
    num_points: int = 200,
    noise_px: float = 1.0,
    outlier_fraction: float = 0.0,
    angle_deg: float = 5.0,
    translation_m: float = 0.3,
) -> Query:
    """A random camera seeing points 1.5-6 m deep all over the image; outliers get uniformly
    random keypoints."""
    T_true = random_se3((), generator=generator, max_translation=2.0)
    pixels = torch.rand(num_points, 2, generator=generator, dtype=F64) * IMAGE_SIZE - 0.5
    depth = 1.5 + 4.5 * torch.rand(num_points, generator=generator, dtype=F64)
    points_cam = CAM.unproject(pixels, depth)
    keypoints = pixels + noise_px * torch.randn(num_points, 2, generator=generator, dtype=F64)
    num_outliers = int(outlier_fraction * num_points)
    index = torch.randperm(num_points, generator=generator)[:num_outliers]
    keypoints[index] = torch.rand(num_outliers, 2, generator=generator, dtype=F64) * IMAGE_SIZE
    is_outlier = torch.zeros(num_points, dtype=torch.bool)
    is_outlier[index] = True
    xi = torch.cat((translation_m * _unit(generator), math.radians(angle_deg) * _unit(generator)))
    return Query(
        T_true,
        T_true @ se3_exp(xi),
        transform_points(T_true, points_cam),
        keypoints,
        is_outlier,
    )


# ---------------------------------------------------------------------------- MotionOnlyCost


def test_cost_residual_sign_and_whitening() -> None:
    cost = MotionOnlyCost(CAM)
    X = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, -1.0]], dtype=F64)
    kp = CAM.project(X)[0] + torch.tensor([[3.0, -1.0], [0.0, 0.0]], dtype=F64)
    sigmas = torch.tensor([2.0, 1.0], dtype=F64)
    T = torch.eye(4, dtype=F64)
    residuals = cost(T, X, kp, sigmas)
    assert_close(residuals, torch.tensor([[1.5, -0.5], [0.0, 0.0]], dtype=F64))  # e = p - proj
    chi2 = cost.chi2(T, X, kp, sigmas)
    assert float(chi2[0]) == pytest.approx(2.5)
    assert math.isinf(float(chi2[1]))  # behind the camera


def test_analytic_jacobian_matches_autodiff() -> None:
    g = torch.Generator().manual_seed(0)
    query = make_query(g, num_points=20)
    cost = MotionOnlyCost(CAM)
    sigmas = 0.5 + torch.rand(20, generator=g, dtype=F64)
    args = (query.points_world, query.keypoints, sigmas)
    T = query.T_init[None]
    residuals, jacobian = cost.linearize(T, *args)
    auto = autodiff_linearize(lambda T_a, _b, _e: cost(T_a, *args), T)
    assert_close(auto.residuals, residuals)
    assert_close(auto.jac_a, jacobian, rtol=1e-8, atol=1e-8)


def test_cost_gradcheck_keypoints_points_pose_tangent() -> None:
    g = torch.Generator().manual_seed(1)
    T = random_se3((2,), generator=g, max_translation=0.2, max_angle=0.2)
    X = transform_points(T, random_points((2, 5), generator=g))
    kp = CAM.project(transform_points(invert(T), X))[0] + torch.randn(2, 5, 2, generator=g)
    sigmas = 1.0 + torch.rand(2, 5, generator=g, dtype=F64)
    cost = MotionOnlyCost(CAM)

    def fn(xi: torch.Tensor, points: torch.Tensor, keypoints: torch.Tensor, s: torch.Tensor):
        return cost(T @ se3_exp(xi), points, keypoints, s)

    assert gradcheck(fn, [torch.zeros(2, 6, dtype=F64), X, kp, sigmas])


@pytest.mark.parametrize("distortion", [None, (-0.2, 0.05, 1e-3, -2e-3)], ids=["pinhole", "rt"])
def test_solver_linearization_matches_the_cost_module(distortion) -> None:
    """The solver's normal equations (normalised coordinates, left twist of T_cw) equal the
    ones assembled from MotionOnlyCost (pixels, right step of T_wc: the gradient flips)."""
    g = torch.Generator().manual_seed(9)
    camera = CAM if distortion is None else PinholeCamera(
        fx=CAM.fx, fy=CAM.fy, cx=CAM.cx, cy=CAM.cy, width=CAM.width, height=CAM.height,
        distortion=torch.tensor(distortion, dtype=F64),
    )  # fmt: skip
    queries = [make_query(g, num_points=30, outlier_fraction=0.2) for _ in range(2)]
    T = torch.stack([q.T_init for q in queries])
    X = torch.stack([q.points_world for q in queries])
    kp = torch.stack([q.keypoints for q in queries])
    X[1, 0, 2] = -X[1, 0, 2]  # one point behind the camera (world and camera roughly agree)
    sigmas = 0.5 + torch.rand(2, 30, generator=g, dtype=F64)
    valid = torch.rand(2, 30, generator=g) > 0.1
    used = valid & (torch.rand(2, 30, generator=g) > 0.2)
    kernel = RobustKernel("huber", 2.0)
    problem = motion_cost._Problem.make(camera, X, kp, sigmas, valid)
    lin = problem.linearize(invert(T)[:, :3], used, make_robust_kernel(kernel))

    cost = MotionOnlyCost(camera)
    residuals, jacobian = cost.linearize(T, X, kp, sigmas, used)
    rho, weight = make_robust_kernel(kernel)((residuals * residuals).sum(-1))
    keep = cost.chi2(T, X, kp, sigmas, used).isfinite()
    weight = torch.where(keep, weight, 0.0)[..., None, None]
    assert_close(lin.cost, 0.5 * torch.where(keep, rho, 0.0).sum(-1))
    assert_close(lin.hessian, (jacobian * weight).flatten(1, 2).mT @ jacobian.flatten(1, 2))
    grad = ((jacobian * weight).flatten(1, 2).mT @ residuals.flatten(1, 2)[..., None])[..., 0]
    assert_close(lin.grad, -grad)
    assert_close(lin.projection.chi2, cost.chi2(T, X, kp, sigmas, valid))


# ---------------------------------------------------------------------------- refine_pose


def test_refine_recovers_pose_and_flags_outliers() -> None:
    g = torch.Generator().manual_seed(2)
    for _ in range(3):
        query = make_query(g, num_points=200, noise_px=1.0, outlier_fraction=0.3)
        result = refine_pose(CAM, query.T_init, query.points_world, query.keypoints)
        translation, rotation = _errors(result.T_wc, query.T_true)
        assert translation < 0.006 and rotation < 0.1, (translation, rotation)
        assert bool(result.converged)
        assert not bool(result.inliers[query.is_outlier].any())  # every outlier is flagged
        assert float(result.inliers[~query.is_outlier].float().mean()) > 0.9
        assert int(result.iterations) <= 40
        # close to least squares on the inliers it kept (which may differ slightly from the
        # set used in the last round)
        oracle = levenberg_marquardt_single_pose(
            query.T_true,
            lambda T, q=query, m=result.inliers: MotionOnlyCost(CAM)(
                T, q.points_world, q.keypoints, torch.ones(200, dtype=F64), m
            ),
        )
        assert _errors(result.T_wc, oracle.T_wc)[0] < 1e-3


def test_batched_refine_equals_single_runs_with_padding() -> None:
    g = torch.Generator().manual_seed(3)
    sizes = (120, 80, 150)
    queries = [make_query(g, num_points=n, outlier_fraction=0.2) for n in sizes]
    N = max(sizes)
    points = torch.full((3, N, 3), float("nan"), dtype=F64)
    keypoints = torch.full((3, N, 2), float("nan"), dtype=F64)
    mask = torch.zeros(3, N, dtype=torch.bool)
    for b, (q, n) in enumerate(zip(queries, sizes, strict=True)):
        points[b, :n], keypoints[b, :n], mask[b, :n] = q.points_world, q.keypoints, True
    T_init = torch.stack([q.T_init for q in queries])
    batched = refine_pose(CAM, T_init, points, keypoints, mask=mask)
    assert batched.T_wc.shape == (3, 4, 4)
    for b, (q, n) in enumerate(zip(queries, sizes, strict=True)):
        single = refine_pose(CAM, q.T_init, q.points_world, q.keypoints)
        assert_close(batched.T_wc[b], single.T_wc, rtol=0.0, atol=1e-10)
        assert torch.equal(batched.inliers[b, :n], single.inliers)
        assert not bool(batched.inliers[b, n:].any())
        assert bool(torch.isinf(batched.chi2[b, n:]).all())
        assert int(batched.iterations[b]) == int(single.iterations)
        assert bool(batched.converged[b]) == bool(single.converged)


def test_too_few_inliers_is_a_result_not_an_error() -> None:
    g = torch.Generator().manual_seed(4)
    good = make_query(g, num_points=60)
    bad = make_query(g, num_points=60, outlier_fraction=0.95)
    T_init = torch.stack((good.T_init, bad.T_init))
    result = refine_pose(
        CAM,
        T_init,
        torch.stack((good.points_world, bad.points_world)),
        torch.stack((good.keypoints, bad.keypoints)),
        config=MotionRefineConfig(min_inliers=15),
    )
    assert result.converged.tolist() == [True, False]
    assert _errors(result.T_wc[0], good.T_true)[0] < 0.02


def test_refine_float32_inputs_are_accepted() -> None:
    g = torch.Generator().manual_seed(5)
    q = make_query(g, num_points=50, noise_px=0.0)
    result = refine_pose(
        CAM.to(torch.float32), q.T_init.float(), q.points_world.float(), q.keypoints.float()
    )
    assert result.T_wc.dtype == F64
    assert _errors(result.T_wc, q.T_true)[0] < 1e-4  # limited by the float32 inputs


def _tight_config(kernel: RobustKernel, rounds: int, robust_rounds: int) -> MotionRefineConfig:
    """Converge each round to full precision (finite differences see the exact optimum)."""
    lm_config = LMConfig(max_iterations=30, step_tolerance=1e-14, cost_tolerance=1e-30)
    return MotionRefineConfig(
        rounds=rounds, kernel=kernel, robust_rounds=robust_rounds, min_inliers=4, lm=lm_config
    )


def _small_query() -> tuple[Query, torch.Tensor]:
    g = torch.Generator().manual_seed(6)
    q = make_query(g, num_points=8, noise_px=0.3, angle_deg=1.0, translation_m=0.05)
    return q, 0.8 + 0.4 * torch.rand(8, generator=g, dtype=F64)


def test_refined_pose_implicit_gradcheck() -> None:
    """Least squares in the last round (ORB-SLAM): gradients w.r.t. every input."""
    q, sigmas = _small_query()
    config = _tight_config(RobustKernel("huber", 5.991**0.5), rounds=2, robust_rounds=1)

    def refined(keypoints: torch.Tensor, points: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        return refine_pose(CAM, q.T_init, points, keypoints, s, config=config).T_wc[:3]

    assert gradcheck(refined, [q.keypoints, q.points_world, sigmas])


def test_refined_pose_implicit_gradcheck_robust_last_round() -> None:
    """A Cauchy kernel in every round: the implicit Hessian includes the kernel's curvature."""
    q, sigmas = _small_query()
    config = _tight_config(RobustKernel("cauchy", 1.0), rounds=1, robust_rounds=1)

    def refined(keypoints: torch.Tensor) -> torch.Tensor:
        return refine_pose(CAM, q.T_init, q.points_world, keypoints, sigmas, config=config).T_wc

    assert gradcheck(refined, [q.keypoints])


def test_refined_pose_gradient_zero_for_unused_matches() -> None:
    g = torch.Generator().manual_seed(7)
    q = make_query(g, num_points=30, noise_px=0.5, outlier_fraction=0.2)
    keypoints = q.keypoints.clone().requires_grad_(True)
    result = refine_pose(CAM, q.T_init, q.points_world, keypoints)
    result.T_wc[:3, 3].sum().backward()
    assert keypoints.grad is not None
    unused = ~result.inliers
    assert bool(unused.any())
    assert bool((keypoints.grad[unused] == 0).all())
    assert float(keypoints.grad[result.inliers].abs().max()) > 0


# ---------------------------------------------------------------------------- bad inputs


def _inputs(n: int = 20) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(8)
    X = random_points((n,), generator=g)
    return torch.eye(4, dtype=F64), X, CAM.project(X)[0]


def test_nan_pose_raises() -> None:
    T, X, kp = _inputs()
    T[0, 3] = float("nan")
    with pytest.raises(ValueError, match="T_wc"):
        refine_pose(CAM, T, X, kp)


def test_mismatched_shapes_raise() -> None:
    T, X, kp = _inputs()
    with pytest.raises(ShapeError, match="keypoints"):
        refine_pose(CAM, T, X, kp[:-1])
    with pytest.raises(ShapeError, match="points_world"):
        refine_pose(CAM, T[None], X, kp)
    with pytest.raises(ShapeError, match="sigmas"):
        refine_pose(CAM, T, X, kp, sigmas=torch.ones(3, dtype=F64))
    with pytest.raises(TypeError, match="mask"):
        refine_pose(CAM, T, X, kp, mask=torch.ones(20))


def test_zero_points_and_bad_sigmas_raise() -> None:
    T, X, kp = _inputs()
    with pytest.raises(ValueError, match="N = 0"):
        refine_pose(CAM, T, X[:0], kp[:0])
    with pytest.raises(ValueError, match="sigmas"):
        refine_pose(CAM, T, X, kp, sigmas=torch.zeros(20, dtype=F64))
    kp_nan = kp.clone()
    kp_nan[0] = float("nan")
    with pytest.raises(ValueError, match="keypoints"):
        refine_pose(CAM, T, X, kp_nan)


@pytest.mark.parametrize(
    "kwargs",
    [{"rounds": 0}, {"robust_rounds": 5}, {"chi2_threshold": -1.0}, {"round_cost_tolerance": 0.0}],
)
def test_bad_config_raises(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        MotionRefineConfig(**kwargs)
