"""``calib.yaml``: camera intrinsics, depth scale, sensor rig and lidar model of a sequence.

Layout (``format_version: 1``)::

    format_version: 1
    camera:
      model: pinhole
      width: 640
      height: 480
      fx: 500.0
      fy: 500.0
      cx: 319.5
      cy: 239.5
      distortion: {model: radtan, k1: 0.0, k2: 0.0, p1: 0.0, p2: 0.0}   # or null
    depth_scale: 1000.0          # depth PNG units per metre
    rig:
      T_body_camera: [[...4...], [...], [...], [...]]   # 4x4 nested list, or null
      T_body_lidar: null                                # 4x4 nested list, or null
      urdf: null                                        # URDF text of the rig, or null
    lidar: null                  # free-form mapping of lidar model parameters, or null

Floats are written with Python's shortest round-trip ``repr`` (PyYAML's float representer),
so reading back gives exactly the values written. Unknown keys are rejected (a misspelt key
must not silently fall back to a default). ``camera.distortion``, ``rig.T_body_lidar``,
``rig.urdf`` and ``lidar`` may be omitted and then mean ``null``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from diffloc.geometry.camera import PinholeCamera
from diffloc.io.atomic import atomic_write_text

__all__ = [
    "CALIB_FORMAT_VERSION",
    "Calibration",
    "calib_to_dict",
    "camera_from_dict",
    "camera_to_dict",
    "read_calib",
    "write_calib",
]

CALIB_FORMAT_VERSION = 1
_RIGID_TOLERANCE = 1e-6


class _FlowList(list):
    """A list that YAML writes on one line (matrix rows)."""


class _BlockStr(str):
    """A multi-line string that YAML writes as a literal block (URDF text)."""


class _Dumper(yaml.SafeDumper):
    pass


_Dumper.add_representer(
    _BlockStr,
    lambda dumper, data: dumper.represent_scalar("tag:yaml.org,2002:str", str(data), style="|"),
)


_Dumper.add_representer(
    _FlowList,
    lambda dumper, data: dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=True),
)


def _where(source: str | os.PathLike, key: str) -> str:
    return f"{source}: key '{key}'"


def _number(value: Any, source: str | os.PathLike, key: str) -> float:
    """A finite float from an int/float (or a numeric string from YAML 1.1 quirks)."""
    if isinstance(value, bool):
        raise ValueError(f"{_where(source, key)} must be a number, got {value!r}")
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            raise ValueError(f"{_where(source, key)} must be a number, got {value!r}") from None
    if not isinstance(value, int | float):
        raise ValueError(f"{_where(source, key)} must be a number, got {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{_where(source, key)} must be finite, got {value}")
    return value


def _positive_int(value: Any, source: str | os.PathLike, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{_where(source, key)} must be a positive integer, got {value!r}")
    return value


def _mapping(
    value: Any,
    source: str | os.PathLike,
    key: str,
    required: set[str],
    optional: set[str] = frozenset(),
) -> dict:
    if not isinstance(value, dict):
        raise ValueError(f"{_where(source, key)} must be a mapping, got {type(value).__name__}")
    missing = sorted(required - set(value))
    if missing:
        raise ValueError(f"{_where(source, key)} is missing {', '.join(map(repr, missing))}")
    unknown = sorted(set(value) - required - set(optional), key=str)
    if unknown:
        raise ValueError(f"{_where(source, key)} has unknown keys {', '.join(map(repr, unknown))}")
    return value


def _scalar(t: torch.Tensor, what: str) -> float:
    if t.numel() != 1:
        raise ValueError(
            f"{what} must belong to a single (unbatched) camera, got shape {tuple(t.shape)}"
        )
    return float(t.reshape(()))


def camera_to_dict(camera: PinholeCamera) -> dict[str, Any]:
    """The ``camera:`` mapping of ``calib.yaml`` for an unbatched camera.

    Args:
        camera: an unbatched :class:`PinholeCamera`.

    Returns:
        ``{model, width, height, fx, fy, cx, cy, distortion}`` with Python floats/ints.
    """
    out: dict[str, Any] = {
        "model": "pinhole",
        "width": int(camera.width),
        "height": int(camera.height),
    }
    for key in ("fx", "fy", "cx", "cy"):
        out[key] = _scalar(getattr(camera, key), f"camera.{key}")
    if camera.distortion is None:
        out["distortion"] = None
    else:
        d = camera.distortion.reshape(-1, 4)
        if d.shape[0] != 1:
            raise ValueError("camera.distortion must belong to a single (unbatched) camera")
        k1, k2, p1, p2 = (float(v) for v in d[0])
        out["distortion"] = {"model": "radtan", "k1": k1, "k2": k2, "p1": p1, "p2": p2}
    return out


def camera_from_dict(
    mapping: Any, source: str | os.PathLike = "<camera>", key: str = "camera"
) -> PinholeCamera:
    """Build an unbatched float64 :class:`PinholeCamera` from a ``camera:`` mapping.

    Args:
        mapping: the mapping (see the module docstring).
        source: file name used in error messages.
        key: key path used in error messages.

    Raises:
        ValueError: missing/unknown keys, wrong types, non-positive sizes or focal lengths.
    """
    cam = _mapping(
        mapping, source, key, {"model", "width", "height", "fx", "fy", "cx", "cy"}, {"distortion"}
    )
    if cam["model"] != "pinhole":
        raise ValueError(
            f"{_where(source, key + '.model')} must be 'pinhole', got {cam['model']!r}"
        )
    width = _positive_int(cam["width"], source, f"{key}.width")
    height = _positive_int(cam["height"], source, f"{key}.height")
    values = {k: _number(cam[k], source, f"{key}.{k}") for k in ("fx", "fy", "cx", "cy")}
    for k in ("fx", "fy"):
        if values[k] <= 0:
            raise ValueError(f"{_where(source, f'{key}.{k}')} must be positive, got {values[k]}")
    distortion = None
    if cam.get("distortion") is not None:
        dkey = f"{key}.distortion"
        dist = _mapping(cam["distortion"], source, dkey, {"model", "k1", "k2", "p1", "p2"})
        if dist["model"] != "radtan":
            raise ValueError(
                f"{_where(source, dkey + '.model')} must be 'radtan', got {dist['model']!r}"
            )
        coefficients = [_number(dist[k], source, f"{dkey}.{k}") for k in ("k1", "k2", "p1", "p2")]
        distortion = torch.tensor(coefficients, dtype=torch.float64)
    return PinholeCamera(
        fx=torch.tensor(values["fx"], dtype=torch.float64),
        fy=torch.tensor(values["fy"], dtype=torch.float64),
        cx=torch.tensor(values["cx"], dtype=torch.float64),
        cy=torch.tensor(values["cy"], dtype=torch.float64),
        width=width,
        height=height,
        distortion=distortion,
    )


def _check_rigid(T: torch.Tensor, source: str | os.PathLike, key: str) -> None:
    R = T[:3, :3]
    ortho = float((R.T @ R - torch.eye(3, dtype=T.dtype)).abs().max())
    det = float(torch.linalg.det(R))
    bottom = float((T[3] - torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype)).abs().max())
    if ortho > _RIGID_TOLERANCE or abs(det - 1) > _RIGID_TOLERANCE or bottom > _RIGID_TOLERANCE:
        raise ValueError(
            f"{_where(source, key)} is not a rigid transform (R^T R - I up to "
            f"{ortho:.2e}, det R = {det:.9f}, last row off by {bottom:.2e})"
        )


def _matrix_from_yaml(value: Any, source: str | os.PathLike, key: str) -> torch.Tensor | None:
    if value is None:
        return None
    if (
        not isinstance(value, list)
        or len(value) != 4
        or not all(isinstance(row, list) and len(row) == 4 for row in value)
    ):
        raise ValueError(f"{_where(source, key)} must be a 4x4 nested list or null")
    T = torch.tensor([[_number(v, source, key) for v in row] for row in value], dtype=torch.float64)
    _check_rigid(T, source, key)
    return T


def _matrix_to_yaml(T: torch.Tensor | None) -> list | None:
    if T is None:
        return None
    return [_FlowList(float(v) for v in row) for row in T.detach().cpu().to(torch.float64)]


@dataclass
class Calibration:
    """Sensor calibration of one sequence.

    Attributes:
        camera: the (unbatched) camera.
        depth_scale: depth PNG units per metre (1000 = millimetres).
        T_body_camera: (4, 4) float64 camera-to-body transform, or ``None``.
        T_body_lidar: (4, 4) float64 lidar-to-body transform, or ``None``.
        rig_urdf: URDF text of the sensor rig, or ``None``.
        lidar: free-form lidar model parameters (YAML-serialisable), or ``None``.
    """

    camera: PinholeCamera
    depth_scale: float = 1000.0
    T_body_camera: torch.Tensor | None = None
    T_body_lidar: torch.Tensor | None = None
    rig_urdf: str | None = None
    lidar: dict | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.camera, PinholeCamera):
            raise TypeError(f"camera must be a PinholeCamera, got {type(self.camera).__name__}")
        self.depth_scale = _number(self.depth_scale, "Calibration", "depth_scale")
        if self.depth_scale <= 0:
            raise ValueError(f"depth_scale must be positive, got {self.depth_scale}")
        for key in ("T_body_camera", "T_body_lidar"):
            T = getattr(self, key)
            if T is None:
                continue
            T = torch.as_tensor(np.asarray(T) if not isinstance(T, torch.Tensor) else T)
            T = T.detach().cpu().to(torch.float64)
            if T.shape != (4, 4):
                raise ValueError(f"{key} must have shape (4, 4), got {tuple(T.shape)}")
            if not bool(torch.isfinite(T).all()):
                raise ValueError(f"{key} contains NaN or infinite values")
            _check_rigid(T, "Calibration", key)
            setattr(self, key, T)
        if self.rig_urdf is not None and not isinstance(self.rig_urdf, str):
            raise ValueError(f"rig_urdf must be a string or None, got {type(self.rig_urdf)}")
        if self.lidar is not None and not isinstance(self.lidar, dict):
            raise ValueError(f"lidar must be a mapping or None, got {type(self.lidar)}")


def calib_to_dict(calib: Calibration) -> dict[str, Any]:
    """The ``calib.yaml`` content of ``calib`` as plain Python data."""
    return {
        "format_version": CALIB_FORMAT_VERSION,
        "camera": camera_to_dict(calib.camera),
        "depth_scale": float(calib.depth_scale),
        "rig": {
            "T_body_camera": _matrix_to_yaml(calib.T_body_camera),
            "T_body_lidar": _matrix_to_yaml(calib.T_body_lidar),
            "urdf": None
            if calib.rig_urdf is None
            else (_BlockStr(calib.rig_urdf) if "\n" in calib.rig_urdf else calib.rig_urdf),
        },
        "lidar": calib.lidar,
    }


def write_calib(path: str | os.PathLike, calib: Calibration) -> None:
    """Write ``calib`` as ``calib.yaml`` (atomically, deterministic bytes).

    Args:
        path: the file to write.
        calib: the calibration.

    Raises:
        ValueError: a batched camera, or ``lidar`` holding values YAML cannot represent.

    Example:
        >>> camera = PinholeCamera(fx=200.0, fy=200.0, cx=79.5, cy=59.5, width=160, height=120)
        >>> write_calib("calib.yaml", Calibration(camera, depth_scale=1000.0))
        >>> read_calib("calib.yaml").camera.width
        160
    """
    try:
        text = yaml.dump(
            calib_to_dict(calib),
            Dumper=_Dumper,
            sort_keys=False,
            default_flow_style=False,
            allow_unicode=False,
            width=100,
        )
    except yaml.representer.RepresenterError as exc:
        raise ValueError(f"{path}: calibration holds a value YAML cannot store: {exc}") from exc
    atomic_write_text(path, "# diffloc sensor calibration\n" + text)


def read_calib(path: str | os.PathLike) -> Calibration:
    """Read and validate a ``calib.yaml``.

    Args:
        path: the file.

    Returns:
        The :class:`Calibration` (camera and matrices in float64).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: unreadable YAML, unknown ``format_version``, missing or unknown keys,
            wrong types, non-positive sizes/focal lengths/depth scale, non-rigid matrices. The
            message names the file and the key.

    Example:
        >>> camera = PinholeCamera(fx=200.0, fy=200.0, cx=79.5, cy=59.5, width=160, height=120)
        >>> write_calib("calib.yaml", Calibration(camera))
        >>> calib = read_calib("calib.yaml")
        >>> calib.camera.width, calib.depth_scale, calib.T_body_camera
        (160, 1000.0, None)
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not valid YAML: {exc}") from exc
    top = _mapping(
        data, path, "<top level>", {"format_version", "camera", "depth_scale", "rig"}, {"lidar"}
    )
    version = top["format_version"]
    if isinstance(version, bool) or version != CALIB_FORMAT_VERSION:
        raise ValueError(
            f"{_where(path, 'format_version')}: unknown version {version!r} "
            f"(this reader knows {CALIB_FORMAT_VERSION})"
        )
    camera = camera_from_dict(top["camera"], path, "camera")
    depth_scale = _number(top["depth_scale"], path, "depth_scale")
    if depth_scale <= 0:
        raise ValueError(f"{_where(path, 'depth_scale')} must be positive, got {depth_scale}")
    rig = _mapping(top["rig"], path, "rig", {"T_body_camera"}, {"T_body_lidar", "urdf"})
    T_body_camera = _matrix_from_yaml(rig["T_body_camera"], path, "rig.T_body_camera")
    T_body_lidar = _matrix_from_yaml(rig.get("T_body_lidar"), path, "rig.T_body_lidar")
    urdf = rig.get("urdf")
    if urdf is not None and not isinstance(urdf, str):
        raise ValueError(f"{_where(path, 'rig.urdf')} must be a string or null")
    lidar = top.get("lidar")
    if lidar is not None and not isinstance(lidar, dict):
        raise ValueError(f"{_where(path, 'lidar')} must be a mapping or null")
    return Calibration(
        camera=camera,
        depth_scale=depth_scale,
        T_body_camera=T_body_camera,
        T_body_lidar=T_body_lidar,
        rig_urdf=urdf,
        lidar=lidar,
    )
