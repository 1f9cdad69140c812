"""Sample distances along rays: stratified, importance from a density grid, lidar-guided.

The density grid (Instant-NGP's occupancy grid, kept as densities) holds, per cell of the
field's cube, a decaying maximum of the field's density, refreshed every few steps. A ray is
marched through it at ``coarse_samples`` points (lookups only, no network), the grid densities
give Eq. 5 weights, and ``importance_samples`` distances are drawn from them by inverse CDF:
empty space and space behind surfaces get few samples. ``uniform_samples`` stratified samples
keep every part of the ray visited, so cells wrongly marked empty can come back. Rays with a
lidar range ``D`` add ``guided_samples`` at ``D + sigma N(0, 1)``, where the depth loss needs
them.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from diffloc.checks import check_int_at_least, check_number, check_shape
from diffloc.maps.nerf.contraction import SceneNormalisation
from diffloc.maps.nerf.rendering import render_weights

__all__ = ["DensityGrid", "SamplerConfig", "interval_lengths", "spacing"]


@dataclass
class SamplerConfig:
    """Settings of ray sampling.

    Attributes:
        grid_resolution: density-grid cells per axis.
        grid_decay: factor applied to the stored densities at each refresh.
        grid_update_every: training steps between refreshes.
        coarse_samples: grid lookups per ray.
        importance_samples: samples drawn from the grid weights (0: uniform sampling only).
        cell_optical_depth: largest optical depth the grid weights give one cell's length of
            ray (cube units, a cell is ``2 / grid_resolution``); 0: no cap. A cell stores the
            maximum density found in it, which spread over the whole cell made it opaque at
            its entry: once the field's surfaces were sharp, the importance samples sat up to
            a cell in front of them (``experiments/results/bench_nerf_sampling.md``). Capped,
            the weights fall by ``exp(-cell_optical_depth)`` over each occupied cell, so the
            samples cover the cell that holds the surface.
        uniform_samples: stratified samples per ray.
        guided_samples: samples around the lidar range of rays that have one.
        far_m: far distance of contracted (unbounded) fields, metres.
        near_m: smallest near distance, metres.
        skip_density: samples in cells whose stored density (1/m), and that of all 26
            neighbours, is below this are not evaluated (density zero) once the grid has been
            refreshed; 0 evaluates all.
        min_weight: samples whose Eq. 5 weight is at most this get no colour or normal
            evaluation (zero); -1 evaluates all.
        normal_min_weight: when rendering without gradients, normals are evaluated only at
            samples whose Eq. 5 weight exceeds this (and ``min_weight``); the others add no
            normal to the composite. Trades accuracy for speed: at 1e-3 (default)
            against 1e-4, on a trained submap of the default indoor scene, the rendered
            normals moved by 0.02-0.03 deg median, 0.25-0.33 deg at the 99th percentile,
            3.3 deg at most, and a 320x240 render computed normals at 13.2 instead of 16.5
            samples per ray (``experiments/results/nerf_speed.md``); set it to
            ``min_weight`` for the unthresholded composite.
        grad_min_weight: when gradients are recorded, a no-grad pre-pass evaluates density at
            every sample first, and only samples whose Eq. 5 weight exceeds this (and lidar
            samples within 3 sigma of the range) are evaluated again with autograd; the others
            keep their pre-pass density as a constant and get no colour or normal (as with
            ``min_weight``): the render changes by at most that weight, and the gradient loses
            only their density terms (proportional to the sample's opacity or transmittance).
            -1 (default): no pre-pass, all differentiable. Off by default because it cost
            12 % more per step over the first 75 CPU s from scratch (little is dropped while
            the field is still transparent) although it saves 9-21 % (1e-4 / 1e-3) per step
            on a trained field (``experiments/results/nerf_speed.md``).
        stop_transmittance: early ray termination when rendering without gradients: samples
            are evaluated ``stop_chunk`` at a time along the rays, and a ray whose
            transmittance has fallen to this or below evaluates no further samples (density
            zero). The dropped samples' weights sum to at most this, so colour and opacity
            change by at most this and range by at most this times the ray's far distance;
            0 evaluates all. Default 1e-4 (``experiments/results/nerf_termination.md``).
        grad_stop_transmittance: the same with gradients recorded (training); lidar-window
            samples are always evaluated. 0 (default): off.
        stop_chunk: samples per ray evaluated at a time when terminating early.
    """

    grid_resolution: int = 48
    grid_decay: float = 0.5
    grid_update_every: int = 16
    coarse_samples: int = 128
    importance_samples: int = 24
    cell_optical_depth: float = 0.5
    uniform_samples: int = 8
    guided_samples: int = 8
    far_m: float = 200.0
    near_m: float = 0.05
    skip_density: float = 0.01
    min_weight: float = 1e-4
    normal_min_weight: float = 1e-3
    grad_min_weight: float = -1.0
    stop_transmittance: float = 1e-4
    grad_stop_transmittance: float = 0.0
    stop_chunk: int = 4

    def __post_init__(self) -> None:
        check_int_at_least(self.grid_resolution, "grid_resolution", 2)
        check_number(self.grid_decay, "grid_decay", 0.0, 1.0)
        for name in ("grid_update_every", "coarse_samples", "stop_chunk"):
            check_int_at_least(getattr(self, name), name, 1)
        for name in ("importance_samples", "uniform_samples", "guided_samples"):
            check_int_at_least(getattr(self, name), name, 0)
        if self.importance_samples + self.uniform_samples + self.guided_samples < 1:
            raise ValueError(
                "importance_samples, uniform_samples and guided_samples must not all be 0"
            )
        check_number(self.near_m, "near_m", 0.0, open_low=True)
        check_number(self.far_m, "far_m", self.near_m, open_low=True)
        check_number(self.skip_density, "skip_density", 0.0)
        check_number(self.cell_optical_depth, "cell_optical_depth", 0.0)
        check_number(self.min_weight, "min_weight", -1.0, 1.0)
        check_number(self.normal_min_weight, "normal_min_weight", -1.0, 1.0)
        check_number(self.grad_min_weight, "grad_min_weight", -1.0, 1.0)
        check_number(self.stop_transmittance, "stop_transmittance", 0.0, 1.0)
        check_number(self.grad_stop_transmittance, "grad_stop_transmittance", 0.0, 1.0)


def _jitter(rows: int, n: int, generator: torch.Generator | None) -> torch.Tensor:
    """Stratified positions (rows, n) in [0, 1): uniform within each of n strata, or the
    strata centres when ``generator`` is ``None`` (deterministic rendering)."""
    offsets = torch.rand(rows, n, generator=generator) if generator is not None else 0.5
    return ((torch.arange(n) + offsets) / n).expand(rows, n)


def spacing(s: torch.Tensor, near: torch.Tensor, far: torch.Tensor, far_outer: float | None):
    """Distances of normalised positions ``s`` in [0, 1] along rays.

    Linear from ``near`` to ``far`` when ``far_outer`` is ``None``; otherwise the first half is
    linear to ``far`` (the box exit) and the second half uniform in inverse distance from
    ``far`` to ``far_outer`` (mip-NeRF 360's spacing for the contracted space).

    Args:
        s: (R, K) positions.
        near: (R,) near distances.
        far: (R,) far (box exit) distances.
        far_outer: outer far distance, or ``None``.

    Returns:
        (R, K) distances.
    """
    near, far = near[:, None], far[:, None]
    if far_outer is None:
        return near + s * (far - near)
    # A ray that meets the box only beyond the outer far distance (a camera far outside the
    # box) has nothing within it to sample: its distances collapse onto far_outer.
    far = far.clamp(max=far_outer)
    near = near.minimum(far)
    inner = near + (2 * s).clamp(max=1.0) * (far - near)
    outer_s = (2 * s - 1).clamp(min=0.0)
    outer = 1.0 / (1.0 / far + outer_s * (1.0 / far_outer - 1.0 / far))
    return torch.where(s <= 0.5, inner, outer)


def interval_lengths(t: torch.Tensor, near: torch.Tensor, far: torch.Tensor) -> torch.Tensor:
    """Length of each sample's interval (bounded by the midpoints to its neighbours and by
    ``near``/``far`` at the ends): t (R, S) sorted, near/far (R,) -> (R, S)."""
    mids = (t[:, 1:] + t[:, :-1]) / 2
    edges = torch.cat((near[:, None].minimum(t[:, :1]), mids, far[:, None].maximum(t[:, -1:])), 1)
    return edges[:, 1:] - edges[:, :-1]


class DensityGrid(nn.Module):
    """A coarse density grid over the field's cube, and the samplers that use it.

    Args:
        config: sampling settings.
    """

    def __init__(self, config: SamplerConfig) -> None:
        super().__init__()
        self.config = config
        g = config.grid_resolution
        self.register_buffer("density", torch.zeros(g, g, g))
        self.register_buffer("refreshed", torch.zeros((), dtype=torch.bool))
        self._occupied_cache: tuple[int, torch.Tensor] | None = None

    @property
    def in_use(self) -> bool:
        """Whether sampling reads the grid (importance samples or skipping)."""
        return self.config.importance_samples > 0 or self.config.skip_density > 0

    @torch.no_grad()
    def refresh(
        self, density_fn, normalisation: SceneNormalisation, generator: torch.Generator
    ) -> None:
        """Refresh every cell with the field's density at a random point of the cell.

        Args:
            density_fn: (N, 3) world points -> (N,) densities.
            normalisation: the field's world-to-cube map.
            generator: source of the points within cells.
        """
        g = self.config.grid_resolution
        idx = torch.arange(g, dtype=torch.float32)
        cells = torch.stack(torch.meshgrid(idx, idx, idx, indexing="ij"), dim=-1).reshape(-1, 3)
        jitter = torch.rand(cells.shape, generator=generator)
        xyz = (cells + jitter) / g * 2.0 - 1.0
        values = torch.cat([density_fn(chunk) for chunk in normalisation.inverse(xyz).split(65536)])
        decayed = self.density * self.config.grid_decay if bool(self.refreshed) else self.density
        self.density.copy_(torch.maximum(decayed, values.reshape(g, g, g)))
        self.refreshed.fill_(True)

    def occupied(self, xyz: torch.Tensor) -> torch.Tensor:
        """Whether (..., 3) cube points lie in cells worth evaluating -> (...) bool: a cell is
        if it or a neighbour (3x3x3 block: the one probe per cell may miss a thin surface)
        stores at least ``skip_density``; all points until the first refresh or when
        ``skip_density`` is 0."""
        if not bool(self.refreshed) or self.config.skip_density <= 0:
            return torch.ones(xyz.shape[:-1], dtype=torch.bool, device=xyz.device)
        return self._occupied_cells().view(-1).take(self._cell_index(xyz))

    def _cell_index(self, xyz: torch.Tensor) -> torch.Tensor:
        """Flat index (...) into the (g, g, g) grid of the cells holding (..., 3) cube points
        (clamped to the grid)."""
        g = self.config.grid_resolution
        u = ((xyz + 1.0) * (g / 2.0)).clamp_(0, g - 1).floor_()
        return ((u[..., 0] * g + u[..., 1]) * g + u[..., 2]).long()

    def _occupied_cells(self) -> torch.Tensor:
        """(g, g, g) bool: cells whose 3x3x3 block stores at least ``skip_density``. Cached
        until the density grid changes (a refresh or a loaded checkpoint writes it in place,
        which bumps the tensor's version counter)."""
        version = self.density._version
        if self._occupied_cache is None or self._occupied_cache[0] != version:
            block = F.max_pool3d(self.density[None, None], 3, stride=1, padding=1)[0, 0]
            self._occupied_cache = (version, block >= self.config.skip_density)
        return self._occupied_cache[1]

    def _line_lookup(
        self, start: torch.Tensor, step: torch.Tensor, t: torch.Tensor
    ) -> torch.Tensor:
        """:meth:`lookup` of the cube points ``start + t step`` of lines: start, step (R, 3),
        t (R, K) -> (R, K); axis by axis on contiguous (R, K) tensors (the same cells as
        :meth:`_cell_index` up to rounding at cell faces)."""
        g = self.config.grid_resolution
        index = torch.zeros_like(t, dtype=torch.long)
        for axis in range(3):
            u = torch.addcmul(
                (start[:, axis, None] + 1.0) * (g / 2.0), t, step[:, axis, None] * (g / 2.0)
            )
            index.mul_(g).add_(u.clamp_(0, g - 1).long())  # >= 0: truncation floors
        return self.density.view(-1).take(index)

    def lookup(self, xyz: torch.Tensor) -> torch.Tensor:
        """Stored density of the cells holding (..., 3) cube points -> (...)."""
        return self.density.view(-1).take(self._cell_index(xyz))

    @torch.no_grad()
    def sample(
        self,
        origins: torch.Tensor,
        directions: torch.Tensor,
        near: torch.Tensor,
        far: torch.Tensor,
        normalisation: SceneNormalisation,
        generator: torch.Generator | None,
        depth: torch.Tensor | None = None,
        depth_sigma: float = 0.0,
    ) -> torch.Tensor:
        """Sorted sample distances along rays.

        Args:
            origins: (R, 3) ray origins (world).
            directions: (R, 3) unit directions.
            near: (R,) near distances.
            far: (R,) far distances (box exit).
            normalisation: the field's world-to-cube map.
            generator: source of the stratification and the guided offsets; ``None`` takes
                strata centres and normal quantiles (the same distances for any batching).
            depth: (R,) lidar ranges along the rays (> 0), or ``None``.
            depth_sigma: spread of the guided samples, metres.

        Returns:
            (R, S) sorted distances, S = uniform + importance (if the grid has been refreshed)
            + guided (if ``depth`` is given).
        """
        check_shape(origins, "R,3", "origins")
        cfg, r = self.config, len(origins)
        far_outer = cfg.far_m if normalisation.contracted else None
        parts = [spacing(_jitter(r, cfg.uniform_samples, generator), near, far, far_outer)]
        if cfg.importance_samples and bool(self.refreshed):
            parts.append(self._importance(origins, directions, near, far, normalisation, generator))
        if depth is not None and cfg.guided_samples:
            quantiles = torch.special.ndtri(_jitter(r, cfg.guided_samples, generator).clamp(1e-6))
            offsets = quantiles * depth_sigma
            upper = far.maximum(near) if far_outer is None else torch.full_like(far, far_outer)
            guided = (depth[:, None] + offsets).clamp(min=near[:, None]).minimum(upper[:, None])
            parts.append(guided)
        return torch.cat(parts, dim=-1).sort(dim=-1).values

    def _importance(
        self,
        origins: torch.Tensor,
        directions: torch.Tensor,
        near: torch.Tensor,
        far: torch.Tensor,
        normalisation: SceneNormalisation,
        generator: torch.Generator | None,
    ) -> torch.Tensor:
        cfg, r = self.config, len(origins)
        far_outer = cfg.far_m if normalisation.contracted else None
        edges = spacing(
            torch.linspace(0, 1, cfg.coarse_samples + 1).expand(r, -1), near, far, far_outer
        )
        lengths = edges[:, 1:] - edges[:, :-1]
        if normalisation.contracted:  # the cell of an interval is that of its chord's midpoint
            cube, inside = normalisation(
                torch.addcmul(origins[:, None], edges[..., None], directions[:, None])
            )
            chords = cube[:, 1:] - cube[:, :-1]
            tau = self.lookup(torch.add(cube[:, :-1], chords, alpha=0.5))
            tau = tau.mul_(lengths).mul_(inside[:, 1:] | inside[:, :-1])
            cube_lengths = chords.norm(dim=-1)
        else:  # affine, and the rays are clipped to the box: lines through the cube
            step = directions / normalisation.half_extent
            start = (origins - normalisation.centre) / normalisation.half_extent
            tau = self._line_lookup(start, step, (edges[:, 1:] + edges[:, :-1]) / 2).mul_(lengths)
            cube_lengths = lengths * step.norm(dim=-1, keepdim=True)
        if cfg.cell_optical_depth > 0:
            cap = cube_lengths.mul_(cfg.cell_optical_depth * cfg.grid_resolution / 2)
            tau = tau.minimum(cap)
        weights = render_weights(tau, torch.ones_like(tau))
        pdf = weights + 1e-3 * weights.sum(-1, keepdim=True).clamp_min(1e-6) / cfg.coarse_samples
        cdf = torch.cumsum(pdf / pdf.sum(-1, keepdim=True), dim=-1)
        cdf = torch.cat((torch.zeros_like(cdf[:, :1]), cdf), dim=-1).contiguous()
        n = cfg.importance_samples
        u = _jitter(r, n, generator)
        bins = torch.searchsorted(cdf, u.contiguous(), right=True).clamp(1, cfg.coarse_samples)
        c0, c1 = cdf.gather(1, bins - 1), cdf.gather(1, bins)
        t0, t1 = edges.gather(1, bins - 1), edges.gather(1, bins)
        frac = ((u - c0) / (c1 - c0).clamp_min(1e-9)).clamp(0, 1)
        return t0 + frac * (t1 - t0)
