"""Simulate a whole dataset folder from a :class:`SceneConfig`.

The folder layout is diffloc's dataset format (see :mod:`diffloc.io.dataset`). Everything is
written into a temporary folder that is renamed into place only when complete, so a failed or
killed run never leaves a folder that looks like a dataset. A folder made earlier with the same
configuration is reused as it is.

The run follows the stage contract (``diffloc/pipeline/design.md``) as far as a folder that is
renamed into place as a whole allows: it holds the dataset's lock, a file beside the folder
(:func:`~diffloc.io.lock.sibling_lock_path`), for the whole run, so a second run on the same
folder waits (or refuses, ``stage.wait``) and then reuses the first one's dataset; under that
lock it removes the temporary folders killed runs left beside it.
"""

from __future__ import annotations

import contextlib
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from diffloc import __version__
from diffloc.checks import check_positive_int
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.pose_offsets import nearest_pose_offsets, offset_summary
from diffloc.geometry.rig import SensorRig
from diffloc.io.atomic import atomic_directory, atomic_write_text
from diffloc.io.calib import Calibration
from diffloc.io.dataset import SequenceWriter, read_dataset_info
from diffloc.io.exposure import EXPOSURE_FILE, write_exposures
from diffloc.io.lock import (
    LockLevel,
    ReadOnlyFolderError,
    folder_lock,
    remove_sibling_temporaries,
    sibling_lock_path,
)
from diffloc.io.mesh_obj import write_textured_mesh_obj
from diffloc.io.ply import write_point_cloud
from diffloc.progress import progress
from diffloc.render.raycast import MeshRenderer
from diffloc.sim.config import CameraConfig, RigConfig, SceneConfig, SequenceConfig
from diffloc.sim.imaging import auto_exposure_scales, expose, metered_luminance, shade
from diffloc.sim.lidar import accumulate_map, simulate_station_scan, simulate_sweep
from diffloc.sim.placement import check_free_space
from diffloc.sim.preview import write_preview
from diffloc.sim.scene import generate_world
from diffloc.sim.side_cameras import side_camera_extrinsic, side_sequence_names
from diffloc.sim.trajectory import (
    TrajectoryConfig,
    interpolate_pose,
    make_trajectory,
    validate_trajectory_config,
)
from diffloc.sim.world import World

DATASET_FORMAT_VERSION = 1
DEPTH_SCALE = 1000.0
FRAMES_PER_BATCH = 4


def camera_from_config(cfg: CameraConfig) -> PinholeCamera:
    """The simulated camera (square pixels, principal point at the image centre)."""
    width = check_positive_int(cfg.width, "scene.camera.width")
    height = check_positive_int(cfg.height, "scene.camera.height")
    if not 0.0 < cfg.hfov_deg < 180.0:
        raise ValueError(f"scene.camera.hfov_deg must be in (0, 180), got {cfg.hfov_deg}")
    coefficients = [cfg.k1, cfg.k2, cfg.p1, cfg.p2]
    distortion = torch.tensor(coefficients, dtype=torch.float64) if any(coefficients) else None
    return PinholeCamera.from_fov(width, height, math.radians(cfg.hfov_deg), distortion=distortion)


def rig_from_config(cfg: RigConfig) -> SensorRig:
    """The body -> camera / lidar rig described by the config's URDF-style xyz and rpy."""
    return SensorRig.from_urdf(
        SensorRig.urdf_from_offsets(
            {
                "camera": (list(cfg.camera_xyz), list(cfg.camera_rpy)),
                "lidar": (list(cfg.lidar_xyz), list(cfg.lidar_rpy)),
            }
        )
    )


def sequence_trajectory(cfg: SceneConfig, seq: SequenceConfig) -> TrajectoryConfig:
    """The trajectory settings a sequence is simulated with: ``scene.trajectory`` with the
    sequence's own frame rate, speed and speed variation where it sets them (what
    ``dataset.json`` records under ``sequence_trajectories``)."""
    trajectory = cfg.trajectory
    if seq.frame_rate_hz > 0:
        trajectory = replace(trajectory, frame_rate_hz=seq.frame_rate_hz)
    if seq.speed_mps > 0:
        trajectory = replace(trajectory, speed_mps=seq.speed_mps)
    if seq.speed_variation_mps is not None:
        trajectory = replace(trajectory, speed_variation_mps=seq.speed_variation_mps)
    return trajectory


def validate_scene_config(cfg: SceneConfig) -> None:
    """Reject configurations that cannot be simulated, naming the offending key."""
    if isinstance(cfg.seed, bool) or not isinstance(cfg.seed, int):
        raise ValueError(f"scene.seed must be an integer, got {cfg.seed!r}")
    if not cfg.sequences:
        raise ValueError("scene.sequences is empty: nothing to simulate")
    names = [s.name for s in cfg.sequences]
    if len(set(names)) != len(names):
        raise ValueError(f"scene.sequences has repeated names: {names}")
    for name in names:
        if not name or not name.replace("_", "").replace("-", "").isalnum():
            raise ValueError(f"sequence name {name!r} must be letters, digits, '_' or '-'")
    if cfg.map.lidar_sequence not in names:
        raise ValueError(f"scene.map.lidar_sequence {cfg.map.lidar_sequence!r} is not in {names}")
    sides = side_sequence_names(cfg.map.lidar_sequence, cfg.rig.side_camera_yaw_deg)
    clash = [name for name in sides if name in names]
    if clash:
        raise ValueError(
            f"scene.rig.side_camera_yaw_deg: the side camera sequence(s) {clash} would replace "
            "simulated sequences of that name; rename those sequences"
        )
    check_positive_int(cfg.sensor.motion_blur_samples, "scene.sensor.motion_blur_samples")
    camera_from_config(cfg.camera)
    rate = cfg.lidar.rate_hz
    if not (isinstance(rate, int | float) and math.isfinite(rate) and rate > 0):
        raise ValueError(f"scene.lidar.rate_hz must be a finite number > 0, got {rate!r}")
    for key in ("voxel_size_m", "normal_radius_m"):
        value = getattr(cfg.map, key)
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise ValueError(f"scene.map.{key} must be a finite number > 0, got {value!r}")
    for index, seq in enumerate(cfg.sequences):
        for key in ("frame_rate_hz", "speed_mps", "start_offset_m"):
            value = getattr(seq, key)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(
                    f"scene.sequences.{index}.{key} must be finite and >= 0, got {value}"
                )
        try:
            validate_trajectory_config(sequence_trajectory(cfg, seq))
        except ValueError as exc:
            raise ValueError(f"scene.sequences.{index} ({seq.name}): {exc}") from exc


def config_record(cfg: SceneConfig) -> dict:
    """The scene configuration as recorded in ``dataset.json`` and compared for reuse.

    A sequence's ``auto_exposure`` is recorded only when it is enabled, and the rig's
    ``side_camera_yaw_deg`` only when it lists a camera: switched off they have no effect, and
    leaving them out keeps the record (and so every file) of datasets made before the options
    existed byte-identical, and those datasets reusable.
    """
    config = OmegaConf.to_container(OmegaConf.structured(cfg))
    if not config["rig"]["side_camera_yaw_deg"]:
        del config["rig"]["side_camera_yaw_deg"]
    for sequence in config["sequences"]:
        if not sequence["auto_exposure"]["enabled"]:
            del sequence["auto_exposure"]
    return config


class DatasetSimulator:
    """Renders the sequences, lidar sweeps and maps of one simulated world.

    Args:
        cfg: the scene configuration.
        show_progress: show progress bars (never in CI).
    """

    def __init__(self, cfg: SceneConfig, show_progress: bool = True) -> None:
        validate_scene_config(cfg)
        self.cfg = cfg
        self.show_progress = show_progress
        self.world: World = generate_world(cfg.name, cfg.seed, cfg.layout)
        self.camera = camera_from_config(cfg.camera)
        self.rig = rig_from_config(cfg.rig)
        with torch.no_grad():
            self.T_body_camera = self.rig.T_body_sensor("camera").to(torch.float64)
            self.T_body_lidar = self.rig.T_body_sensor("lidar").to(torch.float64)
        self.side_cameras = {
            name: side_camera_extrinsic(self.T_body_camera, yaw)
            for name, yaw in side_sequence_names(
                cfg.map.lidar_sequence, cfg.rig.side_camera_yaw_deg
            ).items()
        }
        """``{sequence name: T_body_camera (4, 4)}`` of the side cameras (may be empty)."""
        self._renderers: dict[bool, MeshRenderer] = {}

    def renderer(self, changed: bool) -> MeshRenderer:
        """The renderer of the mapped (``changed=False``) or changed world, built once."""
        if changed not in self._renderers:
            mesh = self.world.changed_mesh if changed else self.world.mesh
            self._renderers[changed] = MeshRenderer(mesh)
        return self._renderers[changed]

    def _extrinsic(self, T_body_camera: torch.Tensor | None) -> torch.Tensor:
        """(4, 4) ``T_body_camera`` of a camera: the front one for ``None``."""
        return self.T_body_camera if T_body_camera is None else T_body_camera

    def calibration(self, T_body_camera: torch.Tensor | None = None) -> Calibration:
        """The calibration of the front camera, or (``T_body_camera`` given) of a side camera
        of the same rig: its extrinsic, and a rig URDF whose ``camera`` is that camera."""
        lidar = OmegaConf.to_container(OmegaConf.structured(self.cfg.lidar))
        rig = self.rig
        if T_body_camera is not None:
            rig = SensorRig.from_transforms({"camera": T_body_camera, "lidar": self.T_body_lidar})
        return Calibration(
            camera=self.camera,
            depth_scale=DEPTH_SCALE,
            T_body_camera=self._extrinsic(T_body_camera),
            T_body_lidar=self.T_body_lidar,
            rig_urdf=rig.to_urdf(),
            lidar=lidar,
        )

    def body_trajectory(self, seq: SequenceConfig) -> tuple[np.ndarray, torch.Tensor]:
        """Timestamps (N,) and body poses T_wb (N, 4, 4) of a sequence."""
        return make_trajectory(
            self.world.route,
            sequence_trajectory(self.cfg, seq),
            lateral_offset_m=seq.lateral_offset_m,
            reverse=seq.reverse,
            phase=seq.sway_phase,
            start_offset_m=seq.start_offset_m,
        )

    def render_linear(
        self,
        renderer: MeshRenderer,
        seq: SequenceConfig,
        timestamps: np.ndarray,
        T_wb: torch.Tensor,
        frame_ids: np.ndarray,
        T_body_camera: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Linear radiance (B, 3, H, W) before exposure and depth (B, 1, H, W) of some frames.

        Motion blur averages ``sensor.motion_blur_samples`` renders spread over the exposure
        time ending at each frame's timestamp; depth is that of the frame's own pose. The
        camera is the front one, or the one of extrinsic ``T_body_camera`` (4, 4).
        """
        sensor = self.cfg.sensor
        samples = sensor.motion_blur_samples
        offsets = np.linspace(-sensor.exposure_time_s, 0.0, samples) if samples > 1 else [0.0]
        times = timestamps[frame_ids][:, None] + np.asarray(offsets)[None, :]
        times = np.clip(times, timestamps[0], timestamps[-1]).reshape(-1)
        T_wb_sub = interpolate_pose(timestamps, T_wb, times)
        T_wc_sub = T_wb_sub @ self._extrinsic(T_body_camera)
        render = renderer.render(T_wc_sub, self.camera)
        linear = shade(render, seq.lighting, sensor, renderer.raycaster)
        linear = linear.reshape(len(frame_ids), samples, *linear.shape[1:]).mean(dim=1)
        depth = render.depth.reshape(len(frame_ids), samples, *render.depth.shape[1:])[:, -1]
        return linear, depth

    def render_frames(
        self,
        renderer: MeshRenderer,
        seq: SequenceConfig,
        timestamps: np.ndarray,
        T_wb: torch.Tensor,
        frame_ids: np.ndarray,
        generator: torch.Generator,
        T_body_camera: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """RGB (B, 3, H, W) in [0, 1] at the sequence's fixed exposure and depth (B, 1, H, W)
        in metres of some frames (see :meth:`render_linear`)."""
        linear, depth = self.render_linear(
            renderer, seq, timestamps, T_wb, frame_ids, T_body_camera
        )
        return expose(linear, seq.lighting, self.cfg.sensor, generator), depth

    def render_auto_exposed(
        self,
        renderer: MeshRenderer,
        seq: SequenceConfig,
        timestamps: np.ndarray,
        T_wb: torch.Tensor,
        frame_ids: np.ndarray,
        generator: torch.Generator,
        previous_scale: float,
        T_body_camera: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Like :meth:`render_frames` under the sequence's auto exposure.

        Returns:
            RGB (B, 3, H, W), depth (B, 1, H, W) and the (B,) auto-exposure multipliers,
            following on from the previous frame's multiplier ``previous_scale``.
        """
        linear, depth = self.render_linear(
            renderer, seq, timestamps, T_wb, frame_ids, T_body_camera
        )
        metered = metered_luminance(linear, seq.lighting)
        scales = auto_exposure_scales(metered, previous_scale, seq.auto_exposure)
        rgb = expose(linear, seq.lighting, self.cfg.sensor, generator, exposure_scales=scales)
        return rgb, depth, scales

    def write_frames(
        self,
        name: str,
        seq: SequenceConfig,
        trajectory: tuple[np.ndarray, torch.Tensor],
        writer: SequenceWriter,
        generator: torch.Generator,
        T_body_camera: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Render every frame of one camera of ``seq`` in batches into ``writer``.

        Args:
            name: the written sequence's name (the progress bar's label).
            seq: the simulated traversal (scene state, lighting, exposure).
            trajectory: its timestamps (N,) and body poses T_wb (N, 4, 4)
                (:meth:`body_trajectory`).
            writer: the sequence folder's writer (closed by the caller).
            generator: the camera's noise stream.
            T_body_camera: (4, 4) the camera's extrinsic; ``None``: the front camera.

        Returns:
            The camera poses T_wc (N, 4, 4) and the first frame's RGB (3, H, W).

        Raises:
            ValueError: a camera pose not in free space.
        """
        renderer = self.renderer(seq.changed_scene)
        timestamps, T_wb = trajectory
        T_wc = T_wb @ self._extrinsic(T_body_camera)
        check_free_space(renderer.raycaster, self.world.bounds, T_wc[:, :3, 3], what="camera")
        batches = np.array_split(
            np.arange(len(timestamps)), math.ceil(len(timestamps) / FRAMES_PER_BATCH)
        )
        first_frame = None
        scales: list[torch.Tensor] = []
        for frame_ids in progress(batches, f"{name}: frames", self.show_progress):
            if seq.auto_exposure.enabled:
                previous = float(scales[-1][-1]) if scales else 1.0
                rgb, depth, batch_scales = self.render_auto_exposed(
                    renderer, seq, timestamps, T_wb, frame_ids, generator, previous, T_body_camera
                )
                scales.append(batch_scales)
            else:
                rgb, depth = self.render_frames(
                    renderer, seq, timestamps, T_wb, frame_ids, generator, T_body_camera
                )
            for k, i in enumerate(frame_ids):
                writer.add_frame(float(timestamps[i]), T_wc[i], rgb[k], depth[k, 0])
            if first_frame is None:
                first_frame = rgb[0]
        if scales:
            exposures = seq.lighting.exposure * torch.cat(scales).numpy()
            write_exposures(writer.seq_dir / EXPOSURE_FILE, timestamps, exposures)
        return T_wc, first_frame

    def simulate_sequence(self, index: int, seq: SequenceConfig, seq_dir: Path) -> dict:
        """Write one sequence folder; return its camera positions and (for mapping) sweeps."""
        renderer = self.renderer(seq.changed_scene)
        timestamps, T_wb = self.body_trajectory(seq)
        generator = torch.Generator().manual_seed(self.cfg.seed * 1009 + index)
        rng = np.random.default_rng([self.cfg.seed, index])
        writer = SequenceWriter(seq_dir, self.calibration())
        T_wc, first_frame = self.write_frames(seq.name, seq, (timestamps, T_wb), writer, generator)
        sweep_times = np.arange(timestamps[0], timestamps[-1] + 1e-9, 1.0 / self.cfg.lidar.rate_hz)
        T_wl = interpolate_pose(timestamps, T_wb, sweep_times) @ self.T_body_lidar
        sweeps_world, origins = [], []
        sweep_bar = progress(sweep_times, f"{seq.name}: lidar", self.show_progress)
        for t, pose in zip(sweep_bar, T_wl, strict=True):
            points = simulate_sweep(renderer.raycaster, pose, self.cfg.lidar, rng)
            writer.add_sweep(float(t), pose, points)
            rotation, translation = pose[:3, :3].float().numpy(), pose[:3, 3].float().numpy()
            sweeps_world.append(points @ rotation.T + translation)
            origins.append(translation)
        writer.close()
        return {
            "T_wc": T_wc,
            "positions": T_wc[:, :3, 3].numpy(),
            "first_frame": first_frame,
            "sweeps_world": sweeps_world,
            "sweep_origins": origins,
        }

    def simulate_side_cameras(self, index: int, seq: SequenceConfig, root: Path) -> list[str]:
        """Write the side cameras' sequences of ``seq`` (the ``index``-th sequence) into
        ``root``, each its own folder of frames, poses and calibration (no lidar), after the
        front camera's and each from its own noise stream, so the front camera's files are
        those of a rig without side cameras. Returns their names."""
        trajectory = self.body_trajectory(seq)
        for k, (name, T_body_camera) in enumerate(self.side_cameras.items()):
            stream = np.random.SeedSequence([self.cfg.seed, index, k + 1]).generate_state(1)
            generator = torch.Generator().manual_seed(int(stream[0]))
            writer = SequenceWriter(root / name, self.calibration(T_body_camera))
            self.write_frames(name, seq, trajectory, writer, generator, T_body_camera)
            writer.close()
        return list(self.side_cameras)

    def write_maps(self, root: Path, mapping: dict) -> np.ndarray:
        """Accumulated lidar map and terrestrial-scanner map with normals; returns map points."""
        cfg = self.cfg
        points, normals = accumulate_map(
            mapping["sweeps_world"],
            mapping["sweep_origins"],
            cfg.map.voxel_size_m,
            cfg.map.normal_radius_m,
        )
        write_point_cloud(root / "map" / "lidar_map.ply", points, normals=normals)
        rng = np.random.default_rng([cfg.seed, 7919])
        raycaster = self.renderer(False).raycaster
        stations = self.world.tls_stations
        check_free_space(raycaster, self.world.bounds, torch.from_numpy(stations), what="scanner")
        scans = [
            simulate_station_scan(raycaster, station, cfg.tls, rng)
            for station in progress(stations, "terrestrial scans", self.show_progress)
        ]
        tls_points, tls_normals = accumulate_map(
            scans, list(stations), cfg.map.voxel_size_m, cfg.map.normal_radius_m
        )
        write_point_cloud(root / "map" / "tls_map.ply", tls_points, normals=tls_normals)
        write_textured_mesh_obj(root / "map" / "mesh" / "scene.obj", self.world.mesh)
        write_textured_mesh_obj(
            root / "map" / "mesh_changed" / "scene.obj", self.world.changed_mesh
        )
        return points

    def nearest_mapping_pose(self, results: dict) -> dict[str, dict[str, float]]:
        """Per sequence: median and p90 of the distance and angle from each of its camera poses
        to the nearest camera pose of the map's sequence (``scene.map.lidar_sequence``)."""
        reference = results[self.cfg.map.lidar_sequence]["T_wc"]
        return {
            name: offset_summary(*nearest_pose_offsets(r["T_wc"], reference))
            for name, r in results.items()
        }

    def write(self, root: Path) -> None:
        """Simulate every sequence and map into the (empty, temporary) folder ``root``."""
        results, sides = {}, []
        for index, seq in enumerate(self.cfg.sequences):
            results[seq.name] = self.simulate_sequence(index, seq, root / seq.name)
            if seq.name == self.cfg.map.lidar_sequence:
                sides = self.simulate_side_cameras(index, seq, root)
        map_points = self.write_maps(root, results[self.cfg.map.lidar_sequence])
        frames = [(name, r["first_frame"]) for name, r in results.items()]
        trajectories = {name: r["positions"] for name, r in results.items()}
        title = f"diffloc simulator: {self.cfg.name} scene, seed {self.cfg.seed}"
        write_preview(root / "preview.png", frames, map_points, trajectories, title)
        info = {
            "format_version": DATASET_FORMAT_VERSION,
            "kind": "diffloc-dataset",
            "generator": f"diffloc {__version__}",
            "sequences": list(results) + sides,
            "config": config_record(self.cfg),
            "world": self.world.metadata(),
            "nearest_mapping_pose": self.nearest_mapping_pose(results),
            "sequence_trajectories": {
                seq.name: {
                    key: getattr(sequence_trajectory(self.cfg, seq), key)
                    for key in ("frame_rate_hz", "speed_mps", "speed_variation_mps")
                }
                for seq in self.cfg.sequences
            },
        }
        if sides:
            yaws = dict(zip(sides, self.cfg.rig.side_camera_yaw_deg, strict=True))
            info["side_cameras"] = {
                name: {"of": self.cfg.map.lidar_sequence, "yaw_deg": float(yaw)}
                for name, yaw in yaws.items()
            }
        atomic_write_text(root / "dataset.json", json.dumps(info, indent=2, sort_keys=True) + "\n")


def simulate_dataset(
    cfg: SceneConfig, out_dir: Path, *, overwrite: bool = False, show_progress: bool = True
) -> Path:
    """Simulate ``cfg`` into ``out_dir`` and return it; reuse it if it already holds this config.

    Holds the dataset's lock (module docstring) for the whole run and first removes the
    temporary folders of killed runs beside ``out_dir``.

    Raises:
        FileExistsError: ``out_dir`` holds something else and ``overwrite`` is false.
        ValueError: the configuration is invalid, or a camera pose leaves the free space.
        diffloc.io.lock.FolderBusyError: another run holds the dataset and the lock settings
            do not wait for it.
        diffloc.io.lock.ReadOnlyFolderError: ``out_dir``'s folder cannot be written and holds
            no dataset of this configuration (one that does is reused).
    """
    out_dir = Path(out_dir)
    config = config_record(cfg)
    validate_scene_config(cfg)
    lock = {"level": LockLevel.DATASET, "lock_path": sibling_lock_path(out_dir)}
    with contextlib.ExitStack() as held:
        try:
            held.enter_context(folder_lock(out_dir, **lock))
            read_only = None
        except ReadOnlyFolderError as exc:  # reuse only, under a reader's lock
            read_only = exc
            held.enter_context(folder_lock(out_dir, shared=True, **lock))
        if read_only is None:
            remove_sibling_temporaries(out_dir)
        if out_dir.exists():
            try:
                if read_dataset_info(out_dir).get("config") == config:
                    return out_dir
            except (FileNotFoundError, ValueError):
                pass
            if not overwrite:
                raise FileExistsError(
                    f"{out_dir} exists and was not made with this configuration; choose another "
                    "out_dir or pass task.overwrite=true to replace it"
                )
        if read_only is not None:
            raise ReadOnlyFolderError(
                f"{read_only}: no dataset of this configuration to reuse at {out_dir}; choose an "
                "out_dir in a folder you can write"
            )
        simulator = DatasetSimulator(cfg, show_progress=show_progress)
        with atomic_directory(out_dir, overwrite=overwrite) as tmp:
            simulator.write(tmp)
    return out_dir
