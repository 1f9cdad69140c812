"""What the database stages return: the typed summaries of ``build_db`` and ``optimize_db``
(the top level of ``<database_dir>/build_db.json`` and ``optimize_db.json``).

Ground-truth figures (keyframe position RMSE) are for scoring only: the stages compute them
after their work and never decide on them.
"""

from __future__ import annotations

from dataclasses import dataclass

from diffloc.pipeline.summary import StageSummary

__all__ = ["BuiltDatabase", "OptimizedDatabase"]


@dataclass(frozen=True)
class BuiltDatabase(StageSummary):
    """The ``build_db`` summary.

    Attributes:
        config: the database settings (:func:`~diffloc.pipeline.config_record.config_record`).
        database: path of the saved database folder.
        keyframes, keypoints, map_points, observations, mean_observations_per_point: the
            database's counts (:meth:`~diffloc.database.database.VisualDatabase.stats`).
        keyframe_frames: frame index (in the mapping sequence) of each keyframe.
        kf_pos_rmse_m: keyframe position RMSE (metres) of the (noisy) database poses.
        pose_prior_sigma_m: the pose prior the gates were sized from.
        guided_radius_px: the guided-matching radius used.
        point_gate_m: the epipolar association's 3D gate used.
        images: mapping images read.
        features_ms_per_image, build_ms_per_image: timings (wall clock).
    """

    config: dict
    database: str
    keyframes: int
    keypoints: int
    map_points: int
    observations: int
    mean_observations_per_point: float
    keyframe_frames: list[int]
    kf_pos_rmse_m: float
    pose_prior_sigma_m: float
    guided_radius_px: float
    point_gate_m: float
    images: int
    features_ms_per_image: float
    build_ms_per_image: float


@dataclass(frozen=True)
class OptimizedDatabase(StageSummary):
    """The ``optimize_db`` summary.

    Attributes:
        config: the database settings.
        database: path of the ``optimized`` database folder.
        accepted: the optimised poses were kept (the check passed, or
            ``db.optim_check.accept=always``).
        check_improved: the check vouched for the optimisation.
        check_reason: the check's verdict in words.
        check_held_out_points, check_held_out_pairs: the held-out tracks it scored.
        check_inlier_fraction_before, check_inlier_fraction_after: held-out inlier shares.
        check_median_px_before, check_median_px_after: held-out median reprojection errors.
        check_rms_move_m, check_rms_move_limit_m, check_max_move_m, check_max_move_limit_m:
            how far the keyframes moved, and the limits from the pose prior.
        kf_pos_rmse_before_m, kf_pos_rmse_after_m: keyframe position RMSE of the built poses
            and of the kept ones.
        kf_pos_rmse_optimized_m: of the optimised poses, kept or not.
        iterations, final_cost, converged: the LM run.
        optimize_ms, optimize_ms_per_image: timings (wall clock).
    """

    config: dict
    database: str
    accepted: bool
    check_improved: bool
    check_reason: str
    check_held_out_points: int
    check_held_out_pairs: int
    check_inlier_fraction_before: float
    check_inlier_fraction_after: float
    check_median_px_before: float
    check_median_px_after: float
    check_rms_move_m: float
    check_rms_move_limit_m: float
    check_max_move_m: float
    check_max_move_limit_m: float
    kf_pos_rmse_before_m: float
    kf_pos_rmse_after_m: float
    kf_pos_rmse_optimized_m: float
    iterations: int
    final_cost: float
    converged: bool
    optimize_ms: float
    optimize_ms_per_image: float
