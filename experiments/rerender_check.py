"""Issue 18, offline: validate a pose on a render made at that pose instead of the database's.

``diffloc task=crossmodal map=mesh|tls`` matches a query against database renders up to the
render spacing and 45 deg away, and the single-image validation then refuses many right poses
for too few inliers or too little coverage. A rendered map can be rendered at any pose. For
every query of the recorded localisation (``<dataset>/crossmodal/<map>/localize_<sequence>/``,
every 4th frame as recorded) whose best candidate succeeded, this script renders the map at
the recorded pose (the database camera; the map stage as cached, never rebuilt), matches the
query against the render (the localiser's XFeat + LighterGlue), lifts with the render's depth
and solves PnP again (:func:`~diffloc.reloc.rerender.rerender_candidate`, the localiser's own
:func:`~diffloc.reloc.rendered.reference_candidate`), and validates that evidence with the
recorded thresholds (:func:`~diffloc.pipeline.crossmodal_replay.replay_validation`, the same
:class:`~diffloc.reloc.validation.PoseValidator`): inliers, coverage, plane share and the
photometric consistency of the new render warped into the query; the rivals are the recorded
candidates' inliers at their distances to the NEW pose. Pass 2 renders once more at pass 1's
pose. Two more verdicts: **rival kept**, pass 1's with the recorded rival verdict in place of
its own, and **second look**, the recorded verdict of an accepted pose and the rival-kept one of
a refused pose: the rule ``task.rerender`` runs (:mod:`diffloc.pipeline.crossmodal_rerender`).
The verdicts of the recorded evidence are replayed first and must equal the run's.

Query images are resized as the localiser got them
(:func:`~diffloc.pipeline.crossmodal_stage.scaled_images`). Ground truth is read for scoring
only: a pose is right within ``task.loose_m`` (1 m) and 30 deg.

Usage:
    OMP_NUM_THREADS=1 PYTHONPATH=. python3 experiments/rerender_check.py \\
        --dataset data/indoor_seed0 --map mesh \\
        --sequence query_same --sequence query_reverse --sequence changed \\
        --out experiments/results/rerender_check_mesh_indoor_seed0
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from diffloc.config import compose_config, to_object
from diffloc.crossmodal.database import RenderedDatabase
from diffloc.crossmodal.synthesize import RGBDMap
from diffloc.eval.metrics import is_correct, pose_errors
from diffloc.eval.report_files import made_by_lines, write_report
from diffloc.features.local import XFeatExtractor
from diffloc.features.matching import LighterGlueMatcher
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.dataset import read_sequence
from diffloc.pipeline.crossmodal_config import CrossmodalTaskConfig, PointMapConfig
from diffloc.pipeline.crossmodal_replay import (
    recorded_evidence,
    recorded_validation,
    replay_validation,
)
from diffloc.pipeline.crossmodal_stage import (
    SequenceLocalization,
    build_rgbd_map,
    crossmodal_folder,
    scaled_images,
)
from diffloc.reloc.rendered import (
    RenderedCandidate,
    RenderedLocalizerConfig,
    localizer_networks,
    pose_evidence,
)
from diffloc.reloc.rerender import RERENDER_STAGES, Rerendered, rerender_candidate
from diffloc.reloc.validation import ValidationConfig
from diffloc.threads import intra_op_threads

RENDERED = ("pass 1", "pass 2")
"""The re-renders: at the recorded pose, at pass 1's pose."""
MEASURED = ("recorded", *RENDERED)
"""The evidence measured (the medians of the report)."""
PASSES = ("recorded", "pass 1", "rival kept", "second look", "pass 2")
"""The evidence validated: the run's, each re-render's, pass 1's with the run's rival verdict,
and that for the refused poses only, the accepted ones as recorded (the rule of
``task.rerender``, :mod:`diffloc.pipeline.crossmodal_rerender`)."""
MAX_ROT_DEG = 30.0
VERDICTS = ("right accepted", "wrong accepted", "right refused", "wrong refused", "no pose")


def load_map(
    dataset: Path, option: str, overrides: list[str]
) -> tuple[RGBDMap, CrossmodalTaskConfig, PinholeCamera, np.ndarray]:
    """The cached map stage's renderer (refused if the cache does not match the database's
    render settings, so it is never rebuilt), the task settings, the database camera and its
    (M,) real-image flags."""
    cfg = compose_config(["task=crossmodal", f"map={option}", *overrides])
    map_config, task = to_object(cfg.map), to_object(cfg.task)
    folder = crossmodal_folder(dataset) / option
    record = json.loads((folder / "database" / "rgbd_database.json").read_text())
    if isinstance(map_config, PointMapConfig):
        recorded = record["stage"]["key"]["config"]["sizes"]
        if asdict(map_config.sizes()) != recorded:
            raise SystemExit(
                f"{folder}/database was rendered with sizes {recorded}, the config gives "
                f"{asdict(map_config.sizes())}: pass e.g. --override map.rho_max=..."
            )
    map_record = folder / "map" / "crossmodal_map.json"
    before = map_record.read_text()
    rgbd_map, _ = build_rgbd_map(dataset, map_config, task.image_scale)
    if map_record.read_text() != before:
        raise SystemExit(f"{map_record}: the map stage was made again; it must be the cached one")
    db = RenderedDatabase.load(folder / "database" / "rgbd")
    return rgbd_map, task, db.camera, db.real.numpy()


def _checked_localizer(folder: Path, config: RenderedLocalizerConfig) -> None:
    """Stop unless ``config`` is the one the recorded run used (its ``localize.json`` key)."""
    record = json.loads((folder / "localize.json").read_text())
    recorded = record["stage"]["key"]["config"]["localizer"]
    if json.loads(json.dumps(asdict(config))) != recorded:
        raise SystemExit(f"{folder}: the localizer settings differ from the recorded run's")


def _errors(
    T_est: np.ndarray, T_gt: np.ndarray, found: np.ndarray, loose_m: float
) -> dict[str, np.ndarray]:
    """(Q,) position errors ``m``, rotation errors ``deg`` and ``right`` (within ``loose_m``
    and :data:`MAX_ROT_DEG`) of (Q, 4, 4) estimates against the truth."""
    errors = pose_errors(T_est, T_gt, found)
    return {
        "m": errors.translation_m,
        "deg": errors.rotation_deg,
        "right": is_correct(errors, loose_m, MAX_ROT_DEG),
    }


def _verdict(found: bool, accepted: bool, right: bool) -> str:
    if not found:
        return "no pose"
    return f"{'right' if right else 'wrong'} {'accepted' if accepted else 'refused'}"


def measure_sequence(
    dataset: Path,
    option: str,
    sequence: str,
    task: CrossmodalTaskConfig,
    rgbd_map: RGBDMap,
    render_camera: PinholeCamera,
    real: np.ndarray,
    networks: tuple[XFeatExtractor, LighterGlueMatcher],
) -> dict:
    """Per query with a recorded pose: the evidence, verdict and errors of each of
    :data:`PASSES`, and the re-render's time per step."""
    folder = crossmodal_folder(dataset) / option / f"localize_{sequence}"
    config = task.localizer_for(option)
    _checked_localizer(folder, config)
    loc = SequenceLocalization.load(folder / "localization.npz")
    validation, min_photometric_real = recorded_validation(folder)
    recorded = recorded_evidence(loc)
    accepted, failed = replay_validation(recorded, validation, real, min_photometric_real)
    if not np.array_equal(accepted, loc.accepted.astype(bool)):
        raise SystemExit(f"{folder}: the replayed verdicts differ from the run's")
    seq = read_sequence(dataset, sequence)
    camera = seq.camera.scaled(render_camera.width / seq.camera.width)
    T_gt = seq.T_wc[loc.frames].numpy()  # scoring only
    before = _errors(loc.T_wc, T_gt, loc.success.astype(bool), task.loose_m)
    queries = []
    for q in np.flatnonzero(loc.success).tolist():
        reference, evidence = recorded[q]
        _, tried = loc.candidates(q)
        image = scaled_images(seq, camera, [int(loc.frames[q])])[0]
        query = networks[0].extract(image)
        row = {
            "frame": int(loc.frames[q]),
            "reference": reference,
            "recorded": {
                "found": True,
                "inliers": evidence.num_inliers,
                "coverage": evidence.coverage,
                "plane_share": evidence.plane_share,
                "photometric": evidence.photometric,
                "failed": list(failed[q]),
                "accepted": bool(accepted[q]),
                "error_m": float(before["m"][q]),
                "error_deg": float(before["deg"][q]),
                "right": bool(before["right"][q]),
            },
        }
        T_wc = torch.from_numpy(loc.T_wc[q])
        for name in RENDERED:
            if T_wc is None:
                row[name] = {"found": False, "accepted": False, "failed": []}
                continue
            generator = torch.Generator().manual_seed(config.seed)
            result = rerender_candidate(
                rgbd_map, T_wc, render_camera, image, query, camera, networks, config, generator
            )
            row[name] = _pass_row(result, tried, reference, validation, real, min_photometric_real)
            row[name]["error_m"], row[name]["error_deg"], row[name]["right"] = _pass_errors(
                result, T_gt[q], task.loose_m
            )
            T_wc = result.candidate.T_wc if result.candidate.success else None
        row["rival kept"] = _rival_kept(row["pass 1"], row["recorded"])
        row["second look"] = row["recorded"] if row["recorded"]["accepted"] else row["rival kept"]
        queries.append(row)
    return {"sequence": sequence, "queries_total": len(loc.frames), "queries": queries}


def _pass_row(
    result: Rerendered,
    tried: tuple[RenderedCandidate, ...],
    reference: int,
    validation: ValidationConfig,
    real: np.ndarray,
    min_photometric_real: float | None,
) -> dict:
    """The evidence and verdict of one re-render (rivals: the recorded candidates)."""
    cand = result.candidate
    row = {
        "found": cand.success,
        "matches": cand.num_matches,
        "inliers": cand.num_inliers,
        "wall_ms": result.wall_ms,
        "cpu_ms": result.cpu_ms,
    }
    if not cand.success:
        return {**row, "accepted": False, "failed": []}
    evidence = pose_evidence(cand, (*tried, cand), result.photometric)
    accepted, failed = replay_validation(
        [(reference, evidence)], validation, real, min_photometric_real
    )
    return {
        **row,
        "coverage": cand.coverage,
        "plane_share": cand.plane_share,
        "photometric": result.photometric,
        "failed": list(failed[0]),
        "accepted": bool(accepted[0]),
    }


def _rival_kept(rendered: dict, recorded: dict) -> dict:
    """``rendered``'s verdict with its rival test replaced by the recorded one (each test
    fails on its own, so dropping ``rival`` equals validating without it)."""
    failed = [t for t in rendered["failed"] if t != "rival"]
    if rendered["found"] and "rival" in recorded["failed"]:
        failed.append("rival")
    return {**rendered, "failed": failed, "accepted": rendered["found"] and not failed}


def _pass_errors(
    result: Rerendered, T_gt: np.ndarray, loose_m: float
) -> tuple[float | None, float | None, bool]:
    if not result.candidate.success:
        return None, None, False
    e = _errors(result.candidate.T_wc.numpy()[None], T_gt[None], np.array([True]), loose_m)
    return float(e["m"][0]), float(e["deg"][0]), bool(e["right"][0])


def _median(values: list) -> float | None:
    clean = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.median(clean)) if clean else None


def summarise(measured: dict) -> dict:
    """Per pass the verdict counts and the tests refusing right poses; medians of the
    evidence, right and wrong recorded poses apart; median ms per re-render step."""
    rows = measured["queries"]
    summary = {"queries": measured["queries_total"], "poses": len(rows), "passes": {}}
    for name in PASSES:
        verdicts = [
            _verdict(r[name]["found"], r[name]["accepted"], r[name].get("right", False))
            for r in rows
        ]
        refusing: dict[str, int] = {}
        for r, v in zip(rows, verdicts, strict=True):
            if v == "right refused":
                for test in r[name]["failed"]:
                    refusing[test] = refusing.get(test, 0) + 1
        medians = {}
        for side, want in (("right", True), ("wrong", False)):
            group = [r for r in rows if r["recorded"]["right"] == want]
            medians[side] = {
                "n": len(group),
                **{
                    k: _median([r[name].get(k) for r in group if r[name]["found"]])
                    for k in ("inliers", "coverage", "photometric", "plane_share")
                },
            }
        summary["passes"][name] = {
            "verdicts": {v: verdicts.count(v) for v in VERDICTS},
            "right refused by": refusing,
            "medians": medians,
        }
    for name in RENDERED:
        timed = [r[name] for r in rows if "wall_ms" in r[name]]
        summary["passes"][name]["median_ms"] = {
            kind: {
                **{s: _median([t[kind][s] for t in timed]) for s in RERENDER_STAGES},
                "total": _median([sum(t[kind].values()) for t in timed]),
            }
            for kind in ("wall_ms", "cpu_ms")
        }
    return summary


def _fmt(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _query_cell(row: dict) -> str:
    """One pass of one query: verdict, failed tests, evidence and error."""
    if not row["found"]:
        return "no pose"
    verdict = _verdict(True, row["accepted"], row["right"])
    tests = ", ".join(row["failed"]) or "-"
    evidence = f"{row['inliers']} / {row['coverage']:.2f} / {_fmt(row['photometric'])}"
    return f"{verdict} ({tests}); {evidence}; {row['error_m']:.2f} m"


def markdown(report: dict) -> str:
    lines = [
        f"# Re-render at the found pose: `map={report['map']}`, {report['dataset']}",
        "",
        *made_by_lines(report["command"]),
        "Every recorded query with a pose (the best candidate succeeded) is validated five "
        "ways with the recorded thresholds "
        f"({report['validation']}): **recorded** (the run's evidence, replayed: equal to the "
        "run's verdicts), **pass 1** (the map rendered at the recorded pose, the query matched "
        "against it, PnP again; rivals: the recorded candidates at their distance to the new "
        "pose), **rival kept** (pass 1's evidence, the rival test the recorded verdict), "
        "**second look** (the recorded verdict of an accepted pose, "
        "rival kept for a refused one: the rule of `task.rerender`) and **pass 2** (rendered "
        "again at pass 1's pose). Right: within "
        f"{report['loose_m']:g} m / {MAX_ROT_DEG:g} deg of the truth (read for scoring only); "
        "a re-render that finds no PnP pose is `no pose`.",
        "",
        "| sequence | queries | poses | evidence | right acc. | wrong acc. | right ref. | "
        "wrong ref. | no pose | right refused by |",
        "|---|---:|---:|---|---:|---:|---:|---:|---:|---|",
    ]
    for seq, s in report["sequences"].items():
        for name in PASSES:
            p = s["summary"]["passes"][name]
            v = p["verdicts"]
            by = ", ".join(f"{k} {n}" for k, n in sorted(p["right refused by"].items())) or "-"
            lines.append(
                f"| {seq} | {s['summary']['queries']} | {s['summary']['poses']} | {name} | "
                + " | ".join(str(v[k]) for k in VERDICTS)
                + f" | {by} |"
            )
    for name in PASSES:
        summaries = [s["summary"] for s in report["sequences"].values()]
        total = {k: sum(x["passes"][name]["verdicts"][k] for x in summaries) for k in VERDICTS}
        lines.append(
            f"| all | {sum(x['queries'] for x in summaries)} | "
            f"{sum(x['poses'] for x in summaries)} | {name} | "
            + " | ".join(str(total[k]) for k in VERDICTS)
            + " | |"
        )
    lines += [
        "",
        "Medians of the evidence, recorded -> pass 1 -> pass 2, over the poses each pass found "
        "(right / wrong: the recorded pose's correctness):",
        "",
        "| sequence | poses | n | inliers | coverage | photometric | plane share |",
        "|---|---|---:|---|---|---|---|",
    ]
    for seq, s in report["sequences"].items():
        passes = s["summary"]["passes"]
        for side in ("right", "wrong"):
            cells = []
            for key, digits in (("inliers", 0), ("coverage", 3), ("photometric", 2)):
                cells.append(
                    " -> ".join(
                        _fmt(passes[n]["medians"][side][key], digits)
                        for n in ("recorded", *RENDERED)
                    )
                )
            cells.append(
                " -> ".join(_fmt(passes[n]["medians"][side]["plane_share"], 3) for n in MEASURED)
            )
            n = passes["recorded"]["medians"][side]["n"]
            lines.append(f"| {seq} | {side} | {n} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Cost of one re-render per query (pass 1; median wall / process CPU ms per step, "
        f"one torch thread; load average {report['load_start']} at the start, "
        f"{report['load_end']} at the end):",
        "",
        "| sequence | " + " | ".join(RERENDER_STAGES) + " | total |",
        "|---|" + "---:|" * (len(RERENDER_STAGES) + 1),
    ]
    for seq, s in report["sequences"].items():
        ms = s["summary"]["passes"]["pass 1"]["median_ms"]
        cells = [
            f"{_fmt(ms['wall_ms'][k], 0)} / {_fmt(ms['cpu_ms'][k], 0)}"
            for k in (*RERENDER_STAGES, "total")
        ]
        lines.append(f"| {seq} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Every wrong recorded pose and every pose whose verdict a pass changes (tests failed; "
        "inliers / coverage / photometric; error of the pose in m):",
        "",
        "| sequence | frame | " + " | ".join(PASSES) + " |",
        "|---|---:|" + "---|" * len(PASSES),
    ]
    for seq, s in report["sequences"].items():
        for r in s["queries"]:
            verdicts = {r[n]["accepted"] for n in PASSES if r[n]["found"]}
            if r["recorded"]["right"] and len(verdicts) == 1 and all(r[n]["found"] for n in PASSES):
                continue
            lines.append(
                f"| {seq} | {r['frame']} | " + " | ".join(_query_cell(r[n]) for n in PASSES) + " |"
            )
    lines += [
        "",
        f"Wall time of the whole script: {report['wall_s']:.0f} s "
        f"(CPU {report['cpu_s']:.0f} s). Per-query rows: the JSON beside this file.",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--map", choices=("mesh", "tls", "cloud"), required=True)
    parser.add_argument("--sequence", action="append", required=True)
    parser.add_argument(
        "--override", action="append", default=[], help="config override, e.g. map.rho_max=8"
    )
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args()
    start, start_cpu = time.perf_counter(), time.process_time()
    load_start = [round(x, 2) for x in os.getloadavg()]
    command = "OMP_NUM_THREADS=1 PYTHONPATH=. python3 " + shlex.join(sys.argv)
    with intra_op_threads(args.threads), torch.no_grad():
        rgbd_map, task, render_camera, real = load_map(args.dataset, args.map, args.override)
        networks = localizer_networks(task.localizer_for(args.map))
        sequences = {}
        for name in args.sequence:
            measured = measure_sequence(
                args.dataset, args.map, name, task, rgbd_map, render_camera, real, networks
            )
            sequences[name] = {"summary": summarise(measured), "queries": measured["queries"]}
            print(name, json.dumps(sequences[name]["summary"]["passes"], default=str)[:600])
    validation = asdict(task.localizer_for(args.map).validation)
    shown = ("theta_in", "min_coverage", "ambiguity_ratio", "min_photometric", "max_plane_share")
    report = {
        "command": command,
        "dataset": str(args.dataset),
        "map": args.map,
        "overrides": args.override,
        "loose_m": task.loose_m,
        "validation": ", ".join(f"{k} {validation[k]}" for k in shown),
        "load_start": load_start,
        "load_end": [round(x, 2) for x in os.getloadavg()],
        "wall_s": time.perf_counter() - start,
        "cpu_s": time.process_time() - start_cpu,
        "sequences": sequences,
    }
    md, _ = write_report(args.out, markdown(report), report)
    print(md.read_text())


if __name__ == "__main__":
    main()
