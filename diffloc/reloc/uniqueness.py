"""Uniqueness of a relocalised pose: no alternative pose explains the query nearly as well.

Where the scene repeats (a tiled floor, a facade of one module, the other storey), a wrong pose
one period away has the inliers, the coverage and the photometric score of the right one. The
question a validation can still ask is whether the image *fixes* the pose: is there another
pose that explains the query about as well? For a pose ``T`` (4, 4) of a query:

1. *alternatives*: ``T`` moved by every multiple ``m * t`` (``0 < |m| <= max_multiple``) of the
   ``shifts`` best-supported repetition shifts ``t`` of its inliers
   (:func:`~diffloc.reloc.repetition.repeated_shifts`), and the poses of the relocaliser's
   other candidates;
2. *score* (the same for the pose and every alternative): every map point in front of the
   camera, inside the image and not hidden is matched in a ``radius_px`` window around its
   projection (:func:`~diffloc.features.matching.match_guided`), no farther in descriptor
   space than the ``distance_quantile`` quantile of the pose's own inlier matches (a lone
   keypoint in the window is otherwise taken whatever it looks like); the matches refine the pose
   by motion-only refinement (:func:`~diffloc.optim.motion_cost.refine_pose`); the score is
   the share of the map points in view at the refined pose that are its inliers (the inlier
   count alone favours wherever the map is densest: the places the database saw most often,
   which a wrong pose tends to sit in). Hidden points: the points are z-buffered on a grid of
   ``occlusion_cell_px`` pixels, and a point farther than ``1 + occlusion_tolerance`` times
   the nearest depth of its cell is hidden (what the map's own points occlude); a pose with
   fewer inliers than the refinement's ``min_inliers`` scores 0;
3. an alternative that the refinement brought back to within ``min_separation_m`` of the
   refined pose is the pose itself and is dropped;
4. the *ratio* is the best alternative's score over the pose's own: near 1 (or above) when
   another place explains the image as well, near 0 for a unique pose.

:class:`~diffloc.reloc.validation.ValidationConfig` ``uniqueness_ratio`` rejects a pose whose
ratio reaches it.

Example (a floor whose texture repeats every metre, seen from 2 m above; the query is all
repetition, so the pose 1 m along explains it as well):
    >>> from diffloc.geometry.camera import PinholeCamera
    >>> from diffloc.testing import tiled_floor
    >>> floor = tiled_floor(period_m=1.0)
    >>> u = pose_uniqueness(floor.T_wc, floor.rivals, floor.inliers, floor.features,
    ...                     floor.camera, floor.positions, floor.descriptors, "l2")
    >>> u.ratio > 0.8
    True
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from diffloc.checks import check_shape
from diffloc.features.local import Features
from diffloc.features.matching import Metric, descriptor_distances, match_guided
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import invert, transform_points
from diffloc.optim.motion_cost import MotionRefineConfig, refine_pose
from diffloc.reloc.repetition import RepetitionConfig, repeated_shifts

__all__ = ["Uniqueness", "UniquenessConfig", "alternative_poses", "pose_uniqueness"]


@dataclass(frozen=True)
class UniquenessConfig:
    """Settings of :func:`pose_uniqueness` (module docstring).

    Attributes:
        shifts: best-supported repetition shifts tried.
        max_multiple: multiples of each shift tried, each with both signs (2: -2t, -t, t, 2t).
        radius_px: window of the guided matching around each projected map point.
        ratio: Lowe's ratio test of the guided matching, or ``None``.
        distance_quantile: the guided matches' largest descriptor distance is this quantile
            of the distances of the pose's own inlier matches.
        min_separation_m: an alternative refined to within this of the pose is the pose.
        occlusion_cell_px: cell size of the z-buffer of the projected map points.
        occlusion_tolerance: a point farther than ``1 + occlusion_tolerance`` times the
            nearest depth in its cell is hidden.
    """

    shifts: int = 3
    max_multiple: int = 2
    radius_px: float = 4.0
    ratio: float | None = 0.9
    distance_quantile: float = 0.9
    min_separation_m: float = 0.5
    occlusion_cell_px: int = 8
    occlusion_tolerance: float = 0.1

    def __post_init__(self) -> None:
        if self.shifts < 0:
            raise ValueError(f"uniqueness.shifts must be >= 0, got {self.shifts}")
        for name in ("max_multiple", "occlusion_cell_px"):
            if getattr(self, name) < 1:
                raise ValueError(f"uniqueness.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("radius_px", "min_separation_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"uniqueness.{name} must be > 0, got {value}")
        if not 0.0 < self.distance_quantile <= 1.0:
            raise ValueError(
                f"uniqueness.distance_quantile must be in (0, 1], got {self.distance_quantile}"
            )
        tolerance = self.occlusion_tolerance
        if not (math.isfinite(tolerance) and tolerance >= 0):
            raise ValueError(f"uniqueness.occlusion_tolerance must be >= 0, got {tolerance}")


@dataclass(frozen=True)
class Uniqueness:
    """How well the best alternative explains a query compared with its pose.

    Attributes:
        own: the pose's refined guided inliers.
        own_visible: the map points in view at the pose's refined pose.
        rival: the best-scoring alternative's inliers (0 without alternatives).
        rival_visible: the map points in its view (0 without alternatives).
        rival_distance_m: distance of the best alternative's refined pose to the pose's
            (0 without alternatives).
        alternatives: alternatives scored (those that stayed apart from the pose).
    """

    own: int
    own_visible: int
    rival: int
    rival_visible: int
    rival_distance_m: float
    alternatives: int

    @property
    def ratio(self) -> float:
        """The rival's score over the pose's, ``(rival / rival_visible) / (own /
        own_visible)`` (``inf`` when the pose explains nothing and a rival does, 0 when
        neither does)."""
        rival = self.rival / self.rival_visible if self.rival_visible else 0.0
        own = self.own / self.own_visible if self.own_visible else 0.0
        if own == 0:
            return math.inf if rival > 0 else 0.0
        return rival / own


def alternative_poses(
    T_wc: torch.Tensor, shifts: torch.Tensor, max_multiple: int, rivals: torch.Tensor
) -> torch.Tensor:
    """The alternatives of a pose: moved by ``m * t`` for every shift ``t`` and
    ``0 < |m| <= max_multiple``, and the rival poses.

    Args:
        T_wc: (4, 4) the pose (camera-to-world).
        shifts: (S, 3) world-frame shifts in metres.
        max_multiple: largest multiple of each shift (both signs are taken).
        rivals: (R, 4, 4) other candidate poses.

    Returns:
        (S * 2 * max_multiple + R, 4, 4) float64 poses.

    Example:
        >>> T = torch.eye(4, dtype=torch.float64)
        >>> A = alternative_poses(T, torch.tensor([[1.0, 0, 0]]), 2, torch.zeros(0, 4, 4))
        >>> A[:, 0, 3].tolist()
        [-2.0, -1.0, 1.0, 2.0]
    """
    check_shape(T_wc, "4,4", "T_wc")
    check_shape(shifts, "S,3", "shifts")
    check_shape(rivals, "R,4,4", "rivals")
    m = torch.arange(1, max_multiple + 1, dtype=torch.float64)
    factors = torch.cat([-m.flip(0), m])
    moves = (factors[None, :, None] * shifts.double()[:, None]).reshape(-1, 3)  # (S*F, 3)
    moved = T_wc.double().expand(len(moves), 4, 4).clone()
    moved[:, :3, 3] += moves
    return torch.cat([moved, rivals.double()])


def _visible(
    T_wc: torch.Tensor, positions: torch.Tensor, camera: PinholeCamera, config: UniquenessConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """(V,) indices and (V, 2) pixels of the map points a camera at ``T_wc`` sees: in front,
    in the image, and not behind a nearer point of the same z-buffer cell."""
    points_cam = transform_points(invert(T_wc), positions)
    uv, valid = camera.project(points_cam)
    valid &= camera.in_image(uv)
    index = torch.nonzero(valid).flatten()
    uv, depth = uv[index], points_cam[index, 2]
    cell_px = config.occlusion_cell_px
    columns = math.ceil(camera.width / cell_px)
    grid = ((uv + 0.5) / cell_px).floor().long()  # in_image: u + 0.5 in [0, W)
    cells = grid[:, 1] * columns + grid[:, 0]
    rows = math.ceil(camera.height / cell_px)
    nearest = torch.full((rows * columns,), math.inf, dtype=depth.dtype)
    nearest = nearest.scatter_reduce(0, cells, depth, "amin")
    shown = depth <= nearest[cells] * (1 + config.occlusion_tolerance)
    return index[shown], uv[shown]


def _scores(
    poses: torch.Tensor,
    features: Features,
    camera: PinholeCamera,
    positions: torch.Tensor,
    descriptors: torch.Tensor,
    metric: Metric,
    config: UniquenessConfig,
    refine: MotionRefineConfig,
    max_distance: float | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Guided matching and motion-only refinement of every pose (module docstring, step 2).

    Returns:
        (B, 4, 4) refined poses (the pose itself where it had too few matches), (B,) int64
        inlier counts (0 below ``refine.min_inliers``) and (B,) int64 map points in view at
        the refined poses.
    """
    matched = []
    for T in poses:  # one guided matching per pose (tens of poses, vectorised over points)
        points, uv = _visible(T, positions, camera, config)
        found = match_guided(
            uv.float(),
            descriptors[points],
            config.radius_px,
            features.keypoints,
            features.descriptors,
            metric=metric,
            ratio=config.ratio,
            max_distance=max_distance,
        ).indices
        matched.append((points[found[:, 0]], found[:, 1]))
    width = max(1, max(len(p) for p, _ in matched))
    X = torch.zeros(len(poses), width, 3, dtype=torch.float64)
    uv = torch.zeros(len(poses), width, 2, dtype=torch.float64)
    sigma = torch.ones(len(poses), width, dtype=torch.float64)
    mask = torch.zeros(len(poses), width, dtype=torch.bool)
    sizes = (features.sizes / features.sizes.min().clamp_min(1e-6)).double().clamp_min(1.0)
    for b, (points, keypoints) in enumerate(matched):
        n = len(points)
        X[b, :n], uv[b, :n] = positions[points], features.keypoints[keypoints].double()
        sigma[b, :n], mask[b, :n] = sizes[keypoints], True
    enough = mask.sum(1) >= refine.min_inliers
    refined_T = poses.clone()
    counts = torch.zeros(len(poses), dtype=torch.int64)
    if bool(enough.any()):
        cam = camera.to(torch.float64)
        out = refine_pose(
            cam, poses[enough], X[enough], uv[enough], sigma[enough], mask[enough], refine
        )
        refined_T[enough], counts[enough] = out.T_wc.detach(), out.num_inliers
    counts = torch.where(counts >= refine.min_inliers, counts, 0)
    visible = torch.tensor([len(_visible(T, positions, camera, config)[0]) for T in refined_T])
    return refined_T, counts, visible


def pose_uniqueness(
    T_wc: torch.Tensor,
    rivals: torch.Tensor,
    inlier_matches: torch.Tensor | None,
    features: Features,
    camera: PinholeCamera,
    point_positions: torch.Tensor,
    point_descriptors: torch.Tensor,
    metric: Metric,
    config: UniquenessConfig | None = None,
    repetition: RepetitionConfig | None = None,
    refine: MotionRefineConfig | None = None,
) -> Uniqueness:
    """The uniqueness of a relocalised pose (module docstring).

    Args:
        T_wc: (4, 4) the pose (camera-to-world, float64).
        rivals: (R, 4, 4) the relocaliser's other candidate poses.
        inlier_matches: (N, 2) int64 ``(query keypoint, map point)`` of the pose's inliers
            (the repetition shifts and the descriptor gate come from them), or ``None`` (no
            shifts and no gate, e.g. the ``naive`` method).
        features: the query's local features.
        camera: the query camera (batch shape ``()``).
        point_positions: (P, 3) map point positions (world frame, metres).
        point_descriptors: (P, D) map point descriptors (same kind as the query's).
        metric: the descriptor metric.
        config: settings (default :class:`UniquenessConfig`).
        repetition: how the repetition shifts are found (default :class:`RepetitionConfig`).
        refine: the motion-only refinement of every scored pose (default
            :class:`MotionRefineConfig`, the relocaliser's).

    Returns:
        A :class:`Uniqueness`.

    Raises:
        ShapeError: inconsistent shapes.
        ValueError: a non-finite pose, or descriptors of another size than the query's.
    """
    config = config or UniquenessConfig()
    repetition = repetition or RepetitionConfig()
    refine = refine or MotionRefineConfig()
    check_shape(T_wc, "4,4", "T_wc")
    check_shape(point_positions, "P,3", "point_positions")
    check_shape(point_descriptors, "P,D", "point_descriptors")
    if not bool(torch.isfinite(T_wc).all()):
        raise ValueError("T_wc must be finite")
    if point_descriptors.shape[1:] != features.descriptors.shape[1:]:
        raise ValueError(
            f"map descriptors {tuple(point_descriptors.shape[1:])} do not match the query's "
            f"{tuple(features.descriptors.shape[1:])}"
        )
    positions = point_positions.double()
    shifts = torch.zeros(0, 3, dtype=torch.float64)
    max_distance = None
    if inlier_matches is not None and len(inlier_matches) > 0:
        check_shape(inlier_matches, "N,2", "inlier_matches")
        own = descriptor_distances(
            features.descriptors[inlier_matches[:, 0]],
            point_descriptors[inlier_matches[:, 1]],
            metric,
        ).diagonal()
        max_distance = float(torch.quantile(own.double(), config.distance_quantile))
        if config.shifts > 0:
            shifts = repeated_shifts(
                inlier_matches[:, 1],
                positions,
                point_descriptors,
                metric,
                repetition,
                config.shifts,
            )[0]
    T_wc = T_wc.double()
    poses = torch.cat([T_wc[None], alternative_poses(T_wc, shifts, config.max_multiple, rivals)])
    camera = camera.to(torch.float64)
    refined, counts, visible = _scores(
        poses, features, camera, positions, point_descriptors, metric, config, refine, max_distance
    )
    distance = torch.linalg.vector_norm(refined[1:, :3, 3] - refined[0, :3, 3], dim=1)
    apart = distance > config.min_separation_m
    own, own_visible = int(counts[0]), int(visible[0])
    if not bool(apart.any()):
        return Uniqueness(own, own_visible, 0, 0, 0.0, 0)
    scores = torch.where(apart, counts[1:] / visible[1:].clamp_min(1), -1.0)
    best = int(torch.argmax(scores)) + 1
    return Uniqueness(
        own,
        own_visible,
        int(counts[best]),
        int(visible[best]),
        float(distance[best - 1]),
        int(apart.sum()),
    )
