"""Scoring and outputs of ``diffloc task=crossmodal``: metrics, tables, TUM files and plots.

The only place the task reads the query sequences' ground-truth poses. Per sequence:

- queries, found (a PnP pose), accepted (found and validated: the answer) and the precision
  of the accepted poses (within the loose bound ``loose_m`` / 30 deg), the wrong accepted
  ones, and how many accepted (and wrong accepted) poses took their reference from the pose
  prior (``task.localizer.prior``; 0 without it);
- localisation rates (shares of all queries accepted within the bound) at 0.25 m / 2 deg,
  0.5 m / 5 deg and ``loose_m`` / 30 deg (seed 2: 1 m indoors, 2 m outdoors);
- retrieval rate: the top-1 retrieved render lies within the render spacing and 45 deg of
  the query (seed 2);
- how near the database comes to the queries whatever its spacing (:func:`nearest_renders`):
  the share of queries with a render within the loose bound (``loose_m`` / 30 deg, so a
  render that is itself a right answer), the median distance to the nearest render and the
  median angle to the best-aligned render within ``loose_m``;
- mATE of the accepted queries and the median wall time per query;
- where the time goes (:func:`time_breakdown`): median wall and CPU ms per query, candidates
  matched, mean CPU ms per stage (:data:`~diffloc.reloc.stage_clock.STAGES`) and the median
  CPU ms of one LighterGlue match.

With ``task.refine.enabled`` (:func:`score_refinement`): the same rates before and after the
refinement of the accepted poses, median and p90 translation and rotation errors of the
localised queries before and after, the share of refined poses kept, those kept that ended
farther from the true position than they started, and the median CPU and wall ms per refined
query.

Files in the run folder: ``results.md`` and ``results.json`` (the same figures),
``trajectory_<sequence>.tum`` (the accepted poses, for ``evo_ape tum``;
``trajectory_<sequence>_refined.tum``: the same after the refinement),
``retrieved_<sequence>.png`` (queries beside the render their pose came from) and
``trajectory_<sequence>.png`` (top-down).

Example:
    >>> rates = localization_rates(np.array([0.1, 0.3, np.nan]), np.array([1.0, 1.0, np.nan]),
    ...                            np.array([True, True, False]), 1.0)
    >>> [round(v, 3) for v in rates.values()]
    [0.333, 0.667, 0.667]
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from diffloc.eval.metrics import PoseErrors, is_correct, mean_ate, pose_errors
from diffloc.eval.plots import plot_trajectory_topdown
from diffloc.features.retrieval_eval import pairwise_pose_distances
from diffloc.io.images import write_rgb
from diffloc.io.sequence import SequenceData
from diffloc.pipeline.crossmodal_refine import SequenceRefinement
from diffloc.pipeline.crossmodal_stage import SequenceLocalization, scaled_images
from diffloc.reloc.stage_clock import STAGES

__all__ = [
    "RETRIEVAL_ANGLE_DEG",
    "localization_rates",
    "markdown_table",
    "nearest_renders",
    "plot_retrieved",
    "refinement_table",
    "retrieval_hits",
    "score_refinement",
    "score_sequence",
    "thresholds",
    "time_breakdown",
    "time_table",
]

RETRIEVAL_ANGLE_DEG = 45.0
"""A retrieved render within the render spacing and this angle of the query is a hit."""


def thresholds(loose_m: float) -> tuple[tuple[float, float], ...]:
    """(metres, degrees) criteria: 0.25 m / 2 deg, 0.5 m / 5 deg, ``loose_m`` / 30 deg."""
    return ((0.25, 2.0), (0.5, 5.0), (loose_m, 30.0))


def _label(metres: float, degrees: float) -> str:
    return f"{metres:g}m_{degrees:g}deg"


def localization_rates(
    translation_m: np.ndarray, rotation_deg: np.ndarray, accepted: np.ndarray, loose_m: float
) -> dict[str, float]:
    """Share of all Q queries accepted within each of :func:`thresholds` (failures count).

    Args:
        translation_m: (Q,) errors in metres (any value where not accepted).
        rotation_deg: (Q,) errors in degrees.
        accepted: (Q,) bool.
        loose_m: the loose bound in metres.
    """
    errors = PoseErrors(translation_m, rotation_deg, accepted)
    return {_label(m, d): float(is_correct(errors, m, d).mean()) for m, d in thresholds(loose_m)}


def retrieval_hits(
    T_query: torch.Tensor, T_retrieved: torch.Tensor, retrieved: np.ndarray, spacing_m: float
) -> np.ndarray:
    """(Q,) bool: the retrieved render lies within ``spacing_m`` and 45 deg of the query.

    Args:
        T_query: (Q, 4, 4) true query poses.
        T_retrieved: (Q, 4, 4) poses of the retrieved renders (any pose where none).
        retrieved: (Q,) bool, a render was retrieved.
        spacing_m: the render spacing.
    """
    distance, angle = pairwise_pose_distances(T_query, T_retrieved)
    return (
        retrieved
        & (distance.diagonal().numpy() <= spacing_m)
        & (np.degrees(angle.diagonal().numpy()) <= RETRIEVAL_ANGLE_DEG)
    )


def nearest_renders(T_query: torch.Tensor, T_render: torch.Tensor, loose_m: float) -> dict:
    """How near the database's renders come to the queries (module docstring).

    Args:
        T_query: (Q, 4, 4) true query poses.
        T_render: (M, 4, 4) render poses of the database.
        loose_m: the loose bound in metres (with 30 deg).

    Returns:
        ``render_near_rate``: share of queries with a render within ``loose_m`` and 30 deg;
        ``median_m``: median over the queries of the distance to the nearest render centre;
        ``median_deg``: median over the queries of the smallest rotation angle to a render
        within ``loose_m`` (180 where there is none).

    Example:
        >>> T_render = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
        >>> T_render[1, 0, 3] = 3.0
        >>> T_query = torch.eye(4, dtype=torch.float64)[None].clone()
        >>> T_query[0, 0, 3] = 2.5
        >>> nearest_renders(T_query, T_render, 1.0)
        {'render_near_rate': 1.0, 'median_m': 0.5, 'median_deg': 0.0}
    """
    distance, angle = pairwise_pose_distances(T_query, T_render)
    degrees = torch.rad2deg(angle)
    within = distance <= loose_m
    best = torch.where(within, degrees, torch.full_like(degrees, 180.0)).amin(dim=1)
    return {
        "render_near_rate": float((within & (degrees <= 30.0)).any(dim=1).double().mean()),
        "median_m": float(np.median(distance.amin(dim=1).numpy())),
        "median_deg": float(np.median(best.numpy())),
    }


def _finite(x: float) -> float | None:
    return None if math.isnan(x) else x


def score_sequence(
    loc: SequenceLocalization,
    T_gt: torch.Tensor,
    T_render: torch.Tensor,
    spacing_m: float,
    loose_m: float,
) -> dict:
    """The figures of one sequence (module docstring).

    Args:
        loc: the localiser's answers.
        T_gt: (Q, 4, 4) true poses of the localised frames.
        T_render: (M, 4, 4) render poses of the database.
        spacing_m: the render spacing.
        loose_m: the loose bound.
    """
    accepted = loc.accepted.astype(bool)
    errors = pose_errors(loc.T_wc, T_gt.numpy(), accepted)
    top = torch.from_numpy(loc.top1)
    hits = retrieval_hits(T_gt, T_render[top.clamp_min(0)], loc.top1 >= 0, spacing_m)
    correct = is_correct(errors, loose_m, 30.0)
    count = int(accepted.sum())
    from_prior = accepted & loc.from_prior.astype(bool)
    return {
        "queries": len(loc.frames),
        "found": int(loc.success.sum()),
        "accepted": count,
        "precision": correct.sum() / count if count else None,
        "wrong_accepted": count - int(correct.sum()),
        "accepted_from_prior": int(from_prior.sum()),
        "wrong_from_prior": int((from_prior & ~correct).sum()),
        "rates": localization_rates(errors.translation_m, errors.rotation_deg, accepted, loose_m),
        "retrieval_rate": float(hits.mean()),
        "nearest_render": nearest_renders(T_gt, T_render, loose_m),
        "mate_m": _finite(mean_ate(errors)),
        "median_ms_per_query": float(np.median(loc.time_ms)),
        "time": time_breakdown(loc),
    }


def _spread(values: np.ndarray) -> dict[str, float | None]:
    """Median and p90 of ``values`` (``None`` for none)."""
    if not len(values):
        return {"median": None, "p90": None}
    return {"median": float(np.median(values)), "p90": float(np.percentile(values, 90))}


def score_refinement(
    loc: SequenceLocalization, refinement: SequenceRefinement, T_gt: torch.Tensor, loose_m: float
) -> dict:
    """The refinement's figures of one sequence (module docstring).

    Args:
        loc: the localiser's answers (Q queries).
        refinement: the refinement of its accepted ones.
        T_gt: (Q, 4, 4) true poses of the localised frames.
        loose_m: the loose bound.

    Returns:
        ``rates_before`` / ``rates_after`` (:func:`localization_rates`), ``before`` /
        ``after``: median and p90 of ``translation_m`` and ``rotation_deg`` over the accepted
        queries, ``localised``, ``refined`` (served by the map), ``kept`` and its share of the
        refined, ``wrong_kept`` (kept, ending farther from the true position than it started),
        ``closer`` (refined queries whose refinement ended nearer the true position than it
        started, kept or not), ``all_kept``: median and p90 errors of the refined queries had
        every refined pose been kept (what the acceptance rule chose from),
        ``median_cpu_ms`` / ``median_wall_ms`` per refined query (``None`` for none).

    Example:
        >>> from types import SimpleNamespace
        >>> T_gt = torch.eye(4, dtype=torch.float64)[None].repeat(2, 1, 1)
        >>> start = np.tile(np.eye(4), (2, 1, 1)); start[:, 0, 3] = [0.1, 0.3]
        >>> after = start.copy(); after[0, 0, 3] = 0.02
        >>> loc = SimpleNamespace(T_wc=start, accepted=np.array([True, True]))
        >>> one = lambda *v: np.array(v)
        >>> ref = SimpleNamespace(query=one(0, 1), T_wc_start=start, T_wc_refined=after,
        ...     T_wc=after, kept=one(True, False), served=one(0, 0), cpu_ms=one(10.0, 30.0),
        ...     wall_ms=one(20.0, 40.0), answers=lambda loc: after)
        >>> s = score_refinement(loc, ref, T_gt, 1.0)
        >>> s["kept"], s["wrong_kept"], round(s["after"]["translation_m"]["median"], 2)
        (1, 0, 0.16)
        >>> s["closer"], round(s["all_kept"]["translation_m"]["median"], 2)
        (1, 0.16)
        >>> s["rates_before"]["0.25m_2deg"], s["rates_after"]["0.25m_2deg"]
        (0.5, 0.5)
    """
    accepted = loc.accepted.astype(bool)
    before = pose_errors(loc.T_wc, T_gt.numpy(), accepted)
    after = pose_errors(refinement.answers(loc), T_gt.numpy(), accepted)
    gt = T_gt.numpy()[refinement.query]
    moved = np.linalg.norm(refinement.T_wc_refined[:, :3, 3] - gt[:, :3, 3], axis=-1)
    started = np.linalg.norm(refinement.T_wc_start[:, :3, 3] - gt[:, :3, 3], axis=-1)
    refined = refinement.served >= 0
    kept = refinement.kept.astype(bool)

    def spread(errors: PoseErrors, rows: np.ndarray = accepted) -> dict:
        return {
            "translation_m": _spread(errors.translation_m[rows]),
            "rotation_deg": _spread(errors.rotation_deg[rows]),
        }

    moves = pose_errors(refinement.T_wc_refined[refined], gt[refined], np.ones(refined.sum(), bool))

    def median(values: np.ndarray) -> float | None:
        return float(np.median(values)) if len(values) else None

    return {
        "rates_before": localization_rates(
            before.translation_m, before.rotation_deg, accepted, loose_m
        ),
        "rates_after": localization_rates(
            after.translation_m, after.rotation_deg, accepted, loose_m
        ),
        "before": spread(before),
        "after": spread(after),
        "localised": int(accepted.sum()),
        "refined": int(refined.sum()),
        "kept": int(kept.sum()),
        "kept_share": float(kept.sum() / refined.sum()) if refined.any() else None,
        "wrong_kept": int((kept & (moved > started)).sum()),
        "closer": int((refined & (moved < started)).sum()),
        "all_kept": spread(moves, np.ones(len(moves.translation_m), bool)),
        "median_cpu_ms": median(refinement.cpu_ms[refined]),
        "median_wall_ms": median(refinement.wall_ms[refined]),
    }


def refinement_table(rows: dict[str, dict], loose_m: float) -> str:
    """Markdown: per sequence the :func:`score_refinement` figures in ``rows[name]["refine"]``,
    "before -> after"."""
    head = ["sequence", "refined", "kept (wrong)", "ended closer"]
    head += [f"{m:g} m / {d:g} deg" for m, d in thresholds(loose_m)]
    head += ["t median", "t p90", "r median", "r p90", "t median / p90 had all been kept"]
    head += ["CPU ms / query"]

    def cm(x: float | None) -> str:
        return "-" if x is None else f"{100 * x:.2f} cm"

    def deg(x: float | None) -> str:
        return "-" if x is None else f"{x:.3f} deg"

    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, r in rows.items():
        f = r["refine"]
        t = [f[when]["translation_m"] for when in ("before", "after")]
        a = [f[when]["rotation_deg"] for when in ("before", "after")]
        cells = [
            name,
            f"{f['refined']} of {f['localised']}",
            f"{f['kept']} ({f['wrong_kept']})",
            str(f["closer"]),
            *[
                f"{100 * f['rates_before'][k]:.1f} -> {100 * f['rates_after'][k]:.1f} %"
                for k in f["rates_before"]
            ],
            f"{cm(t[0]['median'])} -> {cm(t[1]['median'])}",
            f"{cm(t[0]['p90'])} -> {cm(t[1]['p90'])}",
            f"{deg(a[0]['median'])} -> {deg(a[1]['median'])}",
            f"{deg(a[0]['p90'])} -> {deg(a[1]['p90'])}",
            f"{cm(f['all_kept']['translation_m']['median'])} / "
            f"{cm(f['all_kept']['translation_m']['p90'])}",
            "-" if f["median_cpu_ms"] is None else f"{f['median_cpu_ms']:.0f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def time_breakdown(loc: SequenceLocalization) -> dict:
    """Where the time of the queries went.

    Returns:
        ``median_ms`` / ``median_cpu_ms`` (wall / process CPU per query), ``mean_ms`` /
        ``mean_cpu_ms``, ``candidates`` (median and mean references matched per query),
        ``stages``: per stage of :data:`~diffloc.reloc.stage_clock.STAGES` the mean wall and
        CPU ms per query (means, so that they add up to the mean per query but for
        bookkeeping), ``match_cpu_ms`` / ``match_ms``: median CPU / wall ms of one LighterGlue
        match, ``pnp_ms``: median wall ms of one lifting + PnP (``None`` for these three when
        nothing was matched).
    """
    per_query = np.bincount(loc.candidate_query, minlength=len(loc.frames))
    matched = len(loc.candidate_match_ms) > 0
    return {
        "median_ms": float(np.median(loc.time_ms)),
        "median_cpu_ms": float(np.median(loc.cpu_ms)),
        "mean_ms": float(np.mean(loc.time_ms)),
        "mean_cpu_ms": float(np.mean(loc.cpu_ms)),
        "candidates": {"median": float(np.median(per_query)), "mean": float(per_query.mean())},
        "stages": {
            name: {
                "mean_ms": float(loc.stage_ms[:, i].mean()),
                "mean_cpu_ms": float(loc.stage_cpu_ms[:, i].mean()),
            }
            for i, name in enumerate(STAGES)
        },
        "match_ms": float(np.median(loc.candidate_match_ms)) if matched else None,
        "match_cpu_ms": float(np.median(loc.candidate_match_cpu_ms)) if matched else None,
        "pnp_ms": float(np.median(loc.candidate_pnp_ms)) if matched else None,
    }


def time_table(rows: dict[str, dict]) -> str:
    """Markdown: per sequence the :func:`time_breakdown` in ``rows[name]["time"]``."""
    head = ["sequence", "median wall ms", "median CPU ms", "candidates (median / mean)"]
    head += [f"{name} CPU ms" for name in STAGES] + ["CPU ms per match"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, r in rows.items():
        t = r["time"]
        match = t["match_cpu_ms"]
        cells = [
            name,
            f"{t['median_ms']:.0f}",
            f"{t['median_cpu_ms']:.0f}",
            f"{t['candidates']['median']:g} / {t['candidates']['mean']:.1f}",
            *[f"{t['stages'][stage]['mean_cpu_ms']:.0f}" for stage in STAGES],
            "-" if match is None else f"{match:.0f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def markdown_table(rows: dict[str, dict], loose_m: float) -> str:
    """The per-sequence table of :func:`score_sequence` results (Markdown)."""
    head = ["sequence", "queries", "accepted", "precision", "from prior (wrong)"]
    head += [f"{m:g} m / {d:g} deg" for m, d in thresholds(loose_m)]
    head += ["retrieval", "mATE [m]", "ms/query"]

    def pct(x: float | None) -> str:
        return "-" if x is None else f"{100 * x:.1f} %"

    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, r in rows.items():
        cells = [
            name,
            str(r["queries"]),
            f"{r['accepted']} ({pct(r['accepted'] / r['queries'])})",
            pct(r["precision"]),
            f"{r['accepted_from_prior']} ({r['wrong_from_prior']})",
            *[pct(v) for v in r["rates"].values()],
            pct(r["retrieval_rate"]),
            "-" if r["mate_m"] is None else f"{r['mate_m']:.3f}",
            f"{r['median_ms_per_query']:.0f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot_retrieved(
    path: str | os.PathLike,
    loc: SequenceLocalization,
    seq: SequenceData,
    renders: torch.Tensor,
    count: int,
) -> Path:
    """Write ``count`` evenly spread queries (left) beside the render their pose came from,
    or their top-1 render when no pose was found (right), one row each.

    Args:
        path: the PNG.
        loc: the answers.
        seq: the query sequence (images).
        renders: (M, 3, h, w) database images; queries are resized to their size.
        count: rows (at most the number of queries).
    """
    picks = np.unique(np.linspace(0, len(loc.frames) - 1, min(count, len(loc.frames))).round())
    rows = []
    for q in picks.astype(int).tolist():
        camera = seq.camera.scaled(renders.shape[-1] / seq.camera.width)
        query = scaled_images(seq, camera, [int(loc.frames[q])])[0]
        chosen = int(loc.reference[q]) if loc.reference[q] >= 0 else int(loc.top1[q])
        render = renders[chosen] if chosen >= 0 else torch.zeros_like(query)
        rows.append(torch.cat([query, render], dim=2))
    write_rgb(path, torch.cat(rows, dim=1))
    return Path(path)


def plot_trajectory(
    path: str | os.PathLike, loc: SequenceLocalization, T_gt: torch.Tensor, title: str
) -> Path:
    """Top-down: the true trajectory and the accepted / rejected estimates."""
    estimates = np.where(loc.success[:, None, None], loc.T_wc, np.nan)
    return plot_trajectory_topdown(T_gt, estimates, loc.accepted.astype(bool), path, title=title)
