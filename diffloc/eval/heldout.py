"""Held-out seed statistics: per-seed values, mean, standard deviation and worst seed.

The pipeline is tuned on scene seed 0 and reported on other seeds (ARCHITECTURE, "Honest
evaluation"). For every variant (jobs grouped by their overrides, see
:mod:`diffloc.eval.sweeps`), query sequence and figure of :data:`FIGURES`, a row holds the
value of each seed, their mean, sample standard deviation (``ddof=1``; ``None`` with fewer than
two seeds) and the worst seed: the lowest value for recalls and precision, the highest for mATE
and time, and the *smallest* nearest-database-pose distance and angle (the seed whose queries
lie closest to database poses, i.e. the least held-out one).

A figure may be ``None`` for a seed (precision with nothing accepted, mATE with no verified
pose): the statistics are taken over the seeds where it is defined and ``n`` says how many.

Example:
    >>> s = seed_statistics({1: 0.9, 2: 0.7, 3: 0.8}, worst="min")
    >>> round(s.mean, 3), round(s.std, 3), s.worst_seed, s.worst
    (0.8, 0.1, 2, 0.7)
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from diffloc.eval.sweeps import Job, VariantJobs, nested_value
from diffloc.eval.tables import Column, markdown_table

__all__ = [
    "FIGURES",
    "Figure",
    "SeedStatistics",
    "heldout_markdown",
    "heldout_rows",
    "seed_statistics",
]


@dataclass(frozen=True)
class Figure:
    """One reported figure of a sequence entry of ``results.json``.

    Attributes:
        name: the row label, e.g. ``"recall@0.3m [%]"`` (with the display unit).
        path: the keys leading to the value in the sequence entry.
        worst: ``"min"`` if the lowest value is the worst, ``"max"`` if the highest.
        scale: display factor (100 for fractions -> percent, m -> cm).
        fmt: display format.
    """

    name: str
    path: tuple[str, ...]
    worst: Literal["min", "max"]
    scale: float = 1.0
    fmt: str = ".1f"

    def value(self, job: Job, sequence: str) -> float | None:
        """The figure of ``sequence`` in ``job`` (``None`` when the job stored null).

        Raises:
            ValueError: the key is missing or the value is not a number.
        """
        where = f"{job.folder / 'results.json'} sequence {sequence!r}"
        value = nested_value(job.entry(sequence), self.path, where)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{where}: {'.'.join(self.path)} is not a number: {value!r}")
        return float(value)

    def show(self, value: float | None) -> str:
        """The display text of a value (``"-"`` for None)."""
        return "-" if value is None else format(value * self.scale, self.fmt)


FIGURES: tuple[Figure, ...] = (
    Figure("recall@0.1m [%]", ("recall_at", "0.1"), "min", 100.0),
    Figure("recall@0.3m [%]", ("recall_at", "0.3"), "min", 100.0),
    Figure("recall@1.0m [%]", ("recall_at", "1.0"), "min", 100.0),
    Figure("precision@0.3m [%]", ("precision",), "min", 100.0),
    Figure("mATE [cm]", ("mATE_m",), "max", 100.0),
    Figure("median reloc [ms]", ("median_reloc_ms",), "max"),
    Figure(
        "nearest DB pose, median [m]", ("nearest_db_pose", "distance_median_m"), "min", 1, ".2f"
    ),
    Figure("nearest DB pose, median [deg]", ("nearest_db_pose", "angle_median_deg"), "min"),
)
"""The figures of a held-out table, in row order."""


@dataclass(frozen=True)
class SeedStatistics:
    """Statistics of one figure over seeds.

    Attributes:
        values: seed -> value (``None`` where undefined).
        n: the number of seeds with a value.
        mean: their mean (``None`` if n = 0).
        std: their sample standard deviation, ``ddof=1`` (``None`` if n < 2).
        worst_seed: the seed with the worst value (ties: the smallest seed; ``None`` if n = 0).
        worst: that value.
    """

    values: Mapping[int, float | None]
    n: int
    mean: float | None
    std: float | None
    worst_seed: int | None
    worst: float | None


def seed_statistics(
    values: Mapping[int, float | None], worst: Literal["min", "max"]
) -> SeedStatistics:
    """Mean, sample standard deviation and worst seed of per-seed values.

    Args:
        values: seed -> value; ``None`` values are left out of the statistics.
        worst: ``"min"``: the lowest value is the worst; ``"max"``: the highest.

    Returns:
        The statistics (module doc).

    Raises:
        ValueError: no seeds, an unknown ``worst``, or a non-finite value.
    """
    if not values:
        raise ValueError("seed_statistics needs at least one seed")
    if worst not in ("min", "max"):
        raise ValueError(f"worst must be 'min' or 'max', got {worst!r}")
    defined = {s: v for s, v in sorted(values.items()) if v is not None}
    if not all(math.isfinite(v) for v in defined.values()):
        raise ValueError(f"non-finite per-seed values: {dict(values)}")
    if not defined:
        return SeedStatistics(dict(values), 0, None, None, None, None)
    arr = np.array(list(defined.values()), dtype=np.float64)
    pick = np.argmin if worst == "min" else np.argmax  # first index on ties: smallest seed
    worst_seed = list(defined)[int(pick(arr))]
    return SeedStatistics(
        values=dict(values),
        n=arr.size,
        mean=float(arr.mean()),
        std=float(arr.std(ddof=1)) if arr.size > 1 else None,
        worst_seed=worst_seed,
        worst=defined[worst_seed],
    )


def _common_sequences(group: VariantJobs) -> tuple[str, ...]:
    """The sequences of a variant's jobs; they must agree across seeds."""
    first = group.jobs[0]
    for job in group.jobs[1:]:
        if set(job.sequences) != set(first.sequences):
            raise ValueError(
                f"variant {group.variant!r}: {job.folder} relocalised {sorted(job.sequences)} "
                f"but {first.folder} relocalised {sorted(first.sequences)}"
            )
    return first.sequences


def heldout_rows(
    groups: Sequence[VariantJobs], figures: Sequence[Figure] = FIGURES
) -> list[dict[str, object]]:
    """One row per (variant, sequence, figure) with per-seed values and their statistics.

    Args:
        groups: the jobs grouped by variant (:func:`~diffloc.eval.sweeps.group_variants`).
        figures: the figures to report.

    Returns:
        JSON-ready rows: ``variant``, ``sequence``, ``figure``, ``queries`` (per seed),
        ``values`` (seed -> value, seeds as strings), ``n``, ``mean``, ``std``,
        ``worst_seed``, ``worst`` (values in the units of ``results.json``: fractions,
        metres, milliseconds, degrees).

    Raises:
        ValueError: no groups or figures, jobs of one variant with different sequences, or a
            missing key (named with its file).
    """
    if not groups or not figures:
        raise ValueError("heldout_rows needs at least one variant and one figure")
    rows: list[dict[str, object]] = []
    for group in groups:
        for sequence in _common_sequences(group):
            queries = {
                str(j.seed): nested_value(j.entry(sequence), ("queries",), str(j.folder))
                for j in group.jobs
            }
            for figure in figures:
                stats = seed_statistics(
                    {j.seed: figure.value(j, sequence) for j in group.jobs}, figure.worst
                )
                rows.append(
                    {
                        "variant": group.variant,
                        "sequence": sequence,
                        "figure": figure.name,
                        "queries": queries,
                        "values": {str(s): v for s, v in stats.values.items()},
                        "n": stats.n,
                        "mean": stats.mean,
                        "std": stats.std,
                        "worst_seed": stats.worst_seed,
                        "worst": stats.worst,
                    }
                )
    return rows


def _display_row(row: Mapping[str, Any], figure: Figure, seeds: Sequence[int]) -> dict[str, str]:
    """One row of :func:`heldout_rows` as display texts."""
    worst = row["worst"]
    shown = {
        "variant": row["variant"] or "(defaults)",
        "sequence": row["sequence"],
        "figure": figure.name,
        "mean": figure.show(row["mean"]),
        "std": figure.show(row["std"]),
        "worst": "-" if worst is None else f"{figure.show(worst)} (seed {row['worst_seed']})",
    }
    shown.update({f"seed {s}": figure.show(row["values"].get(str(s))) for s in seeds})
    return shown


def heldout_markdown(rows: Sequence[Mapping[str, Any]], figures: Sequence[Figure] = FIGURES) -> str:
    """The rows of :func:`heldout_rows` as a Markdown table, values in display units.

    Columns: variant, sequence, figure, one column per seed (``-`` where a variant has no job
    on that seed or the value is undefined), mean, std and the worst value with its seed.

    Raises:
        ValueError: a row whose figure is not in ``figures``.
    """
    by_name = {f.name: f for f in figures}
    unknown = sorted({r["figure"] for r in rows} - set(by_name))
    if unknown:
        raise ValueError(f"unknown figures {unknown}; known: {sorted(by_name)}")
    seeds = sorted({int(s) for r in rows for s in r["values"]})
    shown = [_display_row(r, by_name[r["figure"]], seeds) for r in rows]
    columns = [Column(k, align="left") for k in ("variant", "sequence", "figure")]
    columns += [Column(f"seed {s}") for s in seeds]
    columns += [Column("mean"), Column("std"), Column("worst", "worst (seed)")]
    return markdown_table(shown, columns)
