"""Render-pose selection on a free-path corridor (seed 2, Sec. III-C).

Given a map point cloud with oriented normals (a TLS or lidar map, normals facing the scanner),
choose camera poses from which database images are rendered:

1. **Floors.** Points whose normal is within ``floor_max_normal_angle_rad`` of world +z face
   up. A histogram of their heights has one peak per floor; peaks closer than
   ``min_floor_gap_m`` are merged (the highest wins) and peaks holding fewer than
   ``min_floor_fraction`` of the largest one (tables, stair landings) are dropped.
2. **Occupancy.** Per floor, a top-down image with cells of ``cell_size_m``: *floor* cells hold
   an upward point within ``floor_tolerance_m`` of the floor height; *obstacle* cells hold any
   point between ``obstacle_min_height_m`` and ``obstacle_max_height_m`` above the floor. Both
   masks are closed (dilation then erosion) to fill sampling gaps: the obstacle mask by a disk
   of ``closing_radius_m`` (small, so doors stay open), the floor mask by a disk of
   ``floor_closing_radius_m`` (it can be larger: a rotating lidar samples the floor in rings
   whose gaps widen with the range, 0.2-0.6 m at 3-6 m; closing the floor across a wall is
   harmless, since the wall is an obstacle). Enclosed holes of the floor mask up to
   ``max_floor_hole_m2`` are filled (the unseen disk under a terrestrial scanner's station);
   free space is floor and not obstacle.
3. **Corridor.** The Euclidean distance transform of free space gives each free cell its
   clearance (distance to the nearest cell centre that is not free, so unmapped areas count as
   walls). The paper thresholds the distance transform normalised by its maximum; a fraction of
   the widest room's half-width would drop narrow corridors next to a hall, so the threshold
   here is a clearance in metres, ``min_clearance_m`` (the normalised image is kept for the
   figure). The thresholded mask is smoothed by a Gaussian blur (``blur_sigma_m``) and
   re-thresholded at 0.5, then intersected with the unblurred mask again so that the
   clearance still holds; corridor pieces smaller than ``min_corridor_area_m2`` are dropped.
4. **Skeleton and samples.** The corridor is thinned to a one-pixel skeleton
   (:func:`skimage.morphology.skeletonize`), whose pixels form a graph (8-neighbours, edge
   length = cell distance). Shortest-path distances from one root per connected piece (a branch
   end where there is one) give candidates where a path crosses a multiple of ``spacing_m``;
   every root and branch end is a candidate too. Candidates are accepted branch ends first,
   then by distance from the root, unless an accepted sample lies within ``spacing_m / 2``
   along the skeleton. So consecutive samples along a path are about ``spacing_m`` apart and
   branch ends are covered.
5. **Views.** Each sample gets ``views_per_sample`` horizontal cameras ``camera_height_m``
   above its floor, their yaws evenly spaced from "forward" along the local skeleton direction
   (principal axis of the skeleton pixels within ``spacing_m / 2`` along the skeleton,
   oriented away from the root): 4 views (seed 2) look forward, back, left and right, 8 views
   add the four diagonals (every 45 deg). The order is :data:`VIEW_NAMES` (the first 4 are
   seed 2's, so the 4-view poses are the 8-view ones without the diagonals).

Sample positions are skeleton cell centres, so their clearance to the nearest obstacle cell
centre is at least ``min_clearance_m``; to the obstacle points themselves it is at least
``min_clearance_m - cell_size_m / sqrt(2)``.

Indoor defaults are those of :class:`PoseSelectionConfig`; outdoors (seed 2) use
``cell_size_m=0.2``, ``spacing_m=4.0`` and coarser closing/blur/clearance.

Example (two bare 8 x 2 m floors 3 m apart; unmapped space counts as walls):
    >>> import numpy as np
    >>> xy = np.mgrid[0:8:0.05, 0:2:0.05].reshape(2, -1).T
    >>> points = np.concatenate([np.c_[xy, np.full(len(xy), z)] for z in (0.0, 3.0)])
    >>> normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))  # two 8 x 2 m floors, 3 m apart
    >>> selection = select_render_poses(points, normals, PoseSelectionConfig())
    >>> selection.T_wc.shape  # (4 views * 8 samples, 4, 4)
    torch.Size([32, 4, 4])
    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as out:  # write_floor_plan_figures: every floor
    ...     plot_floor_plan(selection.floors[0], f"{out}/floor_0.png", dpi=20).stat().st_size > 0
    True
"""

from __future__ import annotations

import io
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse
import torch
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy import ndimage
from scipy.signal import find_peaks
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree
from skimage.morphology import disk, skeletonize

from diffloc.checks import ArrayLike, check_finite, check_shape
from diffloc.crossmodal.trajectory_samples import trajectory_samples
from diffloc.io.atomic import atomic_write_bytes

__all__ = [
    "VIEWS_PER_SAMPLE",
    "VIEW_NAMES",
    "check_views_per_sample",
    "FloorPlan",
    "PoseSelectionConfig",
    "RenderPoses",
    "find_floors",
    "floor_plan",
    "plot_floor_plan",
    "select_render_poses",
    "view_directions",
    "view_poses",
    "write_floor_plan_figures",
]

VIEW_NAMES = (
    "forward",
    "back",
    "left",
    "right",
    "forward-left",
    "back-right",
    "back-left",
    "forward-right",
)
"""Order of the views of every sample (``RenderPoses.view_index``): a sample with ``k`` views
(``PoseSelectionConfig.views_per_sample``) has the first ``k``; yaws counter-clockwise from
forward seen from above: 0, 180, 90, 270, 45, 225, 135, 315 deg."""
VIEWS_PER_SAMPLE = (4, 8)
"""The allowed ``views_per_sample``: seed 2's four views 90 deg apart, or eight 45 deg apart."""


def check_views_per_sample(views: object) -> None:
    """Raise a ValueError unless ``views`` is an int in :data:`VIEWS_PER_SAMPLE`.

    Example:
        >>> check_views_per_sample(6)
        Traceback (most recent call last):
        ...
        ValueError: views_per_sample must be one of (4, 8) (yaws every 90 or 45 deg), got 6
    """
    if (
        isinstance(views, bool)
        or not isinstance(views, int | np.integer)
        or (views not in VIEWS_PER_SAMPLE)
    ):
        raise ValueError(
            f"views_per_sample must be one of {VIEWS_PER_SAMPLE} (yaws every 90 or 45 deg), "
            f"got {views!r}"
        )


@dataclass(frozen=True)
class PoseSelectionConfig:
    """Settings of :func:`select_render_poses` (indoor defaults; see the module docstring).

    Attributes:
        floor_max_normal_angle_rad: a point faces up if the angle between its normal and +z is
            below this; in ``(0, pi/2)``.
        floor_bin_m: bin width of the height histogram of upward points, metres.
        min_floor_gap_m: floors are at least this far apart in height, metres.
        min_floor_fraction: a histogram peak is a floor only if it holds at least this fraction
            of the points of the largest peak; in ``(0, 1]``.
        floor_tolerance_m: upward points within this height of a floor belong to its floor
            mask, metres.
        obstacle_min_height_m: lowest height above the floor of points that block walking.
        obstacle_max_height_m: highest such height (ceilings and the next floor lie above).
        cell_size_m: edge of a top-down image cell, metres (0.05 indoors, 0.2 outdoors).
        closing_radius_m: radius of the disk used to close the obstacle mask, metres (0
            disables closing).
        floor_closing_radius_m: radius of the disk used to close the floor mask, metres (0
            disables closing). 0.1 by default; 0.3 bridges a rotating lidar's ring gaps
            (on indoor seed 0 the lidar map's render poses go from 200 to 376 and the share
            of ``query_same`` frames with a render within 2 m / 45 deg from 61 to 94 %,
            ``experiments/results/render_coverage_indoor_seed0.md``), but it also moves the
            TLS map's poses, which lowers that map's rate, so it is not the default here;
            ``task=crossmodal`` sets it per point map (``task.floor_closing_m``: 0.3 for the
            lidar map indoors).
        max_floor_hole_m2: enclosed holes of the floor mask up to this area are filled, square
            metres (0 disables filling).
        min_clearance_m: smallest distance from a corridor cell to non-free space, metres.
        blur_sigma_m: standard deviation of the Gaussian that smooths the corridor, metres
            (0 disables smoothing).
        min_corridor_area_m2: corridor pieces smaller than this are dropped, square metres.
        spacing_m: distance between samples along the skeleton, metres (seed 2: 2 indoors, 4
            outdoors; `task=crossmodal` uses 1 m indoors, task/scene/crossmodal_indoor.yaml).
        camera_height_m: camera centre height above the floor, metres.
        views_per_sample: horizontal views per sample, yaws evenly spaced from forward along
            the skeleton, one of :data:`VIEWS_PER_SAMPLE` (4 as in seed 2, 8 = every 45 deg;
            order :data:`VIEW_NAMES`).
        trajectory_gap_m: with the map's trajectory given, its cameras farther than this from
            every sample become samples too (:mod:`diffloc.crossmodal.trajectory_samples`,
            beyond seed 2); ``None``: the skeleton's samples only, as seed 2.
    """

    floor_max_normal_angle_rad: float = math.radians(20.0)
    floor_bin_m: float = 0.05
    min_floor_gap_m: float = 2.0
    min_floor_fraction: float = 0.1
    floor_tolerance_m: float = 0.15
    obstacle_min_height_m: float = 0.3
    obstacle_max_height_m: float = 2.0
    cell_size_m: float = 0.05
    closing_radius_m: float = 0.1
    floor_closing_radius_m: float = 0.1
    max_floor_hole_m2: float = 2.0
    min_clearance_m: float = 0.4
    blur_sigma_m: float = 0.2
    min_corridor_area_m2: float = 1.0
    spacing_m: float = 2.0
    camera_height_m: float = 1.5
    views_per_sample: int = 4
    trajectory_gap_m: float | None = None

    def __post_init__(self) -> None:
        check_views_per_sample(self.views_per_sample)
        gap = self.trajectory_gap_m
        if gap is not None and not (_is_number(gap) and 0 < gap < math.inf):
            raise ValueError(
                f"trajectory_gap_m must be a positive finite number or null, got {gap!r}"
            )
        for name in (
            "floor_bin_m",
            "min_floor_gap_m",
            "floor_tolerance_m",
            "obstacle_max_height_m",
            "cell_size_m",
            "spacing_m",
        ):
            value = getattr(self, name)
            if not (_is_number(value) and 0 < value < math.inf):
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        for name in (
            "obstacle_min_height_m",
            "closing_radius_m",
            "floor_closing_radius_m",
            "max_floor_hole_m2",
            "min_clearance_m",
            "blur_sigma_m",
            "min_corridor_area_m2",
            "camera_height_m",
        ):
            value = getattr(self, name)
            if not (_is_number(value) and 0 <= value < math.inf):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        angle = self.floor_max_normal_angle_rad
        if not (_is_number(angle) and 0 < angle < math.pi / 2):
            raise ValueError(f"floor_max_normal_angle_rad must be in (0, pi/2), got {angle!r}")
        fraction = self.min_floor_fraction
        if not (_is_number(fraction) and 0 < fraction <= 1):
            raise ValueError(f"min_floor_fraction must be in (0, 1], got {fraction!r}")
        if self.obstacle_min_height_m >= self.obstacle_max_height_m:
            raise ValueError(
                "obstacle_min_height_m must be below obstacle_max_height_m, got "
                f"{self.obstacle_min_height_m!r} >= {self.obstacle_max_height_m!r}"
            )


def _is_number(value: object) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool)


@dataclass(frozen=True, eq=False)
class FloorPlan:
    """Every image-processing step of one floor (row ``r``, column ``c`` of an image is the cell
    centred at world ``(x, y) = origin_xy + cell_size_m * (c, r)``; images are ``(H, W)``).

    Attributes:
        index: floor number, 0 = lowest.
        height_m: world z of the floor surface.
        origin_xy: (2,) float64 world xy of the centre of cell (0, 0).
        cell_size_m: cell edge, metres.
        floor_mask: (H, W) bool, closed mask of upward points on the floor.
        obstacle_mask: (H, W) bool, closed mask of points in the obstacle band.
        free: (H, W) bool, ``floor_mask & ~obstacle_mask``.
        clearance_m: (H, W) float64 distance transform of ``free`` in metres (0 outside).
        corridor: (H, W) bool free-path corridor.
        skeleton: (H, W) bool skeleton of the corridor.
        samples_xy: (S, 2) float64 world xy of the samples of this floor.
        forward_xy: (S, 2) float64 unit forward direction of each sample.
    """

    index: int
    height_m: float
    origin_xy: np.ndarray
    cell_size_m: float
    floor_mask: np.ndarray
    obstacle_mask: np.ndarray
    free: np.ndarray
    clearance_m: np.ndarray
    corridor: np.ndarray
    skeleton: np.ndarray
    samples_xy: np.ndarray
    forward_xy: np.ndarray

    @property
    def clearance_normalized(self) -> np.ndarray:
        """(H, W) float64 clearance divided by its maximum (the paper's normalised transform)."""
        peak = self.clearance_m.max()
        return self.clearance_m / peak if peak > 0 else self.clearance_m

    def cells_to_xy(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """World xy (K, 2) of the centres of cells ``(rows[k], cols[k])``, each (K,)."""
        return self.origin_xy + self.cell_size_m * np.stack([cols, rows], axis=-1)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(x_min, x_max, y_min, y_max)`` of the image's outer cell edges (for imshow)."""
        h, w = self.free.shape
        half = 0.5 * self.cell_size_m
        x0, y0 = self.origin_xy - half
        return (x0, x0 + w * self.cell_size_m, y0, y0 + h * self.cell_size_m)


@dataclass(frozen=True, eq=False)
class RenderPoses:
    """Selected render poses: ``k = views_per_sample`` views per sample, samples on every floor.

    Rows are sample-major: the views of sample ``s`` are rows ``k s .. k s + k - 1`` in the
    order of :data:`VIEW_NAMES` (forward, back, left, right, then with 8 views forward-left,
    back-right, back-left, forward-right; forward is along the skeleton, away from its root).

    Attributes:
        T_wc: (M, 4, 4) float64 camera-to-world poses, OpenCV camera frame, M = k * samples.
        floor_index: (M,) int64 floor of each view (index into ``floors``; -1 for a sample on
            the map's trajectory, which belongs to no floor's skeleton).
        sample_index: (M,) int64 sample of each view (0 .. S-1 over all floors).
        view_index: (M,) int64 view of each sample, an index into :data:`VIEW_NAMES`.
        floors: one :class:`FloorPlan` per floor, lowest first.
    """

    T_wc: torch.Tensor
    floor_index: torch.Tensor
    sample_index: torch.Tensor
    view_index: torch.Tensor
    floors: tuple[FloorPlan, ...]

    def __len__(self) -> int:
        return int(self.T_wc.shape[0])

    @property
    def views_per_sample(self) -> int:
        """Views of every sample (``k``; :data:`VIEWS_PER_SAMPLE`)."""
        return int(self.view_index.max()) + 1  # every sample has views 0 .. k - 1


def _as_numpy(x: ArrayLike, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    check_shape(x, "N,3", name)
    if not np.issubdtype(x.dtype, np.floating):
        raise TypeError(f"{name} must be floating point, got {x.dtype}")
    check_finite(x, name)
    return np.asarray(x, dtype=np.float64)


def _checked_cloud(points: ArrayLike, normals: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Validated float64 points (N, 3) and unit normals (N, 3)."""
    points = _as_numpy(points, "points")
    normals = _as_numpy(normals, "normals")
    if points.shape[0] == 0:
        raise ValueError("points is empty: the map has no points")
    if normals.shape != points.shape:
        raise ValueError(
            f"normals must have one row per point: points {points.shape}, normals {normals.shape}"
        )
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    if not (length > 1e-6).all():
        raise ValueError("normals contains zero-length vectors")
    return points, normals / length


def find_floors(
    points: ArrayLike, normals: ArrayLike, config: PoseSelectionConfig | None = None
) -> np.ndarray:
    """Heights of the floors: peaks of the height histogram of upward-facing points.

    Args:
        points: (N, 3) map points, world frame (z up), metres.
        normals: (N, 3) normals oriented towards the scanner (so floors face up).
        config: the settings (default :class:`PoseSelectionConfig`).

    Returns:
        (F,) float64 floor heights, ascending: the median z of the upward points within
        ``floor_bin_m`` of each peak.

    Raises:
        ShapeError: ``points`` or ``normals`` not (N, 3).
        ValueError: NaN/inf values, empty input, or no upward-facing point ("no floor found").

    Example:
        >>> import numpy as np
        >>> xy = np.mgrid[0:8:0.05, 0:2:0.05].reshape(2, -1).T
        >>> points = np.concatenate([np.c_[xy, np.full(len(xy), z)] for z in (0.0, 3.0)])
        >>> normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))  # two 8 x 2 m floors, 3 m apart
        >>> find_floors(points, normals)
        array([0., 3.])
    """
    config = PoseSelectionConfig() if config is None else config
    points, normals = _checked_cloud(points, normals)
    return _find_floors(points[_faces_up(normals, config), 2], config)


def _faces_up(normals: np.ndarray, config: PoseSelectionConfig) -> np.ndarray:
    return normals[:, 2] > math.cos(config.floor_max_normal_angle_rad)


def _find_floors(heights: np.ndarray, config: PoseSelectionConfig) -> np.ndarray:
    if heights.size == 0:
        raise ValueError(
            "no floor found: no point has a normal within "
            f"{math.degrees(config.floor_max_normal_angle_rad):.1f} deg of +z (are the normals "
            "oriented towards the scanner, with world z up?)"
        )
    bin_m = config.floor_bin_m
    low = heights.min()
    bins = np.floor((heights - low) / bin_m).astype(np.int64)
    counts = np.pad(np.bincount(bins), 1)  # zero ends, so peaks at the ends are found
    peaks, _ = find_peaks(
        counts,
        height=config.min_floor_fraction * counts.max(),
        distance=max(1, math.ceil(config.min_floor_gap_m / bin_m)),
    )
    centres = low + (peaks - 1 + 0.5) * bin_m
    near = np.abs(heights[None, :] - centres[:, None]) <= bin_m  # (F, N_up)
    return np.array([np.median(heights[row]) for row in near])


def floor_plan(
    points: ArrayLike,
    normals: ArrayLike,
    height_m: float,
    config: PoseSelectionConfig | None = None,
    index: int = 0,
) -> FloorPlan:
    """Occupancy, clearance, corridor, skeleton and samples of the floor at ``height_m``.

    Args:
        points: (N, 3) map points, world frame (z up), metres.
        normals: (N, 3) normals oriented towards the scanner.
        height_m: world z of the floor (e.g. from :func:`find_floors`).
        config: the settings (default :class:`PoseSelectionConfig`).
        index: floor number stored in the result.

    Returns:
        The :class:`FloorPlan` with its samples and their forward directions.

    Raises:
        ShapeError: ``points`` or ``normals`` not (N, 3).
        ValueError: NaN/inf values, no upward point at ``height_m``, or an empty corridor.

    Example:
        >>> import numpy as np
        >>> xy = np.mgrid[0:8:0.05, 0:2:0.05].reshape(2, -1).T
        >>> points = np.concatenate([np.c_[xy, np.full(len(xy), z)] for z in (0.0, 3.0)])
        >>> normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))  # two 8 x 2 m floors, 3 m apart
        >>> plan = floor_plan(points, normals, 0.0)
        >>> plan.samples_xy.shape  # along the 8 m floor, 2 m apart
        (4, 2)
    """
    config = PoseSelectionConfig() if config is None else config
    points, normals = _checked_cloud(points, normals)
    if not math.isfinite(height_m):
        raise ValueError(f"height_m must be finite, got {height_m!r}")
    return _floor_plan(points, _faces_up(normals, config), float(height_m), index, config)


def _floor_plan(
    points: np.ndarray,
    up: np.ndarray,
    height_m: float,
    index: int,
    config: PoseSelectionConfig,
) -> FloorPlan:
    cell = config.cell_size_m
    where = f"floor {index} (z = {height_m:.2f} m)"
    z = points[:, 2] - height_m
    on_floor = up & (np.abs(z) <= config.floor_tolerance_m)
    if not on_floor.any():
        raise ValueError(f"{where}: no upward-facing point within floor_tolerance_m of it")
    in_band = (z >= config.obstacle_min_height_m) & (z <= config.obstacle_max_height_m)
    floor_xy = points[on_floor, :2]
    closing_cells = round(config.closing_radius_m / cell)
    floor_closing_cells = round(config.floor_closing_radius_m / cell)
    margin = max(closing_cells, floor_closing_cells) + 2
    origin_xy = floor_xy.min(axis=0) - margin * cell
    shape = tuple(np.ceil((floor_xy.max(axis=0) - origin_xy) / cell).astype(int)[::-1] + margin)
    floor_mask = _close(_rasterize(floor_xy, origin_xy, cell, shape), floor_closing_cells)
    floor_mask = _fill_holes(floor_mask, config.max_floor_hole_m2 / cell**2)
    obstacle_mask = _close(_rasterize(points[in_band, :2], origin_xy, cell, shape), closing_cells)
    free = floor_mask & ~obstacle_mask
    clearance_m = ndimage.distance_transform_edt(free) * cell
    corridor = _corridor(clearance_m, config)
    if not corridor.any():
        raise ValueError(
            f"{where}: empty corridor, no free space with {config.min_clearance_m} m clearance "
            f"in a piece of at least {config.min_corridor_area_m2} m^2 (largest clearance "
            f"{clearance_m.max():.2f} m); lower min_clearance_m or check the obstacle band"
        )
    skeleton = skeletonize(corridor)
    rows, cols = np.nonzero(skeleton)
    samples, forward_xy = _sample_skeleton(rows, cols, config)
    return FloorPlan(
        index=index,
        height_m=height_m,
        origin_xy=origin_xy,
        cell_size_m=cell,
        floor_mask=floor_mask,
        obstacle_mask=obstacle_mask,
        free=free,
        clearance_m=clearance_m,
        corridor=corridor,
        skeleton=skeleton,
        samples_xy=origin_xy + cell * np.stack([cols[samples], rows[samples]], axis=1),
        forward_xy=forward_xy,
    )


def _rasterize(
    xy: np.ndarray, origin_xy: np.ndarray, cell: float, shape: tuple[int, int]
) -> np.ndarray:
    """(H, W) bool image with the cells holding a point of ``xy`` (K, 2) set (others clipped)."""
    cols, rows = np.round((xy - origin_xy) / cell).astype(np.int64).T
    inside = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
    image = np.zeros(shape, dtype=bool)
    image[rows[inside], cols[inside]] = True
    return image


def _close(mask: np.ndarray, radius_cells: int) -> np.ndarray:
    if radius_cells == 0:
        return mask
    return ndimage.binary_closing(mask, structure=disk(radius_cells))


def _fill_holes(mask: np.ndarray, max_cells: float) -> np.ndarray:
    """``mask`` with its holes (pieces of ``~mask`` not touching the border) of at most
    ``max_cells`` cells set."""
    labels, _ = ndimage.label(~mask)
    small = np.bincount(labels.ravel()) <= max_cells
    small[np.unique(np.r_[labels[[0, -1]].ravel(), labels[:, [0, -1]].ravel()])] = False
    small[0] = False  # label 0 is the mask itself
    return mask | small[labels]


def _corridor(clearance_m: np.ndarray, config: PoseSelectionConfig) -> np.ndarray:
    """Clearance threshold, Gaussian smoothing, then pieces of at least the minimum area."""
    cell = config.cell_size_m
    wide = clearance_m >= max(config.min_clearance_m, 0.5 * cell)  # at least a free cell
    corridor = wide
    if config.blur_sigma_m > 0:
        smooth = ndimage.gaussian_filter(wide.astype(np.float64), config.blur_sigma_m / cell)
        corridor = (smooth >= 0.5) & wide
    labels, _ = ndimage.label(corridor, structure=np.ones((3, 3)))
    area_m2 = np.bincount(labels.ravel()) * cell**2
    keep = area_m2 >= config.min_corridor_area_m2
    keep[0] = False
    return keep[labels]


def _skeleton_graph(rows: np.ndarray, cols: np.ndarray, cell: float) -> scipy.sparse.csr_matrix:
    """Symmetric (P, P) graph of 8-adjacent skeleton pixels, weights in metres."""
    index = np.full((rows.max() + 2, cols.max() + 2), -1, dtype=np.int64)  # -1 pad at far end
    index[rows, cols] = np.arange(rows.size)
    sources, targets, weights = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        neighbour = index[rows + dr, cols + dc]  # cols - 1 = -1 wraps onto the -1 pad column
        linked = neighbour >= 0
        sources.append(np.nonzero(linked)[0])
        targets.append(neighbour[linked])
        weights.append(np.full(linked.sum(), cell * math.hypot(dr, dc)))
    source, target, weight = (np.concatenate(a) for a in (sources, targets, weights))
    graph = scipy.sparse.coo_matrix(
        (np.r_[weight, weight], (np.r_[source, target], np.r_[target, source])),
        shape=(rows.size, rows.size),
    )
    return graph.tocsr()


def _sample_skeleton(
    rows: np.ndarray, cols: np.ndarray, config: PoseSelectionConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Samples along the skeleton pixels ``(rows, cols)``, each (P,).

    Returns:
        ``(samples, forward_xy)``: (S,) int64 pixel indices of the samples and (S, 2) float64
        unit forward directions (world xy).
    """
    spacing = config.spacing_m
    graph = _skeleton_graph(rows, cols, config.cell_size_m)
    degree = np.diff(graph.indptr)
    n_pieces, piece = scipy.sparse.csgraph.connected_components(graph, directed=False)
    # One root per piece: its first branch end (degree 1), else its first pixel.
    order = np.lexsort((np.arange(rows.size), degree != 1, piece))
    roots = order[np.r_[0, np.nonzero(np.diff(piece[order]))[0] + 1]]
    distance, predecessor = dijkstra(
        graph, directed=False, indices=roots, min_only=True, return_predecessors=True
    )[:2]
    level = np.floor(distance / spacing)
    parent = np.where(predecessor >= 0, predecessor, np.arange(rows.size))
    crossing = level > level[parent]
    is_end = degree <= 1
    is_end[roots] = True
    candidates = np.nonzero(is_end | crossing)[0]
    candidates = candidates[np.lexsort((distance[candidates], ~is_end[candidates]))]
    xy = np.stack([cols, rows], axis=1).astype(np.float64) * config.cell_size_m
    nearest = np.full(rows.size, math.inf)
    samples, forward = [], []
    for candidate in candidates:  # one iteration per candidate sample, not per pixel
        if nearest[candidate] < 0.5 * spacing:
            continue
        around = dijkstra(graph, directed=False, indices=candidate, limit=0.5 * spacing)
        nearest = np.minimum(nearest, around)
        samples.append(candidate)
        near = np.isfinite(around)
        forward.append(_forward(xy[near] - xy[candidate], distance[near] - distance[candidate]))
    return np.array(samples, dtype=np.int64), np.array(forward).reshape(-1, 2)


def _forward(offsets: np.ndarray, ahead: np.ndarray) -> np.ndarray:
    """Unit principal direction (2,) of ``offsets`` (K, 2), signed towards larger ``ahead``."""
    covariance = offsets.T @ offsets
    angle = 0.5 * math.atan2(2 * covariance[0, 1], covariance[0, 0] - covariance[1, 1])
    direction = np.array([math.cos(angle), math.sin(angle)])
    if float(ahead @ (offsets @ direction)) < 0:
        direction = -direction
    return direction


def view_directions(forward_xy: torch.Tensor, views_per_sample: int = 4) -> torch.Tensor:
    """The horizontal view directions of each sample, in the order of :data:`VIEW_NAMES`.

    Forward, back, left (forward turned 90 deg counter-clockwise seen from above) and right
    are exact sign flips and swaps of ``forward_xy``; the diagonals (8 views) are the unit
    bisectors of forward and left, back and right, back and left, forward and right.

    Args:
        forward_xy: (S, 2) unit forward directions in the world xy plane.
        views_per_sample: 4 or 8 (:data:`VIEWS_PER_SAMPLE`).

    Returns:
        (S, views_per_sample, 2) unit directions, same dtype as ``forward_xy``.

    Raises:
        ValueError: ``views_per_sample`` not in :data:`VIEWS_PER_SAMPLE`.

    Example:
        >>> view_directions(torch.tensor([[1.0, 0.0]]), 8)[0, 4:]  # the diagonals
        tensor([[ 0.7071,  0.7071],
                [-0.7071, -0.7071],
                [-0.7071,  0.7071],
                [ 0.7071, -0.7071]])
    """
    check_views_per_sample(views_per_sample)
    f = forward_xy
    left = torch.stack([-f[:, 1], f[:, 0]], dim=1)
    looks = [f, -f, left, -left]
    if views_per_sample == 8:
        half = math.sqrt(0.5)
        looks += [half * (f + left), -half * (f + left), half * (left - f), half * (f - left)]
    return torch.stack(looks, dim=1)


def view_poses(
    positions_world: ArrayLike, forward_xy: ArrayLike, views_per_sample: int = 4
) -> tuple[torch.Tensor, torch.Tensor]:
    """Horizontal OpenCV cameras per position, yaws evenly spaced from forward
    (:func:`view_directions`: forward, back, left, right, and with 8 views the diagonals).

    Camera z (optical axis) is the view direction, camera y is world -z (down), camera x is
    ``y x z`` (to the right), so every rotation is proper.

    Args:
        positions_world: (S, 3) camera centres, world frame.
        forward_xy: (S, 2) forward directions in the world xy plane (normalised here).
        views_per_sample: k, 4 or 8 (:data:`VIEWS_PER_SAMPLE`).

    Returns:
        ``(T_wc, view_index)``: (k S, 4, 4) float64 poses, sample-major (views of sample ``s``
        at rows ``k s .. k s + k - 1``), and (k S,) int64 indices into :data:`VIEW_NAMES`.

    Raises:
        ShapeError: wrong shapes.
        ValueError: NaN/inf values, zero forward directions or a ``views_per_sample`` not in
            :data:`VIEWS_PER_SAMPLE`.

    Example:
        >>> T_wc, view = view_poses(np.zeros((1, 3)), np.array([[1.0, 0.0]]))
        >>> T_wc[0, :3, 2]  # camera 0 looks along world +x
        tensor([1., 0., 0.], dtype=torch.float64)
        >>> T_wc, view = view_poses(np.zeros((1, 3)), np.array([[1.0, 0.0]]), 8)
        >>> [VIEW_NAMES[i] for i in view[4:6]], T_wc[4, :3, 2]  # 45 deg to the left
        (['forward-left', 'back-right'], tensor([0.7071, 0.7071, 0.0000], dtype=torch.float64))
    """
    positions = torch.as_tensor(positions_world, dtype=torch.float64)
    forward = torch.as_tensor(forward_xy, dtype=torch.float64)
    check_shape(positions, "S,3", "positions_world")
    check_shape(forward, f"{positions.shape[0]},2", "forward_xy")
    check_finite(positions, "positions_world")
    check_finite(forward, "forward_xy")
    length = torch.linalg.vector_norm(forward, dim=1, keepdim=True)
    if not bool((length > 1e-9).all()):
        raise ValueError("forward_xy contains zero-length directions")
    looks = view_directions(forward / length, views_per_sample).reshape(-1, 2)  # (k S, 2)
    zeros = torch.zeros_like(looks[:, 0])
    z_cam = torch.stack([looks[:, 0], looks[:, 1], zeros], dim=1)
    y_cam = torch.stack([zeros, zeros, zeros - 1.0], dim=1)
    x_cam = torch.linalg.cross(y_cam, z_cam)
    T_wc = torch.eye(4, dtype=torch.float64).repeat(looks.shape[0], 1, 1)
    T_wc[:, :3, :3] = torch.stack([x_cam, y_cam, z_cam], dim=2)
    T_wc[:, :3, 3] = positions.repeat_interleave(views_per_sample, dim=0)
    view_index = torch.arange(views_per_sample, dtype=torch.int64).repeat(positions.shape[0])
    return T_wc, view_index


def select_render_poses(
    points: ArrayLike,
    normals: ArrayLike,
    config: PoseSelectionConfig | None = None,
    trajectory: torch.Tensor | None = None,
) -> RenderPoses:
    """Render poses on the free-path corridors of every floor (module docstring, steps 1-5),
    and with ``config.trajectory_gap_m`` set, on the map's trajectory where the corridors
    leave it uncovered (:func:`~diffloc.crossmodal.trajectory_samples.trajectory_samples`;
    these samples come last, floor -1).

    Args:
        points: (N, 3) map points (numpy or torch, floating), world frame (z up), metres.
        normals: (N, 3) normals oriented towards the scanner (floors face up); normalised here.
        config: the settings (default :class:`PoseSelectionConfig`).
        trajectory: (T, 4, 4) camera-to-world poses of the run that made the map, in time
            order; needed when ``config.trajectory_gap_m`` is set, ignored otherwise.

    Returns:
        The :class:`RenderPoses`: ``config.views_per_sample`` views per sample, floors lowest
        first.

    Raises:
        ShapeError: ``points`` or ``normals`` not (N, 3).
        TypeError: non-floating arrays.
        ValueError: NaN/inf values, empty input, zero normals, no upward normal
            ("no floor found"), a floor with an empty corridor, or ``trajectory_gap_m`` set
            without a trajectory.

    Example:
        >>> import numpy as np
        >>> xy = np.mgrid[0:8:0.05, 0:2:0.05].reshape(2, -1).T
        >>> points = np.concatenate([np.c_[xy, np.full(len(xy), z)] for z in (0.0, 3.0)])
        >>> normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))  # two 8 x 2 m floors, 3 m apart
        >>> selection = select_render_poses(points, normals)
        >>> selection.T_wc.shape, selection.floors[1].height_m
        (torch.Size([32, 4, 4]), 3.0)
    """
    config = PoseSelectionConfig() if config is None else config
    points, normals = _checked_cloud(points, normals)
    up = _faces_up(normals, config)
    heights = _find_floors(points[up, 2], config)
    floors = tuple(_floor_plan(points, up, float(h), k, config) for k, h in enumerate(heights))
    counts = np.array([len(plan.samples_xy) for plan in floors])
    positions = np.concatenate(
        [np.c_[plan.samples_xy, np.full(len(plan.samples_xy), plan.height_m)] for plan in floors]
    )
    positions[:, 2] += config.camera_height_m
    forward = np.concatenate([plan.forward_xy for plan in floors])
    floor_of_sample = torch.from_numpy(np.repeat(np.arange(len(floors)), counts))
    if config.trajectory_gap_m is not None:
        if trajectory is None:
            raise ValueError(
                "trajectory_gap_m is set but no trajectory was given (the map's run poses)"
            )
        extra, ahead = trajectory_samples(
            trajectory, torch.from_numpy(positions), config.trajectory_gap_m
        )
        positions = np.concatenate([positions, extra.numpy()])
        forward = np.concatenate([forward, ahead.numpy()])
        floor_of_sample = torch.cat([floor_of_sample, torch.full((len(extra),), -1)])
    views = config.views_per_sample
    T_wc, view_index = view_poses(positions, forward, views)
    return RenderPoses(
        T_wc=T_wc,
        floor_index=floor_of_sample.repeat_interleave(views),
        sample_index=torch.arange(len(positions)).repeat_interleave(views),
        view_index=view_index,
        floors=floors,
    )


def plot_floor_plan(
    plan: FloorPlan,
    path: str | os.PathLike,
    arrow_m: float | None = None,
    dpi: int = 100,
    views_per_sample: int = 4,
) -> Path:
    """Write a PNG of every step of one floor (like seed 2's Fig. 3).

    Panels: occupancy (floor, obstacles), normalised distance transform, corridor, skeleton,
    and the samples with their view directions (forward in red) over the occupancy.

    Args:
        plan: the floor.
        path: the ``.png`` file (written atomically; parent folders are created).
        arrow_m: length of the view arrows in metres (default: 0.4 times the median distance
            from a sample to its nearest other sample, or 0.5 m with fewer than two samples).
        dpi: resolution; the figure is 15 x 9 inches.
        views_per_sample: the views drawn per sample (:func:`view_directions`).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Example: see the module docstring (:func:`write_floor_plan_figures` calls this per floor).
    """
    occupancy = np.where(plan.free, 1.0, np.where(plan.obstacle_mask, 0.0, 0.35))
    skeleton_view = 0.3 * plan.corridor + 0.7 * plan.skeleton
    panels = (
        ("occupancy (white free, black obstacle, grey no floor)", occupancy, "gray"),
        ("normalised distance transform", plan.clearance_normalized, "viridis"),
        ("free-path corridor", plan.corridor, "gray"),
        ("skeleton", skeleton_view, "magma"),
        (f"{len(plan.samples_xy)} samples, {views_per_sample} views each", occupancy, "gray"),
    )
    fig = Figure(figsize=(15.0, 9.0), dpi=dpi)
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 3).ravel()
    for ax, (title, image, cmap) in zip(axes, panels, strict=False):
        ax.imshow(image, cmap=cmap, origin="lower", extent=plan.extent, interpolation="nearest")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    axes[-1].set_axis_off()
    _draw_views(axes[-2], plan, arrow_m, views_per_sample)
    fig.suptitle(f"floor {plan.index}, z = {round(plan.height_m, 2) + 0.0:.2f} m")  # no "-0.00"
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    atomic_write_bytes(path, buffer.getvalue())
    return Path(path)


def _draw_views(ax: Axes, plan: FloorPlan, arrow_m: float | None, views_per_sample: int) -> None:
    xy = plan.samples_xy
    if arrow_m is None:
        arrow_m = 0.5
        if len(xy) > 1:
            gaps, _ = cKDTree(xy).query(xy, k=2)
            arrow_m = 0.4 * float(np.median(gaps[:, 1]))
    directions = view_directions(torch.from_numpy(plan.forward_xy), views_per_sample).numpy()
    for view in range(views_per_sample):
        direction = directions[:, view]
        ax.quiver(
            xy[:, 0],
            xy[:, 1],
            arrow_m * direction[:, 0],
            arrow_m * direction[:, 1],
            color="red" if view == 0 else "tab:blue",
            angles="xy",
            scale_units="xy",
            scale=1.0,
            width=0.004,
        )
    ax.scatter(xy[:, 0], xy[:, 1], s=12, c="orange", zorder=3)


def write_floor_plan_figures(selection: RenderPoses, out_dir: str | os.PathLike) -> list[Path]:
    """Write ``floor_<k>.png`` (:func:`plot_floor_plan`) for every floor of ``selection``.

    Args:
        selection: the result of :func:`select_render_poses`.
        out_dir: the folder (created if missing).

    Returns:
        The written paths, one per floor.

    Example: see the module docstring.
    """
    out = Path(out_dir)
    views = selection.views_per_sample
    return [
        plot_floor_plan(plan, out / f"floor_{plan.index}.png", views_per_sample=views)
        for plan in selection.floors
    ]
