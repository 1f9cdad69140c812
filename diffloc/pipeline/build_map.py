"""The map-building stage: lidar of a dataset -> surfel map + coloured point maps + a preview.

:func:`build_maps` takes a dataset folder and writes, inside its ``map/`` folder:

- ``surfel_map.ply``: the :class:`~diffloc.maps.surfel.SurfelMap` of the mapping sequence's
  lidar (seed 1, Sec. III-A);
- ``point_map.ply`` (and ``tls_point_map.ply`` when the dataset has a terrestrial-scanner map):
  the lidar map coloured by projecting the mapping images onto it, nearest unoccluded view
  first, as a colour lidar map would be (seed 2's point-cloud map). Occlusion is judged
  against the surfel map rendered into each image, so no ground-truth depth is needed and the
  stage runs the same on real data;
- ``surfel_preview.png``: a few mapping images beside their rendered surfel index maps;
- ``build_map.json``: the :class:`MapSummary` (configuration, counts, clouds named but absent
  from the dataset) and the stage manifest (:mod:`diffloc.pipeline.stage`): the identity
  of every input read and of every output. A folder whose record verifies and holds the same
  configuration and inputs is reused, like hloc's cached stages.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from diffloc.checks import check_positive_int
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.dataset import map_paths, read_sequence
from diffloc.io.identity import identity
from diffloc.io.ply import read_point_cloud
from diffloc.io.sequence import SequenceData
from diffloc.maps.lidar_source import lidar_points_with_origins
from diffloc.maps.pointcloud import ColorizeConfig, PointMap
from diffloc.maps.surfel import SurfelMap, SurfelMapConfig
from diffloc.pipeline.hints import Command
from diffloc.pipeline.stage import LockLevel, StageSummary, open_stage, stage_key
from diffloc.progress import progress
from diffloc.render.surfel_render import render_surfel_index

__all__ = [
    "BUILD_MAP_FORMAT_VERSION",
    "POINT_CLOUD_MAPS",
    "STAGE",
    "BuildMapConfig",
    "MapSummary",
    "build_maps",
    "check_build_map_config",
    "render_views",
]

BUILD_MAP_FORMAT_VERSION = 1

STAGE = "build_map"
"""The stage name: its record is ``map/build_map.json``."""

POINT_CLOUD_MAPS = ("lidar_map", "tls_map")
"""The dataset map clouds (keys of :data:`diffloc.io.dataset.MAP_FILES`) the stage can read."""


@dataclass
class BuildMapConfig:
    """How the map stage runs (the Hydra ``task=build_map`` group).

    Attributes:
        sequence: the dataset sequence whose lidar and images make the maps.
        use_sweeps: build surfels from that sequence's lidar sweeps.
        clouds: dataset map clouds (:data:`POINT_CLOUD_MAPS`, e.g. ``tls_map``) added to the
            surfel input; an unknown name is an error, one the dataset lacks is skipped (and
            listed in the record's ``skipped_clouds``).
        point_maps: dataset map clouds to colour into ``<key without _map>_point_map.ply``
            (``lidar_map`` -> ``point_map.ply``); names as for ``clouds``. Point maps of
            clouds no longer listed are removed.
        image_scale: images and the occlusion depth are resized by this factor before
            colouring (0.5 keeps memory near 300 MB for 256 VGA views).
        render_batch: views rendered per batch (>= 1).
        preview_frames: mapping frames shown in ``surfel_preview.png`` (>= 1).
        overwrite: rebuild even if ``build_map.json`` holds the same configuration and inputs.
        colorize: occlusion tolerance and chunking of the colouring.
    """

    name: str = "build_map"
    sequence: str = "mapping"
    use_sweeps: bool = True
    clouds: list[str] = field(default_factory=lambda: ["tls_map"])
    point_maps: list[str] = field(default_factory=lambda: ["lidar_map", "tls_map"])
    image_scale: float = 0.5
    render_batch: int = 8
    preview_frames: int = 3
    overwrite: bool = False
    colorize: ColorizeConfig = field(default_factory=ColorizeConfig)

    def __post_init__(self) -> None:
        check_build_map_config(self)


def render_views(
    surfels: SurfelMap,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    batch: int,
    show_progress: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Surfel ids and z-depth of many views, rendered ``batch`` views at a time.

    Args:
        surfels: the map.
        T_wc: (V, 4, 4) camera-to-world poses.
        camera: an unbatched camera of size (H, W).
        batch: views per render call.
        show_progress: progress bar over batches.

    Returns:
        ids (V, H, W) int64 (-1 = no surfel) and depth (V, 1, H, W) float32 (0 = none).
    """
    ids, depth = [], []
    starts = range(0, len(T_wc), batch)
    for start in progress(starts, "rendering surfel maps", show_progress):
        render = render_surfel_index(
            surfels.centers,
            surfels.normals,
            surfels.radii,
            T_wc[start : start + batch].to(torch.float32),
            camera,
        )
        ids.append(render.ids)
        depth.append(render.depth[:, None])
    return torch.cat(ids), torch.cat(depth)


def _load_images(
    seq: SequenceData, frames: np.ndarray, scale: float, show_progress: bool
) -> torch.Tensor:
    """(V, 3, h, w) float32 images of ``frames`` resized by ``scale`` (area averaging)."""
    images = []
    for i in progress(frames.tolist(), f"{seq.name}: images", show_progress):
        image = seq.load_rgb(i)[None]
        if scale != 1.0:
            image = F.interpolate(image, scale_factor=scale, mode="area")
        images.append(image[0])
    return torch.stack(images)


def _id_colors(ids: torch.Tensor) -> torch.Tensor:
    """(..., H, W) surfel ids -> (..., H, W, 3) pseudo-random colours, black where -1."""
    hashed = (ids * 2654435761) & 0xFFFFFF
    rgb = torch.stack([(hashed >> s) & 0xFF for s in (16, 8, 0)], -1).float() / 255
    return torch.where((ids >= 0)[..., None], 0.25 + 0.75 * rgb, torch.zeros_like(rgb))


def _write_preview(
    path: Path, images: torch.Tensor, ids: torch.Tensor, depth: torch.Tensor, title: str
) -> None:
    from matplotlib.figure import Figure  # object API: the caller's backend is left alone

    rows = len(images)
    fig = Figure(figsize=(12, 3.2 * rows))
    axes = fig.subplots(rows, 3, squeeze=False)
    for r in range(rows):
        panels = (
            (images[r].permute(1, 2, 0).numpy(), "image", None),
            (_id_colors(ids[r]).numpy(), "rendered surfel ids", None),
            (depth[r, 0].numpy(), "rendered surfel depth (m)", "turbo"),
        )
        for ax, (panel, label, cmap) in zip(axes[r], panels, strict=True):
            shown = ax.imshow(panel, cmap=cmap)
            ax.set_title(label, fontsize=9)
            ax.axis("off")
            if cmap is not None:
                fig.colorbar(shown, ax=ax, fraction=0.035)
    fig.suptitle(title)
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=80)
    tmp.replace(path)


def _colour_cloud(
    cloud_path: Path,
    images: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    depth: torch.Tensor,
    cfg: BuildMapConfig,
    show_progress: bool,
) -> tuple[PointMap, int]:
    cloud = read_point_cloud(cloud_path)
    normals = None
    if cloud.normals is not None:
        normals = torch.from_numpy(cloud.normals)
        normals = normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    point_map, seen = PointMap.colorize(
        torch.from_numpy(cloud.points),
        images,
        T_wc.to(torch.float32),
        camera,
        depth,
        cfg.colorize,
        normals=normals,
        show_progress=show_progress,
    )
    return point_map, len(cloud.points)


def _check_names(names: list[str], setting: str) -> None:
    """Every name of a list setting is a point-cloud map of :data:`MAP_FILES`, named once."""
    unknown = [name for name in names if name not in POINT_CLOUD_MAPS]
    if unknown:
        raise ValueError(
            f"task.{setting} names unknown map clouds {unknown}; choose from "
            f"{list(POINT_CLOUD_MAPS)} (an absent one is skipped and recorded as skipped)"
        )
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ValueError(
            f"task.{setting} names {repeated} more than once (a cloud would be used twice); "
            "name each cloud once"
        )


def check_build_map_config(cfg: BuildMapConfig) -> None:
    """Reject an unusable map-stage configuration before any work starts.

    Raises:
        ValueError: an unknown or repeated cloud name in ``clouds``/``point_maps``,
            ``render_batch`` or ``preview_frames`` below 1, ``image_scale`` not in (0, 1], or
            an empty sequence name; the message names the setting.
    """
    _check_names(list(cfg.clouds), "clouds")
    _check_names(list(cfg.point_maps), "point_maps")
    check_positive_int(cfg.render_batch, "task.render_batch")
    check_positive_int(cfg.preview_frames, "task.preview_frames")
    scale = cfg.image_scale
    if not (isinstance(scale, int | float) and math.isfinite(scale) and 0 < scale <= 1):
        raise ValueError(f"task.image_scale must be in (0, 1], got {scale!r}")
    if not cfg.sequence or "/" in cfg.sequence:
        raise ValueError(f"task.sequence must be a sequence name, got {cfg.sequence!r}")


def _point_map_name(key: str) -> str:
    """``lidar_map`` -> ``point_map``, ``tls_map`` -> ``tls_point_map``."""
    return "point_map" if key == "lidar_map" else f"{key.removesuffix('_map')}_point_map"


OWNED = (
    "surfel_map.ply",
    "surfel_preview.png",
    *(f"{_point_map_name(k)}.ply" for k in POINT_CLOUD_MAPS),
)
"""Every file the map stage may write into ``map/``."""


@dataclass(frozen=True)
class MapSummary(StageSummary):
    """What ``build_map`` made (the top level of ``map/build_map.json``).

    Attributes:
        config: the stage's settings (surfel settings under ``"surfel"``).
        source: the lidar the surfels came from (e.g. ``"mapping sweeps + tls_map"``).
        lidar_points: points given to the surfel construction.
        surfels: surfels in ``surfel_map.ply``.
        surfel_map: path of ``surfel_map.ply``.
        surfel_coverage: share of the rendered pixels of the preview (or colouring) views that
            a surfel covers.
        point_maps: coloured point map file stem (``point_map``, ``tls_point_map``) ->
            ``{"path": str, "points": int, "coloured_fraction": float}`` (share of the cloud's
            points some view coloured; the others are left out of the map).
        preview: path of ``surfel_preview.png``.
        skipped_clouds: clouds named in ``clouds`` / ``point_maps`` that the dataset lacks.
    """

    config: dict
    source: str
    lidar_points: int
    surfels: int
    surfel_map: str
    surfel_coverage: float
    point_maps: dict[str, dict]
    preview: str
    skipped_clouds: list[str]


def build_maps(
    dataset: str | Path,
    cfg: BuildMapConfig,
    surfel_cfg: SurfelMapConfig,
    show_progress: bool = True,
) -> MapSummary:
    """Build the surfel map and coloured point maps of a dataset folder (module docstring).

    The stage commits as a whole (:mod:`diffloc.pipeline.stage`): outputs are written into a
    hidden work folder in ``map/`` and moved into place with ``build_map.json`` written last;
    it is reused only while the configuration and the identity of the sequence folder and of
    every cloud it read are unchanged.

    Args:
        dataset: a diffloc dataset folder (``diffloc task=simulate`` or converted real data).
        cfg: the stage configuration.
        surfel_cfg: surfel construction (seed 1: mean radius 0.02 m indoors, 0.1 m outdoors).
        show_progress: progress bars.

    Returns:
        The summary written to ``map/build_map.json`` (beside the stage manifest).

    Raises:
        FileNotFoundError: no such dataset or sequence, or no lidar data in it.
        ValueError: a corrupt dataset or an unusable configuration (checked before any work).
    """
    check_build_map_config(cfg)
    root = Path(dataset)
    out = root / "map"
    config = {
        "format_version": BUILD_MAP_FORMAT_VERSION,
        **asdict(cfg),
        "surfel": asdict(surfel_cfg),
    }
    config.pop("overwrite")
    seq = read_sequence(root, cfg.sequence)
    existing = map_paths(root)
    used = [key for key in dict.fromkeys([*cfg.clouds, *cfg.point_maps]) if key in existing]
    command = Command("build_map", (f"dataset={dataset}",))
    with open_stage(out, STAGE, command, LockLevel.MAP) as stage:
        inputs = {"sequence": identity(root / cfg.sequence)}
        inputs.update({key: identity(existing[key]) for key in used})
        key = stage_key(config, inputs)
        previous = stage.reusable(key, MapSummary)
        if previous is not None and not cfg.overwrite:
            return previous
        summary, outputs = _build(
            root, seq, existing, cfg, surfel_cfg, stage.workdir(), show_progress
        )
        skipped = [k for k in dict.fromkeys([*cfg.clouds, *cfg.point_maps]) if k not in existing]
        summary = MapSummary(config=config, skipped_clouds=skipped, **summary)
        return stage.commit(key, summary, outputs, OWNED)


def _build(
    root: Path,
    seq: SequenceData,
    existing: dict[str, Path],
    cfg: BuildMapConfig,
    surfel_cfg: SurfelMapConfig,
    work: Path,
    show_progress: bool,
) -> tuple[dict, list[str]]:
    """Write the maps and preview into ``work``; their :class:`MapSummary` fields (all but
    ``config`` and ``skipped_clouds``) and file names."""
    out = root / "map"
    clouds = [existing[key] for key in cfg.clouds if key in existing]
    points, origins, sources = lidar_points_with_origins(seq, cfg.use_sweeps, clouds, show_progress)
    source = " + ".join(sources)
    surfels = SurfelMap.from_points(points, origins, surfel_cfg)
    surfels.save(work / "surfel_map.ply")
    outputs = ["surfel_map.ply"]

    camera = seq.camera.to(torch.float32)
    small = camera.scaled(cfg.image_scale) if cfg.image_scale != 1.0 else camera
    colour = [key for key in cfg.point_maps if key in existing]
    frames = np.linspace(0, len(seq) - 1, max(cfg.preview_frames, 1)).round().astype(int)
    # Colouring needs every view (images and occlusion depth); the preview only a few.
    views = np.arange(len(seq)) if colour else frames
    images = _load_images(seq, views, cfg.image_scale, show_progress)
    ids, depth = render_views(surfels, seq.T_wc[views], small, cfg.render_batch, show_progress)
    summary = {
        "source": source,
        "lidar_points": len(points),
        "surfels": len(surfels),
        "surfel_map": str(out / "surfel_map.ply"),
        "surfel_coverage": float((ids >= 0).float().mean()),
        "point_maps": {},
    }
    for key in colour:
        name = _point_map_name(key)
        point_map, total = _colour_cloud(
            existing[key], images, seq.T_wc, small, depth, cfg, show_progress
        )
        point_map.save(work / f"{name}.ply")
        outputs.append(f"{name}.ply")
        summary["point_maps"][name] = {
            "path": str(out / f"{name}.ply"),
            "points": len(point_map),
            "coloured_fraction": len(point_map) / max(total, 1),
        }
    shown = np.searchsorted(views, frames)
    _write_preview(
        work / "surfel_preview.png",
        images[shown],
        ids[shown],
        depth[shown],
        f"{root.name}: {len(surfels)} surfels from {source}",
    )
    outputs.append("surfel_preview.png")
    summary["preview"] = str(out / "surfel_preview.png")
    return summary, outputs
