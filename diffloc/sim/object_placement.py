"""Movable objects of a world: footprints, rejection-sampled placement, the changed scene.

Furniture, clutter and wall panels are placed (in both scene states) without overlaps and
outside a corridor around the route (:class:`_Placer`); the changed scene moves, removes and
adds some of them (:func:`_change_items`); :func:`_scene_meshes` builds both scene states.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from diffloc.io.textured_mesh import TexturedMesh
from diffloc.sim.primitives import PROPS, Frame, MeshBuilder, wall_panel
from diffloc.sim.route import _sample_polyline
from diffloc.sim.textures import POSTERS

# Horizontal gap kept between placed objects (metres).
_OBJECT_GAP = 0.1
# Spacing of route samples used by the placement checks (metres).
_ROUTE_SAMPLE_STEP = 0.05


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


def _build_items(builder: MeshBuilder, items: list[_Item]) -> None:
    """Add the solids of movable objects with ids ``1, 2, ...`` in list order."""
    for k, item in enumerate(items):
        oid = 1 + k
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


def _scene_meshes(
    structure: MeshBuilder,
    textures: list[np.ndarray],
    items: list[_Item],
    changed_items: list[_Item],
) -> tuple[TexturedMesh, TexturedMesh]:
    """The scene as mapped and as changed: the fixed solids joined with each state's objects.

    Args:
        structure: the fixed solids (object id 0).
        textures: one texture per material of ``structure``.
        items: the movable objects of the mapped scene.
        changed_items: the movable objects of the changed scene.

    Returns:
        ``(mesh, changed_mesh)``.
    """
    fixed = structure.build(textures)
    meshes = []
    for state in (items, changed_items):
        objects = MeshBuilder(structure.material_names)
        _build_items(objects, state)
        if objects.num_faces == 0:
            meshes.append(fixed)
        else:
            meshes.append(TexturedMesh.concatenate([fixed, objects.build(textures)]))
    return meshes[0], meshes[1]
