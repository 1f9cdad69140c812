"""Benchmark PnP RANSAC against poselib, pycolmap and OpenCV; the last stdout line is JSON.

Usage:
    python experiments/bench_pnp.py [--trials 50] [--points 1000] [--threads 2]
        [--out experiments/results/bench_pnp.json]

Every method sees identical synthetic problems: ``--points`` world points in front of a
640x480 pinhole camera (fx = fy = 500, principal point at the centre) at depths uniform in
2-20 m, seen from a random camera pose (uniform rotation, position in [-10, 10]^3 m);
keypoints are the projections plus 1 px Gaussian noise, and a fraction (0.25 / 0.5 / 0.75) of
them is replaced by outliers uniform in the image. All methods run with the same RANSAC
settings: 4 px threshold, confidence 0.9999, 100 to 10000 minimal samples, no multiplier on
the adaptive number of samples (poselib's and COLMAP's defaults triple it), then their own
non-linear refinement on the inliers. ``poselib_default`` is poselib with its default RANSAC
options (except the 4 px threshold) for reference.

Methods and thread counts:
    ``ours``: :func:`diffloc.reloc.pnp.solve_pnp_ransac` with its default config, which runs
    torch with one intra-op thread (like poselib, single-threaded C++); ``ours_mt``: the same
    with ``num_threads=None`` under ``--threads`` torch threads;
    ``poselib``: ``poselib.estimate_absolute_pose`` (LO-RANSAC, Lambda Twist P3P, Cauchy
    bundle adjustment); ``pycolmap``: ``pycolmap.estimate_and_refine_absolute_pose`` (one
    RANSAC thread); ``opencv``: ``cv2.solvePnPRansac(SOLVEPNP_P3P)`` then
    ``cv2.solvePnPRefineLM`` on the inliers (``cv2.setNumThreads(1)``).

Keys (``{method}_{metric}_{outlier ratio}``): ``success`` is the fraction of trials with
rotation error < 5 deg and camera-centre error < 0.5 m (a wrong RANSAC model misses both by
far; correct ones are within millimetres); ``rot_err_deg`` and ``trans_err_m`` are medians of
the rotation error and camera-centre error (m) over all trials; ``ms`` is the median wall
time of one call in milliseconds. ``ours_vs_poselib_ms_{r}`` is the time ratio and
``ours_vs_poselib_paired_ms_{r}`` the median over trials of the per-trial ratio (both ran on
the same problem moments apart: robust to load that drifts during the run).
``load_average_1min`` records how busy the (shared) machine was at the start.

Motion-only refinement (``refine`` keys, same problems): both refiners start from the true
pose perturbed by 5 deg about a random axis and 0.3 m in a random direction and see the same
correspondences, the true inliers (the keypoints that were not replaced by outliers).
``ours_refine``: :func:`diffloc.optim.motion_cost.refine_pose` with its default config
(seed 1 Eq. 5: ORB-SLAM's 4 rounds of at most 10 LM iterations, Huber ``sqrt(5.991)`` px,
outliers re-classified after each round; torch with one thread); ``poselib_refine``:
``poselib.refine_absolute_pose`` with a Huber loss of the same scale and at most 40
iterations. Keys ``{ours,poselib}_refine_{ms,rot_err_deg,trans_err_m}_{r}`` (medians as
above), ``ours_vs_poselib_refine_ms_{r}`` and ``ours_vs_poselib_paired_refine_ms_{r}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import math
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import poselib
import pycolmap
import torch

from diffloc.eval.report_files import write_benchmark
from diffloc.geometry.camera import PinholeCamera
from diffloc.optim.motion_cost import refine_pose
from diffloc.reloc.pnp import PnPRansacConfig, solve_pnp_ransac

WIDTH, HEIGHT, FOCAL = 640, 480, 500.0
CX, CY = (WIDTH - 1) / 2.0, (HEIGHT - 1) / 2.0
NOISE_PX = 1.0
THRESHOLD_PX = 4.0
CONFIDENCE = 0.9999
MIN_SAMPLES, MAX_SAMPLES = 100, 10_000
SUCCESS_ROT_DEG, SUCCESS_TRANS_M = 5.0, 0.5
RATIOS = (0.25, 0.5, 0.75)
K = np.array([[FOCAL, 0.0, CX], [0.0, FOCAL, CY], [0.0, 0.0, 1.0]])

REFINE_START_DEG, REFINE_START_M = 5.0, 0.3
HUBER_PX = math.sqrt(5.991)

# X (N,3), uv (N,2), R_cw, t_cw, true inlier mask (N,)
Problem = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
Solver = Callable[[np.ndarray, np.ndarray, int], tuple[np.ndarray, np.ndarray]]
# (X, uv, R_cw, t_cw of the start) -> refined (R_cw, t_cw)
Refiner = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def make_problem(rng: np.random.Generator, n: int, outlier_ratio: float) -> Problem:
    """World points, noisy keypoints with outliers, the true world-to-camera pose and the
    mask of the true inliers."""
    uv = rng.uniform((-0.5, -0.5), (WIDTH - 0.5, HEIGHT - 0.5), size=(n, 2))
    depth = rng.uniform(2.0, 20.0, size=n)
    points_cam = np.column_stack(((uv - (CX, CY)) / FOCAL * depth[:, None], depth))
    q = rng.normal(size=4)
    R_cw = quaternion_matrix(q / np.linalg.norm(q))
    t_cw = rng.uniform(-10.0, 10.0, size=3)
    points_world = (points_cam - t_cw) @ R_cw  # R^T (X_c - t)
    keypoints = uv + rng.normal(scale=NOISE_PX, size=(n, 2))
    outlier = rng.random(n) < outlier_ratio
    keypoints[outlier] = rng.uniform((-0.5, -0.5), (WIDTH - 0.5, HEIGHT - 0.5), (outlier.sum(), 2))
    return points_world, keypoints, R_cw, t_cw, ~outlier


def perturbed_start(
    rng: np.random.Generator, R_cw: np.ndarray, t_cw: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The camera rotated by REFINE_START_DEG about a random axis and moved REFINE_START_M."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    half = math.radians(REFINE_START_DEG) / 2.0
    dR = quaternion_matrix(np.concatenate(([math.cos(half)], math.sin(half) * axis)))
    step = rng.normal(size=3)
    centre = -R_cw.T @ t_cw + REFINE_START_M * step / np.linalg.norm(step)
    R_start = dR @ R_cw
    return R_start, -R_start @ centre


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def pose_errors(R: np.ndarray, t: np.ndarray, R_true: np.ndarray, t_true: np.ndarray):
    """Rotation error (deg) and camera-centre error (m) of a world-to-camera pose."""
    cos = np.clip((np.trace(R.T @ R_true) - 1.0) / 2.0, -1.0, 1.0)
    centre, centre_true = -R.T @ t, -R_true.T @ t_true
    return math.degrees(math.acos(cos)), float(np.linalg.norm(centre - centre_true))


def torch_camera() -> PinholeCamera:
    return PinholeCamera(
        fx=torch.tensor(FOCAL, dtype=torch.float64),
        fy=torch.tensor(FOCAL, dtype=torch.float64),
        cx=torch.tensor(CX, dtype=torch.float64),
        cy=torch.tensor(CY, dtype=torch.float64),
        width=WIDTH,
        height=HEIGHT,
    )


def make_ours(threads: int | None) -> Solver:
    """Our solver; ``threads=None``: the default config (one intra-op thread inside)."""
    camera = torch_camera()
    config = PnPRansacConfig(
        threshold_px=THRESHOLD_PX,
        confidence=CONFIDENCE,
        min_iterations=MIN_SAMPLES,
        max_iterations=MAX_SAMPLES,
    )
    if threads is not None:
        config = dataclasses.replace(config, num_threads=None)

    def solve(X: np.ndarray, uv: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
        if threads is not None:
            torch.set_num_threads(threads)
        generator = torch.Generator().manual_seed(seed)
        result = solve_pnp_ransac(
            torch.from_numpy(X), torch.from_numpy(uv), camera, config, generator
        )
        T_wc = result.T_wc.numpy()
        R_cw = T_wc[:3, :3].T
        return R_cw, -R_cw @ T_wc[:3, 3]

    return solve


POSELIB_CAMERA = {
    "model": "PINHOLE",
    "width": WIDTH,
    "height": HEIGHT,
    "params": [FOCAL, FOCAL, CX, CY],
}


def ours_refine(
    X: np.ndarray, uv: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`refine_pose` from the start ``(R_cw, t_cw)`` with one torch thread (``ours_mt``
    leaves two set); returns the refined pair."""
    torch.set_num_threads(1)
    T_wc = np.eye(4)
    T_wc[:3, :3], T_wc[:3, 3] = R_cw.T, -R_cw.T @ t_cw
    result = refine_pose(
        REFINE_CAMERA, torch.from_numpy(T_wc), torch.from_numpy(X), torch.from_numpy(uv)
    )
    T = result.T_wc.detach().numpy()
    return T[:3, :3].T, -T[:3, :3].T @ T[:3, 3]


def poselib_refine(
    X: np.ndarray, uv: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``poselib.refine_absolute_pose`` (Huber, same scale) from the start ``(R_cw, t_cw)``."""
    pose = poselib.CameraPose()
    pose.R, pose.t = R_cw, t_cw
    options = {"loss_type": "HUBER", "loss_scale": HUBER_PX, "max_iterations": 40}
    refined, _ = poselib.refine_absolute_pose(uv, X, pose, POSELIB_CAMERA, options)
    return refined.R, refined.t


REFINE_CAMERA = torch_camera()
REFINERS: dict[str, Refiner] = {"ours_refine": ours_refine, "poselib_refine": poselib_refine}


def make_poselib(defaults: bool) -> Solver:
    camera = POSELIB_CAMERA
    options = {"max_reproj_error": THRESHOLD_PX}
    if not defaults:
        options |= {
            "success_prob": CONFIDENCE,
            "min_iterations": MIN_SAMPLES,
            "max_iterations": MAX_SAMPLES,
            "dyn_num_trials_mult": 1.0,
        }

    def solve(X: np.ndarray, uv: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
        pose, _ = poselib.estimate_absolute_pose(uv, X, camera, options | {"seed": seed}, {})
        return pose.R, pose.t

    return solve


def make_pycolmap() -> Solver:
    camera = pycolmap.Camera(
        model="PINHOLE", width=WIDTH, height=HEIGHT, params=[FOCAL, FOCAL, CX, CY]
    )
    options = pycolmap.AbsolutePoseEstimationOptions()
    options.ransac.max_error = THRESHOLD_PX
    options.ransac.confidence = CONFIDENCE
    options.ransac.min_num_trials = MIN_SAMPLES
    options.ransac.max_num_trials = MAX_SAMPLES
    options.ransac.dyn_num_trials_multiplier = 1.0
    options.ransac.num_threads = 1

    def solve(X: np.ndarray, uv: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
        options.ransac.random_seed = seed
        result = pycolmap.estimate_and_refine_absolute_pose(uv, X, camera, options)
        if result is None:
            return np.eye(3), np.full(3, 1e9)
        pose = result["cam_from_world"]
        return pose.rotation.matrix(), np.asarray(pose.translation)

    return solve


def solve_opencv(X: np.ndarray, uv: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    cv2.setRNGSeed(seed)
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        X,
        uv,
        K,
        None,
        iterationsCount=MAX_SAMPLES,
        reprojectionError=THRESHOLD_PX,
        confidence=CONFIDENCE,
        flags=cv2.SOLVEPNP_P3P,
    )
    if not ok or inliers is None or len(inliers) < 4:
        return np.eye(3), np.full(3, 1e9)
    idx = inliers[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(X[idx], uv[idx], K, None, rvec, tvec)
    return cv2.Rodrigues(rvec)[0], tvec[:, 0]


def run(methods: dict[str, Solver], trials: int, points: int) -> dict[str, float]:
    """Errors and timings of every method (and refiner) on the same problems, per outlier
    ratio."""
    rng = np.random.default_rng(0)
    start_rng = np.random.default_rng(1)  # separate, so the problems do not depend on it
    result: dict[str, float] = {}
    for ratio in RATIOS:
        stats = {name: {"rot": [], "trans": [], "ms": []} for name in (*methods, *REFINERS)}
        for trial in range(trials):
            X, uv, R_true, t_true, inlier = make_problem(rng, points, ratio)
            R_start, t_start = perturbed_start(start_rng, R_true, t_true)
            X_in, uv_in = np.ascontiguousarray(X[inlier]), np.ascontiguousarray(uv[inlier])
            calls: dict[str, Callable[[], tuple[np.ndarray, np.ndarray]]] = {
                name: functools.partial(solve, X, uv, trial) for name, solve in methods.items()
            }
            for name, refine in REFINERS.items():
                calls[name] = functools.partial(refine, X_in, uv_in, R_start, t_start)
            names = list(calls)
            rotation = trial % len(names)  # vary the order against drifting machine load
            for name in names[rotation:] + names[:rotation]:
                start = time.perf_counter()
                R, t = calls[name]()
                stats[name]["ms"].append(1e3 * (time.perf_counter() - start))
                rot, trans = pose_errors(R, t, R_true, t_true)
                stats[name]["rot"].append(rot)
                stats[name]["trans"].append(trans)
        result[f"ours_vs_poselib_paired_refine_ms_{ratio}"] = paired_ratio(
            stats["ours_refine"]["ms"], stats["poselib_refine"]["ms"]
        )
        result[f"ours_vs_poselib_paired_ms_{ratio}"] = paired_ratio(
            stats["ours"]["ms"], stats["poselib"]["ms"]
        )
        for name in REFINERS:  # refine keys: {method}_refine_{metric}_{ratio}
            s = stats.pop(name)
            method = name.removesuffix("_refine")
            result[f"{method}_refine_rot_err_deg_{ratio}"] = round(statistics.median(s["rot"]), 5)
            result[f"{method}_refine_trans_err_m_{ratio}"] = round(statistics.median(s["trans"]), 6)
            result[f"{method}_refine_ms_{ratio}"] = round(statistics.median(s["ms"]), 3)
        result[f"ours_vs_poselib_refine_ms_{ratio}"] = round(
            result[f"ours_refine_ms_{ratio}"] / result[f"poselib_refine_ms_{ratio}"], 3
        )
        for name, s in stats.items():
            ok = [
                r < SUCCESS_ROT_DEG and d < SUCCESS_TRANS_M
                for r, d in zip(s["rot"], s["trans"], strict=True)
            ]
            result[f"{name}_success_{ratio}"] = round(sum(ok) / trials, 4)
            result[f"{name}_rot_err_deg_{ratio}"] = round(statistics.median(s["rot"]), 5)
            result[f"{name}_trans_err_m_{ratio}"] = round(statistics.median(s["trans"]), 6)
            result[f"{name}_ms_{ratio}"] = round(statistics.median(s["ms"]), 3)
        result[f"ours_vs_poselib_ms_{ratio}"] = round(
            result[f"ours_ms_{ratio}"] / result[f"poselib_ms_{ratio}"], 3
        )
    return result


def paired_ratio(ours_ms: list[float], peer_ms: list[float]) -> float:
    """Median over trials of the per-trial time ratio."""
    return round(statistics.median(a / b for a, b in zip(ours_ms, peer_ms, strict=True)), 3)


def markdown_table(result: dict[str, float], methods: list[str]) -> str:
    lines = [
        "| method | outliers | success | median rot (deg) | median centre (m) | median ms |",
        "|---|---|---|---|---|---|",
    ]
    for ratio in RATIOS:
        for name in methods:
            lines.append(
                f"| {name} | {ratio} | {result[f'{name}_success_{ratio}']:.2f} "
                f"| {result[f'{name}_rot_err_deg_{ratio}']:.4f} "
                f"| {result[f'{name}_trans_err_m_{ratio}']:.4f} "
                f"| {result[f'{name}_ms_{ratio}']:.2f} |"
            )
    lines += [
        "",
        "| refiner | outliers | median rot (deg) | median centre (m) | median ms |",
        "|---|---|---|---|---|",
    ]
    for ratio in RATIOS:
        for name in ("ours", "poselib"):
            lines.append(
                f"| {name} | {ratio} | {result[f'{name}_refine_rot_err_deg_{ratio}']:.4f} "
                f"| {result[f'{name}_refine_trans_err_m_{ratio}']:.4f} "
                f"| {result[f'{name}_refine_ms_{ratio}']:.2f} |"
            )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=50)
    parser.add_argument("--points", type=int, default=1000)
    parser.add_argument("--threads", type=int, default=2, help="torch threads of 'ours_mt'")
    parser.add_argument("--out", type=Path, default=Path("experiments/results/bench_pnp.json"))
    args = parser.parse_args()
    cv2.setNumThreads(1)
    methods: dict[str, Solver] = {
        "ours": make_ours(None),
        "ours_mt": make_ours(args.threads),
        "poselib": make_poselib(defaults=False),
        "poselib_default": make_poselib(defaults=True),
        "pycolmap": make_pycolmap(),
        "opencv": solve_opencv,
    }
    warm = make_problem(np.random.default_rng(1), args.points, 0.5)
    for solve in methods.values():
        solve(warm[0], warm[1], 0)
    for refine in REFINERS.values():
        refine(warm[0][warm[4]], warm[1][warm[4]], warm[2], warm[3])
    result: dict[str, float] = {
        "trials": args.trials,
        "points": args.points,
        "ours_threads": 1,
        "ours_mt_threads": args.threads,
        "poselib_threads": 1,
        "pycolmap_threads": 1,
        "opencv_threads": cv2.getNumThreads(),
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
    result |= run(methods, args.trials, args.points)
    print(markdown_table(result, list(methods)))
    print(write_benchmark(args.out, result))


if __name__ == "__main__":
    main()
