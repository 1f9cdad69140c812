"""Rays: camera rays of pixels, and ray / box intersection for the near and far bounds."""

from __future__ import annotations

import torch

from diffloc.checks import check_shape
from diffloc.geometry.camera import PinholeCamera

__all__ = ["camera_rays", "ray_box_bounds"]


def camera_rays(
    camera: PinholeCamera, T_wc: torch.Tensor, uv: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """World-frame rays through pixels of a pinhole camera (OpenCV frame, no distortion).

    Args:
        camera: unbatched pinhole camera.
        T_wc: (4, 4) camera-to-world pose.
        uv: (N, 2) pixel coordinates (integers are pixel centres).

    Returns:
        ``(origins, directions, z_per_metre)``: (N, 3) ray origins, (N, 3) unit directions
        and (N,) camera z of a point one metre along each ray (depth = range * z_per_metre).

    Example:
        >>> cam = PinholeCamera.from_fov(4, 3, 1.0)
        >>> o, d, z = camera_rays(cam, torch.eye(4), torch.tensor([[1.5, 1.0]]))
        >>> d.tolist(), z.tolist()
        ([[0.0, 0.0, 1.0]], [1.0])
    """
    check_shape(T_wc, "4,4", "T_wc")
    check_shape(uv, "N,2", "uv")
    if camera.distortion is not None and bool((camera.distortion != 0).any()):
        raise ValueError("camera_rays needs an undistorted pinhole camera")
    T = T_wc.to(uv.dtype)
    x = (uv[:, 0] - camera.cx.to(uv.dtype)) / camera.fx.to(uv.dtype)
    y = (uv[:, 1] - camera.cy.to(uv.dtype)) / camera.fy.to(uv.dtype)
    d_cam = torch.stack((x, y, torch.ones_like(x)), dim=-1)
    z_per_metre = 1.0 / d_cam.norm(dim=-1)
    directions = (d_cam * z_per_metre[:, None]) @ T[:3, :3].T
    return T[:3, 3].expand_as(directions), directions, z_per_metre


def ray_box_bounds(
    origins: torch.Tensor,
    directions: torch.Tensor,
    box_min: torch.Tensor,
    box_max: torch.Tensor,
    near_min: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit distances of rays through an axis-aligned box (slab method).

    Args:
        origins: (N, 3) ray origins.
        directions: (N, 3) ray directions.
        box_min: (3,) lower corner.
        box_max: (3,) upper corner.
        near_min: smallest near distance (metres).

    Returns:
        ``(near, far)``: (N,) each; ``far <= near`` for rays that miss the box.
    """
    check_shape(origins, "N,3", "origins")
    check_shape(directions, "N,3", "directions")
    safe = torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    t0 = (box_min.to(origins) - origins) / safe
    t1 = (box_max.to(origins) - origins) / safe
    near = torch.minimum(t0, t1).amax(dim=-1).clamp_min(near_min)
    far = torch.maximum(t0, t1).amin(dim=-1)
    return near, far
