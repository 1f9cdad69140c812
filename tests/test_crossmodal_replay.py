"""The recorded validation evidence of task=crossmodal and its replay with other thresholds."""

from __future__ import annotations

import importlib.util
import json
import sys
from dataclasses import asdict, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from diffloc.io.npz import write_npz
from diffloc.pipeline.crossmodal_replay import (
    recorded_evidence,
    recorded_validation,
    replay_validation,
)
from diffloc.pipeline.crossmodal_stage import SequenceLocalization, candidate_arrays
from diffloc.reloc.rendered import RenderedCandidate, accept_pose, single_image_validation
from diffloc.reloc.validation import PoseEvidence
from tests.localization_records import sequence_localization

ROOT = Path(__file__).resolve().parents[1]


def _candidate(reference: int, x: float, inliers: int, coverage: float) -> RenderedCandidate:
    T = torch.eye(4, dtype=torch.float64)
    T[:3, 3] = torch.tensor([x, 1.0, 0.5], dtype=torch.float64)
    return RenderedCandidate(
        reference, T, inliers > 0, inliers + 40, inliers + 20, inliers, coverage, 1.0
    )


# Per query: the candidates tried (reference, x, inliers, coverage), the chosen reference and
# the photometric consistency.
QUERIES = [
    ([(4, 0.0, 300, 0.75)], 4, 0.8),  # passes the default tests
    ([(1, 0.0, 300, 0.5)], 1, 0.8),  # coverage 8 of 16 cells
    ([(2, 0.0, 260, 0.75), (9, 6.0, 200, 0.75)], 2, 0.8),  # a rival 6 m away, 77 % inliers
    ([(3, 0.0, 120, 0.75)], 3, 0.8),  # too few inliers
    ([(5, 0.0, 300, 0.75)], 5, 0.1),  # photometric
    ([(6, 0.0, 0, 0.0)], 6, float("nan")),  # no pose
    ([], -1, float("nan")),  # nothing retrieved
]


def _localization() -> tuple[SequenceLocalization, list]:
    answers = []
    for tried, chosen, _ in QUERIES:
        candidates = tuple(_candidate(*c) for c in tried)
        retrieved = torch.tensor([c.reference for c in candidates], dtype=torch.int64)
        answers.append(
            SimpleNamespace(
                reference=chosen,
                candidates=candidates,
                retrieved=retrieved,
                rerank_matches=torch.full_like(retrieved, -1),
            )
        )
    q = len(QUERIES)
    bests = [next((c for c in a.candidates if c.reference == a.reference), None) for a in answers]
    loc = sequence_localization(
        q,
        frames=np.arange(q) * 4,
        T_wc=np.stack([np.eye(4) if b is None else b.T_wc.numpy() for b in bests]),
        success=np.array([b is not None and b.success for b in bests]),
        reference=np.array([a.reference for a in answers]),
        num_inliers=np.array([0 if b is None else b.num_inliers for b in bests]),
        photometric=np.array([p for _, _, p in QUERIES]),
        **candidate_arrays(answers),
    )
    return loc, answers


def test_the_recorded_candidates_rebuild_the_choice_and_its_rivals():
    loc, answers = _localization()
    for q, answer in enumerate(answers):
        best, tried = loc.candidates(q)
        assert [c.reference for c in tried] == [c.reference for c in answer.candidates]
        assert best.reference == (answer.reference if answer.candidates else -1)
        for got, want in zip(tried, answer.candidates, strict=True):
            assert (got.success, got.num_inliers, got.num_points, got.coverage) == (
                want.success,
                want.num_inliers,
                want.num_points,
                want.coverage,
            )
            assert torch.equal(got.T_wc[:3, 3], want.T_wc[:3, 3])


def test_the_replay_gives_the_localisers_verdict_and_every_failed_test():
    loc, answers = _localization()
    validation = replace(single_image_validation(), min_photometric=0.4)
    accepted, failed = replay_validation(recorded_evidence(loc), validation)
    expected = [
        accept_pose(*loc.candidates(q), validation, float(loc.photometric[q]))
        for q in range(len(answers))
    ]
    assert accepted.tolist() == expected == [True, False, False, False, False, False, False]
    assert failed == [(), ("coverage",), ("rival",), ("inliers",), ("photometric",), (), ()]
    # looser thresholds, scored without relocalising
    loose = replace(
        validation, theta_in=100, min_coverage=0.5, ambiguity_ratio=0.8, min_photometric=None
    )
    accepted, failed = replay_validation(recorded_evidence(loc), loose)
    assert accepted.tolist() == [True, True, True, True, True, False, False]


def test_real_references_get_their_own_photometric_threshold():
    loc, _ = _localization()
    validation = replace(single_image_validation(), min_photometric=0.05)
    real = np.zeros(10, dtype=bool)
    real[5] = True  # query 4's reference, photometric 0.1
    evidence = recorded_evidence(loc)
    assert replay_validation(evidence, validation, real, 0.7)[1][4] == ("photometric",)
    assert replay_validation(evidence, validation, real, None)[1][4] == ()
    with pytest.raises(ValueError, match="real flags"):
        replay_validation(evidence, validation, None, 0.7)


def test_the_run_thresholds_come_from_its_stage_record(tmp_path):
    validation = replace(single_image_validation(), min_coverage=0.5)
    localizer = {"validation": asdict(validation), "min_photometric_real": 0.7}
    record = {"stage": {"key": {"config": {"localizer": localizer}}}}
    (tmp_path / "localize.json").write_text(json.dumps(record))
    assert recorded_validation(tmp_path) == (validation, 0.7)
    localizer["validation"] = None
    (tmp_path / "localize.json").write_text(json.dumps(record))
    with pytest.raises(ValueError, match="no validation"):
        recorded_validation(tmp_path)


def _load_choice_script():
    name = "crossmodal_threshold_choice"
    spec = importlib.util.spec_from_file_location(name, ROOT / f"experiments/{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_the_choice_takes_the_most_right_poses_without_more_wrong_ones():
    script = _load_choice_script()

    def evidence(inliers: int, coverage: float) -> tuple[int, PoseEvidence]:
        position = torch.zeros(3, dtype=torch.float64)
        return 0, PoseEvidence(position, inliers, inliers + 20, coverage, ((inliers, 0.0),), 0.8)

    # right poses at coverage 0.5 and 0.5625 (rejected by the run's 0.625), a wrong one at
    # 0.375: the loosest coverage that admits no wrong pose is 0.4375, the rule's choice is the
    # least change from 0.625 that admits both right poses, 0.5
    run = script.Recorded(
        "query_same",
        [evidence(300, 0.75), evidence(300, 0.5), evidence(300, 0.5625), evidence(300, 0.375)],
        np.array([True, True, True, False]),
        replace(single_image_validation(), min_photometric=0.4),
        None,
        None,
    )
    best, points = script.choose([run])
    assert best["setting"]["min_coverage"] == 0.5
    assert (best["right"], best["wrong"]) == (3, 0)
    unchanged = {k: v for k, v in best["setting"].items() if k != "min_coverage"}
    assert unchanged == {
        "theta_in": 150,
        "min_inlier_ratio": 0.0,
        "ambiguity_ratio": 0.7,
        "min_photometric": 0.4,
    }
    assert len(points) == np.prod([len(v) for v in script.GRID.values()])
    step = script.margin([run], best["setting"])["min_coverage"]
    assert (step["value"], step["right"], step["wrong"]) == (0.4375, 3, 0)


def test_a_record_without_the_time_arrays_is_refused_by_name(tmp_path):
    loc, _ = _localization()
    arrays = {k: v for k, v in loc.__dict__.items() if k not in ("stage_ms", "cpu_ms")}
    path = tmp_path / "localization.npz"
    with path.open("wb") as handle:
        write_npz(handle, arrays)
    with pytest.raises(ValueError, match="localization.npz: no cpu_ms, stage_ms"):
        SequenceLocalization.load(path)
    with path.open("wb") as handle:
        write_npz(handle, loc.__dict__)
    assert np.array_equal(SequenceLocalization.load(path).stage_ms, loc.stage_ms)
