"""``task=export_colmap`` killed (SIGKILL) while it exports a changed database: the model folder
holds the previous complete export, the new complete one or nothing (never a mix), and the next
run removes the temporaries and ends byte-identical to an uninterrupted export."""

from __future__ import annotations

import json
import random
import shutil
from dataclasses import replace
from pathlib import Path

import pytest

from diffloc.io.lock import remove_temporaries
from diffloc.pipeline.database_stage import build_database
from tests.conftest import copy_dataset
from tests.kill_runs import (
    STAGE_CONFIGS,
    folder_files,
    killed_run,
    run_stage,
    stage_folder,
    stage_outputs,
    stage_record,
)

TRIALS = 3
STAGE = "export_colmap"
MODEL = ("cameras.txt", "images.txt", "points3D.txt")


def test_a_killed_export_leaves_a_complete_model_or_none_and_the_rerun_cleans_up(
    tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory
):
    reference = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "export_reference")
    run_stage("build_db", reference)
    assert not killed_run(STAGE, reference, None)[0]
    expected = stage_outputs(STAGE, reference)
    expected_record = json.loads(stage_record(STAGE, reference).read_text())
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "export_killed")
    other_seed = replace(STAGE_CONFIGS["build_db"], noise_seed=1)
    build_database(root, other_seed, show_progress=False)
    run_stage(STAGE, root)  # the previous export: another database in the same folder
    folder = stage_folder(STAGE, root)
    previous_folder = folder.parent / "colmap_previous"
    shutil.copytree(folder, previous_folder)
    previous = stage_outputs(STAGE, root)
    assert previous != expected
    run_stage("build_db", root)  # the database of the reference: the export is out of date
    rng = random.Random(3)
    leftovers_seen = 0
    for trial in range(TRIALS):
        shutil.rmtree(folder)
        shutil.copytree(previous_folder, folder)
        # killed once its work folder exists, at once or a little later, on any machine load
        delay = 0.0 if trial == 0 else rng.uniform(0.0, 0.05)
        killed_run(STAGE, root, delay, after_glob=f"{root.name}/db/*/colmap/.tmp-{STAGE}_*")
        model = folder / "database"
        files = {
            f"database/{p.name}": p.read_bytes() for p in sorted(model.glob("*")) if p.is_file()
        }
        assert not model.exists() or files in (previous, expected), f"trial {trial}: mixed"
        leftovers_seen += sum(p.name.startswith(".tmp-") for p in folder.iterdir())
        assert not killed_run(STAGE, root, None)[0]
        assert stage_outputs(STAGE, root) == expected, f"trial {trial}: outputs differ"
        assert json.loads(stage_record(STAGE, root).read_text()) == expected_record
        assert remove_temporaries(folder) == []
    assert leftovers_seen > 0  # a kill landed while the export was being written
    names = {f"database/{name}" for name in MODEL} | {stage_record(STAGE, root).name}
    assert folder_files(folder).keys() == names
