"""How far query poses lie from a set of reference poses (e.g. the database keyframes).

A query that sits on a database pose is an easy one; reporting the distance and the viewing
angle from each query to its nearest reference beside a recall tells a reader how far the
queries really are from what the database saw.

Example:
    >>> T_ref = torch.eye(4, dtype=torch.float64)[None]
    >>> T_q = torch.eye(4, dtype=torch.float64)[None].clone()
    >>> T_q[0, 0, 3] = 0.5
    >>> nearest_pose_offsets(T_q, T_ref)
    (tensor([0.5000], dtype=torch.float64), tensor([0.], dtype=torch.float64))
"""

from __future__ import annotations

import numpy as np
import torch

from diffloc.checks import check_finite, check_shape

__all__ = ["nearest_pose_offsets", "offset_summary"]


def nearest_pose_offsets(
    T_wc_query: torch.Tensor, T_wc_ref: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Distance to the nearest reference position and the angle to that reference's view.

    Args:
        T_wc_query: (Q, 4, 4) query camera-to-world poses.
        T_wc_ref: (R, 4, 4) reference camera-to-world poses, R >= 1.

    Returns:
        distance_m (Q,) float64: distance from each query's camera centre to the nearest
        reference camera centre; angle_deg (Q,) float64: rotation angle between the query's
        camera orientation and that nearest reference's (0 = same view direction, 180 = facing
        the other way).

    Raises:
        ShapeError: shapes other than (Q, 4, 4) / (R, 4, 4).
        ValueError: non-finite poses or no reference pose.
    """
    check_shape(T_wc_query, "Q,4,4", "T_wc_query")
    check_shape(T_wc_ref, "R,4,4", "T_wc_ref")
    check_finite(T_wc_query, "T_wc_query")
    check_finite(T_wc_ref, "T_wc_ref")
    if T_wc_ref.shape[0] == 0:
        raise ValueError("nearest_pose_offsets needs at least one reference pose")
    query = T_wc_query.to(torch.float64)
    ref = T_wc_ref.to(torch.float64)
    distances = torch.cdist(query[:, :3, 3], ref[:, :3, 3])
    distance_m, nearest = distances.min(dim=1)
    # angle of R_q^T R_r by atan2(|vee(R - R^T)| / 2, (trace R - 1) / 2), accurate near 0 and pi
    R = query[:, :3, :3].transpose(1, 2) @ ref[nearest, :3, :3]
    axis = torch.stack(
        (R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]), dim=-1
    )
    sin = torch.linalg.vector_norm(axis, dim=-1) / 2.0
    cos = (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0
    return distance_m, torch.rad2deg(torch.atan2(sin, cos))


def offset_summary(distance_m: torch.Tensor, angle_deg: torch.Tensor) -> dict[str, float]:
    """Median and 90th percentile of :func:`nearest_pose_offsets`' outputs (Q,), as JSON floats.

    Returns:
        ``{"distance_median_m", "distance_p90_m", "angle_median_deg", "angle_p90_deg"}``.

    Raises:
        ValueError: no queries.

    Example:
        >>> offset_summary(torch.tensor([0.0, 1.0]), torch.tensor([10.0, 20.0]))["distance_p90_m"]
        0.9
    """
    if distance_m.numel() == 0:
        raise ValueError("offset_summary needs at least one query")
    d = np.asarray(distance_m, dtype=np.float64)
    a = np.asarray(angle_deg, dtype=np.float64)
    return {
        "distance_median_m": round(float(np.median(d)), 4),
        "distance_p90_m": round(float(np.quantile(d, 0.9)), 4),
        "angle_median_deg": round(float(np.median(a)), 3),
        "angle_p90_deg": round(float(np.quantile(a, 0.9)), 3),
    }
