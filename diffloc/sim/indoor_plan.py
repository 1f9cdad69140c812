"""Floor plan of the indoor world: room sizes, doors, region rectangles and the route."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from diffloc.sim.indoor_layout import _CORNER_MARGIN, _FRAME_WIDTH, IndoorLayoutConfig
from diffloc.sim.object_placement import _WallRun


@dataclass
class _Door:
    """An opening in a wall. ``axis`` "x": the wall runs along x at y = ``line``; "y": along y."""

    floor: int
    axis: str
    line: float
    center: float
    width: float
    thickness: float

    @property
    def cut(self) -> tuple[float, float]:
        """Span of the wall removed for the opening and its frame."""
        half = self.width / 2 + _FRAME_WIDTH
        return self.center - half, self.center + half


class _IndoorPlan:
    """Floor plan of the office building: numbers, doors, regions and the route."""

    def __init__(self, cfg: IndoorLayoutConfig, rng: np.random.Generator) -> None:
        self.cfg = cfg
        c = cfg
        self.H, self.slab = c.storey_height, c.slab_thickness
        self.te, self.tw = c.exterior_wall_thickness, c.wall_thickness
        self.n_steps = int(math.ceil(self.H / c.stair_max_rise - 1e-9))
        self.rise = self.H / self.n_steps
        self.tread = c.stair_tread
        hall_length = 2 * c.landing_length + (self.n_steps - 1) * self.tread
        south = rng.uniform(c.room_depth_min, c.room_depth_max)
        north = rng.uniform(c.room_depth_min, c.room_depth_max)
        self.ys = self.te + south + self.tw / 2
        self.yn = self.ys + self.tw + c.corridor_width
        self.Ly = self.yn + self.tw / 2 + north + self.te
        n = c.rooms_per_floor
        widths = rng.uniform(c.room_width_min, c.room_width_max, n)
        needed = 2 * self.te + hall_length + self.tw + c.office_min_width
        self.Lx = float(max(widths.sum(), needed))
        self.xh = self.Lx - self.te - hall_length - self.tw / 2
        # Stair hall: interior x [hx0, hall_x1]; the stair runs east along the north wall.
        self.hx0 = self.xh + self.tw / 2
        self.hall_x1 = self.Lx - self.te
        self.xs0 = self.hx0 + c.landing_length
        self.xs1 = self.xs0 + (self.n_steps - 1) * self.tread
        self.sb1 = self.Ly - self.te
        self.sb0 = self.sb1 - c.stair_width
        self.hy0 = self.sb0 - 0.1  # south edge of the stairwell void (balustrade included)
        self.y_st = (self.sb0 + self.sb1) / 2
        self.y_c = (self.ys + self.yn) / 2
        # Where the route turns into the stair hall (ground) and out of it (upper floor); the
        # openings there must clear the hall walls.
        opening_half = c.door_width / 2 + _FRAME_WIDTH + 0.05
        self.x_bottom = self.hx0 + max(c.route_clearance + 0.35, opening_half)
        self.x_top = self.xs1 + c.route_clearance + 0.4
        self.partitions = [self._partitions(widths)]
        self.partitions.append(self._partitions(rng.uniform(c.room_width_min, c.room_width_max, n)))
        self.doors: list[_Door] = []
        self.route_points: list[tuple[float, float, float]] = []
        self._make_doors_and_route(rng)

    def _partitions(self, widths: np.ndarray) -> np.ndarray:
        """Wall centre lines x (n + 1,) of the south rooms, the outer ones at 0 and Lx."""
        widths = widths * self.Lx / widths.sum()
        return np.concatenate([[0.0], np.cumsum(widths)])

    def room_rect(self, floor: int, i: int) -> np.ndarray:
        a = self.partitions[floor]
        n = self.cfg.rooms_per_floor
        x0 = self.te if i == 0 else a[i] + self.tw / 2
        x1 = self.Lx - self.te if i == n - 1 else a[i + 1] - self.tw / 2
        return np.array([x0, self.te, x1, self.ys - self.tw / 2])

    def corridor_rect(self) -> np.ndarray:
        return np.array([self.te, self.ys + self.tw / 2, self.Lx - self.te, self.yn - self.tw / 2])

    def office_rect(self) -> np.ndarray:
        return np.array([self.te, self.yn + self.tw / 2, self.xh - self.tw / 2, self.Ly - self.te])

    def hall_rect(self) -> np.ndarray:
        return np.array([self.hx0, self.yn + self.tw / 2, self.hall_x1, self.Ly - self.te])

    def _make_doors_and_route(self, rng: np.random.Generator) -> None:
        c, n = self.cfg, self.cfg.rooms_per_floor
        inset = c.route_clearance + _CORNER_MARGIN  # route corners this far from walls
        office = self.office_rect()
        for floor in (0, 1):
            z = floor * self.H
            rooms = [self.room_rect(floor, i) for i in range(n)]
            # Connecting doors between south rooms (at y = yc[i] in the wall east of room i).
            yc = [rng.uniform(self.te + inset, self.ys - self.tw / 2 - inset) for _ in range(n - 1)]
            for i in range(1, n - 1):  # avoid tiny jogs inside a room
                if abs(yc[i] - yc[i - 1]) < 1.0:
                    yc[i] = yc[i - 1]
            for i in range(n - 1):
                self.doors.append(
                    _Door(floor, "y", self.partitions[floor][i + 1], yc[i], c.door_width, self.tw)
                )
            # Open-office doors: the route uses the east one on floor 0, the west one on floor 1.
            ox0, oy0, ox1, oy1 = office
            y_o = oy0 + rng.uniform(0.4, 0.6) * (oy1 - oy0)
            xob = ox1 - rng.uniform(inset, inset + 0.8)
            xoa = min(ox0 + inset + 1.6 + rng.uniform(0.0, 1.5), xob - 3.0)
            self.doors.append(_Door(floor, "x", self.yn, xoa, c.door_width, self.tw))
            self.doors.append(_Door(floor, "x", self.yn, xob, c.door_width, self.tw))
            # Corridor doors of the south rooms; the chain of rooms starts in the west room.
            exit_x = self.x_bottom if floor == 0 else self.x_top
            xd = []
            for i, rect in enumerate(rooms):
                lo, hi = rect[0] + inset, rect[2] - inset
                if i == 0:  # west of the office door the route turns at
                    turn = xob if floor == 0 else xoa
                    hi = min(hi, rect[0] + 0.45 * (rect[2] - rect[0]), turn - 1.5)
                x = rng.uniform(lo, max(lo, hi))
                if i == n - 1 and abs(x - exit_x) < 1.2:
                    x = exit_x - 1.2 if exit_x - 1.2 >= lo else exit_x + 1.2
                xd.append(x)
                self.doors.append(_Door(floor, "x", self.ys, x, c.door_width, self.tw))
            # Opening between the corridor and the stair hall.
            self.doors.append(_Door(floor, "x", self.yn, exit_x, c.door_width, self.tw))
            chain = [(xd[0], y) for y in (self.y_c, yc[0])]
            for i in range(1, n - 1):
                xm = rng.uniform(rooms[i][0] + inset, rooms[i][2] - inset)
                chain += [(xm, yc[i - 1]), (xm, yc[i])]
            chain += [(xd[n - 1], yc[n - 2]), (xd[n - 1], self.y_c)]
            if floor == 0:
                points = [
                    (ox0 + inset, y_o),
                    (xob, y_o),
                    (xob, self.y_c),
                    *chain,
                    (self.x_bottom, self.y_c),
                    (self.x_bottom, self.y_st),
                    (self.xs0 - self.tread, self.y_st),
                ]
            else:
                points = [
                    (self.xs1, self.y_st),
                    (self.x_top, self.y_st),
                    (self.x_top, self.y_c),
                    *chain[::-1],
                    (xoa, self.y_c),
                    (xoa, y_o),
                    (ox1 - inset, y_o),
                ]
            self.route_points += [(x, y, z) for x, y in points]


def _wall_runs(
    plan: _IndoorPlan, rect: np.ndarray, floor: int, sides: str = "swne"
) -> list[_WallRun]:
    """Free wall stretches around a region rectangle (doors and their surroundings removed)."""
    x0, y0, x1, y1 = rect
    z = floor * plan.H
    specs = {
        "s": (np.array([x0, y0]), np.array([1.0, 0.0]), np.array([0.0, 1.0]), x1 - x0, "x", y0),
        "n": (np.array([x1, y1]), np.array([-1.0, 0.0]), np.array([0.0, -1.0]), x1 - x0, "x", y1),
        "w": (np.array([x0, y1]), np.array([0.0, -1.0]), np.array([1.0, 0.0]), y1 - y0, "y", x0),
        "e": (np.array([x1, y0]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), y1 - y0, "y", x1),
    }
    runs = []
    for side in sides:
        start, direction, normal, length, axis, coord = specs[side]
        blocked = []
        for door in plan.doors:
            if (
                door.floor == floor
                and door.axis == axis
                and abs(door.line - coord) <= door.thickness / 2 + 1e-6
            ):
                lo, hi = door.cut
                along = start[0] if axis == "x" else start[1]
                sign = direction[0] if axis == "x" else direction[1]
                s0, s1 = sorted(((lo - along) * sign, (hi - along) * sign))
                blocked.append((s0 - 0.25, s1 + 0.25))
        edges = [0.0]
        for lo, hi in sorted(blocked):
            edges += [lo, hi]
        edges.append(length)
        for lo, hi in zip(edges[0::2], edges[1::2], strict=True):
            lo, hi = max(lo, 0.0), min(hi, length)
            if hi - lo > 0.3:
                runs.append(_WallRun(start, direction, normal, lo, hi, z))
    return runs
