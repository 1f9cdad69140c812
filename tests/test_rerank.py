"""Mutual-nearest-neighbour re-ranking of retrieved database images (diffloc.reloc.rerank).

Known answers on constructed descriptors: random 64-D unit vectors are nearly orthogonal (their
cosine similarities stay below 0.6 here), so with ``min_similarity=0.8`` only descriptors the
query shares with an image (up to small noise) match, and the counts are exact.
"""

from __future__ import annotations

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.reloc.rerank import MutualNNReranker, RerankConfig, mutual_nn_counts

STRICT = RerankConfig(candidates=10, keypoints=512, min_similarity=0.8, batch=2)


def _unit(n: int, generator: torch.Generator) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.randn(n, 64, generator=generator), dim=1)


@pytest.fixture()
def scene() -> tuple[list[torch.Tensor], list[torch.Tensor], torch.Tensor]:
    """Six images of 300 random descriptors; the query shares 40 (noisy) with image 4, 10
    with image 0, none with the others."""
    g = torch.Generator().manual_seed(0)
    images = [_unit(300, g) for _ in range(6)]
    scores = [torch.rand(300, generator=g) for _ in range(6)]
    shared = torch.cat([images[4][:40], images[0][:10]])
    noisy = torch.nn.functional.normalize(shared + 0.02 * torch.randn_like(shared), dim=1)
    query = torch.cat([noisy, _unit(200, g)])
    return images, scores, query


def test_the_image_sharing_the_most_descriptors_comes_first(scene):
    """NetVLAD's order puts image 4 last; re-ranking puts it first with exactly 40 matches,
    image 0 second with 10, and the rest keep their global order with 0."""
    images, scores, query = scene
    reranker = MutualNNReranker(images, scores, STRICT)
    matches, order = reranker.rerank(query, torch.tensor([1, 2, 0, 3, 5, 4]))
    assert order.tolist() == [4, 0, 1, 2, 3, 5]
    assert matches.tolist() == [40, 10, 0, 0, 0, 0]


def test_counts_agree_with_a_pairwise_reference():
    """Every image against a brute-force mutual check over all descriptor pairs (no
    threshold), with padding from images of different sizes."""
    g = torch.Generator().manual_seed(1)
    query = _unit(30, g)
    images = [_unit(n, g) for n in (25, 40, 7)]
    database = torch.zeros(3, 40, 64)
    valid = torch.zeros(3, 40, dtype=torch.bool)
    expected = []
    for i, d in enumerate(images):
        database[i, : len(d)], valid[i, : len(d)] = d, True
        s = query @ d.T
        forward, backward = s.argmax(1), s.argmax(0)
        expected.append(int((backward[forward] == torch.arange(len(query))).sum()))
    assert mutual_nn_counts(query, database, valid, -1.0).tolist() == expected
    assert min(expected) > 0


def test_counts_without_padding_agree_with_the_pairwise_reference():
    g = torch.Generator().manual_seed(2)
    query = _unit(30, g)
    database = torch.stack([_unit(40, g) for _ in range(4)])
    expected = []
    for d in database:
        s = query @ d.T
        forward, backward = s.argmax(1), s.argmax(0)
        expected.append(int((backward[forward] == torch.arange(len(query))).sum()))
    valid = torch.ones(4, 40, dtype=torch.bool)
    assert mutual_nn_counts(query, database, valid, -1.0).tolist() == expected
    assert mutual_nn_counts(query, database, valid, 2.0).tolist() == [0, 0, 0, 0]


def test_only_the_strongest_keypoints_take_part(scene):
    """Image 4's shared descriptors are its weakest (image 0's its strongest): with 100
    keypoints per image they are left out and image 4 loses its matches; then the query's
    shared ones are made its weakest and no image keeps a match."""
    images, scores, query = scene
    weak_first = [s.clone() for s in scores]
    weak_first[4][:40] = -1.0
    weak_first[0][:10] = 2.0
    few = RerankConfig(keypoints=100, min_similarity=0.8)
    matches, order = MutualNNReranker(images, weak_first, few).rerank(query, torch.tensor([4, 0]))
    assert order.tolist() == [0, 4] and matches.tolist() == [10, 0]
    query_scores = torch.cat([torch.zeros(50), torch.ones(200)])
    matches, _ = MutualNNReranker(images, scores, few).rerank(
        query, torch.tensor([4, 0]), query_scores
    )
    assert matches.tolist() == [0, 0]


def test_a_query_without_keypoints_keeps_the_global_order(scene):
    images, scores, _ = scene
    reranker = MutualNNReranker(images, scores, STRICT)
    candidates = torch.tensor([3, 1, 4])
    matches, order = reranker.rerank(torch.zeros(0, 64), candidates, torch.zeros(0))
    assert torch.equal(order, candidates) and matches.tolist() == [0, 0, 0]


def test_an_image_without_keypoints_gets_no_matches(scene):
    images, scores, query = scene
    images[4], scores[4] = torch.zeros(0, 64), torch.zeros(0)
    matches, order = MutualNNReranker(images, scores, STRICT).rerank(query, torch.tensor([4, 0]))
    assert order.tolist() == [0, 4] and matches.tolist() == [10, 0]


def test_an_empty_database_is_rejected():
    with pytest.raises(ValueError, match="at least one database image"):
        MutualNNReranker([], [], RerankConfig())


def test_mismatched_database_inputs_are_rejected(scene):
    images, scores, _ = scene
    with pytest.raises(ValueError, match="6 descriptor sets but 5 score sets"):
        MutualNNReranker(images, scores[:5], RerankConfig())
    with pytest.raises(ShapeError, match=r"descriptors\[1\]"):
        MutualNNReranker([images[0], torch.zeros(3, 32)], scores[:2], RerankConfig())
    with pytest.raises(ShapeError, match=r"scores\[0\]"):
        MutualNNReranker(images[:1], [torch.zeros(5)], RerankConfig())
    with pytest.raises(ValueError, match="must be float"):
        MutualNNReranker([torch.zeros(3, 32, dtype=torch.uint8)], [torch.zeros(3)], STRICT)


def test_bad_queries_and_candidates_are_rejected(scene):
    images, scores, query = scene
    reranker = MutualNNReranker(images, scores, STRICT)
    with pytest.raises(IndexError, match=r"candidates must lie in \[0, 6\)"):
        reranker.rerank(query, torch.tensor([0, 6]))
    with pytest.raises(ShapeError, match="query"):
        reranker.rerank(query[:, :32], torch.tensor([0]))
    with pytest.raises(ShapeError, match="query_scores"):
        reranker.rerank(query, torch.tensor([0]), torch.zeros(3))


@pytest.mark.parametrize(
    ("field", "value"),
    [("candidates", 0), ("keypoints", -1), ("batch", 0), ("min_similarity", 1.0)],
)
def test_bad_configs_are_rejected(field, value):
    with pytest.raises(ValueError, match=field):
        RerankConfig(**{field: value})
