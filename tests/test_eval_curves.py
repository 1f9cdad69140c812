"""When a learning curve first reaches a level (``diffloc.eval.curves``): known answers."""

from __future__ import annotations

import pytest

from diffloc.eval.curves import common_level, time_to_reach


def test_time_is_interpolated_between_the_marks_around_the_crossing() -> None:
    # 20 -> 24 dB between 30 s and 70 s: 23 dB is 3/4 of the way
    assert time_to_reach([10.0, 30.0, 70.0], [18.0, 20.0, 24.0], 23.0) == pytest.approx(60.0)


def test_first_mark_already_at_the_level_gives_its_time() -> None:
    assert time_to_reach([15.0, 30.0], [22.0, 23.0], 21.0) == 15.0


def test_a_level_never_reached_gives_none() -> None:
    assert time_to_reach([15.0, 30.0], [22.0, 23.0], 23.5) is None


def test_the_first_crossing_counts_not_a_later_one() -> None:
    assert time_to_reach([0.0, 10.0, 20.0, 30.0], [0.0, 2.0, 1.0, 4.0], 2.0) == 10.0


def test_mismatched_lengths_are_rejected() -> None:
    with pytest.raises(ValueError, match="differ in length"):
        time_to_reach([1.0, 2.0], [1.0], 1.0)


def test_times_must_increase() -> None:
    with pytest.raises(ValueError, match="strictly increasing"):
        time_to_reach([2.0, 1.0], [1.0, 2.0], 1.5)


def test_common_level_is_the_lowest_best_score() -> None:
    assert common_level({"a": [1.0, 5.0, 4.0], "b": [2.0, 3.0], "c": [9.0]}) == 3.0


def test_common_level_needs_scores() -> None:
    with pytest.raises(ValueError, match="empty"):
        common_level({"a": [1.0], "b": []})
