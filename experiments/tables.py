"""Collect the jobs of a Hydra multirun sweep into one Markdown table (seed 1 Tables I-IV).

Every job of ``diffloc -m ...`` writes ``results.json`` (and Hydra's ``.hydra/overrides.yaml``)
into its own numbered folder under the sweep folder. This script reads them all and writes
``<out>.md`` (the table, headed by the exact command that made the sweep) and ``<out>.json``
(the rows).

Usage:
    python experiments/tables.py SWEEP_DIR --kind ablation --command "diffloc -m ..." \
        --out experiments/results/table2_ablation

Kinds:
    ``ablation`` (Tables I/II): recall@0.3 m and mATE per query sequence and variant;
    ``noise`` (Table III): the same plus keyframes, map points and keyframe position RMSE of
    the database before/after optimisation;
    ``runtime`` (Table IV): median milliseconds per relocalisation stage.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import yaml

from diffloc.eval.report_files import write_report
from diffloc.eval.tables import Column, markdown_table

STAGES = (
    "features",
    "global_descriptor",
    "retrieval",
    "clustering",
    "matching",
    "essential",
    "pnp",
    "projection",
    "refine",
)


def load_jobs(sweep: Path) -> list[tuple[str, dict]]:
    """``(variant, results)`` of every finished job, variant = its overrides joined."""
    jobs = []
    for results_path in sorted(sweep.glob("*/results.json")):
        overrides_path = results_path.parent / ".hydra" / "overrides.yaml"
        overrides = yaml.safe_load(overrides_path.read_text()) if overrides_path.is_file() else []
        shown = [o for o in overrides if not o.startswith(("hydra.", "task=", "+experiment="))]
        jobs.append(
            (" ".join(shown) or results_path.parent.name, json.loads(results_path.read_text()))
        )
    if not jobs:
        raise FileNotFoundError(f"no */results.json under {sweep}: is it a finished sweep folder?")
    return jobs


def database_stats(results: dict) -> dict:
    """Keyframes, map points and keyframe position RMSE of the job's database."""
    folder = Path(results["database"]).parent
    built = json.loads((folder / "build_db.json").read_text())
    row = {"keyframes": built["keyframes"], "map_points": built["map_points"]}
    optimized = folder / "optimize_db.json"
    row["rmse_before_m"] = built["kf_pos_rmse_m"]
    if results["database"].endswith("optimized") and optimized.is_file():
        row["rmse_after_m"] = json.loads(optimized.read_text())["kf_pos_rmse_after_m"]
    return row


def rows_and_columns(jobs: list[tuple[str, dict]], kind: str) -> tuple[list[dict], list[Column]]:
    rows, columns = [], [Column("variant", align="left"), Column("sequence", align="left")]
    for variant, results in jobs:
        extra = database_stats(results) if kind == "noise" else {}
        for name, entry in results["sequences"].items():
            row = {"variant": variant, "sequence": name, **extra, **entry}
            row.update({f"ms_{s}": entry["median_stage_ms"].get(s) for s in STAGES})
            rows.append(row)
    if kind == "runtime":
        columns += [Column(f"ms_{s}", s, ".1f") for s in STAGES]
        columns += [Column("median_reloc_ms", "reloc total", ".1f")]
        return rows, columns
    columns += [
        Column("queries"),
        Column("recall", "recall@0.3m [%]", ".1f", scale=100),
        Column("precision", "precision [%]", ".1f", scale=100),
        Column("mATE_m", "mATE [cm]", ".1f", scale=100),
    ]
    if kind == "noise":
        columns += [
            Column("keyframes"),
            Column("map_points", "map points"),
            Column("rmse_before_m", "KF RMSE before [m]", ".3f"),
            Column("rmse_after_m", "KF RMSE after [m]", ".3f"),
        ]
    return rows, columns


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep", type=Path)
    parser.add_argument("--kind", choices=("ablation", "noise", "runtime"), required=True)
    parser.add_argument("--command", required=True, help="the command that made the sweep")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    parser.add_argument("--note", default="", help="a paragraph printed under the command")
    args = parser.parse_args()
    rows, columns = rows_and_columns(load_jobs(args.sweep), args.kind)
    table = markdown_table(rows, columns)
    note = f"{args.note}\n\n" if args.note else ""
    text = f"Made by:\n\n```bash\n{args.command}\n```\n\n{note}{table}\n"
    write_report(args.out, text, [{k: v for k, v in r.items() if k != "plots"} for r in rows])
    print(text)


if __name__ == "__main__":
    main()
