"""Render-and-compare pose refinement: :func:`refine_pose_by_rendering` (see the package doc)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from diffloc.checks import check_finite, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.optim.lm import LMConfig, levenberg_marquardt_single_pose
from diffloc.optim.render_refine.config import RenderRefineConfig
from diffloc.optim.render_refine.linearization import (
    DifferentiableMap,
    RenderFn,
    forward_mode_linearization,
)
from diffloc.optim.render_refine.residuals import (
    colour_correlation,
    compared_residuals,
    mean_robust_cost,
)
from diffloc.optim.render_refine.verification import MatchEvidence, Verifier
from diffloc.optim.robust import RobustKernel
from diffloc.render.soft_splat import SoftRender

__all__ = ["RefineResult", "refine_pose_by_rendering"]


@dataclass(frozen=True)
class RefineResult:
    """Outcome of :func:`refine_pose_by_rendering` for ``B`` queries.

    Attributes:
        T_wc: (B, 4, 4) the refined pose where accepted, else the initial one.
        T_refined: (B, 4, 4) the refinement's pose whether accepted or not.
        cost_before: (B,) mean robust cost per compared pixel at the initial pose, finest
            level, over the pixels the map covers at the initial pose (inf: too few).
        cost_after: (B,) the same at the refined pose.
        correlation: (B,) colour correlation of render and query at the refined pose.
        accepted: (B,) bool, the acceptance rule of the package doc.
        evidence: the check on evidence the refinement did not fit, where one was given
            and called (its ``passed`` is part of ``accepted``), else ``None``.
    """

    T_wc: torch.Tensor
    T_refined: torch.Tensor
    cost_before: torch.Tensor
    cost_after: torch.Tensor
    correlation: torch.Tensor
    accepted: torch.Tensor
    evidence: MatchEvidence | None = None


@dataclass
class _Level:
    """One pyramid level: the camera, the query at its size and the compared pixels."""

    camera: PinholeCamera
    image: torch.Tensor  # (B, 3, h, w)
    depth: torch.Tensor | None  # (B, 1, h, w)
    mask: torch.Tensor  # (B, 1, h, w) bool
    config: RenderRefineConfig

    def residuals(self, out: SoftRender) -> torch.Tensor:
        """(B, h * w, R) residuals of a render at this level."""
        dtype = self.image.dtype
        out = SoftRender(out.rgb.to(dtype), out.depth.to(dtype), out.alpha.to(dtype))
        return compared_residuals(out, self.image, self.mask, self.config, self.depth)

    @property
    def flat_mask(self) -> torch.Tensor:
        """(B, h * w) bool."""
        return self.mask.flatten(1)


def _make_level(
    model: DifferentiableMap,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    image: torch.Tensor,
    depth: torch.Tensor | None,
    config: RenderRefineConfig,
) -> _Level:
    """The level of ``camera``'s size; its pixels are those the map covers at ``T_wc``."""
    size = (camera.height, camera.width)
    if tuple(image.shape[-2:]) != size:
        image = F.interpolate(image, size, mode="area")
        depth = None if depth is None else F.interpolate(depth, size, mode="nearest")
    with torch.no_grad():
        alpha = model.render(T_wc, camera).alpha.to(image.dtype)
    return _Level(camera, image, depth, alpha > config.min_alpha, config)


def _linearized(
    level: _Level, model: DifferentiableMap, T_wc: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Residuals (B, N, R) and Jacobians (B, N, R, 6) at ``T_wc``: the map's tangent images
    pushed through the residuals (colour division, affine fit) by forward-mode autodiff."""
    value, tangents = model.linearize(T_wc, level.camera)
    primal = (value.rgb, value.depth, value.alpha)
    columns = []
    for k in range(6):
        direction = (tangents.rgb[k], tangents.depth[k], tangents.alpha[k])
        residuals, column = torch.func.jvp(
            lambda *images: level.residuals(SoftRender(*images)), primal, direction
        )
        columns.append(column)
    return residuals.detach(), torch.stack(columns, dim=-1).detach()


def _check_inputs(
    image: torch.Tensor, T_wc: torch.Tensor, camera: PinholeCamera, depth: torch.Tensor | None
) -> None:
    check_shape(T_wc, "B,4,4", "T_wc")
    batch = T_wc.shape[0]
    size = f"{camera.height},{camera.width}"
    check_shape(image, f"{batch},3,{size}", "image (B, 3, H, W) at the camera's size")
    check_finite(T_wc, "T_wc")
    check_finite(image, "image")
    if depth is not None:
        check_shape(depth, f"{batch},1,{size}", "depth (B, 1, H, W) at the camera's size")
        check_finite(depth, "depth")


def refine_pose_by_rendering(
    render: RenderFn | DifferentiableMap,
    image: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    depth: torch.Tensor | None = None,
    config: RenderRefineConfig | None = None,
    verify: Verifier | None = None,
) -> RefineResult:
    """Refine ``B`` query poses by render-and-compare (package doc).

    Args:
        render: the map: a render (:data:`RenderFn`, linearised by forward-mode autodiff) or
            a :class:`DifferentiableMap` with its own linearisation.
        image: (B, 3, H, W) query images in [0, 1] at ``camera``'s size (float64 advised:
            the solve runs in the images' dtype).
        T_wc: (B, 4, 4) initial camera-to-world poses.
        camera: the query camera; each level renders at a scaled copy.
        depth: optional (B, 1, H, W) query depth in metres, 0 = none (used when
            ``config.depth_weight > 0``).
        config: settings (default :class:`RenderRefineConfig`).
        verify: a check of the refined poses on other evidence
            (:func:`~diffloc.optim.render_refine.verification.match_alignment_check`),
            called once with the initial and refined poses of the whole batch when any refined
            pose passes the cost and correlation rule (else not at all); a refined pose it
            does not pass is refused.

    Returns:
        :class:`RefineResult`.

    Raises:
        ShapeError: inputs of the wrong shapes (the message names the input and its shape).
        ValueError: NaN/inf poses, images or depths.
    """
    cfg = RenderRefineConfig() if config is None else config
    _check_inputs(image, T_wc, camera, depth)
    if not isinstance(render, DifferentiableMap):
        render = DifferentiableMap(render, forward_mode_linearization(render))
    depth = None if depth is None else depth.to(image.dtype)
    T_init = T_wc.to(image.dtype)
    lm = LMConfig(
        max_iterations=cfg.iterations, initial_damping=1e-3, step_expansions=cfg.step_expansions
    )
    T = T_init
    for factor in cfg.levels:
        level_camera = camera.scaled(factor) if factor < 1.0 else camera
        level = _make_level(render, T, level_camera, image, depth, cfg)
        usable = level.flat_mask.sum(-1) >= cfg.min_pixels
        if not bool(usable.any()):
            continue
        result = levenberg_marquardt_single_pose(
            T,
            lambda T_, lv=level: lv.residuals(render.render(T_, lv.camera)),
            jacobian_fn=lambda T_, lv=level: _linearized(lv, render, T_),
            mask=level.flat_mask,
            kernel=RobustKernel("cauchy", cfg.kernel_scale),
            config=lm,
        )
        T = torch.where(usable[:, None, None], result.T_wc, T)
    result = _accept(render, T_init, T.detach(), camera, image, depth, cfg)
    if verify is None or not bool(result.accepted.any()):
        return result
    evidence = verify(T_init, result.T_refined)
    accepted = result.accepted & evidence.passed
    T_out = torch.where(accepted[:, None, None], result.T_refined, T_init)
    return replace(result, T_wc=T_out, accepted=accepted, evidence=evidence)


def _accept(
    model: DifferentiableMap,
    T_init: torch.Tensor,
    T_refined: torch.Tensor,
    camera: PinholeCamera,
    image: torch.Tensor,
    depth: torch.Tensor | None,
    cfg: RenderRefineConfig,
) -> RefineResult:
    """The acceptance rule: compare costs at the finest level over the initial coverage."""
    finest = _make_level(model, T_init, camera, image, depth, cfg)
    with torch.no_grad():
        before = mean_robust_cost(
            finest.residuals(model.render(T_init, camera)), finest.flat_mask, cfg
        )
        refined = model.render(T_refined, camera)
        after = mean_robust_cost(finest.residuals(refined), finest.flat_mask, cfg)
        correlation = colour_correlation(refined, image, finest.mask)
    accepted = (
        (after < (1.0 - cfg.min_improvement) * before)
        & (correlation >= cfg.min_correlation)
        & torch.isfinite(T_refined).all(-1).all(-1)
    )
    T_out = torch.where(accepted[:, None, None], T_refined, T_init)
    return RefineResult(T_out, T_refined, before, after, correlation, accepted)
