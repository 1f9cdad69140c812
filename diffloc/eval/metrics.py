"""Relocalization metrics of seed 1, Sec. IV: pose errors, recall, mATE and precision-recall.

Every query has a ground-truth pose; a query is *localized* when the relocaliser returned a
pose for it (its estimate may be NaN otherwise). Conventions:

- Poses are camera-to-world ``T_wc`` (Q, 4, 4) in the metric map frame, so the absolute
  trajectory error is taken without any alignment (seed 1 aligns only the up-to-scale
  ORB-SLAM baseline).
- Translation error: distance between the estimated and true camera centres, metres.
  Rotation error: angle of ``R_est^T R_gt``, degrees. Both NaN for unlocalized queries.
- Recall at ``(max_trans_m, max_rot_deg)``: the fraction of *all* queries that are localized
  with errors within both thresholds (unlocalized queries are failures). Seed 1 uses a position
  threshold ``theta_r = 0.3`` m and no rotation threshold (``max_rot_deg = inf``).
- mATE: mean translation error of the localized queries (the relocalized poses), metres.
- Precision-recall (seed 1, Fig. 3): the acceptance threshold on a per-query score (e.g. the
  inlier count) is swept; precision is the fraction of accepted queries that are correct, recall
  the fraction of all queries that are accepted and correct.

Results are float64 numpy arrays and Python numbers: this is the end of the pipeline, where
values go to tables, plots and JSON.

Example:
    >>> T_gt = np.tile(np.eye(4), (3, 1, 1))
    >>> T_est = T_gt.copy()
    >>> T_est[1, 0, 3] = 0.5  # 0.5 m off
    >>> errors = pose_errors(T_est, T_gt, np.array([True, True, False]))
    >>> recall(errors), mean_ate(errors)
    (0.3333333333333333, 0.25)
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from diffloc.checks import check_finite, check_shape
from diffloc.io.trajectory import write_tum

__all__ = [
    "LocalizationMetrics",
    "PoseErrors",
    "PrecisionRecallCurve",
    "is_correct",
    "localization_metrics",
    "mean_ate",
    "pose_errors",
    "precision",
    "precision_recall_curve",
    "recall",
    "rmse_ate",
    "write_localized_tum",
]

DEFAULT_MAX_TRANS_M = 0.3
"""Seed 1's position threshold ``theta_r`` for a correct relocalization (metres)."""

ArrayLike = np.ndarray | torch.Tensor | Sequence


def _array(x: ArrayLike, dtype: type | np.dtype, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    try:
        return np.asarray(x, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be convertible to a {np.dtype(dtype)} array") from exc


def _mask(x: ArrayLike, q: int, name: str) -> np.ndarray:
    array = np.asarray(x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else x)
    if array.dtype != np.bool_:
        raise ValueError(f"{name} must be a boolean array, got dtype {array.dtype}")
    check_shape(array, f"{q}", name)
    return array


def _check_thresholds(max_trans_m: float, max_rot_deg: float) -> None:
    if not (max_trans_m >= 0 and max_rot_deg >= 0):  # also rejects NaN
        raise ValueError(
            f"thresholds must be >= 0, got max_trans_m={max_trans_m}, max_rot_deg={max_rot_deg}"
        )


@dataclass(frozen=True)
class PoseErrors:
    """Per-query pose errors.

    Attributes:
        translation_m: (Q,) float64 camera-centre distances, NaN where not localized.
        rotation_deg: (Q,) float64 rotation angles, NaN where not localized.
        localized: (Q,) bool, the relocaliser returned a pose.
    """

    translation_m: np.ndarray
    rotation_deg: np.ndarray
    localized: np.ndarray

    @property
    def num_queries(self) -> int:
        """Q, the number of queries."""
        return int(self.localized.shape[0])


def pose_errors(T_wc_est: ArrayLike, T_wc_gt: ArrayLike, localized: ArrayLike) -> PoseErrors:
    """Translation and rotation errors of estimated camera poses.

    Args:
        T_wc_est: (Q, 4, 4) estimated camera-to-world poses; rows of unlocalized queries are
            ignored (may be NaN).
        T_wc_gt: (Q, 4, 4) true camera-to-world poses (all finite).
        localized: (Q,) bool, which queries have an estimate.

    Returns:
        The :class:`PoseErrors` (NaN for unlocalized queries).

    Raises:
        ShapeError: wrong or mismatched shapes.
        ValueError: NaN/inf in the ground truth or in a localized estimate, non-bool mask.

    Example:
        >>> e = pose_errors(np.eye(4)[None], np.eye(4)[None], np.array([True]))
        >>> e.translation_m, e.rotation_deg
        (array([0.]), array([0.]))
    """
    est = _array(T_wc_est, np.float64, "T_wc_est")
    gt = _array(T_wc_gt, np.float64, "T_wc_gt")
    check_shape(gt, "Q,4,4", "T_wc_gt")
    check_shape(est, f"{gt.shape[0]},4,4", "T_wc_est")
    check_finite(gt, "T_wc_gt")
    mask = _mask(localized, gt.shape[0], "localized")
    check_finite(est[mask], "T_wc_est (localized rows)")
    translation = np.full(gt.shape[0], np.nan)
    rotation = np.full(gt.shape[0], np.nan)
    e, g = est[mask], gt[mask]
    translation[mask] = np.linalg.norm(e[:, :3, 3] - g[:, :3, 3], axis=-1)
    # angle of R = R_e^T R_g by atan2(|vee(R - R^T)| / 2, (trace R - 1) / 2), accurate near 0
    R = np.einsum("qji,qjk->qik", e[:, :3, :3], g[:, :3, :3])
    axis = np.stack((R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]), -1)
    sin = np.linalg.norm(axis, axis=-1) / 2.0
    cos = (np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0
    rotation[mask] = np.degrees(np.arctan2(sin, cos))
    return PoseErrors(translation, rotation, mask.copy())


def is_correct(
    errors: PoseErrors, max_trans_m: float = DEFAULT_MAX_TRANS_M, max_rot_deg: float = math.inf
) -> np.ndarray:
    """(Q,) bool: localized with both errors within the thresholds (inclusive)."""
    _check_thresholds(max_trans_m, max_rot_deg)
    with np.errstate(invalid="ignore"):
        return (
            errors.localized
            & (errors.translation_m <= max_trans_m)
            & (errors.rotation_deg <= max_rot_deg)
        )


def recall(
    errors: PoseErrors, max_trans_m: float = DEFAULT_MAX_TRANS_M, max_rot_deg: float = math.inf
) -> float:
    """Fraction of all queries localized within ``max_trans_m`` and ``max_rot_deg``.

    Unlocalized queries count as failures; no queries gives NaN.

    Example:
        >>> e = pose_errors(np.eye(4)[None], np.eye(4)[None], np.array([False]))
        >>> recall(e)
        0.0
    """
    correct = is_correct(errors, max_trans_m, max_rot_deg)
    return float(correct.mean()) if correct.size else math.nan


def precision(
    errors: PoseErrors, max_trans_m: float = DEFAULT_MAX_TRANS_M, max_rot_deg: float = math.inf
) -> float:
    """Fraction of the localized (accepted) queries that are within the thresholds.

    A relocaliser that says "not localized" loses recall but keeps precision; a confident
    wrong pose costs precision. No localized query gives NaN.

    Example:
        >>> T = np.tile(np.eye(4), (2, 1, 1))
        >>> wrong = T.copy()
        >>> wrong[1, 0, 3] = 5.0
        >>> precision(pose_errors(wrong, T, np.array([True, True])))
        0.5
    """
    correct = is_correct(errors, max_trans_m, max_rot_deg)
    count = int(errors.localized.sum())
    return float(correct.sum() / count) if count else math.nan


def mean_ate(errors: PoseErrors, max_trans_m: float = math.inf) -> float:
    """mATE: mean translation error (metres) of the localized queries.

    Args:
        errors: the per-query errors.
        max_trans_m: only errors up to this are averaged (seed 1 reports the mATE of one
            baseline over its poses within 5 m); ``inf`` averages all localized queries.

    Returns:
        The mean, NaN when no query qualifies.
    """
    _check_thresholds(max_trans_m, 0.0)
    t = errors.translation_m[errors.localized]
    t = t[t <= max_trans_m]
    return float(t.mean()) if t.size else math.nan


def rmse_ate(errors: PoseErrors, max_trans_m: float = math.inf) -> float:
    """Root-mean-square translation error (metres) of the localized queries (NaN if none)."""
    _check_thresholds(max_trans_m, 0.0)
    t = errors.translation_m[errors.localized]
    t = t[t <= max_trans_m]
    return float(np.sqrt(np.mean(t * t))) if t.size else math.nan


@dataclass(frozen=True)
class PrecisionRecallCurve:
    """Precision and recall as functions of a score threshold.

    Attributes:
        thresholds: (T,) float64 increasing distinct scores; a query is accepted at threshold
            ``tau`` when its score is ``>= tau`` (and it passed validation, if given).
        precision: (T,) accepted-and-correct / accepted.
        recall: (T,) accepted-and-correct / all queries; non-increasing in the threshold.
    """

    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray


def precision_recall_curve(
    scores: ArrayLike,
    errors: PoseErrors,
    accepted: ArrayLike | None = None,
    max_trans_m: float = DEFAULT_MAX_TRANS_M,
    max_rot_deg: float = math.inf,
) -> PrecisionRecallCurve:
    """Sweep the acceptance threshold on per-query scores (seed 1, Fig. 3).

    Args:
        scores: (Q,) per-query scores, higher is more confident (e.g. inlier counts); the
            scores of unlocalized or validation-rejected queries are ignored (may be NaN).
        errors: the per-query errors (decides which queries are correct).
        accepted: optional (Q,) bool, the pose validation verdict; ``None`` (no validation)
            accepts every localized query whose score reaches the threshold.
        max_trans_m: translation threshold of a correct pose.
        max_rot_deg: rotation threshold of a correct pose.

    Returns:
        The :class:`PrecisionRecallCurve`, one point per distinct candidate score (empty when
        no query is a candidate).

    Raises:
        ShapeError: wrong shapes.
        ValueError: NaN/inf score of a candidate query, non-bool ``accepted``.

    Example:
        >>> T = np.tile(np.eye(4), (3, 1, 1))
        >>> e = pose_errors(T, T, np.array([True, True, True]))
        >>> c = precision_recall_curve(np.array([5.0, 9.0, 9.0]), e)
        >>> c.thresholds, c.recall
        (array([5., 9.]), array([1.        , 0.66666667]))
    """
    q = errors.num_queries
    values = _array(scores, np.float64, "scores")
    check_shape(values, f"{q}", "scores")
    candidate = errors.localized.copy()
    if accepted is not None:
        candidate &= _mask(accepted, q, "accepted")
    check_finite(values[candidate], "scores (of localized, accepted queries)")
    correct = is_correct(errors, max_trans_m, max_rot_deg)[candidate]
    values = values[candidate]
    order = np.argsort(-values, kind="stable")
    values, correct = values[order], correct[order]
    tp = np.cumsum(correct)
    accepted_count = np.arange(1, len(values) + 1)
    # The last query of each run of equal scores closes a threshold (ties enter together).
    last = np.r_[values[1:] != values[:-1], True] if len(values) else np.zeros(0, dtype=bool)
    thresholds, tp, accepted_count = values[last][::-1], tp[last][::-1], accepted_count[last][::-1]
    return PrecisionRecallCurve(
        thresholds=thresholds.copy(),
        precision=tp / accepted_count,
        recall=tp / max(q, 1),
    )


@dataclass(frozen=True)
class LocalizationMetrics:
    """Summary of one query sequence (one row of seed 1's Tables I-III).

    Attributes:
        queries: number of queries.
        localized: number of queries with a pose.
        recall: see :func:`recall`.
        precision: see :func:`precision`.
        mATE_m: see :func:`mean_ate`.
        ate_rmse_m: see :func:`rmse_ate`.
        median_translation_m: median translation error of the localized queries.
        median_rotation_deg: median rotation error of the localized queries.
        median_reloc_ms: median relocalization time per query, NaN if not given.
        max_trans_m: translation threshold used for ``recall``.
        max_rot_deg: rotation threshold used for ``recall``.
    """

    queries: int
    localized: int
    recall: float
    precision: float
    mATE_m: float
    ate_rmse_m: float
    median_translation_m: float
    median_rotation_deg: float
    median_reloc_ms: float
    max_trans_m: float
    max_rot_deg: float

    def to_dict(self) -> dict[str, int | float | None]:
        """Plain JSON-ready values: NaN and infinities become ``None``."""
        out: dict[str, int | float | None] = {}
        for key, value in asdict(self).items():
            out[key] = None if isinstance(value, float) and not math.isfinite(value) else value
        return out


def localization_metrics(
    errors: PoseErrors,
    reloc_ms: ArrayLike | None = None,
    max_trans_m: float = DEFAULT_MAX_TRANS_M,
    max_rot_deg: float = math.inf,
) -> LocalizationMetrics:
    """Recall, mATE and medians of one query sequence.

    Args:
        errors: the per-query errors.
        reloc_ms: optional (Q,) relocalization time per query in milliseconds (all queries,
            localized or not; must be finite).
        max_trans_m: translation threshold of a correct pose.
        max_rot_deg: rotation threshold of a correct pose.

    Returns:
        The :class:`LocalizationMetrics`.

    Example:
        >>> T = np.tile(np.eye(4), (2, 1, 1))
        >>> m = localization_metrics(pose_errors(T, T, np.array([True, False])), [10.0, 30.0])
        >>> m.recall, m.localized, m.median_reloc_ms
        (0.5, 1, 20.0)
    """
    median_ms = math.nan
    if reloc_ms is not None:
        times = _array(reloc_ms, np.float64, "reloc_ms")
        check_shape(times, f"{errors.num_queries}", "reloc_ms")
        check_finite(times, "reloc_ms")
        median_ms = float(np.median(times)) if times.size else math.nan
    t = errors.translation_m[errors.localized]
    r = errors.rotation_deg[errors.localized]
    return LocalizationMetrics(
        queries=errors.num_queries,
        localized=int(errors.localized.sum()),
        recall=recall(errors, max_trans_m, max_rot_deg),
        precision=precision(errors, max_trans_m, max_rot_deg),
        mATE_m=mean_ate(errors),
        ate_rmse_m=rmse_ate(errors),
        median_translation_m=float(np.median(t)) if t.size else math.nan,
        median_rotation_deg=float(np.median(r)) if r.size else math.nan,
        median_reloc_ms=median_ms,
        max_trans_m=float(max_trans_m),
        max_rot_deg=float(max_rot_deg),
    )


def write_localized_tum(
    path: str | os.PathLike,
    timestamps: ArrayLike,
    T_wc_est: ArrayLike,
    localized: ArrayLike,
) -> Path:
    """Write the estimates of the localized queries as a TUM trajectory (atomically).

    Uses :func:`diffloc.io.trajectory.write_tum`, so the file can be compared with a
    ground-truth TUM file by evo (``evo_ape tum gt.txt est.txt``, no alignment).

    Args:
        path: the file to write.
        timestamps: (Q,) query timestamps in seconds, strictly increasing.
        T_wc_est: (Q, 4, 4) estimates; rows of unlocalized queries are skipped (may be NaN).
        localized: (Q,) bool.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ShapeError: wrong shapes.
        ValueError: non-finite or non-rigid localized estimates, non-increasing timestamps.
    """
    times = _array(timestamps, np.float64, "timestamps")
    check_shape(times, "Q", "timestamps")
    est = _array(T_wc_est, np.float64, "T_wc_est")
    check_shape(est, f"{times.shape[0]},4,4", "T_wc_est")
    mask = _mask(localized, times.shape[0], "localized")
    write_tum(path, times[mask], est[mask])
    return Path(path)
