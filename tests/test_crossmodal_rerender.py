"""The re-render check's record: applying it to a localisation, and its bad settings."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from diffloc.pipeline.crossmodal_pose_checks import RerenderConfig
from diffloc.pipeline.crossmodal_replay import REPLAYED_TESTS
from diffloc.pipeline.crossmodal_rerender import SequenceRerender, rerender_stage
from diffloc.pipeline.crossmodal_stage import SequenceLocalization
from diffloc.reloc.rendered import RenderedLocalizerConfig


def _pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def _localization() -> SequenceLocalization:
    """Five queries: four with a pose found (0, 1, 3, 4), one accepted (4), three refused."""
    arrays = {f.name: np.zeros(5) for f in fields(SequenceLocalization)}
    return SequenceLocalization(
        **{
            **arrays,
            "T_wc": np.stack([_pose(x) for x in (1.0, 2.0, 0.0, 4.0, 5.0)]),
            "success": np.array([True, True, False, True, True]),
            "accepted": np.array([False, False, False, False, True]),
            "accepted_without_photometric": np.array([False, False, False, False, True]),
            "num_inliers": np.array([200, 90, 0, 180, 300]),
            "time_ms": np.full(5, 100.0),
        }
    )


def _check(failed: list[list[str]]) -> SequenceRerender:
    """Re-renders of the refused queries 0, 1, 3: 0 and 1 find a pose, 3 none; ``failed`` per
    query."""
    flags = np.array([[test in f for test in REPLAYED_TESTS] for f in failed])
    success = np.array([True, True, False])
    return SequenceRerender(
        query=np.array([0, 1, 3]),
        success=success,
        T_wc=np.stack([_pose(1.1), _pose(2.2), np.eye(4)]),
        num_matches=np.array([400, 300, 0]),
        num_points=np.array([390, 290, 0]),
        num_inliers=np.array([350, 250, 0]),
        coverage=np.array([1.0, 0.9, 0.0]),
        plane_share=np.array([0.4, 0.5, np.nan]),
        photometric=np.array([0.8, 0.7, np.nan]),
        failed=flags,
        accepted=success & ~flags.any(axis=1),
        wall_ms=np.array([30.0, 40.0, 50.0]),
        cpu_ms=np.array([20.0, 30.0, 40.0]),
    )


def test_applying_the_check_takes_its_poses_and_verdicts():
    loc = _localization()
    checked = _check([["rival"], [], []])
    out = checked.apply(loc)
    # 0 refused (a rival), 1 accepted at its new pose, 3 refused (no pose on the re-render),
    # 4 (accepted, not looked at again) as it was
    assert out.accepted.tolist() == [False, True, False, False, True]
    np.testing.assert_allclose(out.T_wc[:, 0, 3], [1.1, 2.2, 0.0, 4.0, 5.0])
    assert out.num_inliers.tolist() == [350, 250, 0, 180, 300]
    assert out.accepted_without_photometric.tolist() == [False, True, False, False, True]
    assert out.time_ms.tolist() == [130.0, 140.0, 100.0, 150.0, 100.0]
    assert loc.accepted.tolist() == [False, False, False, False, True]  # the record is kept
    assert loc.T_wc[1, 0, 3] == 2.0


def test_a_pose_failing_only_the_photometric_test_counts_as_accepted_without_it():
    out = _check([["photometric"], ["inliers", "photometric"], []]).apply(_localization())
    assert out.accepted.tolist() == [False, False, False, False, True]
    assert out.accepted_without_photometric.tolist() == [True, False, False, False, True]


def test_an_archive_without_an_array_is_refused_with_its_name(tmp_path: Path):
    path = tmp_path / "rerender.npz"
    np.savez(path, query=np.zeros(1, dtype=np.int64))
    with pytest.raises(ValueError, match="rerender.npz: no T_wc"):
        SequenceRerender.load(path)


def test_a_map_that_cannot_be_rendered_at_a_pose_is_refused():
    with pytest.raises(ValueError, match="not one of the maps it can check"):
        RerenderConfig(maps=["images"])
    with pytest.raises(ValueError, match="runs on map=tls"):
        rerender_stage(
            Path("."),
            "images",
            "query_same",
            (None, None),
            (None, None, None),
            RenderedLocalizerConfig(),
        )


def test_the_check_needs_the_localisers_validation():
    with pytest.raises(ValueError, match="validation"):
        rerender_stage(
            Path("."),
            "mesh",
            "query_same",
            (None, None),
            (None, None, None),
            RenderedLocalizerConfig(validation=None),
        )
