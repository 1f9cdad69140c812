"""Concurrent runs on one stage folder: the second waits, says so, and never mixes results."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from diffloc.io import lock
from diffloc.io.lock import folder_lock
from diffloc.pipeline.build_map import BuildMapConfig, build_maps
from diffloc.pipeline.hints import Command
from diffloc.pipeline.stage import open_stage, stage_key, verified_record
from tests.conftest import FINE_SURFELS, copy_dataset


def test_a_second_run_waits_for_the_first_and_then_reuses_its_result(
    tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory, monkeypatch
):
    """While one run holds ``map/`` (here: this test, holding its lock), a second
    ``build_map`` announces that it waits and does nothing until the first one is done."""
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "concurrent")
    waiting, messages, results = threading.Event(), [], []

    def announce(message: str) -> None:
        messages.append(message)
        waiting.set()

    monkeypatch.setattr(lock, "announce_wait", announce)
    cfg = BuildMapConfig(point_maps=[], preview_frames=1)
    second = threading.Thread(
        target=lambda: results.append(build_maps(root, cfg, FINE_SURFELS, False))
    )
    with folder_lock(root / "map"):
        second.start()
        assert waiting.wait(timeout=300), "the second run never said it was waiting"
        assert second.is_alive() and results == []  # it cannot go on while the lock is held
    second.join(timeout=300)
    assert results and results[0] == verified_record(root / "map", "build_map", Command("x"))
    assert "in use by another diffloc run" in messages[0] and str(root / "map") in messages[0]


def test_two_writers_of_one_folder_commit_one_after_the_other(tmp_path: Path):
    """Two runs of a stage with different configs on one folder, started together: each
    commits whole (outputs and record of the same run), the last one's result stands."""
    barrier = threading.Barrier(2)

    def write(value: str) -> None:
        barrier.wait()
        with open_stage(tmp_path, "demo", Command("demo")) as stage:
            for name in ("a.txt", "b.txt"):
                (stage.workdir() / name).write_text(value)
            stage.commit(stage_key({"value": value}, {}), {"value": value}, ["a.txt", "b.txt"])

    threads = [threading.Thread(target=write, args=(v,)) for v in ("x" * 1000, "y" * 1000)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    record = verified_record(tmp_path, "demo", Command("demo"))
    assert {(tmp_path / n).read_text() for n in ("a.txt", "b.txt")} == {record["value"]}
