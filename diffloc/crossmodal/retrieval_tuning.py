"""NetVLAD of a rendered database fine-tuned across the render / real-image gap.

A database rendered from a map is described by a NetVLAD layer fitted (k-means) on the renders
alone, but the queries are real images: renders rank real images poorly. The mapping run's
own images and poses are what a user of the map has (they coloured or textured it), so they
teach the layer: each mapping image is an anchor, its positives are the renders within
``positive_distance_m`` and ``positive_angle_deg`` of it, its negatives the renders farther
than ``negative_distance_m`` (and symmetrically renders as anchors with mapping images as
positives and negatives), the triplet loss of
:func:`~diffloc.features.netvlad_training.finetune_netvlad` with hard mining across the two
domains. The XFeat backbone stays frozen; only the layer (K x 64 centroids and the assignment)
learns, then the renders' global descriptors are computed again with it. No query image or
query pose is ever used.

Usage (XFeat dense maps of every render and mapping image; ``tests/test_retrieval_tuning.py``
runs it on the tiny scene)::

    tuned = tune_render_retrieval(db, mapping_images, mapping_T_wc, RetrievalTuningConfig())
    tuned.database.global_descriptors  # (M, G) with tuned.database.netvlad
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, replace

import torch

from diffloc.checks import ShapeError, check_positive_int, check_shape
from diffloc.crossmodal.database import RenderedDatabase
from diffloc.features.dense import DenseXFeat
from diffloc.features.learned_whitening import LearnedWhiteningConfig
from diffloc.features.netvlad_training import FinetuneConfig, FinetuneResult, finetune_netvlad
from diffloc.progress import progress

__all__ = [
    "RETRIEVAL_METHODS",
    "REAL",
    "RENDER",
    "RetrievalTuningConfig",
    "TunedRetrieval",
    "dense_maps",
    "training_maps",
    "tune_on_dense_maps",
    "tune_render_retrieval",
]

REAL, RENDER = 0, 1
"""Domain labels of the mapping images and the renders."""

RETRIEVAL_METHODS = ("finetune", "whitening")
"""How the mapping images teach the retrieval: triplet fine-tuning of the layer
(:func:`tune_render_retrieval`) or a learned whitening of its descriptors
(:func:`~diffloc.crossmodal.retrieval_whitening.whiten_render_retrieval`)."""


@dataclass
class RetrievalTuningConfig:
    """Settings of :func:`tune_render_retrieval`.

    Attributes:
        method: one of :data:`RETRIEVAL_METHODS`.
        mapping_every: every n-th mapping image is a training image.
        finetune: triplet thresholds and optimisation (positives within 1 m / 30 deg,
            negatives beyond 5 m, 5 hard negatives, margin 0.1 on squared distances); the
            whitening takes its same-place pairs within ``finetune.triplets``' positive
            bounds.
        whitening: dimensions and shrinkage of the learned whitening.
        batch_size: images per XFeat pass.
        seed: seed of the tuple sampling and the batch order.
    """

    method: str = "finetune"
    mapping_every: int = 1
    finetune: FinetuneConfig = field(default_factory=FinetuneConfig)
    whitening: LearnedWhiteningConfig = field(default_factory=LearnedWhiteningConfig)
    batch_size: int = 8
    seed: int = 0

    def __post_init__(self) -> None:
        if self.method not in RETRIEVAL_METHODS:
            raise ValueError(f"method must be one of {RETRIEVAL_METHODS}, got {self.method!r}")
        check_positive_int(self.mapping_every, "mapping_every")
        check_positive_int(self.batch_size, "batch_size")


@dataclass(frozen=True)
class TunedRetrieval:
    """What :func:`tune_render_retrieval` made.

    Attributes:
        database: the input database with the tuned ``netvlad`` and its renders'
            ``global_descriptors`` (images, depth and local features are the same objects).
        result: the loss history (:class:`~diffloc.features.netvlad_training.FinetuneResult`;
            ``None`` for the whitening, which has no loss).
        mapping_images: mapping images used.
        pairs: training tuples (fine-tuning) or same-place pairs (whitening).
    """

    database: RenderedDatabase
    result: FinetuneResult | None
    mapping_images: int
    pairs: int


@torch.no_grad()
def dense_maps(
    images: torch.Tensor,
    dense: DenseXFeat,
    batch_size: int = 8,
    label: str = "images",
    show_progress: bool = False,
) -> torch.Tensor:
    """(N, 64, H // 8, W // 8) float16 XFeat dense maps of (N, 3, H, W) images, ``batch_size``
    images per pass (progress bar ``label``)."""
    batches = progress(images.split(batch_size), label, show_progress)
    return torch.cat([dense(batch).to(torch.float16) for batch in batches])


def tune_render_retrieval(
    database: RenderedDatabase,
    images: torch.Tensor,
    T_wc: torch.Tensor,
    config: RetrievalTuningConfig,
    dense: DenseXFeat | None = None,
    show_progress: bool = False,
) -> TunedRetrieval:
    """Fine-tune a copy of ``database.netvlad`` on mapping images against the renders.

    Args:
        database: the rendered database (its layer is copied, not changed).
        images: (N, 3, H, W) mapping images in [0, 1] at the database camera's size.
        T_wc: (N, 4, 4) their camera-to-world poses (the mapping run's).
        config: settings (``mapping_every`` picks the training images among ``images``).
        dense: the XFeat backbone (loaded when ``None``).
        show_progress: progress bars over the XFeat batches and Lightning's.

    Returns:
        The database with the tuned layer and descriptors, and the loss history.

    Raises:
        ShapeError: images not of the database camera's size, or counts that disagree.
        ValueError: no mapping image has a render within the positive bounds and one beyond
            the negative distance (the message names ``finetune.triplets``).
    """
    real, T_real, renders = training_maps(database, images, T_wc, config, dense, show_progress)
    return tune_on_dense_maps(database, real, T_real, renders, config, show_progress)


def training_maps(
    database: RenderedDatabase,
    images: torch.Tensor,
    T_wc: torch.Tensor,
    config: RetrievalTuningConfig,
    dense: DenseXFeat | None = None,
    show_progress: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The XFeat dense maps the mapping images teach the retrieval with: ``(real (N', 64, h,
    w), their poses (N', 4, 4), renders (M, 64, h, w))``, every ``config.mapping_every``-th
    mapping image and every render of ``database`` (:func:`dense_maps`).

    Raises:
        ShapeError: images not of the database camera's size, or counts that disagree.
    """
    camera = database.camera
    check_shape(images, f"N,3,{camera.height},{camera.width}", "images")
    check_shape(T_wc, "N,4,4", "T_wc")
    if len(images) != len(T_wc):
        raise ShapeError(f"{len(images)} mapping images but {len(T_wc)} poses")
    dense = dense if dense is not None else DenseXFeat()
    keep = slice(None, None, config.mapping_every)
    real = dense_maps(images[keep], dense, config.batch_size, "mapping", show_progress)
    renders = dense_maps(database.rgb, dense, config.batch_size, "renders", show_progress)
    return real, T_wc[keep], renders


def tune_on_dense_maps(
    database: RenderedDatabase,
    real: torch.Tensor,
    T_wc: torch.Tensor,
    renders: torch.Tensor,
    config: RetrievalTuningConfig,
    show_progress: bool = False,
) -> TunedRetrieval:
    """:func:`tune_render_retrieval` on dense maps already made (:func:`dense_maps`; a sweep
    over settings makes them once).

    Args:
        database: the rendered database.
        real: (N, 64, h, w) dense maps of the training mapping images (``mapping_every`` is
            not applied again).
        T_wc: (N, 4, 4) their poses.
        renders: (M, 64, h, w) dense maps of ``database.rgb``.
        config: settings.
        show_progress: Lightning's progress bar.

    Raises:
        ShapeError: counts that disagree.
        ValueError: no training tuple (see :func:`tune_render_retrieval`).
    """
    check_shape(real, "N,D,h,w", "real")
    check_shape(T_wc, f"{len(real)},4,4", "T_wc")
    check_shape(
        renders, f"{database.num_images},{real.shape[1]},{real.shape[2]},{real.shape[3]}", "renders"
    )
    T_wc = T_wc.to(torch.float64)
    domains = torch.cat(
        [torch.full((len(real),), REAL), torch.full((len(renders),), RENDER)]
    ).long()
    netvlad = copy.deepcopy(database.netvlad).train()
    try:
        result = finetune_netvlad(
            netvlad,
            torch.cat([real, renders]),
            torch.cat([T_wc, database.T_wc]),
            config.finetune,
            config.seed,
            show_progress,
            domains,
        )
    except ValueError as exc:
        raise ValueError(
            f"no mapping image pairs with the renders ({exc}); the bounds are finetune.triplets.*"
        ) from exc
    netvlad.eval()
    with torch.no_grad():
        descriptors = torch.cat([netvlad(m.float()) for m in renders.split(config.batch_size)])
    tuned = replace(database, netvlad=netvlad, global_descriptors=descriptors)
    return TunedRetrieval(
        database=tuned, result=result, mapping_images=len(real), pairs=result.num_tuples
    )
