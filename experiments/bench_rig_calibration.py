"""Benchmark the rig calibration (shared extrinsic + time offset); last stdout line is JSON.

Usage:
    python experiments/bench_rig_calibration.py [--data data/indoor_seed0] [--database DIR]
        [--translation-cm 5] [--rotation-deg 1] [--dt-ms 30] [--dense-rate-hz 100]
        [--seed 0] [--threads 1] [--out experiments/results/bench_rig_calibration.json]

The database (default ``<data>/db/xfeat_sigma_0_prior_0_epipolar`` when built, else
``<data>/db/xfeat_sigma_0_prior_0``) holds the ground-truth keyframe poses of the mapping sequence,
``T_wc_k = T_wb(t_k) T_bc`` (``read_sequence``: image times ``t_k``, ``T_wc``, ``T_bc``). Its
keyframe poses are replaced by those of a miscalibrated rig, ``T_wb(t_k + dt_err) T_bc E``
(``E``: ``--translation-cm`` and ``--rotation-deg`` in seeded random directions, camera
frame), with ``T_wb(t)`` of the simulator's continuous trajectory (regenerated from the
dataset's scene configuration at ``--dense-rate-hz``, checked against the ground truth at the
image times). :func:`~diffloc.optim.rig_calibration.calibrate_rig` should return ``C = E^-1``
and ``dt = -dt_err``. Runs, each reporting ``kf_pos_rmse_before_cm`` / ``_after_cm`` and
``kf_rot_rmse_before_deg`` / ``_after_deg`` against ground truth, ``extrinsic_recovered_cm`` /
``_deg`` (``|C^-1|``, to compare with ``extrinsic_error_true_*`` ``|E|``),
``extrinsic_residual_cm`` / ``_deg`` (``|C E|``: what is left of the error),
``dt_recovered_ms`` (``-dt``, to compare with ``dt_true_ms``), ``dt_residual_ms``,
``calibrate_ms``, LM ``iterations``, ``pairs``, costs and the ``std`` / ``dt_correlation``
diagnostics:

- no prefix: the body trajectory at the image times only (the ground truth of the dataset:
  2 Hz on the default scene), as a user with one body pose per image would have it;
- ``dense_``: the body trajectory at ``--dense-rate-hz`` (body twists from close samples);
- ``extrinsic_only_``: ``dt_err = 0`` and the 6-DoF mode;
- ``per_keyframe_*``: the peer, seed 1's per-keyframe optimisation
  (:func:`~diffloc.optim.surfel_cost.optimize_keyframe_poses`, ``DatabaseConfig().optim``) on
  the miscalibrated database: RMSE, time and ``speedup_vs_per_keyframe`` (its time over the
  calibration's).
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
from diffloc.geometry.se3 import invert, se3_exp, se3_log
from diffloc.io.atomic import atomic_write_text
from diffloc.io.dataset import read_dataset_info, read_sequence
from diffloc.maps.surfel import SurfelMap
from diffloc.optim.rig_calibration import RigCalibrationConfig, calibrate_rig
from diffloc.optim.surfel_cost import optimize_keyframe_poses
from diffloc.pipeline.database_stage import DatabaseConfig, database_dir, keyframe_position_rmse
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data/indoor_seed0"))
    parser.add_argument("--database", type=Path, default=None)
    parser.add_argument("--translation-cm", type=float, default=5.0)
    parser.add_argument("--rotation-deg", type=float, default=1.0)
    parser.add_argument("--dt-ms", type=float, default=30.0)
    parser.add_argument("--dense-rate-hz", type=float, default=100.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=RESULT)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    root = args.data
    folder = args.database
    if folder is None:
        epipolar = database_dir(root, DatabaseConfig(builder=BuilderConfig(association="epipolar")))
        projection = database_dir(root, DatabaseConfig())
        folder = epipolar if (epipolar / "build_db.json").is_file() else projection
    built = json.loads((folder / "build_db.json").read_text())
    if built["config"]["noise_sigma"] != 0:
        raise ValueError(f"{folder} was built with noisy poses; the benchmark needs sigma 0")
    db = VisualDatabase.load(folder / "database")
    surfels = SurfelMap.load(root / "map" / "surfel_map.ply")
    centers, normals = surfels.centers.to(F64), surfels.normals.to(F64)
    seq = read_sequence(root, built["config"]["sequence"])
    times = torch.as_tensor(seq.timestamps, dtype=F64)
    T_bc = seq.T_body_camera.to(F64)
    T_wb = seq.T_wc.to(F64) @ invert(T_bc)
    frames = torch.tensor(built["keyframe_frames"], dtype=torch.int64)
    T_truth = seq.T_wc.to(F64)[frames]
    gt_deviation = float((db.T_wc - T_truth).abs().max())

    dense_times, dense_T_wb = continuous_trajectory(root, seq.name, args.dense_rate_hz)
    dense_frames = sample_indices(dense_times, times[frames])
    dense_deviation = float((dense_T_wb[dense_frames] - T_wb[frames]).abs().max())

    g = torch.Generator().manual_seed(args.seed)
    directions = torch.randn(2, 3, generator=g, dtype=F64)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    v = args.translation_cm / 100 * directions[0]
    w = math.radians(args.rotation_deg) * directions[1]
    E = se3_exp(torch.cat((v, w)))
    dt_err = args.dt_ms / 1e3
    true_cm, true_deg = magnitude(E)
    result: dict = {
        "database": str(folder),
        "keyframes": db.num_keyframes,
        "image_interval_s": round(float(times.diff().mean()), 4),
        "dense_rate_hz": args.dense_rate_hz,
        "gt_pose_max_deviation": gt_deviation,
        "dense_trajectory_max_deviation": dense_deviation,
        "threads": args.threads,
        "load_average_1min": os.getloadavg()[0],
        "extrinsic_error_true_cm": true_cm,
        "extrinsic_error_true_deg": true_deg,
        "dt_true_ms": args.dt_ms,
    }

    # Images at body time t_k, database poses from body time t_k + dt_err through T_bc E.
    miscalibrated = interpolate_pose(dense_times, dense_T_wb, times[frames] + dt_err) @ T_bc @ E
    extrinsic_only = T_wb[frames] @ T_bc @ E
    runs = {  # prefix: (database poses, trajectory, its times, keyframe samples, config)
        "": (miscalibrated, T_wb, times, frames, RigCalibrationConfig()),
        "dense_": (miscalibrated, dense_T_wb, dense_times, dense_frames, RigCalibrationConfig()),
        "extrinsic_only_": (
            extrinsic_only,
            None,
            None,
            None,
            RigCalibrationConfig(estimate_time_offset=False),
        ),
    }
    for prefix, (T_wc, trajectory, trajectory_times, samples, config) in runs.items():
        db.T_wc = T_wc
        start = time.perf_counter()
        fit = calibrate_rig(db, centers, normals, trajectory, trajectory_times, samples, config)
        elapsed_ms = (time.perf_counter() - start) * 1e3
        recovered_cm, recovered_deg = magnitude(invert(fit.T_correction))
        residual_cm, residual_deg = magnitude(fit.T_correction @ E)
        figures = {
            "kf_pos_rmse_before_cm": round(keyframe_position_rmse(T_wc, T_truth) * 100, 4),
            "kf_rot_rmse_before_deg": rotation_rmse_deg(T_wc, T_truth),
            "kf_pos_rmse_after_cm": round(keyframe_position_rmse(fit.T_wc, T_truth) * 100, 4),
            "kf_rot_rmse_after_deg": rotation_rmse_deg(fit.T_wc, T_truth),
            "extrinsic_recovered_cm": recovered_cm,
            "extrinsic_recovered_deg": recovered_deg,
            "extrinsic_residual_cm": residual_cm,
            "extrinsic_residual_deg": residual_deg,
            "calibrate_ms": round(elapsed_ms, 1),
            "iterations": fit.iterations,
            "converged": fit.converged,
            "pairs": fit.num_pairs,
            "initial_cost": round(fit.initial_cost, 1),
            "final_cost": round(fit.cost, 1),
            "std": [float(f"{x:.3g}") for x in fit.std.tolist()],
        }
        if config.estimate_time_offset:
            figures["dt_recovered_ms"] = round(-fit.dt * 1e3, 3)
            figures["dt_residual_ms"] = round((fit.dt + dt_err) * 1e3, 3)
            figures["dt_correlation"] = [round(c, 3) for c in fit.dt_correlation.tolist()]
        result.update({prefix + k: x for k, x in figures.items()})
        print(json.dumps({prefix + k: x for k, x in figures.items()}), flush=True)

    db.T_wc = miscalibrated
    start = time.perf_counter()
    T_per_keyframe, per_keyframe = optimize_keyframe_poses(
        db, centers, normals, DatabaseConfig().optim
    )
    per_keyframe_ms = (time.perf_counter() - start) * 1e3
    result.update(
        {
            "per_keyframe_kf_pos_rmse_after_cm": round(
                keyframe_position_rmse(T_per_keyframe, T_truth) * 100, 4
            ),
            "per_keyframe_kf_rot_rmse_after_deg": rotation_rmse_deg(T_per_keyframe, T_truth),
            "per_keyframe_ms": round(per_keyframe_ms, 1),
            "per_keyframe_iterations": int(per_keyframe.iterations),
            "speedup_vs_per_keyframe": round(per_keyframe_ms / result["calibrate_ms"], 1),
            "load_average_1min_after": os.getloadavg()[0],
        }
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
