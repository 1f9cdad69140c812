"""How the TLS cloud is rendered into its database: render settings side by side (issue 18).

Reads the runs of ``experiments/tls_render_runs.sh`` (one folder per named setting under one
dataset's ``experiments/runs/tls_render/<dataset name>/``, each with the ``results.json`` of
``diffloc task=crossmodal map=tls`` and the ``breakdown.json`` of
``experiments/crossmodal_breakdown.py``) and writes one Markdown + JSON report: per setting
its overrides and map settings, the coloured points, the database (images, share of pixels
without depth, render + XFeat + NetVLAD CPU and wall seconds), per query sequence the
localisation rate at 1 m / 30 deg, right and accepted poses, the pooled precision, the
breakdown's outcome counts, and for each wrong accepted pose its horizontal and vertical
position error (the ground truth of the query sequence, read for scoring only: an error of
one storey height in z with the right x, y is a confusion of two storeys that look alike).

``--choose`` (the tuning seed) applies the rule fixed before the runs: the setting with the
most right poses (accepted within 1 m / 30 deg) summed over the sequences, among the settings
whose pooled precision is no lower than the ``default`` run's or at least 95 % (issue 18's
precision goal); ties go to the lower database render CPU time.

Usage:
    PYTHONPATH=. python3 experiments/tls_render_table.py \\
        --runs experiments/runs/tls_render/indoor_seed0 --choose \\
        --command "bash experiments/tls_render_runs.sh data/indoor_seed0 default '' ..." \\
        --out experiments/results/crossmodal_tls_render_indoor_seed0
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import sys
from pathlib import Path

import numpy as np

from diffloc.eval.report_files import made_by_lines, write_report
from diffloc.io.dataset import read_sequence
from diffloc.io.trajectory import read_tum

DEFAULT = "default"
"""The run of the task's defaults, the reference of the rule."""
MIN_PRECISION = 0.95
"""Issue 18's precision goal."""
RATE = "1m_30deg"


def wrong_pose_errors(folder: Path, dataset: Path, sequence: str, rows: list[dict]) -> list:
    """``[frame, horizontal m, vertical m]`` of each wrong accepted pose of ``sequence`` in
    the run ``folder`` (its ``trajectory_<sequence>.tum`` against the ground truth)."""
    frames = [r["frame"] for r in rows if r["outcome"] == "wrong accepted"]
    if not frames:
        return []
    truth = read_sequence(dataset, sequence)
    stamps, T_wc = read_tum(folder / f"trajectory_{sequence}.tum")
    errors = []
    for frame in frames:
        index = int(np.argmin(np.abs(stamps - float(truth.timestamps[frame]))))
        offset = (T_wc[index, :3, 3] - truth.T_wc[frame, :3, 3]).numpy()
        errors.append([frame, round(float(np.hypot(*offset[:2])), 2), round(float(offset[2]), 2)])
    return errors


def read_run(folder: Path) -> dict:
    """The setting, database, per-sequence figures and outcome counts of one run folder."""
    results = json.loads((folder / "results.json").read_text())
    breakdown = json.loads((folder / "breakdown.json").read_text())
    counts = {m["sequence"]: m["counts"] for m in breakdown["maps"]}
    rows = {m["sequence"]: m["rows"] for m in breakdown["maps"]}
    database = results["stages"]["database"]
    sequences = {}
    for name, seq in results["sequences"].items():
        right = round(seq["rates"][RATE] * seq["queries"])
        sequences[name] = {
            "queries": seq["queries"],
            "accepted": seq["accepted"],
            "right": right,
            "rate": seq["rates"][RATE],
            "precision": seq["precision"],
            "median_ms_per_query": seq["median_ms_per_query"],
            "outcomes": counts[name],
            "wrong_pose_errors": wrong_pose_errors(
                folder, Path(results["dataset"]), name, rows[name]
            ),
        }
    return {
        "name": folder.name,
        "command": breakdown["command"],
        "map_settings": results["map_settings"],
        "colored_points": results["stages"]["map"]["colored_points"],
        "points": results["stages"]["map"]["points"],
        "images": database["images"],
        "hole_share": database["hole_share"],
        "render_cpu_s": database["cpu_seconds"],
        "render_wall_s": database["seconds"],
        "machine": results["machine"],
        "sequences": sequences,
    }


def pooled(run: dict) -> tuple[int, int, float | None]:
    """Right poses, accepted poses and precision pooled over the run's sequences."""
    right = sum(s["right"] for s in run["sequences"].values())
    accepted = sum(s["accepted"] for s in run["sequences"].values())
    return right, accepted, right / accepted if accepted else None


def choose(runs: list[dict]) -> dict:
    """The tuning rule (module docstring) over ``runs``, the ``default`` run among them."""
    by_name = {r["name"]: r for r in runs}
    if DEFAULT not in by_name:
        raise SystemExit(f"the rule needs the {DEFAULT!r} run")
    floor = min(pooled(by_name[DEFAULT])[2] or 0.0, MIN_PRECISION)
    scores = [
        {
            "name": r["name"],
            "right": pooled(r)[0],
            "precision": pooled(r)[2],
            "render_cpu_s": r["render_cpu_s"],
            "allowed": (pooled(r)[2] or 0.0) >= floor,
        }
        for r in runs
    ]
    best = max((s for s in scores if s["allowed"]), key=lambda s: (s["right"], -s["render_cpu_s"]))
    return {"precision_floor": floor, "scores": scores, "chosen": best["name"]}


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f} %"


def _map_cell(settings: dict) -> str:
    """The render settings of a run's ``map`` node, e.g. ``single, rho_max 8, no filter``."""
    radius = settings.get("visibility_radius", 0)
    visibility = f"visibility radius {radius}" if radius else "no filter"
    return f"{settings['passes']}, rho_max {settings['rho_max']:g}, {visibility}"


def _rounded(text: str) -> str:
    """``text`` with its decimal numbers rounded to one decimal."""
    return re.sub(r"\d+\.\d+", lambda m: f"{float(m[0]):.1f}", text)


def markdown(report: dict) -> str:
    """The report as Markdown: the settings table, the outcome counts, the rule's choice."""
    runs = report["runs"]
    sequences = list(runs[0]["sequences"])
    lines = [
        *made_by_lines(report["commands"]),
        f"# TLS cloud render settings: {report['dataset']}",
        "",
    ]
    lines.append(
        "Every 4th frame, `task=crossmodal map=tls` defaults otherwise; rate = accepted within "
        "1 m / 30 deg over all queries; map = the run's map settings (rho_max sizes the Eq. 2 "
        "splats of the renders and of the colouring's occlusion test, whose points no mapping "
        "image sees unoccluded are dropped: coloured points); render = the database stage "
        "(render + XFeat + NetVLAD, one thread; colouring the map is not counted)."
    )
    lines.append("")
    head = [
        "setting",
        "overrides",
        "map",
        "coloured points",
        "images",
        "holes",
        "render CPU s (wall)",
    ]
    head += [f"`{s}` rate (right / accepted / queries)" for s in sequences]
    head += ["precision (pooled)"]
    lines += [
        "| " + " | ".join(head) + " |",
        "|" + "|".join([":---"] * 3 + ["---:"] * (len(head) - 3)) + "|",
    ]
    for r in runs:
        cells = [
            r["name"],
            f"`{r['overrides']}`" if r["overrides"] else "-",
            _map_cell(r["map_settings"]),
            f"{r['colored_points']} / {r['points']}",
            str(r["images"]),
            _pct(r["hole_share"]),
            f"{r['render_cpu_s']:.0f} ({r['render_wall_s']:.0f})",
        ]
        for s in sequences:
            seq = r["sequences"][s]
            cells.append(
                f"{_pct(seq['rate'])} ({seq['right']} / {seq['accepted']} / {seq['queries']})"
            )
        cells.append(_pct(pooled(r)[2]))
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "Outcomes (`experiments/crossmodal_breakdown.py`), "
        + " / ".join(f"`{s}`" for s in sequences)
        + ":",
        "",
    ]
    outcomes = list(runs[0]["sequences"][sequences[0]]["outcomes"])
    lines += ["| setting | " + " | ".join(outcomes) + " |", "|:---|" + "---:|" * len(outcomes)]
    for r in runs:
        cells = [
            " / ".join(str(r["sequences"][s]["outcomes"][o]) for s in sequences) for o in outcomes
        ]
        lines.append(f"| {r['name']} | " + " | ".join(cells) + " |")
    lines += ["", "Wrong accepted poses: sequence, frame: horizontal / vertical (z) error, m.", ""]
    for r in runs:
        wrong = [
            f"{s} {frame}: {horizontal:.2f} / {vertical:+.2f}"
            for s in sequences
            for frame, horizontal, vertical in r["sequences"][s]["wrong_pose_errors"]
        ]
        lines.append(f"- {r['name']}: " + ("; ".join(wrong) if wrong else "none"))
    lines += [
        "",
        "Machine and load when each run's results were written: "
        + "; ".join(f"{r['name']}: {_rounded(r['machine'])}" for r in runs)
        + ".",
    ]
    if "choice" in report:
        choice = report["choice"]
        lines += [
            "",
            "Rule fixed before the runs (tuning seed): most right poses over the sequences "
            f"among the settings with pooled precision >= {_pct(choice['precision_floor'])} "
            "(the default's, or 95 %); ties to the lower render CPU time. "
            + "; ".join(
                f"{s['name']}: {s['right']} right at {_pct(s['precision'])}"
                + ("" if s["allowed"] else " (excluded)")
                for s in choice["scores"]
            )
            + f". Chosen: **{choice['chosen']}**.",
        ]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=Path, required=True, help="one dataset's run folders")
    parser.add_argument(
        "--command", action="append", required=True, help="the runs' commands, in order"
    )
    parser.add_argument("--choose", action="store_true", help="apply the tuning rule")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    folders = [p.parent for p in sorted(args.runs.glob("*/breakdown.json"))]
    if not folders:
        raise SystemExit(f"no runs under {args.runs}")
    runs = [read_run(f) for f in folders]
    runs.sort(key=lambda r: (r["name"] != DEFAULT, r["name"]))
    for r in runs:
        words = r["command"].split()  # the overrides follow task.out_dir
        out_dir = next(i for i, w in enumerate(words) if w.startswith("task.out_dir="))
        r["overrides"] = " ".join(words[out_dir + 1 :])
    this = shlex.join(["python3", "experiments/tls_render_table.py", *sys.argv[1:]])
    report = {
        "dataset": str(args.runs.name),
        "commands": [*args.command, f"PYTHONPATH=. {this}"],
        "runs": runs,
    }
    if args.choose:
        report["choice"] = choose(runs)
    write_report(
        args.out,
        markdown(report),
        {**report, "command": " && ".join(report["commands"])},
    )


if __name__ == "__main__":
    main()
