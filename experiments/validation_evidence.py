"""Can per-query evidence tell the wrong query_reverse poses from the right query_same ones?

Reads the ``queries.json`` files of finished relocalisation jobs (``diffloc task=main`` or a
sweep of it) and, for every query whose best candidate passes seed 1's inlier test, takes the
evidence the validation sees (:mod:`diffloc.reloc.validation`): inliers, inlier ratio, grid
coverage, the strongest rival candidate farther than 1 m (its share of the best inliers) and
the position's standard deviation (:mod:`diffloc.reloc.pose_uncertainty`; NaN for runs of an
older diffloc, which did not record it).
Poses within 0.3 m of the truth are *right*, the others *wrong* (scoring only).

For each evidence figure the report gives its distribution (5th / 50th / 95th percentile) over
the right poses of the reference sequence and the wrong poses of the other sequences, and the
test a user could set: the threshold that keeps 95 % of the right reference poses, with the
share of wrong poses it still lets through. Where that share stays high for every figure, no
threshold on that evidence reaches the precision goal without giving up the reference recall.

Usage:
    python3 experiments/validation_evidence.py experiments/runs/heldout_main \\
        --out experiments/results/validation_evidence
        -> experiments/results/validation_evidence.md / .json
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
from pathlib import Path

import numpy as np

from diffloc.eval.report_files import write_report
from diffloc.eval.sweeps import load_jobs
from diffloc.eval.tables import Column, markdown_table

THETA_IN = 15
MAX_TRANS_M = 0.3
RIVAL_DISTANCE_M = 1.0
KEEP = 0.95

FIGURES = {
    "inliers": ("inliers", "higher"),
    "inlier_ratio": ("inlier ratio", "higher"),
    "coverage": ("grid coverage", "higher"),
    "rival_share": ("rival inliers / best", "lower"),
    "position_sigma": ("position sigma [m]", "lower"),
}
"""Evidence figure -> (label, the direction a right pose is expected in)."""


def evidence(query: dict) -> dict[str, float] | None:
    """The validation evidence of one ``queries.json`` entry (``None``: no inlier pose)."""
    candidates = query["candidates"]
    if not query["found"] or not candidates:
        return None
    best = max(candidates, key=lambda c: c["inliers"])
    if best["inliers"] < THETA_IN:
        return None
    rivals = [c["inliers"] for c in candidates if c["distance_to_chosen_m"] > RIVAL_DISTANCE_M]
    return {
        "inliers": float(best["inliers"]),
        "inlier_ratio": best["inliers"] / max(best["matches"], 1),
        "coverage": float(best["coverage"]),
        "rival_share": max(rivals, default=0) / best["inliers"],
        # null: unbounded; missing: a run of an older diffloc, which did not measure it
        "position_sigma": math.nan
        if "position_sigma_m" not in best
        else math.inf
        if best["position_sigma_m"] is None
        else float(best["position_sigma_m"]),
        "right": query["translation_error_m"] is not None
        and query["translation_error_m"] <= MAX_TRANS_M,
    }


def collect(folders: list[Path]) -> dict[str, list[dict]]:
    """Evidence of every inlier pose, per sequence, over all jobs of ``folders``."""
    per_sequence: dict[str, list[dict]] = {}
    for job in load_jobs(folders):
        for name in job.sequences:
            queries = json.loads((job.folder / name / "queries.json").read_text())
            rows = [e for e in map(evidence, queries) if e is not None]
            per_sequence.setdefault(name, []).extend(rows)
    return per_sequence


def separability(per_sequence: dict[str, list[dict]], reference: str) -> list[dict]:
    """One row per figure and sequence: distributions and the 95 %-keeping threshold."""
    right = [e for e in per_sequence[reference] if e["right"]]
    if not right:
        raise ValueError(f"no right poses of the reference sequence {reference!r}")
    rows = []
    for key, (label, direction) in FIGURES.items():
        values = np.array([e[key] for e in right])
        threshold = float(np.quantile(values, 1 - KEEP if direction == "higher" else KEEP))

        for name, rows_of in per_sequence.items():
            wrong = np.array([e[key] for e in rows_of if not e["right"]])
            kept_right = np.array([e[key] for e in rows_of if e["right"]])
            rows.append(
                {
                    "figure": label,
                    "test": f"{'>=' if direction == 'higher' else '<='} {threshold:.3g}",
                    "sequence": name,
                    "right_p5_p50_p95": _quantiles(kept_right),
                    "wrong_p5_p50_p95": _quantiles(wrong),
                    "wrong": len(wrong),
                    "wrong_passing": _passing(wrong, threshold, direction),
                    "right_kept": _passing(kept_right, threshold, direction),
                }
            )
    return rows


def _passing(values: np.ndarray, threshold: float, direction: str) -> float | None:
    """Share of ``values`` on the side of ``threshold`` a right pose is expected on."""
    if len(values) == 0:
        return None
    return float((values >= threshold if direction == "higher" else values <= threshold).mean())


def _quantiles(values: np.ndarray) -> str:
    if len(values) == 0:
        return "-"
    return " / ".join(f"{q:.3g}" for q in np.quantile(values, [0.05, 0.5, 0.95]))


COLUMNS = [
    Column("figure", align="left"),
    Column("test", align="left"),
    Column("sequence", align="left"),
    Column("right_p5_p50_p95", "right poses: p5 / p50 / p95"),
    Column("wrong_p5_p50_p95", "wrong poses: p5 / p50 / p95"),
    Column("wrong", "wrong poses"),
    Column("wrong_passing", "wrong passing the test [%]", ".1f", scale=100),
    Column("right_kept", "right kept [%]", ".1f", scale=100),
]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="job or sweep folders")
    parser.add_argument("--reference", default="query_same", help="sequence whose right poses")
    parser.add_argument("--out", type=Path, required=True, help="report path without suffix")
    args = parser.parse_args(argv)
    per_sequence = collect(args.runs)
    rows = separability(per_sequence, args.reference)
    command = shlex.join(["python3", "experiments/validation_evidence.py", *sys.argv[1:]])
    text = (
        f"Made by:\n\n```bash\n{command}\n```\n\n"
        f"Inlier poses (>= {THETA_IN} inliers) of every job; right = within {MAX_TRANS_M} m. "
        f"Each test keeps {KEEP:.0%} of the right `{args.reference}` poses.\n\n"
        f"{markdown_table(rows, COLUMNS)}\n"
    )
    write_report(args.out, text, rows)
    print(text)


if __name__ == "__main__":
    main()
