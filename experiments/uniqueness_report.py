"""The uniqueness test on and off over finished relocalisation jobs, one table.

Every job must have been run with the uniqueness measured (``reloc.record_uniqueness=true`` or
``reloc.validation.uniqueness_ratio`` set). Per job and sequence, the job's own validation
thresholds are replayed over its ``queries.json`` with ``uniqueness_ratio`` off and at each
``--ratio`` (:func:`diffloc.pipeline.revalidate.replay_validation`; same poses, ground truth read
for scoring only): recall at 0.3 m, precision, wrong accepted poses; plus the largest ratio
of a wrong and the smallest ratio of a right pose accepted with the test off, and the median
wall time of the measurement per query (from the job's stage timings).

Usage:
    python3 experiments/uniqueness_report.py /tmp/R/out0 /tmp/R/in0 --ratio 0.8 \\
        --out experiments/results/uniqueness_seed0 --made-by "diffloc task=relocalize ..."
        -> experiments/results/uniqueness_seed0.md / .json
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from diffloc.eval.metrics import precision, recall
from diffloc.eval.report_files import write_report
from diffloc.eval.tables import Column, markdown_table
from diffloc.pipeline.revalidate import record_errors, replay_validation
from diffloc.reloc.validation import PoseEvidence, ValidationConfig


def job_rows(job: Path, ratios: list[float]) -> list[dict]:
    """One row per sequence of ``job``."""
    results = json.loads((job / "results.json").read_text())
    max_trans = results["config"]["max_trans_m"]
    base = ValidationConfig(**results["config"]["validation"])
    rows = []
    for sequence in results["sequences"]:
        records = json.loads((job / sequence / "queries.json").read_text())
        row: dict = {"job": job.name, "sequence": sequence, "queries": len(records)}
        off = replace(base, uniqueness_ratio=None)
        for label, config in [("off", off)] + [
            (f"{r:g}", replace(base, uniqueness_ratio=r)) for r in ratios
        ]:
            errors = record_errors(records, replay_validation(records, config))
            right = errors.localized & (errors.translation_m <= max_trans)
            row[f"recall_{label}"] = 100 * recall(errors, max_trans)
            row[f"precision_{label}"] = 100 * precision(errors, max_trans)
            row[f"wrong_{label}"] = int((errors.localized & ~right).sum())
        accepted = record_errors(records, replay_validation(records, off))
        scores = [
            PoseEvidence.from_record(r).uniqueness if "uniqueness" in r else None for r in records
        ]
        if any(s is None and a for s, a in zip(scores, accepted.localized, strict=True)):
            raise ValueError(f"{job / sequence}: an accepted pose without a recorded uniqueness")
        good = accepted.localized & (accepted.translation_m <= max_trans)
        wrong = accepted.localized & ~good
        row["max_ratio_wrong"] = max((scores[i] for i in np.flatnonzero(wrong)), default=None)
        row["min_ratio_right"] = min((scores[i] for i in np.flatnonzero(good)), default=None)
        times = [r["timings_ms"]["uniqueness"] for r in records if "uniqueness" in r["timings_ms"]]
        row["median_ms"] = statistics.median(times) if times else None
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("jobs", type=Path, nargs="+", help="finished relocalisation job folders")
    parser.add_argument("--ratio", type=float, action="append", default=[], help="a threshold")
    parser.add_argument("--out", type=Path, required=True, help="report path without suffix")
    parser.add_argument(
        "--made-by", action="append", default=[], help="a command that produced the jobs"
    )
    args = parser.parse_args(argv)
    rows = [row for job in args.jobs for row in job_rows(job, args.ratio)]
    columns = [Column("job"), Column("sequence"), Column("queries")]
    for label in ["off"] + [f"{r:g}" for r in args.ratio]:
        columns += [
            Column(f"recall_{label}", f"recall@0.3m {label} [%]", ".1f"),
            Column(f"precision_{label}", f"precision {label} [%]", ".1f"),
            Column(f"wrong_{label}", f"wrong {label}"),
        ]
    columns += [
        Column("max_ratio_wrong", "largest ratio, wrong (off)", ".2f"),
        Column("min_ratio_right", "smallest ratio, right (off)", ".2f"),
        Column("median_ms", "uniqueness [ms, wall]", ".0f"),
    ]
    command = shlex.join(["python3", "experiments/uniqueness_report.py", *sys.argv[1:]])
    note = (
        "off: the job's validation without the uniqueness test; a number: with "
        "reloc.validation.uniqueness_ratio at it. Recall at 0.3 m; precision of the accepted "
        "poses (nan: none accepted); wrong: accepted poses farther than 0.3 m. The ratio columns "
        "are over the poses accepted with the test off."
    )
    made_by = "\n".join([*args.made_by, command])
    report = f"Made by:\n\n```bash\n{made_by}\n```\n\n{note}\n\n{markdown_table(rows, columns)}\n"
    write_report(args.out, report, rows)
    print(report)


if __name__ == "__main__":
    main()
