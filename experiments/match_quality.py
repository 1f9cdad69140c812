"""Table V of seed 2: local features between real query frames and point-cloud renders.

For every ``--every``-th frame of a query sequence, the coloured TLS cloud (the cache written
by ``experiments/rendered_localization.py``, or with ``--colored-map`` the PLY of
``diffloc task=crossmodal map=tls``'s map stage, ``<dataset>/crossmodal/tls/map/colored_map.ply``)
is rendered at the frame's TRUE pose (ground truth
read to make the pair, as seed 2 does) with single-pass Eq. 2 splats. Features of the real
frame and of the render are matched by each method; a match is **correct** when the render's
keypoint has depth and reprojects within 3 px of the query keypoint. The render shares the
query's pose and camera, so the true relative pose is the identity and the reprojection of
the lifted render keypoint is the render keypoint itself: correct = depth > 0 and
``|u_q - u_r| < 3 px``.

Methods (1024 keypoints each): AKAZE, SIFT, ORB (OpenCV, mutual nearest neighbours, Hamming
for the binary ones), XFeat + mutual nearest neighbours, XFeat + LighterGlue (confidence > 0,
as Algorithm 1). Reported per method: mean keypoints detected (query / render), matches,
correct matches and their share, and median CPU ms per pair (extraction of both images and
matching).

Usage:
    PYTHONPATH=. OMP_NUM_THREADS=1 python3 experiments/match_quality.py \\
        --dataset data/indoor_seed0 --work /tmp/rendered_work --every 8
    PYTHONPATH=. OMP_NUM_THREADS=1 python3 experiments/match_quality.py \\
        --dataset data/indoor_seed0 --every 8 --name crossmodal_table5_indoor_seed0 \\
        --colored-map data/indoor_seed0/crossmodal/tls/map/colored_map.ply
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from diffloc.crossmodal.synthesize import PointCloudMap
from diffloc.eval.report_files import write_report
from diffloc.features.local import (
    AkazeConfig,
    Features,
    OrbConfig,
    SiftConfig,
    XFeatConfig,
    make_extractor,
)
from diffloc.features.matching import (
    LighterGlueConfig,
    LighterGlueMatcher,
    Matches,
    match_descriptors,
)
from diffloc.io.dataset import read_sequence
from diffloc.maps.pointcloud import PointMap
from diffloc.progress import progress
from diffloc.render.point_sizes import PointSizes

CORRECT_PX = 3.0
KEYPOINTS = 1024
METHODS = ("AKAZE", "SIFT", "ORB", "XFeat + MNN", "XFeat + LighterGlue")


def _parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", type=Path, default=Path("data/indoor_seed0"))
    parser.add_argument("--work", type=Path, default=Path("/tmp/rendered_work"))
    parser.add_argument("--out", type=Path, default=Path("experiments/results"))
    parser.add_argument("--tag", default="indoor_seed0")
    parser.add_argument(
        "--colored-map", type=Path, help="a coloured PLY (task=crossmodal's) instead of the cache"
    )
    parser.add_argument("--name", help="file stem under --out (default match_quality_<tag>)")
    parser.add_argument("--sequence", default="query_same")
    parser.add_argument("--every", type=int, default=8)
    parser.add_argument("--scale", type=float, default=0.5)
    return parser.parse_args()


def _correct(
    matches: Matches, query: Features, render: Features, depth: torch.Tensor
) -> torch.Tensor:
    """(K,) bool: the render keypoint has depth and lies within 3 px of the query one."""
    uq = query.keypoints[matches.indices[:, 0]]
    ur = render.keypoints[matches.indices[:, 1]]
    _, height, width = depth.shape
    col = ur[:, 0].round().long().clamp(0, width - 1)
    row = ur[:, 1].round().long().clamp(0, height - 1)
    has_depth = depth[0, row, col] > 0
    return has_depth & (torch.linalg.vector_norm(uq - ur, dim=1) < CORRECT_PX)


def main() -> None:
    args = _parse()
    if args.colored_map is not None:
        if not args.colored_map.is_file():
            sys.exit(f"{args.colored_map} is missing: run diffloc task=crossmodal map=tls first")
        point_map = PointMap.load_ply(args.colored_map)
    else:
        cache = args.work / f"tls_map_colored_x{args.scale:g}.npz"
        if not cache.is_file():
            sys.exit(f"{cache} is missing: run experiments/rendered_localization.py first")
        point_map = PointMap.load(cache)
    cloud = PointCloudMap(point_map.positions, point_map.colors, PointSizes.inverse_depth(1.0, 8.0))
    seq = read_sequence(args.dataset, args.sequence)
    camera = seq.camera.scaled(args.scale)
    size = (camera.height, camera.width)
    extractors = {
        "AKAZE": make_extractor(AkazeConfig(max_keypoints=KEYPOINTS)),
        "SIFT": make_extractor(SiftConfig(max_keypoints=KEYPOINTS)),
        "ORB": make_extractor(OrbConfig(max_keypoints=KEYPOINTS)),
        "XFeat": make_extractor(XFeatConfig(max_keypoints=KEYPOINTS)),
    }
    glue = LighterGlueMatcher(LighterGlueConfig(min_confidence=0.0))
    frames = list(range(0, len(seq), args.every))
    stats: dict[str, dict[str, list[float]]] = {
        m: {k: [] for k in ("query_kp", "render_kp", "matched", "correct", "ms")} for m in METHODS
    }
    for i in progress(frames, "pairs"):
        real = F.interpolate(seq.load_rgb(i)[None], size, mode="area")[0]
        rendered = cloud.render(seq.T_wc[i][None], camera)
        render_rgb, depth = rendered.rgb[0], rendered.depth[0]
        for method in METHODS:
            start = time.process_time()
            extractor = extractors[method.split(" ")[0]]
            query, render = extractor.extract(real), extractor.extract(render_rgb)
            if method == "XFeat + LighterGlue":
                matches = glue.match(query, render, size, size)
            else:
                matches = match_descriptors(query.descriptors, render.descriptors, mutual=True)
            ms = 1e3 * (time.process_time() - start)
            s = stats[method]
            s["query_kp"].append(len(query))
            s["render_kp"].append(len(render))
            s["matched"].append(len(matches))
            s["correct"].append(int(_correct(matches, query, render, depth).sum()))
            s["ms"].append(ms)
    rows = []
    for method, s in stats.items():
        matched, correct = float(np.sum(s["matched"])), float(np.sum(s["correct"]))
        rows.append(
            {
                "method": method,
                "detected_query": float(np.mean(s["query_kp"])),
                "detected_render": float(np.mean(s["render_kp"])),
                "matched": float(np.mean(s["matched"])),
                "correct": float(np.mean(s["correct"])),
                "correct_share": correct / matched if matched else None,
                "median_cpu_ms": float(np.median(s["ms"])),
            }
        )
    report = {
        "tag": args.tag,
        "command": "python3 " + " ".join(sys.argv),
        "sequence": args.sequence,
        "pairs": len(frames),
        "image_size": f"{camera.width}x{camera.height}",
        "machine": f"{platform.node()} {os.cpu_count()} cores, load {os.getloadavg()}",
        "rows": rows,
    }
    head = ["method", "detected (query / render)", "matched", "correct", "correct share"]
    head += ["CPU ms / pair"]
    lines = [
        f"# Table V: real / rendered (TLS cloud) matches, {args.tag} {args.sequence}",
        "",
        f"`{report['command']}`; {len(frames)} pairs, {report['image_size']}, {report['machine']}.",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for r in rows:
        share = "-" if r["correct_share"] is None else f"{100 * r['correct_share']:.1f} %"
        lines.append(
            f"| {r['method']} | {r['detected_query']:.0f} / {r['detected_render']:.0f} | "
            f"{r['matched']:.1f} | {r['correct']:.1f} | {share} | {r['median_cpu_ms']:.0f} |"
        )
    lines += [
        "",
        "Means per pair. A match is correct when the render keypoint has depth and lies within "
        f"{CORRECT_PX:g} px of the query keypoint (the render is at the query's true pose: the "
        "true relative pose is the identity). Correct share: correct / matched over all pairs. "
        "CPU ms: process time of both extractions and the matching, under the machine's load.",
        "",
    ]
    write_report(args.out / (args.name or f"match_quality_{args.tag}"), "\n".join(lines), report)


if __name__ == "__main__":
    main()
