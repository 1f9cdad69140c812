"""Choose the single-image validation thresholds of a map on one dataset, apply them to another.

Replays (:func:`~diffloc.pipeline.crossmodal_replay.replay_validation`, no relocalisation) the
recorded localisations of ``--map`` on the ``--sequence`` s of the tuning dataset for every
combination of a grid of ``theta_in``, ``min_inlier_ratio``, ``min_coverage``,
``ambiguity_ratio`` and ``min_photometric`` (``theta_dist_m`` stays the run's), and chooses by
one rule on the tuning dataset ONLY:

    the most right accepted poses (within ``--loose-m`` / 30 deg) over the sequences, with no
    more wrong accepted poses than the run's own thresholds accept; among equals, the fewest
    thresholds changed from the run's, then the fewest grid steps away from them.

Its margin: each threshold moved one grid step looser alone (wrong and right accepted poses
on the tuning dataset). The chosen thresholds are then applied unchanged to the held-out
dataset; the report gives, per dataset and sequence, accepted / wrong accepted / precision /
localisation rate with the run's thresholds and with the chosen ones.

Usage:
    PYTHONPATH=. python3 experiments/crossmodal_threshold_choice.py --tune data/indoor_seed0 \\
        --heldout data/indoor_seed1 --map mesh --sequence query_same \\
        --sequence query_reverse --command "..." \\
        --out experiments/results/crossmodal_thresholds_mesh_indoor
"""

from __future__ import annotations

import argparse
import itertools
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from diffloc.crossmodal.database import RenderedDatabase
from diffloc.eval.metrics import is_correct
from diffloc.eval.report_files import made_by_lines, write_report
from diffloc.pipeline.crossmodal_replay import (
    recorded_errors,
    recorded_evidence,
    recorded_validation,
    replay_validation,
    verdict_effect,
)
from diffloc.pipeline.crossmodal_stage import SequenceLocalization, crossmodal_folder
from diffloc.reloc.validation import PoseEvidence, ValidationConfig

GRID: dict[str, tuple] = {
    "theta_in": (200, 180, 160, 150, 140, 120, 100, 80, 60, 40),
    "min_inlier_ratio": (0.6, 0.5, 0.4, 0.3, 0.0),
    "min_coverage": (0.75, 0.6875, 0.625, 0.5625, 0.5, 0.4375, 0.375, 0.25, 0.0),
    "ambiguity_ratio": (0.5, 0.6, 0.7, 0.8, 0.9, 1.0, None),
    "min_photometric": (0.6, 0.5, 0.4, 0.3, 0.2, None),
}
"""Values per threshold, strictest first (``None``: the test off; coverage in 16ths)."""


@dataclass
class Recorded:
    """One recorded localisation: its evidence, right poses, the thresholds it ran with and
    (for the report) its frames and position errors (metres)."""

    sequence: str
    evidence: list[tuple[int, PoseEvidence] | None]
    correct: np.ndarray
    validation: ValidationConfig
    real: np.ndarray | None
    min_photometric_real: float | None
    frames: np.ndarray | None = None
    error_m: np.ndarray | None = None

    def effect(self, validation: ValidationConfig) -> dict:
        """Accepted, wrong, precision and rate of ``validation`` replayed."""
        return verdict_effect(self.accepted(validation), self.correct)

    def accepted(self, validation: ValidationConfig) -> np.ndarray:
        """(Q,) bool, the verdict of ``validation`` replayed."""
        return replay_validation(self.evidence, validation, self.real, self.min_photometric_real)[0]

    def wrong(self, validation: ValidationConfig) -> list[dict]:
        """The wrong poses ``validation`` accepts: frame, evidence and position error."""
        wrong = self.accepted(validation) & ~self.correct
        return [
            {
                "frame": int(self.frames[q]),
                "inliers": self.evidence[q][1].num_inliers,
                "coverage": self.evidence[q][1].coverage,
                "photometric": self.evidence[q][1].photometric,
                "error_m": float(self.error_m[q]),
            }
            for q in np.flatnonzero(wrong).tolist()
        ]


def load(dataset: Path, option: str, sequence: str, loose_m: float) -> Recorded:
    """The recorded localisation of ``sequence`` in ``option``'s map of ``dataset``."""
    folder = crossmodal_folder(dataset) / option
    stage = folder / f"localize_{sequence}"
    loc = SequenceLocalization.load(stage / "localization.npz")
    validation, real_threshold = recorded_validation(stage)
    db = RenderedDatabase.load(folder / "database" / "rgbd")
    errors = recorded_errors(dataset, sequence, loc)
    correct = is_correct(errors, loose_m, 30.0)
    real = None if db.real is None else db.real.numpy()
    evidence = recorded_evidence(loc)
    return Recorded(
        sequence,
        evidence,
        correct,
        validation,
        real,
        real_threshold,
        loc.frames,
        errors.translation_m,
    )


def _steps(name: str, value: object, base: object) -> int:
    values = GRID[name]
    if base not in values:
        raise SystemExit(f"the run's {name}={base} is not in the grid {values}")
    return abs(values.index(value) - values.index(base))


def choose(runs: list[Recorded]) -> tuple[dict, list[dict]]:
    """The rule of the module docstring over ``runs`` (one dataset): the chosen thresholds
    and every grid point's totals (right and wrong accepted)."""
    base = runs[0].validation
    names = list(GRID)
    points = []
    for values in itertools.product(*GRID.values()):
        setting = dict(zip(names, values, strict=True))
        effects = [run.effect(replace(run.validation, **setting)) for run in runs]
        wrong = sum(e["wrong"] for e in effects)
        right = sum(e["accepted"] - e["wrong"] for e in effects)
        changed = sum(setting[n] != getattr(base, n) for n in names)
        steps = sum(_steps(n, setting[n], getattr(base, n)) for n in names)
        points.append(
            {"setting": setting, "right": right, "wrong": wrong, "changed": changed, "steps": steps}
        )
    base_wrong = next(
        p["wrong"] for p in points if all(p["setting"][n] == getattr(base, n) for n in names)
    )
    admissible = [p for p in points if p["wrong"] <= base_wrong]
    best = max(admissible, key=lambda p: (p["right"], -p["changed"], -p["steps"]))
    return best, points


def margin(runs: list[Recorded], setting: dict) -> dict:
    """Each threshold one grid step looser than ``setting`` alone: right and wrong accepted
    poses over ``runs`` (``None`` where it is already the loosest)."""
    result = {}
    for name, values in GRID.items():
        index = values.index(setting[name])
        if index + 1 == len(values):
            result[name] = None
            continue
        looser = {**setting, name: values[index + 1]}
        effects = [run.effect(replace(run.validation, **looser)) for run in runs]
        result[name] = {
            "value": values[index + 1],
            "right": sum(e["accepted"] - e["wrong"] for e in effects),
            "wrong": sum(e["wrong"] for e in effects),
        }
    return result


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f}"


def _effect_cells(before: dict, after: dict) -> str:
    return (
        f"{before['accepted']} -> {after['accepted']} | {before['wrong']} -> {after['wrong']} | "
        f"{_pct(before['precision'])} -> {_pct(after['precision'])} | "
        f"{_pct(before['rate'])} -> {_pct(after['rate'])}"
    )


def markdown(report: dict) -> str:
    """The rule, the chosen thresholds, their margin and the before/after table."""
    chosen, base = report["chosen"], report["base"]
    lines = [
        f"# Validation thresholds of map={report['map']} chosen on {report['tune']}, "
        f"applied to {report['heldout']}",
        "",
        *made_by_lines(report["command"]),
        "Rule (on the tuning dataset ONLY, experiments/crossmodal_threshold_choice.py): the most "
        "right accepted poses over the sequences with no more wrong accepted poses than the "
        "run's own thresholds; among equals the fewest thresholds changed, then the fewest grid "
        f"steps. {report['grid_points']} grid points, {report['admissible']} admissible, "
        f"{report['ties']} tie(s) on right poses before the tie-breaks.",
        "",
        "| threshold | run's | chosen | one step looser: value, right / wrong on tuning |",
        "|:---|---:|---:|:---|",
    ]
    for name in GRID:
        step = report["margin"][name]
        looser = "-" if step is None else f"{step['value']}: {step['right']} / {step['wrong']}"
        lines.append(f"| {name} | {base[name]} | {chosen['setting'][name]} | {looser} |")
    lines += [
        "",
        f"Tuning totals: right {report['base_totals']['right']} -> {chosen['right']}, "
        f"wrong {report['base_totals']['wrong']} -> {chosen['wrong']}.",
        "",
        "## Run's thresholds -> chosen, per sequence",
        "",
        "| dataset | sequence | accepted | wrong accepted | precision [%] | rate [%] |",
        "|:---|:---|---:|---:|---:|---:|",
    ]
    for row in report["rows"]:
        lines.append(
            f"| {row['dataset']} | {row['sequence']} | "
            f"{_effect_cells(row['before'], row['after'])} |"
        )
    lines += [
        "",
        "Rate: accepted and within the bound over all queries; precision: right "
        "share of the accepted.",
        "",
        "Wrong poses the chosen thresholds accept (frame: inliers, coverage, photometric, "
        "position error):",
        "",
    ]
    for row in report["rows"]:
        wrong = "; ".join(
            f"{w['frame']}: {w['inliers']}, {w['coverage']:.3f}, {w['photometric']:.2f}, "
            f"{w['error_m']:.1f} m"
            for w in row["wrong_after"]
        )
        lines.append(f"- {row['dataset']} {row['sequence']}: {wrong or 'none'}")
    lines.append("")
    if report["note"]:
        lines += [report["note"], ""]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tune", type=Path, required=True, help="dataset to choose on")
    parser.add_argument("--heldout", type=Path, required=True, help="dataset to apply to")
    parser.add_argument("--map", required=True, help="a map option")
    parser.add_argument("--sequence", action="append", required=True)
    parser.add_argument("--loose-m", type=float, default=1.0, help="loose position bound")
    parser.add_argument("--command", required=True, help="the commands of the runs read")
    parser.add_argument("--note", default="", help="a closing paragraph")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    datasets = {"tune": args.tune, "heldout": args.heldout}
    runs = {
        key: [load(path, args.map, s, args.loose_m) for s in args.sequence]
        for key, path in datasets.items()
    }
    chosen, points = choose(runs["tune"])
    base = runs["tune"][0].validation
    base_setting = {name: getattr(base, name) for name in GRID}
    base_point = next(p for p in points if p["setting"] == base_setting)
    admissible = [p for p in points if p["wrong"] <= base_point["wrong"]]
    rows = [
        {
            "dataset": str(datasets[key]),
            "sequence": run.sequence,
            "before": run.effect(run.validation),
            "after": run.effect(replace(run.validation, **chosen["setting"])),
            "wrong_after": run.wrong(replace(run.validation, **chosen["setting"])),
        }
        for key in datasets
        for run in runs[key]
    ]
    report = {
        "command": args.command,
        "map": args.map,
        "tune": str(args.tune),
        "heldout": str(args.heldout),
        "sequences": args.sequence,
        "loose_m": args.loose_m,
        "note": args.note,
        "grid": GRID,
        "grid_points": len(points),
        "admissible": len(admissible),
        "ties": sum(p["right"] == chosen["right"] for p in admissible),
        "base": base_setting,
        "base_validation": asdict(base),
        "base_totals": {"right": base_point["right"], "wrong": base_point["wrong"]},
        "chosen": chosen,
        "margin": margin(runs["tune"], chosen["setting"]),
        "rows": rows,
    }
    write_report(args.out, markdown(report), report)
    print(markdown(report))


if __name__ == "__main__":
    main()
