"""Residuals of render-and-compare: render vs query image (and depth), robust cost, correlation.

Premultiplied renders are divided by their opacity (the mean colour of a pixel), optionally
mapped to the query by the per-channel least-squares gain and bias over the compared pixels
(:func:`affine_colour_fit`, differentiable: the fit moves with the render), and compared with
the query; the depth term compares rendered and measured depth where the query has one.
"""

from __future__ import annotations

import math

import torch

from diffloc.optim.render_refine.config import RenderRefineConfig
from diffloc.optim.robust import cauchy
from diffloc.render.soft_splat import SoftRender

__all__ = [
    "affine_colour_fit",
    "colour",
    "colour_correlation",
    "compared_residuals",
    "mean_robust_cost",
]

_MIN_ALPHA_DIVISOR = 1e-3
_MIN_GAIN, _MAX_GAIN = 0.2, 5.0


def _masked_moments(
    a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor
) -> tuple[torch.Tensor, ...]:
    """Means, variances and covariance (B, C) of ``a`` and ``b`` (B, C, H, W) over ``mask``
    (B, 1, H, W)."""
    w = mask.to(a.dtype)
    n = w.sum((2, 3)).clamp_min(1.0)
    mean_a, mean_b = (w * a).sum((2, 3)) / n, (w * b).sum((2, 3)) / n
    da, db = (a - mean_a[..., None, None]) * w, (b - mean_b[..., None, None]) * w
    return mean_a, mean_b, (da * da).sum((2, 3)), (db * db).sum((2, 3)), (da * db).sum((2, 3))


def colour(render: SoftRender) -> torch.Tensor:
    """(B, 3, H, W) the un-premultiplied colour ``rgb / alpha`` of a render."""
    return render.rgb / render.alpha.clamp_min(_MIN_ALPHA_DIVISOR)


def affine_colour_fit(
    render: torch.Tensor, target: torch.Tensor, mask: torch.Tensor
) -> torch.Tensor:
    """``g_c render + b_c``, the per-channel least-squares fit of ``render`` to ``target``.

    The gain is clamped to [0.2, 5] (1 where the render is flat); gain and bias are
    differentiable functions of ``render``.

    Args:
        render: (B, C, H, W) rendered colours.
        target: (B, C, H, W) query colours.
        mask: (B, 1, H, W) bool, the pixels the fit uses.

    Returns:
        (B, C, H, W) the fitted render.

    Example:
        >>> r = torch.tensor([0.0, 0.5, 1.0]).view(1, 1, 1, 3)
        >>> affine_colour_fit(r, 0.5 * r + 0.1, torch.ones(1, 1, 1, 3, dtype=torch.bool))
        tensor([[[[0.1000, 0.3500, 0.6000]]]])
    """
    mean_r, mean_t, var, _, cov = _masked_moments(render, target, mask)
    flat = var <= 1e-8
    gain = torch.where(flat, 1.0, cov / torch.where(flat, 1.0, var)).clamp(_MIN_GAIN, _MAX_GAIN)
    bias = mean_t - gain * mean_r
    return gain[..., None, None] * render + bias[..., None, None]


def colour_correlation(render: SoftRender, image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B,) zero-mean normalised cross-correlation of the render's colour and ``image``
    (B, 3, H, W) over ``mask`` (B, 1, H, W), averaged over the channels (0 for a flat one)."""
    _, _, var_r, var_i, cov = _masked_moments(colour(render), image, mask)
    denom = (var_r * var_i).sqrt()
    return torch.where(denom > 1e-12, cov / denom.clamp_min(1e-12), 0.0).mean(-1)


def compared_residuals(
    render: SoftRender,
    image: torch.Tensor,
    mask: torch.Tensor,
    config: RenderRefineConfig,
    depth: torch.Tensor | None = None,
) -> torch.Tensor:
    """Whitened residuals of a render against a query, per pixel.

    ``((g c + b) - I) / photometric_sigma`` per colour channel (``c`` the render's colour,
    ``(g, b)`` its :func:`affine_colour_fit` when ``config.affine_colour``), then, with
    ``depth`` and ``config.depth_weight > 0``, ``sqrt(depth_weight) (d - D) / depth_sigma_m``
    where ``D > 0``; zero outside ``mask``.

    Args:
        render: the render (B, 3 | 1 | 1, H, W).
        image: (B, 3, H, W) query colours.
        mask: (B, 1, H, W) bool, the compared pixels.
        config: the weights.
        depth: optional (B, 1, H, W) query depth in metres, 0 = none.

    Returns:
        (B, H * W, R) residuals, ``R = 3`` or 4 with depth.
    """
    fitted = colour(render)
    if config.affine_colour:
        fitted = affine_colour_fit(fitted, image, mask)
    parts = [(fitted - image) / config.photometric_sigma]
    if depth is not None and config.depth_weight > 0:
        weight = math.sqrt(config.depth_weight) / config.depth_sigma_m
        parts.append((depth > 0).to(image.dtype) * weight * (render.depth - depth))
    residuals = torch.cat(parts, dim=1) * mask.to(image.dtype)
    return residuals.flatten(2).transpose(1, 2)


def mean_robust_cost(
    residuals: torch.Tensor, mask: torch.Tensor, config: RenderRefineConfig
) -> torch.Tensor:
    """(B,) mean Cauchy cost ``rho(|r_p|^2)`` per compared pixel of residuals (B, N, R) over
    ``mask`` (B, N); ``inf`` where fewer than ``config.min_pixels`` pixels are compared."""
    rho, _ = cauchy(residuals.square().sum(-1), config.kernel_scale)
    pixels = mask.sum(-1)
    cost = (rho * mask).sum(-1) / pixels.clamp_min(1)
    return torch.where(pixels >= config.min_pixels, cost, math.inf)
