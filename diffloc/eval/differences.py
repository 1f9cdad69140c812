"""Paired differences between two variants over held-out seeds, with bootstrap intervals.

A :class:`Comparison` names one override key and two of its values, the one claimed better
first (e.g. ``reloc.method.points=FN,F`` for "FN >= F", ``task.optimize=true,false`` for
"optimised > raw"). Jobs that set the key to either value are paired when everything else in
their variant (the *context*, e.g. ``retriever=bow`` or ``db.noise_sigma=0.2``) and the
scene seed agree; inside a pair, queries are paired by (sequence, query index), and their
timestamps must agree.

For every comparison and context, :func:`difference_rows` gives one row pooled over all
sequences (bootstrap strata: seed x sequence; only with several sequences) and one per sequence
(strata: seed), each with
the seeds, the number of paired queries Q, the difference of the per-query success rates
``better - worse`` (outcome ``correct``: accepted and within 0.3 m) and its paired bootstrap
interval (:func:`~diffloc.eval.bootstrap.paired_bootstrap_interval`). The ordering is said to
hold only where the whole interval is above zero.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from hydra.core.override_parser.overrides_parser import OverridesParser

from diffloc.eval.bootstrap import DEFAULT_RESAMPLES, paired_bootstrap_interval
from diffloc.eval.sweeps import Job, VariantJobs, group_variants
from diffloc.eval.tables import Column, markdown_table

__all__ = ["Comparison", "difference_markdown", "difference_rows", "paired_outcomes"]

ALL_SEQUENCES = "all"
"""The ``sequence`` of the row pooled over every sequence."""


@dataclass(frozen=True)
class Comparison:
    """Two values of one override key, the one claimed better first.

    Attributes:
        key: the override key, e.g. ``"reloc.method.points"``.
        better: the value claimed better (e.g. ``"FN"``), as Hydra parses it.
        worse: the value claimed worse (e.g. ``"F"``).
    """

    key: str
    better: object
    worse: object

    @classmethod
    def parse(cls, text: str) -> Comparison:
        """From ``"KEY=BETTER,WORSE"``, e.g. ``"task.optimize=true,false"``.

        Raises:
            ValueError: not of that form (no key, not two values), or the two values are equal.
        """
        try:
            (override,) = OverridesParser.create().parse_overrides([text])
            values = list(override.sweep_iterator()) if override.is_sweep_override() else []
        except Exception as exc:  # Hydra's OverrideParseException
            raise ValueError(f"comparison {text!r}: {exc}") from exc
        if not override.key_or_group or len(values) != 2 or values[0] == values[1]:
            raise ValueError(f"comparison {text!r} must read KEY=BETTER,WORSE (two values)")
        return cls(override.key_or_group, values[0], values[1])

    @property
    def label(self) -> str:
        """E.g. ``"reloc.method.points: FN - F"``."""
        return f"{self.key}: {self.better} - {self.worse}"


def _context(group: VariantJobs, key: str) -> str:
    """The variant's overrides other than ``key`` (sorted text; ``""`` for none)."""
    items = sorted((k, v) for k, v in group.settings.items() if k != key)
    return " ".join(f"{k}={v}" for k, v in items)


def _pairs(
    groups: Sequence[VariantJobs], comparison: Comparison
) -> list[tuple[str, VariantJobs, VariantJobs]]:
    """``(context, better, worse)`` variant pairs of a comparison.

    Raises:
        ValueError: no variant sets one of the values, or a context with only one side.
    """
    sides: dict[str, dict[str, VariantJobs]] = {"better": {}, "worse": {}}
    for group in groups:
        job = group.jobs[0]
        for side in sides:
            if job.setting_equals(comparison.key, getattr(comparison, side)):
                sides[side][_context(group, comparison.key)] = group
    for side, found in sides.items():
        if not found:
            raise ValueError(
                f"comparison {comparison.label!r}: no job sets "
                f"{comparison.key}={getattr(comparison, side)}"
            )
    lonely = set(sides["better"]) ^ set(sides["worse"])
    if lonely:
        raise ValueError(
            f"comparison {comparison.label!r}: contexts with only one side: {sorted(lonely)}"
        )
    return [(c, sides["better"][c], sides["worse"][c]) for c in sorted(sides["better"])]


def paired_outcomes(
    better: VariantJobs, worse: VariantJobs, sequences: Sequence[str], key: str = "correct"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-query outcomes of two variants, paired by (seed, sequence, query index).

    Args:
        better: the jobs of the variant claimed better.
        worse: the jobs of the other variant.
        sequences: the sequences to pool.
        key: the per-query bool field of ``queries.json``.

    Returns:
        ``a`` (Q,) bool, ``b`` (Q,) bool and ``strata`` (Q,) str labels ``"<seed>/<sequence>"``.

    Raises:
        ValueError: the variants ran on different seeds, or a sequence whose query count or
            timestamps differ between the two (not the same queries).
    """
    if better.seeds != worse.seeds:
        raise ValueError(
            f"{better.variant!r} ran on seeds {better.seeds} but {worse.variant!r} on "
            f"{worse.seeds}: cannot pair"
        )
    a, b, strata = [], [], []
    for job_a, job_b in zip(better.jobs, worse.jobs, strict=True):
        for sequence in sequences:
            t_a, out_a = job_a.query_outcomes(sequence, key)
            t_b, out_b = job_b.query_outcomes(sequence, key)
            if t_a.shape != t_b.shape or not np.allclose(t_a, t_b, rtol=0.0, atol=1e-6):
                raise ValueError(
                    f"{_where(job_a, sequence)} and {_where(job_b, sequence)} do not hold the "
                    f"same queries ({t_a.size} and {t_b.size}, or other timestamps)"
                )
            a.append(out_a)
            b.append(out_b)
            strata.append(np.full(out_a.size, f"{job_a.seed}/{sequence}"))
    return np.concatenate(a), np.concatenate(b), np.concatenate(strata)


def _where(job: Job, sequence: str) -> Path:
    return job.folder / sequence / "queries.json"


def _verdict(low: float, high: float) -> str:
    if low > 0.0:
        return "yes"
    return "no (reversed)" if high < 0.0 else "no (interval holds 0)"


def difference_rows(
    jobs: Sequence[Job],
    comparisons: Sequence[Comparison],
    *,
    confidence: float = 0.95,
    resamples: int = DEFAULT_RESAMPLES,
    seed: int = 0,
) -> list[dict[str, object]]:
    """Paired differences ``better - worse`` of the success rate, with bootstrap intervals.

    Args:
        jobs: the finished jobs (every variant on every seed), e.g. from
            :func:`~diffloc.eval.sweeps.load_jobs`.
        comparisons: the claimed orderings.
        confidence: the interval's coverage.
        resamples: bootstrap resamples per row.
        seed: the bootstrap seed (the same for every row, so a row does not depend on which
            other rows are computed).

    Returns:
        JSON-ready rows (module doc): ``comparison``, ``context``, ``sequence``, ``seeds``,
        ``queries``, ``difference``, ``low``, ``high``, ``confidence``, ``resamples``,
        ``ordering_holds`` (``"yes"``, ``"no (interval holds 0)"`` or ``"no (reversed)"``).

    Raises:
        ValueError: no comparisons, unpairable variants or queries (see :func:`_pairs`,
            :func:`paired_outcomes`), or a missing per-query ``correct``.
    """
    if not comparisons:
        raise ValueError("difference_rows needs at least one comparison")
    groups = group_variants(jobs)
    rows: list[dict[str, object]] = []
    for comparison in comparisons:
        for context, better, worse in _pairs(groups, comparison):
            sequences = _shared_sequences(better, worse)
            pooled = [(s, [s]) for s in sequences]
            if len(sequences) > 1:
                pooled.insert(0, (ALL_SEQUENCES, list(sequences)))
            for name, members in pooled:
                a, b, strata = paired_outcomes(better, worse, members)
                interval = paired_bootstrap_interval(
                    a, b, strata, confidence=confidence, resamples=resamples, seed=seed
                )
                rows.append(
                    {
                        "comparison": comparison.label,
                        "context": context,
                        "sequence": name,
                        "seeds": list(better.seeds),
                        **interval.to_dict(),
                        "ordering_holds": _verdict(interval.low, interval.high),
                    }
                )
    return rows


def _shared_sequences(better: VariantJobs, worse: VariantJobs) -> tuple[str, ...]:
    """The sequences every job of both variants relocalised (in the first job's order)."""
    first = better.jobs[0].sequences
    for job in (*better.jobs, *worse.jobs):
        if set(job.sequences) != set(first):
            raise ValueError(
                f"{job.folder} relocalised {sorted(job.sequences)}, "
                f"{better.jobs[0].folder} {sorted(first)}: cannot pair"
            )
    return first


def difference_markdown(rows: Sequence[Mapping[str, Any]]) -> str:
    """The rows of :func:`difference_rows` as a Markdown table (differences in points, pp)."""
    shown = [
        {
            **r,
            "context": r["context"] or "(defaults)",
            "seeds": ",".join(str(s) for s in r["seeds"]),
            "interval": f"[{100 * r['low']:+.1f}, {100 * r['high']:+.1f}]",
        }
        for r in rows
    ]
    level = f"{100 * rows[0]['confidence']:g} %" if rows else "95 %"
    return markdown_table(
        shown,
        [
            Column("comparison", align="left"),
            Column("context", align="left"),
            Column("sequence", align="left"),
            Column("seeds", align="left"),
            Column("queries", "Q"),
            Column("difference", "difference [pp]", "+.1f", scale=100),
            Column("interval", f"{level} interval [pp]"),
            Column("ordering_holds", "ordering holds", align="left"),
        ],
    )
