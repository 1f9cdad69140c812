"""Which saved visual database a stage reads: as built, optimised, or updated with a sequence.

The database stages write into :func:`~diffloc.pipeline.database_stage.database_dir`:

- ``database/`` (``task=build_db``) and ``optimized/`` (``task=optimize_db``), whose keyframes
  are frames of the database sequence listed in ``build_db.json``;
- ``updated_<sequence>/`` (``task=update_db``): a stage folder with the updated database in
  ``database/`` and ``update_db.json``, whose ``keyframe_sources`` name the sequence and frame
  of every keyframe (the database's own and the added sequence's).

:func:`select_database` resolves a name (the ``reloc.database`` setting) to the database
folder, the verified record that identifies it (:mod:`diffloc.pipeline.stage`: its outputs
still match, and an optimised or updated database derives from the current build), where
retrievers of it are cached and the images of its keyframes.

Usage (on a dataset with an updated database)::

    selected = select_database("data/indoor_seed0", DatabaseConfig(), "updated_query_lane")
    VisualDatabase.load(selected.path).num_keyframes == len(selected.keyframe_sources)  # True
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from diffloc.io.dataset import read_sequence
from diffloc.pipeline.database_stage import (
    BUILD_STAGE,
    OPTIMIZE_STAGE,
    DatabaseConfig,
    database_dir,
    db_overrides,
    read_built_record,
)
from diffloc.pipeline.hints import Command, MissingStageError
from diffloc.pipeline.stage import (
    LockLevel,
    check_made_from,
    output_identity,
    read_lock,
    verified_record,
)

__all__ = [
    "BUILT",
    "OPTIMIZED",
    "UPDATED_PREFIX",
    "UPDATE_RECORD",
    "UPDATE_STAGE",
    "SelectedDatabase",
    "check_database_name",
    "keyframe_image_reader",
    "keyframe_images",
    "keyframe_true_poses",
    "select_database",
    "updated_dir",
]

BUILT = "database"
"""The database as built by ``task=build_db``."""
OPTIMIZED = "optimized"
"""The database after ``task=optimize_db``."""
UPDATED_PREFIX = "updated_"
"""``updated_<sequence>``: the built database updated with ``<sequence>`` (``task=update_db``)."""
UPDATE_STAGE = "update_db"
"""The update stage's name."""
UPDATE_RECORD = f"{UPDATE_STAGE}.json"
"""The record of ``task=update_db`` inside its stage folder."""


def check_database_name(which: str) -> str:
    """Validate a database name: ``"database"``, ``"optimized"`` or ``"updated_<sequence>"``.

    Args:
        which: the name.

    Returns:
        ``which``.

    Raises:
        ValueError: any other name (an empty sequence, a path separator).
    """
    sequence = which.removeprefix(UPDATED_PREFIX) if isinstance(which, str) else ""
    named = isinstance(which, str) and which.startswith(UPDATED_PREFIX)
    if which in (BUILT, OPTIMIZED) or (named and sequence and "/" not in sequence):
        return which
    raise ValueError(
        f"database must be {BUILT!r}, {OPTIMIZED!r} or '{UPDATED_PREFIX}<sequence>' "
        f"(after `diffloc task=update_db task.sequence=<sequence>`), got {which!r}"
    )


def updated_dir(dataset: str | Path, db_cfg: DatabaseConfig, sequence: str) -> Path:
    """``<database_dir>/updated_<sequence>``: the stage folder of ``task=update_db``."""
    return database_dir(dataset, db_cfg) / f"{UPDATED_PREFIX}{sequence}"


@dataclass
class SelectedDatabase:
    """A saved database and what identifies it.

    Attributes:
        name: the name it was selected by (:func:`check_database_name`).
        path: the database folder (:meth:`VisualDatabase.load` reads it).
        record: the stage record written with it (verified).
        retriever_root: the folder its retriever caches live in.
        keyframe_sources: ``(sequence, frame)`` of every keyframe, in keyframe order.
        identity: the recorded identity of the database folder; caches derived from the
            database are keyed on it.
    """

    name: str
    path: Path
    record: Path
    retriever_root: Path
    keyframe_sources: list[tuple[str, int]]
    identity: dict


def select_database(dataset: str | Path, db_cfg: DatabaseConfig, which: str) -> SelectedDatabase:
    """Resolve a database name of a dataset to its saved folder (module docstring).

    Args:
        dataset: the dataset folder.
        db_cfg: the database settings (noise level, local features, association).
        which: ``"database"``, ``"optimized"`` or ``"updated_<sequence>"``.

    Returns:
        The selected database.

    Raises:
        ValueError: an unknown name, or an update record without valid keyframe sources.
        MissingStageError: the database was not made; the message names the command to run.
        StaleStageError: a record that does not describe its files, or an optimised or
            updated database made from another build than the current one (``build_db`` ran
            again since); the message names the command that makes it again.
    """
    check_database_name(which)
    folder = database_dir(dataset, db_cfg)
    where = db_overrides(dataset, db_cfg)
    build = Command(BUILD_STAGE, where)
    if not (folder / f"{BUILD_STAGE}.json").is_file():
        raise MissingStageError(folder / f"{BUILD_STAGE}.json", build)
    if which.startswith(UPDATED_PREFIX):
        # Not under the database folder's lock: an updated database is locked alone (the lock
        # order takes upstream folders inside downstream ones, never the reverse).
        with read_lock(folder, LockLevel.DATABASE):
            built = read_built_record(dataset, db_cfg)
        return _select_updated(dataset, db_cfg, which, built)
    with read_lock(folder, LockLevel.DATABASE):
        built = read_built_record(dataset, db_cfg)
        sources = _sources(
            [[db_cfg.sequence, frame] for frame in built.get("keyframe_frames", ())],
            folder / f"{BUILD_STAGE}.json",
        )
        if which == BUILT:
            return SelectedDatabase(
                which,
                folder / BUILT,
                folder / f"{BUILD_STAGE}.json",
                folder,
                sources,
                output_identity(built, BUILT),
            )
        command = Command(OPTIMIZE_STAGE, where)
        if not (folder / f"{OPTIMIZE_STAGE}.json").is_file():
            raise MissingStageError(folder / which, command)
        record = verified_record(folder, OPTIMIZE_STAGE, command)
        path = folder / f"{OPTIMIZE_STAGE}.json"
        check_made_from(record, path, "database", built, BUILT, command)
        return SelectedDatabase(
            which, folder / which, path, folder, sources, output_identity(record, which)
        )


def _select_updated(
    dataset: str | Path, db_cfg: DatabaseConfig, which: str, built: dict
) -> SelectedDatabase:
    """The verified ``updated_<sequence>`` database, checked to derive from ``built``."""
    sequence = which.removeprefix(UPDATED_PREFIX)
    stage = updated_dir(dataset, db_cfg, sequence)
    command = Command("update_db", db_overrides(dataset, db_cfg), (f"task.sequence={sequence}",))
    path = stage / UPDATE_RECORD
    if not (path.is_file() and (stage / BUILT).is_dir()):
        raise MissingStageError(stage, command)
    with read_lock(stage, LockLevel.UPDATED):
        record = verified_record(stage, UPDATE_STAGE, command)
    check_made_from(record, path, "database", built, BUILT, command)
    sources = _sources(record.get("keyframe_sources"), path)
    return SelectedDatabase(
        which, stage / BUILT, path, stage, sources, output_identity(record, BUILT)
    )


def _sources(sources: object, record: Path) -> list[tuple[str, int]]:
    """``(sequence, frame)`` per keyframe from a record's list, validated."""
    try:
        parsed = [(str(name), int(frame)) for name, frame in sources]
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{record}: no valid keyframe list ({exc}); run the stage again") from exc
    if any(frame < 0 for _, frame in parsed):
        raise ValueError(f"{record}: negative frame index in its keyframe list")
    return parsed


def keyframe_image_reader(
    dataset: str | Path, sources: Sequence[tuple[str, int]]
) -> Callable[[int], torch.Tensor]:
    """A reader of keyframe ``k``'s image, for keyframes given by ``(sequence, frame)``.

    Args:
        dataset: the dataset folder.
        sources: ``(sequence, frame)`` per keyframe.

    Returns:
        ``read(k)``: the (3, H, W) float32 image in [0, 1] of keyframe ``k`` (each sequence's
        folder is read once, at its first image).
    """
    sequences: dict = {}

    def read(k: int) -> torch.Tensor:
        name, frame = sources[k]
        if name not in sequences:
            sequences[name] = read_sequence(dataset, name)
        return sequences[name].load_rgb(frame)

    return read


def keyframe_images(
    dataset: str | Path, sources: Sequence[tuple[str, int]]
) -> Iterator[torch.Tensor]:
    """The images of keyframes given by ``(sequence, frame)``, in order, read lazily.

    Args:
        dataset: the dataset folder.
        sources: ``(sequence, frame)`` per keyframe.

    Yields:
        (3, H, W) float32 images in [0, 1].
    """
    read = keyframe_image_reader(dataset, sources)
    for k in range(len(sources)):
        yield read(k)


def keyframe_true_poses(dataset: str | Path, sources: Sequence[tuple[str, int]]) -> torch.Tensor:
    """(K, 4, 4) float64 poses on disk of the keyframes given by ``(sequence, frame)``.

    For a simulated dataset these are the true poses: read for scoring only (how far the
    queries lie from the database), never by the relocaliser.
    """
    sequences = {
        name: read_sequence(dataset, name) for name in dict.fromkeys(n for n, _ in sources)
    }
    return torch.stack([sequences[name].T_wc[frame].double() for name, frame in sources])
