"""A check of a refined pose on evidence the refinement did not fit: feature matches.

The refinement fits the photometric cost of a small render (e.g. 80x60). A move that lowers
that cost can still walk away from the true pose (a local minimum of the cost that fits
better than the start, itself off). This check looks at the query and the map's render at
the pose with other evidence: XFeat keypoints matched (mutual nearest neighbours of their
descriptors) between the query and the render at a larger size (e.g. 256x192). If the pose
is right, a render keypoint and its query match lie at the same pixel: reprojecting the
render keypoint by its rendered depth into the query at the very pose the render was made
from gives back its own pixel, so the reprojection error of a match *is* its displacement
``|u_query - u_render|``. A match is aligned when that displacement is at most
``inlier_px``; wrong matches land anywhere and are rarely aligned.

The refined pose passes if its render has at least ``min_inliers`` aligned matches, at least
``min_fraction`` of all its matches aligned, and at least ``min_gain`` times as many aligned
as the render at the initial pose: a move the matches do not confirm is refused.

Usage::

    verify = match_alignment_check(model, query_rgb, camera, XFeatExtractor(XFeatConfig()))
    result = refine_pose_by_rendering(model, query_small, T_wc, small_camera, verify=verify)
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from diffloc.checks import check_shape
from diffloc.features.local import Features, LocalFeatureExtractor
from diffloc.features.matching import match_descriptors
from diffloc.geometry.camera import PinholeCamera
from diffloc.optim.render_refine.linearization import DifferentiableMap
from diffloc.optim.render_refine.residuals import colour

__all__ = [
    "MatchCheckConfig",
    "MatchEvidence",
    "Verifier",
    "match_alignment_check",
    "match_displacements",
]


@dataclass
class MatchCheckConfig:
    """Settings of :func:`match_alignment_check`.

    Attributes:
        width: the query and the renders are compared at this width (the camera scaled,
            aspect kept); XFeat works on multiples of 32 pixels, so 256 (x192) is exact.
        inlier_px: a match is aligned when its displacement is at most this many pixels at
            ``width``.
        min_inliers: the refined pose needs at least this many aligned matches ...
        min_fraction: ... this fraction of its matches aligned ...
        min_gain: ... and at least this many times the aligned matches of the initial pose.
            ``min_fraction`` and ``min_gain`` were chosen on indoor seed 0 only (18 starts
            10 cm / 2 deg and 30 cm / 5 deg off through a trained field,
            ``experiments/results/render_refine_nerf_safe_indoor_seed0_tune.md``): the rule
            of 2 px that accepts no move ending farther from the truth than its start and the
            most of the others (14 of 16), the stricter one of a tie. Good moves from 10 cm
            ended with 45-59 % of their matches aligned; the one wrong move accepted without
            the check, 19 %.

    Raises:
        ValueError: a setting out of its range (the message names it).

    Example:
        >>> MatchCheckConfig().width
        256
    """

    width: int = 256
    inlier_px: float = 2.0
    min_inliers: int = 20
    min_fraction: float = 0.25
    min_gain: float = 1.5

    def __post_init__(self) -> None:
        if self.width < 32:
            raise ValueError(f"width must be >= 32 (XFeat's smallest image), got {self.width}")
        if not (math.isfinite(self.inlier_px) and self.inlier_px > 0):
            raise ValueError(f"inlier_px must be positive, got {self.inlier_px}")
        if self.min_inliers < 0:
            raise ValueError(f"min_inliers must be >= 0, got {self.min_inliers}")
        if not 0.0 <= self.min_fraction <= 1.0:
            raise ValueError(f"min_fraction must be in [0, 1], got {self.min_fraction}")
        if not (math.isfinite(self.min_gain) and self.min_gain >= 0):
            raise ValueError(f"min_gain must be >= 0, got {self.min_gain}")


@dataclass(frozen=True)
class MatchEvidence:
    """Matches of ``B`` queries with the renders at their initial and refined poses.

    Attributes:
        displacement_before: ``B`` tensors (K_b,): pixel displacement of each match with the
            render at the initial pose (at the check's width).
        displacement_after: the same at the refined pose.
        inliers_before: (B,) aligned matches at the initial pose.
        inliers_after: (B,) aligned matches at the refined pose.
        passed: (B,) bool, the rule of the module doc.
    """

    displacement_before: tuple[torch.Tensor, ...]
    displacement_after: tuple[torch.Tensor, ...]
    inliers_before: torch.Tensor
    inliers_after: torch.Tensor
    passed: torch.Tensor


Verifier = Callable[[torch.Tensor, torch.Tensor], MatchEvidence]
"""``verify(T_init (B, 4, 4), T_refined (B, 4, 4)) -> MatchEvidence``."""


def _as_extractor_image(image: torch.Tensor) -> torch.Tensor:
    return image.float().clamp(0.0, 1.0)


def match_displacements(
    model: DifferentiableMap,
    query: list[Features],
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    extractor: LocalFeatureExtractor,
) -> tuple[torch.Tensor, ...]:
    """Displacements of the matches of each query with the map's render at its pose.

    Args:
        model: the map.
        query: ``B`` query features at ``camera``'s size.
        T_wc: (B, 4, 4) poses to render at.
        camera: the camera of the check.
        extractor: the local features (the same that made ``query``).

    Returns:
        ``B`` tensors (K_b,) of pixel displacements ``|u_query - u_render|`` of the mutual
        nearest-neighbour matches.
    """
    check_shape(T_wc, f"{len(query)},4,4", "T_wc")
    render = _as_extractor_image(colour(model.render(T_wc, camera)))
    rendered = extractor.extract(render)
    out = []
    for q, r in zip(query, rendered, strict=True):
        pairs = match_descriptors(q.descriptors, r.descriptors).indices
        out.append((q.keypoints[pairs[:, 0]] - r.keypoints[pairs[:, 1]]).norm(dim=-1))
    return tuple(out)


def match_alignment_check(
    model: DifferentiableMap,
    image: torch.Tensor,
    camera: PinholeCamera,
    extractor: LocalFeatureExtractor,
    config: MatchCheckConfig | None = None,
) -> Verifier:
    """The :data:`Verifier` of queries ``image`` against renders of ``model`` (module doc).

    Args:
        model: the map the refinement renders.
        image: (B, 3, H, W) query images in [0, 1] at ``camera``'s size (area-resampled to
            the check's width).
        camera: the query camera.
        extractor: local features (XFeat in the experiments).
        config: settings (default :class:`MatchCheckConfig`).

    Returns:
        ``verify(T_init, T_refined) -> MatchEvidence``.

    Raises:
        ShapeError: an image not (B, 3, H, W) at the camera's size.
    """
    cfg = MatchCheckConfig() if config is None else config
    check_shape(image, f"B,3,{camera.height},{camera.width}", "image")
    check_camera = camera.scaled(cfg.width / camera.width)
    size = (check_camera.height, check_camera.width)

    @functools.cache
    def query() -> list[Features]:  # extracted on the first call only
        return extractor.extract(_as_extractor_image(F.interpolate(image, size, mode="area")))

    def count(displacements: tuple[torch.Tensor, ...]) -> torch.Tensor:
        return torch.stack([(d <= cfg.inlier_px).sum() for d in displacements])

    def verify(T_init: torch.Tensor, T_refined: torch.Tensor) -> MatchEvidence:
        before = match_displacements(model, query(), T_init, check_camera, extractor)
        after = match_displacements(model, query(), T_refined, check_camera, extractor)
        n_before, n_after = count(before), count(after)
        matches = torch.tensor([len(d) for d in after])
        passed = (
            (n_after >= cfg.min_inliers)
            & (n_after >= cfg.min_fraction * matches)
            & (n_after >= cfg.min_gain * n_before)
        )
        return MatchEvidence(before, after, n_before, n_after, passed)

    return verify
