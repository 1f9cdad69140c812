"""Loads check values, not just shapes: finite fields, counts that agree, records that parse.

Issue 17, findings 3 (NaN in a loaded database), 4 (a retriever cache whose size does not match
the database), 6 (a PLY header that undercounts its vertices) and 8 (garbage in a stage
record gives a bare ``JSONDecodeError``).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from diffloc.database.database import VisualDatabase
from diffloc.io.ply import read_point_cloud, write_point_cloud
from diffloc.pipeline.database_stage import DatabaseConfig, database_dir
from diffloc.reloc.retrieval import BowRetriever, load_retriever
from tests.conftest import copy_dataset, run_task
from tests.test_database import make_database


@pytest.fixture(scope="module")
def built(tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of the tiny mapped dataset with its built database (no noise)."""
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "loads")
    run_task("build_db", root)
    return root


@pytest.mark.parametrize("field", ["T_wc", "point_positions", "descriptors"])
def test_a_database_with_nan_values_is_refused_naming_the_file_and_field(
    tmp_path: Path, field: str
):
    """Finding 3: NaN in ``T_wc`` used to load and halve the recall; in positions or
    descriptors it ended in a deep traceback naming no file."""
    db = make_database([[0, 1], [0, 1, 2], [2]])
    getattr(db, field).view(-1)[0] = math.nan
    db.save(tmp_path / "db")
    with pytest.raises(ValueError, match=rf"{re.escape(str(tmp_path / 'db'))}.*'{field}'.*NaN"):
        VisualDatabase.load(tmp_path / "db")


def test_a_retriever_cache_of_another_size_is_not_trusted(built: Path):
    """Finding 4: a cached retriever with the configured settings that ranks fewer keyframes
    than the database holds (written newer than the database, as a stale cache would be) used
    to be loaded and used."""
    settings = ("retriever=bow", "reloc.database=database", "reloc.sequences=[query_same]")
    run_task("relocalize", built, *settings, f"task.out_dir={built / 'reloc_a'}")
    folder = database_dir(built, DatabaseConfig())
    db = VisualDatabase.load(folder / "database")
    slices = [db.keyframe_slice(k) for k in range(db.num_keyframes - 1)]
    config = load_retriever(folder / "retriever_bow").config  # the settings of the cache
    fewer = BowRetriever.fit([db.descriptors[s] for s in slices], config)
    fewer.save(folder / "retriever_bow")
    assert load_retriever(folder / "retriever_bow").bow.num_images == db.num_keyframes - 1
    run_task("relocalize", built, *settings, f"task.out_dir={built / 'reloc_b'}")
    assert load_retriever(folder / "retriever_bow").bow.num_images == db.num_keyframes


def test_a_ply_header_that_undercounts_its_vertices_is_refused(tmp_path: Path):
    """Finding 6: an ASCII PLY whose header declares fewer vertices than its body holds was
    read without complaint, the surplus dropped."""
    path = tmp_path / "cloud.ply"
    write_point_cloud(path, np.arange(30, dtype=np.float32).reshape(10, 3), binary=False)
    path.write_text(path.read_text().replace("element vertex 10", "element vertex 7"))
    with pytest.raises(ValueError, match=r"cloud\.ply: the PLY header declares 7 rows.*10 lines"):
        read_point_cloud(path)


@pytest.mark.parametrize(
    ("record", "task", "names"),
    [
        ("map/build_map.json", "build_db", "build_map"),
        ("db/xfeat_sigma_0_prior_0/build_db.json", "optimize_db", "build_db"),
    ],
)
def test_garbage_in_a_stage_record_names_the_file_and_the_command(
    built: Path, tmp_path_factory: pytest.TempPathFactory, record: str, task: str, names: str
):
    """Finding 8: garbage in ``build_map.json`` / ``build_db.json`` gave a bare
    ``JSONDecodeError`` (or was not read at all), naming no file."""
    root = copy_dataset(built, tmp_path_factory, "garbage")
    (root / record).write_bytes(b"\x00{not json")
    with pytest.raises(ValueError, match=rf"{re.escape(str(root / record))}.*task={names}"):
        run_task(task, root)


def test_a_database_changed_after_its_build_is_not_read(built: Path, tmp_path_factory):
    """A database whose files no longer match its record (edited, half-written) is refused,
    with the command that makes it again."""
    root = copy_dataset(built, tmp_path_factory, "edited")
    folder = database_dir(root, DatabaseConfig())
    db = VisualDatabase.load(folder / "database")
    db.T_wc[0, 0, 3] += 0.5
    db.save(folder / "database")
    with pytest.raises(ValueError, match=r"database is not the file .*build_db\.json describes"):
        run_task("optimize_db", root)
