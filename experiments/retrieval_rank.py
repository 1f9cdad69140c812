"""Where the nearest render ranks in the retrieval of ``diffloc task=crossmodal``, query by query.

For every ``--every``-th frame of ``--sequence``, the query image (resized to the database
camera, as the localiser does) is described by the database's NetVLAD and re-ranked by the
localiser's mutual-nearest-neighbour re-ranker (:mod:`diffloc.reloc.rerank`), exactly as
:meth:`~diffloc.reloc.rendered.RenderedDatabaseLocalizer.localize` retrieves before matching.
The ground truth (scoring only) gives each query its *near* renders (within ``--spacing-m``
and 45 deg) and the report gives the rank (1 = first) of the best-ranked near render:

- in the NetVLAD ranking of the whole database;
- after re-ranking NetVLAD's ``rerank.candidates`` best (``-`` when no near render is among
  them: re-ranking cannot bring it up);
- after re-ranking the whole database by the same mutual-nearest-neighbour count.

So the ``top_k`` a localiser must match to reach the near render can be read off per query.
No matching or PnP runs here (a few seconds of CPU per query). ``--tune`` first teaches the
database's NetVLAD the render / real gap with the mapping images (``--method finetune``:
:mod:`diffloc.crossmodal.retrieval_tuning`; ``whitening``:
:mod:`diffloc.crossmodal.retrieval_whitening`; default settings; never on query images).

Usage:
    PYTHONPATH=. python3 experiments/retrieval_rank.py --dataset /tmp/P/indoor_seed0 \\
        --map tls --sequence query_same --every 4 \\
        --out experiments/results/retrieval_rank_indoor_seed0_tls
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from diffloc.crossmodal.database import RenderedDatabase
from diffloc.crossmodal.retrieval_tuning import RetrievalTuningConfig, tune_render_retrieval
from diffloc.crossmodal.retrieval_whitening import whiten_render_retrieval
from diffloc.eval.report_files import write_report
from diffloc.features.retrieval_eval import pairwise_pose_distances
from diffloc.io.dataset import read_sequence
from diffloc.pipeline.crossmodal_report import RETRIEVAL_ANGLE_DEG
from diffloc.pipeline.crossmodal_stage import crossmodal_folder, scaled_images
from diffloc.reloc.rendered import RenderedDatabaseLocalizer, RenderedLocalizerConfig


def first_rank(order: torch.Tensor, near: torch.Tensor) -> int | None:
    """1-based rank of the first image of ``order`` (K,) that ``near`` (N,) bool marks."""
    hits = torch.nonzero(near[order]).flatten()
    return int(hits[0]) + 1 if len(hits) else None


def tuned(dataset: Path, db: RenderedDatabase, method: str) -> RenderedDatabase:
    """``db`` with its NetVLAD taught by the mapping images (their poses are an input)."""
    mapping = read_sequence(dataset, "mapping")
    camera = mapping.camera.scaled(db.camera.width / mapping.camera.width)
    images = scaled_images(mapping, camera, list(range(len(mapping))))
    teach = tune_render_retrieval if method == "finetune" else whiten_render_retrieval
    result = teach(db, images, mapping.T_wc, RetrievalTuningConfig(method=method))
    print(f"tuning ({method}): {result.result}, {result.pairs} tuples or pairs")
    return result.database


def ranks(
    dataset: Path, option: str, sequence: str, every: int, spacing_m: float, tune: str | None = None
) -> list[dict]:
    """Per query: frame, near renders, and the rank of the first near one before/after
    re-ranking (``tune``: with the NetVLAD taught by the mapping images by that method)."""
    db = RenderedDatabase.load(crossmodal_folder(dataset) / option / "database" / "rgbd")
    if tune is not None:
        db = tuned(dataset, db, tune)
    localizer = RenderedDatabaseLocalizer(db, RenderedLocalizerConfig())
    seq = read_sequence(dataset, sequence)
    camera = seq.camera.scaled(db.camera.width / seq.camera.width)
    frames = list(range(0, len(seq), every))
    distance, angle = pairwise_pose_distances(seq.T_wc[frames], db.T_wc)  # truth: scoring only
    near = (distance <= spacing_m) & (angle <= np.radians(RETRIEVAL_ANGLE_DEG))
    pool = localizer.config.rerank.candidates
    rows = []
    for q, frame in enumerate(frames):
        image = scaled_images(seq, camera, [frame])[0]
        query = localizer.extractor.extract(image)
        with torch.no_grad():
            descriptor = localizer.retriever.describe(image, query)
            _, netvlad = localizer.retriever.search(descriptor, db.num_images)
        rerank = localizer.reranker.rerank
        _, reranked = rerank(query.descriptors, netvlad[:pool], query.scores)
        _, everything = rerank(query.descriptors, netvlad, query.scores)
        rows.append(
            {
                "frame": frame,
                "near_renders": int(near[q].sum()),
                "netvlad_rank": first_rank(netvlad, near[q]),
                "reranked_rank": first_rank(reranked, near[q]),
                "reranked_all_rank": first_rank(everything, near[q]),
            }
        )
    return rows


def _cell(value: object) -> str:
    return "-" if value is None else str(value)


def markdown(report: dict) -> str:
    """The per-query table and the share of queries whose near render is within top k."""
    rows = report["rows"]
    covered = [r for r in rows if r["near_renders"]]
    lines = [
        f"# Rank of the nearest render: {report['map']} `{report['sequence']}` of "
        f"{report['dataset']}"
        + (f", NetVLAD taught by {report['tuned']}" if report["tuned"] else ""),
        "",
        f"Made by: `{report['command']}` (experiments/retrieval_rank.py docstring). "
        f"Near: within {report['spacing_m']:g} m and 45 deg; NetVLAD ranks the whole database "
        f"({report['database']} images), the re-ranker its first {report['pool']} or all.",
        "",
        f"{len(covered)} of {len(rows)} queries have a near render. Share of all queries with a "
        "near render within the first k:",
        "",
        "| k | NetVLAD | re-ranked | all re-ranked |",
        "|---:|---:|---:|---:|",
    ]
    for k in (1, 3, 5, 10, 15, 20, 30, 50):
        share = [
            sum(1 for r in rows if r[key] is not None and r[key] <= k) / len(rows)
            for key in ("netvlad_rank", "reranked_rank", "reranked_all_rank")
        ]
        lines.append(f"| {k} | " + " | ".join(f"{100 * x:.1f} %" for x in share) + " |")
    columns = list(rows[0])
    lines += ["", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_cell(r[c]) for c in columns) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--map", required=True, help="a map option with a built database")
    parser.add_argument("--sequence", required=True)
    parser.add_argument("--every", type=int, default=4)
    parser.add_argument("--spacing-m", type=float, default=2.0)
    parser.add_argument("--tune", action="store_true", help="teach NetVLAD first")
    parser.add_argument("--method", choices=("finetune", "whitening"), default="finetune")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    method = args.method if args.tune else None
    rows = ranks(args.dataset, args.map, args.sequence, args.every, args.spacing_m, method)
    db_json = crossmodal_folder(args.dataset) / args.map / "database" / "rgbd_database.json"
    report = {
        "dataset": str(args.dataset),
        "map": args.map,
        "sequence": args.sequence,
        "tuned": method,
        "spacing_m": args.spacing_m,
        "database": json.loads(db_json.read_text())["images"],
        "pool": RenderedLocalizerConfig().rerank.candidates,
        "command": (
            f"PYTHONPATH=. python3 experiments/retrieval_rank.py --dataset {args.dataset} "
            f"--map {args.map} --sequence {args.sequence} --every {args.every} "
            f"--spacing-m {args.spacing_m:g}"
            + (f" --tune --method {method}" if method else "")
            + f" --out {args.out}"
        ),
        "rows": rows,
    }
    write_report(args.out, markdown(report), report)
    print(markdown(report))


if __name__ == "__main__":
    main()
