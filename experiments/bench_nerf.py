"""Radiance-field submap benchmark (issue 19): one JSON line of held-out PSNR, depth and normal
error, training time, time to 25 dB and render time, for the full SiLVR losses and the
photometric-only / photometric+depth ablations, and for both grid encodings.

Protocol: default indoor scene (seed 0), mapping run clustered into submaps (spectral, k=4),
the first submap (<= 80 frames); every 8th mapping frame is held out; images at 160x120.
The clustering, data and training settings are the ``nerf`` node ``diffloc task=train_nerf``
composes for ``--scene`` (``indoor``, the default, or ``outdoor``: mip-NeRF 360 contraction,
lidar returns up to 80 m, a 15 m box; ``diffloc/conf/nerf/scene/silvr_outdoor.yaml``), so
``--scene outdoor --data data/outdoor_seed0`` measures the outdoor courtyard; variant
``uncontracted`` trains the same field without the contraction, ``uncontracted_all`` also with
the box over all the returns used, ``planes512`` adds a 512 tri-plane level. ``--override``
adds Hydra overrides to the composed config (``nerf.train.field.background=learned``: the
learnt background colour the sky composites over, issue 19; ``nerf.train.loss.empty_weight=w``:
the empty-space loss on the lidar rays without a return, which are then built).
Training uses the images, mapping poses and lidar sweeps only. A held-out image's appearance
code is fitted on its left half (field frozen) and PSNR is taken on its right half (NeRF-W).
Ground-truth depth images are read here for scoring only (depth error, normal error).
Training time excludes evaluation; ``train_s`` is wall time on a shared machine,
``train_cpu_s`` the process CPU time (all threads); the curve holds (wall s, CPU s, step, dB);
``time_to_25db_s`` / ``cpu_to_25db_s`` are the wall / CPU time of the first evaluation at or
above 25 dB. ``--clock cpu`` puts the evaluation marks and the budget on CPU time (for a
loaded machine); the goals are wall-clock figures on a quiet one (``--clock wall``).
``--variants full,grid,uniform,noskip`` compares samplers (density grid + lidar-guided, grid
only, uniform, grid without empty-cell skipping; ``sampling``; ``--sampling-md`` /
``--sampling-png`` write the table / PSNR-vs-CPU plot; ``--eval-every-s`` sets the marks).
``--ablation-md`` writes the loss ablation (photometric only, + depth, + depth and normals) as
a Markdown table, with ``--ablation-reference`` (a JSONL whose last line is a full-variant run
measured at another moment, e.g. on a quiet machine) as an extra, marked row.
``--contraction-md`` writes the runs ``full`` and ``uncontracted`` as a Markdown table.
The record's first key, ``command``, is the command line that made it.
``--loc-results`` fills ``loc_rate_nerf`` from the ``results.json`` of a ``diffloc
task=crossmodal map=nerf`` run (rate within the loose bound, 1 m / 30 deg indoors, on
``query_same``; ``loc_rate_nerf_query_reverse`` too when it ran).

    PYTHONPATH=. OMP_NUM_THREADS=2 python3 experiments/bench_nerf.py --budget-s 600 \
        --out experiments/results/bench_nerf.jsonl

or in two processes of one thread each, merged into one line afterwards:

    python3 experiments/bench_nerf.py --threads 1 --encodings triplane,hashgrid --variants full \
        --budget-s 600 --ablation-budget-s 300 --out /tmp/nerf_a.jsonl --work /tmp/nerf_a &
    python3 experiments/bench_nerf.py --threads 1 --encodings triplane \
        --variants rgb_only,rgb_depth --ablation-budget-s 300 --out /tmp/nerf_b.jsonl \
        --work /tmp/nerf_b &
    wait; python3 experiments/bench_nerf.py --merge /tmp/nerf_a.jsonl /tmp/nerf_b.jsonl \
        --out experiments/results/bench_nerf.jsonl
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shlex
import sys
import time
from pathlib import Path

import lightning as L
import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from diffloc.config import nerf_settings
from diffloc.eval.curves import common_level, time_to_reach
from diffloc.eval.field_scores import heldout_field_scores
from diffloc.io.sequence import SequenceData
from diffloc.maps.nerf.data import SubmapRays, build_submap_rays
from diffloc.maps.nerf.module import NerfModule, NerfTrainConfig
from diffloc.maps.nerf.renderer import render_image
from diffloc.maps.nerf.train import fit_submap
from diffloc.pipeline.nerf_stage import submap_training_data

# variant -> (loss overrides, sampler overrides, field overrides, data overrides). "uniform"
# drops the density grid (importance samples and empty-cell skipping) and the lidar-guided
# samples and gives every ray 40 stratified samples (camera rays get 32 and lidar rays 40 with
# the grid), so it never has fewer samples than the default. "uncontracted" switches the
# contraction off (outdoors: nothing beyond the box of the returns within 15 m is in the field);
# "uncontracted_all" also spans the box over all the returns used (up to 80 m outdoors).
# "planes512" adds a 512 x 512 tri-plane level (finer texture in a large outdoor box).
VARIANTS = {
    "full": ({}, {}, {}, {}),
    "rgb_only": ({"depth_weight": 0.0, "normal_weight": 0.0}, {}, {}, {}),
    "rgb_depth": ({"normal_weight": 0.0}, {}, {}, {}),
    "grid": ({}, {"guided_samples": 0}, {}, {}),
    "noskip": ({}, {"skip_density": 0.0}, {}, {}),
    "uniform": (
        {},
        {"importance_samples": 0, "guided_samples": 0, "uniform_samples": 40, "skip_density": 0},
        {},
        {},
    ),
    "uncontracted": ({}, {}, {"contracted": False}, {}),
    "uncontracted_all": ({}, {}, {"contracted": False}, {"box_range_m": 0.0}),
    "planes512": ({}, {}, {"triplane_resolutions": [64, 128, 256, 512]}, {}),
}
EVAL_AT_S = (30, 60, 90, 120, 180, 240, 300, 450, 600, 900)


def evaluate(
    module: NerfModule, seq: SequenceData, rays: SubmapRays, full: bool
) -> dict[str, float]:
    """Held-out scores of the submap's field (``heldout_field_scores``: left-half code,
    right-half PSNR; with ``full`` depth / normal errors, scoring only)."""
    return heldout_field_scores(module.field, module.grid, seq, rays.camera, rays.heldout, full)


class TimedEvaluation(L.Callback):
    """Evaluate at training-time marks (evaluation time excluded) and stop at the budget.
    Marks and budget are on ``clock``: ``"wall"`` or ``"cpu"`` (process time, all threads)."""

    def __init__(
        self,
        seq: SequenceData,
        rays: SubmapRays,
        budget_s: float,
        clock: str,
        every_s: float | None = None,
    ) -> None:
        self.seq, self.rays, self.budget_s = seq, rays, budget_s
        self.elapsed = self.train_cpu_s if clock == "cpu" else self.train_s
        self.curve: list[tuple[float, int, float]] = []
        self.excluded = self.excluded_cpu = 0.0
        marks = EVAL_AT_S if every_s is None else np.arange(every_s, budget_s, every_s)
        self.marks = [float(m) for m in marks if m < budget_s] + [budget_s]

    def train_s(self) -> float:
        return time.perf_counter() - self.start - self.excluded

    def train_cpu_s(self) -> float:
        return time.process_time() - self.cpu_start - self.excluded_cpu

    def on_train_start(self, trainer: L.Trainer, module: NerfModule) -> None:
        self.start, self.cpu_start = time.perf_counter(), time.process_time()

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
        elapsed = self.elapsed()
        if self.marks and elapsed >= self.marks[0]:
            while self.marks and elapsed >= self.marks[0]:
                self.marks.pop(0)
            tic, cpu = time.perf_counter(), time.process_time()
            psnr = evaluate(module, self.seq, self.rays, full=False)["psnr_heldout_db"]
            self.excluded += time.perf_counter() - tic
            self.excluded_cpu += time.process_time() - cpu
            point = (round(self.train_s(), 1), round(self.train_cpu_s(), 1), trainer.global_step)
            self.curve.append((*point, round(psnr, 3)))
            print(f"  {point} psnr={psnr:.2f}", flush=True)
        if elapsed >= self.budget_s:
            trainer.should_stop = True


def _first_reaching(curve: list, psnr_db: float) -> tuple[float | None, float | None]:
    """(wall s, CPU s) of the first evaluation at or above ``psnr_db``, or ``(None, None)``."""
    reached = [(wall, cpu) for wall, cpu, _, p in curve if p >= psnr_db]
    return reached[0] if reached else (None, None)


def _render_times(module: NerfModule, seq: SequenceData, rays: SubmapRays) -> dict[str, float]:
    """Wall and CPU seconds of a 320x240 RGB-D render, without and with normals."""
    camera = seq.camera.scaled(0.5)
    code = module.field.appearance.weight.detach().mean(0)
    times = {}
    for suffix, normals in (("", False), ("_normals", True)):
        tic, cpu = time.perf_counter(), time.process_time()
        pose = seq.T_wc[rays.heldout[0]]
        render_image(module.field, module.grid, camera, pose, code, with_normals=normals)
        times[f"render_320x240{suffix}_s"] = round(time.perf_counter() - tic, 3)
        times[f"render_320x240{suffix}_cpu_s"] = round(time.process_time() - cpu, 3)
    return times


def run_variant(
    seq: SequenceData,
    rays: SubmapRays,
    config: NerfTrainConfig,
    budget_s: float,
    out: Path,
    clock: str,
    every_s: float | None = None,
) -> dict:
    timer = TimedEvaluation(seq, rays, budget_s, clock, every_s)
    module = fit_submap(rays, config, out, epochs=10**6, callbacks=[timer], show_progress=False)
    train_s, train_cpu_s = timer.train_s(), timer.train_cpu_s()
    result = evaluate(module, seq, rays, full=True)
    wall_25, cpu_25 = _first_reaching(timer.curve, 25.0)
    result |= {
        "train_s": round(train_s, 1),
        "train_cpu_s": round(train_cpu_s, 1),
        "steps": module.global_step,
        "cpu_ms_per_step": round(1000 * train_cpu_s / max(module.global_step, 1), 1),
        "time_to_25db_s": wall_25,
        "cpu_to_25db_s": cpu_25,
        **_render_times(module, seq, rays),
        "curve": timer.curve,
    }
    return result


# sampler runs of a record: (key suffix, label); "full" is the default (grid + lidar-guided).
SAMPLERS = (
    ("_uniform", "uniform (40 per ray)"),
    ("_grid", "grid"),
    ("", "grid + lidar-guided"),
    ("_noskip", "grid + lidar-guided, no skipping"),
)


def sampling_comparison(record: dict) -> dict:
    """The sampler runs of a record (uniform, grid, grid + lidar-guided) compared at one
    held-out PSNR level, the highest every run reached at an evaluation mark: the CPU seconds
    each first reached it (linear between marks), and each run's final figures."""
    runs = [(suffix, label) for suffix, label in SAMPLERS if f"curve{suffix}" in record]
    scores = {label: [p for *_, p in record[f"curve{suffix}"]] for suffix, label in runs}
    level = common_level(scores)
    out: dict = {"target_psnr_db": level, "runs": {}}
    for suffix, label in runs:
        curve = record[f"curve{suffix}"]
        cpu = [c for _, c, _, _ in curve]
        out["runs"][label] = {
            "cpu_to_target_s": time_to_reach(cpu, scores[label], level),
            "psnr_heldout_db": record[f"psnr_heldout_db{suffix}"],
            "depth_median_abs_err_m": record[f"depth_median_abs_err_m{suffix}"],
            "normal_median_err_deg": record[f"normal_median_err_deg{suffix}"],
            "train_cpu_s": record[f"train_cpu_s{suffix}"],
            "steps": record[f"steps{suffix}"],
            "cpu_ms_per_step": record[f"cpu_ms_per_step{suffix}"],
        }
    return out


def merge(parts: list[str], out: Path, args: argparse.Namespace) -> None:
    """One JSON line from the last lines of partial runs (run in parallel processes); keys
    that differ between parts (load averages, times) are kept per part under ``parts``."""
    records = [json.loads(Path(p).read_text().splitlines()[-1]) for p in parts]
    merged = {}
    for record in records:
        for key, value in record.items():
            merged.setdefault(key, value)
    merged["command"] = shlex.join(["python3", *sys.argv])
    keys = ("command", "prepare_s", "threads", "load_avg_start", "load_avg_end")
    merged["parts"] = [{k: r[k] for k in keys if k in r} for r in records]
    _finish(merged, out, args)


def sampling_markdown(record: dict) -> str:
    """The sampler comparison of a record as a Markdown table."""
    c = record["sampling"]
    labels = list(c["runs"])
    rows = [
        (f"CPU s to first reach {c['target_psnr_db']:.2f} dB", "cpu_to_target_s", "{:.0f}"),
        ("held-out PSNR at the end, dB", "psnr_heldout_db", "{:.2f}"),
        ("median depth error at the end, cm", "depth_median_abs_err_m", "{:.1f}"),
        ("median normal error at the end, deg", "normal_median_err_deg", "{:.1f}"),
        ("training CPU s", "train_cpu_s", "{:.0f}"),
        ("steps", "steps", "{}"),
        ("CPU ms per step", "cpu_ms_per_step", "{:.0f}"),
    ]
    lines = [
        f"Samplers ({record['data']}, submap {record['submap']}, {record['threads']} thread(s) "
        f"per run, runs side by side, load {record['load_avg_start']:.1f} at start); level = "
        f"the highest held-out PSNR every run reached at an evaluation mark, "
        f"{c['target_psnr_db']:.2f} dB (time linear between marks).",
        "",
        "| | " + " | ".join(labels) + " |",
        "|---|" + "---|" * len(labels),
    ]
    for label, key, fmt in rows:
        values = [c["runs"][run][key] for run in labels]
        values = [v * 100 if v is not None and key.endswith("_m") else v for v in values]
        lines.append(
            f"| {label} | "
            + " | ".join("not reached" if v is None else fmt.format(v) for v in values)
            + " |"
        )
    for suffix, label in SAMPLERS:
        if label in c["runs"]:
            points = ", ".join(f"{cpu:.0f}: {p:.2f}" for _, cpu, _, p in record[f"curve{suffix}"])
            lines.append(
                f"| PSNR at CPU s, {label} | "
                + " | ".join(points if run == label else "" for run in labels)
                + " |"
            )
    return "\n".join(lines) + "\n"


def sampling_plot(record: dict, path: str) -> None:
    """PNG of held-out PSNR against training CPU seconds, one line per sampler run."""
    figure = Figure(figsize=(6.0, 4.5), dpi=100)
    FigureCanvasAgg(figure)
    ax = figure.add_subplot()
    for suffix, label in SAMPLERS:
        if f"curve{suffix}" in record:
            curve = record[f"curve{suffix}"]
            ax.plot([c for _, c, _, _ in curve], [p for *_, p in curve], marker="o", label=label)
    ax.axhline(record["sampling"]["target_psnr_db"], color="grey", linestyle=":", linewidth=1)
    ax.set_xlabel("training CPU s (process time)")
    ax.set_ylabel("held-out PSNR, dB (right half)")
    ax.set_title(f"samplers, {Path(record['data']).name} submap {record['submap']}")
    ax.grid(alpha=0.3)
    ax.legend()
    figure.savefig(path)


def _add_sampling_comparison(record: dict, markdown_path: str | None, png: str | None) -> None:
    """Add ``sampling`` when the record holds two or more sampler runs (and write the table
    and the plot)."""
    if sum(f"curve{suffix}" in record for suffix, _ in SAMPLERS) >= 2:
        record["sampling"] = sampling_comparison(record)
        if markdown_path:
            Path(markdown_path).write_text(sampling_markdown(record))
        if png:
            sampling_plot(record, png)


# loss ablation rows: (key suffix of the run, label); the full run has no suffix.
ABLATIONS = (
    ("_rgb_only", "photometric only"),
    ("_rgb_depth", "photometric + depth (Eq. 6)"),
    ("", "photometric + depth + normals (Eq. 6, 7)"),
)
_ABLATION_COLUMNS = (
    ("held-out PSNR dB", "psnr_heldout_db", "{:.2f}", 1),
    ("median depth error cm", "depth_median_abs_err_m", "{:.1f}", 100),
    ("median normal error deg", "normal_median_err_deg", "{:.1f}", 1),
    ("steps", "steps", "{}", 1),
    ("training wall s", "train_s", "{:.0f}", 1),
    ("training CPU s", "train_cpu_s", "{:.0f}", 1),
    ("wall s to 25 dB", "time_to_25db_s", "{:.0f}", 1),
    ("CPU s to 25 dB", "cpu_to_25db_s", "{:.0f}", 1),
)


def _ablation_row(label: str, record: dict, suffix: str) -> str:
    cells = []
    for _, key, fmt, scale in _ABLATION_COLUMNS:
        value = record.get(f"{key}{suffix}")
        cells.append("not reached" if value is None else fmt.format(value * scale))
    return f"| {label} | " + " | ".join(cells) + " |"


def _budget(record: dict, key: str = "budget_s") -> float:
    """A record's training budget (older records: the training time on its clock)."""
    for name in (key, "budget_s"):
        if name in record:
            return record[name]
    return record["train_cpu_s"] if record.get("clock") == "cpu" else record["train_s"]


def _runs_table(title: str, first_column: str, record: dict, rows: tuple) -> list[str]:
    """The lines of a table of a record's runs ``rows`` ((key suffix, label) pairs, those the
    record holds), after the record's command (when it has one) and a caption."""
    budget, ablation_budget = _budget(record), _budget(record, "ablation_budget_s")
    budgets = (
        f"{budget:.0f} s"
        if ablation_budget == budget
        else f"{budget:.0f} s full, {ablation_budget:.0f} s ablations"
    )
    processes = (
        f"{len(record['parts'])} processes merged by --merge (loads at their starts: "
        + ", ".join(f"{part['load_avg_start']:.1f}" for part in record["parts"])
        + ")"
        if "parts" in record
        else "runs one after another in one process"
    )
    clock = record.get("clock", "wall")
    parts = [f"`{part['command']}`" for part in record.get("parts", ()) if "command" in part]
    command = [f"Made by: `{record['command']}`", ""] if "command" in record else []
    if parts:
        command.insert(1, f"merging the last records of {', '.join(parts)}")
    return [
        *command,
        f"{title} ({record['data']}, submap {record['submap']}, {record['train_frames']} "
        f"training frames, 160x120; {record['threads']} thread(s) per process, {processes}, "
        f"{budgets} {clock}-clock budget each; load "
        f"{record['load_avg_start']:.1f} at the start, {record['load_avg_end']:.1f} at the end).",
        "",
        f"| {first_column} | " + " | ".join(name for name, *_ in _ABLATION_COLUMNS) + " |",
        "|---|" + "---|" * len(_ABLATION_COLUMNS),
        *(
            _ablation_row(label, record, suffix)
            for suffix, label in rows
            if f"psnr_heldout_db{suffix}" in record
        ),
    ]


# contraction rows: (key suffix of the run, label).
CONTRACTION = (
    ("_uncontracted_all", "no contraction, box of all the returns used"),
    ("_uncontracted", "no contraction, the same box"),
    ("", "mip-NeRF 360 contraction"),
)


def contraction_markdown(record: dict) -> str:
    """The runs ``full`` and ``uncontracted`` / ``uncontracted_all`` (those the record holds)
    of a record as a Markdown table (all losses, same budget).

    Raises:
        ValueError: the full run or both uncontracted runs are missing (naming the
            ``--variants`` to run).
    """
    held = {s for s, _ in CONTRACTION if f"psnr_heldout_db{s}" in record}
    if "" not in held or held == {""}:
        raise ValueError(
            f"the contraction table needs the run full and one of uncontracted, "
            f"uncontracted_all; the record of {record.get('data')} has "
            f"{sorted(s.lstrip('_') or 'full' for s in held)}: run bench_nerf.py with "
            "--variants full,uncontracted,uncontracted_all"
        )
    lines = _runs_table("Scene contraction", "field", record, CONTRACTION)
    return "\n".join(lines) + "\n"


def ablation_markdown(record: dict, reference: dict | None = None) -> str:
    """The loss ablation of a record (runs ``rgb_only``, ``rgb_depth`` and ``full``) as a
    Markdown table; ``reference``, a full-variant record measured at another moment, is added
    as a last row marked as such (the record's own full run may then be missing).

    Raises:
        ValueError: a run is missing (naming the ``--variants`` to run).
    """
    missing = [s.lstrip("_") for s, _ in ABLATIONS[:2] if f"psnr_heldout_db{s}" not in record]
    if "psnr_heldout_db" not in record and reference is None:
        missing.append("full")
    if missing:
        raise ValueError(
            f"the ablation table needs the runs {missing}, not in the record of "
            f"{record.get('data')}: run bench_nerf.py with --variants full,rgb_only,rgb_depth "
            "(or give the full run of another moment with --ablation-reference)"
        )
    lines = _runs_table("Loss ablation", "losses", record, ABLATIONS)
    if reference is not None:
        label = (
            f"{ABLATIONS[2][1]}, measured at another moment ({reference['threads']} thread(s), "
            f"{_budget(reference):.0f} s {reference.get('clock', 'wall')}-clock budget, load "
            f"{reference['load_avg_start']:.1f} at the start)"
        )
        lines.append(_ablation_row(label, reference, ""))
    return "\n".join(lines) + "\n"


def add_loc_rate(record: dict, results_path: str | os.PathLike) -> None:
    """Set ``loc_rate_nerf`` (``query_same``, within the run's loose bound / 30 deg) and,
    when it ran, ``loc_rate_nerf_query_reverse`` from a ``task=crossmodal map=nerf``
    ``results.json``.

    Raises:
        ValueError: the results are not of ``map=nerf`` or lack ``query_same``.
    """
    results = json.loads(Path(results_path).read_text())
    if results.get("map") != "nerf":
        raise ValueError(
            f"{results_path} is a map={results.get('map')} run; loc_rate_nerf needs the "
            "results.json of diffloc task=crossmodal map=nerf"
        )
    sequences, loose = results["sequences"], f"{results['loose_m']:g}m_30deg"
    if "query_same" not in sequences:
        raise ValueError(
            f"{results_path} has no query_same sequence ({sorted(sequences)}); rerun "
            "task=crossmodal map=nerf with query_same in task.sequences"
        )
    record["loc_rate_nerf"] = sequences["query_same"]["rates"][loose]
    if "query_reverse" in sequences:
        record["loc_rate_nerf_query_reverse"] = sequences["query_reverse"]["rates"][loose]
    record["loc_results"] = str(results_path)


def _finish(record: dict, out: Path, args: argparse.Namespace) -> None:
    """Add the comparisons the arguments ask for, append the record, then write the tables."""
    _add_sampling_comparison(record, args.sampling_md, args.sampling_png)
    if args.loc_results:
        add_loc_rate(record, args.loc_results)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "a") as f:
        f.write(json.dumps(record) + "\n")
    print(json.dumps(record))
    if args.ablation_md:
        reference = None
        if args.ablation_reference:
            lines = Path(args.ablation_reference).read_text().splitlines()
            reference = json.loads(lines[-1])
        Path(args.ablation_md).write_text(ablation_markdown(record, reference))
    if args.contraction_md:
        Path(args.contraction_md).write_text(contraction_markdown(record))


def variant_config(base: NerfTrainConfig, encoding: str, variant: str) -> NerfTrainConfig:
    """``base`` with the encoding ``encoding`` and the overrides of ``VARIANTS[variant]``."""
    loss, sampler, field, _ = VARIANTS[variant]
    return dataclasses.replace(
        base,
        field=dataclasses.replace(base.field, encoding=encoding, **field),
        loss=dataclasses.replace(base.loss, **loss),
        sampler=dataclasses.replace(base.sampler, **sampler),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", choices=("indoor", "outdoor"), default="indoor")
    parser.add_argument("--data", help="dataset folder (default: data/<scene>_seed0)")
    parser.add_argument("--budget-s", type=float, default=600.0)
    parser.add_argument("--clock", choices=("wall", "cpu"), default="wall")
    parser.add_argument("--sampling-md", help="write the sampler table (Markdown) here")
    parser.add_argument("--sampling-png", help="write the sampler PSNR-vs-CPU plot here")
    parser.add_argument(
        "--eval-every-s", type=float, help="evaluation marks every this many s (default: fixed)"
    )
    parser.add_argument("--ablation-budget-s", type=float, default=None)
    parser.add_argument("--variants", default="full,rgb_only,rgb_depth")
    parser.add_argument("--encodings", default="triplane,hashgrid")
    parser.add_argument("--submap", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--work", default="/tmp/nerf_bench")
    parser.add_argument("--out", default="experiments/results/bench_nerf.jsonl")
    parser.add_argument("--merge", nargs="+", help="merge the last lines of these JSONL files")
    parser.add_argument("--ablation-md", help="write the loss ablation table (Markdown) here")
    parser.add_argument(
        "--contraction-md", help="write the contracted / uncontracted table (Markdown) here"
    )
    parser.add_argument(
        "--ablation-reference", help="JSONL whose last line is a full run of another moment"
    )
    parser.add_argument("--loc-results", help="results.json of task=crossmodal map=nerf")
    parser.add_argument(
        "--override",
        nargs="+",
        default=[],
        help="Hydra overrides, e.g. nerf.train.field.background=learned",
    )
    args = parser.parse_args()
    if args.merge:
        merge(args.merge, Path(args.out), args)
        return
    torch.set_num_threads(args.threads)
    data = args.data or f"data/{args.scene}_seed0"
    nerf = nerf_settings(args.scene, [f"nerf.submap={args.submap}", *args.override])
    tic = time.perf_counter()
    seq, submap, rays = submap_training_data(data, nerf)
    no_return = rays.no_return is not None
    record: dict = {
        "command": shlex.join(["python3", *sys.argv]),
        "data": data,
        "scene": args.scene,
        "contracted": nerf.train.field.contracted,
        "background": nerf.train.field.background,
        "overrides": args.override,
        "encodings": args.encodings,
        "submap": args.submap,
        "frames": len(submap.frames),
        "train_frames": len(rays.frames),
        "heldout_frames": len(rays.heldout),
        "lidar_rays": len(rays.lidar),
        "no_return_rays": len(rays.no_return) if no_return else None,
        "empty_weight": nerf.train.loss.empty_weight,
        "box_m": [round(float(v), 2) for v in rays.box_max - rays.box_min],
        "prepare_s": round(time.perf_counter() - tic, 1),
        "threads": args.threads,
        "budget_s": args.budget_s,
        "ablation_budget_s": args.ablation_budget_s or args.budget_s,
        "load_avg_start": os.getloadavg()[0],
    }
    print(json.dumps(record), flush=True)
    ablation_budget = args.ablation_budget_s or args.budget_s
    encodings = args.encodings.split(",")
    for encoding in encodings:
        for variant in args.variants.split(","):
            if encoding != encodings[0] and variant != "full":
                continue
            config = variant_config(nerf.train, encoding, variant)
            main_run = variant == "full" and encoding == encodings[0]
            budget = args.budget_s if main_run else ablation_budget
            print(f"{encoding} {variant}: {budget:.0f} s", flush=True)
            out = Path(args.work) / f"{encoding}_{variant}"
            data_changes = VARIANTS[variant][3]
            used = rays
            if data_changes:
                data_config = dataclasses.replace(nerf.data, **data_changes)
                used = build_submap_rays(seq, submap.frames, data_config, no_return=no_return)
            result = run_variant(seq, used, config, budget, out, args.clock, args.eval_every_s)
            if data_changes:
                result["box_m"] = [round(float(v), 2) for v in used.box_max - used.box_min]
            suffix = "" if variant == "full" else f"_{variant}"
            prefix = "" if encoding == encodings[0] else f"{encoding}_"
            record |= {f"{prefix}{k}{suffix}": v for k, v in result.items()}
            print(json.dumps(result), flush=True)
    record["load_avg_end"] = os.getloadavg()[0]
    record["clock"] = args.clock
    _finish(record, Path(args.out), args)


if __name__ == "__main__":
    main()
