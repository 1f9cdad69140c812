"""Seed 2's Tables I, III and IV from ``diffloc task=crossmodal`` runs, one row per database.

Each ``--run NAME=RESULTS`` is the ``results.json`` of a ``diffloc task=crossmodal map=MAP``
run, NAME naming it in the report (usually MAP: the rendered ``tls`` / ``cloud`` / ``mesh``
databases, ``images``: the mapping frames with surfel-map depth, or ``hybrid``: both, the
renders no mapping frame covers; the row's label comes from the run's own settings, so
``map=images`` over ``map.sequences=[mapping,mapping_left,mapping_right]`` is the front + side
cameras row). The table of a query sequence gives per database its size and hole share, the
queries (every ``task.every``-th frame), the accepted poses and their precision (within the
loose bound and 30 deg), the localisation rates at 0.25 m / 2 deg, 0.5 m / 5 deg and the
loose bound / 30 deg (shares of all queries), the top-1 retrieval rate, the mATE of the
accepted poses and the median wall ms per query (features, retrieval, matching, PnP; the load
average it ran under is in the JSON). ``--sequence`` given several times makes one table with
a row per sequence and run.

``--seed1 RESULTS`` adds seed 1's hierarchical relocaliser (``diffloc task=main``, its
``<sequence>/estimates.tum`` of accepted poses) scored on the SAME query frames with the same
criteria, for reference (its database is the mapping run's keyframes with surfel-map points;
no retrieval rate: it retrieves keyframe clusters, not one image).

Usage:
    PYTHONPATH=. python3 experiments/crossmodal_tables.py --sequence query_same \\
        --run tls=/tmp/l/tls/results.json --run images=/tmp/l/images/results.json \\
        --seed1 outputs/lead_indoor0/results.json --dataset data/indoor_seed0 \\
        --title "Table I" --command "bash experiments/run_tables.sh crossmodal_tables" \\
        --out experiments/results/crossmodal_table1_indoor_seed0
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from diffloc.eval.metrics import PoseErrors, is_correct, mean_ate, pose_errors
from diffloc.eval.report_files import made_by_lines, write_report
from diffloc.eval.tables import Column, markdown_table
from diffloc.io.dataset import read_sequence
from diffloc.io.trajectory import read_tum
from diffloc.pipeline.crossmodal_report import localization_rates

SOURCES = {
    "tls": "cloud (TLS), rendered",
    "cloud": "cloud (lidar), rendered",
    "mesh": "mesh (lidar), rendered",
    "images": "real images (mapping, front camera)",
    "hybrid": "hybrid: real images + uncovered mesh renders",
}
"""What each ``map`` option's database is."""


def database_label(results: dict) -> str:
    """What the database of a ``task=crossmodal`` run is (:data:`SOURCES`; ``map=images`` over
    other sequences than the front camera's names them)."""
    option = results["map"]
    sequences = results["map_settings"].get("sequences", ["mapping"])
    if option == "images" and sequences != ["mapping"]:
        return f"real images ({' + '.join(sequences)})"
    return SOURCES.get(option, option)


def crossmodal_row(name: str, results: dict, sequence: str) -> dict:
    """The table row of one ``task=crossmodal`` run (called ``name``) for ``sequence``."""
    entry = results["sequences"][sequence]
    load = results["stages"][f"localize_{sequence}"]["load_average"]
    return {
        "sequence": sequence,
        "database": database_label(results),
        "map": name,
        "images": results["database_images"],
        "hole_share": results["hole_share"],
        "queries": entry["queries"],
        "accepted": entry["accepted"],
        "precision": entry["precision"],
        **{f"rate_{k}": v for k, v in entry["rates"].items()},
        "retrieval_rate": entry["retrieval_rate"],
        "mate_m": entry["mate_m"],
        "ms_per_query": entry["median_ms_per_query"],
        "load_average": load,
    }


def seed1_row(
    results_path: Path, dataset: Path, sequence: str, frames: np.ndarray, loose_m: float
) -> dict:
    """Seed 1's accepted poses of ``sequence`` on ``frames`` scored like the other rows.

    A frame without an estimate in ``estimates.tum`` (matched by timestamp) was not accepted.
    """
    results = json.loads(results_path.read_text())
    entry = results["sequences"][sequence]
    times, T_est = read_tum(entry["estimates"])
    seq = read_sequence(dataset, sequence)  # ground truth: scoring only
    stamps = np.asarray(seq.timestamps)[frames]
    index = {round(float(t), 6): i for i, t in enumerate(times)}
    found = [index.get(round(float(t), 6)) for t in stamps]
    accepted = np.array([i is not None for i in found])
    estimates = np.full((len(frames), 4, 4), np.nan)
    estimates[accepted] = T_est.numpy()[[i for i in found if i is not None]]
    errors = pose_errors(estimates, seq.T_wc[frames].numpy(), accepted)
    return {
        "sequence": sequence,
        "database": "seed 1 hierarchical (mapping keyframes + surfels)",
        "map": "seed1",
        "images": None,
        "hole_share": None,
        "queries": len(frames),
        "accepted": int(accepted.sum()),
        "precision": _precision(errors, loose_m),
        **{
            f"rate_{k}": v
            for k, v in localization_rates(
                errors.translation_m, errors.rotation_deg, accepted, loose_m
            ).items()
        },
        "retrieval_rate": None,
        "mate_m": _finite(mean_ate(errors)),
        "ms_per_query": entry.get("median_total_ms"),
        "load_average": None,
        "results": str(results_path),
    }


def _precision(errors: PoseErrors, loose_m: float) -> float | None:
    count = int(errors.localized.sum())
    return float(is_correct(errors, loose_m, 30.0).sum() / count) if count else None


def _finite(x: float) -> float | None:
    return None if np.isnan(x) else float(x)


def _columns(loose_m: float, by_sequence: bool) -> list[Column]:
    return [
        *([Column("sequence", align="left")] if by_sequence else []),
        Column("database", align="left"),
        Column("images", "DB images", "d"),
        Column("hole_share", "holes [%]", ".1f", scale=100),
        Column("queries", "queries", "d"),
        Column("accepted", "accepted", "d"),
        Column("precision", "precision [%]", ".1f", scale=100),
        Column("rate_0.25m_2deg", "0.25 m / 2 deg [%]", ".1f", scale=100),
        Column("rate_0.5m_5deg", "0.5 m / 5 deg [%]", ".1f", scale=100),
        Column(f"rate_{loose_m:g}m_30deg", f"{loose_m:g} m / 30 deg [%]", ".1f", scale=100),
        Column("retrieval_rate", "retrieval [%]", ".1f", scale=100),
        Column("mate_m", "mATE [m]", ".3f"),
        Column("ms_per_query", "ms / query", ".0f"),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequence", action="append", required=True, help="(repeatable)")
    parser.add_argument("--run", action="append", required=True, help="NAME=results.json")
    parser.add_argument("--seed1", type=Path, help="results.json of diffloc task=main")
    parser.add_argument("--dataset", type=Path, help="the dataset (ground truth for --seed1)")
    parser.add_argument("--title", required=True)
    parser.add_argument("--command", required=True, help="the command that made the table")
    parser.add_argument("--note", default="", help="a paragraph under the table")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    runs = dict(item.split("=", 1) for item in args.run)
    loaded = {option: json.loads(Path(path).read_text()) for option, path in runs.items()}
    first = next(iter(loaded.values()))
    every, loose_m = first["every"], first["loose_m"]
    if any(r["every"] != every or r["loose_m"] != loose_m for r in loaded.values()):
        raise SystemExit("the runs disagree on task.every or task.loose_m: not the same queries")
    if args.seed1 is not None and not args.seed1.is_file():
        raise SystemExit(f"{args.seed1} is missing: run diffloc task=main first")
    rows = []
    for sequence in args.sequence:
        rows += [crossmodal_row(o, r, sequence) for o, r in loaded.items()]
        if args.seed1 is not None:
            n = first["sequences"][sequence]["queries"]
            frames = np.arange(0, n * every, every)
            rows.append(seed1_row(args.seed1, args.dataset, sequence, frames, loose_m))
    several = len(args.sequence) > 1
    table = markdown_table(rows, _columns(loose_m, several))
    names = ", ".join(f"`{name}`" for name in args.sequence)
    loads = ", ".join(
        " ".join([r["map"], *([r["sequence"]] if several else []), f"{r['load_average'][0]:.1f}"])
        for r in rows
        if r["load_average"] is not None
    )
    checked = [
        o
        for o, r in loaded.items()
        if any(f"rerender_{sequence}" in r["stages"] for sequence in args.sequence)
    ]
    rerendered = (
        f" (for {', '.join(checked)} the re-render check's time included, `task.rerender`)"
        if checked
        else ""
    )
    seed1 = args.seed1 is not None
    text = "\n".join(
        [
            f"# {args.title}: {names} of {first['dataset']}, every {every}-th frame",
            "",
            *made_by_lines(args.command),
            table,
            "",
            f"Queries: every {every}-th frame of {names} (frames 0, {every}, ...). "
            "Accepted: a pose was found and passed the localiser's validation"
            + (" (seed 1: its accepted poses)" if seed1 else "")
            + f". Precision: accepted poses within {loose_m:g} m / 30 deg. Rates: "
            "share of ALL queries accepted within the bound. Retrieval: the top-1 database "
            "image lies within the render spacing and 45 deg of the query. ms / query: median "
            f"wall time per query including features{rerendered}, under the machine's load "
            "(1-minute load "
            f"average when each localisation ran: {loads}; 2 cores)"
            + (
                "; seed 1's is its median total (features included) from its own run over "
                "every frame."
                if seed1
                else "."
            )
            + (f"\n\n{args.note}" if args.note else ""),
            "",
        ]
    )
    report = {
        "sequence": args.sequence if several else args.sequence[0],
        "every": every,
        "loose_m": loose_m,
        "command": args.command,
        "runs": runs,
        "rows": rows,
    }
    write_report(args.out, text, report)
    print(text)


if __name__ == "__main__":
    main()
