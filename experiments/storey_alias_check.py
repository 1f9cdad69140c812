"""Issue 15/18, offline: is an accepted pose explained as well one storey up or down?

Several wrong poses the rendered-database localiser accepts are storey aliases: the right x, y
and heading one storey (about 3 m) above or below the truth, because the storeys look alike
there (e.g. indoor seed 0, TLS, ``query_same`` frame 20: 2.98 m, 0.6 deg off; seed 2, mesh,
``query_reverse`` frame 84: 3.02 m, 0.4 deg off). The rival test cannot refuse them when no
candidate of the other storey was retrieved. A rendered map can be rendered at the alias pose
itself. For every accepted pose of a recorded localisation (``<dataset>/crossmodal/<map>/
localize_<sequence>/``, the localiser's own verdicts, before any storey-alias stage) this
script renders the map at the pose and at the same pose moved to every other floor (the floors
of the map's render poses), matches the query against each render and solves PnP
(:func:`~diffloc.reloc.storey_alias.storey_alias_evidence`, what ``task.storey_alias`` runs),
and reports which poses :func:`~diffloc.reloc.storey_alias.is_storey_alias` calls aliases at
each ``--ratio`` (an alias render's pose at least the validation's ``theta_dist_m`` away with
at least ``ratio`` times the inliers of the render at the pose; 0.7 is the validation's own
rival ratio, 1.0 the chosen ``task.storey_alias.ratio``). Ground truth is read for scoring only
(right: within ``task.loose_m`` and 30 deg).

Usage:
    OMP_NUM_THREADS=1 PYTHONPATH=. python3 experiments/storey_alias_check.py \\
        --dataset data/indoor_seed0 --map tls \\
        --sequence query_same --sequence query_reverse --sequence changed \\
        --out experiments/results/storey_alias_tls_indoor_seed0
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

from diffloc.eval.metrics import is_correct, pose_errors
from diffloc.eval.report_files import made_by_lines, write_report
from diffloc.io.dataset import read_sequence
from diffloc.io.npz import read_npz_archive
from diffloc.pipeline.crossmodal_stage import SequenceLocalization, crossmodal_folder, scaled_images
from diffloc.reloc.rendered import localizer_networks
from diffloc.reloc.storey_alias import (
    alias_poses,
    floor_heights,
    is_storey_alias,
    storey_alias_evidence,
)
from diffloc.threads import intra_op_threads
from experiments.rerender_check import MAX_ROT_DEG, load_map

POINT_MAPS = {"tls": "tls_map", "mesh": "lidar_map", "cloud": "lidar_map"}
"""The point map whose render poses (and floors) each map option's database uses."""


def map_floors(dataset: Path, option: str) -> torch.Tensor:
    """(F,) the floor heights of the render poses ``option``'s database was rendered at."""
    path = crossmodal_folder(dataset) / f"poses_{POINT_MAPS[option]}" / "poses.npz"
    arrays = read_npz_archive(path)
    return floor_heights(torch.from_numpy(arrays["T_wc"]), torch.from_numpy(arrays["floor_index"]))


def rerendered_verdicts(path: Path, sequence: str) -> dict[int, bool]:
    """Frame -> right, of the queries whose pass-1 re-render evidence
    (``experiments/rerender_check.py``'s JSON) the validation accepts."""
    rows = json.loads(path.read_text())["sequences"][sequence]["queries"]
    return {r["frame"]: r["pass 1"]["right"] for r in rows if r["pass 1"]["accepted"]}


def check_sequence(
    dataset, option, sequence, task, rgbd_map, render_camera, networks, heights, rerender=None
):
    """Per query accepted by the localiser (``rerender``: by the validation of the re-render
    evidence of ``experiments/rerender_check.py``'s JSON, scored by its pass-1 pose): the
    inliers at the pose and at its aliases."""
    folder = crossmodal_folder(dataset) / option / f"localize_{sequence}"
    config = task.localizer_for(option)
    loc = SequenceLocalization.load(folder / "localization.npz")
    seq = read_sequence(dataset, sequence)
    camera = seq.camera.scaled(render_camera.width / seq.camera.width)
    T_gt = seq.T_wc[loc.frames].numpy()  # scoring only
    errors = pose_errors(loc.T_wc, T_gt, loc.success.astype(bool))
    right = is_correct(errors, task.loose_m, MAX_ROT_DEG)
    rows = []
    chosen = np.flatnonzero(loc.accepted)
    if rerender is not None:
        verdict = rerendered_verdicts(rerender, sequence)
        chosen = np.flatnonzero(np.isin(loc.frames, list(verdict)))
        right = right.copy()
        for q in chosen.tolist():
            right[q] = verdict[int(loc.frames[q])]
    for q in chosen.tolist():
        image = scaled_images(seq, camera, [int(loc.frames[q])])[0]
        view = (image, networks[0].extract(image), camera)
        T_wc = torch.from_numpy(loc.T_wc[q])
        e = storey_alias_evidence(rgbd_map, T_wc, heights, render_camera, view, networks, config)
        rows.append(
            {
                "frame": int(loc.frames[q]),
                "right": bool(right[q]),
                "error_m": float(errors.translation_m[q]),
                "error_deg": float(errors.rotation_deg[q]),
                "recorded_inliers": int(loc.num_inliers[q]),
                "own_inliers": e.own_inliers,
                "alias_inliers": list(e.alias_inliers),
                "alias_distance_m": [None if np.isnan(d) else d for d in e.alias_distance_m],
                "alias_dz_m": [float(T[2, 3] - T_wc[2, 3]) for T in alias_poses(T_wc, heights)],
                "evidence": e,
            }
        )
    return {"queries": len(loc.frames), "rows": rows}


def verdicts(report: dict, ratio: float) -> None:
    """Mark every row with its verdict at ``ratio`` (key ``alias_<ratio>``)."""
    for s in report["sequences"].values():
        for r in s["rows"]:
            r[f"alias_{ratio:g}"] = is_storey_alias(r["evidence"], report["theta_dist_m"], ratio)


def markdown(report: dict) -> str:
    ratios = report["ratios"]
    lines = [
        f"# Storey aliases of accepted poses: `map={report['map']}`, {report['dataset']}",
        "",
        *made_by_lines(report["command"]),
        f"Floors (median camera height of the render poses per floor): {report['heights']}. An "
        "accepted pose is a storey alias at ratio r when the map rendered at the pose moved to "
        f"another floor gives a pose at least {report['theta_dist_m']:g} m away with at least r "
        "x the inliers of the map rendered at the pose itself. Right: within "
        f"{report['loose_m']:g} m / {MAX_ROT_DEG:g} deg (truth read for scoring only)."
        + (
            ""
            if report["rerender"] is None
            else f" Poses tested: those the validation accepts on the re-render evidence of "
            f"`{report['rerender']}` (pass 1; right and wrong by its pass-1 pose), not the "
            "localiser's accepted ones."
        ),
        "",
        "| sequence | queries | accepted right | accepted wrong | "
        + " | ".join(f"right called alias ({r:g}) | wrong called alias ({r:g})" for r in ratios)
        + " |",
        "|---|---:|---:|---:|" + "---:|---:|" * len(ratios),
    ]
    total = np.zeros(3 + 2 * len(ratios), dtype=int)
    for name, s in report["sequences"].items():
        rows = s["rows"]
        counts = [s["queries"], sum(r["right"] for r in rows), sum(not r["right"] for r in rows)]
        for ratio in ratios:
            key = f"alias_{ratio:g}"
            counts += [
                sum(r["right"] and r[key] for r in rows),
                sum(not r["right"] and r[key] for r in rows),
            ]
        total += np.array(counts)
        lines.append(f"| {name} | " + " | ".join(str(c) for c in counts) + " |")
    lines.append("| all | " + " | ".join(str(c) for c in total) + " |")
    lines += [
        "",
        "Every wrong accepted pose and every pose called an alias at any ratio (inliers: "
        "recorded / render at the pose; each alias render: dz, inliers, distance of its pose):",
        "",
        "| sequence | frame | right | error | inliers | aliases | "
        + " | ".join(f"alias ({r:g})" for r in ratios)
        + " |",
        "|---|---:|---|---|---|---|" + "---|" * len(ratios),
    ]
    for name, s in report["sequences"].items():
        for r in s["rows"]:
            called = [r[f"alias_{ratio:g}"] for ratio in ratios]
            if r["right"] and not any(called):
                continue
            aliases = "; ".join(
                f"dz {dz:+.2f}: {n}" + (f" at {d:.2f} m" if d is not None else " (no pose)")
                for dz, n, d in zip(
                    r["alias_dz_m"], r["alias_inliers"], r["alias_distance_m"], strict=True
                )
            )
            lines.append(
                f"| {name} | {r['frame']} | {r['right']} | {r['error_m']:.2f} m / "
                f"{r['error_deg']:.1f} deg | {r['recorded_inliers']} / {r['own_inliers']} | "
                f"{aliases} | " + " | ".join(str(c) for c in called) + " |"
            )
    lines += ["", f"Wall {report['wall_s']:.0f} s, load {report['load']} at the end."]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--map", choices=tuple(POINT_MAPS), required=True)
    parser.add_argument("--sequence", action="append", required=True)
    parser.add_argument("--override", action="append", default=[])
    parser.add_argument("--ratio", type=float, action="append", help="default: 0.7 and 1.0")
    parser.add_argument(
        "--rerender",
        type=Path,
        help="experiments/rerender_check.py's JSON: test the poses its pass 1 accepts instead",
    )
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    start = time.perf_counter()
    with intra_op_threads(1), torch.no_grad():
        rgbd_map, task, render_camera, _ = load_map(args.dataset, args.map, args.override)
        networks = localizer_networks(task.localizer_for(args.map))
        heights = map_floors(args.dataset, args.map)
        sequences = {
            name: check_sequence(
                args.dataset,
                args.map,
                name,
                task,
                rgbd_map,
                render_camera,
                networks,
                heights,
                args.rerender,
            )
            for name in args.sequence
        }
    validation = task.localizer_for(args.map).validation
    report = {
        "command": "OMP_NUM_THREADS=1 PYTHONPATH=. python3 " + shlex.join(sys.argv),
        "dataset": str(args.dataset),
        "map": args.map,
        "rerender": None if args.rerender is None else str(args.rerender),
        "heights": [round(float(h), 2) for h in heights],
        "theta_dist_m": validation.theta_dist_m,
        "ratios": args.ratio or [0.7, 1.0],
        "loose_m": task.loose_m,
        "sequences": sequences,
        "wall_s": time.perf_counter() - start,
        "load": [round(x, 2) for x in os.getloadavg()],
    }
    for ratio in report["ratios"]:
        verdicts(report, ratio)
    for s in sequences.values():
        for r in s["rows"]:
            del r["evidence"]  # kept as the lists beside it
    md, _ = write_report(args.out, markdown(report), report)
    print(md.read_text())


if __name__ == "__main__":
    main()
