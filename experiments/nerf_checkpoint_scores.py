"""Held-out scores of a radiance-field training checkpoint (issue 19), with the PSNR split into
pixels with ground-truth depth (surfaces) and without (the sky outdoors), and the field's mean
opacity on the sky pixels of the held-out frames (``sky_opacity_mean`` of
``heldout_field_scores``; near 1: the sky is painted by density, not by a background colour):
appends one JSON line (first key ``command``) to ``--out``. The sky opacity is also split by
the elevation of the pixel's ray: ``sky_opacity_mean_lidar_fov`` (within the lidar's vertical
field of view, where lidar rays without a return exist) and ``sky_opacity_mean_above_lidar``
(above its highest beam, where no lidar ray ever reaches), from the calibration's lidar
pattern (``null`` without one). The sky PSNR is split too (right halves, held-out codes as in
the scores): ``psnr_heldout_sky_open_db`` over sky pixels with no surface pixel within 2 pixels,
``psnr_heldout_sky_edge_db`` over the other sky pixels (silhouettes of facades and trees).

The checkpoint is the end-of-epoch ``last.ckpt`` a ``experiments/bench_nerf.py`` run leaves in
``<work>/triplane_full/checkpoints`` (read with ``weights_only=True``); ``--scene``, ``--data``
and ``--override`` must be those of the run (they rebuild its submap and field). Scores are
those of ``bench_nerf.py`` (``heldout_field_scores``: code fitted on the left half, PSNR on the
right half), of the field at the checkpoint's ``step`` (the checkpoint is written when the
budget stops training, so this is the run's last step; compare with the run's ``steps``).

    PYTHONPATH=. OMP_NUM_THREADS=1 python3 experiments/nerf_checkpoint_scores.py \\
        --scene outdoor --override nerf.train.field.background=learned \\
        --checkpoint /tmp/bench/triplane_full/checkpoints/last.ckpt --out /tmp/scores.jsonl
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

from diffloc.config import nerf_settings
from diffloc.eval.field_scores import heldout_field_scores, left_half_code
from diffloc.io.sequence import SequenceData
from diffloc.maps.nerf.data import SubmapRays, load_image
from diffloc.maps.nerf.field import RadianceField
from diffloc.maps.nerf.no_return import LidarPattern
from diffloc.maps.nerf.rays import camera_rays
from diffloc.maps.nerf.renderer import render_image
from diffloc.maps.nerf.sampler import DensityGrid
from diffloc.maps.nerf.train import load_checkpoint
from diffloc.pipeline.nerf_stage import submap_training_data


def sky_opacity_by_elevation(
    field: RadianceField, grid: DensityGrid, seq: SequenceData, rays: SubmapRays
) -> dict[str, float | None]:
    """Mean rendered opacity of the held-out frames' sky pixels (no ground-truth depth) whose
    ray elevation is at most / above the lidar's highest beam (``None`` where there is none)."""
    calib = seq.info.get("calib")
    pattern = LidarPattern.from_calibration(getattr(calib, "lidar", None), seq.name)
    top = math.radians(pattern.vfov_max_deg)
    code = field.appearance.weight.detach().mean(0)  # opacity does not depend on the code
    uv = rays.camera.pixel_grid(torch.float32).reshape(-1, 2)
    size = (rays.camera.height, rays.camera.width)
    parts: dict[bool, list[torch.Tensor]] = {False: [], True: []}
    for frame in rays.heldout:
        T_wc = seq.T_wc[frame].float()
        opacity = render_image(field, grid, rays.camera, T_wc, code)["opacity"].reshape(-1)
        sky = F.interpolate(seq.load_depth(frame)[None], size=size)[0, 0].reshape(-1) <= 0
        above = torch.asin(camera_rays(rays.camera, T_wc, uv)[1][:, 2].clamp(-1, 1)) > top
        for side in (False, True):
            parts[side].append(opacity[sky & (above == side)])
    means = {side: torch.cat(values) for side, values in parts.items()}
    return {
        f"sky_opacity_mean_{name}": float(means[side].mean()) if len(means[side]) else None
        for side, name in ((False, "lidar_fov"), (True, "above_lidar"))
    }


def sky_psnr_by_edge(
    field: RadianceField, grid: DensityGrid, seq: SequenceData, rays: SubmapRays
) -> dict[str, float | None]:
    """PSNR of the held-out right halves' sky pixels (no ground-truth depth) pooled over the
    frames, split into open sky (no surface pixel within 2 pixels) and sky at an edge."""
    camera, half = rays.camera, rays.camera.width // 2
    squared: dict[str, list[torch.Tensor]] = {"open": [], "edge": []}
    for frame in rays.heldout:
        T_wc = seq.T_wc[frame].float()
        image = load_image(seq, frame, camera)
        code = left_half_code(field, grid, camera, T_wc, image)
        rgb = render_image(field, grid, camera, T_wc, code)["rgb"]
        depth = F.interpolate(seq.load_depth(frame)[None], size=(camera.height, camera.width))
        near_surface = F.max_pool2d((depth[0] > 0).float(), 5, stride=1, padding=2)[0] > 0
        sky = depth[0, 0] <= 0
        error = ((rgb - image) ** 2).mean(0)[:, half:]
        squared["open"].append(error[(sky & ~near_surface)[:, half:]])
        squared["edge"].append(error[(sky & near_surface)[:, half:]])
    out = {}
    for name, errors in squared.items():
        pooled = torch.cat(errors)
        out[f"psnr_heldout_sky_{name}_db"] = (
            -10 * math.log10(max(float(pooled.mean()), 1e-12)) if len(pooled) else None
        )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", choices=("indoor", "outdoor"), default="indoor")
    parser.add_argument("--data", help="dataset folder (default: data/<scene>_seed0)")
    parser.add_argument("--submap", type=int, default=0)
    parser.add_argument("--override", nargs="+", default=[], help="Hydra overrides of the run")
    parser.add_argument("--checkpoint", required=True, help="last.ckpt of the run")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", required=True, help="JSONL to append the record to")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    data = args.data or f"data/{args.scene}_seed0"
    nerf = nerf_settings(args.scene, [f"nerf.submap={args.submap}", *args.override])
    seq, _, rays = submap_training_data(data, nerf)
    module, step = load_checkpoint(rays, nerf.train, args.checkpoint)
    scores = heldout_field_scores(module.field, module.grid, seq, rays.camera, rays.heldout, True)
    record = {
        "command": shlex.join(["python3", *sys.argv]),
        "data": data,
        "background": nerf.train.field.background,
        "empty_weight": nerf.train.loss.empty_weight,
        "step": step,
        "heldout_frames": len(rays.heldout),
        **scores,
        **sky_opacity_by_elevation(module.field, module.grid, seq, rays),
        **sky_psnr_by_edge(module.field, module.grid, seq, rays),
        "load_avg": os.getloadavg()[0],
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "a") as f:
        f.write(json.dumps(record) + "\n")
    print(json.dumps(record))


if __name__ == "__main__":
    main()
