"""The check of the surfel optimisation (held-out tracks, plausible moves) on synthetic scenes."""

from __future__ import annotations

import pytest
import torch

from diffloc.optim.holdout import (
    HoldoutCheckConfig,
    checked_optimize_keyframe_poses,
    held_out_figures,
    holdout_points,
    pose_moves,
)
from diffloc.optim.surfel_cost import SurfelOptimConfig, pairs_from_database
from tests.test_surfel_cost import CAM, Scene, _database, _perturb, _pose_errors, _scene

F64 = torch.float64
OPTIM = SurfelOptimConfig(fix_first_keyframe=False, min_pairs=0)


@pytest.fixture(scope="module")
def scene() -> Scene:
    return _scene(num_keyframes=6, num_surfels=300)


def test_holdout_points_draws_the_fraction_of_pair_giving_points_reproducibly(scene: Scene):
    db = _database(scene, scene.T_true)
    db.point_surfels[:30] = -1  # no surfel: no pairs, never held out
    held = holdout_points(db, 0.25, torch.Generator().manual_seed(4))
    assert held.shape == (db.num_points,) and held.dtype == torch.bool
    assert not bool(held[:30].any())
    assert int(held.sum()) == round(0.25 * 270)
    again = holdout_points(db, 0.25, torch.Generator().manual_seed(4))
    other = holdout_points(db, 0.25, torch.Generator().manual_seed(5))
    assert torch.equal(held, again) and not torch.equal(held, other)
    with pytest.raises(ValueError, match="fraction"):
        holdout_points(db, 1.0, torch.Generator())


def test_held_out_figures_are_exact_at_the_true_poses_and_worse_elsewhere(scene: Scene):
    db = _database(scene, scene.T_true)
    pairs = pairs_from_database(db, scene.centers, scene.normals)
    exact = held_out_figures(pairs, scene.T_true, inlier_px=1.0)
    assert exact.pairs == exact.valid_pairs == len(pairs)
    assert exact.inlier_fraction == 1.0 and exact.median_px < 1e-3  # float32 keypoints
    off = held_out_figures(pairs, _perturb(scene.T_true, torch.Generator()), inlier_px=1.0)
    assert off.inlier_fraction < 0.2 and off.median_px > 10.0
    none = held_out_figures(
        pairs.select(torch.zeros(len(pairs), dtype=torch.bool)), scene.T_true, 1.0
    )
    assert (none.pairs, none.inlier_fraction, none.median_px) == (0, 0.0, None)


def test_a_correcting_optimisation_is_accepted(scene: Scene):
    """Poses 0.2 m / 2 deg off: the training solve recovers the truth, the held-out tracks
    agree and the moves fit a 0.12 m prior (0.2 m = 1.7 sigma per keyframe)."""
    T_init = _perturb(scene.T_true, torch.Generator().manual_seed(3))
    db = _database(scene, T_init)
    checked = checked_optimize_keyframe_poses(
        db, scene.centers, scene.normals, OPTIM, HoldoutCheckConfig(), pose_prior_sigma_m=0.12
    )
    assert checked.improved and checked.accepted, checked.reason
    assert checked.before.inlier_fraction < 0.2 and checked.after.inlier_fraction == 1.0
    assert checked.held_out_points == round(0.2 * scene.centers.shape[0])
    translation, rotation = _pose_errors(checked.T_wc, scene.T_true)
    assert translation < 1e-6 and rotation < 1e-6
    assert torch.equal(checked.T_wc, checked.T_wc_optimized)
    assert torch.equal(db.T_wc, T_init)  # the database is not modified


def test_exact_poses_are_kept_when_the_optimisation_gains_nothing(scene: Scene):
    db = _database(scene, scene.T_true)
    checked = checked_optimize_keyframe_poses(
        db, scene.centers, scene.normals, OPTIM, HoldoutCheckConfig(), pose_prior_sigma_m=0.1
    )
    assert not checked.improved and not checked.accepted
    assert "min_gain" in checked.reason
    assert torch.equal(checked.T_wc, scene.T_true)


def _mislead_training_tracks(scene: Scene, check: HoldoutCheckConfig, keyframe: int) -> Scene:
    """The scene with keyframe ``keyframe``'s keypoints of the *training* tracks as seen from
    0.3 m away (wrong associations the optimisation fits); held-out tracks stay true."""
    db = _database(scene, scene.T_true)
    held = holdout_points(db, check.holdout_fraction, torch.Generator().manual_seed(check.seed))
    T_wrong = scene.T_true[keyframe].clone()
    T_wrong[:3, 3] += torch.tensor([0.3, 0.0, 0.0], dtype=F64)
    keypoints = scene.keypoints.clone()
    training = ~held
    first = torch.tensor([obs[0] for obs in scene.observers])
    moved = training & (first != keyframe)  # beta observations only: the lifts stay true
    keypoints[keyframe, moved] = CAM.project_world(scene.points[moved], T_wrong)[0]
    return Scene(
        scene.T_true, scene.centers, scene.normals, scene.points, scene.observers, keypoints
    )


def test_an_optimisation_that_fits_wrong_tracks_is_rejected_unless_forced(scene: Scene):
    check = HoldoutCheckConfig()
    misled = _mislead_training_tracks(scene, check, keyframe=3)
    db = _database(misled, scene.T_true)
    args = (db, scene.centers, scene.normals, OPTIM)
    checked = checked_optimize_keyframe_poses(*args, check, pose_prior_sigma_m=0.5)
    assert not checked.improved and not checked.accepted, checked.reason
    assert checked.after.inlier_fraction < checked.before.inlier_fraction
    assert torch.equal(checked.T_wc, scene.T_true)  # the initial (here true) poses are kept
    assert _pose_errors(checked.T_wc_optimized, scene.T_true)[0] > 0.1  # it would have moved
    forced = checked_optimize_keyframe_poses(
        *args, HoldoutCheckConfig(accept="always"), pose_prior_sigma_m=0.5
    )
    assert forced.accepted and not forced.improved
    assert torch.equal(forced.T_wc, forced.T_wc_optimized)


def test_moves_beyond_the_pose_prior_fail_the_check(scene: Scene):
    """The correcting optimisation of the accepted test, but the user claims their poses are
    good to 2 cm: 0.2 m moves are 10 sigma, so the built poses are kept."""
    T_init = _perturb(scene.T_true, torch.Generator().manual_seed(3))
    db = _database(scene, T_init)
    checked = checked_optimize_keyframe_poses(
        db, scene.centers, scene.normals, OPTIM, HoldoutCheckConfig(), pose_prior_sigma_m=0.02
    )
    assert checked.after.inlier_fraction == 1.0  # the held-out test passes ...
    assert not checked.improved and "pose_prior_sigma_m" in checked.reason  # ... the move not
    assert torch.equal(checked.T_wc, T_init)


def test_pose_moves_against_the_prior_limits():
    T = torch.eye(4, dtype=F64).repeat(4, 1, 1)
    moved = T.clone()
    moved[:, 0, 3] = torch.tensor([0.1, 0.1, 0.1, 0.5], dtype=F64)
    cfg = HoldoutCheckConfig(max_move_sigmas=6.0, rms_move_sigmas=3.0)
    moves = pose_moves(moved, T, 0.1, cfg)
    assert moves.max_m == pytest.approx(0.5) and moves.rms_m == pytest.approx(0.2646, abs=1e-4)
    assert (moves.max_limit_m, moves.rms_limit_m) == pytest.approx((0.6, 0.3))
    assert moves.plausible
    assert not pose_moves(moved, T, 0.08, cfg).plausible  # 0.5 m > 6 x 0.08 m
    drift = T.clone()
    drift[:, 0, 3] = 0.35  # every keyframe 3.5 sigma: the RMS test catches it
    assert not pose_moves(drift, T, 0.1, cfg).plausible
    assert not pose_moves(moved, T, 0.0, cfg).plausible  # exact poses: no move allowed
    assert pose_moves(T, T, 0.0, cfg).plausible


@pytest.mark.parametrize(
    "bad",
    [
        {"accept": "sometimes"},
        {"holdout_fraction": 0.0},
        {"holdout_fraction": 1.0},
        {"inlier_px": 0.0},
        {"inlier_px": float("nan")},
        {"min_gain": -0.1},
        {"min_holdout_pairs": 0},
        {"max_move_sigmas": 0.0},
        {"rms_move_sigmas": float("inf")},
    ],
)
def test_bad_check_config_raises(bad: dict):
    with pytest.raises(ValueError, match=next(iter(bad))):
        HoldoutCheckConfig(**bad)


def test_bad_prior_raises(scene: Scene):
    db = _database(scene, scene.T_true)
    for prior in (-0.1, float("nan")):
        with pytest.raises(ValueError, match="pose_prior_sigma_m"):
            checked_optimize_keyframe_poses(
                db, scene.centers, scene.normals, OPTIM, HoldoutCheckConfig(), prior
            )
