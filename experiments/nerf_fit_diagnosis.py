"""Underfit or poor generalisation? Scores a radiance-field checkpoint on its training frames and
on its held-out frames with the same protocol, and says where the error sits (issue 19).

Every frame of the submap (training and held out) is scored as ``bench_nerf.py`` scores the
held-out ones: appearance code fitted on the left half (field frozen), PSNR on the right half.
Training frames are also scored with their own learnt code (``own code``). The right halves'
squared errors are pooled by region (``diffloc.eval.field_regions``: sky, ground, facade, far
= ground-truth depth beyond ``--far-m``, default the outdoor box range ``nerf.data.box_range_m``
or 15 m), for training and held-out frames apart. A training / held-out gap much larger than
the spread between frames says the field does not generalise to new views; training frames
near the held-out PSNR say it underfits. Writes ``<out>.md`` / ``<out>.json`` (first line /
key: the command) and ``<out>.png``: per held-out frame the image, the render with the fitted
code, the per-pixel error and the regions (left halves greyed: the code was fitted there).
Ground truth (depth) is read for scoring only.

The checkpoint is the ``last.ckpt`` a ``bench_nerf.py`` run leaves in
``<work>/triplane_full/checkpoints``; ``--scene``, ``--data`` and ``--override`` must be
those of the run.

    PYTHONPATH=. OMP_NUM_THREADS=1 python3 experiments/nerf_fit_diagnosis.py --scene outdoor \\
        --checkpoint /tmp/bench/triplane_full/checkpoints/last.ckpt \\
        --out experiments/results/nerf_outdoor_fit_diagnosis_seed0
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure

from diffloc.config import nerf_settings
from diffloc.eval.field_regions import REGIONS, pixel_regions, region_summary
from diffloc.eval.field_scores import left_half_code, psnr
from diffloc.eval.report_files import write_report
from diffloc.maps.nerf.data import load_image
from diffloc.maps.nerf.module import NerfModule
from diffloc.maps.nerf.renderer import render_image
from diffloc.maps.nerf.train import load_checkpoint
from diffloc.pipeline.nerf_stage import submap_training_data

_REGION_COLOURS = ("#9ecae1", "#a1d99b", "#fdae6b", "#bcbddc")
"""Colours of the regions in the PNG (sky, ground, facade, far)."""


def score_frame(module: NerfModule, seq, camera, frame: int, far_m: float, own: int | None):
    """Right-half scores of one frame: PSNR with the left-half code (and with training code
    ``own`` when given), the right half's per-pixel squared errors and region labels, and the
    images for the figure."""
    T_wc = seq.T_wc[frame].float()
    image = load_image(seq, frame, camera)
    half = camera.width // 2
    code = left_half_code(module.field, module.grid, camera, T_wc, image)
    rgb = render_image(module.field, module.grid, camera, T_wc, code)["rgb"]
    depth = F.interpolate(
        seq.load_depth(frame)[None], size=(camera.height, camera.width), mode="nearest"
    )[0]
    labels = pixel_regions(depth, camera, T_wc, far_m)
    squared = ((rgb - image) ** 2).mean(0)
    out = {
        "frame": frame,
        "psnr_db": psnr(rgb[:, :, half:], image[:, :, half:]),
        "squared": squared[:, half:].reshape(-1),
        "labels": labels[:, half:].reshape(-1),
        "images": (image, rgb, squared, labels),
    }
    if own is not None:
        own_code = module.field.appearance.weight[own].detach()
        own_rgb = render_image(module.field, module.grid, camera, T_wc, own_code)["rgb"]
        out["psnr_own_code_db"] = psnr(own_rgb[:, :, half:], image[:, :, half:])
    return out


def summarise(scores: list[dict]) -> dict:
    """Mean / min / max right-half PSNR over frames and the pooled region summary."""
    values = [s["psnr_db"] for s in scores]
    summary = {
        "frames": len(scores),
        "psnr_mean_db": float(np.mean(values)),
        "psnr_min_db": float(np.min(values)),
        "psnr_max_db": float(np.max(values)),
        "regions": region_summary(
            torch.cat([s["squared"] for s in scores]), torch.cat([s["labels"] for s in scores])
        ),
    }
    own = [s["psnr_own_code_db"] for s in scores if "psnr_own_code_db" in s]
    if own:
        summary["psnr_own_code_mean_db"] = float(np.mean(own))
    return summary


def markdown(record: dict) -> str:
    """The record as Markdown: the train / held-out table and the region table."""
    train, held = record["train"], record["heldout"]
    lines = [
        f"Made by: `{record['command']}`",
        "",
        f"Fit diagnosis of `{record['checkpoint']}` (step {record['step']}; {record['data']}, "
        f"submap {record['submap']}; {train['frames']} training / {held['frames']} held-out "
        f"frames at {record['resolution']}; load {record['load_avg_start']:.1f} at the start). "
        "PSNR on the right half, appearance code fitted on the left half (the held-out "
        "protocol) for both kinds of frame; training frames also with their own learnt code.",
        "",
        "| frames | mean PSNR dB | min | max | own code, mean dB |",
        "|---|---|---|---|---|",
    ]
    for name, s in (("training", train), ("held out", held)):
        own = s.get("psnr_own_code_mean_db")
        lines.append(
            f"| {name} | {s['psnr_mean_db']:.2f} | {s['psnr_min_db']:.2f} | "
            f"{s['psnr_max_db']:.2f} | {'-' if own is None else f'{own:.2f}'} |"
        )
    lines += [
        "",
        f"Error by region (right halves pooled; far = ground-truth depth beyond "
        f"{record['far_m']:g} m; sky = no ground-truth depth; ground = surface at most 0.2 m "
        "above z = 0; facade = other surfaces): PSNR, share of pixels, share of the summed "
        "squared error.",
        "",
        "| region | training PSNR dB | held-out PSNR dB | held-out pixels | held-out error share |",
        "|---|---|---|---|---|",
    ]
    for name in REGIONS:
        t, h = train["regions"][name], held["regions"][name]
        cell = [("-" if r["psnr_db"] is None else f"{r['psnr_db']:.2f}") for r in (t, h)]
        lines.append(
            f"| {name} | {cell[0]} | {cell[1]} | {100 * h['pixel_share']:.0f} % | "
            f"{100 * h['error_share']:.0f} % |"
        )
    lines += ["", f"Held-out frames: {', '.join(str(f) for f in record['heldout_frames'])}."]
    return "\n".join(lines) + "\n"


def figure(scores: list[dict], path: Path) -> None:
    """PNG: per held-out frame the image, the render, the error and the regions."""
    rows = len(scores)
    fig = Figure(figsize=(12.0, 2.6 * rows), dpi=100)
    FigureCanvasAgg(fig)
    regions = ListedColormap(_REGION_COLOURS)
    for r, s in enumerate(scores):
        image, rgb, squared, labels = s["images"]
        half = image.shape[-1] // 2
        panels = (
            ("image", image.permute(1, 2, 0).numpy(), {}),
            (
                f"render (left-half code), right half {s['psnr_db']:.1f} dB",
                rgb.permute(1, 2, 0).numpy(),
                {},
            ),
            ("squared error", squared.sqrt().numpy(), {"cmap": "inferno", "vmin": 0, "vmax": 0.3}),
            (
                " / ".join(REGIONS),
                labels.numpy(),
                {"cmap": regions, "vmin": -0.5, "vmax": len(REGIONS) - 0.5},
            ),
        )
        for c, (title, data, kwargs) in enumerate(panels):
            ax = fig.add_subplot(rows, 4, 4 * r + c + 1)
            ax.imshow(data.clip(0, 1) if data.ndim == 3 else data, **kwargs)
            ax.axvspan(-0.5, half - 0.5, color="white", alpha=0.5 if c else 0.0)
            ax.set_title(f"frame {s['frame']}: {title}" if c == 0 else title, fontsize=8)
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", choices=("indoor", "outdoor"), default="indoor")
    parser.add_argument("--data", help="dataset folder (default: data/<scene>_seed0)")
    parser.add_argument("--submap", type=int, default=0)
    parser.add_argument("--override", nargs="+", default=[], help="Hydra overrides of the run")
    parser.add_argument("--checkpoint", required=True, help="last.ckpt of the run")
    parser.add_argument("--far-m", type=float, help="'far' beyond this depth (default: box)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", required=True, help="output path without suffix")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load_start = os.getloadavg()[0]
    data = args.data or f"data/{args.scene}_seed0"
    nerf = nerf_settings(args.scene, [f"nerf.submap={args.submap}", *args.override])
    far_m = args.far_m or nerf.data.box_range_m or 15.0
    seq, _, rays = submap_training_data(data, nerf)
    module, step = load_checkpoint(rays, nerf.train, args.checkpoint)
    module.eval()
    train = [
        score_frame(module, seq, rays.camera, f, far_m, own=i) for i, f in enumerate(rays.frames)
    ]
    held = [score_frame(module, seq, rays.camera, f, far_m, own=None) for f in rays.heldout]
    record = {
        "command": shlex.join(["python3", *sys.argv]),
        "data": data,
        "submap": args.submap,
        "checkpoint": args.checkpoint,
        "step": step,
        "resolution": f"{rays.camera.width}x{rays.camera.height}",
        "far_m": far_m,
        "heldout_frames": rays.heldout,
        "train": summarise(train),
        "heldout": summarise(held),
        "per_frame": [
            {k: v for k, v in s.items() if k in ("frame", "psnr_db", "psnr_own_code_db")}
            for s in train + held
        ],
        "load_avg_start": load_start,
        "load_avg_end": os.getloadavg()[0],
    }
    out = Path(args.out)
    write_report(out, markdown(record), record)
    figure(held, out.with_suffix(".png"))
    print(markdown(record))


if __name__ == "__main__":
    main()
