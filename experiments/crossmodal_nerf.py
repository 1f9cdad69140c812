"""The radiance-field map of the rendered-database localisation on one dataset, as Markdown + JSON.

Reads the results of ``diffloc task=crossmodal map=nerf`` (its ``results.json``) and of the
same task with another map for reference (optional), and measures each served field's
held-out PSNR as the database sees it: the field of ``<dataset>/crossmodal/nerf/map/fields``
rendered with its mean appearance code (as the database renders are) at the submap's
held-out mapping frames (every ``--holdout-every``-th frame, as ``task=train_nerf`` holds them
out) at 160x120, against the real image (whole image; no code fitted, so exposure differences
count), and at the same frames by bench_nerf's protocol
(:func:`diffloc.eval.field_scores.heldout_field_scores`: code fitted on the left half, PSNR on
the right half, median depth and normal errors against the ground-truth depth; scoring only).
The query sequences' ground truth is read only through the task's scores.

References beside the NeRF rows: ``--reference name=results.json`` (another ``task=crossmodal``
run), ``--reference-record name=<report>.json`` (the NeRF run of an earlier report of this
script, e.g. a committed one) and ``--reference-breakdown name=<breakdown>.json:<map>`` (a
map's queries in a report of ``experiments/crossmodal_breakdown.py``: rates and mATE from its
per-query errors, retrieval from its top-1 hits; it records no time per query).

Usage::

    PYTHONPATH=. python3 experiments/crossmodal_nerf.py --dataset /tmp/K/indoor_seed0 \\
        --nerf <run folder>/results.json --reference tls=<tls run folder>/results.json \\
        --reference-breakdown \\
        mesh=experiments/results/crossmodal_breakdown_indoor_seed0.json:mesh \\
        --train-note "8 epochs of 100 steps per submap" \\
        --out experiments/results/crossmodal_nerf_indoor_seed0
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

from diffloc.crossmodal.submap_fields import SubmapFieldMap
from diffloc.eval.field_scores import heldout_field_scores
from diffloc.eval.metrics import PoseErrors, mean_ate
from diffloc.eval.report_files import write_report
from diffloc.io.dataset import read_sequence
from diffloc.maps.nerf.data import load_image, split_frames
from diffloc.pipeline.crossmodal_report import localization_rates

RATES = ("0.25m_2deg", "0.5m_5deg", "1m_30deg")


def field_psnr(dataset: Path, holdout_every: int, width: int, timing_width: int) -> dict[str, dict]:
    """Per served submap: held-out frames, mean PSNR (dB) of the mean-code render, bench_nerf's
    scores, and the CPU / wall seconds per RGB-D render at ``timing_width``."""
    rgbd_map = SubmapFieldMap.from_folder(dataset / "crossmodal" / "nerf" / "map" / "fields")
    seq = read_sequence(dataset, "mapping")
    camera = seq.camera.scaled(width / seq.camera.width)
    timing_camera = seq.camera.scaled(timing_width / seq.camera.width)
    out = {}
    for k, field in sorted(rgbd_map.fields.items()):
        submap = rgbd_map.submaps[k]
        _, heldout = split_frames(submap.frames, holdout_every)
        start = time.process_time()
        views = field.render(seq.T_wc[heldout], camera)
        errors = [
            float(((views.rgb[i] - load_image(seq, f, camera)) ** 2).mean())
            for i, f in enumerate(heldout)
        ]
        out[str(k)] = {
            "heldout_frames": heldout,
            "psnr_db": float(np.mean([-10 * np.log10(e) for e in errors])),
            "hole_share": float((views.depth <= 0).float().mean()),
            "render_cpu_s_per_image": (time.process_time() - start) / len(heldout),
            "bench_protocol": heldout_field_scores(
                field.field, field.grid, seq, camera, heldout, full=True
            ),
        }
        start, wall = time.process_time(), time.perf_counter()
        field.render(seq.T_wc[heldout], timing_camera)
        out[str(k)]["timing_size"] = f"{timing_camera.width}x{timing_camera.height}"
        out[str(k)]["timing_cpu_s_per_image"] = (time.process_time() - start) / len(heldout)
        out[str(k)]["timing_wall_s_per_image"] = (time.perf_counter() - wall) / len(heldout)
    return out


def breakdown_results(path: Path, map_name: str) -> dict:
    """A map's sequences in a ``crossmodal_breakdown.py`` record as ``results.json`` entries
    (no time per query: the breakdown does not record it)."""
    record = json.loads(path.read_text())
    sequences = {}
    for part in record["maps"]:
        if part["map"] != map_name:
            continue
        rows = part["rows"]
        errors = PoseErrors(
            np.array([r["error_m"] for r in rows], dtype=float),
            np.array([r["error_deg"] for r in rows], dtype=float),
            np.array([r["accepted"] for r in rows], dtype=bool),
        )
        rates = localization_rates(
            errors.translation_m, errors.rotation_deg, errors.localized, record["loose_m"]
        )
        with_test = part["photometric"]["with"]
        sequences[part["sequence"]] = {
            "queries": part["queries"],
            "accepted": with_test["accepted"],
            "precision": with_test["precision"],
            "rates": rates,
            "retrieval_rate": part["top1_retrieval_rate"],
            "mate_m": None if not errors.localized.any() else mean_ate(errors),
            "median_ms_per_query": None,
        }
    if not sequences:
        raise ValueError(f"{path} has no rows of map {map_name!r}")
    return {"sequences": sequences}


def _row(name: str, results: dict, sequence: str) -> str:
    entry = results["sequences"].get(sequence)
    if entry is None:
        return f"| {name} | {sequence} | not run |  |  |  |  |  |  |  |"
    rates = " | ".join(f"{100 * entry['rates'][r]:.1f}" for r in RATES)
    precision, mate = entry["precision"], entry["mate_m"]
    ms = entry.get("median_ms_per_query")
    return (
        f"| {name} | {sequence} | {entry['queries']} | {entry['accepted']} | "
        f"{'-' if precision is None else f'{100 * precision:.1f}'} | {rates} | "
        f"{100 * entry['retrieval_rate']:.1f} | {'-' if mate is None else f'{mate:.3f}'} | "
        f"{'-' if ms is None else f'{ms:.0f}'} |"
    )


def markdown(record: dict) -> str:
    nerf = record["nerf"]
    runs = {"nerf": nerf, **record["reference"]}
    made_by = [*record["made_by"], record["command"]]
    lines = [
        f"# Rendered-database localisation in the radiance-field map ({nerf['dataset']})",
        "",
        "Made by:",
        "",
        *(f"    {line}" for line in made_by),
        "",
        f"`diffloc task=crossmodal map=nerf`, fields: {record['train_note']}. Database: "
        f"{nerf['database_images']} renders of {nerf['image_size']} from "
        f"{len(nerf['stages']['map']['served'])} submap fields, hole share "
        f"{100 * nerf['hole_share']:.1f} %; queries every {nerf['every']}-th frame. "
        f"Rates in % of all queries; mATE in m; machine {nerf['machine']}.",
        "",
        "| map | sequence | queries | accepted | precision | 0.25 m / 2 deg | 0.5 m / 5 deg "
        "| 1 m / 30 deg | retrieval | mATE | ms / query |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for sequence in nerf["sequences"]:
        lines += [_row(name, results, sequence) for name, results in runs.items()]
    lines += [
        "",
        "Fields at the submap's held-out mapping frames (160x120): as the database sees them "
        "(mean appearance code, whole-image PSNR, hole share, render CPU time) and by "
        "bench_nerf's protocol (code fitted on the left half, PSNR on the right half; median "
        "depth and normal error against the ground truth); render time on one thread at "
        f"load {record['load_average'][0]:.1f} when scored:",
        "",
        "| submap | render poses served | held-out frames | PSNR dB | hole share | CPU s / image "
        "| held-out PSNR dB (bench) | depth error cm | normal error deg "
        "| render CPU s / wall s (size) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    stage = nerf["stages"]["map"]
    served = dict(zip(stage["served"], stage["poses_served"], strict=True))
    for k, f in record["fields"].items():
        bench = f["bench_protocol"]
        lines.append(
            f"| {k} | {served[int(k)]} | {len(f['heldout_frames'])} | {f['psnr_db']:.2f} | "
            f"{100 * f['hole_share']:.1f} % | {f['render_cpu_s_per_image']:.2f} | "
            f"{bench['psnr_heldout_db']:.2f} | {100 * bench['depth_median_abs_err_m']:.1f} | "
            f"{bench['normal_median_err_deg']:.1f} | {f['timing_cpu_s_per_image']:.2f} / "
            f"{f['timing_wall_s_per_image']:.2f} ({f['timing_size']}) |"
        )
    if record["notes"]:
        lines += ["", *record["notes"]]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--nerf", type=Path, required=True, help="results.json of map=nerf")
    parser.add_argument("--reference", action="append", default=[], help="name=results.json")
    parser.add_argument(
        "--reference-record", action="append", default=[], help="name=<report of this script>.json"
    )
    parser.add_argument(
        "--reference-breakdown",
        action="append",
        default=[],
        help="name=<crossmodal_breakdown report>.json:<map>",
    )
    parser.add_argument("--note", action="append", default=[], help="a paragraph after the tables")
    parser.add_argument("--train-note", default="", help="how the fields were trained")
    parser.add_argument("--made-by", action="append", default=[], help="a command line")
    parser.add_argument("--holdout-every", type=int, default=8)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--timing-width", type=int, default=320, help="width of the timed render")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    torch.set_num_threads(1)
    references = {}
    for item in args.reference:
        name, path = item.split("=", 1)
        references[name] = json.loads(Path(path).read_text())
    for item in args.reference_record:
        name, path = item.split("=", 1)
        references[name] = json.loads(Path(path).read_text())["nerf"]
    for item in args.reference_breakdown:
        name, spec = item.split("=", 1)
        path, map_name = spec.rsplit(":", 1)
        references[name] = breakdown_results(Path(path), map_name)
    record = {
        "command": "PYTHONPATH=. python3 " + shlex.join(sys.argv),
        "made_by": args.made_by,
        "nerf": json.loads(args.nerf.read_text()),
        "reference": references,
        "train_note": args.train_note,
        "notes": args.note,
        "load_average": list(os.getloadavg()),
        "fields": field_psnr(args.dataset, args.holdout_every, args.width, args.timing_width),
    }
    write_report(args.out, markdown(record), record)
    print(markdown(record))


if __name__ == "__main__":
    main()
