"""A pose prior for the rendered-database localiser's candidate list (beyond seed 2).

A query *sequence* moves continuously: after a pose was accepted, the next query lies near it.
Seed 2's Algorithm 1 localises each image on its own; here the database images near the last
accepted pose (within a radius that grows with the time elapsed since it, their optical axes
within a maximum angle of its) are tried before the retrieval's
(:mod:`diffloc.reloc.sequence_prior` runs it over a sequence). The prior only orders the
candidates: every pose is still validated on its own image.

Example:
    >>> T_db = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    >>> T_db[:, 0, 3] = torch.tensor([3.0, 0.5, 1.0])
    >>> prior_references(T_db, torch.eye(4, dtype=torch.float64), 2.0, 45.0)
    tensor([1, 2])
    >>> PosePriorConfig(radius_m=1.0, growth_mps=0.5).radius_at(4.0)
    3.0
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from diffloc.checks import check_finite, check_number, check_positive_int, check_shape

__all__ = ["PosePriorConfig", "prior_references"]


@dataclass
class PosePriorConfig:
    """Settings of the pose prior (``task.localizer.prior``; ``None`` there: no prior).

    Attributes:
        radius_m: search radius around the last accepted camera centre right after it.
        growth_mps: metres the radius grows per second elapsed since the accepted pose (the
            platform's top speed); ``None``: the scene kind's (``task.prior_growth_mps``,
            1 m/s indoors, 6 m/s outdoors, ``task/scene/crossmodal_<scene>.yaml``).
        max_angle_deg: largest angle between a database image's optical axis and the prior's.
        max_images: most prior images tried (the nearest), before the retrieval's.
        max_age_s: the prior is dropped once this many seconds passed since the accepted pose.

    Raises:
        ValueError: a value out of range, named as ``task.localizer.prior.<field>``.
    """

    radius_m: float = 2.0
    growth_mps: float | None = None
    max_angle_deg: float = 60.0
    max_images: int = 8
    max_age_s: float = 10.0

    def __post_init__(self) -> None:
        where = "task.localizer.prior"
        check_number(self.radius_m, f"{where}.radius_m", 0.0, open_low=True)
        if self.growth_mps is not None:
            check_number(self.growth_mps, f"{where}.growth_mps", 0.0)
        check_number(self.max_angle_deg, f"{where}.max_angle_deg", 0.0, 180.0, open_low=True)
        check_positive_int(self.max_images, f"{where}.max_images")
        check_number(self.max_age_s, f"{where}.max_age_s", 0.0, open_low=True)

    def radius_at(self, age_s: float) -> float:
        """The search radius ``age_s`` seconds after the accepted pose.

        Raises:
            ValueError: ``growth_mps`` is unset (``None``) or ``age_s`` negative.
        """
        if self.growth_mps is None:
            raise ValueError(
                "task.localizer.prior.growth_mps is unset: set it or task.prior_growth_mps"
            )
        check_number(age_s, "age_s", 0.0)
        return self.radius_m + self.growth_mps * age_s


def prior_references(
    T_wc_db: torch.Tensor,
    T_wc_prior: torch.Tensor,
    radius_m: float,
    max_angle_deg: float,
    max_images: int | None = None,
) -> torch.Tensor:
    """Database images near a prior pose, nearest first.

    An image qualifies when its camera centre lies within ``radius_m`` of the prior's and the
    angle between its optical axis (camera z) and the prior's is at most ``max_angle_deg``.

    Args:
        T_wc_db: (N, 4, 4) camera-to-world poses of the database images.
        T_wc_prior: (4, 4) camera-to-world prior pose.
        radius_m: largest centre distance in metres (>= 0).
        max_angle_deg: largest optical-axis angle in degrees, in [0, 180].
        max_images: keep at most this many (the nearest); ``None``: all.

    Returns:
        (k,) int64 database indices ordered by centre distance (ties by index); empty when
        none qualifies.

    Raises:
        ShapeError: wrong shapes.
        ValueError: a non-finite pose, a negative radius or an angle outside [0, 180].

    Example:
        >>> T_db = torch.eye(4).repeat(3, 1, 1)
        >>> T_db[:, 2, 3] = torch.tensor([1.5, 0.5, 0.7])  # along the optical axis
        >>> T_db[2, :3, :3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0]))  # looks back
        >>> prior_references(T_db, torch.eye(4), 2.0, 30.0)
        tensor([1, 0])
        >>> prior_references(T_db, torch.eye(4), 2.0, 180.0, max_images=2)
        tensor([1, 2])
    """
    check_shape(T_wc_db, "N,4,4", "T_wc_db")
    check_shape(T_wc_prior, "4,4", "T_wc_prior")
    check_finite(T_wc_db, "T_wc_db")
    check_finite(T_wc_prior, "T_wc_prior")
    check_number(radius_m, "radius_m", 0.0)
    check_number(max_angle_deg, "max_angle_deg", 0.0, 180.0)
    T_db, T_prior = T_wc_db.to(torch.float64), T_wc_prior.to(torch.float64)
    distance = torch.linalg.vector_norm(T_db[:, :3, 3] - T_prior[:3, 3], dim=-1)
    cosine = (T_db[:, :3, 2] @ T_prior[:3, 2]).clamp(-1.0, 1.0)
    # compare cosines, with a small slack so an axis exactly at the limit qualifies
    keep = (distance <= radius_m) & (cosine >= math.cos(math.radians(max_angle_deg)) - 1e-12)
    index = torch.nonzero(keep).flatten()
    order = torch.sort(distance[index], stable=True).indices
    return index[order][:max_images]
