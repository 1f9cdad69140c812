"""PNG plots of relocalization results: precision-recall curves, top-down trajectories, errors.

Figures are drawn with matplotlib's object API on the Agg renderer (no ``pyplot``, so no global
figure state and no display is needed) and written atomically. Every function takes arrays and
an output path and returns the path; the image is ``figsize * dpi`` pixels.

Example:
    >>> import numpy as np
    >>> plot_error_cdf({"found": np.array([0.01, 0.05, 0.4, np.nan])}, "errors.png", dpi=20)
    PosixPath('errors.png')
"""

from __future__ import annotations

import io
import math
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

__all__ = ["log_axis_limits", "plot_error_cdf", "plot_precision_recall", "plot_trajectory_topdown"]

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
    operating_points: Mapping[str, tuple[float, float]] | None = None,
    title: str | None = None,
    figsize: tuple[float, float] = FIGSIZE,
    dpi: int = DPI,
) -> Path:
    """Precision over recall: one line per curve, one marker per operating point.

    A curve sweeps a score threshold (e.g. the inlier count of every found pose); an operating
    point is one verdict (e.g. the poses that pose validation accepted), drawn as a marker
    whose legend entry gives its recall and precision.

    Args:
        curves: label -> curve from :func:`~diffloc.eval.metrics.precision_recall_curve`.
        path: the PNG to write.
        operating_points: label -> ``(recall, precision)``; a NaN precision (nothing
            accepted) gets a legend entry and no marker.
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
        >>> plot_precision_recall({"found": curve}, "pr.png", dpi=20,
        ...                       operating_points={"validated": (0.5, 1.0)})
        PosixPath('pr.png')
    """
    if not curves:
        raise ValueError("plot_precision_recall needs at least one curve")
    fig = _new_figure(figsize, dpi)
    ax = fig.subplots()
    for label, curve in curves.items():
        ax.plot(curve.recall, curve.precision, marker=".", markersize=3, label=label)
    markers = iter("o*sD^v")
    for label, (recall, precision) in (operating_points or {}).items():
        if np.isfinite(precision):
            figures = f"recall {100 * recall:.1f} %, precision {100 * precision:.1f} %"
        else:
            figures, recall, precision = "nothing accepted", np.nan, np.nan
        ax.plot(
            [recall],
            [precision],
            linestyle="none",
            marker=next(markers, "o"),
            markersize=9,
            clip_on=False,
            label=f"{label}: {figures}",
        )
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.02)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
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


def log_axis_limits(values: np.ndarray, threshold: float | None = None) -> tuple[float, float]:
    """Whole decades around the positive finite ``values`` (and ``threshold``), at least one.

    Args:
        values: (N,) errors; NaN, infinite and zero entries are ignored.
        threshold: a value the axis must show too.

    Returns:
        ``(low, high)``, powers of ten; ``(1e-3, 1)`` when there is nothing to show.

    Example:
        >>> log_axis_limits(np.array([0.004, 0.02, 16.0, np.nan]), 0.3)
        (0.001, 100.0)
    """
    positive = values[np.isfinite(values) & (values > 0)]
    bounds = [threshold] if threshold is not None else []
    if positive.size:
        bounds += [float(positive.min()), float(positive.max())]
    if not bounds:
        return 1e-3, 1.0
    low = 10.0 ** math.floor(math.log10(min(bounds)))
    high = 10.0 ** math.ceil(math.log10(max(bounds)))
    return low, max(high, 10.0 * low)


def plot_error_cdf(
    errors: Mapping[str, np.ndarray | torch.Tensor],
    path: str | os.PathLike,
    *,
    threshold: float | None = None,
    xlabel: str = "position error [m]",
    title: str | None = None,
    figsize: tuple[float, float] = FIGSIZE,
    dpi: int = DPI,
) -> Path:
    """Cumulative error curves on a log x axis: the share of queries within each error.

    Each curve rises by ``1 / Q`` at every finite error of its ``Q`` queries; a NaN entry (a
    query without a pose) never counts, so a curve tops out at the share of queries with a
    pose. The log axis keeps millimetre and metre errors apart (a linear histogram puts every
    centimetre error in one bar next to a single far outlier). At ``threshold`` a curve of the
    accepted poses reads the recall. Errors of 0 are drawn at the left end of the axis.

    Args:
        errors: label -> (Q,) errors, e.g. ``PoseErrors.translation_m``.
        path: the PNG to write.
        threshold: optional vertical line, e.g. the 0.3 m recall threshold.
        xlabel: the x-axis label.
        title: optional figure title.
        figsize: inches.
        dpi: pixels per inch.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ShapeError: an error array is not 1-D.
        TypeError: an error array is neither a numpy array nor a torch tensor.
        ValueError: no curves, a negative error, a non-positive ``threshold``.
    """
    if not errors:
        raise ValueError("plot_error_cdf needs at least one error array")
    if threshold is not None and not threshold > 0:
        raise ValueError(f"threshold must be positive, got {threshold}")
    arrays = {}
    for label, values in errors.items():
        array = _numpy(values, f"errors[{label!r}]").astype(np.float64)
        check_shape(array, "Q", f"errors[{label!r}]")
        if (array < 0).any():
            raise ValueError(f"errors[{label!r}] holds negative errors")
        arrays[label] = array
    low, high = log_axis_limits(np.concatenate(list(arrays.values())), threshold)

    fig = _new_figure(figsize, dpi)
    ax = fig.subplots()
    for label, array in arrays.items():
        found = np.sort(np.clip(array[np.isfinite(array)], low, None))
        share = np.arange(1, found.size + 1) / max(array.size, 1)
        top = share[-1] if found.size else 0.0
        ax.step(
            np.r_[low, found, high],
            np.r_[0.0, share, top],
            where="post",
            label=f"{label} ({found.size} of {array.size})",
        )
    if threshold is not None:
        ax.axvline(threshold, color="tab:red", linestyle="--", label=f"threshold {threshold:g}")
    ax.set_xscale("log")
    ax.set_xlim(low, high)
    ax.set_ylim(0.0, 1.02)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("share of queries within the error")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)
