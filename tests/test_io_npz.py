"""``.npz`` archives: deterministic bytes, safe reading, and the named fields of a record."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

from diffloc.io.npz import read_npz_archive, read_npz_fields, write_npz


def _write(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    with path.open("wb") as handle:
        write_npz(handle, arrays)
    return path


def test_the_same_arrays_give_the_same_bytes_and_read_back(tmp_path: Path):
    arrays = {"a": np.arange(5, dtype=np.int64), "b": np.eye(3)}
    first, second = io.BytesIO(), io.BytesIO()
    write_npz(first, arrays)
    write_npz(second, arrays)
    assert first.getvalue() == second.getvalue()
    back = read_npz_archive(_write(tmp_path / "x.npz", arrays))
    assert back.keys() == arrays.keys()
    for name, values in arrays.items():
        np.testing.assert_array_equal(back[name], values)


def test_the_fields_asked_for_are_read_and_others_ignored(tmp_path: Path):
    path = _write(tmp_path / "x.npz", {"a": np.ones(2), "b": np.zeros(3), "extra": np.ones(1)})
    fields = read_npz_fields(path, ["b", "a"], "run it again")
    assert list(fields) == ["b", "a"] and fields["b"].shape == (3,)


def test_missing_fields_are_named_with_the_file_and_the_remedy(tmp_path: Path):
    path = _write(tmp_path / "x.npz", {"a": np.ones(2)})
    with pytest.raises(ValueError, match=r"x\.npz: no b, c; run the stage again"):
        read_npz_fields(path, ["a", "c", "b"], "run the stage again")


def test_a_file_that_is_no_archive_is_refused(tmp_path: Path):
    path = tmp_path / "x.npz"
    path.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a readable .npz archive"):
        read_npz_fields(path, ["a"], "run it again")
