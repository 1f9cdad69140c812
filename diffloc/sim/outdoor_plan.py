"""Plan of the outdoor world: the per-seed sizes of the courtyard layout and the route."""

from __future__ import annotations

import numpy as np

from diffloc.sim.outdoor_layout import _OUTDOOR_KEEPOUT_MARGIN, OutdoorLayoutConfig
from diffloc.sim.route import _simplify_route


class _OutdoorPlan:
    """Numbers of the courtyard layout and the route."""

    def __init__(self, cfg: OutdoorLayoutConfig, rng: np.random.Generator) -> None:
        self.cfg = cfg
        scale = rng.uniform(1.0 - cfg.size_jitter, 1.0 + cfg.size_jitter, 8)
        self.W, self.D = cfg.courtyard_width * scale[0], cfg.courtyard_depth * scale[1]
        self.wd, self.A = cfg.wing_depth * scale[2], cfg.approach_length * scale[3]
        self.main_height, self.wing_height = cfg.main_height * scale[4], cfg.wing_height * scale[5]
        self.spacing = cfg.window_spacing * scale[6]
        self.pavilion_out = 1.5 * scale[7]  # how far the pavilions stand out of the wing facades
        self.columns = int(rng.choice([4, 6, 8]))
        self.keepout = cfg.route_clearance + _OUTDOOR_KEEPOUT_MARGIN
        self.xr = self.W / 2 - cfg.facade_setback
        self.portico = 6.1  # depth of the portico platform and its step in front of the main block
        self.y_s = cfg.facade_setback
        self.y_n = self.D - max(cfg.facade_setback, self.portico + self.keepout + 0.5)
        self.gate_half = cfg.route_clearance + 1.6
        self.lawn = np.array([-self.xr, self.y_s, self.xr, self.y_n]) + np.array([1, 1, -1, -1]) * (
            cfg.route_clearance + 0.5
        )
        self.world = np.array(
            [
                -self.W / 2 - self.wd - 20,
                -self.A - 15,
                self.W / 2 + self.wd + 20,
                self.D + self.wd + 15,
            ]
        )
        points = [
            (0.0, -self.A),
            (0.0, self.y_s),
            (self.xr, self.y_s),
            (self.xr, self.y_n),
            (-self.xr, self.y_n),
            (-self.xr, self.y_s),
            (0.0, self.y_s),
            (0.0, -self.A + 6.0),
        ]
        self.route = _simplify_route([(x, y, 0.0) for x, y in points])
