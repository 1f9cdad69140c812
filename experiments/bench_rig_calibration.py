"""Benchmark the rig calibration (shared extrinsic + time offset); last stdout line is JSON.

Usage:
    python experiments/bench_rig_calibration.py [--data data/indoor_seed0]
        [--association epipolar] [--translation-cm 5] [--rotation-deg 1] [--dt-ms 30]
        [--dense-rate-hz 100] [--seed 0] [--threads 1]
        [--out experiments/results/bench_rig_calibration.json]

Needs the dataset's surfel map (``diffloc task=build_map``). Scenario: the body (lidar)
trajectory ``T_wb(t)`` is right, the camera extrinsic and the image time offset are not. The
camera of image ``k`` (time ``t_k``) is at ``T_wb(t_k) T_bc`` (``read_sequence``: ``T_wc``,
``T_bc``), but the user's poses for it are ``T_wb(t_k + dt_err) T_bc E`` (``E``:
``--translation-cm`` and ``--rotation-deg`` in seeded random directions, camera frame), with
``T_wb(t)`` of the simulator's continuous trajectory (regenerated from the dataset's scene
configuration at ``--dense-rate-hz``, checked against the sequence at the image times). The
database is built from the mapping images AT THOSE MISCALIBRATED POSES by the builder of
``diffloc task=build_db`` (``DatabaseConfig`` with ``builder.association=--association``), so
its keypoint-surfel associations and tracks are the ones such a user gets.
:func:`~diffloc.optim.rig_calibration.calibrate_rig` is given only what that user has: the
database, the surfel map, the body trajectory, its times and each keyframe's sample of it. It
should return ``C = E^-1`` and ``dt = -dt_err``. Ground truth (the true camera poses, ``E``,
``dt_err``) is read only by :func:`score`. The body trajectory handed to the estimator is the
simulator's exact one: that is the scenario's premise (only the rig is wrong); a real lidar
trajectory has errors of its own, not modelled here.

Runs (``runs`` in the JSON, one stdout line each), each reporting ``oracle``,
``kf_pos_rmse_before_cm`` / ``_after_cm`` and ``kf_rot_rmse_before_deg`` / ``_after_deg``
against ground truth, ``extrinsic_recovered_cm`` / ``_deg`` (``|C^-1|``, to compare with
``extrinsic_error_true_*`` ``|E|``), ``extrinsic_residual_cm`` / ``_deg`` (``|C E|``: what is
left of the error), ``dt_recovered_ms`` (``-dt``, to compare with ``dt_true_ms``),
``dt_residual_ms``, ``calibrate_ms``, LM ``iterations``, ``pairs``, costs and the ``std`` /
``dt_correlation`` diagnostics:

- ``image_rate``: the body trajectory at the image times only (2 Hz on the default scene), as
  a user with one body pose per image has it;
- ``dense``: the body trajectory at ``--dense-rate-hz`` (body twists from close samples);
- ``extrinsic_only``: ``dt_err = 0`` (its own database, built at ``T_wb(t_k) T_bc E``) and the
  6-DoF mode;
- ``per_keyframe``: the peer, seed 1's per-keyframe optimisation
  (:func:`~diffloc.optim.surfel_cost.optimize_keyframe_poses`, the database's ``optim``) on
  the ``image_rate`` database: RMSE, time and ``speedup_vs_per_keyframe`` (its time over the
  ``image_rate`` calibration's);
- ``oracle_<run>`` (``"oracle": true``): the same runs on a database built at the TRUE poses
  whose keyframe poses are then replaced by the miscalibrated ones (this benchmark's former
  setting). Its associations are the truth's, which no user has: a reference for how much of
  what is left the associations made at the wrong poses account for, not a result.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from dataclasses import replace
from pathlib import Path

import torch
from omegaconf import OmegaConf

from diffloc.database.builder import BuilderConfig
from diffloc.database.database import VisualDatabase
from diffloc.eval.report_files import write_benchmark
from diffloc.geometry.se3 import invert, se3_exp, se3_log
from diffloc.io.dataset import read_dataset_info, read_sequence
from diffloc.io.sequence import SequenceData
from diffloc.maps.surfel import SurfelMap
from diffloc.optim.rig_calibration import RigCalibrationConfig, RigCalibrationResult, calibrate_rig
from diffloc.optim.surfel_cost import optimize_keyframe_poses
from diffloc.pipeline.database_stage import (
    DatabaseConfig,
    database_builder,
    keyframe_frames,
    keyframe_position_rmse,
)
from diffloc.sim.config import IndoorSceneConfig, OutdoorSceneConfig
from diffloc.sim.scene import generate_world
from diffloc.sim.trajectory import interpolate_pose, make_trajectory

RESULT = Path("experiments/results/bench_rig_calibration.json")
F64 = torch.float64


def magnitude(T: torch.Tensor) -> tuple[float, float]:
    """Translation (cm) and rotation angle (deg) of a (4, 4) transform."""
    xi = se3_log(T)
    return round(float(T[:3, 3].norm()) * 100, 4), round(math.degrees(float(xi[3:].norm())), 4)


def rotation_rmse_deg(T_wc: torch.Tensor, T_ref: torch.Tensor) -> float:
    """Root mean square rotation angle (deg) between (K, 4, 4) pose sets."""
    angles = se3_log(invert(T_ref) @ T_wc)[:, 3:].norm(dim=-1)
    return round(math.degrees(float(angles.square().mean().sqrt())), 4)


def continuous_trajectory(
    root: Path, sequence: str, rate_hz: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Times (M,) and body poses T_wb (M, 4, 4) of a simulated sequence at ``rate_hz``,
    regenerated from the dataset's scene configuration (same route, sways and bob)."""
    info = read_dataset_info(root)["config"]
    schema = {"indoor": IndoorSceneConfig, "outdoor": OutdoorSceneConfig}[info["name"]]
    cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(schema), info))
    seq = next(s for s in cfg.sequences if s.name == sequence)
    if seq.frame_rate_hz > 0:
        raise ValueError(f"sequence {sequence!r} overrides the frame rate; not supported here")
    world = generate_world(cfg.name, cfg.seed, cfg.layout)
    times, T_wb = make_trajectory(
        world.route,
        replace(cfg.trajectory, frame_rate_hz=rate_hz),
        lateral_offset_m=seq.lateral_offset_m,
        reverse=seq.reverse,
        phase=seq.sway_phase,
    )
    return torch.as_tensor(times, dtype=F64), T_wb.to(F64)


def sample_indices(times: torch.Tensor, query: torch.Tensor) -> torch.Tensor:
    """(K,) index of the sample of ``times`` (N,) at each ``query`` (K,) time (the dense rate
    must be a multiple of the image rate)."""
    index = torch.searchsorted(times, query).clamp(max=len(times) - 1)
    nearest = torch.where((times[index] - query).abs() < 1e-6, index, index - 1)
    if not bool(((times[nearest] - query).abs() < 1e-6).all()):
        raise ValueError("the dense trajectory has no sample at some keyframe time")
    return nearest


def build_at(
    seq: SequenceData, T_wc: torch.Tensor, db_cfg: DatabaseConfig, surfels: SurfelMap
) -> tuple[VisualDatabase, torch.Tensor, float]:
    """The database of the sequence's images placed at ``T_wc`` (N, 4, 4): the database, its
    keyframes' (K,) frame indices and the build time in seconds."""
    start = time.perf_counter()
    db = database_builder(db_cfg, surfels).build(replace(seq, T_wc=T_wc), show_progress=False)
    return db, keyframe_frames(db, T_wc), time.perf_counter() - start


def score(
    fit: RigCalibrationResult,
    T_initial: torch.Tensor,
    T_truth: torch.Tensor,
    E: torch.Tensor,
    dt_err: float | None,
) -> dict:
    """Errors of a calibration against the ground truth: the only place the truth is read.

    Args:
        fit: the calibration.
        T_initial: (K, 4, 4) the miscalibrated keyframe poses it started from.
        T_truth: (K, 4, 4) the true keyframe poses.
        E: (4, 4) the true extrinsic error.
        dt_err: the true time offset, seconds (``None``: not estimated).
    """
    recovered_cm, recovered_deg = magnitude(invert(fit.T_correction))
    residual_cm, residual_deg = magnitude(fit.T_correction @ E)
    figures = {
        "kf_pos_rmse_before_cm": round(keyframe_position_rmse(T_initial, T_truth) * 100, 4),
        "kf_rot_rmse_before_deg": rotation_rmse_deg(T_initial, T_truth),
        "kf_pos_rmse_after_cm": round(keyframe_position_rmse(fit.T_wc, T_truth) * 100, 4),
        "kf_rot_rmse_after_deg": rotation_rmse_deg(fit.T_wc, T_truth),
        "extrinsic_recovered_cm": recovered_cm,
        "extrinsic_recovered_deg": recovered_deg,
        "extrinsic_residual_cm": residual_cm,
        "extrinsic_residual_deg": residual_deg,
    }
    if dt_err is not None:
        figures["dt_recovered_ms"] = round(-fit.dt * 1e3, 3)
        figures["dt_residual_ms"] = round((fit.dt + dt_err) * 1e3, 3)
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/indoor_seed0"))
    parser.add_argument("--association", choices=("epipolar", "projection"), default="epipolar")
    parser.add_argument("--translation-cm", type=float, default=5.0)
    parser.add_argument("--rotation-deg", type=float, default=1.0)
    parser.add_argument("--dt-ms", type=float, default=30.0)
    parser.add_argument("--dense-rate-hz", type=float, default=100.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=RESULT)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    wall_start = time.perf_counter()

    root = args.data
    db_cfg = DatabaseConfig(builder=BuilderConfig(association=args.association))
    surfels = SurfelMap.load(root / "map" / "surfel_map.ply")
    centers, normals = surfels.centers.to(F64), surfels.normals.to(F64)
    seq = read_sequence(root, db_cfg.sequence)
    times = torch.as_tensor(seq.timestamps, dtype=F64)
    T_bc = seq.T_body_camera.to(F64)
    T_true = seq.T_wc.to(F64)  # ground truth: the cameras of the images (scoring, oracle build)
    T_wb = T_true @ invert(T_bc)  # the body trajectory at the image times (right by premise)
    dense_times, dense_T_wb = continuous_trajectory(root, seq.name, args.dense_rate_hz)
    dense_deviation = float((dense_T_wb[sample_indices(dense_times, times)] - T_wb).abs().max())

    g = torch.Generator().manual_seed(args.seed)
    directions = torch.randn(2, 3, generator=g, dtype=F64)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    v = args.translation_cm / 100 * directions[0]
    w = math.radians(args.rotation_deg) * directions[1]
    E = se3_exp(torch.cat((v, w)))
    dt_err = args.dt_ms / 1e3
    true_cm, true_deg = magnitude(E)
    # The user's poses of every image: body time t_k + dt_err, extrinsic T_bc E.
    miscalibrated = interpolate_pose(dense_times, dense_T_wb, times + dt_err) @ T_bc @ E
    extrinsic_only = T_wb @ T_bc @ E

    databases = {}  # name: (database, keyframe frames), built at the poses the user has
    build_s = {}
    for name, T_wc in (("miscalibrated", miscalibrated), ("extrinsic_only", extrinsic_only)):
        db, frames, build_s[name] = build_at(seq, T_wc, db_cfg, surfels)
        databases[name] = (db, frames)
        print(json.dumps({"built": name, "seconds": round(build_s[name], 1)}), flush=True)
    # The former, oracle setting: associations made at the true poses.
    oracle_db, oracle_frames, build_s["oracle_true_poses"] = build_at(seq, T_true, db_cfg, surfels)
    print(
        json.dumps(
            {"built": "oracle_true_poses", "seconds": round(build_s["oracle_true_poses"], 1)}
        ),
        flush=True,
    )

    result: dict = {
        "dataset": str(root),
        "association": args.association,
        "image_interval_s": round(float(times.diff().mean()), 4),
        "dense_rate_hz": args.dense_rate_hz,
        "dense_trajectory_max_deviation": dense_deviation,
        "body_trajectory": "exact (simulator): the scenario's premise, only the rig is wrong",
        "threads": args.threads,
        "load_average_1min": os.getloadavg()[0],
        "extrinsic_error_true_cm": true_cm,
        "extrinsic_error_true_deg": true_deg,
        "dt_true_ms": args.dt_ms,
        "build_s": {name: round(s, 1) for name, s in build_s.items()},
        "runs": {},
    }
    trajectories = {"image": (T_wb, times), "dense": (dense_T_wb, dense_times)}
    runs = {  # name: (database, user's poses of every image, trajectory, config)
        "image_rate": ("miscalibrated", miscalibrated, "image", RigCalibrationConfig()),
        "dense": ("miscalibrated", miscalibrated, "dense", RigCalibrationConfig()),
        "extrinsic_only": (
            "extrinsic_only",
            extrinsic_only,
            None,
            RigCalibrationConfig(estimate_time_offset=False),
        ),
    }
    for oracle in (False, True):
        prefix = "oracle_" if oracle else ""
        for name, (database, T_user, trajectory, config) in runs.items():
            db, frames = (oracle_db, oracle_frames) if oracle else databases[database]
            if oracle:
                db.T_wc = T_user[frames]  # true-pose associations under the user's poses
            body, body_times, samples = None, None, None
            if trajectory is not None:
                body, body_times = trajectories[trajectory]
                samples = (
                    frames if trajectory == "image" else sample_indices(body_times, times[frames])
                )
            start = time.perf_counter()
            fit = calibrate_rig(db, centers, normals, body, body_times, samples, config)
            elapsed_ms = (time.perf_counter() - start) * 1e3
            figures = {
                "oracle": oracle,
                "keyframes": db.num_keyframes,
                **score(
                    fit,
                    T_user[frames],
                    T_true[frames],
                    E,
                    dt_err if config.estimate_time_offset else None,
                ),
                "calibrate_ms": round(elapsed_ms, 1),
                "iterations": fit.iterations,
                "converged": fit.converged,
                "pairs": fit.num_pairs,
                "initial_cost": round(fit.initial_cost, 1),
                "final_cost": round(fit.cost, 1),
                "std": [float(f"{x:.3g}") for x in fit.std.tolist()],
            }
            if config.estimate_time_offset:
                figures["dt_correlation"] = [round(c, 3) for c in fit.dt_correlation.tolist()]
            result["runs"][prefix + name] = figures
            print(json.dumps({"run": prefix + name, **figures}), flush=True)

        db, frames = (oracle_db, oracle_frames) if oracle else databases["miscalibrated"]
        db.T_wc = miscalibrated[frames]
        start = time.perf_counter()
        T_per_keyframe, per_keyframe = optimize_keyframe_poses(db, centers, normals, db_cfg.optim)
        per_keyframe_ms = (time.perf_counter() - start) * 1e3
        figures = {
            "oracle": oracle,
            "keyframes": db.num_keyframes,
            "kf_pos_rmse_after_cm": round(
                keyframe_position_rmse(T_per_keyframe, T_true[frames]) * 100, 4
            ),
            "kf_rot_rmse_after_deg": rotation_rmse_deg(T_per_keyframe, T_true[frames]),
            "per_keyframe_ms": round(per_keyframe_ms, 1),
            "iterations": int(per_keyframe.iterations.max()),
            "speedup_vs_per_keyframe": round(
                per_keyframe_ms / result["runs"][prefix + "image_rate"]["calibrate_ms"], 1
            ),
        }
        result["runs"][prefix + "per_keyframe"] = figures
        print(json.dumps({"run": prefix + "per_keyframe", **figures}), flush=True)

    result["load_average_1min_after"] = os.getloadavg()[0]
    result["wall_s"] = round(time.perf_counter() - wall_start, 1)
    print(write_benchmark(args.out, result))


if __name__ == "__main__":
    main()
