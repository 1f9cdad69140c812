"""Benchmark the simulator on the default scenes; the last stdout line is one JSON object.

Usage:
    python experiments/bench_sim.py [--scene indoor] [--repeats 10]
        [--out experiments/results/bench_sim.json]

Keys: ``world_generation_s``, ``raycast_640x480_ms`` (median time of one RGB-D frame: ray cast,
texture lookup, shading, exposure and noise), ``raycast_only_640x480_ms`` (open3d casting of the
same rays), ``lidar_sweep_ms`` (median 16x1024 spinning-lidar sweep), ``tls_scan_ms``, and the
machine's thread count.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from diffloc.benchmark import median_ms
from diffloc.config import compose_config
from diffloc.eval.report_files import write_benchmark
from diffloc.render.raycast import camera_rays
from diffloc.sim.dataset import DatasetSimulator
from diffloc.sim.lidar import simulate_station_scan, simulate_sweep


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="indoor", choices=["indoor", "outdoor"])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--out", type=Path, default=Path("experiments/results/bench_sim.json"))
    args = parser.parse_args()

    cfg = compose_config([f"scene={args.scene}"])
    scene = OmegaConf.to_object(cfg.scene)

    start = time.perf_counter()
    simulator = DatasetSimulator(scene, show_progress=False)
    generation_s = time.perf_counter() - start
    renderer = simulator.renderer(False)
    seq = scene.sequences[0]
    timestamps, T_wb = simulator.body_trajectory(seq)
    frames = np.linspace(0, len(timestamps) - 1, args.repeats + 1).round().astype(int)
    generator = torch.Generator().manual_seed(0)
    calls = iter(np.resize(frames, 10 * (args.repeats + 1)))

    def render_frame() -> None:
        simulator.render_frames(renderer, seq, timestamps, T_wb, np.array([next(calls)]), generator)

    T_wc = T_wb[frames[:1]] @ simulator.T_body_camera
    origins, directions = camera_rays(simulator.camera, T_wc)

    def cast_only() -> None:
        renderer.raycaster.cast(origins[0], directions[0])

    rng = np.random.default_rng(0)
    T_wl = T_wb[len(T_wb) // 2] @ simulator.T_body_lidar
    station = simulator.world.tls_stations[0]
    result = {
        "scene": args.scene,
        "threads": torch.get_num_threads(),
        "triangles": simulator.world.mesh.num_faces,
        "world_generation_s": round(generation_s, 3),
        "raycast_640x480_ms": round(median_ms(render_frame, args.repeats), 2),
        "raycast_only_640x480_ms": round(median_ms(cast_only, args.repeats), 2),
        "lidar_sweep_ms": round(
            median_ms(
                lambda: simulate_sweep(renderer.raycaster, T_wl, scene.lidar, rng), args.repeats
            ),
            2,
        ),
        "lidar_rays_per_sweep": scene.lidar.beams * scene.lidar.azimuth_steps,
        "tls_scan_ms": round(
            median_ms(
                lambda: simulate_station_scan(renderer.raycaster, station, scene.tls, rng), 3
            ),
            2,
        ),
    }
    print(write_benchmark(args.out, result))


if __name__ == "__main__":
    main()
