"""Render samples on the mapping trajectory where the free-space skeleton leaves it uncovered.

Seed 2 samples render poses on each floor's free-path skeleton at a camera height above that
floor. Places between floors (a staircase, a ramp) and rooms the skeleton misses get no render,
and a query there has nothing near to be localised against. A lidar map comes with the
trajectory it was built from: the sensor went there, so the space is free and reachable.
Beyond seed 2, the trajectory's camera poses are walked in time order and one becomes a sample
wherever it lies farther than ``gap_m`` (3D distance of camera centres) from every sample taken
so far, the skeleton's first; the sample's forward direction is that camera's optical axis in
the horizontal plane, its height the camera's own.

Example (a skeleton sample at the origin; a trajectory going up a stair along +x):
    >>> T = torch.eye(4, dtype=torch.float64).repeat(6, 1, 1)
    >>> T[:, :3, :3] = torch.tensor([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # looks along +x
    >>> T[:, 0, 3] = torch.arange(6.0)  # 0, 1, ..., 5 m along x
    >>> T[:, 2, 3] = 0.5 * torch.arange(6.0)  # climbing 0.5 m per metre
    >>> positions, forward = trajectory_samples(T, torch.zeros(1, 3), gap_m=1.5)
    >>> positions[:, 0].tolist(), forward.tolist()
    ([2.0, 4.0], [[1.0, 0.0], [1.0, 0.0]])
"""

from __future__ import annotations

import math

import torch

from diffloc.checks import check_finite, check_shape

__all__ = ["trajectory_samples"]


def trajectory_samples(
    T_wc: torch.Tensor, taken: torch.Tensor, gap_m: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Trajectory cameras that become render samples (module docstring).

    Args:
        T_wc: (T, 4, 4) camera-to-world poses of the trajectory in time order (OpenCV camera:
            z is the optical axis).
        taken: (S, 3) centres of the samples already taken (the skeleton's; S may be 0).
        gap_m: a camera becomes a sample when it lies farther than this from every sample.

    Returns:
        ``(positions, forward_xy)``: (K, 3) float64 camera centres and (K, 2) float64 unit
        forward directions of the new samples, in time order. Cameras looking straight up or
        down (no horizontal direction) are skipped.

    Raises:
        ShapeError: wrong shapes.
        ValueError: NaN/inf poses or a ``gap_m`` that is not a positive finite number.
    """
    check_shape(T_wc, "T,4,4", "T_wc")
    check_shape(taken, "S,3", "taken")
    check_finite(T_wc, "T_wc")
    if not (isinstance(gap_m, int | float) and 0 < gap_m < math.inf):
        raise ValueError(f"trajectory gap_m must be a positive finite number, got {gap_m!r}")
    centres = T_wc[:, :3, 3].to(torch.float64)
    axis = T_wc[:, :2, 2].to(torch.float64)
    length = torch.linalg.vector_norm(axis, dim=1)
    horizontal = length > 1e-6
    # Distance of every camera to its nearest sample, lowered as samples are added.
    nearest = torch.full((len(centres),), math.inf, dtype=torch.float64)
    if len(taken):
        nearest = torch.cdist(centres, taken.to(torch.float64)).amin(1)
    chosen = []
    for i in range(len(centres)):  # greedy in time order: one step per trajectory camera
        if nearest[i] <= gap_m or not horizontal[i]:
            continue
        chosen.append(i)
        nearest = torch.minimum(nearest, torch.linalg.vector_norm(centres - centres[i], dim=1))
    index = torch.tensor(chosen, dtype=torch.int64)
    return centres[index], axis[index] / length[index, None]
