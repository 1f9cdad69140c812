"""Which rendered views a hybrid database adds to the real images: those no real image covers.

A hybrid database (beyond seed 2) holds the mapping run's real images, which match queries
taken along the mapping route best, plus renders of the map at the render poses where the
mapping run never looked: a query driving the route the other way, or looking sideways, finds
its place among the renders. A render is *covered* when some real image was taken within
``max_distance_m`` of it looking within ``max_angle_deg`` of its direction (the optical axes'
angle), the bounds under which seed 2 counts a retrieved image as the right place (the render
spacing and 45 deg); the hybrid database keeps the renders that are not covered.

Example:
    One real image at the origin looking along +z; renders beside it looking the same way, back
    and sideways, and one 5 m away looking the same way:

    >>> import math, torch
    >>> def pose(x, yaw_deg):
    ...     T = torch.eye(4, dtype=torch.float64)
    ...     c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    ...     T[:3, :3] = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    ...     T[0, 3] = x
    ...     return T
    >>> real = pose(0.0, 0.0)[None]
    >>> renders = torch.stack([pose(0.5, 0), pose(0.5, 180), pose(0.5, 90), pose(5.0, 0)])
    >>> uncovered_views(renders, real, max_distance_m=2.0, max_angle_deg=45.0)
    tensor([False,  True,  True,  True])
"""

from __future__ import annotations

import math

import torch

from diffloc.checks import check_finite, check_shape

__all__ = ["check_coverage_bounds", "uncovered_views"]


def check_coverage_bounds(max_distance_m: float, max_angle_deg: float) -> None:
    """Refuse coverage bounds out of range: a distance not > 0, an angle not in (0, 180].

    Raises:
        ValueError: the first bound out of range, named.
    """
    if not (math.isfinite(max_distance_m) and max_distance_m > 0.0):
        raise ValueError(f"max_distance_m must be a positive number, got {max_distance_m!r}")
    if not 0.0 < max_angle_deg <= 180.0:
        raise ValueError(f"max_angle_deg must be in (0, 180], got {max_angle_deg!r}")


def uncovered_views(
    T_wc: torch.Tensor,
    real_T_wc: torch.Tensor,
    max_distance_m: float,
    max_angle_deg: float,
) -> torch.Tensor:
    """Mask of the views ``T_wc`` that no real image covers.

    A view is covered when a real image's camera centre lies within ``max_distance_m`` of its
    centre and the angle between the two optical axes (camera +z) is at most
    ``max_angle_deg``.

    Args:
        T_wc: (M, 4, 4) camera-to-world poses of the candidate (rendered) views.
        real_T_wc: (N, 4, 4) camera-to-world poses of the real images, N >= 0.
        max_distance_m: camera-centre distance bound, metres, > 0.
        max_angle_deg: optical-axis angle bound, degrees, in (0, 180].

    Returns:
        (M,) bool, True where no real image covers the view (every view when N = 0).

    Raises:
        ShapeError: poses not (M, 4, 4) / (N, 4, 4).
        ValueError: NaN/inf poses, a bound out of range.
    """
    check_shape(T_wc, "M,4,4", "T_wc")
    check_shape(real_T_wc, "N,4,4", "real_T_wc")
    check_finite(T_wc, "T_wc")
    check_finite(real_T_wc, "real_T_wc")
    check_coverage_bounds(max_distance_m, max_angle_deg)
    T, R = T_wc.to(torch.float64), real_T_wc.to(torch.float64)
    near = torch.cdist(T[:, :3, 3], R[:, :3, 3]) <= max_distance_m  # (M, N)
    cos = T[:, :3, 2] @ R[:, :3, 2].T  # (M, N) cosines of the optical axes' angles
    aligned = cos >= math.cos(math.radians(max_angle_deg)) - 1e-12
    return ~(near & aligned).any(dim=1)
