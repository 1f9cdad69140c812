"""How much of a pose's 3D evidence lies on one plane.

A pose found from 2D-3D inliers that all lie on one plane rests on a homography of that plane:
where the plane's texture repeats (a tiled wall, the same panel on every facade), the same
keypoints match the copy on another wall, at another place or turned 90 degrees, and PnP
returns a consistent, confident pose there. Inliers spread over several surfaces (floor and
wall, a corner, furniture) tie the pose to the shape of the scene as well. The validation
(:class:`~diffloc.reloc.validation.ValidationConfig`, ``max_plane_share``) can ask for that.

The share is found by RANSAC over the points, in the frame of the camera that sees them:
``hypotheses`` planes through three points each (one seeded generator, so the share is
reproducible), a point supporting a plane when its distance to it is at most
``max(tolerance_m, relative_tolerance * median depth)`` (a plane seen from afar is measured
less precisely), and the share is the largest support over all hypotheses and the number of
points.

Example (a wall at z = 4 above y = 1 and a floor at y = 1.5 between 1 and 3 m deep, 30
points each):
    >>> g = torch.Generator().manual_seed(0)
    >>> wall = torch.cat([torch.rand(30, 2, generator=g) * 3 - 2, torch.full((30, 1), 4.0)], 1)
    >>> floor = torch.rand(30, 3, generator=g) * 2 + 1
    >>> floor[:, 1] = 1.5
    >>> dominant_plane_share(wall), dominant_plane_share(torch.cat([wall, floor]))
    (1.0, 0.5)
"""

from __future__ import annotations

import torch

from diffloc.checks import check_shape

__all__ = ["dominant_plane_share"]


def dominant_plane_share(
    points: torch.Tensor,
    tolerance_m: float = 0.05,
    relative_tolerance: float = 0.02,
    hypotheses: int = 256,
    seed: int = 0,
) -> float:
    """Largest share of ``points`` within the tolerance of one plane (module docstring).

    Args:
        points: (N, 3) points in a camera frame (z = depth, > 0 in front of the camera).
        tolerance_m: smallest distance (metres) from a plane that still supports it.
        relative_tolerance: the tolerance grows to this fraction of the points' median depth.
        hypotheses: planes tried, each through three points drawn with replacement.
        seed: seed of the generator that draws them.

    Returns:
        The share in [0, 1]; 1.0 for fewer than four points (three always lie on a plane).

    Raises:
        ShapeError: ``points`` not (N, 3).
        ValueError: a negative tolerance, or fewer than one hypothesis.
    """
    check_shape(points, "N,3", "points")
    if tolerance_m < 0 or relative_tolerance < 0:
        raise ValueError(
            f"plane tolerances must be >= 0, got {tolerance_m} m and {relative_tolerance}"
        )
    if hypotheses < 1:
        raise ValueError(f"hypotheses must be >= 1, got {hypotheses}")
    n = len(points)
    if n < 4:
        return 1.0
    x = points.to(torch.float64)
    generator = torch.Generator().manual_seed(seed)
    sample = x[torch.randint(0, n, (hypotheses, 3), generator=generator)]  # (K, 3, 3)
    normals = torch.linalg.cross(sample[:, 1] - sample[:, 0], sample[:, 2] - sample[:, 0])
    lengths = torch.linalg.vector_norm(normals, dim=1)
    proper = lengths > 1e-9 * (1.0 + x.abs().max())  # three distinct, non-collinear points
    if not bool(proper.any()):
        return 1.0  # every draw degenerate: the points lie on a line or coincide
    normals = normals[proper] / lengths[proper, None]
    offsets = (normals * sample[proper, 0]).sum(dim=1)  # (K',) plane: n . x = d
    distances = (x @ normals.T - offsets).abs()  # (N, K')
    tolerance = max(tolerance_m, relative_tolerance * float(x[:, 2].median()))
    return float((distances <= tolerance).sum(dim=0).max()) / n
