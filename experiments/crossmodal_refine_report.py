"""A ``diffloc task=crossmodal task.refine.enabled=true`` run as a committed Markdown + JSON report.

Reads the run folder's ``results.json`` and ``results.md`` (the localisation and refinement
tables the task wrote) and writes ``<out>.md`` (the commands that made it first, then the
run's tables) and ``<out>.json`` (the commands and the run's results, every stage's record
included), through :func:`diffloc.eval.report_files.write_report`.

    PYTHONPATH=. python3 experiments/crossmodal_refine_report.py \\
        --run experiments/runs/nerf_refine_indoor_seed0 \\
        --made-by "diffloc task=crossmodal map=nerf ... task.refine.enabled=true" \\
        --out experiments/results/crossmodal_nerf_refine_indoor_seed0
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from diffloc.eval.report_files import made_by_lines, write_report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, help="the task's run folder (task.out_dir)")
    parser.add_argument("--made-by", action="append", default=[], help="the run's command")
    parser.add_argument("--note", default="", help="a paragraph under the commands")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    run = Path(args.run)
    results = json.loads((run / "results.json").read_text(encoding="utf-8"))
    if results.get("refine") is None:
        raise SystemExit(f"{run}/results.json: the run had task.refine.enabled=false")
    commands = [*args.made_by, "PYTHONPATH=. python3 " + shlex.join(sys.argv)]
    body = (run / "results.md").read_text(encoding="utf-8").splitlines()
    lines = [body[0], "", *made_by_lines(commands)]
    lines += [args.note, ""] if args.note else []
    lines += [line for k, line in enumerate(body[1:]) if k or line]  # one blank line above
    write_report(Path(args.out), "\n".join(lines), {"commands": commands, "results": results})
    print(Path(args.out).with_suffix(".md").read_text(encoding="utf-8"))


if __name__ == "__main__":
    main()
