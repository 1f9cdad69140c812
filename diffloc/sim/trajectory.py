"""Smooth body trajectories along a route of waypoints (walking or driving through a world).

A route is an ordered polyline of ground-level waypoints ``(K, 3)`` in the world frame. The body
path follows it with every interior corner replaced by a circular arc tangent to both adjacent
segments (a fillet), so the path is C1-continuous and never leaves the polyline by more than
``corner_smoothing_m``. Frames come at a constant rate; between them the body travels at the
speed profile ``v(t) = speed_mps + speed_variation_mps * sin(2 pi t / speed_period_s + phase)``
from an arc length ``start_offset_m`` along the path, so two traversals of one route at other
speeds, starts or phases do not land on each other's frame positions. Each frame gets a body
pose ``T_wb`` with

- the ROS body convention: x forward, y left, z up;
- yaw along the horizontal direction of travel; the body stays upright on slopes and stairs
  (no roll, no pitch) apart from small periodic head sways in yaw and pitch;
- height ``route z + body_height_m + bob``, where the bob is a small vertical oscillation with
  one period per walking step.

:func:`interpolate_pose` gives sub-frame poses (rolling shutter, motion blur, lidar sweeps at
their own rate) by geodesic interpolation on SE(3).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from diffloc.checks import check_finite, check_shape
from diffloc.geometry.se3 import compose, invert, se3_exp, se3_log

__all__ = [
    "TrajectoryConfig",
    "arc_lengths",
    "interpolate_pose",
    "make_trajectory",
    "smooth_route",
    "validate_trajectory_config",
]

# The pitch sway runs at this multiple of the yaw sway frequency, so the two never fall into step.
GOLDEN_RATIO = 0.5 * (1.0 + math.sqrt(5.0))
# Lengths (metres) below which a segment or a horizontal direction counts as degenerate.
_EPS_LENGTH = 1e-9
# Turn angles (radians) below which a corner is treated as straight.
_EPS_ANGLE = 1e-9
# Seconds by which a query time may fall outside the trajectory and still be clamped to its end.
_TIME_TOLERANCE_S = 1e-6


@dataclass
class TrajectoryConfig:
    """How a body moves along a route (the Hydra ``scene.trajectory`` group).

    Attributes:
        speed_mps: mean speed along the path, m/s (0.8 is a slow indoor walk).
        speed_variation_mps: amplitude of the sinusoidal speed variation around ``speed_mps``,
            m/s (0 walks at constant speed; must stay below ``speed_mps``).
        speed_period_s: period of that variation, seconds.
        frame_rate_hz: camera frame rate, Hz; at constant speed poses are ``speed / rate``
            metres apart.
        body_height_m: height of the body frame above the route (the floor), metres.
        yaw_sway_deg: amplitude of the periodic head turning around the vertical, degrees.
        pitch_sway_deg: amplitude of the periodic nodding, degrees.
        sway_period_s: period of the yaw sway, seconds (the pitch sway is faster by the golden
            ratio).
        bob_amplitude_m: amplitude of the vertical walking bob, metres (0 for a car).
        bob_wavelength_m: distance travelled per bob period (one walking step), metres.
        corner_smoothing_m: how far before and after each corner the path starts to turn,
            metres; the rounded path stays within this distance of the route polyline. It is
            reduced at a corner whose adjacent segments are shorter than twice this value.
        max_frames: keep at most this many frames (0 keeps all).
        start_time_s: timestamp of the first frame, seconds.
    """

    speed_mps: float = 0.8
    speed_variation_mps: float = 0.0
    speed_period_s: float = 15.0
    frame_rate_hz: float = 5.0
    body_height_m: float = 1.5
    yaw_sway_deg: float = 8.0
    pitch_sway_deg: float = 2.0
    sway_period_s: float = 6.0
    bob_amplitude_m: float = 0.02
    bob_wavelength_m: float = 0.7
    corner_smoothing_m: float = 1.0
    max_frames: int = 0
    start_time_s: float = 0.0


def validate_trajectory_config(cfg: TrajectoryConfig) -> None:
    """Raise ``ValueError`` naming the first unusable field of ``cfg``."""
    positive = ("speed_mps", "frame_rate_hz", "sway_period_s", "bob_wavelength_m", "speed_period_s")
    for name in positive:
        value = getattr(cfg, name)
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise ValueError(f"trajectory.{name} must be a positive finite number, got {value!r}")
    for name in (
        "body_height_m",
        "yaw_sway_deg",
        "pitch_sway_deg",
        "bob_amplitude_m",
        "corner_smoothing_m",
        "start_time_s",
        "speed_variation_mps",
    ):
        value = getattr(cfg, name)
        if not (isinstance(value, int | float) and math.isfinite(value)):
            raise ValueError(f"trajectory.{name} must be a finite number, got {value!r}")
    if not 0.0 <= cfg.speed_variation_mps < cfg.speed_mps:
        raise ValueError(
            f"trajectory.speed_variation_mps must be in [0, speed_mps={cfg.speed_mps}) so the "
            f"body never stops or reverses, got {cfg.speed_variation_mps}"
        )
    if cfg.corner_smoothing_m < 0:
        raise ValueError(
            f"trajectory.corner_smoothing_m must be >= 0, got {cfg.corner_smoothing_m}"
        )
    if isinstance(cfg.max_frames, bool) or not isinstance(cfg.max_frames, int | np.integer):
        raise ValueError(f"trajectory.max_frames must be an integer, got {cfg.max_frames!r}")
    if cfg.max_frames < 0:
        raise ValueError(f"trajectory.max_frames must be >= 0 (0 = no cap), got {cfg.max_frames}")


def _as_route(route: np.ndarray | torch.Tensor) -> np.ndarray:
    """Validated (K, 3) float64 route with consecutive duplicate waypoints removed."""
    if isinstance(route, torch.Tensor):
        route = route.detach().cpu().numpy()
    route = np.asarray(route, dtype=np.float64)
    check_shape(route, "K,3", "route")
    check_finite(route, "route")
    if len(route) < 2:
        raise ValueError(f"route needs at least 2 waypoints, got {len(route)}")
    step = np.linalg.norm(np.diff(route, axis=0), axis=1)
    route = route[np.concatenate([[True], step > _EPS_LENGTH])]
    if len(route) < 2:
        raise ValueError("route needs at least 2 distinct waypoints; all of them coincide")
    return route


def _unit(vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row-normalised ``vectors`` (..., 3) and their norms (...,); zero rows stay zero."""
    norms = np.linalg.norm(vectors, axis=-1)
    safe = np.where(norms > _EPS_LENGTH, norms, 1.0)
    return vectors / safe[..., None], norms


def _fill_invalid(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Replace rows of ``values`` where ``valid`` is false by the nearest earlier valid row.

    Leading invalid rows take the first valid row. ``valid`` must have at least one true entry.
    """
    index = np.where(valid, np.arange(len(valid)), 0)
    index = np.maximum.accumulate(index)
    first = int(np.argmax(valid))
    index = np.where(np.arange(len(valid)) < first, first, index)
    return values[index]


def _horizontal_directions(points: np.ndarray) -> np.ndarray:
    """(K-1, 3) unit horizontal directions of the segments of a polyline (K, 3).

    Vertical segments take the direction of the nearest earlier (or first) non-vertical one.

    Raises:
        ValueError: no segment has a horizontal extent, so no heading is defined.
    """
    horizontal = np.diff(points, axis=0)
    horizontal[:, 2] = 0.0
    units, norms = _unit(horizontal)
    valid = norms > _EPS_LENGTH
    if not valid.any():
        raise ValueError("route has no horizontal extent, so the walking direction is undefined")
    return _fill_invalid(units, valid)


def _offset_route(route: np.ndarray, offset_m: float) -> np.ndarray:
    """Shift a polyline sideways by ``offset_m`` (left of travel positive), mitering corners.

    Each segment moves along its horizontal left normal; interior waypoints move to the
    intersection of the two shifted segments (the miter, capped at very sharp turns).

    Raises:
        ValueError: a segment would reverse (the offset is too large for it).
    """
    if offset_m == 0.0:
        return route
    heading = _horizontal_directions(route)
    left = np.stack([-heading[:, 1], heading[:, 0], np.zeros(len(heading))], axis=1)
    n_in = np.concatenate([left[:1], left], axis=0)
    n_out = np.concatenate([left, left[-1:]], axis=0)
    cos_turn = (n_in * n_out).sum(axis=1)
    # |n_in + n_out| / (1 + cos) is the miter length factor; cap it near U-turns.
    miter = (n_in + n_out) / np.maximum(1.0 + cos_turn, 0.1)[:, None]
    shifted = route + offset_m * miter
    before, after = np.diff(route, axis=0), np.diff(shifted, axis=0)
    reversed_ = (before * after).sum(axis=1) <= 0.0
    if reversed_.any():
        j = int(np.argmax(reversed_))
        raise ValueError(
            f"lateral_offset_m={offset_m} is too large for route segment {j} "
            f"(length {np.linalg.norm(before[j]):.3f} m): the offset segment reverses"
        )
    return shifted


@dataclass
class _Path:
    """A polyline with filleted corners as alternating line and arc pieces (numpy, float64).

    Piece ``j`` starts at arc length ``starts[j]``, has length ``lengths[j]`` and begins at
    ``origins[j]`` heading along ``directions[j]``. Arcs (``radii > 0``) bend towards
    ``bends[j]`` (unit, perpendicular to ``directions[j]``): at distance ``sigma`` into the piece,
    ``p = origin + r (1 - cos a) bend + r sin(a) direction`` with ``a = sigma / r``.
    """

    starts: np.ndarray
    lengths: np.ndarray
    origins: np.ndarray
    directions: np.ndarray
    bends: np.ndarray
    radii: np.ndarray

    @property
    def length(self) -> float:
        return float(self.starts[-1] + self.lengths[-1])

    def evaluate(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (M, 3) and unit tangents (M, 3) at arc lengths ``s`` (M,)."""
        piece = np.clip(np.searchsorted(self.starts, s, side="right") - 1, 0, len(self.starts) - 1)
        sigma = np.clip(s - self.starts[piece], 0.0, self.lengths[piece])[:, None]
        origin, direction = self.origins[piece], self.directions[piece]
        bend, radius = self.bends[piece], self.radii[piece][:, None]
        is_arc = radius > 0.0
        angle = sigma / np.where(is_arc, radius, 1.0)
        arc_pos = (
            origin + radius * (1.0 - np.cos(angle)) * bend + radius * np.sin(angle) * direction
        )
        arc_tan = np.sin(angle) * bend + np.cos(angle) * direction
        line_pos = origin + sigma * direction
        position = np.where(is_arc, arc_pos, line_pos)
        tangent = np.where(is_arc, arc_tan, direction)
        return position, tangent


def _fillet(route: np.ndarray, smoothing_m: float) -> _Path:
    """Round the interior corners of a polyline (K, 3) with tangent circular arcs.

    At a corner turning by ``phi`` the arc starts and ends ``d = min(smoothing_m, half of each
    adjacent segment)`` from the corner, so its radius is ``d / tan(phi / 2)`` and its farthest
    point is ``d tan(phi / 4) < d`` from the corner.
    """
    segments = np.diff(route, axis=0)
    units, seg_len = _unit(segments)
    u_in, u_out = units[:-1], units[1:]
    cos_turn = np.clip((u_in * u_out).sum(axis=1), -1.0, 1.0)
    turn = np.arccos(cos_turn)
    straight = turn < _EPS_ANGLE
    tangent_len = np.minimum(smoothing_m, 0.5 * np.minimum(seg_len[:-1], seg_len[1:]))
    tangent_len = np.where(straight, 0.0, tangent_len)
    tan_half = np.tan(0.5 * np.where(straight, 1.0, turn))
    radius = np.where(straight, 0.0, tangent_len / tan_half)
    bend, bend_norm = _unit(u_out - cos_turn[:, None] * u_in)
    # U-turns have no turning plane; any perpendicular works as the radius there is ~0.
    fallback, fallback_norm = _unit(np.cross(u_in, np.array([0.0, 0.0, 1.0])))
    fallback = np.where(fallback_norm[:, None] > _EPS_LENGTH, fallback, np.cross(u_in, [1, 0, 0]))
    bend = np.where(bend_norm[:, None] > 1e-12, bend, _unit(fallback)[0])

    d_start = np.concatenate([[0.0], tangent_len])  # trimmed off the start of each segment
    d_end = np.concatenate([tangent_len, [0.0]])  # trimmed off the end of each segment
    line_len = np.maximum(seg_len - d_start - d_end, 0.0)
    line_origin = route[:-1] + d_start[:, None] * units
    arc_len = radius * np.where(straight, 0.0, turn)
    arc_origin = route[1:-1] - tangent_len[:, None] * u_in

    pieces = 2 * len(segments) - 1
    lengths = np.empty(pieces)
    origins = np.empty((pieces, 3))
    directions = np.empty((pieces, 3))
    bends = np.zeros((pieces, 3))
    radii = np.zeros(pieces)
    lengths[0::2], lengths[1::2] = line_len, arc_len
    origins[0::2], origins[1::2] = line_origin, arc_origin
    directions[0::2], directions[1::2] = units, u_in
    bends[1::2], radii[1::2] = bend, radius
    starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    return _Path(starts, lengths, origins, directions, bends, radii)


def _route_path(
    route: np.ndarray | torch.Tensor,
    corner_smoothing_m: float,
    lateral_offset_m: float,
    reverse: bool,
) -> _Path:
    """The validated, optionally reversed and offset, corner-rounded path of a route."""
    route = _as_route(route)
    for name, value in (
        ("corner_smoothing_m", corner_smoothing_m),
        ("lateral_offset_m", lateral_offset_m),
    ):
        if not math.isfinite(value):
            raise ValueError(f"{name} must be finite, got {value}")
    if corner_smoothing_m < 0:
        raise ValueError(f"corner_smoothing_m must be >= 0, got {corner_smoothing_m}")
    if reverse:
        route = route[::-1].copy()
    route = _offset_route(route, float(lateral_offset_m))
    return _fillet(route, float(corner_smoothing_m))


def smooth_route(
    route: np.ndarray | torch.Tensor,
    corner_smoothing_m: float,
    spacing_m: float,
    *,
    lateral_offset_m: float = 0.0,
    reverse: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Sample the corner-rounded route at a constant arc-length spacing (no body motion).

    Args:
        route: (K, 3) waypoints, K >= 2.
        corner_smoothing_m: distance before and after each corner where the turn starts (>= 0).
        spacing_m: arc length between consecutive samples (> 0).
        lateral_offset_m: shift of the path to the left of the direction of travel, metres.
        reverse: traverse the route from its last waypoint to its first.

    Returns:
        positions (N, 3) and unit tangents (N, 3), float64; the first sample is the (offset)
        first waypoint and ``N = floor(length / spacing) + 1``.

    Example:
        >>> p, t = smooth_route(np.array([[0.0, 0, 0], [2, 0, 0]]), 0.5, 0.5)
        >>> p[:, 0]
        array([0. , 0.5, 1. , 1.5, 2. ])
    """
    if not (math.isfinite(spacing_m) and spacing_m > 0):
        raise ValueError(f"spacing_m must be positive and finite, got {spacing_m}")
    path = _route_path(route, corner_smoothing_m, lateral_offset_m, reverse)
    count = int(math.floor(path.length / spacing_m + 1e-9)) + 1
    return path.evaluate(np.arange(count) * spacing_m)


def arc_lengths(
    cfg: TrajectoryConfig, length_m: float, start_offset_m: float = 0.0, phase: float = 0.0
) -> np.ndarray:
    """Arc lengths (N,) of the frames of a traversal of a path ``length_m`` long.

    Frame ``i`` comes at ``t_i = i / frame_rate_hz`` and lies at
    ``s(t) = s0 + v t + (A P / 2 pi) (cos(phase) - cos(2 pi t / P + phase))``, the integral of
    the speed profile ``v + A sin(2 pi t / P + phase)`` (``v = speed_mps``,
    ``A = speed_variation_mps``, ``P = speed_period_s``, ``s0 = start_offset_m``); frames run
    while ``s <= length_m`` (at most ``max_frames`` when that is set).

    Raises:
        ValueError: ``start_offset_m`` outside ``[0, length_m]``.

    Example:
        >>> arc_lengths(TrajectoryConfig(speed_mps=1.0, frame_rate_hz=2.0), 2.0, 0.3)
        array([0.3, 0.8, 1.3, 1.8])
    """
    if not (math.isfinite(start_offset_m) and 0.0 <= start_offset_m <= length_m):
        raise ValueError(
            f"start_offset_m must be in [0, {length_m:.3f}] (the path length), got {start_offset_m}"
        )
    slowest = cfg.speed_mps - cfg.speed_variation_mps
    bound = int(math.floor((length_m - start_offset_m) / slowest * cfg.frame_rate_hz)) + 2
    t = np.arange(bound) / cfg.frame_rate_hz
    omega = 2.0 * math.pi / cfg.speed_period_s
    wave = (math.cos(phase) - np.cos(omega * t + phase)) / omega
    s = start_offset_m + cfg.speed_mps * t + cfg.speed_variation_mps * wave
    s = s[s <= length_m + 1e-9]
    return s[: cfg.max_frames] if cfg.max_frames > 0 else s


def _rotation_zy(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations ``Rz(yaw) @ Ry(pitch)``."""
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    zero = np.zeros_like(yaw)
    rows = [
        [cy * cp, -sy, cy * sp],
        [sy * cp, cy, sy * sp],
        [-sp, zero, cp],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def make_trajectory(
    route: np.ndarray | torch.Tensor,
    cfg: TrajectoryConfig,
    *,
    lateral_offset_m: float = 0.0,
    reverse: bool = False,
    phase: float = 0.0,
    start_offset_m: float = 0.0,
) -> tuple[np.ndarray, torch.Tensor]:
    """Timestamped body poses walking along a route at the configured speed profile.

    Args:
        route: (K, 3) ordered ground-level waypoints in the world frame, K >= 2.
        cfg: speed, frame rate, body height, sways, bob and corner smoothing.
        lateral_offset_m: shift of the path to the left of the direction of travel, metres
            (a "laterally offset" query route).
        reverse: traverse the route from its last waypoint to its first (facing that way).
        phase: phase (radians) of the sways, the bob and the speed variation, so repeated
            traversals differ.
        start_offset_m: arc length along the (reversed, offset) path of the first frame, metres.

    Returns:
        timestamps (N,) float64 seconds, ``start_time_s + i / frame_rate_hz``, and body-to-world
        poses T_wb (N, 4, 4) torch.float64 (x forward, y left, z up). Frames lie at the arc
        lengths of :func:`arc_lengths` (at constant speed ``speed_mps / frame_rate_hz`` apart),
        plus the vertical bob.

    Raises:
        ValueError: fewer than 2 distinct waypoints, NaN input, a non-positive speed or rate,
            a speed variation not below the speed, a start offset off the path, a lateral
            offset too large for a route segment, or a purely vertical route.

    Example:
        >>> cfg = TrajectoryConfig(speed_mps=1.0, frame_rate_hz=2.0)
        >>> t, T_wb = make_trajectory(np.array([[0.0, 0, 0], [2, 0, 0]]), cfg)
        >>> t
        array([0. , 0.5, 1. , 1.5, 2. ])
        >>> T_wb.shape
        torch.Size([5, 4, 4])
    """
    validate_trajectory_config(cfg)
    if not (math.isfinite(lateral_offset_m) and math.isfinite(phase)):
        raise ValueError(
            f"lateral_offset_m and phase must be finite, got {lateral_offset_m}, {phase}"
        )
    path = _route_path(route, cfg.corner_smoothing_m, lateral_offset_m, reverse)
    s = arc_lengths(cfg, path.length, start_offset_m, phase)
    positions, tangents = path.evaluate(s)
    count = len(positions)
    elapsed = np.arange(count) / cfg.frame_rate_hz
    travelled = s - start_offset_m

    horizontal = np.hypot(tangents[:, 0], tangents[:, 1])
    valid = horizontal > 1e-6
    if not valid.any():
        raise ValueError("route has no horizontal extent, so the walking direction is undefined")
    yaw = _fill_invalid(np.arctan2(tangents[:, 1], tangents[:, 0]), valid)

    omega = 2.0 * math.pi / cfg.sway_period_s
    yaw = yaw + math.radians(cfg.yaw_sway_deg) * np.sin(omega * elapsed + phase)
    pitch = math.radians(cfg.pitch_sway_deg) * np.sin(GOLDEN_RATIO * (omega * elapsed + phase))
    bob = cfg.bob_amplitude_m * np.sin(2.0 * math.pi * travelled / cfg.bob_wavelength_m + phase)

    T_wb = np.zeros((count, 4, 4))
    T_wb[:, :3, :3] = _rotation_zy(yaw, pitch)
    T_wb[:, :3, 3] = positions
    T_wb[:, 2, 3] += cfg.body_height_m + bob
    T_wb[:, 3, 3] = 1.0
    timestamps = cfg.start_time_s + elapsed
    return timestamps, torch.from_numpy(T_wb)


def interpolate_pose(
    timestamps: np.ndarray | torch.Tensor,
    T: np.ndarray | torch.Tensor,
    t_query: np.ndarray | torch.Tensor,
) -> torch.Tensor:
    """Geodesic (constant-twist) interpolation of timestamped poses.

    Between samples ``i`` and ``i + 1`` the pose is ``T_i exp(alpha log(T_i^-1 T_{i+1}))`` with
    ``alpha = (t - t_i) / (t_{i+1} - t_i)``. Queries up to 1 microsecond outside the sampled
    interval are clamped to its ends.

    Args:
        timestamps: (N,) strictly increasing times, seconds.
        T: (N, 4, 4) poses at those times (any frame pair, e.g. T_wb).
        t_query: (M,) query times within ``[timestamps[0], timestamps[-1]]``.

    Returns:
        (M, 4, 4) torch.float64 interpolated poses.

    Raises:
        ValueError: bad shapes, NaN, timestamps not increasing, or a query out of range.

    Example:
        >>> T = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
        >>> T[1, 0, 3] = 2.0
        >>> interpolate_pose(np.array([0.0, 1.0]), T, np.array([0.25]))[0, 0, 3]
        tensor(0.5000, dtype=torch.float64)
    """
    times = np.asarray(
        timestamps.detach().cpu().numpy() if isinstance(timestamps, torch.Tensor) else timestamps,
        dtype=np.float64,
    )
    query = np.asarray(
        t_query.detach().cpu().numpy() if isinstance(t_query, torch.Tensor) else t_query,
        dtype=np.float64,
    )
    poses = torch.as_tensor(T).detach().to(torch.float64).cpu()
    check_shape(times, "N", "timestamps")
    check_shape(poses, f"{len(times)},4,4", "T")
    check_shape(query, "M", "t_query")
    check_finite(times, "timestamps")
    check_finite(poses, "T")
    check_finite(query, "t_query")
    if len(times) == 0:
        raise ValueError("cannot interpolate an empty trajectory")
    if np.any(np.diff(times) <= 0):
        raise ValueError("timestamps must be strictly increasing")
    low, high = times[0] - _TIME_TOLERANCE_S, times[-1] + _TIME_TOLERANCE_S
    outside = (query < low) | (query > high)
    if outside.any():
        bad = float(query[np.argmax(outside)])
        raise ValueError(f"query time {bad} is outside the trajectory [{times[0]}, {times[-1]}]")
    query = np.clip(query, times[0], times[-1])
    if len(times) == 1:
        return poses[:1].expand(len(query), 4, 4).clone()
    i = np.clip(np.searchsorted(times, query, side="right") - 1, 0, len(times) - 2)
    alpha = (query - times[i]) / (times[i + 1] - times[i])
    index = torch.from_numpy(i)
    T_a, T_b = poses[index], poses[index + 1]
    xi = se3_log(compose(invert(T_a), T_b))
    step = se3_exp(torch.from_numpy(alpha)[:, None] * xi)
    return compose(T_a, step)
