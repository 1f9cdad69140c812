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
        uniform_samples: stratified samples per ray.
        guided_samples: samples around the lidar range of rays that have one.
        far_m: far distance of contracted (unbounded) fields, metres.
        near_m: smallest near distance, metres.
    """

    grid_resolution: int = 48
    grid_decay: float = 0.9
    grid_update_every: int = 32
    coarse_samples: int = 128
    importance_samples: int = 24
    uniform_samples: int = 8
    guided_samples: int = 8
    far_m: float = 200.0
    near_m: float = 0.05

    def __post_init__(self) -> None:
        check_int_at_least(self.grid_resolution, "grid_resolution", 2)
        check_number(self.grid_decay, "grid_decay", 0.0, 1.0)
        for name in ("grid_update_every", "coarse_samples"):
            check_int_at_least(getattr(self, name), name, 1)
        for name in ("importance_samples", "uniform_samples", "guided_samples"):
            check_int_at_least(getattr(self, name), name, 0)
        if self.importance_samples + self.uniform_samples + self.guided_samples < 1:
            raise ValueError(
                "importance_samples, uniform_samples and guided_samples must not all be 0"
            )
        check_number(self.near_m, "near_m", 0.0, open_low=True)
        check_number(self.far_m, "far_m", self.near_m, open_low=True)


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

    def lookup(self, xyz: torch.Tensor) -> torch.Tensor:
        """Stored density of the cells holding (..., 3) cube points -> (...)."""
        g = self.config.grid_resolution
        cell = ((xyz + 1.0) * (g / 2.0)).long().clamp(0, g - 1)
        return self.density[cell[..., 0], cell[..., 1], cell[..., 2]]

    @torch.no_grad()
    def sample(
        self,
        origins: torch.Tensor,
        directions: torch.Tensor,
        near: torch.Tensor,
        far: torch.Tensor,
        normalisation: SceneNormalisation,
        generator: torch.Generator,
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
            generator: source of the stratification and the guided offsets.
            depth: (R,) lidar ranges along the rays (> 0), or ``None``.
            depth_sigma: spread of the guided samples, metres.

        Returns:
            (R, S) sorted distances, S = uniform + importance (if the grid has been refreshed)
            + guided (if ``depth`` is given).
        """
        check_shape(origins, "R,3", "origins")
        cfg, r = self.config, len(origins)
        far_outer = cfg.far_m if normalisation.contracted else None
        u = torch.arange(cfg.uniform_samples) + torch.rand(
            r, cfg.uniform_samples, generator=generator
        )
        parts = [spacing(u / cfg.uniform_samples, near, far, far_outer)]
        if cfg.importance_samples and bool(self.refreshed):
            parts.append(self._importance(origins, directions, near, far, normalisation, generator))
        if depth is not None and cfg.guided_samples:
            offsets = torch.randn(r, cfg.guided_samples, generator=generator) * depth_sigma
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
        generator: torch.Generator,
    ) -> torch.Tensor:
        cfg, r = self.config, len(origins)
        far_outer = cfg.far_m if normalisation.contracted else None
        edges = spacing(
            torch.linspace(0, 1, cfg.coarse_samples + 1).expand(r, -1), near, far, far_outer
        )
        mids = (edges[:, 1:] + edges[:, :-1]) / 2
        xyz, inside = normalisation(origins[:, None] + mids[..., None] * directions[:, None])
        weights = render_weights(self.lookup(xyz) * inside, edges[:, 1:] - edges[:, :-1])
        pdf = weights + 1e-3 * weights.sum(-1, keepdim=True).clamp_min(1e-6) / cfg.coarse_samples
        cdf = torch.cumsum(pdf / pdf.sum(-1, keepdim=True), dim=-1)
        cdf = torch.cat((torch.zeros_like(cdf[:, :1]), cdf), dim=-1).contiguous()
        n = cfg.importance_samples
        u = (torch.arange(n) + torch.rand(r, n, generator=generator)) / n
        bins = torch.searchsorted(cdf, u.contiguous(), right=True).clamp(1, cfg.coarse_samples)
        c0, c1 = cdf.gather(1, bins - 1), cdf.gather(1, bins)
        t0, t1 = edges.gather(1, bins - 1), edges.gather(1, bins)
        frac = ((u - c0) / (c1 - c0).clamp_min(1e-9)).clamp(0, 1)
        return t0 + frac * (t1 - t0)
