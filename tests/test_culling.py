"""The two culling rules of seed 1 Sec. III-A on constructed databases."""

from __future__ import annotations

import pytest
import torch

from diffloc.database.culling import (
    CullingConfig,
    cull_redundant_keyframes,
    cull_unconfirmed_points,
    redundancy,
)
from tests.test_database import make_database


def test_a_redundant_keyframe_is_culled_and_a_distinctive_one_stays():
    # Keyframe 0 sees points 0-9, all also seen by keyframes 1, 2, 3 (3 others each).
    # Keyframes 1-3 also see points 10-19 that only they see (2 others each).
    everyone = [[0, 1, 2, 3]] * 10
    shared = [[1, 2, 3]] * 10
    db = make_database(everyone + shared)
    assert redundancy(db, CullingConfig()).tolist() == [1.0, 0.5, 0.5, 0.5]
    removed = cull_redundant_keyframes(db, CullingConfig())
    assert removed.tolist() == [0]
    assert db.num_keyframes == 3 and db.num_points == 20
    # After the removal, nobody is redundant any more.
    assert cull_redundant_keyframes(db, CullingConfig()).tolist() == []


def test_mutually_redundant_keyframes_are_not_all_culled():
    db = make_database([[0, 1, 2, 3, 4]] * 10)  # five identical keyframes
    removed = cull_redundant_keyframes(db, CullingConfig())
    assert removed.tolist() == [0, 1]  # then each point has 3 observers: 2 others
    assert db.num_keyframes == 3 and db.num_points == 10


def test_fraction_threshold_and_candidates():
    # Keyframe 0: 9 of 10 points well seen (90%) -> redundant; 8 of 10 would not be.
    # Keyframes 1-3: 9 of 11 (two points of their own) -> not redundant.
    own = [[1], [1], [2], [2], [3], [3]]
    db = make_database([[0, 1, 2, 3]] * 9 + [[0]] + own)
    assert cull_redundant_keyframes(db, CullingConfig(), torch.tensor([1, 2])).tolist() == []
    assert cull_redundant_keyframes(db, CullingConfig()).tolist() == [0]
    db = make_database([[0, 1, 2, 3]] * 8 + [[0], [0]] + own)
    assert cull_redundant_keyframes(db, CullingConfig()).tolist() == []


def test_point_not_reobserved_within_the_window_is_removed():
    # Point 0: created by kf 0, seen again by kf 2 (inside the window) -> kept.
    # Point 1: created by kf 0, seen again only by kf 3 (outside) -> removed.
    # Point 2: created by kf 0, never again -> removed.
    # Point 3: created by kf 2, window (3, 4) incomplete -> not judged.
    db = make_database([[0, 2], [0, 3], [0], [2], [3]])
    positions = db.point_positions.clone()
    removed = cull_unconfirmed_points(db, CullingConfig())
    assert removed.tolist() == [1, 2]
    assert torch.equal(db.point_positions, positions[[0, 3, 4]])


def test_only_points_of_the_given_keyframes_are_judged():
    db = make_database([[0], [1], [1, 2], [4]])
    assert cull_unconfirmed_points(db, CullingConfig(), torch.tensor([1])).tolist() == [1]
    assert db.num_points == 3
    assert cull_unconfirmed_points(db, CullingConfig(new_point_window=1)).tolist() == [0]


def test_bad_config_is_rejected():
    with pytest.raises(ValueError, match="redundant_fraction"):
        CullingConfig(redundant_fraction=1.5)
    with pytest.raises(ValueError, match="new_point_window"):
        CullingConfig(new_point_window=0)
