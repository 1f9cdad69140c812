"""Where the time of ``diffloc task=crossmodal`` goes, and how settings compare, per query.

Reads the ``results.json`` of ``task=crossmodal`` runs (each given as ``--run LABEL=PATH``;
the time breakdown is the localisation stage's record,
:func:`~diffloc.pipeline.crossmodal_report.time_breakdown`) and writes one Markdown + JSON
report: per run and sequence the accepted poses, their precision and the localisation rate
within the loose bound / 30 deg, the median wall and CPU ms per query, the candidates matched,
the mean CPU ms per stage (features, global retrieval, re-ranking, LighterGlue, lifting + PnP,
photometric test; matching and PnP summed over the candidates) and the median CPU ms of one
LighterGlue match, with the load average when the localisation ended.

Usage:
    PYTHONPATH=. python3 experiments/crossmodal_time.py \\
        --run before=outputs/<run>/results.json --run after=outputs/<run>/results.json \\
        --command "PYTHONPATH=\\$PWD OMP_NUM_THREADS=1 diffloc task=crossmodal map=mesh ..." \\
        --out experiments/results/crossmodal_time_mesh_indoor_seed0
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from diffloc.eval.report_files import made_by_lines, write_report
from diffloc.reloc.stage_clock import STAGES


def rows(label: str, results: dict) -> list[dict]:
    """One row per sequence of a run's ``results.json`` (``results``), labelled ``label``."""
    loose = f"{results['loose_m']:g}m_30deg"
    out = []
    for name, entry in results["sequences"].items():
        time = entry["time"]
        out.append(
            {
                "run": label,
                "dataset": results["dataset"],
                "map": results["map"],
                "sequence": name,
                "queries": entry["queries"],
                "accepted": entry["accepted"],
                "wrong_accepted": entry["wrong_accepted"],
                "precision": entry["precision"],
                "rate": entry["rates"][loose],
                "median_ms": time["median_ms"],
                "median_cpu_ms": time["median_cpu_ms"],
                "mean_ms": time["mean_ms"],
                "mean_cpu_ms": time["mean_cpu_ms"],
                "candidates_median": time["candidates"]["median"],
                "candidates_mean": time["candidates"]["mean"],
                "stage_cpu_ms": {s: time["stages"][s]["mean_cpu_ms"] for s in STAGES},
                "match_cpu_ms": time["match_cpu_ms"],
                "load_average": results["stages"][f"localize_{name}"]["load_average"],
            }
        )
    return out


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f} %"


def markdown(report: dict) -> str:
    """The two tables: outcome and time per run and sequence, then the stage breakdown."""
    lines = [
        f"# Time per query of the rendered-database localiser: {report['title']}",
        "",
        *made_by_lines(report["commands"]),
        "Rate: accepted within the loose bound / 30 deg over all queries; precision: of the "
        "accepted poses. Times: the localisation stage's record (wall and process CPU per "
        "query; one thread, so CPU is the work done, wall also holds the waits of a shared "
        "2-core machine under the load shown, 1/5/15-minute averages when the stage ended).",
        "",
        "| run | sequence | queries | accepted (wrong) | precision | rate | median wall ms "
        "| median CPU ms | candidates median / mean | load |",
        "|:---|:---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in report["rows"]:
        load = "/".join(f"{x:.1f}" for x in r["load_average"])
        lines.append(
            f"| {r['run']} | {r['sequence']} | {r['queries']} | {r['accepted']} "
            f"({r['wrong_accepted']}) | {_pct(r['precision'])} | {_pct(r['rate'])} | "
            f"{r['median_ms']:.0f} | {r['median_cpu_ms']:.0f} | "
            f"{r['candidates_median']:g} / {r['candidates_mean']:.1f} | {load} |"
        )
    lines += [
        "",
        "Mean CPU ms per query and stage (matching and PnP summed over the candidates; the "
        "rest of the mean is bookkeeping), and the median CPU ms of one LighterGlue match:",
        "",
        "| run | sequence | mean CPU ms | " + " | ".join(STAGES) + " | per match |",
        "|:---|:---|" + "---:|" * (len(STAGES) + 2),
    ]
    for r in report["rows"]:
        match = r["match_cpu_ms"]
        lines.append(
            f"| {r['run']} | {r['sequence']} | {r['mean_cpu_ms']:.0f} | "
            + " | ".join(f"{r['stage_cpu_ms'][s]:.0f}" for s in STAGES)
            + f" | {'-' if match is None else f'{match:.0f}'} |"
        )
    if report["note"]:
        lines += ["", report["note"]]
    return "\n".join(lines) + "\n"


def _labelled(text: str) -> tuple[str, Path]:
    label, sep, path = text.partition("=")
    if not sep or not label or not path:
        raise argparse.ArgumentTypeError(f"--run takes LABEL=PATH, got {text!r}")
    return label, Path(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=_labelled, action="append", required=True)
    parser.add_argument("--command", action="append", required=True, help="commands of the runs")
    parser.add_argument("--title", default="mesh map, indoor")
    parser.add_argument("--note", default="", help="a paragraph under the tables")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    table = []
    for label, path in args.run:
        if not path.is_file():
            raise SystemExit(f"{path} is missing: run diffloc task=crossmodal first")
        table += rows(label, json.loads(path.read_text()))
    report = {
        "title": args.title,
        "commands": args.command,
        "runs": {label: str(path) for label, path in args.run},
        "note": args.note,
        "rows": table,
    }
    write_report(args.out, markdown(report), report)
    print(markdown(report))


if __name__ == "__main__":
    main()
