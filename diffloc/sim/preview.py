"""A preview figure of a simulated dataset: sample frames and a top-down map."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure


def write_preview(
    path: Path,
    frames: list[tuple[str, torch.Tensor]],
    map_points: np.ndarray,
    trajectories: dict[str, np.ndarray],
    title: str,
) -> None:
    """Save a PNG with up to four frames and a top-down view of the map and trajectories.

    Args:
        path: output PNG path.
        frames: (caption, image (3, H, W) float in [0, 1]) pairs.
        map_points: (N, 3) lidar map points in the world frame, drawn coloured by height.
        trajectories: sequence name -> (M, 3) camera positions.
        title: figure title.
    """
    frames = frames[:4]
    # matplotlib's object API: no pyplot state, and the caller's backend (e.g. a notebook's
    # inline one) is left alone.
    fig = Figure(figsize=(16, 7.5), dpi=80)
    grid = fig.add_gridspec(2, 4, width_ratios=[1, 1, 1.35, 1.35])
    for k, (caption, image) in enumerate(frames):
        ax = fig.add_subplot(grid[k // 2, k % 2])
        ax.imshow(image.permute(1, 2, 0).clamp(0, 1).numpy())
        ax.set_title(caption, fontsize=10)
        ax.axis("off")
    ax = fig.add_subplot(grid[:, 2:])
    if len(map_points):
        step = max(1, len(map_points) // 200_000)
        pts = map_points[::step]
        ax.scatter(pts[:, 0], pts[:, 1], c=pts[:, 2], s=0.2, cmap="Greys", alpha=0.6, linewidths=0)
    for name, positions in trajectories.items():
        ax.plot(positions[:, 0], positions[:, 1], lw=1.5, label=name)
        ax.plot(positions[0, 0], positions[0, 1], "o", ms=4, color=ax.lines[-1].get_color())
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("top-down: lidar map (grey by height) and camera trajectories")
    ax.legend(loc="upper right", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, metadata={"Software": None})
