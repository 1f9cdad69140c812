"""Benchmark the splatting renderers on the default indoor scene; the last stdout line is JSON.

Usage:
    python experiments/bench_render.py [--repeats 10] [--out experiments/results/bench_render.json]

Simulates the default indoor dataset if it is not there yet. Keys:

- ``splat_1m_points_640x480_ms``: hard RGB-D render of 1M coloured lidar-map points with
  inverse-depth sizes (seed 2 Eq. 2), median; ``splat_1m_points_peak_mb``: peak resident memory
  added by that render (``VmHWM`` after resetting it through ``/proc/self/clear_refs``);
- ``surfel_index_500k_640x480_ms``: surfel index render of 500k surfels (0.02 m, seed 1's indoor
  radius, built from the mapping sweeps and the scanner map around the camera), median;
- ``open3d_mesh_raycast_640x480_ms``: open3d ``RaycastingScene`` on the textured mesh, same
  camera, same run, its calls interleaved with the surfel renders (so that load changes on a
  shared machine hit both alike); ``surfel_index_to_open3d_ratio``: the ratio of the two;
  ``load_average``: the 1-minute load average before and after the run;
- ``surfel_depth_median_abs_err_m``: median |surfel depth - mesh depth| over the pixels both
  cover, on mapping frames near the camera; ``surfel_depth_coverage``: fraction of pixels with
  both;
- ``see_through_fraction_fixed`` / ``..._inverse_depth``: fraction of pixels of surfaces closer
  than 3 m where a render of the lidar map shows something more than 0.3 m behind the true
  surface, or nothing (seed 2 Fig. 4), with 1-pixel points vs inverse-depth sizes.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from diffloc.benchmark import median_ms, peak_added_mb
from diffloc.config import compose_config
from diffloc.eval.report_files import write_benchmark
from diffloc.io.dataset import map_paths, read_sequence
from diffloc.io.mesh_obj import read_textured_mesh_obj
from diffloc.io.ply import read_point_cloud
from diffloc.maps.lidar_source import lidar_points_with_origins
from diffloc.maps.surfel import SurfelMap, SurfelMapConfig
from diffloc.render.point_render import render_points
from diffloc.render.point_sizes import PointSizes
from diffloc.render.raycast import MeshRaycaster, camera_rays
from diffloc.render.surfel_render import render_surfel_index
from diffloc.sim.dataset import simulate_dataset

NEAR_SURFACE_M = 3.0
BEHIND_M = 0.3


def default_dataset() -> tuple[Path, object]:
    cfg = compose_config(["progress=false"])
    root = simulate_dataset(OmegaConf.to_object(cfg.scene), Path(cfg.out_dir), show_progress=False)
    return root, cfg


def fine_surfels_near(seq, clouds: list[Path], centre: np.ndarray, count: int) -> SurfelMap:
    """0.02 m surfels of the lidar data within reach of ``centre``, ``count`` of them."""
    points, origins, _ = lidar_points_with_origins(seq, True, clouds)
    distance = (points - torch.from_numpy(centre)).norm(dim=1)
    order = torch.argsort(distance)[: int(count * 3.5)]
    config = SurfelMapConfig(voxel_size_m=0.02, mean_radius_m=0.02, normal_radius_m=0.08)
    surfels = SurfelMap.from_points(points[order], origins[order], config)
    keep = torch.argsort((surfels.centers.double() - torch.from_numpy(centre)).norm(dim=1))
    return surfels.select(keep[:count])


def million_points(cloud_path: Path, generator: torch.Generator) -> tuple[torch.Tensor, ...]:
    """1M lidar-map points (drawn with replacement if the map is smaller) and grey colours."""
    cloud = read_point_cloud(cloud_path)
    points = torch.from_numpy(cloud.points)
    index = torch.randint(len(points), (1_000_000,), generator=generator)
    colors = torch.full((1_000_000, 3), 0.5)
    return points[index], colors


def interleaved_median_ms(functions: dict[str, Callable[[], object]], repeats: int) -> dict:
    """Median wall time (ms) of each function after a warm-up, the calls taken in turns."""
    for function in functions.values():
        function()
    times = {name: [] for name in functions}
    for _ in range(repeats):
        for name, function in functions.items():
            start = time.perf_counter()
            function()
            times[name].append((time.perf_counter() - start) * 1e3)
    return {name: round(statistics.median(values), 3) for name, values in times.items()}


def see_through(render_depth: torch.Tensor, true_depth: torch.Tensor) -> float:
    near = (true_depth > 0) & (true_depth < NEAR_SURFACE_M)
    through = (render_depth == 0) | (render_depth > true_depth + BEHIND_M)
    return float((through & near).sum() / near.sum().clamp_min(1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--out", type=Path, default=Path("experiments/results/bench_render.json"))
    args = parser.parse_args()
    generator = torch.Generator().manual_seed(0)
    load_before = os.getloadavg()[0]

    root, _ = default_dataset()
    seq = read_sequence(root, "mapping")
    maps = map_paths(root)
    camera = seq.camera.to(torch.float32)
    frame = len(seq) // 3
    T_wc = seq.T_wc[frame : frame + 1].to(torch.float32)
    nearby = (seq.T_wc[:, :3, 3] - seq.T_wc[frame, :3, 3]).norm(dim=1) < 1.5
    frames = torch.nonzero(nearby).flatten()[::2][:8]

    surfels = fine_surfels_near(seq, [maps["tls_map"]], seq.T_wc[frame, :3, 3].numpy(), 500_000)

    def surfel_render(T: torch.Tensor):
        return render_surfel_index(surfels.centers, surfels.normals, surfels.radii, T, camera)

    mesh = read_textured_mesh_obj(maps["mesh"])
    raycaster = MeshRaycaster(mesh)
    origins, directions = camera_rays(camera, T_wc)
    timed = interleaved_median_ms(
        {
            "surfel": lambda: surfel_render(T_wc),
            "raycast": lambda: raycaster.cast(origins[0], directions[0]),
        },
        args.repeats,
    )
    surfel_ms, raycast_ms = timed["surfel"], timed["raycast"]
    errors, covered = [], []
    for i in frames.tolist():
        depth = surfel_render(seq.T_wc[i : i + 1].to(torch.float32)).depth[0]
        truth = seq.load_depth(i)[0]
        both = (depth > 0) & (truth > 0)
        errors.append((depth - truth).abs()[both])
        covered.append(float(both.float().mean()))

    points, colors = million_points(maps["lidar_map"], generator)
    inverse_depth = PointSizes.inverse_depth(1.0, 16.0)
    splat_ms = median_ms(
        lambda: render_points(points, colors, T_wc, camera, inverse_depth), args.repeats
    )
    splat_peak = peak_added_mb(lambda: render_points(points, colors, T_wc, camera, inverse_depth))

    cloud = torch.from_numpy(read_point_cloud(maps["lidar_map"]).points)
    grey = torch.full_like(cloud, 0.5)
    fixed, inverse = [], []
    for i in frames.tolist():
        T = seq.T_wc[i : i + 1].to(torch.float32)
        truth = seq.load_depth(i)[0]
        for sizes, out in ((PointSizes.fixed(1), fixed), (inverse_depth, inverse)):
            out.append(see_through(render_points(cloud, grey, T, camera, sizes).depth[0], truth))

    result = {
        "threads": torch.get_num_threads(),
        "splat_1m_points_640x480_ms": round(splat_ms, 2),
        "splat_1m_points_peak_mb": round(splat_peak, 1),
        "surfel_index_500k_640x480_ms": round(surfel_ms, 2),
        "surfels": len(surfels),
        "open3d_mesh_raycast_640x480_ms": round(raycast_ms, 2),
        "surfel_index_to_open3d_ratio": round(surfel_ms / raycast_ms, 3),
        "load_average": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "surfel_depth_median_abs_err_m": round(float(torch.cat(errors).median()), 4),
        "surfel_depth_coverage": round(float(np.mean(covered)), 3),
        "see_through_fraction_fixed": round(float(np.mean(fixed)), 4),
        "see_through_fraction_inverse_depth": round(float(np.mean(inverse)), 4),
        "inverse_depth_sizes_px": [inverse_depth.rho_min, inverse_depth.rho_max],
    }
    print(write_benchmark(args.out, result))


if __name__ == "__main__":
    main()
