"""Held-out seed reports: per-seed statistics and paired differences with bootstrap intervals.

The pipeline is tuned on scene seed 0; these reports read jobs on other seeds (ARCHITECTURE,
"Honest evaluation"). Each takes job folders and/or Hydra sweep folders (e.g. from
``diffloc -m task=main scene.seed=1,2,3,4,5 hydra.sweep.dir=DIR``), groups the jobs by variant
(their overrides without ``scene.seed``), refuses jobs on a tuning seed, and writes a Markdown
table headed by the commands that made the runs, plus the rows as JSON.

Usage:
    # Per variant, sequence and figure: every seed's value, mean, std and the worst seed.
    python3 experiments/heldout.py stats DIR... --name main --command "diffloc -m ..."
        -> experiments/results/heldout_main.md / .json

    # Paired differences better - worse of the per-query success (correct within 0.3 m), with
    # a paired bootstrap 95 % interval over all seeds' queries; "ordering holds" only where the
    # interval is above zero.
    python3 experiments/heldout.py differences DIR... --name table2_xfeat \
        --compare reloc.method.points=FN,F --compare reloc.method.points=F,naive \
        --command "diffloc -m ..."
        -> experiments/results/heldout_table2_xfeat_differences.md / .json
"""

from __future__ import annotations

import argparse
import shlex
from collections.abc import Sequence
from pathlib import Path

from diffloc.eval.bootstrap import DEFAULT_RESAMPLES
from diffloc.eval.differences import Comparison, difference_markdown, difference_rows
from diffloc.eval.heldout import heldout_markdown, heldout_rows
from diffloc.eval.report_files import write_report
from diffloc.eval.sweeps import check_held_out, group_variants, load_jobs

SCRIPT = "experiments/heldout.py"


def report_text(commands: Sequence[str], aggregation: str, table: str, notes: Sequence[str]) -> str:
    """The Markdown report: the run commands, the aggregation command, notes and the table."""
    runs = "\n".join(commands)
    parts = [f"Made by:\n\n```bash\n{runs}\n{aggregation}\n```\n"]
    parts += [f"{note}\n" for note in notes]
    return "\n".join([*parts, f"{table}\n"])


def aggregation_command(args: argparse.Namespace) -> str:
    """This script's command line for the report (the long ``--command`` texts left out)."""
    words = ["python3", SCRIPT, args.report, *map(str, args.runs), "--name", args.name]
    for comparison in getattr(args, "compare", None) or []:
        words += ["--compare", comparison]
    return shlex.join(words)


def run(args: argparse.Namespace) -> Path:
    """Build the requested report; returns the path of the ``.md`` written."""
    jobs = load_jobs(args.runs)
    check_held_out(jobs, args.tuning_seeds)
    if args.report == "stats":
        rows = heldout_rows(group_variants(jobs))
        table, out = heldout_markdown(rows), args.results_dir / f"heldout_{args.name}"
    else:
        comparisons = [Comparison.parse(c) for c in args.compare]
        rows = difference_rows(
            jobs, comparisons, resamples=args.resamples, seed=args.bootstrap_seed
        )
        table = difference_markdown(rows)
        out = args.results_dir / f"heldout_{args.name}_differences"
    text = report_text(args.command, aggregation_command(args), table, args.note)
    write_report(out, text, rows)
    print(text)
    return out.with_suffix(".md")


def parser() -> argparse.ArgumentParser:
    """The command-line interface (module doc)."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="report", required=True)
    stats = sub.add_parser("stats", help="per-seed values, mean, std, worst seed")
    diff = sub.add_parser("differences", help="paired differences with bootstrap intervals")
    diff.add_argument(
        "--compare",
        action="append",
        required=True,
        help="KEY=BETTER,WORSE, e.g. reloc.method.points=FN,F (repeatable)",
    )
    diff.add_argument("--resamples", type=int, default=DEFAULT_RESAMPLES)
    diff.add_argument("--bootstrap-seed", type=int, default=0)
    for s in (stats, diff):
        s.add_argument("runs", type=Path, nargs="+", help="job folders and/or sweep folders")
        s.add_argument("--name", required=True, help="output name: heldout_<name>[...].md")
        s.add_argument(
            "--command", action="append", required=True, help="a command that made the runs"
        )
        s.add_argument("--note", action="append", default=[], help="a line under the header")
        s.add_argument("--results-dir", type=Path, default=Path("experiments/results"))
        s.add_argument(
            "--tuning-seeds",
            type=int,
            nargs="*",
            default=[0],
            help="scene seeds used for tuning, refused (default: 0; give none to allow all)",
        )
    return p


def main(argv: Sequence[str] | None = None) -> Path:
    """Parse ``argv`` and write the report."""
    return run(parser().parse_args(argv))


if __name__ == "__main__":
    main()
