"""Differentiable maps for render-and-compare: a render and its linearisation in the pose.

A map is rendered by ``render(T_wc, camera) -> SoftRender`` (premultiplied rgb, depth,
alpha). Refinement needs, per pixel, the derivative of those images w.r.t. a right
(camera-frame) perturbation ``T_wc @ se3_exp(delta)`` at ``delta = 0``: six tangent images,
given by ``linearize(T_wc, camera) -> (value, tangents)``. Any render written in torch ops
that support forward-mode autodiff gets it from :func:`forward_mode_linearization` (six
``torch.func.jvp`` passes, e.g. :func:`~diffloc.render.soft_splat.soft_render_points`); a
render that does not (``grid_sample`` in the radiance field's encodings has no forward-mode
rule) brings its own (:mod:`~diffloc.optim.render_refine.radiance_field`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import se3_exp
from diffloc.render.soft_splat import SoftRender

__all__ = [
    "DifferentiableMap",
    "LinearizeFn",
    "RenderFn",
    "forward_mode_linearization",
]

RenderFn = Callable[[torch.Tensor, PinholeCamera], SoftRender]
"""``render(T_wc (B, 4, 4), camera) -> SoftRender``: premultiplied rgb (B, 3, H, W), depth
(B, 1, H, W) and alpha (B, 1, H, W)."""

LinearizeFn = Callable[[torch.Tensor, PinholeCamera], tuple[SoftRender, SoftRender]]
"""``linearize(T_wc (B, 4, 4), camera) -> (value, tangents)``: the render at ``T_wc`` and its
derivatives w.r.t. ``T_wc @ se3_exp(delta)`` at ``delta = 0``, each field of ``tangents``
with a leading dimension of 6 (the direction ``delta = e_k``, translation first)."""


@dataclass(frozen=True)
class DifferentiableMap:
    """A map's render and its pose linearisation.

    Attributes:
        render: the render (:data:`RenderFn`), called without gradients.
        linearize: value and six tangent images (:data:`LinearizeFn`).
    """

    render: RenderFn
    linearize: LinearizeFn


def forward_mode_linearization(render: RenderFn) -> LinearizeFn:
    """The :data:`LinearizeFn` of ``render`` by six forward-mode passes (``torch.func.jvp``).

    Each pass perturbs every pose of the batch along the same direction ``e_k``; as an image
    depends only on its own pose, that gives every image's derivative.

    Args:
        render: a render written in torch ops with forward-mode rules.

    Returns:
        ``linearize(T_wc, camera)``.

    Example:
        >>> from diffloc.render.soft_splat import soft_render_points
        >>> cam = PinholeCamera.from_fov(8, 6, 1.0)
        >>> pts = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64)
        >>> render = lambda T, c: soft_render_points(pts, torch.ones(1, 3), 0.05, T, c)
        >>> value, tangents = forward_mode_linearization(render)(
        ...     torch.eye(4, dtype=torch.float64)[None], cam)
        >>> tuple(tangents.rgb.shape)
        (6, 1, 3, 6, 8)
    """

    def linearize(T_wc: torch.Tensor, camera: PinholeCamera) -> tuple[SoftRender, SoftRender]:
        zero = torch.zeros(6, dtype=T_wc.dtype, device=T_wc.device)

        def images(delta: torch.Tensor) -> tuple[torch.Tensor, ...]:
            out = render(T_wc @ se3_exp(delta), camera)
            return out.rgb, out.depth, out.alpha

        columns = []
        for direction in torch.eye(6, dtype=T_wc.dtype, device=T_wc.device):
            value, column = torch.func.jvp(images, (zero,), (direction,))
            columns.append(column)
        tangents = (torch.stack(parts).detach() for parts in zip(*columns, strict=True))
        return SoftRender(*(v.detach() for v in value)), SoftRender(*tangents)

    return linearize
