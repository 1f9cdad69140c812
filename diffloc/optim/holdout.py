"""A check of the surfel reprojection optimisation: keep its poses only where it helped.

The optimisation of seed 1 Eq. 4 (:func:`~diffloc.optim.surfel_cost.optimize_keyframe_poses`)
lowers its own cost whatever the data. Where a few wrong tracks dominate, the lower cost
comes with worse poses; where the visible surfel planes leave a motion unconstrained (a
corridor seen by a few frames: translation along it), the poses drift along it at no cost at
all (a 5-frame 160x120 scene: keyframes moved by 0.4 m at exact poses and by 1.5 m at
0.2 m noise, while every reprojection error, held out or not, fell). Ground truth cannot
referee that for a user and the minimised cost cannot either, so two independent tests
decide, neither reading ground truth:

1. Held-out tracks (does the relative geometry fit unseen data better?). The surfel-anchored
   map points that give Eq. 4 pairs (a surfel, at least two observers) are split at random
   (seeded) into training tracks and ``holdout_fraction`` held-out tracks; the optimisation
   runs on the training pairs only. Whole tracks are held out, not single pairs: the pairs of
   one track share its first observer's keypoint and surfel, so a held-out pair of a track in
   the cost is not unseen. The held-out pairs are scored at the initial and the optimised
   poses by their reprojection errors in pixels (Eq. 3 unwhitened, no robust kernel): the
   fraction within ``inlier_px`` (the test; invalid lifts and points behind the camera count
   as outliers) and the median over valid pairs (reported). The inlier fraction, unlike a
   mean or a median, does not break down when most held-out tracks are wrong associations.
   The test passes when it rises by at least ``min_gain`` over at least
   ``min_holdout_pairs`` pairs.
2. Plausible moves (did the poses move only as far as the user's error belief allows?). No
   reprojection residual sees a drift along an unconstrained direction, but its size does.
   With ``sigma`` the user's pose prior (``db.pose_prior_sigma_m``, the per-axis standard
   deviation they believe their positions have), a correction of their errors moves the
   keyframes by ``sqrt(3) sigma`` RMS: the RMS move must stay within ``rms_move_sigmas``
   sigma (a drift of all keyframes together) and every single move within
   ``max_move_sigmas`` sigma (one keyframe running off). A prior of 0 (exact poses) allows no
   move: nothing is kept.

The optimisation counts as an improvement when both pass; otherwise the caller keeps the
initial poses, unless ``accept="always"`` forces the result (the figures are still reported).
The poses kept on acceptance are those of the training solve, on which the figures were
measured: the held-out tracks do not enter a final solve (it would return poses the check
never saw, for a fifth more pairs). Map points are then re-placed from all tracks by
:func:`~diffloc.optim.surfel_cost.replace_map_points`, as before.

Example:
    >>> cfg = HoldoutCheckConfig()
    >>> cfg.accept, cfg.holdout_fraction
    ('checked', 0.2)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from diffloc.checks import check_shape
from diffloc.database.database import VisualDatabase
from diffloc.optim.lm import LMResult
from diffloc.optim.surfel_cost import (
    SurfelOptimConfig,
    SurfelPairs,
    SurfelReprojectionCost,
    optimize_keyframe_poses,
    pairs_from_database,
)

__all__ = [
    "ACCEPT_MODES",
    "CheckedOptimisation",
    "HeldOutFigures",
    "HoldoutCheckConfig",
    "checked_optimize_keyframe_poses",
    "held_out_figures",
    "PoseMoves",
    "holdout_points",
    "pose_moves",
]

ACCEPT_MODES = ("checked", "always")


@dataclass
class HoldoutCheckConfig:
    """Settings of :func:`checked_optimize_keyframe_poses` (module docstring).

    Attributes:
        accept: ``"checked"``: keep the optimised poses only where the held-out check says
            they improved; ``"always"``: keep them whatever the check says (it still runs
            and is reported).
        holdout_fraction: share of the pair-giving map points held out, in (0, 1).
        inlier_px: a held-out pair is an inlier when its reprojection error is below this
            many pixels. 3 px: about three keypoint standard deviations, and the ~1 px error
            of the surfel planes themselves (the tiny scene's true poses put 65-70 % of the
            pairs within 3 px, noisy ones at 0.2 m ~10 %).
        min_gain: the smallest rise of the held-out inlier fraction (absolute, 0.01 = one
            percentage point) that counts as an improvement; below it the change is within
            the spread of a few tracks and the initial poses are kept.
        min_holdout_pairs: fewer held-out pairs cannot vouch for anything: the check fails.
        max_move_sigmas: the largest keyframe position move, in standard deviations of the
            pose prior. The norm of a 3D Gaussian error exceeds 5 sigma with probability
            1.5e-5 (chi-square, 3 degrees of freedom); 6 leaves a sigma for the optimised
            pose's own error (a 25-frame scene at 0.2 m: 4.2 sigma at most). A larger move is
            not a correction of the error the user expects but the optimisation's (drift).
        rms_move_sigmas: the largest RMS keyframe position move, in prior standard
            deviations. Correcting Gaussian errors moves them by ``sqrt(3) = 1.73`` sigma
            RMS, plus the optimised poses' own error: as large as the initial one, ``sqrt(6)
            = 2.45`` sigma; 3 leaves room for the spread of a few keyframes (a 25-frame scene
            at 0.2 m: 2.1 sigma) or a prior understated by ~20 %.
        seed: seed of the split.
    """

    accept: str = "checked"
    holdout_fraction: float = 0.2
    inlier_px: float = 3.0
    min_gain: float = 0.01
    min_holdout_pairs: int = 20
    max_move_sigmas: float = 6.0
    rms_move_sigmas: float = 3.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.accept not in ACCEPT_MODES:
            raise ValueError(f"accept must be one of {ACCEPT_MODES}, got {self.accept!r}")
        if not 0.0 < self.holdout_fraction < 1.0:
            raise ValueError(f"holdout_fraction must be in (0, 1), got {self.holdout_fraction}")
        if not (math.isfinite(self.inlier_px) and self.inlier_px > 0):
            raise ValueError(f"inlier_px must be positive, got {self.inlier_px}")
        if not (math.isfinite(self.min_gain) and 0.0 <= self.min_gain < 1.0):
            raise ValueError(f"min_gain must be in [0, 1), got {self.min_gain}")
        if self.min_holdout_pairs < 1:
            raise ValueError(f"min_holdout_pairs must be >= 1, got {self.min_holdout_pairs}")
        for name in ("max_move_sigmas", "rms_move_sigmas"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be positive, got {value}")


@dataclass
class HeldOutFigures:
    """Reprojection figures of the held-out pairs at one set of poses.

    Attributes:
        pairs: number of held-out pairs.
        valid_pairs: those whose lift and reprojection are valid.
        inlier_fraction: share of all ``pairs`` valid and within ``inlier_px`` (0 if none).
        median_px: median reprojection error of the valid pairs, pixels (``None`` if none).
    """

    pairs: int
    valid_pairs: int
    inlier_fraction: float
    median_px: float | None


@dataclass
class CheckedOptimisation:
    """Outcome of :func:`checked_optimize_keyframe_poses`.

    Attributes:
        T_wc: (K, 4, 4) float64 poses to keep: the optimised ones if ``accepted``, else the
            initial ones.
        T_wc_optimized: (K, 4, 4) float64 poses of the training solve (kept or not).
        result: the :class:`~diffloc.optim.lm.LMResult` of the training solve.
        improved: the check's verdict.
        accepted: ``T_wc`` holds the optimised poses (``improved``, or forced).
        reason: one line saying why the check passed or failed.
        before: held-out figures at the initial poses.
        after: held-out figures at the optimised poses.
        held_out_points: number of held-out map points.
        moves: the keyframe position moves of the training solve (:class:`PoseMoves`).
    """

    T_wc: torch.Tensor
    T_wc_optimized: torch.Tensor
    result: LMResult
    improved: bool
    accepted: bool
    reason: str
    before: HeldOutFigures
    after: HeldOutFigures
    held_out_points: int
    moves: PoseMoves


def holdout_points(db: VisualDatabase, fraction: float, generator: torch.Generator) -> torch.Tensor:
    """A random share of the map points that give Eq. 4 pairs, to hold out of the optimisation.

    Candidates are the points anchored to a surfel (``point_surfels >= 0``) and observed by
    at least two keyframes; ``round(fraction * candidates)`` of them are drawn.

    Args:
        db: the visual database.
        fraction: share of the candidates to hold out, in (0, 1).
        generator: the random source.

    Returns:
        (P,) bool, true on held-out map points.

    Example:
        >>> holdout_points(VisualDatabase(2), 0.2, torch.Generator()).shape
        torch.Size([0])
    """
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"fraction must be in (0, 1), got {fraction}")
    candidates = torch.nonzero((db.point_surfels >= 0) & (db.observation_counts() >= 2)).flatten()
    count = round(fraction * len(candidates))
    order = torch.randperm(len(candidates), generator=generator)
    held = torch.zeros(db.num_points, dtype=torch.bool)
    held[candidates[order[:count]]] = True
    return held


def held_out_figures(pairs: SurfelPairs, T_wc: torch.Tensor, inlier_px: float) -> HeldOutFigures:
    """Reprojection figures of ``pairs`` at poses ``T_wc`` (module docstring, step 3).

    Args:
        pairs: the ``M`` held-out pairs.
        T_wc: (K, 4, 4) camera-to-world keyframe poses.
        inlier_px: inlier threshold, pixels.

    Returns:
        :class:`HeldOutFigures`.

    Example:
        >>> from diffloc.optim.surfel_cost import pairs_from_database
        >>> s = torch.zeros(1, 3, dtype=torch.float64)
        >>> pairs = pairs_from_database(VisualDatabase(2), s, s)
        >>> held_out_figures(pairs, torch.eye(4, dtype=torch.float64)[None], 3.0).pairs
        0
    """
    check_shape(T_wc, "K,4,4", "T_wc")
    T = T_wc.to(torch.float64)
    cost = SurfelReprojectionCost.from_pairs(pairs)  # sigma 1: residuals in pixels
    residuals, valid = cost.residuals_and_valid(T[pairs.alpha], T[pairs.beta])
    errors = torch.linalg.vector_norm(residuals, dim=-1)
    inliers = valid & (errors < inlier_px)
    count = len(pairs)
    return HeldOutFigures(
        pairs=count,
        valid_pairs=int(valid.sum()),
        inlier_fraction=float(inliers.sum()) / count if count else 0.0,
        median_px=float(errors[valid].median()) if bool(valid.any()) else None,
    )


@dataclass
class PoseMoves:
    """How far the keyframe positions moved, and how far the pose prior lets them (metres).

    Attributes:
        max_m: the largest move.
        rms_m: the root mean square move.
        max_limit_m: ``max_move_sigmas`` x the prior.
        rms_limit_m: ``rms_move_sigmas`` x the prior.
    """

    max_m: float
    rms_m: float
    max_limit_m: float
    rms_limit_m: float

    @property
    def plausible(self) -> bool:
        """Both moves within their limits."""
        return self.max_m <= self.max_limit_m and self.rms_m <= self.rms_limit_m


def pose_moves(
    T_wc_a: torch.Tensor, T_wc_b: torch.Tensor, prior_sigma_m: float, cfg: HoldoutCheckConfig
) -> PoseMoves:
    """The position moves between two pose sets against the limits of a pose prior.

    Args:
        T_wc_a: (K, 4, 4) poses.
        T_wc_b: (K, 4, 4) poses.
        prior_sigma_m: believed per-axis standard deviation of the positions, metres.
        cfg: the limits in prior standard deviations.

    Returns:
        :class:`PoseMoves` (zero moves for ``K = 0``).

    Example:
        >>> T = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
        >>> moved = T.clone(); moved[0, 0, 3] = 0.3
        >>> pose_moves(moved, T, 0.1, HoldoutCheckConfig()).plausible
        True
    """
    check_shape(T_wc_a, "K,4,4", "T_wc_a")
    check_shape(T_wc_b, f"{T_wc_a.shape[0]},4,4", "T_wc_b")
    moves = torch.linalg.vector_norm(T_wc_a[:, :3, 3] - T_wc_b[:, :3, 3], dim=-1)
    empty = moves.numel() == 0
    return PoseMoves(
        max_m=0.0 if empty else float(moves.max()),
        rms_m=0.0 if empty else float(moves.square().mean().sqrt()),
        max_limit_m=cfg.max_move_sigmas * prior_sigma_m,
        rms_limit_m=cfg.rms_move_sigmas * prior_sigma_m,
    )


def _verdict(
    before: HeldOutFigures, after: HeldOutFigures, moves: PoseMoves, cfg: HoldoutCheckConfig
) -> tuple[bool, str]:
    """``(improved, reason)``: both tests of the module docstring, and why they failed."""
    change = (
        f"held-out inliers within {cfg.inlier_px:g} px {100 * before.inlier_fraction:.1f} % -> "
        f"{100 * after.inlier_fraction:.1f} % of {before.pairs} pairs; keyframes moved by "
        f"{moves.rms_m:.3g} m RMS, {moves.max_m:.3g} m at most (the pose prior allows "
        f"{moves.rms_limit_m:.3g} / {moves.max_limit_m:.3g} m)"
    )
    failed = []
    if before.pairs < cfg.min_holdout_pairs:
        failed.append(f"fewer held-out pairs than min_holdout_pairs={cfg.min_holdout_pairs}")
    elif after.inlier_fraction - before.inlier_fraction < cfg.min_gain:
        failed.append(f"a held-out gain below min_gain={cfg.min_gain:g}")
    if not moves.plausible:
        failed.append(
            "moves beyond what db.pose_prior_sigma_m allows (raise the prior if your poses "
            "are worse than it says)"
        )
    if failed:
        return False, f"{change}: {'; '.join(failed)}"
    return True, change


def checked_optimize_keyframe_poses(
    db: VisualDatabase,
    surfel_centers: torch.Tensor,
    surfel_normals: torch.Tensor,
    optim: SurfelOptimConfig,
    check: HoldoutCheckConfig,
    pose_prior_sigma_m: float,
) -> CheckedOptimisation:
    """Optimise the keyframe poses on training tracks and check them (module docstring).

    The database is not modified.

    Args:
        db: the visual database; ``db.T_wc`` gives the initial poses.
        surfel_centers: (S, 3) surfel centres, world frame.
        surfel_normals: (S, 3) surfel normals.
        optim: settings of the optimisation.
        check: settings of the check.
        pose_prior_sigma_m: the believed per-axis standard deviation of the initial
            positions, metres (>= 0).

    Returns:
        :class:`CheckedOptimisation`.

    Raises:
        ShapeError, ValueError: as :func:`~diffloc.optim.surfel_cost.optimize_keyframe_poses`
            on the training tracks.
    """
    if not (math.isfinite(pose_prior_sigma_m) and pose_prior_sigma_m >= 0):
        raise ValueError(f"pose_prior_sigma_m must be finite and >= 0, got {pose_prior_sigma_m}")
    generator = torch.Generator().manual_seed(check.seed)
    held = holdout_points(db, check.holdout_fraction, generator)
    T_optimized, result = optimize_keyframe_poses(
        db, surfel_centers, surfel_normals, optim, points=~held
    )
    pairs = pairs_from_database(db, surfel_centers, surfel_normals)
    held_pairs = pairs.select(held[pairs.points])
    T_initial = db.T_wc.to(torch.float64)
    before = held_out_figures(held_pairs, T_initial, check.inlier_px)
    after = held_out_figures(held_pairs, T_optimized, check.inlier_px)
    moves = pose_moves(T_optimized, T_initial, pose_prior_sigma_m, check)
    improved, reason = _verdict(before, after, moves, check)
    accepted = improved or check.accept == "always"
    return CheckedOptimisation(
        T_wc=T_optimized if accepted else T_initial.clone(),
        T_wc_optimized=T_optimized,
        result=result,
        improved=improved,
        accepted=accepted,
        reason=reason,
        before=before,
        after=after,
        held_out_points=int(held.sum()),
        moves=moves,
    )
