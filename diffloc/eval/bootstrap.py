"""Paired bootstrap interval of the difference between two success rates on the same queries.

Two variants (e.g. FN and F points, or the optimised and the raw database) are run on the same
queries; each query has a binary outcome under each (``correct``: accepted and within 0.3 m).
The difference of the success rates is the mean of the per-query differences
``d_q = a_q - b_q`` in {-1, 0, +1}. The bootstrap resamples *queries* with replacement, keeping
each query's two outcomes together (paired), and takes the mean difference of every resample;
the ``confidence`` percentile interval of those means is returned (the plain percentile method,
no bias correction).

Strata: queries may carry a stratum label (e.g. ``"seed 3/query_same"``). Each stratum is then
resampled on its own, with its own size, so every resample has the same mix of seeds and
sequences as the data; only the within-stratum variation is resampled. The difference is still
the mean over all Q queries (strata weighted by their query counts).

Vectorised without a (resamples, Q) index array: a resample of ``n_s`` queries of stratum ``s``
only matters through how many of its draws have ``d = +1``, ``0`` and ``-1``, which is one
multinomial draw with the stratum's frequencies of the three values. This has exactly the
distribution of index resampling and costs ``resamples x strata`` draws.

Limits: queries are treated as exchangeable within a stratum. Successive queries of one
sequence are correlated (the temporal pose validation uses the previous accepted pose), so the
interval is, if anything, too narrow; and with few seeds it describes the query sample of those
seeds, not the spread of the effect over further, unseen seeds.

Example:
    >>> a = np.ones(1000, dtype=bool)           # variant A right on every query
    >>> b = np.arange(1000) >= 300              # variant B wrong on 30 % of them
    >>> r = paired_bootstrap_interval(a, b, seed=0)
    >>> r.queries, round(r.difference, 3), r.low > 0.25, r.high < 0.35
    (1000, 0.3, True, True)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["BootstrapInterval", "paired_bootstrap_interval"]

DEFAULT_RESAMPLES = 10_000
"""Bootstrap resamples: the Monte Carlo error of a 95 % percentile bound is then ~1e-3."""


@dataclass(frozen=True)
class BootstrapInterval:
    """A paired difference ``mean(a) - mean(b)`` and its bootstrap percentile interval.

    Attributes:
        difference: the observed mean difference (a fraction in [-1, 1]).
        low: the lower bound of the interval.
        high: the upper bound of the interval.
        queries: Q, the number of paired queries.
        strata: the number of strata resampled separately (1 without strata).
        confidence: the interval's nominal coverage (e.g. 0.95).
        resamples: the number of bootstrap resamples.
    """

    difference: float
    low: float
    high: float
    queries: int
    strata: int
    confidence: float
    resamples: int

    @property
    def excludes_zero(self) -> bool:
        """Whether 0 lies outside ``[low, high]``."""
        return self.low > 0.0 or self.high < 0.0

    def to_dict(self) -> dict[str, float | int]:
        """The fields as a JSON-ready dict."""
        return asdict(self)


def _binary(x: object, name: str) -> np.ndarray:
    """``x`` as a 1-D bool array; bool, or integers that are all 0 or 1."""
    arr = np.asarray(x)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be a 1-D array of per-query outcomes, got shape {arr.shape}")
    if arr.dtype == bool:
        return arr
    if np.issubdtype(arr.dtype, np.integer) and np.isin(arr, (0, 1)).all():
        return arr.astype(bool)
    raise ValueError(f"{name} must hold binary outcomes (bool, or integers 0/1), got {arr.dtype}")


def _stratum_index(strata: object | None, q: int) -> np.ndarray:
    """An integer stratum id per query (all 0 without strata)."""
    if strata is None:
        return np.zeros(q, dtype=np.int64)
    labels = np.asarray(strata)
    if labels.shape != (q,):
        raise ValueError(f"strata must have shape ({q},) like a and b, got {labels.shape}")
    return np.unique(labels, return_inverse=True)[1].reshape(q)


def paired_bootstrap_interval(
    a: np.ndarray | Sequence[bool],
    b: np.ndarray | Sequence[bool],
    strata: np.ndarray | Sequence[object] | None = None,
    *,
    confidence: float = 0.95,
    resamples: int = DEFAULT_RESAMPLES,
    seed: int | np.random.Generator = 0,
) -> BootstrapInterval:
    """Paired bootstrap percentile interval of ``mean(a) - mean(b)`` (see the module doc).

    Args:
        a: (Q,) bool, the outcome of every query under variant A.
        b: (Q,) bool, the outcome of the same queries, in the same order, under variant B.
        strata: (Q,) labels (ints or strings); each stratum is resampled separately and keeps
            its size. ``None``: one stratum.
        confidence: the interval's coverage, in (0, 1).
        resamples: the number of bootstrap resamples (>= 1).
        seed: an int seed or a ``numpy.random.Generator``; the same int gives the same
            interval. (``None`` is refused: it would not be reproducible.)

    Returns:
        The observed difference, the interval ``[low, high]``, Q and the settings.

    Raises:
        ValueError: a or b not 1-D binary, different lengths, no queries, strata of another
            shape, confidence outside (0, 1), resamples < 1, or a seed that is not an int or a
            Generator.

    Example:
        >>> same = np.array([True, False, True])
        >>> r = paired_bootstrap_interval(same, same)
        >>> (r.difference, r.low, r.high)
        (0.0, 0.0, 0.0)
    """
    a, b = _binary(a, "a"), _binary(b, "b")
    if a.shape != b.shape:
        raise ValueError(f"a and b must pair the same queries, got {a.size} and {b.size} outcomes")
    q = a.size
    if q == 0:
        raise ValueError("a and b hold no queries")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    if isinstance(resamples, bool) or not isinstance(resamples, int | np.integer) or resamples < 1:
        raise ValueError(f"resamples must be a positive integer, got {resamples!r}")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer | np.random.Generator):
        raise ValueError(f"seed must be an int or a numpy Generator, got {seed!r}")
    rng = np.random.default_rng(seed)
    stratum = _stratum_index(strata, q)
    diff = a.astype(np.int64) - b.astype(np.int64)
    # counts[s, k]: queries of stratum s with difference +1 (k=0), 0 (k=1), -1 (k=2).
    counts = np.stack([np.bincount(stratum, diff == v) for v in (1, 0, -1)], axis=1)
    sizes = counts.sum(axis=1).astype(np.int64)
    draws = rng.multinomial(sizes, counts / sizes[:, None], size=(int(resamples), sizes.size))
    means = (draws[..., 0] - draws[..., 2]).sum(axis=1) / q
    alpha = 1.0 - confidence
    low, high = np.quantile(means, [alpha / 2, 1.0 - alpha / 2])
    return BootstrapInterval(
        difference=float(diff.sum() / q),
        low=float(low),
        high=float(high),
        queries=int(q),
        strata=int(sizes.size),
        confidence=float(confidence),
        resamples=int(resamples),
    )
