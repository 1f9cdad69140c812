"""The shared RANSAC core: uniform sampling, the adaptive sample count, batch sizes, the
arcsine bail-out test and the search loop with its local-optimisation hook on a toy problem."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import pytest
import torch

from diffloc.geometry.ransac import (
    bailout_keep,
    bailout_subset,
    batch_count,
    ransac,
    required_samples,
    sample_minimal_sets,
)


@dataclass
class _Settings:
    confidence: float = 0.999
    min_iterations: int = 10
    max_iterations: int = 1000
    batch_size: int = 64


@pytest.mark.parametrize("size", [1, 3, 5])
def test_samples_are_distinct_and_uniform(size: int) -> None:
    n, count = 7, 70_000
    sets = sample_minimal_sets(n, count, size, torch.Generator().manual_seed(size))
    assert sets.shape == (count, size) and sets.dtype == torch.int64
    assert int(sets.min()) >= 0 and int(sets.max()) < n
    ordered = sets.sort(dim=1).values
    assert bool((ordered[:, 1:] > ordered[:, :-1]).all())  # distinct
    # Every unordered set equally likely: chi-square over the C(7, size) subsets.
    subsets = {s: k for k, s in enumerate(itertools.combinations(range(n), size))}
    codes = torch.tensor([subsets[tuple(row)] for row in ordered.tolist()])
    observed = torch.bincount(codes, minlength=len(subsets)).double()
    expected = count / len(subsets)
    chi2 = float(((observed - expected) ** 2 / expected).sum())
    dof = len(subsets) - 1
    assert chi2 < dof + 5 * math.sqrt(2 * dof)
    # Every position uniform over the elements.
    for j in range(size):
        frequency = torch.bincount(sets[:, j], minlength=n).double() / count
        assert float((frequency - 1 / n).abs().max()) < 0.01


def test_samples_are_deterministic_and_checked() -> None:
    a = sample_minimal_sets(1000, 50, 5, torch.Generator().manual_seed(3))
    b = sample_minimal_sets(1000, 50, 5, torch.Generator().manual_seed(3))
    assert torch.equal(a, b)
    assert sample_minimal_sets(4, 0, 3, torch.Generator()).shape == (0, 3)
    with pytest.raises(ValueError, match="distinct"):
        sample_minimal_sets(4, 1, 5, torch.Generator())
    with pytest.raises(ValueError, match="distinct"):
        sample_minimal_sets(4, 1, 0, torch.Generator())


def test_required_samples_known_answers_and_clamps() -> None:
    # 50 % inliers, triples, 99 %: log(0.01) / log(7 / 8) = 34.5
    assert required_samples(0.5, 3, 0.99, 1, 10_000) == 35
    assert required_samples(0.5, 5, 0.999, 1, 10_000) == 218
    assert required_samples(0.5, 3, 0.99, 50, 10_000) == 50  # min clamp
    assert required_samples(0.1, 5, 0.999, 1, 1000) == 1000  # max clamp
    assert required_samples(0.0, 3, 0.99, 1, 777) == 777  # no inliers: the most
    assert required_samples(1.0, 3, 0.99, 5, 777) == 5  # all inliers: the fewest


def test_a_small_remainder_joins_the_batch() -> None:
    settings = _Settings(batch_size=512, min_iterations=100)
    assert batch_count(50, settings) == 50
    assert batch_count(515, settings) == 515  # not 512 and then 3
    assert batch_count(611, settings) == 611
    assert batch_count(612, settings) == 512
    small = _Settings(batch_size=64, min_iterations=100)  # a remainder below 64 joins
    assert (batch_count(127, small), batch_count(128, small)) == (127, 64)


def test_bailout_subset() -> None:
    subset = bailout_subset(200, 64, torch.Generator().manual_seed(0))
    assert subset is not None and subset.shape == (64,) and len(set(subset.tolist())) == 64
    assert bailout_subset(127, 64, torch.Generator()) is None  # fewer than twice the subset
    assert bailout_subset(1000, 0, torch.Generator()) is None  # disabled


def test_bailout_keeps_candidates_near_the_best_subset_count() -> None:
    # 64 subset points. At a low inlier ratio (best count 7) counts of 0 and 1 are hopeless
    # (a normal approximation of the binomial would keep them), 2 and more are kept.
    assert bailout_keep(torch.tensor([7, 0, 1, 2, 5]), 64, 0.0).tolist() == [0, 3, 4]
    # Half inliers: the bound is ~20.3, three standard deviations below 32.
    assert bailout_keep(torch.tensor([32, 21, 20, 19]), 64, 0.0).tolist() == [0, 1]
    # The best model so far (ratio 0.5) is the reference when no candidate comes close.
    assert bailout_keep(torch.tensor([10, 9]), 64, 0.5).tolist() == []
    # Counts too small to tell candidates apart: all are scored (None).
    assert bailout_keep(torch.tensor([2, 0, 1]), 64, 0.0) is None


@dataclass(frozen=True)
class _Line:
    """A toy model: the line ``y = a x + b`` and its MSAC score."""

    a: float
    b: float
    cost: float
    num_inliers: int


@dataclass
class _LineProblem:
    """Points on ``y = 2 x + 1`` with outliers; minimal samples are pairs of points."""

    x: torch.Tensor
    y: torch.Tensor
    threshold: float = 0.1
    sample_size: int = 2
    lo_every_batch: bool = True
    batches_with_a_model: int = 0
    batch_bests: list[_Line] = field(default_factory=list)
    optimised: list[_Line] = field(default_factory=list)

    @property
    def num_points(self) -> int:
        return self.x.shape[0]

    def _scored(self, a: float, b: float) -> _Line:
        err2 = (self.y - a * self.x - b).square()
        cost = float(err2.clamp(max=self.threshold**2).sum())
        return _Line(a, b, cost, int((err2 <= self.threshold**2).sum()))

    def candidates(self, samples: torch.Tensor, best_ratio: float) -> _Line | None:
        x, y = self.x[samples], self.y[samples]
        dx = x[:, 1] - x[:, 0]
        ok = dx.abs() > 1e-9
        if not bool(ok.any()):
            return None
        a = (y[ok, 1] - y[ok, 0]) / dx[ok]
        b = y[ok, 0] - a * x[ok, 0]
        self.batches_with_a_model += 1
        lines = [self._scored(float(p), float(q)) for p, q in zip(a, b, strict=True)]
        self.batch_bests.append(min(lines, key=lambda line: line.cost))
        return self.batch_bests[-1]

    def local_optimisation(self, candidates: _Line) -> _Line:
        self.optimised.append(candidates)
        inliers = (self.y - candidates.a * self.x - candidates.b).abs() <= self.threshold
        design = torch.stack((self.x[inliers], torch.ones_like(self.x[inliers])), dim=1)
        a, b = torch.linalg.lstsq(design, self.y[inliers, None]).solution[:, 0].tolist()
        refit = self._scored(a, b)
        return refit if refit.cost < candidates.cost else candidates


def _line_problem(
    n: int, outlier_ratio: float, seed: int, lo_every_batch: bool = True
) -> tuple[_LineProblem, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, generator=g, dtype=torch.float64) * 10
    y = 2 * x + 1 + 0.01 * torch.randn(n, generator=g, dtype=torch.float64)
    outlier = torch.rand(n, generator=g) < outlier_ratio
    y = torch.where(outlier, torch.rand(n, generator=g, dtype=torch.float64) * 20, y)
    return _LineProblem(x, y, lo_every_batch=lo_every_batch), ~outlier


def test_ransac_finds_the_line_and_locally_optimises_every_batch() -> None:
    problem, truth = _line_problem(300, 0.6, 0)
    settings = _Settings()
    best, drawn = ransac(problem, settings, torch.Generator().manual_seed(0))
    assert best is not None
    assert abs(best.a - 2) < 0.01 and abs(best.b - 1) < 0.05
    assert best.num_inliers >= 0.98 * int(truth.sum())
    # The adaptive count for the inlier ratio found, within the clamps (batches may overshoot).
    needed = required_samples(best.num_inliers / 300, 2, 0.999, 10, 1000)
    assert needed <= drawn < needed + settings.batch_size
    # LO ran on the best candidate of every batch, and the best model is the best LO result.
    assert len(problem.optimised) == problem.batches_with_a_model > 1
    refits = [problem.local_optimisation(line).cost for line in list(problem.optimised)]
    assert best.cost == min(refits)


def test_ransac_optimises_only_a_new_best_that_does_not_end_the_search() -> None:
    problem, truth = _line_problem(300, 0.6, 0, lo_every_batch=False)
    settings = _Settings(batch_size=16)
    best, drawn = ransac(problem, settings, torch.Generator().manual_seed(0))
    assert best is not None and abs(best.a - 2) < 0.01 and abs(best.b - 1) < 0.05
    assert best.num_inliers >= 0.9 * int(truth.sum())
    # LO (Chum et al.) saw only batch bests that beat every batch best before them (the best
    # model, LO'd, is no worse than those), on fewer batches than there were.
    assert 0 < len(problem.optimised) < problem.batches_with_a_model
    costs = [line.cost for line in problem.batch_bests]
    for line in problem.optimised:
        k = next(i for i, b in enumerate(problem.batch_bests) if b is line)
        assert all(line.cost < c for c in costs[:k])
    needed = required_samples(best.num_inliers / 300, 2, 0.999, 10, 1000)
    assert needed <= drawn < needed + settings.batch_size


def test_ransac_stops_at_min_iterations_without_outliers() -> None:
    problem, _ = _line_problem(100, 0.0, 1)
    best, drawn = ransac(problem, _Settings(min_iterations=10), torch.Generator().manual_seed(1))
    assert best is not None and best.num_inliers == 100 and drawn == 10


def test_ransac_without_any_model_draws_max_iterations() -> None:
    problem = _LineProblem(
        torch.ones(50, dtype=torch.float64), torch.zeros(50, dtype=torch.float64)
    )
    settings = _Settings(max_iterations=300, batch_size=128)
    best, drawn = ransac(problem, settings, torch.Generator().manual_seed(2))
    assert best is None and drawn == 300 and problem.optimised == []
