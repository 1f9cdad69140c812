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
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from diffloc.io.textured_mesh import TexturedMesh
from diffloc.sim.primitives import PROPS, Frame, MeshBuilder, wall_panel, window_unit
from diffloc.sim.textures import MATERIALS, make_materials

__all__ = [
    "INDOOR_MATERIALS",
    "OUTDOOR_MATERIALS",
    "WORLD_KINDS",
    "IndoorLayoutConfig",
    "OutdoorLayoutConfig",
    "Region",
    "World",
    "generate_world",
]

WORLD_KINDS = ("indoor", "outdoor")
POSTERS = tuple(spec.name for spec in MATERIALS if spec.name.startswith("poster_"))

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

OUTDOOR_MATERIALS = (
    "asphalt",
    "gravel",
    "grass",
    "paving",
    "facade_stone",
    "facade_brick",
    "facade_render",
    "stone_trim",
    "roof_slate",
    "window_facade",
    "door_facade",
    "car_red",
    "car_blue",
    "car_silver",
    "car_glass",
    "rubber",
    "bark",
    "foliage",
    "water",
    "sign_text",
    "metal",
    "metal_dark",
    "paint_red",
    "wood",
    "wood_dark",
    "concrete",
    "light_panel",
    *POSTERS,
)

# Horizontal gap kept between placed objects (metres).
_OBJECT_GAP = 0.1
# Extra margin beyond the route clearance kept free of furniture / clutter (metres).
_INDOOR_KEEPOUT_MARGIN = 0.3
_OUTDOOR_KEEPOUT_MARGIN = 1.5
# Width of door frame bars and how far they stand out of the wall (metres).
_FRAME_WIDTH = 0.07
_FRAME_PROUD = 0.03
# Minimum distance of in-room route corners from walls (metres, beyond the clearance).
_CORNER_MARGIN = 0.5
# Spacing of route samples used by the placement checks (metres).
_ROUTE_SAMPLE_STEP = 0.05
# Scanner heights above the floor / ground (metres).
_TLS_HEIGHT_INDOOR = 1.3
_TLS_HEIGHT_OUTDOOR = 1.8


# --------------------------------------------------------------------------- configs


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


# --------------------------------------------------------------------------- world


@dataclass
class Region:
    """A named axis-aligned box of the world (a room, a corridor, a facade, a building, ...).

    Attributes:
        name: unique name, e.g. ``"f1_room2"``.
        kind: ``"room"``, ``"corridor"``, ``"stair_hall"``, ``"courtyard"``, ``"avenue"``,
            ``"building"`` or ``"facade"``.
        floor: storey index (0 = ground).
        lo: (3,) min corner in metres.
        hi: (3,) max corner in metres.
    """

    name: str
    kind: str
    floor: int
    lo: np.ndarray
    hi: np.ndarray

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: which of the (N, 3) points lie inside the box."""
        return ((points >= self.lo) & (points <= self.hi)).all(axis=1)


@dataclass
class World:
    """A generated world.

    Attributes:
        kind: ``"indoor"`` or ``"outdoor"``.
        seed: the generating seed.
        mesh: the scene as mapped.
        changed_mesh: the same scene with some movable objects moved, removed or added (same
            material list; object ids of added objects are new).
        route: (K, 3) float64 ordered waypoints of the walking / driving path; z is the floor
            height under each waypoint (straight lines between waypoints stay on the floor or
            stair nosing line).
        route_clearance: metres of free space guaranteed on each side of the route at heights up
            to 2 m above it (both scene states).
        tls_stations: (S, 3) float64 free-space positions of a static terrestrial scanner
            (1.3 m above the floor indoors, 1.8 m above the ground outdoors).
        bounds: (2, 3) float64 min and max corner of the world (both scene states).
        regions: rooms, corridors, stair hall (indoor) or courtyard, avenue, buildings, facades
            (outdoor).
        floor_heights: z of each storey's floor (indoor: two storeys; outdoor: ``[0.0]``).
        num_objects: movable objects in ``mesh``.
        num_changes: objects moved, removed or added in ``changed_mesh``.
    """

    kind: str
    seed: int
    mesh: TexturedMesh
    changed_mesh: TexturedMesh
    route: np.ndarray
    route_clearance: float
    tls_stations: np.ndarray
    bounds: np.ndarray
    regions: list[Region] = field(default_factory=list)
    floor_heights: list[float] = field(default_factory=list)
    num_objects: int = 0
    num_changes: int = 0

    @property
    def route_length(self) -> float:
        """Length of the route polyline in metres."""
        return float(np.linalg.norm(np.diff(self.route, axis=0), axis=1).sum())

    def count(self, kind: str) -> int:
        """Number of regions of a kind (``"room"``, ``"facade"``, ...)."""
        return sum(region.kind == kind for region in self.regions)

    def metadata(self) -> dict[str, Any]:
        """JSON-serialisable summary (counts, lengths, bounds) for dataset descriptions."""
        kinds = sorted({region.kind for region in self.regions})
        return {
            "kind": self.kind,
            "seed": int(self.seed),
            "triangles": self.mesh.num_faces,
            "changed_triangles": self.changed_mesh.num_faces,
            "materials": len(self.mesh.material_names),
            "movable_objects": int(self.num_objects),
            "changed_objects": int(self.num_changes),
            "route_waypoints": int(len(self.route)),
            "route_length_m": round(self.route_length, 3),
            "route_clearance_m": float(self.route_clearance),
            "tls_stations": int(len(self.tls_stations)),
            "floor_heights_m": [float(z) for z in self.floor_heights],
            "bounds_m": np.round(self.bounds, 3).tolist(),
            "regions": {kind: self.count(kind) for kind in kinds},
        }


# --------------------------------------------------------------------------- placement


@dataclass
class _Item:
    """A movable object: a prop (or wall panel) with its pose and footprint.

    ``aabb`` is (x0, y0, x1, y1) in the world; ``origin`` (3,) is the prop frame origin.
    """

    prop: str
    floor: int
    origin: np.ndarray
    yaw: float
    variant: int
    region: int
    aabb: np.ndarray


# Wall panels that are movable objects: width (m), (bottom, top) heights (m), trim material.
_PANELS: dict[str, tuple[float, tuple[float, float], str | None]] = {
    "whiteboard": (1.6, (0.9, 2.0), "metal"),
    "notice_board": (1.2, (1.0, 1.9), "wood_dark"),
}
_POSTER_SIZES = ((0.7, (1.2, 2.1)), (0.9, (1.15, 2.05)), (1.1, (1.0, 2.05)), (0.6, (1.3, 2.0)))


def _footprint(prop: str, variant: int) -> tuple[float, float, float, float]:
    """Local footprint rectangle (x0, y0, x1, y1) of a prop, panel or pillar."""
    if prop in PROPS:
        return PROPS[prop].footprint
    if prop == "pillar":
        return (-0.2, -0.2, 0.2, 0.2)
    width = _PANELS[prop][0] if prop in _PANELS else _POSTER_SIZES[variant % len(_POSTER_SIZES)][0]
    return (-width / 2 - 0.05, 0.0, width / 2 + 0.05, 0.05)


def _aabb(
    footprint: tuple[float, float, float, float], origin: np.ndarray, yaw: float
) -> np.ndarray:
    """World AABB (4,) of a local footprint rectangle rotated by ``yaw`` about ``origin``."""
    x0, y0, x1, y1 = footprint
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    c, s = math.cos(yaw), math.sin(yaw)
    world = corners @ np.array([[c, s], [-s, c]]) + origin[:2]
    return np.concatenate([world.min(axis=0), world.max(axis=0)])


def _sample_polyline(route: np.ndarray, step: float) -> np.ndarray:
    """Points (M, 3) along a polyline (K, 3), at most ``step`` apart, including the waypoints."""
    pieces = []
    for start, end in zip(route[:-1], route[1:], strict=True):
        count = max(1, int(math.ceil(np.linalg.norm(end - start) / step)))
        t = np.arange(count)[:, None] / count
        pieces.append(start + t * (end - start))
    pieces.append(route[-1:])
    return np.concatenate(pieces)


class _Placer:
    """Rejection sampling of object footprints: no overlaps, no objects near the route.

    Args:
        route: (K, 3) route waypoints.
        keepout: minimum horizontal distance of footprints from the route.
        floor_heights: z of each storey; route samples within one storey height of a floor
            count for it (stairs count for both floors they join).
    """

    def __init__(self, route: np.ndarray, keepout: float, floor_heights: list[float]) -> None:
        samples = _sample_polyline(route, _ROUTE_SAMPLE_STEP)
        storey = floor_heights[1] - floor_heights[0] if len(floor_heights) > 1 else np.inf
        self.route_xy = [
            samples[np.abs(samples[:, 2] - z) < storey - 1e-6, :2] for z in floor_heights
        ]
        self.keepout = keepout
        self.occupied: list[list[np.ndarray]] = [[] for _ in floor_heights]

    def copy(self) -> _Placer:
        other = _Placer.__new__(_Placer)
        other.route_xy, other.keepout = self.route_xy, self.keepout
        other.occupied = [list(boxes) for boxes in self.occupied]
        return other

    def route_distance(self, floor: int, aabb: np.ndarray) -> float:
        """Horizontal distance (m) from an AABB (4,) to the route on a floor."""
        points = self.route_xy[floor]
        if len(points) == 0:
            return math.inf
        dx = np.maximum(np.maximum(aabb[0] - points[:, 0], points[:, 0] - aabb[2]), 0.0)
        dy = np.maximum(np.maximum(aabb[1] - points[:, 1], points[:, 1] - aabb[3]), 0.0)
        return float(np.sqrt(dx**2 + dy**2).min())

    def is_free(self, floor: int, aabb: np.ndarray, gap: float = _OBJECT_GAP) -> bool:
        if self.occupied[floor]:
            boxes = np.asarray(self.occupied[floor])
            overlap = (
                (aabb[0] < boxes[:, 2] + gap)
                & (boxes[:, 0] < aabb[2] + gap)
                & (aabb[1] < boxes[:, 3] + gap)
                & (boxes[:, 1] < aabb[3] + gap)
            )
            if overlap.any():
                return False
        return self.route_distance(floor, aabb) >= self.keepout

    def occupy(self, floor: int, aabb: np.ndarray) -> None:
        self.occupied[floor].append(np.asarray(aabb, float))

    def release(self, floor: int, aabb: np.ndarray) -> None:
        for k, box in enumerate(self.occupied[floor]):
            if np.array_equal(box, aabb):
                del self.occupied[floor][k]
                return


@dataclass
class _WallRun:
    """A free stretch of wall face: points ``start + s * direction`` for s in [lo, hi].

    ``normal`` (2,) points away from the wall into the region; z is the floor height.
    """

    start: np.ndarray
    direction: np.ndarray
    normal: np.ndarray
    lo: float
    hi: float
    z: float


def _place_on_wall(
    placer: _Placer,
    rng: np.random.Generator,
    runs: list[_WallRun],
    prop: str,
    variant: int,
    floor: int,
    region: int,
    attempts: int = 25,
) -> _Item | None:
    """Try to stand a prop or panel with its back on one of the wall runs."""
    x0, y0, x1, _ = _footprint(prop, variant)
    width = x1 - x0
    usable = [run for run in runs if run.hi - run.lo > width + 0.1]
    if not usable:
        return None
    lengths = np.array([run.hi - run.lo for run in usable])
    for _ in range(attempts):
        run = usable[int(rng.choice(len(usable), p=lengths / lengths.sum()))]
        s = rng.uniform(run.lo - x0 + 0.05, run.hi - x1 - 0.05)
        xy = run.start + s * run.direction + (0.005 - y0) * run.normal
        origin = np.array([xy[0], xy[1], run.z])
        yaw = math.atan2(-run.normal[0], run.normal[1])
        aabb = _aabb((x0, y0, x1, _footprint(prop, variant)[3]), origin, yaw)
        if placer.is_free(floor, aabb):
            placer.occupy(floor, aabb)
            return _Item(prop, floor, origin, yaw, variant, region, aabb)
    return None


def _place_free(
    placer: _Placer,
    rng: np.random.Generator,
    rect: np.ndarray,
    z: float,
    prop: str,
    variant: int,
    floor: int,
    region: int,
    yaw_choices: tuple[float, ...] = (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi),
    jitter: float = 0.0,
    attempts: int = 25,
) -> _Item | None:
    """Try to stand a prop anywhere inside ``rect`` (x0, y0, x1, y1) with a given yaw choice."""
    footprint = _footprint(prop, variant)
    for _ in range(attempts):
        yaw = float(rng.choice(yaw_choices)) + rng.uniform(-jitter, jitter)
        local = _aabb(footprint, np.zeros(3), yaw)
        lo = rect[:2] - local[:2] + 0.02
        hi = rect[2:] - local[2:] - 0.02
        if (hi <= lo).any():
            continue
        xy = rng.uniform(lo, hi)
        origin = np.array([xy[0], xy[1], z])
        aabb = local + np.tile(xy, 2)
        if placer.is_free(floor, aabb):
            placer.occupy(floor, aabb)
            return _Item(prop, floor, origin, yaw, variant, region, aabb)
    return None


def _build_items(builder: MeshBuilder, items: list[_Item], first_id: int = 1) -> None:
    """Add the solids of movable objects with ids ``first_id, first_id + 1, ...``."""
    for k, item in enumerate(items):
        oid = first_id + k
        frame = Frame(item.origin, item.yaw)
        if item.prop in PROPS:
            PROPS[item.prop].build(builder, frame, oid, item.variant)
        elif item.prop in _PANELS:
            width, z_range, trim = _PANELS[item.prop]
            wall_panel(builder, frame, width, z_range, item.prop, oid, trim=trim)
        else:
            width, z_range = _POSTER_SIZES[item.variant % len(_POSTER_SIZES)]
            poster = POSTERS[item.variant % len(POSTERS)]
            wall_panel(
                builder, frame, width, z_range, poster, oid, trim="wood_dark", trim_width=0.03
            )


def _change_items(
    rng: np.random.Generator,
    items: list[_Item],
    placer: _Placer,
    count: int,
    relocate: Any,
    add: Any,
) -> tuple[list[_Item], int]:
    """Move, remove and add objects; return the new item list and the number of changes.

    Args:
        rng: randomness.
        items: the mapped scene's items (not modified).
        placer: a copy of the mapped scene's placer (modified).
        count: number of changes wanted (fewer if objects find no room after 4 * count tries).
        relocate: ``relocate(item, placer) -> _Item | None`` places an item anew.
        add: ``add(placer) -> _Item | None`` places a new object.
    """
    changed = list(items)
    done = attempts = 0
    while done < count and attempts < 4 * count:
        action = (
            ("move", "remove", "add")[attempts % 3]
            if attempts < 3
            else str(rng.choice(["move", "remove", "add"]))
        )
        attempts += 1
        if action in ("move", "remove") and changed:
            index = int(rng.integers(len(changed)))
            item = changed[index]
            placer.release(item.floor, item.aabb)
            if action == "remove":
                del changed[index]
                done += 1
                continue
            moved = relocate(item, placer)
            if moved is None:
                placer.occupy(item.floor, item.aabb)
                continue
            changed[index] = moved
            done += 1
        else:
            new = add(placer)
            if new is not None:
                changed.append(new)
                done += 1
    return changed, done


def _simplify_route(points: list[tuple[float, float, float]]) -> np.ndarray:
    """(K, 3) route without repeated waypoints or waypoints on a straight line."""
    route = [np.asarray(points[0], float)]
    for p in points[1:]:
        p = np.asarray(p, float)
        if np.linalg.norm(p - route[-1]) > 1e-6:
            route.append(p)
    keep = [route[0]]
    for k in range(1, len(route) - 1):
        a, b = route[k] - keep[-1], route[k + 1] - route[k]
        if (
            np.linalg.norm(np.cross(a, b)) > 1e-9 * np.linalg.norm(a) * np.linalg.norm(b)
            or a @ b < 0
        ):
            keep.append(route[k])
    keep.append(route[-1])
    return np.asarray(keep, dtype=np.float64)


def _tls_stations(route: np.ndarray, spacing: float, height: float) -> np.ndarray:
    """(S, 3) scanner positions ``height`` above level parts of the route, ~``spacing`` apart."""
    samples = _sample_polyline(route, 0.25)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(samples, axis=0), axis=1))])
    count = max(2, int(arc[-1] // spacing))
    targets = (np.arange(count) + 0.5) * arc[-1] / count
    index = np.searchsorted(arc, targets).clip(0, len(samples) - 1)
    # Level parts only: the waypoints on either side have the same height.
    segment = np.searchsorted(np.cumsum(np.linalg.norm(np.diff(route, axis=0), axis=1)), targets)
    segment = segment.clip(0, len(route) - 2)
    level = np.abs(route[segment, 2] - route[segment + 1, 2]) < 1e-9
    stations = samples[index[level]] + np.array([0.0, 0.0, height])
    return stations.astype(np.float64)


def _mesh_bounds(*meshes: TexturedMesh) -> np.ndarray:
    vertices = np.concatenate([m.vertices for m in meshes]).astype(np.float64)
    return np.stack([vertices.min(axis=0), vertices.max(axis=0)])


def _check_config(cfg: Any, positive: tuple[str, ...], counts: tuple[str, ...]) -> None:
    for name in positive:
        value = getattr(cfg, name)
        if not isinstance(value, int | float) or isinstance(value, bool) or not value > 0:
            raise ValueError(f"layout.{name} must be a positive number, got {value!r}")
    for name in counts:
        value = getattr(cfg, name)
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
            raise ValueError(f"layout.{name} must be a non-negative integer, got {value!r}")
    size = cfg.texture_size
    if isinstance(size, bool) or not isinstance(size, int | np.integer) or size < 16:
        raise ValueError(f"layout.texture_size must be an integer >= 16, got {size!r}")


# --------------------------------------------------------------------------- indoor


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
    axis: str,
    line: float,
    thickness: float,
    span: tuple[float, float],
    z: tuple[float, float],
    floor_z: float,
    doors: list[_Door],
    material: str,
    door_height: float,
    slab: float,
) -> None:
    """A straight wall with framed door openings (lintels, jambs, head trims, thresholds)."""
    cuts = sorted(door.cut for door in doors)
    edges = [span[0]] + [c for cut in cuts for c in cut] + [span[1]]
    for lo, hi in zip(edges[0::2], edges[1::2], strict=True):
        if hi - lo > 1e-6:
            b.add_box(*_axis_box(axis, line, thickness, (lo, hi), z), material, 0)
    head = floor_z + door_height
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


def _indoor_world(seed: int, cfg: IndoorLayoutConfig) -> World:
    _validate_indoor(cfg)
    rng = np.random.default_rng(seed)
    names, textures = make_materials(rng, int(cfg.texture_size), INDOOR_MATERIALS)
    plan = _IndoorPlan(cfg, rng)
    route = _simplify_route(plan.route_points)
    H, slab, te, tw = plan.H, plan.slab, plan.te, plan.tw
    n = cfg.rooms_per_floor
    b = MeshBuilder(names)

    # Regions and their finishes.
    regions: list[Region] = []
    rects: list[tuple[int, str, np.ndarray]] = []  # (floor, kind, rect) in region order
    for floor in (0, 1):
        z = floor * H
        types = rng.permutation(list(_ROOM_TYPES))
        for i in range(n):
            rects.append((floor, f"room:{types[i % len(types)]}", plan.room_rect(floor, i)))
        rects.append((floor, "room:open_office", plan.office_rect()))
        rects.append((floor, "corridor", plan.corridor_rect()))
        rects.append((floor, "stair_hall", plan.hall_rect()))
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

    def region_index(floor: int, kind: str, i: int = 0) -> int:
        matches = [k for k, r in enumerate(regions) if r.floor == floor and r.kind == kind]
        return matches[i]

    # Slabs: lower layer (ceiling below), per-region floor finish on top, and the roof.
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
    for k, (floor, kind, rect) in enumerate(rects):
        z = floor * H
        pieces = [rect]
        if kind == "stair_hall" and floor == 1:
            pieces = [
                np.array([rect[0], rect[1], rect[2], plan.hy0]),
                np.array([plan.xs1, plan.hy0, rect[2], rect[3]]),
            ]
        for x0, y0, x1, y1 in pieces:
            b.add_box([x0, y0, z - slab / 2], [x1, y1, z], floor_finish[k], 0)

    # Walls.
    for floor in (0, 1):
        z = floor * H
        wall_z = (z - slab / 2, z + H - slab)
        doors = [d for d in plan.doors if d.floor == floor]
        room_ids = [region_index(floor, "room", i) for i in range(n)]
        corridor_id = region_index(floor, "corridor")
        office_id, hall_id = region_index(floor, "room", n), region_index(floor, "stair_hall")

        def wall(
            axis: str,
            line: float,
            span: tuple[float, float],
            material: str,
            doors=doors,
            wall_z=wall_z,
            z=z,
        ) -> None:
            on_line = [d for d in doors if d.axis == axis and abs(d.line - line) < 1e-9]
            _build_wall(
                b, axis, line, tw, span, wall_z, z, on_line, material, cfg.door_height, slab
            )

        wall("x", plan.ys, (te, plan.Lx - te), wall_finish[corridor_id])
        wall("x", plan.yn, (te, plan.Lx - te), wall_finish[corridor_id])
        for i in range(1, n):
            finish = wall_finish[room_ids[i - 1 + int(rng.integers(2))]]
            wall("y", plan.partitions[floor][i], (te, plan.ys - tw / 2), finish)
        wall("y", plan.xh, (plan.yn + tw / 2, plan.Ly - te), wall_finish[office_id])
        # Exterior walls, one segment per room so each room shows its own finish.
        ext_z = (-slab, H - slab) if floor == 0 else (H - slab, 2 * H)
        a = plan.partitions[floor]
        for i in range(n):
            lo, hi = _axis_box("x", te / 2, te, (a[i], a[i + 1]), ext_z)
            b.add_box(lo, hi, wall_finish[room_ids[i]], 0)
        for (x0, x1), rid in (((0.0, plan.xh), office_id), ((plan.xh, plan.Lx), hall_id)):
            lo, hi = _axis_box("x", plan.Ly - te / 2, te, (x0, x1), ext_z)
            b.add_box(lo, hi, wall_finish[rid] if rid != hall_id else "concrete", 0)
        for x_line in (te / 2, plan.Lx - te / 2):
            east = x_line > plan.Lx / 2
            spans = (
                ((te, plan.ys), room_ids[-1] if east else room_ids[0]),
                ((plan.ys, plan.yn), corridor_id),
                ((plan.yn, plan.Ly - te), hall_id if east else office_id),
            )
            for (y0, y1), rid in spans:
                lo, hi = _axis_box("y", x_line, te, (y0, y1), ext_z)
                b.add_box(lo, hi, wall_finish[rid] if rid != hall_id else "concrete", 0)

    # Stairs: solid steps, a balustrade on the open side and one around the void upstairs.
    for k in range(1, plan.n_steps):
        x0 = plan.xs0 + (k - 1) * plan.tread
        b.add_box([x0, plan.sb0, 0.0], [x0 + plan.tread, plan.sb1, k * plan.rise], "concrete", 0)
        b.add_box(
            [x0, plan.sb0 - 0.1, 0.0],
            [x0 + plan.tread, plan.sb0, k * plan.rise + 0.9],
            "wood_dark",
            0,
        )
    b.add_box([plan.hx0, plan.hy0 - 0.1, H], [plan.xs1, plan.hy0, H + 1.0], "wood_dark", 0)

    placer = _Placer(route, cfg.route_clearance + _INDOOR_KEEPOUT_MARGIN, [0.0, H])
    # Keep doorways, the stairs and the stairwell void free of furniture.
    for door in plan.doors:
        lo, hi = door.cut
        depth = door.thickness / 2 + 1.0
        box = (lo - 0.2, door.line - depth, hi + 0.2, door.line + depth)
        if door.axis == "y":
            box = (door.line - depth, lo - 0.2, door.line + depth, hi + 0.2)
        placer.occupy(door.floor, np.array(box))
    placer.occupy(0, np.array([plan.xs0 - plan.tread, plan.hy0 - 0.2, plan.Lx - te, plan.Ly - te]))
    placer.occupy(1, np.array([plan.hx0, plan.hy0 - 0.2, plan.xs1, plan.Ly - te]))

    # Fixed fittings: windows with radiators, skirting, ceiling lights, office pillars.
    ext_sides = {
        "s": lambda r: r[1] <= te + 1e-9,
        "n": lambda r: r[3] >= plan.Ly - te - 1e-9,
        "w": lambda r: r[0] <= te + 1e-9,
        "e": lambda r: r[2] >= plan.Lx - te - 1e-9,
    }
    for floor, kind, rect in rects:
        z = floor * H
        if cfg.windows:
            sides = "".join(s for s, test in ext_sides.items() if test(rect))
            if kind == "stair_hall":
                sides = sides.replace("n", "")
            for run in _wall_runs(plan, rect, floor, sides):
                count = int((run.hi - run.lo) // 2.6)
                for j in range(count):
                    s = run.lo + (j + 0.5) * (run.hi - run.lo) / count
                    xy = run.start + s * run.direction
                    frame = Frame(
                        np.array([xy[0], xy[1], z]), math.atan2(-run.normal[0], run.normal[1])
                    )
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
        if kind != "stair_hall":
            for run in _wall_runs(plan, rect, floor):
                start = run.start + run.lo * run.direction
                frame = Frame(
                    np.array([start[0], start[1], z]), math.atan2(-run.normal[0], run.normal[1])
                )
                frame.box(b, (0.0, 0.0, 0.0), (run.hi - run.lo, 0.015, 0.08), "wood_dark", 0)
        ceiling = z + H - slab
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
    for floor in (0, 1):
        office = plan.office_rect()
        for _ in range(3):  # structural pillars wherever the sampler finds room
            pillar = _place_free(
                placer, rng, office, floor * H, "pillar", 0, floor, -1, attempts=20
            )
            if pillar is not None:
                x0, y0, x1, y1 = pillar.aabb
                b.add_box([x0, y0, floor * H], [x1, y1, floor * H + H - slab], "concrete", 0)

    # Movable objects: furniture, posters and boards.
    posters = [int(v) for v in rng.permutation(len(POSTERS))]
    poster_cursor = [0]

    def next_poster() -> int:
        variant = posters[poster_cursor[0] % len(posters)] + len(POSTERS) * int(rng.integers(4))
        poster_cursor[0] += 1
        return variant

    items: list[_Item] = []
    for k, (floor, kind, rect) in enumerate(rects):
        z = floor * H
        sides = "swe" if kind == "stair_hall" else "swne"
        if kind == "stair_hall" and floor == 1:
            continue
        runs = _wall_runs(plan, rect, floor, sides)
        wanted: list[str]
        if kind == "corridor":
            wanted = ["extinguisher", "notice_board", "extinguisher"]
            panels = cfg.posters_per_room + 1
        elif kind == "stair_hall":
            wanted = ["vending_machine", "sofa", "plant"]
            panels = 1
        else:
            catalogue = (
                _OPEN_OFFICE if kind == "room:open_office" else _ROOM_TYPES[kind.split(":")[1]]
            )
            count = cfg.furniture_per_room * (2 if kind == "room:open_office" else 1)
            wanted = [catalogue[j % len(catalogue)] for j in range(count)]
            panels = cfg.posters_per_room
            if kind in ("room:meeting", "room:office"):
                wanted.insert(1, "whiteboard")
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
            item = _place_on_wall(placer, rng, runs, "poster", next_poster(), floor, k)
            if item is not None:
                items.append(item)

    structure = b.build(textures)
    objects = MeshBuilder(names)
    _build_items(objects, items)

    def relocate(item: _Item, placer: _Placer) -> _Item | None:
        floor, kind, rect = rects[item.region]
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
            placer, rng, rect, floor * H, item.prop, item.variant, floor, item.region, jitter=0.3
        )

    def add(placer: _Placer) -> _Item | None:
        candidates = [k for k, (floor, kind, _) in enumerate(rects) if kind.startswith("room")]
        k = int(rng.choice(candidates))
        floor, _, rect = rects[k]
        prop = str(rng.choice(["boxes", "plant", "boxes", "poster", "cabinet"]))
        variant = next_poster() if prop == "poster" else int(rng.integers(12))
        if prop in ("poster", "cabinet"):
            return _place_on_wall(
                placer, rng, _wall_runs(plan, rect, floor), prop, variant, floor, k
            )
        return _place_free(placer, rng, rect, floor * H, prop, variant, floor, k, jitter=0.4)

    changed_items, changes = _change_items(
        rng, items, placer.copy(), cfg.n_changed_objects, relocate, add
    )
    changed_objects = MeshBuilder(names)
    _build_items(changed_objects, changed_items)
    mesh = _join(structure, objects, textures)
    changed_mesh = _join(structure, changed_objects, textures)
    return World(
        kind="indoor",
        seed=seed,
        mesh=mesh,
        changed_mesh=changed_mesh,
        route=route,
        route_clearance=float(cfg.route_clearance),
        tls_stations=_tls_stations(route, 8.0, _TLS_HEIGHT_INDOOR),
        bounds=_mesh_bounds(mesh, changed_mesh),
        regions=regions,
        floor_heights=[0.0, float(H)],
        num_objects=len(items),
        num_changes=changes,
    )


def _join(
    structure: TexturedMesh, objects: MeshBuilder, textures: list[np.ndarray]
) -> TexturedMesh:
    if objects.num_faces == 0:
        return structure
    return TexturedMesh.concatenate([structure, objects.build(textures)])


# --------------------------------------------------------------------------- outdoor


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


def _ground(b: MeshBuilder, plan: _OutdoorPlan) -> None:
    """Ground slabs: a grid of boxes, each cell taking the first area (by priority) it lies in."""
    lx0, ly0, lx1, ly1 = plan.lawn
    ym = (ly0 + ly1) / 2
    areas = [  # (x0, y0, x1, y1, material, top z)
        (-1.5, ly0, 1.5, ly1, "gravel", 0.12),
        (lx0, ym - 1.5, lx1, ym + 1.5, "gravel", 0.12),
        (lx0, ly0, lx1, ly1, "grass", 0.12),
        (-plan.xr - 4, plan.y_s - 4, plan.xr + 4, plan.y_n + 4, "asphalt", 0.0),
        (-4.0, 0.0, 4.0, plan.y_s, "asphalt", 0.0),
        (-4.0, plan.world[1], 4.0, 0.0, "gravel", 0.0),
        (-plan.W / 2, 0.0, plan.W / 2, plan.D, "paving", 0.0),
        (*plan.world, "grass", 0.0),
    ]
    box = np.array([a[:4] for a in areas], float)
    xs = np.unique(np.clip(box[:, [0, 2]].ravel(), plan.world[0], plan.world[2]))
    ys = np.unique(np.clip(box[:, [1, 3]].ravel(), plan.world[1], plan.world[3]))
    cx, cy = np.meshgrid((xs[:-1] + xs[1:]) / 2, (ys[:-1] + ys[1:]) / 2, indexing="ij")
    inside = (
        (box[:, 0, None, None] <= cx)
        & (cx <= box[:, 2, None, None])
        & (box[:, 1, None, None] <= cy)
        & (cy <= box[:, 3, None, None])
    )
    first = np.argmax(inside, axis=0)
    ix, iy = np.meshgrid(np.arange(len(xs) - 1), np.arange(len(ys) - 1), indexing="ij")
    for k, (*_, material, top) in enumerate(areas):
        sel = first == k
        if not sel.any():
            continue
        lo = np.stack([xs[ix[sel]], ys[iy[sel]], np.full(sel.sum(), -0.5)], 1)
        hi = np.stack([xs[ix[sel] + 1], ys[iy[sel] + 1], np.full(sel.sum(), top)], 1)
        b.add_boxes((lo + hi) / 2, (hi - lo) / 2, material, 0)


def _outdoor_world(seed: int, cfg: OutdoorLayoutConfig) -> World:
    _validate_outdoor(cfg)
    rng = np.random.default_rng(seed)
    names, textures = make_materials(rng, int(cfg.texture_size), OUTDOOR_MATERIALS)
    plan = _OutdoorPlan(cfg, rng)
    W, D, wd, A = plan.W, plan.D, plan.wd, plan.A
    main_h, wing_h, spacing = plan.main_height, plan.wing_height, plan.spacing
    route = plan.route
    b = MeshBuilder(names)
    placer = _Placer(route, plan.keepout, [0.0])
    regions: list[Region] = [
        Region(
            "courtyard", "courtyard", 0, np.array([-W / 2, 0.0, 0.0]), np.array([W / 2, D, main_h])
        ),
        Region("avenue", "avenue", 0, np.array([-4.0, -A, 0.0]), np.array([4.0, 0.0, 10.0])),
    ]
    _ground(b, plan)

    def building(name: str, rect: np.ndarray, height: float, material: str, roof: str) -> None:
        b.add_box([rect[0], rect[1], 0.0], [rect[2], rect[3], height], material, 0)
        if roof == "gable":
            _gable_roof(
                b,
                rect,
                height,
                min(5.0, 0.35 * min(rect[2] - rect[0], rect[3] - rect[1])),
                "roof_slate",
            )
        elif roof == "hip":
            half = (rect[2:] - rect[:2]) / 2 + 0.3
            square = np.array(
                [[-half[0], -half[1]], [half[0], -half[1]], [half[0], half[1]], [-half[0], half[1]]]
            )
            center = np.array([(rect[0] + rect[2]) / 2, (rect[1] + rect[3]) / 2, height])
            b.add_prism(square, center, np.eye(3), 4.5, "roof_slate", 0, top_scale=0.25)
        placer.occupy(0, np.asarray(rect, float))
        regions.append(
            Region(
                name,
                "building",
                0,
                np.array([rect[0], rect[1], 0.0]),
                np.array([rect[2], rect[3], height]),
            )
        )

    def facade(
        name: str,
        start: tuple[float, float],
        direction: tuple[float, float],
        length: float,
        height: float,
        trim: str,
        opening: Any,
    ) -> None:
        start_a, direction_a = np.asarray(start, float), np.asarray(direction, float)
        frame = _facade_frame(start_a, direction_a)
        _facade(b, frame, length, height, cfg.storey_height, spacing, trim, opening)
        end = start_a + length * direction_a
        normal = np.array([-direction_a[1], direction_a[0]])
        lo = np.minimum(start_a, end + 0.6 * normal)
        hi = np.maximum(start_a, end + 0.6 * normal)
        regions.append(Region(name, "facade", 0, np.array([*lo, 0.0]), np.array([*hi, height])))

    doors_every = int(rng.integers(3, 6))

    def regular(x: float, f: int, period: int = doors_every) -> str:
        column = int(round((x - spacing / 2) / spacing))
        return "door" if f == 0 and column % period == period // 2 else "window"

    # The palace: main block, wings, corner pavilions, portico.
    pav = plan.pavilion_out
    pavilion_y = (-4.0, 12.0)
    pavilion_h = main_h + 2.0
    building(
        "main_block",
        np.array([-W / 2 - wd, D, W / 2 + wd, D + wd]),
        main_h,
        "facade_stone",
        "gable",
    )
    for side, sign in (("east", 1.0), ("west", -1.0)):
        x_in, x_out = sign * W / 2, sign * (W / 2 + wd)
        building(
            f"{side}_wing",
            np.array([min(x_in, x_out), pavilion_y[1], max(x_in, x_out), D]),
            wing_h,
            "facade_stone",
            "gable",
        )
        x_pav_in, x_pav_out = sign * (W / 2 - pav), sign * (W / 2 + wd + pav)
        building(
            f"{side}_pavilion",
            np.array(
                [min(x_pav_in, x_pav_out), pavilion_y[0], max(x_pav_in, x_pav_out), pavilion_y[1]]
            ),
            pavilion_h,
            "facade_stone",
            "hip",
        )
        length = D - pavilion_y[1]
        if sign > 0:
            facade(
                f"{side}_wing_facade",
                (x_in, pavilion_y[1]),
                (0.0, 1.0),
                length,
                wing_h,
                "stone_trim",
                regular,
            )
        else:
            facade(
                f"{side}_wing_facade", (x_in, D), (0.0, -1.0), length, wing_h, "stone_trim", regular
            )
        # Pavilion faces: a banner towards the courtyard, windows towards the avenue.
        pav_len = pavilion_y[1] - pavilion_y[0]
        banner = POSTERS[int(rng.integers(len(POSTERS)))]
        if sign > 0:
            inner = _facade_frame(np.array([x_pav_in, pavilion_y[0]]), np.array([0.0, 1.0]))
            south = _facade_frame(np.array([x_pav_out, pavilion_y[0]]), np.array([-1.0, 0.0]))
        else:
            inner = _facade_frame(np.array([x_pav_in, pavilion_y[1]]), np.array([0.0, -1.0]))
            south = _facade_frame(np.array([x_pav_in, pavilion_y[0]]), np.array([-1.0, 0.0]))
        banner_frame = Frame(inner.point((pav_len / 2, 0.0, 0.0)), inner.yaw)
        wall_panel(
            b,
            banner_frame,
            5.0,
            (4.0, 10.0),
            banner,
            0,
            depth=0.05,
            trim="metal_dark",
            trim_width=0.15,
        )
        _facade(
            b,
            inner,
            pav_len,
            pavilion_h,
            cfg.storey_height,
            spacing,
            "stone_trim",
            lambda x, f, n=pav_len: "window" if f >= 3 and abs(x - n / 2) > 2.0 else "none",
        )
        width = wd + 2 * pav
        _facade(
            b,
            south,
            width,
            pavilion_h,
            cfg.storey_height,
            spacing,
            "stone_trim",
            lambda x, f, n=width: "door" if f == 0 and abs(x - n / 2) < spacing / 2 else "window",
        )
        regions.append(
            Region(
                f"{side}_pavilion_facade",
                "facade",
                0,
                np.array([min(x_pav_in, x_pav_out), pavilion_y[0] - 0.6, 0.0]),
                np.array([max(x_pav_in, x_pav_out), pavilion_y[0], pavilion_h]),
            )
        )

    def main_opening(x: float, f: int) -> str:
        world_x = W / 2 - x
        if abs(world_x) < spacing / 2:
            return "door" if f == 0 else ("window" if f == 1 else "none")
        if abs(world_x) < 10.5 and f >= 2:
            return "none"
        return regular(x, f, doors_every + 2)

    facade("main_facade", (W / 2, D), (-1.0, 0.0), W, main_h, "stone_trim", main_opening)
    # Portico: platform, step, columns, entablature and pediment.
    b.add_box([-10.0, D - 5.5, 0.0], [10.0, D, 0.6], "stone_trim", 0)
    b.add_box([-8.0, D - plan.portico, 0.0], [8.0, D - 5.5, 0.3], "stone_trim", 0)
    for x in np.linspace(-7.5, 7.5, plan.columns):
        b.add_box([x - 0.6, D - 5.1, 0.6], [x + 0.6, D - 3.9, 0.9], "stone_trim", 0)
        b.add_cylinder(
            [x, D - 4.5, 0.9], [0, 0, 1], 0.45, 7.8, "stone_trim", 0, segments=16, top_scale=0.88
        )
        b.add_box([x - 0.6, D - 5.1, 8.7], [x + 0.6, D - 3.9, 9.0], "stone_trim", 0)
    b.add_box([-9.5, D - 5.3, 9.0], [9.5, D, 10.4], "stone_trim", 0)
    pediment = np.array([[-9.8, 0.0], [9.8, 0.0], [0.0, 3.0]])
    b.add_prism(
        pediment,
        [0.0, D - 5.3, 10.4],
        np.array([[-1, 0, 0], [0, 0, 1], [0, 1, 0]], float),
        5.3,
        "stone_trim",
        0,
    )
    placer.occupy(0, np.array([-10.0, D - plan.portico, 10.0, D]))
    # Gate wall with piers and finials.
    for sign in (1.0, -1.0):
        x_pier = sign * plan.gate_half
        x_far = sign * (W / 2 - pav)
        pier = np.array(
            [min(x_pier, x_pier + sign * 1.4), -0.9, max(x_pier, x_pier + sign * 1.4), 0.3]
        )
        b.add_box([pier[0], pier[1], 0.0], [pier[2], pier[3], 4.2], "stone_trim", 0)
        b.add_box(
            [pier[0] - 0.15, pier[1] - 0.15, 4.2],
            [pier[2] + 0.15, pier[3] + 0.15, 4.45],
            "stone_trim",
            0,
        )
        b.add_cylinder(
            [(pier[0] + pier[2]) / 2, (pier[1] + pier[3]) / 2, 4.45],
            [0, 0, 1],
            0.4,
            0.9,
            "stone_trim",
            0,
            segments=12,
            top_scale=0.3,
        )
        lo, hi = sorted((x_pier + sign * 1.4, x_far))
        b.add_box([lo, -0.6, 0.0], [hi, 0.0, 2.4], "facade_brick", 0)
        b.add_box([lo, -0.7, 2.4], [hi, 0.1, 2.6], "stone_trim", 0)
        placer.occupy(0, np.array([min(pier[0], lo), -0.9, max(pier[2], hi), 0.3]))
    # Centrepiece of the lawn: a fountain or an obelisk.
    lx0, ly0, lx1, ly1 = plan.lawn
    fc = np.array([0.0, (ly0 + ly1) / 2, 0.12])
    if rng.random() < 0.6:
        b.add_cylinder(fc, [0, 0, 1], 3.6, 0.55, "stone_trim", 0, segments=24)
        b.add_cylinder(fc + [0, 0, 0.55], [0, 0, 1], 3.3, 0.03, "water", 0, segments=24)
        b.add_cylinder(fc + [0, 0, 0.58], [0, 0, 1], 0.5, 1.6, "stone_trim", 0, segments=12)
        b.add_cylinder(
            fc + [0, 0, 2.18], [0, 0, 1], 0.6, 0.5, "stone_trim", 0, segments=16, top_scale=2.4
        )
        b.add_cylinder(
            fc + [0, 0, 2.68], [0, 0, 1], 0.15, 1.0, "metal_dark", 0, segments=8, top_scale=0.4
        )
    else:
        b.add_box(fc + [-3.0, -3.0, 0.0], fc + [3.0, 3.0, 0.4], "stone_trim", 0)
        b.add_box(fc + [-1.4, -1.4, 0.4], fc + [1.4, 1.4, 2.2], "facade_stone", 0)
        square = np.array([[-0.8, -0.8], [0.8, -0.8], [0.8, 0.8], [-0.8, 0.8]])
        b.add_prism(square, fc + [0, 0, 2.2], np.eye(3), 9.0, "stone_trim", 0, top_scale=0.45)
        b.add_prism(
            square * 0.45, fc + [0, 0, 11.2], np.eye(3), 1.0, "metal_dark", 0, top_scale=0.05
        )
    placer.occupy(0, np.array([-3.8, fc[1] - 3.8, 3.8, fc[1] + 3.8]))

    # Outbuildings along the avenue (the asymmetric part).
    for k in range(cfg.n_outbuildings):
        for _ in range(30):
            size = rng.uniform([12.0, 8.0], [20.0, 12.0])
            east = rng.random() < 0.5
            x0 = rng.uniform(plan.keepout + 6.0, W / 2 + wd)
            y0 = rng.uniform(-A - 8.0, -8.0 - size[1])
            rect = np.array([x0, y0, x0 + size[0], y0 + size[1]])
            if not east:
                rect = np.array([-rect[2], rect[1], -rect[0], rect[3]])
            if (
                placer.is_free(0, rect, gap=3.0)
                and placer.route_distance(0, rect) >= plan.keepout + 5.0
            ):
                height = float(rng.uniform(6.0, 10.0))
                material = str(rng.choice(["facade_brick", "facade_render"]))
                building(f"outbuilding{k}", rect, height, material, "gable")
                if east:
                    start, direction = (rect[0], rect[1]), (0.0, 1.0)
                else:
                    start, direction = (rect[2], rect[3]), (0.0, -1.0)
                facade(
                    f"outbuilding{k}_facade",
                    start,
                    direction,
                    size[1],
                    height,
                    "stone_trim",
                    regular,
                )
                break

    # Zones for movable clutter: (rect, yaw choices, ground z).
    half = 0.5 * math.pi
    m = 0.8
    zones = [
        (np.array([W / 2 - 5.5, m, W / 2 - m, D - m]), (0.0, math.pi), 0.0),
        (np.array([-W / 2 + m, m, -W / 2 + 5.5, D - m]), (0.0, math.pi), 0.0),
        (np.array([-W / 2 + m, D - 6.5, W / 2 - m, D - m]), (half, -half), 0.0),
        (np.array([-W / 2 + m, m, W / 2 - m, plan.y_s - 3.0]), (half, -half), 0.0),
        (np.array([lx0 + 0.3, ly0 + 0.3, lx1 - 0.3, ly1 - 0.3]), (0.0, half, math.pi, -half), 0.12),
        (np.array([4.5, -A - 12.0, W / 2 + wd + 15, -1.5]), (0.0, half, math.pi, -half), 0.0),
        (np.array([-W / 2 - wd - 15, -A - 12.0, -4.5, -1.5]), (0.0, half, math.pi, -half), 0.0),
    ]
    zone_props = {
        "car": (0, 1, 2, 3, 5, 6),
        "bike": (0, 1, 3, 5, 6),
        "tree": (4, 4, 5, 6),
        "bench": (0, 1, 2, 4, 5, 6),
        "bin": (0, 1, 2, 3, 4, 5, 6),
        "sign": (0, 1, 3, 5, 6),
        "planter": (0, 1, 2, 3),
        "ad_column": (0, 1, 3, 5, 6),
        "statue": (4,),
    }

    def place(prop: str, zone: int, variant: int, target: _Placer) -> _Item | None:
        rect, yaws, z = zones[zone]
        return _place_free(
            target,
            rng,
            rect,
            z,
            prop,
            variant,
            0,
            zone,
            yaw_choices=yaws,
            jitter=0.05 if prop in ("car", "bike") else 0.0,
        )

    # Avenue trees in two regular rows (movable objects, the same model repeated).
    items: list[_Item] = []
    row_x = plan.keepout + 2.6
    for y in np.arange(-A + 3.0, -3.0, 8.0):
        for side, zone in ((1.0, 5), (-1.0, 6)):
            origin = np.array([side * row_x, y, 0.0])
            aabb = _aabb(PROPS["tree"].footprint, origin, 0.0)
            if placer.is_free(0, aabb, gap=0.0):
                placer.occupy(0, aabb)
                items.append(_Item("tree", 0, origin, 0.0, int(rng.integers(12)), zone, aabb))

    # Structure along the roads: lamp posts (repeated) and bollards at the avenue.
    offset = plan.keepout + 0.5
    spots = [(plan.xr + offset, y) for y in np.arange(plan.y_s, plan.y_n, 12.0)]
    spots += [(-plan.xr - offset, y) for y in np.arange(plan.y_s, plan.y_n, 12.0)]
    spots += [(x, plan.y_n + offset) for x in np.arange(-plan.xr + 6, plan.xr - 5, 12.0)]
    spots += [(side * offset, y) for side in (1, -1) for y in np.arange(-A + 7.0, -2, 8.0)]
    for x, y in spots:
        origin = np.array([x, y, 0.0])
        aabb = _aabb(PROPS["lamp_post"].footprint, origin, 0.0)
        if placer.is_free(0, aabb, gap=0.05):
            placer.occupy(0, aabb)
            PROPS["lamp_post"].build(b, Frame(origin, 0.0), 0, 0)
    for side in (1, -1):
        for y in np.arange(-A + 1.0, -1.0, 2.5):
            origin = np.array([side * (plan.keepout + 0.2), y, 0.0])
            aabb = _aabb(PROPS["bollard"].footprint, origin, 0.0)
            if placer.is_free(0, aabb, gap=0.05):
                placer.occupy(0, aabb)
                PROPS["bollard"].build(b, Frame(origin, 0.0), 0, 0)

    clutter = ("bench", "bin", "sign", "planter", "bench", "bin", "ad_column", "statue")
    wanted = (
        ["tree"] * cfg.n_trees
        + ["car"] * cfg.n_cars
        + ["bike"] * cfg.n_bikes
        + [clutter[k % len(clutter)] for k in range(cfg.clutter_count)]
    )
    for prop in wanted:
        item = place(prop, int(rng.choice(zone_props[prop])), int(rng.integers(12)), placer)
        if item is not None:
            items.append(item)

    structure = b.build(textures)
    objects = MeshBuilder(names)
    _build_items(objects, items)

    def relocate(item: _Item, target: _Placer) -> _Item | None:
        return place(item.prop, item.region, item.variant, target)

    def add(target: _Placer) -> _Item | None:
        prop = str(rng.choice(["car", "bike", "bin", "car", "sign", "bench"]))
        return place(prop, int(rng.choice(zone_props[prop])), int(rng.integers(12)), target)

    changed_items, changes = _change_items(
        rng, items, placer.copy(), cfg.n_changed_objects, relocate, add
    )
    changed_objects = MeshBuilder(names)
    _build_items(changed_objects, changed_items)
    mesh = _join(structure, objects, textures)
    changed_mesh = _join(structure, changed_objects, textures)
    return World(
        kind="outdoor",
        seed=seed,
        mesh=mesh,
        changed_mesh=changed_mesh,
        route=route,
        route_clearance=float(cfg.route_clearance),
        tls_stations=_tls_stations(route, 30.0, _TLS_HEIGHT_OUTDOOR),
        bounds=_mesh_bounds(mesh, changed_mesh),
        regions=regions,
        floor_heights=[0.0],
        num_objects=len(items),
        num_changes=changes,
    )


# --------------------------------------------------------------------------- entry point


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

    Example:
        >>> world = generate_world("indoor", 0)
        >>> world.route.shape[1]
        3
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
