"""The indoor world: a two-storey office building, built section by section.

:func:`_indoor_world` draws the plan (:mod:`~diffloc.sim.indoor_plan`), then the regions and
their finishes, slabs, walls, stairs, fixed fittings (windows, skirting, lights, pillars), the
movable furniture, posters and boards, and the changed scene's moves, removals and additions.
Every section draws from the one generator in this order, so equal seeds give byte-identical
worlds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from diffloc.sim.indoor_layout import _FRAME_WIDTH, IndoorLayoutConfig, _validate_indoor
from diffloc.sim.indoor_plan import _IndoorPlan, _wall_runs
from diffloc.sim.object_placement import (
    _PANELS,
    _aabb,
    _change_items,
    _Item,
    _place_free,
    _place_on_wall,
    _Placer,
    _scene_meshes,
)
from diffloc.sim.primitives import PROPS, Frame, MeshBuilder, wall_panel
from diffloc.sim.route import _simplify_route, _tls_stations
from diffloc.sim.textures import POSTERS, make_materials
from diffloc.sim.world import Region, World, _mesh_bounds

__all__ = ["INDOOR_MATERIALS"]

INDOOR_MATERIALS = (
    "plaster_white",
    "plaster_warm",
    "plaster_blue",
    "plaster_green",
    "brick_wall",
    "concrete",
    "floor_tiles",
    "floor_checker",
    "carpet_grey",
    "carpet_red",
    "wood_floor",
    "ceiling_tiles",
    "light_panel",
    "wood",
    "wood_dark",
    "metal",
    "metal_dark",
    "paint_red",
    "fabric_blue",
    "fabric_green",
    "cardboard",
    "books",
    "door_wood",
    "window_glass",
    "whiteboard",
    "notice_board",
    "foliage",
    *POSTERS,
)

# Extra margin beyond the route clearance kept free of furniture (metres).
_INDOOR_KEEPOUT_MARGIN = 0.3
# How far door frame bars stand out of the wall (metres).
_FRAME_PROUD = 0.03
# Scanner height above the floor (metres).
_TLS_HEIGHT_INDOOR = 1.3

_ROOM_TYPES = {
    "office": ("desk", "desk", "bookcase", "desk", "cabinet", "plant", "copier", "bookcase"),
    "meeting": ("meeting_table", "bookcase", "plant", "cabinet", "sofa", "plant"),
    "storage": ("locker", "bookcase", "locker", "boxes", "boxes", "cabinet", "bookcase", "boxes"),
    "lounge": ("sofa", "plant", "vending_machine", "sofa", "bookcase", "plant"),
}
_OPEN_OFFICE = (
    "desk",
    "desk",
    "desk",
    "desk",
    "bookcase",
    "plant",
    "desk",
    "cabinet",
    "locker",
    "desk",
    "copier",
    "plant",
)
_FLOOR_FINISHES = ("carpet_grey", "carpet_red", "wood_floor", "floor_tiles")
_WALL_FINISHES = (
    "plaster_white",
    "plaster_warm",
    "plaster_blue",
    "plaster_green",
    "brick_wall",
    "concrete",
)


def _indoor_world(seed: int, cfg: IndoorLayoutConfig) -> World:
    """The office building of ``seed`` (see :func:`~diffloc.sim.scene.generate_world`)."""
    _validate_indoor(cfg)
    rng = np.random.default_rng(seed)
    names, textures = make_materials(rng, int(cfg.texture_size), INDOOR_MATERIALS)
    plan = _IndoorPlan(cfg, rng)
    route = _simplify_route(plan.route_points)
    b = MeshBuilder(names)
    rooms = _draw_rooms(plan, rng)
    _build_slabs(b, plan, rooms)
    for floor in (0, 1):
        _build_interior_walls(b, plan, rooms, floor, rng)
        _build_exterior_walls(b, plan, rooms, floor)
    _build_stairs(b, plan)
    placer = _indoor_placer(plan, route)
    for floor, kind, rect in rooms.rects:
        _build_fittings(b, plan, floor, kind, rect, placer)
    _build_pillars(b, plan, placer, rng)
    posters = _PosterDeck(rng)
    items = _furnish(plan, rooms, placer, posters, rng)
    changed_items, changes = _change_furniture(plan, rooms, placer, items, posters, rng)
    mesh, changed_mesh = _scene_meshes(b, textures, items, changed_items)
    return World(
        kind="indoor",
        seed=seed,
        mesh=mesh,
        changed_mesh=changed_mesh,
        route=route,
        route_clearance=float(cfg.route_clearance),
        tls_stations=_tls_stations(route, 8.0, _TLS_HEIGHT_INDOOR),
        bounds=_mesh_bounds(mesh, changed_mesh),
        regions=rooms.regions,
        floor_heights=[0.0, float(plan.H)],
        num_objects=len(items),
        num_changes=changes,
    )


# --------------------------------------------------------------------------- regions


@dataclass
class _Rooms:
    """The regions of the building and their finishes, in region order (per floor: the south
    rooms, the open office, the corridor and the stair hall).

    Attributes:
        rects: ``(floor, kind, (x0, y0, x1, y1))`` per region; ``kind`` is ``"room:<type>"``,
            ``"room:open_office"``, ``"corridor"`` or ``"stair_hall"``.
        regions: the :class:`Region` of each.
        floor_finish: floor material of each.
        wall_finish: wall material of each.
    """

    rects: list[tuple[int, str, np.ndarray]]
    regions: list[Region]
    floor_finish: list[str]
    wall_finish: list[str]

    def index(self, floor: int, kind: str, i: int = 0) -> int:
        """Position of the ``i``-th region of a kind (``"room"``, ...) on a floor."""
        matches = [k for k, r in enumerate(self.regions) if r.floor == floor and r.kind == kind]
        return matches[i]


def _draw_rooms(plan: _IndoorPlan, rng: np.random.Generator) -> _Rooms:
    """Room types (a random order per floor), regions and random floor and wall finishes."""
    H, slab, n = plan.H, plan.slab, plan.cfg.rooms_per_floor
    rects: list[tuple[int, str, np.ndarray]] = []
    for floor in (0, 1):
        types = rng.permutation(list(_ROOM_TYPES))
        for i in range(n):
            rects.append((floor, f"room:{types[i % len(types)]}", plan.room_rect(floor, i)))
        rects.append((floor, "room:open_office", plan.office_rect()))
        rects.append((floor, "corridor", plan.corridor_rect()))
        rects.append((floor, "stair_hall", plan.hall_rect()))
    regions: list[Region] = []
    floor_finish, wall_finish = [], []
    for floor, kind, rect in rects:
        z = floor * H
        kind_name = kind.split(":")[0]
        index = sum(r.floor == floor and r.kind == kind_name for r in regions)
        top = z + H - slab if kind != "stair_hall" else 2 * H - slab
        regions.append(
            Region(
                f"f{floor}_{kind_name}{index}",
                kind_name,
                floor,
                np.array([rect[0], rect[1], z]),
                np.array([rect[2], rect[3], top]),
            )
        )
        if kind == "corridor":
            floor_finish.append("floor_tiles")
        elif kind == "stair_hall":
            floor_finish.append("floor_checker")
        elif kind == "room:open_office":
            floor_finish.append("carpet_grey")
        else:
            floor_finish.append(str(rng.choice(_FLOOR_FINISHES)))
        wall_finish.append(
            str(rng.choice(_WALL_FINISHES[:4] if kind == "corridor" else _WALL_FINISHES))
        )
    return _Rooms(rects, regions, floor_finish, wall_finish)


# --------------------------------------------------------------------------- structure


def _build_slabs(b: MeshBuilder, plan: _IndoorPlan, rooms: _Rooms) -> None:
    """Slabs: lower layer (ceiling below), per-region floor finish on top, and the roof."""
    H, slab, te = plan.H, plan.slab, plan.te
    interior = np.array([te, te, plan.Lx - te, plan.Ly - te])
    b.add_box(
        [interior[0], interior[1], -slab], [interior[2], interior[3], -slab / 2], "concrete", 0
    )
    lower_z = (H - slab, H - slab / 2)
    for x0, y0, x1, y1 in (
        (te, te, plan.Lx - te, plan.hy0),
        (te, plan.hy0, plan.hx0, plan.Ly - te),
        (plan.xs1, plan.hy0, plan.Lx - te, plan.Ly - te),
    ):
        b.add_box([x0, y0, lower_z[0]], [x1, y1, lower_z[1]], "ceiling_tiles", 0)
    b.add_box(
        [interior[0], interior[1], 2 * H - slab],
        [interior[2], interior[3], 2 * H],
        "ceiling_tiles",
        0,
    )
    for k, (floor, kind, rect) in enumerate(rooms.rects):
        z = floor * H
        pieces = [rect]
        if kind == "stair_hall" and floor == 1:
            pieces = [
                np.array([rect[0], rect[1], rect[2], plan.hy0]),
                np.array([plan.xs1, plan.hy0, rect[2], rect[3]]),
            ]
        for x0, y0, x1, y1 in pieces:
            b.add_box([x0, y0, z - slab / 2], [x1, y1, z], rooms.floor_finish[k], 0)


def _axis_box(
    axis: str,
    line: float,
    thickness: float,
    along: tuple[float, float],
    z: tuple[float, float],
    proud: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Corners (lo, hi) of a wall-aligned box: ``along`` the wall, ``thickness`` across it."""
    half = thickness / 2 + proud
    if axis == "x":
        return np.array([along[0], line - half, z[0]]), np.array([along[1], line + half, z[1]])
    return np.array([line - half, along[0], z[0]]), np.array([line + half, along[1], z[1]])


def _build_wall(
    b: MeshBuilder,
    plan: _IndoorPlan,
    floor: int,
    axis: str,
    line: float,
    span: tuple[float, float],
    material: str,
) -> None:
    """An interior wall of a floor with framed door openings (lintels, jambs, head trims,
    thresholds): the wall runs along ``axis`` at ``line`` over ``span``."""
    floor_z, slab, thickness = floor * plan.H, plan.slab, plan.tw
    z = (floor_z - slab / 2, floor_z + plan.H - slab)
    doors = [
        d for d in plan.doors if d.floor == floor and d.axis == axis and abs(d.line - line) < 1e-9
    ]
    cuts = sorted(door.cut for door in doors)
    edges = [span[0]] + [c for cut in cuts for c in cut] + [span[1]]
    for lo, hi in zip(edges[0::2], edges[1::2], strict=True):
        if hi - lo > 1e-6:
            b.add_box(*_axis_box(axis, line, thickness, (lo, hi), z), material, 0)
    head = floor_z + plan.cfg.door_height
    top = head + _FRAME_WIDTH
    for lo, hi in cuts:
        b.add_box(*_axis_box(axis, line, thickness, (lo, hi), (top, z[1])), material, 0)
        b.add_box(
            *_axis_box(axis, line, thickness, (lo, hi), (floor_z - slab / 2, floor_z)),
            "wood_dark",
            0,
        )
        for jamb in ((lo, lo + _FRAME_WIDTH), (hi - _FRAME_WIDTH, hi)):
            b.add_box(
                *_axis_box(axis, line, thickness, jamb, (floor_z, head), _FRAME_PROUD), "wood", 0
            )
        b.add_box(*_axis_box(axis, line, thickness, (lo, hi), (head, top), _FRAME_PROUD), "wood", 0)


def _build_interior_walls(
    b: MeshBuilder, plan: _IndoorPlan, rooms: _Rooms, floor: int, rng: np.random.Generator
) -> None:
    """The corridor walls, the partitions between the south rooms (each showing the finish of
    a random one of its two rooms) and the wall between the open office and the stair hall."""
    te, tw, n = plan.te, plan.tw, plan.cfg.rooms_per_floor
    room_ids = [rooms.index(floor, "room", i) for i in range(n)]
    corridor = rooms.wall_finish[rooms.index(floor, "corridor")]
    _build_wall(b, plan, floor, "x", plan.ys, (te, plan.Lx - te), corridor)
    _build_wall(b, plan, floor, "x", plan.yn, (te, plan.Lx - te), corridor)
    for i in range(1, n):
        finish = rooms.wall_finish[room_ids[i - 1 + int(rng.integers(2))]]
        _build_wall(b, plan, floor, "y", plan.partitions[floor][i], (te, plan.ys - tw / 2), finish)
    office = rooms.wall_finish[rooms.index(floor, "room", n)]
    _build_wall(b, plan, floor, "y", plan.xh, (plan.yn + tw / 2, plan.Ly - te), office)


def _build_exterior_walls(b: MeshBuilder, plan: _IndoorPlan, rooms: _Rooms, floor: int) -> None:
    """Exterior walls of a floor, one segment per region so each shows its own finish (the
    stair hall's in concrete)."""
    H, slab, te, n = plan.H, plan.slab, plan.te, plan.cfg.rooms_per_floor
    room_ids = [rooms.index(floor, "room", i) for i in range(n)]
    corridor_id = rooms.index(floor, "corridor")
    office_id, hall_id = rooms.index(floor, "room", n), rooms.index(floor, "stair_hall")
    ext_z = (-slab, H - slab) if floor == 0 else (H - slab, 2 * H)
    a = plan.partitions[floor]
    for i in range(n):
        lo, hi = _axis_box("x", te / 2, te, (a[i], a[i + 1]), ext_z)
        b.add_box(lo, hi, rooms.wall_finish[room_ids[i]], 0)
    for (x0, x1), rid in (((0.0, plan.xh), office_id), ((plan.xh, plan.Lx), hall_id)):
        lo, hi = _axis_box("x", plan.Ly - te / 2, te, (x0, x1), ext_z)
        b.add_box(lo, hi, rooms.wall_finish[rid] if rid != hall_id else "concrete", 0)
    for x_line in (te / 2, plan.Lx - te / 2):
        east = x_line > plan.Lx / 2
        spans = (
            ((te, plan.ys), room_ids[-1] if east else room_ids[0]),
            ((plan.ys, plan.yn), corridor_id),
            ((plan.yn, plan.Ly - te), hall_id if east else office_id),
        )
        for (y0, y1), rid in spans:
            lo, hi = _axis_box("y", x_line, te, (y0, y1), ext_z)
            b.add_box(lo, hi, rooms.wall_finish[rid] if rid != hall_id else "concrete", 0)


def _build_stairs(b: MeshBuilder, plan: _IndoorPlan) -> None:
    """Solid steps, a balustrade on the open side and one around the void upstairs."""
    for k in range(1, plan.n_steps):
        x0 = plan.xs0 + (k - 1) * plan.tread
        b.add_box([x0, plan.sb0, 0.0], [x0 + plan.tread, plan.sb1, k * plan.rise], "concrete", 0)
        b.add_box(
            [x0, plan.sb0 - 0.1, 0.0],
            [x0 + plan.tread, plan.sb0, k * plan.rise + 0.9],
            "wood_dark",
            0,
        )
    H = plan.H
    b.add_box([plan.hx0, plan.hy0 - 0.1, H], [plan.xs1, plan.hy0, H + 1.0], "wood_dark", 0)


# --------------------------------------------------------------------------- fittings


def _indoor_placer(plan: _IndoorPlan, route: np.ndarray) -> _Placer:
    """The placement state, with doorways, the stairs and the stairwell void kept free."""
    te = plan.te
    placer = _Placer(route, plan.cfg.route_clearance + _INDOOR_KEEPOUT_MARGIN, [0.0, plan.H])
    for door in plan.doors:
        lo, hi = door.cut
        depth = door.thickness / 2 + 1.0
        box = (lo - 0.2, door.line - depth, hi + 0.2, door.line + depth)
        if door.axis == "y":
            box = (door.line - depth, lo - 0.2, door.line + depth, hi + 0.2)
        placer.occupy(door.floor, np.array(box))
    placer.occupy(0, np.array([plan.xs0 - plan.tread, plan.hy0 - 0.2, plan.Lx - te, plan.Ly - te]))
    placer.occupy(1, np.array([plan.hx0, plan.hy0 - 0.2, plan.xs1, plan.Ly - te]))
    return placer


def _build_fittings(
    b: MeshBuilder, plan: _IndoorPlan, floor: int, kind: str, rect: np.ndarray, placer: _Placer
) -> None:
    """The fixed fittings of one region: windows with radiators, skirting, ceiling lights."""
    if plan.cfg.windows:
        _build_windows(b, plan, floor, kind, rect, placer)
    if kind != "stair_hall":
        _build_skirting(b, plan, floor, rect)
    _build_ceiling_lights(b, plan, floor, kind, rect)


def _build_windows(
    b: MeshBuilder, plan: _IndoorPlan, floor: int, kind: str, rect: np.ndarray, placer: _Placer
) -> None:
    """Window panels with a sill and a radiator below, evenly along the exterior walls."""
    te, z = plan.te, floor * plan.H
    ext_sides = {
        "s": rect[1] <= te + 1e-9,
        "n": rect[3] >= plan.Ly - te - 1e-9,
        "w": rect[0] <= te + 1e-9,
        "e": rect[2] >= plan.Lx - te - 1e-9,
    }
    sides = "".join(s for s, exterior in ext_sides.items() if exterior)
    if kind == "stair_hall":
        sides = sides.replace("n", "")
    for run in _wall_runs(plan, rect, floor, sides):
        count = int((run.hi - run.lo) // 2.6)
        for j in range(count):
            s = run.lo + (j + 0.5) * (run.hi - run.lo) / count
            xy = run.start + s * run.direction
            frame = Frame(np.array([xy[0], xy[1], z]), math.atan2(-run.normal[0], run.normal[1]))
            wall_panel(
                b,
                frame,
                1.3,
                (0.95, 2.2),
                "window_glass",
                0,
                depth=0.04,
                trim="wood",
                trim_width=0.06,
            )
            frame.box(b, (-0.75, 0.0, 0.85), (0.75, 0.14, 0.89), "wood", 0)
            frame.box(b, (-0.5, 0.04, 0.15), (0.5, 0.12, 0.7), "metal", 0)
            placer.occupy(floor, _aabb((-0.8, 0.0, 0.8, 0.16), frame.origin, frame.yaw))


def _build_skirting(b: MeshBuilder, plan: _IndoorPlan, floor: int, rect: np.ndarray) -> None:
    """Skirting boards along the free wall stretches of a region."""
    z = floor * plan.H
    for run in _wall_runs(plan, rect, floor):
        start = run.start + run.lo * run.direction
        frame = Frame(np.array([start[0], start[1], z]), math.atan2(-run.normal[0], run.normal[1]))
        frame.box(b, (0.0, 0.0, 0.0), (run.hi - run.lo, 0.015, 0.08), "wood_dark", 0)


def _build_ceiling_lights(
    b: MeshBuilder, plan: _IndoorPlan, floor: int, kind: str, rect: np.ndarray
) -> None:
    """A grid of light panels about 2.4 m apart under the ceiling of a region (the stair
    hall's under the roof, outside the stairwell void)."""
    H, slab = plan.H, plan.slab
    ceiling = floor * H + H - slab
    x0, y0, x1, y1 = rect
    if kind == "stair_hall" and floor == 0:
        y1 = plan.hy0
    nx, ny = max(1, int((x1 - x0) // 2.4)), max(1, int((y1 - y0) // 2.4))
    gx = x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx
    gy = y0 + (np.arange(ny) + 0.5) * (y1 - y0) / ny
    if kind == "stair_hall" and floor == 1:
        ceiling = 2 * H - slab
    centers = np.stack(np.meshgrid(gx, gy), -1).reshape(-1, 2)
    centers = np.concatenate([centers, np.full((len(centers), 1), ceiling - 0.02)], axis=1)
    b.add_boxes(
        centers, np.tile([0.3, 0.3, 0.02], (len(centers), 1)), "light_panel", 0, repeat_m=0.0
    )


def _build_pillars(
    b: MeshBuilder, plan: _IndoorPlan, placer: _Placer, rng: np.random.Generator
) -> None:
    """Up to three structural pillars in each open office, wherever the sampler finds room."""
    H, slab = plan.H, plan.slab
    for floor in (0, 1):
        office = plan.office_rect()
        for _ in range(3):
            pillar = _place_free(
                placer, rng, office, floor * H, "pillar", 0, floor, -1, attempts=20
            )
            if pillar is not None:
                x0, y0, x1, y1 = pillar.aabb
                b.add_box([x0, y0, floor * H], [x1, y1, floor * H + H - slab], "concrete", 0)


# --------------------------------------------------------------------------- movable objects


class _PosterDeck:
    """Poster variants: the posters in a random order, each with a random one of four sizes.

    Args:
        rng: draws the order now and a size per poster.
    """

    def __init__(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self._order = [int(v) for v in rng.permutation(len(POSTERS))]
        self._drawn = 0

    def draw(self) -> int:
        """The variant of the next poster (poster ``variant % len(POSTERS)``)."""
        poster = self._order[self._drawn % len(self._order)]
        self._drawn += 1
        return poster + len(POSTERS) * int(self._rng.integers(4))


def _wanted(cfg: IndoorLayoutConfig, kind: str) -> tuple[list[str], int]:
    """The props tried in a region, in order, and how many posters / boards go on its walls."""
    if kind == "corridor":
        return ["extinguisher", "notice_board", "extinguisher"], cfg.posters_per_room + 1
    if kind == "stair_hall":
        return ["vending_machine", "sofa", "plant"], 1
    catalogue = _OPEN_OFFICE if kind == "room:open_office" else _ROOM_TYPES[kind.split(":")[1]]
    count = cfg.furniture_per_room * (2 if kind == "room:open_office" else 1)
    wanted = [catalogue[j % len(catalogue)] for j in range(count)]
    if kind in ("room:meeting", "room:office"):
        wanted.insert(1, "whiteboard")
    return wanted, cfg.posters_per_room


def _furnish(
    plan: _IndoorPlan,
    rooms: _Rooms,
    placer: _Placer,
    posters: _PosterDeck,
    rng: np.random.Generator,
) -> list[_Item]:
    """Movable objects of the mapped scene: furniture, posters and boards (none upstairs in
    the stair hall)."""
    items: list[_Item] = []
    for k, (floor, kind, rect) in enumerate(rooms.rects):
        z = floor * plan.H
        sides = "swe" if kind == "stair_hall" else "swne"
        if kind == "stair_hall" and floor == 1:
            continue
        runs = _wall_runs(plan, rect, floor, sides)
        wanted, panels = _wanted(plan.cfg, kind)
        for prop in wanted:
            variant = int(rng.integers(12))
            if prop in _PANELS or PROPS[prop].against_wall:
                item = _place_on_wall(placer, rng, runs, prop, variant, floor, k)
            else:
                jitter = 0.4 if prop in ("plant", "boxes") else 0.0
                item = _place_free(placer, rng, rect, z, prop, variant, floor, k, jitter=jitter)
            if item is not None:
                items.append(item)
        for _ in range(panels):
            item = _place_on_wall(placer, rng, runs, "poster", posters.draw(), floor, k)
            if item is not None:
                items.append(item)
    return items


def _change_furniture(
    plan: _IndoorPlan,
    rooms: _Rooms,
    placer: _Placer,
    items: list[_Item],
    posters: _PosterDeck,
    rng: np.random.Generator,
) -> tuple[list[_Item], int]:
    """The changed scene's objects: some moved within their region, removed, or added (boxes,
    plants, posters and cabinets in rooms); and the number of changes."""

    def relocate(item: _Item, placer: _Placer) -> _Item | None:
        floor, kind, rect = rooms.rects[item.region]
        if item.prop == "poster" or item.prop in _PANELS or PROPS[item.prop].against_wall:
            sides = "swe" if kind == "stair_hall" else "swne"
            return _place_on_wall(
                placer,
                rng,
                _wall_runs(plan, rect, floor, sides),
                item.prop,
                item.variant,
                floor,
                item.region,
            )
        return _place_free(
            placer,
            rng,
            rect,
            floor * plan.H,
            item.prop,
            item.variant,
            floor,
            item.region,
            jitter=0.3,
        )

    def add(placer: _Placer) -> _Item | None:
        candidates = [k for k, (_, kind, _) in enumerate(rooms.rects) if kind.startswith("room")]
        k = int(rng.choice(candidates))
        floor, _, rect = rooms.rects[k]
        prop = str(rng.choice(["boxes", "plant", "boxes", "poster", "cabinet"]))
        variant = posters.draw() if prop == "poster" else int(rng.integers(12))
        if prop in ("poster", "cabinet"):
            return _place_on_wall(
                placer, rng, _wall_runs(plan, rect, floor), prop, variant, floor, k
            )
        return _place_free(placer, rng, rect, floor * plan.H, prop, variant, floor, k, jitter=0.4)

    return _change_items(rng, items, placer.copy(), plan.cfg.n_changed_objects, relocate, add)
