"""Submaps of a mapping trajectory by spectral clustering, with overlap (SiLVR, seed 2 III-D3).

Affinity of frames i, j: ``exp(-|p_i - p_j|^2 / (2 s_p^2)) exp(-theta_ij^2 / (2 s_a^2))`` with
``p`` the camera positions and ``theta`` the angle between the viewing directions (camera z
axes). The normalised Laplacian ``I - D^-1/2 A D^-1/2`` gives a spectral embedding (its
eigenvectors of the k smallest eigenvalues, rows normalised, Ng-Jordan-Weiss); k-means on it
gives the clusters. k is configured, or chosen by the largest gap among the smallest
eigenvalues (k >= 2). Each submap is a cluster (its core) plus every other frame within
``overlap_m`` of a core frame, so neighbouring submaps share frames at their boundary.
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.cluster.vq import kmeans2
from scipy.linalg import eigh

from diffloc.checks import check_finite, check_int_at_least, check_number, check_shape
from diffloc.io.atomic import atomic_write_bytes, atomic_write_text

__all__ = [
    "Submap",
    "SubmapConfig",
    "affinity",
    "cluster_trajectory",
    "load_submaps",
    "plot_submaps",
    "save_submaps",
    "serving_submap",
]

FORMAT_VERSION = 1


@dataclass
class SubmapConfig:
    """Settings of the trajectory clustering.

    Attributes:
        num_submaps: k; 0 picks k by the eigengap.
        max_submaps: largest k the eigengap may pick.
        position_sigma_m: s_p, metres.
        angle_sigma_deg: s_a, degrees.
        overlap_m: frames within this distance of a core frame join the submap.
        box_margin_m: margin of the camera bounding box, metres.
        seed: k-means initialisation seed.
    """

    num_submaps: int = 0
    max_submaps: int = 12
    position_sigma_m: float = 3.0
    angle_sigma_deg: float = 90.0
    overlap_m: float = 1.0
    box_margin_m: float = 3.0
    seed: int = 0

    def __post_init__(self) -> None:
        check_int_at_least(self.num_submaps, "num_submaps", 0)
        check_int_at_least(self.max_submaps, "max_submaps", 1)
        check_number(self.position_sigma_m, "position_sigma_m", 0.0, open_low=True)
        check_number(self.angle_sigma_deg, "angle_sigma_deg", 0.0, open_low=True)
        check_number(self.overlap_m, "overlap_m", 0.0)
        check_number(self.box_margin_m, "box_margin_m", 0.0)
        check_int_at_least(self.seed, "seed", 0)


@dataclass
class Submap:
    """One submap: frame indices and the camera bounding box.

    Attributes:
        index: submap number.
        core: sorted frame indices of its cluster.
        frames: sorted frame indices, core plus overlap.
        box_min: world lower corner (3 floats) of the frames' positions minus the margin.
        box_max: upper corner.
    """

    index: int
    core: list[int]
    frames: list[int]
    box_min: list[float]
    box_max: list[float]


def affinity(T_wc: torch.Tensor, position_sigma_m: float, angle_sigma_deg: float) -> np.ndarray:
    """Frame-to-frame affinity (module docstring): T_wc (N, 4, 4) -> (N, N) float64."""
    check_shape(T_wc, "N,4,4", "T_wc")
    check_finite(T_wc, "T_wc")
    T = T_wc.detach().cpu().double().numpy()
    p, z = T[:, :3, 3], T[:, :3, 2]
    d2 = ((p[:, None] - p[None]) ** 2).sum(-1)
    angle = np.arccos(np.clip(z @ z.T, -1.0, 1.0))
    sa = np.deg2rad(angle_sigma_deg)
    return np.exp(-d2 / (2 * position_sigma_m**2) - angle**2 / (2 * sa**2))


def _embedding(a: np.ndarray, k: int, max_k: int) -> tuple[np.ndarray, int]:
    d = 1.0 / np.sqrt(a.sum(axis=1))
    laplacian = np.eye(len(a)) - d[:, None] * a * d[None]
    count = min(len(a), max(k, max_k) + 1)
    values, vectors = eigh(laplacian, subset_by_index=[0, count - 1])
    if k == 0:
        k = int(np.argmax(np.diff(values[1 : max_k + 1]))) + 2
    rows = vectors[:, :k]
    return rows / np.linalg.norm(rows, axis=1, keepdims=True).clip(1e-12), k


def cluster_trajectory(T_wc: torch.Tensor, config: SubmapConfig) -> list[Submap]:
    """Split a mapping trajectory into overlapping submaps.

    Args:
        T_wc: (N, 4, 4) camera-to-world poses of the mapping frames.
        config: clustering settings.

    Returns:
        The submaps, ordered by their first core frame; every frame is in exactly one core.

    Raises:
        ValueError: fewer than two frames, or more submaps asked for than frames.
    """
    check_shape(T_wc, "N,4,4", "T_wc")
    n = len(T_wc)
    if n < 2:
        raise ValueError(f"clustering needs at least 2 frames, got {n}")
    if config.num_submaps > n:
        raise ValueError(f"{config.num_submaps} submaps asked for but only {n} frames")
    a = affinity(T_wc, config.position_sigma_m, config.angle_sigma_deg)
    rows, k = _embedding(a, config.num_submaps, min(config.max_submaps, n - 1))
    rng = np.random.default_rng(config.seed)
    _, labels = kmeans2(rows, k, minit="++", seed=rng)
    positions = T_wc[:, :3, 3].double().numpy()
    d = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    cores = sorted((np.flatnonzero(labels == c) for c in np.unique(labels)), key=lambda c: c[0])
    submaps = []
    for index, core in enumerate(cores):
        frames = np.flatnonzero((d[:, core] <= config.overlap_m).any(axis=1))
        p = positions[frames]
        submaps.append(
            Submap(
                index=index,
                core=core.tolist(),
                frames=frames.tolist(),
                box_min=(p.min(0) - config.box_margin_m).tolist(),
                box_max=(p.max(0) + config.box_margin_m).tolist(),
            )
        )
    return submaps


def serving_submap(
    T_wc: torch.Tensor, submaps: list[Submap], mapping_T_wc: torch.Tensor, config: SubmapConfig
) -> torch.Tensor:
    """The submap that serves each pose: the one whose core frames have the largest affinity
    (position and viewing direction) to it.

    Args:
        T_wc: (Q, 4, 4) render poses.
        submaps: the submaps of the mapping trajectory.
        mapping_T_wc: (N, 4, 4) the mapping poses the submaps index.
        config: the clustering settings (affinity scales).

    Returns:
        (Q,) int64 submap indices.
    """
    check_shape(T_wc, "Q,4,4", "T_wc")
    both = torch.cat((T_wc.double(), mapping_T_wc.double()))
    a = affinity(both, config.position_sigma_m, config.angle_sigma_deg)[: len(T_wc), len(T_wc) :]
    best = np.stack([a[:, s.core].max(axis=1) for s in submaps], axis=1)
    return torch.from_numpy(best.argmax(axis=1))


def save_submaps(path: str | os.PathLike, submaps: list[Submap], config: SubmapConfig) -> None:
    """Write submaps and their config as JSON (atomically)."""
    record = {
        "format_version": FORMAT_VERSION,
        "config": asdict(config),
        "submaps": [asdict(s) for s in submaps],
    }
    atomic_write_text(path, json.dumps(record, indent=1))


def load_submaps(path: str | os.PathLike) -> tuple[list[Submap], SubmapConfig]:
    """Read :func:`save_submaps` output.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a submap file of a known version.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"submap file {path} does not exist")
    try:
        record = json.loads(path.read_text())
        if record.get("format_version") != FORMAT_VERSION:
            raise ValueError(f"format_version {record.get('format_version')!r}")
        return [Submap(**s) for s in record["submaps"]], SubmapConfig(**record["config"])
    except (json.JSONDecodeError, KeyError, TypeError, AttributeError, ValueError) as error:
        raise ValueError(f"{path}: not a diffloc submap file ({error})") from error


def plot_submaps(path: str | os.PathLike, T_wc: torch.Tensor, submaps: list[Submap]) -> None:
    """PNG of the trajectory seen from above, frames coloured by submap, overlap frames ringed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = T_wc[:, :3, 3].double().numpy()
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.plot(p[:, 0], p[:, 1], color="0.8", linewidth=0.8)
    for s in submaps:
        colour = plt.cm.tab10(s.index % 10)
        ax.scatter(p[s.core, 0], p[s.core, 1], s=10, color=colour, label=f"submap {s.index}")
        extra = sorted(set(s.frames) - set(s.core))
        ax.scatter(p[extra, 0], p[extra, 1], s=40, facecolors="none", edgecolors=colour)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(fontsize=7)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())
