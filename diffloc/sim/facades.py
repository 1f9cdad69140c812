"""Building faces of the outdoor world: windows, doors and ornaments, and gable roofs."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from diffloc.sim.primitives import Frame, MeshBuilder, wall_panel, window_unit


def _facade_frame(start: np.ndarray, direction: np.ndarray) -> Frame:
    """Frame on a facade: local x along ``direction``, local y out of the facade (to its left)."""
    normal = np.array([-direction[1], direction[0]])
    return Frame(np.array([start[0], start[1], 0.0]), math.atan2(-normal[0], normal[1]))


def _facade(
    b: MeshBuilder,
    frame: Frame,
    length: float,
    height: float,
    storey: float,
    spacing: float,
    trim: str,
    opening: Any,
) -> None:
    """Windows, doors, pilasters, string courses and a cornice on a building face.

    Args:
        b: receives the solids.
        frame: facade frame (see :func:`_facade_frame`) at the start of the face.
        length: face length along local x.
        height: eaves height.
        storey: storey height (window rows).
        spacing: distance between window axes.
        trim: stone material of the ornaments.
        opening: ``opening(x_local, storey_index) -> "window" | "door" | "none"``.
    """
    columns = max(1, int((length - 1.5) // spacing))
    margin = (length - columns * spacing) / 2
    axes = margin + (np.arange(columns) + 0.5) * spacing
    floors = max(1, int((height - 0.6 - 1.2 - 2.4) // storey) + 1)
    for f in range(floors):
        z0 = f * storey + 1.2
        z1 = z0 + min(2.4, storey - 1.6)
        for x in axes:
            kind = opening(float(x), f)
            at = Frame(frame.point((float(x), 0.0, 0.0)), frame.yaw)
            if kind == "door":
                wall_panel(
                    b, at, 1.8, (0.0, 3.0), "door_facade", 0, depth=0.08, trim=trim, trim_width=0.2
                )
                at.box(b, (-1.3, 0.0, 3.3), (1.3, 0.45, 3.55), trim, 0)
            elif kind == "window":
                window_unit(b, at, 1.5, (z0, z1), "window_facade", trim, 0, pediment=f == 1)
    for k in range(0, columns + 1, 3):
        x = margin + k * spacing
        frame.box(b, (x - 0.35, 0.0, 0.0), (x + 0.35, 0.25, height - 0.6), trim, 0)
    for f in range(1, floors):
        frame.box(b, (0.0, 0.0, f * storey - 0.15), (length, 0.15, f * storey + 0.15), trim, 0)
    frame.box(b, (0.0, 0.0, height - 0.6), (length, 0.55, height), trim, 0)


def _gable_roof(b: MeshBuilder, rect: np.ndarray, z: float, rise: float, material: str) -> None:
    """A gable roof (triangular prism) over a rectangle (x0, y0, x1, y1), ridge along its length."""
    x0, y0, x1, y1 = rect
    along_x = (x1 - x0) >= (y1 - y0)
    w = np.array([1.0, 0.0, 0.0]) if along_x else np.array([0.0, 1.0, 0.0])
    up = np.array([0.0, 0.0, 1.0])
    a = np.cross(up, w)
    span = (y1 - y0) if along_x else (x1 - x0)
    length = (x1 - x0) if along_x else (y1 - y0)
    origin = np.array([x0, (y0 + y1) / 2, z]) if along_x else np.array([(x0 + x1) / 2, y0, z])
    eave = 0.4
    polygon = np.array([[-span / 2 - eave, 0.0], [span / 2 + eave, 0.0], [0.0, rise]])
    b.add_prism(polygon, origin, np.stack([a, up, w]), length, material, 0)
