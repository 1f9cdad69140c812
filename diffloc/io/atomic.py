"""Atomic file and folder writes: readers never see a half-written file or dataset.

Files are written to a temporary file in the destination folder and renamed over the final
name with :func:`os.replace` (atomic on POSIX within one file system). Folders are built under
a temporary name next to their destination and renamed into place once complete. ``fsync`` is
not called: the guarantee is "complete or absent", not durability across a power cut.
"""

from __future__ import annotations

import contextlib
import functools
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

__all__ = ["atomic_directory", "atomic_open", "atomic_write_bytes", "atomic_write_text"]


@functools.cache
def _umask() -> int:
    """The process umask (read once; ``os.umask`` can only be read by setting it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _remove_quietly(path: Path) -> None:
    with contextlib.suppress(FileNotFoundError):
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb", encoding: str = "utf-8") -> Iterator[IO]:
    """Open a temporary file that replaces ``path`` when the ``with`` block succeeds.

    Missing parent folders are created. If the block raises, the temporary file is deleted and
    ``path`` is left untouched.

    Args:
        path: final file path.
        mode: ``"wb"`` or ``"w"``.
        encoding: text encoding for ``mode="w"``.

    Yields:
        The open file object.

    Example:
        >>> with atomic_open("a.txt", "w") as f:
        ...     f.write("hello")
        5
        >>> Path("a.txt").read_text()
        'hello'
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_open mode must be 'wb' or 'w', got {mode!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    tmp = Path(tmp_name)
    try:
        if mode == "wb":
            handle: IO = os.fdopen(fd, "wb")
        else:
            handle = os.fdopen(fd, "w", encoding=encoding, newline="")
        with handle:
            yield handle
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        _remove_quietly(tmp)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder + rename).

    Args:
        path: destination; missing parent folders are created.
        data: the file content.
    """
    with atomic_open(path, "wb") as handle:
        handle.write(data)


def atomic_write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> None:
    """Write ``text`` to ``path`` atomically. Newlines are written as given (no translation).

    Args:
        path: destination; missing parent folders are created.
        text: the file content.
        encoding: text encoding.
    """
    atomic_write_bytes(path, text.encode(encoding))


@contextlib.contextmanager
def atomic_directory(final_dir: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Build a folder under a temporary name and move it to ``final_dir`` only when complete.

    The temporary folder is created next to ``final_dir`` (same file system, so the final
    rename is atomic). If the ``with`` block raises (including ``KeyboardInterrupt``), the
    temporary folder is deleted and ``final_dir`` is untouched.

    Args:
        final_dir: where the finished folder ends up; its parent is created if missing.
        overwrite: replace an existing ``final_dir``. The old folder is removed only after the
            new one is complete; there is a short window between moving the old folder aside
            and moving the new one in.

    Yields:
        The (empty) temporary folder to write into.

    Raises:
        FileExistsError: ``final_dir`` exists and ``overwrite`` is false (raised before the
            block runs, and again if it appeared while the block ran).

    Example:
        >>> with atomic_directory("dataset") as tmp:
        ...     (tmp / "a.txt").write_text("x")
        ...     Path("dataset").exists()  # not yet: renamed into place on success
        1
        False
        >>> sorted(p.name for p in Path("dataset").iterdir())
        ['a.txt']
    """
    final_dir = Path(final_dir)
    if final_dir.exists() and not overwrite:
        raise FileExistsError(f"{final_dir} already exists (pass overwrite=True to replace it)")
    final_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=final_dir.parent, prefix=f".{final_dir.name}.tmp-"))
    try:
        os.chmod(tmp, 0o777 & ~_umask())
        yield tmp
        if final_dir.exists() or final_dir.is_symlink():
            if not overwrite:
                raise FileExistsError(f"{final_dir} appeared while it was being written")
            old = Path(tempfile.mkdtemp(dir=final_dir.parent, prefix=f".{final_dir.name}.old-"))
            old.rmdir()
            os.replace(final_dir, old)
            try:
                os.replace(tmp, final_dir)
            except BaseException:
                os.replace(old, final_dir)
                raise
            _remove_quietly(old)
        else:
            os.replace(tmp, final_dir)
    except BaseException:
        _remove_quietly(tmp)
        raise
