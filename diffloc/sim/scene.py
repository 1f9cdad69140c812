"""Procedural worlds: a two-storey office building (indoor) and a palace courtyard (outdoor).

:func:`generate_world` turns a kind, an integer seed and a layout config into a :class:`World`:
the textured mesh as mapped, the same scene with some movable objects moved, removed or added,
a walking / driving route through free space, terrestrial scanner stations and the world bounds.

Geometry rules (relied upon by free-space checks and the tests):

- every part is a closed solid with outward, counter-clockwise triangles (see
  :mod:`diffloc.sim.primitives`); object id 0 is the building structure, ``k > 0`` is movable
  object ``k`` (furniture, clutter);
- the route keeps at least ``route_clearance`` metres horizontally from every solid at heights up
  to 2 m above it (on stairs the steps ahead are the floor and are excluded below 0.5 m), and at
  least 2.2 m of head room; furniture and clutter are placed (in both scene states) outside a
  corridor around the route that is wider than that;
- the route's z is the floor under it (the nosing line on stairs).

Everything is drawn from ``np.random.default_rng(seed)``, so equal seeds give byte-identical
arrays.

Frames and units: metres, world z up, the ground floor / ground at z = 0.

Modules: :mod:`~diffloc.sim.world` (the :class:`World` data types), the builders
:mod:`~diffloc.sim.indoor` and :mod:`~diffloc.sim.outdoor` with their layout configs
(:mod:`~diffloc.sim.indoor_layout`, :mod:`~diffloc.sim.outdoor_layout`) and plans
(:mod:`~diffloc.sim.indoor_plan`, :mod:`~diffloc.sim.outdoor_plan`), and what both use:
:mod:`~diffloc.sim.object_placement` (movable objects), :mod:`~diffloc.sim.route`,
:mod:`~diffloc.sim.facades` and :mod:`~diffloc.sim.primitives`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields

import numpy as np

from diffloc.sim.indoor import _indoor_world
from diffloc.sim.indoor_layout import IndoorLayoutConfig
from diffloc.sim.outdoor import _outdoor_world
from diffloc.sim.outdoor_layout import OutdoorLayoutConfig
from diffloc.sim.world import WORLD_KINDS, World

__all__ = ["generate_world"]


def generate_world(
    kind: str, seed: int, layout: IndoorLayoutConfig | OutdoorLayoutConfig | None = None
) -> World:
    """Generate a procedural world.

    Args:
        kind: ``"indoor"`` (two-storey office) or ``"outdoor"`` (palace courtyard).
        seed: non-negative integer; equal seeds give byte-identical worlds.
        layout: the matching layout config (or a mapping of its fields, such as an OmegaConf
            ``DictConfig``); ``None`` uses the defaults.

    Returns:
        The :class:`World`.

    Raises:
        ValueError: unknown kind, a seed that is not a non-negative integer, a layout of the wrong
            type or with invalid values.

    Usage (a few seconds: no doctest)::

        world = generate_world("indoor", 0)
        world.route.shape[1]  # 3
    """
    if kind not in WORLD_KINDS:
        raise ValueError(f"unknown world kind {kind!r}; valid kinds are {list(WORLD_KINDS)}")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    expected = IndoorLayoutConfig if kind == "indoor" else OutdoorLayoutConfig
    if layout is None:
        layout = expected()
    elif isinstance(layout, Mapping):  # e.g. an OmegaConf DictConfig of the layout group
        known = {f.name for f in fields(expected)}
        unknown = sorted(set(layout) - known)
        if unknown:
            raise ValueError(
                f"unknown {kind} layout keys {unknown}; valid keys are {sorted(known)}"
            )
        layout = expected(**{str(k): v for k, v in layout.items()})
    if not isinstance(layout, expected):
        raise ValueError(f"a {kind} world needs a {expected.__name__}, got {type(layout).__name__}")
    if kind == "indoor":
        return _indoor_world(int(seed), layout)
    return _outdoor_world(int(seed), layout)
