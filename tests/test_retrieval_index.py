"""Tests of RetrievalIndex (matmul vs KD-tree, save/load, bad files) and retrieval recall."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.features.index import RetrievalIndex
from diffloc.features.retrieval_eval import pairwise_pose_distances, retrieval_recall
from diffloc.testing import assert_close


def random_descriptors(n: int, d: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    return torch.randn(n, d, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def poses_at(x: list[float], yaw_deg: list[float] | None = None) -> torch.Tensor:
    """Poses on the x axis, rotated about z by ``yaw_deg``."""
    T = torch.eye(4, dtype=torch.float64).repeat(len(x), 1, 1)
    T[:, 0, 3] = torch.tensor(x, dtype=torch.float64)
    for i, yaw in enumerate(yaw_deg or [0.0] * len(x)):
        c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
        T[i, :2, :2] = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    return T


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_matmul_and_kdtree_give_identical_top_k(dtype: torch.dtype) -> None:
    database = random_descriptors(1000, 32, seed=0, dtype=dtype)
    queries = random_descriptors(25, 32, seed=1, dtype=dtype)
    scores_mm, indices_mm = RetrievalIndex(database, backend="matmul").search(queries, k=30)
    scores_kd, indices_kd = RetrievalIndex(database, backend="kdtree").search(queries, k=30)
    assert torch.equal(indices_mm, indices_kd)
    assert_close(scores_kd, scores_mm, rtol=1e-5, atol=1e-6)


def test_search_is_exact_cosine_top_k() -> None:
    database = random_descriptors(200, 8, seed=2)
    queries = random_descriptors(5, 8, seed=3)
    scores, indices = RetrievalIndex(database).search(3.0 * queries, k=7)
    cosine = torch.nn.functional.cosine_similarity(queries[:, None], database[None], dim=-1)
    expected_scores, expected_indices = torch.sort(cosine, dim=1, descending=True)
    assert torch.equal(indices, expected_indices[:, :7])
    assert_close(scores, expected_scores[:, :7])


def test_k_larger_than_database_and_ids() -> None:
    database = random_descriptors(4, 3, seed=4)
    ids = torch.tensor([10, 20, 30, 40])
    index = RetrievalIndex(database, ids=ids)
    scores, found = index.search_ids(database[2:3], k=30)
    assert scores.shape == (1, 4) and int(found[0, 0]) == 30
    assert_close(scores[0, 0], torch.tensor(1.0, dtype=torch.float64))


def test_save_load_round_trip_is_exact(tmp_path: Path) -> None:
    index = RetrievalIndex(
        random_descriptors(50, 16, seed=5, dtype=torch.float32), backend="kdtree"
    )
    path = index.save(tmp_path / "sub" / "index.npz")
    assert sorted(p.name for p in path.parent.iterdir()) == ["index.npz"]  # no temp files left
    loaded = RetrievalIndex.load(path)
    assert loaded.backend == "kdtree" and len(loaded) == 50 and loaded.dim == 16
    assert torch.equal(loaded.descriptors, index.descriptors)
    assert torch.equal(loaded.ids, index.ids)
    queries = random_descriptors(3, 16, seed=6, dtype=torch.float32)
    for a, b in zip(loaded.search(queries, 5), index.search(queries, 5), strict=True):
        assert torch.equal(a, b)
    assert RetrievalIndex.load(path, backend="matmul").backend == "matmul"


def write_npz(path: Path, **arrays: np.ndarray) -> Path:
    np.savez(path, **arrays)
    return path


def metadata(**overrides: object) -> np.ndarray:
    meta = {
        "format_version": 1,
        "kind": "diffloc-retrieval-index",
        "backend": "matmul",
        "num_descriptors": 2,
        "dim": 3,
    }
    meta.update(overrides)
    return np.array(json.dumps(meta))


def valid_arrays(**overrides: object) -> dict:
    arrays = {
        "descriptors": np.eye(2, 3, dtype=np.float32),
        "ids": np.arange(2, dtype=np.int64),
        "metadata": metadata(),
    }
    arrays.update(overrides)
    return arrays


def test_load_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        RetrievalIndex.load(tmp_path / "missing.npz")


def test_load_valid_handmade_file(tmp_path: Path) -> None:
    loaded = RetrievalIndex.load(write_npz(tmp_path / "ok.npz", **valid_arrays()))
    assert len(loaded) == 2


@pytest.mark.parametrize(
    ("arrays", "message"),
    [
        ({"other": np.zeros(3)}, "missing arrays"),
        (valid_arrays(metadata=metadata(kind="something-else")), "kind"),
        (valid_arrays(metadata=metadata(format_version=99)), "format_version"),
        (valid_arrays(metadata=metadata(backend="faiss")), "backend"),
        (valid_arrays(metadata=np.array("{not json")), "JSON"),
        (valid_arrays(metadata=np.array([1, 2])), "JSON string"),
        (valid_arrays(descriptors=np.zeros((3, 3), np.float32)), "shape"),
        (valid_arrays(ids=np.arange(2, dtype=np.int32)), "int64 ids"),
        (valid_arrays(descriptors=np.array([[{}] * 3] * 2, dtype=object)), "pickle"),
    ],
)
def test_load_foreign_or_corrupt_npz(tmp_path: Path, arrays: dict, message: str) -> None:
    path = write_npz(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match=message) as info:
        RetrievalIndex.load(path)
    assert str(path) in str(info.value)


def test_load_non_npz_files(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"this is not an archive at all")
    npy = tmp_path / "single.npz"
    with npy.open("wb") as handle:
        np.save(handle, np.zeros(3))
    good = RetrievalIndex(random_descriptors(10, 4, seed=7)).save(tmp_path / "good.npz")
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[:200])
    for path in (garbage, npy, truncated):
        with pytest.raises(ValueError, match=path.name):
            RetrievalIndex.load(path)


def test_bad_shapes_and_arguments() -> None:
    with pytest.raises(ShapeError):
        RetrievalIndex(torch.randn(10))
    with pytest.raises(ShapeError):
        RetrievalIndex(torch.randn(0, 4))
    with pytest.raises(ShapeError):
        RetrievalIndex(torch.randn(5, 4), ids=torch.arange(4))
    with pytest.raises(TypeError):
        RetrievalIndex(torch.ones(5, 4, dtype=torch.int64))
    with pytest.raises(ValueError, match="NaN"):
        RetrievalIndex(torch.full((5, 4), float("nan")))
    with pytest.raises(ValueError, match="backend"):
        RetrievalIndex(torch.randn(5, 4), backend="faiss")
    index = RetrievalIndex(torch.randn(5, 4))
    with pytest.raises(ShapeError):
        index.search(torch.randn(2, 3), k=1)
    with pytest.raises(ShapeError):
        index.search(torch.randn(4), k=1)
    with pytest.raises(ValueError, match="k"):
        index.search(torch.randn(2, 4), k=0)


# --- retrieval ground truth -----------------------------------------------------------------


def test_pairwise_pose_distances_known_answers() -> None:
    a = poses_at([0.0], [0.0])
    b = poses_at([3.0, 0.0], [0.0, 90.0])
    b[0, 1, 3] = 4.0
    distance, angle = pairwise_pose_distances(a, b)
    assert_close(distance, torch.tensor([[5.0, 0.0]], dtype=torch.float64))
    assert_close(angle, torch.tensor([[0.0, math.pi / 2]], dtype=torch.float64))


def test_retrieval_recall_known_answer() -> None:
    database = poses_at([0.0, 1.0, 10.0, 20.0], [0.0, 0.0, 0.0, 0.0])
    queries = poses_at([0.5, 10.5, 20.0], [0.0, 0.0, 45.0])
    retrieved = torch.tensor(
        [
            [0, 2, 3],  # correct at rank 1
            [3, 0, 2],  # correct at rank 3
            [3, 2, 1],  # database frame 3 is close but rotated 45 degrees: never correct
        ]
    )
    recall = retrieval_recall(queries, database, retrieved, ks=(1, 2, 3))
    assert recall == {1: pytest.approx(1 / 3), 2: pytest.approx(1 / 3), 3: pytest.approx(2 / 3)}
    loose = retrieval_recall(queries, database, retrieved, max_angle_deg=50.0, ks=(1,))
    assert loose == {1: pytest.approx(2 / 3)}


def test_retrieval_recall_bad_inputs() -> None:
    database = poses_at([0.0, 1.0])
    queries = poses_at([0.0])
    with pytest.raises(ShapeError):
        retrieval_recall(queries, database, torch.tensor([[0, 1]]), ks=(1, 5))
    with pytest.raises(ShapeError):
        retrieval_recall(queries, database, torch.tensor([[0], [1]]), ks=(1,))
    with pytest.raises(ValueError, match="indices"):
        retrieval_recall(queries, database, torch.tensor([[2]]), ks=(1,))
    with pytest.raises(ValueError, match="ks"):
        retrieval_recall(queries, database, torch.tensor([[0]]), ks=())
    with pytest.raises(ShapeError):
        retrieval_recall(queries[0], database, torch.tensor([[0]]), ks=(1,))
