"""diffloc's own dataset folder format.

Layout::

    <root>/dataset.json              {"format_version": 1, "kind": "diffloc-dataset",
                                      "sequences": ["seq_a", ...], ...free metadata}
    <root>/<seq>/calib.yaml          see diffloc.io.calib
    <root>/<seq>/poses.txt           TUM trajectory of T_world_camera, row i <-> image i
    <root>/<seq>/rgb/000000.png      8-bit RGB
    <root>/<seq>/depth/000000.png    16-bit depth, calib.yaml depth_scale units per metre
                                     (optional folder)
    <root>/<seq>/lidar/000000.ply    binary PLY, float32 x y z in the lidar frame (optional)
    <root>/<seq>/lidar/poses.txt     TUM trajectory of T_world_lidar at sweep times
    <root>/<seq>/exposure.txt        per-frame exposure, simulator ground truth (only with
                                     auto exposure; see diffloc.io.exposure)
    <root>/<seq>_left/ ...           another camera of a multi-camera rig: a sequence of its
                                     own (calib.yaml with its T_body_camera, poses.txt at
                                     the same timestamps, rgb/, optional depth/; no lidar/),
                                     e.g. the simulator's side cameras (mapping_left,
                                     mapping_right; dataset.json "side_cameras" names the
                                     sequence each belongs to and its yaw)
    <root>/map/lidar_map.ply         accumulated lidar map (points + normals)
    <root>/map/tls_map.ply           terrestrial laser scanner map
    <root>/map/mesh/scene.obj        textured mesh of the mapped scene
    <root>/map/mesh_changed/scene.obj  textured mesh of the changed scene

Frame ``i`` is ``f"{i:06d}.png"`` (more digits beyond 999999). Writers produce the folder in a
temporary place (see :func:`diffloc.io.atomic.atomic_directory`) so a reader never sees a
half-written dataset.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from diffloc.checks import ShapeError, check_finite, check_shape
from diffloc.io.atomic import atomic_write_text
from diffloc.io.calib import Calibration, read_calib, write_calib
from diffloc.io.images import write_depth, write_rgb
from diffloc.io.ply import write_point_cloud
from diffloc.io.sequence import SequenceData
from diffloc.io.trajectory import read_tum, rotation_error_of_rigid, write_tum

__all__ = [
    "DATASET_FORMAT_VERSION",
    "DATASET_KIND",
    "MAP_FILES",
    "SequenceWriter",
    "frame_name",
    "map_paths",
    "read_dataset_info",
    "read_sequence",
    "read_sequence_dir",
    "write_dataset_info",
]

DATASET_FORMAT_VERSION = 1
DATASET_KIND = "diffloc-dataset"
MAP_FILES = {
    "lidar_map": "map/lidar_map.ply",
    "tls_map": "map/tls_map.ply",
    "mesh": "map/mesh/scene.obj",
    "mesh_changed": "map/mesh_changed/scene.obj",
}
"""Scene-level map files, relative to the dataset root."""

_RIGID_TOLERANCE = 1e-6


def frame_name(index: int, suffix: str) -> str:
    """File name of frame ``index``, e.g. ``frame_name(7, ".png") == "000007.png"``."""
    return f"{index:06d}{suffix}"


def _pose(T: Any, name: str) -> torch.Tensor:
    T = T if isinstance(T, torch.Tensor) else torch.as_tensor(np.asarray(T))
    T = T.detach().cpu().to(torch.float64)
    check_shape(T, "4,4", name)
    check_finite(T, name)
    if float(rotation_error_of_rigid(T)) > _RIGID_TOLERANCE:
        raise ValueError(f"{name} is not a rigid transform")
    return T


class SequenceWriter:
    """Writes one sequence folder frame by frame; poses files are written by :meth:`close`.

    Args:
        seq_dir: the sequence folder; created if missing, must be empty if it exists.
        calib: the calibration, written to ``calib.yaml`` at once.

    Raises:
        FileExistsError: ``seq_dir`` exists and is not empty.

    Example:
        >>> from diffloc.geometry.camera import PinholeCamera
        >>> camera = PinholeCamera(fx=40.0, fy=40.0, cx=15.5, cy=11.5, width=32, height=24)
        >>> with SequenceWriter("seq0", Calibration(camera)) as writer:
        ...     writer.add_frame(0.0, torch.eye(4), torch.zeros(3, 24, 32), torch.ones(24, 32))
        ...     writer.add_sweep(0.0, torch.eye(4), torch.rand(100, 3))
        0
        0
        >>> sorted(p.name for p in Path("seq0").iterdir())
        ['calib.yaml', 'depth', 'lidar', 'poses.txt', 'rgb']
    """

    def __init__(self, seq_dir: str | os.PathLike, calib: Calibration) -> None:
        self.seq_dir = Path(seq_dir)
        if self.seq_dir.exists() and any(self.seq_dir.iterdir()):
            raise FileExistsError(f"{self.seq_dir} exists and is not empty")
        if not isinstance(calib, Calibration):
            raise TypeError(f"calib must be a Calibration, got {type(calib).__name__}")
        self.calib = calib
        (self.seq_dir / "rgb").mkdir(parents=True, exist_ok=True)
        write_calib(self.seq_dir / "calib.yaml", calib)
        self._times: list[float] = []
        self._poses: list[torch.Tensor] = []
        self._has_depth: bool | None = None
        self._sweep_times: list[float] = []
        self._sweep_poses: list[torch.Tensor] = []
        self._closed = False

    @property
    def num_frames(self) -> int:
        return len(self._times)

    @property
    def num_sweeps(self) -> int:
        return len(self._sweep_times)

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"SequenceWriter for {self.seq_dir} is already closed")

    @staticmethod
    def _check_time(timestamp: float, previous: list[float], what: str) -> float:
        t = float(timestamp)
        if not math.isfinite(t):
            raise ValueError(f"{what} timestamp must be finite, got {timestamp}")
        if previous and t <= previous[-1]:
            raise ValueError(f"{what} timestamps must increase: {t} after {previous[-1]}")
        return t

    def add_frame(
        self,
        timestamp: float,
        T_wc: torch.Tensor | np.ndarray,
        rgb: torch.Tensor | np.ndarray,
        depth: torch.Tensor | np.ndarray | None = None,
    ) -> int:
        """Write frame ``i = num_frames``: ``rgb/<i>.png`` and ``depth/<i>.png``.

        Args:
            timestamp: seconds, greater than the previous frame's.
            T_wc: (4, 4) camera-to-world pose.
            rgb: (3, H, W) float in [0, 1] or (H, W, 3) uint8, the camera's size.
            depth: (H, W) or (1, H, W) metres (0 = no measurement), or ``None``; either
                every frame has depth or none does.

        Returns:
            The frame index.
        """
        self._check_open()
        t = self._check_time(timestamp, self._times, "frame")
        pose = _pose(T_wc, "T_wc")
        width, height = self.calib.camera.width, self.calib.camera.height
        shape = tuple(rgb.shape)
        if shape not in ((3, height, width), (height, width, 3)):
            raise ShapeError(
                f"rgb must be (3, {height}, {width}) or ({height}, {width}, 3) for "
                f"this camera, got {shape}"
            )
        has_depth = depth is not None
        if self._has_depth is not None and has_depth != self._has_depth:
            raise ValueError("either every frame has a depth image or none does")
        if has_depth and tuple(depth.shape)[-2:] != (height, width):
            raise ShapeError(
                f"depth must be ({height}, {width}) for this camera, got {tuple(depth.shape)}"
            )
        i = len(self._times)
        write_rgb(self.seq_dir / "rgb" / frame_name(i, ".png"), rgb)
        if has_depth:
            write_depth(
                self.seq_dir / "depth" / frame_name(i, ".png"), depth, self.calib.depth_scale
            )
        self._has_depth = has_depth
        self._times.append(t)
        self._poses.append(pose)
        return i

    def add_sweep(
        self,
        timestamp: float,
        T_wl: torch.Tensor | np.ndarray,
        points_lidar: torch.Tensor | np.ndarray,
    ) -> int:
        """Write sweep ``j = num_sweeps`` as ``lidar/<j>.ply``.

        Args:
            timestamp: seconds, greater than the previous sweep's.
            T_wl: (4, 4) lidar-to-world pose at the sweep time.
            points_lidar: (P, 3) points in the lidar frame (stored as float32).

        Returns:
            The sweep index.
        """
        self._check_open()
        t = self._check_time(timestamp, self._sweep_times, "sweep")
        pose = _pose(T_wl, "T_wl")
        j = len(self._sweep_times)
        write_point_cloud(self.seq_dir / "lidar" / frame_name(j, ".ply"), points_lidar)
        self._sweep_times.append(t)
        self._sweep_poses.append(pose)
        return j

    def close(self) -> Path:
        """Write ``poses.txt`` (and ``lidar/poses.txt`` if there are sweeps).

        Returns:
            The sequence folder.

        Raises:
            ValueError: no frames were added.
        """
        self._check_open()
        if not self._times:
            raise ValueError(f"{self.seq_dir}: a sequence needs at least one frame")
        write_tum(self.seq_dir / "poses.txt", np.array(self._times), torch.stack(self._poses))
        if self._sweep_times:
            write_tum(
                self.seq_dir / "lidar" / "poses.txt",
                np.array(self._sweep_times),
                torch.stack(self._sweep_poses),
            )
        self._closed = True
        return self.seq_dir

    def __enter__(self) -> SequenceWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None and not self._closed:
            self.close()


def write_dataset_info(
    root: str | os.PathLike, sequences: list[str], metadata: dict[str, Any] | None = None
) -> Path:
    """Write ``<root>/dataset.json`` (atomically, sorted keys).

    Args:
        root: the dataset folder.
        sequences: sequence folder names.
        metadata: further JSON-serialisable entries (must not redefine the reserved keys).

    Returns:
        The path of ``dataset.json``.
    """
    reserved = {"format_version", "kind", "sequences"}
    extra = dict(metadata or {})
    clash = reserved & set(extra)
    if clash:
        raise ValueError(f"metadata must not set reserved keys {sorted(clash)}")
    if not all(isinstance(s, str) and s for s in sequences):
        raise ValueError(f"sequence names must be non-empty strings, got {sequences}")
    info = {
        "format_version": DATASET_FORMAT_VERSION,
        "kind": DATASET_KIND,
        "sequences": list(sequences),
        **extra,
    }
    path = Path(root) / "dataset.json"
    atomic_write_text(path, json.dumps(info, indent=2, sort_keys=True) + "\n")
    return path


def read_dataset_info(root: str | os.PathLike) -> dict[str, Any]:
    """Read and validate ``<root>/dataset.json``.

    Returns:
        The parsed JSON object.

    Raises:
        FileNotFoundError: no ``dataset.json``.
        ValueError: not JSON, wrong ``kind``, unknown ``format_version``, bad ``sequences``.
    """
    path = Path(root) / "dataset.json"
    if not path.is_file():
        raise FileNotFoundError(f"dataset description not found: {path}")
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON: {exc}") from exc
    if not isinstance(info, dict):
        raise ValueError(f"{path}: expected a JSON object")
    if info.get("kind") != DATASET_KIND:
        raise ValueError(f"{path}: 'kind' must be {DATASET_KIND!r}, got {info.get('kind')!r}")
    version = info.get("format_version")
    if isinstance(version, bool) or version != DATASET_FORMAT_VERSION:
        raise ValueError(
            f"{path}: unknown format_version {version!r} (this reader knows "
            f"{DATASET_FORMAT_VERSION})"
        )
    sequences = info.get("sequences")
    if not isinstance(sequences, list) or not all(isinstance(s, str) and s for s in sequences):
        raise ValueError(f"{path}: 'sequences' must be a list of sequence names")
    return info


def map_paths(root: str | os.PathLike) -> dict[str, Path]:
    """The scene-level map files of :data:`MAP_FILES` that exist under ``root``."""
    root = Path(root)
    return {key: root / rel for key, rel in MAP_FILES.items() if (root / rel).is_file()}


def _frame_files(folder: Path, count: int, suffix: str, source: Path) -> list[Path]:
    """The ``count`` frame files of ``folder``, checking that exactly those exist."""
    if not folder.is_dir():
        raise FileNotFoundError(f"folder not found: {folder}")
    found = sorted(p.name for p in folder.glob(f"*{suffix}"))
    expected = [frame_name(i, suffix) for i in range(count)]
    if len(found) != count:
        raise ValueError(
            f"{folder}: holds {len(found)} {suffix} files but {source} has {count} rows"
        )
    if set(found) != set(expected):
        odd = sorted(set(found) - set(expected))[:3]
        raise ValueError(f"{folder}: unexpected file names {odd} (expected 000000{suffix} ...)")
    return [folder / name for name in expected]


def read_sequence_dir(seq_dir: str | os.PathLike, name: str | None = None) -> SequenceData:
    """Read one sequence folder of the dataset format.

    Args:
        seq_dir: the sequence folder.
        name: the sequence name (default: the folder name).

    Returns:
        The :class:`SequenceData` (depth and lidar when their folders exist).

    Raises:
        FileNotFoundError: a missing folder, ``calib.yaml``, ``poses.txt``, ``rgb/`` or
            ``lidar/poses.txt`` (when ``lidar/`` exists).
        ValueError: malformed files, or file counts that differ from the poses rows.
    """
    seq_dir = Path(seq_dir)
    if not seq_dir.is_dir():
        raise FileNotFoundError(f"sequence folder not found: {seq_dir}")
    calib = read_calib(seq_dir / "calib.yaml")
    poses = seq_dir / "poses.txt"
    timestamps, T_wc = read_tum(poses)
    rgb_paths = _frame_files(seq_dir / "rgb", len(timestamps), ".png", poses)
    depth_paths = None
    if (seq_dir / "depth").exists():
        depth_paths = _frame_files(seq_dir / "depth", len(timestamps), ".png", poses)
    lidar_paths: list[Path] = []
    lidar_timestamps = np.zeros(0)
    T_wl = None
    if (seq_dir / "lidar").exists():
        lidar_poses = seq_dir / "lidar" / "poses.txt"
        lidar_timestamps, T_wl = read_tum(lidar_poses)
        lidar_paths = _frame_files(seq_dir / "lidar", len(lidar_timestamps), ".ply", lidar_poses)
    return SequenceData(
        name=name if name is not None else seq_dir.name,
        timestamps=timestamps,
        T_wc=T_wc,
        camera=calib.camera,
        rgb_paths=rgb_paths,
        depth_paths=depth_paths,
        depth_scale=calib.depth_scale,
        T_body_camera=calib.T_body_camera,
        T_body_lidar=calib.T_body_lidar,
        lidar_paths=lidar_paths,
        lidar_timestamps=lidar_timestamps,
        T_wl=T_wl,
        info={"calib": calib},
    )


def read_sequence(root: str | os.PathLike, name: str) -> SequenceData:
    """Read sequence ``name`` of the dataset at ``root``.

    Args:
        root: the dataset folder (with ``dataset.json``).
        name: a sequence listed in ``dataset.json``.

    Returns:
        The :class:`SequenceData`.

    Raises:
        FileNotFoundError: missing ``dataset.json`` or sequence files.
        ValueError: ``name`` not listed, malformed files, count mismatches.

    Example:
        >>> from diffloc.geometry.camera import PinholeCamera
        >>> camera = PinholeCamera(fx=40.0, fy=40.0, cx=15.5, cy=11.5, width=32, height=24)
        >>> with SequenceWriter("data/mapping", Calibration(camera)) as writer:
        ...     for i in range(3):
        ...         _ = writer.add_frame(0.5 * i, torch.eye(4), torch.zeros(3, 24, 32))
        >>> _ = write_dataset_info("data", ["mapping"])
        >>> seq = read_sequence("data", "mapping")
        >>> len(seq), seq.load_rgb(2).shape
        (3, torch.Size([3, 24, 32]))
    """
    info = read_dataset_info(root)
    if name not in info["sequences"]:
        raise ValueError(
            f"{Path(root) / 'dataset.json'}: no sequence {name!r} (it lists {info['sequences']})"
        )
    return read_sequence_dir(Path(root) / name, name)
