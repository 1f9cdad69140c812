"""Folder locks between processes, and removal of what killed writers left behind.

Every stage that writes into a folder holds :func:`folder_lock` on it (exclusive) for its whole
run; a stage that reads another stage's folder holds it shared while it reads. A second run on
the same folder waits (saying so once on stderr) instead of mixing its files with the first
one's. The lock is ``fcntl.flock`` on the hidden file ``.diffloc.lock`` in the folder: the
kernel drops it when its process dies, so a killed run never leaves the folder locked.

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
import fcntl
import os
import re
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path

__all__ = ["LOCK_NAME", "folder_lock", "remove_temporaries"]

LOCK_NAME = ".diffloc.lock"
"""The lock file inside a locked folder."""

_TEMPORARY = re.compile(r"^\.(tmp-.*|.+\.tmp-.*|.+\.tmp(\.[A-Za-z0-9]+)?|.+\.old-.*)$")
"""Hidden names of temporary files and folders written by :mod:`diffloc.io.atomic` and
:mod:`diffloc.pipeline.stage`."""


def announce_wait(message: str) -> None:
    """Tell the user a run is waiting for a lock (stderr; tests replace it)."""
    print(f"waiting: {message}", file=sys.stderr, flush=True)


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike, shared: bool = False) -> Iterator[Path]:
    """Hold the lock of ``folder`` (created if missing) for the ``with`` block.

    Args:
        folder: the folder to lock.
        shared: a reader's lock (many readers together, no writer); else a writer's lock.

    Yields:
        The lock file.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_NAME
    mode = fcntl.LOCK_SH if shared else fcntl.LOCK_EX
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, mode | fcntl.LOCK_NB)
        except BlockingIOError:
            verb = "read" if shared else "write"
            announce_wait(
                f"{folder} is in use by another diffloc run (lock {path}); this run will "
                f"{verb} it when that one finishes (stop the other run to go on now)"
            )
            fcntl.flock(fd, mode)
        yield path
    finally:
        os.close(fd)


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
