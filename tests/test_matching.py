"""Descriptor matching: known answers, references, guided search, LighterGlue, real stereo pair."""

from __future__ import annotations

import numpy as np
import pytest
import skimage.data
import torch
from scipy.ndimage import map_coordinates

from diffloc.checks import ShapeError
from diffloc.features.local import Features, OrbConfig, XFeatConfig, make_extractor
from diffloc.features.matching import (
    LighterGlueConfig,
    LighterGlueMatcher,
    Matches,
    descriptor_distances,
    match_descriptors,
    match_guided,
)


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """Small networks on a shared 2-core machine: one thread avoids oversubscription stalls."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def numpy_hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, B), (M, B) uint8 -> (N, M) differing bits, the obvious way."""
    return np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=-1).sum(-1)


def numpy_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    if a.dtype == np.uint8:
        return numpy_hamming(a, b).astype(np.float64)
    return np.linalg.norm(a[:, None, :].astype(np.float64) - b[None, :, :], axis=-1)


# ---------------------------------------------------------------- distances and MNN / ratio


@pytest.mark.parametrize("size", [(37, 53, 32), (5, 1, 61), (1, 9, 1)])
def test_hamming_matches_numpy_unpackbits(size: tuple[int, int, int]) -> None:
    n, m, b = size
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (n, b), dtype=np.uint8)
    c = rng.integers(0, 256, (m, b), dtype=np.uint8)
    distances = descriptor_distances(torch.from_numpy(a), torch.from_numpy(c))
    np.testing.assert_array_equal(distances.numpy(), numpy_hamming(a, c))


def test_float_metrics_match_references() -> None:
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(20, 16, generator=g), torch.randn(30, 16, generator=g)
    torch.testing.assert_close(descriptor_distances(a, b), torch.cdist(a, b))
    cosine = 1.0 - torch.nn.functional.cosine_similarity(a[:, None], b[None], dim=-1)
    torch.testing.assert_close(descriptor_distances(a, b, "cosine"), cosine)


def test_mnn_known_answer() -> None:
    # desc1 = a permutation of desc0 plus small noise: MNN recovers the permutation.
    g = torch.Generator().manual_seed(1)
    desc0 = torch.nn.functional.normalize(torch.randn(50, 64, generator=g), dim=1)
    permutation = torch.randperm(50, generator=g)
    desc1 = desc0[permutation] + 0.01 * torch.randn(50, 64, generator=g)
    matches = match_descriptors(desc0, desc1)
    assert isinstance(matches, Matches) and len(matches) == 50
    torch.testing.assert_close(matches.indices[:, 0], torch.arange(50))
    torch.testing.assert_close(permutation[matches.indices[:, 1]], torch.arange(50))
    assert bool((matches.scores <= 0).all()) and matches.indices.dtype == torch.int64


def test_mnn_drops_one_sided_nearest_neighbours() -> None:
    # 0 -> 0 and 1 -> 0 (1 is nearer to 0 than to anything else), but 0 is mutual with 0 only.
    desc0 = torch.tensor([[0.0], [1.0]])
    desc1 = torch.tensor([[0.2], [5.0]])
    torch.testing.assert_close(match_descriptors(desc0, desc1).indices, torch.tensor([[0, 0]]))
    one_sided = match_descriptors(desc0, desc1, mutual=False)
    torch.testing.assert_close(one_sided.indices, torch.tensor([[0, 0], [1, 0]]))
    torch.testing.assert_close(one_sided.scores, torch.tensor([-0.2, -0.8]))


def test_ratio_test_rejects_ambiguous_matches() -> None:
    desc1 = torch.tensor([[0.0, 0.0], [10.0, 0.0], [10.0, 0.5]])
    desc0 = torch.tensor([[0.1, 0.0], [10.0, 0.25]])  # the second is halfway between two
    assert len(match_descriptors(desc0, desc1)) == 2
    matches = match_descriptors(desc0, desc1, ratio=0.8)
    torch.testing.assert_close(matches.indices, torch.tensor([[0, 0]]))
    assert len(match_descriptors(desc0, desc1, max_distance=0.05)) == 0


def test_hamming_ratio_and_ties() -> None:
    desc1 = torch.tensor([[0b0000_0000], [0b1111_0000], [0b0000_1111]], dtype=torch.uint8)
    desc0 = torch.tensor([[0b0000_0001], [0b0011_0011]], dtype=torch.uint8)
    # row 1 is at distance 4 from both 1 and 2 (an exact tie): the ratio test rejects it.
    matches = match_descriptors(desc0, desc1, mutual=False, ratio=1.0)
    torch.testing.assert_close(matches.indices, torch.tensor([[0, 0]]))
    torch.testing.assert_close(matches.scores, torch.tensor([-1.0]))


def mnn_reference(distances: np.ndarray, ratio: float | None) -> np.ndarray:
    """Mutual nearest neighbours the obvious way, with match_descriptors' tie rules: a row's
    nearest neighbour is its first column at the smallest distance; a column at the same
    smallest distance from several rows goes to the first whose nearest neighbour it is."""
    found, taken = [], set()
    for i, row in enumerate(distances):
        j = int(np.argmin(row))
        if row[j] != distances[:, j].min() or j in taken:
            continue
        taken.add(j)
        second = np.sort(row)[1] if len(row) > 1 else np.inf
        if ratio is None or row[j] < ratio * second:
            found.append((i, j))
    return np.array(found, dtype=np.int64).reshape(-1, 2)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("ratio", [None, 0.9])
def test_mnn_equals_reference_with_many_ties(seed: int, ratio: float | None) -> None:
    # 6-bit descriptors: distances 0..6, so rows and columns tie all the time.
    rng = np.random.default_rng(seed)
    a = rng.integers(0, 64, (60, 1), dtype=np.uint8)
    b = rng.integers(0, 64, (45, 1), dtype=np.uint8)
    matches = match_descriptors(torch.from_numpy(a), torch.from_numpy(b), ratio=ratio)
    expected = mnn_reference(numpy_hamming(a, b), ratio)
    assert len(expected) > 5
    np.testing.assert_array_equal(matches.indices.numpy(), expected)
    float_a, float_b = rng.normal(size=(70, 8)), rng.normal(size=(50, 8))
    matches = match_descriptors(torch.from_numpy(float_a), torch.from_numpy(float_b), ratio=ratio)
    np.testing.assert_array_equal(
        matches.indices.numpy(), mnn_reference(numpy_distances(float_a, float_b), ratio)
    )


def test_empty_descriptor_sets() -> None:
    assert len(match_descriptors(torch.zeros(0, 8), torch.rand(4, 8))) == 0
    assert len(match_descriptors(torch.rand(4, 8), torch.zeros(0, 8), ratio=0.8)) == 0


@pytest.mark.parametrize(
    ("desc0", "desc1", "kwargs", "error"),
    [
        (torch.rand(4), torch.rand(4, 8), {}, ShapeError),
        (torch.rand(4, 8), torch.rand(4, 9), {}, ShapeError),
        (torch.rand(4, 8), torch.zeros(4, 8, dtype=torch.uint8), {}, ValueError),
        (torch.rand(4, 8), torch.rand(4, 8), {"metric": "hamming"}, ValueError),
        (torch.rand(4, 8), torch.rand(4, 8), {"metric": "manhattan"}, ValueError),
        (torch.full((4, 8), float("nan")), torch.rand(4, 8), {}, ValueError),
        (torch.rand(4, 8), torch.rand(4, 8), {"ratio": 1.5}, ValueError),
        (
            torch.zeros(4, 8, dtype=torch.int32),
            torch.zeros(4, 8, dtype=torch.int32),
            {},
            ValueError,
        ),
    ],
    ids=["rank", "dim", "mixed", "hamming-float", "metric", "nan", "ratio", "int32"],
)
def test_match_descriptors_bad_inputs(desc0, desc1, kwargs: dict, error: type) -> None:
    with pytest.raises(error):
        match_descriptors(desc0, desc1, **kwargs)


# ---------------------------------------------------------------- guided projection search


def guided_reference(
    points, point_desc, radius, keypoints, keypoint_desc, ratio, max_distance, unique
):
    """Brute force over all (point, keypoint) pairs, one point at a time."""
    pixel = np.linalg.norm(points[:, None, :] - keypoints[None, :, :], axis=-1)
    descriptor = numpy_distances(point_desc, keypoint_desc)
    found = []
    for i in range(len(points)):
        candidates = np.flatnonzero(pixel[i] <= radius[i])
        if len(candidates) == 0:
            continue
        ranked = candidates[np.argsort(descriptor[i, candidates], kind="stable")]
        best = descriptor[i, ranked[0]]
        second = descriptor[i, ranked[1]] if len(ranked) > 1 else np.inf
        if ratio is not None and not best < ratio * second:
            continue
        if max_distance is not None and best > max_distance:
            continue
        found.append((i, ranked[0], best))
    if unique:
        winner = {}
        for i, j, d in found:  # in increasing point order: ties keep the lower point index
            if j not in winner or d < winner[j][2]:
                winner[j] = (i, j, d)
        found = sorted(winner.values())
    indices = np.array([(i, j) for i, j, _ in found], dtype=np.int64).reshape(-1, 2)
    return indices, -np.array([d for _, _, d in found])


def random_scene(seed: int, binary: bool, m: int = 300, n: int = 800):
    rng = np.random.default_rng(seed)
    points = rng.uniform([0, 0], [640, 480], (m, 2))
    keypoints = rng.uniform([-20, -20], [660, 500], (n, 2))
    radius = rng.uniform(4.0, 40.0, m)
    if binary:
        point_desc = rng.integers(0, 256, (m, 4), dtype=np.uint8)
        keypoint_desc = rng.integers(0, 256, (n, 4), dtype=np.uint8)
    else:
        point_desc = rng.normal(size=(m, 8)).astype(np.float32)
        keypoint_desc = rng.normal(size=(n, 8)).astype(np.float32)
    return points, point_desc, radius, keypoints, keypoint_desc


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("binary", [False, True], ids=["float", "binary"])
@pytest.mark.parametrize(
    ("ratio", "max_distance", "unique"),
    [(None, None, False), (0.9, None, True), (0.8, 3.0, True), (None, 2.5, False)],
)
def test_guided_search_equals_brute_force(seed, binary, ratio, max_distance, unique) -> None:
    if max_distance is not None and binary:
        max_distance *= 4  # 32-bit random descriptors are ~16 bits apart, 8-d normal ones ~4
    scene = random_scene(seed, binary)
    expected_indices, expected_scores = guided_reference(*scene, ratio, max_distance, unique)
    points, point_desc, radius, keypoints, keypoint_desc = map(torch.from_numpy, scene)
    matches = match_guided(
        points, point_desc, radius, keypoints, keypoint_desc,
        ratio=ratio, max_distance=max_distance, unique=unique,
    )  # fmt: skip
    assert len(expected_indices) > 20
    np.testing.assert_array_equal(matches.indices.numpy(), expected_indices)
    np.testing.assert_allclose(matches.scores.numpy(), expected_scores, rtol=1e-5, atol=1e-5)


def test_guided_search_respects_radius() -> None:
    # The perfect descriptor match lies outside the radius: the point takes the one inside.
    points = torch.tensor([[100.0, 100.0]])
    point_desc = torch.tensor([[1.0, 0.0]])
    keypoints = torch.tensor([[112.0, 100.0], [104.0, 103.0], [300.0, 300.0]])
    keypoint_desc = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0]])
    inside = match_guided(points, point_desc, 10.0, keypoints, keypoint_desc)
    torch.testing.assert_close(inside.indices, torch.tensor([[0, 1]]))
    wider = match_guided(points, point_desc, torch.tensor([12.5]), keypoints, keypoint_desc)
    torch.testing.assert_close(wider.indices, torch.tensor([[0, 0]]))
    assert len(match_guided(points, point_desc, 3.0, keypoints, keypoint_desc)) == 0


def test_guided_search_radius_bound_on_random_data() -> None:
    points, point_desc, radius, keypoints, keypoint_desc = map(
        torch.from_numpy, random_scene(3, binary=False)
    )
    matches = match_guided(points, point_desc, radius, keypoints, keypoint_desc, unique=False)
    i, j = matches.indices.unbind(1)
    assert bool((torch.linalg.vector_norm(points[i] - keypoints[j], dim=1) <= radius[i]).all())


def test_guided_search_empty_and_bad_inputs() -> None:
    desc = torch.rand(3, 8)
    uv = torch.rand(3, 2) * 100
    assert len(match_guided(uv[:0], desc[:0], 5.0, uv, desc)) == 0
    assert len(match_guided(uv, desc, 5.0, uv[:0], desc[:0])) == 0
    with pytest.raises(ShapeError):
        match_guided(uv, desc[:2], 5.0, uv, desc)
    with pytest.raises(ShapeError):
        match_guided(uv, desc, torch.ones(2), uv, desc)
    with pytest.raises(ValueError):
        match_guided(uv, desc, 0.0, uv, desc)
    with pytest.raises(ValueError):
        match_guided(uv * float("nan"), desc, 5.0, uv, desc)
    with pytest.raises(ValueError):
        match_guided(uv, desc, 5.0, uv, desc.to(torch.uint8))


# ---------------------------------------------------------------- LighterGlue


def test_lighterglue_bad_inputs_and_empty() -> None:
    matcher = LighterGlueMatcher(LighterGlueConfig())
    empty = Features(torch.zeros(0, 2), torch.zeros(0), torch.zeros(0, 64), torch.zeros(0))
    one = Features(torch.tensor([[5.0, 5.0]]), torch.ones(1), torch.ones(1, 64), torch.ones(1))
    assert len(matcher.match(empty, one, (10, 10), (10, 10))) == 0
    assert "model" not in vars(matcher)  # nothing to match, nothing loaded
    orb_like = Features(torch.zeros(1, 2), torch.ones(1), torch.zeros(1, 32), torch.ones(1))
    with pytest.raises(ShapeError):
        matcher.match(orb_like, orb_like, (10, 10), (10, 10))
    with pytest.raises(ValueError, match="outside"):
        matcher.match(one, one, (4, 10), (10, 10))
    with pytest.raises(ValueError):
        LighterGlueConfig(min_confidence=1.5)


# ---------------------------------------------------------------- real stereo pair


def correspondence_inliers(
    features0: Features, features1: Features, matches: Matches, disparity: np.ndarray
) -> tuple[int, float]:
    """Matches with ground truth, and the fraction of them within 2 px of the truth.

    A left keypoint (u, v) corresponds to the right pixel (u - d(u, v), v); d is interpolated
    bilinearly and matches where it is invalid (inf) are skipped.
    """
    left = features0.keypoints[matches.indices[:, 0]].double().numpy()
    right = features1.keypoints[matches.indices[:, 1]].double().numpy()
    d = map_coordinates(disparity, [left[:, 1], left[:, 0]], order=1, mode="nearest")
    valid = np.isfinite(d)
    error = np.hypot(
        right[valid, 0] - (left[valid, 0] - d[valid]), right[valid, 1] - left[valid, 1]
    )
    return int(valid.sum()), float((error < 2.0).mean())


@pytest.fixture(scope="module")
def motorcycle():
    """Middlebury 2014 'motorcycle' (500x741), disparity of the left image in pixels."""
    left, right, disparity = skimage.data.stereo_motorcycle()
    to_chw = lambda rgb: torch.from_numpy(rgb).permute(2, 0, 1)  # noqa: E731
    return to_chw(left), to_chw(right), disparity.astype(np.float64)


@pytest.fixture(scope="module")
def motorcycle_xfeat(motorcycle):
    left, right, _ = motorcycle
    extractor = make_extractor(XFeatConfig(max_keypoints=1000))
    return extractor.extract(left), extractor.extract(right)


def test_motorcycle_disparity_convention(motorcycle) -> None:
    _, _, disparity = motorcycle
    assert disparity.shape == (500, 741)
    assert np.isinf(disparity).any() and not np.isnan(disparity).any()
    assert np.nanmin(disparity[np.isfinite(disparity)]) > 0


def test_motorcycle_xfeat_ratio_matches_agree_with_ground_truth(motorcycle, motorcycle_xfeat):
    # Measured (1000 keypoints, ratio 0.8): 420 matches, 281 with ground truth, 73.7% < 2 px.
    features0, features1 = motorcycle_xfeat
    matches = match_descriptors(features0.descriptors, features1.descriptors, ratio=0.8)
    count, inlier_ratio = correspondence_inliers(features0, features1, matches, motorcycle[2])
    assert count >= 200
    assert inlier_ratio >= 0.6


def test_motorcycle_lighterglue_matches_agree_with_ground_truth(motorcycle, motorcycle_xfeat):
    # Measured (1000 keypoints): 485 matches, 306 with ground truth, 75.8% < 2 px.
    features0, features1 = motorcycle_xfeat
    matches = LighterGlueMatcher(LighterGlueConfig()).match(
        features0, features1, (500, 741), (500, 741)
    )
    assert bool((matches.scores >= 0.1).all()) and bool((matches.scores <= 1).all())
    count, inlier_ratio = correspondence_inliers(features0, features1, matches, motorcycle[2])
    assert count >= 200
    assert inlier_ratio >= 0.6


def test_motorcycle_orb_hamming_matches_agree_with_ground_truth(motorcycle) -> None:
    # Measured (1000 keypoints, ratio 0.8): 265 matches, 202 with ground truth, 87.6% < 2 px.
    left, right, disparity = motorcycle
    extractor = make_extractor(OrbConfig(max_keypoints=1000))
    features0, features1 = extractor.extract(left), extractor.extract(right)
    matches = match_descriptors(features0.descriptors, features1.descriptors, ratio=0.8)
    count, inlier_ratio = correspondence_inliers(features0, features1, matches, disparity)
    assert count >= 150
    assert inlier_ratio >= 0.75
