"""One localised query refined against the part of a map serving it, timed.

:func:`refine_query` is what ``experiments/render_refine.py`` and the refinement stage of
``diffloc task=crossmodal`` (``task.refine``) do per query: the map part's differentiable
model at the start pose (for a radiance field, the query's appearance code fitted there,
:class:`~diffloc.optim.render_refine.sources.FieldSubmaps`), the optional match check on the
full-size query (:func:`match_alignment_check`), then :func:`refine_pose_by_rendering` on the
query area-resampled to ``scale`` of its size. The process CPU and wall time of all of it are
recorded, the appearance fit's and the check's apart.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from diffloc.checks import check_shape
from diffloc.features.local import LocalFeatureExtractor
from diffloc.geometry.camera import PinholeCamera
from diffloc.optim.render_refine.config import RenderRefineConfig
from diffloc.optim.render_refine.refine import RefineResult, refine_pose_by_rendering
from diffloc.optim.render_refine.sources import QueryMaps
from diffloc.optim.render_refine.verification import (
    MatchCheckConfig,
    MatchEvidence,
    Verifier,
    match_alignment_check,
)

__all__ = ["QueryRefinement", "TimedVerifier", "refine_query"]


class TimedVerifier:
    """A :data:`Verifier` that adds up the process CPU time of its calls in ``cpu_ms``."""

    def __init__(self, verify: Verifier) -> None:
        self.verify, self.cpu_ms = verify, 0.0

    def __call__(self, T_init: torch.Tensor, T_refined: torch.Tensor) -> MatchEvidence:
        cpu = time.process_time()
        try:
            return self.verify(T_init, T_refined)
        finally:
            self.cpu_ms += 1e3 * (time.process_time() - cpu)


@dataclass(frozen=True)
class QueryRefinement:
    """One query's refinement.

    Attributes:
        result: the refinement (batch of one).
        info: how the map part was made (``submap`` and ``fit_cpu_ms`` for a field, ``points``
            for a cloud) and, with a check, its process CPU ms (``check_cpu_ms``).
        cpu_ms: process CPU ms of the whole query (model, fit, check, refinement).
        wall_ms: its wall ms.
    """

    result: RefineResult
    info: dict[str, float]
    cpu_ms: float
    wall_ms: float


def refine_query(
    maps: QueryMaps,
    served: int,
    image: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    scale: float,
    config: RenderRefineConfig,
    check: MatchCheckConfig | None = None,
    extractor: LocalFeatureExtractor | None = None,
) -> QueryRefinement:
    """Refine one query's pose against map part ``served`` (module doc).

    Args:
        maps: the map (:class:`~diffloc.optim.render_refine.sources.QueryMaps`).
        served: the part serving the query (``maps.serving`` of its start pose).
        image: (1, 3, H, W) the query in [0, 1] at ``camera``'s size (float64 advised).
        T_wc: (1, 4, 4) its start pose.
        camera: the query camera.
        scale: the refinement compares the query at ``camera.scaled(scale)``.
        config: the refinement's settings.
        check: the match check on the full-size query, or ``None``.
        extractor: its local features (needed with ``check``).

    Returns:
        :class:`QueryRefinement`.

    Raises:
        ShapeError: an image not (1, 3, H, W) at the camera's size or a pose not (1, 4, 4).
        ValueError: a check without an extractor.
    """
    check_shape(image, f"1,3,{camera.height},{camera.width}", "image")
    check_shape(T_wc, "1,4,4", "T_wc")
    if check is not None and extractor is None:
        raise ValueError("the match check needs a local feature extractor")
    small = camera.scaled(scale).to(image.dtype)
    query = F.interpolate(image, (small.height, small.width), mode="area")
    cpu, wall = time.process_time(), time.perf_counter()
    model, info = maps.model(served, T_wc, query, small)
    verify = None
    if check is not None:
        check_cpu = time.process_time()
        verify = TimedVerifier(match_alignment_check(model, image, camera, extractor, check))
        setup_ms = 1e3 * (time.process_time() - check_cpu)
    result = refine_pose_by_rendering(model, query, T_wc, small, config=config, verify=verify)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    if verify is not None:
        info = {**info, "check_cpu_ms": setup_ms + verify.cpu_ms}
    return QueryRefinement(result, info, 1e3 * cpu, 1e3 * wall)
