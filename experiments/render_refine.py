"""Render-and-compare refinement of localised query poses: TLS point cloud or trained NeRF.

For every ``--every``-th frame of ``query_same`` with a localised pose (the relocaliser's
``estimates.tum``, camera-to-world, matched by timestamp), the pose is refined through a
differentiable render of a map, and again from the true pose perturbed by each seeded
``--perturb-m`` / ``--perturb-deg`` pair (the refinement's basin; with no values, the localised
starts only). The per-query work is the library's
(:func:`diffloc.optim.render_refine.refine_query`, as ``diffloc task=crossmodal
task.refine.enabled=true`` runs it). ``--map`` picks the map:

- ``cloud``: the soft-splatted TLS cloud coloured from the mapping images (as
  ``task=crossmodal map=tls`` does: :func:`diffloc.pipeline.crossmodal_stage.colored_point_map`);
- ``nerf``: the dataset's trained radiance-field submaps (``diffloc task=train_nerf
  nerf.submap=<k>``, read from ``--nerf-dir``, ``<scene>/nerf`` by default). Each query is
  served, as ``map=nerf`` serves a render pose, by the submap whose core mapping frames have
  the largest affinity to its *localised* pose (what a user has; the perturbed starts of the
  same query use the same field); the query's appearance code is fitted at each start pose
  (NeRF-W test-time fit, its CPU time counted in the query's) before the refinement.
  ``--submaps`` keeps only the queries served by those submaps, so only they need training.

Writes ``experiments/results/render_refine_<label>.{json,md}``, both starting with the
commands that made them (``--command`` for the inputs' commands, then this one): median / p90
translation and rotation error before and after, the fraction accepted, CPU and wall ms per
query, and the load.

    python3 experiments/render_refine.py --scene data/indoor_seed0 \
        --estimates outputs/seed0_indoor/query_same/estimates.tum --label indoor_seed0 \
        --every 15 --max-queries 8
    python3 experiments/render_refine.py --map nerf --scene data/indoor_seed0 \
        --estimates <run>/query_same/estimates.tum --label nerf_indoor_seed0 \
        --submaps 1 2 --every 5 --max-queries 12 --perturb-m 0.1 0.3 --perturb-deg 2 5
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from diffloc.eval.report_files import made_by_lines, write_report
from diffloc.features.local import XFeatConfig, XFeatExtractor
from diffloc.geometry.se3 import se3_exp
from diffloc.io.dataset import read_sequence
from diffloc.io.ply import read_point_cloud
from diffloc.io.trajectory import read_tum
from diffloc.maps.nerf.export import load_field
from diffloc.maps.nerf.submaps import load_submaps
from diffloc.maps.pointcloud import PointMap
from diffloc.optim.render_refine import (
    CloudMaps,
    FieldSubmaps,
    MatchCheckConfig,
    RenderRefineConfig,
    refine_query,
)
from diffloc.pipeline.crossmodal_stage import colored_point_map
from diffloc.render.point_sizes import PointSizes


def coloured_cloud(scene: Path, voxel_m: float, cache: Path) -> PointMap:
    """The TLS cloud thinned to one point per ``voxel_m`` cell (``--thin-m`` thins it
    further for rendering), coloured from the mapping
    images at 160x120 (cached as PLY in ``cache``)."""
    path = cache / f"{scene.name}_tls_{voxel_m:g}.ply"
    if path.is_file():
        return PointMap.load_ply(path)
    cloud = read_point_cloud(scene / "map" / "tls_map.ply")
    _, first = np.unique(np.floor(cloud.points / voxel_m), axis=0, return_index=True)
    cloud.points, cloud.normals = cloud.points[first], cloud.normals[first]
    mapping = read_sequence(scene, "mapping")
    camera = mapping.camera.scaled(160 / mapping.camera.width)
    coloured = colored_point_map(cloud, mapping, camera, PointSizes.inverse_depth(1.0, 8.0))
    cache.mkdir(parents=True, exist_ok=True)
    coloured.save_ply(path)
    return coloured


def cloud_maps(args: argparse.Namespace, scene: Path) -> CloudMaps:
    """The TLS cloud, thinned to one point per ``--thin-m`` cell and cropped to each start's
    view (one map, served index 0)."""
    cloud = coloured_cloud(scene, args.voxel_m, Path(args.cache))
    return CloudMaps(cloud.positions, cloud.colors, args.thin_m, args.max_depth_m)


def field_maps(args: argparse.Namespace, scene: Path) -> FieldSubmaps:
    """The dataset's trained submap fields, each query served by one (module doc)."""
    folder = Path(args.nerf_dir) if args.nerf_dir else scene / "nerf"
    submaps, config = load_submaps(folder / "submaps.json")

    def load(k: int):
        path = folder / f"submap_{k}" / "field"
        if not (path / "field.json").is_file():
            raise SystemExit(
                f"{path} has no trained field: run `diffloc task=train_nerf "
                f"dataset={scene} nerf.submap={k}` (with the run's nerf.* overrides)"
            )
        return load_field(path)

    mapping_T_wc = read_sequence(scene, "mapping").T_wc
    every = [s.index for s in submaps]
    return FieldSubmaps(submaps, config, mapping_T_wc, load, every, args.fit_steps)


def pose_errors(T: torch.Tensor, T_gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,) translation error (m) and rotation error (deg) of poses (B, 4, 4)."""
    dt = (T[:, :3, 3] - T_gt[:, :3, 3]).norm(dim=-1)
    R = T_gt[:, :3, :3].transpose(1, 2) @ T[:, :3, :3]
    cos = ((R.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1)
    return dt, torch.rad2deg(torch.arccos(cos))


def perturbed(T_gt: torch.Tensor, metres: float, degrees: float, seed: int) -> torch.Tensor:
    """``T_gt @ exp(delta)`` with a random direction of ``metres`` and an axis of ``degrees``."""
    g = torch.Generator().manual_seed(seed)
    v = F.normalize(torch.randn(len(T_gt), 3, generator=g, dtype=T_gt.dtype), dim=-1) * metres
    w = F.normalize(torch.randn(len(T_gt), 3, generator=g, dtype=T_gt.dtype), dim=-1)
    return T_gt @ se3_exp(torch.cat((v, w * math.radians(degrees)), -1))


def perturbations(settings: dict) -> list[tuple[float, float]]:
    """The (metres, degrees) pairs of the perturbed starts (one float each in older files)."""
    metres, degrees = settings["perturb_m"], settings["perturb_deg"]
    if not isinstance(metres, list):
        return [(metres, degrees)]
    return list(zip(metres, degrees, strict=True))


def start_name(metres: float, degrees: float) -> str:
    return f"perturbed {100 * metres:g} cm / {degrees:g} deg"


def summary(values: np.ndarray) -> dict[str, float]:
    return {"median": float(np.median(values)), "p90": float(np.percentile(values, 90))}


def query_frames(args: argparse.Namespace, maps, seq, stamps, T_est: torch.Tensor) -> list:
    """(frame, estimate row, serving map) of the queries: every ``--every``-th localised frame,
    served by one of ``--submaps`` (all when empty), at most ``--max-queries``."""
    index = {round(float(t), 6): i for i, t in enumerate(seq.timestamps)}
    frames = [(index[round(float(t), 6)], k) for k, t in enumerate(stamps)]
    frames = [f for f in frames if f[0] % args.every == 0]
    served = maps.serving(torch.stack([T_est[k] for _, k in frames]).double())
    keep = [
        (frame, k, s)
        for (frame, k), s in zip(frames, served, strict=True)
        if not args.submaps or s in args.submaps
    ]
    return keep[: args.max_queries]


def run(args: argparse.Namespace) -> list[dict]:
    scene = Path(args.scene)
    maps = cloud_maps(args, scene) if args.map == "cloud" else field_maps(args, scene)
    seq = read_sequence(scene, "query_same")
    stamps, T_est_all = read_tum(args.estimates)
    camera = seq.camera.scaled(args.scale)  # the refinement's size, for the record
    config = RenderRefineConfig(
        levels=tuple(args.levels),
        iterations=args.iterations,
        min_alpha=args.min_alpha,
        min_improvement=args.min_improvement,
        min_correlation=args.min_correlation,
        photometric_sigma=args.photometric_sigma,
        kernel_scale=args.kernel_scale,
    )
    check = check_config(args)
    extractor = XFeatExtractor(XFeatConfig()) if check else None
    args.load_start = list(os.getloadavg())
    rows = []
    for frame, k, served in query_frames(args, maps, seq, stamps, T_est_all):
        full = seq.load_rgb(frame)[None].double()
        T_gt = seq.T_wc[frame][None].double()
        starts = {} if args.skip_localised else {"localised": T_est_all[k][None].double()}
        for metres, degrees in perturbations(vars(args)):
            starts[start_name(metres, degrees)] = perturbed(
                T_gt, metres, degrees, args.seed + frame
            )
        for name, T0 in starts.items():
            refined = refine_query(
                maps, served, full, T0, seq.camera, args.scale, config, check, extractor
            )
            result, info = refined.result, dict(refined.info)
            if result.evidence is not None:
                info |= evidence_record(result.evidence)
            before, after = pose_errors(T0, T_gt), pose_errors(result.T_wc, T_gt)
            moved = pose_errors(result.T_refined, T_gt)
            rows.append(
                {
                    "frame": frame,
                    "start": name,
                    **info,
                    "t_before_m": float(before[0][0]),
                    "r_before_deg": float(before[1][0]),
                    "t_after_m": float(after[0][0]),
                    "r_after_deg": float(after[1][0]),
                    "t_refined_m": float(moved[0][0]),
                    "r_refined_deg": float(moved[1][0]),
                    "accepted": bool(result.accepted[0]),
                    "correlation": float(result.correlation[0]),
                    "cost_before": float(result.cost_before[0]),
                    "cost_after": float(result.cost_after[0]),
                    "cpu_ms": refined.cpu_ms,
                    "wall_ms": refined.wall_ms,
                }
            )
            print(json.dumps(rows[-1]), flush=True)
            args.load_end = list(os.getloadavg())
            write(args, rows, [camera.width, camera.height])
    return rows


CHECK_PX = (1.0, 1.5, 2.0, 3.0, 4.0)
"""Tolerances at which each row records its aligned matches (so that a rule can be chosen
from the recorded rows, without re-running a query)."""


def check_config(args: argparse.Namespace) -> MatchCheckConfig | None:
    """The match check of ``--check-*`` (None with ``--check-width 0``)."""
    if not args.check_width:
        return None
    return MatchCheckConfig(
        width=args.check_width,
        inlier_px=args.check_px,
        min_inliers=args.check_min_inliers,
        min_fraction=args.check_min_fraction,
        min_gain=args.check_min_gain,
    )


def evidence_record(evidence) -> dict:
    """The row fields of one query's match evidence: matches, median displacement and aligned
    matches at each of :data:`CHECK_PX`, before and after, and whether it passed."""
    out = {"check_passed": bool(evidence.passed[0])}
    for when in ("before", "after"):
        d = getattr(evidence, f"displacement_{when}")[0]
        out[f"matches_{when}"] = len(d)
        out[f"median_px_{when}"] = float(d.median()) if len(d) else math.inf
        out[f"aligned_{when}"] = {f"{px:g}": int((d <= px).sum()) for px in CHECK_PX}
    return out


def photometric_accepted(row: dict, s: dict) -> bool:
    """The cost and correlation rule (package doc, (a) and (b)) from a row's record."""
    return (
        row["cost_after"] < (1 - s["min_improvement"]) * row["cost_before"]
        and row["correlation"] >= s["min_correlation"]
    )


def check_rule(
    row: dict, px: float, min_inliers: int, min_fraction: float, min_gain: float
) -> bool:
    """The match check (c) at ``px`` / ``min_inliers`` / ``min_fraction`` / ``min_gain`` from a
    row's record."""
    after, before = row["aligned_after"][f"{px:g}"], row["aligned_before"][f"{px:g}"]
    return (
        after >= min_inliers
        and after >= min_fraction * row["matches_after"]
        and after >= min_gain * before
    )


def redecide(rows: list[dict], s: dict) -> list[dict]:
    """Rows re-decided under the settings' check rule from their record (``--from-json`` with
    other ``--check-*`` values): accepted = (a), (b) and (c), the pose after = the refined one
    where accepted, else the start."""
    out = []
    for r in rows:
        keep = photometric_accepted(r, s) and check_rule(
            r,
            s["check_px"],
            s["check_min_inliers"],
            s["check_min_fraction"],
            s["check_min_gain"],
        )
        out.append(
            r
            | {
                "accepted": keep,
                "t_after_m": r["t_refined_m"] if keep else r["t_before_m"],
                "r_after_deg": r["r_refined_deg"] if keep else r["r_before_deg"],
            }
        )
    return out


def wrong(row: dict, accepted: bool) -> bool:
    """A move accepted that ends farther from the true position than it started."""
    return accepted and row["t_refined_m"] > row["t_before_m"]


RULE_KEYS = ("px", "min_inliers", "min_fraction", "min_gain")


def rule_grid(rows: list[dict], s: dict) -> list[dict]:
    """Accepted / wrong accepted of every perturbed start under a grid of check rules (the
    tuning table, read from the recorded rows)."""
    sel = [r for r in rows if r["start"] != "localised"]
    photo = [photometric_accepted(r, s) for r in sel]
    grid = [{"px": None, "min_inliers": None, "min_fraction": None, "min_gain": None}]
    grid += [
        {"px": px, "min_inliers": 20, "min_fraction": f, "min_gain": g}
        for px in (1.0, 2.0, 3.0)
        for f in (0.0, 0.25, 0.35, 0.45)
        for g in (1.0, 1.5, 2.0)
    ]
    out = []
    for rule in grid:
        acc = [
            p and (rule["px"] is None or check_rule(r, *(rule[k] for k in RULE_KEYS)))
            for r, p in zip(sel, photo, strict=True)
        ]
        good = [a and not wrong(r, a) for r, a in zip(sel, acc, strict=True)]
        out.append(
            rule
            | {
                "starts": len(sel),
                "accepted": int(sum(acc)),
                "wrong_accepted": int(sum(wrong(r, a) for r, a in zip(sel, acc, strict=True))),
                "right_accepted": int(sum(good)),
            }
        )
    return out


def summarise(args: argparse.Namespace, rows: list[dict], size: list[int]) -> dict:
    """The JSON record: commands, settings, camera size, per-start summary and all rows."""
    table = {}
    for name in dict.fromkeys(r["start"] for r in rows):
        sel = [r for r in rows if r["start"] == name]
        col = lambda key, sel=sel: np.array([r[key] for r in sel])  # noqa: E731
        table[name] = {
            "queries": len(sel),
            "t_before_m": summary(col("t_before_m")),
            "t_after_m": summary(col("t_after_m")),
            "r_before_deg": summary(col("r_before_deg")),
            "r_after_deg": summary(col("r_after_deg")),
            "accepted": float(col("accepted").mean()),
            "accepted_n": int(col("accepted").sum()),
            "wrong_accepted_n": int(sum(wrong(r, r["accepted"]) for r in sel)),
            "improved_t": float((col("t_after_m") < col("t_before_m")).mean()),
            **strict_rule(sel, args.strict_improvement),
            "cpu_ms_median": float(np.median(col("cpu_ms"))),
            "wall_ms_median": float(np.median(col("wall_ms"))),
        }
    settings = {k: v for k, v in vars(args).items() if k != "commands"}
    return {
        "commands": getattr(args, "commands", []),
        "settings": settings,
        "camera": size,
        "summary": table,
        "check_rules": rule_grid(rows, settings),
        "rows": rows,
    }


def strict_rule(rows: list[dict], improvement: float) -> dict:
    """The figures had the run required a cost drop of ``improvement`` (>= the run's): the
    rule reads only the recorded costs and the acceptance, so no query is re-run."""
    keep = np.array(
        [r["accepted"] and r["cost_after"] < (1 - improvement) * r["cost_before"] for r in rows]
    )
    t = np.where(keep, [r["t_after_m"] for r in rows], [r["t_before_m"] for r in rows])
    deg = np.where(keep, [r["r_after_deg"] for r in rows], [r["r_before_deg"] for r in rows])
    return {
        "strict_improvement": improvement,
        "strict_accepted": float(keep.mean()),
        "strict_t_after_m": summary(t),
        "strict_r_after_deg": summary(deg),
    }


def write(args: argparse.Namespace, rows: list[dict], size: list[int]) -> None:
    """(Re)write the JSON and Markdown results with the rows so far."""
    result = summarise(args, rows, size)
    write_report(Path(args.out) / f"render_refine_{args.label}", markdown(result), result)


def describe_map(s: dict) -> tuple[str, str]:
    """The title's map name and the sentence on how the map was rendered."""
    if s.get("map", "cloud") == "cloud":
        return "TLS cloud, soft splats", (
            f"cloud coloured at {s['voxel_m']} m and rendered thinned to one point per "
            f"{s['thin_m']} m cell within {s['max_depth_m']} m"
        )
    served = f"submaps {s['submaps']}" if s["submaps"] else "all submaps"
    return "trained NeRF submaps", (
        f"fields of {s['nerf_dir'] or s['scene'] + '/nerf'} ({served}; each query served by the "
        f"submap of its localised pose), appearance code fitted at each start pose in "
        f"{s['fit_steps']} Adam steps (CPU time included)"
    )


def markdown(result: dict) -> str:
    s = result["settings"]
    w, h = result["camera"]
    title, rendered = describe_map(s)
    lines = [f"# Render-and-compare refinement, {s['label']} query_same ({title})", ""]
    if result.get("commands"):
        lines += made_by_lines(result["commands"])
    starts = ", ".join(f"{100 * m:g} cm / {d:g} deg" for m, d in perturbations(s))
    acceptance = ""
    if "min_improvement" in s:  # older files did not record it
        acceptance = (
            f"; acceptance: cost drop > {100 * s['min_improvement']:g} %, correlation >= "
            f"{s['min_correlation']:g}"
        )
    if s.get("check_width"):
        acceptance += (
            f", and the match check at {s['check_width']} px width: >= "
            f"{s['check_min_inliers']} XFeat matches and >= "
            f"{100 * s.get('check_min_fraction', 0.0):g} % of them aligned within "
            f"{s['check_px']:g} px, and >= {s['check_min_gain']:g} x the aligned at the start"
            + (" (rows re-decided under this rule from their record)" if s.get("redecided") else "")
        )
    residual = ""
    if "photometric_sigma" in s:  # older files did not record it
        residual = (
            f"; photometric sigma {s['photometric_sigma']:g}, Cauchy scale {s['kernel_scale']:g}"
        )
    load = ""
    if "load_start" in s:
        load = (
            f" Load (1 / 5 / 15 min) at start {'/'.join(f'{x:.1f}' for x in s['load_start'])}, "
            f"at end {'/'.join(f'{x:.1f}' for x in s['load_end'])}."
        )
    lines += [
        f"Every {s['every']}th localised query, {w}x{h}, levels {s['levels']}, "
        f"{s['iterations']} LM iterations per level, {rendered}{residual}; "
        f"perturbed starts: true pose + {starts} (seeded, one direction per query){acceptance}. "
        f"CPU ms per query; wall ms under load (2 shared cores).{load}",
        "",
        "| start | n | t med before | t med after | t p90 before | t p90 after | r med before | "
        "r med after | r p90 before | r p90 after | accepted | wrong accepted | t improved | "
        "CPU ms | wall ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, t in result["summary"].items():
        lines.append(
            f"| {name} | {t['queries']} | {100 * t['t_before_m']['median']:.2f} cm | "
            f"{100 * t['t_after_m']['median']:.2f} cm | {100 * t['t_before_m']['p90']:.2f} cm | "
            f"{100 * t['t_after_m']['p90']:.2f} cm | {t['r_before_deg']['median']:.3f} | "
            f"{t['r_after_deg']['median']:.3f} | {t['r_before_deg']['p90']:.3f} | "
            f"{t['r_after_deg']['p90']:.3f} | {100 * t['accepted']:.0f} % | "
            f"{t.get('wrong_accepted_n', '-')} | "
            f"{100 * t['improved_t']:.0f} % | {t['cpu_ms_median']:.0f} | "
            f"{t['wall_ms_median']:.0f} |"
        )
    lines += [
        "",
        "Had the run required a cost drop of more than "
        f"{100 * s['strict_improvement']:.0f} % (recomputed from "
        "the recorded costs, no query re-run):",
        "",
        "| start | accepted | t med after | t p90 after | r med after | r p90 after |",
        "|---|---|---|---|---|---|",
    ]
    for name, t in result["summary"].items():
        lines.append(
            f"| {name} | {100 * t['strict_accepted']:.0f} % | "
            f"{100 * t['strict_t_after_m']['median']:.2f} cm | "
            f"{100 * t['strict_t_after_m']['p90']:.2f} cm | "
            f"{t['strict_r_after_deg']['median']:.3f} | {t['strict_r_after_deg']['p90']:.3f} |"
        )
    if result.get("check_rules") and result["check_rules"][0]["starts"]:
        lines += [
            "",
            "Perturbed starts accepted under other match-check rules (from the recorded rows; "
            "wrong = ends farther from the true position than it started; px = alignment "
            "tolerance, n = min aligned matches, fraction = min aligned fraction of the "
            "matches, gain = min ratio to the start's aligned):",
            "",
            "| px | n | fraction | gain | starts | accepted | right | wrong |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for g in result["check_rules"]:
            rule = (
                "no check | | | "
                if g["px"] is None
                else f"{g['px']:g} | {g['min_inliers']} | {g['min_fraction']:g} | {g['min_gain']:g}"
            )
            lines.append(
                f"| {rule} | {g['starts']} | {g['accepted']} | {g['right_accepted']} | "
                f"{g['wrong_accepted']} |"
            )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--map", choices=("cloud", "nerf"), default="cloud")
    parser.add_argument("--scene", default="data/indoor_seed0")
    parser.add_argument("--estimates", default="outputs/seed0_indoor/query_same/estimates.tum")
    parser.add_argument("--label", default="indoor_seed0")
    parser.add_argument("--every", type=int, default=4)
    parser.add_argument("--max-queries", type=int, default=1000)
    parser.add_argument("--scale", type=float, default=0.125)
    parser.add_argument("--levels", type=float, nargs="+", default=[0.5, 1.0])
    parser.add_argument("--min-alpha", type=float, default=0.5)
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--min-improvement", type=float, default=0.05)
    parser.add_argument("--min-correlation", type=float, default=0.5)
    parser.add_argument("--photometric-sigma", type=float, default=0.05)
    parser.add_argument("--kernel-scale", type=float, default=2.0)
    parser.add_argument("--voxel-m", type=float, default=0.05, help="cloud: colouring voxel")
    parser.add_argument("--thin-m", type=float, default=0.1, help="cloud: render spacing")
    parser.add_argument("--max-depth-m", type=float, default=8.0, help="cloud: crop depth")
    parser.add_argument("--nerf-dir", default="", help="nerf: train_nerf's folder")
    parser.add_argument("--submaps", type=int, nargs="*", default=[], help="nerf: served by")
    parser.add_argument("--fit-steps", type=int, default=60, help="nerf: appearance fit steps")
    parser.add_argument(
        "--perturb-m", type=float, nargs="*", default=[0.10], help="none: localised starts only"
    )
    parser.add_argument("--perturb-deg", type=float, nargs="*", default=[2.0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--skip-localised", action="store_true", help="refine the perturbed starts only"
    )
    parser.add_argument("--cache", default="/tmp/diffloc_render_refine")
    parser.add_argument("--out", default="experiments/results")
    parser.add_argument("--strict-improvement", type=float, default=0.05)
    parser.add_argument(
        "--command", action="append", default=[], help="a command that made the inputs"
    )
    parser.add_argument(
        "--from-json", default="", help="re-summarise the rows of an earlier result file"
    )
    parser.add_argument(
        "--check-width", type=int, default=0, help="match check at this width (0: none)"
    )
    parser.add_argument("--check-px", type=float, default=2.0, help="aligned match, pixels")
    parser.add_argument("--check-min-inliers", type=int, default=20)
    parser.add_argument("--check-min-fraction", type=float, default=0.25)
    parser.add_argument("--check-min-gain", type=float, default=1.5)
    parser.add_argument(
        "--redecide",
        action="store_true",
        help="with --from-json: re-decide the rows under these --check-* and "
        "--min-correlation values (written under --label)",
    )
    args = parser.parse_args()
    if len(args.perturb_m) != len(args.perturb_deg):
        parser.error("--perturb-m and --perturb-deg need the same number of values")
    if args.map == "cloud" and args.submaps:
        parser.error("--submaps selects radiance-field submaps (--map nerf)")
    this = "PYTHONPATH=. OMP_NUM_THREADS=1 python3 " + shlex.join(sys.argv)
    args.commands = [*args.command, this]
    torch.set_num_threads(1)
    if args.from_json:
        earlier = json.loads(Path(args.from_json).read_text())
        settings = earlier["settings"] | {"strict_improvement": args.strict_improvement}
        settings |= {"out": args.out, "from_json": args.from_json}
        settings["commands"] = earlier.get("commands", [])
        rows = earlier["rows"]
        if args.redecide:
            names = ("check_px", "check_min_inliers", "check_min_fraction", "check_min_gain")
            settings |= {k: getattr(args, k) for k in names} | {"redecided": True}
            settings |= {"min_correlation": args.min_correlation, "label": args.label}
            settings["commands"] = [*settings["commands"], this]
            rows = redecide(rows, settings)
        write(argparse.Namespace(**settings), rows, earlier["camera"])
        args.label = settings["label"]
    else:
        run(args)
    print((Path(args.out) / f"render_refine_{args.label}.md").read_text())


if __name__ == "__main__":
    main()
