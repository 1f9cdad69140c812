"""``experiments/render_density_table.py``: run folders, the tuning rule and the held-out rule."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location(
        "render_density_table", ROOT / "experiments" / "render_density_table.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _write_run(folder: Path, name: str, samples: int, views: int, accepted_wrong: dict) -> None:
    """A ``results.json`` with ``accepted_wrong[sequence] = (accepted, wrong)`` of 30 queries."""
    sequences = {}
    for sequence, (accepted, wrong) in accepted_wrong.items():
        sequences[sequence] = {
            "queries": 30,
            "accepted": accepted,
            "wrong_accepted": wrong,
            "precision": (accepted - wrong) / accepted if accepted else None,
            "rates": {"1m_30deg": (accepted - wrong) / 30},
            "retrieval_rate": 0.5,
            "nearest_render": {"render_near_rate": 0.9, "median_m": 0.4, "median_deg": 10.0},
            "time": {
                "median_cpu_ms": 300.0,
                "median_ms": 600.0,
                "mean_cpu_ms": 400.0,
                "candidates": {"median": 1.0, "mean": 2.5},
            },
        }
    results = {
        "loose_m": 1.0,
        "database_images": samples * views,
        "sequences": sequences,
        "stages": {
            "poses": {"poses": samples * views, "samples": samples},
            "database": {"seconds": 60.0, "cpu_seconds": 40.0},
            **{f"localize_{s}": {"load_average": [4.0, 4.0, 4.0]} for s in sequences},
        },
    }
    (folder / name).mkdir(parents=True)
    (folder / name / "results.json").write_text(json.dumps(results))


@pytest.fixture
def runs(tmp_path: Path) -> Path:
    """The mesh grid: 1 m / 4 views has the most right poses but one more wrong pose; 2 m / 8
    and 1 m / 8 tie on right poses at the default's precision, 2 m / 8 is the smaller database;
    a TLS run of the default alone does not take part in the choice."""
    cells = {
        "mesh_s2.0_v4": (100, 4, {"same": (20, 0), "reverse": (10, 0)}),
        "mesh_s2.0_v8": (100, 8, {"same": (22, 0), "reverse": (14, 0)}),
        "mesh_s1.0_v4": (200, 4, {"same": (25, 1), "reverse": (14, 0)}),
        "mesh_s1.0_v8": (200, 8, {"same": (21, 0), "reverse": (15, 0)}),
        "tls_s2.0_v4": (90, 4, {"same": (5, 0), "reverse": (1, 0)}),
        "notes": (1, 4, {}),  # not a run folder name: ignored
    }
    for name, (samples, views, seqs) in cells.items():
        _write_run(tmp_path, name, samples, views, seqs)
    return tmp_path


def test_runs_are_read_from_their_folders_in_order(runs):
    table = _script().read_runs(runs)
    assert [(r["map"], r["spacing_m"], r["views"]) for r in table] == [
        ("mesh", 2.0, 4),
        ("mesh", 2.0, 8),
        ("mesh", 1.0, 4),
        ("mesh", 1.0, 8),
        ("tls", 2.0, 4),
    ]
    assert table[1]["images"] == 800 and table[1]["render_cpu_s"] == 40.0
    assert table[2]["sequences"]["same"]["right"] == 24


def test_the_tuning_rule_keeps_the_default_precision_and_breaks_ties_by_size(runs):
    script = _script()
    with pytest.raises(SystemExit, match="every setting"):
        script.choose(script.read_runs(runs), ["mesh", "tls"])  # tls ran the default only
    choice = script.choose(script.read_runs(runs), ["mesh"])
    assert choice["maps"] == ["mesh"]
    scores = {tuple(s["setting"]): s for s in choice["scores"]}
    assert not scores[(1.0, 4)]["allowed"] and scores[(1.0, 4)]["right"] == 38
    assert scores[(2.0, 8)]["right"] == scores[(1.0, 8)]["right"] == 36
    assert choice["chosen"] == [2.0, 8]
    report = {"dataset": "d", "commands": ["cmd"], "note": "", "runs": [], "choice": choice}
    assert "(precision below default)" in script.markdown(report)
    assert "Chosen: 2 m, 8 views." in script.markdown(report)


def test_the_held_out_rule_needs_a_gain_and_no_loss(runs):
    script = _script()
    table = script.read_runs(runs)
    decision = script.decide(table, (2.0, 8))
    assert decision["replace_default"] and decision["maps"]["mesh"]["better"]
    worse = script.decide(table, (1.0, 4))  # precision 38/39 >= 95 %: allowed, and gains
    assert worse["replace_default"]
    _write_run(runs, "tls_s2.0_v8", 90, 8, {"same": (6, 0), "reverse": (0, 0)})  # loses one
    assert not script.decide(script.read_runs(runs), (2.0, 8))["replace_default"]


def test_a_run_with_the_wrong_view_count_is_refused(tmp_path):
    _write_run(tmp_path, "mesh_s2.0_v8", 10, 4, {"same": (1, 0)})
    with pytest.raises(ValueError, match="40 poses at 10 samples"):
        _script().read_runs(tmp_path)
