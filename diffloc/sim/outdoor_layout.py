"""Layout config of the outdoor world (a palace courtyard) and its validation."""

from __future__ import annotations

from dataclasses import dataclass

from diffloc.sim.layout_checks import _check_config

__all__ = ["OutdoorLayoutConfig"]

# Margin beyond the route clearance kept free of clutter (metres).
_OUTDOOR_KEEPOUT_MARGIN = 1.5


@dataclass
class OutdoorLayoutConfig:
    """A palace-like courtyard reached by an avenue (metres unless stated).

    A main block (north) and two wings (east, west) with corner pavilions enclose a courtyard
    with a raised lawn and a centrepiece; a gate wall closes it to the south, where an avenue
    lined by trees and outbuildings leads in. The route drives in along the avenue, once around
    the lawn and back out. Each seed scales the sizes below by a random factor within
    +-``size_jitter`` (validation assumes the smallest factor).

    Attributes:
        courtyard_width: distance between the two wing facades (x).
        courtyard_depth: distance from the gate wall to the main facade (y).
        wing_depth: depth of the wings and the main block.
        main_height: eaves height of the main block.
        wing_height: eaves height of the wings.
        storey_height: facade storey height (window rows).
        window_spacing: distance between window axes on facades.
        approach_length: length of the avenue south of the gate.
        facade_setback: distance from the route to the courtyard facades.
        size_jitter: relative per-seed variation of the courtyard, building and avenue sizes.
        n_trees: trees attempted on the lawn and outside.
        n_cars: parked cars attempted.
        n_bikes: bikes attempted.
        clutter_count: other clutter attempted (benches, bins, signs, planters, columns, statues).
        n_outbuildings: outbuildings along the avenue (asymmetric part of the layout).
        route_clearance: free space kept on each side of the route (more than the largest
            lateral offset of a query route).
        texture_size: texture side length in texels.
        n_changed_objects: movable objects moved, removed or added in the changed scene.
    """

    courtyard_width: float = 70.0
    courtyard_depth: float = 56.0
    wing_depth: float = 14.0
    main_height: float = 18.0
    wing_height: float = 14.0
    storey_height: float = 4.4
    window_spacing: float = 3.8
    approach_length: float = 35.0
    facade_setback: float = 10.5
    size_jitter: float = 0.08
    n_trees: int = 16
    n_cars: int = 10
    n_bikes: int = 8
    clutter_count: int = 30
    n_outbuildings: int = 3
    route_clearance: float = 4.0
    texture_size: int = 256
    n_changed_objects: int = 12


def _validate_outdoor(cfg: OutdoorLayoutConfig) -> None:
    positive = (
        "courtyard_width",
        "courtyard_depth",
        "wing_depth",
        "main_height",
        "wing_height",
        "storey_height",
        "window_spacing",
        "approach_length",
        "facade_setback",
        "route_clearance",
    )
    counts = (
        "n_trees",
        "n_cars",
        "n_bikes",
        "clutter_count",
        "n_outbuildings",
        "n_changed_objects",
    )
    _check_config(cfg, positive, counts)
    keepout = cfg.route_clearance + _OUTDOOR_KEEPOUT_MARGIN
    if not 0.0 <= cfg.size_jitter <= 0.3:
        raise ValueError(f"layout.size_jitter must be in [0, 0.3], got {cfg.size_jitter!r}")
    low = 1.0 - cfg.size_jitter
    rules = [
        (
            cfg.facade_setback >= keepout + 1.0,
            f"facade_setback must be >= route_clearance + {_OUTDOOR_KEEPOUT_MARGIN + 1.0}",
        ),
        (
            low * cfg.courtyard_width >= 2 * cfg.facade_setback + 2 * (cfg.route_clearance + 6.0),
            "courtyard_width too small for the setback, the road and the lawn",
        ),
        (
            low * cfg.courtyard_depth
            >= 2 * cfg.facade_setback + 2 * (cfg.route_clearance + 6.0) + 6.0,
            "courtyard_depth too small for the setback, the portico, the road and the lawn",
        ),
        (
            low * min(cfg.main_height, cfg.wing_height) >= cfg.storey_height + 2.0,
            "buildings lower than one storey",
        ),
        (cfg.storey_height >= 3.5, "storey_height must be >= 3.5"),
        (low * cfg.window_spacing >= 2.5, "window_spacing must be >= 2.5"),
        (low * cfg.approach_length >= 10.0, "approach_length must be >= 10"),
        (low * cfg.wing_depth >= 6.0, "wing_depth must be >= 6"),
    ]
    for ok, message in rules:
        if not ok:
            raise ValueError(f"outdoor layout: {message}")
