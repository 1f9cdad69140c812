"""Pose validation of relocalised queries (seed 1 Sec. III-C, last paragraph).

A refined query pose with ``n_in >= theta_in`` inlier matches is an *inlier pose*. In
sequence mode it is *verified* only if it also lies within ``theta_dist`` of the previous
inlier pose; every inlier pose (verified or not) becomes the new reference. The first inlier
pose of a sequence has no reference and is not verified. In single-image mode only the inlier
test applies.

Seed 1 evaluates on 20 Hz EuRoC images, where ``theta_dist`` (0.3 m indoors, 0.8 m outdoors)
bounds the motion between consecutive queries. For sparser query streams the threshold grows
with the time since the reference: ``theta_dist + max_speed_mps * dt`` (``max_speed_mps = 0``
gives the paper's test exactly). A reference older than ``max_reference_age_s`` says little
about where the camera is now (after 10 s at 1 m/s the allowance is 10 m), so it verifies
nothing: the pose becomes the new reference unverified, like the first one of a sequence.
Two wrong poses of one repeated place (the same storey shift, the facade window one period
along) far apart in time would otherwise verify each other. With
``conflict_keeps_reference``, a pose that fails the distance test against a live reference
does not replace it either: a jump to a repeated place (two consecutive queries that both
match the other storey) then cannot verify itself on the next query while the right track's
reference is still young.

Seed 1's tests let confident wrong poses through where the scene repeats or is seen from the
other side: a chain of consistently wrong poses passes the distance test. Three further tests,
on the evidence of the relocaliser's candidates (:class:`PoseEvidence`),
make an *inlier pose* also need

- an inlier ratio ``n_in / matches >= min_inlier_ratio``;
- inliers spread over the image: ``coverage >= min_coverage``;
- no competing candidate (another covisibility cluster) with at least ``ambiguity_ratio`` times
  its inliers at a pose farther than ``theta_dist`` away: two well-supported places for one
  image mean the image is ambiguous;
- photometric consistency ``>= min_photometric``: the keyframe the pose came from, warped into
  the query through the surfel map at that pose, agrees with the query image
  (:mod:`diffloc.reloc.photometric`, median NCC over image cells). A repeated place seen from
  the other side (the neighbouring room, the far end of a uniform facade) has as many
  consistent inliers as the right one; the content the inliers do not cover differs;
- no repeated structure under it: fewer than ``max_repeated`` of its inliers have a twin in the
  map at one common shift (:mod:`diffloc.reloc.repetition`). Where everything the query sees
  repeats (a tiled floor filling the view, a uniform facade), a pose one period away is as
  consistent, photometrically too, as the right one: the image does not fix the pose;
- uniqueness: no alternative pose (the pose moved by the repetition shifts and their
  multiples, the other candidates), refined and scored like the pose itself, explains the
  query with at least ``uniqueness_ratio`` times the pose's own score (the share of the map
  points in view that are its refined guided inliers)
  (:mod:`diffloc.reloc.uniqueness`).

:meth:`ValidationConfig.seed1_rule` switches them off, giving seed 1's rule.

Example:
    >>> v = PoseValidator(ValidationConfig(theta_in=15, theta_dist_m=0.3))
    >>> T = torch.eye(4, dtype=torch.float64)
    >>> v.validate(T, 20, 0.0), v.validate(T, 20, 0.05), v.validate(T, 5, 0.1)
    (False, True, False)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from diffloc.checks import check_finite, check_shape
from diffloc.reloc.hierarchical import RelocResult
from diffloc.reloc.repetition import RepeatedShift
from diffloc.reloc.uniqueness import Uniqueness

__all__ = ["PoseEvidence", "PoseValidator", "ValidationConfig"]


@dataclass
class ValidationConfig:
    """Thresholds of :class:`PoseValidator`.

    Attributes:
        theta_in: fewest inlier matches of an inlier pose (seed 1: 15).
        theta_dist_m: largest distance to the previous inlier pose (seed 1: 0.3 m indoors,
            0.8 m outdoors).
        max_speed_mps: allowance per second since the previous inlier pose, for query streams
            sparser than seed 1's 20 Hz (0 disables it).
        max_reference_age_s: a previous inlier pose older than this (seconds) verifies
            nothing (``None``: no limit, as seed 1).
        temporal: apply the distance test (sequence mode); ``False`` is single-image mode.
        min_inlier_ratio: fewest inliers per refined match (0 disables the test).
        min_coverage: smallest fraction of the image grid holding inliers (0 disables it).
        ambiguity_ratio: a competing candidate with at least this fraction of the inliers,
            farther than ``theta_dist_m`` from the pose, rejects it (``None`` disables it).
        min_photometric: lowest photometric consistency (median per-cell NCC of the keyframe
            warped into the query, :mod:`diffloc.reloc.photometric`; no overlap fails) of an
            inlier pose (``None`` disables it).
        max_repeated: largest fraction of an inlier pose's inliers with a twin at one common
            shift (:mod:`diffloc.reloc.repetition`; ``None`` disables the test).
        uniqueness_ratio: an alternative pose scoring at least this fraction of the pose's own
            score rejects it (:mod:`diffloc.reloc.uniqueness`; ``None`` disables the test).
        conflict_keeps_reference: an inlier pose that fails the distance test against a live
            reference (not older than ``max_reference_age_s``) is not verified and does not
            replace the reference (seed 1: every inlier pose replaces it, ``False``). A jump
            to a repeated place then needs the reference to expire before it can verify
            itself (module docstring).
    """

    theta_in: int = 15
    theta_dist_m: float = 0.3
    max_speed_mps: float = 0.0
    max_reference_age_s: float | None = None
    temporal: bool = True
    min_inlier_ratio: float = 0.0
    min_coverage: float = 0.0
    ambiguity_ratio: float | None = None
    min_photometric: float | None = None
    max_repeated: float | None = None
    uniqueness_ratio: float | None = None
    conflict_keeps_reference: bool = False

    def __post_init__(self) -> None:
        if self.theta_in < 0:
            raise ValueError(f"theta_in must be >= 0, got {self.theta_in}")
        for name in ("theta_dist_m", "max_speed_mps"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        age = self.max_reference_age_s
        if age is not None and not (math.isfinite(age) and age > 0):
            raise ValueError(f"validation.max_reference_age_s must be > 0 or null, got {age}")
        for name in ("min_inlier_ratio", "min_coverage"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise ValueError(f"validation.{name} must be in [0, 1], got {value}")
        ratio = self.ambiguity_ratio
        if ratio is not None and not (math.isfinite(ratio) and 0.0 < ratio <= 1.0):
            raise ValueError(f"validation.ambiguity_ratio must be in (0, 1] or null, got {ratio}")
        ncc = self.min_photometric
        if ncc is not None and not (math.isfinite(ncc) and -1.0 <= ncc <= 1.0):
            raise ValueError(f"validation.min_photometric must be in [-1, 1] or null, got {ncc}")
        repeated = self.max_repeated
        if repeated is not None and not (math.isfinite(repeated) and 0.0 <= repeated <= 1.0):
            raise ValueError(f"validation.max_repeated must be in [0, 1] or null, got {repeated}")
        unique = self.uniqueness_ratio
        if unique is not None and not (math.isfinite(unique) and unique > 0):
            raise ValueError(
                f"validation.uniqueness_ratio must be a finite number > 0 or null, got {unique}"
            )

    def seed1_rule(self) -> ValidationConfig:
        """These thresholds with the tests beyond seed 1's (ratio, coverage, ambiguity,
        photometric consistency, repetition, uniqueness, the reference age, the kept
        reference) off; the
        speed allowance of sparse query streams stays."""
        return replace(
            self,
            min_inlier_ratio=0.0,
            min_coverage=0.0,
            ambiguity_ratio=None,
            min_photometric=None,
            max_repeated=None,
            uniqueness_ratio=None,
            max_reference_age_s=None,
            conflict_keeps_reference=False,
        )


@dataclass(frozen=True)
class PoseEvidence:
    """What the validation reads of one query's answer (a :class:`RelocResult`, or the
    candidates a relocalisation run recorded in ``queries.json``).

    Attributes:
        position: (3,) float64 camera position of the best candidate's refined pose.
        num_inliers: its inliers ``n_in``.
        num_matches: the matches its refinement started from.
        coverage: the fraction of the image grid holding its inliers.
        rivals: ``(inliers, distance to the best pose in metres)`` of every candidate (the
            best one among them, at distance 0).
        photometric: the best candidate's photometric consistency (NaN: no overlap with its
            keyframe), or ``None`` when it was not measured.
        repeated: how many of the best candidate's inliers have a twin at one common shift
            (:attr:`~diffloc.reloc.repetition.RepeatedShift.support`), or ``None`` when it was
            not measured.
        uniqueness: the best alternative's score over the pose's own
            (:attr:`~diffloc.reloc.uniqueness.Uniqueness.ratio`), or ``None`` when it was not
            measured.
    """

    position: torch.Tensor
    num_inliers: int
    num_matches: int
    coverage: float
    rivals: tuple[tuple[int, float], ...]
    photometric: float | None = None
    repeated: int | None = None
    uniqueness: float | None = None

    @classmethod
    def from_result(
        cls,
        result: RelocResult,
        photometric: float | None = None,
        repeated: int | None = None,
        uniqueness: float | None = None,
    ) -> PoseEvidence | None:
        """The evidence of a relocaliser's answer (``None`` when it found nothing), with the
        best candidate's ``photometric`` consistency, ``repeated`` inliers and ``uniqueness``
        ratio where they were measured."""
        best = result.best
        if best is None:
            return None
        position = best.T_wc[:3, 3]
        rivals = tuple(
            (c.num_inliers, float(torch.linalg.vector_norm(c.T_wc[:3, 3] - position)))
            for c in result.candidates
        )
        return cls(
            position,
            best.num_inliers,
            best.num_matches,
            best.coverage,
            rivals,
            photometric,
            repeated,
            uniqueness,
        )

    @classmethod
    def from_record(cls, record: dict) -> PoseEvidence | None:
        """The evidence a relocalisation run recorded for one query in ``queries.json``
        (``found``, ``position_m``, ``candidates`` with ``inliers``, ``matches``,
        ``coverage`` and ``distance_to_chosen_m``, ``photometric`` where it was measured,
        null for no overlap, ``repetition`` with its ``support`` and ``uniqueness`` with its
        ``own``, ``own_visible``, ``rival`` and ``rival_visible`` counts where they were
        measured); ``None`` when it found
        nothing.

        Raises:
            ValueError: a found query without a position or candidates.
        """
        if not record["found"]:
            return None
        candidates = record["candidates"]
        if record.get("position_m") is None or not candidates:
            raise ValueError("a found query needs position_m and candidates in queries.json")
        best = max(candidates, key=lambda c: c["inliers"])
        rivals = tuple((int(c["inliers"]), float(c["distance_to_chosen_m"])) for c in candidates)
        position = torch.tensor(record["position_m"], dtype=torch.float64)
        photometric = None
        if "photometric" in record:
            photometric = math.nan if record["photometric"] is None else record["photometric"]
        repeated = int(record["repetition"]["support"]) if "repetition" in record else None
        uniqueness = None
        if "uniqueness" in record:
            scores = record["uniqueness"]
            uniqueness = Uniqueness(
                int(scores["own"]),
                int(scores["own_visible"]),
                int(scores["rival"]),
                int(scores["rival_visible"]),
                0.0,
                0,
            ).ratio
        return cls(
            position,
            int(best["inliers"]),
            int(best["matches"]),
            float(best["coverage"]),
            rivals,
            photometric,
            repeated,
            uniqueness,
        )


class PoseValidator:
    """Stateful pose validation over one query sequence (module docstring).

    Args:
        config: thresholds.
    """

    def __init__(self, config: ValidationConfig) -> None:
        self.config = config
        self.reset()

    def reset(self) -> None:
        """Forget the previous inlier pose (start of a new sequence)."""
        self._last_position: torch.Tensor | None = None
        self._last_time = 0.0

    def plausible(self, evidence: PoseEvidence) -> bool:
        """The tests beyond seed 1's: inlier ratio, coverage, photometric consistency, no
        repeated structure, uniqueness and no well-supported rival.

        Raises:
            ValueError: ``min_photometric``, ``max_repeated`` or ``uniqueness_ratio`` is set
                but the evidence lacks that measurement (a run that did not measure it).
        """
        cfg = self.config
        if cfg.min_photometric is not None:
            if evidence.photometric is None:
                raise ValueError(
                    "validation.min_photometric is set but this answer's photometric "
                    "consistency was not measured (a relocalisation run of an older diffloc: "
                    "run it again, or set reloc.validation.min_photometric=null)"
                )
            if not evidence.photometric >= cfg.min_photometric:  # NaN (no overlap) fails
                return False
        if cfg.max_repeated is not None:
            if evidence.repeated is None:
                raise ValueError(
                    "validation.max_repeated is set but this answer's repeated structure was not "
                    "measured (a relocalisation run of an older diffloc, or the naive method: "
                    "run it again, or set reloc.validation.max_repeated=null)"
                )
            if evidence.repeated > cfg.max_repeated * evidence.num_inliers:
                return False
        if cfg.uniqueness_ratio is not None:
            if evidence.uniqueness is None:
                raise ValueError(
                    "validation.uniqueness_ratio is set but this answer's uniqueness was not "
                    "measured (a relocalisation run of an older diffloc: run it again, or set "
                    "reloc.validation.uniqueness_ratio=null)"
                )
            if evidence.uniqueness >= cfg.uniqueness_ratio:
                return False
        if evidence.num_inliers < cfg.min_inlier_ratio * max(evidence.num_matches, 1):
            return False
        if evidence.coverage < cfg.min_coverage:
            return False
        if cfg.ambiguity_ratio is None:
            return True
        return not any(
            distance > cfg.theta_dist_m and inliers >= cfg.ambiguity_ratio * evidence.num_inliers
            for inliers, distance in evidence.rivals
        )

    def validate_result(
        self,
        result: RelocResult,
        timestamp: float,
        photometric: float | None = None,
        repetition: RepeatedShift | None = None,
        uniqueness: Uniqueness | None = None,
    ) -> bool:
        """Whether a relocaliser's answer is verified (:meth:`validate_evidence`), with its
        best candidate's ``photometric`` consistency, ``repetition`` and ``uniqueness`` where
        they were measured."""
        repeated = None if repetition is None else repetition.support
        ratio = None if uniqueness is None else uniqueness.ratio
        evidence = PoseEvidence.from_result(result, photometric, repeated, ratio)
        return self.validate_evidence(evidence, timestamp)

    def validate_evidence(self, evidence: PoseEvidence | None, timestamp: float) -> bool:
        """Whether an answer is verified (module docstring); ``False`` when nothing was found
        (``evidence`` None). A pose that fails the tests beyond seed 1's is not an inlier
        pose, so it does not become the reference of the distance test."""
        if evidence is None:
            return False
        if evidence.num_inliers >= self.config.theta_in and not self.plausible(evidence):
            return False
        return self.validate_position(evidence.position, evidence.num_inliers, timestamp)

    def validate(self, T_wc: torch.Tensor, num_inliers: int, timestamp: float) -> bool:
        """Whether a refined pose is verified (:meth:`validate_position` of its position).

        Raises:
            ShapeError: ``T_wc`` is not (4, 4).
            ValueError: a non-finite pose or timestamp.
        """
        check_shape(T_wc, "4,4", "T_wc")
        check_finite(T_wc, "T_wc")
        return self.validate_position(T_wc[:3, 3], num_inliers, timestamp)

    def validate_position(self, position: torch.Tensor, num_inliers: int, timestamp: float) -> bool:
        """Whether a refined pose is verified; updates the reference on inlier poses.

        Args:
            position: (3,) camera position of the refined pose (world frame).
            num_inliers: its inlier matches ``n_in``.
            timestamp: query time in seconds (increasing over the sequence).

        Returns:
            ``True`` if the pose passes the inlier test and, in sequence mode, the distance
            test against the previous inlier pose.

        Raises:
            ShapeError: ``position`` is not (3,).
            ValueError: a non-finite position or timestamp.
        """
        check_shape(position, "3", "position")
        check_finite(position, "position")
        if not math.isfinite(timestamp):
            raise ValueError(f"timestamp must be finite, got {timestamp}")
        if num_inliers < self.config.theta_in:
            return False
        if not self.config.temporal:
            return True
        position = position.to(torch.float64)
        previous, dt = self._last_position, abs(timestamp - self._last_time)
        age = self.config.max_reference_age_s
        if previous is None or (age is not None and dt > age):
            self._last_position, self._last_time = position, float(timestamp)
            return False
        limit = self.config.theta_dist_m + self.config.max_speed_mps * dt
        verified = bool(torch.linalg.vector_norm(position - previous) <= limit)
        if verified or not self.config.conflict_keeps_reference:
            self._last_position, self._last_time = position, float(timestamp)
        return verified
