"""Render-pose coverage of the query sequences: how many queries have a render near them.

For each ``--point-map`` and each ``--floor-closing`` radius, render poses are selected as
``diffloc task=crossmodal`` does (:func:`~diffloc.crossmodal.pose_selection.select_render_poses`
with the indoor scene's ``task.poses``, only ``floor_closing_radius_m`` changed) and every
``--every``-th frame of each ``--sequence`` is scored against them with its ground truth
(scoring only): *covered* when a render lies within ``--spacing-m`` and 45 deg of it (the
``near`` of ``experiments/crossmodal_breakdown.py``). Also reported: render poses, samples
per floor and the free floor area (m^2) per floor, where the lidar map's ring gaps show.

Usage:
    PYTHONPATH=. python3 experiments/render_coverage.py --dataset /tmp/P/indoor_seed0 \\
        --point-map lidar_map --point-map tls_map --floor-closing 0.1 --floor-closing 0.3 \\
        --sequence query_same --sequence query_reverse \\
        --out experiments/results/render_coverage_indoor_seed0
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

from diffloc.crossmodal.pose_selection import PoseSelectionConfig, select_render_poses
from diffloc.eval.report_files import write_report
from diffloc.features.retrieval_eval import pairwise_pose_distances
from diffloc.io.dataset import MAP_FILES, read_sequence
from diffloc.io.ply import read_point_cloud
from diffloc.pipeline.crossmodal_report import RETRIEVAL_ANGLE_DEG

INDOOR = PoseSelectionConfig(cell_size_m=0.05, spacing_m=2.0)
"""``task.poses`` of ``task/scene/crossmodal_indoor.yaml``."""


def coverage(
    dataset: Path,
    point_map: str,
    radius_m: float,
    sequences: list[str],
    every: int,
    spacing_m: float,
) -> dict:
    """Poses, samples and free area per floor, and the covered share per sequence."""
    cloud = read_point_cloud(dataset / MAP_FILES[point_map])
    config = replace(INDOOR, floor_closing_radius_m=radius_m)
    selection = select_render_poses(cloud.points, cloud.normals, config)
    covered = {}
    for name in sequences:
        seq = read_sequence(dataset, name)
        frames = list(range(0, len(seq), every))
        distance, angle = pairwise_pose_distances(seq.T_wc[frames], selection.T_wc)
        near = (distance <= spacing_m) & (angle <= np.radians(RETRIEVAL_ANGLE_DEG))
        covered[name] = float(near.any(1).float().mean())
    return {
        "point_map": point_map,
        "floor_closing_radius_m": radius_m,
        "poses": len(selection),
        "samples_per_floor": [len(plan.samples_xy) for plan in selection.floors],
        "free_m2_per_floor": [
            round(float(plan.free.sum()) * plan.cell_size_m**2, 1) for plan in selection.floors
        ],
        "covered": covered,
    }


def markdown(report: dict) -> str:
    """One row per point map and radius."""
    sequences = report["sequences"]
    lines = [
        f"# Render-pose coverage of {report['dataset']}",
        "",
        f"Made by: `{report['command']}` (experiments/render_coverage.py docstring). Covered: a "
        f"render within {report['spacing_m']:g} m and 45 deg of the query (every "
        f"{report['every']}th frame).",
        "",
        "| point map | floor closing [m] | poses | samples per floor | free m^2 per floor | "
        + " | ".join(f"covered {s} [%]" for s in sequences)
        + " |",
        "|:---|---:|---:|---:|---:|" + "---:|" * len(sequences),
    ]
    for row in report["rows"]:
        cells = [
            row["point_map"],
            f"{row['floor_closing_radius_m']:g}",
            str(row["poses"]),
            " / ".join(map(str, row["samples_per_floor"])),
            " / ".join(map(str, row["free_m2_per_floor"])),
            *(f"{100 * row['covered'][s]:.1f}" for s in sequences),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--point-map", action="append", required=True, choices=sorted(MAP_FILES))
    parser.add_argument("--floor-closing", action="append", type=float, required=True)
    parser.add_argument("--sequence", action="append", required=True)
    parser.add_argument("--every", type=int, default=4)
    parser.add_argument("--spacing-m", type=float, default=2.0)
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    rows = [
        coverage(args.dataset, point_map, radius, args.sequence, args.every, args.spacing_m)
        for point_map in args.point_map
        for radius in args.floor_closing
    ]
    options = " ".join(
        [f"--point-map {m}" for m in args.point_map]
        + [f"--floor-closing {r:g}" for r in args.floor_closing]
        + [f"--sequence {s}" for s in args.sequence]
    )
    report = {
        "dataset": str(args.dataset),
        "sequences": args.sequence,
        "every": args.every,
        "spacing_m": args.spacing_m,
        "command": (
            f"PYTHONPATH=. python3 experiments/render_coverage.py --dataset {args.dataset} "
            f"{options} --every {args.every} --out {args.out}"
        ),
        "rows": rows,
    }
    write_report(args.out, markdown(report), report)
    print(markdown(report))


if __name__ == "__main__":
    main()
