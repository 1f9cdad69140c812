"""Where the localisation rate of ``diffloc task=crossmodal`` is lost, query by query.

Reads the cached ``localize_<sequence>`` stage of each ``--map`` (``localization.npz`` under
``<dataset>/crossmodal/<map>/``: per query the top-1 retrieved render, the reference the pose
came from, LighterGlue matches, points with depth, PnP inliers, the photometric consistency
and the validation's verdicts) and the query ground truth (scoring only), and gives each query
ONE outcome, the first stage that decides it:

- ``localized``: accepted, within ``--loose-m`` / 30 deg;
- ``wrong accepted``: accepted, outside it;
- ``no pose``: no reference gave a PnP pose with enough inliers;
- ``right pose rejected: inliers`` / ``...: coverage or rival`` / ``...: photometric``: a pose
  within the bound that the validation refused, by the first test it failed (fewer than
  ``theta_in`` inliers; the coverage or ambiguity tests; the photometric consistency);
- ``wrong pose, no render near``: a wrong pose (rejected) and no database image at all lies
  within the render spacing and 45 deg of the query: the render poses do not cover it;
- ``wrong pose, far reference``: a wrong pose (rejected) from a reference that is not within
  them although one is: retrieval (and re-ranking) failed;
- ``wrong pose, near reference``: a wrong pose (rejected) from a reference within them:
  matching or PnP failed on the right render.

With the pose prior on (``task.localizer.prior``), each row says whether the reference came
from the prior (``from_prior``), and per map and sequence the report counts the accepted and
the wrong accepted poses whose reference came from it.

``--min-photometric`` replays another threshold from the recorded scores
(``accepted_without_photometric`` and ``photometric >= t``); by default the run's own verdict.
Per map and sequence the report also gives the photometric test's effect: accepted poses,
wrong accepted poses, precision and localisation rate without it (``accepted_without_photometric``)
and with it, and per map the threshold rule of ``task.min_photometric``: the 1st percentile of
the scores of the right poses the other tests accept, over the given sequences, rounded down
to 0.1.

Usage:
    PYTHONPATH=. python3 experiments/crossmodal_breakdown.py --dataset data/indoor_seed0 \\
        --map tls --map mesh --sequence query_same \\
        --command "bash experiments/run_tables.sh crossmodal_tables data/indoor_seed0" \\
        --out experiments/results/crossmodal_breakdown_indoor_seed0
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from diffloc.crossmodal.database import RenderedDatabase
from diffloc.eval.metrics import is_correct, pose_errors
from diffloc.eval.report_files import write_report
from diffloc.features.retrieval_eval import pairwise_pose_distances
from diffloc.io.dataset import read_sequence
from diffloc.pipeline.crossmodal_report import RETRIEVAL_ANGLE_DEG, retrieval_hits
from diffloc.pipeline.crossmodal_stage import SequenceLocalization, crossmodal_folder
from diffloc.reloc.rendered import THETA_IN

OUTCOMES = (
    "localized",
    "wrong accepted",
    "no pose",
    "right pose rejected: inliers",
    "right pose rejected: coverage or rival",
    "right pose rejected: photometric",
    "wrong pose, no render near",
    "wrong pose, far reference",
    "wrong pose, near reference",
)


def outcomes(
    loc: SequenceLocalization,
    accepted: np.ndarray,
    correct: np.ndarray,
    reference_hit: np.ndarray,
    near_renders: np.ndarray,
    theta_in: int,
) -> list[str]:
    """The outcome (:data:`OUTCOMES`) of each of the Q queries (module docstring).

    Args:
        loc: the localiser's answers.
        accepted: (Q,) bool, the verdict (the run's or a replayed threshold's).
        correct: (Q,) bool, the pose found is within the bound.
        reference_hit: (Q,) bool, the reference of the pose lies within the render spacing
            and 45 deg of the query.
        near_renders: (Q,) int, database images within them.
        theta_in: the validation's fewest inliers.
    """
    result = []
    for q in range(len(loc.frames)):
        if accepted[q]:
            result.append("localized" if correct[q] else "wrong accepted")
        elif not loc.success[q]:
            result.append("no pose")
        elif correct[q] and loc.num_inliers[q] < theta_in:
            result.append("right pose rejected: inliers")
        elif correct[q] and not loc.accepted_without_photometric[q]:
            result.append("right pose rejected: coverage or rival")
        elif correct[q]:
            result.append("right pose rejected: photometric")
        elif reference_hit[q]:
            result.append("wrong pose, near reference")
        else:
            far = "far reference" if near_renders[q] else "no render near"
            result.append(f"wrong pose, {far}")
    return result


def breakdown(
    dataset: Path,
    option: str,
    sequence: str,
    spacing_m: float,
    loose_m: float,
    theta_in: int,
    min_photometric: float | None,
) -> dict:
    """Per-query rows and outcome counts of one map's localisation of ``sequence``."""
    folder = crossmodal_folder(dataset) / option
    path = folder / f"localize_{sequence}" / "localization.npz"
    if not path.is_file():
        raise SystemExit(
            f"{path} is missing: run diffloc task=crossmodal map={option} dataset={dataset} "
            f"task.sequences=[{sequence}] first"
        )
    loc = SequenceLocalization.load(path)
    T_render = RenderedDatabase.load(folder / "database" / "rgbd").T_wc
    T_gt = read_sequence(dataset, sequence).T_wc[loc.frames]  # ground truth: scoring only
    accepted = loc.accepted.astype(bool)
    if min_photometric is not None:
        accepted = loc.accepted_without_photometric.astype(bool) & (
            loc.photometric >= min_photometric
        )
    found = loc.success.astype(bool)
    errors = pose_errors(loc.T_wc, T_gt.numpy(), found)
    correct = is_correct(errors, loose_m, 30.0)

    def hits(index: np.ndarray) -> np.ndarray:
        chosen = torch.from_numpy(index).clamp_min(0)
        return retrieval_hits(T_gt, T_render[chosen], index >= 0, spacing_m)

    top1_hit, reference_hit = hits(loc.top1), hits(loc.reference)
    distance, angle = pairwise_pose_distances(T_gt, T_render)
    near = (distance <= spacing_m) & (angle <= np.radians(RETRIEVAL_ANGLE_DEG))
    near_renders = near.sum(1).numpy()
    verdicts = outcomes(loc, accepted, correct, reference_hit, near_renders, theta_in)
    geometric = loc.accepted_without_photometric.astype(bool)
    rows = [
        {
            "frame": int(loc.frames[q]),
            "near_renders": int(near_renders[q]),
            "top1_hit": bool(top1_hit[q]),
            "reference_hit": bool(reference_hit[q]),
            "matches": int(loc.num_matches[q]),
            "points": int(loc.num_points[q]),
            "inliers": int(loc.num_inliers[q]),
            "pnp": bool(found[q]),
            "photometric": None if np.isnan(loc.photometric[q]) else float(loc.photometric[q]),
            "error_m": float(errors.translation_m[q]) if found[q] else None,
            "error_deg": float(errors.rotation_deg[q]) if found[q] else None,
            "accepted": bool(accepted[q]),
            "from_prior": bool(loc.from_prior[q]),
            "outcome": verdicts[q],
        }
        for q in range(len(loc.frames))
    ]
    counts = Counter(verdicts)
    from_prior = accepted & loc.from_prior.astype(bool)
    return {
        "map": option,
        "sequence": sequence,
        "queries": len(rows),
        "photometric": {
            "without": _effect(geometric, correct),
            "with": _effect(accepted, correct),
            "right_scores": loc.photometric[geometric & correct].tolist(),
        },
        "accepted_from_prior": int(from_prior.sum()),
        "wrong_from_prior": int((from_prior & ~correct).sum()),
        "queries_with_prior": int((loc.prior_images > 0).sum()),
        "median_ms": float(np.median(loc.time_ms)),
        "load_average": json.loads((path.parent / "localize.json").read_text())["load_average"],
        "top1_retrieval_rate": float(top1_hit.mean()),
        "reference_hit_rate": float(reference_hit.mean()),
        "counts": {name: counts.get(name, 0) for name in OUTCOMES},
        "rows": rows,
    }


def _effect(accepted: np.ndarray, correct: np.ndarray) -> dict:
    """Accepted and wrong accepted poses, precision and localisation rate of a verdict."""
    count, right = int(accepted.sum()), int((accepted & correct).sum())
    return {
        "accepted": count,
        "wrong": count - right,
        "precision": right / count if count else None,
        "rate": right / len(accepted),
    }


def threshold_rule(scores: list[float]) -> float | None:
    """The 1st percentile of right poses' photometric scores, rounded down to 0.1 (``None``
    without scores)."""
    values = np.asarray(scores, dtype=np.float64)
    values = values[~np.isnan(values)]
    if not len(values):
        return None
    return float(np.floor(np.percentile(values, 1) * 10) / 10)


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f}"


def _cell(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.2f}"
    return str(value)


def _label(entry: dict) -> str:
    return f"{entry['map']} {entry['sequence']}"


def _frames(rows: list[dict]) -> str:
    frames = [r["frame"] for r in rows]
    return ", ".join(map(str, frames[:3])) + (f", ... {frames[-1]}" if len(frames) > 3 else "")


def markdown(report: dict) -> str:
    """The summary table (outcome counts per map) and one per-query table per map."""
    maps = report["maps"]
    sequences = ", ".join(f"`{s}`" for s in report["sequences"])
    lines = [
        f"# Where the localisation rate is lost: {sequences} of {report['dataset']}",
        "",
        "Made by:",
        "",
        f"```bash\n{report['command']}\n```",
        "",
        f"Each query (frames {_frames(maps[0]['rows'])}) gets the outcome of the first stage "
        "that decides it (experiments/crossmodal_breakdown.py docstring). Bound "
        f"{report['loose_m']:g} m / 30 deg; a reference is near the query within "
        f"{report['spacing_m']:g} m and 45 deg; theta_in {report['theta_in']}; "
        + (
            f"photometric threshold replayed at {report['min_photometric']:g}."
            if report["min_photometric"] is not None
            else "the runs' own validation."
        ),
        "",
        "## The photometric test (without -> with)",
        "",
        "| map | sequence | accepted | wrong accepted | precision [%] | rate [%] |",
        "|:---|:---|---:|---:|---:|---:|",
    ]
    for m in maps:
        a, b = m["photometric"]["without"], m["photometric"]["with"]
        lines.append(
            f"| {m['map']} | {m['sequence']} | {a['accepted']} -> {b['accepted']} | "
            f"{a['wrong']} -> {b['wrong']} | {_pct(a['precision'])} -> {_pct(b['precision'])} | "
            f"{_pct(a['rate'])} -> {_pct(b['rate'])} |"
        )
    lines += [
        "",
        "Threshold rule per map (1st percentile of the right poses' scores that pass "
        "the other tests, over these sequences, rounded down to 0.1):",
        "",
    ]
    for option, rule in report["threshold_rule"].items():
        lines.append(f"- {option}: {'-' if rule is None else f'{rule:g}'}")
    lines += [
        "",
        "## Outcomes",
        "",
        "| outcome | " + " | ".join(_label(m) for m in maps) + " |",
        "|:---|" + "---:|" * len(maps),
    ]
    for name in OUTCOMES:
        lines.append(f"| {name} | " + " | ".join(str(m["counts"][name]) for m in maps) + " |")
    for key, label in (
        ("accepted_from_prior", "accepted from the prior"),
        ("wrong_from_prior", "wrong accepted from the prior"),
        ("queries_with_prior", "queries with prior images"),
    ):
        lines.append(f"| {label} | " + " | ".join(str(m[key]) for m in maps) + " |")
    lines.append(
        "| median ms per query | " + " | ".join(f"{m['median_ms']:.0f}" for m in maps) + " |"
    )
    lines.append(
        "| load (1/5/15 min) when the localisation ended | "
        + " | ".join("/".join(f"{x:.1f}" for x in m["load_average"]) for m in maps)
        + " |"
    )
    for key, label in (
        ("top1_retrieval_rate", "top-1 render near"),
        ("reference_hit_rate", "reference near"),
    ):
        lines.append(f"| {label} [%] | " + " | ".join(f"{100 * m[key]:.1f}" for m in maps) + " |")
    if report["note"]:
        lines += ["", report["note"]]
    columns = list(maps[0]["rows"][0])
    for m in maps:
        lines += ["", f"## {_label(m)}", "", "| " + " | ".join(columns) + " |"]
        lines.append("|" + "---|" * len(columns))
        lines += ["| " + " | ".join(_cell(r[c]) for c in columns) + " |" for r in m["rows"]]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--map", action="append", required=True, help="a map option")
    parser.add_argument("--sequence", action="append", required=True)
    parser.add_argument("--spacing-m", type=float, default=2.0, help="render spacing")
    parser.add_argument("--loose-m", type=float, default=1.0, help="loose position bound")
    parser.add_argument("--theta-in", type=int, default=THETA_IN)
    parser.add_argument("--min-photometric", type=float, help="replay this threshold")
    parser.add_argument("--command", required=True, help="the command of the runs read")
    parser.add_argument("--note", default="", help="a paragraph under the outcome counts")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    maps = [
        breakdown(
            args.dataset,
            option,
            sequence,
            args.spacing_m,
            args.loose_m,
            args.theta_in,
            args.min_photometric,
        )
        for option in args.map
        for sequence in args.sequence
    ]
    rules = {
        option: threshold_rule(
            [x for m in maps if m["map"] == option for x in m["photometric"]["right_scores"]]
        )
        for option in args.map
    }
    report = {
        "dataset": str(args.dataset),
        "sequences": args.sequence,
        "threshold_rule": rules,
        "spacing_m": args.spacing_m,
        "loose_m": args.loose_m,
        "theta_in": args.theta_in,
        "min_photometric": args.min_photometric,
        "command": args.command,
        "note": args.note,
        "maps": maps,
    }
    write_report(args.out, markdown(report), report)
    print(markdown(report).split("\n## Outcomes")[0])


if __name__ == "__main__":
    main()
