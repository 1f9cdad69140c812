"""Simulated range sensors and the point-cloud maps accumulated from them.

- A spinning multi-beam lidar (Velodyne-like): ``beams`` lasers at fixed elevations spin about
  the sensor's z axis; one sweep fires every beam at ``azimuth_steps`` azimuths.
- A terrestrial laser scanner (TLS) on a levelled tripod: a dense elevation x azimuth grid,
  millimetre noise, used to make reference maps.
- :func:`accumulate_map` merges scans into one map: voxel-grid averaging, normal estimation
  (open3d, hybrid KD-tree search) and normals oriented towards the sensors that saw the points.

Sensor frames follow the body convention: x forward, y left, z up. Azimuth 0 is +x and grows
towards +y; elevation is positive upwards. A sweep is simulated at one pose (no motion
distortion within the sweep).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from diffloc.checks import check_finite, check_positive_int, check_shape
from diffloc.geometry.voxel import voxel_average
from diffloc.o3d import open3d
from diffloc.render.raycast import MeshRaycaster

__all__ = [
    "SpinningLidarConfig",
    "TerrestrialScannerConfig",
    "accumulate_map",
    "scanner_directions",
    "simulate_station_scan",
    "simulate_sweep",
    "spinning_lidar_directions",
    "voxel_downsample",
]


@dataclass
class SpinningLidarConfig:
    """A spinning multi-beam lidar (the Hydra ``scene.lidar`` group).

    Attributes:
        beams: number of lasers, spread evenly over the vertical field of view.
        vfov_min_deg: elevation of the lowest beam, degrees.
        vfov_max_deg: elevation of the highest beam, degrees.
        azimuth_steps: firings per revolution (horizontal resolution ``360 / azimuth_steps``).
        min_range_m: returns closer than this are discarded, metres.
        max_range_m: returns farther than this are discarded, metres (30 indoors, 80 outdoors).
        range_noise_std_m: standard deviation of the Gaussian range noise, metres.
        rate_hz: revolutions (sweeps) per second.
        dropout: probability in [0, 1] that a return is missing.
    """

    beams: int = 16
    vfov_min_deg: float = -15.0
    vfov_max_deg: float = 15.0
    azimuth_steps: int = 1024
    min_range_m: float = 0.3
    max_range_m: float = 30.0
    range_noise_std_m: float = 0.01
    rate_hz: float = 10.0
    dropout: float = 0.0


@dataclass
class TerrestrialScannerConfig:
    """A levelled terrestrial laser scanner (the Hydra ``scene.tls`` group).

    Attributes:
        elevation_steps: rows of the scan grid, spread evenly over the elevation range.
        azimuth_steps: columns of the scan grid over a full turn.
        elevation_min_deg: lowest elevation, degrees (the tripod hides what is below).
        elevation_max_deg: highest elevation, degrees.
        min_range_m: returns closer than this are discarded, metres.
        max_range_m: returns farther than this are discarded, metres.
        range_noise_std_m: standard deviation of the Gaussian range noise, metres.
    """

    elevation_steps: int = 240
    azimuth_steps: int = 480
    elevation_min_deg: float = -60.0
    elevation_max_deg: float = 88.0
    min_range_m: float = 0.3
    max_range_m: float = 30.0
    range_noise_std_m: float = 0.003


def _check_number(value: object, name: str, *, low: float | None = None, strict: bool = False):
    """Raise ``ValueError`` unless ``value`` is a finite number (above ``low`` if given)."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise ValueError(f"{name} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    if low is not None and (value <= low if strict else value < low):
        relation = ">" if strict else ">="
        raise ValueError(f"{name} must be {relation} {low}, got {value}")


def _check_ranges(min_range: float, max_range: float, noise: float, prefix: str) -> None:
    _check_number(min_range, f"{prefix}.min_range_m", low=0.0)
    _check_number(max_range, f"{prefix}.max_range_m", low=0.0, strict=True)
    _check_number(noise, f"{prefix}.range_noise_std_m", low=0.0)
    if min_range >= max_range:
        raise ValueError(
            f"{prefix}.min_range_m ({min_range}) must be smaller than max_range_m ({max_range})"
        )


def _check_elevations(low_deg: float, high_deg: float, low_name: str, high_name: str) -> None:
    _check_number(low_deg, low_name)
    _check_number(high_deg, high_name)
    if not -90.0 <= low_deg <= high_deg <= 90.0:
        raise ValueError(
            f"need -90 <= {low_name} <= {high_name} <= 90 degrees, got {low_deg}, {high_deg}"
        )


def _validate_lidar(cfg: SpinningLidarConfig) -> None:
    check_positive_int(cfg.beams, "lidar.beams")
    check_positive_int(cfg.azimuth_steps, "lidar.azimuth_steps")
    _check_elevations(
        cfg.vfov_min_deg, cfg.vfov_max_deg, "lidar.vfov_min_deg", "lidar.vfov_max_deg"
    )
    _check_ranges(cfg.min_range_m, cfg.max_range_m, cfg.range_noise_std_m, "lidar")
    _check_number(cfg.rate_hz, "lidar.rate_hz", low=0.0, strict=True)
    _check_number(cfg.dropout, "lidar.dropout", low=0.0)
    if cfg.dropout > 1.0:
        raise ValueError(f"lidar.dropout must be a probability in [0, 1], got {cfg.dropout}")


def _validate_scanner(cfg: TerrestrialScannerConfig) -> None:
    check_positive_int(cfg.elevation_steps, "tls.elevation_steps")
    check_positive_int(cfg.azimuth_steps, "tls.azimuth_steps")
    _check_elevations(
        cfg.elevation_min_deg,
        cfg.elevation_max_deg,
        "tls.elevation_min_deg",
        "tls.elevation_max_deg",
    )
    _check_ranges(cfg.min_range_m, cfg.max_range_m, cfg.range_noise_std_m, "tls")


def _grid_directions(
    elevation_min_deg: float, elevation_max_deg: float, rows: int, azimuth_steps: int
) -> np.ndarray:
    """(azimuth_steps * rows, 3) unit directions; row index varies fastest.

    Elevations are ``linspace(min, max, rows)`` (the midpoint if ``rows == 1``); azimuths are
    ``2 pi k / azimuth_steps``.
    """
    if rows == 1:
        elevation = np.radians([0.5 * (elevation_min_deg + elevation_max_deg)])
    else:
        elevation = np.radians(np.linspace(elevation_min_deg, elevation_max_deg, rows))
    azimuth = 2.0 * np.pi * np.arange(azimuth_steps) / azimuth_steps
    az, el = np.meshgrid(azimuth, elevation, indexing="ij")
    cos_el = np.cos(el)
    directions = np.stack([cos_el * np.cos(az), cos_el * np.sin(az), np.sin(el)], axis=-1)
    return directions.reshape(-1, 3)


def spinning_lidar_directions(cfg: SpinningLidarConfig) -> np.ndarray:
    """Unit ray directions of one sweep in the lidar frame (x forward, y left, z up).

    Ray ``a * beams + b`` is beam ``b`` (elevations ``linspace(vfov_min, vfov_max, beams)``,
    lowest first) fired at azimuth ``2 pi a / azimuth_steps`` (0 along +x, towards +y), i.e. the
    firing order of a spinning sensor.

    Args:
        cfg: the lidar configuration.

    Returns:
        (beams * azimuth_steps, 3) float64 unit directions.

    Example:
        >>> d = spinning_lidar_directions(SpinningLidarConfig(beams=2, azimuth_steps=4))
        >>> d.shape
        (8, 3)
    """
    _validate_lidar(cfg)
    return _grid_directions(cfg.vfov_min_deg, cfg.vfov_max_deg, cfg.beams, cfg.azimuth_steps)


def scanner_directions(cfg: TerrestrialScannerConfig) -> np.ndarray:
    """Unit ray directions of a terrestrial scan in the levelled scanner frame (world axes).

    Ray ``a * elevation_steps + e`` has elevation ``linspace(min, max, elevation_steps)[e]`` and
    azimuth ``2 pi a / azimuth_steps``.

    Args:
        cfg: the scanner configuration.

    Returns:
        (elevation_steps * azimuth_steps, 3) float64 unit directions.
    """
    _validate_scanner(cfg)
    return _grid_directions(
        cfg.elevation_min_deg, cfg.elevation_max_deg, cfg.elevation_steps, cfg.azimuth_steps
    )


def _measure(
    raycaster: MeshRaycaster,
    origin: np.ndarray,
    directions: np.ndarray,
    min_range: float,
    max_range: float,
    noise_std: float,
    dropout: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Noisy ranges of rays from one origin: (kept ray indices (P,), ranges (P,) float64).

    The random numbers drawn depend only on the number of rays, not on what they hit, so a
    generator in the same state always gives the same noise pattern.
    """
    count = len(directions)
    noise = rng.standard_normal(count) * noise_std
    dropped = rng.random(count) < dropout if dropout > 0 else np.zeros(count, dtype=bool)
    origins = torch.from_numpy(np.broadcast_to(origin, directions.shape).copy())
    hits = raycaster.cast(origins, torch.from_numpy(directions))
    distance = hits.distance.numpy().astype(np.float64)
    ranges = distance + noise
    keep = np.isfinite(distance) & (ranges >= min_range) & (ranges <= max_range) & ~dropped
    index = np.flatnonzero(keep)
    return index, ranges[index]


def _as_numpy64(x: np.ndarray | torch.Tensor) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def simulate_sweep(
    raycaster: MeshRaycaster,
    T_wl: np.ndarray | torch.Tensor,
    cfg: SpinningLidarConfig,
    rng: np.random.Generator,
) -> np.ndarray:
    """One sweep of a spinning lidar at pose ``T_wl`` (all rays cast at once).

    Each ray's true range gets Gaussian noise of ``range_noise_std_m``; returns whose noisy range
    lies outside ``[min_range_m, max_range_m]``, rays that miss the mesh, and (with probability
    ``dropout``) random returns are dropped.

    Args:
        raycaster: caster of the world mesh.
        T_wl: (4, 4) lidar-to-world pose.
        cfg: the lidar configuration.
        rng: source of the range noise and dropout.

    Returns:
        (P, 3) float32 points in the lidar frame, in firing order (see
        :func:`spinning_lidar_directions`).

    Example:
        >>> from diffloc.sim.primitives import MeshBuilder
        >>> builder = MeshBuilder(["concrete"])
        >>> builder.add_box([-5, -5, -5], [5, 5, 5], "concrete", object_id=0)  # a 10 m room
        >>> mesh = builder.build([np.full((4, 4, 3), 0.5, dtype=np.float32)])
        >>> config = SpinningLidarConfig(beams=4, azimuth_steps=64)
        >>> points = simulate_sweep(MeshRaycaster(mesh), np.eye(4), config,
        ...                         np.random.default_rng(0))
        >>> points.shape[1], bool(np.abs(points).max() < 5.1)  # hits on the walls (lidar frame)
        (3, True)
    """
    directions_lidar = spinning_lidar_directions(cfg)
    pose = _as_numpy64(T_wl)
    check_shape(pose, "4,4", "T_wl")
    check_finite(pose, "T_wl")
    directions_world = directions_lidar @ pose[:3, :3].T
    index, ranges = _measure(
        raycaster,
        pose[:3, 3],
        directions_world,
        cfg.min_range_m,
        cfg.max_range_m,
        cfg.range_noise_std_m,
        float(cfg.dropout),
        rng,
    )
    return (directions_lidar[index] * ranges[:, None]).astype(np.float32)


def simulate_station_scan(
    raycaster: MeshRaycaster,
    position_world: np.ndarray | torch.Tensor,
    cfg: TerrestrialScannerConfig,
    rng: np.random.Generator,
) -> np.ndarray:
    """A full-dome scan of a levelled terrestrial laser scanner standing at ``position_world``.

    Args:
        raycaster: caster of the world mesh.
        position_world: (3,) optical centre of the scanner in the world frame.
        cfg: the scanner configuration.
        rng: source of the range noise.

    Returns:
        (P, 3) float32 points in the world frame (returns within the range limits only).

    Example:
        >>> from diffloc.sim.primitives import MeshBuilder
        >>> builder = MeshBuilder(["concrete"])
        >>> builder.add_box([-5, -5, -5], [5, 5, 5], "concrete", object_id=0)  # a 10 m room
        >>> mesh = builder.build([np.full((4, 4, 3), 0.5, dtype=np.float32)])
        >>> config = TerrestrialScannerConfig(elevation_steps=8, azimuth_steps=16)
        >>> points = simulate_station_scan(MeshRaycaster(mesh), np.array([1.0, 2.0, 1.5]),
        ...                                config, np.random.default_rng(0))
        >>> points.shape[1], bool(np.abs(points).max() < 5.1)  # world frame, inside the room
        (3, True)
    """
    directions = scanner_directions(cfg)
    origin = _as_numpy64(position_world)
    check_shape(origin, "3", "position_world")
    check_finite(origin, "position_world")
    index, ranges = _measure(
        raycaster,
        origin,
        directions,
        cfg.min_range_m,
        cfg.max_range_m,
        cfg.range_noise_std_m,
        0.0,
        rng,
    )
    return (origin + directions[index] * ranges[:, None]).astype(np.float32)


def voxel_downsample(
    points: np.ndarray, voxel_size_m: float, *attributes: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Average points (and per-point attributes) over the cells of a voxel grid.

    The grid is anchored at the world origin (cell ``floor(p / voxel_size_m)``), so clouds
    downsampled separately share one grid. The output is sorted lexicographically by cell index,
    so it does not depend on the input order of whole cells.

    Args:
        points: (P, 3) points, P >= 1.
        voxel_size_m: cell edge length, metres (> 0).
        *attributes: (P, C) per-point values averaged the same way (e.g. sensor origins).

    Returns:
        (M, 3) float64 cell means of the points, then one (M, C) float64 array per attribute.

    Example:
        >>> voxel_downsample(np.array([[0.1, 0, 0], [0.3, 0, 0], [1.5, 0, 0]]), 1.0)[0]
        array([[0.2, 0. , 0. ],
               [1.5, 0. , 0. ]])
    """
    points = np.asarray(points, dtype=np.float64)
    check_shape(points, "P,3", "points")
    if len(points) == 0:
        raise ValueError("cannot voxel-downsample an empty point cloud")
    _check_number(voxel_size_m, "voxel_size_m", low=0.0, strict=True)
    for i, attribute in enumerate(attributes):
        if len(attribute) != len(points):
            raise ValueError(
                f"attribute {i} has {len(attribute)} rows but there are {len(points)} points"
            )
    centers, _, *means = voxel_average(points, voxel_size_m, *attributes)
    return (centers, *means)


def _per_point_origins(
    clouds: list[np.ndarray], origins: Sequence[np.ndarray | torch.Tensor] | np.ndarray
) -> np.ndarray:
    """(P, 3) sensor origin of every point of the concatenated clouds."""
    if isinstance(origins, np.ndarray | torch.Tensor):
        array = _as_numpy64(origins)
        total = sum(len(c) for c in clouds)
        if array.ndim == 2 and array.shape == (len(clouds), 3):
            return np.repeat(array, [len(c) for c in clouds], axis=0)
        if array.ndim == 2 and array.shape == (total, 3):
            return array
        raise ValueError(
            f"sensor_origins_world must have shape ({len(clouds)}, 3) (one per cloud) or "
            f"({total}, 3) (one per point), got {array.shape}"
        )
    if len(origins) != len(clouds):
        raise ValueError(
            f"got {len(clouds)} point clouds but {len(origins)} sensor origins; pass one origin "
            "(3,) or one origin per point (P_i, 3) for every cloud"
        )
    per_point = []
    for i, (cloud, origin) in enumerate(zip(clouds, origins, strict=True)):
        origin = _as_numpy64(origin)
        if origin.shape == (3,):
            per_point.append(np.broadcast_to(origin, cloud.shape))
        elif origin.shape == cloud.shape:
            per_point.append(origin)
        else:
            raise ValueError(
                f"sensor origin {i} must have shape (3,) or {cloud.shape}, got {origin.shape}"
            )
    return np.concatenate(per_point, axis=0)


def accumulate_map(
    points_world_list: Sequence[np.ndarray | torch.Tensor],
    sensor_origins_world: Sequence[np.ndarray | torch.Tensor] | np.ndarray,
    voxel_size_m: float,
    normal_radius_m: float,
    max_nn: int = 30,
) -> tuple[np.ndarray, np.ndarray]:
    """Merge scans into one voxel-filtered map with normals facing the sensors.

    Steps: concatenate the clouds; average points and their sensor origins per voxel
    (:func:`voxel_downsample`, output sorted by voxel index, hence deterministic); estimate
    normals with open3d (hybrid KD-tree search: at most ``max_nn`` neighbours within
    ``normal_radius_m``); flip every normal with ``dot(normal, origin - point) < 0`` so it
    faces the (voxel-averaged) position of the sensors that observed the point.

    Args:
        points_world_list: scans, each (P_i, 3) in the world frame.
        sensor_origins_world: the sensor position for each scan, either one (3,) per scan or
            (P_i, 3) per point (e.g. a moving sensor); or one array (S, 3) with a row per scan,
            or (sum P_i, 3) with a row per point.
        voxel_size_m: voxel edge length, metres (> 0).
        normal_radius_m: neighbourhood radius for normal estimation, metres (> 0).
        max_nn: maximum neighbours used per normal (>= 3).

    Returns:
        points (M, 3) float32 and unit normals (M, 3) float32 in the world frame.

    Raises:
        ValueError: the input is empty (no scans or no points), shapes mismatch, NaN values or
            non-positive sizes.

    Example:
        >>> xy = np.stack(np.meshgrid(np.arange(0, 1, 0.02), np.arange(0, 1, 0.02)), -1)
        >>> floor = np.c_[xy.reshape(-1, 2), np.zeros(2500)]  # two scans of a 1 m floor patch
        >>> points, normals = accumulate_map([floor, floor + [0.01, 0, 0]],
        ...                                  [[0.5, 0.5, 1.0], [0.5, 0.5, 2.0]], 0.05, 0.15)
        >>> points.shape, bool(np.abs(normals - [0, 0, 1]).max() < 1e-5)  # facing the sensors
        ((400, 3), True)
    """
    _check_number(voxel_size_m, "voxel_size_m", low=0.0, strict=True)
    _check_number(normal_radius_m, "normal_radius_m", low=0.0, strict=True)
    max_nn = check_positive_int(max_nn, "max_nn")
    if max_nn < 3:
        raise ValueError(f"max_nn must be at least 3 to fit a plane, got {max_nn}")
    clouds = [_as_numpy64(c) for c in points_world_list]
    if not clouds:
        raise ValueError("cannot accumulate a map from an empty list of scans")
    for i, cloud in enumerate(clouds):
        check_shape(cloud, "P,3", f"points_world_list[{i}]")
        check_finite(cloud, f"points_world_list[{i}]")
    origins = _per_point_origins(clouds, sensor_origins_world)
    check_finite(origins, "sensor_origins_world")
    points = np.concatenate(clouds, axis=0)
    if len(points) == 0:
        raise ValueError("cannot accumulate a map: all scans are empty")

    points, origins = voxel_downsample(points, voxel_size_m, origins)
    o3d = open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(float(normal_radius_m), max_nn))
    normals = np.asarray(cloud.normals, dtype=np.float64)
    norms = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.where(norms > 0, normals / np.where(norms > 0, norms, 1.0), [0.0, 0.0, 1.0])
    away = (normals * (origins - points)).sum(axis=1) < 0
    normals[away] *= -1.0
    return points.astype(np.float32), normals.astype(np.float32)
