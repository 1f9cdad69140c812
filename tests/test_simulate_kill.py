"""``task=simulate`` killed at random points (SIGKILL): it never leaves a folder that looks
like a dataset, and the next run removes its temporaries and ends byte-identical to an
uninterrupted run."""

from __future__ import annotations

import random
from pathlib import Path

from tests.kill_runs import folder_files, killed_run

TRIALS = 3


def test_a_killed_simulate_leaves_no_dataset_and_the_next_run_cleans_up(
    tiny_indoor_dataset: Path, tmp_path: Path
):
    expected = folder_files(tiny_indoor_dataset)
    _, seconds = killed_run("simulate", tmp_path / "timed" / "indoor_seed0", None)
    rng = random.Random(2)
    leftovers_seen = 0
    for trial in range(TRIALS):
        root = tmp_path / f"trial{trial}" / "indoor_seed0"
        if trial == 0:  # while the dataset is being written into its temporary folder
            killed_run("simulate", root, 0.0, after_glob=".indoor_seed0.tmp-*")
        else:  # anywhere in the run, scene building included
            killed_run("simulate", root, rng.uniform(0.2, 0.9) * seconds)
        assert not root.exists() or folder_files(root) == expected, f"trial {trial}: partial"
        leftovers_seen += sum(
            p.name.startswith(".indoor_seed0.tmp-") for p in root.parent.iterdir()
        )
        killed_run("simulate", root, None)
        assert folder_files(root) == expected, f"trial {trial}: outputs differ"
        assert sorted(p.name for p in root.parent.iterdir()) == [
            ".indoor_seed0.diffloc.lock",
            "indoor_seed0",
        ]
    assert leftovers_seen > 0  # the kills did leave temporaries, and the reruns removed them
