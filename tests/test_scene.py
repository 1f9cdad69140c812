"""Procedural worlds: determinism, closed outward solids, route clearance, layout counts, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from diffloc.render.raycast import MeshRaycaster
from diffloc.sim.indoor import INDOOR_MATERIALS
from diffloc.sim.indoor_layout import IndoorLayoutConfig
from diffloc.sim.outdoor import OUTDOOR_MATERIALS
from diffloc.sim.outdoor_layout import OutdoorLayoutConfig
from diffloc.sim.primitives import PROPS, Frame, MeshBuilder
from diffloc.sim.scene import generate_world
from diffloc.sim.world import World

KINDS = ("indoor", "outdoor")


@pytest.fixture(scope="module", params=KINDS)
def world(request) -> World:
    return generate_world(request.param, 0)


def dense_route(route: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (M, 3) along the route polyline at most ``step`` apart, and whether each lies on
    level floor (M,): on a level segment and more than 1 m from any stair (sloped segment)."""
    points, level = [], []
    for a, b in zip(route[:-1], route[1:], strict=True):
        count = max(1, math.ceil(np.linalg.norm(b - a) / step))
        t = np.arange(count + 1)[:, None] / count
        points.append(a + t * (b - a))
        level.append(np.full(count + 1, abs(a[2] - b[2]) < 1e-9))
    points, level = np.concatenate(points), np.concatenate(level)
    stairs = points[~level]
    if len(stairs):
        near = np.linalg.norm(points[:, None, :2] - stairs[None, :, :2], axis=2).min(axis=1) < 1.0
        level &= ~near
    return points, level


def cast(caster: MeshRaycaster, origins: np.ndarray, directions: np.ndarray):
    return caster.cast(
        torch.as_tensor(origins, dtype=torch.float32),
        torch.as_tensor(directions, dtype=torch.float32),
    )


def horizontal_directions(count: int) -> np.ndarray:
    angles = 2 * np.pi * (np.arange(count) + 0.5) / count
    return np.stack([np.cos(angles), np.sin(angles), np.zeros(count)], 1)


def sphere_directions(count: int) -> np.ndarray:
    k = np.arange(count) + 0.5
    z = 1 - 2 * k / count
    azimuth = k * np.pi * (3 - np.sqrt(5))
    r = np.sqrt(1 - z**2)
    return np.stack([r * np.cos(azimuth), r * np.sin(azimuth), z], 1)


# --------------------------------------------------------------------------- determinism


@pytest.mark.parametrize("kind", KINDS)
def test_same_seed_gives_identical_arrays_and_other_seed_differs(kind):
    a, b = generate_world(kind, 3), generate_world(kind, 3)
    for name in ("vertices", "triangles", "corner_uvs", "material_ids", "object_ids"):
        assert np.array_equal(getattr(a.mesh, name), getattr(b.mesh, name)), name
        assert np.array_equal(getattr(a.changed_mesh, name), getattr(b.changed_mesh, name)), name
    for ta, tb in zip(a.mesh.textures, b.mesh.textures, strict=True):
        assert np.array_equal(ta, tb)
    assert np.array_equal(a.route, b.route) and np.array_equal(a.tls_stations, b.tls_stations)
    assert np.array_equal(a.bounds, b.bounds)
    c = generate_world(kind, 4)
    same_shape = c.mesh.vertices.shape == a.mesh.vertices.shape
    assert not (same_shape and np.array_equal(c.mesh.vertices, a.mesh.vertices))
    assert not np.array_equal(c.mesh.textures[0], a.mesh.textures[0])


def test_generation_does_not_touch_the_global_rng():
    before = np.random.get_state()  # noqa: NPY002 - checking the legacy global state on purpose
    generate_world("indoor", 1)
    after = np.random.get_state()  # noqa: NPY002
    assert all(np.array_equal(x, y) for x, y in zip(before, after, strict=True))


# --------------------------------------------------------------------------- geometry


def test_mesh_arrays_and_sizes(world):
    for mesh in (world.mesh, world.changed_mesh):
        assert mesh.vertices.dtype == np.float32 and mesh.triangles.dtype == np.int32
        assert np.isfinite(mesh.corner_uvs).all()
        assert mesh.material_names == list(
            INDOOR_MATERIALS if world.kind == "indoor" else OUTDOOR_MATERIALS
        )
        limit = 50_000 if world.kind == "indoor" else 100_000
        assert 1_000 < mesh.num_faces < limit
        corners = mesh.vertices[mesh.triangles].astype(np.float64)
        area = 0.5 * np.linalg.norm(
            np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1
        )
        assert area.min() > 1e-7, "degenerate triangles"
    assert world.route.dtype == np.float64 and world.route.shape[1] == 3
    assert world.bounds.shape == (2, 3) and (world.bounds[1] > world.bounds[0]).all()
    assert world.tls_stations.shape[1] == 3 and len(world.tls_stations) >= 4
    inside = (world.tls_stations > world.bounds[0]) & (world.tls_stations < world.bounds[1])
    assert inside.all()


def test_every_solid_is_closed_consistently_wound_and_outward(world):
    """Directed edges pair up with their reverses, and each connected solid has positive volume."""
    for mesh in (world.mesh, world.changed_mesh):
        tri = mesh.triangles.astype(np.int64)
        edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
        forward = edges[:, 0] * len(mesh.vertices) + edges[:, 1]
        backward = edges[:, 1] * len(mesh.vertices) + edges[:, 0]
        f_keys, f_counts = np.unique(forward, return_counts=True)
        b_keys, b_counts = np.unique(backward, return_counts=True)
        assert np.array_equal(f_keys, b_keys) and np.array_equal(f_counts, b_counts)
        assert f_counts.max() == 1, (
            "an edge is used twice in one direction (non-manifold or flipped)"
        )
        # Solids = connected components of the vertex graph; each must enclose positive volume.
        graph = coo_matrix(
            (np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(len(mesh.vertices),) * 2
        )
        _, labels = connected_components(graph, directed=False)
        corners = mesh.vertices[mesh.triangles].astype(np.float64)
        signed = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])) / 6.0
        volume = np.bincount(labels[mesh.triangles[:, 0]], weights=signed)
        assert volume.min() > 0.0, "a solid is inside out"


def test_primitives_are_watertight_with_trimesh():
    trimesh = pytest.importorskip("trimesh")
    names = sorted({"concrete", "stone_trim", *INDOOR_MATERIALS, *OUTDOOR_MATERIALS})
    for prop in PROPS.values():
        builder = MeshBuilder(names)
        prop.build(builder, Frame(np.array([1.0, 2.0, 0.0]), 0.7), 1, 1)
        mesh = builder.build([np.zeros((4, 4, 3), np.float32)] * len(names))
        tm = trimesh.Trimesh(mesh.vertices, mesh.triangles, process=False)
        for body in tm.split(only_watertight=False):
            assert body.is_watertight and body.is_winding_consistent and body.volume > 0
    builder = MeshBuilder(names)
    builder.add_cylinder([0, 0, 0], [1, 1, 0.3], 0.5, 2.0, "concrete", 0, segments=7, top_scale=0.4)
    builder.add_prism(
        np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, 1.5]]), [0, 0, 0], np.eye(3), 3.0, "concrete", 0
    )
    mesh = builder.build([np.zeros((4, 4, 3), np.float32)] * len(names))
    tm = trimesh.Trimesh(mesh.vertices, mesh.triangles, process=False)
    bodies = tm.split(only_watertight=False)
    assert len(bodies) == 2 and all(b.is_watertight and b.volume > 0 for b in bodies)


def test_rays_from_the_route_hit_front_faces(world):
    for mesh in (world.mesh, world.changed_mesh):
        caster = MeshRaycaster(mesh)
        points, _ = dense_route(world.route, 1.0)
        directions = sphere_directions(64)
        origins = np.concatenate([points + [0, 0, h] for h in (0.5, 1.0, 1.6, 2.0)])
        o = np.repeat(origins, len(directions), axis=0)
        d = np.tile(directions, (len(origins), 1))
        hits = cast(caster, o, d)
        hit = hits.hit.numpy()
        facing = (hits.normals.numpy() * d).sum(1)
        assert hit.mean() > (0.99 if world.kind == "indoor" else 0.4)
        assert (facing[hit] < 0).mean() >= 0.999


# --------------------------------------------------------------------------- route


def test_route_keeps_its_clearance_and_head_room(world):
    step = 0.1 if world.kind == "indoor" else 0.5
    points, level = dense_route(world.route, step)
    directions = horizontal_directions(48)
    for mesh in (world.mesh, world.changed_mesh):
        caster = MeshRaycaster(mesh)
        for height in (0.1, 0.5, 1.0, 1.5, 2.0):
            base = points if height >= 0.5 else points[level]
            origins = np.repeat(base + [0, 0, height], len(directions), axis=0)
            hits = cast(caster, origins, np.tile(directions, (len(base), 1)))
            nearest = hits.distance.numpy().reshape(len(base), -1).min(axis=1)
            worst = int(np.argmin(nearest))
            assert nearest[worst] >= world.route_clearance - 1e-3, (
                f"{mesh is world.mesh=} height {height}: {nearest[worst]:.3f} m at {base[worst]}"
            )
        up = cast(caster, points + [0, 0, 0.05], np.tile([0.0, 0.0, 1.0], (len(points), 1)))
        assert (up.distance.numpy() + 0.05).min() >= 2.2
        down = cast(caster, points + [0, 0, 0.5], np.tile([0.0, 0.0, -1.0], (len(points), 1)))
        gap = down.distance.numpy() - 0.5  # how far the floor lies below the route
        flat = np.abs(np.diff(world.route[:, 2])).max() < 1e-9
        assert np.abs(gap[level if not flat else slice(None)]).max() < 0.01
        assert gap.min() > -0.01 and gap.max() < 0.25


def test_route_length_and_layout_counts(world):
    route = world.route
    assert np.linalg.norm(np.diff(route, axis=0), axis=1).min() > 0.5
    points, _ = dense_route(route, 0.2)
    if world.kind == "indoor":
        assert world.route_length >= 40.0
        assert world.count("room") >= 6 and world.count("corridor") >= 2
        assert set(np.round(route[:, 2], 6)) >= {0.0, world.floor_heights[1]}
        rooms = [r for r in world.regions if r.kind == "room"]
        visited = [r.contains(points + [0, 0, 0.1]).any() for r in rooms]
        assert np.mean(visited) >= 0.75
        for floor in (0, 1):
            assert any(v for v, r in zip(visited, rooms, strict=True) if r.floor == floor)
        slope = np.abs(np.diff(route[:, 2])) / np.linalg.norm(np.diff(route[:, :2], axis=0), axis=1)
        assert math.degrees(math.atan(slope.max())) <= 35.0
    else:
        assert world.route_length >= 150.0
        assert world.count("facade") >= 5 and world.count("building") >= 5
        lo, hi = world.bounds
        assert (hi - lo)[:2].min() >= 60.0
    metadata = world.metadata()
    assert metadata["route_length_m"] == pytest.approx(world.route_length, abs=1e-3)
    assert metadata["regions"]["room" if world.kind == "indoor" else "facade"] >= 5


def test_changed_scene_differs_only_in_movable_objects(world):
    a, b = world.mesh, world.changed_mesh
    assert world.num_changes >= 3
    assert a.material_names == b.material_names
    assert a.num_faces != b.num_faces or not np.array_equal(a.vertices, b.vertices)
    fixed_a, fixed_b = a.select_faces(a.object_ids == 0), b.select_faces(b.object_ids == 0)
    assert np.array_equal(fixed_a.vertices, fixed_b.vertices)
    assert np.array_equal(fixed_a.triangles, fixed_b.triangles)
    assert len(np.unique(a.object_ids[a.object_ids > 0])) == world.num_objects >= 10


def test_tls_stations_are_in_free_space(world):
    caster = MeshRaycaster(world.mesh)
    directions = sphere_directions(64)
    hits = cast(
        caster,
        np.repeat(world.tls_stations, 64, axis=0),
        np.tile(directions, (len(world.tls_stations), 1)),
    )
    facing = (hits.normals.numpy() * np.tile(directions, (len(world.tls_stations), 1))).sum(1)
    assert (facing[hits.hit.numpy()] < 0).all()
    assert hits.distance.numpy().min() > 0.3


# --------------------------------------------------------------------------- errors


def test_unknown_kind_lists_the_valid_kinds():
    with pytest.raises(ValueError, match="indoor.*outdoor"):
        generate_world("moon_base", 0)


@pytest.mark.parametrize("seed", [1.5, "0", None, True, -1])
def test_bad_seed_is_refused(seed):
    with pytest.raises(ValueError, match="seed"):
        generate_world("indoor", seed)


def test_wrong_or_invalid_layout_is_refused():
    with pytest.raises(ValueError, match="IndoorLayoutConfig"):
        generate_world("indoor", 0, OutdoorLayoutConfig())
    with pytest.raises(ValueError, match="door_width"):
        generate_world("indoor", 0, IndoorLayoutConfig(door_width=1.0))
    with pytest.raises(ValueError, match="rooms_per_floor"):
        generate_world("indoor", 0, IndoorLayoutConfig(rooms_per_floor=1))
    with pytest.raises(ValueError, match="texture_size"):
        generate_world("outdoor", 0, OutdoorLayoutConfig(texture_size=8))
    with pytest.raises(ValueError, match="facade_setback"):
        generate_world("outdoor", 0, OutdoorLayoutConfig(facade_setback=3.0))


def test_layout_configs_are_structured_config_compatible():
    omegaconf = pytest.importorskip("omegaconf")
    for schema in (IndoorLayoutConfig, OutdoorLayoutConfig):
        cfg = omegaconf.OmegaConf.structured(schema)
        assert omegaconf.OmegaConf.to_object(cfg) == schema()


@pytest.mark.parametrize("rooms", [2, 4])
def test_other_room_counts_still_give_a_clear_route(rooms):
    world = generate_world("indoor", 5, IndoorLayoutConfig(rooms_per_floor=rooms, texture_size=32))
    assert world.count("room") == 2 * (rooms + 1)
    points, _ = dense_route(world.route, 0.2)
    caster = MeshRaycaster(world.changed_mesh)
    directions = horizontal_directions(24)
    origins = np.repeat(points + [0, 0, 1.0], len(directions), axis=0)
    hits = cast(caster, origins, np.tile(directions, (len(points), 1)))
    assert hits.distance.numpy().min() >= world.route_clearance - 1e-3
