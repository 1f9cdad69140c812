"""Per-step CPU time of radiance-field training, for a same-moment A/B of two checkouts.

Trains submap 0 of the indoor scene (seed 0; spectral clustering, k=4, default data config)
from scratch with the default ``NerfTrainConfig``, stepping a ``NerfModule`` by hand with its
Adam optimiser (no Lightning loop, no logging cost), one thread, and records the process CPU
time of every step (forward, backward, optimiser step; the density-grid refresh falls on
every ``grid_update_every``-th step). Batches and sample jitter are functions of the step, so
two checkouts see the same rays. Run one process per checkout side by side (the machine load
then hits both alike), then compare the two JSON files::

    python3 experiments/nerf_step_ab.py --rays /tmp/ab/rays.pkl --steps 0  # the ray cache
    PYTHONPATH=/path/to/main python3 experiments/nerf_step_ab.py --out /tmp/ab/main.json \\
        --rays /tmp/ab/rays.pkl &
    PYTHONPATH=. python3 experiments/nerf_step_ab.py --out /tmp/ab/branch.json \\
        --rays /tmp/ab/rays.pkl &
    wait; python3 experiments/nerf_step_ab.py --compare /tmp/ab/main.json /tmp/ab/branch.json

``--rays`` caches the submap's rays (a local pickle of this machine's own run, not an
interchange format) so that both processes start from the same tensors without rebuilding.
The comparison prints the median CPU ms per step over step windows (the mean includes the
grid refreshes) as a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import statistics
import time
from pathlib import Path

import torch

from diffloc.eval.report_files import write_benchmark
from diffloc.io.dataset import read_sequence
from diffloc.maps.nerf.data import SubmapDataConfig, SubmapRays, build_submap_rays
from diffloc.maps.nerf.module import NerfModule, NerfTrainConfig, StepBatches
from diffloc.maps.nerf.submaps import SubmapConfig, cluster_trajectory

WINDOWS = ((3, 35), (35, 100), (100, 200), (200, 240))


def _rays(dataset: Path, cache: Path | None) -> SubmapRays:
    if cache is not None and cache.exists():
        with cache.open("rb") as f:
            return pickle.load(f)
    seq = read_sequence(dataset, "mapping")
    submap = cluster_trajectory(seq.T_wc, SubmapConfig(num_submaps=4))[0]
    rays = build_submap_rays(seq, submap.frames, SubmapDataConfig())
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        with cache.open("wb") as f:
            pickle.dump(rays, f)
    return rays


def run(dataset: Path, cache: Path | None, steps: int) -> dict:
    """Train ``steps`` steps; per-step CPU ms and loss terms."""
    torch.set_num_threads(1)
    rays = _rays(dataset, cache)
    cfg = NerfTrainConfig()
    module = NerfModule(cfg, rays.box_min, rays.box_max, len(rays.frames))
    terms: dict[str, float] = {}
    module.log = lambda name, value, **_: terms.__setitem__(name, float(value))
    optimiser = module.configure_optimizers()
    batches = StepBatches(rays, cfg.ray_batch, cfg.lidar_batch, cfg.seed)
    step = [0]
    type(module).global_step = property(lambda _: step[0])
    records = []
    for k in range(steps):
        step[0] = k
        batch = batches[k]
        tic = time.process_time()
        loss = module.training_step(batch, k)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        records.append({"step": k, "cpu_ms": 1000 * (time.process_time() - tic), **terms})
    return {"pythonpath": os.environ.get("PYTHONPATH", ""), "steps": records}


def compare(paths: list[Path]) -> str:
    """Markdown table: median CPU ms per step over :data:`WINDOWS`, mean, last train PSNR."""
    runs = [json.loads(p.read_text())["steps"] for p in paths]
    head = "| steps | " + " | ".join(p.stem for p in paths) + " |"
    lines = [head, "|" + "---|" * (len(paths) + 1)]
    for a, b in [w for w in WINDOWS if w[1] <= min(len(run) for run in runs)]:
        cells = [f"{statistics.median(r['cpu_ms'] for r in run[a:b]):.0f}" for run in runs]
        lines.append(f"| {a}-{b - 1} (median ms) | " + " | ".join(cells) + " |")
    means = [f"{statistics.mean(r['cpu_ms'] for r in run[3:]):.0f}" for run in runs]
    lines.append("| 3-end (mean ms) | " + " | ".join(means) + " |")
    psnr = [f"{statistics.mean(r['psnr_train'] for r in run[-20:]):.2f}" for run in runs]
    lines.append("| train PSNR, last 20 steps (dB) | " + " | ".join(psnr) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", type=Path, default=Path("data/indoor_seed0"))
    parser.add_argument("--rays", type=Path, default=None, help="cache of the submap's rays")
    parser.add_argument("--steps", type=int, default=240)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--compare", type=Path, nargs="+", default=None)
    args = parser.parse_args()
    if args.compare:
        print(compare(args.compare))
        return
    result = run(args.dataset, args.rays, args.steps)
    if args.out is not None:
        write_benchmark(args.out, result)
    if args.out is not None and args.steps > 3:
        print(compare([args.out]))


if __name__ == "__main__":
    main()
