"""Reading ``.npz`` archives safely: no pickles, and every failure a ``ValueError``."""

from __future__ import annotations

import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

__all__ = ["read_npz_archive"]


def read_npz_archive(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """All arrays of an ``.npz`` file, loaded with ``allow_pickle=False``.

    Args:
        path: the archive (its existence is the caller's check, for a message that names
            what the file should have been).

    Returns:
        Entry name -> array.

    Raises:
        ValueError: an unreadable, truncated or corrupt archive, a single ``.npy`` array, or
            pickled (object) entries; the message names the file.
    """
    path = Path(path)
    try:
        loaded = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path}: not a readable .npz archive ({exc})") from exc
    if not isinstance(loaded, np.lib.npyio.NpzFile):
        raise ValueError(f"{path}: not an .npz archive (it holds a single .npy array)")
    try:
        with loaded:
            return {name: loaded[name] for name in loaded.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as exc:
        raise ValueError(f"{path}: corrupt .npz archive ({exc})") from exc
