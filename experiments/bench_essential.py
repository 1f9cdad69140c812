"""Benchmark the essential check against kornia's essential RANSAC; the last stdout line is JSON.

Usage:
    python experiments/bench_essential.py [--trials 30] [--points 500]
        [--out experiments/results/bench_essential.json]

Every method sees identical synthetic problems, those of ``tests/test_essential_ransac.py``:
``--points`` keypoints uniform in a 640x480 keyframe (fx = fy = 500, principal point at the
centre) at depths uniform in 2-20 m, seen from a query camera 0.5-1 m away in a random
direction and rotated by ~0.1 rad per axis; 1 px Gaussian noise in both images, and a fraction
(0.2 / 0.4 / 0.6) of the query keypoints replaced by outliers uniform in the image. All methods
run with the same RANSAC settings: 3 px Sampson threshold (3 / 500 in normalised
coordinates for kornia, which takes those), confidence 0.999, at most 1024 five-point samples,
the first 128 in one batch, then their own local optimisation and refinement. ``kornia_default`` is
kornia with its default RANSAC options (except the threshold and the seed) for reference.

Methods (torch with one intra-op thread, OpenCV with one thread):
    ``ours``: :func:`diffloc.geometry.essential_ransac.essential_check` with its default config
    (128 to 1024 samples, LO-RANSAC with Gauss-Newton on the Sampson distances);
    ``kornia``: ``kornia.geometry.ransac.RANSAC("essential", ...)`` on normalised coordinates
    (five-point samples, MSAC, Levenberg-Marquardt LO of the eight best minimal models and a
    Cauchy refinement), ``batch_size=128, max_iter=8``; ``kornia_default``: the same with
    ``batch_size="auto", max_iter=10, confidence=0.99``; ``opencv``:
    ``cv2.findEssentialMat(method=cv2.RANSAC, prob=0.999, threshold=3, maxIters=1024)``.

Every estimate is scored the same way: its rotation and translation direction come from
``kornia.geometry.epipolar.motion_from_essential_choose_solution`` on the method's inliers
(the decomposition with most points in front of both cameras); a method that returns no model
scores 180 deg. Keys (``{method}_{metric}_{outlier ratio}``): ``rot_err_deg`` and
``tdir_err_deg`` are the median rotation error and angle between the true and estimated
translation directions, ``*_p90`` their 90th percentiles; ``e_err`` the median unit-norm
Frobenius distance (up to sign) to the true E; ``recall`` and ``precision`` the mean share of
the true inliers that are returned as inliers and of the returned inliers that are true ones;
``ms`` the median wall time of one call in milliseconds. ``ours_vs_kornia_ms_{r}`` is the time
ratio and ``ours_vs_kornia_paired_ms_{r}`` the median over trials of the per-trial ratio
(both ran on the same problem moments apart: robust to load that drifts during the run).
``load_average_1min`` records how busy the (shared) machine was at the start.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import kornia
import torch
from kornia.geometry.epipolar import motion_from_essential_choose_solution
from kornia.geometry.ransac import RANSAC

from diffloc.eval.report_files import write_benchmark
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.essential_ransac import EssentialCheckConfig, essential_check
from diffloc.geometry.se3 import hat, se3_exp

WIDTH, HEIGHT, FOCAL = 640, 480, 500.0
CX, CY = (WIDTH - 1) / 2.0, (HEIGHT - 1) / 2.0
NOISE_PX = 1.0
THRESHOLD_PX = 3.0
CONFIDENCE = 0.999
BATCH, MAX_SAMPLES = 128, 1024
RATIOS = (0.2, 0.4, 0.6)
K = torch.tensor([[FOCAL, 0.0, CX], [0.0, FOCAL, CY], [0.0, 0.0, 1.0]], dtype=torch.float64)
CENTRE = torch.tensor([CX, CY], dtype=torch.float64)


def camera() -> PinholeCamera:
    return PinholeCamera(
        fx=torch.tensor(FOCAL, dtype=torch.float64),
        fy=torch.tensor(FOCAL, dtype=torch.float64),
        cx=torch.tensor(CX, dtype=torch.float64),
        cy=torch.tensor(CY, dtype=torch.float64),
        width=WIDTH,
        height=HEIGHT,
    )


class Problem:
    """Keypoints (N, 2) in the keyframe and the query, the true T_qk and inlier mask (N,)."""

    def __init__(self, n: int, outlier_ratio: float, seed: int, cam: PinholeCamera) -> None:
        g = torch.Generator().manual_seed(seed)
        f64 = torch.float64
        direction = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=f64), dim=0)
        xi = torch.cat(
            (
                direction * (0.5 + 0.5 * torch.rand((), generator=g, dtype=f64)),
                torch.randn(3, generator=g, dtype=f64) * 0.1,
            )
        )
        T_qk = se3_exp(xi)  # keyframe camera -> query camera
        size = torch.tensor([WIDTH, HEIGHT], dtype=f64)
        uv = torch.rand(n, 2, generator=g, dtype=f64) * size - 0.5
        depth = 2.0 + 18.0 * torch.rand(n, generator=g, dtype=f64)
        points_kf = cam.unproject(uv, depth)
        points_q = points_kf @ T_qk[:3, :3].T + T_qk[:3, 3]
        self.uv_kf = cam.project(points_kf)[0] + NOISE_PX * torch.randn(
            n, 2, generator=g, dtype=f64
        )
        uv_q = cam.project(points_q)[0] + NOISE_PX * torch.randn(n, 2, generator=g, dtype=f64)
        outlier = torch.rand(n, generator=g) < outlier_ratio
        random_uv = torch.rand(n, 2, generator=g, dtype=f64) * size - 0.5
        self.uv_q = torch.where(outlier[:, None], random_uv, uv_q)
        self.inliers = ~outlier
        self.R = T_qk[:3, :3]
        self.t = T_qk[:3, 3] / T_qk[:3, 3].norm()
        self.E = hat(self.t) @ self.R / math.sqrt(2.0)  # unit Frobenius norm


# A solver takes a problem and a seed and returns (E (3, 3) or None, inlier mask (N,)).
Solver = Callable[[Problem, int], tuple[torch.Tensor | None, torch.Tensor]]


def make_ours() -> Solver:
    cam = camera()
    config = EssentialCheckConfig(
        threshold_px=THRESHOLD_PX,
        confidence=CONFIDENCE,
        min_iterations=BATCH,
        max_iterations=MAX_SAMPLES,
    )

    def solve(p: Problem, seed: int) -> tuple[torch.Tensor | None, torch.Tensor]:
        r = essential_check(p.uv_kf, p.uv_q, cam, cam, config, torch.Generator().manual_seed(seed))
        return r.E, r.inliers

    return solve


def make_kornia(defaults: bool) -> Solver:
    options = {} if defaults else {"batch_size": BATCH, "max_iter": MAX_SAMPLES // BATCH}
    if not defaults:
        options["confidence"] = CONFIDENCE

    def solve(p: Problem, seed: int) -> tuple[torch.Tensor | None, torch.Tensor]:
        ransac = RANSAC("essential", inl_th=THRESHOLD_PX / FOCAL, seed=seed, **options)
        E, inliers = ransac((p.uv_kf - CENTRE) / FOCAL, (p.uv_q - CENTRE) / FOCAL)
        return (None if not bool(E.abs().sum() > 0) else E), inliers

    return solve


def solve_opencv(p: Problem, seed: int) -> tuple[torch.Tensor | None, torch.Tensor]:
    cv2.setRNGSeed(seed)
    E, mask = cv2.findEssentialMat(
        p.uv_kf.numpy(),
        p.uv_q.numpy(),
        K.numpy(),
        method=cv2.RANSAC,
        prob=CONFIDENCE,
        threshold=THRESHOLD_PX,
        maxIters=MAX_SAMPLES,
    )
    n = p.uv_kf.shape[0]
    if E is None or mask is None:
        return None, torch.zeros(n, dtype=torch.bool)
    return torch.from_numpy(E[:3]), torch.from_numpy(mask[:, 0].astype(bool))


def angle_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    """Angle between unit vectors, accurate at small angles."""
    return math.degrees(2.0 * math.asin(min(1.0, float((a - b).norm()) / 2.0)))


def scores(p: Problem, E: torch.Tensor | None, inliers: torch.Tensor) -> dict[str, float]:
    """Rotation and translation-direction errors (deg), E error, inlier recall and precision."""
    hits = int((inliers & p.inliers).sum())
    out = {
        "recall": hits / max(int(p.inliers.sum()), 1),
        "precision": hits / max(int(inliers.sum()), 1),
        "rot": 180.0,
        "tdir": 180.0,
        "e_err": math.sqrt(2.0),
    }
    if E is None or int(inliers.sum()) < 5:
        return out
    E = E / torch.linalg.matrix_norm(E)
    out["e_err"] = float(min(torch.linalg.matrix_norm(E - p.E), torch.linalg.matrix_norm(E + p.E)))
    R, t, _, _ = motion_from_essential_choose_solution(E, K, K, p.uv_kf[inliers], p.uv_q[inliers])
    chord = float(torch.linalg.matrix_norm(R - p.R)) / math.sqrt(8.0)
    out["rot"] = math.degrees(2.0 * math.asin(min(1.0, chord)))
    out["tdir"] = angle_deg(t[:, 0] / t.norm(), p.t)
    return out


def run(methods: dict[str, Solver], trials: int, points: int) -> dict[str, float]:
    """Accuracy and timings of every method on the same problems, per outlier ratio."""
    cam = camera()
    result: dict[str, float] = {}
    for r_index, ratio in enumerate(RATIOS):
        stats: dict[str, dict[str, list[float]]] = {name: {} for name in methods}
        for trial in range(trials):
            problem = Problem(points, ratio, 1000 * r_index + trial, cam)
            names = list(methods)
            rotation = trial % len(names)  # vary the order against drifting machine load
            for name in names[rotation:] + names[:rotation]:
                start = time.perf_counter()
                E, inliers = methods[name](problem, trial)
                elapsed = 1e3 * (time.perf_counter() - start)
                for key, value in (scores(problem, E, inliers) | {"ms": elapsed}).items():
                    stats[name].setdefault(key, []).append(value)
        for name, s in stats.items():
            for key in ("rot", "tdir"):
                values = sorted(s[key])
                result[f"{name}_{key}_err_deg_{ratio}"] = round(statistics.median(values), 4)
                result[f"{name}_{key}_err_deg_p90_{ratio}"] = round(
                    values[math.ceil(0.9 * len(values)) - 1], 4
                )
            result[f"{name}_e_err_{ratio}"] = round(statistics.median(s["e_err"]), 5)
            result[f"{name}_recall_{ratio}"] = round(statistics.mean(s["recall"]), 4)
            result[f"{name}_precision_{ratio}"] = round(statistics.mean(s["precision"]), 4)
            result[f"{name}_ms_{ratio}"] = round(statistics.median(s["ms"]), 2)
        result[f"ours_vs_kornia_ms_{ratio}"] = round(
            result[f"ours_ms_{ratio}"] / result[f"kornia_ms_{ratio}"], 3
        )
        result[f"ours_vs_kornia_paired_ms_{ratio}"] = round(
            statistics.median(
                a / b for a, b in zip(stats["ours"]["ms"], stats["kornia"]["ms"], strict=True)
            ),
            3,
        )
    return result


def markdown_table(result: dict[str, float], methods: list[str]) -> str:
    lines = [
        "| method | outliers | rot (deg) | t dir (deg) | rot p90 | t dir p90 | E err | recall "
        "| precision | ms |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for ratio in RATIOS:
        for name in methods:
            lines.append(
                f"| {name} | {ratio} | {result[f'{name}_rot_err_deg_{ratio}']:.3f} "
                f"| {result[f'{name}_tdir_err_deg_{ratio}']:.3f} "
                f"| {result[f'{name}_rot_err_deg_p90_{ratio}']:.3f} "
                f"| {result[f'{name}_tdir_err_deg_p90_{ratio}']:.3f} "
                f"| {result[f'{name}_e_err_{ratio}']:.4f} "
                f"| {result[f'{name}_recall_{ratio}']:.3f} "
                f"| {result[f'{name}_precision_{ratio}']:.3f} "
                f"| {result[f'{name}_ms_{ratio}']:.1f} |"
            )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=30)
    parser.add_argument("--points", type=int, default=500)
    parser.add_argument(
        "--out", type=Path, default=Path("experiments/results/bench_essential.json")
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    methods: dict[str, Solver] = {
        "ours": make_ours(),
        "kornia": make_kornia(defaults=False),
        "kornia_default": make_kornia(defaults=True),
        "opencv": solve_opencv,
    }
    warm = Problem(args.points, 0.4, 999_999, camera())
    for solve in methods.values():
        solve(warm, 0)
    result: dict[str, float | str] = {
        "trials": args.trials,
        "points": args.points,
        "torch_threads": 1,
        "opencv_threads": cv2.getNumThreads(),
        "kornia_version": kornia.__version__,
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
    scored = run(methods, args.trials, args.points)
    result |= scored
    print(markdown_table(scored, list(methods)))
    print(write_benchmark(args.out, result))


if __name__ == "__main__":
    main()
