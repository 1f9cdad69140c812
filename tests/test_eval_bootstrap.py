"""Paired bootstrap interval: known answers, stratification, determinism, a slow reference and
bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from diffloc.eval.bootstrap import paired_bootstrap_interval


def _a_right_b_wrong_on(q: int, wrong: int) -> tuple[np.ndarray, np.ndarray]:
    a = np.ones(q, dtype=bool)
    b = np.arange(q) >= wrong
    return a, b


def test_identical_variants_give_the_point_interval_zero() -> None:
    outcomes = np.random.default_rng(3).random(500) < 0.6
    r = paired_bootstrap_interval(outcomes, outcomes, seed=1)
    assert (r.difference, r.low, r.high) == (0.0, 0.0, 0.0)
    assert r.queries == 500 and not r.excludes_zero


def test_a_always_right_b_wrong_on_30_percent() -> None:
    a, b = _a_right_b_wrong_on(1000, 300)
    r = paired_bootstrap_interval(a, b, seed=0)
    assert r.difference == pytest.approx(0.3)
    assert r.low < 0.3 < r.high and r.excludes_zero
    # The binomial standard error sqrt(0.3 * 0.7 / 1000) = 0.0145 sets the half width.
    half_width = 1.959964 * math.sqrt(0.3 * 0.7 / 1000)
    assert (r.high - r.low) / 2 == pytest.approx(half_width, abs=0.003)
    # Swapping the variants mirrors the interval.
    m = paired_bootstrap_interval(b, a, seed=0)
    assert m.difference == pytest.approx(-0.3) and m.high < 0 and m.excludes_zero


def test_small_samples_do_not_exclude_zero() -> None:
    a, b = _a_right_b_wrong_on(10, 1)  # one query of ten differs
    r = paired_bootstrap_interval(a, b, seed=0)
    assert r.difference == pytest.approx(0.1) and r.low == 0.0 and not r.excludes_zero


def test_strata_keep_their_sizes() -> None:
    """Within each stratum the difference is constant, so a stratified resample cannot move
    the mean; resampling across strata does."""
    a, b = _a_right_b_wrong_on(100, 30)
    strata = np.where(np.arange(100) < 30, "seed 1", "seed 2")
    r = paired_bootstrap_interval(a, b, strata, seed=0)
    assert (r.low, r.high, r.strata) == (pytest.approx(0.3), pytest.approx(0.3), 2)
    pooled = paired_bootstrap_interval(a, b, seed=0)
    assert pooled.high - pooled.low > 0.1 and pooled.strata == 1


def _index_bootstrap(a, b, strata, resamples, rng) -> np.ndarray:
    """Slow reference: resample query indices with replacement inside each stratum."""
    d = a.astype(float) - b.astype(float)
    means = np.zeros(resamples)
    for label in np.unique(strata):
        members = np.flatnonzero(strata == label)
        picks = rng.choice(members, size=(resamples, members.size), replace=True)
        means += d[picks].sum(axis=1)
    return means / d.size


def test_matches_index_resampling() -> None:
    rng = np.random.default_rng(7)
    a = rng.random(300) < 0.8
    b = rng.random(300) < 0.6
    strata = rng.integers(0, 3, 300)
    r = paired_bootstrap_interval(a, b, strata, resamples=20_000, seed=0)
    means = _index_bootstrap(a, b, strata, 20_000, np.random.default_rng(1))
    low, high = np.quantile(means, [0.025, 0.975])
    assert r.difference == pytest.approx(means.mean(), abs=0.003)
    assert (r.low, r.high) == (pytest.approx(low, abs=0.006), pytest.approx(high, abs=0.006))


def test_deterministic_with_a_fixed_seed_and_int_outcomes() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.random(200) < 0.7, rng.random(200) < 0.5
    first = paired_bootstrap_interval(a, b, seed=5)
    assert paired_bootstrap_interval(a.astype(int), b.astype(np.int8), seed=5) == first
    again = paired_bootstrap_interval(a, b, seed=np.random.default_rng(5))
    assert again == first
    assert paired_bootstrap_interval(a, b, seed=6) != first
    narrow = paired_bootstrap_interval(a, b, seed=5, confidence=0.5)
    assert first.low < narrow.low <= narrow.high < first.high


@pytest.mark.parametrize(
    ("a", "b", "kwargs", "match"),
    [
        (np.ones(3, bool), np.ones(4, bool), {}, "same queries"),
        (np.ones((2, 2), bool), np.ones((2, 2), bool), {}, "1-D"),
        (np.zeros(0, bool), np.zeros(0, bool), {}, "no queries"),
        (np.array([0.5, 1.0]), np.array([1.0, 1.0]), {}, "binary"),
        (np.array([0, 2]), np.array([1, 1]), {}, "binary"),
        (np.ones(3, bool), np.ones(3, bool), {"strata": [1, 2]}, "strata"),
        (np.ones(3, bool), np.ones(3, bool), {"confidence": 1.0}, "confidence"),
        (np.ones(3, bool), np.ones(3, bool), {"resamples": 0}, "resamples"),
        (np.ones(3, bool), np.ones(3, bool), {"seed": None}, "seed"),
    ],
)
def test_bad_input_raises(a, b, kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        paired_bootstrap_interval(a, b, **kwargs)
