"""Build and update a visual database from posed images and a surfel map (seed 1 Sec. III-A).

For every image (keyframe) with its pose ``T_wc``:

1. extract local features and render the global surfel index map at the pose (with the
   epipolar association, only at the pixels the keypoints read: their disks);
2. associate every keypoint with the surfel at its (rounded) pixel and store its neighbouring
   surfel set (surfels within the keypoint's radius, ``size / 2``);
3. collect the covisible keyframes (those observing any of this image's surfels) and match
   their map points to the keypoints: ``association="projection"`` projects them into the
   image (dropping points behind the rendered surface) and matches in a local window with
   Lowe's ratio test (seed 1); ``association="epipolar"`` matches by descriptor alone the
   points of the ``epipolar.candidate_keyframes`` covisible keyframes with most keypoints on
   this image's surfels and keeps the matches two-view essential checks agree with, so noisy
   poses do not steer the tracks (:mod:`diffloc.database.epipolar_matching`);
4. matched keypoints become observations of the map points, whose descriptors are re-fused
   (the observation descriptor with the smallest median distance to the others);
5. unmatched keypoints on a surfel create new map points at the surfel centre (a later
   optimisation re-places them on the surfel plane, seed 1 Eq. 1);
6. cull: points created ``new_point_window`` keyframes ago that were not re-observed, then
   redundant keyframes whose new-point windows are complete.

Updating with a new sequence uses the same path: call :meth:`DatabaseBuilder.build` again.

Usage (needs a surfel map and posed images; ``tests/test_database_builder.py`` runs it on
the tiny scene, ``notebooks/pipeline_tiny_scene.ipynb`` shows it)::

    builder = DatabaseBuilder(BuilderConfig(), surfels, make_extractor(XFeatConfig()))
    db = builder.build(read_sequence(root, "mapping"), show_progress=False)
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch

from diffloc.checks import check_finite, check_shape
from diffloc.database.culling import (
    CullingConfig,
    cull_redundant_keyframes,
    cull_unconfirmed_points,
)
from diffloc.database.database import VisualDatabase
from diffloc.database.epipolar_matching import EpipolarMatchingConfig, match_epipolar
from diffloc.database.neighbours import KeypointDisks
from diffloc.features.local import Features, LocalFeatureExtractor
from diffloc.features.matching import match_guided
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import invert, transform_points
from diffloc.io.sequence import SequenceData
from diffloc.maps.surfel import SurfelMap
from diffloc.progress import progress
from diffloc.render.surfel_render import SurfelIndexRenderer, SurfelRender

__all__ = ["ASSOCIATIONS", "BuildCounts", "BuilderConfig", "DatabaseBuilder"]

ASSOCIATIONS = ("projection", "epipolar")


@dataclass
class BuilderConfig:
    """Thresholds of the database builder.

    Attributes:
        association: how a new keyframe finds the map points it observes: ``"projection"``
            (guided search around the projections at the given pose, seed 1) or
            ``"epipolar"`` (descriptor matching verified by essential matrices, independent
            of the poses; use it when the poses are noisy).
        guided_radius_px: search radius (pixels) around each projected map point in which
            keypoints are match candidates (the "local grid" of seed 1 / ORB-SLAM).
        ratio: Lowe's ratio test threshold (best / second-best distance), or ``None``.
        max_descriptor_distance: largest accepted descriptor distance, or ``None`` (in the
            descriptor metric: L2 for XFeat, bits for ORB).
        max_keypoints: keep at most this many keypoints per image (highest scores), or
            ``None`` for all the extractor returns.
        occlusion_tolerance_m: a projected map point farther than the rendered surface at its
            pixel by more than this (metres) is hidden and not matched.
        culling: thresholds of the culling rules.
        epipolar: settings of the ``"epipolar"`` association.
        seed: seed of the random source of the essential checks.
    """

    association: str = "projection"
    guided_radius_px: float = 8.0
    ratio: float | None = 0.8
    max_descriptor_distance: float | None = None
    max_keypoints: int | None = None
    occlusion_tolerance_m: float = 0.1
    culling: CullingConfig = field(default_factory=CullingConfig)
    epipolar: EpipolarMatchingConfig = field(default_factory=EpipolarMatchingConfig)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.association not in ASSOCIATIONS:
            raise ValueError(f"association must be one of {ASSOCIATIONS}, got {self.association!r}")
        if not self.guided_radius_px > 0:
            raise ValueError(f"guided_radius_px must be positive, got {self.guided_radius_px}")
        if self.max_keypoints is not None and self.max_keypoints <= 0:
            raise ValueError(f"max_keypoints must be positive, got {self.max_keypoints}")
        if not self.occlusion_tolerance_m >= 0:
            raise ValueError(
                f"occlusion_tolerance_m must be >= 0, got {self.occlusion_tolerance_m}"
            )


@dataclass
class BuildCounts:
    """What a :class:`DatabaseBuilder` added and culled since it was created.

    Attributes:
        keyframes_added: images added as keyframes.
        points_created: map points created for unmatched keypoints.
        keyframes_culled: keyframes removed as redundant (of the database passed in too).
        points_unconfirmed: new points removed because the next keyframes did not observe them.
        points_orphaned: points removed with culled keyframes (no observation left).
    """

    keyframes_added: int = 0
    points_created: int = 0
    keyframes_culled: int = 0
    points_unconfirmed: int = 0
    points_orphaned: int = 0


def _rounded_pixels(uv: torch.Tensor, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(N,) int64 columns and rows of the rounded pixels ``uv`` (N, 2), clamped to the image."""
    u = uv[:, 0].round().long().clamp(0, width - 1)
    v = uv[:, 1].round().long().clamp(0, height - 1)
    return u, v


def _pixel_lookup(image: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Values of an (H, W) image at the rounded, clamped pixels ``uv`` (N, 2)."""
    u, v = _rounded_pixels(uv, *image.shape)
    return image[v, u]


def _keypoint_pixels(features: Features, disks: KeypointDisks) -> torch.Tensor:
    """(1, H, W) bool: the pixels the keypoints read in the index map, their rounded pixels
    (:func:`_pixel_lookup`) and their disks of radius ``size / 2`` (``disks``)."""
    mask = disks.mask()
    u, v = _rounded_pixels(features.keypoints, disks.height, disks.width)
    mask[v, u] = True
    return mask[None]


class DatabaseBuilder:
    """Builds a :class:`VisualDatabase` image by image (seed 1 Sec. III-A).

    Args:
        config: builder thresholds.
        surfel_map: the surfel map the poses live in.
        extractor: local feature extractor.
        database: an existing database to update, or ``None`` to start an empty one (created
            at the first image with the extractor's descriptor size and dtype).

    Usage (the first image becomes keyframe 0)::

        builder = DatabaseBuilder(BuilderConfig(), surfels, extractor)
        builder.add_image(image, T_wc, camera)
    """

    def __init__(
        self,
        config: BuilderConfig,
        surfel_map: SurfelMap,
        extractor: LocalFeatureExtractor,
        database: VisualDatabase | None = None,
    ) -> None:
        if len(surfel_map) == 0:
            raise ValueError("the surfel map is empty")
        self.config = config
        self.surfel_map = surfel_map
        self.renderer = SurfelIndexRenderer(
            surfel_map.centers, surfel_map.normals, surfel_map.radii
        )
        """Renders the surfel index maps (validated and culled by cells once per map)."""
        self.extractor = extractor
        self.database = database
        self.generator = torch.Generator().manual_seed(config.seed)
        self.timings_ms: dict[str, float] = {"features": 0.0, "database": 0.0}
        """Accumulated wall time of :meth:`add_image`: feature extraction and the rest."""
        self.counts = BuildCounts()
        """Keyframes and points added and culled so far."""
        start = 0 if database is None else database.num_keyframes
        self.keyframe_ids = torch.arange(start, dtype=torch.int64)
        """(K,) int64 insertion number of every keyframe of :attr:`database`: the keyframes of
        the database passed in are ``0 .. K0 - 1`` and the added images count on from ``K0``,
        so a caller can tell which inputs survived culling."""
        self._next_id = start

    def build(
        self,
        sequence: SequenceData,
        frames: Sequence[int] | None = None,
        show_progress: bool = True,
    ) -> VisualDatabase:
        """Add the images of a sequence (all, or ``frames``) and return the database.

        Args:
            sequence: a sequence read by :func:`diffloc.io.dataset.read_sequence`.
            frames: frame indices to use, in order (default: every frame).
            show_progress: show a progress bar.

        Returns:
            The (updated) database.

        Raises:
            ValueError: no frames.
        """
        frames = range(len(sequence.rgb_paths)) if frames is None else frames
        if len(frames) == 0:
            raise ValueError(f"sequence {sequence.name!r}: no frames to add")
        camera = sequence.camera
        for i in progress(frames, f"database {sequence.name}", show_progress):
            self.add_image(sequence.load_rgb(i), sequence.T_wc[i], camera)
        return self.database

    def add_image(self, image: torch.Tensor, T_wc: torch.Tensor, camera: PinholeCamera) -> int:
        """Add one posed image as a keyframe, match, create map points and cull.

        Args:
            image: (3, H, W) float32 image in [0, 1].
            T_wc: (4, 4) camera-to-world pose in the surfel map's frame.
            camera: the ideal pinhole camera of the image.

        Returns:
            The index of the new keyframe (it is never culled by its own insertion).

        Raises:
            ShapeError: wrong shapes.
            ValueError: a non-finite pose, a distorted camera, an image size that does not
                match the camera.
        """
        check_shape(image, "3,H,W", "image")
        check_shape(T_wc, "4,4", "T_wc")
        check_finite(T_wc, "T_wc")
        if tuple(image.shape[1:]) != (camera.height, camera.width):
            raise ValueError(f"image size {tuple(image.shape[1:])} does not match the camera")
        start = time.perf_counter()
        features = self._features(image)
        extracted = time.perf_counter()
        disks = KeypointDisks.of(
            features.keypoints, features.sizes / 2, camera.height, camera.width
        )
        # The projection association reads depths anywhere; the other only at the keypoints.
        pixels = (
            None if self.config.association == "projection" else _keypoint_pixels(features, disks)
        )
        render = self.renderer.render(
            T_wc.to(torch.float32)[None], camera.to(torch.float32), pixels=pixels
        )
        ids = render.ids[0]
        surfels = _pixel_lookup(ids, features.keypoints)
        neighbours = disks.neighbours(ids)
        db = self._database(features)
        epipolar = self.config.association == "epipolar"
        seen = torch.cat([surfels[:, None], neighbours], dim=1)
        covisible = db.keyframes_observing(
            seen.flatten(),
            top_n=self.config.epipolar.candidate_keyframes if epipolar else None,
        )
        keyframe = db.add_keyframe(
            T_wc.to(torch.float64),
            camera.to(torch.float64),
            features.keypoints,
            features.descriptors,
            features.sizes,
            keypoint_surfels=surfels,
            neighbour_surfels=neighbours,
        )
        self.keyframe_ids = torch.cat([self.keyframe_ids, torch.tensor([self._next_id])])
        self._next_id += 1
        self.counts.keyframes_added += 1
        matched = self._match(db, covisible, features, seen, T_wc, camera, render)
        self._create_points(db, keyframe, surfels, matched)
        self._cull(db)
        self.timings_ms["features"] += (extracted - start) * 1e3
        self.timings_ms["database"] += (time.perf_counter() - extracted) * 1e3
        return db.num_keyframes - 1

    def _features(self, image: torch.Tensor) -> Features:
        features = self.extractor.extract(image)
        budget = self.config.max_keypoints
        if budget is None or len(features) <= budget:
            return features
        keep = torch.sort(torch.argsort(features.scores, descending=True, stable=True)[:budget])
        index = keep.values
        return Features(
            features.keypoints[index],
            features.scores[index],
            features.descriptors[index],
            features.sizes[index],
        )

    def _database(self, features: Features) -> VisualDatabase:
        if self.database is None:
            self.database = VisualDatabase(
                features.descriptors.shape[1], descriptor_dtype=features.descriptors.dtype
            )
        return self.database

    def _match(
        self,
        db: VisualDatabase,
        covisible: torch.Tensor,
        features: Features,
        seen: torch.Tensor,
        T_wc: torch.Tensor,
        camera: PinholeCamera,
        render: SurfelRender,
    ) -> torch.Tensor:
        """Match the covisible map points; returns (N,) bool keypoints that got a point.

        ``seen``: (N, S) int64 surfels each keypoint sees at ``T_wc`` (at its pixel and its
        neighbours; -1 padding)."""
        if self.config.association == "epipolar":
            keypoint_ids, point_ids = match_epipolar(
                db,
                covisible,
                features,
                camera,
                self.config.epipolar,
                self.generator,
                keypoint_surfels=seen,
                surfel_centers=self.surfel_map.centers,
                ratio=self.config.ratio,
                max_descriptor_distance=self.config.max_descriptor_distance,
            )
        else:
            keypoint_ids, point_ids = self._match_projected(
                db, covisible, features, T_wc, camera, render
            )
        db.add_observations(db.num_keyframes - 1, keypoint_ids, point_ids)
        db.fuse_descriptors(point_ids)
        matched = torch.zeros(len(features), dtype=torch.bool)
        matched[keypoint_ids] = True
        return matched

    def _match_projected(
        self,
        db: VisualDatabase,
        covisible: torch.Tensor,
        features: Features,
        T_wc: torch.Tensor,
        camera: PinholeCamera,
        render: SurfelRender,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Guided search around the projected map points: ``(keypoint_ids, point_ids)``."""
        points = db.points_observed_by(covisible)
        if len(points) == 0:
            return points, points
        points_cam = transform_points(invert(T_wc.to(torch.float64)), db.point_positions[points])
        uv, valid = camera.to(torch.float64).project(points_cam)
        valid &= camera.in_image(uv)
        surface = _pixel_lookup(render.depth[0], uv).double()
        hidden = (surface > 0) & (points_cam[:, 2] > surface + self.config.occlusion_tolerance_m)
        valid &= ~hidden
        points, uv = points[valid], uv[valid]
        matches = match_guided(
            uv.float(),
            db.point_descriptors[points],
            self.config.guided_radius_px,
            features.keypoints,
            features.descriptors,
            metric=db.metric,
            ratio=self.config.ratio,
            max_distance=self.config.max_descriptor_distance,
        )
        return matches.indices[:, 1], points[matches.indices[:, 0]]

    def _create_points(
        self, db: VisualDatabase, keyframe: int, surfels: torch.Tensor, matched: torch.Tensor
    ) -> None:
        """New map points at the surfel centres of unmatched keypoints that lie on a surfel."""
        new = torch.nonzero(~matched & (surfels >= 0)).flatten()
        rows = db.keyframe_slice(keyframe)
        ids = db.add_points(
            self.surfel_map.centers[surfels[new]].double(),
            db.descriptors[rows][new],
            surfels[new],
        )
        db.add_observations(keyframe, new, ids)
        self.counts.points_created += len(ids)

    def _cull(self, db: VisualDatabase) -> None:
        """Apply the culling rules to the keyframes whose new-point window just completed."""
        window = self.config.culling.new_point_window
        judged = db.num_keyframes - 1 - window
        if judged < 0:
            return
        unconfirmed = cull_unconfirmed_points(db, self.config.culling, torch.tensor([judged]))
        points = db.num_points
        culled = cull_redundant_keyframes(db, self.config.culling, torch.arange(judged + 1))
        kept = ~torch.isin(torch.arange(len(self.keyframe_ids)), culled)
        self.keyframe_ids = self.keyframe_ids[kept]
        self.counts.points_unconfirmed += len(unconfirmed)
        self.counts.keyframes_culled += len(culled)
        self.counts.points_orphaned += points - db.num_points
