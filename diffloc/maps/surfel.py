"""Surfel maps: oriented discs built from lidar point clouds (seed 1, Sec. III-A).

A surfel is a disc with a centre, a unit normal and a radius, optionally a colour and a
confidence. :meth:`SurfelMap.from_points` turns an accumulated lidar map into surfels:

1. voxel downsampling: points, colours and sensor origins are averaged per cell of a grid
   anchored at the world origin (cell ``floor(p / voxel_size_m)``); the output is sorted by
   cell, so it does not depend on the input order. The number of points merged into a cell is
   kept as the surfel's ``confidence`` (observation count, as in surfel fusion);
2. statistical outlier removal (open3d ``remove_statistical_outlier``);
3. normals by open3d's PCA over a hybrid KD-tree neighbourhood (``normal_radius_m``, at most
   ``normal_max_nn`` points), flipped to face the mean sensor origin of the cell's points;
   surfels with fewer than two neighbours within ``normal_radius_m`` have no surface to fit
   and are dropped;
4. radii from the local density: the distance to the ``density_neighbours``-th nearest
   surfel, scaled so that the mean over the map is ``mean_radius_m``, then clamped to
   ``[radius_min_factor, radius_max_factor] * mean_radius_m``.

Seed 1 uses a mean radius of 0.02 m indoors (EuRoC) and 0.1 m outdoors (CARLA); the defaults
of :class:`SurfelMapConfig` are the indoor ones.

Files: ``.ply`` (readable by point-cloud viewers; ``radius``, ``confidence`` and exact float
colours as extra vertex properties) and ``.npz`` (``format_version`` 1); both round trip
bit-exactly.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from diffloc.checks import ShapeError, check_finite, check_shape
from diffloc.geometry.voxel import voxel_average
from diffloc.io.ply import read_point_cloud, write_point_cloud
from diffloc.maps._storage import (
    colors_from_ply,
    exact_color_columns,
    map_suffix,
    naming_file,
    read_npz,
    write_npz,
)
from diffloc.maps._tensors import PerPointFields, as_float32, check_in_range, check_unit_vectors
from diffloc.o3d import open3d

__all__ = ["SURFEL_MAP_FORMAT_VERSION", "SurfelMap", "SurfelMapConfig"]

SURFEL_MAP_FORMAT_VERSION = 1
"""``format_version`` of surfel-map ``.npz`` files."""

_KIND = "diffloc-surfel-map"
_ArrayLike = torch.Tensor | np.ndarray


@dataclass
class SurfelMapConfig:
    """How :meth:`SurfelMap.from_points` builds surfels (defaults: indoor, seed 1 EuRoC).

    Attributes:
        voxel_size_m: edge of the downsampling voxel grid, metres; at most one surfel per cell.
        mean_radius_m: mean surfel radius, metres (seed 1: 0.02 indoors, 0.1 outdoors).
        radius_min_factor: smallest radius as a fraction of ``mean_radius_m`` (> 0).
        radius_max_factor: largest radius as a multiple of ``mean_radius_m``
            (>= ``radius_min_factor``).
        density_neighbours: the radius follows the distance to this nearest neighbour (k-th
            nearest surfel centre, the surfel itself not counted).
        normal_radius_m: neighbourhood radius of the PCA normal fit, metres.
        normal_max_nn: at most this many neighbours in the normal fit (>= 3).
        outlier_neighbours: neighbours whose mean distance is compared in the statistical
            outlier removal.
        outlier_std_ratio: points whose mean neighbour distance exceeds the map average by
            more than this many standard deviations are removed (> 0).
    """

    voxel_size_m: float = 0.02
    mean_radius_m: float = 0.02
    radius_min_factor: float = 0.5
    radius_max_factor: float = 2.0
    density_neighbours: int = 8
    normal_radius_m: float = 0.06
    normal_max_nn: int = 30
    outlier_neighbours: int = 20
    outlier_std_ratio: float = 3.0

    def __post_init__(self) -> None:
        for name in ("voxel_size_m", "mean_radius_m", "radius_min_factor", "normal_radius_m"):
            _check_positive_number(getattr(self, name), name)
        _check_positive_number(self.outlier_std_ratio, "outlier_std_ratio")
        _check_positive_number(self.radius_max_factor, "radius_max_factor")
        if self.radius_max_factor < self.radius_min_factor:
            raise ValueError(
                f"radius_max_factor ({self.radius_max_factor}) must be >= radius_min_factor "
                f"({self.radius_min_factor})"
            )
        for name in ("density_neighbours", "outlier_neighbours"):
            _check_count(getattr(self, name), name, 1)
        _check_count(self.normal_max_nn, "normal_max_nn", 3)

    @property
    def min_points(self) -> int:
        """Fewest voxel-downsampled points the neighbourhood statistics need."""
        return max(self.density_neighbours, self.outlier_neighbours, 2) + 1


def _check_positive_number(value: object, name: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < np.inf:
        raise ValueError(f"SurfelMapConfig.{name} must be a positive finite number, got {value!r}")


def _check_count(value: object, name: str, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ValueError(f"SurfelMapConfig.{name} must be an integer >= {low}, got {value!r}")


@dataclass(frozen=True, eq=False)
class SurfelMap(PerPointFields):
    """A map of N surfels (oriented discs); all tensors on one device.

    Attributes:
        centers: (N, 3) float32 disc centres, world frame, metres.
        normals: (N, 3) float32 unit normals (facing the sensors that observed the surface).
        radii: (N,) float32 disc radii, metres, > 0.
        colors: (N, 3) float32 RGB in [0, 1], or ``None``.
        confidence: (N,) float32 >= 0 (from :meth:`from_points`: the number of input points
            merged into the surfel), or ``None``.

    Floating tensors or numpy arrays are accepted and stored as float32 tensors.

    Raises:
        ShapeError: a field of the wrong shape.
        TypeError: a field that is not a floating tensor or array.
        ValueError: NaN/inf values, non-positive radii, non-unit normals, colours outside
            [0, 1], negative confidence, or fields on different devices.

    Example:
        >>> surfels = SurfelMap(torch.zeros(1, 3), torch.tensor([[0.0, 0, 1]]), torch.ones(1))
        >>> len(surfels)
        1
    """

    centers: torch.Tensor
    normals: torch.Tensor
    radii: torch.Tensor
    colors: torch.Tensor | None = None
    confidence: torch.Tensor | None = None

    def __post_init__(self) -> None:
        centers = as_float32(self.centers, "N,3", "centers")
        n = centers.shape[0]
        normals = as_float32(self.normals, f"{n},3", "normals")
        radii = as_float32(self.radii, f"{n}", "radii")
        check_unit_vectors(normals, "normals")
        if n and not bool((radii > 0).all()):
            raise ValueError(f"radii must be positive, got a minimum of {float(radii.min())}")
        object.__setattr__(self, "centers", centers)
        object.__setattr__(self, "normals", normals)
        object.__setattr__(self, "radii", radii)
        if self.colors is not None:
            colors = as_float32(self.colors, f"{n},3", "colors")
            check_in_range(colors, 0.0, 1.0, "colors")
            object.__setattr__(self, "colors", colors)
        if self.confidence is not None:
            confidence = as_float32(self.confidence, f"{n}", "confidence")
            check_in_range(confidence, 0.0, float("inf"), "confidence")
            object.__setattr__(self, "confidence", confidence)
        self._check_same_device()

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_points(
        cls,
        points: _ArrayLike,
        sensor_origins: _ArrayLike,
        config: SurfelMapConfig | None = None,
        colors: _ArrayLike | None = None,
    ) -> SurfelMap:
        """Build surfels from a point cloud (see the module docstring for the steps).

        Args:
            points: (N, 3) points, world frame, metres.
            sensor_origins: (N, 3) position of the sensor that measured each point, or (3,)
                one position for all points; normals are flipped to face it.
            config: construction parameters (default: :class:`SurfelMapConfig`).
            colors: optional (N, 3) RGB in [0, 1], averaged per voxel.

        Returns:
            The surfel map (CPU tensors) with ``confidence`` = points merged per surfel.

        Raises:
            ShapeError: inputs of the wrong shape.
            ValueError: an empty cloud, NaN/inf values, colours outside [0, 1], fewer
                downsampled points than the neighbourhood sizes need, or no surfel left.

        Example:
            >>> xy = np.stack(np.meshgrid(np.arange(0, 1, 0.02), np.arange(0, 1, 0.02)), -1)
            >>> floor = np.c_[xy.reshape(-1, 2), np.zeros(2500)]  # 1 x 1 m floor, 2 cm grid
            >>> surfels = SurfelMap.from_points(floor, [0.5, 0.5, 1.5], SurfelMapConfig())
            >>> len(surfels) > 100, bool((surfels.normals[:, 2] > 0.99).all())  # face the sensor
            (True, True)
        """
        config = SurfelMapConfig() if config is None else config
        points_np, origins, attributes = _checked_inputs(points, sensor_origins, colors)
        voxels = _voxel_average(points_np, config.voxel_size_m, attributes)
        _require_points(len(voxels["centers"]), config, "voxel downsampling")
        voxels = _subset(voxels, _inliers(voxels["centers"], config))
        _require_points(len(voxels["centers"]), config, "outlier removal")
        centers = voxels["centers"]
        normals = _estimate_normals(centers, config)
        voxels["normals"] = _face_origins(normals, centers, voxels.get("origins", origins))
        voxels["kth_distance"], supported = _neighbour_distances(centers, config)
        if not supported.any():
            raise ValueError(
                f"no surfel has two neighbours within normal_radius_m = {config.normal_radius_m}"
                " m; the cloud is too sparse for this SurfelMapConfig"
            )
        voxels = _subset(voxels, supported)

        def as_tensor(name: str) -> torch.Tensor | None:
            values = voxels.get(name)
            return None if values is None else torch.from_numpy(values.astype(np.float32))

        return cls(
            centers=as_tensor("centers"),
            normals=as_tensor("normals"),
            radii=torch.from_numpy(_density_radii(voxels["kth_distance"], config)).float(),
            colors=as_tensor("colors"),
            confidence=as_tensor("counts"),
        )

    # ------------------------------------------------------------------ persistence

    def save(self, path: str | os.PathLike) -> None:
        """Write to ``.ply`` (:meth:`save_ply`) or ``.npz`` (:meth:`save_npz`) by suffix."""
        {".ply": self.save_ply, ".npz": self.save_npz}[map_suffix(path)](path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> SurfelMap:
        """Read a ``.ply`` (:meth:`load_ply`) or ``.npz`` (:meth:`load_npz`) file by suffix."""
        return {".ply": cls.load_ply, ".npz": cls.load_npz}[map_suffix(path)](path)

    def save_ply(self, path: str | os.PathLike) -> None:
        """Write a binary PLY file atomically.

        Vertex properties: float ``x y z nx ny nz radius``, ``uchar red green blue`` (for
        viewers) plus float ``red_f32 green_f32 blue_f32`` (exact) when there are colours,
        float ``confidence`` when there is a confidence.

        Args:
            path: the ``.ply`` file.
        """
        extra = {"radius": self.radii.detach().cpu().numpy()}
        if self.confidence is not None:
            extra["confidence"] = self.confidence.detach().cpu().numpy()
        extra.update(exact_color_columns(self.colors))
        write_point_cloud(path, self.centers, self.normals, self.colors, extra=extra)

    @classmethod
    def load_ply(cls, path: str | os.PathLike) -> SurfelMap:
        """Read a PLY file with ``x y z nx ny nz radius`` and optional colours/confidence.

        Colours come from ``red_f32 green_f32 blue_f32`` when present, else from ``red green
        blue`` (integers divided by their maximum). Other vertex properties are ignored.

        Args:
            path: the ``.ply`` file.

        Returns:
            The surfel map (CPU tensors).

        Raises:
            FileNotFoundError: the file does not exist.
            ValueError: a malformed PLY, no normals or radius, or invalid values; the message
                names the file.
        """
        cloud = read_point_cloud(path)
        if cloud.normals is None or "radius" not in cloud.extra:
            raise ValueError(f"{path}: a surfel map PLY needs nx, ny, nz and radius properties")
        with naming_file(path, "surfel map"):
            return cls(
                centers=cloud.points,
                normals=cloud.normals,
                radii=cloud.extra["radius"],
                colors=colors_from_ply(cloud),
                confidence=cloud.extra.get("confidence"),
            )

    def save_npz(self, path: str | os.PathLike) -> None:
        """Write an uncompressed ``.npz`` (with ``format_version`` and ``kind``) atomically.

        Args:
            path: the ``.npz`` file.
        """
        write_npz(path, _KIND, SURFEL_MAP_FORMAT_VERSION, self._tensors())

    @classmethod
    def load_npz(cls, path: str | os.PathLike) -> SurfelMap:
        """Read a file written by :meth:`save_npz` (``allow_pickle=False``).

        Args:
            path: the ``.npz`` file.

        Returns:
            The surfel map (CPU tensors).

        Raises:
            FileNotFoundError: the file does not exist.
            ValueError: a corrupt or truncated archive, another kind or format version,
                missing/unknown entries, or invalid values; the message names the file.
        """
        arrays = read_npz(
            path,
            _KIND,
            SURFEL_MAP_FORMAT_VERSION,
            required=("centers", "normals", "radii"),
            optional=("colors", "confidence"),
        )
        with naming_file(path, "surfel map"):
            return cls(**arrays)


def _require_points(count: int, config: SurfelMapConfig, stage: str) -> None:
    if count < config.min_points:
        raise ValueError(
            f"only {count} points are left after {stage}; building surfels needs at least "
            f"{config.min_points} (see SurfelMapConfig: voxel size and neighbour counts)"
        )


def _as_float64(x: _ArrayLike, spec: str, name: str) -> np.ndarray:
    """A finite float64 numpy copy of a tensor or array of shape ``spec``."""
    array = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    check_shape(array, spec, name)
    array = array.astype(np.float64)
    check_finite(array, name)
    return array


def _checked_inputs(
    points: _ArrayLike, sensor_origins: _ArrayLike, colors: _ArrayLike | None
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Validated float64 ``(points (N, 3), origins (3,) or (N, 3), per-point attributes)``.

    The attributes to average per voxel are the per-point origins and the colours, if given.
    """
    points_np = _as_float64(points, "N,3", "points")
    n = len(points_np)
    if n == 0:
        raise ValueError("cannot build a surfel map from an empty point cloud")
    origins = _as_float64(sensor_origins, "*,3", "sensor_origins")
    if origins.shape not in ((3,), (n, 3)):
        raise ShapeError(
            f"sensor_origins must have shape ({n}, 3) or (3,), got {tuple(origins.shape)}"
        )
    attributes = {} if origins.ndim == 1 else {"origins": origins}
    if colors is not None:
        attributes["colors"] = _as_float64(colors, f"{n},3", "colors")
        check_in_range(torch.from_numpy(attributes["colors"]), 0.0, 1.0, "colors")
    return points_np, origins, attributes


def _voxel_average(
    points: np.ndarray, voxel_size_m: float, attributes: dict[str, np.ndarray]
) -> dict[str, np.ndarray]:
    """Average points and per-point attributes over the occupied cells of a voxel grid.

    Args:
        points: (N, 3) float64 points, N >= 1.
        voxel_size_m: cell edge; cell of a point is ``floor(p / voxel_size_m)``.
        attributes: name -> (N, C) float64 per-point values.

    Returns:
        ``"centers"`` (M, 3) point means, ``"counts"`` (M,) points per cell and the (M, C)
        mean of every attribute, sorted by cell.
    """
    centers, counts, *means = voxel_average(points, voxel_size_m, *attributes.values())
    return {"centers": centers, "counts": counts, **dict(zip(attributes, means, strict=True))}


def _subset(arrays: dict[str, np.ndarray], index: np.ndarray) -> dict[str, np.ndarray]:
    """Every array of ``arrays`` indexed by the same mask or index along its first axis."""
    return {name: values[index] for name, values in arrays.items()}


def _inliers(points: np.ndarray, config: SurfelMapConfig) -> np.ndarray:
    """Indices (K,) of the points kept by open3d's statistical outlier removal."""
    o3d = open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    _, kept = cloud.remove_statistical_outlier(config.outlier_neighbours, config.outlier_std_ratio)
    return np.asarray(kept, dtype=np.int64)


def _estimate_normals(points: np.ndarray, config: SurfelMapConfig) -> np.ndarray:
    """(M, 3) float64 unit normals (unoriented) by open3d's hybrid-neighbourhood PCA."""
    o3d = open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(
        o3d.geometry.KDTreeSearchParamHybrid(config.normal_radius_m, config.normal_max_nn)
    )
    normals = np.asarray(cloud.normals, dtype=np.float64)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _face_origins(normals: np.ndarray, points: np.ndarray, origins: np.ndarray) -> np.ndarray:
    """Flip the normals (M, 3) that point away from their sensor origins ((M, 3) or (3,))."""
    away = ((origins - points) * normals).sum(axis=1) < 0
    return np.where(away[:, None], -normals, normals)


def _neighbour_distances(
    points: np.ndarray, config: SurfelMapConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Distance to the k-th neighbour (M,) and whether a normal could be fitted (M,) bool.

    open3d fits a normal only where the hybrid search finds at least three points (the point
    itself included) within ``normal_radius_m``.
    """
    ranks = sorted({3, config.density_neighbours + 1})  # ranks count the point itself as 1
    distances, _ = cKDTree(points).query(points, k=ranks, workers=-1)
    by_rank = dict(zip(ranks, distances.T, strict=True))
    return by_rank[config.density_neighbours + 1], by_rank[3] <= config.normal_radius_m


def _density_radii(kth_distance: np.ndarray, config: SurfelMapConfig) -> np.ndarray:
    """Radii proportional to the local spacing, mean ``mean_radius_m`` before clamping."""
    radii = kth_distance * (config.mean_radius_m / kth_distance.mean())
    return np.clip(
        radii,
        config.mean_radius_m * config.radius_min_factor,
        config.mean_radius_m * config.radius_max_factor,
    )
