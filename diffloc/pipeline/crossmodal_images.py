"""The database stage of ``diffloc task=crossmodal map=images``: the mapping run's real images.

Seed 2's comparison rows localise the queries against the mapping images themselves, with the
same Algorithm 1. The stage ``<dataset>/crossmodal/images/database/`` (``rgbd_database.json``)
keeps every ``map.every``-th ``mapping`` frame, resized to the task's camera, with its pose
(``mapping/poses.txt``, the database's poses as in seed 2) and z-depth rendered from the surfel
map (:func:`~diffloc.crossmodal.real_images.surfel_depth_views`), and builds XFeat features and
NetVLAD (``rgbd/``) like the rendered databases; the localisation stage
(:func:`~diffloc.pipeline.crossmodal_stage.localize_sequence`) takes it unchanged. Keyed on
``map.every``, ``task.database``, the camera, the surfel map and the mapping sequence's images,
poses and calibration. No render poses and no map stage: there is nothing to render.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

from diffloc.crossmodal.database import DatabaseConfig, RenderedDatabase, build_database
from diffloc.crossmodal.real_images import surfel_depth_views
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.dataset import read_sequence
from diffloc.pipeline.crossmodal_config import ImageMapConfig
from diffloc.pipeline.crossmodal_stage import (
    MAPPING,
    camera_settings,
    crossmodal_folder,
    scaled_images,
    sequence_inputs,
    stage_command,
)
from diffloc.pipeline.database_stage import read_surfel_map
from diffloc.pipeline.stage import (
    LockLevel,
    StageOutcome,
    StageSummary,
    open_stage,
    output_identity,
    stage_key,
)

__all__ = ["ImageDatabaseSummary", "build_image_database"]


@dataclass(frozen=True)
class ImageDatabaseSummary(StageSummary):
    """The ``rgbd_database`` summary of ``map=images``: ``images`` mapping frames (every
    ``every``-th) and their share of pixels without surfel depth (``hole_share``)."""

    images: int
    every: int
    hole_share: float


def build_image_database(
    dataset: Path,
    config: ImageMapConfig,
    database: DatabaseConfig,
    camera: PinholeCamera,
    show_progress: bool = False,
) -> tuple[RenderedDatabase, StageOutcome[ImageDatabaseSummary]]:
    """The real-image RGB-D database (made or reused) and the stage's outcome.

    Args:
        dataset: the dataset folder (``mapping/`` and ``map/surfel_map.ply``).
        config: the ``map=images`` node.
        database: features and NetVLAD settings (``task.database``).
        camera: the database camera (the mapping camera scaled by ``task.image_scale``).
        show_progress: progress bars.

    Returns:
        The database (M = ceil(mapping frames / ``every``) images) and the outcome, whose
        output ``rgbd`` keys the localisation stages.

    Raises:
        MissingStageError: no surfel map; the message names ``diffloc task=build_map``.
        FileNotFoundError: no ``mapping`` sequence.
    """
    folder = crossmodal_folder(dataset) / "images" / "database"
    map_record, surfels = read_surfel_map(dataset)
    key = stage_key(
        {"images": asdict(config), "database": asdict(database), "camera": camera_settings(camera)},
        {
            "surfel_map": output_identity(map_record, "surfel_map.ply"),
            **sequence_inputs(dataset, MAPPING, with_poses=True),
        },
    )
    with open_stage(
        folder, "rgbd_database", stage_command(dataset, "images"), LockLevel.DATABASE
    ) as stage:
        summary = stage.reusable(key, ImageDatabaseSummary)
        if summary is None:
            seq = read_sequence(dataset, MAPPING)
            frames = list(range(0, len(seq), config.every))
            views = surfel_depth_views(
                scaled_images(seq, camera, frames),
                seq.T_wc[frames],
                camera,
                surfels,
                database.batch_size,
                show_progress,
            )
            source = f"mapping images (every {config.every}-th), surfel-map depth"
            db = build_database(
                views,
                seq.T_wc[frames],
                camera,
                database,
                source,
                show_progress=show_progress,
                real=True,
            )
            db.save(stage.workdir() / "rgbd")
            summary = ImageDatabaseSummary(
                images=db.num_images, every=config.every, hole_share=float(db.holes.mean())
            )
            summary = stage.commit(key, summary, ["rgbd"])
        outcome = stage.outcome(summary)
        return RenderedDatabase.load(folder / "rgbd"), outcome
