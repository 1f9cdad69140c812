"""Textured mesh maps from the lidar and TLS maps: exposure estimated vs recorded vs none.

Usage:
    python experiments/mesh_texture.py [--data /tmp/mesh_data/indoor_ae_seed0]
        [--out experiments/results] [--atlas-size 1024] [--target-faces 80000]

The scene is the default indoor scene (seed 0) at 160x120 with the mapping run limited to
its first 96 frames and auto exposure on in the mapping run (``SCENE_OVERRIDES``); it is
simulated into ``--data`` unless already there. Every 8th mapping frame is held out; the
others texture the mesh. For each point map (``lidar_map``, and ``tls_map`` cropped to the
lidar map's bounding box, the region the mapping run covers) the mesh is reconstructed once
and textured three times:

- ``estimated``: exposures estimated from the images (what the library does);
- ``recorded``: the simulator's recorded exposures (an oracle: ground truth);
- ``none``: no exposure compensation.

Scores per variant: PSNR of the textured-mesh render at each held-out pose against the real
held-out image over the pixels the mesh covers, (a) as rendered and (b) after fitting one
gain per held-out image (the median linear ratio image / render: the held-out image's own
exposure is unknown to the map), the covered share of pixels, the exposure estimation error
(log-exposure error of the training images after removing the common gauge), mesh size and
wall times. Writes ``mesh_texture.json``, ``mesh_texture.md`` and ``mesh_texture.png`` (held-out
image beside the renders) to ``--out``; the meshes of the ``estimated`` variant go to
``--mesh-out`` as OBJ + MTL + PNG and PLY.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from diffloc.config import compose_config
from diffloc.crossmodal.mesh_map import TexturedMeshConfig, texture_mesh
from diffloc.eval.report_files import write_report
from diffloc.io.dataset import MAP_FILES, read_sequence
from diffloc.io.exposure import EXPOSURE_FILE, read_exposures
from diffloc.io.images import write_rgb
from diffloc.io.mesh_export import write_atlas_obj, write_atlas_ply
from diffloc.io.ply import read_point_cloud
from diffloc.maps.mesh import MeshReconstructionConfig, reconstruct_mesh
from diffloc.render.raycast import MeshRenderer
from diffloc.sim.dataset import simulate_dataset

SCENE_OVERRIDES = [
    "scene=indoor",
    "scene.camera.width=160",
    "scene.camera.height=120",
    "scene.trajectory.max_frames=96",
    "scene.lidar.azimuth_steps=512",
    "scene.sequences.0.auto_exposure.enabled=true",
    "progress=false",
]
HOLDOUT_EVERY = 8
MODES = ("estimated", "recorded", "none")
GAMMA = 2.2


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


def score_renders(renders: torch.Tensor, depth: torch.Tensor, images: torch.Tensor) -> dict:
    """PSNR (raw and per-image gain fitted) over covered pixels, and the covered share."""
    raw, fitted, covered = [], [], []
    for render, d, image in zip(renders, depth, images, strict=True):
        mask = d[0] > 0
        r = render[:, mask]
        i = image[:, mask]
        r_lin, i_lin = r.clamp(0, 1) ** GAMMA, i.clamp(0, 1) ** GAMMA
        usable = (r_lin.mean(0) > 1e-3) & (i.mean(0) > 0.04) & (i.mean(0) < 0.96)
        gain = float((i_lin.mean(0)[usable] / r_lin.mean(0)[usable]).median())
        raw.append(psnr(r, i))
        fitted.append(psnr((gain * r_lin).clamp(0, 1) ** (1 / GAMMA), i))
        covered.append(float(mask.float().mean()))
    return {
        "psnr_raw_db": float(np.mean(raw)),
        "psnr_gain_fitted_db": float(np.mean(fitted)),
        "psnr_gain_fitted_per_frame_db": [round(x, 2) for x in fitted],
        "covered_fraction": float(np.mean(covered)),
    }


def exposure_error(estimated: torch.Tensor, recorded: np.ndarray) -> dict:
    """Log-exposure error after removing the gauge (both at geometric mean 1)."""
    est = estimated.numpy().astype(np.float64)
    log_err = np.log(est) - np.log(recorded)
    log_err -= log_err.mean()
    return {
        "median_abs_pct": float(np.median(np.abs(np.expm1(log_err))) * 100),
        "max_abs_pct": float(np.max(np.abs(np.expm1(log_err))) * 100),
        "rms_log": float(np.sqrt(np.mean(log_err**2))),
        "recorded_range": [float(recorded.min()), float(recorded.max())],
    }


def paired(variants: dict) -> dict:
    """Per held-out frame PSNR differences (gain fitted) between exposure variants."""
    frames = {m: np.array(v["psnr_gain_fitted_per_frame_db"]) for m, v in variants.items()}
    out = {}
    for a, b in (("estimated", "none"), ("recorded", "estimated")):
        d = frames[a] - frames[b]
        out[f"{a}-{b}"] = {
            "mean": float(d.mean()),
            "min": float(d.min()),
            "max": float(d.max()),
            "positive": int((d > 0).sum()),
            "frames": len(d),
        }
    return out


def crop_to_box(points: np.ndarray, normals: np.ndarray, low: np.ndarray, high: np.ndarray):
    keep = ((points >= low) & (points <= high)).all(axis=1)
    return points[keep], normals[keep]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("/tmp/mesh_data/indoor_ae_seed0"))
    parser.add_argument("--out", type=Path, default=Path("experiments/results"))
    parser.add_argument("--mesh-out", type=Path, default=Path("/tmp/mesh_out"))
    parser.add_argument("--atlas-size", type=int, default=1024)
    parser.add_argument("--target-faces", type=int, default=80_000)
    args = parser.parse_args()
    load_start = os.getloadavg()

    scene = OmegaConf.to_object(compose_config(SCENE_OVERRIDES).scene)
    start = time.perf_counter()
    root = simulate_dataset(scene, args.data, show_progress=False)
    simulate_s = time.perf_counter() - start

    seq = read_sequence(root, "mapping")
    ids = np.arange(len(seq))
    train, test = ids[ids % HOLDOUT_EVERY != 0], ids[ids % HOLDOUT_EVERY == 0]
    images = torch.stack([seq.load_rgb(int(i)) for i in ids])
    _, recorded_all = read_exposures(root / "mapping" / EXPOSURE_FILE)  # scoring / oracle only
    recorded = recorded_all[train] / np.exp(np.log(recorded_all[train]).mean())
    cfg = TexturedMeshConfig(
        reconstruction=MeshReconstructionConfig(target_faces=args.target_faces),
        atlas_size=args.atlas_size,
    )

    lidar = read_point_cloud(root / MAP_FILES["lidar_map"])
    low, high = lidar.points.min(axis=0) - 0.05, lidar.points.max(axis=0) + 0.05
    results: dict = {
        "command": "python experiments/mesh_texture.py "
        f"--atlas-size {args.atlas_size} --target-faces {args.target_faces}",
        "scene_overrides": SCENE_OVERRIDES,
        "frames": {"mapping": len(ids), "texturing": len(train), "held_out": len(test)},
        "image_size": [seq.camera.width, seq.camera.height],
        "atlas_size": args.atlas_size,
        "simulate_s": simulate_s,
        "maps": {},
    }
    panels = {}
    for name in ("lidar_map", "tls_map"):
        cloud = read_point_cloud(root / MAP_FILES[name])
        points, normals = crop_to_box(cloud.points, cloud.normals, low, high)
        start = time.perf_counter()
        geometry = reconstruct_mesh(points, normals, cfg.reconstruction)
        entry = {
            "map_points": len(points),
            "reconstruct_s": time.perf_counter() - start,
            "faces": len(geometry.faces),
            "vertices": len(geometry.vertices),
            "area_m2": float(geometry.area),
            "variants": {},
        }
        for mode in MODES:
            exposures = torch.from_numpy(recorded_all[train]) if mode == "recorded" else mode
            built = texture_mesh(
                geometry, images[train], seq.T_wc[train], seq.camera, cfg, exposures
            )
            renderer = MeshRenderer(built.mesh)
            start = time.perf_counter()
            render = renderer.render(seq.T_wc[test], seq.camera)
            render_ms = (time.perf_counter() - start) * 1000 / len(test)
            variant = {
                **score_renders(render.albedo, render.depth, images[test]),
                "textured_texel_fraction": built.textured_fraction,
                "atlas_s": built.seconds["atlas"],
                "texture_s": built.seconds["texture"],
                "render_ms_per_frame": render_ms,
            }
            if built.estimate is not None:
                variant["exposure_error"] = exposure_error(built.exposures, recorded)
                variant["exposure_pairs"] = built.estimate.pairs
                variant["unlinked_views"] = int((~built.estimate.linked).sum())
            entry["variants"][mode] = variant
            panels[(name, mode)] = render.albedo
            if mode == "estimated":
                obj = write_atlas_obj(args.mesh_out / name / "mesh.obj", built.mesh)
                ply = write_atlas_ply(args.mesh_out / name / "mesh.ply", built.mesh)
                entry["export_bytes"] = {
                    "obj+mtl+png": sum(
                        p.stat().st_size for p in obj.parent.iterdir() if p.suffix != ".ply"
                    ),
                    "ply": ply.stat().st_size,
                }
            print(name, mode, json.dumps(variant)[:300], flush=True)
        entry["paired_gain_fitted_db"] = paired(entry["variants"])
        results["maps"][name] = entry
    results["load_average"] = {"start": load_start, "end": os.getloadavg()}
    results["threads"] = torch.get_num_threads()

    frame = len(test) // 2
    row_top = [images[test][frame]] + [panels[("lidar_map", m)][frame] for m in MODES]
    row_bottom = [images[test][frame]] + [panels[("tls_map", m)][frame] for m in MODES]
    grid = torch.cat([torch.cat(row_top, dim=2), torch.cat(row_bottom, dim=2)], dim=1)
    args.out.mkdir(parents=True, exist_ok=True)
    write_rgb(args.out / "mesh_texture.png", grid)
    write_report(args.out / "mesh_texture", markdown(results, int(test[frame])), results)


def markdown(results: dict, frame: int) -> str:
    lines = [
        "# Textured mesh from lidar / TLS maps (seed 2 Eq. 3-4)",
        "",
        f"`{results['command']}`",
        "",
        f"Indoor scene seed 0, {results['image_size'][0]}x{results['image_size'][1]} images, "
        f"mapping run limited to {results['frames']['mapping']} frames with auto exposure; "
        f"{results['frames']['texturing']} frames texture the mesh, every "
        f"{HOLDOUT_EVERY}th ({results['frames']['held_out']}) is held out. Atlas "
        f"{results['atlas_size']}^2, n = 5 views per texel. The TLS map is cropped to the lidar "
        "map's bounding box. PSNR over the pixels the mesh covers; 'gain fitted' fits one "
        "gain per held-out image (its exposure is unknown to the map). `recorded` uses the "
        "simulator's ground-truth exposures: an oracle.",
        "",
        "| map | faces | reconstruct s | exposures | PSNR raw dB | PSNR gain fitted dB | "
        "covered | texels seen | exposure error median / max % | atlas s | texture s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, entry in results["maps"].items():
        for mode, v in entry["variants"].items():
            err = v.get("exposure_error")
            err_text = f"{err['median_abs_pct']:.2f} / {err['max_abs_pct']:.2f}" if err else "-"
            lines.append(
                f"| {name} | {entry['faces']} | {entry['reconstruct_s']:.1f} | {mode} | "
                f"{v['psnr_raw_db']:.2f} | {v['psnr_gain_fitted_db']:.2f} | "
                f"{v['covered_fraction']:.3f} | {v['textured_texel_fraction']:.3f} | "
                f"{err_text} | {v['atlas_s']:.1f} | {v['texture_s']:.1f} |"
            )
    lines += ["", "Paired per-frame differences of the gain-fitted PSNR (dB):", ""]
    for name, entry in results["maps"].items():
        for pair, d in entry["paired_gain_fitted_db"].items():
            lines.append(
                f"- {name}, {pair}: mean {d['mean']:+.2f}, range [{d['min']:+.2f}, "
                f"{d['max']:+.2f}], positive on {d['positive']} of {d['frames']} frames"
            )
    rng = next(iter(results["maps"].values()))["variants"]["estimated"]["exposure_error"]
    lines += [
        "",
        f"Recorded exposures of the texturing frames span {rng['recorded_range'][0]:.2f} - "
        f"{rng['recorded_range'][1]:.2f} (after normalising to geometric mean 1).",
        "The exposure estimator's pair weighting (by shared samples) was chosen on this scene "
        "(seed 0); no other seed has been run. The atlas (xatlas) is the same on every run; "
        "with open3d's UVAtlas before, whose layout varied from run to run, two runs of this "
        "command differed by up to 0.15 dB in a variant's gain-fitted PSNR.",
        f"Load average at start / end: {results['load_average']['start']} / "
        f"{results['load_average']['end']} (2 cores, shared).",
        "",
        f"`mesh_texture.png`: held-out frame {frame}; columns: real image, render with "
        "exposures estimated, recorded, none; rows: lidar map, TLS map.",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
