"""The COLMAP export stage: a saved visual database as a COLMAP TEXT model.

``export_colmap`` picks a database of the dataset like relocalisation does (``task.database``:
``database``, ``optimized`` or ``updated_<sequence>``, in the folder the root ``db`` settings
select) and writes it with :func:`~diffloc.database.colmap.write_colmap_text`:

- image names are the keyframes' image files relative to the dataset folder (e.g.
  ``mapping/rgb/000012.png``), so ``image_dir=<dataset>`` works for hloc and COLMAP;
- map point colours are those of their anchor surfels when ``<dataset>/map/surfel_map.ply``
  has colours, else grey (also when there is no surfel map).

It is a stage (:mod:`diffloc.pipeline.stage`) writing into the model folder's parent: the
model folder ``<name>`` (default ``<database_dir>/colmap/<database>``) is its one output and
``export_colmap_<name>.json`` beside it its record, keyed on ``task.database`` and the
identities of the database folder, the image names and the surfel map. The model is written
into a hidden work folder and renamed into place with the record, so a failed or killed export
leaves the previous complete model (or none); a rerun with nothing changed reuses it, and a
database built, optimised or updated again since is exported again. A non-empty folder that
holds no export of this stage is replaced only with ``task.overwrite=true`` (which also
exports again when the model is up to date).

What it reads is checked first, each error naming the file and field: the database through its
verified record (:func:`~diffloc.pipeline.database_select.select_database`; loading it refuses
non-finite values), the surfel map through its verified ``build_map`` record (a map changed
since is refused), made before the database (the database's record names the surfel map it was
built on; a map built again since is refused), every anchor id (``point_surfels``) in
``[-1, surfels)``, every keyframe's frame in its sequence.

Usage (on a dataset whose database is built; ``diffloc task=export_colmap`` does this)::

    export_colmap("data/indoor_seed0", DatabaseConfig(), ExportColmapTaskConfig())
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diffloc.database.colmap import write_colmap_text
from diffloc.database.database import VisualDatabase
from diffloc.io.dataset import read_sequence
from diffloc.io.json_record import read_json_record
from diffloc.maps.surfel import SurfelMap
from diffloc.pipeline.database_select import (
    BUILT,
    SelectedDatabase,
    check_database_name,
    select_database,
)
from diffloc.pipeline.database_stage import (
    DatabaseConfig,
    database_dir,
    db_overrides,
    read_surfel_map,
)
from diffloc.pipeline.hints import Command, ExistingOutputError, StaleStageError
from diffloc.pipeline.stage import StageRun, StageSummary, open_stage, output_identity, stage_key

__all__ = ["STAGE", "ColmapExport", "ColmapSummary", "ExportColmapTaskConfig", "export_colmap"]

STAGE = "export_colmap"
"""The stage's name; the record of model folder ``<name>`` is ``export_colmap_<name>.json``."""
SURFEL_MAP = "surfel_map.ply"


@dataclass(frozen=True)
class ColmapSummary(StageSummary):
    """The ``export_colmap`` record's summary (``export_colmap_<name>.json``).

    Attributes:
        images: keyframes written as images.
        points: observed map points written (points no keyframe observes are left out).
        observations: 2D-3D observations written (track elements).
        colors: where the point colours came from (``anchor surfels of map/surfel_map.ply``
            or why they are grey).
    """

    images: int
    points: int
    observations: int
    colors: str


@dataclass(frozen=True)
class ColmapExport:
    """What :func:`export_colmap` returns: the record's summary and this run's paths.

    Attributes:
        model: the model folder.
        database: the database folder exported.
        summary: the counts and colour source (:class:`ColmapSummary`).
        reused: the model was up to date and reused, not written again.
    """

    model: str
    database: str
    summary: ColmapSummary
    reused: bool


@dataclass
class ExportColmapTaskConfig:
    """``task=export_colmap``: the database folder comes from the root ``db`` node.

    Attributes:
        database: which database: ``database`` (as built), ``optimized`` or
            ``updated_<sequence>``.
        out_dir: the COLMAP model folder; empty: ``<database_dir>/colmap/<database>``.
        overwrite: replace a non-empty ``out_dir`` that holds no export of this stage, and
            export again even when the export is up to date.
    """

    name: str = "export_colmap"
    database: str = BUILT
    out_dir: str = ""
    overwrite: bool = False

    def __post_init__(self) -> None:
        check_database_name(self.database)


def _surfel_map(dataset: Path) -> tuple[dict, SurfelMap] | None:
    """The verified ``build_map`` record and surfel map of ``dataset``, or ``None`` without
    one (the points are then grey)."""
    if not (dataset / "map" / SURFEL_MAP).is_file():
        return None
    return read_surfel_map(dataset)


def _point_colors(
    dataset: Path,
    db: VisualDatabase,
    selected: SelectedDatabase,
    surfel_map: tuple[dict, SurfelMap] | None,
    rebuild: Command,
) -> tuple[np.ndarray | None, str]:
    """(P, 3) uint8 colours of the anchor surfels, or ``None``; and where they came from.

    ``surfel_map`` is :func:`_surfel_map`'s; ``rebuild`` the command that builds the database
    again (for messages).

    Raises:
        StaleStageError: the surfel map is not the one the database's record names.
        ValueError: an anchor id outside the surfel map (the message names the field).
    """
    if surfel_map is None:
        return None, "grey (no surfel map)"
    map_record, surfels = surfel_map
    path = dataset / "map" / SURFEL_MAP
    used = read_json_record(selected.record)["stage"]["key"]["inputs"].get("surfel_map")
    if used != output_identity(map_record, SURFEL_MAP):
        raise StaleStageError(
            f"{selected.path} (record {selected.record}) was built on another surfel map than "
            f"{path} (the map was built again since): build the database again",
            rebuild,
        )
    anchors = db.point_surfels
    count = surfels.centers.shape[0]
    if bool(((anchors < -1) | (anchors >= count)).any()):
        raise ValueError(
            f"{selected.path / 'arrays.npz'}: field 'point_surfels' holds surfel ids outside "
            f"[-1, {count}) of {path}; the database is corrupt: build it again"
        )
    if surfels.colors is None:
        return None, "grey (the surfel map has no colours)"
    colors = np.full((db.num_points, 3), 128, dtype=np.uint8)
    has = (anchors >= 0).numpy()
    rgb = surfels.colors[anchors[anchors >= 0]].double().numpy()
    colors[has] = np.rint(rgb * 255.0).astype(np.uint8)
    return colors, f"anchor surfels of map/{SURFEL_MAP}"


def _image_names(dataset: Path, selected: SelectedDatabase) -> list[str]:
    """The keyframes' image files relative to ``dataset``, in keyframe order.

    Raises:
        ValueError: a keyframe's frame is not in its sequence (the message names the record).
    """
    sequences = {name: read_sequence(dataset, name) for name, _ in selected.keyframe_sources}
    names = []
    for name, frame in selected.keyframe_sources:
        paths = sequences[name].rgb_paths
        if frame >= len(paths):
            raise ValueError(
                f"{selected.record}: keyframe frame {frame} of sequence {name!r} is beyond its "
                f"{len(paths)} images (the sequence changed since): build the database again"
            )
        names.append(paths[frame].resolve().relative_to(dataset.resolve()).as_posix())
    return names


def _names_identity(names: list[str]) -> dict:
    """The identity of the image names written (they derive from the database's record and
    the sequences' file lists): their count and the SHA-256 of the lines."""
    digest = hashlib.sha256("".join(f"{name}\n" for name in names).encode("utf-8"))
    return {"kind": "names", "count": len(names), "sha256": digest.hexdigest()}


def export_colmap(
    dataset: str | Path, db_cfg: DatabaseConfig, task: ExportColmapTaskConfig
) -> ColmapExport:
    """Write a saved database of ``dataset`` as a COLMAP TEXT model (module docstring).

    Args:
        dataset: the dataset folder.
        db_cfg: the database settings (which database folder: :func:`database_dir`).
        task: which database, where to write, whether to overwrite.

    Returns:
        The model and database paths of this run, the record's :class:`ColmapSummary` and
        whether the model was reused.

    Raises:
        MissingStageError: the database was not made; the message names the command to run.
        StaleStageError: the surfel map changed since its record, or since the database was
            built (the message names the files and the command).
        ValueError: anchor ids outside the surfel map, keyframe frames outside their sequence
            (the message names the file and field).
        ExistingOutputError: ``out_dir`` is a file, or a non-empty folder that holds no export
            of this stage while ``task.overwrite`` is false; the message names the command with
            ``task.overwrite=true``.
    """
    dataset = Path(dataset)
    default = database_dir(dataset, db_cfg) / "colmap" / task.database
    out = Path(os.path.abspath(task.out_dir)) if task.out_dir else default
    chosen = [f"task.database={task.database}"]
    chosen += [f"task.out_dir={task.out_dir}"] if task.out_dir else []
    command = Command(STAGE, (*db_overrides(dataset, db_cfg), *chosen))
    with open_stage(out.parent, f"{STAGE}_{out.name}", command) as stage:
        selected = select_database(dataset, db_cfg, task.database)
        names = _image_names(dataset, selected)
        surfel_map = _surfel_map(dataset)
        inputs = {"database": selected.identity, "image_names": _names_identity(names)}
        if surfel_map is not None:
            inputs["surfel_map"] = output_identity(surfel_map[0], SURFEL_MAP)
        key = stage_key({"database": task.database}, inputs)
        paths = {"model": str(out), "database": str(selected.path)}
        previous = None if task.overwrite else stage.reusable(key, ColmapSummary)
        if previous is not None:
            return ColmapExport(**paths, summary=previous, reused=True)
        _check_out_dir(out, stage, task.overwrite)
        work = stage.workdir() / out.name
        db = VisualDatabase.load(selected.path)
        rebuild = Command("build_db", db_overrides(dataset, db_cfg))
        colors, color_source = _point_colors(dataset, db, selected, surfel_map, rebuild)
        write_colmap_text(db, work, names, colors)
        summary = ColmapSummary(
            images=db.num_keyframes,
            points=int((db.observation_counts() > 0).sum()),
            observations=int(db.stats()["observations"]),
            colors=color_source,
        )
        summary = stage.commit(key, summary, [out.name])
        return ColmapExport(**paths, summary=summary, reused=False)


def _check_out_dir(out: Path, stage: StageRun, overwrite: bool) -> None:
    """Refuse to replace what is not an export of this stage unless ``overwrite``.

    Raises:
        ExistingOutputError: ``out`` is a file, or a non-empty folder without this stage's
            record beside it; the message names the command with ``task.overwrite=true``.
    """
    replace = Command(STAGE, stage.command.selection, ("task.overwrite=true",))
    if out.exists() and not out.is_dir():
        raise ExistingOutputError(f"{out} exists and is not a folder", replace)
    ours = stage.record_path.is_file()
    if not (ours or overwrite) and out.is_dir() and any(out.iterdir()):
        raise ExistingOutputError(
            f"{out} exists, is not empty and holds no export of `diffloc task=export_colmap` "
            f"(no {stage.record_path})",
            replace,
        )
