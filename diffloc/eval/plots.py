"""PNG plots of relocalization results: precision-recall curves, top-down trajectories, errors.

Figures are drawn with matplotlib's object API on the Agg renderer (no ``pyplot``, so no global
figure state and no display is needed) and written atomically. Every function takes arrays and
an output path and returns the path; the image is ``figsize * dpi`` pixels.

Example:
    >>> plot_error_histogram(np.array([0.01, 0.05, 0.4, np.nan]), tmp_path / "errors.png")
    PosixPath('.../errors.png')
"""

from __future__ import annotations

import io
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from diffloc.checks import check_shape
from diffloc.eval.metrics import PrecisionRecallCurve
from diffloc.io.atomic import atomic_write_bytes

__all__ = ["plot_error_histogram", "plot_precision_recall", "plot_trajectory_topdown"]

FIGSIZE = (6.0, 4.5)
"""Default figure size in inches."""
DPI = 100
"""Default resolution: a default figure is 600 x 450 pixels."""


def _numpy(x: np.ndarray | torch.Tensor, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    if not isinstance(x, np.ndarray):
        raise TypeError(f"{name} must be a numpy array or torch tensor, got {type(x).__name__}")
    return x


def _new_figure(figsize: tuple[float, float], dpi: int) -> Figure:
    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: str | os.PathLike) -> Path:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    atomic_write_bytes(path, buffer.getvalue())
    return Path(path)


def plot_precision_recall(
    curves: Mapping[str, PrecisionRecallCurve],
    path: str | os.PathLike,
    *,
    title: str | None = None,
    figsize: tuple[float, float] = FIGSIZE,
    dpi: int = DPI,
) -> Path:
    """Precision over recall, one line per curve (e.g. with and without pose validation).

    Args:
        curves: label -> curve from :func:`~diffloc.eval.metrics.precision_recall_curve`.
        path: the PNG to write.
        title: optional figure title.
        figsize: inches.
        dpi: pixels per inch.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ValueError: no curves.

    Example:
        >>> curve = PrecisionRecallCurve(np.array([1.0, 2.0]), np.array([0.8, 1.0]),
        ...                              np.array([0.6, 0.3]))
        >>> plot_precision_recall({"with PV": curve}, tmp_path / "pr.png")
        PosixPath('.../pr.png')
    """
    if not curves:
        raise ValueError("plot_precision_recall needs at least one curve")
    fig = _new_figure(figsize, dpi)
    ax = fig.subplots()
    for label, curve in curves.items():
        ax.plot(curve.recall, curve.precision, marker=".", markersize=3, label=label)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.02)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower left")
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)


def plot_trajectory_topdown(
    T_wc_gt: np.ndarray | torch.Tensor,
    T_wc_est: np.ndarray | torch.Tensor,
    accepted: np.ndarray | torch.Tensor,
    path: str | os.PathLike,
    *,
    axes: tuple[int, int] = (0, 1),
    title: str | None = None,
    figsize: tuple[float, float] = FIGSIZE,
    dpi: int = DPI,
) -> Path:
    """Top-down view: true query trajectory, accepted (green) and rejected (red) estimates.

    Each estimate is joined to its true position by a thin grey line. Queries whose estimate
    is not finite (not localized) are drawn on the trajectory only.

    Args:
        T_wc_gt: (Q, 4, 4) true camera-to-world poses, in query order (drawn as a line).
        T_wc_est: (Q, 4, 4) estimates, NaN rows for unlocalized queries.
        accepted: (Q,) bool, the estimate passed validation (others with a finite estimate
            are drawn as rejected).
        path: the PNG to write.
        axes: the two world axes shown (default x-y, i.e. z up).
        title: optional figure title.
        figsize: inches.
        dpi: pixels per inch.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ShapeError: wrong or mismatched shapes.
        ValueError: non-finite ground truth, bad ``axes``.
    """
    gt = _numpy(T_wc_gt, "T_wc_gt").astype(np.float64)
    est = _numpy(T_wc_est, "T_wc_est").astype(np.float64)
    ok = _numpy(accepted, "accepted")
    check_shape(gt, "Q,4,4", "T_wc_gt")
    check_shape(est, f"{gt.shape[0]},4,4", "T_wc_est")
    check_shape(ok, f"{gt.shape[0]}", "accepted")
    if ok.dtype != np.bool_:
        raise ValueError(f"accepted must be a boolean array, got dtype {ok.dtype}")
    if not np.isfinite(gt).all():
        raise ValueError("T_wc_gt contains NaN or infinite values")
    if len(axes) != 2 or len(set(axes)) != 2 or not all(a in (0, 1, 2) for a in axes):
        raise ValueError(f"axes must be two different indices of (0, 1, 2), got {axes}")
    a, b = axes
    p_gt = gt[:, :3, 3][:, [a, b]]
    p_est = est[:, :3, 3][:, [a, b]]
    has_estimate = np.isfinite(est).all(axis=(1, 2))
    good = has_estimate & ok
    bad = has_estimate & ~ok

    fig = _new_figure(figsize, dpi)
    ax = fig.subplots()
    ax.plot(p_gt[:, 0], p_gt[:, 1], color="black", linewidth=1.0, label="ground truth")
    segments = np.stack((p_est[has_estimate], p_gt[has_estimate]), axis=1)
    ax.add_collection(LineCollection(segments, colors="0.6", linewidths=0.6))
    ax.scatter(*p_est[good].T, s=10, color="tab:green", label=f"accepted ({int(good.sum())})")
    ax.scatter(*p_est[bad].T, s=10, color="tab:red", label=f"rejected ({int(bad.sum())})")
    names = "xyz"
    ax.set_xlabel(f"{names[a]} [m]")
    ax.set_ylabel(f"{names[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)


def plot_error_histogram(
    errors: np.ndarray | torch.Tensor,
    path: str | os.PathLike,
    *,
    bins: int = 30,
    max_value: float | None = None,
    threshold: float | None = None,
    xlabel: str = "translation error [m]",
    title: str | None = None,
    figsize: tuple[float, float] = FIGSIZE,
    dpi: int = DPI,
) -> Path:
    """Histogram of per-query errors (NaN entries, the unlocalized queries, are left out).

    Args:
        errors: (Q,) errors, e.g. ``PoseErrors.translation_m``.
        path: the PNG to write.
        bins: number of bins.
        max_value: errors above it are counted in the last bin (default: the largest error).
        threshold: optional vertical line, e.g. the 0.3 m recall threshold.
        xlabel: the x-axis label.
        title: optional figure title.
        figsize: inches.
        dpi: pixels per inch.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ShapeError: ``errors`` is not 1-D.
        ValueError: ``bins`` < 1, or a non-positive ``max_value``.
    """
    values = _numpy(errors, "errors").astype(np.float64)
    check_shape(values, "Q", "errors")
    if bins < 1:
        raise ValueError(f"bins must be positive, got {bins}")
    if max_value is not None and not max_value > 0:
        raise ValueError(f"max_value must be positive, got {max_value}")
    values = values[~np.isnan(values)]
    top = max_value if max_value is not None else float(values.max()) if values.size else 1.0
    top = top if top > 0 else 1.0
    fig = _new_figure(figsize, dpi)
    ax = fig.subplots()
    ax.hist(np.minimum(values, top), bins=bins, range=(0.0, top), color="tab:blue")
    if threshold is not None:
        ax.axvline(threshold, color="tab:red", linestyle="--", label=f"{threshold:g}")
        ax.legend(loc="upper right")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("queries")
    ax.grid(True, alpha=0.3)
    ax.set_title(title if title else f"{values.size} localized queries")
    fig.tight_layout()
    return _save(fig, path)
