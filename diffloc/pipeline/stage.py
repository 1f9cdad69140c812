"""The stage contract: atomic commits, content-keyed reuse, locks and verified records.

A stage (``build_map``, ``build_db``, ...) writes its outputs into a folder and describes them
in a record ``<folder>/<name>.json``: the stage's typed summary (a
:class:`~diffloc.pipeline.summary.StageSummary`: counts, timings, ...) with a ``"stage"`` entry
holding

- ``key``: the configuration and the identity (size + SHA-256, :func:`diffloc.io.identity`)
  of every input the stage read, upstream stages' outputs included;
- ``outputs``: the identity of every output file or folder, relative to the folder.

:func:`open_stage` holds the folder's lock for the whole run (a second run on the folder waits)
and removes temporaries of killed runs. The stage computes into a fresh hidden work folder
(:meth:`StageRun.workdir`) and :meth:`StageRun.commit` writes a journal (the new record) into
it, moves the outputs into place and writes the record last, so a run that fails or is killed
while computing leaves the previous result and its record untouched, and a commit cut short (a
kill between its renames) is completed by the next run on the folder from its journal. A
record is trusted only if every output it lists still has its recorded identity
(:func:`verified_record`): a hand-edited, truncated or half-moved output reads as "not made"
and is made again, never reused.

A result is reused only when its record verifies and holds the same key
(:meth:`StageRun.reusable`). A stage that reads another stage's output takes it from the
verified record (:func:`verified_record`), keys itself on the recorded identity of that output
(:func:`output_identity`), and a reader checks that a derived result was made from the current
upstream output (:func:`check_made_from`), e.g. that ``optimized/`` belongs to the current
``build_db`` database.

Example:
    A stage that writes one note: the second run with the same text reuses the first one's
    result, another text makes it again.

    >>> from dataclasses import dataclass
    >>> from pathlib import Path
    >>> @dataclass(frozen=True)
    ... class NoteSummary(StageSummary):
    ...     chars: int
    >>> def write_note(folder, text):
    ...     with open_stage(folder, "note", Command("note")) as stage:
    ...         key = stage_key({"text": text}, {})
    ...         if stage.reusable(key, NoteSummary) is not None:
    ...             return "reused"
    ...         (stage.workdir() / "note.txt").write_text(text)
    ...         return stage.commit(key, NoteSummary(len(text)), ["note.txt"]).chars
    >>> _ = Path("notes").mkdir()
    >>> write_note("notes", "hello"), write_note("notes", "hello"), write_note("notes", "hi")
    (5, 'reused', 2)
    >>> Path("notes/note.txt").read_text()
    'hi'
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Generic, TypeVar

from diffloc.io.atomic import atomic_write_text
from diffloc.io.identity import identity
from diffloc.io.json_record import read_json_record
from diffloc.io.lock import LockLevel, ReadOnlyFolderError, folder_lock, remove_temporaries
from diffloc.pipeline.hints import Command, MissingStageError, StaleStageError
from diffloc.pipeline.summary import StageSummary

__all__ = [
    "STAGE_FORMAT_VERSION",
    "LockLevel",
    "StageSummary",
    "StageOutcome",
    "StageRun",
    "check_made_from",
    "open_stage",
    "output_identity",
    "read_lock",
    "record_path",
    "stage_key",
    "verified_record",
]

S = TypeVar("S", bound=StageSummary)

STAGE_FORMAT_VERSION = 1
"""Version of the ``"stage"`` entry of a record."""

JOURNAL = "commit.json"
"""The journal of a commit in progress, inside the work folder: the record (its file name and
content) to write and the stale outputs to remove."""


def record_path(folder: str | os.PathLike, name: str) -> Path:
    """``<folder>/<name>.json``: the record of stage ``name`` writing into ``folder``."""
    return Path(folder) / f"{name}.json"


def stage_key(config: Mapping, inputs: Mapping[str, dict]) -> dict:
    """The reuse key of a stage run: its configuration and the identities of its inputs.

    Args:
        config: the stage's settings (JSON types; tuples become lists).
        inputs: input name -> identity (:func:`diffloc.io.identity.identity`, or an upstream
            record's :func:`output_identity`).

    Returns:
        ``{"config": ..., "inputs": ...}`` as it is stored in the record.
    """
    return json.loads(json.dumps({"config": dict(config), "inputs": dict(sorted(inputs.items()))}))


def _stage_entry(record: dict, path: Path) -> dict:
    """The validated ``"stage"`` entry of a record read from ``path``."""
    entry = record.get("stage")
    valid = (
        isinstance(entry, dict)
        and entry.get("format_version") == STAGE_FORMAT_VERSION
        and isinstance(entry.get("key"), dict)
        and isinstance(entry.get("outputs"), dict)
        and all(isinstance(v, dict) for v in entry["outputs"].values())
    )
    if not valid:
        raise ValueError(
            f"{path} has no valid stage manifest (format {STAGE_FORMAT_VERSION}): it was written "
            "by an older diffloc or by hand"
        )
    return entry


def verified_record(folder: str | os.PathLike, name: str, command: Command) -> dict:
    """The record of stage ``name`` in ``folder``, after checking every output it lists.

    Args:
        folder: the stage's folder.
        name: the stage (its record is ``<folder>/<name>.json``).
        command: the command that makes the stage again, for messages.

    Returns:
        The record (summary and ``"stage"`` entry).

    Raises:
        MissingStageError: no record; the message names ``command``.
        StaleStageError: a record that is not JSON or has no valid manifest, or an output that
            is missing or differs from its recorded identity (half-written, changed by hand);
            the message names the file and ``command``.
    """
    folder = Path(folder)
    path = record_path(folder, name)
    if not path.is_file():
        raise MissingStageError(path, command)
    try:
        record = read_json_record(path)
        entry = _stage_entry(record, path)
    except ValueError as exc:
        raise StaleStageError(str(exc), command) from exc
    for rel, recorded in entry["outputs"].items():
        output = folder / rel
        if not output.exists():
            raise StaleStageError(f"{output}, listed in {path}, is missing", command)
        if identity(output) != recorded:
            raise StaleStageError(
                f"{output} is not the file {path} describes (changed, or left half-written by "
                "a killed run)",
                command,
            )
    return record


def output_identity(record: dict, rel: str) -> dict:
    """The recorded identity of output ``rel`` of a verified record."""
    return record["stage"]["outputs"][rel]


def check_made_from(
    record: dict, path: Path, input_name: str, upstream: dict, output: str, command: Command
) -> None:
    """Check that a derived result was made from the current upstream output.

    Args:
        record: the derived stage's verified record (e.g. ``optimize_db.json``).
        path: its file, for messages.
        input_name: the name of the input in its key (e.g. ``"database"``).
        upstream: the upstream stage's verified record (e.g. ``build_db.json``).
        output: the upstream output (e.g. ``"database"``).
        command: the command that makes the derived result again.

    Raises:
        StaleStageError: the derived result was made from another version of the output.
    """
    used = record["stage"]["key"]["inputs"].get(input_name)
    if used != output_identity(upstream, output):
        raise StaleStageError(
            f"{path} was made from another {output!r} than the current one (the upstream stage "
            "ran again since)",
            command,
        )


@contextlib.contextmanager
def read_lock(folder: str | os.PathLike, level: LockLevel) -> Iterator[None]:
    """Hold ``folder``'s lock shared while reading a stage's outputs (no-op if it is missing).

    Args:
        folder: the stage folder.
        level: its place in the lock order (:class:`LockLevel`).
    """
    if not Path(folder).is_dir():
        yield
        return
    with folder_lock(folder, shared=True, level=level):
        yield


@dataclass(frozen=True)
class StageOutcome(Generic[S]):
    """A stage's result as the next stage needs it.

    Attributes:
        summary: the stage's typed summary.
        outputs: output (relative path) -> identity (:func:`diffloc.io.identity.identity`),
            as listed in the record; a downstream stage keys itself on these.
    """

    summary: S
    outputs: dict[str, dict]


class StageRun:
    """A stage run holding its folder's lock (made by :func:`open_stage`).

    Attributes:
        folder: the folder the outputs go to.
        name: the stage name; the record is ``<folder>/<name>.json``.
        command: the command that runs the stage, for messages.
    """

    def __init__(
        self, folder: Path, name: str, command: Command, read_only: str | None = None
    ) -> None:
        self.folder = folder
        self.name = name
        self.command = command
        self.read_only = read_only
        self._workdir: Path | None = None
        self._outputs: dict[str, dict] | None = None

    def _refuse_write(self) -> ReadOnlyFolderError:
        return ReadOnlyFolderError(
            f"{self.read_only}, and it holds no result of `diffloc task={self.command.task}` "
            "with these settings and inputs to reuse: copy the dataset to a folder you can "
            "write and run there (or make the folder writable)"
        )

    @property
    def record_path(self) -> Path:
        """``<folder>/<name>.json``."""
        return record_path(self.folder, self.name)

    def reusable(self, key: dict, kind: type[S]) -> S | None:
        """The summary of a complete earlier run with the same key, else ``None``.

        A missing, corrupt or half-written result, or a record without every field of
        ``kind`` (an older diffloc's), is not reusable (it is made again).

        Args:
            key: the run's :func:`stage_key`.
            kind: the stage's summary type.

        Raises:
            ReadOnlyFolderError: the folder cannot be written and holds no reusable result
                (the message names the folder and what to do).
        """
        try:
            record = verified_record(self.folder, self.name, self.command)
            summary = kind.from_record(record, self.record_path)
        except (MissingStageError, StaleStageError, ValueError):
            record = None
        if record is not None and record["stage"]["key"] == key:
            self._outputs = record["stage"]["outputs"]
            return summary
        if self.read_only is not None:
            raise self._refuse_write()
        return None

    def workdir(self) -> Path:
        """A fresh hidden folder next to the outputs to write them into (made once per run).

        Raises:
            ReadOnlyFolderError: the folder cannot be written.
        """
        if self.read_only is not None:
            raise self._refuse_write()
        if self._workdir is None:
            self._workdir = Path(tempfile.mkdtemp(dir=self.folder, prefix=f".tmp-{self.name}-"))
        return self._workdir

    def _previous_outputs(self) -> set[str]:
        try:
            return set(
                _stage_entry(read_json_record(self.record_path), self.record_path)["outputs"]
            )
        except (FileNotFoundError, ValueError):
            return set()

    def commit(self, key: dict, summary: S, outputs: Iterable[str], owned: Iterable[str] = ()) -> S:
        """Move the outputs from :meth:`workdir` into place and write the record last.

        The new record and the stale outputs are journaled in the work folder first; a kill
        between the renames leaves the folder without a record, and the next
        :func:`open_stage` on it completes the commit from the journal.

        Args:
            key: the run's :func:`stage_key`.
            summary: the stage's typed summary, stored at the top level of the record.
            outputs: the outputs, relative to :meth:`workdir` (files or folders).
            owned: other names this stage may write; those of them that exist in the folder
                but are not among ``outputs`` (and outputs of the previous record that are not
                among them) are removed, so no stale output stays beside the new ones.

        Returns:
            ``summary`` as it reads back from the record (equal to what a reuse returns).
        """
        outputs = list(outputs)
        work = self.workdir()
        manifest = {rel: identity(work / rel) for rel in outputs}
        entry = {"format_version": STAGE_FORMAT_VERSION, "key": key, "outputs": manifest}
        record = {**summary.to_json(), "stage": entry}
        stale = sorted((self._previous_outputs() | set(owned)) - set(outputs))
        journal = {"record_name": self.record_path.name, "record": record, "stale": stale}
        atomic_write_text(work / JOURNAL, json.dumps(journal, indent=2) + "\n")
        _finish_commit(self.folder, work)
        self._outputs = manifest
        return summary.round_trip()

    def outcome(self, summary: S) -> StageOutcome[S]:
        """``summary`` (what :meth:`reusable` or :meth:`commit` returned) with the identities of
        the outputs this run reused or committed, for a downstream stage's key.

        Raises:
            RuntimeError: the run has neither reused nor committed a result yet.
        """
        if self._outputs is None:
            raise RuntimeError(f"{self.record_path}: no result reused or committed yet")
        return StageOutcome(summary, dict(self._outputs))

    def close(self) -> None:
        """Remove the work folder, unless it holds the journal of a commit that did not finish
        (the next run on the folder completes that commit)."""
        if self._workdir is not None and not (self._workdir / JOURNAL).is_file():
            _remove(self._workdir)


def _finish_commit(folder: Path, work: Path) -> None:
    """Carry out (or complete) the commit journaled in ``work``: move every output still in
    ``work`` into place, remove stale outputs, write the record, remove ``work``. Running it
    again after a kill at any point ends in the same state."""
    journal = json.loads((work / JOURNAL).read_text(encoding="utf-8"))
    record = folder / journal["record_name"]
    record.unlink(missing_ok=True)
    for rel in journal["record"]["stage"]["outputs"]:
        if (work / rel).exists():
            _replace(work / rel, folder / rel)
    for rel in journal["stale"]:
        _remove(folder / rel)
    atomic_write_text(record, json.dumps(journal["record"], indent=2) + "\n")
    _remove(work)


def _complete_commits(folder: Path) -> None:
    """Complete the commits that killed runs of any stage left journaled in ``folder``."""
    for work in sorted(folder.glob(".tmp-*")):
        if (work / JOURNAL).is_file():
            _finish_commit(folder, work)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


def _replace(source: Path, target: Path) -> None:
    """Move ``source`` over ``target`` (a folder target is moved aside, then removed)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    if target.is_dir() and not target.is_symlink():
        old = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}.old-"))
        old.rmdir()
        os.replace(target, old)
        os.replace(source, target)
        shutil.rmtree(old)
    else:
        os.replace(source, target)


@contextlib.contextmanager
def open_stage(
    folder: str | os.PathLike,
    name: str,
    command: Command,
    level: LockLevel = LockLevel.RESULTS,
) -> Iterator[StageRun]:
    """Run stage ``name`` into ``folder``: lock it, complete a commit a killed run left
    journaled, clear killed runs' temporaries, clean up.

    A folder this run cannot write (read-only mount, another user's) is opened for reuse only:
    it is locked shared (:func:`diffloc.io.lock.folder_lock`), nothing in it is changed, and
    :meth:`StageRun.reusable` returns a complete result with the same key or raises
    :class:`~diffloc.io.lock.ReadOnlyFolderError` saying what to do.

    Args:
        folder: the output folder (created if missing).
        name: the stage name.
        command: the command that runs the stage, for messages.
        level: the folder's place in the lock order (:class:`LockLevel`).

    Yields:
        The :class:`StageRun`; its work folder is removed when the block ends, committed or not.
    """
    folder = Path(folder)
    with contextlib.ExitStack() as locks:
        try:
            locks.enter_context(folder_lock(folder, level=level))
            read_only = None
        except ReadOnlyFolderError as exc:
            read_only = str(exc)
            locks.enter_context(read_lock(folder, level))
        if read_only is None:
            _complete_commits(folder)
            remove_temporaries(folder)
        run = StageRun(folder, name, command, read_only)
        try:
            yield run
        finally:
            run.close()
