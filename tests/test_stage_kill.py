"""Stages killed at random points and run again end byte-identical to an uninterrupted run.

Each trial removes the stage's record (so the run has to make its outputs again), runs the
stage in a forked child, SIGKILLs it after a random delay drawn uniformly over the length of an
uninterrupted run (seeded, so the trials repeat), runs it again to the end and compares every
output file the record lists, byte for byte, and the record's manifest with those of an
uninterrupted run on another copy of the dataset; no temporary file may be left.

N = 8 trials here (2 of ``build_map`` with a coloured point map, 6 of ``build_db`` with noisy
poses; about 50 s on 2 busy cores); ``experiments/fault_cases.py --kills N`` runs more.
"""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

from diffloc.io.lock import remove_temporaries
from tests.conftest import copy_dataset
from tests.kill_runs import killed_run, stage_folder, stage_outputs, stage_record

TRIALS = {"build_map": 2, "build_db": 6}


def _manifest(stage: str, root: Path) -> dict:
    return json.loads(stage_record(stage, root).read_text())["stage"]


@pytest.mark.parametrize("stage", list(TRIALS))
def test_killed_runs_end_byte_identical_to_an_uninterrupted_run(
    tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory, stage: str
):
    reference = copy_dataset(tiny_indoor_mapped, tmp_path_factory, f"{stage}_reference")
    killed, work_s = killed_run(stage, reference, None)
    assert not killed
    expected, expected_manifest = stage_outputs(stage, reference), _manifest(stage, reference)
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, f"{stage}_killed")
    rng = random.Random(17)
    kills = 0
    for _ in range(TRIALS[stage]):
        stage_record(stage, root).unlink(missing_ok=True)
        kills += killed_run(stage, root, rng.uniform(0.0, 1.1 * work_s))[0]
        assert not killed_run(stage, root, None)[0]
        assert stage_outputs(stage, root) == expected
        assert _manifest(stage, root) == expected_manifest
        assert remove_temporaries(stage_folder(stage, root)) == []
    assert kills >= 1  # at least one trial was killed before it finished
