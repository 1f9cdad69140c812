"""Replay ``task.localizer.min_rerank_ratio`` on a recorded localisation without matching again.

The localiser tries the re-ranked images in order, so a ratio only cuts the tail of that list:
the candidates it keeps are a prefix of the ones the run tried, matched with the same RANSAC
draws (one generator per query, consumed in order). Reading a run made with the ratio off
(``localization.npz``: every candidate's re-ranking matches, inliers, coverage and position),
this script keeps, per query and ratio, the candidates with at least that share of the first
image's mutual-NN matches, chooses among them as the localiser does
(:func:`~diffloc.reloc.rendered.choose_candidate`, the run's ``select`` and ``stop_inliers``)
and validates the choice (:func:`~diffloc.reloc.rendered.accept_pose`, the run's thresholds).
Where the choice is the run's, the recorded photometric score applies and the verdict is
exact; where another candidate becomes the answer its photometric score was never measured,
and the query is counted as ``changed`` (scored as accepted only if it passes every other test
and lies within 1 m of the truth by position, the only part of a candidate's pose recorded).
The query ground truth is read for scoring only.

Usage:
    PYTHONPATH=. python3 experiments/rerank_ratio_replay.py --dataset data/indoor_seed0 \\
        --map mesh --sequence query_same --sequence query_reverse \\
        --command "..." --out experiments/results/rerank_ratio_replay_mesh_indoor_seed0
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from diffloc.eval.metrics import is_correct
from diffloc.eval.report_files import made_by_lines, write_report
from diffloc.io.dataset import read_sequence
from diffloc.pipeline.crossmodal_replay import recorded_errors, recorded_validation
from diffloc.pipeline.crossmodal_stage import SequenceLocalization, crossmodal_folder
from diffloc.reloc.rendered import accept_pose, choose_candidate

RATIOS = (0.8, 0.85, 0.9, 0.95)


def replay(dataset: Path, option: str, sequence: str, ratios: tuple[float, ...]) -> list[dict]:
    """Per ratio: candidates matched, accepted, wrong accepted, right poses lost, and the
    queries whose answer changes (photometric unknown), over the run's queries."""
    folder = crossmodal_folder(dataset) / option / f"localize_{sequence}"
    loc = SequenceLocalization.load(folder / "localization.npz")
    localizer = json.loads((folder / "localize.json").read_text())["stage"]["key"]["config"][
        "localizer"
    ]
    if localizer["min_rerank_ratio"] is not None or localizer["rerank"] is None:
        raise SystemExit(f"{folder}: replay needs a run with rerank on and min_rerank_ratio off")
    validation, _ = recorded_validation(folder)
    geometric = replace(validation, min_photometric=None)
    correct = is_correct(recorded_errors(dataset, sequence, loc), 1.0, 30.0)
    truth = read_sequence(dataset, sequence).T_wc[loc.frames].numpy()[:, :3, 3]
    accepted = loc.accepted.astype(bool)
    rows = []
    for ratio in (None, *ratios):
        matched, now, wrong, changed = 0, 0, 0, []
        for q in range(len(loc.frames)):
            best, tried = loc.candidates(q)
            counts = loc.candidate_rerank_matches[loc.candidate_query == q]
            keep = [
                c
                for c, n in zip(tried, counts, strict=True)
                if ratio is None or n >= ratio * counts[0]
            ]
            choice, kept = choose_candidate(keep, localizer["select"], localizer["stop_inliers"])
            matched += len(kept)
            if choice.reference == best.reference:
                ok = accept_pose(choice, kept, validation, float(loc.photometric[q]))
                right = bool(correct[q])
            else:
                changed.append(int(loc.frames[q]))
                ok = accept_pose(choice, kept, geometric)
                right = bool(np.linalg.norm(choice.T_wc[:3, 3].numpy() - truth[q]) < 1.0)
            now += ok
            wrong += ok and not right
        rows.append(
            {
                "sequence": sequence,
                "ratio": ratio,
                "queries": len(loc.frames),
                "candidates": matched,
                "accepted": now,
                "wrong": wrong,
                "right": now - wrong,
                "run_right": int((accepted & correct).sum()),
                "changed_frames": changed,
            }
        )
    return rows


def markdown(report: dict) -> str:
    lines = [
        f"# Replayed `min_rerank_ratio`: {report['dataset']}, map={report['map']}",
        "",
        *made_by_lines(report["commands"]),
        "Ratio `-`: the run itself (ratio off). Changed: frames whose answer becomes another "
        "candidate (its photometric score unknown; scored by the other tests and its "
        "position, module docstring).",
        "",
        "| sequence | ratio | queries | candidates matched | accepted | right | wrong | "
        "right in the run | changed frames |",
        "|:---|---:|---:|---:|---:|---:|---:|---:|:---|",
    ]
    for r in report["rows"]:
        ratio = "-" if r["ratio"] is None else f"{r['ratio']:g}"
        lines.append(
            f"| {r['sequence']} | {ratio} | {r['queries']} | {r['candidates']} | "
            f"{r['accepted']} | {r['right']} | {r['wrong']} | {r['run_right']} | "
            f"{', '.join(map(str, r['changed_frames'])) or '-'} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--map", default="mesh")
    parser.add_argument("--sequence", action="append", required=True)
    parser.add_argument("--ratio", type=float, action="append", help=f"default {RATIOS}")
    parser.add_argument("--command", action="append", required=True, help="the run's command")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    ratios = tuple(args.ratio or RATIOS)
    rows = [r for s in args.sequence for r in replay(args.dataset, args.map, s, ratios)]
    report = {
        "dataset": str(args.dataset),
        "map": args.map,
        "commands": args.command,
        "rows": rows,
    }
    write_report(args.out, markdown(report), report)
    print(markdown(report))


if __name__ == "__main__":
    main()
