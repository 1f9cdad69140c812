"""Settings of ``diffloc task=crossmodal``: the ``map`` options ``tls`` / ``cloud`` / ``mesh``
/ ``images`` / ``nerf`` and the task node (render poses, RGB-D database, localiser, query
sequences).

The map options mirror :mod:`diffloc.crossmodal`: ``map=tls`` and ``map=cloud`` are the
dataset's TLS and lidar point maps coloured from the mapping images and rendered as splats
(:class:`PointMapConfig`), ``map=mesh`` is the textured mesh reconstructed from a point map
(:class:`MeshMapConfig`), ``map=nerf`` the radiance-field submaps of ``task=train_nerf``
(:class:`NerfMapConfig`); ``map=images`` is no rendered map but the mapping run's own images
with depth from the surfel map, seed 2's real-image comparison (:class:`ImageMapConfig`);
``map=hybrid`` holds both: the mapping images plus the mesh renders no mapping image covers
(:class:`HybridMapConfig`, beyond seed 2).
``map=surfel`` (:class:`~diffloc.maps.surfel.SurfelMapConfig`) is
the surfel map of the other tasks; :func:`map_option` names the option a typed map node came
from, so the CLI can refuse a map a task cannot use.

Example:
    >>> PointMapConfig(point_map="lidar_map", passes="multi").sizes().levels
    (1, 2, 4, 8)
    >>> map_option(MeshMapConfig()), map_option(PointMapConfig(point_map="tls_map"))
    ('mesh', 'tls')
    >>> map_option(ImageMapConfig(every=4))
    'images'
    >>> map_option(NerfMapConfig(min_opacity=0.3))
    'nerf'
    >>> map_option(HybridMapConfig()), HybridMapConfig().mesh.point_map
    ('hybrid', 'lidar_map')
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

from diffloc.checks import check_number, check_positive_int
from diffloc.crossmodal.database import DatabaseConfig as RGBDDatabaseConfig
from diffloc.crossmodal.hybrid import check_coverage_bounds
from diffloc.crossmodal.mesh_map import POINT_MAPS, TexturedMeshConfig
from diffloc.crossmodal.pose_selection import PoseSelectionConfig
from diffloc.crossmodal.retrieval_tuning import RetrievalTuningConfig
from diffloc.maps.surfel import SurfelMapConfig
from diffloc.optim.render_refine import MatchCheckConfig, RenderRefineConfig
from diffloc.pipeline.crossmodal_pose_checks import RerenderConfig, StoreyAliasConfig
from diffloc.reloc.rendered import RenderedLocalizerConfig
from diffloc.reloc.validation import ValidationConfig
from diffloc.render.point_sizes import PointSizes
from diffloc.render.screen_space import ScreenSpaceVisibility

__all__ = [
    "MAP_OPTIONS",
    "REFINE_MAPS",
    "CrossmodalRefineConfig",
    "CrossmodalTaskConfig",
    "HybridMapConfig",
    "ImageMapConfig",
    "MeshMapConfig",
    "NerfMapConfig",
    "PointMapConfig",
    "map_option",
]

MAPPING_SEQUENCE = "mapping"
"""The mapping run: the sequence ``map=images`` takes its frames from by default."""
POINT_MAP_OPTIONS = {"tls_map": "tls", "lidar_map": "cloud"}
"""The ``map`` option of each dataset point map rendered as a cloud."""

MAP_OPTIONS = ("surfel", "tls", "cloud", "mesh", "images", "nerf", "hybrid")
"""Every option of the ``map`` group (``diffloc/conf/map/*.yaml``)."""

PASSES = ("single", "multi")
EXPOSURES = ("estimated", "none")


def _check_point_map(point_map: str) -> None:
    if point_map not in POINT_MAPS:
        raise ValueError(f"point_map must be one of {POINT_MAPS}, got {point_map!r}")


@dataclass
class PointMapConfig:
    """``map=tls`` / ``map=cloud``: a dataset point map coloured from the mapping images and
    rendered as square splats of seed 2 Eq. 2 sizes.

    Attributes:
        point_map: ``"tls_map"`` (``map=tls``) or ``"lidar_map"`` (``map=cloud``).
        passes: ``"single"`` (every point its own Eq. 2 size) or ``"multi"`` (sizes snapped to
            ``levels`` and rendered in passes merged by nearest depth, seed 2 Fig. 5).
        rho_min: smallest splat size, pixels.
        rho_max: Eq. 2 splat size at 1 m, pixels (also the sizes of the occlusion depth used
            when colouring, unless ``occlusion_rho_max`` is set).
        levels: the multi-pass sizes, pixels.
        visibility_radius: the database renders' screen-space visibility filter
            (:mod:`~diffloc.render.screen_space`: a pixel that nearer splats enclose takes
            their point): pixels searched in each of 8 directions; 0 turns it off.
        visibility_sectors: directions (of 8) that must hold a nearer splat, in [5, 8].
        visibility_depth_ratio: a splat is nearer below this times the pixel's depth.
        occlusion_rho_max: the Eq. 2 size at 1 m of the occlusion depth the cloud is coloured
            with (a point no mapping image sees unoccluded is dropped); ``None``: ``rho_max``.
    """

    point_map: str = "tls_map"
    passes: str = "single"
    rho_min: float = 1.0
    rho_max: float = 8.0
    levels: list[int] = field(default_factory=lambda: [1, 2, 4, 8])
    visibility_radius: int = 0
    visibility_sectors: int = 7
    visibility_depth_ratio: float = 0.9
    occlusion_rho_max: float | None = None

    def __post_init__(self) -> None:
        _check_point_map(self.point_map)
        if self.passes not in PASSES:
            raise ValueError(f"passes must be one of {PASSES}, got {self.passes!r}")
        if isinstance(self.visibility_radius, bool) or not isinstance(self.visibility_radius, int):
            raise ValueError(
                f"visibility_radius must be an integer, got {self.visibility_radius!r}"
            )
        if self.visibility_radius < 0:
            raise ValueError(f"visibility_radius must be >= 0, got {self.visibility_radius}")
        self.sizes()
        self.visibility()
        if self.occlusion_rho_max is not None and not (
            math.isfinite(self.occlusion_rho_max) and self.occlusion_rho_max >= self.rho_min
        ):
            raise ValueError(
                f"occlusion_rho_max must be a finite number >= rho_min ({self.rho_min}), "
                f"got {self.occlusion_rho_max!r}"
            )

    def sizes(self) -> PointSizes:
        """The splat sizes of the database renders."""
        if self.passes == "single":
            return PointSizes.inverse_depth(self.rho_min, self.rho_max)
        return PointSizes.multi_pass(self.rho_min, self.rho_max, tuple(self.levels))

    def occlusion_sizes(self) -> PointSizes:
        """The splat sizes of the occlusion depth the cloud is coloured with (Eq. 2 per point).

        Example:
            >>> PointMapConfig(rho_max=12.0).occlusion_sizes().rho_max
            12.0
            >>> PointMapConfig(rho_max=12.0, occlusion_rho_max=8.0).occlusion_sizes().rho_max
            8.0
        """
        rho_max = self.rho_max if self.occlusion_rho_max is None else self.occlusion_rho_max
        return PointSizes.inverse_depth(self.rho_min, rho_max)

    def visibility(self) -> ScreenSpaceVisibility | None:
        """The database renders' screen-space visibility filter (``None``: off).

        Example:
            >>> PointMapConfig().visibility() is None
            True
            >>> PointMapConfig(visibility_radius=16, visibility_sectors=6).visibility()
            ScreenSpaceVisibility(radius=16, min_sectors=6, depth_ratio=0.9)
        """
        if self.visibility_radius == 0:
            return None
        return ScreenSpaceVisibility(
            self.visibility_radius, self.visibility_sectors, self.visibility_depth_ratio
        )


@dataclass
class MeshMapConfig:
    """``map=mesh``: a mesh reconstructed from a point map and textured from the mapping images
    by seed 2 Eq. 3-4 (the simulator's ground-truth mesh and exposures are never read).

    Attributes:
        point_map: the point map the mesh is reconstructed from (``"lidar_map"``, seed 2).
        exposures: ``"estimated"`` from overlapping views, or ``"none"`` (no compensation).
        texture: reconstruction, UV atlas and blend settings.
    """

    point_map: str = "lidar_map"
    exposures: str = "estimated"
    texture: TexturedMeshConfig = field(default_factory=TexturedMeshConfig)

    def __post_init__(self) -> None:
        _check_point_map(self.point_map)
        if self.exposures not in EXPOSURES:
            raise ValueError(f"exposures must be one of {EXPOSURES}, got {self.exposures!r}")


@dataclass
class ImageMapConfig:
    """``map=images``: a database of the mapping run's real images instead of renders (seed 2's
    real-image rows): every ``every``-th frame of each of ``sequences`` with its pose and
    z-depth rendered from the surfel map (``<dataset>/map/surfel_map.ply``, ``diffloc
    task=build_map``); the simulator's depth images are never read.

    Attributes:
        every: keep every n-th frame of each sequence (frames 0, n, 2n, ...).
        sequences: the sequences whose frames make the database: the mapping run's front
            camera, and with a multi-camera rig its other cameras too (seed 2's "front + side"
            rows: ``[mapping, mapping_left, mapping_right]``, the side cameras of a dataset
            simulated with ``scene.rig.side_camera_yaw_deg=[90,-90]``), all in the surfel
            map's frame.

    Example:
        >>> ImageMapConfig(sequences=["mapping", "mapping_left"]).key()
        {'every': 2, 'sequences': ['mapping', 'mapping_left']}
        >>> ImageMapConfig().key()  # the front camera only: the key of before the setting
        {'every': 2}
    """

    every: int = 2
    sequences: list[str] = field(default_factory=lambda: [MAPPING_SEQUENCE])

    def __post_init__(self) -> None:
        check_positive_int(self.every, "every")
        if not self.sequences:
            raise ValueError("map.sequences must name at least one sequence (e.g. [mapping])")
        for name in self.sequences:
            if not isinstance(name, str) or not name:
                raise ValueError(f"map.sequences must be sequence names, got {name!r}")
        if len(set(self.sequences)) != len(self.sequences):
            raise ValueError(f"map.sequences repeats a sequence: {list(self.sequences)}")

    def key(self) -> dict[str, Any]:
        """The settings the database depends on, as its stage key records them
        (``sequences`` only when it is not the front camera alone)."""
        out = asdict(self)
        if out["sequences"] == [MAPPING_SEQUENCE]:
            del out["sequences"]
        return out


@dataclass
class NerfMapConfig:
    """``map=nerf``: the radiance-field submaps trained by ``task=train_nerf`` (the root
    ``nerf`` node says which: ``nerf.out_dir``, ``nerf.submaps``, ... as when they were
    trained), each render pose rendered by the submap that serves it (seed 2 III-D3).

    Attributes:
        point_map: the point map the render poses are selected on (``"lidar_map"``: the
            mapping run's, as the fields are).
        min_opacity: rendered pixels of lower opacity are holes (no depth).
    """

    point_map: str = "lidar_map"
    min_opacity: float = 0.5

    def __post_init__(self) -> None:
        _check_point_map(self.point_map)
        if not 0.0 < self.min_opacity <= 1.0:
            raise ValueError(f"min_opacity must be in (0, 1], got {self.min_opacity!r}")


@dataclass
class HybridMapConfig:
    """``map=hybrid`` (beyond seed 2): the real-image database of ``map=images`` plus the
    renders of the textured mesh of ``map=mesh`` at the render poses no mapping image covers
    (:func:`~diffloc.crossmodal.hybrid.uncovered_views`): the mapping run's own images where it
    looked, renders where it never did (the other driving direction, the sides). Both parts
    are the stages of ``map=images`` and ``map=mesh`` with these settings (reused when those
    ran); the hybrid stage describes their union with one NetVLAD.

    Attributes:
        every: keep every n-th mapping frame (as ``map=images``).
        mesh: the textured mesh rendered (as ``map=mesh``).
        max_distance_m: a mapping image within this distance of a render ...
        max_angle_deg: ... whose optical axis is within this angle of the render's covers it
            (seed 2's bounds of a right retrieval: the render spacing, 2 m indoors and 4 m
            outdoors, and 45 deg).
    """

    every: int = 2
    mesh: MeshMapConfig = field(default_factory=MeshMapConfig)
    max_distance_m: float = 2.0
    max_angle_deg: float = 45.0

    def __post_init__(self) -> None:
        check_positive_int(self.every, "every")
        check_coverage_bounds(self.max_distance_m, self.max_angle_deg)

    def images(self) -> ImageMapConfig:
        """The real-image part's settings (``map=images`` with the same ``every``)."""
        return ImageMapConfig(every=self.every)


def map_option(config: object) -> str:
    """The ``map`` option (:data:`MAP_OPTIONS`) a built map node came from.

    Raises:
        TypeError: ``config`` is no map schema.
    """
    if isinstance(config, SurfelMapConfig):
        return "surfel"
    if isinstance(config, PointMapConfig):
        return POINT_MAP_OPTIONS[config.point_map]
    if isinstance(config, MeshMapConfig):
        return "mesh"
    if isinstance(config, ImageMapConfig):
        return "images"
    if isinstance(config, NerfMapConfig):
        return "nerf"
    if isinstance(config, HybridMapConfig):
        return "hybrid"
    raise TypeError(f"not a map config: {type(config).__name__}")


REFINE_MAPS = ("nerf", "tls", "cloud")
"""The ``map`` options whose map the refinement renders differentiably: the radiance-field
submaps and the coloured point clouds."""


@dataclass
class CrossmodalRefineConfig:
    """``task.refine``: render-and-compare refinement of every accepted pose
    (:mod:`diffloc.pipeline.crossmodal_refine`, :mod:`diffloc.optim.render_refine`).

    Attributes:
        enabled: refine after each sequence's localisation (``map=nerf``, ``tls``, ``cloud``;
            refused with the others).
        image_scale: the query is compared at this share of its own size (0.125: 80x60 of
            640x480).
        fit_steps: ``map=nerf``: Adam steps of the query's appearance-code fit at its
            localised pose.
        render: the refinement's settings (levels, iterations, acceptance); the correlation
            floor 0.7 was chosen on indoor seed 0 (README, "Render-and-compare pose
            refinement").
        verify: also require the match check (:attr:`check`) before a refined pose is kept.
        check: the match check's settings.
        cloud_spacing_m: ``map=tls|cloud``: the coloured cloud is thinned to one point per
            cell of this size (splats of half its radius).
        cloud_max_depth_m: ``map=tls|cloud``: points farther from the query are not rendered.

    Example:
        >>> cfg = CrossmodalRefineConfig()
        >>> cfg.enabled, cfg.render.levels, cfg.render.min_correlation, cfg.check.width
        (False, (0.25, 0.5, 1.0), 0.7, 256)
    """

    enabled: bool = False
    image_scale: float = 0.125
    fit_steps: int = 60
    render: RenderRefineConfig = field(
        default_factory=lambda: RenderRefineConfig(min_correlation=0.7)
    )
    verify: bool = True
    check: MatchCheckConfig = field(default_factory=MatchCheckConfig)
    cloud_spacing_m: float = 0.1
    cloud_max_depth_m: float = 8.0

    def __post_init__(self) -> None:
        if not 0.0 < self.image_scale <= 1.0:
            raise ValueError(f"task.refine.image_scale must be in (0, 1], got {self.image_scale}")
        check_positive_int(self.fit_steps, "task.refine.fit_steps")
        for name in ("cloud_spacing_m", "cloud_max_depth_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"task.refine.{name} must be positive, got {value}")

    def settings(self) -> dict:
        """Everything but :attr:`enabled`: what a refinement's result depends on."""
        out = asdict(self)
        del out["enabled"]
        return out


POSE_SETTINGS = {
    "floor_closing_m": "floor_closing_radius_m",
    "trajectory_gap_m": "trajectory_gap_m",
}
"""Per-point-map task settings -> the :class:`PoseSelectionConfig` field each sets."""
MAP_SETTINGS = ("top_k", "validation")
"""Per-``map``-option task settings (read by :meth:`CrossmodalTaskConfig.localizer_for`)."""


@dataclass
class CrossmodalTaskConfig:
    """``task=crossmodal``: seed 2's localisation in a database rendered from the ``map``.

    Render poses on the free-path corridor of the map's point cloud -> the map (coloured cloud,
    textured mesh or radiance-field submaps) -> its RGB-D database with features and NetVLAD
    -> Algorithm 1 on every ``every``-th frame of each of ``sequences``; each step a cached
    stage under ``<dataset>/crossmodal/``; results, TUM files and plots under the run folder.

    Attributes:
        out_dir: where results go; empty: the Hydra run folder
            (``<dataset>/crossmodal/<map>/results`` outside a Hydra run).
        sequences: the query sequences to localise.
        every: localise every n-th frame.
        image_scale: images (mapping, database renders, queries) are resized by this factor.
        poses: render-pose selection (5 cm cells, 2 m spacing indoors; 20 cm, 4 m outdoors).
        floor_closing_m: per point map (``"lidar_map"`` / ``"tls_map"``), the
            ``poses.floor_closing_radius_m`` its render poses are selected with (a point map
            not listed keeps ``poses``'s own). Set per scene kind: indoors the lidar map's
            rings leave floor gaps that 0.3 m closes, while the dense TLS map keeps 0.1 m
            (see :meth:`poses_for`). Keyed on the point map, not the ``map`` option, because
            the render poses are: ``map=cloud``, ``mesh`` and ``nerf`` share the lidar map's.
        trajectory_gap_m: per point map, the ``poses.trajectory_gap_m`` its render poses are
            selected with: the map's trajectory (the ``mapping`` run's camera poses) adds
            samples where the skeleton leaves it farther than this uncovered (a point map not
            listed keeps ``poses``'s own, by default none). A map made along that run (the
            lidar map) or coloured from its images at their poses (the TLS map) has it.
        database: features and NetVLAD of the rendered database.
        tune_retrieval: teach the rendered database's NetVLAD the render / real gap with the
            mapping images before localising (a cached stage,
            :mod:`diffloc.pipeline.crossmodal_retrieval`; ``retrieval.method``: triplet
            fine-tuning or a learned whitening); refused with ``map=images`` and
            ``map=hybrid``, whose databases hold the mapping images themselves.
        retrieval: the settings of that stage.
        localizer: Algorithm 1 with re-ranking and validation (``localizer.prior``: the pose
            prior over a query sequence, off by default).
        prior_growth_mps: the scene kind's growth of the pose prior's radius per second
            (the platform's top speed: 1 m/s indoors, 6 m/s outdoors; set in
            ``task/scene/crossmodal_<scene>.yaml``), used where ``localizer.prior.growth_mps``
            is unset (see :meth:`localizer_for`).
        validation: per ``map`` option, fields of ``localizer.validation`` that map uses
            instead (e.g. ``{"mesh": {"theta_in": 80, "min_photometric": 0.3}}``; any
            :class:`~diffloc.reloc.validation.ValidationConfig` field, ``None`` turns a test
            off; an option not listed keeps the localizer's own). The rendered maps differ in
            how many inliers, how much coverage and what photometric consistency a right pose
            reaches, so the thresholds are set per map and scene kind
            (``task/scene/crossmodal_<scene>.yaml``), see :meth:`localizer_for`.
        top_k: per ``map`` option, the ``localizer.top_k`` (re-ranked images matched) that map
            uses instead (an option not listed keeps the localizer's own; see
            :meth:`localizer_for`).
        loose_m: position bound of the loose localisation criterion (with 30 deg): 1 m
            indoors, 2 m outdoors (seed 2).
        plot_queries: queries shown beside their retrieved render per sequence.
        refine: render-and-compare refinement of the accepted poses (off by default).
        rerender: the re-render check of the poses found
            (:class:`~diffloc.pipeline.crossmodal_pose_checks.RerenderConfig`).
        storey_alias: the storey-alias test of the accepted poses
            (:class:`~diffloc.pipeline.crossmodal_pose_checks.StoreyAliasConfig`).
    """

    name: str = "crossmodal"
    out_dir: str = ""
    sequences: list[str] = field(
        default_factory=lambda: ["query_same", "query_lane", "query_reverse"]
    )
    every: int = 1
    image_scale: float = 0.5
    poses: PoseSelectionConfig = field(default_factory=PoseSelectionConfig)
    database: RGBDDatabaseConfig = field(default_factory=RGBDDatabaseConfig)
    tune_retrieval: bool = False
    retrieval: RetrievalTuningConfig = field(default_factory=RetrievalTuningConfig)
    localizer: RenderedLocalizerConfig = field(default_factory=RenderedLocalizerConfig)
    prior_growth_mps: float = 1.0
    floor_closing_m: dict[str, float] = field(default_factory=dict)
    trajectory_gap_m: dict[str, float] = field(default_factory=dict)
    validation: dict[str, dict[str, Any]] = field(default_factory=dict)
    top_k: dict[str, int] = field(default_factory=dict)
    loose_m: float = 1.0
    plot_queries: int = 4
    refine: CrossmodalRefineConfig = field(default_factory=CrossmodalRefineConfig)
    rerender: RerenderConfig = field(default_factory=RerenderConfig)
    storey_alias: StoreyAliasConfig = field(default_factory=StoreyAliasConfig)

    def __post_init__(self) -> None:
        check_positive_int(self.every, "every")
        check_positive_int(self.plot_queries, "plot_queries")
        if not self.sequences:
            raise ValueError("sequences must name at least one query sequence")
        if not 0.0 < self.image_scale <= 1.0:
            raise ValueError(f"image_scale must be in (0, 1], got {self.image_scale!r}")
        if not 0.0 < self.loose_m < math.inf:
            raise ValueError(f"loose_m must be a positive finite number, got {self.loose_m!r}")
        check_number(self.prior_growth_mps, "task.prior_growth_mps", 0.0)
        for name in POSE_SETTINGS:
            for point_map in getattr(self, name):
                if point_map not in POINT_MAP_OPTIONS:
                    raise ValueError(
                        f"task.{name}.{point_map}: not a point map (one of "
                        f"{tuple(POINT_MAP_OPTIONS)})"
                    )
                self.poses_for(point_map)  # the pose selection checks the values
        for name in MAP_SETTINGS:
            for option in getattr(self, name):
                if option not in MAP_OPTIONS:
                    raise ValueError(
                        f"task.{name}.{option}: not a map option (one of {MAP_OPTIONS})"
                    )
        for option, k in self.top_k.items():
            check_positive_int(k, f"task.top_k.{option}")
        for option in self.validation:
            self.localizer_for(option)  # the validation checks the names and values

    def poses_for(self, point_map: str) -> PoseSelectionConfig:
        """The render-pose settings of ``point_map``: :attr:`poses` with
        ``floor_closing_radius_m`` from :attr:`floor_closing_m` and ``trajectory_gap_m`` from
        :attr:`trajectory_gap_m` where they list the point map.

        Raises:
            ValueError: a listed value the pose selection refuses (named by its key).

        Example:
            >>> task = CrossmodalTaskConfig(floor_closing_m={"lidar_map": 0.3},
            ...                             trajectory_gap_m={"lidar_map": 1.0})
            >>> lidar = task.poses_for("lidar_map")
            >>> lidar.floor_closing_radius_m, lidar.trajectory_gap_m
            (0.3, 1.0)
            >>> task.poses_for("tls_map").floor_closing_radius_m
            0.1
        """
        poses = self.poses
        for name, setting in POSE_SETTINGS.items():
            if point_map in getattr(self, name):
                try:
                    poses = replace(poses, **{setting: getattr(self, name)[point_map]})
                except ValueError as exc:
                    raise ValueError(f"task.{name}.{point_map}: {exc}") from exc
        return poses

    def localizer_for(self, option: str) -> RenderedLocalizerConfig:
        """The localiser settings of the ``map`` option ``option``: ``localizer`` with the
        option's :attr:`top_k` where listed and the validation fields :attr:`validation` lists
        for the option (a localiser without validation stays without); ``map=hybrid`` holds
        its real images to the ``images`` entry's ``min_photometric``
        (``min_photometric_real``) where it is listed; a pose prior without its own
        ``growth_mps`` takes :attr:`prior_growth_mps`.

        Raises:
            ValueError: a listed field that is no validation setting, or a value the
                validation refuses (named by its key, ``task.validation.<option>.<field>``).

        Example:
            >>> task = CrossmodalTaskConfig(validation={"images": {"min_photometric": 0.7}})
            >>> task.localizer_for("images").validation.min_photometric
            0.7
            >>> task.localizer_for("tls").validation.min_photometric is None
            True
            >>> task = CrossmodalTaskConfig(validation={"images": {"min_photometric": 0.7},
            ...                                         "hybrid": {"min_photometric": 0.4}})
            >>> hybrid = task.localizer_for("hybrid")
            >>> hybrid.validation.min_photometric, hybrid.min_photometric_real
            (0.4, 0.7)
            >>> from diffloc.reloc.pose_prior import PosePriorConfig
            >>> prior = replace(task.localizer, prior=PosePriorConfig())
            >>> task = CrossmodalTaskConfig(localizer=prior, prior_growth_mps=6.0)
            >>> task.localizer_for("mesh").prior.growth_mps
            6.0
            >>> task = CrossmodalTaskConfig(validation={"mesh": {"theta_in": 80,
            ...                                                  "max_plane_share": 0.95}})
            >>> mesh = task.localizer_for("mesh").validation
            >>> mesh.theta_in, mesh.max_plane_share, task.localizer.validation.theta_in
            (80, 0.95, 150)
            >>> task = CrossmodalTaskConfig(top_k={"tls": 10})
            >>> task.localizer_for("tls").top_k, task.localizer_for("mesh").top_k
            (10, 5)
        """
        localizer = self.localizer
        if option in self.top_k:
            localizer = replace(localizer, top_k=self.top_k[option])
        if localizer.prior is not None and localizer.prior.growth_mps is None:
            prior = replace(localizer.prior, growth_mps=self.prior_growth_mps)
            localizer = replace(localizer, prior=prior)
        if localizer.validation is None or option not in self.validation:
            return localizer
        settings = dict(self.validation[option])
        names = {f.name for f in fields(ValidationConfig)}
        for name in settings:
            if name not in names:
                raise ValueError(
                    f"task.validation.{option}.{name}: not a validation setting (one of "
                    f"{sorted(names)})"
                )
        try:
            validation = replace(localizer.validation, **settings)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"task.validation.{option}: {exc}") from exc
        real = self.validation.get("images", {}).get("min_photometric")
        if option == "hybrid" and real is not None:
            localizer = replace(localizer, min_photometric_real=real)
        return replace(localizer, validation=validation)
