"""The radiance-field map of the rendered-database localisation on one dataset, as Markdown + JSON.

Reads the results of ``diffloc task=crossmodal map=nerf`` (its ``results.json``) and of the
same task with another map for reference (optional), and measures each served field's
held-out PSNR as the database sees it: the field of ``<dataset>/crossmodal/nerf/map/fields``
rendered with its mean appearance code (as the database renders are) at the submap's
held-out mapping frames (every ``--holdout-every``-th frame, as ``task=train_nerf`` holds them
out) at 160x120, against the real image (whole image; no code fitted, so exposure differences
count). The query sequences' ground truth is read only through the task's scores.

Usage::

    PYTHONPATH=. python3 experiments/crossmodal_nerf.py --dataset /tmp/K/indoor_seed0 \\
        --nerf <run folder>/results.json --reference tls=<tls run folder>/results.json \\
        --train-note "8 epochs of 100 steps per submap" \\
        --out experiments/results/crossmodal_nerf_indoor_seed0
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from diffloc.crossmodal.submap_fields import SubmapFieldMap
from diffloc.eval.report_files import write_report
from diffloc.io.dataset import read_sequence
from diffloc.maps.nerf.data import load_image, split_frames

RATES = ("0.25m_2deg", "0.5m_5deg", "1m_30deg")


def field_psnr(dataset: Path, holdout_every: int, width: int) -> dict[str, dict]:
    """Per served submap: held-out frames and their mean PSNR (dB) of the mean-code render."""
    rgbd_map = SubmapFieldMap.from_folder(dataset / "crossmodal" / "nerf" / "map" / "fields")
    seq = read_sequence(dataset, "mapping")
    camera = seq.camera.scaled(width / seq.camera.width)
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
        }
    return out


def _row(name: str, results: dict, sequence: str) -> str:
    entry = results["sequences"].get(sequence)
    if entry is None:
        return f"| {name} | {sequence} | not run |  |  |  |  |  |  |"
    rates = " | ".join(f"{100 * entry['rates'][r]:.1f}" for r in RATES)
    precision, mate = entry["precision"], entry["mate_m"]
    return (
        f"| {name} | {sequence} | {entry['queries']} | {entry['accepted']} | "
        f"{'-' if precision is None else f'{100 * precision:.1f}'} | {rates} | "
        f"{100 * entry['retrieval_rate']:.1f} | {'-' if mate is None else f'{mate:.3f}'} |"
    )


def markdown(record: dict) -> str:
    nerf = record["nerf"]
    runs = {"nerf": nerf, **record["reference"]}
    lines = [
        f"# Rendered-database localisation in the radiance-field map ({nerf['dataset']})",
        "",
        f"`diffloc task=crossmodal map=nerf`, fields: {record['train_note']}. Database: "
        f"{nerf['database_images']} renders of {nerf['image_size']} from "
        f"{len(nerf['stages']['map']['served'])} submap fields, hole share "
        f"{100 * nerf['hole_share']:.1f} %; queries every {nerf['every']}-th frame. "
        f"Rates in % of all queries; mATE in m; machine {nerf['machine']}.",
        "",
        "| map | sequence | queries | accepted | precision | 0.25 m / 2 deg | 0.5 m / 5 deg "
        "| 1 m / 30 deg | retrieval | mATE |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for sequence in nerf["sequences"]:
        lines += [_row(name, results, sequence) for name, results in runs.items()]
    lines += [
        "",
        "Fields as the database sees them (mean appearance code, whole-image PSNR at the "
        "submap's held-out mapping frames, 160x120):",
        "",
        "| submap | render poses served | held-out frames | PSNR dB | hole share | CPU s / image |",
        "|---|---|---|---|---|---|",
    ]
    stage = nerf["stages"]["map"]
    served = dict(zip(stage["served"], stage["poses_served"], strict=True))
    for k, f in record["fields"].items():
        lines.append(
            f"| {k} | {served[int(k)]} | {len(f['heldout_frames'])} | {f['psnr_db']:.2f} | "
            f"{100 * f['hole_share']:.1f} % | {f['render_cpu_s_per_image']:.2f} |"
        )
    if record["made_by"]:
        lines += ["", "Made by:", "", *(f"    {line}" for line in record["made_by"])]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--nerf", type=Path, required=True, help="results.json of map=nerf")
    parser.add_argument("--reference", action="append", default=[], help="name=results.json")
    parser.add_argument("--train-note", default="", help="how the fields were trained")
    parser.add_argument("--made-by", action="append", default=[], help="a command line")
    parser.add_argument("--holdout-every", type=int, default=8)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    torch.set_num_threads(1)
    references = dict(item.split("=", 1) for item in args.reference)
    record = {
        "nerf": json.loads(args.nerf.read_text()),
        "reference": {k: json.loads(Path(v).read_text()) for k, v in references.items()},
        "train_note": args.train_note,
        "made_by": args.made_by,
        "fields": field_psnr(args.dataset, args.holdout_every, args.width),
    }
    write_report(args.out, markdown(record), record)
    print(markdown(record))


if __name__ == "__main__":
    main()
