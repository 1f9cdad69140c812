"""The relocalisation stage: query sequences against a visual database, metrics and plots.

``relocalize_dataset`` loads the database of one noise level (optimised or as built), fits or
reuses the keyframe retriever, relocalises every query of each query sequence with
:class:`~diffloc.reloc.hierarchical.HierarchicalRelocalizer`, validates the poses, and writes
into ``out``:

- ``<sequence>/estimates.tum`` (accepted poses, TUM format for evo), ``found.tum`` (every
  found pose, accepted or not: what a replay of other validation settings reads),
  ``groundtruth.tum``,
  ``queries.json`` (per query: found, accepted by the configured validation and by seed 1's
  rule, correct, the found position and rotation, inliers, the photometric consistency of the
  found pose where it passed the inlier test (:mod:`diffloc.reloc.photometric`, null for no
  overlap), errors, stage times and every candidate's inliers, matches, coverage and distance
  to the chosen pose);
- ``<sequence>/precision_recall.png`` (precision and recall of every found pose as the inlier
  threshold is swept, with the operating points of pose validation and of seed 1's rule),
  ``trajectory.png``, ``errors.png`` (cumulative position error of the found and of the
  accepted poses, log x axis);
- ``results.md`` (a Markdown table) and ``results.json`` with, per sequence, ``recall``
  (verified poses within ``max_trans_m``), ``recall_at`` (within 0.1 / 0.3 / 1.0 m),
  ``precision`` (the share of verified poses within ``max_trans_m``), ``seed1_rule`` (recall
  and precision under seed 1's tests alone), ``nearest_db_pose`` (median / p90 distance and
  angle from each query's true pose to the nearest database keyframe's true pose, a scoring
  figure), ``mATE_m`` (mean error of the verified poses),
  ``queries``, ``median_reloc_ms`` (per query, local feature extraction and the global
  descriptor network excluded) and ``median_total_ms`` (all included).
"""

from __future__ import annotations

import hashlib
import json
import math
import statistics
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from diffloc.database.database import VisualDatabase
from diffloc.eval.metrics import (
    PoseErrors,
    is_correct,
    localization_metrics,
    pose_errors,
    precision,
    precision_recall_curve,
    recall,
    write_localized_tum,
)
from diffloc.eval.plots import plot_error_cdf, plot_precision_recall, plot_trajectory_topdown
from diffloc.eval.tables import Column, markdown_table
from diffloc.features.local import Features, make_extractor
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.pose_offsets import nearest_pose_offsets, offset_summary
from diffloc.io.atomic import atomic_write_text
from diffloc.io.dataset import read_sequence
from diffloc.io.identity import identity
from diffloc.io.trajectory import write_tum
from diffloc.maps.surfel import SurfelMap
from diffloc.pipeline.config_record import config_record
from diffloc.pipeline.database_select import (
    UPDATED_PREFIX,
    SelectedDatabase,
    check_database_name,
    keyframe_image_reader,
    keyframe_images,
    keyframe_true_poses,
    select_database,
)
from diffloc.pipeline.database_stage import DatabaseConfig
from diffloc.pipeline.hints import Command, StaleStageError
from diffloc.pipeline.stage import LockLevel, StageSummary, open_stage, stage_key
from diffloc.progress import progress
from diffloc.reloc.hierarchical import (
    Candidate,
    HierarchicalRelocalizer,
    RelocConfig,
    RelocResult,
)
from diffloc.reloc.photometric import PhotometricCheck, PhotometricConfig
from diffloc.reloc.repetition import RepeatedShift, RepetitionConfig, repeated_shift
from diffloc.reloc.retrieval import (
    BowConfig,
    BowRetriever,
    NetVLADConfig,
    NetVLADRetriever,
    load_retriever,
)
from diffloc.reloc.uniqueness import Uniqueness, UniquenessConfig, pose_uniqueness
from diffloc.reloc.validation import PoseValidator, ValidationConfig

__all__ = ["RelocStageConfig", "RelocalizeSummary", "RetrieverSummary", "relocalize_dataset"]


@dataclass(frozen=True)
class RetrieverSummary(StageSummary):
    """The record summary of a fitted retriever (``<retriever_root>/<name>.json``).

    Attributes:
        config: ``{"settings": the retriever's settings, "keyframe_sources": [[sequence,
            frame], ...] of the keyframes it ranks}``.
    """

    config: dict


@dataclass(frozen=True)
class RelocalizeSummary(StageSummary):
    """The record summary of a relocalisation run (``<out>/relocalize.json``); the figures
    are in its ``results.json`` (what :func:`relocalize_dataset` returns).

    Attributes:
        sequences: the relocalised sequences, one output folder each.
    """

    sequences: list[str]


EXTRACTION_STAGES = ("features", "global_descriptor")
"""Stages counted as feature extraction (left out of ``median_reloc_ms``)."""

RECALL_THRESHOLDS_M = (0.1, 0.3, 1.0)
"""Position thresholds of the reported recalls (``recall_at``), metres."""


@dataclass
class RelocStageConfig:
    """The relocalisation stage (the Hydra ``reloc`` node).

    Attributes:
        sequences: query sequences to relocalise.
        database: ``"optimized"`` (after ``task=optimize_db``), ``"database"`` (as built) or
            ``"updated_<sequence>"`` (after ``task=update_db task.sequence=<sequence>``).
        retriever: the keyframe retriever's settings, :class:`NetVLADConfig` or
            :class:`BowConfig`: the type picks the retriever (``retriever=netvlad|bow`` on the
            command line, whose ``_target_`` is the class).
        query_stride: use every n-th query frame.
        max_trans_m: position threshold of a correct pose (seed 1: 0.3 m).
        max_rot_deg: rotation threshold of ``recall_rot`` (degrees).
        method: the hierarchical relocaliser.
        validation: pose validation thresholds.
        photometric: how the photometric consistency of a found pose is measured (every pose
            that passes the inlier test is measured, so a changed
            ``validation.min_photometric`` can be replayed by ``experiments/revalidate.py``).
        repetition: how the repeated structure under a found pose is measured
            (:mod:`diffloc.reloc.repetition`); it is measured and recorded like
            ``photometric`` where ``validation.max_repeated`` is set or
            ``record_repetition`` is true.
        record_repetition: measure and record the repetition even when the validation does
            not test it (to replay thresholds; about 0.1 s CPU per query outdoors).
        uniqueness: how the uniqueness of a found pose is measured
            (:mod:`diffloc.reloc.uniqueness`); measured and recorded like ``photometric``
            where ``validation.uniqueness_ratio`` is set or ``record_uniqueness`` is true.
        record_uniqueness: measure and record the uniqueness even when the validation does
            not test it (to replay thresholds).
    """

    sequences: list[str] = field(default_factory=lambda: ["query_same", "changed"])
    database: str = "optimized"
    retriever: Any = field(default_factory=NetVLADConfig)
    query_stride: int = 1
    max_trans_m: float = 0.3
    max_rot_deg: float = 5.0
    method: RelocConfig = field(default_factory=RelocConfig)
    validation: ValidationConfig = field(default_factory=ValidationConfig)
    photometric: PhotometricConfig = field(default_factory=PhotometricConfig)
    repetition: RepetitionConfig = field(default_factory=RepetitionConfig)
    record_repetition: bool = False
    uniqueness: UniquenessConfig = field(default_factory=UniquenessConfig)
    record_uniqueness: bool = False

    def __post_init__(self) -> None:
        check_database_name(self.database)
        if not isinstance(self.retriever, NetVLADConfig | BowConfig):
            raise ValueError(
                "reloc.retriever must be a NetVLADConfig or BowConfig (on the command line "
                f"retriever=netvlad|bow), got {self.retriever!r}"
            )
        if self.query_stride < 1:
            raise ValueError(f"query_stride must be >= 1, got {self.query_stride}")
        for name in ("max_trans_m", "max_rot_deg"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"reloc.{name} must be a finite number > 0, got {value!r}")
        if self.validation.max_repeated is not None and self.method.points == "naive":
            raise ValueError(
                "reloc.validation.max_repeated needs the inliers' map points, which "
                "reloc.method.points=naive does not have: use F or FN, or set "
                "reloc.validation.max_repeated=null"
            )
        if not self.sequences or any(not s or "/" in s for s in self.sequences):
            raise ValueError(f"reloc.sequences must be sequence names, got {self.sequences!r}")


def _load_database(
    dataset: Path, db_cfg: DatabaseConfig, which: str
) -> tuple[VisualDatabase, SelectedDatabase]:
    selected = select_database(dataset, db_cfg, which)
    return VisualDatabase.load(selected.path), selected


def _retriever_inputs(
    dataset: Path, cfg: RelocStageConfig, db: VisualDatabase, selected: SelectedDatabase
) -> dict:
    """What a retriever is fitted on: the keyframe images' sequences (NetVLAD) or the
    keyframes' local descriptors (bag of words)."""
    if isinstance(cfg.retriever, BowConfig):
        digest = hashlib.sha256(db.keypoint_offsets.numpy().tobytes())
        digest.update(db.descriptors.contiguous().numpy().tobytes())
        return {"descriptors": {"kind": "arrays", "sha256": digest.hexdigest()}}
    names = dict.fromkeys(name for name, _ in selected.keyframe_sources)
    return {f"sequence:{name}": identity(dataset / name) for name in names}


def _retriever(
    dataset: Path,
    cfg: RelocStageConfig,
    db: VisualDatabase,
    selected: SelectedDatabase,
) -> NetVLADRetriever | BowRetriever:
    """Load the cached retriever of this database's keyframes (same settings, same images or
    descriptors: :mod:`diffloc.pipeline.stage`), or fit and cache it."""
    name = f"retriever_{cfg.retriever.kind}"
    settings = asdict(cfg.retriever)
    config = {"settings": settings, "keyframe_sources": selected.keyframe_sources}
    command = Command("relocalize", (f"dataset={dataset}",))
    level = LockLevel.UPDATED if selected.name.startswith(UPDATED_PREFIX) else LockLevel.DATABASE
    with open_stage(selected.retriever_root, name, command, level) as stage:
        key = stage_key(config, _retriever_inputs(dataset, cfg, db, selected))
        if stage.reusable(key, RetrieverSummary) is not None:
            retriever = load_retriever(selected.retriever_root / name)
        else:
            if isinstance(cfg.retriever, BowConfig):
                slices = [db.keyframe_slice(k) for k in range(db.num_keyframes)]
                retriever = BowRetriever.fit([db.descriptors[s] for s in slices], cfg.retriever)
            else:
                images = keyframe_images(dataset, selected.keyframe_sources)
                retriever = NetVLADRetriever.fit(images, cfg.retriever)
            retriever.save(stage.workdir() / name)
            stage.commit(key, RetrieverSummary(config), [name])
    if retriever.num_keyframes != db.num_keyframes:
        raise StaleStageError(
            f"{selected.retriever_root / name} ranks {retriever.num_keyframes} keyframes but "
            f"{selected.path} has {db.num_keyframes}",
            command,
        )
    return retriever


@dataclass
class _SequenceRun:
    """Per-query outcomes of one sequence.

    ``accepted`` is the verdict of the configured validation, ``accepted_seed1`` that of seed
    1's own tests (inlier count and distance to the previous inlier pose) alone.
    """

    timestamps: np.ndarray
    T_wc_true: np.ndarray
    T_wc_est: np.ndarray
    found: np.ndarray
    accepted: np.ndarray
    accepted_seed1: np.ndarray
    inliers: np.ndarray
    photometric: list[float | None]
    repetition: list[RepeatedShift | None]
    uniqueness: list[Uniqueness | None]
    timings: list[dict[str, float]]
    candidates: list[list[dict]]


def _relocalize_sequence(
    dataset: Path,
    name: str,
    cfg: RelocStageConfig,
    extractor,
    relocalizer: HierarchicalRelocalizer,
    photometric: PhotometricCheck,
    show_progress: bool,
) -> _SequenceRun:
    sequence = read_sequence(dataset, name)
    frames = list(range(0, len(sequence), cfg.query_stride))
    validator = PoseValidator(cfg.validation)
    seed1 = PoseValidator(cfg.validation.seed1_rule())
    estimates, found, accepted, accepted_seed1, inliers = [], [], [], [], []
    scores, repeats, uniques, timings, candidates = [], [], [], [], []
    for i in progress(frames, f"relocalise {name}", show_progress):
        image = sequence.load_rgb(i)
        start = time.perf_counter()
        features = extractor.extract(image)
        extract_ms = (time.perf_counter() - start) * 1e3
        result: RelocResult = relocalizer.relocalize(image, features, sequence.camera)
        timestamp = float(sequence.timestamps[i])
        score, repeat, unique = None, None, None
        if result.found and result.num_inliers >= cfg.validation.theta_in:
            start = time.perf_counter()
            score = photometric.score(image, result.T_wc, sequence.camera, result.canonical)
            result.timings_ms["photometric"] = (time.perf_counter() - start) * 1e3
            if cfg.record_repetition or cfg.validation.max_repeated is not None:
                start = time.perf_counter()
                repeat = _repetition(result, relocalizer.db, cfg.repetition)
                result.timings_ms["repetition"] = (time.perf_counter() - start) * 1e3
            if cfg.record_uniqueness or cfg.validation.uniqueness_ratio is not None:
                start = time.perf_counter()
                unique = _uniqueness(result, features, sequence.camera, relocalizer, cfg)
                result.timings_ms["uniqueness"] = (time.perf_counter() - start) * 1e3
        scores.append(score)
        repeats.append(repeat)
        uniques.append(unique)
        accepted.append(
            result.found and validator.validate_result(result, timestamp, score, repeat, unique)
        )
        accepted_seed1.append(result.found and seed1.validate_result(result, timestamp))
        estimates.append(result.T_wc if result.found else torch.full((4, 4), math.nan))
        found.append(result.found)
        inliers.append(result.num_inliers)
        timings.append({"features": extract_ms, **result.timings_ms})
        candidates.append([_candidate_entry(c, result.T_wc) for c in result.candidates])
    return _SequenceRun(
        timestamps=np.asarray(sequence.timestamps)[frames],
        T_wc_true=sequence.T_wc[frames].double().numpy(),
        T_wc_est=torch.stack(estimates).double().numpy(),
        found=np.array(found),
        accepted=np.array(accepted),
        accepted_seed1=np.array(accepted_seed1),
        inliers=np.array(inliers, dtype=np.float64),
        photometric=scores,
        repetition=repeats,
        uniqueness=uniques,
        timings=timings,
        candidates=candidates,
    )


def _repetition(
    result: RelocResult, db: VisualDatabase, config: RepetitionConfig
) -> RepeatedShift | None:
    """The repeated structure under the best candidate's inliers (``None`` for the ``naive``
    method, whose inliers are not map points)."""
    matches = result.best.inlier_matches
    if matches is None:
        return None
    return repeated_shift(
        matches[:, 1],
        db.point_positions,
        db.point_descriptors,
        db.metric,
        config,
    )


def _uniqueness(
    result: RelocResult,
    features: Features,
    camera: PinholeCamera,
    relocalizer: HierarchicalRelocalizer,
    cfg: RelocStageConfig,
) -> Uniqueness:
    """The uniqueness of the best candidate's pose against its repetition shifts and the
    other candidates (:func:`~diffloc.reloc.uniqueness.pose_uniqueness`)."""
    best = result.best
    rivals = [c.T_wc for c in result.candidates if c is not best]
    db = relocalizer.db
    return pose_uniqueness(
        best.T_wc,
        torch.stack(rivals) if rivals else torch.zeros(0, 4, 4, dtype=torch.float64),
        best.inlier_matches,
        features,
        camera,
        relocalizer.point_positions,
        db.point_descriptors,
        db.metric,
        cfg.uniqueness,
        cfg.repetition,
        cfg.method.refine,
    )


def _candidate_entry(candidate: Candidate, T_wc_best: torch.Tensor) -> dict:
    """A candidate's figures for ``queries.json``, with its distance to the chosen pose."""
    distance = torch.linalg.vector_norm(candidate.T_wc[:3, 3] - T_wc_best[:3, 3])
    return {
        "canonical": candidate.canonical,
        "inliers": candidate.num_inliers,
        "matches": candidate.num_matches,
        "coverage": round(candidate.coverage, 4),
        "distance_to_chosen_m": round(float(distance), 4),
        "position_sigma_m": finite_or_none(round(candidate.position_sigma_m, 5)),
        "plane_share": finite_or_none(round(candidate.plane_share, 4)),
    }


def _report_sequence(
    run: _SequenceRun,
    cfg: RelocStageConfig,
    out: Path,
    final: Path,
    name: str,
    T_wc_db_true: torch.Tensor,
) -> dict:
    """Metrics, TUM files and plots of one sequence; returns its results entry.

    The files are written into ``out`` (the stage's work folder); the entry names them where
    the commit puts them, in ``final``. ``T_wc_db_true`` (K, 4, 4) are the true poses of the
    database keyframes, read for scoring only: how far each query lies from the nearest of them.
    """
    out.mkdir(parents=True, exist_ok=True)
    verified = pose_errors(run.T_wc_est, run.T_wc_true, run.accepted)
    seed1 = pose_errors(run.T_wc_est, run.T_wc_true, run.accepted_seed1)
    raw = pose_errors(run.T_wc_est, run.T_wc_true, run.found)
    reloc_ms = [sum(v for k, v in t.items() if k not in EXTRACTION_STAGES) for t in run.timings]
    total_ms = [sum(t.values()) for t in run.timings]
    metrics = localization_metrics(verified, reloc_ms, cfg.max_trans_m)
    correct = is_correct(verified, cfg.max_trans_m)
    offsets = offset_summary(
        *nearest_pose_offsets(torch.from_numpy(run.T_wc_true), T_wc_db_true.double())
    )
    write_localized_tum(out / "estimates.tum", run.timestamps, run.T_wc_est, run.accepted)
    write_localized_tum(out / "found.tum", run.timestamps, run.T_wc_est, run.found)
    write_tum(out / "groundtruth.tum", run.timestamps, torch.from_numpy(run.T_wc_true))
    seed1_recall = recall(seed1, cfg.max_trans_m)
    seed1_precision = precision(seed1, cfg.max_trans_m)
    plots = {
        "precision_recall": plot_precision_recall(
            {
                "every found pose, by inlier count": precision_recall_curve(
                    run.inliers, raw, None, cfg.max_trans_m
                )
            },
            out / "precision_recall.png",
            operating_points={
                "pose validation": (metrics.recall, metrics.precision),
                "seed 1's rule": (seed1_recall, seed1_precision),
            },
            title=f"{name}: inlier threshold swept, and the validated poses",
        ),
        "trajectory": plot_trajectory_topdown(
            run.T_wc_true,
            np.where(run.found[:, None, None], run.T_wc_est, np.nan),
            run.accepted,
            out / "trajectory.png",
            title=f"{name}: accepted (green) and rejected (red) poses",
        ),
        "errors": plot_error_cdf(
            {"every found pose": raw.translation_m, "accepted": verified.translation_m},
            out / "errors.png",
            threshold=cfg.max_trans_m,
            title=f"{name}: cumulative position error",
        ),
    }
    stages = sorted({k for t in run.timings for k in t})
    per_query = [
        {
            "timestamp": float(run.timestamps[q]),
            "found": bool(run.found[q]),
            "accepted": bool(run.accepted[q]),
            "accepted_seed1": bool(run.accepted_seed1[q]),
            "correct": bool(correct[q]),
            "position_m": (
                [round(float(x), 6) for x in run.T_wc_est[q, :3, 3]] if run.found[q] else None
            ),
            "rotation_wc": (
                [[round(float(x), 9) for x in row] for row in run.T_wc_est[q, :3, :3]]
                if run.found[q]
                else None
            ),
            "inliers": int(run.inliers[q]),
            **(
                {}
                if run.photometric[q] is None
                else {"photometric": finite_or_none(round(run.photometric[q], 4))}
            ),
            **(
                {}
                if run.repetition[q] is None
                else {
                    "repetition": {
                        "support": run.repetition[q].support,
                        "shift_m": round(run.repetition[q].shift_m, 4),
                    }
                }
            ),
            **(
                {}
                if run.uniqueness[q] is None
                else {
                    "uniqueness": {
                        "own": run.uniqueness[q].own,
                        "own_visible": run.uniqueness[q].own_visible,
                        "rival": run.uniqueness[q].rival,
                        "rival_visible": run.uniqueness[q].rival_visible,
                        "ratio": finite_or_none(round(run.uniqueness[q].ratio, 4)),
                        "rival_distance_m": round(run.uniqueness[q].rival_distance_m, 4),
                        "alternatives": run.uniqueness[q].alternatives,
                    }
                }
            ),
            "translation_error_m": finite_or_none(raw.translation_m[q]),
            "rotation_error_deg": finite_or_none(raw.rotation_deg[q]),
            "timings_ms": {k: round(v, 3) for k, v in run.timings[q].items()},
            "candidates": run.candidates[q],
        }
        for q in range(len(run.found))
    ]
    atomic_write_text(out / "queries.json", json.dumps(per_query, indent=1) + "\n")
    return {
        **verdict_figures(verified, seed1, cfg.max_trans_m, cfg.max_rot_deg),
        "nearest_db_pose": offsets,
        "queries": metrics.queries,
        "median_reloc_ms": finite_or_none(metrics.median_reloc_ms),
        "median_total_ms": statistics.median(total_ms) if total_ms else None,
        "found": int(run.found.sum()),
        "median_stage_ms": {
            s: statistics.median(t.get(s, 0.0) for t in run.timings) for s in stages
        },
        "plots": {k: str(final / Path(v).name) for k, v in plots.items()},
        "estimates": str(final / "estimates.tum"),
    }


RESULT_COLUMNS = [
    Column("sequence"),
    Column("queries"),
    Column("db_distance", "to nearest db pose: median / p90 [m]"),
    Column("db_angle", "angle: median / p90 [deg]"),
    *[
        Column(f"recall_{t:.1f}", f"recall@{t:g}m [%]", ".1f", scale=100)
        for t in RECALL_THRESHOLDS_M
    ],
    Column("precision", "precision [%]", ".1f", scale=100),
    Column("seed1", "seed 1's rule: recall / precision [%]"),
    Column("mATE_m", "mATE [cm]", ".1f", scale=100),
    Column("median_reloc_ms", "reloc [ms]", ".1f"),
    Column("median_total_ms", "with features [ms]", ".1f"),
]
"""The columns of ``results.md``; mATE is over all accepted poses, right or wrong."""


def table_row(name: str, entry: dict) -> dict:
    """One ``results.md`` row of a sequence's results entry."""
    near, rule = entry["nearest_db_pose"], entry["seed1_rule"]
    rule_precision = "-" if rule["precision"] is None else f"{100 * rule['precision']:.1f}"
    return {
        "sequence": name,
        **entry,
        **{f"recall_{k}": v for k, v in entry["recall_at"].items()},
        "db_distance": f"{near['distance_median_m']:.2f} / {near['distance_p90_m']:.2f}",
        "db_angle": f"{near['angle_median_deg']:.1f} / {near['angle_p90_deg']:.1f}",
        "seed1": f"{100 * rule['recall']:.1f} / {rule_precision}",
    }


def finite_or_none(x: float) -> float | None:
    """``x`` as a float, ``None`` where it is NaN or infinite (JSON has no NaN)."""
    return float(x) if math.isfinite(x) else None


def verdict_figures(
    verified: PoseErrors, seed1: PoseErrors, max_trans_m: float, max_rot_deg: float
) -> dict:
    """The figures of a sequence's results entry that follow from the validation verdicts.

    Args:
        verified: errors with ``localized`` = accepted by the configured validation.
        seed1: errors with ``localized`` = accepted by seed 1's rule alone.
        max_trans_m: position threshold of a correct pose.
        max_rot_deg: rotation threshold of ``recall_rot``.

    Returns:
        ``recall``, ``recall_at``, ``precision``, ``seed1_rule``, ``mATE_m``, ``recall_rot``
        and ``accepted``.
    """
    metrics = localization_metrics(verified, None, max_trans_m)
    return {
        "recall": metrics.recall,
        "recall_at": {f"{t:.1f}": recall(verified, t) for t in RECALL_THRESHOLDS_M},
        "precision": finite_or_none(metrics.precision),
        "seed1_rule": {
            "accepted": int(seed1.localized.sum()),
            "recall": recall(seed1, max_trans_m),
            "precision": finite_or_none(precision(seed1, max_trans_m)),
        },
        "mATE_m": finite_or_none(metrics.mATE_m),
        "recall_rot": localization_metrics(verified, None, max_trans_m, max_rot_deg).recall,
        "accepted": int(verified.localized.sum()),
    }


def relocalize_dataset(
    dataset: str | Path,
    db_cfg: DatabaseConfig,
    cfg: RelocStageConfig,
    out: str | Path,
    surfel_map: str | Path | None = None,
    show_progress: bool = True,
) -> dict:
    """Relocalise the query sequences of ``dataset`` and write metrics and plots (module doc).

    The results commit as a whole (:func:`~diffloc.pipeline.stage.open_stage`): the sequence
    folders, ``results.md``, ``results.json`` and the record ``relocalize.json`` appear
    together, and a run that fails or is killed leaves the folder's previous results intact.

    Args:
        dataset: the dataset folder (with ``db/sigma_<s>/`` from the database stages).
        db_cfg: the database settings (noise level, local features).
        cfg: the stage settings.
        out: the folder to write results into.
        surfel_map: the surfel map PLY (default ``<dataset>/map/surfel_map.ply``): the
            ``naive`` method's surfel centres and the photometric check's depth renders.
        show_progress: progress bars.

    Returns:
        The ``results.json`` content.

    Raises:
        FileNotFoundError: a missing database, surfel map or sequence.
    """
    dataset, out = Path(dataset), Path(out)
    missing = [name for name in cfg.sequences if not (dataset / name).is_dir()]
    if missing:
        raise FileNotFoundError(
            f"reloc.sequences names {missing}, which {dataset} does not hold; its sequences are "
            f"{sorted(p.name for p in dataset.iterdir() if (p / 'calib.yaml').is_file())}"
        )
    db, selected = _load_database(dataset, db_cfg, cfg.database)
    retriever = _retriever(dataset, cfg, db, selected)
    surfels = SurfelMap.load(Path(surfel_map) if surfel_map else dataset / "map" / "surfel_map.ply")
    centers = surfels.centers if cfg.method.points == "naive" else None
    relocalizer = HierarchicalRelocalizer(db, retriever, cfg.method, centers)
    photometric = PhotometricCheck(
        surfels,
        db.T_wc,
        db.camera,
        keyframe_image_reader(dataset, selected.keyframe_sources),
        cfg.photometric,
    )
    extractor = make_extractor(db_cfg.features)
    results: dict = {"sequences": {}}
    rows = []
    T_wc_db_true = keyframe_true_poses(dataset, selected.keyframe_sources)
    command = Command("relocalize", (f"dataset={dataset}",))
    with open_stage(out, "relocalize", command, LockLevel.RESULTS) as stage:
        work = stage.workdir()
        for name in cfg.sequences:
            run = _relocalize_sequence(
                dataset, name, cfg, extractor, relocalizer, photometric, show_progress
            )
            entry = _report_sequence(run, cfg, work / name, out / name, name, T_wc_db_true)
            results["sequences"][name] = entry
            rows.append(table_row(name, entry))
        sequences = results["sequences"]
        headline = sequences.get("query_same") or next(iter(sequences.values()))
        for key in ("recall", "mATE_m", "queries", "median_reloc_ms"):
            results[key] = headline[key]
        results["database"] = str(selected.path)
        results["config"] = config_record(cfg)
        table = markdown_table(rows, RESULT_COLUMNS)
        results["table"] = table
        atomic_write_text(work / "results.md", table + "\n")
        atomic_write_text(work / "results.json", json.dumps(results, indent=2) + "\n")
        key = stage_key({"reloc": config_record(cfg), "database": str(selected.path)}, {})
        outputs = [*cfg.sequences, "results.md", "results.json"]
        stage.commit(key, RelocalizeSummary(list(cfg.sequences)), outputs)
    return results
