"""Plots: PNG files are written (atomically), readable, of the requested size and not blank."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from matplotlib.image import imread

from diffloc.checks import ShapeError
from diffloc.eval.metrics import pose_errors, precision_recall_curve
from diffloc.eval.plots import plot_error_histogram, plot_precision_recall, plot_trajectory_topdown
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


def test_trajectory_plot(tmp_path) -> None:
    T_gt, T_est, _, accepted = _sequence()
    out = plot_trajectory_topdown(
        torch.from_numpy(T_gt), T_est, accepted, tmp_path / "sub" / "traj.png", figsize=(4, 4)
    )
    _check_png(out, 400, 400)
    out = plot_trajectory_topdown(T_gt, T_est, accepted, tmp_path / "xz.png", axes=(0, 2), dpi=50)
    _check_png(out, 300, 225)


def test_error_histogram(tmp_path) -> None:
    T_gt, T_est, localized, _ = _sequence()
    errors = pose_errors(T_est, T_gt, localized)
    out = plot_error_histogram(errors.translation_m, tmp_path / "hist.png", threshold=0.3)
    _check_png(out, 600, 450)
    out = plot_error_histogram(
        errors.rotation_deg, tmp_path / "rot.png", max_value=5.0, xlabel="rotation error [deg]"
    )
    _check_png(out, 600, 450)
    # All unlocalized: an empty (but valid) histogram.
    plot_error_histogram(np.full(5, np.nan), tmp_path / "empty.png")
    assert imread(tmp_path / "empty.png").shape[:2] == (450, 600)


def test_overwrites_existing_file(tmp_path) -> None:
    path = tmp_path / "hist.png"
    path.write_bytes(b"old")
    plot_error_histogram(np.array([0.1, 0.2]), path)
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
        plot_error_histogram(np.zeros((3, 2)), tmp_path / "f.png")
    with pytest.raises(ValueError, match="bins"):
        plot_error_histogram(np.zeros(3), tmp_path / "g.png", bins=0)
    with pytest.raises(TypeError):
        plot_error_histogram([0.1, 0.2], tmp_path / "h.png")
    assert not list(tmp_path.iterdir())
