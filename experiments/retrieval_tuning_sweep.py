"""Recall of the near render under NetVLAD tuned on the mapping images, per tuning setting.

For a built ``diffloc task=crossmodal`` database (``<dataset>/crossmodal/<map>/database``) the
dense XFeat maps of the renders, the mapping images and every ``--every``-th frame of each
``--sequence`` are made once; then for the untuned layer and each ``--variant`` (settings of
:class:`~diffloc.crossmodal.retrieval_tuning.RetrievalTuningConfig` as ``key=value`` pairs:
``lr``, ``epochs``, ``margin``, ``negatives``, ``pos_m``, ``pos_deg``, ``neg_m``, ``every``)
the layer is tuned (:func:`~diffloc.crossmodal.retrieval_tuning.tune_on_dense_maps`; mapping
images only) and each query's rank of the first *near* render (within ``--spacing-m`` and
45 deg; the query's true pose is used for scoring only) is taken in NetVLAD's ranking of the
whole database, and with ``--rerank`` after the localiser's mutual-nearest-neighbour
re-ranking of NetVLAD's first ``rerank.candidates`` (what the localiser matches). The table
gives the share of queries with a near render within the first k and the tuning's CPU time.

Usage:
    PYTHONPATH=. OMP_NUM_THREADS=2 python3 experiments/retrieval_tuning_sweep.py \\
        --dataset /tmp/S/indoor_seed0 --map tls --sequence query_same \\
        --sequence query_reverse --variant lr=1e-3 --variant lr=1e-2,epochs=10 --rerank \\
        --out experiments/results/retrieval_tuning_indoor_seed0_tls
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

from diffloc.crossmodal.database import RenderedDatabase
from diffloc.crossmodal.retrieval_tuning import (
    RetrievalTuningConfig,
    dense_maps,
    tune_on_dense_maps,
)
from diffloc.eval.report_files import write_report
from diffloc.features.dense import DenseXFeat
from diffloc.features.local import XFeatConfig, XFeatExtractor
from diffloc.features.netvlad_training import FinetuneConfig, TripletConfig
from diffloc.features.retrieval_eval import pairwise_pose_distances
from diffloc.io.dataset import read_sequence
from diffloc.pipeline.crossmodal_report import RETRIEVAL_ANGLE_DEG
from diffloc.pipeline.crossmodal_stage import crossmodal_folder, scaled_images
from diffloc.reloc.rendered import RenderedLocalizerConfig
from diffloc.reloc.rerank import MutualNNReranker

KS = (1, 3, 5, 10, 20, 50)
FINETUNE_KEYS = {"lr": "learning_rate", "epochs": "epochs", "margin": "margin"}
TRIPLET_KEYS = {
    "negatives": "num_negatives",
    "pos_m": "positive_distance_m",
    "pos_deg": "positive_angle_deg",
    "neg_m": "negative_distance_m",
}


def variant_config(text: str) -> RetrievalTuningConfig:
    """``"lr=1e-2,epochs=10"`` -> the tuning settings (defaults elsewhere)."""
    finetune, triplets, every = {}, {}, 1
    for pair in filter(None, text.split(",")):
        key, value = pair.split("=")
        if key in FINETUNE_KEYS:
            finetune[FINETUNE_KEYS[key]] = int(value) if key == "epochs" else float(value)
        elif key in TRIPLET_KEYS:
            triplets[TRIPLET_KEYS[key]] = int(value) if key == "negatives" else float(value)
        elif key == "every":
            every = int(value)
        else:
            raise SystemExit(f"--variant {text}: unknown key {key!r}")
    config = FinetuneConfig(**finetune, triplets=TripletConfig(**triplets))
    return RetrievalTuningConfig(mapping_every=every, finetune=config)


def first_rank(order: torch.Tensor, near: torch.Tensor) -> int | None:
    """1-based rank of the first image of ``order`` that ``near`` marks."""
    hits = torch.nonzero(near[order]).flatten()
    return int(hits[0]) + 1 if len(hits) else None


class Queries:
    """The query frames of one sequence: dense maps, local features and near renders."""

    def __init__(self, dataset: Path, name: str, every: int, db: RenderedDatabase, spacing_m):
        seq = read_sequence(dataset, name)
        camera = seq.camera.scaled(db.camera.width / seq.camera.width)
        self.frames = list(range(0, len(seq), every))
        images = scaled_images(seq, camera, self.frames)
        extractor = XFeatExtractor(XFeatConfig(max_keypoints=1024))
        self.features = [extractor.extract(image) for image in images]
        self.maps = torch.stack([f.dense for f in self.features])
        distance, angle = pairwise_pose_distances(seq.T_wc[self.frames], db.T_wc)  # scoring
        self.near = (distance <= spacing_m) & (angle <= np.radians(RETRIEVAL_ANGLE_DEG))


def score(db: RenderedDatabase, queries: Queries, reranker: MutualNNReranker | None) -> dict:
    """Recall at each k of NetVLAD (and re-ranked) for one database and sequence."""
    with torch.no_grad():
        descriptors = db.netvlad(queries.maps.float())
    order = torch.argsort(descriptors @ db.global_descriptors.T, dim=1, descending=True)
    ranks = {"netvlad": [first_rank(o, n) for o, n in zip(order, queries.near, strict=True)]}
    if reranker is not None:
        pool = RenderedLocalizerConfig().rerank.candidates
        ranks["reranked"] = [
            first_rank(reranker.rerank(f.descriptors, o[:pool], f.scores)[1], n)
            for f, o, n in zip(queries.features, order, queries.near, strict=True)
        ]
    n = len(queries.frames)
    return {
        name: {
            "ranks": values,
            "recall": {k: sum(r is not None and r <= k for r in values) / n for k in KS},
        }
        for name, values in ranks.items()
    }


def markdown(report: dict) -> str:
    """One row per setting and sequence: recall at each k."""
    lines = [
        f"# NetVLAD tuned on the mapping images: {report['map']} of {report['dataset']}",
        "",
        f"Made by: `{report['command']}` (experiments/retrieval_tuning_sweep.py docstring). "
        f"Share of the queries (every {report['every']}-th frame) with a render within "
        f"{report['spacing_m']:g} m / 45 deg among the first k; `netvlad`: the whole "
        "database ranked by NetVLAD, `reranked`: NetVLAD's first 50 re-ranked by "
        "mutual-nearest-neighbour matches (the localiser's order). CPU: the tuning's CPU "
        f"seconds ({report['machine']}).",
        "",
        "| setting | sequence | order | " + " | ".join(f"@{k}" for k in KS) + " | CPU s |",
        "|---|---|---|" + "---:|" * (len(KS) + 1),
    ]
    for row in report["rows"]:
        for sequence, orders in row["sequences"].items():
            for order, entry in orders.items():
                cells = " | ".join(f"{100 * entry['recall'][k]:.1f}" for k in KS)
                lines.append(
                    f"| {row['setting']} | {sequence} | {order} | {cells} | {row['cpu_s']:.0f} |"
                )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--map", required=True)
    parser.add_argument("--sequence", action="append", required=True)
    parser.add_argument("--every", type=int, default=4)
    parser.add_argument("--spacing-m", type=float, default=2.0)
    parser.add_argument("--variant", action="append", default=[])
    parser.add_argument("--rerank", action="store_true")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    db = RenderedDatabase.load(crossmodal_folder(args.dataset) / args.map / "database" / "rgbd")
    mapping = read_sequence(args.dataset, "mapping")
    camera = mapping.camera.scaled(db.camera.width / mapping.camera.width)
    dense = DenseXFeat()
    real = dense_maps(scaled_images(mapping, camera, list(range(len(mapping)))), dense)
    renders = dense_maps(db.rgb, dense)
    queries = {s: Queries(args.dataset, s, args.every, db, args.spacing_m) for s in args.sequence}
    reranker = None
    if args.rerank:
        config = RenderedLocalizerConfig().rerank
        features = db.features
        reranker = MutualNNReranker(
            [f.descriptors for f in features], [f.scores for f in features], config
        )
    rows = [
        {
            "setting": "untuned",
            "cpu_s": 0.0,
            "sequences": {s: score(db, q, reranker) for s, q in queries.items()},
        }
    ]
    for text in args.variant:
        config = variant_config(text)
        keep = slice(None, None, config.mapping_every)
        start = time.process_time()
        tuned = tune_on_dense_maps(
            db, real[keep], mapping.T_wc[keep], renders, config, show_progress=False
        )
        cpu = time.process_time() - start
        result = tuned.result
        print(
            f"{text}: {result.num_tuples} tuples, loss {result.initial_loss:.3f} -> "
            f"{result.final_loss:.3f}, {cpu:.0f} s CPU",
            flush=True,
        )
        rows.append(
            {
                "setting": text,
                "cpu_s": cpu,
                "loss": [result.initial_loss, result.final_loss],
                "sequences": {s: score(tuned.database, q, reranker) for s, q in queries.items()},
            }
        )
    threads = os.environ.get("OMP_NUM_THREADS")
    command = " ".join(
        [
            "PYTHONPATH=.",
            *([f"OMP_NUM_THREADS={threads}"] if threads else []),
            "python3 experiments/retrieval_tuning_sweep.py",
            f"--dataset {args.dataset} --map {args.map}",
            *(f"--sequence {s}" for s in args.sequence),
            f"--every {args.every}",
            *(f"--variant {v}" for v in args.variant),
            *(["--rerank"] if args.rerank else []),
            f"--out {args.out}",
        ]
    )
    report = {
        "dataset": str(args.dataset),
        "map": args.map,
        "every": args.every,
        "spacing_m": args.spacing_m,
        "command": command,
        "machine": f"{platform.node()}, load {os.getloadavg()} at the end",
        "rows": rows,
    }
    write_report(args.out, markdown(report), report)
    print(markdown(report))


if __name__ == "__main__":
    main()
