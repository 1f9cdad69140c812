"""``.npz`` archives: read safely (no pickles, every failure a ``ValueError``), written
deterministically."""

from __future__ import annotations

import os
import zipfile
import zlib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO

import numpy as np

__all__ = ["read_npz_archive", "read_npz_fields", "write_npz"]

_FIXED_DATE = (1980, 1, 1, 0, 0, 0)
"""The date of every entry written by :func:`write_npz` (the earliest a zip file can hold)."""


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


def read_npz_fields(
    path: str | os.PathLike, names: Sequence[str], remedy: str
) -> dict[str, np.ndarray]:
    """The arrays ``names`` of an ``.npz`` file (:func:`read_npz_archive`), e.g. the fields of a
    record dataclass; other entries are ignored.

    Args:
        path: the archive.
        names: the entries wanted.
        remedy: what to do when some are missing, for the message (e.g. "run the stage again").

    Raises:
        ValueError: an archive without some of ``names`` (the message names the file, the
            missing entries and ``remedy``), or any error of :func:`read_npz_archive`.
    """
    arrays = read_npz_archive(path)
    missing = sorted(set(names) - set(arrays))
    if missing:
        raise ValueError(f"{path}: no {', '.join(missing)}; {remedy}")
    return {name: arrays[name] for name in names}


def write_npz(handle: IO[bytes], arrays: Mapping[str, np.ndarray]) -> None:
    """Write arrays as an uncompressed ``.npz`` archive whose bytes depend only on the arrays.

    ``numpy.savez`` stamps every entry with the current time, so saving the same arrays twice
    gives different files; here every entry carries the same fixed date, so a stage run again
    writes the same bytes and its output identity (:mod:`diffloc.io.identity`) holds.

    Args:
        handle: a binary file open for writing.
        arrays: entry name -> array (no object arrays), written in this order.
    """
    with zipfile.ZipFile(handle, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
        for name, array in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_FIXED_DATE)
            info.external_attr = 0o644 << 16
            with archive.open(info, "w", force_zip64=True) as entry:
                np.lib.format.write_array(entry, np.asanyarray(array), allow_pickle=False)
