"""CPU time of the uniqueness test per query (:mod:`diffloc.reloc.uniqueness`); last line JSON.

Relocalises every ``--stride``-th query of the given sequences of a dataset (its optimised
database, the scene's reloc settings), and for each found pose times
:func:`~diffloc.reloc.uniqueness.pose_uniqueness` with ``time.process_time`` (CPU, one
thread), next to the relocalisation's own CPU time.

Usage:
    OMP_NUM_THREADS=1 python3 experiments/bench_uniqueness.py \\
        --data /work/main/data/outdoor_seed0 --scene outdoor --stride 10
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from diffloc.config import compose_config, to_object
from diffloc.database.database import VisualDatabase
from diffloc.features.local import make_extractor
from diffloc.io.dataset import read_sequence
from diffloc.pipeline.database_select import select_database
from diffloc.reloc.hierarchical import HierarchicalRelocalizer
from diffloc.reloc.retrieval import load_retriever
from diffloc.reloc.uniqueness import pose_uniqueness


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--scene", default="outdoor")
    parser.add_argument("--sequences", default="query_same,query_reverse")
    parser.add_argument("--stride", type=int, default=10)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    cfg = compose_config(["task=relocalize", f"scene={args.scene}"])
    reloc, db_cfg = to_object(cfg.reloc), to_object(cfg.db)
    selected = select_database(args.data, db_cfg, reloc.database)
    db = VisualDatabase.load(selected.path)
    retriever = load_retriever(selected.retriever_root / f"retriever_{reloc.retriever.kind}")
    relocalizer = HierarchicalRelocalizer(db, retriever, reloc.method)
    extractor = make_extractor(db_cfg.features)
    reloc_ms, unique_ms = [], []
    for name in args.sequences.split(","):
        sequence = read_sequence(args.data, name)
        for i in range(0, len(sequence), args.stride):
            image = sequence.load_rgb(i)
            features = extractor.extract(image)
            start = time.process_time()
            result = relocalizer.relocalize(image, features, sequence.camera)
            reloc_ms.append((time.process_time() - start) * 1e3)
            best = result.best
            if best is None:
                continue
            rivals = [c.T_wc for c in result.candidates if c is not best]
            start = time.process_time()
            pose_uniqueness(
                best.T_wc,
                torch.stack(rivals) if rivals else torch.zeros(0, 4, 4, dtype=torch.float64),
                best.inlier_matches,
                features,
                sequence.camera,
                relocalizer.point_positions,
                db.point_descriptors,
                db.metric,
                reloc.uniqueness,
                reloc.repetition,
                reloc.method.refine,
            )
            unique_ms.append((time.process_time() - start) * 1e3)
    print(
        json.dumps(
            {
                "data": str(args.data),
                "queries": len(reloc_ms),
                "measured": len(unique_ms),
                "median_reloc_cpu_ms": statistics.median(reloc_ms),
                "median_uniqueness_cpu_ms": statistics.median(unique_ms),
                "p90_uniqueness_cpu_ms": sorted(unique_ms)[int(0.9 * (len(unique_ms) - 1))],
            }
        )
    )


if __name__ == "__main__":
    main()
