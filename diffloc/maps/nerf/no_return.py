"""Lidar rays without a return: the directions of a spinning lidar's firing grid in which a
sweep measured nothing within the sensor's range.

A spinning lidar fires a known grid of directions every sweep: ``beams`` lasers at fixed
elevations, each at ``azimuth_steps`` azimuths (the pattern a real user reads from the driver
configuration or the ring index). A grid direction with no return in a sweep saw no surface
between the sensor's minimum and maximum range: sky, or something beyond range (or, on a real
sensor, a dropout on a dark or specular surface). The returns are binned into the
``(beam, azimuth)`` grid by their direction in the lidar frame; the empty cells are the
no-return directions. The pattern is read from the sequence's calibration (``calib.yaml``,
``lidar:``, which diffloc's simulator writes); without it nothing is guessed and a clear
error is raised.

Grid (the simulated lidar's, ``diffloc.sim.lidar.spinning_lidar_directions``; lidar frame x
forward, y left, z up): beam ``b`` has elevation ``linspace(vfov_min_deg, vfov_max_deg,
beams)[b]`` (the midpoint for one beam), azimuth step ``a`` is ``2 pi a / azimuth_steps``
from +x towards +y.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from diffloc.checks import check_int_at_least, check_number, check_shape
from diffloc.io.sequence import SequenceData

__all__ = ["LidarPattern", "NoReturnRays", "no_return_mask", "no_return_rays"]

_PATTERN_KEYS = ("beams", "vfov_min_deg", "vfov_max_deg", "azimuth_steps", "max_range_m")


@dataclass(frozen=True)
class LidarPattern:
    """The firing grid of a spinning lidar.

    Attributes:
        beams: lasers, evenly spread over the elevations below.
        vfov_min_deg: elevation of the lowest beam, degrees.
        vfov_max_deg: elevation of the highest beam, degrees.
        azimuth_steps: firings per revolution.
        max_range_m: farthest return the sensor reports, metres.
    """

    beams: int
    vfov_min_deg: float
    vfov_max_deg: float
    azimuth_steps: int
    max_range_m: float

    def __post_init__(self) -> None:
        check_int_at_least(self.beams, "lidar.beams", 1)
        check_int_at_least(self.azimuth_steps, "lidar.azimuth_steps", 1)
        check_number(self.vfov_min_deg, "lidar.vfov_min_deg", -90.0, 90.0)
        check_number(self.vfov_max_deg, "lidar.vfov_max_deg", self.vfov_min_deg, 90.0)
        check_number(self.max_range_m, "lidar.max_range_m", 0.0, open_low=True)

    @classmethod
    def from_calibration(cls, lidar: dict | None, where: str) -> LidarPattern:
        """The pattern recorded in a calibration's ``lidar`` mapping.

        Args:
            lidar: the ``lidar:`` mapping of ``calib.yaml`` (``Calibration.lidar``), or ``None``.
            where: names the sequence in error messages.

        Raises:
            ValueError: no mapping, or one without the grid's keys (``beams``,
                ``vfov_min_deg``, ``vfov_max_deg``, ``azimuth_steps``, ``max_range_m``).

        Example:
            >>> LidarPattern.from_calibration({"beams": 2, "vfov_min_deg": -10,
            ...     "vfov_max_deg": 10, "azimuth_steps": 4, "max_range_m": 50}, "demo").beams
            2
        """
        if lidar is None:
            raise ValueError(
                f"{where}: the calibration records no lidar pattern (calib.yaml has no "
                f"'lidar:' mapping), so the directions without a return are unknown; record "
                f"the spinning lidar's {', '.join(_PATTERN_KEYS)}"
            )
        missing = [key for key in _PATTERN_KEYS if key not in lidar]
        if missing:
            raise ValueError(
                f"{where}: the calibration's lidar mapping lacks {missing}, so the directions "
                f"without a return are unknown (it has {sorted(lidar)})"
            )
        return cls(**{key: lidar[key] for key in _PATTERN_KEYS})

    def elevations(self) -> np.ndarray:
        """(beams,) float64 beam elevations, radians, lowest first."""
        if self.beams == 1:
            return np.radians([0.5 * (self.vfov_min_deg + self.vfov_max_deg)])
        return np.radians(np.linspace(self.vfov_min_deg, self.vfov_max_deg, self.beams))

    def directions(self) -> np.ndarray:
        """(beams, azimuth_steps, 3) float64 unit directions in the lidar frame."""
        azimuth = 2.0 * np.pi * np.arange(self.azimuth_steps) / self.azimuth_steps
        el, az = np.meshgrid(self.elevations(), azimuth, indexing="ij")
        return np.stack((np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), axis=-1)


def no_return_mask(points_lidar: np.ndarray, pattern: LidarPattern, where: str) -> np.ndarray:
    """Grid cells of one sweep without a return.

    Each return is binned to the nearest beam elevation and azimuth step of its direction
    (vectorised, no loop over points); a return farther than a quarter of the grid spacing
    from its cell's direction means the pattern does not describe this sweep, which is refused.

    Args:
        points_lidar: (P, 3) returns of the sweep in the lidar frame (any order, P >= 0).
        pattern: the lidar's firing grid.
        where: names the sweep in error messages.

    Returns:
        (beams, azimuth_steps) bool, true where the sweep has no return.

    Raises:
        ValueError: a return off the grid, or a zero-length return.

    Example:
        >>> pattern = LidarPattern(2, -10.0, 10.0, 4, 50.0)
        >>> hits = 5.0 * pattern.directions()[[0, 1], [0, 3]]  # beam 0 at azimuth step 0, ...
        >>> no_return_mask(hits, pattern, "demo").astype(int).tolist()
        [[0, 1, 1, 1], [1, 1, 1, 0]]
    """
    check_shape(points_lidar, "P,3", "points_lidar")
    points = np.asarray(points_lidar, dtype=np.float64)
    ranges = np.linalg.norm(points, axis=1)
    if (ranges <= 0).any():
        raise ValueError(f"{where}: a return at zero range has no direction")
    elevation = np.arcsin(np.clip(points[:, 2] / np.maximum(ranges, 1e-12), -1.0, 1.0))
    grid = pattern.elevations()
    beam = np.abs(elevation[:, None] - grid[None]).argmin(axis=1)
    azimuth_step = 2.0 * np.pi / pattern.azimuth_steps
    steps = np.arctan2(points[:, 1], points[:, 0]) / azimuth_step
    column = np.rint(steps).astype(np.int64) % pattern.azimuth_steps
    elevation_step = np.diff(grid).min() if len(grid) > 1 else math.pi
    off_elevation = np.abs(elevation - grid[beam]) > 0.25 * elevation_step
    off_azimuth = np.abs(steps - np.rint(steps)) > 0.25
    off = off_elevation | off_azimuth
    if off.any():
        raise ValueError(
            f"{where}: {int(off.sum())} of {len(points)} returns lie off the recorded lidar grid "
            f"({pattern.beams} beams over {pattern.vfov_min_deg}..{pattern.vfov_max_deg} deg, "
            f"{pattern.azimuth_steps} azimuth steps): the pattern does not describe this sweep"
        )
    empty = np.ones((pattern.beams, pattern.azimuth_steps), dtype=bool)
    empty[beam, column] = False
    return empty


@dataclass
class NoReturnRays:
    """Lidar rays without a return (world frame, float32).

    Attributes:
        origins: (M, 3) sensor positions.
        directions: (M, 3) unit directions.
    """

    origins: torch.Tensor
    directions: torch.Tensor

    def __len__(self) -> int:
        return len(self.directions)


def no_return_rays(seq: SequenceData, sweeps: list[int]) -> NoReturnRays:
    """The no-return rays of some sweeps of a sequence, in the world frame.

    Args:
        seq: a sequence with lidar sweeps, their poses ``T_wl`` and the lidar pattern in its
            calibration (``seq.info["calib"].lidar``).
        sweeps: indices of the sweeps.

    Returns:
        The rays (origin at the sensor of each sweep, every grid direction without a return).

    Raises:
        ValueError: no sweep given, no recorded pattern, or returns off the pattern.
    """
    where = f"sequence {seq.name!r}"
    if not sweeps:
        raise ValueError(f"{where}: no lidar sweeps for these frames")
    calib = seq.info.get("calib")
    pattern = LidarPattern.from_calibration(getattr(calib, "lidar", None), where)
    directions_lidar = pattern.directions()
    origins, directions = [], []
    for i in sweeps:
        empty = no_return_mask(seq.load_lidar(i).numpy(), pattern, f"{where}, sweep {i}")
        T_wl = seq.T_wl[i].numpy()
        directions.append(directions_lidar[empty] @ T_wl[:3, :3].T)
        origins.append(np.broadcast_to(T_wl[:3, 3], directions[-1].shape))
    return NoReturnRays(
        origins=torch.from_numpy(np.concatenate(origins).astype(np.float32)),
        directions=torch.from_numpy(np.concatenate(directions).astype(np.float32)),
    )
