"""Tests of diffloc.sim.trajectory: smooth constant-speed body paths and pose interpolation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from omegaconf.errors import ConfigKeyError

from diffloc.geometry.se3 import se3_exp
from diffloc.sim.trajectory import (
    TrajectoryConfig,
    interpolate_pose,
    make_trajectory,
    smooth_route,
)

# An L-shaped walk that ends on a ramp (1 m rise over 4 m).
ROUTE = np.array([[0.0, 0.0, 0.0], [6.0, 0.0, 0.0], [6.0, 5.0, 0.0], [10.0, 5.0, 1.0]])


def still_config(**overrides) -> TrajectoryConfig:
    """A config without sways or bob, so poses follow the path exactly."""
    values = dict(yaw_sway_deg=0.0, pitch_sway_deg=0.0, bob_amplitude_m=0.0)
    values.update(overrides)
    return TrajectoryConfig(**values)


def closest_on_polyline(points: np.ndarray, route: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (N,) of points (N, 3) to a polyline and the index (N,) of the closest segment."""
    a, b = route[:-1], route[1:]
    ab = b - a
    t = ((points[:, None] - a[None]) * ab[None]).sum(-1) / (ab * ab).sum(-1)[None]
    closest = a[None] + np.clip(t, 0.0, 1.0)[..., None] * ab[None]
    distance = np.linalg.norm(points[:, None] - closest, axis=-1)
    return distance.min(axis=1), distance.argmin(axis=1)


def body_positions(T_wb: torch.Tensor, cfg: TrajectoryConfig) -> np.ndarray:
    """Positions on the ground path (body height removed)."""
    p = T_wb[:, :3, 3].numpy().copy()
    p[:, 2] -= cfg.body_height_m
    return p


def test_config_is_a_structured_config():
    cfg = OmegaConf.structured(TrajectoryConfig)
    assert cfg.speed_mps == 0.8 and cfg.max_frames == 0
    with pytest.raises(ConfigKeyError):
        OmegaConf.merge(cfg, {"sped_mps": 1.0})


def test_shapes_dtypes_and_timestamps():
    cfg = still_config(frame_rate_hz=5.0, start_time_s=12.5)
    t, T_wb = make_trajectory(ROUTE, cfg)
    assert t.dtype == np.float64 and T_wb.dtype == torch.float64
    assert T_wb.shape == (len(t), 4, 4)
    np.testing.assert_allclose(np.diff(t), 0.2, atol=1e-12)
    assert t[0] == 12.5
    R = T_wb[:, :3, :3]
    eye = torch.eye(3, dtype=torch.float64).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(1, 2), eye)
    torch.testing.assert_close(T_wb[:, 3], torch.tensor([0.0, 0, 0, 1]).expand(len(t), 4).double())


def test_constant_speed():
    cfg = still_config(speed_mps=0.8, frame_rate_hz=5.0, corner_smoothing_m=1.0)
    _, T_wb = make_trajectory(ROUTE, cfg)
    steps = np.linalg.norm(np.diff(T_wb[:, :3, 3].numpy(), axis=0), axis=1)
    np.testing.assert_allclose(steps, 0.16, rtol=0.02)
    # The path length is the polyline length minus what the two 90-degree fillets cut.
    length = 6.0 + 5.0 + math.sqrt(17.0) - 2 * (2.0 - math.pi / 2)
    assert length - 0.16 - 0.03 < steps.sum() <= length


def test_constant_horizontal_speed_with_bob_and_sway():
    cfg = TrajectoryConfig(speed_mps=0.8, frame_rate_hz=5.0)
    _, T_wb = make_trajectory(ROUTE[:3], cfg)
    steps = np.linalg.norm(np.diff(T_wb[:, :2, 3].numpy(), axis=0), axis=1)
    np.testing.assert_allclose(steps, 0.16, rtol=0.02)


@pytest.mark.parametrize("smoothing", [0.3, 1.0, 2.5])
def test_stays_within_corner_smoothing_of_the_polyline(smoothing):
    route = np.array([[0.0, 0, 0], [4, 0, 0], [4, 3, 0], [1, 5, 0], [1, 5.5, 0], [6, 8, 0.5]])
    cfg = still_config(corner_smoothing_m=smoothing, speed_mps=1.0, frame_rate_hz=20.0)
    _, T_wb = make_trajectory(route, cfg)
    distance, _ = closest_on_polyline(body_positions(T_wb, cfg), route)
    assert distance.max() < smoothing
    # The corners really are cut: the path does not pass through the waypoint (4, 0).
    assert np.linalg.norm(body_positions(T_wb, cfg) - route[1], axis=1).min() > 0.1 * smoothing
    np.testing.assert_allclose(body_positions(T_wb, cfg)[0], route[0], atol=1e-12)


def test_zero_smoothing_follows_the_polyline_exactly():
    cfg = still_config(corner_smoothing_m=0.0, speed_mps=1.0, frame_rate_hz=1.0)
    _, T_wb = make_trajectory(ROUTE[:3], cfg)
    distance, _ = closest_on_polyline(body_positions(T_wb, cfg), ROUTE[:3])
    assert distance.max() < 1e-12
    np.testing.assert_allclose(body_positions(T_wb, cfg)[6], [6.0, 0.0, 0.0], atol=1e-12)


def test_yaw_follows_the_tangent_and_body_stays_upright():
    cfg = still_config(speed_mps=0.5, frame_rate_hz=10.0)
    _, T_wb = make_trajectory(ROUTE, cfg)
    _, tangents = smooth_route(ROUTE, cfg.corner_smoothing_m, 0.05)
    forward = T_wb[:, :3, 0].numpy()
    yaw = np.arctan2(forward[:, 1], forward[:, 0])
    np.testing.assert_allclose(yaw, np.arctan2(tangents[:, 1], tangents[:, 0]), atol=1e-12)
    # Central differences of the positions agree with the heading.
    p = T_wb[:, :3, 3].numpy()
    chord = p[2:] - p[:-2]
    chord_yaw = np.arctan2(chord[:, 1], chord[:, 0])
    error = np.angle(np.exp(1j * (chord_yaw - yaw[1:-1])))
    assert np.abs(error).max() < math.radians(2.0)
    # Upright even on the ramp: z axis vertical, x axis horizontal, left axis horizontal.
    np.testing.assert_allclose(
        T_wb[:, :3, 2].numpy(), np.tile([0.0, 0, 1], (len(p), 1)), atol=1e-12
    )
    np.testing.assert_allclose(T_wb[:, 2, 0].numpy(), 0.0, atol=1e-12)
    # Starts facing +x along the first segment.
    np.testing.assert_allclose(forward[0], [1.0, 0.0, 0.0], atol=1e-12)


def test_height_follows_the_route_plus_body_height_and_bob():
    cfg = still_config(body_height_m=1.5)
    _, T_wb = make_trajectory(ROUTE, cfg)
    ground = body_positions(T_wb, cfg)
    first_segment = ground[:, 0] < 5.0
    np.testing.assert_allclose(ground[first_segment, 2], 0.0, atol=1e-12)
    np.testing.assert_allclose(T_wb[-1, 2, 3].item(), 1.5 + 1.0, atol=0.05)
    bobbing = TrajectoryConfig(yaw_sway_deg=0.0, pitch_sway_deg=0.0, bob_amplitude_m=0.03)
    _, T_bob = make_trajectory(ROUTE, bobbing)
    bob = (T_bob[:, 2, 3] - T_wb[:, 2, 3]).numpy()
    assert np.abs(bob).max() <= 0.03 + 1e-12 and np.abs(bob).max() > 0.02
    torch.testing.assert_close(T_bob[:, :2], T_wb[:, :2])


def test_sways_are_small_rotations_with_the_configured_amplitude():
    cfg = TrajectoryConfig(yaw_sway_deg=8.0, pitch_sway_deg=2.0, sway_period_s=6.0)
    _, T_sway = make_trajectory(ROUTE[:2], cfg)  # a straight route: heading is constant
    forward = T_sway[:, :3, 0].numpy()
    yaw = np.degrees(np.arctan2(forward[:, 1], forward[:, 0]))
    pitch = np.degrees(np.arcsin(-forward[:, 2]))
    assert 7.5 < np.abs(yaw).max() <= 8.0 + 1e-9
    assert 1.8 < np.abs(pitch).max() <= 2.0 + 1e-9
    # No roll: the left axis stays horizontal.
    np.testing.assert_allclose(T_sway[:, 2, 1].numpy(), 0.0, atol=1e-12)


def test_phase_changes_sways_but_not_the_path():
    cfg = TrajectoryConfig(bob_amplitude_m=0.0)
    _, T_a = make_trajectory(ROUTE, cfg, phase=0.0)
    _, T_b = make_trajectory(ROUTE, cfg, phase=1.7)
    torch.testing.assert_close(T_a[:, :3, 3], T_b[:, :3, 3])
    assert (T_a[:, :3, :3] - T_b[:, :3, :3]).abs().max() > 0.05


def test_deterministic():
    cfg = TrajectoryConfig()
    t1, T1 = make_trajectory(ROUTE, cfg, lateral_offset_m=0.3, reverse=True, phase=0.4)
    t2, T2 = make_trajectory(ROUTE.copy(), cfg, lateral_offset_m=0.3, reverse=True, phase=0.4)
    np.testing.assert_array_equal(t1, t2)
    assert torch.equal(T1, T2)
    _, T3 = make_trajectory(
        torch.from_numpy(ROUTE), cfg, lateral_offset_m=0.3, reverse=True, phase=0.4
    )
    assert torch.equal(T1, T3)


def test_reverse_traverses_the_route_backwards():
    cfg = still_config()
    _, T_fwd = make_trajectory(ROUTE, cfg)
    _, T_rev = make_trajectory(ROUTE, cfg, reverse=True)
    p_fwd, p_rev = body_positions(T_fwd, cfg), body_positions(T_rev, cfg)
    np.testing.assert_allclose(p_rev[0], ROUTE[-1], atol=1e-12)
    assert np.linalg.norm(p_rev[-1] - ROUTE[0]) <= cfg.speed_mps / cfg.frame_rate_hz + 1e-9
    assert np.linalg.norm(p_fwd[-1] - ROUTE[-1]) <= cfg.speed_mps / cfg.frame_rate_hz + 1e-9
    # Same geometric path, opposite heading.
    distance, _ = closest_on_polyline(p_rev, ROUTE)
    assert distance.max() < cfg.corner_smoothing_m
    heading_rev_start = T_rev[0, :3, 0].numpy()
    last_segment = (ROUTE[-1] - ROUTE[-2]) * [1, 1, 0]
    last_segment /= np.linalg.norm(last_segment)
    np.testing.assert_allclose(heading_rev_start, -last_segment, atol=1e-12)
    np.testing.assert_allclose(T_rev[-1, :3, 0].numpy(), [-1.0, 0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("offset", [0.4, -0.7])
def test_lateral_offset_on_straight_segments(offset):
    cfg = still_config(corner_smoothing_m=1.0, speed_mps=0.5, frame_rate_hz=4.0)
    route = ROUTE[:3]
    _, T_wb = make_trajectory(route, cfg, lateral_offset_m=offset)
    p = body_positions(T_wb, cfg)
    distance, segment = closest_on_polyline(p, route)
    corner_distance = np.linalg.norm(p - route[1], axis=1)
    straight = corner_distance > cfg.corner_smoothing_m + abs(offset) + 0.1
    assert straight.sum() > 10
    np.testing.assert_allclose(distance[straight], abs(offset), atol=1e-9)
    # Left of the direction of travel is positive.
    direction = (route[1:] - route[:-1])[segment]
    side = direction[:, 0] * (p[:, 1] - route[segment, 1]) - direction[:, 1] * (
        p[:, 0] - route[segment, 0]
    )
    assert np.all(np.sign(side[straight]) == np.sign(offset))
    # Offsetting keeps the constant speed.
    steps = np.linalg.norm(np.diff(T_wb[:, :3, 3].numpy(), axis=0), axis=1)
    np.testing.assert_allclose(steps, 0.125, rtol=0.02)


def test_lateral_offset_with_reverse_is_left_of_the_reversed_direction():
    cfg = still_config()
    _, T_wb = make_trajectory(ROUTE[:2], cfg, lateral_offset_m=0.5, reverse=True)
    # Walking towards -x, left is -y.
    np.testing.assert_allclose(T_wb[:, 1, 3].numpy(), -0.5, atol=1e-12)


def test_max_frames_truncates():
    cfg = still_config(max_frames=7)
    t, T_wb = make_trajectory(ROUTE, cfg)
    assert len(t) == 7 and T_wb.shape == (7, 4, 4)
    _, T_all = make_trajectory(ROUTE, still_config())
    assert torch.equal(T_all[:7], T_wb)


def test_speed_profile_and_start_offset_place_frames_at_the_integrated_arc_length():
    cfg = still_config(
        speed_mps=0.8, speed_variation_mps=0.2, speed_period_s=6.0, frame_rate_hz=1.0
    )
    straight = np.array([[0.0, 0.0, 0.0], [40.0, 0.0, 0.0]])
    phase, offset = 0.7, 0.37
    t, T_wb = make_trajectory(straight, cfg, phase=phase, start_offset_m=offset)
    x = T_wb[:, 0, 3].numpy()
    omega = 2.0 * math.pi / 6.0
    expected = offset + 0.8 * t + 0.2 * (math.cos(phase) - np.cos(omega * t + phase)) / omega
    np.testing.assert_allclose(x, expected, atol=1e-12)
    steps = np.diff(x)
    assert 0.6 - 1e-9 <= steps.min() < 0.65 and 0.95 < steps.max() <= 1.0 + 1e-9
    assert x[-1] <= 40.0 < x[-1] + steps.max()


def test_other_offset_and_speed_do_not_retrace_the_frames():
    mapping = still_config(speed_mps=0.8, frame_rate_hz=2.0)
    query = still_config(speed_mps=0.85, speed_variation_mps=0.15, frame_rate_hz=1.0)
    _, T_map = make_trajectory(ROUTE, mapping)
    _, T_query = make_trajectory(ROUTE, query, start_offset_m=0.23, phase=1.7)
    gaps = torch.cdist(T_query[:, :3, 3], T_map[:, :3, 3]).min(dim=1).values
    assert float(gaps.median()) > 0.05
    _, T_same = make_trajectory(ROUTE, still_config(speed_mps=0.8, frame_rate_hz=1.0))
    assert float(torch.cdist(T_same[:, :3, 3], T_map[:, :3, 3]).min(dim=1).values.max()) < 1e-9


def test_duplicate_waypoints_and_a_short_route():
    cfg = still_config(speed_mps=1.0, frame_rate_hz=1.0)
    route = np.array([[0.0, 0, 0], [0.0, 0, 0], [0.5, 0, 0]])
    t, T_wb = make_trajectory(route, cfg)
    assert len(t) == 1
    np.testing.assert_allclose(T_wb[0, :3, 0].numpy(), [1.0, 0.0, 0.0])


def test_bad_inputs():
    cfg = TrajectoryConfig()
    with pytest.raises(ValueError, match="at least 2"):
        make_trajectory(np.zeros((1, 3)), cfg)
    with pytest.raises(ValueError, match="distinct"):
        make_trajectory(np.zeros((3, 3)), cfg)
    with pytest.raises(ValueError, match="NaN"):
        make_trajectory(np.array([[0.0, 0, 0], [np.nan, 1, 0]]), cfg)
    with pytest.raises(ValueError, match="shape"):
        make_trajectory(np.zeros((4, 2)), cfg)
    with pytest.raises(ValueError, match="speed_mps"):
        make_trajectory(ROUTE, TrajectoryConfig(speed_mps=0.0))
    with pytest.raises(ValueError, match="frame_rate_hz"):
        make_trajectory(ROUTE, TrajectoryConfig(frame_rate_hz=-5.0))
    with pytest.raises(ValueError, match="max_frames"):
        make_trajectory(ROUTE, TrajectoryConfig(max_frames=-1))
    with pytest.raises(ValueError, match="corner_smoothing_m"):
        make_trajectory(ROUTE, TrajectoryConfig(corner_smoothing_m=-1.0))
    with pytest.raises(ValueError, match="speed_variation_mps"):
        make_trajectory(ROUTE, TrajectoryConfig(speed_mps=0.8, speed_variation_mps=0.8))
    with pytest.raises(ValueError, match="speed_period_s"):
        make_trajectory(ROUTE, TrajectoryConfig(speed_period_s=0.0))
    with pytest.raises(ValueError, match="start_offset_m"):
        make_trajectory(ROUTE, cfg, start_offset_m=-0.1)
    with pytest.raises(ValueError, match="start_offset_m"):
        make_trajectory(ROUTE, cfg, start_offset_m=100.0)
    with pytest.raises(ValueError, match="finite"):
        make_trajectory(ROUTE, cfg, lateral_offset_m=float("nan"))
    with pytest.raises(ValueError, match="horizontal"):
        make_trajectory(np.array([[0.0, 0, 0], [0.0, 0, 3]]), cfg)
    zigzag = np.array([[0.0, 0, 0], [5, 0, 0], [5, 0.3, 0], [0, 0.3, 0]])
    with pytest.raises(ValueError, match="too large"):
        make_trajectory(zigzag, cfg, lateral_offset_m=0.5)


def test_interpolate_pose_hits_samples_and_follows_the_geodesic():
    xi = torch.tensor([1.0, 0.5, 0.2, 0.1, -0.2, 0.9], dtype=torch.float64)
    T0 = se3_exp(torch.tensor([0.3, -1.0, 2.0, 0.2, 0.1, -0.4], dtype=torch.float64))
    T1 = T0 @ se3_exp(xi)
    T2 = T1 @ se3_exp(0.5 * xi)
    T = torch.stack([T0, T1, T2])
    times = np.array([1.0, 2.0, 4.0])
    out = interpolate_pose(times, T, np.array([1.0, 1.25, 2.0, 3.0, 4.0]))
    torch.testing.assert_close(out[0], T0)
    torch.testing.assert_close(out[1], T0 @ se3_exp(0.25 * xi))
    torch.testing.assert_close(out[2], T1)
    torch.testing.assert_close(out[3], T1 @ se3_exp(0.25 * xi))
    torch.testing.assert_close(out[4], T2)
    # Torch inputs and numpy poses work too.
    out_t = interpolate_pose(torch.from_numpy(times), T.numpy(), torch.tensor([1.25]))
    torch.testing.assert_close(out_t[0], out[1])


def test_interpolate_pose_on_a_trajectory_and_errors():
    t, T_wb = make_trajectory(ROUTE, TrajectoryConfig())
    mid = interpolate_pose(t, T_wb, 0.5 * (t[:-1] + t[1:]))
    halfway = 0.5 * (T_wb[:-1, :3, 3] + T_wb[1:, :3, 3])
    assert (mid[:, :3, 3] - halfway).norm(dim=1).max() < 0.01
    # Slightly past the end (float round-off) is clamped; far past raises.
    torch.testing.assert_close(interpolate_pose(t, T_wb, np.array([t[-1] + 1e-9]))[0], T_wb[-1])
    with pytest.raises(ValueError, match="outside"):
        interpolate_pose(t, T_wb, np.array([t[-1] + 0.1]))
    with pytest.raises(ValueError, match="increasing"):
        interpolate_pose(np.array([0.0, 0.0]), T_wb[:2], np.array([0.0]))
    with pytest.raises(ValueError, match="shape"):
        interpolate_pose(t[:3], T_wb[:2], np.array([0.0]))
    single = interpolate_pose(t[:1], T_wb[:1], np.array([t[0], t[0]]))
    assert single.shape == (2, 4, 4) and torch.equal(single[1], T_wb[0])
