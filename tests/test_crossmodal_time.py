"""``experiments/crossmodal_time.py``: rows and tables from a run's ``results.json``."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from diffloc.reloc.stage_clock import STAGES

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location(
        "crossmodal_time", ROOT / "experiments" / "crossmodal_time.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _results() -> dict:
    time = {
        "median_ms": 640.0,
        "median_cpu_ms": 318.0,
        "mean_ms": 900.0,
        "mean_cpu_ms": 450.0,
        "candidates": {"median": 1.0, "mean": 4.1},
        "stages": {s: {"mean_ms": 20.0 + i, "mean_cpu_ms": 10.0 + i} for i, s in enumerate(STAGES)},
        "match_ms": 300.0,
        "match_cpu_ms": 185.0,
        "pnp_ms": 25.0,
    }
    entry = {
        "queries": 31,
        "accepted": 25,
        "wrong_accepted": 0,
        "precision": 1.0,
        "rates": {"0.25m_2deg": 0.5, "0.5m_5deg": 0.7, "1m_30deg": 25 / 31},
        "time": time,
    }
    return {
        "dataset": "data/indoor_seed0",
        "map": "mesh",
        "loose_m": 1.0,
        "sequences": {"query_same": entry},
        "stages": {"localize_query_same": {"load_average": [3.9, 4.0, 3.1]}},
    }


def test_rows_carry_the_rates_times_and_stages_of_each_sequence():
    script = _script()
    (row,) = script.rows("before", _results())
    assert (row["run"], row["sequence"], row["rate"]) == ("before", "query_same", 25 / 31)
    assert (row["median_ms"], row["median_cpu_ms"], row["match_cpu_ms"]) == (640.0, 318.0, 185.0)
    assert row["stage_cpu_ms"] == {s: 10.0 + i for i, s in enumerate(STAGES)}
    assert row["load_average"] == [3.9, 4.0, 3.1]
    text = script.markdown(
        {"title": "t", "commands": ["diffloc task=crossmodal"], "note": "", "rows": [row]}
    )
    assert text.startswith("# Time per query") and "diffloc task=crossmodal" in text
    assert "| before | query_same | 31 | 25 (0) | 100.0 % | 80.6 % | 640 | 318 | 1 / 4.1 |" in text
    assert "| before | query_same | 450 | 10 | 11 | 12 | 13 | 14 | 15 | 185 |" in text
