"""Render rays through a radiance field: sample, evaluate, composite (colour, range, normal)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from diffloc.checks import check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.maps.nerf.field import RadianceField
from diffloc.maps.nerf.rays import camera_rays, ray_box_bounds
from diffloc.maps.nerf.rendering import composite, composite_over, render_weights
from diffloc.maps.nerf.sampler import DensityGrid, interval_lengths

__all__ = ["RenderedRays", "render_image", "render_rays"]


@dataclass
class RenderedRays:
    """Per-ray render results.

    Attributes:
        rgb: (R, 3) colour (over the field's background colour, if it has one), or ``None``
            when colour was not asked for.
        range: (R,) expected termination distance along the ray, metres.
        opacity: (R,) sum of the weights.
        normal: (R, 3) unit rendered normal, or ``None``.
        weights: (R, S) Eq. 5 weights.
        density: (R, S) sample densities, zero where not evaluated (1/m).
        t: (R, S) sample distances.
        deltas: (R, S) sample interval lengths.
    """

    rgb: torch.Tensor | None
    range: torch.Tensor
    opacity: torch.Tensor
    normal: torch.Tensor | None
    weights: torch.Tensor
    density: torch.Tensor
    t: torch.Tensor
    deltas: torch.Tensor


def _scatter(values: torch.Tensor, index: torch.Tensor, total: int) -> torch.Tensor:
    """Values (K, ...) of samples ``index`` (K,) into zeros (total, ...) (differentiable)."""
    return values.new_zeros(total, *values.shape[1:]).index_copy(0, index, values)


class _Marcher:
    """Early ray termination: evaluates samples in chunks of ``chunk`` along the rays (all rays
    at once per chunk) and leaves out the samples of rays whose transmittance, from the
    densities evaluated so far, has fallen to ``stop`` or below, except the lidar window's;
    ``stop`` <= 0 evaluates every sample in one call.

    Args:
        deltas: (R * S,) interval lengths.
        window: (R * S,) bool, samples always evaluated.
        rays: R.
        samples: S.
        stop: transmittance threshold.
        chunk: samples per ray per chunk.
    """

    def __init__(
        self,
        deltas: torch.Tensor,
        window: torch.Tensor,
        rays: int,
        samples: int,
        stop: float,
        chunk: int,
    ) -> None:
        self.deltas, self.window, self.rays, self.samples = deltas, window, rays, samples
        self.max_depth = -math.log(stop) if stop > 0 else None
        self.chunk = chunk

    def __call__(
        self, evaluate: Callable[[torch.Tensor], tuple[torch.Tensor, ...]], index: torch.Tensor
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        """Evaluate samples ``index`` (K,) (flat, ray-major) -> (the evaluated ones (K',),
        ``evaluate``'s outputs for them, each (K', ...), density (K',) first)."""
        if self.max_depth is None:
            return index, evaluate(index)
        depth = self.deltas.new_zeros(self.rays)  # optical depth so far per ray
        part = torch.div(index % self.samples, self.chunk, rounding_mode="floor")
        ray, window = index // self.samples, self.window[index]
        kept, outputs = [], []
        for k in range(-(-self.samples // self.chunk)):
            take = index[(part == k) & ((depth[ray] < self.max_depth) | window)]
            out = evaluate(take)
            tau = out[0].detach() * self.deltas[take]
            depth = depth.index_add(0, take // self.samples, tau)
            kept.append(take)
            outputs.append(out)
        return torch.cat(kept), tuple(torch.cat(o) for o in zip(*outputs, strict=True))


def render_rays(
    field: RadianceField,
    grid: DensityGrid,
    origins: torch.Tensor,
    directions: torch.Tensor,
    generator: torch.Generator | None,
    appearance: torch.Tensor | None = None,
    depth: torch.Tensor | None = None,
    depth_sigma: float = 0.0,
    with_normals: bool = False,
) -> RenderedRays:
    """Render rays.

    Only samples worth it are evaluated (``grid.config``): density where the density grid
    is occupied (and always within 3 ``depth_sigma`` of a lidar range, which the depth loss
    supervises), colour and normals where the Eq. 5 weight exceeds ``min_weight`` (with grad,
    normals from the same evaluation as the density, :meth:`RadianceField.geometry_and_normals`,
    so that the normal loss needs no second evaluation nor double backward); the others
    count as zero, which changes the result by at most those thresholds. With grad enabled,
    a no-grad pre-pass finds the weights first and only samples above ``grad_min_weight``
    (and the lidar window) are differentiable; the others enter as constants. Early ray
    termination (``stop_transmittance`` without grad, ``grad_stop_transmittance`` with):
    samples after a ray's transmittance has fallen to the threshold are not evaluated
    (:class:`_Marcher`), which changes colour and opacity by at most the threshold.
    A field with a background model (``field.config.background``) composites each ray's
    remaining transmittance over its background colour (:func:`composite_over`); range,
    opacity and normals do not see the background.

    Args:
        field: the radiance field.
        grid: its density grid (the sampler).
        origins: (R, 3) world ray origins.
        directions: (R, 3) unit directions.
        generator: source of the sample positions (``None``: deterministic samples).
        appearance: (R, A) appearance codes; ``None`` renders density only (no colour).
        depth: (R,) lidar ranges for guided samples, or ``None``.
        depth_sigma: spread of the guided samples, metres.
        with_normals: also render normals (differentiable when grad is enabled).

    Returns:
        The :class:`RenderedRays`.
    """
    check_shape(origins, "R,3", "origins")
    check_shape(directions, "R,3", "directions")
    box_min = field.normalise.centre - field.normalise.half_extent
    box_max = field.normalise.centre + field.normalise.half_extent
    near, far = ray_box_bounds(origins, directions, box_min, box_max, grid.config.near_m)
    far = far.maximum(near + 1e-3)
    t = grid.sample(origins, directions, near, far, field.normalise, generator, depth, depth_sigma)
    deltas = interval_lengths(t, near, t[:, -1] if field.normalise.contracted else far)
    r, s = t.shape
    points = (origins[:, None] + t[..., None] * directions[:, None]).reshape(-1, 3)
    xyz, inside = field.normalise(points)
    window = torch.zeros_like(inside)
    if depth is not None:
        window = ((t - depth[:, None]).abs() <= 3 * depth_sigma).reshape(-1)
    evaluated = ((grid.occupied(xyz) | window) & inside).nonzero().squeeze(1)
    cfg, grad = grid.config, torch.is_grad_enabled()
    stop = cfg.grad_stop_transmittance if grad else cfg.stop_transmittance
    march = _Marcher(deltas.reshape(-1), window, r, s, stop, cfg.stop_chunk)
    fixed = points.new_zeros(r * s)
    if grad and cfg.grad_min_weight >= 0:
        with torch.no_grad():
            evaluated, (density,) = march(lambda i: (field.density(points[i]),), evaluated)
            fixed = _scatter(density, evaluated, r * s)
            live = render_weights(fixed.reshape(r, s), deltas).reshape(-1)
        live = (live > cfg.grad_min_weight) | window
        evaluated = evaluated[live[evaluated]]
    # With grad (training), normals come from the same evaluation as the density; without
    # (rendering), the density gradient is formed only at the visible samples, usually a small
    # part of the evaluated ones (RadianceField.normals).
    joint = with_normals and grad

    def evaluate(i: torch.Tensor) -> tuple[torch.Tensor, ...]:
        if joint:
            return field.geometry_and_normals(points[i])
        return field.geometry_in_cube(xyz[i], inside[i])

    evaluated, (density, geo, *normals) = march(evaluate, evaluated)
    densities = fixed.index_copy(0, evaluated, density).reshape(r, s)
    weights = render_weights(densities, deltas)
    seen = weights.detach().reshape(-1)[evaluated] > cfg.min_weight
    visible, ray = evaluated[seen], evaluated[seen] // s
    rgb = normal = None
    if appearance is not None:
        colour = field.colour(geo[seen], directions[ray], appearance[ray])
        colours = _scatter(colour, visible, r * s).reshape(r, s, 3)
        background = field.background(appearance)
        if background is None:
            rgb = composite(weights, colours)
        else:
            rgb = composite_over(weights, colours, background)
    if with_normals:
        if joint:
            normals, shaded = normals[0][seen], visible
        else:
            shaded = visible[weights.reshape(-1)[visible] > cfg.normal_min_weight]
            normals = field.normals(points[shaded])
        normal = composite(weights, _scatter(normals, shaded, r * s).reshape(r, s, 3))
        normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    return RenderedRays(
        rgb=rgb,
        range=composite(weights, t),
        opacity=weights.sum(-1),
        normal=normal,
        weights=weights,
        density=densities,
        t=t,
        deltas=deltas,
    )


@torch.no_grad()
def render_image(
    field: RadianceField,
    grid: DensityGrid,
    camera: PinholeCamera,
    T_wc: torch.Tensor,
    appearance: torch.Tensor,
    chunk: int = 8192,
    with_normals: bool = False,
) -> dict[str, torch.Tensor]:
    """Render an image (RGB, depth, optionally normals) at a pose, with deterministic samples
    (strata centres), so that the image does not depend on ``chunk``.

    Args:
        field: the radiance field.
        grid: its density grid.
        camera: unbatched pinhole camera (the output size).
        T_wc: (4, 4) camera-to-world pose.
        appearance: (A,) appearance code.
        chunk: rays per batch.
        with_normals: also render world-frame normals.

    Returns:
        ``rgb`` (3, H, W) in [0, 1], ``depth`` (1, H, W) camera z in metres, ``opacity``
        (1, H, W), and ``normal`` (3, H, W) when asked for.
    """
    uv = camera.pixel_grid(torch.float32).reshape(-1, 2)
    origins, directions, z_per_metre = camera_rays(camera, T_wc.float(), uv)
    parts: dict[str, list[torch.Tensor]] = {"rgb": [], "depth": [], "opacity": [], "normal": []}
    for sl in torch.arange(len(uv)).split(chunk):
        out = render_rays(
            field,
            grid,
            origins[sl],
            directions[sl],
            None,
            appearance.expand(len(sl), -1),
            with_normals=with_normals,
        )
        parts["rgb"].append(out.rgb)
        parts["depth"].append((out.range * z_per_metre[sl])[:, None])
        parts["opacity"].append(out.opacity[:, None])
        if with_normals:
            parts["normal"].append(out.normal)
    h, w = camera.height, camera.width
    return {k: torch.cat(v).T.reshape(-1, h, w) for k, v in parts.items() if v}
