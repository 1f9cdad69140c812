"""The COLMAP export stage: a saved visual database as a COLMAP TEXT model.

``export_colmap`` picks a database of the dataset like relocalisation does (``task.database``:
``database``, ``optimized`` or ``updated_<sequence>``, in the folder the root ``db`` settings
select) and writes it with :func:`~diffloc.database.colmap.write_colmap_text`:

- image names are the keyframes' image files relative to the dataset folder (e.g.
  ``mapping/rgb/000012.png``), so ``image_dir=<dataset>`` works for hloc and COLMAP;
- map point colours are those of their anchor surfels when ``<dataset>/map/surfel_map.ply``
  has colours, else grey (also when there is no surfel map).

What it reads is checked first, each error naming the file and field: the surfel map through
its verified ``build_map`` record (a map changed since is refused), made before the database
(the database's record names the surfel map it was built on; a map built again since is
refused), every anchor id (``point_surfels``) in ``[-1, surfels)``, every keyframe's frame
in its sequence.

Usage (on a dataset whose database is built; ``diffloc task=export_colmap`` does this)::

    export_colmap("data/indoor_seed0", DatabaseConfig(), ExportColmapTaskConfig())
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diffloc.database.colmap import write_colmap_text
from diffloc.database.database import VisualDatabase
from diffloc.io.dataset import read_sequence
from diffloc.io.json_record import read_json_record
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
from diffloc.pipeline.stage import output_identity

__all__ = ["ExportColmapTaskConfig", "export_colmap"]


@dataclass
class ExportColmapTaskConfig:
    """``task=export_colmap``: the database folder comes from the root ``db`` node.

    Attributes:
        database: which database: ``database`` (as built), ``optimized`` or
            ``updated_<sequence>``.
        out_dir: the COLMAP model folder; empty: ``<database_dir>/colmap/<database>``.
        overwrite: replace a non-empty ``out_dir`` as a whole.
    """

    name: str = "export_colmap"
    database: str = BUILT
    out_dir: str = ""
    overwrite: bool = False

    def __post_init__(self) -> None:
        check_database_name(self.database)


def _point_colors(
    dataset: Path, db: VisualDatabase, selected: SelectedDatabase, rebuild: Command
) -> tuple[np.ndarray | None, str]:
    """(P, 3) uint8 colours of the anchor surfels, or ``None``; and where they came from.

    ``rebuild`` is the command that builds the database again (for messages).

    Raises:
        StaleStageError: the surfel map is not the one its record or the database's names.
        ValueError: an anchor id outside the surfel map (the message names the field).
    """
    path = dataset / "map" / "surfel_map.ply"
    if not path.is_file():
        return None, "grey (no surfel map)"
    map_record, surfels = read_surfel_map(dataset)
    used = read_json_record(selected.record)["stage"]["key"]["inputs"].get("surfel_map")
    if used != output_identity(map_record, "surfel_map.ply"):
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
    return colors, f"anchor surfels of {path}"


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


def export_colmap(
    dataset: str | Path, db_cfg: DatabaseConfig, task: ExportColmapTaskConfig
) -> dict:
    """Write a saved database of ``dataset`` as a COLMAP TEXT model (module docstring).

    Args:
        dataset: the dataset folder.
        db_cfg: the database settings (which database folder: :func:`database_dir`).
        task: which database, where to write, whether to overwrite.

    Returns:
        A summary: ``model`` (the folder), ``database``, ``images``, ``points`` (observed map
        points written), ``observations`` and ``colors`` (their source).

    Raises:
        MissingStageError: the database was not made; the message names the command to run.
        StaleStageError: the surfel map changed since its record, or since the database was
            built (the message names the files and the command).
        ValueError: anchor ids outside the surfel map, keyframe frames outside their sequence
            (the message names the file and field).
        ExistingOutputError: ``out_dir`` is not empty and ``task.overwrite`` is false; the
            message names the command with ``task.overwrite=true``.
    """
    dataset = Path(dataset)
    selected = select_database(dataset, db_cfg, task.database)
    db = VisualDatabase.load(selected.path)
    names = _image_names(dataset, selected)
    rebuild = Command("build_db", db_overrides(dataset, db_cfg))
    colors, color_source = _point_colors(dataset, db, selected, rebuild)
    default = database_dir(dataset, db_cfg) / "colmap" / task.database
    out = Path(task.out_dir) if task.out_dir else default
    try:
        write_colmap_text(db, out, names, colors, overwrite=task.overwrite)
    except FileExistsError as exc:
        chosen = [f"task.database={task.database}"]
        chosen += [f"task.out_dir={task.out_dir}"] if task.out_dir else []
        command = Command(
            "export_colmap", (*db_overrides(dataset, db_cfg), *chosen), ("task.overwrite=true",)
        )
        raise ExistingOutputError(str(exc), command) from exc
    observed = int((db.observation_counts() > 0).sum())
    return {
        "model": str(out),
        "database": str(selected.path),
        "images": db.num_keyframes,
        "points": observed,
        "observations": int(db.stats()["observations"]),
        "colors": color_source,
    }
