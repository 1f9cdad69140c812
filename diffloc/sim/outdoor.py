"""The outdoor world: a palace courtyard reached by an avenue, built section by section.

:func:`_outdoor_world` draws the plan (:mod:`~diffloc.sim.outdoor_plan`), then the ground, the
palace (main block, wings, corner pavilions, portico), the gate wall, the lawn's centrepiece,
the outbuildings along the avenue, the avenue trees, lamp posts and bollards, the movable
clutter, and the changed scene's moves, removals and additions. Every section draws from the
one generator in this order, so equal seeds give byte-identical worlds.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from diffloc.sim.facades import _facade, _facade_frame, _gable_roof
from diffloc.sim.object_placement import (
    _aabb,
    _change_items,
    _Item,
    _place_free,
    _Placer,
    _scene_meshes,
)
from diffloc.sim.outdoor_layout import OutdoorLayoutConfig, _validate_outdoor
from diffloc.sim.outdoor_plan import _OutdoorPlan
from diffloc.sim.primitives import PROPS, Frame, MeshBuilder, wall_panel
from diffloc.sim.route import _tls_stations
from diffloc.sim.textures import POSTERS, make_materials
from diffloc.sim.world import Region, World, _mesh_bounds

__all__ = ["OUTDOOR_MATERIALS"]

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

# Scanner height above the ground (metres).
_TLS_HEIGHT_OUTDOOR = 1.8
# South and north end (y, metres) of the corner pavilions.
_PAVILION_Y = (-4.0, 12.0)
# The clutter zones (indices into :func:`_clutter_zones`) each kind of prop may stand in.
_ZONE_PROPS = {
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

_Zone = tuple[np.ndarray, tuple[float, ...], float]
"""A clutter zone: (x0, y0, x1, y1) rectangle, yaw choices, ground z."""
_Opening = Callable[[float, int], str]
"""``opening(x_local, storey_index) -> "window" | "door" | "none"`` of a facade."""


def _outdoor_world(seed: int, cfg: OutdoorLayoutConfig) -> World:
    """The palace courtyard of ``seed`` (see :func:`~diffloc.sim.scene.generate_world`)."""
    _validate_outdoor(cfg)
    rng = np.random.default_rng(seed)
    names, textures = make_materials(rng, int(cfg.texture_size), OUTDOOR_MATERIALS)
    plan = _OutdoorPlan(cfg, rng)
    site = _Site(MeshBuilder(names), plan, _Placer(plan.route, plan.keepout, [0.0]))
    _ground(site.b, plan)
    doors_every = int(rng.integers(3, 6))
    regular = functools.partial(_regular_opening, spacing=plan.spacing, period=doors_every)
    _build_palace(site, regular, rng)
    _build_main_front(site, doors_every)
    _build_gate(site)
    _build_centrepiece(site, rng)
    _build_outbuildings(site, regular, rng)
    zones = _clutter_zones(plan)
    items = _plant_avenue_trees(site, rng)
    _build_street_furniture(site)
    items += _place_clutter(site, zones, rng)
    changed_items, changes = _change_clutter(site, zones, items, rng)
    mesh, changed_mesh = _scene_meshes(site.b, textures, items, changed_items)
    return World(
        kind="outdoor",
        seed=seed,
        mesh=mesh,
        changed_mesh=changed_mesh,
        route=plan.route,
        route_clearance=float(cfg.route_clearance),
        tls_stations=_tls_stations(plan.route, 30.0, _TLS_HEIGHT_OUTDOOR),
        bounds=_mesh_bounds(mesh, changed_mesh),
        regions=site.regions,
        floor_heights=[0.0],
        num_objects=len(items),
        num_changes=changes,
    )


@dataclass
class _Site:
    """What the sections build into: the fixed solids, the placement state and the regions
    (the courtyard and the avenue first, then buildings and facades as they are built)."""

    b: MeshBuilder
    plan: _OutdoorPlan
    placer: _Placer
    regions: list[Region] = field(init=False)

    def __post_init__(self) -> None:
        plan = self.plan
        W, D, A = plan.W, plan.D, plan.A
        self.regions = [
            Region(
                "courtyard",
                "courtyard",
                0,
                np.array([-W / 2, 0.0, 0.0]),
                np.array([W / 2, D, plan.main_height]),
            ),
            Region("avenue", "avenue", 0, np.array([-4.0, -A, 0.0]), np.array([4.0, 0.0, 10.0])),
        ]

    def building(
        self, name: str, rect: np.ndarray, height: float, material: str, roof: str
    ) -> None:
        """A block over ``rect`` (x0, y0, x1, y1) with a ``"gable"``, ``"hip"`` or no roof."""
        b = self.b
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
        self.placer.occupy(0, np.asarray(rect, float))
        self.regions.append(
            Region(
                name,
                "building",
                0,
                np.array([rect[0], rect[1], 0.0]),
                np.array([rect[2], rect[3], height]),
            )
        )

    def facade(
        self,
        name: str,
        start: tuple[float, float],
        direction: tuple[float, float],
        length: float,
        height: float,
        trim: str,
        opening: _Opening,
    ) -> None:
        """The ornaments of a building face (see :func:`_facade`) and its region."""
        start_a, direction_a = np.asarray(start, float), np.asarray(direction, float)
        frame = _facade_frame(start_a, direction_a)
        plan = self.plan
        _facade(self.b, frame, length, height, plan.cfg.storey_height, plan.spacing, trim, opening)
        end = start_a + length * direction_a
        normal = np.array([-direction_a[1], direction_a[0]])
        lo = np.minimum(start_a, end + 0.6 * normal)
        hi = np.maximum(start_a, end + 0.6 * normal)
        self.regions.append(
            Region(name, "facade", 0, np.array([*lo, 0.0]), np.array([*hi, height]))
        )


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


# --------------------------------------------------------------------------- buildings


def _regular_opening(x: float, f: int, spacing: float, period: int) -> str:
    """A door on every ``period``-th window axis of the ground floor, windows elsewhere."""
    column = int(round((x - spacing / 2) / spacing))
    return "door" if f == 0 and column % period == period // 2 else "window"


def _main_opening(x: float, f: int, width: float, spacing: float, period: int) -> str:
    """The main facade (``width`` long): the entrance and one window above it on the middle
    axis, no upper windows behind the portico, doors every ``period + 2`` axes elsewhere."""
    world_x = width / 2 - x
    if abs(world_x) < spacing / 2:
        return "door" if f == 0 else ("window" if f == 1 else "none")
    if abs(world_x) < 10.5 and f >= 2:
        return "none"
    return _regular_opening(x, f, spacing, period + 2)


def _build_palace(site: _Site, regular: _Opening, rng: np.random.Generator) -> None:
    """The main block (north) and, east and west, a wing and its corner pavilion."""
    plan = site.plan
    W, D, wd = plan.W, plan.D, plan.wd
    site.building(
        "main_block",
        np.array([-W / 2 - wd, D, W / 2 + wd, D + wd]),
        plan.main_height,
        "facade_stone",
        "gable",
    )
    for side, sign in (("east", 1.0), ("west", -1.0)):
        _build_wing(site, side, sign, regular, rng)


def _build_wing(
    site: _Site, side: str, sign: float, regular: _Opening, rng: np.random.Generator
) -> None:
    """A wing with its courtyard facade and its corner pavilion: a banner towards the
    courtyard, windows and a door towards the avenue."""
    plan = site.plan
    W, D, wd, pav, spacing = plan.W, plan.D, plan.wd, plan.pavilion_out, plan.spacing
    wing_h, pavilion_h = plan.wing_height, plan.main_height + 2.0
    storey = plan.cfg.storey_height
    x_in, x_out = sign * W / 2, sign * (W / 2 + wd)
    site.building(
        f"{side}_wing",
        np.array([min(x_in, x_out), _PAVILION_Y[1], max(x_in, x_out), D]),
        wing_h,
        "facade_stone",
        "gable",
    )
    x_pav_in, x_pav_out = sign * (W / 2 - pav), sign * (W / 2 + wd + pav)
    site.building(
        f"{side}_pavilion",
        np.array(
            [min(x_pav_in, x_pav_out), _PAVILION_Y[0], max(x_pav_in, x_pav_out), _PAVILION_Y[1]]
        ),
        pavilion_h,
        "facade_stone",
        "hip",
    )
    length = D - _PAVILION_Y[1]
    if sign > 0:
        site.facade(
            f"{side}_wing_facade",
            (x_in, _PAVILION_Y[1]),
            (0.0, 1.0),
            length,
            wing_h,
            "stone_trim",
            regular,
        )
    else:
        site.facade(
            f"{side}_wing_facade", (x_in, D), (0.0, -1.0), length, wing_h, "stone_trim", regular
        )
    pav_len = _PAVILION_Y[1] - _PAVILION_Y[0]
    banner = POSTERS[int(rng.integers(len(POSTERS)))]
    if sign > 0:
        inner = _facade_frame(np.array([x_pav_in, _PAVILION_Y[0]]), np.array([0.0, 1.0]))
        south = _facade_frame(np.array([x_pav_out, _PAVILION_Y[0]]), np.array([-1.0, 0.0]))
    else:
        inner = _facade_frame(np.array([x_pav_in, _PAVILION_Y[1]]), np.array([0.0, -1.0]))
        south = _facade_frame(np.array([x_pav_in, _PAVILION_Y[0]]), np.array([-1.0, 0.0]))
    banner_frame = Frame(inner.point((pav_len / 2, 0.0, 0.0)), inner.yaw)
    wall_panel(
        site.b,
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
        site.b,
        inner,
        pav_len,
        pavilion_h,
        storey,
        spacing,
        "stone_trim",
        lambda x, f, n=pav_len: "window" if f >= 3 and abs(x - n / 2) > 2.0 else "none",
    )
    width = wd + 2 * pav
    _facade(
        site.b,
        south,
        width,
        pavilion_h,
        storey,
        spacing,
        "stone_trim",
        lambda x, f, n=width: "door" if f == 0 and abs(x - n / 2) < spacing / 2 else "window",
    )
    site.regions.append(
        Region(
            f"{side}_pavilion_facade",
            "facade",
            0,
            np.array([min(x_pav_in, x_pav_out), _PAVILION_Y[0] - 0.6, 0.0]),
            np.array([max(x_pav_in, x_pav_out), _PAVILION_Y[0], pavilion_h]),
        )
    )


def _build_main_front(site: _Site, doors_every: int) -> None:
    """The main facade and the portico: platform, step, columns, entablature and pediment."""
    plan = site.plan
    W, D, b = plan.W, plan.D, site.b
    main_opening = functools.partial(
        _main_opening, width=W, spacing=plan.spacing, period=doors_every
    )
    site.facade(
        "main_facade", (W / 2, D), (-1.0, 0.0), W, plan.main_height, "stone_trim", main_opening
    )
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
    site.placer.occupy(0, np.array([-10.0, D - plan.portico, 10.0, D]))


def _build_gate(site: _Site) -> None:
    """The gate wall closing the courtyard to the south, with piers and finials."""
    plan, b = site.plan, site.b
    for sign in (1.0, -1.0):
        x_pier = sign * plan.gate_half
        x_far = sign * (plan.W / 2 - plan.pavilion_out)
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
        site.placer.occupy(0, np.array([min(pier[0], lo), -0.9, max(pier[2], hi), 0.3]))


def _build_centrepiece(site: _Site, rng: np.random.Generator) -> None:
    """The centrepiece of the lawn: a fountain (60 %) or an obelisk."""
    b = site.b
    _, ly0, _, ly1 = site.plan.lawn
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
    site.placer.occupy(0, np.array([-3.8, fc[1] - 3.8, 3.8, fc[1] + 3.8]))


def _build_outbuildings(site: _Site, regular: _Opening, rng: np.random.Generator) -> None:
    """Outbuildings along the avenue (the asymmetric part), each where 30 random tries find
    room far enough from the route."""
    plan = site.plan
    for k in range(plan.cfg.n_outbuildings):
        for _ in range(30):
            size = rng.uniform([12.0, 8.0], [20.0, 12.0])
            east = rng.random() < 0.5
            x0 = rng.uniform(plan.keepout + 6.0, plan.W / 2 + plan.wd)
            y0 = rng.uniform(-plan.A - 8.0, -8.0 - size[1])
            rect = np.array([x0, y0, x0 + size[0], y0 + size[1]])
            if not east:
                rect = np.array([-rect[2], rect[1], -rect[0], rect[3]])
            if (
                site.placer.is_free(0, rect, gap=3.0)
                and site.placer.route_distance(0, rect) >= plan.keepout + 5.0
            ):
                height = float(rng.uniform(6.0, 10.0))
                material = str(rng.choice(["facade_brick", "facade_render"]))
                site.building(f"outbuilding{k}", rect, height, material, "gable")
                if east:
                    start, direction = (rect[0], rect[1]), (0.0, 1.0)
                else:
                    start, direction = (rect[2], rect[3]), (0.0, -1.0)
                site.facade(
                    f"outbuilding{k}_facade",
                    start,
                    direction,
                    size[1],
                    height,
                    "stone_trim",
                    regular,
                )
                break


def _build_street_furniture(site: _Site) -> None:
    """Lamp posts along the roads and bollards at the avenue (fixed, the same models)."""
    plan, placer = site.plan, site.placer
    A = plan.A
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
            PROPS["lamp_post"].build(site.b, Frame(origin, 0.0), 0, 0)
    for side in (1, -1):
        for y in np.arange(-A + 1.0, -1.0, 2.5):
            origin = np.array([side * (plan.keepout + 0.2), y, 0.0])
            aabb = _aabb(PROPS["bollard"].footprint, origin, 0.0)
            if placer.is_free(0, aabb, gap=0.05):
                placer.occupy(0, aabb)
                PROPS["bollard"].build(site.b, Frame(origin, 0.0), 0, 0)


# --------------------------------------------------------------------------- movable objects


def _clutter_zones(plan: _OutdoorPlan) -> list[_Zone]:
    """Where movable clutter stands: along the wings and the main block, by the gate, on the
    lawn and on either side of the avenue (the zones of :data:`_ZONE_PROPS`)."""
    W, D, wd, A = plan.W, plan.D, plan.wd, plan.A
    lx0, ly0, lx1, ly1 = plan.lawn
    half = 0.5 * math.pi
    m = 0.8
    return [
        (np.array([W / 2 - 5.5, m, W / 2 - m, D - m]), (0.0, math.pi), 0.0),
        (np.array([-W / 2 + m, m, -W / 2 + 5.5, D - m]), (0.0, math.pi), 0.0),
        (np.array([-W / 2 + m, D - 6.5, W / 2 - m, D - m]), (half, -half), 0.0),
        (np.array([-W / 2 + m, m, W / 2 - m, plan.y_s - 3.0]), (half, -half), 0.0),
        (np.array([lx0 + 0.3, ly0 + 0.3, lx1 - 0.3, ly1 - 0.3]), (0.0, half, math.pi, -half), 0.12),
        (np.array([4.5, -A - 12.0, W / 2 + wd + 15, -1.5]), (0.0, half, math.pi, -half), 0.0),
        (np.array([-W / 2 - wd - 15, -A - 12.0, -4.5, -1.5]), (0.0, half, math.pi, -half), 0.0),
    ]


def _place_in_zone(
    target: _Placer,
    rng: np.random.Generator,
    zones: list[_Zone],
    prop: str,
    zone: int,
    variant: int,
) -> _Item | None:
    """Try to stand a prop anywhere in a clutter zone, with one of the zone's yaws."""
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


def _plant_avenue_trees(site: _Site, rng: np.random.Generator) -> list[_Item]:
    """Avenue trees in two regular rows (movable objects, the same model repeated)."""
    plan, placer = site.plan, site.placer
    items: list[_Item] = []
    row_x = plan.keepout + 2.6
    for y in np.arange(-plan.A + 3.0, -3.0, 8.0):
        for side, zone in ((1.0, 5), (-1.0, 6)):
            origin = np.array([side * row_x, y, 0.0])
            aabb = _aabb(PROPS["tree"].footprint, origin, 0.0)
            if placer.is_free(0, aabb, gap=0.0):
                placer.occupy(0, aabb)
                items.append(_Item("tree", 0, origin, 0.0, int(rng.integers(12)), zone, aabb))
    return items


def _place_clutter(site: _Site, zones: list[_Zone], rng: np.random.Generator) -> list[_Item]:
    """Trees, cars, bikes and other clutter, each in a random zone allowed for its kind."""
    cfg = site.plan.cfg
    clutter = ("bench", "bin", "sign", "planter", "bench", "bin", "ad_column", "statue")
    wanted = (
        ["tree"] * cfg.n_trees
        + ["car"] * cfg.n_cars
        + ["bike"] * cfg.n_bikes
        + [clutter[k % len(clutter)] for k in range(cfg.clutter_count)]
    )
    items: list[_Item] = []
    for prop in wanted:
        zone = int(rng.choice(_ZONE_PROPS[prop]))
        item = _place_in_zone(site.placer, rng, zones, prop, zone, int(rng.integers(12)))
        if item is not None:
            items.append(item)
    return items


def _change_clutter(
    site: _Site, zones: list[_Zone], items: list[_Item], rng: np.random.Generator
) -> tuple[list[_Item], int]:
    """The changed scene's objects: some moved within their zone, removed, or added (cars,
    bikes, bins, signs, benches); and the number of changes."""

    def relocate(item: _Item, target: _Placer) -> _Item | None:
        return _place_in_zone(target, rng, zones, item.prop, item.region, item.variant)

    def add(target: _Placer) -> _Item | None:
        prop = str(rng.choice(["car", "bike", "bin", "car", "sign", "bench"]))
        zone = int(rng.choice(_ZONE_PROPS[prop]))
        return _place_in_zone(target, rng, zones, prop, zone, int(rng.integers(12)))

    n_changes = site.plan.cfg.n_changed_objects
    return _change_items(rng, items, site.placer.copy(), n_changes, relocate, add)
