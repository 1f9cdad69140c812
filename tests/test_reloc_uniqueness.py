"""The uniqueness test (diffloc/reloc/uniqueness.py) and its validation rule."""

from __future__ import annotations

import math

import pytest
import torch

from diffloc.features.local import Features
from diffloc.reloc.hierarchical import Candidate, RelocResult
from diffloc.reloc.repetition import RepetitionConfig, repeated_shifts
from diffloc.reloc.uniqueness import (
    Uniqueness,
    UniquenessConfig,
    alternative_poses,
    pose_uniqueness,
)
from diffloc.reloc.validation import PoseEvidence, PoseValidator, ValidationConfig
from diffloc.testing import TiledFloor, tiled_floor


def uniqueness_of(
    floor: TiledFloor,
    rivals: torch.Tensor | None = None,
    config: UniquenessConfig | None = None,
) -> Uniqueness:
    return pose_uniqueness(
        floor.T_wc,
        floor.rivals if rivals is None else rivals,
        floor.inliers,
        floor.features,
        floor.camera,
        floor.positions,
        floor.descriptors,
        "l2",
        config,
    )


@pytest.fixture(scope="module")
def periodic() -> TiledFloor:
    return tiled_floor(period_m=1.0)


def test_the_shifts_of_a_tiled_floor_are_its_periods_without_duplicates(periodic):
    shifts, support = repeated_shifts(
        periodic.inliers[:, 1],
        periodic.positions,
        periodic.descriptors,
        "l2",
        RepetitionConfig(),
        3,
    )
    # every seen point has twins one and two periods away along x (the floor reaches 6 m)
    assert support.tolist() == [len(periodic.inliers)] * 3
    assert shifts[:, 1:].abs().max() < 1e-6
    assert sorted(round(float(x), 6) for x in shifts[:, 0]) == [-2.0, -1.0, 1.0]


def test_a_periodic_ambiguity_is_found_one_or_more_periods_away(periodic):
    u = uniqueness_of(periodic)
    assert u.own >= 0.85 * len(periodic.inliers) and u.own_visible == len(periodic.inliers)
    assert u.ratio >= 0.95
    periods = u.rival_distance_m / 1.0
    assert periods == pytest.approx(round(periods), abs=0.02) and round(periods) >= 1


def test_a_marking_that_does_not_repeat_makes_the_pose_unique():
    # a 1.6 m square of its own texture fills ~half the view: one period along, half the
    # keypoints find nothing
    marked = uniqueness_of(tiled_floor(period_m=1.0, marking_m=0.8))
    assert 0.35 <= marked.ratio <= 0.7
    distinct = uniqueness_of(tiled_floor(period_m=1.0, marking_m=10.0))  # nothing repeats
    assert distinct.ratio < 0.1
    assert distinct.own >= 0.95 * marked.own
    # the validation's rule: the ambiguous pose is rejected, the marked and distinct ones kept
    rule = ValidationConfig(uniqueness_ratio=0.8)
    assert [u.ratio < rule.uniqueness_ratio for u in (marked, distinct)] == [True, True]
    assert not uniqueness_of(tiled_floor(period_m=1.0)).ratio < rule.uniqueness_ratio


def test_a_rival_pose_is_refined_before_it_is_scored(periodic):
    # a rival candidate 1.02 m along and slightly turned (within the matching window of
    # 4 px): refinement brings it onto the period (1 m), where it explains the query as well
    # as the pose
    rival = periodic.T_wc.clone()
    rival[0, 3] += 1.02
    angle = 0.01
    turn = torch.tensor(
        [[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]],
        dtype=torch.float64,
    )
    rival[:3, :3] = turn @ rival[:3, :3]
    u = uniqueness_of(periodic, rival[None], UniquenessConfig(shifts=0))  # the only alternative
    assert u.alternatives == 1 and u.ratio >= 0.95
    assert u.rival_distance_m == pytest.approx(1.0, abs=0.01)


def test_an_alternative_that_refines_onto_the_pose_is_the_pose(periodic):
    near = periodic.T_wc.clone()
    near[0, 3] += 0.04
    u = uniqueness_of(periodic, near[None], UniquenessConfig(shifts=0))
    assert (u.alternatives, u.rival, u.rival_visible, u.ratio) == (0, 0, 0, 0.0)


def test_alternatives_are_both_signs_of_every_multiple_then_the_rivals():
    T = torch.eye(4, dtype=torch.float64)
    rivals = torch.eye(4, dtype=torch.float64).expand(1, 4, 4).clone()
    rivals[0, 2, 3] = 7.0
    shifts = torch.tensor([[1.0, 0, 0], [0, 0.5, 0]])
    poses = alternative_poses(T, shifts, 2, rivals)
    assert poses[:, :3, 3].tolist() == [
        [-2.0, 0, 0],
        [-1.0, 0, 0],
        [1.0, 0, 0],
        [2.0, 0, 0],
        [0, -1.0, 0],
        [0, -0.5, 0],
        [0, 0.5, 0],
        [0, 1.0, 0],
        [0, 0, 7.0],
    ]
    assert torch.equal(poses[:, :3, :3], torch.eye(3, dtype=torch.float64).expand(9, 3, 3))


def test_points_behind_nearer_points_are_not_matched(periodic):
    """A sheet of points 1 m below the camera with descriptors of their own hides the floor:
    the pose explains (almost) nothing, since the query saw the floor."""
    g = torch.Generator().manual_seed(3)
    grid = torch.arange(-40, 41, dtype=torch.float64) * 0.025  # 2 m x 2 m, ~3 px apart
    x, y = torch.meshgrid(grid + 0.3, grid + 0.2, indexing="ij")
    sheet = torch.stack([x, y, torch.ones_like(x)], -1).reshape(-1, 3)
    positions = torch.cat([periodic.positions, sheet])
    own = torch.nn.functional.normalize(torch.randn(len(sheet), 32, generator=g), dim=1)
    descriptors = torch.cat([periodic.descriptors, own])
    u = pose_uniqueness(
        periodic.T_wc,
        periodic.rivals,
        periodic.inliers,
        periodic.features,
        periodic.camera,
        positions,
        descriptors,
        "l2",
    )
    assert u.own < 0.05 * len(periodic.inliers) and u.own_visible > len(periodic.inliers)


def test_the_validation_rejects_an_ambiguous_pose_and_accepts_a_unique_one():
    v = PoseValidator(ValidationConfig(theta_in=15, temporal=False, uniqueness_ratio=0.8))
    result = RelocResult(
        torch.zeros(0, dtype=torch.int64),
        {},
        [Candidate(torch.eye(4, dtype=torch.float64), 500, 520, 1.0, 0)],
    )
    # scores are shares of the map points in view: 500 / 1000 own
    assert not v.validate_result(result, 0.0, uniqueness=Uniqueness(500, 1000, 240, 500, 1.0, 9))
    assert v.validate_result(result, 1.0, uniqueness=Uniqueness(500, 1000, 240, 800, 1.0, 9))
    assert not v.validate_result(result, 2.0, uniqueness=Uniqueness(0, 900, 3, 9, 1.0, 9))  # inf
    with pytest.raises(ValueError, match="uniqueness_ratio"):
        v.validate_result(result, 3.0)  # not measured
    seed1 = PoseValidator(ValidationConfig(uniqueness_ratio=0.8).seed1_rule())
    assert seed1.config.uniqueness_ratio is None


def test_a_recorded_uniqueness_replays():
    record = {
        "found": True,
        "position_m": [0.0, 0.0, 0.0],
        "candidates": [{"inliers": 40, "matches": 50, "coverage": 1.0, "distance_to_chosen_m": 0}],
        "uniqueness": {"own": 200, "own_visible": 400, "rival": 150, "rival_visible": 400},
    }
    evidence = PoseEvidence.from_record(record)
    assert evidence.uniqueness == pytest.approx(0.75)
    for ratio, verdict in ((0.7, False), (0.8, True)):
        v = PoseValidator(ValidationConfig(temporal=False, uniqueness_ratio=ratio))
        assert v.validate_evidence(evidence, 0.0) is verdict
    del record["uniqueness"]
    assert PoseEvidence.from_record(record).uniqueness is None


@pytest.mark.parametrize("ratio", [0.0, -0.5, math.nan, math.inf])
def test_bad_uniqueness_ratio_is_refused(ratio):
    with pytest.raises(ValueError, match="validation.uniqueness_ratio"):
        ValidationConfig(uniqueness_ratio=ratio)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"shifts": -1}, "uniqueness.shifts"),
        ({"max_multiple": 0}, "uniqueness.max_multiple"),
        ({"radius_px": 0.0}, "uniqueness.radius_px"),
        ({"min_separation_m": math.nan}, "uniqueness.min_separation_m"),
        ({"occlusion_cell_px": 0}, "uniqueness.occlusion_cell_px"),
        ({"occlusion_tolerance": -0.1}, "uniqueness.occlusion_tolerance"),
        ({"distance_quantile": 0.0}, "uniqueness.distance_quantile"),
    ],
)
def test_bad_uniqueness_settings_are_refused(kwargs, name):
    with pytest.raises(ValueError, match=name):
        UniquenessConfig(**kwargs)


def test_descriptors_of_another_kind_are_refused(periodic):
    wrong = Features(
        periodic.features.keypoints,
        periodic.features.scores,
        torch.zeros(len(periodic.features), 16),
        periodic.features.sizes,
    )
    with pytest.raises(ValueError, match="descriptors"):
        pose_uniqueness(
            periodic.T_wc,
            periodic.rivals,
            None,
            wrong,
            periodic.camera,
            periodic.positions,
            periodic.descriptors,
            "l2",
        )
