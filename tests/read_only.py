"""A dataset folder made to behave as a read-only mount, for tests and ``experiments/``.

We run as root here, and root ignores permission bits, so ``chmod`` cannot make a folder
read-only; a read-only mount needs privileges the test runner lacks. :func:`read_only` instead
makes every call that would create, replace or delete something under the folder fail with
``EROFS``, as a read-only mount does (``os.open`` with a write flag, ``os.mkdir``,
``os.replace``, ``os.rename``, ``os.unlink``, ``os.rmdir``). Writes through other calls are
not caught: tests compare :func:`snapshot` of the folder before and after too.
"""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Iterator
from pathlib import Path
from unittest import mock

WRITES = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND
GUARDED = ("mkdir", "replace", "rename", "unlink", "rmdir")


@contextlib.contextmanager
def read_only(root: Path) -> Iterator[None]:
    """Make ``root`` behave as a read-only mount for the ``with`` block."""
    inside = str(Path(root).resolve()) + os.sep

    def under(path: object) -> bool:
        if not isinstance(path, str | bytes | os.PathLike):
            return False
        return str(Path(os.fsdecode(path)).resolve()).startswith(inside)

    def refuse(path: object) -> None:
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fsdecode(path))

    real_open = os.open

    def fake_open(path, flags, *args, **kwargs):
        if flags & WRITES and under(path):
            refuse(path)
        return real_open(path, flags, *args, **kwargs)

    def guard(real):
        def fake(path, *args, **kwargs):
            if under(path) or (args and under(args[0])):
                refuse(path)
            return real(path, *args, **kwargs)

        return fake

    with contextlib.ExitStack() as patches:
        patches.enter_context(mock.patch.object(os, "open", fake_open))
        for name in GUARDED:
            patches.enter_context(mock.patch.object(os, name, guard(getattr(os, name))))
        yield


def snapshot(root: Path) -> dict[str, tuple[int, int]]:
    """Size and mtime of every file and folder under ``root`` (hidden ones included)."""
    return {
        p.relative_to(root).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in Path(root).rglob("*")
    }
