"""experiments/crossmodal_breakdown.py: each query's outcome is the first stage that decides it."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

from diffloc.io.identity import identity
from diffloc.io.npz import write_npz
from tests.localization_records import sequence_localization

ROOT = Path(__file__).resolve().parents[1]


def load_script():
    spec = importlib.util.spec_from_file_location(
        "crossmodal_breakdown", ROOT / "experiments/crossmodal_breakdown.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_query_gets_the_first_stage_that_decides_it():
    script = load_script()
    # columns: success, accepted, accepted without photometric, inliers, correct,
    # reference near, renders near, refused as a storey alias, accepted on the second look
    cases = {
        "localized": (True, True, True, 300, True, True, 3, False, False),
        "wrong accepted": (True, True, True, 300, False, False, 3, False, False),
        "localized: second look": (True, False, False, 120, True, True, 3, False, True),
        "wrong accepted: second look": (True, False, False, 120, False, True, 3, False, True),
        "right pose refused: storey alias": (True, True, True, 300, True, True, 3, True, False),
        "wrong pose refused: storey alias": (True, False, False, 120, False, False, 3, True, True),
        "no pose": (False, False, False, 0, False, True, 3, False, False),
        "right pose rejected: inliers": (True, False, False, 120, True, True, 3, False, False),
        "right pose rejected: coverage or rival": (
            *(True, False, False, 300, True, True, 3, False, False),
        ),
        "right pose rejected: photometric": (True, False, True, 300, True, True, 3, False, False),
        "wrong pose, no render near": (True, False, False, 90, False, False, 0, False, False),
        "wrong pose, far reference": (True, False, False, 90, False, False, 2, False, False),
        "wrong pose, near reference": (True, False, False, 90, False, True, 2, False, False),
    }
    assert tuple(cases) == script.OUTCOMES
    success, accepted, geometric, inliers, correct, near, renders, aliases, second = map(
        np.array, zip(*cases.values(), strict=True)
    )
    q = len(cases)
    loc = sequence_localization(
        q,
        success=success,
        accepted=accepted,
        num_matches=inliers + 100,
        num_points=inliers + 50,
        num_inliers=inliers,
        accepted_without_photometric=geometric,
    )
    # the tests each pose fails, as the replay gives them
    failed = [
        (),
        (),
        ("inliers",),
        ("inliers", "coverage"),
        (),
        ("inliers",),
        (),
        ("inliers", "coverage"),
        ("rival",),
        ("photometric",),
        ("inliers",),
        ("coverage",),
        ("photometric", "rival"),
    ]
    verdicts = script.outcomes(loc, accepted, correct, near, renders, failed, aliases, second)
    assert verdicts == list(cases)
    # without the second look its queries are the refusals they were
    first = script.outcomes(loc, accepted, correct, near, renders, failed, aliases)
    assert first[2:4] == ["right pose rejected: inliers", "wrong pose, near reference"]


def _localization(folder: Path) -> Path:
    """A stand-in ``localize_query_same/localization.npz`` (only its identity is read)."""
    path = folder / "localize_query_same" / "localization.npz"
    path.parent.mkdir()
    path.write_bytes(b"the localisation's record")
    return path


def _record(path: Path, outputs: dict) -> None:
    """A stage record at ``path`` whose key names the localisation ``outputs`` it tested."""
    path.write_text(json.dumps({"stage": {"key": {"inputs": {"localization": outputs}}}}))


def test_storey_aliases_count_only_when_the_test_ran_on_this_localisation(tmp_path: Path):
    script = load_script()
    localization = _localization(tmp_path)
    alias = tmp_path / "alias_query_same"
    alias.mkdir()
    with (alias / "alias.npz").open("wb") as handle:
        write_npz(
            handle,
            {
                "query": np.array([0, 2]),
                "own_inliers": np.array([300, 200]),
                "alias_inliers": np.array([[10], [260]]),
                "alias_distance_m": np.array([[3.0], [3.0]]),
                "alias": np.array([False, True]),
                "cpu_ms": np.zeros(2),
            },
        )

    def tested(outputs: dict, looked: bool = False) -> list[bool]:
        _record(alias / "alias.json", outputs)
        return script.storey_aliases(tmp_path, "query_same", 3, looked).tolist()

    own = {"localization.npz": identity(localization)}
    assert tested(own) == [False, False, True]
    # after a re-render check the test saw other answers; another localisation, other poses
    second = tmp_path / "rerender_query_same" / "rerender.npz"
    second.parent.mkdir()
    second.write_bytes(b"the second look's record")
    after = {**own, "rerender.npz": identity(second)}
    assert tested(after) == [False] * 3
    assert tested({"localization.npz": {**own["localization.npz"], "size": 1}}) == [False] * 3
    # the breakdown applies that second look: the test saw its answers
    assert tested(after, looked=True) == [False, False, True]
    assert tested(own, looked=True) == [False] * 3


def test_the_second_look_is_read_only_when_it_looked_at_this_localisation(tmp_path: Path):
    script = load_script()
    localization = _localization(tmp_path)
    folder = tmp_path / "rerender_query_same"
    folder.mkdir()
    assert script.second_look(tmp_path, "query_same") is None  # no check ran
    with (folder / "rerender.npz").open("wb") as handle:
        write_npz(
            handle,
            {
                "query": np.array([1]),
                "success": np.array([True]),
                "T_wc": np.eye(4)[None],
                "num_matches": np.array([400]),
                "num_points": np.array([390]),
                "num_inliers": np.array([350]),
                "coverage": np.array([1.0]),
                "plane_share": np.array([0.4]),
                "photometric": np.array([0.8]),
                "failed": np.zeros((1, len(script.REPLAYED_TESTS)), dtype=bool),
                "accepted": np.array([True]),
                "wall_ms": np.array([30.0]),
                "cpu_ms": np.array([20.0]),
            },
        )

    _record(folder / "rerender.json", {"localization.npz": identity(localization)})
    assert script.second_look(tmp_path, "query_same").query.tolist() == [1]
    other = {"localization.npz": {**identity(localization), "size": 1}}  # another localisation
    _record(folder / "rerender.json", other)
    assert script.second_look(tmp_path, "query_same") is None
