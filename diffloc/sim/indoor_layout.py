"""Layout config of the indoor world (a two-storey office building) and its validation."""

from __future__ import annotations

import math
from dataclasses import dataclass

from diffloc.sim.layout_checks import _check_config

__all__ = ["IndoorLayoutConfig"]

# Width of door frame bars (metres).
_FRAME_WIDTH = 0.07
# Minimum distance of in-room route corners from walls (metres, beyond the clearance).
_CORNER_MARGIN = 0.5


@dataclass
class IndoorLayoutConfig:
    """Two-storey office building (metres unless stated).

    Each floor has ``rooms_per_floor`` rooms in a row south of a corridor (adjacent rooms joined
    by doors), an open-plan office north of the corridor and a stair hall with a straight stair
    at the east end.

    Attributes:
        storey_height: floor-to-floor height.
        slab_thickness: floor slab thickness (the clear room height is the difference).
        rooms_per_floor: enclosed rooms south of the corridor on each floor (>= 2).
        room_width_min: smallest room width (centre to centre of its walls, along x).
        room_width_max: largest room width.
        room_depth_min: smallest depth of the south room row and of the north office row.
        room_depth_max: largest such depth.
        office_min_width: smallest clear width of the open-plan office.
        corridor_width: clear corridor width.
        wall_thickness: interior wall thickness.
        exterior_wall_thickness: exterior wall thickness.
        door_width: clear door width (must exceed twice the route clearance).
        door_height: clear door height (>= 2.2 m head room).
        stair_width: clear stair width between wall and balustrade.
        stair_tread: step depth.
        stair_max_rise: largest step height (the stair angle is atan(rise / tread)).
        landing_length: length of the landings before and after the stair.
        furniture_per_room: furniture items attempted per room (the open office gets twice as many).
        posters_per_room: posters / boards attempted per room.
        windows: put window panels on the exterior walls.
        route_clearance: free space kept on each side of the route.
        texture_size: texture side length in texels.
        n_changed_objects: movable objects moved, removed or added in the changed scene.
    """

    storey_height: float = 3.0
    slab_thickness: float = 0.2
    rooms_per_floor: int = 3
    room_width_min: float = 6.5
    room_width_max: float = 8.5
    room_depth_min: float = 5.5
    room_depth_max: float = 6.5
    office_min_width: float = 9.0
    corridor_width: float = 2.6
    wall_thickness: float = 0.15
    exterior_wall_thickness: float = 0.3
    door_width: float = 1.6
    door_height: float = 2.3
    stair_width: float = 1.8
    stair_tread: float = 0.3
    stair_max_rise: float = 0.18
    landing_length: float = 2.0
    furniture_per_room: int = 6
    posters_per_room: int = 2
    windows: bool = True
    route_clearance: float = 0.6
    texture_size: int = 256
    n_changed_objects: int = 8


def _validate_indoor(cfg: IndoorLayoutConfig) -> None:
    positive = (
        "storey_height",
        "slab_thickness",
        "room_width_min",
        "room_width_max",
        "room_depth_min",
        "room_depth_max",
        "office_min_width",
        "corridor_width",
        "wall_thickness",
        "exterior_wall_thickness",
        "door_width",
        "door_height",
        "stair_width",
        "stair_tread",
        "stair_max_rise",
        "landing_length",
        "route_clearance",
    )
    counts = ("rooms_per_floor", "furniture_per_room", "posters_per_room", "n_changed_objects")
    _check_config(cfg, positive, counts)
    need = 2 * cfg.route_clearance + 0.1
    rules = [
        (cfg.rooms_per_floor >= 2, "rooms_per_floor must be >= 2"),
        (cfg.room_width_min <= cfg.room_width_max, "room_width_min must be <= room_width_max"),
        (cfg.room_depth_min <= cfg.room_depth_max, "room_depth_min must be <= room_depth_max"),
        (cfg.door_width >= need, f"door_width must be >= 2 * route_clearance + 0.1 = {need:.2f}"),
        (cfg.corridor_width >= need, f"corridor_width must be >= {need:.2f}"),
        (cfg.stair_width >= need, f"stair_width must be >= {need:.2f}"),
        (cfg.door_height >= 2.2, "door_height must be >= 2.2 (head room)"),
        (
            cfg.storey_height - cfg.slab_thickness >= cfg.door_height + 0.3,
            "storey_height - slab_thickness must exceed door_height by >= 0.3",
        ),
        (
            math.degrees(math.atan2(cfg.stair_max_rise, cfg.stair_tread)) <= 40.0,
            "stairs steeper than 40 degrees (stair_max_rise / stair_tread)",
        ),
        (
            cfg.landing_length
            >= cfg.route_clearance + 0.4 + cfg.door_width / 2 + _FRAME_WIDTH + 0.05,
            "landing_length must be >= route_clearance + door_width / 2 + 0.52",
        ),
        (
            cfg.landing_length
            >= cfg.stair_tread + 0.3 + max(cfg.route_clearance + 0.35, cfg.door_width / 2 + 0.12),
            "landing_length too short for the turn onto the stairs",
        ),
        (
            2 * (cfg.route_clearance + _CORNER_MARGIN) + 0.5
            <= cfg.room_width_min - cfg.wall_thickness,
            "room_width_min too small for the route clearance",
        ),
        (
            2 * (cfg.route_clearance + _CORNER_MARGIN) + 0.5 <= cfg.room_depth_min,
            "room_depth_min too small for the route clearance",
        ),
        (cfg.office_min_width >= 6.0 + 2 * cfg.route_clearance, "office_min_width too small"),
    ]
    for ok, message in rules:
        if not ok:
            raise ValueError(f"indoor layout: {message}")
