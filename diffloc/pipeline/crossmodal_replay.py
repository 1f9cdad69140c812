"""Replaying the validation of a recorded rendered-database localisation with other thresholds.

The localisation stage of ``diffloc task=crossmodal`` records per query every candidate it
tried (``candidate_*`` arrays of
:class:`~diffloc.pipeline.crossmodal_stage.SequenceLocalization`) and the photometric
consistency of the pose found: the whole evidence of the single-image validation. The
validation is a pure function of that evidence and the thresholds, so any
:class:`~diffloc.reloc.validation.ValidationConfig` can be scored without matching again: the
chosen candidate (the most inliers) does not depend on the validation, only the verdict does.

:func:`recorded_evidence` rebuilds the evidence once; :func:`replay_validation` gives the
verdict and, per query, every test the pose fails
(``"inliers"``: fewer than ``theta_in``; then those of
:meth:`~diffloc.reloc.validation.PoseValidator.failed_tests`), so a report can say which tests
reject right and wrong poses. :func:`recorded_validation` reads the thresholds a run used from
its stage record. Scoring a verdict (:func:`recorded_errors`, :func:`verdict_effect`) reads the
query ground truth, for scoring only.

Usage::

    loc = SequenceLocalization.load(folder / "localization.npz")
    validation, _ = recorded_validation(folder)
    accepted, failed = replay_validation(
        recorded_evidence(loc), replace(validation, min_coverage=0.5)
    )
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from diffloc.eval.metrics import PoseErrors, pose_errors
from diffloc.io.dataset import read_sequence
from diffloc.pipeline.crossmodal_stage import SequenceLocalization
from diffloc.reloc.rendered import pose_evidence, reference_validation
from diffloc.reloc.validation import (
    PLAUSIBILITY_TESTS,
    PoseEvidence,
    PoseValidator,
    ValidationConfig,
)

__all__ = [
    "REPLAYED_TESTS",
    "recorded_errors",
    "recorded_evidence",
    "recorded_validation",
    "replay_validation",
    "verdict_effect",
]

REPLAYED_TESTS = ("inliers", *PLAUSIBILITY_TESTS)
"""The names :func:`replay_validation` gives the tests, in the order it reports them."""


def recorded_validation(folder: Path) -> tuple[ValidationConfig, float | None]:
    """The validation thresholds and ``min_photometric_real`` a localisation stage ran with
    (its ``localize.json`` key), ``folder`` being ``<dataset>/crossmodal/<map>/localize_<seq>``.

    Raises:
        ValueError: the run had no validation (``validation: null`` accepts every pose).
    """
    record = json.loads((folder / "localize.json").read_text())
    localizer = record["stage"]["key"]["config"]["localizer"]
    if localizer["validation"] is None:
        raise ValueError(f"{folder}: the run had no validation to replay")
    return ValidationConfig(**localizer["validation"]), localizer["min_photometric_real"]


def recorded_evidence(loc: SequenceLocalization) -> list[tuple[int, PoseEvidence] | None]:
    """Per query, the reference and the validation's evidence of the pose found (``None``: no
    pose), rebuilt from the recorded candidates and photometric consistency as the localiser
    built it (:func:`~diffloc.reloc.rendered.pose_evidence`); computed once, replayed often."""
    evidence: list[tuple[int, PoseEvidence] | None] = []
    for q in range(len(loc.frames)):
        best, tried = loc.candidates(q)
        found = best.success
        photometric = float(loc.photometric[q])
        evidence.append(
            (best.reference, pose_evidence(best, tried, photometric)) if found else None
        )
    return evidence


def replay_validation(
    evidence: list[tuple[int, PoseEvidence] | None],
    validation: ValidationConfig,
    real: np.ndarray | None = None,
    min_photometric_real: float | None = None,
) -> tuple[np.ndarray, list[tuple[str, ...]]]:
    """The verdict of ``validation`` on each of Q recorded answers.

    Args:
        evidence: per query, :func:`recorded_evidence`.
        validation: single-image thresholds (``temporal=False``).
        real: (N,) bool per database image, a real image (``RenderedDatabase.real``); with
            ``min_photometric_real`` set, a pose from a real image needs that photometric
            consistency instead (as the localiser does).
        min_photometric_real: see ``real``.

    Returns:
        ``(accepted, failed)``: (Q,) bool, a pose was found and passes; per query the names
        (:data:`REPLAYED_TESTS`) of every test its pose fails (empty when accepted or when no
        pose was found).

    Raises:
        ValueError: a sequence-mode validation, or ``min_photometric_real`` without ``real``.

    Example (a pose of 100 inliers over 80 % of the image, a rival of 90 inliers 5 m away):
        >>> from dataclasses import replace
        >>> import torch
        >>> evidence = PoseEvidence(torch.zeros(3, dtype=torch.float64), 100, 150, 0.8,
        ...                         ((100, 0.0), (90, 5.0)), 0.6)
        >>> check = ValidationConfig(theta_in=150, theta_dist_m=1.0, temporal=False,
        ...                          ambiguity_ratio=0.7)
        >>> replay_validation([(3, evidence), None], check)
        (array([False, False]), [('inliers', 'rival'), ()])
        >>> replay_validation([(3, evidence)], replace(check, theta_in=60, ambiguity_ratio=None))
        (array([ True]), [()])
    """
    if validation.temporal:
        raise ValueError("replay_validation needs a single-image validation (temporal=False)")
    if min_photometric_real is not None and real is None:
        raise ValueError("min_photometric_real needs the database's real flags")
    accepted = np.zeros(len(evidence), dtype=bool)
    failed: list[tuple[str, ...]] = []
    plain = PoseValidator(validation)
    for q, answer in enumerate(evidence):
        if answer is None:
            failed.append(())
            continue
        reference, pose = answer
        config = reference_validation(
            validation, min_photometric_real, real is not None and bool(real[reference])
        )
        validator = plain if config is validation else PoseValidator(config)
        tests = validator.failed_tests(pose)
        if pose.num_inliers < validation.theta_in:
            tests = ("inliers", *tests)
        failed.append(tests)
        accepted[q] = not tests
    return accepted, failed


def recorded_errors(dataset: Path, sequence: str, loc: SequenceLocalization) -> PoseErrors:
    """The errors of the poses found against the query ground truth (read for scoring only;
    a right pose is ``is_correct(errors, loose_m, 30.0)``)."""
    T_gt = read_sequence(dataset, sequence).T_wc[loc.frames].numpy()
    return pose_errors(loc.T_wc, T_gt, loc.success.astype(bool))


def verdict_effect(accepted: np.ndarray, correct: np.ndarray) -> dict:
    """Accepted and wrong accepted poses, precision of the accepted (``None`` without any) and
    localisation rate (accepted and right, over all Q queries) of a (Q,) bool verdict.

    Example:
        >>> accepted, right = np.array([1, 1, 0, 0], bool), np.array([1, 0, 1, 0], bool)
        >>> verdict_effect(accepted, right)
        {'accepted': 2, 'wrong': 1, 'precision': 0.5, 'rate': 0.25}
    """
    count, right = int(accepted.sum()), int((accepted & correct).sum())
    return {
        "accepted": count,
        "wrong": count - right,
        "precision": right / count if count else None,
        "rate": right / len(accepted),
    }
