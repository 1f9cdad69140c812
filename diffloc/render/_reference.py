"""Slow, obviously correct pure-torch twins of the renderers, for tests and checks only.

Each fast renderer is compared against one of these: a dense float64 ray-disk intersection of
every pixel with every surfel (:func:`reference_surfels`, twin of
:func:`~diffloc.render.surfel_render.render_surfel_index`), a per-point loop that paints
squares into a z-buffer (:func:`reference_points`, twin of
:func:`~diffloc.render.point_render.render_points`) and every point against every pixel,
composited in depth order with a cumulative product (:func:`reference_soft_points`, twin of
:func:`~diffloc.render.soft_splat.soft_render_points`). They allocate (pixels x primitives)
tensors or loop in Python: tiny scenes only.
"""

from __future__ import annotations

import math

import torch

from diffloc.geometry.camera import MIN_DEPTH, PinholeCamera
from diffloc.geometry.se3 import invert, se3_exp, transform_points
from diffloc.render.point_sizes import PointSizes
from diffloc.render.soft_splat import ALPHA_MAX

__all__ = ["reference_points", "reference_soft_points", "reference_surfels"]


def reference_surfels(
    centers: torch.Tensor,
    normals: torch.Tensor,
    radii: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Dense float64 ray-disk z-buffer of two-sided surfels.

    ``margin`` is how far (relative to the radius) the winning hit is from the disk rim and
    from the runner-up depth: pixels with a tiny margin may legitimately differ in float32.

    Args:
        centers: (N, 3) surfel centres, world frame.
        normals: (N, 3) surfel normals (any non-zero length).
        radii: (N,) disk radii.
        T_wc: (B, 4, 4) camera-to-world poses.
        camera: one ideal pinhole camera or a batch of ``B``.

    Returns:
        ``(ids, depth, margin)``: (B, H, W) int64 surfel index (-1 where none), (B, H, W)
        float64 z-depth (0 where none) and (B, H, W) float64 margin.
    """
    c_w, n_w, r = centers.double(), normals.double(), radii.double()
    n_w = n_w / n_w.norm(dim=-1, keepdim=True)
    cam = camera.to(torch.float64)
    uv = cam.pixel_grid().reshape(-1, 2)
    batch = T_wc.shape[0]
    fx, fy = cam.fx.expand(batch), cam.fy.expand(batch)
    cx, cy = cam.cx.expand(batch), cam.cy.expand(batch)
    ids, depths, margins = [], [], []
    for b in range(batch):
        T_cw = invert(T_wc[b].double())
        c = transform_points(T_cw, c_w)  # (N, 3)
        n = n_w @ T_cw[:3, :3].T
        d = torch.stack(
            ((uv[:, 0] - cx[b]) / fx[b], (uv[:, 1] - cy[b]) / fy[b], torch.ones(len(uv))), -1
        )  # (P, 3)
        t = (n * c).sum(-1)[None] / (d @ n.T)  # (P, N)
        hit = t[..., None] * d[:, None] - c[None]
        rim = hit.norm(dim=-1) / r - 1.0
        ok = (rim <= 0) & (t > MIN_DEPTH) & (c[:, 2] > MIN_DEPTH)[None]
        t = torch.where(ok, t, math.inf)
        best, winner = t.min(-1)
        second = t.topk(min(2, t.shape[1]), dim=-1, largest=False).values[:, -1]
        gap = torch.where(second > best, (second - best) / best, math.inf).nan_to_num(math.inf)
        rim_margin = torch.where(ok, math.inf, rim.abs()).min(-1).values
        rim_margin = torch.minimum(rim_margin, rim.abs().gather(1, winner[:, None])[:, 0])
        margin = torch.minimum(rim_margin, gap)
        found = torch.isfinite(best)
        ids.append(torch.where(found, winner, -1).view(cam.height, cam.width))
        depths.append(torch.where(found, best, 0.0).view(cam.height, cam.width))
        margins.append(margin.view(cam.height, cam.width))
    return torch.stack(ids), torch.stack(depths), torch.stack(margins)


def reference_points(
    points: torch.Tensor,
    colors: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    sizes: PointSizes,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-point loop painting flat squares into a z-buffer (nearest float32 depth, then the
    lower index, wins).

    Args:
        points: (N, 3) points, world frame; rows with NaN/inf are skipped.
        colors: (N, 3) colours (unused: the ids pick them).
        T_wc: (B, 4, 4) camera-to-world poses.
        camera: one camera or a batch of ``B`` (distortion allowed).
        sizes: splat sizes.

    Returns:
        ``(ids, depth)``: (B, H, W) int64 point index (-1 where none) and (B, H, W) float64
        z-depth rounded to float32 (0 where none).
    """
    batch, h, w = T_wc.shape[0], camera.height, camera.width
    levels = sizes.pass_sizes()
    ids = torch.full((batch, h, w), -1)
    depth = torch.full((batch, h, w), math.inf)
    for b in range(batch):
        cam = camera if len(camera.batch_shape) == 0 else camera[b]
        p_c = transform_points(invert(T_wc[b].double()), points.double())
        uv, valid = cam.to(torch.float64).project(p_c)
        for i in range(points.shape[0]):
            z = float(p_c[i, 2])
            if not (valid[i] and torch.isfinite(points[i]).all()):
                continue
            rho = min(max(sizes.rho_max / z, sizes.rho_min), sizes.rho_max)
            side = min(levels, key=lambda k, rho=rho: (abs(k - rho), -k))
            u0 = math.ceil(float(uv[i, 0]) - side / 2)
            v0 = math.ceil(float(uv[i, 1]) - side / 2)
            for v in range(max(v0, 0), min(v0 + side, h)):
                for u in range(max(u0, 0), min(u0 + side, w)):
                    z32 = float(torch.tensor(z, dtype=torch.float32))
                    if (z32, i) < (float(depth[b, v, u]), int(ids[b, v, u])):
                        depth[b, v, u], ids[b, v, u] = z32, i
    return ids, torch.where(ids >= 0, depth, 0.0)


def reference_soft_points(
    points: torch.Tensor,
    colors: torch.Tensor,
    radii: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    xi: torch.Tensor,
    window: int,
    min_sigma: float,
    opacity: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every point against every pixel, composited in depth order with a cumulative product.

    Args:
        points: (N, 3) points, world frame.
        colors: (N, 3) colours.
        radii: (N,) world-space splat radii.
        T_wc: (B, 4, 4) camera-to-world poses.
        camera: one camera or a batch of ``B``.
        xi: (B, 6) left pose perturbation, ``T = se3_exp(xi) @ T_wc``.
        window: odd side of the square pixel support of each splat.
        min_sigma: smallest Gaussian standard deviation in pixels.
        opacity: peak opacity of a splat.

    Returns:
        ``(rgb, depth, alpha)``: (B, 3, H, W), (B, 1, H, W) and (B, 1, H, W), differentiable
        w.r.t. the points, colours and ``xi``.
    """
    T = se3_exp(xi) @ T_wc
    points_cam = transform_points(invert(T), points)  # (B, N, 3)
    uv, valid = camera.project(points_cam)
    z = points_cam[..., 2]
    batch = T_wc.shape[0]
    fx = camera.fx.expand(batch)[:, None]
    fy = camera.fy.expand(batch)[:, None]
    sigma_u = (fx * radii / z).clamp(min_sigma, window / 6)
    sigma_v = (fy * radii / z).clamp(min_sigma, window / 6)
    grid = camera.pixel_grid(points.dtype).reshape(-1, 2)  # (P, 2)
    du = grid[None, :, None, 0] - uv[:, None, :, 0]  # (B, P, N)
    dv = grid[None, :, None, 1] - uv[:, None, :, 1]
    centre = torch.floor(uv.detach() + 0.5)
    half = window // 2
    in_window = ((grid[None, :, None, 0] - centre[:, None, :, 0]).abs() <= half) & (
        (grid[None, :, None, 1] - centre[:, None, :, 1]).abs() <= half
    )
    gauss = torch.exp(-0.5 * ((du / sigma_u[:, None]) ** 2 + (dv / sigma_v[:, None]) ** 2))
    alpha = torch.where(in_window & valid[:, None], (opacity * gauss).clamp_max(ALPHA_MAX), 0.0)
    order = torch.argsort(z.detach(), dim=-1, stable=True)  # (B, N) front to back
    alpha = alpha.gather(2, order[:, None].expand_as(alpha))
    z_sorted = z.gather(1, order)
    color_sorted = colors[order]  # (B, N, 3)
    keep = torch.cumprod(1 - alpha, dim=-1)
    transmittance = torch.cat((torch.ones_like(keep[..., :1]), keep[..., :-1]), dim=-1)
    weight = transmittance * alpha  # (B, P, N)
    rgb = weight @ color_sorted  # (B, P, 3)
    alpha_sum = weight.sum(-1)
    depth_sum = (weight * z_sorted[:, None]).sum(-1)
    depth = torch.where(alpha_sum > 0, depth_sum / alpha_sum.clamp_min(1e-300), 0.0)
    h, w = camera.height, camera.width
    return (
        rgb.transpose(1, 2).reshape(batch, 3, h, w),
        depth.view(batch, 1, h, w),
        alpha_sum.view(batch, 1, h, w),
    )
