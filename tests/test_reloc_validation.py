"""Pose validation (seed 1 Sec. III-C): inlier count, distance to the previous inlier pose."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.geometry.se3 import so3_exp
from diffloc.reloc.hierarchical import Candidate, RelocResult
from diffloc.reloc.validation import PoseEvidence, PoseValidator, ValidationConfig


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


def test_a_reference_older_than_the_age_limit_verifies_nothing():
    cfg = ValidationConfig(theta_in=15, theta_dist_m=0.3, max_speed_mps=1.0)
    unlimited, limited = PoseValidator(cfg), PoseValidator(replace(cfg, max_reference_age_s=2.0))
    for v in (unlimited, limited):
        v.validate(pose_at(0.0), 30, 0.0)
    # 3 s later, 3.0 m away (a storey above): within 0.3 + 1.0 * 3 m, but the reference is old.
    assert unlimited.validate(pose_at(3.0), 30, 3.0)
    assert not limited.validate(pose_at(3.0), 30, 3.0)
    assert limited.validate(pose_at(3.5), 30, 4.0)  # the old pose was the new reference
    assert limited.validate(pose_at(5.0), 30, 6.0)  # 2 s: still young enough
    assert replace(cfg, max_reference_age_s=2.0).seed1_rule().max_reference_age_s is None


@pytest.mark.parametrize("age", [0.0, -1.0, math.nan, math.inf])
def test_bad_reference_age_is_refused(age: float):
    with pytest.raises(ValueError, match="max_reference_age_s"):
        ValidationConfig(max_reference_age_s=age)


def test_a_conflicting_pose_keeps_the_live_reference_when_configured():
    cfg = ValidationConfig(theta_in=15, theta_dist_m=0.3, max_reference_age_s=2.0)
    seed1, kept = PoseValidator(cfg), PoseValidator(replace(cfg, conflict_keeps_reference=True))
    for v in (seed1, kept):
        v.validate(pose_at(0.0), 30, 0.0)
        assert not v.validate(pose_at(6.7), 200, 1.0)  # a jump to a repeated place
    # Seed 1: the jump became the reference and its repetition verifies it.
    assert seed1.validate(pose_at(6.7), 200, 2.0)
    # Kept: the reference is still at 0 (2 s old), so the repetition is not verified ...
    assert not kept.validate(pose_at(6.7), 200, 2.0)
    assert kept.validate(pose_at(0.1), 30, 2.0)  # ... and the track at 0 goes on.
    # Once the reference expires, the other place can start a track of its own.
    assert not kept.validate(pose_at(6.7), 200, 4.5)
    assert kept.validate(pose_at(6.8), 200, 5.0)
    assert not replace(cfg, conflict_keeps_reference=True).seed1_rule().conflict_keeps_reference


def test_speed_allowance_grows_with_the_time_gap():
    v = PoseValidator(ValidationConfig(theta_in=15, theta_dist_m=0.3, max_speed_mps=1.0))
    v.validate(pose_at(0.0), 30, 0.0)
    assert v.validate(pose_at(1.2), 30, 1.0)  # 1.2 <= 0.3 + 1.0 * 1
    assert not v.validate(pose_at(2.1), 30, 1.5)  # 0.9 > 0.3 + 1.0 * 0.5


def pose_on_circle(angle: float, radius_m: float = 5.0) -> torch.Tensor:
    """A camera on a circle about the origin in the xy plane, looking along its path."""
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = so3_exp(torch.tensor([0.0, 0.0, angle], dtype=torch.float64))
    T[:3, 3] = torch.tensor([radius_m * math.sin(angle), radius_m * (1 - math.cos(angle)), 0.0])
    return T


MOTION = ValidationConfig(
    theta_in=15, theta_dist_m=0.3, max_speed_mps=6.0, max_reference_age_s=2.0, max_accel_mps2=1.0
)


def test_motion_test_rejects_a_pose_snapped_one_period_back_along_the_track():
    """2 m/s along x, a query every 0.5 s; the third pose lands 1.25 m short (a ground tile one
    period back). The speed allowance (0.3 + 6 * 0.5 m) passes it; the motion test does not."""
    for accel, expected in ((None, True), (1.0, False)):
        v = PoseValidator(replace(MOTION, max_accel_mps2=accel))
        v.validate(pose_at(0.0), 30, 0.0)
        assert v.validate(pose_at(1.0), 30, 0.5)
        assert v.validate(pose_at(2.0 - 1.25), 30, 1.0) is expected
    # Within theta_dist + accel dt^2 / 2 = 0.425 m of the prediction (2.0 m): a change of speed.
    v = PoseValidator(MOTION)
    v.validate(pose_at(0.0), 30, 0.0)
    v.validate(pose_at(1.0), 30, 0.5)
    assert v.validate(pose_at(2.4), 30, 1.0)
    assert not replace(MOTION).seed1_rule().max_accel_mps2


def test_a_pose_failing_the_motion_test_keeps_the_reference_and_drops_the_velocity():
    v = PoseValidator(MOTION)
    v.validate(pose_at(0.0), 30, 0.0)
    v.validate(pose_at(1.0), 30, 0.5)  # velocity 2 m/s
    assert not v.validate(pose_at(0.75), 30, 1.0)  # snapped back: rejected
    # The reference is still at 1.0 m (t = 0.5 s), without a velocity: a pose 0.8 m on, 1 s
    # later (1.2 m short of the old velocity's prediction of 3.0 m), meets the distance test
    # alone.
    assert v.validate(pose_at(1.8), 30, 1.5)


def test_motion_test_follows_a_turning_track():
    """3 m/s on a 5 m circle (a 34 degree turn per 0.5 s): a velocity not turned with the
    camera would miss the next pose by 0.44 m; the turned one predicts it."""
    step = 3.0 * 0.5 / 5.0
    v = PoseValidator(MOTION)
    assert not v.validate(pose_on_circle(0.0), 30, 0.0)
    assert all(v.validate(pose_on_circle(k * step), 30, 0.5 * k) for k in range(1, 8))
    straight = pose_on_circle(step)[:3, 3] - pose_on_circle(0.0)[:3, 3]
    miss = pose_on_circle(2 * step)[:3, 3] - pose_on_circle(step)[:3, 3] - straight
    assert 0.4 < float(torch.linalg.vector_norm(miss)) < 0.5


def test_motion_test_needs_the_rotation():
    v = PoseValidator(MOTION)
    with pytest.raises(ValueError, match="max_accel_mps2"):
        v.validate_position(torch.zeros(3, dtype=torch.float64), 30, 0.0)
    with pytest.raises(ValueError, match="max_accel_mps2"):
        ValidationConfig(max_accel_mps2=-1.0)


def test_a_track_needs_three_poses_before_its_poses_are_accepted():
    """Two consecutive poses of one wrong place pass the distance test against each other; the
    third must come from a track whose reference was itself verified."""
    for track, expected in ((2, [False, True, True, True]), (3, [False, False, True, True])):
        v = PoseValidator(replace(MOTION, min_track_poses=track))
        got = [v.validate(pose_at(1.0 * k), 30, 0.5 * k) for k in range(4)]
        assert got == expected
    assert replace(MOTION, min_track_poses=3).seed1_rule().min_track_poses == 2


def test_a_track_restarts_after_a_pose_fails_the_motion_test():
    v = PoseValidator(replace(MOTION, min_track_poses=3))
    v.validate(pose_at(0.0), 30, 0.0)
    v.validate(pose_at(1.0), 30, 0.5)
    assert v.validate(pose_at(2.0), 30, 1.0)  # three poses: accepted
    assert not v.validate(pose_at(3.0 - 1.25), 30, 1.5)  # snapped back: the track ends at 2.0
    assert not v.validate(pose_at(4.0), 30, 2.0)  # verified against 2.0: a track of two
    assert v.validate(pose_at(5.0), 30, 2.5)  # three again


def test_an_unverified_pose_starts_a_new_track():
    """A pose that fails the distance test and replaces the reference (seed 1's rule) starts a
    track of one, so the pose after it is not yet accepted."""
    v = PoseValidator(ValidationConfig(theta_in=15, theta_dist_m=0.3, min_track_poses=3))
    for k in range(3):
        v.validate(pose_at(0.1 * k), 30, 0.1 * k)
    assert not v.validate(pose_at(5.0), 30, 0.3)  # a jump: the new reference, track of one
    assert not v.validate(pose_at(5.1), 30, 0.4)
    assert v.validate(pose_at(5.2), 30, 0.5)


@pytest.mark.parametrize("poses", [0, 1, -3])
def test_a_track_shorter_than_two_poses_is_refused(poses: int):
    with pytest.raises(ValueError, match="min_track_poses"):
        ValidationConfig(min_track_poses=poses)


PLANAR_TRACK = ValidationConfig(
    theta_in=15, theta_dist_m=0.3, max_speed_mps=1.0, min_track_poses=3, max_track_plane_share=0.95
)


def track_verdicts(validator: PoseValidator, shares: list[float]) -> list[bool]:
    """Verdicts of a straight track at 1 m/s, one pose per second, with these plane shares."""
    return [
        validator.validate_position(pose_at(float(k))[:3, 3], 30, float(k), plane_share=share)
        for k, share in enumerate(shares)
    ]


def test_a_track_resting_on_one_plane_throughout_is_not_accepted():
    """A turned copy of a tiled wall: every pose of the track has all its inliers on one plane;
    seed 1's rule and the track length accept it, the track's planarity test does not until a
    pose sees more than the plane."""
    shares = [1.0, 0.99, 1.0, 1.0, 0.6, 1.0]
    tested = track_verdicts(PoseValidator(PLANAR_TRACK), shares)
    no_test = replace(PLANAR_TRACK, max_track_plane_share=None)
    untested = track_verdicts(PoseValidator(no_test), shares)
    assert tested == [False, False, False, False, True, True]
    assert untested == [False, False, True, True, True, True]
    assert PLANAR_TRACK.seed1_rule().max_track_plane_share is None


def test_one_planar_pose_inside_a_track_stays_accepted():
    """A camera passing a bare wall: the track has seen more than the plane before."""
    shares = [0.5, 0.7, 0.8, 1.0, 1.0, 0.6]
    accepted = track_verdicts(PoseValidator(PLANAR_TRACK), shares)
    assert accepted == [False, False, True, True, True, True]


def test_a_new_track_forgets_the_planarity_of_the_old_one():
    """After a jump (the reference replaced by an unverified pose) the new track must show 3D
    evidence beyond one plane of its own."""
    v = PoseValidator(replace(PLANAR_TRACK, conflict_keeps_reference=False))
    assert track_verdicts(v, [0.5, 0.5, 0.5]) == [False, False, True]
    jumped = [
        v.validate_position(pose_at(10.0 + k)[:3, 3], 30, 3.0 + k, plane_share=1.0)
        for k in range(4)
    ]
    assert jumped == [False, False, False, False]


def test_the_tracks_planarity_test_needs_the_plane_share():
    with pytest.raises(ValueError, match="max_track_plane_share"):
        PoseValidator(PLANAR_TRACK).validate_position(torch.zeros(3, dtype=torch.float64), 30, 0.0)
    with pytest.raises(ValueError, match="max_track_plane_share"):
        ValidationConfig(max_track_plane_share=1.5)


def test_the_tracks_planarity_is_read_from_the_recorded_evidence():
    """The replay path (``queries.json``) reads the best candidate's plane share."""
    v = PoseValidator(PLANAR_TRACK)
    verdicts = []
    for k in range(4):
        record = {
            "found": True,
            "position_m": [float(k), 0.0, 0.0],
            "candidates": [
                {
                    "inliers": 40,
                    "matches": 60,
                    "coverage": 0.8,
                    "distance_to_chosen_m": 0.0,
                    "plane_share": 1.0 if k < 3 else 0.4,
                }
            ],
        }
        verdicts.append(v.validate_evidence(PoseEvidence.from_record(record), float(k)))
    assert verdicts == [False, False, False, True]


def test_evidence_reads_the_recorded_rotation():
    T = pose_on_circle(0.3)
    record = {
        "found": True,
        "position_m": T[:3, 3].tolist(),
        "rotation_wc": T[:3, :3].tolist(),
        "candidates": [{"inliers": 40, "matches": 60, "coverage": 0.8, "distance_to_chosen_m": 0}],
    }
    evidence = PoseEvidence.from_record(record)
    assert torch.equal(evidence.rotation, T[:3, :3])
    assert PoseEvidence.from_record({**record, "rotation_wc": None}).rotation is None


def test_a_loosely_fixed_position_is_rejected():
    cfg = replace(STRICT, max_position_sigma_m=0.1)
    precise, loose = candidate(0.1, 60), candidate(0.1, 60)
    precise.position_sigma_m, loose.position_sigma_m = 0.02, 0.25
    for sigma_candidate, expected in ((precise, True), (loose, False)):
        v = PoseValidator(cfg)
        v.validate_result(result_of(candidate(0.0, 60, position_sigma=0.02)), 0.0)
        assert v.validate_result(result_of(sigma_candidate), 1.0) is expected
    # seed 1's rule does not ask
    seed1 = PoseValidator(cfg.seed1_rule())
    seed1.validate_result(result_of(candidate(0.0, 60)), 0.0)
    assert seed1.validate_result(result_of(loose), 1.0)


def test_the_precision_test_needs_the_measurement():
    v = PoseValidator(replace(STRICT, max_position_sigma_m=0.1))
    with pytest.raises(ValueError, match="max_position_sigma_m"):
        v.validate_result(result_of(candidate(0.0, 60)), 0.0)  # NaN: not measured
    with pytest.raises(ValueError, match="max_position_sigma_m"):
        ValidationConfig(max_position_sigma_m=0.0)


def test_evidence_reads_the_recorded_position_sigma():
    record = {
        "found": True,
        "position_m": [0.0, 0.0, 0.0],
        "candidates": [
            {
                "inliers": 40,
                "matches": 60,
                "coverage": 0.8,
                "distance_to_chosen_m": 0,
                "position_sigma_m": 0.03,
            }
        ],
    }
    assert PoseEvidence.from_record(record).position_sigma == 0.03
    record["candidates"][0]["position_sigma_m"] = None  # JSON for an unbounded position
    assert PoseEvidence.from_record(record).position_sigma == math.inf
    del record["candidates"][0]["position_sigma_m"]
    assert PoseEvidence.from_record(record).position_sigma is None


def test_evidence_on_one_plane_is_rejected_when_the_test_is_on():
    cfg = replace(STRICT, max_plane_share=0.9)
    spread, flat = candidate(0.1, 60), candidate(0.1, 60)
    spread.plane_share, flat.plane_share = 0.55, 1.0
    for plane_candidate, expected in ((spread, True), (flat, False)):
        v = PoseValidator(cfg)
        first = candidate(0.0, 60)
        first.plane_share = 0.5
        v.validate_result(result_of(first), 0.0)
        assert v.validate_result(result_of(plane_candidate), 1.0) is expected
    assert PoseValidator(cfg).failed_tests(PoseEvidence.from_result(result_of(flat))) == ("planar",)
    seed1 = PoseValidator(cfg.seed1_rule())  # seed 1's rule does not ask
    seed1.validate_result(result_of(candidate(0.0, 60)), 0.0)
    assert seed1.validate_result(result_of(flat), 1.0)


def test_the_plane_test_needs_the_measurement_and_a_share():
    v = PoseValidator(replace(STRICT, max_plane_share=0.9))
    with pytest.raises(ValueError, match="max_plane_share"):
        v.validate_result(result_of(candidate(0.0, 60)), 0.0)  # NaN: not measured
    for bad in (1.5, -0.1, math.nan):
        with pytest.raises(ValueError, match="max_plane_share"):
            ValidationConfig(max_plane_share=bad)


def test_evidence_reads_the_recorded_plane_share():
    entry = {"inliers": 40, "matches": 60, "coverage": 0.8, "distance_to_chosen_m": 0}
    record = {"found": True, "position_m": [0.0, 0.0, 0.0], "candidates": [entry]}
    assert PoseEvidence.from_record(record).plane_share is None  # an older run
    entry["plane_share"] = 0.97
    assert PoseEvidence.from_record(record).plane_share == 0.97


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


def candidate(
    x: float,
    inliers: int,
    matches: int = 100,
    coverage: float = 1.0,
    position_sigma: float = math.nan,
) -> Candidate:
    return Candidate(
        pose_at(x), inliers, matches, coverage, canonical=0, position_sigma_m=position_sigma
    )


def result_of(*candidates: Candidate) -> RelocResult:
    return RelocResult(torch.zeros(0, dtype=torch.int64), {}, list(candidates))


STRICT = ValidationConfig(
    theta_in=15, theta_dist_m=0.3, min_inlier_ratio=0.3, min_coverage=0.25, ambiguity_ratio=0.5
)


@pytest.mark.parametrize(
    ("evidence", "reason"),
    [
        ((candidate(0.1, 20, matches=100),), "inlier ratio 0.2 < 0.3"),
        ((candidate(0.1, 60, coverage=0.125),), "inliers on 2 of 16 cells"),
        ((candidate(0.1, 60), candidate(4.0, 30)), "a rival 3.9 m away with half the inliers"),
    ],
)
def test_implausible_poses_are_rejected_and_do_not_become_the_reference(evidence, reason):
    v = PoseValidator(STRICT)
    assert not v.validate_result(result_of(candidate(0.0, 60)), 0.0)  # the reference
    assert not v.validate_result(result_of(*evidence), 1.0), reason
    # the rejected pose did not replace the reference: a pose near 0 still verifies
    assert v.validate_result(result_of(candidate(0.2, 60)), 2.0)
    # seed 1's rule alone accepts the same evidence
    seed1 = PoseValidator(STRICT.seed1_rule())
    seed1.validate_result(result_of(candidate(0.0, 60)), 0.0)
    assert seed1.validate_result(result_of(*evidence), 1.0), reason


def test_rivals_near_the_pose_or_with_few_inliers_are_no_ambiguity():
    v = PoseValidator(STRICT)
    v.validate_result(result_of(candidate(0.0, 60)), 0.0)
    assert v.validate_result(result_of(candidate(0.1, 60), candidate(0.3, 59)), 1.0)
    assert v.validate_result(result_of(candidate(0.1, 60), candidate(5.0, 29)), 2.0)


def test_a_result_without_a_pose_is_not_verified():
    v = PoseValidator(STRICT)
    nothing = RelocResult(torch.zeros(0, dtype=torch.int64), {})
    assert not v.validate_result(nothing, 0.0)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"min_inlier_ratio": 1.5}, "min_inlier_ratio"),
        ({"min_coverage": -0.1}, "min_coverage"),
        ({"ambiguity_ratio": 0.0}, "ambiguity_ratio"),
        ({"ambiguity_ratio": math.nan}, "ambiguity_ratio"),
    ],
)
def test_bad_plausibility_thresholds_are_clear_errors(kwargs, name):
    with pytest.raises(ValueError, match=name):
        ValidationConfig(**kwargs)
