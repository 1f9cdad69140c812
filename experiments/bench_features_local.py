"""Benchmark local features and matching; the last stdout line is one JSON object.

Usage:
    python experiments/bench_features_local.py [--repeats 10] [--threads 1]
        [--out experiments/results/bench_features_local.json]

Times are medians over ``--repeats`` calls after one warm-up call, in milliseconds, with
``--threads`` torch/OpenCV threads (default 1: stable numbers on a shared machine); the
machine's 1-minute load average at the start is recorded as ``load_average_1min``.

Keys:
    ``xfeat_640x480_ms``, ``orb_640x480_ms``, ``sift_640x480_ms``: extraction from a 640x480
    RGB photo (``skimage.data.astronaut`` resized) with the default configs; ``*_keypoints``
    the counts. Peer: ``orb_opencv_640x480_ms`` (plain ``cv2.ORB`` detectAndCompute, 1000
    keypoints) and ``orb_vs_opencv_ratio``.
    ``mnn_1000x1000_ms``: mutual nearest neighbours + ratio test, 1000 x 1000 XFeat
    descriptors (64-d float); ``hamming_mnn_1000x1000_ms`` the same for 256-bit ORB
    descriptors; peer ``bf_opencv_hamming_1000x1000_ms`` (``cv2.BFMatcher`` cross-check).
    ``guided_2000x2000_ms``: guided projection search, 2000 points, 2000 ORB keypoints, 15 px.
    ``lighterglue_ms``: LighterGlue on the motorcycle pair, 1000 x 1000 XFeat keypoints.
    ``motorcycle_*``: Middlebury 'motorcycle' stereo pair (``skimage.data``, 500x741), XFeat
    top-1000 keypoints matched by MNN + ratio 0.8 (``xfeat``) or LighterGlue: number of
    matches and fraction of those with ground-truth disparity within 2 px of the truth.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import cv2
import numpy as np
import skimage.data
import torch
from scipy.ndimage import map_coordinates

from diffloc.benchmark import median_ms
from diffloc.eval.report_files import write_benchmark
from diffloc.features.local import Features, OrbConfig, SiftConfig, XFeatConfig, make_extractor
from diffloc.features.matching import (
    LighterGlueConfig,
    LighterGlueMatcher,
    Matches,
    match_descriptors,
    match_guided,
)

RATIO = 0.8
TOP_K = 1000
INLIER_PX = 2.0


def to_chw(rgb: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(rgb).permute(2, 0, 1).contiguous()


def inlier_ratio(
    features0: Features, features1: Features, matches: Matches, disparity: np.ndarray
) -> float:
    """Fraction of matches with valid disparity whose right keypoint is within 2 px of truth."""
    left = features0.keypoints[matches.indices[:, 0]].double().numpy()
    right = features1.keypoints[matches.indices[:, 1]].double().numpy()
    d = map_coordinates(disparity, [left[:, 1], left[:, 0]], order=1, mode="nearest")
    valid = np.isfinite(d)
    error = np.hypot(right[valid, 0] - left[valid, 0] + d[valid], right[valid, 1] - left[valid, 1])
    return round(float((error < INLIER_PX).mean()), 4)


def extraction(image: torch.Tensor, repeats: int) -> dict:
    result = {}
    for name, config in (("xfeat", XFeatConfig()), ("orb", OrbConfig()), ("sift", SiftConfig())):
        extractor = make_extractor(config)
        result[f"{name}_640x480_ms"] = median_ms(lambda e=extractor: e.extract(image), repeats)
        result[f"{name}_keypoints"] = len(extractor.extract(image))
    grey = cv2.cvtColor(image.permute(1, 2, 0).numpy(), cv2.COLOR_RGB2GRAY)
    orb = cv2.ORB_create(1000)
    result["orb_opencv_640x480_ms"] = median_ms(lambda: orb.detectAndCompute(grey, None), repeats)
    result["orb_vs_opencv_ratio"] = round(
        result["orb_640x480_ms"] / result["orb_opencv_640x480_ms"], 2
    )
    return result


def matching(image: torch.Tensor, repeats: int) -> dict:
    flipped = image.flip(-1)  # another view with a different keypoint set
    xfeat = make_extractor(XFeatConfig(max_keypoints=TOP_K))
    float0, float1 = (xfeat.extract(x).descriptors for x in (image, flipped))
    orb = make_extractor(OrbConfig(max_keypoints=TOP_K))
    orb0, orb1 = orb.extract(image), orb.extract(flipped)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    binary0, binary1 = orb0.descriptors.numpy(), orb1.descriptors.numpy()

    g = torch.Generator().manual_seed(0)
    n = 2000
    keypoints = torch.rand(n, 2, generator=g) * torch.tensor([640.0, 480.0])
    points = keypoints + 5.0 * torch.randn(n, 2, generator=g)
    descriptors = torch.randint(0, 256, (n, 32), dtype=torch.uint8, generator=g)
    return {
        "mnn_descriptors": [len(float0), len(float1)],
        "mnn_1000x1000_ms": median_ms(
            lambda: match_descriptors(float0, float1, ratio=RATIO), repeats
        ),
        "hamming_mnn_1000x1000_ms": median_ms(
            lambda: match_descriptors(orb0.descriptors, orb1.descriptors, ratio=RATIO), repeats
        ),
        "bf_opencv_hamming_1000x1000_ms": median_ms(lambda: bf.match(binary0, binary1), repeats),
        "guided_2000x2000_ms": median_ms(
            lambda: match_guided(points, descriptors, 15.0, keypoints, descriptors, ratio=RATIO),
            repeats,
        ),
    }


def motorcycle(repeats: int) -> dict:
    left, right, disparity = skimage.data.stereo_motorcycle()
    disparity = disparity.astype(np.float64)
    xfeat = make_extractor(XFeatConfig(max_keypoints=TOP_K))
    features0, features1 = xfeat.extract(to_chw(left)), xfeat.extract(to_chw(right))
    mnn = match_descriptors(features0.descriptors, features1.descriptors, ratio=RATIO)
    matcher = LighterGlueMatcher(LighterGlueConfig())

    def lighterglue() -> Matches:
        return matcher.match(features0, features1, left.shape[:2], right.shape[:2])

    glue = lighterglue()
    return {
        "lighterglue_ms": median_ms(lighterglue, max(1, repeats // 2)),
        "lighterglue_keypoints": [len(features0), len(features1)],
        "motorcycle_xfeat_inlier_ratio": inlier_ratio(features0, features1, mnn, disparity),
        "motorcycle_lighterglue_inlier_ratio": inlier_ratio(features0, features1, glue, disparity),
        "motorcycle_xfeat_matches": len(mnn),
        "motorcycle_lighterglue_matches": len(glue),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--out", type=Path, default=Path("experiments/results/bench_features_local.json")
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)

    rgb = cv2.resize(skimage.data.astronaut(), (640, 480), interpolation=cv2.INTER_AREA)
    image = to_chw(rgb)
    result = {"threads": args.threads, "repeats": args.repeats}
    result["load_average_1min"] = round(os.getloadavg()[0], 2)  # other jobs slow timings down
    result |= extraction(image, args.repeats)
    result |= matching(image, args.repeats)
    result |= motorcycle(args.repeats)
    print(write_benchmark(args.out, result))


if __name__ == "__main__":
    main()
