"""``task=train_nerf`` killed (SIGKILL) while it trains: the next run resumes (or trains again)
and ends with the field of an uninterrupted training, byte for byte, under a record that
describes it; no temporary is left."""

from __future__ import annotations

import random
import shutil
from pathlib import Path

import pytest

from diffloc.io.lock import remove_temporaries
from diffloc.maps.nerf.export import load_field
from diffloc.pipeline.hints import Command
from diffloc.pipeline.stage import verified_record
from tests.conftest import copy_dataset
from tests.kill_runs import killed_run, stage_folder, stage_outputs, work_started

TRIALS = 2
STAGE = "train_nerf"


def test_a_killed_training_ends_with_the_uninterrupted_field(
    tiny_indoor_dataset: Path, tmp_path_factory: pytest.TempPathFactory
):
    reference = copy_dataset(tiny_indoor_dataset, tmp_path_factory, "nerf_reference")
    started = work_started(STAGE, reference)
    killed, seconds = killed_run(STAGE, reference, None, after_glob=started)
    assert not killed
    expected = stage_outputs(STAGE, reference)
    root = copy_dataset(tiny_indoor_dataset, tmp_path_factory, "nerf_killed")
    rng = random.Random(11)
    kills = 0
    for trial in range(TRIALS):
        shutil.rmtree(root / "nerf", ignore_errors=True)
        # the first kill as soon as training starts, the next anywhere in it
        delay = 0.0 if trial == 0 else rng.uniform(0.0, seconds)
        kills += killed_run(STAGE, root, delay, after_glob=started)[0]
        if (stage_folder(STAGE, root) / f"{STAGE}.json").is_file():  # finished before the kill
            verified_record(stage_folder(STAGE, root), STAGE, Command(STAGE))
        assert not killed_run(STAGE, root, None)[0]
        assert stage_outputs(STAGE, root) == expected, f"trial {trial}: another field"
        verified_record(stage_folder(STAGE, root), STAGE, Command(STAGE))
        load_field(stage_folder(STAGE, root) / "field")
        assert remove_temporaries(stage_folder(STAGE, root)) == []
    assert kills >= 1
