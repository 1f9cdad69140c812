"""Keyframe retrievers: ranking, save/load round trips, bad folders."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from diffloc.features.local import Features
from diffloc.reloc.retrieval import (
    BowConfig,
    BowRetriever,
    NetVLADConfig,
    NetVLADRetriever,
    load_retriever,
)


def features_of(descriptors: torch.Tensor) -> Features:
    n = descriptors.shape[0]
    return Features(torch.zeros(n, 2), torch.zeros(n), descriptors, torch.ones(n))


@pytest.fixture(scope="module")
def keyframe_descriptors() -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return [
        torch.nn.functional.normalize(torch.randn(200, 64, generator=g), dim=1) for _ in range(6)
    ]


@pytest.fixture(scope="module")
def images() -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    return [torch.rand(3, 64, 96, generator=g) for _ in range(4)]


def test_bow_finds_the_keyframe_a_query_was_taken_from(keyframe_descriptors):
    bow = BowRetriever.fit(keyframe_descriptors, BowConfig(words=64, kmeans_iterations=5))
    query = bow.describe(torch.zeros(3, 8, 8), features_of(keyframe_descriptors[4][:120]))
    scores, keyframes = bow.search(query, 3)
    assert int(keyframes[0]) == 4 and scores.shape == (3,)
    assert bool((scores[:-1] >= scores[1:]).all())


def test_netvlad_ranks_the_same_image_first(images):
    retriever = NetVLADRetriever.fit(images, NetVLADConfig(clusters=4, samples_per_image=50))
    for k, image in enumerate(images):
        scores, keyframes = retriever.search(retriever.describe(image), 2)
        assert int(keyframes[0]) == k
        assert float(scores[0]) == pytest.approx(1.0, abs=1e-4)


@pytest.mark.parametrize("kind", ["bow", "netvlad"])
def test_save_load_round_trip_gives_identical_rankings(
    kind, tmp_path: Path, keyframe_descriptors, images
):
    if kind == "bow":
        retriever = BowRetriever.fit(keyframe_descriptors, BowConfig(words=64, kmeans_iterations=5))
        query = retriever.describe(images[0], features_of(keyframe_descriptors[2][:50]))
    else:
        retriever = NetVLADRetriever.fit(images, NetVLADConfig(clusters=4, samples_per_image=50))
        query = retriever.describe(images[1])
    loaded = load_retriever(retriever.save(tmp_path / kind))
    assert loaded.config == retriever.config
    for a, b in zip(retriever.search(query, 4), loaded.search(query, 4), strict=True):
        torch.testing.assert_close(a, b)


def test_missing_and_foreign_folders_are_clear_errors(tmp_path: Path, keyframe_descriptors):
    with pytest.raises(FileNotFoundError, match="retriever.json"):
        load_retriever(tmp_path / "nothing")
    folder = BowRetriever.fit(keyframe_descriptors, BowConfig(words=16, kmeans_iterations=2)).save(
        tmp_path / "bow"
    )
    (folder / "retriever.json").write_text(json.dumps({"format_version": 99}))
    with pytest.raises(ValueError, match="not a diffloc retriever"):
        load_retriever(folder)
    (folder / "retriever.json").write_text("{broken")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_retriever(folder)


def test_bow_refuses_binary_descriptors():
    with pytest.raises(ValueError, match="float descriptors"):
        BowRetriever.fit([torch.zeros(10, 32, dtype=torch.uint8)], BowConfig())
