"""Tests of diffloc.sim.lidar: spinning lidar, terrestrial scanner and map accumulation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from diffloc.geometry.se3 import se3_exp
from diffloc.io.textured_mesh import TexturedMesh
from diffloc.render.raycast import MeshRaycaster
from diffloc.sim.lidar import (
    SpinningLidarConfig,
    TerrestrialScannerConfig,
    accumulate_map,
    scanner_directions,
    simulate_station_scan,
    simulate_sweep,
    spinning_lidar_directions,
    voxel_downsample,
)

ROOM_MIN = np.array([0.0, 0.0, 0.0])
ROOM_MAX = np.array([6.0, 4.0, 3.0])


def box_mesh(low: np.ndarray, high: np.ndarray, inward: bool = True) -> TexturedMesh:
    """A closed axis-aligned box of 12 triangles; normals face inside if ``inward``."""
    corners = np.array(
        [[high[i] if (k >> i) & 1 else low[i] for i in range(3)] for k in range(8)],
        dtype=np.float32,
    )
    # Corner k has x from bit 0, y from bit 1, z from bit 2; faces are CCW seen from outside.
    quads = [
        (0, 2, 3, 1),  # z = low
        (4, 5, 7, 6),  # z = high
        (0, 1, 5, 4),  # y = low
        (2, 6, 7, 3),  # y = high
        (0, 4, 6, 2),  # x = low
        (1, 3, 7, 5),  # x = high
    ]
    triangles = np.array([[a, b, c] for a, b, c, d in quads] + [[a, c, d] for a, b, c, d in quads])
    if inward:
        triangles = triangles[:, ::-1]
    faces = len(triangles)
    return TexturedMesh(
        vertices=corners,
        triangles=triangles.astype(np.int32),
        corner_uvs=np.zeros((faces, 3, 2), dtype=np.float32),
        material_ids=np.zeros(faces, dtype=np.int32),
        object_ids=np.zeros(faces, dtype=np.int32),
        textures=[np.full((4, 4, 3), 0.5, dtype=np.float32)],
        material_names=["wall"],
    )


@pytest.fixture(scope="module")
def room() -> MeshRaycaster:
    return MeshRaycaster(box_mesh(ROOM_MIN, ROOM_MAX))


def box_exit_distance(origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Analytic distance (R,) from an origin inside the room to its walls along directions."""
    with np.errstate(divide="ignore"):
        bound = np.where(directions > 0, ROOM_MAX, ROOM_MIN)
        t = (bound - origin) / directions
    t = np.where(np.abs(directions) > 1e-12, t, np.inf)
    return t.min(axis=1)


def lidar_pose() -> np.ndarray:
    """A tilted, yawed lidar pose inside the room (float64 numpy)."""
    xi = torch.tensor([2.5, 1.7, 1.2, 0.05, -0.08, 0.5], dtype=torch.float64)
    T = se3_exp(xi).numpy()
    T[:3, 3] = [2.5, 1.7, 1.2]
    return T


def expected_ranges(T_wl: np.ndarray, directions_lidar: np.ndarray) -> np.ndarray:
    return box_exit_distance(T_wl[:3, 3], directions_lidar @ T_wl[:3, :3].T)


def test_configs_are_structured_configs():
    lidar = OmegaConf.structured(SpinningLidarConfig)
    tls = OmegaConf.structured(TerrestrialScannerConfig)
    assert lidar.beams == 16 and lidar.azimuth_steps == 1024 and tls.elevation_steps == 240


def test_spinning_lidar_directions_known_answers():
    cfg = SpinningLidarConfig(beams=16, vfov_min_deg=-15.0, vfov_max_deg=15.0, azimuth_steps=1024)
    d = spinning_lidar_directions(cfg)
    assert d.shape == (16 * 1024, 3) and d.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    elevation = np.degrees(np.arcsin(d[:, 2]))
    np.testing.assert_allclose([elevation.min(), elevation.max()], [-15.0, 15.0], atol=1e-9)
    np.testing.assert_allclose(elevation[:16], np.linspace(-15.0, 15.0, 16), atol=1e-9)
    assert len(np.unique(np.round(elevation, 6))) == 16
    # Ray a * beams + b: azimuth 2 pi a / steps, starting along +x and turning towards +y.
    azimuth = np.arctan2(d[::16, 1], d[::16, 0]) % (2 * np.pi)
    np.testing.assert_allclose(azimuth, 2 * np.pi * np.arange(1024) / 1024, atol=1e-9)
    el, az = math.radians(-15.0 + 7 * 2.0), 2 * math.pi * 8 / 1024  # beam 7 at azimuth step 8
    expected = [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]
    np.testing.assert_allclose(d[8 * 16 + 7], expected, atol=1e-12)
    assert d[256 * 16, 1] > 0.9  # a quarter turn later the beams point to +y (left)
    single = spinning_lidar_directions(SpinningLidarConfig(beams=1, azimuth_steps=4))
    np.testing.assert_allclose(single, [[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], atol=1e-12)


def test_scanner_directions_known_answers():
    cfg = TerrestrialScannerConfig(elevation_steps=30, azimuth_steps=60)
    d = scanner_directions(cfg)
    assert d.shape == (1800, 3)
    elevation = np.degrees(np.arcsin(np.clip(d[:, 2], -1, 1)))
    np.testing.assert_allclose([elevation.min(), elevation.max()], [-60.0, 88.0], atol=1e-9)


def test_sweep_ranges_are_exact_without_noise(room):
    cfg = SpinningLidarConfig(range_noise_std_m=0.0, min_range_m=0.1, max_range_m=100.0)
    T_wl = lidar_pose()
    points = simulate_sweep(room, T_wl, cfg, np.random.default_rng(0))
    assert points.dtype == np.float32 and points.shape == (16 * 1024, 3)
    d = spinning_lidar_directions(cfg)
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), expected_ranges(T_wl, d), atol=1e-4)
    # Points are in the lidar frame along their rays; in the world frame they lie on the walls.
    world = points.astype(np.float64) @ T_wl[:3, :3].T + T_wl[:3, 3]
    on_wall = np.minimum(np.abs(world - ROOM_MIN), np.abs(world - ROOM_MAX)).min(axis=1)
    assert on_wall.max() < 1e-4
    # Torch poses work too.
    again = simulate_sweep(room, torch.from_numpy(T_wl), cfg, np.random.default_rng(0))
    np.testing.assert_array_equal(points, again)


def test_sweep_range_noise_is_gaussian_with_the_configured_sigma(room):
    sigma = 0.01
    cfg = SpinningLidarConfig(range_noise_std_m=sigma, min_range_m=0.1, max_range_m=100.0)
    T_wl = lidar_pose()
    points = simulate_sweep(room, T_wl, cfg, np.random.default_rng(3))
    assert len(points) == 16 * 1024
    error = np.linalg.norm(points, axis=1) - expected_ranges(T_wl, spinning_lidar_directions(cfg))
    assert np.abs(error).max() < 5 * sigma
    assert np.mean(np.abs(error) < 4 * sigma) > 0.999
    assert abs(error.std() - sigma) < 0.1 * sigma and abs(error.mean()) < 0.05 * sigma


def test_sweep_drops_returns_outside_the_range_limits(room):
    cfg = SpinningLidarConfig(range_noise_std_m=0.0, min_range_m=2.0, max_range_m=3.0)
    T_wl = lidar_pose()
    points = simulate_sweep(room, T_wl, cfg, np.random.default_rng(0))
    ranges = np.linalg.norm(points, axis=1)
    assert ranges.min() >= 2.0 - 1e-5 and ranges.max() <= 3.0 + 1e-5
    truth = expected_ranges(T_wl, spinning_lidar_directions(cfg))
    inside = (truth >= 2.0) & (truth <= 3.0)
    assert 0 < len(points) < len(truth)
    assert abs(len(points) - inside.sum()) <= 3  # rays within float error of a limit


def test_sweep_in_open_space_and_dropout(room):
    cfg = SpinningLidarConfig(range_noise_std_m=0.0, dropout=0.5, max_range_m=100.0)
    points = simulate_sweep(room, lidar_pose(), cfg, np.random.default_rng(0))
    assert abs(len(points) / (16 * 1024) - 0.5) < 0.02
    outside = np.eye(4)
    outside[:3, 3] = [3.0, 2.0, 10.0]  # above the room: the +-15 degree beams pass it by
    empty = simulate_sweep(room, outside, SpinningLidarConfig(), np.random.default_rng(0))
    assert empty.shape == (0, 3) and empty.dtype == np.float32


def test_sweep_is_deterministic_given_the_rng(room):
    cfg = SpinningLidarConfig(dropout=0.1)
    a = simulate_sweep(room, lidar_pose(), cfg, np.random.default_rng(42))
    b = simulate_sweep(room, lidar_pose(), cfg, np.random.default_rng(42))
    c = simulate_sweep(room, lidar_pose(), cfg, np.random.default_rng(43))
    np.testing.assert_array_equal(a, b)
    assert a.shape != c.shape or not np.array_equal(a, c)


def test_sweep_bad_inputs(room):
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="beams"):
        simulate_sweep(room, np.eye(4), SpinningLidarConfig(beams=0), rng)
    with pytest.raises(ValueError, match="min_range_m"):
        simulate_sweep(room, np.eye(4), SpinningLidarConfig(min_range_m=5.0, max_range_m=4.0), rng)
    with pytest.raises(ValueError, match="dropout"):
        simulate_sweep(room, np.eye(4), SpinningLidarConfig(dropout=1.5), rng)
    with pytest.raises(ValueError, match="vfov"):
        simulate_sweep(room, np.eye(4), SpinningLidarConfig(vfov_min_deg=20.0), rng)
    with pytest.raises(ValueError, match="shape"):
        simulate_sweep(room, np.eye(3), SpinningLidarConfig(), rng)
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        simulate_sweep(room, bad, SpinningLidarConfig(), rng)


def test_station_scan_covers_every_face_of_the_room(room):
    cfg = TerrestrialScannerConfig(elevation_steps=60, azimuth_steps=120, max_range_m=30.0)
    station = np.array([3.2, 1.9, 1.4])
    points = simulate_station_scan(room, station, cfg, np.random.default_rng(0))
    assert points.dtype == np.float32 and points.shape == (60 * 120, 3)
    tolerance = 5 * cfg.range_noise_std_m
    for axis in range(3):
        for bound in (ROOM_MIN[axis], ROOM_MAX[axis]):
            on_face = np.abs(points[:, axis] - bound) < tolerance
            assert on_face.sum() > 50, f"no points on face {axis}={bound}"
    ranges = np.linalg.norm(points - station, axis=1)
    truth = box_exit_distance(station, scanner_directions(cfg))
    assert np.abs(ranges - truth).max() < tolerance
    with pytest.raises(ValueError, match="position_world"):
        simulate_station_scan(room, np.zeros(2), cfg, np.random.default_rng(0))


def observer_mean(
    scans: list[np.ndarray], origins: list[np.ndarray], points: np.ndarray, voxel: float
) -> np.ndarray:
    """(M, 3) mean sensor origin over the raw points in each map point's voxel (slow reference)."""
    raw = np.concatenate(scans).astype(np.float64)
    raw_origins = np.concatenate(
        [np.broadcast_to(o, s.shape) for o, s in zip(origins, scans, strict=True)]
    )
    raw_cells = np.floor(raw / voxel).astype(np.int64)
    cells, inverse = np.unique(raw_cells, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(cells), 3))
    np.add.at(sums, inverse, raw_origins)
    means = sums / np.bincount(inverse)[:, None]
    assert len(means) == len(points)  # map points come sorted by voxel index
    return means


@pytest.fixture(scope="module")
def room_scans(room) -> tuple[list[np.ndarray], list[np.ndarray]]:
    # Looking down to -85 degrees leaves only a small unseen disc under each tripod.
    cfg = TerrestrialScannerConfig(elevation_steps=200, azimuth_steps=400, elevation_min_deg=-85.0)
    stations = [np.array([1.5, 1.2, 1.5]), np.array([4.5, 2.8, 1.2])]
    rng = np.random.default_rng(0)
    return [simulate_station_scan(room, s, cfg, rng) for s in stations], stations


def test_accumulated_map_normals_face_the_sensors_and_match_the_walls(room_scans):
    scans, stations = room_scans
    voxel, radius = 0.05, 0.15
    points, normals = accumulate_map(scans, stations, voxel, radius)
    assert points.dtype == np.float32 and normals.dtype == np.float32
    assert points.shape == normals.shape and len(points) > 1000
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    # Every normal faces the (mean) position of the stations that saw its voxel.
    assert np.all(((observer_mean(scans, stations, points, voxel) - points) * normals).sum(1) > 0)
    # Away from the room's edges each normal is the analytic inward wall normal.
    p = points.astype(np.float64)
    gap = np.concatenate([p - ROOM_MIN, ROOM_MAX - p], axis=1)  # distance to the 6 planes
    face = gap.argmin(axis=1)
    sorted_gap = np.sort(gap, axis=1)
    interior = (sorted_gap[:, 0] < 0.02) & (sorted_gap[:, 1] > radius + voxel)
    assert interior.sum() > 0.5 * len(p)
    for station in stations:
        assert np.all(((station - points[interior]) * normals[interior]).sum(axis=1) > 0)
    inward = np.zeros((len(p), 3))
    inward[np.arange(len(p)), face % 3] = np.where(face < 3, 1.0, -1.0)
    cosine = (normals[interior] * inward[interior]).sum(axis=1)
    assert np.degrees(np.arccos(np.clip(cosine, -1, 1))).max() < 5.0


def test_voxel_filter_keeps_about_one_point_per_voxel(room_scans):
    scans, stations = room_scans
    voxel = 0.1
    points, _ = accumulate_map(scans, stations, voxel, 0.3)
    raw = np.concatenate(scans).astype(np.float64)
    raw_cells = np.unique(np.floor(raw / voxel).astype(np.int64), axis=0)
    cells = np.floor(points.astype(np.float64) / voxel).astype(np.int64)
    assert len(points) == len(raw_cells)
    assert len(np.unique(cells, axis=0)) >= 0.99 * len(points)  # float32 rounding at cell edges
    assert len(points) < 0.25 * len(raw)
    # Sorted by voxel index.
    order = np.lexsort(raw_cells.T[::-1])
    np.testing.assert_array_equal(raw_cells[order], raw_cells)


def test_accumulate_map_is_deterministic_and_takes_per_point_origins(room_scans):
    scans, stations = room_scans
    a = accumulate_map(scans, stations, 0.08, 0.2)
    b = accumulate_map([s.copy() for s in scans], [s.copy() for s in stations], 0.08, 0.2)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    per_point = [np.broadcast_to(s, scan.shape) for s, scan in zip(stations, scans, strict=True)]
    c = accumulate_map(scans, per_point, 0.08, 0.2)
    np.testing.assert_array_equal(a[0], c[0])
    np.testing.assert_array_equal(a[1], c[1])
    d = accumulate_map(scans, np.stack(stations), 0.08, 0.2)
    np.testing.assert_array_equal(a[1], d[1])
    # Shuffling the points inside the scans only changes float rounding of the voxel means.
    rng = np.random.default_rng(1)
    shuffled = [s[rng.permutation(len(s))] for s in scans]
    e = accumulate_map(shuffled, stations, 0.08, 0.2)
    np.testing.assert_allclose(a[0], e[0], atol=1e-6)
    np.testing.assert_allclose(a[1], e[1], atol=1e-4)


def test_accumulate_map_from_lidar_sweeps_of_a_moving_sensor(room):
    cfg = SpinningLidarConfig(beams=16, azimuth_steps=512)
    rng = np.random.default_rng(0)
    sweeps, origins = [], []
    for x in np.linspace(1.0, 5.0, 5):
        T_wl = np.eye(4)
        T_wl[:3, 3] = [x, 2.0, 1.5]
        local = simulate_sweep(room, T_wl, cfg, rng)
        sweeps.append(local + T_wl[:3, 3].astype(np.float32))
        origins.append(T_wl[:3, 3])
    points, normals = accumulate_map(sweeps, origins, 0.05, 0.2)
    observers = observer_mean(sweeps, origins, points, 0.05)
    assert np.all(((observers - points) * normals).sum(axis=1) > 0)
    # Where the walls are densely sampled the normals face the middle of the room.
    gap = np.concatenate([points - ROOM_MIN, ROOM_MAX - points], axis=1)
    walls = np.sort(gap, axis=1)[:, 1] > 0.3
    centre = np.array([3.0, 2.0, 1.5])
    assert np.mean(((centre - points[walls]) * normals[walls]).sum(axis=1) > 0) > 0.99


def test_accumulate_map_bad_inputs():
    with pytest.raises(ValueError, match="empty"):
        accumulate_map([], [], 0.1, 0.3)
    with pytest.raises(ValueError, match="empty"):
        accumulate_map([np.zeros((0, 3))], [np.zeros(3)], 0.1, 0.3)
    cloud = np.random.default_rng(0).random((20, 3))
    with pytest.raises(ValueError, match="sensor origins"):
        accumulate_map([cloud], [np.zeros(3), np.zeros(3)], 0.1, 0.3)
    with pytest.raises(ValueError, match="shape"):
        accumulate_map([cloud], [np.zeros(2)], 0.1, 0.3)
    with pytest.raises(ValueError, match="voxel_size_m"):
        accumulate_map([cloud], [np.zeros(3)], 0.0, 0.3)
    with pytest.raises(ValueError, match="normal_radius_m"):
        accumulate_map([cloud], [np.zeros(3)], 0.1, -1.0)
    with pytest.raises(ValueError, match="max_nn"):
        accumulate_map([cloud], [np.zeros(3)], 0.1, 0.3, max_nn=2)
    nan_cloud = cloud.copy()
    nan_cloud[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        accumulate_map([nan_cloud], [np.zeros(3)], 0.1, 0.3)


def test_voxel_downsample_known_answer():
    points = np.array([[0.1, 0.1, 0.1], [0.3, 0.1, 0.1], [1.5, 0.2, 0.0], [-0.5, 0.0, 0.0]])
    attribute = np.array([[0.0], [2.0], [5.0], [7.0]])
    means, attr = voxel_downsample(points, 1.0, attribute)
    np.testing.assert_allclose(means, [[-0.5, 0, 0], [0.2, 0.1, 0.1], [1.5, 0.2, 0.0]])
    np.testing.assert_allclose(attr, [[7.0], [1.0], [5.0]])
    assert math.isclose(voxel_downsample(points[:1], 0.5)[0][0, 0], 0.1)
