"""The database stage of ``diffloc task=crossmodal map=images``: the mapping run's real images.

Seed 2's comparison rows localise the queries against the mapping images themselves, with the
same Algorithm 1. The stage ``<dataset>/crossmodal/images/database/`` (``rgbd_database.json``)
keeps every ``map.every``-th frame of each of ``map.sequences`` (the ``mapping`` front camera
by default; seed 2's "front + side" rows add the side cameras' sequences, e.g.
``mapping_left``, ``mapping_right``), resized to the task's camera, with its pose
(``<sequence>/poses.txt``, the database's poses as in seed 2) and z-depth rendered from the
surfel map (:func:`~diffloc.crossmodal.real_images.surfel_depth_views`), and builds XFeat
features and NetVLAD (``rgbd/``) like the rendered databases; the localisation stage
(:func:`~diffloc.pipeline.crossmodal_stage.localize_sequence`) takes it unchanged. Keyed on
``map.every``, ``map.sequences`` (when not the front camera alone), ``task.database``, the
camera, the surfel map and each sequence's images, poses and calibration. No render poses and
no map stage: there is nothing to render. Another ``map.sequences`` makes the stage again in
the same folder (the localisation stages follow).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from diffloc.crossmodal.database import DatabaseConfig, RenderedDatabase, build_database
from diffloc.crossmodal.real_images import surfel_depth_views
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.dataset import read_dataset_info, read_sequence
from diffloc.io.sequence import SequenceData
from diffloc.pipeline.crossmodal_config import ImageMapConfig
from diffloc.pipeline.crossmodal_stage import (
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

__all__ = ["ImageDatabaseSummary", "build_image_database", "check_image_sequences"]

CAMERA_TOLERANCE = 1e-6
"""Relative difference of intrinsics under which two sequences' cameras are the same."""


@dataclass(frozen=True)
class ImageDatabaseSummary(StageSummary):
    """The ``rgbd_database`` summary of ``map=images``: ``images`` frames (every ``every``-th
    of each of ``map.sequences``) and their share of pixels without surfel depth
    (``hole_share``)."""

    images: int
    every: int
    hole_share: float


def check_image_sequences(dataset: Path, sequences: list[str]) -> None:
    """Refuse ``map.sequences`` naming a sequence ``dataset`` does not hold.

    Raises:
        FileNotFoundError: a missing sequence; the message names it and, for a side camera,
            the simulation that makes one.
    """
    held = read_dataset_info(dataset)["sequences"]
    missing = [name for name in sequences if name not in held]
    if missing:
        raise FileNotFoundError(
            f"map.sequences: {dataset} has no sequence {', '.join(map(repr, missing))} (it has "
            f"{held}). A simulated rig's side cameras are sequences <mapping>_left / _right / "
            "_back / _yaw<deg> of a dataset simulated with them, e.g. `diffloc task=simulate "
            "scene=indoor scene.rig.side_camera_yaw_deg=[90,-90] out_dir=<new folder>` "
            "(mapping_left, mapping_right); a real rig's other cameras are sequences of their "
            "own in the dataset format (README, Dataset format)"
        )


def _check_camera(seq: SequenceData, camera: PinholeCamera) -> None:
    """Refuse a sequence whose camera, scaled to ``camera``'s width, is not ``camera``: the
    database holds one camera."""
    scaled = camera_settings(seq.camera.scaled(camera.width / seq.camera.width))
    expected = camera_settings(camera)
    if any(abs(scaled[k] - v) > CAMERA_TOLERANCE * max(1.0, abs(v)) for k, v in expected.items()):
        raise ValueError(
            f"map.sequences: {seq.name}'s camera {scaled} is not the database camera "
            f"{expected} (the mapping camera scaled by task.image_scale): the database holds "
            "one camera, so every sequence must have the same intrinsics"
        )


def build_image_database(
    dataset: Path,
    config: ImageMapConfig,
    database: DatabaseConfig,
    camera: PinholeCamera,
    show_progress: bool = False,
) -> tuple[RenderedDatabase, StageOutcome[ImageDatabaseSummary]]:
    """The real-image RGB-D database (made or reused) and the stage's outcome.

    Args:
        dataset: the dataset folder (the sequences of ``config.sequences`` and
            ``map/surfel_map.ply``).
        config: the ``map=images`` node.
        database: features and NetVLAD settings (``task.database``).
        camera: the database camera (the mapping camera scaled by ``task.image_scale``).
        show_progress: progress bars.

    Returns:
        The database (M = the sum over the sequences of ceil(frames / ``every``) images, in
        the order of ``config.sequences``) and the outcome, whose output ``rgbd`` keys the
        localisation stages.

    Raises:
        MissingStageError: no surfel map; the message names ``diffloc task=build_map``.
        FileNotFoundError: a sequence of ``config.sequences`` the dataset does not hold (the
            message names it and how to simulate side cameras).
        ValueError: a sequence whose camera differs from the database camera.
    """
    folder = crossmodal_folder(dataset) / "images" / "database"
    check_image_sequences(dataset, config.sequences)
    map_record, surfels = read_surfel_map(dataset)
    inputs = {
        name: identity
        for sequence in config.sequences
        for name, identity in sequence_inputs(dataset, sequence, with_poses=True).items()
    }
    key = stage_key(
        {"images": config.key(), "database": asdict(database), "camera": camera_settings(camera)},
        {"surfel_map": output_identity(map_record, "surfel_map.ply"), **inputs},
    )
    with open_stage(
        folder, "rgbd_database", stage_command(dataset, "images"), LockLevel.DATABASE
    ) as stage:
        summary = stage.reusable(key, ImageDatabaseSummary)
        if summary is None:
            images, poses = [], []
            for name in config.sequences:
                seq = read_sequence(dataset, name)
                _check_camera(seq, camera)
                frames = list(range(0, len(seq), config.every))
                images.append(scaled_images(seq, camera, frames))
                poses.append(seq.T_wc[frames])
            T_wc = torch.cat(poses)
            views = surfel_depth_views(
                torch.cat(images), T_wc, camera, surfels, database.batch_size, show_progress
            )
            source = (
                f"{' + '.join(config.sequences)} images (every {config.every}-th), surfel-map depth"
            )
            db = build_database(
                views,
                T_wc,
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
