"""What each pose-validation test costs and buys, replayed on a finished relocalisation job.

The job's own validation thresholds (``results.json``) are replayed over its ``queries.json``
(same poses, :func:`diffloc.pipeline.revalidate.replay_validation`), then each ``--vary
KEY=VALUE`` alone (a field of :class:`diffloc.reloc.validation.ValidationConfig`; ``null``
switches a test off), and seed 1's rule. Per sequence: recall at the job's ``max_trans_m`` and
the precision of the accepted poses (ground truth read for scoring only). Tune on seed 0 only.

Usage:
    python3 experiments/validation_replay.py outputs/seed0_outdoor_revalidated \\
        --vary min_inlier_ratio=0.25 --vary min_coverage=0 \\
        --out experiments/results/validation_replay_outdoor_seed0
        -> experiments/results/validation_replay_outdoor_seed0.md / .json
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from dataclasses import replace
from pathlib import Path

import yaml

from diffloc.eval.metrics import precision, recall
from diffloc.eval.report_files import write_report
from diffloc.eval.tables import Column, markdown_table
from diffloc.pipeline.revalidate import record_errors, replay_validation
from diffloc.reloc.validation import ValidationConfig


def variants(base: ValidationConfig, vary: list[str]) -> dict[str, ValidationConfig]:
    """The job's thresholds, each ``KEY=VALUE`` of ``vary`` alone, and seed 1's rule."""
    out = {"job's thresholds": base}
    for item in vary:
        key, _, value = item.partition("=")
        out[item] = replace(base, **{key: yaml.safe_load(value)})
    out["seed 1's rule"] = base.seed1_rule()
    return out


def replay(job: Path, vary: list[str]) -> list[dict]:
    """One row per variant: recall and precision of every sequence of ``job``."""
    results = json.loads((job / "results.json").read_text())
    max_trans = results["config"]["max_trans_m"]
    base = ValidationConfig(**results["config"]["validation"])
    rows = []
    for name, config in variants(base, vary).items():
        row: dict = {"validation": name}
        for sequence in results["sequences"]:
            records = json.loads((job / sequence / "queries.json").read_text())
            errors = record_errors(records, replay_validation(records, config))
            row[sequence] = (
                f"{100 * recall(errors, max_trans):.1f} / {100 * precision(errors, max_trans):.1f}"
            )
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("job", type=Path, help="a finished relocalisation job folder")
    parser.add_argument("--vary", action="append", default=[], help="KEY=VALUE, one at a time")
    parser.add_argument("--out", type=Path, required=True, help="report path without suffix")
    args = parser.parse_args(argv)
    rows = replay(args.job, args.vary)
    sequences = [k for k in rows[0] if k != "validation"]
    columns = [Column("validation")]
    columns += [Column(s, f"{s}: recall / precision [%]") for s in sequences]
    command = shlex.join(["python3", "experiments/validation_replay.py", *sys.argv[1:]])
    note = "Recall at the job's max_trans_m; precision of the accepted poses; nan: none accepted."
    report = f"Made by:\n\n```bash\n{command}\n```\n\n{note}\n\n{markdown_table(rows, columns)}\n"
    write_report(args.out, report, rows)
    print(report)


if __name__ == "__main__":
    main()
