"""Early ray termination (``SamplerConfig.stop_transmittance``) against the full render of a
trained radiance field: 320x240 RGB-D render CPU time (process time) and the largest change of
colour, opacity and depth, at poses of the mapping run, the variants interleaved (same moment).

    PYTHONPATH=. OMP_NUM_THREADS=1 python3 experiments/nerf_termination.py \
        --field data/indoor_seed0/nerf/submap_0/field --data data/indoor_seed0 \
        --out experiments/results/nerf_termination.json

Writes one JSON record and prints a Markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import time
from pathlib import Path

import torch

from diffloc.eval.report_files import write_benchmark
from diffloc.io.dataset import read_sequence
from diffloc.maps.nerf.export import load_field
from diffloc.maps.nerf.renderer import render_image
from diffloc.maps.nerf.submaps import SubmapConfig, cluster_trajectory


def count_evaluations(field) -> list[int]:
    """Make ``field.geometry`` count the points it evaluates (the density evaluations of an
    RGB-D render); returns the counter, ``[points]``."""
    counter, geometry = [0], field.geometry

    def counted(points):
        counter[0] += len(points)
        return geometry(points)

    field.geometry = counted
    return counter


def render(field, grid, camera, pose, code, stop: float) -> tuple[dict, float]:
    """One RGB-D render with ``stop_transmittance = stop`` and its process CPU seconds."""
    grid.config = dataclasses.replace(grid.config, stop_transmittance=stop)
    tic = time.process_time()
    out = render_image(field, grid, camera, pose, code)
    return out, time.process_time() - tic


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--field", required=True, help="an exported field folder")
    parser.add_argument("--data", default="data/indoor_seed0")
    parser.add_argument("--submap", type=int, default=0)
    parser.add_argument("--poses", type=int, default=4, help="poses of the submap, evenly spread")
    parser.add_argument("--stops", default="1e-4,1e-3")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default="experiments/results/nerf_termination.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    field, grid = load_field(args.field)
    field.eval()
    seq = read_sequence(args.data, "mapping")
    frames = cluster_trajectory(seq.T_wc, SubmapConfig(num_submaps=4))[args.submap].frames
    frames = [int(f) for f in frames[:: max(1, len(frames) // args.poses)][: args.poses]]
    camera = seq.camera.scaled(0.5)
    code = field.appearance.weight.detach().mean(0)
    stops = [0.0] + [float(s) for s in args.stops.split(",")]
    load_start = os.getloadavg()[0]
    cpu: dict[float, list[float]] = {s: [] for s in stops}
    evaluations = {s: 0 for s in stops}
    counter = count_evaluations(field)
    diff: dict[float, dict[str, float]] = {
        s: {"rgb": 0.0, "opacity": 0.0, "depth_m": 0.0} for s in stops
    }
    for frame in frames:
        pose = seq.T_wc[frame].float()
        reference = None
        for stop in stops:
            counter[0] = 0
            out, seconds = render(field, grid, camera, pose, code, stop)
            evaluations[stop] += counter[0]
            cpu[stop].append(seconds)
            reference = out if reference is None else reference
            for key, name in (("rgb", "rgb"), ("opacity", "opacity"), ("depth", "depth_m")):
                change = float((out[key] - reference[key]).abs().max())
                diff[stop][name] = max(diff[stop][name], change)
    record = {
        "field": args.field,
        "data": args.data,
        "frames": frames,
        "size": [camera.width, camera.height],
        "threads": args.threads,
        "load_avg_start": load_start,
        "load_avg_end": os.getloadavg()[0],
        "cpu_s_median": {str(s): round(statistics.median(cpu[s]), 3) for s in stops},
        "cpu_s": {str(s): [round(c, 3) for c in cpu[s]] for s in stops},
        "density_evaluations_per_ray": {
            str(s): round(evaluations[s] / (len(frames) * camera.width * camera.height), 2)
            for s in stops
        },
        "max_abs_change": {str(s): diff[s] for s in stops},
    }
    write_benchmark(Path(args.out), record)
    print(
        "| stop_transmittance | median CPU s | evaluations per ray | max change rgb | opacity |"
        " depth, m |"
    )
    print("|---|---|---|---|---|---|")
    for s in stops:
        d = diff[s]
        print(
            f"| {s:g} | {statistics.median(cpu[s]):.2f} "
            f"| {record['density_evaluations_per_ray'][str(s)]:.1f} | {d['rgb']:.1e} "
            f"| {d['opacity']:.1e} "
            f"| {d['depth_m']:.1e} |"
        )


if __name__ == "__main__":
    main()
