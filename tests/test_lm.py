"""Batched Levenberg-Marquardt: known answers, Jacobians, robustness, damping, bad inputs."""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import invert, se3_exp, se3_log, transform_points
from diffloc.optim.lm import (
    BlockLinearization,
    LMConfig,
    autodiff_linearize,
    block_system,
    levenberg_marquardt,
    levenberg_marquardt_single_pose,
    minimize,
    solve_spd,
)
from diffloc.optim.lm.block_assembly import _assemble
from diffloc.optim.lm.loop import _expand_step
from diffloc.optim.lm.pose_front_end import _PoseProblem
from diffloc.optim.lm.retraction import _retract
from diffloc.optim.lm.structure import _Structure
from diffloc.optim.robust import KernelFn, RobustKernel, make_robust_kernel
from diffloc.testing import TransferBlocks, assert_close, random_points, random_rotation

# torch's forward-mode AD loads its decompositions with the deprecated torch.jit.script.
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated")

F64 = torch.float64
CAM = PinholeCamera.from_fov(320, 240, math.radians(80), dtype=F64)


def _pose_error(T: torch.Tensor, T_true: torch.Tensor) -> torch.Tensor:
    """(...) norm of the twist between two poses (metres and radians mixed)."""
    return torch.linalg.vector_norm(se3_log(invert(T_true) @ T), dim=-1)


def _perturb(T: torch.Tensor, generator: torch.Generator, scale: float) -> torch.Tensor:
    return T @ se3_exp(scale * torch.randn(*T.shape[:-2], 6, generator=generator, dtype=F64))


# ---------------------------------------------------------------------------- two-view transfer


@dataclass
class Transfer:
    """Seed-1-like two-pose blocks: a point at known depth in camera a, observed in camera b.

    ``r = project(T_b^-1 T_a X_a) - p_b``; poses are cameras on a line looking at a box of
    points, pairs ``(i, i+1)`` and ``(i, i+2)``.
    """

    T_true: torch.Tensor  # (P, 4, 4)
    index_a: torch.Tensor  # (M,)
    index_b: torch.Tensor  # (M,)
    points_a: torch.Tensor  # (M, 3) in camera a
    keypoints_b: torch.Tensor  # (M, 2)

    def __post_init__(self) -> None:
        blocks = TransferBlocks(CAM, self.points_a, self.keypoints_b)
        self.residual_fn = blocks.residual_fn
        self.jacobian_fn = blocks.jacobian_fn


def make_transfer(
    generator: torch.Generator, num_poses: int = 6, per_pair: int = 12, noise_px: float = 0.0
) -> Transfer:
    angles = random_rotation((num_poses,), generator=generator, max_angle=math.radians(8))
    T_true = torch.eye(4, dtype=F64).repeat(num_poses, 1, 1)
    T_true[:, :3, :3] = angles
    T_true[:, 0, 3] = torch.linspace(-1.0, 1.0, num_poses, dtype=F64)
    T_true[:, 1, 3] = 0.1 * torch.randn(num_poses, generator=generator, dtype=F64)
    pairs = [(i, j) for i in range(num_poses) for j in (i + 1, i + 2) if j < num_poses]
    index_a = torch.tensor([a for a, _ in pairs], dtype=torch.long).repeat_interleave(per_pair)
    index_b = torch.tensor([b for _, b in pairs], dtype=torch.long).repeat_interleave(per_pair)
    points_world = random_points(
        (index_a.numel(),), generator=generator, low=(-1.5, -1.0, 4.0), high=(1.5, 1.0, 7.0)
    )
    points_a = transform_points(invert(T_true[index_a]), points_world[:, None, :])[:, 0]
    points_b = transform_points(invert(T_true[index_b]), points_world[:, None, :])[:, 0]
    keypoints_b = CAM.project(points_b)[0]
    keypoints_b = keypoints_b + noise_px * torch.randn(
        keypoints_b.shape, generator=generator, dtype=F64
    )
    return Transfer(T_true, index_a, index_b, points_a, keypoints_b)


@pytest.mark.parametrize("solver", ["cholesky", "cg"])
@pytest.mark.parametrize("analytic", [True, False])
def test_recovers_exact_poses_two_pose_blocks(solver: str, analytic: bool) -> None:
    g = torch.Generator().manual_seed(0)
    problem = make_transfer(g)
    T0 = _perturb(problem.T_true, g, 0.05)
    T0[0] = problem.T_true[0]
    result = levenberg_marquardt(
        T0,
        problem.residual_fn,
        problem.index_a,
        problem.index_b,
        jacobian_fn=problem.jacobian_fn if analytic else None,
        fixed=[0],
        config=LMConfig(solver=solver),
    )
    assert bool(result.converged), result.reason
    assert float(_pose_error(result.T_wc, problem.T_true).max()) < 1e-6
    assert torch.equal(result.T_wc[0], T0[0])  # the gauge pose is untouched
    assert float(result.cost) < 1e-12
    history = result.cost_history
    assert bool((history[1:] <= history[:-1]).all())  # LM never accepts an uphill step


def test_one_pose_blocks_recover_poses_and_extra_parameter() -> None:
    """Reprojection of known points; the extra parameter is an unknown focal-length scale."""
    g = torch.Generator().manual_seed(1)
    num_poses, per_pose = 4, 15
    T_true = torch.eye(4, dtype=F64).repeat(num_poses, 1, 1)
    T_true[:, :3, :3] = random_rotation((num_poses,), generator=g, max_angle=0.2)
    index = torch.arange(num_poses).repeat_interleave(per_pose)
    points_cam = random_points((index.numel(),), generator=g)
    points_world = transform_points(T_true[index], points_cam[:, None, :])[:, 0]
    true_scale = 1.05
    centre = torch.stack((CAM.cx, CAM.cy))
    keypoints = (CAM.project(points_cam)[0] - centre) * true_scale + centre

    def residual_fn(T_a: torch.Tensor, _: torch.Tensor | None, extra: torch.Tensor | None):
        points = transform_points(invert(T_a), points_world[:, None, :])[..., 0, :]
        uv = (CAM.project(points)[0] - centre) * extra[:, None, :1] + centre
        return uv - keypoints

    result = levenberg_marquardt(
        _perturb(T_true, g, 0.03), residual_fn, index, extra=torch.ones(1, dtype=F64)
    )
    assert bool(result.converged)
    assert float(_pose_error(result.T_wc, T_true).max()) < 1e-6
    assert abs(float(result.extra[0]) - true_scale) < 1e-9


def test_analytic_and_autodiff_jacobians_agree() -> None:
    g = torch.Generator().manual_seed(2)
    problem = make_transfer(g, num_poses=4, per_pair=5, noise_px=1.0)
    T = _perturb(problem.T_true, g, 0.1)[None]
    T_a, T_b = T[:, problem.index_a], T[:, problem.index_b]
    analytic = problem.jacobian_fn(T_a, T_b, None)
    auto = autodiff_linearize(problem.residual_fn, T_a, T_b)
    assert_close(auto.residuals, analytic.residuals)
    assert_close(auto.jac_a, analytic.jac_a, rtol=1e-8, atol=1e-8)
    assert_close(auto.jac_b, analytic.jac_b, rtol=1e-8, atol=1e-8)
    # and both match finite differences of the right perturbation T_a @ exp(eps e_k)
    eps = 1e-6
    for k in range(6):
        step = torch.zeros(6, dtype=F64)
        step[k] = eps
        plus = problem.residual_fn(T_a @ se3_exp(step), T_b, None)
        minus = problem.residual_fn(T_a @ se3_exp(-step), T_b, None)
        assert_close((plus - minus) / (2 * eps), analytic.jac_a[..., k], rtol=1e-5, atol=1e-5)


def test_huber_reduces_outlier_influence() -> None:
    g = torch.Generator().manual_seed(3)
    problem = make_transfer(g, per_pair=20, noise_px=0.5)
    outliers = torch.rand(problem.index_a.numel(), generator=g) < 0.15
    problem.keypoints_b[outliers] += 40.0 * torch.randn(int(outliers.sum()), 2, generator=g)
    T0 = _perturb(problem.T_true, g, 0.02)
    T0[0] = problem.T_true[0]
    errors = {}
    for name in ("trivial", "huber"):
        result = levenberg_marquardt(
            T0,
            problem.residual_fn,
            problem.index_a,
            problem.index_b,
            jacobian_fn=problem.jacobian_fn,
            fixed=[0],
            kernel=RobustKernel(name, 2.0),
        )
        errors[name] = float(_pose_error(result.T_wc, problem.T_true).mean())
    assert errors["huber"] < 0.3 * errors["trivial"], errors


def test_badly_scaled_start_converges() -> None:
    """Far start, residual rows scaled by 1e-3 .. 1e3: damping keeps every step downhill."""
    g = torch.Generator().manual_seed(4)
    points_cam = random_points((30,), generator=g)
    keypoints = CAM.project(points_cam)[0]
    row_scale = torch.logspace(-3, 3, 30, dtype=F64)[:, None]

    def residual_fn(T_wc: torch.Tensor) -> torch.Tensor:
        points = transform_points(invert(T_wc), points_cam)
        return row_scale * (CAM.project(points)[0] - keypoints)

    xi = torch.tensor([0.4, -0.3, 0.2, 0.3, -0.35, 0.2], dtype=F64)  # ~27 deg, 0.54 m
    for initial_damping in (1e-8, 1e4):
        result = levenberg_marquardt_single_pose(
            se3_exp(xi),
            residual_fn,
            config=LMConfig(initial_damping=initial_damping, max_iterations=200),
        )
        assert bool(result.converged), result.reason
        assert float(_pose_error(result.T_wc, torch.eye(4, dtype=F64))) < 1e-8
        assert bool((result.cost_history[1:] <= result.cost_history[:-1]).all())


def test_batched_problems_equal_separate_runs() -> None:
    g = torch.Generator().manual_seed(5)
    problem = make_transfer(g, num_poses=4, per_pair=8, noise_px=0.3)
    T0 = torch.stack([_perturb(problem.T_true, g, s) for s in (0.01, 0.05, 0.1)])
    mask = torch.rand(3, problem.index_a.numel(), generator=g) > 0.2
    kwargs = dict(jacobian_fn=problem.jacobian_fn, fixed=[0], kernel=RobustKernel("huber", 1.0))
    batched = levenberg_marquardt(
        T0, problem.residual_fn, problem.index_a, problem.index_b, mask=mask, **kwargs
    )
    assert batched.T_wc.shape == (3, 4, 4, 4)
    assert batched.iterations.shape == batched.converged.shape == (3,)
    for b in range(3):
        single = levenberg_marquardt(
            T0[b], problem.residual_fn, problem.index_a, problem.index_b, mask=mask[b], **kwargs
        )
        assert_close(batched.T_wc[b], single.T_wc, rtol=0.0, atol=1e-10)
        assert int(batched.iterations[b]) == int(single.iterations)
        assert batched.reason[b] == single.reason[0]


def test_masked_blocks_are_ignored_even_if_nan() -> None:
    g = torch.Generator().manual_seed(6)
    problem = make_transfer(g, num_poses=4, per_pair=8)
    mask = torch.ones(problem.index_a.numel(), dtype=torch.bool)
    mask[::5] = False
    problem.keypoints_b[~mask] = float("nan")
    T0 = _perturb(problem.T_true, g, 0.03)
    result = levenberg_marquardt(
        T0, problem.residual_fn, problem.index_a, problem.index_b, mask=mask, fixed=[0]
    )
    assert float(_pose_error(result.T_wc[1:], problem.T_true[1:]).max()) > 0  # moved
    assert bool(torch.isfinite(result.T_wc).all())
    # pose 0 is fixed at its perturbed value, so compare relative poses
    relative = invert(result.T_wc[0]) @ result.T_wc
    relative_true = invert(problem.T_true[0]) @ problem.T_true
    assert float(_pose_error(relative, relative_true).max()) < 1e-2


def test_unobserved_pose_stays_put() -> None:
    """A free pose no block touches: damping keeps its (zero) system regular."""
    g = torch.Generator().manual_seed(7)
    problem = make_transfer(g, num_poses=4, per_pair=8)
    T0 = torch.cat((_perturb(problem.T_true, g, 0.02), torch.eye(4, dtype=F64)[None]))
    T0[0] = problem.T_true[0]
    result = levenberg_marquardt(
        T0, problem.residual_fn, problem.index_a, problem.index_b, fixed=[0]
    )
    assert torch.equal(result.T_wc[4], T0[4])
    assert float(_pose_error(result.T_wc[:4], problem.T_true).max()) < 1e-6


def test_max_iterations_reports_not_converged() -> None:
    g = torch.Generator().manual_seed(8)
    problem = make_transfer(g, num_poses=4, per_pair=8)
    T0 = _perturb(problem.T_true, g, 0.1)
    result = levenberg_marquardt(
        T0,
        problem.residual_fn,
        problem.index_a,
        problem.index_b,
        fixed=[0],
        config=LMConfig(max_iterations=1),
    )
    assert not bool(result.converged)
    assert result.reason == ("max_iterations",)
    assert int(result.iterations) == 1
    assert result.cost_history.shape == (2,)


def _translation_problem(goal: torch.Tensor, calls: list[str]) -> _PoseProblem:
    """One-pose problems ``t(T) - goal`` (goal (B, 1, 3)) that log their linearizations."""

    def jacobian_fn(T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        calls.append("linearize")
        J = torch.cat((T[:, :3, :3], torch.zeros(len(T), 3, 3, dtype=F64)), -1)[:, None]
        return T[:, None, :3, 3] - goal, J

    kernel = make_robust_kernel(RobustKernel())
    return _PoseProblem(lambda T: T[:, None, :3, 3] - goal, jacobian_fn, None, kernel)


def test_minimize_leaves_inactive_problems_untouched() -> None:
    goal = torch.tensor([[[1.0, 2.0, 3.0]], [[-1.0, 0.5, 2.0]]], dtype=F64)
    T0 = torch.eye(4, dtype=F64).repeat(2, 1, 1)
    run = minimize(_translation_problem(goal, []), T0, LMConfig(), active=[True, False])
    assert run.reason[1] == "inactive" and run.iterations[1] == 0
    assert torch.equal(run.params[1], T0[1])
    assert_close(run.params[0, :3, 3], goal[0, 0])
    assert run.converged == [True, False]


def test_steps_too_small_to_matter_are_not_evaluated() -> None:
    """A step whose predicted decrease is below ``cost_tolerance`` of the cost stops the
    problem without a linearization at the candidate, and the step is not taken."""
    goal = torch.tensor([[[1.0, 2.0, 3.0]]], dtype=F64)
    T0 = torch.eye(4, dtype=F64)[None].clone()
    T0[0, :3, 3] = goal[0, 0] + 1e-4
    calls: list[str] = []
    run = minimize(_translation_problem(goal, calls), T0, LMConfig(cost_tolerance=1.5))
    assert run.reason == ("cost",) and run.iterations == [1]
    assert calls == ["linearize"]  # the initial linearization only
    assert torch.equal(run.params, T0)
    calls.clear()
    run = minimize(_translation_problem(goal, calls), T0, LMConfig())  # a step that matters
    assert len(calls) > 1 and run.converged == [True]
    assert_close(run.params[0, :3, 3], goal[0, 0], rtol=0.0, atol=1e-12)


def test_solve_spd_falls_back_for_singular_systems() -> None:
    H = torch.stack((torch.diag(torch.tensor([2.0, 4.0])), torch.zeros(2, 2))).to(F64)
    b = torch.tensor([[2.0, 2.0], [0.0, 0.0]], dtype=F64)
    assert_close(solve_spd(H, b), torch.tensor([[1.0, 0.5], [0.0, 0.0]], dtype=F64))


# ---------------------------------------------------------------------------- normal equations


def _random_blocks(
    generator: torch.Generator, batch: int = 2, num_poses: int = 5, num_extra: int = 2
) -> tuple[BlockLinearization, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random two-pose blocks (R = 2) touching every case of the block structure.

    Returns the linearization, ``index_a``, ``index_b`` (M,), the (B, M) mask and the (P,)
    fixed-pose mask: pose 1 is fixed; blocks run in both index orders, on the same pose
    twice, on the fixed pose, and some are masked (and NaN, which must not leak).
    """
    pairs = torch.tensor(
        [(0, 2), (2, 0), (3, 4), (4, 3), (2, 2), (0, 1), (1, 3), (1, 1), (3, 0), (4, 2)]
    ).repeat(3, 1)
    M = pairs.shape[0]
    lin = BlockLinearization(
        residuals=torch.randn(batch, M, 2, generator=generator, dtype=F64) * 3.0,
        jac_a=torch.randn(batch, M, 2, 6, generator=generator, dtype=F64),
        jac_b=torch.randn(batch, M, 2, 6, generator=generator, dtype=F64),
        jac_extra=torch.randn(batch, M, 2, num_extra, generator=generator, dtype=F64),
    )
    mask = torch.rand(batch, M, generator=generator) > 0.2
    for x in (lin.residuals, lin.jac_a, lin.jac_b, lin.jac_extra):
        x[~mask] = float("nan")
    is_fixed = torch.zeros(num_poses, dtype=torch.bool)
    is_fixed[1] = True
    return lin, pairs[:, 0], pairs[:, 1], mask, is_fixed


def _dense_reference(
    lin: BlockLinearization,
    index_a: torch.Tensor,
    index_b: torch.Tensor,
    mask: torch.Tensor,
    is_fixed: torch.Tensor,
    kernel: KernelFn,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cost (B,), H (B, D, D), g (B, D) and support (B, P_free) from the full Jacobian."""
    B, M, R = lin.residuals.shape
    P, E = is_fixed.shape[0], lin.jac_extra.shape[-1]
    J = torch.zeros(B, M, R, 6 * P + E, dtype=F64)
    rows = torch.arange(M)
    for index, J_pose in ((index_a, lin.jac_a), (index_b, lin.jac_b)):
        columns = 6 * index[:, None] + torch.arange(6)  # (M, 6)
        J[:, rows[:, None], :, columns] += torch.nan_to_num(J_pose).permute(1, 3, 0, 2)
    J[..., 6 * P :] = lin.jac_extra
    free = torch.cat((~is_fixed.repeat_interleave(6), torch.ones(E, dtype=torch.bool)))
    J = torch.where(mask[..., None, None], J[..., free], 0.0)
    r = torch.where(mask[..., None], lin.residuals, 0.0)
    rho, weight = kernel((r * r).sum(-1))
    weight = torch.where(mask, weight, 0.0)
    H = torch.einsum("bmri,bm,bmrj->bij", J, weight, J)
    g = torch.einsum("bmri,bm,bmr->bi", J, weight, r)
    slots = torch.cumsum(~is_fixed, 0) - 1
    support = torch.zeros(B, int((~is_fixed).sum()), dtype=F64)
    for index in (index_a, torch.where(index_a == index_b, -1, index_b)):
        use = (index >= 0) & ~is_fixed[index.clamp(min=0)]
        support.index_add_(1, slots[index[use]], R * weight[:, use])
    return 0.5 * torch.where(mask, rho, 0.0).sum(-1), H, g, support


def test_assembly_matches_dense_reference() -> None:
    """The component-major block assembly against ``J^T W J`` of the full Jacobian."""
    g = torch.Generator().manual_seed(11)
    lin, index_a, index_b, mask, is_fixed = _random_blocks(g)
    kernel = make_robust_kernel(RobustKernel("cauchy", 2.0))
    structure = _Structure.from_blocks(5, index_a, index_b, is_fixed, num_extra=2)
    system = _assemble(lin, mask, kernel, structure)
    cost, H, grad, support = _dense_reference(lin, index_a, index_b, mask, is_fixed, kernel)
    assert_close(system.cost, cost, rtol=1e-12, atol=0.0)
    assert_close(system.grad, grad, rtol=1e-12, atol=1e-12)
    assert_close(system.support, support, rtol=1e-12, atol=1e-12)
    assert_close(system.dense(torch.ones_like(grad), F64), H, rtol=1e-12, atol=1e-12)
    assert_close(system.diagonal(), H.diagonal(dim1=-2, dim2=-1), rtol=1e-12, atol=1e-12)
    x = torch.randn(grad.shape, generator=g, dtype=F64)
    assert_close(system.matvec(x), (H @ x[..., None])[..., 0], rtol=1e-12, atol=1e-12)
    scale = torch.rand(grad.shape, generator=g, dtype=F64) + 0.5
    scaled = system.dense(scale, torch.float32)
    assert scaled.dtype == torch.float32
    assert_close(scaled, (scale[:, :, None] * H * scale[:, None, :]).float())


@pytest.mark.parametrize("conditioning", ["well", "ill"])
def test_mixed_precision_solve_matches_float64(
    conditioning: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A float32 factor plus float64 refinement gives the float64 step; systems too
    ill-conditioned for float32 fall back to a float64 factorization."""
    g = torch.Generator().manual_seed(12)
    lin, index_a, index_b, mask, is_fixed = _random_blocks(g)
    if conditioning == "ill":  # two nearly equal columns: cond(H) ~ 1e9, even Jacobi-scaled
        for J in (lin.jac_a, lin.jac_b):
            J[..., 5] = J[..., 4] + 3e-5 * torch.randn(J.shape[:-1], generator=g, dtype=F64)
    kernel = make_robust_kernel(RobustKernel())
    structure = _Structure.from_blocks(5, index_a, index_b, is_fixed, num_extra=2)
    system = _assemble(lin, mask, kernel, structure)
    damping = torch.tensor([1e-9, 1e-3], dtype=F64)
    scaled = damping[:, None] * system.diagonal().clamp(min=1e-30)
    H = system.dense(torch.ones_like(system.grad), F64) + torch.diag_embed(scaled)
    expected = torch.linalg.solve(H, -system.grad)
    float64_solves = []
    monkeypatch.setattr(
        block_system, "solve_spd", lambda A, b: float64_solves.append(len(b)) or solve_spd(A, b)
    )
    config = LMConfig(min_diagonal=1e-30)
    delta, _, float64 = system.solve(damping, config)
    rtol = 1e-8 if conditioning == "well" else 1e-5  # float64 itself: cond * eps ~ 1e-6
    assert_close(delta, expected, rtol=rtol, atol=rtol * float(expected.abs().max()))
    assert float64 == (conditioning == "ill")
    assert float64_solves == ([1] if conditioning == "ill" else [])  # only the failed problem
    delta, _, float64 = system.solve(damping, config, mixed_precision=False)
    assert_close(delta, expected, rtol=rtol, atol=rtol * float(expected.abs().max()))
    assert float64


def test_step_expansions_skip_weakly_supported_poses() -> None:
    """Supported poses and the extra parameters get 2, 4, 8 times the step while the cost
    falls; a pose held mostly by down-weighted blocks keeps its plain step."""
    g = torch.Generator().manual_seed(13)
    lin, index_a, index_b, mask, is_fixed = _random_blocks(g, batch=2)
    structure = _Structure.from_blocks(5, index_a, index_b, is_fixed, num_extra=2)
    system = _assemble(lin, mask, make_robust_kernel(RobustKernel()), structure)
    system.support = torch.tensor([[10.0, 10.0, 5.9, 10.0], [10.0, 10.0, 10.0, 10.0]], dtype=F64)
    T = torch.eye(4, dtype=F64).repeat(2, 5, 1, 1)
    extra = torch.zeros(2, 2, dtype=F64)
    delta = torch.randn(2, structure.size, generator=g, dtype=F64)

    def farther_is_cheaper(T_new: torch.Tensor, extra_new: torch.Tensor | None) -> torch.Tensor:
        return -(T_new[:, :, :3, 3].square().sum((1, 2)) + extra_new.square().sum(-1))

    problem = SimpleNamespace(
        evaluate=lambda params: farther_is_cheaper(*params),
        retract=lambda params, d: _retract(*params, d, structure),
    )
    cost = farther_is_cheaper(*_retract(T, extra, delta, structure)).tolist()
    config = LMConfig(step_expansions=3)
    step, best = _expand_step(problem, (T, extra), delta, system, cost, [True, False], config)
    expected = 8.0 * delta[0]
    expected[12:18] = delta[0, 12:18]  # slot 2 (pose 3) is below the support of 6
    assert_close(step[0], expected, rtol=0.0, atol=0.0)
    assert_close(step[1], delta[1], rtol=0.0, atol=0.0)  # not expanded at all
    assert best == farther_is_cheaper(*_retract(T, extra, step, structure)).tolist()


def test_step_expansions_converge_to_the_same_optimum_in_fewer_iterations() -> None:
    g = torch.Generator().manual_seed(14)
    problem = make_transfer(g, num_poses=6, per_pair=12, noise_px=0.5)
    problem.keypoints_b[::7] += 40.0  # outliers for the redescending kernel
    T0 = _perturb(problem.T_true, g, 0.05)
    results = [
        levenberg_marquardt(
            T0,
            problem.residual_fn,
            problem.index_a,
            problem.index_b,
            jacobian_fn=problem.jacobian_fn,
            fixed=[0],
            kernel=RobustKernel("cauchy", 1.0),
            config=LMConfig(step_expansions=expansions),
        )
        for expansions in (0, 3)
    ]
    plain, expanded = results
    assert bool(plain.converged) and bool(expanded.converged), (plain.reason, expanded.reason)
    assert_close(expanded.cost, plain.cost, rtol=1e-10, atol=0.0)
    assert float(_pose_error(expanded.T_wc, plain.T_wc).max()) < 1e-6
    assert int(expanded.iterations) < int(plain.iterations)
    history = expanded.cost_history
    assert bool((history[1:] <= history[:-1]).all())


# ---------------------------------------------------------------------------- bad inputs


def _simple_fn(T_a: torch.Tensor, T_b: torch.Tensor | None, extra: torch.Tensor | None):
    return T_a[..., :3, 3]


def test_nan_pose_raises() -> None:
    T = torch.eye(4, dtype=F64).repeat(2, 1, 1)
    T[1, 0, 3] = float("nan")
    with pytest.raises(ValueError, match="T_wc"):
        levenberg_marquardt(T, _simple_fn, torch.tensor([0, 1]))
    with pytest.raises(ValueError, match="T_wc"):
        levenberg_marquardt_single_pose(T, lambda T_wc: T_wc[:, None, :3, 3])


def test_bad_shapes_and_indices_raise() -> None:
    T = torch.eye(4, dtype=F64).repeat(2, 1, 1)
    with pytest.raises(ShapeError, match="T_wc"):
        levenberg_marquardt(torch.eye(4, dtype=F64), _simple_fn, torch.tensor([0]))
    with pytest.raises(ValueError, match="index_a"):
        levenberg_marquardt(T, _simple_fn, torch.tensor([0, 2]))
    with pytest.raises(ValueError, match="empty"):
        levenberg_marquardt(T, _simple_fn, torch.zeros(0, dtype=torch.long))
    with pytest.raises(ShapeError, match="index_b"):
        levenberg_marquardt(T, _simple_fn, torch.tensor([0, 1]), torch.tensor([0]))
    with pytest.raises(ShapeError, match="mask"):
        levenberg_marquardt(T, _simple_fn, torch.tensor([0, 1]), mask=torch.ones(3).bool())
    with pytest.raises(ValueError, match="fixed"):
        levenberg_marquardt(T, _simple_fn, torch.tensor([0, 1]), fixed=[0, 1])
    with pytest.raises(ShapeError, match="residuals"):
        levenberg_marquardt(T, lambda Ta, Tb, e: Ta[0, :, :3, 3], torch.tensor([0, 1]))
    with pytest.raises(ShapeError, match="residuals"):
        levenberg_marquardt_single_pose(T, lambda T_wc: T_wc[:, :3, 3])


def test_non_finite_initial_residuals_raise() -> None:
    with pytest.raises(ValueError, match="not finite"):
        levenberg_marquardt_single_pose(
            torch.eye(4, dtype=F64), lambda T_wc: torch.full((1, 3, 2), float("nan"))
        )


@pytest.mark.parametrize(
    "kwargs",
    [
        {"max_iterations": 0},
        {"step_tolerance": 0.0},
        {"solver": "qr"},
        {"initial_damping": 1e13},
        {"step_expansions": -1},
        {"expansion_min_support": 0.0},
    ],
)
def test_bad_config_raises(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        LMConfig(**kwargs)
