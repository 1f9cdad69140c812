"""Training rays of one submap: pixels of its mapping images (with their poses) and the
returns of its lidar sweeps; every ``holdout_every``-th mapping frame is held out, with the
sweep nearest to it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from diffloc.checks import check_int_at_least, check_number
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.sequence import SequenceData
from diffloc.maps.nerf.lidar_rays import LidarRays, lidar_rays
from diffloc.maps.nerf.no_return import NoReturnRays, no_return_rays
from diffloc.maps.nerf.rays import camera_rays

__all__ = [
    "SubmapDataConfig",
    "SubmapRays",
    "build_submap_rays",
    "load_image",
    "split_frames",
    "training_sweeps",
]


@dataclass
class SubmapDataConfig:
    """Settings of the training rays.

    Attributes:
        image_scale: image resize factor (0.25: 640x480 -> 160x120).
        holdout_every: frames whose index is a multiple of this are held out (0: none).
        lidar_max_range_m: returns farther than this are not used.
        box_range_m: returns within this range of the sensor span the field's box (with the
            camera positions); 0: every return used. With the mip-NeRF 360 contraction the box
            is the part of the cube at full resolution and farther returns still supervise
            depth in the contracted space (outdoors: a 15 m box, returns up to 80 m).
        lidar_stride: every n-th return becomes a ray.
        normal_radius_m: neighbourhood radius of the lidar normals.
        box_percentile: the field's box spans these percentiles of the lidar endpoints.
        box_padding_m: padding of the box, metres.
    """

    image_scale: float = 0.25
    holdout_every: int = 8
    lidar_max_range_m: float = 10.0
    box_range_m: float = 0.0
    lidar_stride: int = 2
    normal_radius_m: float = 0.15
    box_percentile: float = 0.5
    box_padding_m: float = 0.3

    def __post_init__(self) -> None:
        check_number(self.image_scale, "image_scale", 0.0, 1.0, open_low=True)
        check_int_at_least(self.holdout_every, "holdout_every", 0)
        check_number(self.lidar_max_range_m, "lidar_max_range_m", 0.0, open_low=True)
        check_number(self.box_range_m, "box_range_m", 0.0)
        check_int_at_least(self.lidar_stride, "lidar_stride", 1)
        check_number(self.normal_radius_m, "normal_radius_m", 0.0, open_low=True)
        check_number(self.box_percentile, "box_percentile", 0.0, 50.0, open_high=True)
        check_number(self.box_padding_m, "box_padding_m", 0.0)


@dataclass
class SubmapRays:
    """Everything training one submap needs, as tensors.

    Attributes:
        frames: mapping frame indices used for training; image code i is ``frames[i]``.
        heldout: held-out frame indices of the submap.
        camera: the (resized) camera.
        rgb: (P, 3) pixel colours of the training images.
        origins: (P, 3) camera ray origins.
        directions: (P, 3) unit camera ray directions.
        image: (P,) int64 training-image index of each pixel.
        lidar: the lidar rays.
        box_min: (3,) lower corner of the field's box.
        box_max: (3,) upper corner.
        no_return: the lidar rays without a return of the same sweeps, or ``None`` (not
            built).
    """

    frames: list[int]
    heldout: list[int]
    camera: PinholeCamera
    rgb: torch.Tensor
    origins: torch.Tensor
    directions: torch.Tensor
    image: torch.Tensor
    lidar: LidarRays
    box_min: torch.Tensor
    box_max: torch.Tensor
    no_return: NoReturnRays | None = None


def split_frames(frames: list[int], holdout_every: int) -> tuple[list[int], list[int]]:
    """``(train, heldout)`` frames: held out are those whose index is a multiple of
    ``holdout_every`` (none when it is 0)."""
    heldout = [f for f in frames if holdout_every and f % holdout_every == 0]
    return [f for f in frames if f not in heldout], heldout


def load_image(seq: SequenceData, frame: int, camera: PinholeCamera) -> torch.Tensor:
    """Image ``frame`` resized (area) to ``camera``'s size: (3, H, W) float32."""
    rgb = seq.load_rgb(frame)[None]
    return F.interpolate(rgb, size=(camera.height, camera.width), mode="area")[0]


def _sweeps_of(seq: SequenceData, frames: list[int]) -> set[int]:
    """Indices of the sweeps nearest in time to the frames."""
    if not len(seq.lidar_timestamps) or not frames:
        return set()
    times = seq.timestamps[frames]
    nearest = np.abs(seq.lidar_timestamps[None] - times[:, None]).argmin(axis=1)
    return set(nearest.tolist())


def training_sweeps(seq: SequenceData, train: list[int], heldout: list[int]) -> list[int]:
    """The sweeps a submap trains on: those nearest in time to its training frames, except
    those nearest to a held-out frame. With a lidar slower than the camera (outdoors 1 Hz
    against 2 Hz) a training frame's nearest sweep can be the one taken at a held-out frame;
    it is left out, so that nothing recorded at a held-out frame is trained on.

    Args:
        seq: the mapping sequence.
        train: training frame indices.
        heldout: held-out frame indices.

    Returns:
        Sorted sweep indices (empty when the sequence has no sweeps).
    """
    return sorted(_sweeps_of(seq, train) - _sweeps_of(seq, heldout))


def build_submap_rays(
    seq: SequenceData,
    frames: list[int],
    config: SubmapDataConfig,
    name: str = "submap",
    no_return: bool = False,
) -> SubmapRays:
    """Training rays of the submap made of ``frames`` of the mapping sequence ``seq``.

    Uses the images, the mapping poses and the lidar sweeps, nothing else (no depth images).

    Args:
        seq: the mapping sequence.
        frames: the submap's frame indices.
        config: settings.
        name: used in error messages.
        no_return: also build the lidar rays without a return of the training sweeps
            (:func:`~diffloc.maps.nerf.no_return.no_return_rays`, the empty-space loss).

    Returns:
        The :class:`SubmapRays`.

    Raises:
        ValueError: fewer than two training frames, no lidar sweep near them, no return
            within ``box_range_m``, or (``no_return``) no lidar pattern in the calibration.
    """
    train, heldout = split_frames(sorted(frames), config.holdout_every)
    if len(train) < 2:
        raise ValueError(f"{name}: needs at least 2 training frames, has {len(train)}")
    sweeps = training_sweeps(seq, train, heldout)
    if not sweeps:
        raise ValueError(f"{name}: no lidar sweeps (the depth and normal losses need them)")
    lidar = lidar_rays(
        seq, sweeps, config.lidar_max_range_m, config.normal_radius_m, config.lidar_stride
    )
    camera = seq.camera.scaled(config.image_scale)
    uv = camera.pixel_grid(torch.float32).reshape(-1, 2)
    rgb, origins, directions, image = [], [], [], []
    for i, frame in enumerate(train):
        rgb.append(load_image(seq, frame, camera).reshape(3, -1).T)
        o, d, _ = camera_rays(camera, seq.T_wc[frame].float(), uv)
        origins.append(o)
        directions.append(d)
        image.append(torch.full((len(uv),), i, dtype=torch.int64))
    near = lidar.ranges <= config.box_range_m if config.box_range_m > 0 else slice(None)
    ends = (lidar.origins + lidar.ranges[:, None] * lidar.directions)[near].numpy()
    if not len(ends):
        raise ValueError(f"{name}: no lidar return within box_range_m={config.box_range_m} m")
    cams = seq.T_wc[train, :3, 3].float().numpy()
    low = np.minimum(np.percentile(ends, config.box_percentile, axis=0), cams.min(0))
    high = np.maximum(np.percentile(ends, 100 - config.box_percentile, axis=0), cams.max(0))
    return SubmapRays(
        frames=train,
        heldout=heldout,
        camera=camera,
        rgb=torch.cat(rgb),
        origins=torch.cat(origins).contiguous(),
        directions=torch.cat(directions),
        image=torch.cat(image),
        lidar=lidar,
        box_min=torch.from_numpy(low - config.box_padding_m).float(),
        box_max=torch.from_numpy(high + config.box_padding_m).float(),
        no_return=no_return_rays(seq, sweeps) if no_return else None,
    )
