"""Concurrent runs on one stage folder: the second waits (at most ``stage.timeout_s``) or
refuses (``stage.wait=false``), says so, and never mixes results; locks nest in one order."""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from diffloc.io import lock
from diffloc.io.lock import (
    LOCK_NAME,
    FolderBusyError,
    LockConfig,
    LockOrderError,
    folder_lock,
    lock_config,
)
from diffloc.pipeline.build_map import BuildMapConfig, MapSummary, build_maps
from diffloc.pipeline.hints import Command
from diffloc.pipeline.stage import StageSummary, open_stage, stage_key, verified_record
from tests.conftest import FINE_SURFELS, copy_dataset, run_task


@dataclass(frozen=True)
class ValueSummary(StageSummary):
    value: str


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
    record = verified_record(root / "map", "build_map", Command("x"))
    assert results and results[0] == MapSummary.from_record(record)
    assert f"in use by process {os.getpid()}" in messages[0] and str(root / "map") in messages[0]


def test_two_writers_of_one_folder_commit_one_after_the_other(tmp_path: Path):
    """Two runs of a stage with different configs on one folder, started together: each
    commits whole (outputs and record of the same run), the last one's result stands."""
    barrier = threading.Barrier(2)

    def write(value: str) -> None:
        barrier.wait()
        with open_stage(tmp_path, "demo", Command("demo")) as stage:
            for name in ("a.txt", "b.txt"):
                (stage.workdir() / name).write_text(value)
            stage.commit(stage_key({"value": value}, {}), ValueSummary(value), ["a.txt", "b.txt"])

    threads = [threading.Thread(target=write, args=(v,)) for v in ("x" * 1000, "y" * 1000)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    record = verified_record(tmp_path, "demo", Command("demo"))
    assert {(tmp_path / n).read_text() for n in ("a.txt", "b.txt")} == {record["value"]}


def _try_lock(folder: Path, config: LockConfig) -> tuple[BaseException | None, float]:
    """Take ``folder``'s lock in another thread under ``config``; its error and the seconds
    it took."""
    outcome: list = []

    def take() -> None:
        start = time.monotonic()
        try:
            with lock_config(config), folder_lock(folder):
                outcome.append(None)
        except FolderBusyError as exc:
            outcome.append(exc)
        outcome.append(time.monotonic() - start)

    thread = threading.Thread(target=take)
    thread.start()
    thread.join(timeout=60)
    return outcome[0], outcome[1]


def test_a_run_that_must_not_wait_refuses_naming_the_folder_and_the_holder(
    tmp_path: Path, monkeypatch
):
    monkeypatch.setattr(lock, "announce_wait", lambda message: None)
    with folder_lock(tmp_path):
        assert (tmp_path / LOCK_NAME).read_text() == f"{os.getpid()}\n"
        error, seconds = _try_lock(tmp_path, LockConfig(wait=False))
    assert isinstance(error, FolderBusyError) and seconds < 5
    assert str(tmp_path) in str(error) and f"process {os.getpid()}" in str(error)
    assert "stage.wait=false" in str(error)
    assert (tmp_path / LOCK_NAME).read_text() == ""  # the holder's id goes with its lock
    assert _try_lock(tmp_path, LockConfig(wait=False))[0] is None  # free again: no error


def test_a_run_waits_at_most_timeout_s(tmp_path: Path, monkeypatch):
    monkeypatch.setattr(lock, "announce_wait", lambda message: None)
    with folder_lock(tmp_path):
        error, seconds = _try_lock(tmp_path, LockConfig(timeout_s=0.5))
    assert isinstance(error, FolderBusyError) and seconds >= 0.5
    assert str(tmp_path) in str(error) and "after 0.5 s (stage.timeout_s)" in str(error)
    # A holder that lets go within the limit: the waiting run gets the lock.
    holding = folder_lock(tmp_path)
    holding.__enter__()
    threading.Timer(0.3, lambda: holding.__exit__(None, None, None)).start()
    error, seconds = _try_lock(tmp_path, LockConfig(timeout_s=30))
    assert error is None and 0.2 < seconds < 30


def test_stage_wait_false_on_the_command_line_refuses_a_busy_stage_folder(
    tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory
):
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "refuse")
    outcome: list = []

    def second() -> None:
        try:
            run_task("build_map", root, "task.point_maps=[]", "stage.wait=false")
        except FolderBusyError as exc:
            outcome.append(exc)

    with folder_lock(root / "map"):
        thread = threading.Thread(target=second)
        thread.start()
        thread.join(timeout=300)
    assert outcome and str(root / "map") in str(outcome[0])


@pytest.mark.parametrize("bad", ["stage.timeout_s=-1", "stage.timeout_s=nan"])
def test_a_bad_lock_setting_fails_before_any_work(tiny_indoor_mapped: Path, bad: str):
    with pytest.raises(ValueError, match=r"stage\.timeout_s must be null or a number >= 0"):
        run_task("build_map", tiny_indoor_mapped, bad)


def test_locks_nest_only_downstream_first(tmp_path: Path):
    """While holding a lock of level 2 a thread may take level 1 (an upstream folder), never
    level 2 or 3: two runs nesting in opposite orders could wait for each other forever."""
    database, upstream, results = tmp_path / "db", tmp_path / "map", tmp_path / "out"
    with folder_lock(database, level=2):
        with folder_lock(upstream, shared=True, level=1):
            pass
        for folder, level in ((results, 3), (upstream, 2), (database, 2)):
            with pytest.raises(LockOrderError, match=f"lock of {folder} .*holding {database}"):
                with folder_lock(folder, level=level):
                    pass
    with folder_lock(results, level=3):  # nothing held: any level
        pass
