"""Seed 2's Algorithm 1 on rendered point-cloud databases of a simulated dataset.

For each point map (``map/tls_map.ply``, ``map/lidar_map.ply``):

1. colour the points from the ``mapping`` images (:meth:`PointMap.colorize`); the occlusion
   test uses depth rendered from the cloud itself at the mapping poses (no simulator depth);
2. select render poses on the free-path corridor (:func:`select_render_poses`, indoor
   defaults: 2 m spacing, 4 views, camera 1.5 m above the floor); ``--yaw-views 8``
   (``PoseSelectionConfig.views_per_sample``) adds the four diagonals (views 45 deg apart);
3. render the RGB-D database, single-pass Eq. 2 (every point its own rounded size) and the
   multi-pass merge (a few fixed sizes), and build local features + NetVLAD;
4. localise every frame of the query sequences (:class:`RenderedDatabaseLocalizer`) and score
   against the ground truth (read here for scoring only).

Reported per sequence and database: found (a PnP pose; seed 2's answer) and the precision of
the found poses, accepted (found and passed the localiser's validation) and the precision of
the accepted poses (within 1 m / 30 deg), localisation rates at (0.25 m, 2 deg), (0.5 m,
5 deg) and (1 m, 30 deg) (seed 2's indoor criterion) as shares of all queries counting only
accepted poses, median translation / rotation error of the accepted queries, retrieval rate
(top-1 retrieved render within the sampling distance and 45 deg of the query), hole share of
the database images, candidates matched per query, median ms per query (features, retrieval,
re-ranking, matching, PnP; wall time under the load recorded in the file, and the process's CPU
time, which the load inflates less), and the distance / angle from
each query to its nearest render pose. The JSON also holds every query's candidates with
their evidence and true errors (``per_query``), which ``experiments/rendered_replay.py``
replays to choose the re-ranking and validation settings. Re-ranking and validation default
to :class:`RenderedLocalizerConfig`'s; ``--top-k 1 --select first --no-validation
--rerank-candidates 0`` is seed 2's Algorithm 1 (``--rerank-candidates 0``: no
mutual-nearest-neighbour re-ranking of the global retrieval). Images are downscaled by
``--scale`` (0.5: 320x240 for the 640x480 dataset).

Usage:
    PYTHONPATH=. OMP_NUM_THREADS=1 python3 experiments/rendered_localization.py \\
        --dataset data/indoor_seed0 --work /tmp/rendered_work
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch

from diffloc.crossmodal.database import DatabaseConfig, RenderedDatabase, render_database
from diffloc.crossmodal.pose_selection import (
    VIEWS_PER_SAMPLE,
    PoseSelectionConfig,
    select_render_poses,
)
from diffloc.crossmodal.synthesize import PointCloudMap
from diffloc.eval.metrics import PoseErrors, pose_errors, precision, recall
from diffloc.eval.report_files import write_report
from diffloc.features.local import XFeatConfig, XFeatExtractor
from diffloc.features.matching import LighterGlueConfig, LighterGlueMatcher
from diffloc.features.retrieval_eval import pairwise_pose_distances
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.dataset import read_sequence
from diffloc.io.ply import read_point_cloud
from diffloc.io.sequence import SequenceData
from diffloc.maps.pointcloud import PointMap
from diffloc.pipeline.crossmodal_report import retrieval_hits
from diffloc.pipeline.crossmodal_stage import colored_point_map, scaled_images
from diffloc.progress import progress
from diffloc.reloc.rendered import (
    RenderedDatabaseLocalizer,
    RenderedLocalization,
    RenderedLocalizerConfig,
)
from diffloc.reloc.rerank import RerankConfig
from diffloc.render.point_sizes import PointSizes

THRESHOLDS = ((0.25, 2.0), (0.5, 5.0), (1.0, 30.0))
"""(metres, degrees) localisation criteria; (1 m, 30 deg) is seed 2's indoor one."""
CORRECT = (1.0, 30.0)
"""An accepted pose within this is correct (precision)."""


def _parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", type=Path, default=Path("data/indoor_seed0"))
    parser.add_argument("--work", type=Path, default=Path("/tmp/rendered_work"))
    parser.add_argument("--out", type=Path, default=Path("experiments/results"))
    parser.add_argument("--tag", default="indoor_seed0")
    parser.add_argument("--maps", nargs="+", default=["tls_map", "lidar_map"])
    parser.add_argument("--modes", nargs="+", default=["single", "multi"])
    parser.add_argument(
        "--sequences", nargs="+", default=["query_same", "query_lane", "query_reverse"]
    )
    parser.add_argument("--retrievers", nargs="+", default=["netvlad"])
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--rho-min", type=float, default=1.0)
    parser.add_argument("--rho-max", type=float, default=8.0, help="Eq. 2 size at 1 m (px)")
    parser.add_argument("--levels", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--every", type=int, default=1, help="localise every n-th query frame")
    parser.add_argument(
        "--yaw-views", type=int, choices=VIEWS_PER_SAMPLE, default=4, help="views per position"
    )
    defaults = RenderedLocalizerConfig()
    parser.add_argument("--top-k", type=int, default=defaults.top_k)
    parser.add_argument("--select", choices=["first", "most_inliers"], default=defaults.select)
    parser.add_argument(
        "--stop-inliers", type=int, default=defaults.stop_inliers, help="0: try all top-k"
    )
    parser.add_argument(
        "--no-validation", action="store_true", help="accept every pose found (seed 2)"
    )
    rerank = defaults.rerank or RerankConfig()
    parser.add_argument(
        "--rerank-candidates",
        type=int,
        default=rerank.candidates,
        help="global-retrieval images re-ranked by mutual NN matches (0: no re-ranking)",
    )
    parser.add_argument("--rerank-keypoints", type=int, default=rerank.keypoints)
    parser.add_argument("--rerank-min-similarity", type=float, default=rerank.min_similarity)
    parser.add_argument(
        "--oracle-retrieval",
        action="store_true",
        help="ORACLE: try the render nearest to the true query pose instead of retrieving",
    )
    return parser.parse_args()


def _sizes(mode: str, args: argparse.Namespace) -> PointSizes:
    if mode == "single":
        return PointSizes.inverse_depth(args.rho_min, args.rho_max)
    return PointSizes.multi_pass(args.rho_min, args.rho_max, tuple(args.levels))


def _colored_map(
    name: str, args: argparse.Namespace, mapping: SequenceData, camera: PinholeCamera
) -> PointMap:
    """The map ``name`` coloured from the mapping images (cached under ``--work``)."""
    cache = args.work / f"{name}_colored_x{args.scale:g}.npz"
    if cache.is_file():
        return PointMap.load(cache)
    cloud = read_point_cloud(args.dataset / "map" / f"{name}.ply")
    sizes = PointSizes.inverse_depth(args.rho_min, args.rho_max)
    point_map = colored_point_map(cloud, mapping, camera, sizes, show_progress=True)
    args.work.mkdir(parents=True, exist_ok=True)
    point_map.save(cache)
    return point_map


def _nearest_render(
    T_query: torch.Tensor, T_render: torch.Tensor
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Per query: distance to the nearest render position, the smallest angle among the
    renders at that position (its 4 views), and the index of that render (an ORACLE when
    used as the reference: it reads the true query poses)."""
    distance, angle = pairwise_pose_distances(T_query, T_render)
    nearest = distance.min(1, keepdim=True).values
    at_nearest = torch.where(distance <= nearest + 1e-6, angle, torch.full_like(angle, math.inf))
    best_angle, index = at_nearest.min(1)
    return nearest[:, 0].numpy(), np.degrees(best_angle.numpy()), index.tolist()


def _evaluate(
    localizer: RenderedDatabaseLocalizer,
    db: RenderedDatabase,
    seq: SequenceData,
    camera: PinholeCamera,
    indices: list[int],
    spacing_m: float,
    oracle: bool,
) -> dict:
    T_gt = seq.T_wc[indices]
    near_m, near_deg, nearest = _nearest_render(T_gt, db.T_wc)
    if not oracle:
        nearest = [None] * len(indices)
    results = []
    for i, reference in zip(progress(indices, f"{seq.name}"), nearest, strict=True):
        image = scaled_images(seq, camera, [i])[0]
        references = None if reference is None else torch.tensor([reference])
        results.append(localizer.localize(image, camera, references))
    T_est = torch.stack([r.T_wc for r in results])
    found = np.array([r.success for r in results])
    accepted = np.array([r.accepted for r in results])
    errors = pose_errors(T_est.numpy(), T_gt.numpy(), accepted)
    errors_found = pose_errors(T_est.numpy(), T_gt.numpy(), found)
    top = torch.tensor([int(r.retrieved[0]) if len(r.retrieved) else -1 for r in results])
    retrieved_ok = retrieval_hits(T_gt, db.T_wc[top.clamp_min(0)], (top >= 0).numpy(), spacing_m)
    m, d = CORRECT
    return {
        "queries": len(indices),
        "found": int(found.sum()),
        "accepted": int(accepted.sum()),
        "precision_found": _precision(errors_found, m, d),
        "precision_accepted": _precision(errors, m, d),
        "rates": {f"{m:g}m_{d:g}deg": recall(errors, m, d) for m, d in THRESHOLDS},
        "rates_found": {f"{m:g}m_{d:g}deg": recall(errors_found, m, d) for m, d in THRESHOLDS},
        "retrieval_rate": float(retrieved_ok.mean()),
        "median_translation_m": _median(errors.translation_m[accepted]),
        "median_rotation_deg": _median(errors.rotation_deg[accepted]),
        "median_ms_per_query": float(np.median([r.time_ms for r in results])),
        "median_cpu_ms_per_query": float(np.median([r.cpu_ms for r in results])),
        "median_candidates_tried": float(np.median([len(r.candidates) for r in results])),
        "median_matches": float(np.median([r.num_matches for r in results])),
        "median_points_with_depth": float(np.median([r.num_points for r in results])),
        "nearest_render_m": {"median": float(np.median(near_m)), "max": float(near_m.max())},
        "nearest_render_deg": {"median": float(np.median(near_deg)), "max": float(near_deg.max())},
        "per_query": [
            _query_record(i, r, T) for i, r, T in zip(indices, results, T_gt, strict=True)
        ],
    }


def _precision(errors: PoseErrors, metres: float, degrees: float) -> float | None:
    """Share of the localised poses within (``metres``, ``degrees``); ``None`` if none."""
    value = precision(errors, metres, degrees)
    return None if math.isnan(value) else value


def _query_record(frame: int, result: RenderedLocalization, T_gt: torch.Tensor) -> dict:
    """Every candidate's evidence and its true error (for choosing the validation)."""
    rows = []
    for c in result.candidates:
        e = pose_errors(c.T_wc[None].numpy(), T_gt[None].numpy(), np.array([c.success]))
        rows.append(
            {
                "reference": c.reference,
                "success": c.success,
                "matches": c.num_matches,
                "points": c.num_points,
                "inliers": c.num_inliers,
                "coverage": c.coverage,
                "rms_px": None if math.isnan(c.rms_px) else round(c.rms_px, 3),
                "position_m": c.T_wc[:3, 3].tolist(),
                "error_m": round(float(e.translation_m[0]), 4) if c.success else None,
                "error_deg": round(float(e.rotation_deg[0]), 3) if c.success else None,
            }
        )
    return {
        "frame": frame,
        "retrieved": result.retrieved.tolist(),
        "accepted": result.accepted,
        "candidates": rows,
    }


def _median(x: np.ndarray) -> float | None:
    return float(np.median(x)) if x.size else None


def _retrieval_label(retrieval: dict) -> str:
    if retrieval["oracle_nearest_render"]:
        return "ORACLE nearest render to the true pose (diagnostic, not a result)"
    rerank = retrieval.get("rerank")
    label = f"top-{retrieval['top_k']} ({retrieval['select']})"
    if rerank is None:
        return label
    return (
        f"{label} of the global top-{rerank['candidates']} re-ranked by mutual NN matches "
        f"({rerank['keypoints']} keypoints, similarity > {rerank['min_similarity']:g})"
    )


def _markdown(report: dict) -> str:
    head = ["sequence", "map", "mode", "retr.", "DB", "holes", "found", "prec. found"]
    head += ["accepted", "precision"]
    head += [f"{m:g} m / {d:g} deg" for m, d in THRESHOLDS]
    head += ["ret. rate", "med. t [m]", "med. R [deg]", "tried", "ms/query", "CPU ms/query"]
    head += ["nearest m / deg"]
    lines = [
        f"# Rendered-database localisation (seed 2 Algorithm 1), {report['tag']}",
        "",
        f"Images {report['image_size']}, {report.get('yaw_views', 4)} views per render "
        f"position, retrieval: {_retrieval_label(report['retrieval'])}; "
        f"`{report['command']}`",
        f"Machine: {report['machine']}",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]

    def pct(x: float | None) -> str:
        return "-" if x is None else f"{100 * x:.1f} %"

    def num(x: float | None, fmt: str) -> str:
        return "-" if x is None else format(x, fmt)

    for row in report["rows"]:
        r = row["result"]
        cells = [
            row["sequence"],
            row["map"],
            row["mode"],
            row["retriever"],
            str(row["database_images"]),
            pct(row["hole_share"]),
            pct(r["found"] / r["queries"]),
            pct(r["precision_found"]),
            pct(r["accepted"] / r["queries"]),
            pct(r["precision_accepted"]),
            *[pct(v) for v in r["rates"].values()],
            pct(r["retrieval_rate"]),
            num(r["median_translation_m"], ".3f"),
            num(r["median_rotation_deg"], ".2f"),
            f"{r['median_candidates_tried']:g}",
            f"{r['median_ms_per_query']:.0f}",
            _cpu_ms(r),
            f"{r['nearest_render_m']['median']:.2f} / {r['nearest_render_deg']['median']:.1f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "Found: a PnP pose was found (seed 2's answer); accepted: it also passed the "
        f"validation ({report['validation']}). Precision: share of the found / accepted poses "
        f"within {CORRECT[0]:g} m / {CORRECT[1]:g} deg. Rates are shares of all queries localised "
        "(accepted) within the bounds (a query not localised counts as a failure); queries per "
        f"sequence: {report['queries']}. Median errors over the accepted queries; tried: median "
        "candidates matched per query; ms/query: median wall time under the load shown; CPU "
        "ms/query: median CPU time of the process (features, retrieval, matching, PnP). "
        "Retrieval rate: the top-1 retrieved render lies within the sampling distance (2 m) "
        "and 45 deg of the query. Nearest render: median over queries of the distance to the "
        "nearest render position and the smallest angle among its views.",
        "",
    ]
    return "\n".join(lines)


def _cpu_ms(result: dict) -> str:
    """The median CPU ms per query, "-" in reports written before it was recorded."""
    value = result.get("median_cpu_ms_per_query")
    return "-" if value is None else f"{value:.0f}"


def _rerank(args: argparse.Namespace) -> RerankConfig | None:
    if args.rerank_candidates == 0:
        return None
    return RerankConfig(
        candidates=args.rerank_candidates,
        keypoints=args.rerank_keypoints,
        min_similarity=args.rerank_min_similarity,
    )


def main() -> None:
    args = _parse()
    torch.manual_seed(0)
    mapping = read_sequence(args.dataset, "mapping")
    camera = mapping.camera.scaled(args.scale)
    sequences = {name: read_sequence(args.dataset, name) for name in args.sequences}
    step = args.every
    extractor = XFeatExtractor(XFeatConfig(max_keypoints=1024))
    matcher = LighterGlueMatcher(LighterGlueConfig(min_confidence=0.0))
    pose_config = PoseSelectionConfig(views_per_sample=args.yaw_views)
    rows = []
    for map_name in args.maps:
        point_map = _colored_map(map_name, args, mapping, camera)
        cloud = read_point_cloud(args.dataset / "map" / f"{map_name}.ply")
        selection = select_render_poses(cloud.points, cloud.normals, pose_config)
        T_render = selection.T_wc
        for mode in args.modes:
            views = "" if args.yaw_views == 4 else f"_v{args.yaw_views}"
            path = args.work / f"db_{map_name}_{mode}_x{args.scale:g}{views}"
            start = time.perf_counter()
            if (path / "database.json").is_file():
                db = RenderedDatabase.load(path)
            else:
                rgbd_map = PointCloudMap(point_map.positions, point_map.colors, _sizes(mode, args))
                db = render_database(
                    rgbd_map,
                    T_render,
                    camera,
                    DatabaseConfig(),
                    f"{map_name} {mode}",
                    extractor,
                    show_progress=True,
                )
                db.save(path)
            build_s = time.perf_counter() - start
            for retriever in args.retrievers:
                config = replace(
                    RenderedLocalizerConfig(),
                    retriever=retriever,
                    top_k=args.top_k,
                    select=args.select,
                    stop_inliers=args.stop_inliers or None,
                    validation=None if args.no_validation else RenderedLocalizerConfig().validation,
                    rerank=_rerank(args),
                )
                localizer = RenderedDatabaseLocalizer(db, config, extractor, matcher)
                for seq_name, seq in sequences.items():
                    indices = list(range(0, len(seq), step))
                    result = _evaluate(
                        localizer,
                        db,
                        seq,
                        camera,
                        indices,
                        pose_config.spacing_m,
                        args.oracle_retrieval,
                    )
                    rows.append(
                        {
                            "sequence": seq_name,
                            "map": map_name,
                            "mode": mode,
                            "retriever": retriever,
                            "database_images": db.num_images,
                            "database_build_s": build_s,
                            "hole_share": float(db.holes.mean()),
                            "result": result,
                        }
                    )
                    print(json.dumps(rows[-1]), flush=True)
    report = {
        "tag": args.tag,
        "command": "python3 " + " ".join(sys.argv),
        "image_size": f"{camera.width}x{camera.height}",
        "machine": f"{platform.node()} {os.cpu_count()} cores, load {os.getloadavg()}",
        "yaw_views": args.yaw_views,
        "point_sizes": {"rho_min": args.rho_min, "rho_max": args.rho_max, "levels": args.levels},
        "retrieval": {
            "top_k": args.top_k,
            "select": args.select,
            "stop_inliers": args.stop_inliers or None,
            "oracle_nearest_render": args.oracle_retrieval,
            "rerank": None if _rerank(args) is None else asdict(_rerank(args)),
        },
        "validation": None if args.no_validation else asdict(RenderedLocalizerConfig().validation),
        "queries": {name: len(range(0, len(seq), step)) for name, seq in sequences.items()},
        "rows": rows,
    }
    write_report(args.out / f"rendered_localization_{args.tag}", _markdown(report), report)


if __name__ == "__main__":
    main()
