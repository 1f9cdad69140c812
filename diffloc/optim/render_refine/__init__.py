"""Render-and-compare pose refinement: Levenberg-Marquardt on se(3) through a differentiable render.

A localised query's pose ``T_wc`` is refined by minimising, over a right (camera-frame)
perturbation ``T_wc @ exp(delta)``, the robust difference between the query image ``I`` (and
optionally its depth ``D``) and a differentiable render of the map: soft point splatting
(:func:`point_cloud_map`, :func:`~diffloc.render.soft_splat.soft_render_points`) or a trained
radiance field (:func:`radiance_field_map`).

Cost
    ``E(delta) = sum_p m_p rho(|r_p(delta)|^2)``, ``rho`` the Cauchy kernel
    (:func:`~diffloc.optim.robust.cauchy`, scale ``kernel_scale``), with per pixel ``p``::

        r_p = [ (g_c c_pc + b_c - I_pc) / sigma  for c in r, g, b ;
                sqrt(lambda_d) [D_p > 0] (d_p - D_p) / sigma_d ]

    ``c_p = rgb_p / alpha_p`` the render's un-premultiplied colour at the perturbed pose,
    ``d_p`` its depth; ``m_p`` keeps the pixels the map covers (``alpha > min_alpha``) at the
    level's starting pose, fixed during the level so that the level minimises one function.
    ``(g_c, b_c)`` is the per-channel least-squares gain and bias of the render to the query
    over those pixels (:func:`affine_colour_fit`): the map's colours come from other images
    under other exposures (for a radiance field, the query's appearance code is fitted first,
    :func:`fit_query_appearance`). The fit is part of the residual function (variable
    projection), so its dependence on the pose enters the Jacobian.

Jacobian
    The map supplies the six tangent images ``d(rgb, depth, alpha) / d delta_k`` at
    ``delta = 0`` (:class:`DifferentiableMap`): forward-mode autodiff through the splatting,
    reverse mode per ray for the field (rays are independent, so one backward pass per output
    channel gives every ray's derivative). They are pushed through the colour division, the
    affine fit and the whitening by forward mode (:func:`torch.func.jvp`), giving the
    per-pixel ``J_p`` (R x 6). Gauss-Newton with IRLS weights ``rho'`` and Marquardt damping is
    :func:`~diffloc.optim.lm.levenberg_marquardt_single_pose` (its Cayley retraction agrees
    with ``exp`` to first order). Splat placement, depth order and the compared-pixel mask are
    piecewise constant, as in any splatting or sampled volume render: their derivative is 0.

Coarse to fine
    The query is compared at each scale of ``levels`` in turn (the camera scaled, the query
    area-averaged), each level starting from where the previous one ended: a coarse render is
    smoother, so its basin is wider.

Acceptance
    The refined pose replaces the initial one only if, at the finest level and over the pixels
    the map covers at the initial pose, (a) the mean robust cost per pixel fell by more than
    ``min_improvement`` (5 %) of itself, and (b) the render at the refined pose correlates
    with the query by at least ``min_correlation`` (zero-mean normalised cross-correlation,
    averaged over channels). (a) keeps a pose the optimiser cannot show to be better; (b) refuses a
    "better" fit to an image the map does not explain (another place, an occluded view),
    where the cost falls by flattening the render rather than by aligning it.
    Neither (a) nor (b) can tell a move into a wrong local minimum of the cost from a good
    one (both lower the cost and correlate): given a ``verify`` check
    (:func:`match_alignment_check`), (c) the refined pose must also be confirmed by evidence
    the refinement did not fit: feature matches between the query and a larger render at the
    pose, of which at least ``min_inliers`` and no fewer than at the initial pose must be
    aligned (:mod:`~diffloc.optim.render_refine.verification`).

Example:
    >>> RenderRefineConfig().min_correlation
    0.5

Per query, against the part of a map serving it (a thinned cloud or radiance-field submaps,
:mod:`~diffloc.optim.render_refine.sources`), with the appearance fit, the match check and
the timing: :func:`refine_query` (what ``experiments/render_refine.py`` and ``diffloc
task=crossmodal task.refine.enabled=true`` run).

Usage::

    cloud = point_cloud_map(points, colors, radius_m=0.02)      # or radiance_field_map(...)
    result = refine_pose_by_rendering(cloud, query_rgb, T_wc_localised, camera)
    T_wc = result.T_wc        # the refined pose where accepted, else the input
"""

from diffloc.optim.render_refine.config import RenderRefineConfig
from diffloc.optim.render_refine.linearization import (
    DifferentiableMap,
    LinearizeFn,
    RenderFn,
    forward_mode_linearization,
)
from diffloc.optim.render_refine.point_cloud import crop_to_view, point_cloud_map
from diffloc.optim.render_refine.query import QueryRefinement, TimedVerifier, refine_query
from diffloc.optim.render_refine.radiance_field import fit_query_appearance, radiance_field_map
from diffloc.optim.render_refine.refine import RefineResult, refine_pose_by_rendering
from diffloc.optim.render_refine.residuals import (
    affine_colour_fit,
    colour_correlation,
    compared_residuals,
    mean_robust_cost,
)
from diffloc.optim.render_refine.sources import NO_MAP, CloudMaps, FieldSubmaps, QueryMaps
from diffloc.optim.render_refine.verification import (
    MatchCheckConfig,
    MatchEvidence,
    Verifier,
    match_alignment_check,
    match_displacements,
)

__all__ = [
    "NO_MAP",
    "CloudMaps",
    "DifferentiableMap",
    "FieldSubmaps",
    "LinearizeFn",
    "MatchCheckConfig",
    "MatchEvidence",
    "QueryMaps",
    "QueryRefinement",
    "RefineResult",
    "RenderFn",
    "RenderRefineConfig",
    "TimedVerifier",
    "Verifier",
    "affine_colour_fit",
    "colour_correlation",
    "compared_residuals",
    "crop_to_view",
    "fit_query_appearance",
    "forward_mode_linearization",
    "match_alignment_check",
    "match_displacements",
    "mean_robust_cost",
    "point_cloud_map",
    "radiance_field_map",
    "refine_pose_by_rendering",
    "refine_query",
]
