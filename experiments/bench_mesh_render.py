"""Split one textured-mesh RGB-D render (``map=mesh``'s ``MeshMap.render``) into its parts.

Renders the mesh stage's OBJ (``<dataset>/crossmodal/mesh/map/mesh/mesh.obj``) at the mapping
camera's full size from ``--renders`` of the lidar map's render poses spread evenly (the poses
``experiments/bench_crossmodal.py`` times for ``mesh_render_ms``), after one warm-up render.
Per render it times, by CPU (``time.process_time``: every thread of this process) and by wall
clock (``time.perf_counter``):

- ``rays``: camera-frame rays of every pixel (:func:`~diffloc.render.raycast.camera_frame_rays`,
  float64, computed once per camera by the renderer) and their rotation into the world
  (:func:`~diffloc.render.raycast.world_rays`, done per render);
- ``cast``: :meth:`~diffloc.render.raycast.MeshRaycaster.cast` (open3d ``cast_rays`` with its
  own threads plus the float32 ray packing and the hit conversions); ``cast_open3d``: the bare
  open3d call on the same packed rays;
- ``render``: the whole ``MeshMap.render`` (albedo clamped to [0, 1], depth), timed over all
  poses back to back before the parts are; ``shade``: the median ``render`` minus the medians
  of ``world_rays`` and ``cast``: hit -> UV and texel footprint, trilinear texture lookup,
  depth, images.

Keys: ``<part>_cpu_ms`` / ``<part>_wall_ms`` (medians) with ``torch_threads`` torch threads
(``--threads``; open3d casts with all cores whatever it is), ``retain_freed_heap`` (whether
``--retain-heap`` made glibc keep freed memory for reuse, see
:func:`~diffloc.benchmark.retain_freed_heap`), ``minor_faults_per_render`` (page faults of the
back-to-back renders), ``hit_fraction`` (median share of pixels that hit), ``triangles``,
``size``, ``open3d``, ``load_average`` before and after, the command. Wall times are under the
load of a shared 2-core machine.

Usage:
    PYTHONPATH=. OMP_NUM_THREADS=1 python3 experiments/bench_mesh_render.py \\
        --dataset data/indoor_seed0 --threads 1
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from diffloc.benchmark import retain_freed_heap
from diffloc.crossmodal.synthesize import MeshMap
from diffloc.eval.report_files import write_benchmark
from diffloc.io.dataset import read_sequence
from diffloc.io.mesh_obj import read_textured_mesh_obj
from diffloc.io.npz import read_npz_archive
from diffloc.o3d import open3d
from diffloc.pipeline.crossmodal_stage import crossmodal_folder
from diffloc.render.raycast import camera_frame_rays, world_rays


def _parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", type=Path, default=Path("data/indoor_seed0"))
    parser.add_argument("--renders", type=int, default=20)
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument(
        "--retain-heap",
        action="store_true",
        help="keep freed memory for reuse (diffloc.benchmark.retain_freed_heap) before timing",
    )
    parser.add_argument(
        "--out", type=Path, default=Path("experiments/results/bench_mesh_render.json")
    )
    return parser.parse_args()


def _timed(function: Callable[..., Any], *args: object) -> tuple[Any, float, float]:
    """``function(*args)``, its CPU ms and its wall ms."""
    cpu, wall = time.process_time(), time.perf_counter()
    out = function(*args)
    return out, 1e3 * (time.process_time() - cpu), 1e3 * (time.perf_counter() - wall)


def _minor_faults() -> int:
    """Minor page faults of this process so far (Linux ``/proc/self/stat``, field 10)."""
    return int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[7])


def main() -> None:
    args = _parse()
    torch.set_num_threads(args.threads)
    retained = retain_freed_heap() if args.retain_heap else False
    load_before = os.getloadavg()[0]
    folder = crossmodal_folder(args.dataset)
    mesh_map = MeshMap(read_textured_mesh_obj(folder / "mesh" / "map" / "mesh" / "mesh.obj"))
    raycaster = mesh_map.renderer.raycaster
    T_all = torch.from_numpy(read_npz_archive(folder / "poses_lidar_map" / "poses.npz")["T_wc"])
    camera = read_sequence(args.dataset, "mapping").camera
    picks = torch.linspace(0, len(T_all) - 1, args.renders).round().long().tolist()
    o3d = open3d()
    mesh_map.render(T_all[:1], camera)  # warm-up
    parts: dict[str, list[tuple[float, float]]] = {"render": []}
    faults = _minor_faults()
    for i in picks:  # whole renders back to back, as a database is rendered
        parts["render"].append(_timed(mesh_map.render, T_all[i : i + 1], camera)[1:])
    faults = _minor_faults() - faults
    hit_fractions = []
    for i in picks:  # then the parts
        T_wc = T_all[i : i + 1]
        rays_cam, cpu, wall = _timed(camera_frame_rays, camera)
        parts.setdefault("camera_rays", []).append((cpu, wall))
        (origins, directions), cpu, wall = _timed(world_rays, rays_cam, T_wc)
        parts.setdefault("world_rays", []).append((cpu, wall))
        flat_o, flat_d = origins.reshape(-1, 3), directions.reshape(-1, 3)
        hits, cpu, wall = _timed(raycaster.cast, flat_o, flat_d)
        parts.setdefault("cast", []).append((cpu, wall))
        hit_fractions.append(float(hits.hit.float().mean()))
        packed = o3d.core.Tensor(torch.cat([flat_o, flat_d], 1).numpy())
        _, cpu, wall = _timed(raycaster._scene.cast_rays, packed)
        parts.setdefault("cast_open3d", []).append((cpu, wall))
    report: dict = {"command": shlex.join(["python3", *sys.argv])}
    for clock, column in (("cpu", 0), ("wall", 1)):
        medians = {
            name: statistics.median(v[column] for v in values) for name, values in parts.items()
        }
        medians["shade"] = medians["render"] - medians["world_rays"] - medians["cast"]
        report.update({f"{name}_{clock}_ms": round(ms, 1) for name, ms in medians.items()})
    report["torch_threads"] = args.threads
    report["retain_freed_heap"] = retained
    report["minor_faults_per_render"] = faults // len(picks)
    report["renders"] = len(picks)
    report["hit_fraction"] = round(statistics.median(hit_fractions), 3)
    report["triangles"] = mesh_map.renderer.raycaster.mesh.num_faces
    report["size"] = f"{camera.width}x{camera.height}"
    report["open3d"] = o3d.__version__
    report["load_average"] = [round(load_before, 2), round(os.getloadavg()[0], 2)]
    report["machine"] = f"{platform.node()} {os.cpu_count()} cores, shared"
    print(write_benchmark(args.out, report))


if __name__ == "__main__":
    main()
