"""Score a finished relocalisation run again under other pose-validation thresholds.

Pose validation (:mod:`diffloc.reloc.validation`) reads only what the relocalisation stage
records per query in ``<sequence>/queries.json``: whether a pose was found, its position, the
timestamp and every candidate's inliers, matches, coverage and distance to the chosen pose.
So a change of ``reloc.validation`` needs no new relocalisation: :func:`revalidate_run` replays
the validator over those records and writes the job again, with the relocalised poses, errors
and timings unchanged and the verdicts and the figures that depend on them (recall,
``recall_at``, precision, mATE, accepted) recomputed by the same metric functions as the
stage. ``seed1_rule`` is replayed too (seed 1's tests under the new thresholds).

What is written into ``dst``: ``results.json`` (with ``revalidated_from`` and the validation
settings used in its ``config``), ``results.md``, per sequence ``queries.json`` with the new
verdicts, ``estimates.tum`` (the accepted poses, taken from the source run's ``found.tum``,
which holds every pose it found; a run of an older diffloc has only ``estimates.tum``, the poses
it accepted, and the new accepted set must then lie within it), ``found.tum`` where the source
has one, and ``groundtruth.tum``; and the source's ``.hydra`` folder, so held-out reports group
the job as before. Plots are not redrawn.

Usage (on the folder of a finished run)::

    revalidate_run("runs/heldout/0", "runs/heldout_v2/0", ValidationConfig())
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import asdict
from pathlib import Path

import numpy as np

from diffloc.eval.metrics import PoseErrors, is_correct
from diffloc.eval.tables import markdown_table
from diffloc.io.atomic import atomic_write_text
from diffloc.pipeline.reloc_stage import RESULT_COLUMNS, table_row, verdict_figures
from diffloc.reloc.validation import PoseEvidence, PoseValidator, ValidationConfig

__all__ = ["record_errors", "replay_validation", "revalidate_run"]


def replay_validation(records: list[dict], config: ValidationConfig) -> np.ndarray:
    """(Q,) bool verdicts of ``config`` over one sequence's ``queries.json`` records, in order.

    Raises:
        ValueError: a found query without the evidence the validation reads.
    """
    validator = PoseValidator(config)
    return np.array(
        [
            validator.validate_evidence(PoseEvidence.from_record(r), float(r["timestamp"]))
            for r in records
        ],
        dtype=bool,
    )


def record_errors(records: list[dict], accepted: np.ndarray) -> PoseErrors:
    """The pose errors a ``queries.json`` recorded, with ``accepted`` (Q,) as the localised
    queries (the verdicts of some validation)."""

    def column(key: str) -> np.ndarray:
        return np.array([math.nan if r[key] is None else r[key] for r in records], np.float64)

    return PoseErrors(column("translation_error_m"), column("rotation_error_deg"), accepted)


def _accepted_tum_lines(source: Path, records: list[dict], accepted: np.ndarray) -> str:
    """The header and the lines of the newly accepted queries of the source's ``found.tum``
    (or, from an older run, ``estimates.tum``)."""
    lines = [ln for ln in source.read_text().splitlines() if ln]
    out = [ln for ln in lines if ln.startswith("#")]
    by_time = {round(float(ln.split()[0]), 6): ln for ln in lines if not ln.startswith("#")}
    for record, keep in zip(records, accepted, strict=True):
        if not keep:
            continue
        line = by_time.get(round(float(record["timestamp"]), 6))
        if line is None:
            raise ValueError(
                f"{source}: no pose at t={record['timestamp']}, which the new validation "
                "accepts; the source run (of an older diffloc, without found.tum) did not accept "
                "it, so relocalise again instead"
            )
        out.append(line)
    return "\n".join(out) + ("\n" if out else "")


def revalidate_run(src: str | Path, dst: str | Path, config: ValidationConfig) -> dict:
    """Write the relocalisation job ``src`` again into ``dst`` under ``config`` (module doc).

    Args:
        src: a finished job folder (``results.json``, ``<sequence>/queries.json``).
        dst: the folder to write (must not be ``src``).
        config: the validation thresholds to apply.

    Returns:
        The new ``results.json`` content.

    Raises:
        FileNotFoundError: a missing ``results.json`` or ``queries.json``.
        ValueError: ``dst`` equal to ``src``, records without the evidence the validation
            reads, or a newly accepted pose the source run did not write.
    """
    src, dst = Path(src), Path(dst)
    if src.resolve() == dst.resolve():
        raise ValueError(f"revalidate into a new folder, not the source {src}")
    results_path = src / "results.json"
    if not results_path.is_file():
        raise FileNotFoundError(f"{results_path} is missing: not a finished relocalisation job")
    results = json.loads(results_path.read_text())
    max_trans, max_rot = results["config"]["max_trans_m"], results["config"]["max_rot_deg"]
    sequences, rows = {}, []
    for name, entry in results["sequences"].items():
        records = json.loads((src / name / "queries.json").read_text())
        accepted = replay_validation(records, config)
        seed1 = replay_validation(records, config.seed1_rule())
        verified, seed1_errors = record_errors(records, accepted), record_errors(records, seed1)
        sequences[name] = {**entry, **verdict_figures(verified, seed1_errors, max_trans, max_rot)}
        out = dst / name
        out.mkdir(parents=True, exist_ok=True)
        correct = is_correct(verified, max_trans)
        for record, keep, keep1, right in zip(records, accepted, seed1, correct, strict=True):
            record["accepted"], record["accepted_seed1"] = bool(keep), bool(keep1)
            record["correct"] = bool(right)
        atomic_write_text(out / "queries.json", json.dumps(records, indent=1) + "\n")
        found = src / name / "found.tum"
        source = found if found.is_file() else src / name / "estimates.tum"
        atomic_write_text(out / "estimates.tum", _accepted_tum_lines(source, records, accepted))
        if found.is_file():
            shutil.copyfile(found, out / "found.tum")
        shutil.copyfile(src / name / "groundtruth.tum", out / "groundtruth.tum")
        rows.append(table_row(name, sequences[name]))
    headline = sequences.get("query_same") or next(iter(sequences.values()))
    new = {
        **results,
        "sequences": sequences,
        **{key: headline[key] for key in ("recall", "mATE_m", "queries", "median_reloc_ms")},
        "config": {**results["config"], "validation": asdict(config)},
        "revalidated_from": str(src),
    }
    new["table"] = markdown_table(rows, RESULT_COLUMNS)
    if (src / ".hydra").is_dir():
        shutil.copytree(src / ".hydra", dst / ".hydra", dirs_exist_ok=True)
    atomic_write_text(dst / "results.md", new["table"] + "\n")
    atomic_write_text(dst / "results.json", json.dumps(new, indent=2) + "\n")
    return new
