"""Settings of render-and-compare pose refinement (:class:`RenderRefineConfig`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["RenderRefineConfig"]


@dataclass
class RenderRefineConfig:
    """Settings of :func:`~diffloc.optim.render_refine.refine_pose_by_rendering`.

    Attributes:
        levels: image scale factors, coarse to fine, each in (0, 1].
        iterations: Levenberg-Marquardt iterations (linear solves) per level.
        step_expansions: LM step expansions (:class:`~diffloc.optim.lm.LMConfig`; IRLS steps
            under the Cauchy kernel are short).
        min_alpha: pixels whose accumulated opacity is at most this are not compared.
        affine_colour: fit a per-channel gain and bias of the render to the query at every
            evaluation (the map's colours come from other images, exposures and lighting).
        photometric_sigma: intensity noise the colour residuals are divided by.
        kernel_scale: Cauchy scale of the whitened residual norm of a pixel.
        depth_weight: weight ``lambda_d`` of the depth term (0: photometric only; it needs
            query depth).
        depth_sigma_m: depth noise (metres) the depth residuals are divided by.
        min_pixels: fewer compared pixels than this at a level: the query is left alone
            there (too little of the map in view to say anything).
        min_improvement: the refined pose is accepted only if it lowers the finest-level cost
            by more than this fraction. 0.05: on indoor seed 0's real queries against the
            coloured TLS cloud, refinements that moved cm-accurate poses by 6-40 cm lowered
            the cost by 1.5-5.1 % (``experiments/results/render_refine_indoor_seed0.md``);
            no threshold makes that safe when the map's render has its minimum off the
            true pose.
        min_correlation: ... and only if the render at the refined pose correlates with the
            query by at least this (zero-mean normalised cross-correlation, averaged over the
            colour channels): an unrelated image lowers the cost too, but does not correlate.

    Raises:
        ValueError: a setting out of its range (the message names it).

    Example:
        >>> cfg = RenderRefineConfig()
        >>> cfg.levels, cfg.iterations
        ((0.25, 0.5, 1.0), 15)
    """

    levels: tuple[float, ...] = (0.25, 0.5, 1.0)
    iterations: int = 15
    step_expansions: int = 2
    min_alpha: float = 0.5
    affine_colour: bool = True
    photometric_sigma: float = 0.05
    kernel_scale: float = 2.0
    depth_weight: float = 0.0
    depth_sigma_m: float = 0.05
    min_pixels: int = 50
    min_improvement: float = 0.05
    min_correlation: float = 0.5

    def __post_init__(self) -> None:
        self.levels = tuple(float(s) for s in self.levels)
        if not self.levels or not all(0.0 < s <= 1.0 for s in self.levels):
            raise ValueError(f"levels must be scale factors in (0, 1], got {self.levels}")
        for name in ("iterations", "min_pixels"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.step_expansions < 0:
            raise ValueError(f"step_expansions must be >= 0, got {self.step_expansions}")
        for name in ("photometric_sigma", "kernel_scale", "depth_sigma_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be positive, got {value}")
        if not 0.0 <= self.min_alpha < 1.0:
            raise ValueError(f"min_alpha must be in [0, 1), got {self.min_alpha}")
        if not (math.isfinite(self.depth_weight) and self.depth_weight >= 0):
            raise ValueError(f"depth_weight must be >= 0, got {self.depth_weight}")
        if not 0.0 <= self.min_improvement < 1.0:
            raise ValueError(f"min_improvement must be in [0, 1), got {self.min_improvement}")
        if not -1.0 <= self.min_correlation <= 1.0:
            raise ValueError(f"min_correlation must be in [-1, 1], got {self.min_correlation}")
