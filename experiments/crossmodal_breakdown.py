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

``--min-photometric`` replays another threshold from the recorded scores
(``accepted_without_photometric`` and ``photometric >= t``); by default the run's own verdict.

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
from diffloc.features.retrieval_eval import pairwise_pose_distances
from diffloc.io.atomic import atomic_write_text
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
    loc = SequenceLocalization.load(folder / f"localize_{sequence}" / "localization.npz")
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
            "outcome": verdicts[q],
        }
        for q in range(len(loc.frames))
    ]
    counts = Counter(verdicts)
    return {
        "map": option,
        "queries": len(rows),
        "top1_retrieval_rate": float(top1_hit.mean()),
        "reference_hit_rate": float(reference_hit.mean()),
        "counts": {name: counts.get(name, 0) for name in OUTCOMES},
        "rows": rows,
    }


def _cell(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.2f}"
    return str(value)


def _frames(rows: list[dict]) -> str:
    frames = [r["frame"] for r in rows]
    return ", ".join(map(str, frames[:3])) + (f", ... {frames[-1]}" if len(frames) > 3 else "")


def markdown(report: dict) -> str:
    """The summary table (outcome counts per map) and one per-query table per map."""
    maps = report["maps"]
    lines = [
        f"# Where the localisation rate is lost: `{report['sequence']}` of {report['dataset']}",
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
        "| outcome | " + " | ".join(m["map"] for m in maps) + " |",
        "|:---|" + "---:|" * len(maps),
    ]
    for name in OUTCOMES:
        lines.append(f"| {name} | " + " | ".join(str(m["counts"][name]) for m in maps) + " |")
    for key, label in (
        ("top1_retrieval_rate", "top-1 render near"),
        ("reference_hit_rate", "reference near"),
    ):
        lines.append(f"| {label} [%] | " + " | ".join(f"{100 * m[key]:.1f}" for m in maps) + " |")
    columns = list(maps[0]["rows"][0])
    for m in maps:
        lines += ["", f"## {m['map']}", "", "| " + " | ".join(columns) + " |"]
        lines.append("|" + "---|" * len(columns))
        lines += ["| " + " | ".join(_cell(r[c]) for c in columns) + " |" for r in m["rows"]]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--map", action="append", required=True, help="a map option")
    parser.add_argument("--sequence", default="query_same")
    parser.add_argument("--spacing-m", type=float, default=2.0, help="render spacing")
    parser.add_argument("--loose-m", type=float, default=1.0, help="loose position bound")
    parser.add_argument("--theta-in", type=int, default=THETA_IN)
    parser.add_argument("--min-photometric", type=float, help="replay this threshold")
    parser.add_argument("--command", required=True, help="the command of the runs read")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    maps = [
        breakdown(
            args.dataset,
            option,
            args.sequence,
            args.spacing_m,
            args.loose_m,
            args.theta_in,
            args.min_photometric,
        )
        for option in args.map
    ]
    report = {
        "dataset": str(args.dataset),
        "sequence": args.sequence,
        "spacing_m": args.spacing_m,
        "loose_m": args.loose_m,
        "theta_in": args.theta_in,
        "min_photometric": args.min_photometric,
        "command": args.command,
        "maps": maps,
    }
    atomic_write_text(args.out.with_suffix(".json"), json.dumps(report, indent=2) + "\n")
    atomic_write_text(args.out.with_suffix(".md"), markdown(report))
    print(markdown(report).split("\n## ")[0])


if __name__ == "__main__":
    main()
