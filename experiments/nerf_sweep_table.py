"""A Markdown table of ``bench_nerf.py`` runs (a sweep of ``--override`` settings, issue 19):
one row per JSONL record of the full variant, with its difference to the record without
overrides (tri-plane) on the same dataset (the baseline; the last such record when there
are several), and to the default of its own training seed (the record on the same dataset
whose only override is the same ``nerf.train.seed=K``; seed 0 without one), since the
training seed alone moves the held-out PSNR by tenths of a dB. ``sky opacity`` is the mean
rendered opacity of the held-out sky pixels (``sky_opacity_mean``; records made before it
existed show ``-``). ``run`` is the name of the JSONL file the record's command wrote (its
``--out``), which tells apart runs of one setting made with different code; ``render CPU s``
the CPU time of the run's 320x240 RGB-D render (``render_320x240_cpu_s``).

Writes ``<out>.md`` (first line: the command) and ``<out>.json`` (the rows).

    python3 experiments/nerf_sweep_table.py experiments/results/nerf_outdoor_sweep_seed0.jsonl \\
        --out experiments/results/nerf_outdoor_sweep_seed0
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from diffloc.eval.report_files import write_report

_MARKS_S = (60.0, 120.0)
"""CPU-time marks whose held-out PSNR the table shows (from the run's curve)."""


def _at_mark(curve: list, mark_s: float) -> float | None:
    """Held-out PSNR of the first evaluation at or after ``mark_s`` CPU s of a curve of
    (wall s, CPU s, step, dB) points; ``None`` when the run stopped before."""
    return next((p for _, cpu, _, p in curve if cpu >= mark_s), None)


def _setting(record: dict) -> str:
    """A record's overrides, and its encodings when not the tri-plane alone (records written
    before these keys existed: none, tri-plane); ``"default"`` when neither."""
    encodings = record.get("encodings", "triplane")
    parts = [
        *(record.get("overrides") or []),
        *([f"--encodings {encodings}"] * (encodings != "triplane")),
    ]
    return " ".join(parts) or "default"


_SEED = "nerf.train.seed="


def _run_name(record: dict) -> str:
    """The stem of the ``--out`` file of a record's command, ``"-"`` without one."""
    words = shlex.split(record.get("command", ""))
    outs = [words[i + 1] for i, w in enumerate(words[:-1]) if w == "--out"]
    return Path(outs[-1]).stem if outs else "-"


def _train_seed(record: dict) -> tuple[int, str]:
    """A record's training seed (0 without a ``nerf.train.seed`` override) and its setting
    without that override."""
    overrides = record.get("overrides") or []
    seeds = [int(o[len(_SEED) :]) for o in overrides if o.startswith(_SEED)]
    rest = dict(record, overrides=[o for o in overrides if not o.startswith(_SEED)])
    return (seeds[-1] if seeds else 0), _setting(rest)


def sweep_rows(records: list[dict]) -> list[dict]:
    """One row per record: its settings and figures, ``delta_db`` against the baseline
    (no overrides, same ``data``; ``None`` without one) and ``delta_same_seed_db`` against the
    default of the same training seed on the same ``data`` (``None`` without one).

    Raises:
        ValueError: a record without the full variant's ``psnr_heldout_db``.
    """
    for r in records:
        if "psnr_heldout_db" not in r:
            raise ValueError(f"record of {r.get('command')!r} has no full-variant run")
    baselines = {r["data"]: r["psnr_heldout_db"] for r in records if _setting(r) == "default"}
    seeded = {
        (r["data"], _train_seed(r)[0]): r["psnr_heldout_db"]
        for r in records
        if _train_seed(r)[1] == "default"
    }
    rows = []
    for r in records:
        base = baselines.get(r["data"])
        same_seed = seeded.get((r["data"], _train_seed(r)[0]))
        rows.append(
            {
                "setting": _setting(r),
                "run": _run_name(r),
                "data": r["data"],
                "psnr_heldout_db": r["psnr_heldout_db"],
                "delta_db": None if base is None else r["psnr_heldout_db"] - base,
                "delta_same_seed_db": (
                    None if same_seed is None else r["psnr_heldout_db"] - same_seed
                ),
                "surface_db": r.get("psnr_heldout_surface_db"),
                "sky_db": r.get("psnr_heldout_sky_db"),
                "sky_opacity": r.get("sky_opacity_mean"),
                "depth_cm": 100 * r["depth_median_abs_err_m"],
                "normal_deg": r["normal_median_err_deg"],
                "steps": r["steps"],
                "cpu_ms_per_step": r["cpu_ms_per_step"],
                "train_cpu_s": r["train_cpu_s"],
                "render_cpu_s": r.get("render_320x240_cpu_s"),
                **{f"psnr_at_{m:.0f}s_db": _at_mark(r["curve"], m) for m in _MARKS_S},
                "load": [r["load_avg_start"], r["load_avg_end"]],
            }
        )
    return rows


def _cell(value: float | None, fmt: str) -> str:
    return "-" if value is None else fmt.format(value)


def sweep_markdown(rows: list[dict], command: str) -> str:
    """The rows as a Markdown table after the command that made it."""
    marks = " | ".join(f"dB at {m:.0f} CPU s" for m in _MARKS_S)
    lines = [
        f"Made by: `{command}`",
        "",
        "| setting | run | data | held-out PSNR dB | vs default dB | vs default, same training "
        "seed dB | surface / sky dB | sky opacity | depth cm | normal deg | steps | CPU ms/step | "
        f"{marks} | render CPU s | load start / end |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|" + "---|" * len(_MARKS_S) + "---|---|",
    ]
    for r in rows:
        at = " | ".join(_cell(r[f"psnr_at_{m:.0f}s_db"], "{:.2f}") for m in _MARKS_S)
        lines.append(
            f"| `{r['setting']}` | {r['run']} | {Path(r['data']).name} | "
            f"{r['psnr_heldout_db']:.2f} | "
            f"{_cell(r['delta_db'], '{:+.2f}')} | {_cell(r['delta_same_seed_db'], '{:+.2f}')} | "
            f"{_cell(r['surface_db'], '{:.2f}')} / "
            f"{_cell(r['sky_db'], '{:.2f}')} | {_cell(r['sky_opacity'], '{:.3f}')} | "
            f"{r['depth_cm']:.1f} | {r['normal_deg']:.2f} | "
            f"{r['steps']} | {r['cpu_ms_per_step']:.0f} | {at} | "
            f"{_cell(r['render_cpu_s'], '{:.2f}')} | {r['load'][0]:.1f} / {r['load'][1]:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("jsonl", nargs="+", help="bench_nerf.py output files")
    parser.add_argument("--out", required=True, help="output path without suffix")
    args = parser.parse_args()
    records = [
        json.loads(line)
        for path in args.jsonl
        for line in Path(path).read_text().splitlines()
        if line.strip()
    ]
    command = shlex.join(["python3", *sys.argv])
    rows = sweep_rows(records)
    write_report(Path(args.out), sweep_markdown(rows, command), {"command": command, "rows": rows})
    print(sweep_markdown(rows, command))


if __name__ == "__main__":
    main()
