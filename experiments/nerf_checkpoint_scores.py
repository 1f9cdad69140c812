"""Held-out scores of a radiance-field training checkpoint (issue 19), with the PSNR split into
pixels with ground-truth depth (surfaces) and without (the sky outdoors), and the field's mean
opacity on the sky pixels of the held-out frames (``sky_opacity_mean`` of
``heldout_field_scores``; near 1: the sky is painted by density, not by a background colour):
appends one JSON line (first key ``command``) to ``--out``.

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
import os
import shlex
import sys
from pathlib import Path

import torch

from diffloc.config import compose_config, to_object
from diffloc.eval.field_scores import heldout_field_scores
from diffloc.io.dataset import read_sequence
from diffloc.maps.nerf.data import build_submap_rays
from diffloc.maps.nerf.submaps import cluster_trajectory
from diffloc.maps.nerf.train import load_checkpoint


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
    overrides = [f"scene={args.scene}", "task=train_nerf", *args.override]
    nerf = to_object(compose_config(overrides)).nerf
    seq = read_sequence(data, "mapping")
    submap = cluster_trajectory(seq.T_wc, nerf.submaps)[args.submap]
    rays = build_submap_rays(seq, submap.frames, nerf.data)
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
        "load_avg": os.getloadavg()[0],
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "a") as f:
        f.write(json.dumps(record) + "\n")
    print(json.dumps(record))


if __name__ == "__main__":
    main()
