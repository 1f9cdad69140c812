"""Atomic file and folder writes: complete or absent, never half-written."""

from pathlib import Path

import pytest

from diffloc.io.atomic import atomic_directory, atomic_open, atomic_write_bytes, atomic_write_text


def test_write_bytes_and_text_round_trip(tmp_path: Path):
    atomic_write_bytes(tmp_path / "sub" / "a.bin", b"\x00\x01abc")
    atomic_write_text(tmp_path / "b.txt", "line 1\nline 2\n")
    assert (tmp_path / "sub" / "a.bin").read_bytes() == b"\x00\x01abc"
    assert (tmp_path / "b.txt").read_bytes() == b"line 1\nline 2\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.txt", "sub"]


def test_overwrite_replaces_whole_file(tmp_path: Path):
    atomic_write_text(tmp_path / "a.txt", "a much longer old content")
    atomic_write_text(tmp_path / "a.txt", "new")
    assert (tmp_path / "a.txt").read_text() == "new"


def test_failed_write_leaves_old_file_and_no_temp(tmp_path: Path):
    target = tmp_path / "a.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError, match="boom"), atomic_open(target, "w") as handle:
        handle.write("half")
        raise RuntimeError("boom")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_atomic_directory_moves_complete_folder(tmp_path: Path):
    final = tmp_path / "out" / "dataset"
    with atomic_directory(final) as tmp:
        assert tmp.parent == final.parent and tmp != final and not final.exists()
        (tmp / "a.txt").write_text("x")
    assert (final / "a.txt").read_text() == "x"
    assert [p.name for p in final.parent.iterdir()] == ["dataset"]


def test_atomic_directory_refuses_existing_before_doing_work(tmp_path: Path):
    final = tmp_path / "dataset"
    final.mkdir()
    ran = []
    with pytest.raises(FileExistsError, match="overwrite"), atomic_directory(final):
        ran.append(True)
    assert not ran


def test_atomic_directory_overwrite_replaces_only_when_complete(tmp_path: Path):
    final = tmp_path / "dataset"
    final.mkdir()
    (final / "old.txt").write_text("old")
    with pytest.raises(RuntimeError), atomic_directory(final, overwrite=True) as tmp:
        (tmp / "new.txt").write_text("new")
        raise RuntimeError("failed midway")
    assert [p.name for p in final.iterdir()] == ["old.txt"]
    with atomic_directory(final, overwrite=True) as tmp:
        (tmp / "new.txt").write_text("new")
    assert [p.name for p in final.iterdir()] == ["new.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["dataset"]


def test_atomic_directory_failure_midway_leaves_nothing(tmp_path: Path):
    final = tmp_path / "dataset"
    with pytest.raises(KeyboardInterrupt), atomic_directory(final) as tmp:
        (tmp / "seq").mkdir()
        (tmp / "seq" / "000000.png").write_bytes(b"partial")
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []
