"""The pose prior over a query sequence: the last accepted pose orders the next candidates.

:class:`SequencePrior` keeps the last ACCEPTED pose of a sequence and its timestamp; for the
next query it gives the database images near it
(:func:`~diffloc.reloc.pose_prior.prior_references`, the radius grown by the time elapsed),
or ``None`` before the first accepted pose and once the accepted pose is older than
``max_age_s``. :func:`localize_in_order` runs a localiser over a sequence's frames with it.
A pose found but rejected never updates the prior, and the prior never relaxes a threshold:
it only puts its images before the retrieval's
(:meth:`~diffloc.reloc.rendered.RenderedDatabaseLocalizer.localize`).

Example:
    >>> T_db = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    >>> T_db[:, 0, 3] = torch.tensor([0.5, 4.0, 9.0])
    >>> prior = SequencePrior(PosePriorConfig(radius_m=1.0, growth_mps=1.0, max_age_s=5.0), T_db)
    >>> prior.references(0.0) is None  # nothing accepted yet
    True
    >>> prior.update(0.0, True, torch.eye(4, dtype=torch.float64))
    >>> prior.references(1.0), prior.references(4.0)  # radius 2 m, then 5 m
    (tensor([0]), tensor([0, 1]))
    >>> prior.references(6.0) is None  # older than max_age_s
    True
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from typing import Protocol

import torch

from diffloc.checks import check_finite, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.reloc.pose_prior import PosePriorConfig, prior_references
from diffloc.reloc.rendered import RenderedLocalization

__all__ = ["SequencePrior", "localize_in_order"]


class SequencePrior:
    """The last accepted pose of a sequence as a prior for the next query's candidates.

    Args:
        config: the prior's settings (``growth_mps`` must be set).
        T_wc_db: (N, 4, 4) camera-to-world poses of the database images.

    Raises:
        ValueError: ``config.growth_mps`` unset or non-finite database poses.
        ShapeError: ``T_wc_db`` not (N, 4, 4).
    """

    def __init__(self, config: PosePriorConfig, T_wc_db: torch.Tensor) -> None:
        config.radius_at(0.0)  # refuses an unset growth_mps before any work
        check_shape(T_wc_db, "N,4,4", "T_wc_db")
        check_finite(T_wc_db, "T_wc_db")
        self.config = config
        self.T_wc_db = T_wc_db.to(torch.float64)
        self.T_wc: torch.Tensor | None = None
        self.time_s = math.nan

    def references(self, time_s: float) -> torch.Tensor | None:
        """(k,) int64 database images to try first at ``time_s`` (nearest first; possibly
        empty), or ``None`` without an accepted pose of at most ``max_age_s`` before it.

        Raises:
            ValueError: ``time_s`` lies before the accepted pose's.
        """
        if self.T_wc is None:
            return None
        age_s = time_s - self.time_s
        if age_s < 0:
            raise ValueError(
                f"query time {time_s} s lies before the accepted pose's ({self.time_s} s): "
                "the frames must be in time order"
            )
        if age_s > self.config.max_age_s:
            return None
        c = self.config
        return prior_references(
            self.T_wc_db, self.T_wc, c.radius_at(age_s), c.max_angle_deg, c.max_images
        )

    def update(self, time_s: float, accepted: bool, T_wc: torch.Tensor) -> None:
        """Record the answer at ``time_s``: an accepted (4, 4) pose becomes the prior; a
        rejected or missing one changes nothing."""
        if accepted:
            check_shape(T_wc, "4,4", "T_wc")
            check_finite(T_wc, "T_wc")
            self.T_wc, self.time_s = T_wc.to(torch.float64), float(time_s)


class Localizer(Protocol):
    """What :func:`localize_in_order` needs (:class:`RenderedDatabaseLocalizer` is one)."""

    def localize(
        self,
        image: torch.Tensor,
        camera: PinholeCamera,
        references: torch.Tensor | None = None,
        prior: torch.Tensor | None = None,
    ) -> RenderedLocalization: ...


def localize_in_order(
    localizer: Localizer,
    images: Iterable[torch.Tensor],
    times_s: Iterable[float],
    camera: PinholeCamera,
    prior: SequencePrior | None,
) -> Iterator[RenderedLocalization]:
    """Localise a sequence's frames in time order, each with the prior of the answers before.

    Args:
        localizer: the localiser.
        images: (3, H, W) query images in time order.
        times_s: their timestamps in seconds.
        camera: the query camera (size W x H).
        prior: the sequence's prior (fresh); ``None``: every frame on its own.

    Yields:
        One :class:`RenderedLocalization` per frame, lazily.
    """
    for image, time_s in zip(images, times_s, strict=True):
        references = None if prior is None else prior.references(float(time_s))
        result = localizer.localize(image, camera, prior=references)
        if prior is not None:
            prior.update(float(time_s), result.accepted, result.T_wc)
        yield result
