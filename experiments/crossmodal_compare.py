"""Two settings of ``diffloc task=crossmodal`` side by side, from their cached localisations.

Each setting is a dataset folder whose ``crossmodal/<map>/localize_<sequence>/`` stages hold
the localisation of that setting (e.g. ``data/indoor_seed0`` with the defaults and a hard-link
copy ``/tmp/W/indoor_seed0`` run with ``task.tune_retrieval=true``; the stages write new files,
so the copy's runs leave the original's untouched). Per map and sequence the report gives,
for the baseline and the variant, the queries, right poses (accepted within ``--loose-m`` /
30 deg; the query ground truth is read for scoring only), wrong accepted poses, the precision,
the median CPU milliseconds per query and the mean candidates matched, then the totals per
map. The variant's retrieval stage record (``crossmodal/<map>/retrieval/retrieval.json``)
is quoted where it exists.

Usage:
    PYTHONPATH=. python3 experiments/crossmodal_compare.py --baseline data/indoor_seed0 \\
        --variant /tmp/W/indoor_seed0 --variant-name whitening --map mesh --map tls \\
        --sequence query_same --sequence query_reverse --sequence changed \\
        --command "..." --out experiments/results/crossmodal_whitening_indoor_seed0
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import numpy as np

from diffloc.eval.report_files import made_by_lines, write_report
from diffloc.pipeline.crossmodal_replay import recorded_errors
from diffloc.pipeline.crossmodal_stage import SequenceLocalization, crossmodal_folder


def scored(dataset: Path, option: str, sequence: str, loose_m: float) -> dict:
    """Right / wrong accepted poses, precision, median CPU ms and mean candidates of one
    cached localisation."""
    loc = SequenceLocalization.load(
        crossmodal_folder(dataset) / option / f"localize_{sequence}" / "localization.npz"
    )
    errors = recorded_errors(dataset, sequence, loc)
    right = (np.asarray(errors.translation_m) <= loose_m) & (
        np.asarray(errors.rotation_deg) <= 30.0
    )
    accepted = np.asarray(loc.accepted, dtype=bool)
    n_accepted = int(accepted.sum())
    return {
        "queries": len(accepted),
        "right": int((accepted & right).sum()),
        "wrong": int((accepted & ~right).sum()),
        "precision": float((accepted & right).sum() / n_accepted) if n_accepted else None,
        "median_cpu_ms": float(np.median(loc.cpu_ms)),
        "candidates_mean": float(np.bincount(loc.candidate_query, minlength=len(accepted)).mean()),
    }


def _percent(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f} %"


def markdown(report: dict) -> str:
    """The per-sequence table and the totals per map."""
    base, var = report["baseline_name"], report["variant_name"]
    lines = [
        f"# `task=crossmodal`: {base} against {var}",
        "",
        *made_by_lines(report["command"]),
        "",
        f"Baseline: `{report['baseline']}`; variant: `{report['variant']}`. Right: accepted "
        f"within {report['loose_m']:g} m / 30 deg. CPU: median process CPU ms per query (one "
        "thread). Candidates: mean references matched per query.",
        "",
        f"| map | sequence | queries | right {base} -> {var} | wrong | precision | CPU ms | "
        "candidates |",
        "|---|---|---:|---|---|---|---|---|",
    ]
    for row in report["rows"]:
        b, v = row["baseline"], row["variant"]
        lines.append(
            f"| {row['map']} | {row['sequence']} | {b['queries']} | {b['right']} -> {v['right']} "
            f"| {b['wrong']} -> {v['wrong']} | {_percent(b['precision'])} -> "
            f"{_percent(v['precision'])} | {b['median_cpu_ms']:.0f} -> {v['median_cpu_ms']:.0f} "
            f"| {b['candidates_mean']:.1f} -> {v['candidates_mean']:.1f} |"
        )
    lines += ["", "| map | right | wrong |", "|---|---|---|"]
    for option, total in report["totals"].items():
        lines.append(
            f"| {option} | {total['baseline_right']} -> {total['variant_right']} | "
            f"{total['baseline_wrong']} -> {total['variant_wrong']} |"
        )
    for option, record in report["variant_retrieval"].items():
        lines += ["", f"Variant's retrieval stage, {option}: `{json.dumps(record)}`"]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", type=Path, required=True)
    parser.add_argument("--variant", type=Path, required=True)
    parser.add_argument("--baseline-name", default="default")
    parser.add_argument("--variant-name", default="variant")
    parser.add_argument("--map", action="append", required=True)
    parser.add_argument("--sequence", action="append", required=True)
    parser.add_argument("--loose-m", type=float, default=1.0)
    parser.add_argument("--command", default="", help="the commands that made the two runs")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    rows, totals, retrieval = [], {}, {}
    for option in args.map:
        total = dict.fromkeys(
            ("baseline_right", "variant_right", "baseline_wrong", "variant_wrong"), 0
        )
        for sequence in args.sequence:
            b = scored(args.baseline, option, sequence, args.loose_m)
            v = scored(args.variant, option, sequence, args.loose_m)
            rows.append({"map": option, "sequence": sequence, "baseline": b, "variant": v})
            for side, scores in (("baseline", b), ("variant", v)):
                total[f"{side}_right"] += scores["right"]
                total[f"{side}_wrong"] += scores["wrong"]
        totals[option] = total
        record = crossmodal_folder(args.variant) / option / "retrieval" / "retrieval.json"
        if record.is_file():
            stored = json.loads(record.read_text())
            keys = ("method", "mapping_images", "tuples", "seconds")
            retrieval[option] = {k: stored.get(k) for k in keys}
    this = "PYTHONPATH=. python3 " + shlex.join(sys.argv)
    report = {
        "command": [c for c in (args.command, this) if c],
        "baseline": str(args.baseline),
        "variant": str(args.variant),
        "baseline_name": args.baseline_name,
        "variant_name": args.variant_name,
        "loose_m": args.loose_m,
        "rows": rows,
        "totals": totals,
        "variant_retrieval": retrieval,
    }
    write_report(args.out, markdown(report), report)
    print(markdown(report))


if __name__ == "__main__":
    main()
