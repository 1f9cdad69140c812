"""Folder locks between processes, and removal of what killed writers left behind.

Every stage that writes into a folder holds :func:`folder_lock` on it (exclusive) for its whole
run; a stage that reads another stage's folder holds it shared while it reads. The lock is
``fcntl.flock`` on the hidden file ``.diffloc.lock`` in the folder: the kernel drops it when
its process dies, so a killed run never leaves the folder locked. A writer records its process
id in the lock file while it holds it, for the messages of the runs it keeps out.

A run that finds the folder in use waits (saying so once on stderr), waits at most
``timeout_s`` seconds, or refuses at once, as :class:`LockConfig` (the root ``stage`` config
node) says; a run that gives up raises :class:`FolderBusyError` naming the folder and the
process that holds it.

A folder the run cannot write (a read-only mount, another user's folder) cannot hold a new lock
file: a writer's lock raises :class:`ReadOnlyFolderError`, and a reader's lock is taken shared
on the existing lock file opened read-only (so it still excludes writers), or, if the folder
has none, on a per-user lock file in the runtime folder keyed by the folder's resolved path.

Locks are taken in one order: each has a level (the stage's place in the pipeline, see
``diffloc/pipeline/design.md``), and while a thread holds locks it may take only a lock of a
lower level than all of them, so two runs can never wait for each other; an out-of-order
acquisition raises :class:`LockOrderError` (a bug in the caller).

While a writer holds the exclusive lock no live process is writing into the folder, so the
hidden temporary files and folders there (``.tmp-*``, ``.<name>.tmp-*``, ``.<name>.*.tmp``,
``.<name>.old-*`` of :mod:`diffloc.io.atomic`) are leftovers of killed runs:
:func:`remove_temporaries` deletes them.

Example:
    >>> from pathlib import Path
    >>> _ = (Path("map") / ".tmp-build_map-1").mkdir(parents=True)
    >>> with folder_lock("map"):
    ...     [p.name for p in remove_temporaries("map")]
    ['.tmp-build_map-1']
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import math
import os
import re
import shutil
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path

__all__ = [
    "LOCK_NAME",
    "FolderBusyError",
    "LockConfig",
    "LockLevel",
    "LockOrderError",
    "ReadOnlyFolderError",
    "folder_lock",
    "lock_config",
    "remove_sibling_temporaries",
    "remove_temporaries",
    "runtime_lock_path",
    "sibling_lock_path",
]

LOCK_NAME = ".diffloc.lock"
"""The lock file inside a locked folder."""

POLL_S = 0.1
"""Seconds between two tries of a lock while waiting with a time limit."""

_TEMPORARY = re.compile(r"^\.(tmp-.*|.+\.tmp-.*|.+\.tmp(\.[A-Za-z0-9]+)?|.+\.old-.*)$")
"""Hidden names of temporary files and folders written by :mod:`diffloc.io.atomic` and
:mod:`diffloc.pipeline.stage`."""

_READ_ONLY_ERRNOS = (errno.EACCES, errno.EPERM, errno.EROFS)
"""``OSError.errno`` values that mean "this folder cannot be written"."""


class LockLevel(IntEnum):
    """The lock order of diffloc's folders (:func:`folder_lock` levels): a downstream stage's
    folder has the higher level and is locked first; while holding it, a run may lock the
    folders of stages upstream of it (lower levels), never the reverse."""

    DATASET = 0
    """The dataset folder (``task=simulate``)."""
    MAP = 1
    """``<dataset>/map`` (``build_map``)."""
    DATABASE = 2
    """A database folder ``<dataset>/db/<name>`` (``build_db``, ``optimize_db``,
    ``calibrate_rig``, its retriever caches) and a radiance-field submap folder."""
    UPDATED = 3
    """An updated database ``<database folder>/updated_<sequence>`` (``update_db``) and its
    retriever caches."""
    RESULTS = 4
    """Relocalisation results (``task.out_dir``) and stages outside the pipeline."""


@dataclass
class LockConfig:
    """What a run does when a folder it needs is in use by another run (root ``stage`` node).

    Attributes:
        wait: wait for the other run; ``False``: refuse at once (:class:`FolderBusyError`).
        timeout_s: with ``wait``, give up after this many seconds; ``None``: wait as long as
            it takes.
    """

    wait: bool = True
    timeout_s: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.wait, bool):
            raise ValueError(f"stage.wait must be true or false, got {self.wait!r}")
        timeout = self.timeout_s
        if timeout is not None and not (
            isinstance(timeout, int | float)
            and not isinstance(timeout, bool)
            and math.isfinite(timeout)
            and timeout >= 0
        ):
            raise ValueError(f"stage.timeout_s must be null or a number >= 0, got {timeout!r}")


class FolderBusyError(OSError):
    """Another run holds a folder's lock and this run does not wait (longer) for it."""


class ReadOnlyFolderError(PermissionError):
    """A writer's lock on a folder this run cannot write."""


class LockOrderError(RuntimeError):
    """A lock taken out of the order of levels (a bug: two such runs could wait for each
    other forever)."""


_config = LockConfig()
_held = threading.local()


@contextlib.contextmanager
def lock_config(config: LockConfig) -> Iterator[None]:
    """Use ``config`` for every lock taken in the ``with`` block (any thread)."""
    global _config
    previous, _config = _config, config
    try:
        yield
    finally:
        _config = previous


def announce_wait(message: str) -> None:
    """Tell the user a run is waiting for a lock (stderr; tests replace it)."""
    print(f"waiting: {message}", file=sys.stderr, flush=True)


def runtime_lock_path(folder: str | os.PathLike) -> Path:
    """The per-user lock file of a folder that has no lock file and cannot hold one:
    ``$XDG_RUNTIME_DIR`` (else the temporary folder) ``/diffloc-locks-<uid>/<hash>.lock``,
    keyed by the folder's resolved path."""
    base = Path(os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir())
    digest = hashlib.sha256(str(Path(folder).resolve()).encode("utf-8")).hexdigest()[:32]
    return base / f"diffloc-locks-{os.getuid()}" / f"{digest}.lock"


def _holder(path: Path) -> str:
    """Who holds the lock ``path``: the writer process it records, if that one is alive."""
    try:
        pid = int(path.read_text(encoding="ascii").strip())
    except (OSError, ValueError):
        return "another diffloc run"
    try:
        os.kill(pid, 0)
    except PermissionError:  # alive, another user's
        pass
    except OSError:
        return "another diffloc run"
    return f"process {pid}"


def _check_order(folder: Path, level: int) -> None:
    stack = getattr(_held, "stack", [])
    for other, other_level in stack:
        if level >= other_level:
            raise LockOrderError(
                f"lock of {folder} (level {level}) taken while holding {other} (level "
                f"{other_level}): locks must be taken in decreasing level (downstream stage "
                "first), see diffloc/pipeline/design.md"
            )


def sibling_lock_path(folder: str | os.PathLike) -> Path:
    """The lock file of a folder that is made whole and renamed into place (a simulated
    dataset): ``<parent>/.<name>.diffloc.lock``, beside it, since a lock inside it would be
    replaced with it."""
    folder = Path(folder)
    return folder.parent / f".{folder.name}{LOCK_NAME}"


def _open(folder: Path, shared: bool, path: Path) -> tuple[int, Path]:
    """An open file descriptor of ``folder``'s lock file ``path``, and that file."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        return os.open(path, os.O_RDWR | os.O_CREAT, 0o666), path
    except OSError as exc:
        if exc.errno not in _READ_ONLY_ERRNOS:
            raise
        if not shared:
            raise ReadOnlyFolderError(f"{folder} cannot be written ({exc.strerror})") from exc
    with contextlib.suppress(FileNotFoundError):
        return os.open(path, os.O_RDONLY), path
    path = runtime_lock_path(folder)
    path.parent.mkdir(parents=True, exist_ok=True)
    return os.open(path, os.O_RDWR | os.O_CREAT, 0o600), path


def _acquire(fd: int, mode: int, folder: Path, path: Path, shared: bool) -> None:
    """Take the lock as :data:`_config` says; :class:`FolderBusyError` if this run gives up."""
    with contextlib.suppress(BlockingIOError):
        fcntl.flock(fd, mode | fcntl.LOCK_NB)
        return
    config = _config
    if not config.wait or config.timeout_s == 0:
        raise FolderBusyError(
            f"{folder} is in use by {_holder(path)} (lock {path}) and stage.wait=false: run "
            "again when it has finished, or set stage.wait=true to wait for it",
        )
    verb = "read" if shared else "write"
    limit = "" if config.timeout_s is None else f" (at most {config.timeout_s:g} s)"
    announce_wait(
        f"{folder} is in use by {_holder(path)} (lock {path}); this run will {verb} it when "
        f"that one finishes{limit} (stop the other run to go on now)"
    )
    if config.timeout_s is None:
        fcntl.flock(fd, mode)
        return
    deadline = time.monotonic() + config.timeout_s
    while True:
        time.sleep(max(0.0, min(POLL_S, deadline - time.monotonic())))
        with contextlib.suppress(BlockingIOError):
            fcntl.flock(fd, mode | fcntl.LOCK_NB)
            return
        if time.monotonic() >= deadline:
            raise FolderBusyError(
                f"{folder} is still in use by {_holder(path)} (lock {path}) after "
                f"{config.timeout_s:g} s (stage.timeout_s): run again when it has finished, "
                "or raise stage.timeout_s",
            )


@contextlib.contextmanager
def folder_lock(
    folder: str | os.PathLike,
    shared: bool = False,
    level: int = LockLevel.DATASET,
    lock_path: str | os.PathLike | None = None,
) -> Iterator[Path]:
    """Hold the lock of ``folder`` (created if missing) for the ``with`` block.

    Args:
        folder: the folder to lock.
        shared: a reader's lock (many readers together, no writer); else a writer's lock.
        level: the lock's place in the lock order (:class:`LockLevel`): while this thread
            holds locks, ``level`` must be lower than each of theirs.
        lock_path: the lock file; default ``<folder>/.diffloc.lock`` (the folder is created);
            :func:`sibling_lock_path` for a folder that is renamed into place as a whole (the
            folder is not created).

    Yields:
        The lock file (the runtime lock file for a reader of a folder without one).

    Raises:
        FolderBusyError: another run holds the lock and the :class:`LockConfig` in force
            does not wait (longer); the message names the folder and the holder.
        ReadOnlyFolderError: a writer's lock on a folder this run cannot write.
        LockOrderError: ``level`` is not below the level of every lock this thread holds.
    """
    folder = Path(folder)
    _check_order(folder, level)
    fd, path = _open(folder, shared, Path(lock_path) if lock_path else folder / LOCK_NAME)
    writes_pid = not shared  # a writer's lock file is never the per-user runtime one
    try:
        _acquire(fd, fcntl.LOCK_SH if shared else fcntl.LOCK_EX, folder, path, shared)
        if writes_pid:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        stack = _held.__dict__.setdefault("stack", [])
        stack.append((folder, level))
        try:
            yield path
        finally:
            stack.pop()
            if writes_pid:
                os.ftruncate(fd, 0)
    finally:
        os.close(fd)


def remove_sibling_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporaries that killed runs of :func:`diffloc.io.atomic.atomic_directory`
    left beside ``folder`` (``.<name>.tmp-*``, ``.<name>.old-*``).

    Call it only while holding ``folder``'s lock at :func:`sibling_lock_path`.

    Returns:
        The removed paths.
    """
    folder = Path(folder)
    if not folder.parent.is_dir():
        return []
    prefixes = (f".{folder.name}.tmp-", f".{folder.name}.old-")
    removed = sorted(p for p in folder.parent.iterdir() if p.name.startswith(prefixes))
    for path in removed:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    return removed


def remove_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporary files and folders of killed runs anywhere under ``folder``.

    Call it only while holding the exclusive :func:`folder_lock` of ``folder``. Sub-folders
    that hold a lock file of their own are other writers' and are left alone.

    Args:
        folder: the folder.

    Returns:
        The removed paths.
    """
    removed = []
    for base, dirs, names in os.walk(folder):
        # A sub-folder with a lock of its own belongs to another writer (a stage folder inside).
        dirs[:] = [d for d in dirs if not (Path(base) / d / LOCK_NAME).exists()]
        for name in [*dirs, *names]:
            if _TEMPORARY.match(name):
                path = Path(base) / name
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path, ignore_errors=True)
                else:
                    path.unlink(missing_ok=True)
                removed.append(path)
        dirs[:] = [d for d in dirs if not _TEMPORARY.match(d)]
    return removed
