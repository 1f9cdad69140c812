"""Choose the re-ranking depth and the validation of rendered-database localisation by replay.

A run of ``experiments/rendered_localization.py`` with ``--top-k K --select most_inliers
--stop-inliers 0 --no-validation`` records, per query, every retrieved candidate's evidence
(inliers, points with depth, coverage, position) and its true error. The candidates of a
prefix of the ranking are exactly what a run with a smaller ``top_k`` or an early stop would
have computed (the RANSAC generator is consumed in rank order), so every setting is replayed
here with the localiser's own :func:`choose_candidate` and :func:`accept_pose` instead of
re-matching. Each setting is varied alone from the base (all other tests as in the base).

Reported per setting and sequence: found (a pose), accepted (found and validated), precision
of the accepted poses and localisation rate (accepted within 1 m / 30 deg over all queries),
and the mean number of candidates matched per query (the cost).

Usage:
    PYTHONPATH=. python3 experiments/rendered_replay.py \\
        --run /tmp/rendered_tune/rendered_localization_tune_top10.json \\
        --out experiments/results/rendered_replay_indoor_seed0
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import torch

from diffloc.eval.report_files import write_report
from diffloc.reloc.rendered import (
    RenderedCandidate,
    RenderedLocalizerConfig,
    accept_pose,
    choose_candidate,
)
from diffloc.reloc.validation import ValidationConfig

CORRECT_M, CORRECT_DEG = 1.0, 30.0


def _candidate(record: dict) -> RenderedCandidate:
    T = torch.eye(4, dtype=torch.float64)
    T[:3, 3] = torch.tensor(record["position_m"], dtype=torch.float64)
    rms = record["rms_px"]
    return RenderedCandidate(
        record["reference"],
        T,
        record["success"],
        record["matches"],
        record["points"],
        record["inliers"],
        record["coverage"],
        float("nan") if rms is None else rms,
    )


def _correct(record: dict) -> bool:
    return bool(
        record["success"] and record["error_m"] <= CORRECT_M and record["error_deg"] <= CORRECT_DEG
    )


def _score(
    queries: list[dict], top_k: int, stop: int | None, validation: ValidationConfig | None
) -> dict:
    found = accepted = correct = tried = 0
    for query in queries:
        records = query["candidates"][:top_k]
        by_reference = {r["reference"]: r for r in records}
        best, seen = choose_candidate(map(_candidate, records), "most_inliers", stop)
        tried += len(seen)
        found += best.success
        if accept_pose(best, seen, validation):
            accepted += 1
            correct += _correct(by_reference[best.reference])
    n = len(queries)
    return {
        "found": found / n,
        "accepted": accepted / n,
        "precision": correct / accepted if accepted else None,
        "rate_1m_30deg": correct / n,
        "mean_tried": tried / n,
    }


def _settings(base: RenderedLocalizerConfig) -> list[tuple[str, int, int | None, object]]:
    """(label, top_k, stop_inliers, validation): the base, then one knob varied at a time."""
    v = base.validation
    rows = [
        ("base", base.top_k, base.stop_inliers, v),
        ("no validation", base.top_k, base.stop_inliers, None),
    ]
    rows += [(f"top_k={k}", k, base.stop_inliers, v) for k in (1, 2, 3, 5, 10)]
    rows += [(f"stop_inliers={s}", base.top_k, s, v) for s in (50, 100, 150, None)]
    rows += [
        (f"theta_in={t}", base.top_k, base.stop_inliers, replace(v, theta_in=t))
        for t in (6, 12, 20, 30, 40, 60)
    ]
    rows += [
        (f"min_inlier_ratio={r}", base.top_k, base.stop_inliers, replace(v, min_inlier_ratio=r))
        for r in (0.0, 0.2, 0.3, 0.4, 0.5)
    ]
    rows += [
        (f"min_coverage={c}", base.top_k, base.stop_inliers, replace(v, min_coverage=c))
        for c in (0.0, 0.25, 0.375, 0.5)
    ]
    rows += [
        (f"ambiguity_ratio={a}", base.top_k, base.stop_inliers, replace(v, ambiguity_ratio=a))
        for a in (None, 0.3, 0.5, 0.7, 0.9)
    ]
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True, help="output stem (.md, .json)")
    args = parser.parse_args()
    run = json.loads(args.run.read_text())
    if run["retrieval"]["stop_inliers"] is not None or run.get("validation") is not None:
        sys.exit(f"{args.run}: replay needs a run with --stop-inliers 0 --no-validation")
    base = RenderedLocalizerConfig()
    rows = []
    for label, top_k, stop, validation in _settings(base):
        if top_k > run["retrieval"]["top_k"]:
            continue
        per_sequence = {
            row["sequence"]: _score(row["result"]["per_query"], top_k, stop, validation)
            for row in run["rows"]
        }
        rows.append({"setting": label, "sequences": per_sequence})
    sequences = [row["sequence"] for row in run["rows"]]
    head = ["setting"] + [f"{s} acc. / prec. / rate / tried" for s in sequences]
    lines = [
        f"# Replay of re-ranking and validation settings ({args.run.name})",
        "",
        f"`python3 {' '.join(sys.argv)}`; base: top_k={base.top_k}, "
        f"stop_inliers={base.stop_inliers}, validation {base.validation}.",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]

    def pct(x: float | None) -> str:
        return "-" if x is None else f"{100 * x:.1f}"

    for row in rows:
        cells = [row["setting"]]
        for s in sequences:
            r = row["sequences"][s]
            cells.append(
                f"{pct(r['accepted'])} / {pct(r['precision'])} / {pct(r['rate_1m_30deg'])} / "
                f"{r['mean_tried']:.1f}"
            )
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "acc.: accepted share of the queries (%); prec.: share of the accepted within "
        f"{CORRECT_M:g} m / {CORRECT_DEG:g} deg (%); rate: accepted and within it, share of all "
        "queries (%); tried: mean candidates matched per query.",
        "",
    ]
    write_report(args.out, "\n".join(lines), rows)


if __name__ == "__main__":
    main()
