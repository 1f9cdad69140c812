"""The map stage of ``diffloc task=crossmodal map=nerf``: the trained radiance-field submaps.

``<dataset>/crossmodal/nerf/map/`` (``crossmodal_map.json``) holds ``fields/``, a
:class:`~diffloc.crossmodal.submap_fields.SubmapFieldMap` folder: the clustering of the
mapping run by the root ``nerf`` node's settings, the mapping poses, and a copy of the field of
every submap that serves at least one render pose. The database stage renders it like the other
maps (:func:`~diffloc.pipeline.crossmodal_stage.build_rgbd_database`).

The fields are not trained here: each needed submap must have been committed by
``diffloc task=train_nerf nerf.submap=<k>`` with the same ``nerf.*`` settings (the field that
stage would reuse). If one is missing, trained with other settings, or changed since, the run
stops after the (cached) render-pose stage and before any rendering, with one line naming the
``train_nerf`` command. Each field is read under its submap folder's shared lock, then the map
stage's own folder is locked, so no lock is held out of order.

Key: the ``map`` and clustering settings, the render poses, the mapping poses and the identity
of every field read, so a retrained submap makes the map, and from it the database, again.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch

from diffloc.crossmodal.submap_fields import SubmapFieldMap, write_submap_fields
from diffloc.io.dataset import read_sequence
from diffloc.io.identity import identity
from diffloc.maps.nerf.submaps import cluster_trajectory, serving_submap
from diffloc.pipeline.crossmodal_config import NerfMapConfig
from diffloc.pipeline.crossmodal_stage import MAP_OUTPUTS, crossmodal_folder
from diffloc.pipeline.hints import Command
from diffloc.pipeline.nerf_config import TrainNerfConfig
from diffloc.pipeline.nerf_stage import TrainedField, read_trained_field
from diffloc.pipeline.stage import LockLevel, StageOutcome, StageSummary, open_stage, stage_key

__all__ = ["NerfMapSummary", "build_nerf_map"]

FIELDS = MAP_OUTPUTS[NerfMapConfig]


@dataclass(frozen=True)
class NerfMapSummary(StageSummary):
    """The ``crossmodal_map`` summary of ``map=nerf``.

    Attributes:
        map: ``"nerf"``.
        submaps: submaps of the clustering.
        served: the submaps that serve at least one render pose (their fields were copied).
        poses_served: render poses each of ``served`` serves.
        field_steps: training steps of each served field (from its ``train_nerf`` record).
        field_final_loss: its last training loss.
    """

    map: str
    submaps: int
    served: list[int]
    poses_served: list[int]
    field_steps: list[int]
    field_final_loss: list[float | None]


def build_nerf_map(
    dataset: str | os.PathLike,
    config: NerfMapConfig,
    nerf: TrainNerfConfig,
    poses: tuple[torch.Tensor, StageOutcome],
) -> tuple[SubmapFieldMap, StageOutcome[NerfMapSummary]]:
    """The submap-field map serving the render poses (made or reused) and the stage's outcome.

    Args:
        dataset: the dataset folder.
        config: the ``map`` node (``map=nerf``).
        nerf: the root ``nerf`` node: where the fields are and how the mapping run was
            clustered and trained.
        poses: the (M, 4, 4) render poses and their outcome
            (:func:`~diffloc.pipeline.crossmodal_stage.render_pose_stage`).

    Raises:
        MissingStageError: a needed submap was never trained; the message names the
            ``diffloc task=train_nerf ... nerf.submap=<k>`` command.
        StaleStageError: a needed field was trained with other ``nerf.*`` settings or data,
            or changed since its record; the message names the same command.
    """
    dataset = Path(dataset)
    T_wc, pose_outcome = poses
    mapping = read_sequence(dataset, nerf.sequence)
    submaps = cluster_trajectory(mapping.T_wc, nerf.submaps)
    serving = serving_submap(T_wc, submaps, mapping.T_wc, nerf.submaps)
    served, counts = torch.unique(serving, return_counts=True)
    sequence = identity(dataset / nerf.sequence)
    fields: dict[int, TrainedField] = {
        k: read_trained_field(dataset, replace(nerf, submap=k), sequence) for k in served.tolist()
    }
    key = stage_key(
        {"map": asdict(config), "submaps": asdict(nerf.submaps)},
        {
            "poses": pose_outcome.outputs["poses.npz"],
            "sequence": sequence,
            **{f"field_{k}": field.identity for k, field in fields.items()},
        },
    )
    folder = crossmodal_folder(dataset) / "nerf" / "map"
    command = Command("crossmodal", (f"dataset={dataset}", "map=nerf"))
    with open_stage(folder, "crossmodal_map", command, LockLevel.MAP) as stage:
        summary = stage.reusable(key, NerfMapSummary)
        if summary is None:
            write_submap_fields(
                stage.workdir() / FIELDS,
                submaps,
                nerf.submaps,
                mapping.T_wc,
                {k: field.files for k, field in fields.items()},
                config.min_opacity,
            )
            summary = NerfMapSummary(
                map="nerf",
                submaps=len(submaps),
                served=list(fields),
                poses_served=counts.tolist(),
                field_steps=[field.summary.steps for field in fields.values()],
                field_final_loss=[field.summary.final_loss for field in fields.values()],
            )
            summary = stage.commit(key, summary, [FIELDS])
        outcome = stage.outcome(summary)
        return SubmapFieldMap.from_folder(folder / FIELDS), outcome
