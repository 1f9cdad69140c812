"""Per-frame exposure files: ``timestamp exposure`` per line (simulator ground truth).

The simulator writes ``<sequence>/exposure.txt`` when a sequence runs with auto exposure: one
line per image, the frame's timestamp (seconds) and the factor that multiplied its linear
radiance. Lines starting with ``#`` are comments. It is ground truth: the library never reads
it to build a map; experiments read it to score exposure estimates and for oracle ablations.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from diffloc.checks import check_shape
from diffloc.io.atomic import atomic_write_text

__all__ = ["EXPOSURE_FILE", "read_exposures", "write_exposures"]

EXPOSURE_FILE = "exposure.txt"
"""Name of the exposure file inside a sequence folder."""

_HEADER = "# timestamp exposure"


def write_exposures(path: str | os.PathLike, timestamps: np.ndarray, exposures: np.ndarray) -> None:
    """Write (N,) timestamps and (N,) positive exposures atomically.

    Raises:
        ValueError: shapes differ, values are not finite, or an exposure is not positive.
    """
    timestamps = np.asarray(timestamps, dtype=np.float64)
    exposures = np.asarray(exposures, dtype=np.float64)
    check_shape(timestamps, "N", "timestamps")
    check_shape(exposures, f"{timestamps.shape[0]}", "exposures")
    if not (np.isfinite(timestamps).all() and np.isfinite(exposures).all()):
        raise ValueError(f"{path}: timestamps and exposures must be finite")
    if (exposures <= 0).any():
        raise ValueError(f"{path}: exposures must be > 0")
    lines = [_HEADER] + [
        f"{t!r} {e!r}" for t, e in zip(timestamps.tolist(), exposures.tolist(), strict=True)
    ]
    atomic_write_text(path, "\n".join(lines) + "\n")


def read_exposures(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read an exposure file.

    Returns:
        timestamps (N,) and exposures (N,), float64.

    Raises:
        FileNotFoundError: no such file (the sequence was simulated without auto exposure).
        ValueError: a line is not two numbers, or an exposure is not finite and positive; the
            message names the file and line.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: no exposure file (only sequences simulated with auto exposure have one)"
        )
    rows = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = text.split()
        try:
            values = [float(f) for f in fields]
        except ValueError:
            values = []
        if len(values) != 2 or not np.isfinite(values).all() or values[1] <= 0:
            raise ValueError(
                f"{path}:{number}: expected 'timestamp exposure' with a finite exposure > 0, "
                f"got {line!r}"
            )
        rows.append(values)
    array = np.asarray(rows, dtype=np.float64).reshape(-1, 2)
    return array[:, 0], array[:, 1]
