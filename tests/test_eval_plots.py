"""Plots: PNG files are written (atomically), readable, of the requested size and not blank."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from matplotlib.image import imread

from diffloc.checks import ShapeError
from diffloc.eval.metrics import pose_errors, precision_recall_curve
from diffloc.eval.plots import (
    log_axis_limits,
    plot_error_cdf,
    plot_precision_recall,
    plot_trajectory_topdown,
)
from diffloc.geometry.se3 import se3_exp


def _check_png(path, width: int, height: int) -> None:
    assert path.is_file()
    image = imread(path)
    assert image.shape[:2] == (height, width)
    # Not blank: a good share of non-white pixels and several distinct colours.
    rgb = image[..., :3]
    assert (rgb.min(axis=-1) < 0.9).mean() > 0.01
    assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 10
    assert not list(path.parent.glob(".*.tmp"))  # no temporary files left


def _sequence(q: int = 60, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    xi = torch.cumsum(0.1 * torch.randn(q, 6, generator=g, dtype=torch.float64), dim=0)
    T_gt = se3_exp(xi).numpy()
    rng = np.random.default_rng(seed)
    T_est = T_gt.copy()
    T_est[:, :3, 3] += rng.normal(0.0, 0.2, (q, 3))
    localized = rng.random(q) < 0.8
    T_est[~localized] = math.nan
    accepted = localized & (rng.random(q) < 0.8)
    return T_gt, T_est, localized, accepted


def test_precision_recall_plot(tmp_path) -> None:
    T_gt, T_est, localized, accepted = _sequence()
    errors = pose_errors(T_est, T_gt, localized)
    scores = np.random.default_rng(0).integers(10, 100, len(T_gt)).astype(np.float64)
    curves = {
        "without PV": precision_recall_curve(scores, errors),
        "with PV": precision_recall_curve(scores, errors, accepted),
    }
    out = plot_precision_recall(curves, tmp_path / "pr.png", title="V101")
    assert out == tmp_path / "pr.png"
    _check_png(out, 600, 450)


def test_precision_recall_plot_with_operating_points(tmp_path) -> None:
    T_gt, T_est, localized, accepted = _sequence()
    errors = pose_errors(T_est, T_gt, localized)
    scores = np.random.default_rng(0).integers(10, 100, len(T_gt)).astype(np.float64)
    curve = {"found": precision_recall_curve(scores, errors)}
    points = {"validated": (0.4, 0.9), "nothing accepted": (0.0, math.nan)}
    out = plot_precision_recall(curve, tmp_path / "pr.png", operating_points=points)
    _check_png(out, 600, 450)
    # The marker changes the picture: the same curve without it differs.
    bare = plot_precision_recall(curve, tmp_path / "bare.png")
    assert not np.array_equal(imread(out), imread(bare))


def test_trajectory_plot(tmp_path) -> None:
    T_gt, T_est, _, accepted = _sequence()
    out = plot_trajectory_topdown(
        torch.from_numpy(T_gt), T_est, accepted, tmp_path / "sub" / "traj.png", figsize=(4, 4)
    )
    _check_png(out, 400, 400)
    out = plot_trajectory_topdown(T_gt, T_est, accepted, tmp_path / "xz.png", axes=(0, 2), dpi=50)
    _check_png(out, 300, 225)


def test_error_cdf(tmp_path) -> None:
    T_gt, T_est, localized, accepted = _sequence()
    found = pose_errors(T_est, T_gt, localized)
    kept = pose_errors(T_est, T_gt, accepted)
    curves = {"found": found.translation_m, "accepted": torch.from_numpy(kept.translation_m)}
    out = plot_error_cdf(curves, tmp_path / "cdf.png", threshold=0.3)
    _check_png(out, 600, 450)
    out = plot_error_cdf(
        {"found": found.rotation_deg}, tmp_path / "rot.png", xlabel="rotation error [deg]"
    )
    _check_png(out, 600, 450)
    # Millimetre errors beside one 16 m outlier, exact zeros, nothing localized: valid plots.
    spread = np.r_[np.full(50, 0.004), 0.0, 16.0]
    _check_png(plot_error_cdf({"found": spread}, tmp_path / "spread.png"), 600, 450)
    plot_error_cdf({"none": np.full(5, np.nan)}, tmp_path / "empty.png", threshold=0.3)
    assert imread(tmp_path / "empty.png").shape[:2] == (450, 600)


def test_error_axis_keeps_centimetre_errors_apart_from_an_outlier() -> None:
    # Centimetre errors beside one 16 m outlier: the log axis spans whole decades, 1 cm and
    # 5 cm sit 0.7 decades (17.5 % of the axis) apart instead of in one bar of a 0-16 m axis.
    errors = np.r_[np.full(40, 0.01), np.full(40, 0.05), 16.0, np.nan, 0.0]
    low, high = log_axis_limits(errors, threshold=0.3)
    assert (low, high) == (0.01, 100.0)
    share = math.log10(0.05 / 0.01) / math.log10(high / low)
    assert share == pytest.approx(0.175, abs=1e-3)
    assert log_axis_limits(np.array([0.3]), 0.3) == (0.1, 1.0)
    assert log_axis_limits(np.full(3, np.nan)) == (1e-3, 1.0)


def test_overwrites_existing_file(tmp_path) -> None:
    path = tmp_path / "cdf.png"
    path.write_bytes(b"old")
    plot_error_cdf({"found": np.array([0.1, 0.2])}, path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_inputs_raise(tmp_path) -> None:
    T_gt, T_est, _, accepted = _sequence(10)
    with pytest.raises(ValueError, match="at least one"):
        plot_precision_recall({}, tmp_path / "a.png")
    with pytest.raises(ShapeError):
        plot_trajectory_topdown(T_gt, T_est[:5], accepted, tmp_path / "b.png")
    with pytest.raises(ValueError, match="boolean"):
        plot_trajectory_topdown(T_gt, T_est, accepted.astype(float), tmp_path / "c.png")
    with pytest.raises(ValueError, match="axes"):
        plot_trajectory_topdown(T_gt, T_est, accepted, tmp_path / "d.png", axes=(0, 0))
    broken = T_gt.copy()
    broken[2, 0, 0] = math.nan
    with pytest.raises(ValueError, match="T_wc_gt"):
        plot_trajectory_topdown(broken, T_est, accepted, tmp_path / "e.png")
    with pytest.raises(ShapeError):
        plot_error_cdf({"a": np.zeros((3, 2))}, tmp_path / "f.png")
    with pytest.raises(ValueError, match="negative"):
        plot_error_cdf({"a": np.array([0.1, -0.2])}, tmp_path / "g.png")
    with pytest.raises(ValueError, match="threshold"):
        plot_error_cdf({"a": np.zeros(3)}, tmp_path / "g.png", threshold=0.0)
    with pytest.raises(ValueError, match="at least one"):
        plot_error_cdf({}, tmp_path / "g.png")
    with pytest.raises(TypeError):
        plot_error_cdf({"a": [0.1, 0.2]}, tmp_path / "h.png")
    assert not list(tmp_path.iterdir())
