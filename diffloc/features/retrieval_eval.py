"""Ground truth for image retrieval: which database frames see the same place as a query.

A database frame is a correct retrieval for a query when the two camera poses are within a
distance and a rotation angle of each other (defaults 2 m and 30 degrees). The same pose test
labels positives and negatives for NetVLAD training.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from diffloc.checks import ShapeError, check_finite, check_shape

__all__ = ["pairwise_pose_distances", "retrieval_recall"]


def _poses(T: torch.Tensor, name: str) -> torch.Tensor:
    T = torch.as_tensor(T).to(torch.float64)
    check_shape(T, "N,4,4", name)
    check_finite(T, name)
    return T


def pairwise_pose_distances(
    T_wa: torch.Tensor, T_wb: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-centre distances and relative rotation angles between two sets of poses.

    Args:
        T_wa: (A, 4, 4) camera-to-world poses.
        T_wb: (B, 4, 4) camera-to-world poses.

    Returns:
        ``(distance_m (A, B), angle_rad (A, B))`` float64: ``||t_a - t_b||`` and the angle of
        ``R_a^T R_b``.

    Example:
        >>> d, a = pairwise_pose_distances(torch.eye(4)[None], torch.eye(4)[None])
        >>> float(d), float(a)
        (0.0, 0.0)
    """
    T_wa, T_wb = _poses(T_wa, "T_wa"), _poses(T_wb, "T_wb")
    distance = torch.cdist(T_wa[:, :3, 3], T_wb[:, :3, 3])
    # trace(R_a^T R_b) = sum_ij R_a[i, j] R_b[i, j]
    trace = torch.einsum("aij,bij->ab", T_wa[:, :3, :3], T_wb[:, :3, :3])
    angle = torch.acos(((trace - 1.0) / 2.0).clamp(-1.0, 1.0))
    return distance, angle


def retrieval_recall(
    query_T_wc: torch.Tensor,
    db_T_wc: torch.Tensor,
    retrieved: torch.Tensor,
    max_distance_m: float = 2.0,
    max_angle_deg: float = 30.0,
    ks: Sequence[int] = (1, 5),
) -> dict[int, float]:
    """Recall@k: the fraction of queries with a correct frame among their top-k retrievals.

    Args:
        query_T_wc: (Q, 4, 4) true query poses.
        db_T_wc: (N, 4, 4) database poses.
        retrieved: (Q, K) database indices, best first (K >= max(ks)).
        max_distance_m: largest camera-centre distance of a correct retrieval.
        max_angle_deg: largest relative rotation angle of a correct retrieval.
        ks: the k of each recall@k.

    Returns:
        ``{k: recall@k}`` with values in [0, 1].

    Raises:
        ShapeError: mismatched shapes, or fewer than ``max(ks)`` retrievals per query.
        ValueError: indices outside the database, an empty ``ks`` or non-positive k.

    Example:
        >>> T = torch.eye(4, dtype=torch.float64)[None].repeat(3, 1, 1)
        >>> retrieval_recall(T[:1], T, torch.tensor([[2, 0]]), ks=(1, 2))
        {1: 1.0, 2: 1.0}
    """
    query_T_wc, db_T_wc = _poses(query_T_wc, "query_T_wc"), _poses(db_T_wc, "db_T_wc")
    retrieved = torch.as_tensor(retrieved)
    check_shape(retrieved, "Q,K", "retrieved")
    if retrieved.shape[0] != query_T_wc.shape[0]:
        raise ShapeError(
            f"retrieved has {retrieved.shape[0]} rows but there are {len(query_T_wc)} queries"
        )
    if not ks or min(ks) < 1:
        raise ValueError(f"ks must be positive integers, got {ks}")
    if retrieved.shape[1] < max(ks):
        raise ShapeError(f"retrieved has {retrieved.shape[1]} columns, need {max(ks)}")
    if retrieved.numel() and (retrieved.min() < 0 or retrieved.max() >= len(db_T_wc)):
        raise ValueError(f"retrieved indices must lie in [0, {len(db_T_wc)})")
    distance, angle = pairwise_pose_distances(query_T_wc, db_T_wc)
    correct = (distance <= max_distance_m) & (angle <= math.radians(max_angle_deg))
    hit = torch.gather(correct, 1, retrieved.long())
    num_queries = max(len(query_T_wc), 1)
    return {int(k): float(hit[:, :k].any(dim=1).sum()) / num_queries for k in ks}
