"""Re-rendering a rendered map at a pose found, and matching the query against that render.

The rendered-database localiser (:mod:`diffloc.reloc.rendered`) matches a query against
database renders up to the render spacing and 45 deg away from it, so a right pose may rest on
few inliers over little of the image. A rendered map can be rendered at any pose: rendered at
the pose found (nearly the query's viewpoint when the pose is right), it should give the query
more matches, spread over more of the image. :func:`rerender_candidate` does that one step:
render the map at ``T_wc`` with the database camera, XFeat on the render, LighterGlue against
the query's features, lifting with the render's depth and PnP RANSAC + refinement
(:func:`~diffloc.reloc.rendered.reference_candidate`, the localiser's own code), and the
photometric consistency of the render warped into the query at the new pose
(:func:`~diffloc.reloc.photometric.warped_ncc`). Each step is timed (wall and process CPU).

Used by the re-render check of ``diffloc task=crossmodal``
(:mod:`diffloc.pipeline.crossmodal_rerender`), the storey-alias test
(:mod:`diffloc.reloc.storey_alias`) and ``experiments/rerender_check.py``.

Usage::

    result = rerender_candidate(rgbd_map, T_wc, db.camera, image, query, camera,
                                (localizer.extractor, localizer.matcher), config, generator)
    result.candidate.num_inliers, result.candidate.coverage, result.photometric
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from diffloc.checks import check_finite, check_shape
from diffloc.crossmodal.synthesize import RGBDMap
from diffloc.features.local import Features, XFeatExtractor
from diffloc.features.matching import LighterGlueMatcher
from diffloc.geometry.camera import PinholeCamera
from diffloc.reloc.photometric import grey_image, warped_ncc
from diffloc.reloc.rendered import RenderedCandidate, RenderedLocalizerConfig, reference_candidate
from diffloc.reloc.stage_clock import StageClock

__all__ = ["RERENDER_STAGES", "Rerendered", "rerender_candidate"]

RERENDER_STAGES = ("render", "features", "matching", "pnp", "photometric")
"""The timed steps of :func:`rerender_candidate`, in order."""


@dataclass(frozen=True)
class Rerendered:
    """The outcome of matching a query against a render made at a pose.

    Attributes:
        candidate: the pose from the render (``reference`` -1; ``T_wc`` the new (4, 4)
            float64 query camera-to-world pose when ``success``), with its matches, points
            with depth, inliers, coverage and plane share.
        photometric: the render warped into the query at the new pose, median per-cell NCC
            (NaN: no new pose, or too little overlap to score).
        wall_ms: step of :data:`RERENDER_STAGES` -> wall milliseconds.
        cpu_ms: step -> process CPU milliseconds.
    """

    candidate: RenderedCandidate
    photometric: float
    wall_ms: dict[str, float]
    cpu_ms: dict[str, float]


def rerender_candidate(
    rgbd_map: RGBDMap,
    T_wc: torch.Tensor,
    render_camera: PinholeCamera,
    image: torch.Tensor,
    query: Features,
    camera: PinholeCamera,
    networks: tuple[XFeatExtractor, LighterGlueMatcher],
    config: RenderedLocalizerConfig,
    generator: torch.Generator,
    photometric: bool = True,
) -> Rerendered:
    """Render ``rgbd_map`` at ``T_wc``, match the query against the render and solve its pose.

    Args:
        rgbd_map: the map (a :class:`~diffloc.crossmodal.synthesize.RGBDMap`).
        T_wc: (4, 4) the pose to render at (the query pose found), camera-to-world.
        render_camera: the render's camera (unbatched; the database's).
        image: (3, H, W) the query image in [0, 1], of ``camera``'s size.
        query: the query's features (keypoints in ``image``'s pixels).
        camera: the query camera (unbatched).
        networks: ``(extractor, matcher)``: XFeat for the render and LighterGlue (the
            localiser's own).
        config: the localiser's settings (matching confidence, PnP, coverage grid, photometric
            settings).
        generator: RANSAC's random generator.
        photometric: also score the photometric consistency of the pose found (``False``:
            ``photometric`` is NaN, for callers that read only the candidate).

    Returns:
        The :class:`Rerendered` outcome.

    Raises:
        ShapeError: ``T_wc`` not (4, 4), or ``image`` not (3, H, W) of ``camera``'s size.
        ValueError: a non-finite ``T_wc``.
    """
    check_shape(T_wc, "4,4", "T_wc")
    check_finite(T_wc, "T_wc")
    check_shape(image, f"3,{camera.height},{camera.width}", "image")
    extractor, matcher = networks
    T_wc = T_wc.to(torch.float64)
    clock = StageClock(RERENDER_STAGES)
    with clock.measure("render"):
        view = rgbd_map.render(T_wc[None], render_camera)
    rgb, depth = view.rgb[0], view.depth[0]
    with clock.measure("features"):
        features = extractor.extract(rgb)
    with clock.measure("matching"):
        matches = matcher.match(
            query,
            features,
            (camera.height, camera.width),
            (render_camera.height, render_camera.width),
        )
    with clock.measure("pnp"):
        candidate = reference_candidate(
            query, camera, matches, (features, depth, render_camera, T_wc), config, generator
        )
    consistency = math.nan
    if photometric and candidate.success:
        with clock.measure("photometric"):
            grey = grey_image(rgb, render_camera.height, render_camera.width)
            consistency = warped_ncc(
                grey,
                depth[0],
                render_camera,
                T_wc,
                image,
                camera,
                candidate.T_wc,
                config.photometric,
            )
    return Rerendered(candidate, consistency, clock.wall_ms, clock.cpu_ms)
