"""Where a radiance-field training step spends its CPU time (issue 19): ``steps`` training
steps of one encoding on a submap under ``torch.profiler``, after ``warmup`` unprofiled steps;
prints the operators by self CPU time and the CPU ms per step. With ``--render``, then also
one 320x240 RGB-D render (the benchmark's ``render_320x240_s``: the first held-out pose, the
mean appearance code) of the field as trained so far, profiled the same way, and ``--repeat``
unprofiled renders, each one's CPU s printed. With ``--checkpoint`` (a training checkpoint of
the same settings, e.g. a ``bench_nerf.py`` run's ``checkpoints/last.ckpt``) only the renders
of that trained field, no training: the render cost of one field under two versions of the code.

    PYTHONPATH=. OMP_NUM_THREADS=1 python3 experiments/profile_nerf_step.py --scene outdoor \\
        --data data/outdoor_seed0 --encoding hashgrid --steps 30 [--render] [--checkpoint CKPT]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time

import lightning as L
import torch
from torch.profiler import ProfilerActivity, profile

from diffloc.config import nerf_settings
from diffloc.maps.nerf.renderer import render_image
from diffloc.maps.nerf.train import fit_submap, load_checkpoint
from diffloc.pipeline.nerf_stage import submap_training_data


class _Profiled(L.Callback):
    """Profile the training steps after ``warmup`` and stop after ``steps`` of them."""

    def __init__(self, warmup: int, steps: int) -> None:
        self.warmup, self.steps = warmup, steps
        self.profiler = profile(activities=[ProfilerActivity.CPU])

    def on_train_batch_start(self, trainer, module, batch, batch_idx) -> None:
        if trainer.global_step == self.warmup:
            self.cpu = time.process_time()
            self.profiler.__enter__()

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
        if trainer.global_step == self.warmup + self.steps:
            self.cpu = time.process_time() - self.cpu
            self.profiler.__exit__(None, None, None)
            trainer.should_stop = True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", choices=("indoor", "outdoor"), default="indoor")
    parser.add_argument("--data", required=True)
    parser.add_argument("--encoding", default="hashgrid")
    parser.add_argument("--submap", type=int, default=0)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--rows", type=int, default=25)
    parser.add_argument("--override", nargs="+", default=[])
    parser.add_argument("--render", action="store_true", help="also profile a 320x240 render")
    parser.add_argument("--repeat", type=int, default=3, help="unprofiled renders timed")
    parser.add_argument("--checkpoint", help="render this trained field; no training")
    args = parser.parse_args()
    torch.set_num_threads(1)
    nerf = nerf_settings(args.scene, [f"nerf.submap={args.submap}", *args.override])
    seq, _, rays = submap_training_data(args.data, nerf)
    config = dataclasses.replace(
        nerf.train, field=dataclasses.replace(nerf.train.field, encoding=args.encoding)
    )
    if args.checkpoint:
        module = load_checkpoint(rays, config, args.checkpoint)[0]
    else:
        timer = _Profiled(args.warmup, args.steps)
        with tempfile.TemporaryDirectory() as work:
            module = fit_submap(
                rays, config, work, epochs=10**6, callbacks=[timer], show_progress=False
            )
        table = timer.profiler.key_averages().table(
            sort_by="self_cpu_time_total", row_limit=args.rows
        )
        print(table)
        print(f"{args.encoding}: {1000 * timer.cpu / args.steps:.1f} CPU ms per step (profiled)")
    if args.render or args.checkpoint:
        code = module.field.appearance.weight.detach().mean(0)
        pose = seq.T_wc[rays.heldout[0]]

        def render() -> float:
            cpu = time.process_time()
            render_image(module.field, module.grid, seq.camera.scaled(0.5), pose, code)
            return time.process_time() - cpu

        with profile(activities=[ProfilerActivity.CPU]) as prof:
            cpu = render()
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.rows))
        print(f"{args.encoding}: {cpu:.3f} CPU s per 320x240 RGB-D render (profiled)")
        times = [round(render(), 3) for _ in range(args.repeat)]
        print(f"{args.encoding}: CPU s per 320x240 RGB-D render, unprofiled: {times}")


if __name__ == "__main__":
    main()
