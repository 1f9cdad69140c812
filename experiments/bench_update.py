"""Benchmark the database update (seed 1 Sec. III-A): build, update, relocalise a third sequence.

Usage:
    python experiments/bench_update.py [--data data/indoor_seed0] [--scene indoor]
        [--update query_lane] [--query changed] [--query-stride 1] [--noise-sigma 0]
        [--threads 2] [--out experiments/results/bench_update.json] [overrides ...]

On one dataset (simulated with ``scene=<scene>`` and the trailing Hydra ``overrides`` if the
folder does not exist; its surfel map is built if missing) the script runs, through the same
functions as the ``diffloc`` tasks and with the configs composed from ``diffloc/conf/``:

1. ``task=build_db`` on the mapping sequence (``build_database``);
2. ``task=update_db task.sequence=<update>`` (``update_database``): the update sequence's
   frames are added with the builder's matching, fusion and both culling rules;
3. ``task=relocalize reloc.sequences=[<query>]`` against ``reloc.database=database`` and
   ``reloc.database=updated_<update>`` (NetVLAD retrieval fitted on each database's keyframes).

It writes ``--out`` (JSON) and the same name with ``.md`` (a Markdown table) with: keyframes and
map points before the update, after adding and after culling; what each culling rule removed
(and how many culled keyframes belonged to the original database); the redundancy quantiles
of the final keyframes; per database the query count, recall@``reloc.max_trans_m`` with a 95 %
Wilson interval, the median relocalisation time (features excluded, as ``median_reloc_ms`` of
the relocalisation stage) and with features; the distance (median, 90th percentile, largest)
and median angle from each query to its nearest database keyframe (queries are not database
poses in disguise); the recall over the queries "covered" by the original database (a
keyframe of it within ``--covered-m``), so a gain from new coverage shows apart from a gain where
the original already had keyframes; and the paired
comparison: queries correct against only one of the two databases; and, per database, the
culling diagnostic of ``experiments/culling_diagnostic.py`` (track lengths, redundancy per
observer count and the ORACLE geometric visibility from ground-truth depth that explains
whether the 90 %/3-observer rule can fire). Relocalisation outputs (TUM files, plots) go to
``<data>/bench_update/<database>/``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
from culling_diagnostic import culling_diagnostic
from omegaconf import OmegaConf

from diffloc.config import compose_config, to_object
from diffloc.database.database import VisualDatabase
from diffloc.eval.report_files import write_report
from diffloc.eval.tables import Column, markdown_table
from diffloc.geometry.se3 import invert
from diffloc.io.dataset import read_sequence
from diffloc.pipeline.build_map import build_maps
from diffloc.pipeline.database_select import BUILT, UPDATED_PREFIX, select_database
from diffloc.pipeline.database_stage import build_database
from diffloc.pipeline.reloc_stage import relocalize_dataset
from diffloc.pipeline.update_stage import update_database
from diffloc.sim.dataset import simulate_dataset

RESULT = Path("experiments/results/bench_update.json")
WILSON_Z = 1.959964
"""Standard normal quantile of a two-sided 95 % interval."""


def wilson_interval(successes: int, trials: int, z: float = WILSON_Z) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (``(nan, nan)`` without trials)."""
    if trials == 0:
        return math.nan, math.nan
    p = successes / trials
    centre = (p + z * z / (2 * trials)) / (1 + z * z / trials)
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials))
    return centre - half / (1 + z * z / trials), centre + half / (1 + z * z / trials)


def nearest_keyframe(
    T_wc_query: torch.Tensor, T_wc_db: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per query, the distance to the nearest database keyframe position and the rotation
    angle to that keyframe.

    Args:
        T_wc_query: (Q, 4, 4) true query poses.
        T_wc_db: (K, 4, 4) database keyframe poses.

    Returns:
        ``(distance_m, angle_deg)``: (Q,) float64 each.
    """
    distance = torch.cdist(T_wc_query[:, :3, 3].double(), T_wc_db[:, :3, 3].double())
    nearest = distance.argmin(1)
    relative = invert(T_wc_db[nearest].double()) @ T_wc_query.double()
    cosine = ((relative[:, 0, 0] + relative[:, 1, 1] + relative[:, 2, 2] - 1) / 2).clamp(-1, 1)
    return distance.min(1).values, torch.rad2deg(cosine.acos())


def correct_queries(reloc_dir: Path, max_trans_m: float) -> np.ndarray:
    """(Q,) bool: accepted queries within ``max_trans_m`` (from the stage's ``queries.json``)."""
    queries = json.loads((reloc_dir / "queries.json").read_text())
    return np.array(
        [
            q["accepted"]
            and q["translation_error_m"] is not None
            and q["translation_error_m"] <= max_trans_m
            for q in queries
        ]
    )


def ensure_mapped(root: Path, cfg) -> None:
    """Simulate the scene and build its surfel map unless they exist."""
    if not (root / "dataset.json").is_file():
        simulate_dataset(OmegaConf.to_object(cfg.scene), root, show_progress=True)
    if not (root / "map" / "surfel_map.ply").is_file():
        build_maps(root, OmegaConf.to_object(cfg.task.build_map), to_object(cfg.map))


def git_commit() -> str:
    done = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True)
    return done.stdout.strip()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/indoor_seed0"))
    parser.add_argument("--scene", default="indoor")
    parser.add_argument("--update", default="query_lane")
    parser.add_argument("--query", default="changed")
    parser.add_argument("--query-stride", type=int, default=1)
    parser.add_argument("--noise-sigma", type=float, default=0.0)
    parser.add_argument(
        "--covered-m",
        type=float,
        default=1.0,
        help="a query is covered by the original database if a keyframe lies this close",
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULT)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides (scene.*, db.*, reloc.*)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    data = args.data
    cfg = compose_config(
        [
            f"scene={args.scene}",
            "task=update_db",
            f"task.sequence={args.update}",
            f"dataset={data}",
            f"db.noise_sigma={args.noise_sigma}",
            f"reloc.sequences=[{args.query}]",
            f"reloc.query_stride={args.query_stride}",
            *args.overrides,
        ],
    )
    ensure_mapped(data, compose_config([f"scene={args.scene}", "task=main", *args.overrides]))
    db_cfg = to_object(cfg.db)
    result: dict = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "commit": git_commit(),
        "threads": args.threads,
        "load_average_1min": os.getloadavg()[0],
        "dataset": str(data),
        "update_sequence": args.update,
        "query_sequence": args.query,
        "noise_sigma": args.noise_sigma,
        "culling": OmegaConf.to_container(cfg.db.builder.culling),
    }
    built = build_database(data, db_cfg, rebuild=True)
    updated = update_database(data, db_cfg, OmegaConf.to_object(cfg.task), rebuild=True)
    result["build_ms_per_image"] = built.build_ms_per_image
    result["update"] = {
        key: getattr(updated, key)
        for key in ("images", "before", "after_adding", "after_culling", "culled", "redundancy")
    }
    result["update"]["update_ms_per_image"] = updated.update_ms_per_image
    result["update"]["features_ms_per_image"] = updated.features_ms_per_image
    culling = to_object(cfg.db).builder.culling
    result["diagnostic"] = {
        which: culling_diagnostic(data, VisualDatabase.load(record.database), sources, culling)
        for which, record, sources in (
            (BUILT, built, [(db_cfg.sequence, f) for f in built.keyframe_frames]),
            (f"{UPDATED_PREFIX}{args.update}", updated, updated.keyframe_sources),
        )
    }
    truth = read_sequence(data, args.query).T_wc[:: args.query_stride]
    rows, correct, covered = [], {}, None
    for which in (BUILT, f"{UPDATED_PREFIX}{args.update}"):
        reloc = to_object(cfg.reloc)
        reloc.database = which
        out = data / "bench_update" / which
        results = relocalize_dataset(data, db_cfg, reloc, out)
        entry = results["sequences"][args.query]
        correct[which] = correct_queries(out / args.query, reloc.max_trans_m)
        hits, queries = int(correct[which].sum()), len(correct[which])
        low, high = wilson_interval(hits, queries)
        db = VisualDatabase.load(select_database(data, db_cfg, which).path)
        distance_m, angle_deg = nearest_keyframe(truth, db.T_wc)
        if covered is None:  # the original database comes first
            covered = (distance_m <= args.covered_m).numpy()
        row = {
            "database": which,
            "keyframes": db.num_keyframes,
            "map_points": db.num_points,
            "queries": queries,
            "correct": hits,
            "recall": entry["recall"],
            "recall_low": low,
            "recall_high": high,
            "median_reloc_ms": entry["median_reloc_ms"],
            "median_total_ms": entry["median_total_ms"],
            "nearest_keyframe_m": float(distance_m.median()),
            "nearest_keyframe_p90_m": float(torch.quantile(distance_m, 0.9)),
            "nearest_keyframe_max_m": float(distance_m.max()),
            "nearest_keyframe_deg": float(angle_deg.median()),
            "covered_queries": int(covered.sum()),
            "covered_recall": float(correct[which][covered].mean()) if covered.any() else None,
        }
        if not math.isclose(hits / max(queries, 1), entry["recall"]):
            raise RuntimeError(f"recount of correct queries disagrees with the stage: {row}")
        rows.append(row)
    original, update = correct[BUILT], correct[f"{UPDATED_PREFIX}{args.update}"]
    result["databases"] = rows
    result["paired"] = {
        "only_original": int((original & ~update).sum()),
        "only_updated": int((update & ~original).sum()),
        "both": int((original & update).sum()),
    }
    result["load_average_1min_after"] = os.getloadavg()[0]
    table = markdown_table(
        rows,
        [
            Column("database"),
            Column("keyframes"),
            Column("map_points", "map points"),
            Column("queries"),
            Column("recall", f"recall@{cfg.reloc.max_trans_m:g}m [%]", ".1f", scale=100),
            Column("recall_low", "95% low", ".1f", scale=100),
            Column("recall_high", "95% high", ".1f", scale=100),
            Column("median_reloc_ms", "reloc [ms]", ".1f"),
            Column("median_total_ms", "with features [ms]", ".1f"),
            Column("nearest_keyframe_m", "nearest kf median [m]", ".2f"),
            Column("nearest_keyframe_p90_m", "nearest kf p90 [m]", ".2f"),
            Column("nearest_keyframe_deg", "nearest kf [deg]", ".1f"),
            Column("covered_queries", "covered"),
            Column("covered_recall", "covered recall [%]", ".1f", scale=100),
        ],
    )
    before, added = updated.before, updated.after_adding
    after, culled = updated.after_culling, updated.culled
    summary = (
        f"Update of `{data}` with `{args.update}` ({updated.images} images), queries "
        f"`{args.query}`: keyframes {before['keyframes']} -> {added['keyframes']} (added) -> "
        f"{after['keyframes']} (culled {culled['keyframes']}, {culled['keyframes_of_base']} of "
        f"them from the original database); map points {before['map_points']} -> "
        f"{added['map_points']} -> {after['map_points']} (culled {culled['points_unconfirmed']} "
        f"unconfirmed, {culled['points_of_culled_keyframes']} with culled keyframes). Paired: "
        f"{result['paired']['only_original']} queries correct only against the original, "
        f"{result['paired']['only_updated']} only against the updated database."
    )
    result["table"] = table
    write_report(args.out, f"{summary}\n\n{table}\n", result)
    print(summary)
    print(table)
    print(json.dumps({k: v for k, v in result.items() if k != "table"}))


if __name__ == "__main__":
    main()
