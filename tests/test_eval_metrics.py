"""Evaluation metrics: known-answer pose errors, recall, mATE, precision-recall curves, the TUM
export checked against evo's APE, and bad inputs."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.eval.metrics import (
    LocalizationMetrics,
    PoseErrors,
    is_correct,
    localization_metrics,
    mean_ate,
    pose_errors,
    precision_recall_curve,
    recall,
    rmse_ate,
    write_localized_tum,
)
from diffloc.geometry.se3 import se3_exp, so3_exp
from diffloc.io.trajectory import read_tum
from diffloc.testing import random_se3


def _offset_poses(
    T_gt: np.ndarray, trans_m: np.ndarray, rot_deg: np.ndarray, seed: int = 0
) -> np.ndarray:
    """Estimates with exactly the given translation / rotation errors in random directions."""
    g = torch.Generator().manual_seed(seed)
    q = len(T_gt)
    direction = torch.nn.functional.normalize(torch.randn(q, 3, generator=g, dtype=torch.float64))
    axis = torch.nn.functional.normalize(torch.randn(q, 3, generator=g, dtype=torch.float64))
    angle = torch.from_numpy(np.radians(rot_deg))[:, None]
    T = torch.from_numpy(T_gt).clone()
    T[:, :3, :3] = T[:, :3, :3] @ so3_exp(axis * angle)
    T[:, :3, 3] += direction * torch.from_numpy(trans_m)[:, None]
    return T.numpy()


def _trajectory(q: int, seed: int = 0) -> np.ndarray:
    g = torch.Generator().manual_seed(seed)
    return random_se3((q,), generator=g, max_translation=5.0).numpy()


def test_pose_errors_known_answer() -> None:
    T_gt = _trajectory(5)
    trans = np.array([0.0, 0.1, 0.29, 0.31, 2.0])
    rot = np.array([0.0, 1.0, 5.0, 170.0, 1e-7])
    errors = pose_errors(_offset_poses(T_gt, trans, rot), T_gt, np.ones(5, dtype=bool))
    np.testing.assert_allclose(errors.translation_m, trans, atol=1e-12)
    np.testing.assert_allclose(errors.rotation_deg, rot, rtol=1e-9, atol=1e-12)
    assert errors.translation_m.dtype == np.float64 and errors.num_queries == 5


def test_pose_errors_nan_for_unlocalized_and_torch_inputs() -> None:
    T_gt = torch.from_numpy(_trajectory(3))
    T_est = T_gt.clone()
    T_est[1] = math.nan  # no estimate
    errors = pose_errors(T_est, T_gt, torch.tensor([True, False, True]))
    assert np.isnan(errors.translation_m[1]) and np.isnan(errors.rotation_deg[1])
    np.testing.assert_allclose(errors.translation_m[[0, 2]], 0.0, atol=1e-12)
    np.testing.assert_allclose(errors.rotation_deg[[0, 2]], 0.0, atol=1e-6)


def test_recall_counts_unlocalized_as_failures() -> None:
    T_gt = _trajectory(6)
    trans = np.array([0.05, 0.299, 0.301, 0.1, 0.1, 0.1])
    rot = np.array([1.0, 1.0, 1.0, 20.0, 1.0, 1.0])
    localized = np.array([True, True, True, True, True, False])
    errors = pose_errors(_offset_poses(T_gt, trans, rot), T_gt, localized)
    # Seed 1 has no rotation threshold by default.
    assert recall(errors) == pytest.approx(4 / 6)
    assert recall(errors, max_trans_m=0.3, max_rot_deg=10.0) == pytest.approx(3 / 6)
    assert recall(errors, max_trans_m=1.0) == pytest.approx(5 / 6)
    np.testing.assert_array_equal(is_correct(errors), [True, True, False, True, True, False])


def test_mate_and_rmse() -> None:
    T_gt = _trajectory(4)
    trans = np.array([0.1, 0.2, 0.6, 9.0])
    localized = np.array([True, True, True, False])
    errors = pose_errors(_offset_poses(T_gt, trans, np.zeros(4)), T_gt, localized)
    assert mean_ate(errors) == pytest.approx(0.3, abs=1e-12)
    assert rmse_ate(errors) == pytest.approx(math.sqrt((0.01 + 0.04 + 0.36) / 3), abs=1e-12)
    assert mean_ate(errors, max_trans_m=0.5) == pytest.approx(0.15, abs=1e-12)
    none = pose_errors(T_gt, T_gt, np.zeros(4, dtype=bool))
    assert math.isnan(mean_ate(none)) and math.isnan(rmse_ate(none)) and recall(none) == 0.0


def test_localization_metrics_and_to_dict() -> None:
    T_gt = _trajectory(4)
    trans = np.array([0.1, 0.2, 0.5, 0.0])
    rot = np.array([1.0, 2.0, 3.0, 0.0])
    localized = np.array([True, True, True, False])
    errors = pose_errors(_offset_poses(T_gt, trans, rot), T_gt, localized)
    m = localization_metrics(errors, reloc_ms=np.array([10.0, 20.0, 40.0, 100.0]))
    assert isinstance(m, LocalizationMetrics)
    assert (m.queries, m.localized) == (4, 3)
    assert m.recall == pytest.approx(0.5)
    assert m.mATE_m == pytest.approx(0.8 / 3)
    assert m.median_translation_m == pytest.approx(0.2)
    assert m.median_rotation_deg == pytest.approx(2.0)
    assert m.median_reloc_ms == pytest.approx(30.0)
    d = m.to_dict()
    assert d["max_rot_deg"] is None  # inf -> None: strict JSON
    assert json.loads(json.dumps(d, allow_nan=False)) == d
    assert math.isnan(localization_metrics(errors).median_reloc_ms)


def test_precision_recall_curve_known_answer() -> None:
    T_gt = _trajectory(6)
    #                 correct, wrong, correct, correct, wrong, unlocalized
    trans = np.array([0.1, 1.0, 0.2, 0.1, 2.0, 0.0])
    localized = np.array([True, True, True, True, True, False])
    errors = pose_errors(_offset_poses(T_gt, trans, np.zeros(6)), T_gt, localized)
    scores = np.array([50.0, 40.0, 30.0, 30.0, 10.0, math.nan])
    curve = precision_recall_curve(scores, errors)
    np.testing.assert_array_equal(curve.thresholds, [10.0, 30.0, 40.0, 50.0])
    np.testing.assert_allclose(curve.precision, [3 / 5, 3 / 4, 1 / 2, 1.0])
    np.testing.assert_allclose(curve.recall, [3 / 6, 3 / 6, 1 / 6, 1 / 6])
    # Validation rejects query 1 (the wrong pose with a high score): precision goes up.
    accepted = np.array([True, False, True, True, True, True])
    with_pv = precision_recall_curve(scores, errors, accepted)
    np.testing.assert_array_equal(with_pv.thresholds, [10.0, 30.0, 50.0])
    np.testing.assert_allclose(with_pv.precision, [3 / 4, 1.0, 1.0])
    np.testing.assert_allclose(with_pv.recall, [3 / 6, 3 / 6, 1 / 6])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_precision_recall_curve_monotonic_recall(seed: int) -> None:
    rng = np.random.default_rng(seed)
    q = 200
    T_gt = _trajectory(q, seed)
    trans = rng.exponential(0.3, q)
    localized = rng.random(q) < 0.8
    errors = pose_errors(_offset_poses(T_gt, trans, np.zeros(q), seed), T_gt, localized)
    # Inlier counts that correlate with correctness, with ties.
    scores = np.round(rng.normal(40.0, 10.0, q) - 30.0 * trans)
    accepted = rng.random(q) < 0.7
    for curve in (
        precision_recall_curve(scores, errors),
        precision_recall_curve(scores, errors, accepted),
    ):
        assert np.all(np.diff(curve.thresholds) > 0)
        assert np.all(np.diff(curve.recall) <= 0)
        assert np.all((curve.precision >= 0) & (curve.precision <= 1))
    # The lowest threshold accepts every localized query: its recall is the overall recall.
    no_pv = precision_recall_curve(scores, errors)
    assert no_pv.recall[0] == pytest.approx(recall(errors))
    with_pv = precision_recall_curve(scores, errors, accepted)
    assert np.all(with_pv.recall[0] <= no_pv.recall[0])


def test_precision_recall_curve_empty() -> None:
    T_gt = _trajectory(3)
    errors = pose_errors(T_gt, T_gt, np.zeros(3, dtype=bool))
    curve = precision_recall_curve(np.full(3, math.nan), errors)
    assert curve.thresholds.shape == curve.precision.shape == curve.recall.shape == (0,)


def test_tum_export_matches_evo_ape(tmp_path) -> None:
    """Our mATE / RMSE equal evo's APE (translation part, no alignment) on the written files."""
    from evo.core import metrics as evo_metrics
    from evo.core import sync
    from evo.tools import file_interface

    q = 40
    g = torch.Generator().manual_seed(3)
    timestamps = 100.0 + 0.05 * np.arange(q)
    xi = torch.cumsum(0.1 * torch.randn(q, 6, generator=g, dtype=torch.float64), dim=0)
    T_gt = se3_exp(xi).numpy()
    rng = np.random.default_rng(3)
    T_est = _offset_poses(T_gt, rng.exponential(0.2, q), rng.exponential(2.0, q), seed=3)
    localized = rng.random(q) < 0.7
    T_est[~localized] = math.nan
    gt_path = write_localized_tum(tmp_path / "gt.txt", timestamps, T_gt, np.ones(q, dtype=bool))
    est_path = write_localized_tum(tmp_path / "est.txt", timestamps, T_est, localized)
    assert len(read_tum(est_path)[0]) == int(localized.sum())

    errors = pose_errors(T_est, T_gt, localized)
    traj_ref = file_interface.read_tum_trajectory_file(str(gt_path))
    traj_est = file_interface.read_tum_trajectory_file(str(est_path))
    traj_ref, traj_est = sync.associate_trajectories(traj_ref, traj_est, max_diff=0.01)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))
    assert ape.get_statistic(evo_metrics.StatisticsType.mean) == pytest.approx(
        mean_ate(errors), abs=1e-6
    )
    assert ape.get_statistic(evo_metrics.StatisticsType.rmse) == pytest.approx(
        rmse_ate(errors), abs=1e-6
    )
    rot = evo_metrics.APE(evo_metrics.PoseRelation.rotation_angle_deg)
    rot.process_data((traj_ref, traj_est))
    assert rot.get_statistic(evo_metrics.StatisticsType.max) == pytest.approx(
        float(np.nanmax(errors.rotation_deg)), abs=1e-6
    )


def test_bad_inputs_raise() -> None:
    T = _trajectory(3)
    ok = np.ones(3, dtype=bool)
    with pytest.raises(ShapeError):
        pose_errors(T[:2], T, ok)
    with pytest.raises(ShapeError):
        pose_errors(T, T, ok[:2])
    with pytest.raises(ShapeError):
        pose_errors(T[:, :3], T[:, :3], ok)
    with pytest.raises(ValueError, match="boolean"):
        pose_errors(T, T, np.ones(3))
    bad = T.copy()
    bad[0, 0, 3] = math.nan
    with pytest.raises(ValueError, match="T_wc_gt"):
        pose_errors(T, bad, ok)
    with pytest.raises(ValueError, match="T_wc_est"):
        pose_errors(bad, T, ok)
    pose_errors(bad, T, np.array([False, True, True]))  # NaN only where unlocalized: fine
    errors = pose_errors(T, T, ok)
    with pytest.raises(ValueError, match="scores"):
        precision_recall_curve(np.array([1.0, math.nan, 2.0]), errors)
    with pytest.raises(ShapeError):
        precision_recall_curve(np.ones(2), errors)
    with pytest.raises(ValueError, match="thresholds"):
        recall(errors, max_trans_m=-1.0)
    with pytest.raises(ValueError, match="thresholds"):
        recall(errors, max_rot_deg=math.nan)
    with pytest.raises(ValueError, match="reloc_ms"):
        localization_metrics(errors, reloc_ms=np.array([1.0, math.inf, 2.0]))


def test_write_localized_tum_bad_inputs(tmp_path) -> None:
    T = _trajectory(3)
    with pytest.raises(ValueError, match="strictly increasing"):
        write_localized_tum(tmp_path / "a.txt", np.array([0.0, 0.0, 1.0]), T, np.ones(3, bool))
    broken = T.copy()
    broken[1] = math.nan
    with pytest.raises(ValueError):
        write_localized_tum(tmp_path / "b.txt", np.arange(3.0), broken, np.ones(3, bool))
    write_localized_tum(tmp_path / "c.txt", np.arange(3.0), broken, np.array([True, False, True]))
    assert not (tmp_path / "a.txt").exists() and not (tmp_path / "b.txt").exists()


def test_pose_errors_dataclass_is_the_metric_input() -> None:
    errors = PoseErrors(np.array([0.1]), np.array([1.0]), np.array([True]))
    assert recall(errors) == 1.0 and mean_ate(errors) == pytest.approx(0.1)
