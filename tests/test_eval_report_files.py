"""Experiment result files: Markdown + JSON pairs and benchmark JSON, written whole or not."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from diffloc.eval.report_files import write_benchmark, write_report


def test_report_pair_round_trips_and_replaces_the_suffix(tmp_path: Path) -> None:
    rows = [{"sequence": "query_same", "recall": 0.95}]
    md, js = write_report(tmp_path / "deep" / "table.json", "| a |", rows)
    assert (md, js) == (tmp_path / "deep" / "table.md", tmp_path / "deep" / "table.json")
    assert md.read_text() == "| a |\n"
    assert json.loads(js.read_text()) == rows


def test_unserialisable_report_leaves_the_previous_pair_untouched(tmp_path: Path) -> None:
    write_report(tmp_path / "table", "old\n", {"n": 1})
    with pytest.raises(TypeError, match="not JSON serializable"):
        write_report(tmp_path / "table", "new\n", {"n": object()})
    assert (tmp_path / "table.md").read_text() == "old\n"
    assert json.loads((tmp_path / "table.json").read_text()) == {"n": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table.json", "table.md"]


def test_benchmark_line_equals_the_file(tmp_path: Path) -> None:
    out = tmp_path / "results" / "bench.json"
    line = write_benchmark(out, {"b": 2, "a": [1.5, None]})
    assert "\n" not in line
    assert json.loads(line) == json.loads(out.read_text()) == {"b": 2, "a": [1.5, None]}
    with pytest.raises(TypeError):
        write_benchmark(out, {"a": {1, 2}})
    assert json.loads(out.read_text())["b"] == 2
