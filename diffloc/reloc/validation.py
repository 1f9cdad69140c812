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

The speed allowance is loose (at 6 m/s, 3.8 m after half a second): a pose snapped one period
along a repeated ground or facade (1-3 m) passes it. With ``max_accel_mps2``, a track that has
a velocity (its last pose was verified against the one before) must also keep moving as that
velocity predicts: the previous interval's world velocity ``v = (p_1 - p_0) / (t_1 - t_0)``,
turned by half the camera's rotation from ``t_0`` to ``t`` (a constant turn rate turns the
heading by that much between the middles of the two intervals: a vehicle moves along its
heading), predicts ``p_1 + R_half v (t - t_1)``; the pose must lie within
``theta_dist + max_accel_mps2 (t - t_1)^2 / 2`` of it (what a change of speed moves it by).
The rotation needs no up axis and comes from the poses themselves. A pose that fails only the
motion test is not verified and does not replace the reference, and the track forgets its
velocity: either may be the wrong one (one pose 0.8 m off gives a velocity that would reject
the right poses after it), so the next pose meets the distance test alone.

A track's first verified pose rests on one loose distance test against a pose that nothing
verified; two consecutive wrong poses of one repeated place pass it. With
``min_track_poses = 3`` a verified pose is accepted only once its track holds three consecutive
poses, each verified against the one before: the reference must itself have been verified, so
the track has a velocity (and the motion test, where set, has checked the pose). A pose that
fails the motion test ends its track: the next verified pose starts counting again from its
reference. The pose that is not yet accepted still serves as the reference. ``2`` is seed 1's
test: a pose and its reference.

A track can be wrong throughout where the camera sees one plane whose texture repeats (a tiled
wall, the same paint on the wall ahead and on the wall beside): each pose is a homography of
that plane matched to a turned or shifted copy, and the copy's poses move as consistently as
the right ones. With ``max_track_plane_share`` a verified pose is accepted only once its track
holds a pose with 3D evidence beyond one plane: at most that share of its inliers' map points
on their dominant plane (:mod:`diffloc.geometry.plane_share`). A single pose on one plane
inside a track that has seen more (the camera passing a bare wall) stays accepted, unlike
``max_plane_share``, which rejects every such pose.

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
  (:mod:`diffloc.reloc.uniqueness`);
- a precise position: the first-order standard deviation of the camera position along its
  worst direction, from the inliers' geometry and residuals, at most ``max_position_sigma_m``
  (:mod:`diffloc.reloc.pose_uncertainty`): inliers that all lie far away or along one
  direction leave the camera free to slide, and such a pose is not one to trust;
- 3D evidence beyond one plane: at most ``max_plane_share`` of its inliers' map points on
  their dominant plane (:mod:`diffloc.geometry.plane_share`). A pose resting on one textured
  plane is a homography of it: where that texture repeats (a tiled wall), a copy on another
  wall, turned or shifted, gives as many consistent inliers.

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
from diffloc.geometry.se3 import so3_exp, so3_log
from diffloc.reloc.hierarchical import RelocResult
from diffloc.reloc.repetition import RepeatedShift
from diffloc.reloc.uniqueness import Uniqueness

__all__ = [
    "PLAUSIBILITY_TESTS",
    "PoseEvidence",
    "PoseValidator",
    "ValidationConfig",
    "predicted_displacement",
]

PLAUSIBILITY_TESTS = (
    "photometric",
    "repeated",
    "uniqueness",
    "position sigma",
    "planar",
    "inlier ratio",
    "coverage",
    "rival",
)
"""The names :meth:`PoseValidator.failed_tests` gives the tests beyond seed 1's."""


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
        max_position_sigma_m: largest standard deviation (metres) of an inlier pose's camera
            position along its worst direction (:mod:`diffloc.reloc.pose_uncertainty`;
            ``None`` disables the test).
        max_plane_share: largest share of an inlier pose's inlier map points on one plane
            (:mod:`diffloc.geometry.plane_share`; ``None`` disables the test).
        max_accel_mps2: the motion test's largest change of speed (m/s^2) of a track with a
            velocity: the pose must lie within ``theta_dist_m + max_accel_mps2 dt^2 / 2`` of
            the position the turned velocity predicts (module docstring; ``None``: no motion
            test, as seed 1).
        min_track_poses: fewest consecutive poses, each verified against the one before, a
            pose's track must hold (the pose included) for the pose to be accepted (module
            docstring; seed 1: 2, a pose and its reference).
        max_track_plane_share: a verified pose is accepted only once its track (the pose
            included) holds a pose with at most this share of its inliers on one plane
            (module docstring; ``None``: not tested, as seed 1).
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
    max_accel_mps2: float | None = None
    max_position_sigma_m: float | None = None
    max_plane_share: float | None = None
    min_track_poses: int = 2
    max_track_plane_share: float | None = None

    def __post_init__(self) -> None:
        if self.theta_in < 0:
            raise ValueError(f"theta_in must be >= 0, got {self.theta_in}")
        if self.min_track_poses < 2:
            raise ValueError(
                "validation.min_track_poses must be >= 2 (a pose and the reference it is "
                f"verified against), got {self.min_track_poses}"
            )
        for name in ("theta_dist_m", "max_speed_mps"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        sigma = self.max_position_sigma_m
        if sigma is not None and not (math.isfinite(sigma) and sigma > 0):
            raise ValueError(f"validation.max_position_sigma_m must be > 0 or null, got {sigma}")
        accel = self.max_accel_mps2
        if accel is not None and not (math.isfinite(accel) and accel >= 0):
            raise ValueError(f"validation.max_accel_mps2 must be >= 0 or null, got {accel}")
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
        for name in ("max_repeated", "max_plane_share", "max_track_plane_share"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and 0.0 <= value <= 1.0):
                raise ValueError(f"validation.{name} must be in [0, 1] or null, got {value}")
        unique = self.uniqueness_ratio
        if unique is not None and not (math.isfinite(unique) and unique > 0):
            raise ValueError(
                f"validation.uniqueness_ratio must be a finite number > 0 or null, got {unique}"
            )

    def seed1_rule(self) -> ValidationConfig:
        """These thresholds with the tests beyond seed 1's (ratio, coverage, ambiguity,
        photometric consistency, repetition, uniqueness, position precision, planarity, the
        reference age, the kept reference, the motion test, the track length and the track's
        planarity) off; the speed allowance of sparse query streams stays."""
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
            max_accel_mps2=None,
            max_position_sigma_m=None,
            max_plane_share=None,
            min_track_poses=2,
            max_track_plane_share=None,
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
        rotation: (3, 3) float64 camera-to-world rotation of that pose, or ``None`` (a record
            of an older run, which did not keep it); the motion test needs it.
        position_sigma: the best candidate's position standard deviation in metres
            (``inf``: its inliers do not fix it), or ``None`` when it was not measured.
        plane_share: share of the best candidate's inliers on their dominant plane, or
            ``None`` when it was not measured.
    """

    position: torch.Tensor
    num_inliers: int
    num_matches: int
    coverage: float
    rivals: tuple[tuple[int, float], ...]
    photometric: float | None = None
    repeated: int | None = None
    uniqueness: float | None = None
    rotation: torch.Tensor | None = None
    position_sigma: float | None = None
    plane_share: float | None = None

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
            best.T_wc[:3, :3].to(torch.float64),
            None if math.isnan(best.position_sigma_m) else best.position_sigma_m,
            None if math.isnan(best.plane_share) else best.plane_share,
        )

    @classmethod
    def from_record(cls, record: dict) -> PoseEvidence | None:
        """The evidence a relocalisation run recorded for one query in ``queries.json``
        (``found``, ``position_m``, ``candidates`` with ``inliers``, ``matches``,
        ``coverage`` and ``distance_to_chosen_m``, ``photometric`` where it was measured,
        null for no overlap, ``repetition`` with its ``support`` and ``uniqueness`` with its
        ``own``, ``own_visible``, ``rival`` and ``rival_visible`` counts where they were
        measured, ``rotation_wc`` (3 x 3, row-major) and the best candidate's
        ``position_sigma_m`` (null: unbounded) and ``plane_share`` where they were recorded);
        ``None`` when it found nothing.

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
        rotation = record.get("rotation_wc")
        sigma = None
        if "position_sigma_m" in best:
            sigma = (
                math.inf if best["position_sigma_m"] is None else float(best["position_sigma_m"])
            )
        return cls(
            position,
            int(best["inliers"]),
            int(best["matches"]),
            float(best["coverage"]),
            rivals,
            photometric,
            repeated,
            uniqueness,
            None if rotation is None else torch.tensor(rotation, dtype=torch.float64),
            sigma,
            best.get("plane_share"),
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
        self._last_rotation: torch.Tensor | None = None
        self._last_time = 0.0
        # The track's velocity (3,) over its last verified interval, and the rotation (3, 3)
        # at that interval's start; None until a pose is verified against the one before.
        self._velocity: tuple[torch.Tensor, torch.Tensor] | None = None
        # Consecutive poses of the reference's track, each verified against the one before.
        self._track_poses = 0
        # Whether the reference rests on more than one plane, and whether a pose of its track
        # does (always True when the track's planarity is not tested).
        self._last_off_plane = self._track_off_plane = True

    def plausible(self, evidence: PoseEvidence) -> bool:
        """The tests beyond seed 1's: inlier ratio, coverage, photometric consistency, no
        repeated structure, uniqueness, position precision, evidence beyond one plane and no
        well-supported rival
        (:meth:`failed_tests` finds none).

        Raises:
            ValueError: as :meth:`failed_tests`.
        """
        return not self.failed_tests(evidence)

    def failed_tests(self, evidence: PoseEvidence) -> tuple[str, ...]:
        """Every test beyond seed 1's the evidence fails, of :data:`PLAUSIBILITY_TESTS` in
        that order (empty: plausible); a disabled test never fails.

        Raises:
            ValueError: ``min_photometric``, ``max_repeated``, ``uniqueness_ratio``,
                ``max_position_sigma_m`` or ``max_plane_share`` is set but the evidence lacks
                that measurement (a run that did not measure it).

        Example (coverage 0.25 and a rival with 80 % of the 100 inliers 5 m away):
            >>> check = PoseValidator(ValidationConfig(theta_in=20, theta_dist_m=1.0,
            ...     temporal=False, min_coverage=0.5, ambiguity_ratio=0.7))
            >>> evidence = PoseEvidence(torch.zeros(3, dtype=torch.float64), 100, 200, 0.25,
            ...                         ((100, 0.0), (80, 5.0)))
            >>> check.failed_tests(evidence)
            ('coverage', 'rival')
        """
        cfg = self.config
        failed = []
        if cfg.min_photometric is not None:
            if evidence.photometric is None:
                raise ValueError(
                    "validation.min_photometric is set but this answer's photometric "
                    "consistency was not measured (a relocalisation run of an older diffloc: "
                    "run it again, or set reloc.validation.min_photometric=null)"
                )
            if not evidence.photometric >= cfg.min_photometric:  # NaN (no overlap) fails
                failed.append("photometric")
        if cfg.max_repeated is not None:
            if evidence.repeated is None:
                raise ValueError(
                    "validation.max_repeated is set but this answer's repeated structure was not "
                    "measured (a relocalisation run of an older diffloc, or the naive method: "
                    "run it again, or set reloc.validation.max_repeated=null)"
                )
            if evidence.repeated > cfg.max_repeated * evidence.num_inliers:
                failed.append("repeated")
        if cfg.uniqueness_ratio is not None:
            if evidence.uniqueness is None:
                raise ValueError(
                    "validation.uniqueness_ratio is set but this answer's uniqueness was not "
                    "measured (a relocalisation run of an older diffloc: run it again, or set "
                    "reloc.validation.uniqueness_ratio=null)"
                )
            if evidence.uniqueness >= cfg.uniqueness_ratio:
                failed.append("uniqueness")
        if cfg.max_position_sigma_m is not None:
            if evidence.position_sigma is None:
                raise ValueError(
                    "validation.max_position_sigma_m is set but this answer's position "
                    "uncertainty was not measured (a relocalisation run of an older diffloc: run "
                    "it again, or set reloc.validation.max_position_sigma_m=null)"
                )
            if not evidence.position_sigma <= cfg.max_position_sigma_m:
                failed.append("position sigma")
        if cfg.max_plane_share is not None:
            if evidence.plane_share is None:
                raise ValueError(
                    "validation.max_plane_share is set but this answer's plane share was not "
                    "measured (a run of an older diffloc: run it again, or set "
                    "validation.max_plane_share=null)"
                )
            if evidence.plane_share > cfg.max_plane_share:
                failed.append("planar")
        if evidence.num_inliers < cfg.min_inlier_ratio * max(evidence.num_matches, 1):
            failed.append("inlier ratio")
        if evidence.coverage < cfg.min_coverage:
            failed.append("coverage")
        if cfg.ambiguity_ratio is not None and any(
            distance > cfg.theta_dist_m and inliers >= cfg.ambiguity_ratio * evidence.num_inliers
            for inliers, distance in evidence.rivals
        ):
            failed.append("rival")
        return tuple(failed)

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
        return self.validate_position(
            evidence.position,
            evidence.num_inliers,
            timestamp,
            evidence.rotation,
            evidence.plane_share,
        )

    def validate(self, T_wc: torch.Tensor, num_inliers: int, timestamp: float) -> bool:
        """Whether a refined pose is verified (:meth:`validate_position` of its position).

        Raises:
            ShapeError: ``T_wc`` is not (4, 4).
            ValueError: a non-finite pose or timestamp.
        """
        check_shape(T_wc, "4,4", "T_wc")
        check_finite(T_wc, "T_wc")
        return self.validate_position(T_wc[:3, 3], num_inliers, timestamp, T_wc[:3, :3])

    def validate_position(
        self,
        position: torch.Tensor,
        num_inliers: int,
        timestamp: float,
        rotation: torch.Tensor | None = None,
        plane_share: float | None = None,
    ) -> bool:
        """Whether a refined pose is verified; updates the reference on inlier poses.

        Args:
            position: (3,) camera position of the refined pose (world frame).
            num_inliers: its inlier matches ``n_in``.
            timestamp: query time in seconds (increasing over the sequence).
            rotation: (3, 3) its camera-to-world rotation; needed by the motion test
                (``max_accel_mps2``) only.
            plane_share: share of its inliers' map points on their dominant plane; needed
                by the track's planarity test (``max_track_plane_share``) only.

        Returns:
            ``True`` if the pose passes the inlier test and, in sequence mode, the distance
            test against the previous inlier pose, the motion test where it applies, and ends
            a track of at least ``min_track_poses`` poses that holds a pose beyond one plane
            where ``max_track_plane_share`` is set.

        Raises:
            ShapeError: ``position`` is not (3,), ``rotation`` not (3, 3).
            ValueError: a non-finite position, rotation or timestamp, or the motion test is
                set and ``rotation`` is missing, or the track's planarity test is set and
                ``plane_share`` is missing.
        """
        check_shape(position, "3", "position")
        check_finite(position, "position")
        if not math.isfinite(timestamp):
            raise ValueError(f"timestamp must be finite, got {timestamp}")
        cfg = self.config
        if cfg.temporal and cfg.max_accel_mps2 is not None:
            if rotation is None:
                raise ValueError(
                    "validation.max_accel_mps2 is set but this pose has no rotation (a "
                    "relocalisation record of an older diffloc: run it again, or set "
                    "reloc.validation.max_accel_mps2=null)"
                )
            check_shape(rotation, "3,3", "rotation")
            check_finite(rotation, "rotation")
            rotation = rotation.to(torch.float64)
        off_plane = True
        if cfg.temporal and cfg.max_track_plane_share is not None:
            if plane_share is None:
                raise ValueError(
                    "validation.max_track_plane_share is set but this pose's plane share was "
                    "not measured (a relocalisation record of an older diffloc: run it again, "
                    "or set reloc.validation.max_track_plane_share=null)"
                )
            off_plane = plane_share <= cfg.max_track_plane_share
        if num_inliers < cfg.theta_in:
            return False
        if not cfg.temporal:
            return True
        position = position.to(torch.float64)
        previous, dt = self._last_position, abs(timestamp - self._last_time)
        age = cfg.max_reference_age_s
        if previous is None or (age is not None and dt > age):
            self._set_reference(position, rotation, timestamp, None, 1, off_plane, off_plane)
            return False
        limit = cfg.theta_dist_m + cfg.max_speed_mps * dt
        verified = bool(torch.linalg.vector_norm(position - previous) <= limit)
        if verified and cfg.max_accel_mps2 is not None and self._velocity is not None:
            assert rotation is not None  # checked above
            predicted = previous + predicted_displacement(*self._velocity, rotation, dt)
            deviation = torch.linalg.vector_norm(position - predicted)
            if deviation > cfg.theta_dist_m + 0.5 * cfg.max_accel_mps2 * dt**2:
                # The pose or the velocity is wrong: trust neither; the track restarts at the
                # reference.
                self._velocity, self._track_poses = None, 1
                self._track_off_plane = self._last_off_plane
                return False
        if verified or not cfg.conflict_keeps_reference:
            velocity = None
            if verified and dt > 0 and self._last_rotation is not None:
                velocity = ((position - previous) / dt, self._last_rotation)
            track_poses = self._track_poses + 1 if verified else 1
            track_off_plane = off_plane or (verified and self._track_off_plane)
            self._set_reference(
                position, rotation, timestamp, velocity, track_poses, off_plane, track_off_plane
            )
        return verified and self._track_poses >= cfg.min_track_poses and self._track_off_plane

    def _set_reference(
        self,
        position: torch.Tensor,
        rotation: torch.Tensor | None,
        timestamp: float,
        velocity: tuple[torch.Tensor, torch.Tensor] | None,
        track_poses: int,
        off_plane: bool,
        track_off_plane: bool,
    ) -> None:
        self._last_position, self._last_rotation = position, rotation
        self._last_time, self._velocity = float(timestamp), velocity
        self._track_poses = track_poses
        self._last_off_plane, self._track_off_plane = off_plane, track_off_plane


def predicted_displacement(
    velocity: torch.Tensor, R_start: torch.Tensor, R_now: torch.Tensor, dt: float
) -> torch.Tensor:
    """Displacement over ``dt`` seconds of a track moving at a constant speed and turn rate.

    ``velocity`` (3,) is the world velocity over the track's previous interval, whose start had
    the camera-to-world rotation ``R_start`` (3, 3); ``R_now`` (3, 3) is the rotation now. At a
    constant turn rate the heading turns between the middles of the two intervals by half the
    rotation from ``R_start`` to ``R_now``, so the velocity is turned by that half.

    Returns:
        (3,) the predicted displacement ``R_half velocity dt``.

    Example (driving along x at 2 m/s while turning 90 degrees left about z over the two
    intervals: the velocity turns by 45 degrees):
        >>> R_now = so3_exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
        >>> d = predicted_displacement(torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64),
        ...                            torch.eye(3, dtype=torch.float64), R_now, 1.0)
        >>> [round(x, 3) for x in d.tolist()]
        [1.414, 1.414, 0.0]
    """
    half_turn = so3_exp(0.5 * so3_log(R_now @ R_start.transpose(-1, -2)))
    return half_turn @ velocity * dt
