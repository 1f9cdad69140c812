"""The RANSAC core shared by PnP and the essential check: sampling, stopping, bail-out, LO.

A solver describes its problem (:class:`RansacProblem`: how to turn minimal samples into
scored candidates, and how to locally optimise them) and :func:`ransac` runs the search:

- Minimal samples are drawn in batches (:func:`sample_minimal_sets`, uniform over index sets
  of distinct elements); every batch draws the samples still needed, ``min_iterations`` at
  first (:func:`batch_count`: at most ``batch_size``, unless that would leave a remainder
  smaller than ``min(min_iterations, batch_size)``).
- The number of samples adapts to the inlier ratio ``w`` of the best model so far:
  ``k = log(1 - confidence) / log(1 - w^s)`` for samples of size ``s``, clamped to
  ``[min_iterations, max_iterations]`` (:func:`required_samples`).
- Scoring dominates the cost, so a problem first scores its candidates on a fixed random
  subset of the correspondences (:func:`bailout_subset`) and scores in full only those that
  pass :func:`bailout_keep`: a batched form of the bail-out test of Capel (BMVC 2005) on the
  variance-stabilised (arcsine) scale of binomial counts.
- Local optimisation (LO-RANSAC, Chum et al. 2003): the problem's
  :meth:`RansacProblem.local_optimisation` hook turns a batch's best candidates into one
  model (typically Gauss-Newton on the inliers, re-scored after every step), which becomes
  the best model when its cost is lower; the better inlier ratio also shortens the search.
  When it runs is the problem's :attr:`RansacProblem.lo_every_batch`: on every batch (it
  also optimises candidates that only beat the best model after LO, the robust cost having
  local minima; the essential check, whose five-point candidates are few and cheap to
  optimise beside the epipolar scoring), or, as in Chum et al., only on a batch whose best
  candidate beats the best model as it is, and not when that candidate ends the search (the
  solver's final refinement does the same work once). For PnP the second solves 140 instead
  of 209 Gauss-Newton systems over 40 problems with 75 % outliers, the same samples drawn,
  and is 8-15 % faster at 50-75 % outliers (``experiments/results/refactor_before_after.md``).

Scores are costs (lower is better, e.g. MSAC); all randomness comes from one
``torch.Generator``.

Example:
    >>> g = torch.Generator().manual_seed(0)
    >>> sets = sample_minimal_sets(10, 4, 3, g)
    >>> sets.shape, all(len(set(row)) == 3 for row in sets.tolist())
    (torch.Size([4, 3]), True)
    >>> required_samples(0.5, 3, confidence=0.99, min_iterations=1, max_iterations=1000)
    35
"""

from __future__ import annotations

import math
from typing import Protocol, TypeVar

import torch

__all__ = [
    "RansacModel",
    "RansacProblem",
    "RansacSettings",
    "bailout_keep",
    "bailout_subset",
    "batch_count",
    "ransac",
    "required_samples",
    "sample_minimal_sets",
]

_BAILOUT_SIGMAS = 3.0  # keep candidates within this many standard deviations of the best


class RansacModel(Protocol):
    """A scored model: the core reads its cost and inlier count only."""

    @property
    def cost(self) -> float:
        """Robust cost on all correspondences (lower is better)."""
        ...

    @property
    def num_inliers(self) -> int:
        """Correspondences within the inlier threshold."""
        ...


ModelT = TypeVar("ModelT", bound=RansacModel)


class RansacProblem(Protocol[ModelT]):
    """What :func:`ransac` needs from a solver: minimal solutions, scores and LO."""

    @property
    def num_points(self) -> int:
        """Number of correspondences ``n`` (at least ``sample_size``)."""
        ...

    @property
    def sample_size(self) -> int:
        """Size ``s`` of a minimal sample."""
        ...

    def candidates(self, samples: torch.Tensor, best_ratio: float) -> ModelT | None:
        """Solve and score a batch of minimal samples.

        Args:
            samples: (count, s) int64 indices of the correspondences of each sample.
            best_ratio: inlier ratio of the best model so far (0 without one), the reference
                of :func:`bailout_keep` beside the batch's own best subset count.

        Returns:
            The batch's best candidate(s), best first: ``cost`` and ``num_inliers`` are those
            of the best; ``None`` when no sample gives a model.
        """
        ...

    @property
    def lo_every_batch(self) -> bool:
        """Optimise every batch's candidates (``True``) or only a new best that does not end
        the search (``False``; the solver refines the final model itself)."""
        ...

    def local_optimisation(self, candidates: ModelT) -> ModelT:
        """The new best model from a batch's best candidates (LO-RANSAC hook).

        Args:
            candidates: the return value of :meth:`candidates`.

        Returns:
            One model, with a cost no higher than that of the best candidate.
        """
        ...


class RansacSettings(Protocol):
    """The sampling settings of a RANSAC config (validated by
    :func:`diffloc.checks.check_ransac_settings`)."""

    confidence: float
    min_iterations: int
    max_iterations: int
    batch_size: int


def sample_minimal_sets(n: int, count: int, size: int, generator: torch.Generator) -> torch.Tensor:
    """Uniformly random index sets of ``size`` distinct elements of ``range(n)``.

    Element ``j`` of a set is the ``r_j``-th (from 0) of the ``n - j`` elements not drawn
    yet, ``r_j`` uniform: every ordered tuple of distinct indices is equally likely. Costs
    ``O(count * size^2)``, independent of ``n``.

    Args:
        n: number of elements (at least ``size``).
        count: number of sets.
        size: elements per set.
        generator: the source of randomness.

    Returns:
        (count, size) int64 indices.

    Raises:
        ValueError: ``size < 1`` or ``n < size``.

    Example:
        >>> sample_minimal_sets(5, 2, 5, torch.Generator().manual_seed(1)).sort(1).values
        tensor([[0, 1, 2, 3, 4],
                [0, 1, 2, 3, 4]])
    """
    if size < 1 or n < size:
        raise ValueError(f"cannot draw {size} distinct elements of range({n})")
    ranks = torch.rand(count, size, generator=generator, dtype=torch.float64)
    ranks = ranks.mul_(torch.arange(n, n - size, -1, dtype=torch.float64)).long()
    columns = [ranks[:, 0]]
    drawn = ranks[:, :1]  # (count, j) the elements drawn so far, ascending
    for j in range(1, size):
        index = ranks[:, j]
        for k in range(j):  # step over the drawn elements at or below it, in ascending order
            index = index + (index >= drawn[:, k])
        columns.append(index)
        drawn = torch.cat((drawn, index[:, None]), dim=1).sort(dim=1).values
    return torch.stack(columns, dim=1)


def required_samples(
    inlier_ratio: float,
    sample_size: int,
    confidence: float,
    min_iterations: int,
    max_iterations: int,
) -> int:
    """Samples needed to draw an all-inlier minimal set with probability ``confidence``.

    ``log(1 - confidence) / log(1 - w^s)``, rounded up and clamped to
    ``[min_iterations, max_iterations]``; ``max_iterations`` without inliers (``w = 0``).

    Args:
        inlier_ratio: ``w`` in [0, 1].
        sample_size: ``s``.
        confidence: in (0, 1).
        min_iterations: lower clamp.
        max_iterations: upper clamp.

    Returns:
        The total number of samples to draw.

    Example:
        >>> required_samples(0.0, 5, 0.999, 10, 500), required_samples(1.0, 5, 0.999, 10, 500)
        (500, 10)
    """
    p_good = inlier_ratio**sample_size
    if p_good >= 1.0:
        needed = 0
    elif p_good <= 0.0:
        needed = max_iterations
    else:
        needed = math.ceil(math.log(1.0 - confidence) / math.log1p(-p_good))
    return min(max_iterations, max(min_iterations, needed))


def batch_count(needed: int, settings: RansacSettings) -> int:
    """Samples of the next batch given the ``needed`` ones: ``batch_size``, or all of them if
    that would leave fewer than ``min(min_iterations, batch_size)`` for another batch.

    A batch has a fixed cost of a few hundred small torch operations, about that of solving
    and scoring 150 PnP samples (measured with 1000 points), so a small remainder is cheaper
    drawn with the current batch than in a batch of its own.

    Args:
        needed: samples still to draw (positive).
        settings: ``batch_size`` and ``min_iterations``.

    Returns:
        The size of the next batch.
    """
    tail = min(settings.min_iterations, settings.batch_size)
    return needed if needed < settings.batch_size + tail else settings.batch_size


def bailout_subset(n: int, points: int, generator: torch.Generator) -> torch.Tensor | None:
    """The random subset of correspondences every candidate is scored on first.

    Args:
        n: number of correspondences.
        points: subset size; 0 disables the bail-out.
        generator: the source of randomness.

    Returns:
        (points,) int64 distinct indices, or ``None`` (score every candidate in full) when
        ``points`` is 0 or more than ``n / 2``.
    """
    if 0 < points and 2 * points <= n:
        return torch.randperm(n, generator=generator)[:points]
    return None


def bailout_keep(counts: torch.Tensor, subset_size: int, best_ratio: float) -> torch.Tensor | None:
    """Indices of the candidates worth a full score, from their subset inlier counts.

    The reference is the larger of the best subset count and the count the best model so
    far would have; candidates more than three standard deviations below it are dropped.
    The deviations are measured on the variance-stabilised scale of the binomial count ``k``
    of ``n`` draws, ``asin(sqrt(k / n))`` (standard deviation ``1 / (2 sqrt(n))`` whatever the
    inlier ratio), which unlike the normal approximation of ``k`` itself stays accurate for
    the small counts of low inlier ratios.

    Args:
        counts: (H,) subset inlier counts of H candidates.
        subset_size: size ``n`` of the subset.
        best_ratio: inlier ratio of the best model so far (0 without one).

    Returns:
        (K,) int64 indices of the kept candidates (possibly none), or ``None`` when every
        candidate is kept.

    Example:
        >>> bailout_keep(torch.tensor([32, 21, 20, 19]), 64, 0.0)
        tensor([0, 1])
    """
    ref = max(float(counts.max()), best_ratio * subset_size)
    angle = math.asin(math.sqrt(min(ref / subset_size, 1.0)))
    angle -= _BAILOUT_SIGMAS / (2.0 * math.sqrt(subset_size))
    if angle <= 0.0:
        return None
    keep = torch.nonzero(counts >= subset_size * math.sin(angle) ** 2)[:, 0]
    return None if keep.shape[0] == counts.shape[0] else keep


def ransac(
    problem: RansacProblem[ModelT], settings: RansacSettings, generator: torch.Generator
) -> tuple[ModelT | None, int]:
    """Adaptive batched RANSAC with local optimisation of every batch's best candidates.

    Args:
        problem: the solver's problem (minimal solutions, scoring, LO hook).
        settings: ``confidence``, ``min_iterations``, ``max_iterations``, ``batch_size``.
        generator: the source of the samples.

    Returns:
        ``(best, drawn)``: the best model (``None`` if no sample gave one) and the number of
        minimal samples drawn.
    """
    n = problem.num_points

    def samples_needed(model: ModelT | None) -> int:
        return required_samples(
            0.0 if model is None else model.num_inliers / n,
            problem.sample_size,
            settings.confidence,
            settings.min_iterations,
            settings.max_iterations,
        )

    best: ModelT | None = None
    drawn = 0
    target = max(settings.min_iterations, 1)
    while drawn < target:
        count = batch_count(target - drawn, settings)
        samples = sample_minimal_sets(n, count, problem.sample_size, generator)
        drawn += count
        ratio = 0.0 if best is None else best.num_inliers / n
        candidates = problem.candidates(samples, ratio)
        if candidates is None:
            pass
        elif problem.lo_every_batch:
            optimised = problem.local_optimisation(candidates)
            if best is None or optimised.cost < best.cost:
                best = optimised
        elif best is None or candidates.cost < best.cost:
            best = candidates
            if drawn < samples_needed(best):
                best = problem.local_optimisation(best)
        target = samples_needed(best)
    return best, drawn
