"""The COLMAP export stage: a saved visual database as a COLMAP TEXT model.

``export_colmap`` picks a database of the dataset like relocalisation does (``task.database``:
``database``, ``optimized`` or ``updated_<sequence>``, in the folder the root ``db`` settings
select) and writes it with :func:`~diffloc.database.colmap.write_colmap_text`:

- image names are the keyframes' image files relative to the dataset folder (e.g.
  ``mapping/rgb/000012.png``), so ``image_dir=<dataset>`` works for hloc and COLMAP;
- map point colours are those of their anchor surfels when ``<dataset>/map/surfel_map.ply``
  has colours and holds every anchor id, else grey.

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
from diffloc.maps.surfel import SurfelMap
from diffloc.pipeline.database_select import BUILT, check_database_name, select_database
from diffloc.pipeline.database_stage import DatabaseConfig, database_dir, db_overrides
from diffloc.pipeline.hints import Command, ExistingOutputError

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


def _point_colors(dataset: Path, db: VisualDatabase) -> tuple[np.ndarray | None, str]:
    """(P, 3) uint8 colours of the anchor surfels, or ``None``; and where they came from."""
    path = dataset / "map" / "surfel_map.ply"
    if not path.is_file():
        return None, "grey (no surfel map)"
    surfels = SurfelMap.load(path)
    anchors = db.point_surfels
    if surfels.colors is None:
        return None, "grey (the surfel map has no colours)"
    if bool((anchors >= surfels.centers.shape[0]).any()):
        return None, "grey (the database's anchor surfels are not in the surfel map)"
    colors = np.full((db.num_points, 3), 128, dtype=np.uint8)
    has = (anchors >= 0).numpy()
    rgb = surfels.colors[anchors[anchors >= 0]].double().numpy()
    colors[has] = np.rint(rgb * 255.0).astype(np.uint8)
    return colors, f"anchor surfels of {path}"


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
        ExistingOutputError: ``out_dir`` is not empty and ``task.overwrite`` is false; the
            message names the command with ``task.overwrite=true``.
    """
    dataset = Path(dataset)
    selected = select_database(dataset, db_cfg, task.database)
    db = VisualDatabase.load(selected.path)
    sequences = {name: read_sequence(dataset, name) for name, _ in selected.keyframe_sources}
    names = [
        sequences[name].rgb_paths[frame].resolve().relative_to(dataset.resolve()).as_posix()
        for name, frame in selected.keyframe_sources
    ]
    colors, color_source = _point_colors(dataset, db)
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
