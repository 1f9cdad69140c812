"""Learned whitening of NetVLAD across the render / real gap: what it learns, the NetVLAD copy
it makes, the retrieval stage with ``method="whitening"``, bad input.

The tiny scene part reuses ``tests/test_retrieval_tuning.py``'s set-up: five mapping images and
five renders of the mesh at the same views, poses 3 m apart on a line, so each mapping image
has exactly one same-place render (its own view).
"""

from __future__ import annotations

import json

import pytest
import torch
import torch.nn.functional as F

from diffloc.checks import ShapeError
from diffloc.crossmodal.retrieval_tuning import RetrievalTuningConfig
from diffloc.crossmodal.retrieval_whitening import (
    same_place_pairs,
    whiten_on_dense_maps,
    whiten_render_retrieval,
)
from diffloc.features.dense import DenseXFeat
from diffloc.features.global_ import NetVLAD
from diffloc.features.learned_whitening import LearnedWhiteningConfig, learned_whitening
from diffloc.pipeline import crossmodal_retrieval
from diffloc.pipeline.crossmodal_retrieval import tune_retrieval_stage
from tests.test_retrieval_tuning import _line_poses, scene, stage_inputs  # noqa: F401 (fixture)

WHITEN = RetrievalTuningConfig(
    method="whitening", whitening=LearnedWhiteningConfig(dim=4, pca_dim=8)
)


def _two_domains(places: int = 40, dim: int = 32, nuisance: float = 4.0, seed: int = 0):
    """(real (P, G), render (P, G)): place vectors plus a large nuisance in a 3-D subspace that
    differs between the two images of a place (lighting / render gap) and a little noise."""
    g = torch.Generator().manual_seed(seed)
    place = torch.randn(places, dim, generator=g)
    basis = torch.linalg.qr(torch.randn(dim, 3, generator=g))[0]  # (G, 3)

    def seen() -> torch.Tensor:
        shift = nuisance * torch.randn(places, 3, generator=g) @ basis.T
        return place + shift + 0.05 * torch.randn(places, dim, generator=g)

    return seen(), seen()


def _top1(queries: torch.Tensor, database: torch.Tensor, truth: torch.Tensor) -> float:
    """Share of the queries whose most similar database row is ``truth`` (Q,)."""
    similarity = F.normalize(queries, dim=1) @ F.normalize(database, dim=1).T
    return float((similarity.argmax(1) == truth).float().mean())


def test_whitening_removes_the_nuisance_that_separates_same_place_pairs():
    real, render = _two_domains()
    assert _top1(real, render, torch.arange(40)) < 0.5  # the nuisance dominates the raw descriptors
    train = torch.arange(30)  # pairs of 30 places teach; 10 held-out places are scored
    descriptors = torch.cat([real[train], render])
    pairs = torch.stack([torch.arange(30), 30 + train], 1)
    mean, projection = learned_whitening(descriptors, pairs, dim=16, pca_dim=32)
    assert mean.shape == (32,) and projection.shape == (32, 16)
    held = torch.arange(30, 40)
    white = lambda x: (x - mean) @ projection  # noqa: E731
    assert _top1(white(real[held]), white(render), held) == 1.0
    assert _top1(real[held], render, held) < 0.5


def test_without_shrinkage_few_pairs_are_still_finite():
    real, render = _two_domains(places=12)
    pairs = torch.stack([torch.arange(3), 12 + torch.arange(3)], 1)  # 3 pairs, 8 dimensions
    _, projection = learned_whitening(torch.cat([real, render]), pairs, 4, 8, shrinkage=0.0)
    assert bool(torch.isfinite(projection).all())


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"pairs": torch.zeros(0, 2, dtype=torch.int64)}, "at least one pair"),
        ({"pairs": torch.tensor([[0, 40]])}, r"indices in \[0, 40\)"),
        ({"pairs": torch.tensor([[0.0, 1.0]])}, "int64"),
        ({"dim": 8, "pca_dim": 4}, "dim <= pca_dim"),
        ({"pca_dim": 40}, "min"),
        ({"shrinkage": 1.5}, "shrinkage"),
    ],
)
def test_bad_whitening_input_is_refused(kwargs, message):
    real, render = _two_domains(places=20)
    args = {
        "descriptors": torch.cat([real, render]),
        "pairs": torch.tensor([[0, 20]]),
        "dim": 4,
        "pca_dim": 8,
        **kwargs,
    }
    with pytest.raises(ValueError, match=message):
        learned_whitening(**args)


def test_non_finite_descriptors_and_bad_shapes_are_refused():
    real, render = _two_domains(places=20)
    x = torch.cat([real, render])
    x[3, 0] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        learned_whitening(x, torch.tensor([[0, 20]]), 4, 8)
    with pytest.raises(ShapeError, match="pairs"):
        learned_whitening(real, torch.tensor([0, 1]), 4, 8)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"dim": 0}, "dim"), ({"dim": 8, "pca_dim": 4}, "pca_dim"), ({"shrinkage": -0.1}, "shrink")],
)
def test_bad_whitening_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        LearnedWhiteningConfig(**kwargs)
    with pytest.raises(ValueError, match="method"):
        RetrievalTuningConfig(method="pca")


def test_whitened_netvlad_copy_keeps_the_clusters_and_projects():
    layer = NetVLAD(num_clusters=2, dim=4)
    layer.init_from_kmeans(torch.randn(50, 4), torch.Generator().manual_seed(0))
    mean, projection = torch.randn(8), torch.randn(8, 3)
    white = layer.whitened(mean, projection)
    x = torch.randn(2, 4, 3, 3)
    with torch.no_grad():
        expected = F.normalize((layer(x) - mean) @ projection, dim=1)
        assert torch.allclose(white(x), expected, atol=1e-6)
    assert torch.equal(white.centroids, layer.centroids) and layer.whiten_dim is None
    with pytest.raises(ShapeError, match="projection"):
        layer.whitened(mean, torch.randn(7, 3))
    with pytest.raises(ShapeError, match="mean"):
        layer.whitened(torch.randn(7), projection)


def test_same_place_pairs_apply_both_bounds():
    T = _line_poses(3)
    turned = T.clone()
    turned[1, :3, :3] = torch.tensor(
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64
    )  # render 1 at real 1's place, turned 90 deg
    assert same_place_pairs(T, turned, 1.0, 30.0).tolist() == [[0, 0], [2, 2]]
    assert same_place_pairs(T, turned, 3.0, 90.0).tolist() == [
        [0, 0],
        [0, 1],
        [1, 0],
        [1, 1],
        [1, 2],
        [2, 1],
        [2, 2],
    ]


def test_whitening_the_tiny_database_redescribes_the_renders(scene):  # noqa: F811
    db, images, T_wc = scene
    before = {k: v.clone() for k, v in db.netvlad.state_dict().items()}
    tuned = whiten_render_retrieval(db, images, T_wc, WHITEN)
    assert tuned.mapping_images == len(images) and tuned.pairs == len(images)
    assert tuned.result is None
    out = tuned.database
    assert out.global_descriptors.shape == (db.num_images, 4)
    assert out.rgb is db.rgb and out.features == db.features
    for name, value in db.netvlad.state_dict().items():  # the input layer is unchanged
        assert torch.equal(value, before[name])
    with torch.no_grad():  # queries are described by the same layer the renders were
        expected = out.netvlad(DenseXFeat()(db.rgb).half().float())
    assert torch.allclose(out.global_descriptors, expected, atol=1e-5)


def test_no_pair_within_the_bounds_names_them(scene):  # noqa: F811
    db, _, T_wc = scene
    maps = torch.zeros(db.num_images, 64, 15, 20, dtype=torch.float16)
    far = T_wc.clone()
    far[:, 1, 3] += 100.0
    with pytest.raises(ValueError, match=r"finetune\.triplets\.positive_distance_m"):
        whiten_on_dense_maps(db, maps, far, maps, WHITEN)
    with pytest.raises(ShapeError, match="renders"):
        whiten_on_dense_maps(db, maps, T_wc, maps[:4], WHITEN)


def test_the_stage_saves_and_reloads_the_whitened_layer(scene, tmp_path, monkeypatch):  # noqa: F811
    db, images, _ = scene
    dataset, outcome = stage_inputs(scene, tmp_path, monkeypatch)
    first, made = tune_retrieval_stage(dataset, "mesh", WHITEN, (db, outcome))
    record = json.loads(
        (dataset / "crossmodal" / "mesh" / "retrieval" / "retrieval.json").read_text()
    )
    assert record["method"] == "whitening" and record["tuples"] == len(images)
    assert record["initial_loss"] is None and record["final_loss"] is None
    monkeypatch.setattr(crossmodal_retrieval, "whiten_render_retrieval", None)  # must not run
    again, reused = tune_retrieval_stage(dataset, "mesh", WHITEN, (db, outcome))
    assert reused.outputs == made.outputs and again.netvlad.whiten_dim == 4
    assert torch.equal(again.global_descriptors, first.global_descriptors)
    x = torch.randn(1, 64, 15, 20)
    with torch.no_grad():
        assert torch.equal(again.netvlad(x), first.netvlad(x))
