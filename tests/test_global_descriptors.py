"""Tests of the global descriptors: DenseXFeat, k-means, NetVLAD (+ fine-tuning), bag of words."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from diffloc.checks import ShapeError
from diffloc.features.dense import DenseXFeat
from diffloc.features.global_ import BagOfWords, NetVLAD, kmeans, nearest_centroids
from diffloc.features.netvlad_training import (
    FinetuneConfig,
    NetVLADFineTuner,
    TripletConfig,
    TripletDataset,
    finetune_netvlad,
)
from diffloc.testing import assert_close, gradcheck


def generator(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def initialised_netvlad(
    k: int = 3, d: int = 4, alpha: float | None = 5.0, whiten_dim: int | None = None
) -> NetVLAD:
    netvlad = NetVLAD(num_clusters=k, dim=d, whiten_dim=whiten_dim)
    netvlad.init_from_kmeans(torch.randn(200, d, generator=generator(1)), generator(2), alpha)
    return netvlad


def reference_vlad(x: torch.Tensor, centroids: torch.Tensor, alpha: float) -> torch.Tensor:
    """Slow VLAD with the soft assignment softmax_k(-alpha ||x - c_k||^2), loop by loop.

    x: (D, h, w) one map; centroids: (K, D). Returns (K * D,).
    """
    d, h, w = x.shape
    k = len(centroids)
    vlad = torch.zeros(k, d, dtype=x.dtype)
    for i in range(h):
        for j in range(w):
            local = x[:, i, j] / torch.linalg.vector_norm(x[:, i, j])
            weights = [math.exp(-alpha * float(((local - c) ** 2).sum())) for c in centroids]
            total = sum(weights)
            for c in range(k):
                vlad[c] += weights[c] / total * (local - centroids[c])
    for c in range(k):
        vlad[c] /= torch.linalg.vector_norm(vlad[c])
    flat = vlad.flatten()
    return flat / torch.linalg.vector_norm(flat)


# --- DenseXFeat -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def dense_xfeat() -> DenseXFeat:
    return DenseXFeat()


def test_dense_shape_and_unit_norm(dense_xfeat: DenseXFeat) -> None:
    images = torch.rand(2, 3, 64, 96, generator=generator())
    maps = dense_xfeat(images)
    assert maps.shape == (2, 64, 8, 12) and maps.dtype == torch.float32
    assert_close(torch.linalg.vector_norm(maps, dim=1), torch.ones(2, 8, 12))


def test_dense_accepts_uint8_and_grey(dense_xfeat: DenseXFeat) -> None:
    grey = torch.randint(0, 256, (1, 1, 64, 64), generator=generator(), dtype=torch.uint8)
    from_uint8 = dense_xfeat(grey)
    from_float = dense_xfeat(grey.float() / 255)
    from_rgb = dense_xfeat(grey.expand(1, 3, 64, 64).float() / 255)
    assert_close(from_uint8, from_float)
    assert_close(from_rgb, from_float, rtol=1e-4, atol=1e-4)


def test_dense_size_not_multiple_of_32(dense_xfeat: DenseXFeat) -> None:
    maps = dense_xfeat(torch.rand(1, 3, 120, 160, generator=generator()))
    assert maps.shape == (1, 64, 15, 20)
    assert_close(torch.linalg.vector_norm(maps, dim=1), torch.ones(1, 15, 20))


def test_dense_backbone_stays_frozen_and_in_eval(dense_xfeat: DenseXFeat) -> None:
    dense_xfeat.train()
    assert not dense_xfeat.net.training
    assert not any(p.requires_grad for p in dense_xfeat.parameters())
    dense_xfeat.eval()


def test_dense_bad_inputs(dense_xfeat: DenseXFeat) -> None:
    with pytest.raises(ShapeError):
        dense_xfeat(torch.rand(3, 64, 64))
    with pytest.raises(ShapeError):
        dense_xfeat(torch.rand(1, 2, 64, 64))
    with pytest.raises(ShapeError):
        dense_xfeat(torch.rand(1, 3, 4, 64))
    with pytest.raises(TypeError):
        dense_xfeat(torch.zeros(1, 3, 64, 64, dtype=torch.int32))


# --- k-means ------------------------------------------------------------------------------


def test_kmeans_recovers_separated_clusters() -> None:
    centres = torch.tensor([[0.0, 0.0, 0.0], [10.0, 0, 0], [0, 10.0, 0], [0, 0, 10.0]])
    truth = torch.arange(4).repeat_interleave(50)
    points = centres[truth] + 0.1 * torch.randn(200, 3, generator=generator())
    centroids, labels = kmeans(points, 4, generator(1))
    # each true cluster gets exactly one label, and the labels are a permutation
    mapping = torch.stack([labels[truth == c].unique() for c in range(4)]).flatten()
    assert sorted(mapping.tolist()) == [0, 1, 2, 3]
    assert_close(centroids[mapping], centres, atol=0.05, rtol=0)
    again_centroids, again_labels = kmeans(points, 4, generator(1))
    assert torch.equal(again_centroids, centroids) and torch.equal(again_labels, labels)


def test_kmeans_handles_duplicate_points() -> None:
    points = torch.tensor([[0.0, 0.0]] * 5 + [[1.0, 1.0]] * 5)
    centroids, labels = kmeans(points, 3, generator())
    assert centroids.shape == (3, 2) and torch.isfinite(centroids).all()
    d2, nearest = nearest_centroids(points, centroids)
    assert torch.equal(nearest[:, 0], labels) and float(d2.max()) == 0.0


def test_kmeans_bad_inputs() -> None:
    with pytest.raises(ValueError, match="at least k"):
        kmeans(torch.randn(3, 2), 4, generator())
    with pytest.raises(ShapeError):
        kmeans(torch.randn(10), 2, generator())
    with pytest.raises(ValueError):
        kmeans(torch.full((10, 2), float("nan")), 2, generator())


# --- NetVLAD ------------------------------------------------------------------------------


def test_netvlad_shape_and_unit_norm() -> None:
    netvlad = initialised_netvlad(k=8, d=16, alpha=None)
    out = netvlad(torch.randn(3, 16, 5, 7, generator=generator()))
    assert out.shape == (3, 8 * 16) and netvlad.output_dim == 128
    assert_close(torch.linalg.vector_norm(out, dim=1), torch.ones(3))
    assert float(netvlad.alpha) > 0


def test_netvlad_kmeans_init_matches_reference() -> None:
    netvlad = initialised_netvlad(k=3, d=4, alpha=5.0).double()
    x = torch.randn(2, 4, 3, 5, generator=generator(3), dtype=torch.float64)
    expected = torch.stack([reference_vlad(m, netvlad.centroids.detach(), 5.0) for m in x])
    # the conv holds float32-rounded 2 alpha c and -alpha |c|^2
    assert_close(netvlad(x), expected, rtol=1e-5, atol=1e-6)


def test_netvlad_large_alpha_is_hard_vlad() -> None:
    netvlad = initialised_netvlad(k=3, d=4, alpha=1e4).double()
    x = torch.randn(1, 4, 4, 4, generator=generator(4), dtype=torch.float64)
    local = F.normalize(x[0].flatten(1).T, dim=1)  # (N, D)
    centroids = netvlad.centroids.detach()
    nearest = torch.cdist(local, centroids).argmin(1)
    vlad = torch.stack([(local[nearest == c] - centroids[c]).sum(0) for c in range(3)])
    expected = F.normalize(F.normalize(vlad, dim=1).flatten(), dim=0)
    assert_close(netvlad(x)[0], expected, rtol=1e-6, atol=1e-6)


def test_netvlad_gradcheck() -> None:
    netvlad = initialised_netvlad(k=3, d=4, alpha=2.0).double()
    x = torch.randn(2, 4, 2, 3, generator=generator(5), dtype=torch.float64)
    assert gradcheck(netvlad, [x])


def test_netvlad_whitening_gradcheck() -> None:
    netvlad = initialised_netvlad(k=2, d=3, alpha=2.0, whiten_dim=4)
    maps = torch.randn(20, 3, 2, 2, generator=generator(6))
    netvlad.fit_whitening(netvlad.aggregate(maps).detach())
    netvlad = netvlad.double()
    assert gradcheck(netvlad, [maps[:2].double()])


def test_netvlad_whitening_decorrelates_database() -> None:
    netvlad = initialised_netvlad(k=4, d=8, alpha=None, whiten_dim=6)
    vlad = netvlad.aggregate(torch.randn(50, 8, 3, 3, generator=generator(7))).detach()
    variances = netvlad.fit_whitening(vlad.double(), eps=0.0)
    assert torch.all(variances[:-1] >= variances[1:])
    projected = (vlad.double() - netvlad.pca_mean.double()) @ netvlad.pca_projection.double()
    covariance = projected.T @ projected / (len(vlad) - 1)
    assert_close(covariance, torch.eye(6, dtype=torch.float64), rtol=0, atol=1e-3)
    out = netvlad(torch.randn(2, 8, 3, 3))
    assert out.shape == (2, 6)
    assert_close(torch.linalg.vector_norm(out, dim=1), torch.ones(2))


def test_netvlad_bad_inputs() -> None:
    netvlad = initialised_netvlad(k=3, d=4)
    with pytest.raises(ShapeError):
        netvlad(torch.randn(2, 5, 3, 3))
    with pytest.raises(ShapeError):
        netvlad(torch.randn(4, 3, 3))
    with pytest.raises(ShapeError):
        netvlad.init_from_kmeans(torch.randn(100, 5), generator())
    with pytest.raises(ValueError, match="alpha"):
        netvlad.init_from_kmeans(torch.randn(100, 4), generator(), alpha=-1.0)
    with pytest.raises(RuntimeError, match="no whitening"):
        netvlad.fit_whitening(torch.randn(10, 12))
    whitened = NetVLAD(num_clusters=3, dim=4, whiten_dim=8)
    with pytest.raises(RuntimeError, match="not fitted"):
        whitened(torch.randn(1, 4, 2, 2))
    with pytest.raises(ValueError, match="more than 8"):
        whitened.fit_whitening(torch.randn(8, 12))
    with pytest.raises(ValueError):
        NetVLAD(num_clusters=0, dim=4)


# --- fine-tuning --------------------------------------------------------------------------


def place_data(n: int = 40, d: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """Frames 0.5 m apart on a line; each 2 m stretch shares a pattern, plus per-frame noise."""
    T_wc = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    T_wc[:, 0, 3] = 0.5 * torch.arange(n, dtype=torch.float64)
    patterns = torch.randn(n // 4 + 1, d, 4, 4, generator=generator(8))
    features = patterns[torch.arange(n) // 4] + 0.8 * torch.randn(
        n, d, 4, 4, generator=generator(9)
    )
    return features, T_wc


def finetune_once(seed: int) -> tuple[NetVLAD, object]:
    features, T_wc = place_data()
    netvlad = NetVLAD(num_clusters=4, dim=8)
    netvlad.init_from_kmeans(features.permute(0, 2, 3, 1).reshape(-1, 8), generator(10))
    config = FinetuneConfig(epochs=1, batch_size=4, learning_rate=1e-2)
    return netvlad, finetune_netvlad(netvlad, features, T_wc, config, seed, show_progress=False)


def test_finetuning_one_epoch_reduces_loss_and_is_deterministic() -> None:
    netvlad, result = finetune_once(seed=0)
    assert result.num_tuples == 40 and len(result.epoch_losses) == 1
    assert result.final_loss < 0.8 * result.initial_loss
    again, _ = finetune_once(seed=0)
    for a, b in zip(netvlad.state_dict().values(), again.state_dict().values(), strict=True):
        assert torch.equal(a, b)


def test_triplet_dataset_respects_pose_thresholds() -> None:
    features, T_wc = place_data()
    dataset = TripletDataset(features, T_wc, TripletConfig(num_negatives=3), seed=0)
    x = T_wc[:, 0, 3]
    anchor, positive, negatives = dataset.tuples[:, 0], dataset.tuples[:, 1], dataset.tuples[:, 2:]
    assert torch.all((x[anchor] - x[positive]).abs() <= 1.0) and torch.all(anchor != positive)
    assert torch.all((x[anchor, None] - x[negatives]).abs() > 5.0)
    assert dataset[0].shape == (5, 8, 4, 4)


def test_triplets_across_domains_pair_only_frames_of_another_domain() -> None:
    features, T_wc = place_data()
    domains = torch.arange(40) % 2  # alternate frames: "real" 0, "render" 1
    dataset = TripletDataset(features, T_wc, TripletConfig(num_negatives=3), 0, domains)
    assert len(dataset) == 40
    assert torch.all(
        (dataset.positive | dataset.negative) <= (domains[dataset.anchors, None] != domains)
    )
    netvlad = NetVLAD(num_clusters=4, dim=8)
    netvlad.init_from_kmeans(features.permute(0, 2, 3, 1).reshape(-1, 8), generator(10))
    for tuples in (dataset.tuples, (dataset.mine(netvlad), dataset.tuples)[1]):
        anchor, others = domains[tuples[:, :1]], domains[tuples[:, 1:]]
        assert torch.all(others != anchor)
    with pytest.raises(ShapeError):
        TripletDataset(features, T_wc, TripletConfig(), 0, domains[:5])


def test_mining_picks_best_positive_and_hardest_negatives() -> None:
    features, T_wc = place_data()
    netvlad = NetVLAD(num_clusters=4, dim=8)
    netvlad.init_from_kmeans(features.permute(0, 2, 3, 1).reshape(-1, 8), generator(10))
    dataset = TripletDataset(features, T_wc, TripletConfig(num_negatives=3), seed=0)
    dataset.mine(netvlad)
    embedding = netvlad.aggregate(features).detach()
    similarity = embedding @ embedding.T
    for row, (anchor, positive, *negatives) in enumerate(dataset.tuples.tolist()):
        candidates = torch.nonzero(dataset.positive[row]).flatten()
        assert positive in candidates.tolist()
        assert similarity[anchor, positive] == similarity[anchor, candidates].max()
        pool = torch.nonzero(dataset.negative[row]).flatten()
        hardest = pool[torch.topk(similarity[anchor, pool], 3).indices]
        assert sorted(negatives) == sorted(hardest.tolist())


def test_triplet_loss_is_zero_when_margin_satisfied() -> None:
    netvlad = initialised_netvlad(k=3, d=4)
    module = NetVLADFineTuner(netvlad, margin=0.1)
    a = torch.randn(1, 1, 4, 3, 3, generator=generator(11))
    far = -a  # opposite descriptors: maximal distance
    batch = torch.cat([a, a, far], dim=1)
    assert float(module.triplet_loss(batch).detach()) == 0.0


def test_triplet_dataset_bad_inputs() -> None:
    features, T_wc = place_data()
    with pytest.raises(ShapeError):
        TripletDataset(features[:5], T_wc, TripletConfig())
    with pytest.raises(ValueError, match="positive and a negative"):
        TripletDataset(features, T_wc, TripletConfig(negative_distance_m=100.0))


# --- bag of words -------------------------------------------------------------------------


def word_vocabulary(num_words: int = 6, d: int = 4) -> torch.Tensor:
    """Well separated words: multiples of the unit axes."""
    return 10.0 * torch.eye(max(num_words, d))[:num_words, :d] + torch.arange(num_words)[:, None]


def image_with_words(vocabulary: torch.Tensor, words: list[int]) -> torch.Tensor:
    noise = 0.01 * torch.randn(len(words), vocabulary.shape[1], generator=generator(len(words)))
    return vocabulary[torch.tensor(words)] + noise


def test_bow_identical_image_scores_highest() -> None:
    descriptors = torch.randn(3000, 16, generator=generator(12))
    bow = BagOfWords.train(descriptors, num_words=64, generator=generator(13))
    database = [torch.randn(80, 16, generator=generator(20 + i)) for i in range(10)]
    bow.build(database)
    queries = [database[i] for i in (7, 2, 5)]
    scores, indices = bow.search(queries, k=3)
    assert indices[:, 0].tolist() == [7, 2, 5]
    assert_close(scores[:, 0], torch.ones(3))
    assert torch.all(scores[:, 0] > scores[:, 1])


def test_bow_tfidf_downweights_a_word_present_everywhere() -> None:
    vocabulary = word_vocabulary()
    bow = BagOfWords(vocabulary)
    database = [image_with_words(vocabulary, [0, 0, w]) for w in (1, 2, 3, 4)]
    bow.build(database)
    assert float(bow.idf[0]) == 0.0 and float(bow.idf[1]) == pytest.approx(math.log(4))
    histogram = bow.histograms([image_with_words(vocabulary, [0, 0, 0, 1])])[0]
    assert float(histogram[0]) == 0.0 and float(histogram[1]) == pytest.approx(1.0)
    # the ubiquitous word adds nothing: a query sharing only it scores 0 everywhere
    assert torch.all(bow.score([image_with_words(vocabulary, [0, 5])]) == 0)


def test_bow_inverted_index_equals_dense_dot_products() -> None:
    descriptors = torch.randn(2000, 8, generator=generator(14))
    bow = BagOfWords.train(descriptors, num_words=40, generator=generator(15))
    database = [torch.randn(n, 8, generator=generator(30 + n)) for n in (5, 50, 17, 1, 33, 60)]
    queries = [torch.randn(n, 8, generator=generator(40 + n)) for n in (12, 3, 44)]
    bow.build(database)
    assert bow.indptr.shape == (41,) and int(bow.indptr[-1]) == len(bow.doc_ids)
    expected = bow.histograms(queries) @ bow.histograms(database).T
    assert_close(bow.score(queries), expected)
    assert_close(torch.linalg.vector_norm(bow.histograms(database), dim=1), torch.ones(6))


def test_bow_bad_inputs() -> None:
    bow = BagOfWords(word_vocabulary())
    with pytest.raises(RuntimeError, match="build"):
        bow.score([torch.randn(3, 4)])
    with pytest.raises(ShapeError):
        bow.build([torch.randn(3, 5)])
    with pytest.raises(TypeError):
        bow.build(torch.randn(3, 4))
    with pytest.raises(TypeError):
        BagOfWords(torch.zeros(4, 32, dtype=torch.uint8))
