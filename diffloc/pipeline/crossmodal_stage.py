"""The stages of ``diffloc task=crossmodal``: render poses, map, RGB-D database, localisation.

Seed 2's localisation in a map without images of its own, each step a cached, atomic stage
(:mod:`diffloc.pipeline.stage`) under ``<dataset>/crossmodal/``:

- ``poses_<point map>/`` (``render_poses.json``): render poses on the free-path corridor of
  the point map (:func:`~diffloc.crossmodal.pose_selection.select_render_poses`), ``poses.npz``
  and the step figures ``floors/floor_<k>.png``; keyed on ``task.poses`` and the point map;
- ``<map>/map/`` (``crossmodal_map.json``): ``map=tls|cloud``: the point map coloured from the
  mapping images (``colored_map.ply``; occlusion by depth rendered from the cloud itself);
  ``map=mesh``: the textured mesh (``mesh/mesh.obj`` + MTL + PNG, ``mesh/mesh.ply``); keyed on
  the map settings, the image scale, the point map and the mapping sequence's images, poses
  and calibration;
- ``<map>/database/`` (``rgbd_database.json``): the map rendered at the render poses with
  XFeat features and NetVLAD (``rgbd/``); keyed on ``task.database``, the render settings and
  the two outputs above;
- ``<map>/localize_<sequence>/`` (``localize.json``): Algorithm 1 on every ``task.every``-th
  frame (``localization.npz``); keyed on ``task.localizer``, the database and the query
  sequence's images and calibration.

The ground-truth poses of the query sequences and the simulator's meshes and exposures are
never read here; scoring is :mod:`diffloc.pipeline.crossmodal_report`'s.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from diffloc.crossmodal.database import DatabaseConfig, RenderedDatabase, render_database
from diffloc.crossmodal.mesh_map import build_textured_mesh
from diffloc.crossmodal.pose_selection import (
    PoseSelectionConfig,
    select_render_poses,
    write_floor_plan_figures,
)
from diffloc.crossmodal.synthesize import MeshMap, PointCloudMap, RGBDMap
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.atomic import atomic_open
from diffloc.io.dataset import MAP_FILES, read_sequence
from diffloc.io.identity import identity
from diffloc.io.mesh_export import write_atlas_obj, write_atlas_ply
from diffloc.io.mesh_obj import read_textured_mesh_obj
from diffloc.io.npz import read_npz_archive, read_npz_fields, write_npz
from diffloc.io.ply import PointCloudData, read_point_cloud
from diffloc.io.sequence import SequenceData
from diffloc.maps.pointcloud import PointMap
from diffloc.pipeline.crossmodal_config import (
    MAPPING_SEQUENCE,
    MeshMapConfig,
    NerfMapConfig,
    PointMapConfig,
    map_option,
)
from diffloc.pipeline.hints import Command
from diffloc.pipeline.stage import (
    LockLevel,
    StageOutcome,
    StageSummary,
    open_stage,
    stage_key,
)
from diffloc.progress import progress
from diffloc.reloc.rendered import (
    RenderedCandidate,
    RenderedDatabaseLocalizer,
    RenderedLocalization,
    RenderedLocalizerConfig,
)
from diffloc.reloc.sequence_prior import SequencePrior, localize_in_order
from diffloc.reloc.stage_clock import STAGES
from diffloc.render.point_render import render_points
from diffloc.render.point_sizes import PointSizes

__all__ = [
    "LOCALIZATION_RECORD",
    "MAP_OUTPUTS",
    "RETRIEVAL_FILE",
    "TIMING_ARRAYS",
    "SequenceLocalization",
    "build_rgbd_database",
    "build_rgbd_map",
    "camera_settings",
    "candidate_arrays",
    "colored_point_map",
    "crossmodal_folder",
    "localize_sequence",
    "render_pose_stage",
    "scaled_images",
    "sequence_inputs",
    "stage_command",
]

MAPPING = MAPPING_SEQUENCE
"""The sequence whose images colour or texture the map."""

MAP_OUTPUTS: dict[type, str] = {
    PointMapConfig: "colored_map.ply",
    MeshMapConfig: "mesh",
    NerfMapConfig: "fields",
}
"""The output of the map stage each map option renders the database from."""
TIMING_ARRAYS = (
    "time_ms",
    "cpu_ms",
    "stage_ms",
    "stage_cpu_ms",
    "candidate_match_ms",
    "candidate_match_cpu_ms",
    "candidate_pnp_ms",
)
"""The arrays of ``localization.npz`` that hold times: all others are the same in every run
of the same settings."""
RETRIEVAL_FILE = "netvlad.safetensors"
"""The output of the retrieval stage (:mod:`diffloc.pipeline.crossmodal_retrieval`)."""
LOCALIZATION_RECORD = 4
"""Version of ``localization.npz``'s contents, part of the localisation stage's key: a record
of an older version (2: the ``candidate_*`` arrays, the validation's evidence; 3: the time per
stage and per candidate, the re-ranking's matches; 4: each candidate's plane share) is made
again."""


def crossmodal_folder(dataset: str | os.PathLike) -> Path:
    """``<dataset>/crossmodal``: where the stages of ``task=crossmodal`` live."""
    return Path(dataset) / "crossmodal"


def stage_command(dataset: Path, option: str) -> Command:
    """The command a stage of ``task=crossmodal`` records as its maker."""
    return Command("crossmodal", (f"dataset={dataset}", f"map={option}"))


def sequence_inputs(dataset: Path, name: str, with_poses: bool) -> dict[str, dict]:
    """Identities of the files of sequence ``name`` a stage reads: images and calibration,
    and the poses only where they are an input (the mapping run), never a query's truth."""
    files = ["rgb", "calib.yaml", *(["poses.txt"] if with_poses else [])]
    return {f"{name}/{rel}": identity(dataset / name / rel) for rel in files}


def scaled_images(seq: SequenceData, camera: PinholeCamera, indices: list[int]) -> torch.Tensor:
    """(N, 3, h, w) frames ``indices`` of ``seq`` resized (area) to ``camera``'s size."""
    size = (camera.height, camera.width)
    return torch.stack(
        [F.interpolate(seq.load_rgb(i)[None], size, mode="area")[0] for i in indices]
    )


@dataclass(frozen=True)
class RenderPosesSummary(StageSummary):
    """The ``render_poses`` summary: ``poses`` render poses at ``samples`` samples on
    ``floors`` floors of ``point_map``, ``trajectory_samples`` of them on the map's trajectory
    (``task.poses.trajectory_gap_m``)."""

    point_map: str
    poses: int
    samples: int
    floors: int
    trajectory_samples: int = 0


@dataclass(frozen=True)
class ColoredCloudSummary(StageSummary):
    """The ``crossmodal_map`` summary of ``map=tls|cloud``: ``colored_points`` of the
    cloud's ``points`` were seen by a mapping image (the others are dropped)."""

    map: str
    points: int
    colored_points: int


@dataclass(frozen=True)
class TexturedMeshSummary(StageSummary):
    """The ``crossmodal_map`` summary of ``map=mesh``: the mesh's ``faces`` and
    ``vertices``, the share of texels a mapping view textured, the build's wall ``seconds``."""

    map: str
    faces: int
    vertices: int
    textured_fraction: float
    seconds: float


@dataclass(frozen=True)
class RgbdDatabaseSummary(StageSummary):
    """The ``rgbd_database`` summary: rendered ``images``, their share of pixels without
    depth (``hole_share``), and the wall ``seconds`` and process ``cpu_seconds`` of rendering
    them with their features and NetVLAD."""

    images: int
    hole_share: float
    seconds: float
    cpu_seconds: float


@dataclass(frozen=True)
class LocalizationSummary(StageSummary):
    """The ``localize`` summary: ``accepted`` of ``queries`` frames of ``sequence``, and the
    1/5/15-minute load average the times in ``localization.npz`` ran under."""

    sequence: str
    queries: int
    accepted: int
    load_average: list[float]


def _checked(path: Path, what: str = "the dataset has no such point map") -> Path:
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: {what}")
    return path


def _read_cloud(path: Path) -> PointCloudData:
    """A dataset point map with normals (what the poses, colours and mesh need)."""
    cloud = read_point_cloud(_checked(path))
    if cloud.normals is None:
        raise ValueError(f"{path}: the point map has no normals (nx, ny, nz); they are needed")
    return cloud


def render_pose_stage(
    dataset: Path, point_map: str, config: PoseSelectionConfig, option: str
) -> tuple[torch.Tensor, StageOutcome[RenderPosesSummary]]:
    """The render poses of ``point_map`` (made or reused): (M, 4, 4) float64 and the stage's
    outcome.

    Raises:
        ValueError: the point map has no normals, no upward normal or an empty corridor on a
            floor; the message names the file and the ``task.poses`` settings.
    """
    path = dataset / MAP_FILES[point_map]
    folder = crossmodal_folder(dataset) / f"poses_{point_map}"
    inputs = {"point_map": identity(_checked(path))}
    with_trajectory = config.trajectory_gap_m is not None
    if with_trajectory:  # the mapping run's camera poses: the map's trajectory
        trajectory = _checked(
            dataset / MAPPING / "poses.txt",
            "the mapping run's poses give the render samples on its trajectory "
            "(task.trajectory_gap_m; remove the map's entry to select without them)",
        )
        inputs[f"{MAPPING}/poses.txt"] = identity(trajectory)
    key = stage_key({"poses": asdict(config)}, inputs)
    with open_stage(folder, "render_poses", stage_command(dataset, option), LockLevel.MAP) as stage:
        summary = stage.reusable(key, RenderPosesSummary)
        if summary is None:
            cloud = _read_cloud(path)
            trajectory = read_sequence(dataset, MAPPING).T_wc if with_trajectory else None
            try:
                selection = select_render_poses(cloud.points, cloud.normals, config, trajectory)
            except ValueError as exc:
                raise ValueError(f"{path}: {exc} (settings: task.poses.*)") from exc
            work = stage.workdir()
            arrays = {
                "T_wc": selection.T_wc.numpy(),
                "floor_index": selection.floor_index.numpy(),
                "sample_index": selection.sample_index.numpy(),
                "view_index": selection.view_index.numpy(),
            }
            with atomic_open(work / "poses.npz", "wb") as handle:
                write_npz(handle, arrays)
            write_floor_plan_figures(selection, work / "floors")
            summary = RenderPosesSummary(
                point_map=point_map,
                poses=len(selection),
                samples=int(selection.sample_index.max()) + 1,
                floors=len(selection.floors),
                trajectory_samples=int((selection.floor_index < 0).sum())
                // selection.views_per_sample,
            )
            summary = stage.commit(key, summary, ["poses.npz", "floors"])
        outcome = stage.outcome(summary)
        T_wc = torch.from_numpy(read_npz_archive(folder / "poses.npz")["T_wc"])
    return T_wc, outcome


def colored_point_map(
    cloud: PointCloudData,
    mapping: SequenceData,
    camera: PinholeCamera,
    sizes: PointSizes,
    show_progress: bool = False,
) -> PointMap:
    """The point map coloured from the mapping images (:meth:`PointMap.colorize`).

    The occlusion test uses depth rendered from the cloud itself at the mapping poses with
    ``sizes`` (no sensor depth); images are resized to ``camera``.

    Args:
        cloud: (N, 3) points with normals.
        mapping: the mapping sequence (images and poses).
        camera: the camera of the resized images.
        sizes: splat sizes of the occlusion depth.
        show_progress: progress bar over the views.

    Returns:
        The coloured points (those no view sees are dropped).
    """
    points = torch.from_numpy(cloud.points)
    normals = F.normalize(torch.from_numpy(cloud.normals), dim=1)
    images = scaled_images(mapping, camera, list(range(len(mapping))))
    grey = torch.full_like(points, 0.5)
    depths = torch.cat(
        [render_points(points, grey, T, camera, sizes).depth for T in mapping.T_wc.split(8)]
    )
    point_map, _ = PointMap.colorize(
        points, images, mapping.T_wc, camera, depths, normals=normals, show_progress=show_progress
    )
    return point_map


def _map_settings(config: PointMapConfig | MeshMapConfig) -> dict:
    """The settings the map depends on: a cloud's colours depend on its occlusion sizes only
    (the render passes are the database's), a mesh on all of its settings."""
    if isinstance(config, PointMapConfig):
        occlusion = config.occlusion_sizes()
        return {
            "point_map": config.point_map,
            "rho_min": occlusion.rho_min,
            "rho_max": occlusion.rho_max,
        }
    return asdict(config)


def _make_cloud(
    cloud: PointCloudData,
    mapping: SequenceData,
    camera: PinholeCamera,
    config: PointMapConfig,
    work: Path,
    show_progress: bool,
) -> tuple[ColoredCloudSummary, list[str]]:
    """Colour the cloud into ``work/colored_map.ply``; the summary and the outputs."""
    colored = colored_point_map(cloud, mapping, camera, config.occlusion_sizes(), show_progress)
    colored.save_ply(work / "colored_map.ply")
    summary = ColoredCloudSummary(
        map=map_option(config), points=len(cloud.points), colored_points=len(colored.positions)
    )
    return summary, ["colored_map.ply"]


def _make_mesh(
    cloud: PointCloudData,
    mapping: SequenceData,
    camera: PinholeCamera,
    config: MeshMapConfig,
    work: Path,
    show_progress: bool,
) -> tuple[TexturedMeshSummary, list[str]]:
    """Reconstruct and texture the mesh into ``work/mesh/``; the summary and the outputs."""
    images = scaled_images(mapping, camera, list(range(len(mapping))))
    built = build_textured_mesh(
        cloud.points,
        cloud.normals,
        images,
        mapping.T_wc,
        camera,
        config.texture,
        config.exposures,
        show_progress,
    )
    write_atlas_obj(work / "mesh" / "mesh.obj", built.mesh)
    write_atlas_ply(work / "mesh" / "mesh.ply", built.mesh)
    summary = TexturedMeshSummary(
        map=map_option(config),
        faces=len(built.mesh.triangles),
        vertices=len(built.mesh.vertices),
        textured_fraction=built.textured_fraction,
        seconds=built.seconds,
    )
    return summary, ["mesh"]


def build_rgbd_map(
    dataset: Path,
    config: PointMapConfig | MeshMapConfig,
    image_scale: float,
    show_progress: bool = False,
) -> tuple[RGBDMap, StageOutcome[ColoredCloudSummary | TexturedMeshSummary]]:
    """The coloured cloud or textured mesh of ``config`` (made or reused) and the stage's
    outcome.

    Args:
        dataset: the dataset folder.
        config: the ``map`` node.
        image_scale: the mapping images are resized by this factor.
        show_progress: progress bars.
    """
    option = map_option(config)
    path = _checked(dataset / MAP_FILES[config.point_map])
    folder = crossmodal_folder(dataset) / option / "map"
    key = stage_key(
        {"map": _map_settings(config), "image_scale": image_scale},
        {"point_map": identity(path), **sequence_inputs(dataset, MAPPING, with_poses=True)},
    )
    with open_stage(
        folder, "crossmodal_map", stage_command(dataset, option), LockLevel.MAP
    ) as stage:
        cloud = isinstance(config, PointMapConfig)
        summary = stage.reusable(key, ColoredCloudSummary if cloud else TexturedMeshSummary)
        if summary is None:
            mapping = read_sequence(dataset, MAPPING)
            make = _make_cloud if cloud else _make_mesh
            summary, outputs = make(
                _read_cloud(path),
                mapping,
                mapping.camera.scaled(image_scale),
                config,
                stage.workdir(),
                show_progress,
            )
            summary = stage.commit(key, summary, outputs)
        outcome = stage.outcome(summary)
        if cloud:
            colored = PointMap.load_ply(folder / "colored_map.ply")
            rgbd_map = PointCloudMap(
                colored.positions, colored.colors, config.sizes(), config.visibility()
            )
            return rgbd_map, outcome
        return MeshMap(read_textured_mesh_obj(folder / "mesh" / "mesh.obj")), outcome


def build_rgbd_database(
    dataset: Path,
    config: PointMapConfig | MeshMapConfig | NerfMapConfig,
    database: DatabaseConfig,
    rgbd_map: tuple[RGBDMap, StageOutcome],
    poses: tuple[torch.Tensor, StageOutcome],
    camera: PinholeCamera,
    show_progress: bool = False,
) -> tuple[RenderedDatabase, StageOutcome[RgbdDatabaseSummary]]:
    """The RGB-D database of the map at the render poses (made or reused) and the stage's
    outcome.

    Args:
        dataset: the dataset folder.
        config: the map settings (the render sizes of a cloud are part of the key, and its
            screen-space visibility filter when it is on).
        database: features and NetVLAD settings.
        rgbd_map: the map and its outcome (:func:`build_rgbd_map`, or
            :func:`~diffloc.pipeline.crossmodal_nerf.build_nerf_map`).
        poses: the (M, 4, 4) render poses and their outcome (:func:`render_pose_stage`).
        camera: the render camera.
        show_progress: progress bars.
    """
    option = map_option(config)
    folder = crossmodal_folder(dataset) / option / "database"
    renderer, map_outcome = rgbd_map
    T_wc, pose_outcome = poses
    cloud = isinstance(config, PointMapConfig)
    sizes = asdict(config.sizes()) if cloud else None
    settings = {"database": asdict(database), "sizes": sizes, "camera": camera_settings(camera)}
    visibility = config.visibility() if cloud else None
    if visibility is not None:  # keyed only when on: the keys of the renders before stay
        settings["visibility"] = asdict(visibility)
    map_output = MAP_OUTPUTS[type(config)]
    key = stage_key(
        settings,
        {
            "map": map_outcome.outputs[map_output],
            "poses": pose_outcome.outputs["poses.npz"],
        },
    )
    command = stage_command(dataset, option)
    with open_stage(folder, "rgbd_database", command, LockLevel.DATABASE) as stage:
        summary = stage.reusable(key, RgbdDatabaseSummary)
        if summary is None:
            filtered = ", screen-space visibility" if visibility is not None else ""
            source = f"{option} ({config.passes}{filtered})" if cloud else option
            start, start_cpu = time.perf_counter(), time.process_time()
            db = render_database(
                renderer, T_wc, camera, database, source, show_progress=show_progress
            )
            summary = RgbdDatabaseSummary(
                images=db.num_images,
                hole_share=float(db.holes.mean()),
                seconds=round(time.perf_counter() - start, 2),
                cpu_seconds=round(time.process_time() - start_cpu, 2),
            )
            db.save(stage.workdir() / "rgbd")
            summary = stage.commit(key, summary, ["rgbd"])
        outcome = stage.outcome(summary)
        return RenderedDatabase.load(folder / "rgbd"), outcome


def camera_settings(camera: PinholeCamera) -> dict:
    """A camera's intrinsics and size as floats (a stage key's part; compared by value)."""
    return {k: float(getattr(camera, k)) for k in ("fx", "fy", "cx", "cy", "width", "height")}


@dataclass(frozen=True)
class SequenceLocalization:
    """Algorithm 1's answers for Q query frames of one sequence.

    Attributes:
        frames: (Q,) int64 frame indices.
        T_wc: (Q, 4, 4) float64 estimates (identity where no pose was found).
        success: (Q,) bool, a PnP pose was found.
        accepted: (Q,) bool, found and passed the validation (the answer).
        reference: (Q,) int64 database image the pose came from (-1: none).
        top1: (Q,) int64 first retrieved database image (-1: none).
        num_matches: (Q,) int64 LighterGlue matches with the reference.
        num_points: (Q,) int64 of those, matches whose reference keypoint has depth.
        num_inliers: (Q,) int64 PnP inliers of the answer.
        photometric: (Q,) float64 photometric consistency of the pose found (NaN: no pose
            or too little overlap).
        accepted_without_photometric: (Q,) bool, found and passed every validation test but
            the photometric one (a replay of another threshold needs it).
        from_prior: (Q,) bool, the reference came from the pose prior (``task.localizer.prior``;
            all false without it).
        prior_images: (Q,) int64 database images the pose prior put first (0: no prior).
        time_ms: (Q,) float64 wall time per query (features, retrieval, matching, PnP,
            photometric consistency).
        cpu_ms: (Q,) float64 process CPU time per query over the same span.
        stage_ms: (Q, S) float64 wall ms per stage, columns in the order of
            :data:`~diffloc.reloc.stage_clock.STAGES` (matching and PnP summed over the
            candidates).
        stage_cpu_ms: (Q, S) float64 process CPU ms per stage.
        candidate_query: (C,) int64 the query of each of the C candidates tried over all
            queries (each query's in the order tried): the validation's evidence, so that a
            replay (``experiments/crossmodal_breakdown.py``) can score other thresholds.
        candidate_reference: (C,) int64 its database image.
        candidate_chosen: (C,) bool, it is its query's answer.
        candidate_success: (C,) bool, PnP found a pose.
        candidate_matches: (C,) int64 LighterGlue matches.
        candidate_points: (C,) int64 matches with depth.
        candidate_inliers: (C,) int64 PnP inliers.
        candidate_coverage: (C,) float64 share of the query grid cells holding an inlier.
        candidate_rms_px: (C,) float64 RMS reprojection error of the inliers (NaN: none).
        candidate_position: (C, 3) float64 camera position of its pose (world frame).
        candidate_rerank_matches: (C,) int64 its mutual-NN matches in the re-ranking (-1: not
            re-ranked, e.g. a prior image or re-ranking off).
        candidate_match_ms: (C,) float64 wall ms of its LighterGlue match.
        candidate_match_cpu_ms: (C,) float64 process CPU ms of its LighterGlue match.
        candidate_pnp_ms: (C,) float64 wall ms of its lifting and PnP.
        candidate_plane_share: (C,) float64 share of its inliers on their dominant plane (NaN:
            no pose).
    """

    frames: np.ndarray
    T_wc: np.ndarray
    success: np.ndarray
    accepted: np.ndarray
    reference: np.ndarray
    top1: np.ndarray
    num_matches: np.ndarray
    num_points: np.ndarray
    num_inliers: np.ndarray
    photometric: np.ndarray
    accepted_without_photometric: np.ndarray
    from_prior: np.ndarray
    prior_images: np.ndarray
    time_ms: np.ndarray
    cpu_ms: np.ndarray
    stage_ms: np.ndarray
    stage_cpu_ms: np.ndarray
    candidate_query: np.ndarray
    candidate_reference: np.ndarray
    candidate_chosen: np.ndarray
    candidate_success: np.ndarray
    candidate_matches: np.ndarray
    candidate_points: np.ndarray
    candidate_inliers: np.ndarray
    candidate_coverage: np.ndarray
    candidate_rms_px: np.ndarray
    candidate_position: np.ndarray
    candidate_rerank_matches: np.ndarray
    candidate_match_ms: np.ndarray
    candidate_match_cpu_ms: np.ndarray
    candidate_pnp_ms: np.ndarray
    candidate_plane_share: np.ndarray

    @classmethod
    def load(cls, path: Path) -> SequenceLocalization:
        """Read ``localization.npz`` written by :func:`localize_sequence`.

        Raises:
            ValueError: an archive without some of the arrays (e.g. one written before
                :data:`LOCALIZATION_RECORD` had them); the message names the file.
        """
        remedy = (
            f"written before record version {LOCALIZATION_RECORD}? Run the localisation again "
            "(diffloc task=crossmodal)"
        )
        return cls(**read_npz_fields(path, list(cls.__dataclass_fields__), remedy))

    def candidates(self, query: int) -> tuple[RenderedCandidate, tuple[RenderedCandidate, ...]]:
        """``(best, tried)`` of query ``query`` (index into ``frames``) rebuilt from the record,
        as :func:`~diffloc.reloc.rendered.choose_candidate` returned them (the poses carry
        their positions only, which is all the validation reads); ``best`` is
        :meth:`RenderedCandidate.none` when nothing was tried."""
        tried = []
        best = RenderedCandidate.none()
        for c in np.flatnonzero(self.candidate_query == query).tolist():
            T_wc = torch.eye(4, dtype=torch.float64)
            T_wc[:3, 3] = torch.from_numpy(self.candidate_position[c])
            candidate = RenderedCandidate(
                int(self.candidate_reference[c]),
                T_wc,
                bool(self.candidate_success[c]),
                int(self.candidate_matches[c]),
                int(self.candidate_points[c]),
                int(self.candidate_inliers[c]),
                float(self.candidate_coverage[c]),
                float(self.candidate_rms_px[c]),
                float(self.candidate_match_ms[c]),
                float(self.candidate_match_cpu_ms[c]),
                float(self.candidate_pnp_ms[c]),
                float(self.candidate_plane_share[c]),
            )
            tried.append(candidate)
            if self.candidate_chosen[c]:
                best = candidate
        return best, tuple(tried)


def _rerank_matches(result: RenderedLocalization, reference: int) -> int:
    """The re-ranking's matches of ``reference`` in ``result`` (-1: it was not re-ranked)."""
    hit = (result.retrieved == reference).nonzero()
    return int(result.rerank_matches[hit[0, 0]]) if len(hit) else -1


def candidate_arrays(results: list[RenderedLocalization]) -> dict[str, np.ndarray]:
    """The ``candidate_*`` arrays of :class:`SequenceLocalization` from the answers of its
    queries (the candidate of an answer is the one of its reference)."""
    rows = [(q, r, c) for q, r in enumerate(results) for c in r.candidates]
    if not rows:
        position = np.zeros((0, 3))
    else:
        position = np.stack([c.T_wc[:3, 3].numpy() for _, _, c in rows])
    return {
        "candidate_query": np.array([q for q, _, _ in rows], dtype=np.int64),
        "candidate_reference": np.array([c.reference for _, _, c in rows], dtype=np.int64),
        "candidate_chosen": np.array([c.reference == r.reference for _, r, c in rows], dtype=bool),
        "candidate_success": np.array([c.success for _, _, c in rows], dtype=bool),
        "candidate_matches": np.array([c.num_matches for _, _, c in rows], dtype=np.int64),
        "candidate_points": np.array([c.num_points for _, _, c in rows], dtype=np.int64),
        "candidate_inliers": np.array([c.num_inliers for _, _, c in rows], dtype=np.int64),
        "candidate_coverage": np.array([c.coverage for _, _, c in rows], dtype=np.float64),
        "candidate_rms_px": np.array([c.rms_px for _, _, c in rows], dtype=np.float64),
        "candidate_position": position.astype(np.float64),
        "candidate_rerank_matches": np.array(
            [_rerank_matches(r, c.reference) for _, r, c in rows], dtype=np.int64
        ),
        "candidate_match_ms": np.array([c.match_ms for _, _, c in rows], dtype=np.float64),
        "candidate_match_cpu_ms": np.array([c.match_cpu_ms for _, _, c in rows], dtype=np.float64),
        "candidate_pnp_ms": np.array([c.pnp_ms for _, _, c in rows], dtype=np.float64),
        "candidate_plane_share": np.array([c.plane_share for _, _, c in rows], dtype=np.float64),
    }


def _stage_table(times: list[dict[str, float]]) -> np.ndarray:
    """(Q, S) float64 ms per query and stage (:data:`~diffloc.reloc.stage_clock.STAGES`)."""
    return np.array([[t[name] for name in STAGES] for t in times], dtype=np.float64).reshape(
        len(times), len(STAGES)
    )


def localize_sequence(
    dataset: Path,
    option: str,
    sequence: str,
    every: int,
    config: RenderedLocalizerConfig,
    database: tuple[RenderedDatabase, StageOutcome],
    show_progress: bool = False,
    retrieval: StageOutcome | None = None,
) -> tuple[SequenceLocalization, StageOutcome[LocalizationSummary]]:
    """Localise every ``every``-th frame of ``sequence`` (made or reused) and the stage's
    outcome.

    Query images are resized (area) to the database camera's size. With ``config.prior`` set
    (its ``growth_mps`` too), the frames are localised in time order with the last accepted
    pose as a prior (:mod:`diffloc.reloc.sequence_prior`). ``retrieval``: the outcome
    of the stage that tuned the database's NetVLAD
    (:func:`~diffloc.pipeline.crossmodal_retrieval.tune_retrieval_stage`, whose database
    ``database`` then is), part of the key; ``None`` for the database as built.
    """
    db, db_outcome = database
    folder = crossmodal_folder(dataset) / option / f"localize_{sequence}"
    tuned = {} if retrieval is None else {"retrieval": retrieval.outputs[RETRIEVAL_FILE]}
    key = stage_key(
        {
            "localizer": asdict(config),
            "every": every,
            "camera": camera_settings(db.camera),
            "record": LOCALIZATION_RECORD,
        },
        {
            "database": db_outcome.outputs["rgbd"],
            **tuned,
            **sequence_inputs(dataset, sequence, with_poses=False),
        },
    )
    command = stage_command(dataset, option)
    with open_stage(folder, "localize", command, LockLevel.UPDATED) as stage:
        summary = stage.reusable(key, LocalizationSummary)
        if summary is None:
            seq = read_sequence(dataset, sequence)
            camera = seq.camera.scaled(db.camera.width / seq.camera.width)
            localizer = RenderedDatabaseLocalizer(db, config)
            frames = list(range(0, len(seq), every))
            prior = None if config.prior is None else SequencePrior(config.prior, db.T_wc)
            images = (
                scaled_images(seq, camera, [i])[0]
                for i in progress(frames, sequence, show_progress)
            )
            times = seq.timestamps[frames].tolist()
            results = list(localize_in_order(localizer, images, times, camera, prior))
            arrays = {
                "frames": np.array(frames, dtype=np.int64),
                "T_wc": torch.stack([r.T_wc for r in results]).numpy(),
                "success": np.array([r.success for r in results]),
                "accepted": np.array([r.accepted for r in results]),
                "reference": np.array([r.reference for r in results], dtype=np.int64),
                "top1": np.array(
                    [int(r.retrieved[0]) if len(r.retrieved) else -1 for r in results],
                    dtype=np.int64,
                ),
                "num_matches": np.array([r.num_matches for r in results], dtype=np.int64),
                "num_points": np.array([r.num_points for r in results], dtype=np.int64),
                "num_inliers": np.array([r.num_inliers for r in results], dtype=np.int64),
                "photometric": np.array([r.photometric for r in results], dtype=np.float64),
                "accepted_without_photometric": np.array(
                    [r.accepted_without_photometric for r in results]
                ),
                "from_prior": np.array([r.from_prior for r in results]),
                "prior_images": np.array([len(r.prior) for r in results], dtype=np.int64),
                "time_ms": np.array([r.time_ms for r in results], dtype=np.float64),
                "cpu_ms": np.array([r.cpu_ms for r in results], dtype=np.float64),
                "stage_ms": _stage_table([r.stage_ms for r in results]),
                "stage_cpu_ms": _stage_table([r.stage_cpu_ms for r in results]),
                **candidate_arrays(results),
            }
            with atomic_open(stage.workdir() / "localization.npz", "wb") as handle:
                write_npz(handle, arrays)
            summary = LocalizationSummary(
                sequence=sequence,
                queries=len(frames),
                accepted=int(arrays["accepted"].sum()),
                load_average=list(os.getloadavg()),  # the times of localization.npz ran under
            )
            summary = stage.commit(key, summary, ["localization.npz"])
        outcome = stage.outcome(summary)
        return SequenceLocalization.load(folder / "localization.npz"), outcome
