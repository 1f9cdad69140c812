"""All feature benchmarks in one run; the last stdout line is one merged JSON object.

Usage:
    python experiments/bench_features.py [--threads 1]

Runs ``bench_features_local.py`` (extraction, matching, the motorcycle stereo pair with ground
truth disparity) and ``bench_retrieval.py`` (NetVLAD, fine-tuned NetVLAD and bag of words on
the default indoor scene: recall@1/5 of ``query_same`` against ``mapping``, top-30 search time)
and merges their JSON into ``experiments/results/bench_features.json``. Keys include
``xfeat_640x480_ms``, ``orb_640x480_ms``, ``mnn_1000x1000_ms``, ``lighterglue_ms``,
``retrieval_top30_1000db_ms``, ``motorcycle_xfeat_inlier_ratio``,
``motorcycle_lighterglue_inlier_ratio``, ``netvlad_recall_at_1`` and ``bow_recall_at_1``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from diffloc.eval.report_files import write_benchmark

HERE = Path(__file__).resolve().parent
PARTS = ("bench_features_local.py", "bench_retrieval.py")


def run_part(script: str, threads: int) -> dict:
    """Run one benchmark script, streaming its output, and parse its last line."""
    command = [sys.executable, str(HERE / script), "--threads", str(threads)]
    process = subprocess.run(command, stdout=subprocess.PIPE, text=True, check=True)
    lines = process.stdout.strip().splitlines()
    print("\n".join(lines[:-1]))
    return json.loads(lines[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=HERE / "results" / "bench_features.json")
    args = parser.parse_args()
    result: dict = {}
    for script in PARTS:
        result.update(run_part(script, args.threads))
    print(write_benchmark(args.out, result))


if __name__ == "__main__":
    main()
