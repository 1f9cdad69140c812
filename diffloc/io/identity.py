"""The identity of a file or folder: its size and SHA-256, for content-keyed stage caches.

A stage records the identity of every input it read and of every output it wrote; a result is
reused only while those identities still hold (:mod:`diffloc.pipeline.stage`). A folder's
identity covers the relative path, size and hash of every file under it (hidden temporary
entries such as ``.tmp-*`` and lock files excluded), so two folders with the same files have
the same identity wherever they live.

Example:
    >>> from pathlib import Path
    >>> _ = Path("a.txt").write_text("hello")
    >>> identity("a.txt")  # doctest: +ELLIPSIS
    {'kind': 'file', 'size': 5, 'sha256': '2cf24dba...'}
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

__all__ = ["identity"]

_CHUNK = 1 << 20


def _file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def _folder_files(folder: Path) -> list[Path]:
    """Every regular file under ``folder`` (hidden entries skipped), sorted by relative path."""
    files = []
    for base, dirs, names in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        files += [Path(base) / n for n in names if not n.startswith(".")]
    return sorted(files, key=lambda p: p.relative_to(folder).as_posix())


def identity(path: str | os.PathLike) -> dict:
    """Size and SHA-256 of a file, or of every file under a folder.

    Args:
        path: a file or a folder.

    Returns:
        ``{"kind": "file", "size", "sha256"}`` or ``{"kind": "folder", "files", "size",
        "sha256"}`` (the hash of the sorted ``relative path, size, sha256`` lines).

    Raises:
        FileNotFoundError: ``path`` does not exist (the message names it).
    """
    path = Path(path)
    if path.is_file():
        return {"kind": "file", "size": path.stat().st_size, "sha256": _file_sha256(path)}
    if not path.is_dir():
        raise FileNotFoundError(f"{path} does not exist")
    lines, total = [], 0
    files = _folder_files(path)
    for file in files:
        size = file.stat().st_size
        total += size
        lines.append(f"{file.relative_to(path).as_posix()}\t{size}\t{_file_sha256(file)}\n")
    digest = hashlib.sha256("".join(lines).encode("utf-8")).hexdigest()
    return {"kind": "folder", "files": len(files), "size": total, "sha256": digest}
