"""Hierarchical relocalisation of a query image in a visual database (seed 1 Sec. III-C).

For one query (its local features, image and camera):

1. retrieval: the top-K (30) keyframes by global descriptor similarity;
2. clustering: the retrieved keyframes are grouped by covisibility (two keyframes are linked
   when they share at least ``min_shared_points`` map points; clusters are the connected
   components); the best-scored keyframe of each cluster is *canonical*; the
   ``min(N_db, N_max = 3)`` best clusters are processed;
3. local points: the map points seen by the canonical keyframe ``F_c`` and its ``N_co = 5``
   most covisible keyframes (F) are matched to the query keypoints (mutual nearest neighbour
   + ratio test); with ``points = "FN"`` the map points anchored to the neighbouring surfels
   of ``F_c`` that are not in F (N) are then matched to the still unmatched keypoints;
4. essential check between ``F_c`` and the query (keyframe side: the keypoint of ``F_c`` that
   observes the point, else the point projected into ``F_c``, kept even outside the image);
5. PnP RANSAC on the surviving 2D-3D matches gives a rough pose;
6. projection search: every local point is projected with the rough pose and matched in a
   window around its projection; these matches and the PnP inliers go to
7. motion-only refinement (Eq. 5: Huber, keypoint-scale covariance), giving ``n_in``.

The candidate with the most inliers is the answer; pose validation (inlier count, distance to
the previous inlier pose) lives in :mod:`diffloc.reloc.validation`. ``points = "naive"`` is
seed 1's baseline: keypoints of the best retrieved keyframe tied directly to the centres of
their surfels, no covisibility, no essential check, no projection search.

Usage (needs a database and a retriever; ``notebooks/pipeline_tiny_scene.ipynb`` runs it on
the tiny scene)::

    reloc = HierarchicalRelocalizer(db, retriever, RelocConfig())
    result = reloc.relocalize(image, features, camera)
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import torch

from diffloc.checks import check_shape
from diffloc.database.database import VisualDatabase
from diffloc.features.local import Features
from diffloc.features.matching import match_descriptors, match_guided
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.essential_ransac import EssentialCheckConfig, essential_check
from diffloc.geometry.plane_share import dominant_plane_share
from diffloc.geometry.se3 import invert, transform_points
from diffloc.optim.motion_cost import MotionRefineConfig, refine_pose
from diffloc.reloc.pnp import PnPRansacConfig, solve_pnp_ransac
from diffloc.reloc.pose_uncertainty import position_sigma_m
from diffloc.reloc.retrieval import KeyframeRetriever

__all__ = [
    "Candidate",
    "HierarchicalRelocalizer",
    "RelocConfig",
    "RelocResult",
    "covisibility_clusters",
    "grid_coverage",
]

POINT_MODES = ("naive", "F", "FN")


@dataclass
class RelocConfig:
    """Settings of :class:`HierarchicalRelocalizer` (seed 1 defaults).

    Attributes:
        top_k: keyframes retrieved (K = 30).
        n_max: canonical keyframes processed (N_max = 3).
        n_co: covisible keyframes added to each canonical one (N_co = 5).
        points: ``"naive"``, ``"F"`` (local visible points) or ``"FN"`` (plus the points of
            neighbouring surfels).
        min_shared_points: map points two retrieved keyframes must share to be clustered.
        ratio: Lowe's ratio of the descriptor matching, or ``None``.
        use_essential: run the essential check before PnP.
        min_matches: fewest 2D-3D matches to attempt PnP.
        projection_radius_px: window of the projection search around each projected point.
        projection_ratio: ratio test of the projection search, or ``None``.
        stop_inliers: stop processing further canonical keyframes once a candidate pose has
            this many inliers (``None``: always process ``min(N_db, N_max)``, as seed 1).
        coverage_grid: the image is split into this many cells per side to measure how much
            of it a candidate's inliers cover (:attr:`Candidate.coverage`).
        essential: settings of the essential check. It only pre-filters matches for PnP, so
            its local optimisation is off by default: on the default scene that halves its
            time and leaves the refined inlier counts unchanged.
        pnp: settings of PnP RANSAC.
        refine: settings of the motion-only refinement.
        seed: seed of the per-query random generators (RANSAC).
    """

    top_k: int = 30
    n_max: int = 3
    n_co: int = 5
    points: str = "FN"
    min_shared_points: int = 1
    ratio: float | None = 0.9
    use_essential: bool = True
    min_matches: int = 12
    projection_radius_px: float = 10.0
    projection_ratio: float | None = 0.9
    stop_inliers: int | None = None
    coverage_grid: int = 4
    essential: EssentialCheckConfig = field(
        default_factory=lambda: EssentialCheckConfig(
            min_iterations=64, lo_rounds=0, refine_iterations=0
        )
    )
    pnp: PnPRansacConfig = field(default_factory=PnPRansacConfig)
    refine: MotionRefineConfig = field(default_factory=MotionRefineConfig)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.points not in POINT_MODES:
            raise ValueError(f"points must be one of {POINT_MODES}, got {self.points!r}")
        for name in ("top_k", "n_max", "min_matches", "coverage_grid"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.n_co < 0 or self.min_shared_points < 1:
            raise ValueError("n_co must be >= 0 and min_shared_points >= 1")
        if not self.projection_radius_px > 0:
            raise ValueError(f"projection_radius_px must be > 0, got {self.projection_radius_px}")


@dataclass
class RelocResult:
    """Outcome of one query: every refined candidate; the answer is the one with the most
    inliers (the first of equals).

    Attributes:
        retrieved: (k,) int64 retrieved keyframes, best first.
        timings_ms: milliseconds per stage (global_descriptor, retrieval, clustering, matching,
            essential, pnp, projection, refine).
        candidates: every refined candidate in processing order, for pose validation; empty
            when nothing reached a refined pose ("could not localise").
    """

    retrieved: torch.Tensor
    timings_ms: dict[str, float]
    candidates: list[Candidate] = field(default_factory=list)

    @property
    def best(self) -> Candidate | None:
        """The candidate the pose comes from (``None`` when nothing was found)."""
        return max(self.candidates, key=lambda c: c.num_inliers) if self.candidates else None

    @property
    def found(self) -> bool:
        """A candidate pose was refined (it still has to pass validation)."""
        return bool(self.candidates)

    @property
    def T_wc(self) -> torch.Tensor:
        """(4, 4) float64 camera-to-world pose of the best candidate (identity if none)."""
        best = self.best
        return torch.eye(4, dtype=torch.float64) if best is None else best.T_wc

    @property
    def num_inliers(self) -> int:
        """Inliers ``n_in`` of the best candidate's refined pose (0 if none)."""
        best = self.best
        return 0 if best is None else best.num_inliers

    @property
    def canonical(self) -> int:
        """The canonical keyframe of the best candidate (-1 if none)."""
        best = self.best
        return -1 if best is None else best.canonical


@dataclass
class Candidate:
    """One canonical keyframe's refined pose (every processed cluster yields at most one).

    Attributes:
        T_wc: (4, 4) float64 refined camera-to-world pose.
        num_inliers: inliers ``n_in`` of the refinement.
        num_matches: 2D-3D matches the refinement started from (``n_in`` of them survived).
        coverage: fraction of the cells of a ``coverage_grid`` x ``coverage_grid`` grid over
            the image that hold at least one inlier keypoint (inliers bunched on one repeated
            structure cover little of the image).
        canonical: the canonical keyframe.
        inlier_matches: (n_in, 2) int64 ``(query keypoint, map point)`` of the inliers, for
            the repetition test (:mod:`diffloc.reloc.repetition`); ``None`` for the ``naive``
            method, whose 3D points are surfel centres, not map points.
        position_sigma_m: standard deviation of the camera position along its worst
            direction, from the inliers (:func:`~diffloc.reloc.pose_uncertainty.position_sigma_m`;
            ``inf``: they do not fix it, NaN: not measured).
        plane_share: share of the inliers' 3D points on their dominant plane
            (:func:`~diffloc.geometry.plane_share.dominant_plane_share`, in the camera
            frame; NaN: not measured).
    """

    T_wc: torch.Tensor
    num_inliers: int
    num_matches: int
    coverage: float
    canonical: int
    inlier_matches: torch.Tensor | None = None
    position_sigma_m: float = math.nan
    plane_share: float = math.nan


class _Timer:
    """Accumulates wall time per stage name."""

    def __init__(self) -> None:
        self.ms: dict[str, float] = defaultdict(float)
        self._start = time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.ms[stage] += (now - self._start) * 1e3
        self._start = now


def _concat_ranges(starts: torch.Tensor, ends: torch.Tensor) -> torch.Tensor:
    """``cat([arange(s, e) for s, e in zip(starts, ends)])`` without a Python loop."""
    lengths = ends - starts
    first = torch.repeat_interleave(starts - torch.cumsum(lengths, 0) + lengths, lengths)
    return first + torch.arange(len(first))


def grid_coverage(uv: torch.Tensor, camera: PinholeCamera, cells: int) -> float:
    """Fraction of the ``cells x cells`` grid over the image holding at least one pixel.

    Args:
        uv: (N, 2) pixel coordinates (pixel centres at integers).
        camera: the image's camera (batch shape ``()``), for its size.
        cells: grid cells per side (>= 1).

    Returns:
        The covered fraction in [0, 1] (0 for no pixels).

    Example:
        >>> cam = PinholeCamera.from_fov(100, 100, 1.0)
        >>> grid_coverage(torch.tensor([[10.0, 10.0], [90.0, 90.0]]), cam, 2)
        0.5
    """
    check_shape(uv, "N,2", "uv")
    col = (uv[:, 0] * cells / camera.width).floor().clamp(0, cells - 1).long()
    row = (uv[:, 1] * cells / camera.height).floor().clamp(0, cells - 1).long()
    occupied = torch.zeros(cells * cells, dtype=torch.bool)
    occupied[row * cells + col] = True
    return float(occupied.sum()) / (cells * cells)


def covisibility_clusters(
    keyframes: torch.Tensor, covisibility: torch.Tensor, min_shared: int
) -> list[torch.Tensor]:
    """Group retrieved keyframes into connected components of the covisibility graph.

    Args:
        keyframes: (k,) int64 retrieved keyframes, best first.
        covisibility: (K, K) int64 dense shared-point counts of all keyframes.
        min_shared: shared points needed for an edge.

    Returns:
        Clusters as (m_i,) int64 tensors of keyframes in retrieval order; the clusters are
        ordered by their best (first) keyframe, so ``cluster[0]`` is canonical.

    Example:
        >>> C = torch.tensor([[0, 5, 0], [5, 0, 0], [0, 0, 0]])
        >>> covisibility_clusters(torch.tensor([2, 0, 1]), C, 1)
        [tensor([2]), tensor([0, 1])]
    """
    sub = (covisibility[keyframes][:, keyframes] >= min_shared).numpy()
    labels = scipy.sparse.csgraph.connected_components(scipy.sparse.csr_matrix(sub))[1]
    labels = torch.from_numpy(labels.astype(np.int64))
    order = list(dict.fromkeys(labels.tolist()))  # cluster labels by first appearance
    return [keyframes[labels == label] for label in order]


class HierarchicalRelocalizer:
    """Relocalise query images in a :class:`VisualDatabase` (module docstring).

    Args:
        database: the (optimised) visual database.
        retriever: ranks keyframes for a query (:mod:`diffloc.reloc.retrieval`).
        config: settings.
        surfel_centers: (S, 3) surfel centres, needed only by ``points = "naive"``.

    Raises:
        ValueError: an empty database, or ``naive`` without surfel centres.
    """

    def __init__(
        self,
        database: VisualDatabase,
        retriever: KeyframeRetriever,
        config: RelocConfig,
        surfel_centers: torch.Tensor | None = None,
    ) -> None:
        if database.num_keyframes == 0 or database.num_points == 0:
            raise ValueError("the visual database has no keyframes or no map points")
        if config.points == "naive":
            if surfel_centers is None:
                raise ValueError("points='naive' needs the surfel centres")
            check_shape(surfel_centers, "S,3", "surfel_centers")
        self.db = database
        self.retriever = retriever
        self.config = config
        self.surfel_centers = None if surfel_centers is None else surfel_centers.double()
        self.covisibility = database.covisibility().to_dense()
        self.point_positions = database.point_positions.to(torch.float64)
        observations = database.observations()  # (O, 3) keyframe, keypoint, point
        order = torch.argsort(observations[:, 0], stable=True)
        self._keyframe_points = observations[order, 2]
        counts = torch.bincount(observations[:, 0], minlength=database.num_keyframes)
        self._keyframe_offsets = torch.cat([torch.zeros(1, dtype=torch.int64), counts.cumsum(0)])
        # Surfel ids index a mask with one more slot, which -1 ("no surfel") indexes.
        surfel_ids = (database.point_surfels, database.keypoint_surfels, database.neighbour_surfels)
        self._surfel_slots = 2 + max(int(ids.max()) if len(ids) else -1 for ids in surfel_ids)

    # ------------------------------------------------------------------ public API

    def relocalize(
        self, image: torch.Tensor, features: Features, camera: PinholeCamera
    ) -> RelocResult:
        """Estimate the pose of one query image.

        Args:
            image: (3, H, W) float image in [0, 1] (for the global descriptor).
            features: the query's local features (same extractor as the database).
            camera: the query camera (batch shape ``()``).

        Returns:
            A :class:`RelocResult`; ``found = False`` when no candidate reached a refined pose
            ("could not localise" is a normal result).

        Raises:
            ShapeError: an image that is not (3, H, W).
            TypeError: an image that is not floating point (e.g. uint8).
            ValueError: an image size that does not match the camera, or descriptors of
                another kind than the database's.
        """
        check_shape(image, "3,H,W", "image")
        if not image.is_floating_point():
            raise TypeError(
                f"the query image must be float in [0, 1] (diffloc.io.images loads it so), "
                f"got {image.dtype}"
            )
        if tuple(image.shape[1:]) != (camera.height, camera.width):
            raise ValueError(
                f"query image size {tuple(image.shape[1:])} does not match the camera "
                f"({camera.height}, {camera.width})"
            )
        if features.descriptors.shape[1:] != self.db.descriptors.shape[1:] or (
            features.descriptors.dtype != self.db.descriptors.dtype
        ):
            raise ValueError(
                f"query descriptors {tuple(features.descriptors.shape[1:])} "
                f"{features.descriptors.dtype} do not match the database's "
                f"{tuple(self.db.descriptors.shape[1:])} {self.db.descriptors.dtype}"
            )
        timer = _Timer()
        query = self.retriever.describe(image, features)
        timer.lap("global_descriptor")
        retrieved = self.retriever.search(query, self.config.top_k)[1]
        timer.lap("retrieval")
        generator = torch.Generator().manual_seed(self.config.seed)
        camera = camera.to(torch.float64)
        if len(features) < self.config.min_matches:
            return RelocResult(retrieved, dict(timer.ms))
        if self.config.points == "naive":
            best = self._naive(int(retrieved[0]), features, camera, generator, timer)
            return RelocResult(retrieved, dict(timer.ms), [] if best is None else [best])
        clusters = covisibility_clusters(
            retrieved, self.covisibility, self.config.min_shared_points
        )
        timer.lap("clustering")
        candidates: list[Candidate] = []
        for cluster in clusters[: self.config.n_max]:
            candidate = self._candidate(int(cluster[0]), features, camera, generator, timer)
            if candidate is not None:
                candidates.append(candidate)
            stop = self.config.stop_inliers
            if stop is not None and max((c.num_inliers for c in candidates), default=0) >= stop:
                break
        return RelocResult(retrieved, dict(timer.ms), candidates)

    # ------------------------------------------------------------------ stages

    def _local_points(self, canonical: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(F, N): point ids seen by ``F_c`` and its covisible keyframes, and the points of
        ``F_c``'s neighbouring surfels that are not in F (empty unless ``points = "FN"``)."""
        db = self.db
        weights = self.covisibility[canonical]
        co = torch.topk(weights, min(self.config.n_co, len(weights))).indices
        local = torch.cat([torch.tensor([canonical]), co[weights[co] > 0]])
        rows = _concat_ranges(self._keyframe_offsets[local], self._keyframe_offsets[local + 1])
        # Sets of ids as masks: a scatter and a nonzero (sorted ids) instead of sorting.
        in_f = torch.zeros(db.num_points, dtype=torch.bool)
        in_f[self._keyframe_points[rows]] = True
        points_f = torch.nonzero(in_f).squeeze(1)
        if self.config.points != "FN":
            return points_f, points_f[:0]
        kp = db.keyframe_slice(canonical)
        start, stop = int(db.neighbour_offsets[kp.start]), int(db.neighbour_offsets[kp.stop])
        surfels = torch.cat([db.neighbour_surfels[start:stop], db.keypoint_surfels[kp]])
        near = torch.zeros(self._surfel_slots, dtype=torch.bool)
        near[surfels] = True
        near[-1] = False  # the slot of "no surfel" (-1)
        in_n = near[db.point_surfels] & ~in_f
        return points_f, torch.nonzero(in_n).squeeze(1)

    def _match(self, features: Features, points: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
        """(M, 2) int64 ``(keypoint, point)`` descriptor matches of the ``free`` keypoints."""
        if len(points) == 0 or not bool(free.any()):
            return torch.zeros(0, 2, dtype=torch.int64)
        keypoints = torch.nonzero(free).flatten()
        matches = match_descriptors(
            features.descriptors[keypoints],
            self.db.point_descriptors[points],
            metric=self.db.metric,
            ratio=self.config.ratio,
        )
        return torch.stack([keypoints[matches.indices[:, 0]], points[matches.indices[:, 1]]], 1)

    def _keyframe_keypoints(self, canonical: int, points: torch.Tensor) -> torch.Tensor:
        """(M, 2) pixels of ``points`` in ``F_c``: its observing keypoint, else the projection
        (possibly outside the image); NaN for points behind ``F_c``."""
        db = self.db
        rows = db.keyframe_slice(canonical)
        observed = db.keypoint_points[rows]
        lookup = torch.full((db.num_points,), -1, dtype=torch.int64)
        has = observed >= 0
        lookup[observed[has]] = torch.nonzero(has).flatten() + rows.start
        rows_of_points = lookup[points]
        camera = db.camera(canonical)
        points_cam = transform_points(invert(db.T_wc[canonical]), self.point_positions[points])
        uv, in_front = camera.project(points_cam)
        uv = torch.where(in_front[:, None], uv, math.nan)
        seen = rows_of_points >= 0
        uv[seen] = db.keypoints[rows_of_points[seen]].double()
        return uv

    def _pnp_and_refine(
        self,
        matches: torch.Tensor,
        features: Features,
        camera: PinholeCamera,
        generator: torch.Generator,
        timer: _Timer,
        search_points: torch.Tensor | None,
        canonical: int,
        points_world: torch.Tensor | None = None,
    ) -> Candidate | None:
        """PnP RANSAC, projection search (unless ``search_points`` is None) and refinement."""
        if len(matches) < self.config.min_matches:
            return None
        X = self.point_positions[matches[:, 1]] if points_world is None else points_world
        uv = features.keypoints[matches[:, 0]].double()
        pnp = solve_pnp_ransac(X, uv, camera, self.config.pnp, generator)
        timer.lap("pnp")
        if not pnp.success:
            return None
        if search_points is not None:
            matches = self._projection_search(
                pnp.T_wc, matches[pnp.inliers], search_points, features, camera
            )
            X = self.point_positions[matches[:, 1]]
            uv = features.keypoints[matches[:, 0]].double()
            timer.lap("projection")
            T0 = pnp.T_wc
            mask = None
        else:
            T0, mask = pnp.T_wc, pnp.inliers
        sigmas = (features.sizes[matches[:, 0]] / features.sizes.min()).double().clamp_min(1.0)
        refined = refine_pose(camera, T0, X, uv, sigmas, mask, self.config.refine)
        inliers = refined.inliers  # masked matches have chi2 = inf, so never inliers
        T_wc = refined.T_wc.detach()
        sigma_m = position_sigma_m(camera, T_wc, X[inliers], uv[inliers], sigmas[inliers])
        plane = dominant_plane_share(transform_points(invert(T_wc), X[inliers]))
        timer.lap("refine")
        return Candidate(
            T_wc=T_wc,
            num_inliers=int(refined.num_inliers),
            num_matches=int(len(uv) if mask is None else mask.sum()),
            coverage=grid_coverage(uv[inliers], camera, self.config.coverage_grid),
            canonical=canonical,
            inlier_matches=None if points_world is not None else matches[inliers],
            position_sigma_m=sigma_m,
            plane_share=plane,
        )

    def _projection_search(
        self,
        T_wc: torch.Tensor,
        inlier_matches: torch.Tensor,
        points: torch.Tensor,
        features: Features,
        camera: PinholeCamera,
    ) -> torch.Tensor:
        """PnP inliers plus window matches of the projected ``points`` (M, 2) ``(kp, point)``."""
        points_cam = transform_points(invert(T_wc), self.point_positions[points])
        uv, valid = camera.project(points_cam)
        valid &= camera.in_image(uv)
        points, uv = points[valid], uv[valid]
        found = match_guided(
            uv.float(),
            self.db.point_descriptors[points],
            self.config.projection_radius_px,
            features.keypoints,
            features.descriptors,
            metric=self.db.metric,
            ratio=self.config.projection_ratio,
        )
        guided = torch.stack([found.indices[:, 1], points[found.indices[:, 0]]], 1)
        taken_kp = torch.isin(inlier_matches[:, 0], guided[:, 0])
        taken_pt = torch.isin(inlier_matches[:, 1], guided[:, 1])
        return torch.cat([guided, inlier_matches[~taken_kp & ~taken_pt]])

    def _candidate(
        self,
        canonical: int,
        features: Features,
        camera: PinholeCamera,
        generator: torch.Generator,
        timer: _Timer,
    ) -> Candidate | None:
        points_f, points_n = self._local_points(canonical)
        matches = self._match(features, points_f, torch.ones(len(features), dtype=torch.bool))
        free = torch.ones(len(features), dtype=torch.bool)
        free[matches[:, 0]] = False
        matches = torch.cat([matches, self._match(features, points_n, free)])
        timer.lap("matching")
        if len(matches) < self.config.min_matches:
            return None
        if self.config.use_essential:
            uv_kf = self._keyframe_keypoints(canonical, matches[:, 1])
            usable = torch.isfinite(uv_kf).all(-1)
            matches, uv_kf = matches[usable], uv_kf[usable]
            check = essential_check(
                uv_kf,
                features.keypoints[matches[:, 0]].double(),
                self.db.camera(canonical),
                camera,
                self.config.essential,
                generator,
            )
            timer.lap("essential")
            if not check.success:
                return None
            matches = matches[check.inliers]
        return self._pnp_and_refine(
            matches, features, camera, generator, timer, torch.cat([points_f, points_n]), canonical
        )

    def _naive(
        self,
        keyframe: int,
        features: Features,
        camera: PinholeCamera,
        generator: torch.Generator,
        timer: _Timer,
    ) -> Candidate | None:
        """Seed 1's Naive baseline: keyframe keypoints tied to their surfel centres."""
        db = self.db
        rows = db.keyframe_slice(keyframe)
        surfels = db.keypoint_surfels[rows]
        on_surfel = torch.nonzero(surfels >= 0).flatten()
        matches = match_descriptors(
            features.descriptors,
            db.descriptors[rows][on_surfel],
            metric=db.metric,
            ratio=self.config.ratio,
        ).indices
        timer.lap("matching")
        X = self.surfel_centers[surfels[on_surfel[matches[:, 1]]]]
        return self._pnp_and_refine(
            matches, features, camera, generator, timer, None, keyframe, points_world=X
        )
