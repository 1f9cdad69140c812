"""RGB and depth image files (PNG through OpenCV).

Inside diffloc images are float32 ``(3, H, W)`` RGB in [0, 1] and depth is float32
``(1, H, W)`` metres with 0 = no measurement. Files hold 8-bit RGB and 16-bit depth PNGs.
PNGs are written with a fixed compression level so the bytes are deterministic, and
atomically.

Depth PNG: ``value = round(depth_m * scale)`` (round half to even) as uint16, ``scale`` units
per metre (1000 = millimetres, TUM RGB-D uses 5000). 0 stays 0 (no measurement). Depths whose
value exceeds 65535 (above 65.535 m at scale 1000, 13.107 m at 5000) and positive depths that
round to 0 (below half a unit) are stored as 0, i.e. they become "no measurement".
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np
import torch

from diffloc.checks import ShapeError
from diffloc.io.atomic import atomic_write_bytes

__all__ = ["PNG_COMPRESSION", "read_depth", "read_rgb", "write_depth", "write_rgb"]

PNG_COMPRESSION = 3
"""zlib level of written PNGs (fixed, so the same pixels always give the same bytes)."""

_WRITABLE = {".png": [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION]}


def _to_numpy(x: np.ndarray | torch.Tensor) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _encode(path: Path, image: np.ndarray) -> bytes:
    suffix = path.suffix.lower()
    if suffix not in _WRITABLE:
        raise ValueError(f"{path}: only PNG files can be written (got suffix {suffix!r})")
    ok, buffer = cv2.imencode(suffix, image, _WRITABLE[suffix])
    if not ok:
        raise ValueError(f"{path}: OpenCV could not encode the image")
    return buffer.tobytes()


def _decode(path: str | os.PathLike) -> tuple[Path, np.ndarray]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image file not found: {path}")
    data = np.frombuffer(path.read_bytes(), dtype=np.uint8)
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if image is None:
        raise ValueError(f"{path}: not a readable image (corrupt or unsupported format)")
    return path, image


def write_rgb(path: str | os.PathLike, image: np.ndarray | torch.Tensor) -> None:
    """Write an RGB image as an 8-bit PNG (atomically, deterministic bytes).

    Args:
        path: a ``.png`` path.
        image: (3, H, W) float in [0, 1] (values outside are clamped; stored as
            ``round(255 * x)``), or (H, W, 3) uint8 RGB (stored as is).

    Raises:
        ShapeError: another shape.
        ValueError: NaN values, or a suffix other than ``.png``.

    Example:
        >>> write_rgb("frame.png", torch.full((3, 120, 160), 0.5))
        >>> read_rgb("frame.png")[:, 0, 0]  # round(255 * 0.5) / 255
        tensor([0.5020, 0.5020, 0.5020])
    """
    path = Path(path)
    array = _to_numpy(image)
    if array.ndim == 3 and array.shape[2] == 3 and array.dtype == np.uint8:
        rgb = array
    elif array.ndim == 3 and array.shape[0] == 3 and array.dtype.kind == "f":
        if np.isnan(array).any():
            raise ValueError(f"{path}: image contains NaN values")
        scaled = np.rint(np.clip(array.astype(np.float64), 0.0, 1.0) * 255.0)
        rgb = scaled.astype(np.uint8).transpose(1, 2, 0)
    else:
        raise ShapeError(
            f"{path}: image must be (3, H, W) float in [0, 1] or (H, W, 3) uint8, got "
            f"{tuple(array.shape)} {array.dtype}"
        )
    bgr = np.ascontiguousarray(rgb[:, :, ::-1])
    atomic_write_bytes(path, _encode(path, bgr))


def read_rgb(path: str | os.PathLike) -> torch.Tensor:
    """Read an image file as RGB.

    Grey images are repeated over the three channels, an alpha channel is dropped, 16-bit
    images are divided by 65535 instead of 255.

    Args:
        path: the image file (any format OpenCV decodes).

    Returns:
        (3, H, W) float32 tensor in [0, 1], RGB order.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file cannot be decoded.

    Example:
        >>> write_rgb("frame.png", torch.zeros(3, 120, 160))
        >>> rgb = read_rgb("frame.png")
        >>> rgb.shape, rgb.dtype
        (torch.Size([3, 120, 160]), torch.float32)
    """
    path, image = _decode(path)
    if image.dtype == np.uint8:
        scale = 255.0
    elif image.dtype == np.uint16:
        scale = 65535.0
    else:
        raise ValueError(f"{path}: unsupported image dtype {image.dtype}")
    if image.ndim == 2:
        rgb = np.repeat(image[:, :, None], 3, axis=2)
    elif image.ndim == 3 and image.shape[2] in (3, 4):
        rgb = image[:, :, 2::-1]
    elif image.ndim == 3 and image.shape[2] == 1:
        rgb = np.repeat(image, 3, axis=2)
    else:
        raise ValueError(f"{path}: unsupported image shape {image.shape}")
    chw = np.ascontiguousarray(rgb.transpose(2, 0, 1)).astype(np.float32)
    return torch.from_numpy(chw / np.float32(scale))


def _check_scale(scale: float) -> float:
    if (
        isinstance(scale, bool)
        or not isinstance(scale, int | float)
        or not math.isfinite(scale)
        or scale <= 0
    ):
        raise ValueError(f"depth scale must be a positive finite number, got {scale!r}")
    return float(scale)


def write_depth(
    path: str | os.PathLike, depth_m: np.ndarray | torch.Tensor, scale: float = 1000.0
) -> None:
    """Write a depth map as a 16-bit PNG (atomically, deterministic bytes).

    Args:
        path: a ``.png`` path.
        depth_m: (H, W) or (1, H, W) depth in metres; 0 = no measurement.
        scale: PNG units per metre (1000 = millimetres). Values above ``65535 / scale`` metres
            (including +inf) are stored as 0 (no measurement).

    Raises:
        ShapeError: another shape.
        ValueError: NaN or negative depths, a non-positive scale.

    Example:
        >>> write_depth("depth.png", torch.full((120, 160), 2.5))  # stored as 2500 mm
        >>> float(read_depth("depth.png").max())
        2.5
    """
    path = Path(path)
    scale = _check_scale(scale)
    array = _to_numpy(depth_m)
    if array.ndim == 3 and array.shape[0] == 1:
        array = array[0]
    if array.ndim != 2:
        raise ShapeError(f"{path}: depth must be (H, W) or (1, H, W), got {tuple(array.shape)}")
    array = array.astype(np.float64)
    if np.isnan(array).any():
        raise ValueError(f"{path}: depth contains NaN values (use 0 for no measurement)")
    if (array < 0).any():
        raise ValueError(f"{path}: depth contains negative values")
    with np.errstate(over="ignore", invalid="ignore"):
        units = np.rint(array * scale)
    units[~(units <= 65535)] = 0
    atomic_write_bytes(path, _encode(path, units.astype(np.uint16)))


def read_depth(path: str | os.PathLike, scale: float = 1000.0) -> torch.Tensor:
    """Read a 16-bit depth PNG.

    Args:
        path: the file.
        scale: PNG units per metre.

    Returns:
        (1, H, W) float32 tensor in metres; 0 = no measurement.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file cannot be decoded or is not a single-channel 16-bit image.

    Example:
        >>> write_depth("depth.png", torch.tensor([[0.0, 1.2345]]))
        >>> read_depth("depth.png", scale=1000.0)  # (1, H, W) metres; 0 = no measurement
        tensor([[[0.0000, 1.2350]]])
    """
    scale = _check_scale(scale)
    path, image = _decode(path)
    if image.dtype != np.uint16 or image.ndim != 2:
        raise ValueError(
            f"{path}: expected a single-channel 16-bit depth PNG, got "
            f"{image.dtype} with shape {image.shape}"
        )
    metres = (image.astype(np.float64) / scale).astype(np.float32)
    return torch.from_numpy(metres[None])
