"""NetVLAD of a rendered database whitened across the render / real-image gap.

The alternative to fine-tuning the layer (:mod:`diffloc.crossmodal.retrieval_tuning`): keep
the layer and learn a linear projection of its descriptors in closed form. The mapping run's
images and poses (what a user of the map has; no query image or pose is read) give
same-place pairs: a mapping image and every render within the positive bounds of
``config.finetune.triplets`` (1 m / 30 deg). The learned whitening
(:func:`~diffloc.features.learned_whitening.learned_whitening`) over the renders' and the
mapping images' descriptors damps the directions in which those pairs differ (the render /
real gap, lighting) and keeps those in which places differ. The renders' global descriptors
are computed again through the whitened layer, and queries are described with it.

Usage (XFeat dense maps of every render and mapping image; ``tests/test_retrieval_whitening.py``
runs it on the tiny scene)::

    tuned = whiten_render_retrieval(db, mapping_images, mapping_T_wc, RetrievalTuningConfig(
        method="whitening"))
    tuned.database.global_descriptors  # (M, 256) with tuned.database.netvlad
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from diffloc.checks import check_shape
from diffloc.crossmodal.database import RenderedDatabase
from diffloc.crossmodal.retrieval_tuning import (
    RetrievalTuningConfig,
    TunedRetrieval,
    training_maps,
)
from diffloc.features.dense import DenseXFeat
from diffloc.features.learned_whitening import learned_whitening
from diffloc.features.retrieval_eval import pairwise_pose_distances

__all__ = ["same_place_pairs", "whiten_on_dense_maps", "whiten_render_retrieval"]


def same_place_pairs(
    T_real: torch.Tensor, T_render: torch.Tensor, max_distance_m: float, max_angle_deg: float
) -> torch.Tensor:
    """(P, 2) int64 pairs ``(i, j)``: real image i and render j within the distance and angle.

    Args:
        T_real: (N, 4, 4) camera-to-world poses of the real images.
        T_render: (M, 4, 4) those of the renders.
        max_distance_m: largest camera-centre distance of a pair.
        max_angle_deg: largest relative rotation angle of a pair.

    Example:
        >>> T = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
        >>> T[1, 0, 3], T[2, 0, 3] = 0.5, 5.0
        >>> same_place_pairs(T[:1], T, 1.0, 30.0).tolist()
        [[0, 0], [0, 1]]
    """
    distance, angle = pairwise_pose_distances(T_real, T_render)
    near = (distance <= max_distance_m) & (angle <= np.radians(max_angle_deg))
    return torch.nonzero(torch.as_tensor(near), as_tuple=False).long()


@torch.no_grad()
def whiten_on_dense_maps(
    database: RenderedDatabase,
    real: torch.Tensor,
    T_wc: torch.Tensor,
    renders: torch.Tensor,
    config: RetrievalTuningConfig,
) -> TunedRetrieval:
    """:func:`whiten_render_retrieval` on dense maps already made
    (:func:`~diffloc.crossmodal.retrieval_tuning.training_maps`).

    Args:
        database: the rendered database (its layer is copied, not changed).
        real: (N, 64, h, w) dense maps of the mapping images (``mapping_every`` is not applied
            again).
        T_wc: (N, 4, 4) their poses.
        renders: (M, 64, h, w) dense maps of ``database.rgb``.
        config: settings (``whitening``; the pair bounds of ``finetune.triplets``).

    Raises:
        ShapeError: counts that disagree.
        ValueError: no mapping image has a render within the pair bounds (the message names
            ``finetune.triplets``), or whitening dimensions the descriptors cannot carry.
    """
    check_shape(real, "N,D,h,w", "real")
    check_shape(T_wc, f"{len(real)},4,4", "T_wc")
    check_shape(
        renders, f"{database.num_images},{real.shape[1]},{real.shape[2]},{real.shape[3]}", "renders"
    )
    bounds = config.finetune.triplets
    pairs = same_place_pairs(
        T_wc.to(torch.float64),
        database.T_wc,
        bounds.positive_distance_m,
        bounds.positive_angle_deg,
    )
    if len(pairs) == 0:
        raise ValueError(
            "no mapping image has a render within finetune.triplets.positive_distance_m / "
            "positive_angle_deg: nothing to learn the whitening from"
        )
    layer = database.netvlad

    def describe(maps: torch.Tensor) -> torch.Tensor:
        return torch.cat([layer.aggregate(m.float()) for m in maps.split(config.batch_size)])

    own = describe(renders)
    descriptors = torch.cat([describe(real), own])
    pairs[:, 1] += len(real)  # render indices after the real images
    w = config.whitening
    mean, projection = learned_whitening(descriptors, pairs, w.dim, w.pca_dim, w.shrinkage)
    whitened = layer.whitened(mean, projection)
    tuned = replace(
        database,
        netvlad=whitened,
        global_descriptors=torch.nn.functional.normalize((own - mean) @ projection, dim=1),
    )
    return TunedRetrieval(database=tuned, result=None, mapping_images=len(real), pairs=len(pairs))


def whiten_render_retrieval(
    database: RenderedDatabase,
    images: torch.Tensor,
    T_wc: torch.Tensor,
    config: RetrievalTuningConfig,
    dense: DenseXFeat | None = None,
    show_progress: bool = False,
) -> TunedRetrieval:
    """The database with its NetVLAD whitened by same-place pairs of mapping images and renders.

    Args:
        database: the rendered database (its layer is copied, not changed).
        images: (N, 3, H, W) mapping images in [0, 1] at the database camera's size.
        T_wc: (N, 4, 4) their camera-to-world poses (the mapping run's).
        config: settings (``mapping_every`` picks the images among ``images``).
        dense: the XFeat backbone (loaded when ``None``).
        show_progress: progress bars over the XFeat batches.

    Raises:
        ShapeError: images not of the database camera's size, or counts that disagree.
        ValueError: see :func:`whiten_on_dense_maps`.
    """
    real, T_real, renders = training_maps(database, images, T_wc, config, dense, show_progress)
    return whiten_on_dense_maps(database, real, T_real, renders, config)
