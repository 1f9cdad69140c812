"""Where the localisation rate of ``diffloc task=crossmodal`` is lost, query by query.

Reads the cached ``localize_<sequence>`` stage of each ``--map`` (``localization.npz`` under
``<dataset>/crossmodal/<map>/``: per query the top-1 retrieved render, the reference the pose
came from, LighterGlue matches, points with depth, PnP inliers, the photometric consistency
and the validation's verdicts) and the query ground truth (scoring only), and gives each query
ONE outcome, the first stage that decides it:

- ``localized``: accepted, within ``--loose-m`` / 30 deg;
- ``wrong accepted``: accepted, outside it;
- ``localized: second look`` / ``wrong accepted: second look``: refused, then accepted by the
  re-render check's second look (``task.rerender``, when it ran on this localisation), at its
  new pose within / outside the bound;
- ``right pose refused: storey alias`` / ``wrong pose refused: storey alias``: accepted by the
  validation, then refused by the storey-alias test (``task.storey_alias``, when it ran on this
  localisation);
- ``no pose``: no reference gave a PnP pose with enough inliers;
- ``right pose rejected: inliers`` / ``...: coverage or rival`` / ``...: photometric``: a pose
  within the bound that the validation refused, by the first test it failed (fewer than
  ``theta_in`` inliers; the inlier ratio, coverage or ambiguity tests; the photometric
  consistency);
- ``wrong pose, no render near``: a wrong pose (rejected) and no database image at all lies
  within the render spacing and 45 deg of the query: the render poses do not cover it;
- ``wrong pose, far reference``: a wrong pose (rejected) from a reference that is not within
  them although one is: retrieval (and re-ranking) failed;
- ``wrong pose, near reference``: a wrong pose (rejected) from a reference within them:
  matching or PnP failed on the right render.

The re-render check (``task.rerender``, indoors on for ``mesh`` and ``cloud``) is read from its
record, not replayed: with ``--set`` overrides of the thresholds its second look is left out
(``experiments/rerender_check.py`` reports that check query by query).

With the pose prior on (``task.localizer.prior``), each row says whether the reference came
from the prior (``from_prior``), and per map and sequence the report counts the accepted and
the wrong accepted poses whose reference came from it.

The verdicts are replayed from the recorded evidence
(:func:`~diffloc.pipeline.crossmodal_replay.replay_validation`) with the thresholds the run
used (read from its ``localize.json``), or with ``--theta-in``, ``--min-coverage``,
``--ambiguity-ratio``, ``--min-inlier-ratio``, ``--min-photometric`` and ``--max-plane-share``
in their place
(``none`` turns a test off): other thresholds are scored without relocalising.
Without any of them the replay must give the run's own verdicts (it stops otherwise).

Per map and sequence the report also gives which tests reject the poses found (every test a
rejected pose fails, and the poses it alone rejects, right and wrong poses apart), the
photometric test's effect: accepted poses, wrong accepted poses, precision and localisation
rate without it and with it, and per map the threshold rule of
``task.validation.<map>.min_photometric``: the
1st percentile of the scores of the right poses the other tests accept, over the given
sequences, rounded down to 0.1.

Usage:
    PYTHONPATH=. python3 experiments/crossmodal_breakdown.py --dataset data/indoor_seed0 \\
        --map tls --map mesh --sequence query_same \\
        --command "bash experiments/run_tables.sh crossmodal_tables data/indoor_seed0" \\
        --out experiments/results/crossmodal_breakdown_indoor_seed0
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch

from diffloc.crossmodal.database import RenderedDatabase
from diffloc.eval.metrics import is_correct, pose_errors
from diffloc.eval.report_files import made_by_lines, write_report
from diffloc.features.retrieval_eval import pairwise_pose_distances
from diffloc.io.dataset import read_sequence
from diffloc.io.identity import identity
from diffloc.pipeline.crossmodal_alias import SequenceAliases
from diffloc.pipeline.crossmodal_replay import (
    REPLAYED_TESTS,
    recorded_evidence,
    recorded_validation,
    replay_validation,
    verdict_effect,
)
from diffloc.pipeline.crossmodal_report import RETRIEVAL_ANGLE_DEG, retrieval_hits
from diffloc.pipeline.crossmodal_rerender import SequenceRerender
from diffloc.pipeline.crossmodal_stage import SequenceLocalization, crossmodal_folder
from diffloc.reloc.validation import ValidationConfig

OUTCOMES = (
    "localized",
    "wrong accepted",
    "localized: second look",
    "wrong accepted: second look",
    "right pose refused: storey alias",
    "wrong pose refused: storey alias",
    "no pose",
    "right pose rejected: inliers",
    "right pose rejected: coverage or rival",
    "right pose rejected: photometric",
    "wrong pose, no render near",
    "wrong pose, far reference",
    "wrong pose, near reference",
)


def outcomes(
    loc: SequenceLocalization,
    accepted: np.ndarray,
    correct: np.ndarray,
    reference_hit: np.ndarray,
    near_renders: np.ndarray,
    failed: list[tuple[str, ...]],
    aliases: np.ndarray,
    second: np.ndarray | None = None,
) -> list[str]:
    """The outcome (:data:`OUTCOMES`) of each of the Q queries (module docstring).

    Args:
        loc: the localiser's answers.
        accepted: (Q,) bool, the verdict (the run's or a replayed threshold's).
        correct: (Q,) bool, the pose found is within the bound.
        reference_hit: (Q,) bool, the reference of the pose lies within the render spacing
            and 45 deg of the query.
        near_renders: (Q,) int, database images within them.
        failed: per query, the validation tests its pose fails
            (:func:`~diffloc.pipeline.crossmodal_replay.replay_validation`).
        aliases: (Q,) bool, the storey-alias test refused the pose (:func:`storey_aliases`).
        second: (Q,) bool, refused and then accepted by the re-render check's second look
            (:func:`second_look`; ``correct`` of those is their new pose's); ``None``: none.
    """
    second = np.zeros(len(loc.frames), dtype=bool) if second is None else second
    result = []
    for q in range(len(loc.frames)):
        if (accepted[q] or second[q]) and aliases[q]:
            result.append(f"{'right' if correct[q] else 'wrong'} pose refused: storey alias")
        elif accepted[q]:
            result.append("localized" if correct[q] else "wrong accepted")
        elif second[q]:
            result.append(f"{'localized' if correct[q] else 'wrong accepted'}: second look")
        elif not loc.success[q]:
            result.append("no pose")
        elif correct[q] and "inliers" in failed[q]:
            result.append("right pose rejected: inliers")
        elif correct[q] and set(failed[q]) != {"photometric"}:
            result.append("right pose rejected: coverage or rival")
        elif correct[q]:
            result.append("right pose rejected: photometric")
        elif reference_hit[q]:
            result.append("wrong pose, near reference")
        else:
            far = "far reference" if near_renders[q] else "no render near"
            result.append(f"wrong pose, {far}")
    return result


def _tested_outputs(record: Path) -> dict | None:
    """The outputs a check's stage record says it tested (``None``: no record)."""
    if not record.is_file():
        return None
    return json.loads(record.read_text())["stage"]["key"]["inputs"]["localization"]


def second_look(folder: Path, sequence: str) -> SequenceRerender | None:
    """The re-render check's record of ``<map>/rerender_<sequence>`` if it looked at this very
    localisation (its record names the ``localization.npz`` it read), else ``None``."""
    localization = folder / f"localize_{sequence}" / "localization.npz"
    record = folder / f"rerender_{sequence}" / "rerender.json"
    if _tested_outputs(record) != {"localization.npz": identity(localization)}:
        return None
    return SequenceRerender.load(record.parent / "rerender.npz")


def storey_aliases(folder: Path, sequence: str, queries: int, looked: bool) -> np.ndarray:
    """(Q,) bool, the accepted poses ``task.storey_alias`` refused (``<map>/alias_<sequence>``;
    all false unless it tested this very localisation's answers, after the re-render check's
    second look when ``looked``: its record names the outputs it tested)."""
    refused = np.zeros(queries, dtype=bool)
    record = folder / f"alias_{sequence}" / "alias.json"
    answers = {"localization.npz": identity(folder / f"localize_{sequence}" / "localization.npz")}
    if looked:
        answers["rerender.npz"] = identity(folder / f"rerender_{sequence}" / "rerender.npz")
    if _tested_outputs(record) == answers:
        aliases = SequenceAliases.load(record.parent / "alias.npz")
        refused[aliases.query[aliases.alias]] = True
    return refused


def breakdown(
    dataset: Path,
    option: str,
    sequence: str,
    spacing_m: float,
    loose_m: float,
    overrides: dict,
) -> dict:
    """Per-query rows, outcome counts and rejecting tests of one map's localisation of
    ``sequence``, the validation replayed with ``overrides`` of the run's thresholds."""
    folder = crossmodal_folder(dataset) / option
    path = folder / f"localize_{sequence}" / "localization.npz"
    if not path.is_file():
        raise SystemExit(
            f"{path} is missing: run diffloc task=crossmodal map={option} dataset={dataset} "
            f"task.sequences=[{sequence}] first"
        )
    loc = SequenceLocalization.load(path)
    db = RenderedDatabase.load(folder / "database" / "rgbd")
    recorded, real_threshold = recorded_validation(path.parent)
    validation = replace(recorded, **overrides)
    real = None if db.real is None else db.real.numpy()
    evidence = recorded_evidence(loc)

    def replay(config: ValidationConfig) -> tuple[np.ndarray, list[tuple[str, ...]]]:
        return replay_validation(evidence, config, real, real_threshold)

    accepted, failed = replay(validation)
    if not overrides and not np.array_equal(accepted, loc.accepted.astype(bool)):
        raise SystemExit(f"{path}: the replay of the run's own thresholds differs from its verdict")
    geometric, _ = replay(replace(validation, min_photometric=None))
    T_gt = read_sequence(dataset, sequence).T_wc[loc.frames]  # ground truth: scoring only
    found = loc.success.astype(bool)
    first_pass = is_correct(pose_errors(loc.T_wc, T_gt.numpy(), found), loose_m, 30.0)
    looked = None if overrides else second_look(folder, sequence)
    second = np.zeros(len(loc.frames), dtype=bool)
    T_wc = loc.T_wc
    if looked is not None:  # refused poses the second look accepted, at their new pose
        answers = looked.apply(loc)
        second = answers.accepted.astype(bool) & ~accepted
        T_wc = np.where(second[:, None, None], answers.T_wc, loc.T_wc)
    errors = pose_errors(T_wc, T_gt.numpy(), found)
    correct = is_correct(errors, loose_m, 30.0)  # the answers': first pass or second look

    def hits(index: np.ndarray) -> np.ndarray:
        chosen = torch.from_numpy(index).clamp_min(0)
        return retrieval_hits(T_gt, db.T_wc[chosen], index >= 0, spacing_m)

    top1_hit, reference_hit = hits(loc.top1), hits(loc.reference)
    distance, angle = pairwise_pose_distances(T_gt, db.T_wc)
    near = (distance <= spacing_m) & (angle <= np.radians(RETRIEVAL_ANGLE_DEG))
    near_renders = near.sum(1).numpy()
    aliases = storey_aliases(folder, sequence, len(loc.frames), looked is not None)
    verdicts = outcomes(
        loc, accepted, correct, reference_hit, near_renders, failed, aliases, second
    )
    rows = [
        {
            "frame": int(loc.frames[q]),
            "near_renders": int(near_renders[q]),
            "top1_hit": bool(top1_hit[q]),
            "reference_hit": bool(reference_hit[q]),
            "matches": int(loc.num_matches[q]),
            "points": int(loc.num_points[q]),
            "inliers": int(loc.num_inliers[q]),
            "coverage": None if evidence[q] is None else evidence[q][1].coverage,
            "pnp": bool(found[q]),
            "photometric": None if np.isnan(loc.photometric[q]) else float(loc.photometric[q]),
            "error_m": float(errors.translation_m[q]) if found[q] else None,
            "error_deg": float(errors.rotation_deg[q]) if found[q] else None,
            "accepted": bool((accepted[q] or second[q]) and not aliases[q]),
            "failed": ", ".join(failed[q]),
            "from_prior": bool(loc.from_prior[q]),
            "outcome": verdicts[q],
        }
        for q in range(len(loc.frames))
    ]
    counts = Counter(verdicts)
    from_prior = accepted & loc.from_prior.astype(bool)
    return {
        "map": option,
        "sequence": sequence,
        "queries": len(rows),
        "validation": asdict(validation),
        "rejections": rejections(failed, found & ~accepted, first_pass),
        "photometric": {
            "without": verdict_effect(geometric, first_pass),
            "with": verdict_effect(accepted, first_pass),
            "right_scores": loc.photometric[geometric & first_pass].tolist(),
        },
        "accepted_from_prior": int(from_prior.sum()),
        "wrong_from_prior": int((from_prior & ~first_pass).sum()),
        "queries_with_prior": int((loc.prior_images > 0).sum()),
        "median_ms": float(np.median(loc.time_ms)),
        "load_average": json.loads((path.parent / "localize.json").read_text())["load_average"],
        "top1_retrieval_rate": float(top1_hit.mean()),
        "reference_hit_rate": float(reference_hit.mean()),
        "counts": {name: counts.get(name, 0) for name in OUTCOMES},
        "rows": rows,
    }


def rejections(failed: list[tuple[str, ...]], rejected: np.ndarray, correct: np.ndarray) -> dict:
    """Per test (:data:`REPLAYED_TESTS`), the rejected right and wrong poses that fail it
    (``right``, ``wrong``) and those it alone rejects (``right_only``, ``wrong_only``).

    Args:
        failed: per query, the tests its pose fails.
        rejected: (Q,) bool, a pose was found and rejected.
        correct: (Q,) bool, the pose is within the bound.

    Example:
        >>> table = rejections([("coverage", "rival"), ("rival",), ()],
        ...                    np.array([True, True, False]), np.array([True, False, True]))
        >>> table["rival"], table["coverage"]["right_only"]
        ({'right': 1, 'wrong': 1, 'right_only': 0, 'wrong_only': 1}, 0)
    """
    table = {}
    for test in REPLAYED_TESTS:
        fails = np.array([test in f for f in failed], dtype=bool) & rejected
        alone = fails & np.array([len(f) == 1 for f in failed], dtype=bool)
        table[test] = {
            "right": int((fails & correct).sum()),
            "wrong": int((fails & ~correct).sum()),
            "right_only": int((alone & correct).sum()),
            "wrong_only": int((alone & ~correct).sum()),
        }
    return table


def threshold_rule(scores: list[float]) -> float | None:
    """The 1st percentile of right poses' photometric scores, rounded down to 0.1 (``None``
    without scores)."""
    values = np.asarray(scores, dtype=np.float64)
    values = values[~np.isnan(values)]
    if not len(values):
        return None
    return float(np.floor(np.percentile(values, 1) * 10) / 10)


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f}"


def _cell(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.2f}"
    return str(value)


THRESHOLDS = (
    "theta_in",
    "min_inlier_ratio",
    "min_coverage",
    "ambiguity_ratio",
    "min_photometric",
    "max_plane_share",
)
"""The single-image thresholds a replay can change (``theta_dist_m`` stays the run's)."""


def _thresholds(validation: dict) -> dict:
    return {name: validation.get(name) for name in THRESHOLDS}  # older runs: no plane test


def _settings(values: dict) -> str:
    return ", ".join(f"{name}={value}" for name, value in values.items())


def _label(entry: dict) -> str:
    return f"{entry['map']} {entry['sequence']}"


def _frames(rows: list[dict]) -> str:
    frames = [r["frame"] for r in rows]
    return ", ".join(map(str, frames[:3])) + (f", ... {frames[-1]}" if len(frames) > 3 else "")


def markdown(report: dict) -> str:
    """The summary table (outcome counts per map) and one per-query table per map."""
    maps = report["maps"]
    sequences = ", ".join(f"`{s}`" for s in report["sequences"])
    lines = [
        f"# Where the localisation rate is lost: {sequences} of {report['dataset']}",
        "",
        *made_by_lines(report["command"]),
        f"Each query (frames {_frames(maps[0]['rows'])}) gets the outcome of the first stage "
        "that decides it (experiments/crossmodal_breakdown.py docstring). Bound "
        f"{report['loose_m']:g} m / 30 deg; a reference is near the query within "
        f"{report['spacing_m']:g} m and 45 deg. Validation replayed from the recorded "
        "evidence with "
        + (
            "the runs' own thresholds (the replay reproduces their verdicts)"
            if not report["overrides"]
            else f"the runs' thresholds but {_settings(report['overrides'])}"
        )
        + f": {_settings(_thresholds(maps[0]['validation']))}.",
        "",
        "## Which tests reject the poses found",
        "",
        "Per test, the rejected right / wrong poses that fail it (a pose may fail several), "
        "and in brackets those it alone rejects.",
        "",
        "| test | " + " | ".join(_label(m) + " right / wrong" for m in maps) + " |",
        "|:---|" + "---:|" * len(maps),
    ]
    for test in REPLAYED_TESTS:
        cells = [m["rejections"][test] for m in maps]
        if not any(c["right"] or c["wrong"] for c in cells):
            continue
        lines.append(
            f"| {test} | "
            + " | ".join(
                f"{c['right']} / {c['wrong']} ({c['right_only']} / {c['wrong_only']})"
                for c in cells
            )
            + " |"
        )
    lines += [
        "",
        "## The photometric test (without -> with)",
        "",
        "| map | sequence | accepted | wrong accepted | precision [%] | rate [%] |",
        "|:---|:---|---:|---:|---:|---:|",
    ]
    for m in maps:
        a, b = m["photometric"]["without"], m["photometric"]["with"]
        lines.append(
            f"| {m['map']} | {m['sequence']} | {a['accepted']} -> {b['accepted']} | "
            f"{a['wrong']} -> {b['wrong']} | {_pct(a['precision'])} -> {_pct(b['precision'])} | "
            f"{_pct(a['rate'])} -> {_pct(b['rate'])} |"
        )
    lines += [
        "",
        "Threshold rule per map (1st percentile of the right poses' scores that pass "
        "the other tests, over these sequences, rounded down to 0.1):",
        "",
    ]
    for option, rule in report["threshold_rule"].items():
        lines.append(f"- {option}: {'-' if rule is None else f'{rule:g}'}")
    lines += [
        "",
        "## Outcomes",
        "",
        "| outcome | " + " | ".join(_label(m) for m in maps) + " |",
        "|:---|" + "---:|" * len(maps),
    ]
    for name in OUTCOMES:
        lines.append(f"| {name} | " + " | ".join(str(m["counts"][name]) for m in maps) + " |")
    for key, label in (
        ("accepted_from_prior", "accepted from the prior"),
        ("wrong_from_prior", "wrong accepted from the prior"),
        ("queries_with_prior", "queries with prior images"),
    ):
        lines.append(f"| {label} | " + " | ".join(str(m[key]) for m in maps) + " |")
    lines.append(
        "| median ms per query | " + " | ".join(f"{m['median_ms']:.0f}" for m in maps) + " |"
    )
    lines.append(
        "| load (1/5/15 min) when the localisation ended | "
        + " | ".join("/".join(f"{x:.1f}" for x in m["load_average"]) for m in maps)
        + " |"
    )
    for key, label in (
        ("top1_retrieval_rate", "top-1 render near"),
        ("reference_hit_rate", "reference near"),
    ):
        lines.append(f"| {label} [%] | " + " | ".join(f"{100 * m[key]:.1f}" for m in maps) + " |")
    if report["note"]:
        lines += ["", report["note"]]
    columns = list(maps[0]["rows"][0])
    for m in maps:
        lines += ["", f"## {_label(m)}", "", "| " + " | ".join(columns) + " |"]
        lines.append("|" + "---|" * len(columns))
        lines += ["| " + " | ".join(_cell(r[c]) for c in columns) + " |" for r in m["rows"]]
    return "\n".join(lines) + "\n"


KEEP = object()
"""A threshold's command-line default: the run's own."""


def optional_float(text: str) -> float | None:
    """A threshold from the command line; ``none`` turns the test off."""
    return None if text.lower() == "none" else float(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--map", action="append", required=True, help="a map option")
    parser.add_argument("--sequence", action="append", required=True)
    parser.add_argument("--spacing-m", type=float, default=2.0, help="render spacing")
    parser.add_argument("--loose-m", type=float, default=1.0, help="loose position bound")
    parser.add_argument("--theta-in", type=int, default=KEEP, help="replay: fewest inliers")
    for name in THRESHOLDS[1:]:
        flag = "--" + name.replace("_", "-")
        parser.add_argument(flag, type=optional_float, default=KEEP, help="replay (none: off)")
    parser.add_argument("--command", required=True, help="the command of the runs read")
    parser.add_argument("--note", default="", help="a paragraph under the outcome counts")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    overrides = {
        name: getattr(args, name) for name in THRESHOLDS if getattr(args, name) is not KEEP
    }
    for name in ("min_inlier_ratio", "min_coverage"):  # off is 0 for these
        if overrides.get(name, 0.0) is None:
            overrides[name] = 0.0
    maps = [
        breakdown(args.dataset, option, sequence, args.spacing_m, args.loose_m, overrides)
        for option in args.map
        for sequence in args.sequence
    ]
    rules = {
        option: threshold_rule(
            [x for m in maps if m["map"] == option for x in m["photometric"]["right_scores"]]
        )
        for option in args.map
    }
    report = {
        "command": args.command,
        "dataset": str(args.dataset),
        "sequences": args.sequence,
        "threshold_rule": rules,
        "spacing_m": args.spacing_m,
        "loose_m": args.loose_m,
        "overrides": overrides,
        "note": args.note,
        "maps": maps,
    }
    write_report(args.out, markdown(report), report)
    print(markdown(report).split("\n## Outcomes")[0])


if __name__ == "__main__":
    main()
