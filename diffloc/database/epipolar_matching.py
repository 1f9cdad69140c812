"""Pose-independent association of a new keyframe with the map points of covisible keyframes.

The builder's guided search (:func:`diffloc.features.matching.match_guided`) looks for each map
point near its projection at the new keyframe's pose. When the database poses are noisy (seed 1
Table III) the projection is off by tens of pixels; the search then either misses the true
keypoint or accepts a wrong one near the wrong projection, and these wrong tracks pull the
surfel optimisation towards the noisy poses. This module associates without using any
position:

1. every keypoint of the new keyframe is matched to the fused descriptors of the candidate map
   points (those of the covisible keyframes) by mutual nearest neighbours and Lowe's ratio test;
2. optionally (``max_point_distance_m``) a match is kept only when its map point lies within that
   distance of a surfel the keypoint sees at the new keyframe's pose (the surfel at its pixel or
   one of its neighbouring surfels, so keypoints on depth edges and surfel gaps keep both
   sides). Both are surfels of the one lidar map, each reached through one noisy camera pose,
   so for a true match they differ by about the two position errors (and a surfel radius),
   whatever the depth; a descriptor match to a repeated structure elsewhere on the same
   epipolar line (a row of windows along a straight drive, where all keyframes' epipolar
   geometries nearly coincide) is metres away;
3. the matches are verified two-view: for the ``verify_keyframes`` covisible keyframes that
   observe most matched points, an essential matrix between that keyframe's detected keypoints
   and the new keypoints is fitted by RANSAC
   (:func:`diffloc.geometry.essential_ransac.essential_check`, which needs only the
   intrinsics); a match is kept when it is an inlier of every successful
   check whose keyframe observes its point, and at least one such check exists.

A wrong match that happens to lie on one keyframe's epipolar line is unlikely to lie on the
line of another keyframe with a different baseline, hence "every" rather than "any".

Usage (inside :class:`diffloc.database.builder.DatabaseBuilder`, with a database under
construction)::

    g = torch.Generator().manual_seed(0)
    kp, pts = match_epipolar(db, covisible, features, camera, EpipolarMatchingConfig(), g)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from diffloc.database.database import VisualDatabase
from diffloc.features.local import Features
from diffloc.features.matching import match_descriptors
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.essential_ransac import EssentialCheckConfig, essential_check

__all__ = ["EpipolarMatchingConfig", "match_epipolar"]


@dataclass
class EpipolarMatchingConfig:
    """Settings of :func:`match_epipolar`.

    Attributes:
        candidate_keyframes: only the map points of this many covisible keyframes, those with
            most keypoints on the new keyframe's surfels, are match candidates (ORB-SLAM's
            local map of the best covisible keyframes); ``None`` for all covisible keyframes.
            Nearly all verified matches are points of the best two or three (on the indoor
            scene 99.7 % are seen by one of the best ten), while the candidates, and the cost
            of the descriptor distances, grow with every revisit. Default ``None``: with 10
            the default scene's sigma-0.4 database optimised to 0.28 instead of 0.26 m (2
            threads; 0.25 m at 1 thread), about the spread of the RANSAC decisions, but
            enough to move Table III's recall@0.3 m from 83 to 65 %; 10 saves ~8 ms per image.
        max_point_distance_m: largest distance (metres) between a matched map point and the
            nearest surfel centre the keypoint sees at the new keyframe's pose (its own and
            neighbouring surfels), or ``None`` for no 3D gate. A true match is off by about
            the difference of two keyframes' position errors: with Gaussian errors of ``s``
            metres per axis, allow ``~4 s`` on top of a floor of a few surfel radii
            (``task=build_db`` adds ``db.point_gate_m_per_prior_m`` times the user's
            ``db.pose_prior_sigma_m`` to this floor).
        verify_keyframes: how many covisible keyframes (most matched points first) check the
            matches with an essential matrix.
        essential: RANSAC settings of the check (its ``min_inliers`` is the fewest matches
            a keyframe must share to verify anything).
    """

    candidate_keyframes: int | None = None
    max_point_distance_m: float | None = 0.5
    verify_keyframes: int = 3
    essential: EssentialCheckConfig = field(
        default_factory=lambda: EssentialCheckConfig(
            threshold_px=2.0, min_iterations=64, lo_rounds=0, refine_iterations=0
        )
    )

    def __post_init__(self) -> None:
        if self.candidate_keyframes is not None and self.candidate_keyframes < 1:
            raise ValueError(
                f"candidate_keyframes must be >= 1 or None, got {self.candidate_keyframes}"
            )
        if self.max_point_distance_m is not None and not self.max_point_distance_m > 0:
            raise ValueError(
                f"max_point_distance_m must be positive or None, got {self.max_point_distance_m}"
            )
        if self.verify_keyframes < 1:
            raise ValueError(f"verify_keyframes must be >= 1, got {self.verify_keyframes}")


def match_epipolar(
    db: VisualDatabase,
    covisible: torch.Tensor,
    features: Features,
    camera: PinholeCamera,
    config: EpipolarMatchingConfig,
    generator: torch.Generator,
    keypoint_surfels: torch.Tensor | None = None,
    surfel_centers: torch.Tensor | None = None,
    ratio: float | None = 0.8,
    max_descriptor_distance: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Associate keypoints of a new keyframe with map points of covisible keyframes.

    Args:
        db: the database (the new keyframe need not be in it yet).
        covisible: (C,) int64 covisible keyframe indices (the new keyframe excluded).
        features: the new keyframe's N keypoints and descriptors.
        camera: the new keyframe's camera.
        config: matching and verification settings.
        generator: the RANSAC random source.
        keypoint_surfels: (N, S) int64 surfels each keypoint sees at the new keyframe's pose
            (its own and its neighbours; -1 padding); needed by the 3D gate
            (``config.max_point_distance_m``), which rejects the matches of keypoints that
            see no surfel.
        surfel_centers: (M, 3) centres of the surfel map (world frame), for the 3D gate.
        ratio: Lowe's ratio test over all candidate map points (``None`` to skip).
        max_descriptor_distance: largest accepted descriptor distance, or ``None``.

    Returns:
        ``(keypoint_ids, point_ids)``: (M,) int64 indices into ``features`` and the (M,)
        distinct map points they observe.

    Raises:
        ValueError: the 3D gate is on but ``keypoint_surfels`` is missing or not (N, S), or
            ``surfel_centers`` is missing.
    """
    gate = config.max_point_distance_m
    if gate is not None and (
        surfel_centers is None
        or keypoint_surfels is None
        or keypoint_surfels.dim() != 2
        or keypoint_surfels.shape[0] != len(features)
    ):
        raise ValueError(
            f"the 3D gate (max_point_distance_m) needs keypoint_surfels of shape "
            f"({len(features)}, S) and surfel_centers, got keypoint_surfels "
            f"{None if keypoint_surfels is None else tuple(keypoint_surfels.shape)}"
        )
    empty = torch.zeros(0, dtype=torch.int64)
    points = db.points_observed_by(covisible)
    if len(points) == 0 or len(features) == 0:
        return empty, empty
    matches = match_descriptors(
        features.descriptors,
        db.point_descriptors[points],
        metric=db.metric,
        mutual=True,
        ratio=ratio,
        max_distance=max_descriptor_distance,
    )
    keypoint_ids, point_ids = matches.indices[:, 0], points[matches.indices[:, 1]]
    if gate is not None:
        seen = keypoint_surfels[keypoint_ids]  # (M, S), -1 padding
        offsets = surfel_centers[seen.clamp(min=0)].double() - db.point_positions[point_ids, None]
        distance = torch.where(seen >= 0, offsets.norm(dim=-1), torch.inf).amin(-1)
        near = distance <= gate
        keypoint_ids, point_ids = keypoint_ids[near], point_ids[near]
    # Observations of the matched points in covisible keyframes: their keypoint rows, the
    # observing keyframes and the match indices; a point has at most one keypoint per keyframe.
    slot = torch.full((db.num_points + 1,), -1, dtype=torch.int64)
    slot[point_ids + 1] = torch.arange(len(point_ids))
    rows = db.keyframe_rows(covisible)
    obs_match = slot[db.keypoint_points[rows] + 1]
    rows, obs_match = rows[obs_match >= 0], obs_match[obs_match >= 0]
    obs_keyframe = db.keypoint_keyframes()[rows]
    counts = torch.bincount(obs_keyframe, minlength=db.num_keyframes)
    verifiers = torch.argsort(counts, descending=True, stable=True)[: config.verify_keyframes]
    verifiers = verifiers[counts[verifiers] >= config.essential.min_inliers]
    checked = torch.zeros(len(point_ids), dtype=torch.bool)
    rejected = torch.zeros(len(point_ids), dtype=torch.bool)
    for keyframe in verifiers.tolist():
        observed = obs_keyframe == keyframe
        match = obs_match[observed]
        result = essential_check(
            db.keypoints[rows[observed]].double(),
            features.keypoints[keypoint_ids[match]].double(),
            db.camera(keyframe),
            camera.to(torch.float64),
            config.essential,
            generator,
        )
        if not result.success:
            continue
        checked[match] = True
        rejected[match] |= ~result.inliers
    keep = checked & ~rejected
    return keypoint_ids[keep], point_ids[keep]
