"""Soft, differentiable point splatting: depth-ordered alpha compositing of 2D Gaussians.

Each point is an isotropic world-space blob of radius ``r`` drawn as an axis-aligned 2D
Gaussian with screen-space standard deviations ``sigma_u = fx r / z`` and ``sigma_v = fy r / z``
(clamped to ``[min_sigma_px, window / 6]``) centred on its projection. Its opacity at a pixel
centre ``p`` is ``alpha = min(opacity * exp(-|p - uv|^2_sigma / 2), 0.99)``. Per pixel the
points are composited front to back in order of their camera-frame depth ``z``
(3D Gaussian splatting style):

    w_i = alpha_i * prod_{j nearer than i} (1 - alpha_j)
    rgb = sum_i w_i c_i,   alpha = sum_i w_i = 1 - prod_i (1 - alpha_i),
    depth = sum_i w_i z_i / alpha  (0 where alpha = 0)

``rgb`` is premultiplied (composited over black): ``rgb / alpha`` is the mean colour.

**Support.** A point only touches the ``window x window`` pixels around the pixel nearest to
its projection (``floor(uv + 0.5)``); the Gaussian is cut off outside. With
``sigma <= window / 6`` the cut is beyond three standard deviations. The cost and memory are
``O(B N window^2)``: every (camera, point, window pixel) triple is one candidate; candidates
are sorted by pixel (stably, after sorting the points by depth), and a segmented exclusive
cumulative sum of ``log(1 - alpha)`` gives the transmittances in one vectorised pass.

**Gradients** flow to the camera pose (through a left perturbation ``xi``, see
:func:`soft_render_points`), the point positions (Gaussian centres, sizes and depths), the
colours and the radii. They are zero through the depth order, the window placement and
clamped sizes/opacities (piecewise-constant choices), as in other splatting renderers.

Points with NaN/inf coordinates or behind the camera (``z <= MIN_DEPTH`` of
:mod:`diffloc.geometry.camera`) are culled, like in :mod:`diffloc.render.point_render`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from diffloc.checks import ShapeError, check_finite, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import invert, se3_exp, transform_points

__all__ = ["ALPHA_MAX", "SoftRender", "soft_render_points"]

ALPHA_MAX = 0.99
"""Largest opacity of one splat at one pixel, so that ``log(1 - alpha)`` stays finite."""


@dataclass(frozen=True)
class SoftRender:
    """Differentiable render of a point map.

    Attributes:
        rgb: (B, 3, H, W) colour composited over black (premultiplied by ``alpha``).
        depth: (B, 1, H, W) alpha-normalised expected z-depth in metres, 0 where alpha is 0.
        alpha: (B, 1, H, W) accumulated opacity in [0, 1).
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor


@dataclass(frozen=True)
class _Splats:
    """Visible (camera, point) pairs sorted by depth: projections and sizes, all (E,)."""

    cam: torch.Tensor  # camera index
    point: torch.Tensor  # point index
    u: torch.Tensor  # projection
    v: torch.Tensor
    z: torch.Tensor  # camera-frame depth
    sigma_u: torch.Tensor  # screen-space standard deviations (pixels)
    sigma_v: torch.Tensor


def _check_inputs(
    points: torch.Tensor,
    colors: torch.Tensor,
    radii: torch.Tensor | float,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    xi: torch.Tensor | None,
) -> torch.Tensor:
    """Validate the inputs; return the radii as an (N,) tensor of the points' dtype."""
    check_shape(points, "N,3", "points")
    check_shape(colors, "N,3", "colors")
    if colors.shape[0] != points.shape[0]:
        raise ShapeError(
            f"colors must have one row per point: {colors.shape[0]} != {points.shape[0]}"
        )
    if not points.is_floating_point():
        raise TypeError(f"points must be a floating point tensor, got {points.dtype}")
    check_shape(T_wc, "B,4,4", "T_wc")
    batch = T_wc.shape[0]
    if batch == 0:
        raise ShapeError("T_wc must hold at least one pose, got shape (0, 4, 4)")
    check_finite(T_wc, "T_wc")
    if xi is not None:
        check_shape(xi, "B,6", "xi")
        if xi.shape[0] != batch:
            raise ShapeError(f"xi must have shape ({batch}, 6), got {tuple(xi.shape)}")
        check_finite(xi, "xi")
    if tuple(camera.batch_shape) not in ((), (batch,)):
        raise ShapeError(
            f"camera batch shape must be () or ({batch},), got {tuple(camera.batch_shape)}"
        )
    radii = torch.as_tensor(radii, dtype=points.dtype, device=points.device)
    if radii.dim() == 0:
        radii = radii.expand(points.shape[0])
    check_shape(radii, "N", "radii")
    if radii.shape[0] != points.shape[0]:
        raise ShapeError(f"radii must have shape ({points.shape[0]},), got {tuple(radii.shape)}")
    if bool((radii <= 0).any()):
        raise ValueError("radii must be positive")
    return radii


def _visible_splats(
    points: torch.Tensor,
    radii: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    min_sigma_px: float,
    max_sigma_px: float,
) -> _Splats:
    """Project the points into every camera, cull and sort the visible pairs by depth."""
    batch, num_points = T_wc.shape[0], points.shape[0]
    points_cam = transform_points(invert(T_wc), points)  # (B, N, 3)
    uv, valid = camera.project(points_cam)
    valid = valid & torch.isfinite(points_cam).all(-1) & torch.isfinite(uv).all(-1)
    cam, point = valid.nonzero(as_tuple=True)
    z = points_cam[..., 2].reshape(-1).index_select(0, cam * num_points + point)
    order = torch.argsort(z.detach(), stable=True)
    cam, point, z = (t.index_select(0, order) for t in (cam, point, z))
    flat = cam * num_points + point
    u, v = (c.reshape(-1).index_select(0, flat) for c in uv.unbind(-1))
    size = radii.index_select(0, point) / z
    fx = camera.fx.expand(batch).index_select(0, cam)
    fy = camera.fy.expand(batch).index_select(0, cam)
    sigma_u = (fx * size).clamp(min_sigma_px, max_sigma_px)
    sigma_v = (fy * size).clamp(min_sigma_px, max_sigma_px)
    return _Splats(cam, point, u, v, z, sigma_u, sigma_v)


def _transmittance(log_keep: torch.Tensor, slot: torch.Tensor) -> torch.Tensor:
    """Exclusive product of ``1 - alpha`` within runs of equal ``slot`` (sorted by slot).

    Args:
        log_keep: (K,) ``log(1 - alpha)`` of the candidates, front to back within a slot.
        slot: (K,) pixel slot of each candidate, non-decreasing.

    Returns:
        (K,) ``prod_{earlier j in the same slot} (1 - alpha_j)``.
    """
    wide = log_keep.double()  # a global running sum: keep it exact enough in float64
    exclusive = wide.cumsum(0) - wide
    first = torch.ones_like(slot, dtype=torch.bool)
    first[1:] = slot[1:] != slot[:-1]
    run = first.cumsum(0) - 1
    return torch.exp(exclusive - exclusive[first][run]).to(log_keep.dtype)


def soft_render_points(
    points: torch.Tensor,
    colors: torch.Tensor,
    radii: torch.Tensor | float,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    xi: torch.Tensor | None = None,
    *,
    window: int = 5,
    min_sigma_px: float = 0.5,
    opacity: float = 1.0,
) -> SoftRender:
    """Render points as depth-composited 2D Gaussians, differentiably (see the module doc).

    The camera pose used is ``T_wc' = se3_exp(xi) @ T_wc``: ``xi = [v, w]`` is a left
    (world-frame) perturbation, so ``d render / d xi`` at ``xi = 0`` is the gradient with
    respect to the pose on the manifold; update with ``T_wc <- se3_exp(step) @ T_wc``.

    Args:
        points: (N, 3) world points (metres), float32 or float64; sets the compute dtype.
        colors: (N, 3) colours.
        radii: (N,) or scalar world radius of each blob in metres (> 0).
        T_wc: (B, 4, 4) camera-to-world poses.
        camera: one camera or a batch of ``B`` (same image size); distortion allowed.
        xi: optional (B, 6) pose perturbations (the usual choice: zeros requiring grad).
        window: odd side of the square pixel support of each splat.
        min_sigma_px: smallest screen-space standard deviation in pixels (> 0).
        opacity: peak opacity of a splat in (0, 1]; the per-pixel opacity is capped at
            :data:`ALPHA_MAX`.

    Returns:
        A :class:`SoftRender` with rgb (B, 3, H, W), depth (B, 1, H, W), alpha (B, 1, H, W).

    Raises:
        ShapeError: wrong shapes, ``B = 0``, or a camera batch that does not match ``T_wc``.
        ValueError: non-finite poses or ``xi``, radii ``<= 0``, a bad window, sigma or opacity.

    Example:
        >>> cam = PinholeCamera.from_fov(16, 12, 1.0)
        >>> xi = torch.zeros(1, 6, requires_grad=True)
        >>> out = soft_render_points(torch.tensor([[0.0, 0.0, 2.0]]), torch.ones(1, 3), 0.05,
        ...                          torch.eye(4)[None], cam, xi)
        >>> out.depth[0, 0, 6, 8].item()
        2.0
        >>> out.rgb.sum().backward()
    """
    radii = _check_inputs(points, colors, radii, T_wc, camera, xi)
    if not (isinstance(window, int) and window > 0 and window % 2 == 1):
        raise ValueError(f"window must be a positive odd integer, got {window!r}")
    if not (math.isfinite(min_sigma_px) and 0 < min_sigma_px <= window / 6):
        raise ValueError(f"min_sigma_px must be in (0, window / 6], got {min_sigma_px!r}")
    if not (0 < opacity <= 1):
        raise ValueError(f"opacity must be in (0, 1], got {opacity!r}")
    dtype = points.dtype
    batch, height, width = T_wc.shape[0], camera.height, camera.width
    camera = camera.to(dtype)
    T_wc = T_wc.to(dtype)
    if xi is not None:
        T_wc = se3_exp(xi.to(dtype)) @ T_wc
    splats = _visible_splats(points, radii, T_wc, camera, min_sigma_px, window / 6)

    # Candidates: every splat x every pixel of its window that lies in the image.
    half = window // 2
    offsets = torch.arange(-half, half + 1, device=points.device)
    ov, ou = torch.meshgrid(offsets, offsets, indexing="ij")
    pu = torch.floor(splats.u.detach() + 0.5).long()[:, None] + ou.reshape(1, -1)
    pv = torch.floor(splats.v.detach() + 0.5).long()[:, None] + ov.reshape(1, -1)
    inside = ((pu >= 0) & (pu < width) & (pv >= 0) & (pv < height)).view(-1)
    candidate = inside.nonzero()[:, 0]
    splat = torch.arange(len(splats.z), device=points.device).repeat_interleave(window**2)
    splat = splat.index_select(0, candidate)
    pu, pv = pu.view(-1).index_select(0, candidate), pv.view(-1).index_select(0, candidate)
    slot = (splats.cam.index_select(0, splat) * height + pv) * width + pu
    slot, by_pixel = torch.sort(slot, stable=True)  # stable: depth order kept per pixel
    splat, pu, pv = (t.index_select(0, by_pixel) for t in (splat, pu, pv))

    def pick(values: torch.Tensor) -> torch.Tensor:  # (E,) -> per candidate
        return values.index_select(0, splat)

    du = (pu.to(dtype) - pick(splats.u)) / pick(splats.sigma_u)
    dv = (pv.to(dtype) - pick(splats.v)) / pick(splats.sigma_v)
    alpha = (opacity * torch.exp(-0.5 * (du * du + dv * dv))).clamp_max(ALPHA_MAX)
    weight = alpha * _transmittance(torch.log1p(-alpha), slot)

    num_slots = batch * height * width
    colors = colors.to(dtype).T.contiguous().index_select(1, pick(splats.point))  # (3, K)
    zeros = torch.zeros(num_slots, dtype=dtype, device=points.device)
    rgb = torch.zeros(3, num_slots, dtype=dtype, device=points.device)
    rgb = rgb.index_add(1, slot, weight * colors)
    alpha_sum = zeros.index_add(0, slot, weight)
    depth_sum = zeros.index_add(0, slot, weight * pick(splats.z))
    covered = alpha_sum > 0
    depth = torch.where(covered, depth_sum / torch.where(covered, alpha_sum, 1.0), 0.0)
    return SoftRender(
        rgb.view(3, batch, height, width).transpose(0, 1).contiguous(),
        depth.view(batch, 1, height, width),
        alpha_sum.view(batch, 1, height, width),
    )
