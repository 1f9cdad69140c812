"""The database update stage: add a new sequence to a built database (seed 1 Sec. III-A).

``update_database`` loads the database ``task=build_db`` made (``<database_dir>/database``), adds
the frames of another sequence of the dataset at that sequence's poses with the same builder
(covisible matching, descriptor fusion, new map points, both culling rules), and writes the
stage folder ``<database_dir>/updated_<sequence>/`` as a whole (:mod:`diffloc.pipeline.stage`;
reused while its configuration, the built database, the surfel map and the sequence are
unchanged):

- ``database/``: the updated :class:`~diffloc.database.database.VisualDatabase`;
- ``update_db.json``: the :class:`UpdateSummary`: the counts before the update, after adding
  (every added image and every created point, before any removal) and after culling, what
  each culling rule removed, the ``(sequence, frame)`` of every surviving keyframe
  (``keyframe_sources``), the keyframe position RMSE against the dataset's ground truth and
  per-step timings.

A user's update run has its own poses: with ``db.noise_sigma > 0`` they are perturbed like the
database's (:func:`~diffloc.pipeline.database_stage.perturb_positions`) but from the seed
``task.noise_seed``, and the guided-search radius and the epipolar 3D gate grow with the user's
pose prior ``db.pose_prior_sigma_m`` as in ``build_database``. Culling may remove keyframes of
the original database too (a revisit makes them redundant); the builder's insertion numbers
tell which inputs survived.

Relocalise against the result with ``reloc.database=updated_<sequence>``.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch

from diffloc.database.builder import DatabaseBuilder
from diffloc.database.culling import redundancy
from diffloc.database.database import VisualDatabase
from diffloc.features.local import make_extractor
from diffloc.io.dataset import read_sequence
from diffloc.io.identity import identity
from diffloc.io.sequence import SequenceData
from diffloc.maps.surfel import SurfelMap
from diffloc.pipeline.config_record import config_record
from diffloc.pipeline.database_select import (
    BUILT,
    UPDATE_STAGE,
    SelectedDatabase,
    select_database,
    updated_dir,
)
from diffloc.pipeline.database_stage import (
    DatabaseConfig,
    db_overrides,
    keyframe_position_rmse,
    perturb_positions,
    read_surfel_map,
)
from diffloc.pipeline.hints import Command, StaleStageError
from diffloc.pipeline.stage import (
    LockLevel,
    StageSummary,
    open_stage,
    output_identity,
    stage_key,
)

__all__ = ["UpdateSummary", "UpdateTaskConfig", "update_database"]


@dataclass
class UpdateTaskConfig:
    """``task=update_db``: the database comes from the root ``db`` node.

    Attributes:
        sequence: the sequence whose frames are added (a user's new recording).
        noise_seed: seed of the position noise of the added poses when ``db.noise_sigma > 0``
            (its own, so the update's noise is not a replay of the database's draws).
    """

    name: str = "update_db"
    sequence: str = "query_lane"
    noise_seed: int = 1

    def __post_init__(self) -> None:
        if not self.sequence or "/" in self.sequence:
            raise ValueError(f"task.sequence must be a sequence name, got {self.sequence!r}")


@dataclass(frozen=True)
class UpdateSummary(StageSummary):
    """The ``update_db`` summary (``update_db.json``; module docstring).

    Attributes:
        config: ``{"db": database settings, "task": the stage's settings}``.
        base_database: path of the database that was updated.
        database: path of the updated database.
        sequence: the sequence whose frames were added.
        images: its frames.
        before, after_adding, after_culling: ``{"keyframes": int, "map_points": int}``
            before the update, after adding every image and point, after both culling rules.
        culled: what culling removed: ``keyframes`` (of them ``keyframes_of_base`` of the
            original database), ``points_unconfirmed``, ``points_of_culled_keyframes``.
        stats: the updated database's counts
            (:meth:`~diffloc.database.database.VisualDatabase.stats`).
        redundancy: quantiles ``median`` / ``p90`` / ``max`` of the keyframes' redundancy
            and the culling ``threshold`` (empty for an empty database).
        keyframe_sources: ``[sequence, frame]`` of every surviving keyframe.
        kf_pos_rmse_m: keyframe position RMSE against ground truth (scoring only).
        timings_ms: ``load`` / ``features`` / ``update`` / ``save`` wall times.
        features_ms_per_image, update_ms_per_image: per added image.
    """

    config: dict
    base_database: str
    database: str
    sequence: str
    images: int
    before: dict[str, int]
    after_adding: dict[str, int]
    after_culling: dict[str, int]
    culled: dict[str, int]
    stats: dict[str, float]
    redundancy: dict[str, float]
    keyframe_sources: list[list]
    kf_pos_rmse_m: float
    timings_ms: dict[str, float]
    features_ms_per_image: float
    update_ms_per_image: float


def _counts(keyframes: int, points: int) -> dict[str, int]:
    return {"keyframes": int(keyframes), "map_points": int(points)}


def _redundancy_summary(db: VisualDatabase, builder: DatabaseBuilder) -> dict[str, float]:
    """Quantiles of the keyframes' redundancy (fraction of their points seen by
    ``min_other_observers`` other keyframes) in the final database: how far from culling."""
    score = redundancy(db, builder.config.culling).float()
    if len(score) == 0:
        return {}
    quantiles = torch.quantile(score, torch.tensor([0.5, 0.9, 1.0]))
    return {
        "median": float(quantiles[0]),
        "p90": float(quantiles[1]),
        "max": float(quantiles[2]),
        "threshold": builder.config.culling.redundant_fraction,
    }


def update_database(
    dataset: str | Path,
    db_cfg: DatabaseConfig,
    cfg: UpdateTaskConfig,
    show_progress: bool = True,
    *,
    rebuild: bool = False,
) -> UpdateSummary:
    """Update the built database of ``dataset`` with the frames of ``cfg.sequence``.

    Args:
        dataset: the dataset folder (with ``map/surfel_map.ply`` and the ``build_db`` output).
        db_cfg: the database settings; the same as for ``task=build_db``.
        cfg: the stage settings.
        show_progress: show a progress bar.
        rebuild: update even if a complete result of the same config and inputs exists.

    Returns:
        The summary written to ``<database_dir>/updated_<sequence>/update_db.json`` (module
        docstring).

    Raises:
        MissingStageError: no built database or surfel map (the message names the command).
        FileNotFoundError: no such sequence.
        StaleStageError: the build record does not describe the saved database.
    """
    start = time.perf_counter()
    root = Path(dataset)
    base = select_database(root, db_cfg, BUILT)
    stage_dir = updated_dir(root, db_cfg, cfg.sequence)
    command = Command(UPDATE_STAGE, db_overrides(root, db_cfg), (f"task.sequence={cfg.sequence}",))
    sequence = read_sequence(root, cfg.sequence)
    with open_stage(stage_dir, UPDATE_STAGE, command, LockLevel.UPDATED) as stage:
        map_record, surfels = read_surfel_map(root)
        inputs = {
            "database": base.identity,
            "surfel_map": output_identity(map_record, "surfel_map.ply"),
            "sequence": identity(root / cfg.sequence),
        }
        key = stage_key({"db": config_record(db_cfg), "task": asdict(cfg)}, inputs)
        previous = stage.reusable(key, UpdateSummary)
        if previous is not None and not rebuild:
            return previous
        db = VisualDatabase.load(base.path)
        if db.num_keyframes != len(base.keyframe_sources):
            raise StaleStageError(
                f"{base.record} lists {len(base.keyframe_sources)} keyframes but {base.path} "
                f"has {db.num_keyframes}",
                Command("build_db", db_overrides(root, db_cfg)),
            )
        summary = _update(root, db_cfg, cfg, base, db, sequence, surfels, start, show_progress)
        saving = time.perf_counter()
        db.save(stage.workdir() / BUILT)
        timings = {**summary.timings_ms, "save": (time.perf_counter() - saving) * 1e3}
        return stage.commit(key, replace(summary, timings_ms=timings), [BUILT])


def _update(
    root: Path,
    db_cfg: DatabaseConfig,
    cfg: UpdateTaskConfig,
    base: SelectedDatabase,
    db: VisualDatabase,
    sequence: SequenceData,
    surfels: SurfelMap,
    start: float,
    show_progress: bool,
) -> UpdateSummary:
    """Add ``sequence`` to ``db`` in place; the summary (without the save time)."""
    truth = sequence.T_wc.clone()
    generator = torch.Generator().manual_seed(cfg.noise_seed)
    sequence.T_wc = perturb_positions(sequence.T_wc, db_cfg.noise_sigma, generator)
    builder = DatabaseBuilder(
        db_cfg.builder_config(), surfels, make_extractor(db_cfg.features), database=db
    )
    before = _counts(db.num_keyframes, db.num_points)
    loaded = time.perf_counter()
    builder.build(sequence, show_progress=show_progress)
    counts = builder.counts
    sources = list(base.keyframe_sources) + [(cfg.sequence, i) for i in range(len(sequence))]
    kept = [sources[i] for i in builder.keyframe_ids.tolist()]
    true_poses = {db_cfg.sequence: read_sequence(root, db_cfg.sequence).T_wc, cfg.sequence: truth}
    T_wc_true = torch.stack([true_poses[name][frame] for name, frame in kept])
    base_kept = int((builder.keyframe_ids < before["keyframes"]).sum())
    images = len(sequence)
    stage = updated_dir(root, db_cfg, cfg.sequence)
    return UpdateSummary(
        config={"db": config_record(db_cfg), "task": asdict(cfg)},
        base_database=str(base.path),
        database=str(stage / BUILT),
        sequence=cfg.sequence,
        images=images,
        before=before,
        after_adding=_counts(
            before["keyframes"] + counts.keyframes_added,
            before["map_points"] + counts.points_created,
        ),
        after_culling=_counts(db.num_keyframes, db.num_points),
        culled={
            "keyframes": counts.keyframes_culled,
            "keyframes_of_base": before["keyframes"] - base_kept,
            "points_unconfirmed": counts.points_unconfirmed,
            "points_of_culled_keyframes": counts.points_orphaned,
        },
        stats=db.stats(),
        redundancy=_redundancy_summary(db, builder),
        keyframe_sources=[[name, frame] for name, frame in kept],
        kf_pos_rmse_m=keyframe_position_rmse(db.T_wc, T_wc_true),
        timings_ms={
            "load": (loaded - start) * 1e3,
            "features": builder.timings_ms["features"],
            "update": builder.timings_ms["database"],
        },
        features_ms_per_image=builder.timings_ms["features"] / images,
        update_ms_per_image=builder.timings_ms["database"] / images,
    )
