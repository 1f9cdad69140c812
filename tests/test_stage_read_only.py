"""Stages on a dataset folder the run cannot write (issue 17, read-only mounts).

Root ignores permission bits, so the folder is made read-only by :func:`tests.read_only.
read_only` (every create, replace or delete under it fails with ``EROFS``), and the tests
compare the folder's snapshot (every file, hidden ones included, with size and mtime) too.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from diffloc.io.lock import LOCK_NAME, ReadOnlyFolderError, runtime_lock_path
from diffloc.pipeline.build_map import BuildMapConfig, MapSummary, build_maps
from diffloc.pipeline.database_stage import DatabaseConfig, build_database, database_dir
from diffloc.pipeline.database_summary import BuiltDatabase
from diffloc.pipeline.hints import Command
from diffloc.pipeline.stage import verified_record
from tests.conftest import FINE_SURFELS, copy_dataset
from tests.read_only import read_only, snapshot

MAP_CFG = BuildMapConfig(point_maps=[], preview_frames=1)


@pytest.fixture(scope="module")
def built(tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of the tiny mapped dataset with its database built."""
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "read_only")
    build_database(root, DatabaseConfig(), show_progress=False)
    return root


def test_the_read_only_check_refuses_writes(built: Path):
    with read_only(built), pytest.raises(OSError, match="Read-only"):
        (built / "map" / "new").mkdir()


def test_complete_results_are_reused_without_writing(built: Path):
    db_folder = database_dir(built, DatabaseConfig())
    expected_map = MapSummary.from_record(
        verified_record(built / "map", "build_map", Command("build_map"))
    )
    expected_db = BuiltDatabase.from_record(
        verified_record(db_folder, "build_db", Command("build_db"))
    )
    before = snapshot(built)
    with read_only(built):
        assert build_maps(built, MAP_CFG, FINE_SURFELS, show_progress=False) == expected_map
        assert build_database(built, DatabaseConfig(), show_progress=False) == expected_db
    assert snapshot(built) == before


def test_a_folder_without_lock_files_is_read_under_a_per_user_lock(
    built: Path, tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch
):
    """A read-only copy made without the hidden lock files: the reader's lock is a per-user
    file keyed by the folder, outside it."""
    root = copy_dataset(built, tmp_path_factory, "no_locks")
    for path in root.rglob(LOCK_NAME):
        path.unlink()
    runtime = tmp_path_factory.mktemp("runtime")
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))
    expected = BuiltDatabase.from_record(
        verified_record(database_dir(root, DatabaseConfig()), "build_db", Command("x"))
    )
    with read_only(root):
        assert build_database(root, DatabaseConfig(), show_progress=False) == expected
    assert runtime_lock_path(root / "map").parent == runtime / f"diffloc-locks-{os.getuid()}"
    assert runtime_lock_path(root / "map").is_file()
    assert not list(root.rglob(LOCK_NAME))


def test_a_stage_that_must_build_fails_naming_the_folder(built: Path):
    before = snapshot(built)
    coarse = FINE_SURFELS.__class__(voxel_size_m=0.05, mean_radius_m=0.05, normal_radius_m=0.15)
    with read_only(built):
        with pytest.raises(ReadOnlyFolderError) as error:
            build_maps(built, MAP_CFG, coarse, show_progress=False)
        assert f"{built / 'map'} cannot be written" in str(error.value)
        assert "task=build_map" in str(error.value) and "copy the dataset" in str(error.value)
        noisy = DatabaseConfig(noise_sigma=0.05)  # its folder does not exist and cannot be made
        with pytest.raises(ReadOnlyFolderError, match="copy the dataset to a folder you can"):
            build_database(built, noisy, show_progress=False)
    assert snapshot(built) == before
