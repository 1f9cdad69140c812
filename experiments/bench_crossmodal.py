"""Benchmark of seed 2's rendered-database localisation (``diffloc task=crossmodal``).

Prints one JSON line and writes it to ``--out``. It reads the ``results.json`` of the
``task=crossmodal`` runs ``<runs>/crossmodal_<dataset>_<map>`` (``bash experiments/run_tables.sh
crossmodal_tables DATASET`` makes them; every stage is cached under ``<dataset>/crossmodal/``)
and measures, in this process, what those runs do not record. Keys:

- ``loc_rate_<map>`` (``tls``, ``cloud``, ``mesh``, ``realdb`` = ``map=images``): share of the
  ``query_same`` queries localised within the loose bound (1 m indoors) and 30 deg;
  ``reverse_loc_rate_<map>``: the same on ``query_reverse``; ``changed_loc_rate_<map>``: on
  ``changed``; ``queries_every``: the runs' query subsampling;
- ``query_ms``: median wall ms per ``query_same`` query in the TLS database (features,
  retrieval, re-ranking, matching, PnP) as the run recorded it, under its load
  (``query_ms_load``); ``query_ms_<map>`` likewise; ``query_cpu_ms``: median process CPU ms per
  query of ``--cpu-queries`` ``query_same`` frames localised here in the TLS database (one
  thread, after one warm-up query, so less inflated by the load);
- ``query_wall_ms_mesh``: median wall ms per query of every ``queries_every``-th
  ``query_same`` frame localised here in the mesh database (features included, after one
  warm-up query) with ``--wall-threads`` torch threads (``query_wall_threads``): the figure for
  the 250 ms goal, meaningful only at a low ``load_average``;
- ``rerender_wall_ms_mesh``: median wall ms of the re-render check (``task.rerender``, on for
  the mesh indoors: render at the pose found, XFeat, LighterGlue, PnP, photometric
  consistency) per query of the same frames with a pose, the same threads; the task looks
  again only at refused poses, so a refused query costs ``query_wall_ms_mesh`` plus this and
  an accepted one nothing more;
- ``render_db_s`` / ``render_db_cpu_s``: wall / CPU seconds to render the cloud (lidar map)
  database at its render poses here (``render_db_images`` renders, features not included);
  ``render_ms_per_image``;
- ``mesh_render_ms``: median wall ms of one RGB-D render of the textured mesh (the mesh stage's
  OBJ, open3d ray casting + texture lookup) at the mapping camera's full size
  (``mesh_render_size``), over ``--mesh-renders`` render poses spread over the lidar map's;
- ``mesh_build_s``: wall seconds of the mesh stage (reconstruction, UV atlas, Eq. 3-4
  texturing; each in ``mesh_build_parts_s``) as its record holds them (the load they ran
  under was not recorded);
- ``load_average`` before and after this run, ``machine``; every wall time is under the load of
  a shared 2-core machine (``wall_times_under_load``).

Usage:
    PYTHONPATH=. OMP_NUM_THREADS=1 python3 experiments/bench_crossmodal.py \\
        --dataset data/indoor_seed0 --runs experiments/runs
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from diffloc.crossmodal.database import RenderedDatabase
from diffloc.crossmodal.synthesize import MeshMap, PointCloudMap, RGBDMap, render_views
from diffloc.eval.report_files import write_benchmark
from diffloc.io.dataset import read_sequence
from diffloc.io.mesh_obj import read_textured_mesh_obj
from diffloc.io.npz import read_npz_archive
from diffloc.maps.pointcloud import PointMap
from diffloc.pipeline.crossmodal_config import PointMapConfig
from diffloc.pipeline.crossmodal_stage import crossmodal_folder, scaled_images
from diffloc.reloc.rendered import (
    RenderedDatabaseLocalizer,
    RenderedLocalizerConfig,
    localizer_networks,
)
from diffloc.reloc.rerender import rerender_candidate

MESH_OBJ = Path("mesh", "map", "mesh", "mesh.obj")
"""The mesh stage's OBJ under ``<dataset>/crossmodal/``."""
MAPS = {"tls": "tls", "cloud": "cloud", "mesh": "mesh", "realdb": "images"}
"""Key suffix -> ``map`` option."""
SEQUENCES = {
    "loc_rate": "query_same",
    "reverse_loc_rate": "query_reverse",
    "changed_loc_rate": "changed",
}


def _parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", type=Path, default=Path("data/indoor_seed0"))
    parser.add_argument("--runs", type=Path, default=Path("experiments/runs"))
    parser.add_argument("--cpu-queries", type=int, default=8)
    parser.add_argument("--mesh-renders", type=int, default=20)
    parser.add_argument("--wall-threads", type=int, default=2)
    parser.add_argument(
        "--out", type=Path, default=Path("experiments/results/bench_crossmodal.json")
    )
    return parser.parse_args()


def _loose_rate(entry: dict, loose_m: float) -> float:
    return entry["rates"][f"{loose_m:g}m_30deg"]


def _query_ms(
    dataset: Path,
    option: str,
    clock: Callable[[], float],
    every: int | None = None,
    count: int | None = None,
    threads: int = 1,
    rerender: RGBDMap | None = None,
) -> float:
    """Median ms by ``clock`` (``time.process_time``: CPU, ``time.perf_counter``: wall) per
    ``query_same`` query in the database of ``option`` with ``threads`` torch threads, after
    one warm-up query: every ``every``-th frame (``None``: ``count`` frames spread over the
    sequence), at most ``count``. With ``rerender`` (the map of ``option``), the time of the
    re-render check (``task.rerender``: the map rendered at the pose found, XFeat on it,
    LighterGlue, PnP, photometric consistency) per query with a pose, instead of the
    localisation's."""
    db = RenderedDatabase.load(crossmodal_folder(dataset) / option / "database" / "rgbd")
    config = RenderedLocalizerConfig()
    localizer = RenderedDatabaseLocalizer(db, config)
    networks = localizer_networks(config)
    seq = read_sequence(dataset, "query_same")
    camera = seq.camera.scaled(db.camera.width / seq.camera.width)
    step = every if every is not None else max(1, len(seq) // count)
    frames = list(range(0, len(seq), step))[:count]

    def timed(image: torch.Tensor) -> float | None:
        if rerender is None:
            start = clock()
            localizer.localize(image, camera)
            return 1e3 * (clock() - start)
        found = localizer.localize(image, camera)
        if not found.success:
            return None
        query = networks[0].extract(image)
        generator = torch.Generator().manual_seed(config.seed)
        start = clock()
        rerender_candidate(
            rerender, found.T_wc, db.camera, image, query, camera, networks, config, generator
        )
        return 1e3 * (clock() - start)

    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        timed(scaled_images(seq, camera, [frames[0]])[0])
        times = [timed(scaled_images(seq, camera, [i])[0]) for i in frames]
    finally:
        torch.set_num_threads(previous)
    return statistics.median(t for t in times if t is not None)


def _render_cloud_db(dataset: Path, scale: float) -> tuple[float, float, int]:
    """Wall and CPU seconds to render the lidar-cloud database at its render poses."""
    folder = crossmodal_folder(dataset)
    colored = PointMap.load_ply(folder / "cloud" / "map" / "colored_map.ply")
    cloud = PointCloudMap(colored.positions, colored.colors, PointMapConfig("lidar_map").sizes())
    T_wc = read_npz_archive(folder / "poses_lidar_map" / "poses.npz")["T_wc"]
    camera = read_sequence(dataset, "mapping").camera.scaled(scale)
    T_wc = torch.from_numpy(T_wc)
    wall, cpu = time.perf_counter(), time.process_time()
    render_views(cloud, T_wc, camera)
    return time.perf_counter() - wall, time.process_time() - cpu, len(T_wc)


def _render_mesh_frames(dataset: Path, count: int) -> tuple[float, str]:
    """Median wall ms of single-frame textured-mesh renders at the full camera size, and
    the size, over ``count`` of the lidar map's render poses spread evenly."""
    folder = crossmodal_folder(dataset)
    mesh = MeshMap(read_textured_mesh_obj(folder / MESH_OBJ))
    T_wc = torch.from_numpy(read_npz_archive(folder / "poses_lidar_map" / "poses.npz")["T_wc"])
    camera = read_sequence(dataset, "mapping").camera
    times = []
    for i in torch.linspace(0, len(T_wc) - 1, count).round().long().tolist():
        start = time.perf_counter()
        mesh.render(T_wc[i : i + 1], camera)
        times.append(1e3 * (time.perf_counter() - start))
    return statistics.median(times), f"{camera.width}x{camera.height}"


def main() -> None:
    args = _parse()
    torch.set_num_threads(1)  # as the task's runs (OMP_NUM_THREADS=1)
    load_before = os.getloadavg()[0]
    tag = args.dataset.name
    results = {}
    for option in MAPS.values():
        path = args.runs / f"crossmodal_{tag}_{option}" / "results.json"
        if not path.is_file():
            raise SystemExit(f"{path} is missing: bash experiments/run_tables.sh crossmodal_tables")
        results[option] = json.loads(path.read_text())
    tls = results["tls"]
    loose_m = tls["loose_m"]
    report: dict = {"dataset": str(args.dataset), "queries_every": tls["every"]}
    for prefix, sequence in SEQUENCES.items():
        for key, option in MAPS.items():
            report[f"{prefix}_{key}"] = _loose_rate(results[option]["sequences"][sequence], loose_m)
    report["query_ms"] = tls["sequences"]["query_same"]["median_ms_per_query"]
    report["query_ms_load"] = tls["stages"]["localize_query_same"]["load_average"][0]
    for key, option in MAPS.items():
        report[f"query_ms_{key}"] = results[option]["sequences"]["query_same"][
            "median_ms_per_query"
        ]
    cpu_ms = _query_ms(args.dataset, "tls", time.process_time, count=args.cpu_queries)
    report["query_cpu_ms"] = round(cpu_ms, 1)
    wall_ms = _query_ms(
        args.dataset, "mesh", time.perf_counter, every=tls["every"], threads=args.wall_threads
    )
    report["query_wall_ms_mesh"] = round(wall_ms, 1)
    mesh = MeshMap(read_textured_mesh_obj(crossmodal_folder(args.dataset) / MESH_OBJ))
    rerender_ms = _query_ms(
        args.dataset,
        "mesh",
        time.perf_counter,
        every=tls["every"],
        threads=args.wall_threads,
        rerender=mesh,
    )
    report["rerender_wall_ms_mesh"] = round(rerender_ms, 1)
    report["query_wall_threads"] = args.wall_threads
    width = int(tls["image_size"].split("x")[0])
    scale = width / read_sequence(args.dataset, "mapping").camera.width
    wall_s, cpu_s, images = _render_cloud_db(args.dataset, scale)
    report["render_db_s"] = round(wall_s, 2)
    report["render_db_cpu_s"] = round(cpu_s, 2)
    report["render_db_images"] = images
    report["render_ms_per_image"] = round(1e3 * wall_s / images, 1)
    report["mesh_render_ms"], report["mesh_render_size"] = _render_mesh_frames(
        args.dataset, args.mesh_renders
    )
    report["mesh_render_ms"] = round(report["mesh_render_ms"], 1)
    seconds = results["mesh"]["stages"]["map"]["seconds"]
    report["mesh_build_s"] = round(sum(seconds.values()), 1)
    report["mesh_build_parts_s"] = {k: round(v, 1) for k, v in seconds.items()}
    report["image_size"] = tls["image_size"]
    report["load_average"] = [round(load_before, 2), round(os.getloadavg()[0], 2)]
    report["machine"] = f"{platform.node()} {os.cpu_count()} cores, shared"
    report["wall_times_under_load"] = True
    print(write_benchmark(args.out, report))


if __name__ == "__main__":
    main()
