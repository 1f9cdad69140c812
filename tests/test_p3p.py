"""Lambda Twist P3P: known answers, batching, degenerate samples, bad inputs, poselib."""

from __future__ import annotations

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.geometry.se3 import invert, transform_points
from diffloc.reloc.p3p import P3P_MAX_SOLUTIONS, solve_p3p
from diffloc.testing import random_points, random_se3


def _samples(h: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random true poses T_cw (h, 4, 4), bearings (h, 3, 3) and world points (h, 3, 3)."""
    g = torch.Generator().manual_seed(seed)
    T_cw = random_se3((h,), generator=g, max_translation=2.0)
    points_cam = random_points((h, 3), generator=g, low=(-2.0, -2.0, 1.0), high=(2.0, 2.0, 10.0))
    points_world = transform_points(invert(T_cw), points_cam)
    bearings = points_cam / torch.linalg.vector_norm(points_cam, dim=-1, keepdim=True)
    return T_cw, bearings, points_world


def _best_error(T_cw: torch.Tensor, solutions: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Smallest max-abs difference between the truth (h, 4, 4) and a valid solution."""
    err = (solutions - T_cw[:, None]).abs().amax((-1, -2))
    return torch.where(valid, err, torch.full_like(err, torch.inf)).amin(-1)


def test_one_solution_is_the_true_pose():
    T_cw, bearings, points_world = _samples(2000, seed=0)
    solutions, valid = solve_p3p(bearings, points_world)
    assert solutions.shape == (2000, P3P_MAX_SOLUTIONS, 4, 4)
    assert valid.shape == (2000, P3P_MAX_SOLUTIONS)
    err = _best_error(T_cw, solutions, valid)
    # A few random triples are ill-conditioned (rays nearly on the danger cylinder): the
    # solution is then only as accurate as the conditioning allows.
    assert float(err.median()) < 1e-12
    assert float((err < 1e-9).double().mean()) > 0.995
    assert float(err.max()) < 1e-6


def test_valid_solutions_satisfy_the_correspondences():
    _, bearings, points_world = _samples(500, seed=1)
    solutions, valid = solve_p3p(bearings, points_world)
    assert bool(torch.isfinite(solutions).all())
    points_cam = transform_points(solutions, points_world[:, None])  # (h, 4, 3, 3)
    rays = points_cam / torch.linalg.vector_norm(points_cam, dim=-1, keepdim=True)
    angle_err = (rays - bearings[:, None]).abs().amax((-1, -2))
    assert bool((angle_err[valid] < 1e-8).all())
    assert bool((points_cam[..., 2][valid] > 0).all())
    rotations = solutions[..., :3, :3]
    eye = torch.eye(3, dtype=torch.float64)
    assert bool(((rotations @ rotations.transpose(-1, -2) - eye).abs() < 1e-9).all())
    assert bool((torch.linalg.det(rotations) > 0).all())


@pytest.mark.parametrize("batch", [(), (2,), (1, 2)])
def test_batch_shapes(batch):
    T_cw, bearings, points_world = _samples(2, seed=2)
    n = int(torch.tensor(batch).prod()) if batch else 1
    y = bearings[:n].reshape(*batch, 3, 3)
    x = points_world[:n].reshape(*batch, 3, 3)
    solutions, valid = solve_p3p(y, x)
    assert solutions.shape == (*batch, P3P_MAX_SOLUTIONS, 4, 4)
    assert valid.shape == (*batch, P3P_MAX_SOLUTIONS)
    flat, flat_valid = solve_p3p(bearings[:n], points_world[:n])
    assert torch.equal(valid.reshape(n, -1), flat_valid)
    assert torch.equal(solutions.reshape(n, -1, 4, 4), flat)


def test_unnormalised_float32_bearings_are_accepted():
    T_cw, bearings, points_world = _samples(50, seed=3)
    rays = (bearings / bearings[..., 2:]).float()  # [x, y, 1], float32
    solutions, valid = solve_p3p(rays, points_world.float())
    assert solutions.dtype == torch.float64
    assert float(_best_error(T_cw, solutions, valid).max()) < 1e-4  # float32 inputs


def test_degenerate_samples_are_invalid_and_finite():
    _, bearings, points_world = _samples(3, seed=4)
    collinear = points_world.clone()
    collinear[0, 2] = 2.0 * collinear[0, 1] - collinear[0, 0]  # x3 on the line x1 x2
    collinear[1, 1] = collinear[1, 0]  # two coincident points
    collinear[2] = 0.0  # all three coincide
    solutions, valid = solve_p3p(bearings, collinear)
    assert not bool(valid.any())
    assert bool(torch.isfinite(solutions).all())
    assert torch.equal(solutions, torch.eye(4, dtype=torch.float64).expand_as(solutions))


def test_identical_rays_are_invalid():
    _, bearings, points_world = _samples(1, seed=5)
    same = bearings[:, :1].expand(1, 3, 3)
    solutions, valid = solve_p3p(same, points_world)
    assert not bool(valid.any())
    assert bool(torch.isfinite(solutions).all())


def test_bad_inputs():
    y = torch.eye(3, dtype=torch.float64)
    with pytest.raises(ShapeError):
        solve_p3p(y[:2], y[:2])
    with pytest.raises(ShapeError):
        solve_p3p(y[None].expand(2, 3, 3), y)
    bad = y.clone()
    bad[0, 0] = torch.nan
    with pytest.raises(ValueError, match="NaN"):
        solve_p3p(bad, y)


def test_same_solution_set_as_poselib():
    poselib = pytest.importorskip("poselib")
    _, bearings, points_world = _samples(50, seed=6)
    solutions, valid = solve_p3p(bearings, points_world)
    for k in range(50):
        theirs = poselib.p3p(bearings[k].numpy(), points_world[k].numpy())
        ours = solutions[k][valid[k]]
        assert len(theirs) == ours.shape[0]
        for pose in theirs:
            T = torch.eye(4, dtype=torch.float64)
            T[:3, :3] = torch.tensor(pose.R)
            T[:3, 3] = torch.tensor(pose.t)
            assert float((ours - T).abs().amax((-1, -2)).min()) < 1e-8
