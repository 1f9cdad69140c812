"""The contract of :mod:`diffloc.pipeline.stage`: a stage commits as a whole (outputs and
record together) and is reused only while its config and inputs are unchanged.

The findings of issue 17 it fixes are tested in ``test_stage_cache_keys.py``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from diffloc.io.identity import identity
from diffloc.pipeline import stage as stage_module
from diffloc.pipeline.hints import Command, MissingStageError, StaleStageError
from diffloc.pipeline.stage import StageSummary, open_stage, stage_key, verified_record

COMMAND = Command("demo")


@dataclass(frozen=True)
class CountSummary(StageSummary):
    count: int


def _commit(folder: Path, key: dict, files: dict[str, str], owned=()) -> CountSummary:
    with open_stage(folder, "demo", COMMAND) as stage:
        for name, text in files.items():
            (stage.workdir() / name).write_text(text)
        return stage.commit(key, CountSummary(len(files)), list(files), owned)


def test_a_commit_writes_outputs_and_a_record_that_verifies(tmp_path: Path):
    key = stage_key({"a": 1}, {"input": {"kind": "file", "size": 1, "sha256": "x"}})
    summary = _commit(tmp_path, key, {"out.txt": "hello"})
    assert (tmp_path / "out.txt").read_text() == "hello"
    record = verified_record(tmp_path, "demo", COMMAND)
    assert CountSummary.from_record(record) == summary == CountSummary(1)
    assert record["stage"]["outputs"]["out.txt"] == identity(tmp_path / "out.txt")
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".tmp")] == []


def test_a_failed_run_leaves_the_previous_result_and_record_intact(tmp_path: Path):
    key = stage_key({"a": 1}, {})
    _commit(tmp_path, key, {"out.txt": "old"})
    record = verified_record(tmp_path, "demo", COMMAND)
    with pytest.raises(RuntimeError), open_stage(tmp_path, "demo", COMMAND) as stage:
        (stage.workdir() / "out.txt").write_text("new")
        raise RuntimeError("the stage failed before its commit")
    assert (tmp_path / "out.txt").read_text() == "old"
    assert verified_record(tmp_path, "demo", COMMAND) == record


def test_an_output_changed_after_the_commit_is_not_trusted(tmp_path: Path):
    key = stage_key({"a": 1}, {})
    _commit(tmp_path, key, {"out.txt": "old"})
    (tmp_path / "out.txt").write_text("half-written")
    with pytest.raises(StaleStageError, match=r"out\.txt is not the file .*demo\.json describes"):
        verified_record(tmp_path, "demo", COMMAND)
    with open_stage(tmp_path, "demo", COMMAND) as stage:
        assert stage.reusable(key, CountSummary) is None
    (tmp_path / "demo.json").unlink()
    with pytest.raises(MissingStageError, match="task=demo"):
        verified_record(tmp_path, "demo", COMMAND)


def test_reuse_needs_the_same_config_and_inputs(tmp_path: Path):
    key = stage_key({"a": 1}, {"input": {"sha256": "x"}})
    _commit(tmp_path, key, {"out.txt": "x"})
    with open_stage(tmp_path, "demo", COMMAND) as stage:
        assert stage.reusable(key, CountSummary) is not None
        assert stage.reusable(stage_key({"a": 2}, {"input": {"sha256": "x"}}), CountSummary) is None
        assert stage.reusable(stage_key({"a": 1}, {"input": {"sha256": "y"}}), CountSummary) is None


def test_outputs_the_new_run_does_not_make_are_removed(tmp_path: Path):
    key = stage_key({}, {})
    _commit(tmp_path, key, {"a.txt": "a", "b.txt": "b"})
    (tmp_path / "c.txt").write_text("an output of a run before the records")
    _commit(tmp_path, key, {"a.txt": "a"}, owned=["c.txt"])
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".")) == [
        "a.txt",
        "demo.json",
    ]


def test_a_commit_cut_short_is_completed_by_the_next_run(tmp_path: Path, monkeypatch):
    """A kill between the renames of a commit (here: an interrupt after the first output
    moved) leaves no record that could be trusted; the next run on the folder completes the
    commit from its journal."""
    _commit(tmp_path, stage_key({"run": 1}, {}), {"a.txt": "old", "b.txt": "old"})
    moved = []

    def cut_short(source: Path, target: Path) -> None:
        if moved:
            raise KeyboardInterrupt
        moved.append(target)
        replace(source, target)

    replace = stage_module._replace
    monkeypatch.setattr(stage_module, "_replace", cut_short)
    new_key = stage_key({"run": 2}, {})
    with pytest.raises(KeyboardInterrupt):
        _commit(tmp_path, new_key, {"a.txt": "new", "b.txt": "new"})
    monkeypatch.undo()
    with pytest.raises(MissingStageError):
        verified_record(tmp_path, "demo", COMMAND)
    with open_stage(tmp_path, "demo", COMMAND) as stage:
        assert stage.reusable(new_key, CountSummary) is not None
    assert [(tmp_path / n).read_text() for n in ("a.txt", "b.txt")] == ["new", "new"]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".tmp")] == []


@dataclass(frozen=True)
class CountAndSizeSummary(StageSummary):
    count: int
    size: int


def test_a_record_without_a_field_of_the_summary_is_not_reused(tmp_path: Path):
    """A record an older diffloc wrote (fewer summary fields) is made again, not half-read."""
    key = stage_key({"a": 1}, {})
    _commit(tmp_path, key, {"out.txt": "x"})
    with open_stage(tmp_path, "demo", COMMAND) as stage:
        assert stage.reusable(key, CountSummary) == CountSummary(1)
        assert stage.reusable(key, CountAndSizeSummary) is None
    record = verified_record(tmp_path, "demo", COMMAND)
    with pytest.raises(ValueError, match=r"demo\.json lacks size of a CountAndSizeSummary"):
        CountAndSizeSummary.from_record(record, tmp_path / "demo.json")


def test_a_summary_field_json_cannot_store_is_refused_at_the_commit(tmp_path: Path):
    with pytest.raises(TypeError, match="'object', which JSON cannot store"):
        _commit_summary(tmp_path, CountSummary(object()))
    assert not (tmp_path / "demo.json").exists()


def _commit_summary(folder: Path, summary: StageSummary) -> StageSummary:
    with open_stage(folder, "demo", COMMAND) as stage:
        (stage.workdir() / "out.txt").write_text("x")
        return stage.commit(stage_key({}, {}), summary, ["out.txt"])


def test_the_outcome_names_the_identities_of_the_committed_or_reused_outputs(tmp_path: Path):
    key = stage_key({"a": 1}, {})
    with open_stage(tmp_path, "demo", COMMAND) as stage:
        with pytest.raises(RuntimeError, match="no result reused or committed yet"):
            stage.outcome(CountSummary(1))
        (stage.workdir() / "out.txt").write_text("x")
        made = stage.outcome(stage.commit(key, CountSummary(1), ["out.txt"]))
    assert made.outputs == {"out.txt": identity(tmp_path / "out.txt")}
    with open_stage(tmp_path, "demo", COMMAND) as stage:
        assert stage.outcome(stage.reusable(key, CountSummary)) == made
