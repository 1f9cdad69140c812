"""Checks that camera or sensor positions lie in the free space of a simulated world."""

from __future__ import annotations

import numpy as np
import torch

from diffloc.checks import check_finite, check_shape
from diffloc.render.raycast import MeshRaycaster


def _probe_directions(count: int = 64) -> torch.Tensor:
    """(count, 3) unit directions spread evenly on the sphere (Fibonacci lattice)."""
    index = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * index / count
    azimuth = index * np.pi * (3.0 - np.sqrt(5.0))
    radius = torch.sqrt(1.0 - z**2)
    return torch.stack([radius * torch.cos(azimuth), radius * torch.sin(azimuth), z], dim=1)


def check_free_space(
    raycaster: MeshRaycaster,
    bounds: np.ndarray,
    positions: torch.Tensor,
    min_clearance_m: float = 0.05,
    what: str = "camera",
) -> None:
    """Raise ``ValueError`` unless every position is inside ``bounds`` and in free space.

    A position is inside a solid (a wall, a floor slab, furniture) when most rays cast from it
    first hit the back of a triangle, because all solids are closed with outward normals.

    Args:
        raycaster: caster of the world mesh.
        bounds: (2, 3) min and max corner of the world.
        positions: (N, 3) positions in the world frame.
        min_clearance_m: a position closer than this to any surface is rejected too.
        what: how to call the positions in error messages.
    """
    check_shape(bounds, "2,3", "bounds")
    check_shape(positions, "N,3", f"{what} positions")
    check_finite(positions, f"{what} positions")
    low = torch.as_tensor(bounds[0], dtype=torch.float64)
    high = torch.as_tensor(bounds[1], dtype=torch.float64)
    p = positions.to(torch.float64)
    outside = ((p < low) | (p > high)).any(dim=1)
    if outside.any():
        i = int(torch.nonzero(outside)[0])
        raise ValueError(
            f"{what} {i} at {p[i].tolist()} is outside the world bounds "
            f"{low.tolist()} .. {high.tolist()}"
        )
    directions = _probe_directions()
    origins = p[:, None, :].expand(-1, len(directions), -1).reshape(-1, 3)
    rays = directions[None].expand(len(p), -1, -1).reshape(-1, 3)
    hits = raycaster.cast(origins, rays)
    facing = (hits.normals.to(torch.float64) * rays).sum(-1)
    back = (hits.hit & (facing > 0)).reshape(len(p), -1).to(torch.float64).mean(dim=1)
    nearest = torch.where(hits.hit, hits.distance, torch.full_like(hits.distance, np.inf))
    nearest = nearest.reshape(len(p), -1).min(dim=1).values
    inside = back > 0.5
    if inside.any():
        i = int(torch.nonzero(inside)[0])
        raise ValueError(f"{what} {i} at {p[i].tolist()} is inside a wall or another solid")
    close = nearest < min_clearance_m
    if close.any():
        i = int(torch.nonzero(close)[0])
        raise ValueError(
            f"{what} {i} at {p[i].tolist()} is {float(nearest[i]):.3f} m from a surface "
            f"(less than {min_clearance_m} m)"
        )
