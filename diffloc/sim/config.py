"""Structured configuration of a simulated scene (the Hydra ``scene`` group)."""

from __future__ import annotations

from dataclasses import dataclass, field

from omegaconf import MISSING

from diffloc.sim.imaging import AutoExposureConfig, LightingConfig, SensorConfig
from diffloc.sim.indoor_layout import IndoorLayoutConfig
from diffloc.sim.lidar import SpinningLidarConfig, TerrestrialScannerConfig
from diffloc.sim.outdoor_layout import OutdoorLayoutConfig
from diffloc.sim.trajectory import TrajectoryConfig

HALF_PI = 1.5707963267948966


@dataclass
class CameraConfig:
    """Pinhole camera with optional radial-tangential distortion (k1, k2, p1, p2)."""

    width: int = 640
    height: int = 480
    hfov_deg: float = 90.0
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0


@dataclass
class RigConfig:
    """Sensor extrinsics in the body frame (x forward, y left, z up), URDF xyz (m) + rpy (rad).

    The default camera rpy turns the OpenCV optical frame (z forward, y down) to look along
    the body's x axis. ``side_camera_yaw_deg`` adds cameras to the mapping run (the map's
    sequence, ``scene.map.lidar_sequence``): each is the front camera turned by that yaw
    about the body's up (z) axis, e.g. ``[90, -90]`` for a left and a right camera, written as
    sequences of their own (:mod:`diffloc.sim.side_cameras`); empty (the default): the front
    camera only.
    """

    camera_xyz: list[float] = field(default_factory=lambda: [0.1, 0.0, 0.0])
    camera_rpy: list[float] = field(default_factory=lambda: [-HALF_PI, 0.0, -HALF_PI])
    lidar_xyz: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.25])
    lidar_rpy: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    side_camera_yaw_deg: list[float] = field(default_factory=list)


@dataclass
class MapConfig:
    """Accumulated lidar and terrestrial-scanner maps."""

    voxel_size_m: float = 0.03
    normal_radius_m: float = 0.12
    lidar_sequence: str = "mapping"


@dataclass
class SequenceConfig:
    """One simulated traversal: route direction, lateral offset, speed, scene state and lighting.

    ``frame_rate_hz`` and ``speed_mps`` override ``trajectory.frame_rate_hz`` / ``speed_mps``
    for this sequence (0 keeps them) and ``speed_variation_mps`` overrides
    ``trajectory.speed_variation_mps`` (``None`` keeps it), so queries can be sparser than the
    mapping run and walk at their own speed profile. ``start_offset_m`` is the arc length along
    the (reversed, offset) path where the sequence starts: with its own offset and speed a
    query does not retrace the mapping run's frame positions. ``auto_exposure`` (off by
    default) lets the exposure follow each frame's brightness; the exposures are then recorded
    as ground truth in ``<sequence>/exposure.txt``.
    """

    name: str = MISSING
    frame_rate_hz: float = 0.0
    speed_mps: float = 0.0
    speed_variation_mps: float | None = None
    start_offset_m: float = 0.0
    reverse: bool = False
    lateral_offset_m: float = 0.0
    changed_scene: bool = False
    sway_phase: float = 0.0
    lighting: LightingConfig = field(default_factory=LightingConfig)
    auto_exposure: AutoExposureConfig = field(default_factory=AutoExposureConfig)


@dataclass
class SceneConfig:
    """Everything that defines a simulated dataset; ``name`` selects the world generator."""

    name: str = MISSING
    seed: int = 0
    camera: CameraConfig = field(default_factory=CameraConfig)
    rig: RigConfig = field(default_factory=RigConfig)
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    lidar: SpinningLidarConfig = field(default_factory=SpinningLidarConfig)
    tls: TerrestrialScannerConfig = field(default_factory=TerrestrialScannerConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    map: MapConfig = field(default_factory=MapConfig)
    sequences: list[SequenceConfig] = field(default_factory=list)


@dataclass
class IndoorSceneConfig(SceneConfig):
    name: str = "indoor"
    layout: IndoorLayoutConfig = field(default_factory=IndoorLayoutConfig)


@dataclass
class OutdoorSceneConfig(SceneConfig):
    name: str = "outdoor"
    layout: OutdoorLayoutConfig = field(default_factory=OutdoorLayoutConfig)
