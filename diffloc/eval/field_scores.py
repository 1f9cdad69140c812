"""Held-out scores of a trained radiance field: NeRF-W PSNR, depth and normal error.

The protocol of issue 19 (``experiments/bench_nerf.py``, ``experiments/crossmodal_nerf.py``):
at each held-out mapping frame the appearance code is fitted on the left half of the image
(field frozen, :func:`~diffloc.maps.nerf.appearance.fit_appearance_code`) and PSNR is taken on
the right half, as NeRF-W does; depth and normal errors compare the render with that code to
the ground-truth depth image (scoring only: nothing here feeds the pipeline).

Example:
    >>> round(psnr(torch.zeros(3, 2, 2), torch.full((3, 2, 2), 0.1)), 6)
    20.0
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from diffloc.checks import check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.sequence import SequenceData
from diffloc.maps.nerf.appearance import fit_appearance_code
from diffloc.maps.nerf.data import load_image
from diffloc.maps.nerf.field import RadianceField
from diffloc.maps.nerf.rays import camera_rays
from diffloc.maps.nerf.renderer import render_image, render_rays
from diffloc.maps.nerf.sampler import DensityGrid

__all__ = ["depth_image_normals", "heldout_field_scores", "left_half_code", "psnr"]

_CODE_STEPS, _CODE_BATCH, _CODE_LR = 20, 512, 0.05
"""Adam steps, rays per step and learning rate of the left-half appearance-code fit."""
_DEPTH_JUMP = 0.05
"""Relative depth difference to a neighbour above which a pixel gets no reference normal."""


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR in dB of images ``a`` and ``b`` (same shape, values in [0, 1])."""
    return -10 * math.log10(max(float(((a - b) ** 2).mean()), 1e-12))


def depth_image_normals(depth: torch.Tensor, camera: PinholeCamera) -> torch.Tensor:
    """Camera-frame unit normals of a depth image by central differences, facing the camera.

    Args:
        depth: (1, H, W) z-depth in metres (0 = no measurement).
        camera: its pinhole camera (H, W the image size).

    Returns:
        (3, H, W) normals; zero at the border, where a neighbour has no depth and across a
        depth jump of more than 5 %.

    Example:
        >>> cam = PinholeCamera.from_fov(5, 4, 1.0)
        >>> depth_image_normals(torch.full((1, 4, 5), 2.0), cam)[:, 1, 2]
        tensor([ 0.,  0., -1.])
    """
    check_shape(depth, f"1,{camera.height},{camera.width}", "depth")
    h, w = depth.shape[-2:]
    uv = camera.pixel_grid(torch.float32)
    x = (uv[..., 0] - camera.cx) / camera.fx * depth[0]
    y = (uv[..., 1] - camera.cy) / camera.fy * depth[0]
    p = torch.stack((x, y, depth[0]), dim=0).float()
    du = p[:, 1:-1, 2:] - p[:, 1:-1, :-2]
    dv = p[:, 2:, 1:-1] - p[:, :-2, 1:-1]
    n = torch.cross(dv, du, dim=0)
    n = -n / n.norm(dim=0, keepdim=True).clamp_min(1e-9)
    n = torch.where((n * p[:, 1:-1, 1:-1]).sum(0, keepdim=True) > 0, -n, n)
    d = depth[0]
    patch = torch.stack((d[1:-1, 2:], d[1:-1, :-2], d[2:, 1:-1], d[:-2, 1:-1]))
    centre = d[1:-1, 1:-1]
    ok = (patch > 0).all(0) & ((patch - centre).abs() < _DEPTH_JUMP * centre).all(0)
    out = torch.zeros(3, h, w)
    out[:, 1:-1, 1:-1] = n * ok
    return out


@torch.no_grad()
def _render_rays_rgb(
    field: RadianceField,
    grid: DensityGrid,
    origins: torch.Tensor,
    directions: torch.Tensor,
    code: torch.Tensor,
) -> torch.Tensor:
    """(P, 3) colours of rays (P, 3) rendered with appearance ``code`` (A,), 8192 at a time."""
    g = torch.Generator().manual_seed(0)
    parts = [
        render_rays(field, grid, origins[sl], directions[sl], g, code.expand(len(sl), -1)).rgb
        for sl in torch.arange(len(origins)).split(8192)
    ]
    return torch.cat(parts)


def left_half_code(
    field: RadianceField,
    grid: DensityGrid,
    camera: PinholeCamera,
    T_wc: torch.Tensor,
    image: torch.Tensor,
) -> torch.Tensor:
    """The appearance code of the NeRF-W protocol: fitted (field frozen) on the left half of
    ``image`` (3, H, W) seen from ``T_wc`` (4, 4) by ``camera``; returns (A,)."""
    check_shape(image, f"3,{camera.height},{camera.width}", "image")
    uv = camera.pixel_grid(torch.float32).reshape(-1, 2)
    left = uv[:, 0] < camera.width / 2
    o, d, _ = camera_rays(camera, T_wc.float(), uv[left])
    colours = image.reshape(3, -1).T[left]
    return fit_appearance_code(field, grid, o, d, colours, _CODE_STEPS, _CODE_BATCH, _CODE_LR)


def heldout_field_scores(
    field: RadianceField,
    grid: DensityGrid,
    seq: SequenceData,
    camera: PinholeCamera,
    heldout: list[int],
    full: bool,
) -> dict[str, float]:
    """Held-out PSNR of a field (code fitted on the left half, PSNR on the right half); with
    ``full`` also the median depth and normal errors against the ground-truth depth images.

    Args:
        field: the trained field (put in eval mode while scoring, then back in train mode).
        grid: its density grid.
        seq: the sequence the held-out frames belong to (its ``T_wc``, images, depth).
        camera: the scoring resolution (e.g. ``seq.camera.scaled(0.25)``).
        heldout: frame indices of ``seq`` the field was not trained on (at least one).
        full: also render whole images and score depth and normals.

    Returns:
        ``psnr_heldout_db`` (mean over the frames); with ``full`` also
        ``depth_median_abs_err_m`` (over pixels with ground-truth depth) and
        ``normal_median_err_deg`` (over pixels with a reference normal), and the PSNR of the
        right halves split by the ground truth, pooled over the frames:
        ``psnr_heldout_surface_db`` (pixels with depth) and ``psnr_heldout_sky_db`` (pixels
        without, the sky outdoors; ``None`` when there is none), and ``sky_opacity_mean``,
        the mean rendered opacity of the pixels without depth over the whole held-out images
        (near 1: the field paints the sky with density instead of leaving it to a background
        colour; ``None`` without such pixels).

    Raises:
        ValueError: no held-out frame.
    """
    if not heldout:
        raise ValueError("heldout_field_scores needs at least one held-out frame")
    was_training = field.training
    field.eval()
    psnrs, depth_err, normal_err = [], [], []
    squared: dict[str, list[torch.Tensor]] = {"surface": [], "sky": []}
    sky_opacity = []
    uv = camera.pixel_grid(torch.float32).reshape(-1, 2)
    left = uv[:, 0] < camera.width / 2
    half = camera.width // 2
    for frame in heldout:
        T_wc = seq.T_wc[frame].float()
        image = load_image(seq, frame, camera)
        o, d, _ = camera_rays(camera, T_wc, uv)
        code = left_half_code(field, grid, camera, T_wc, image)
        if full:
            out = render_image(field, grid, camera, T_wc, code, with_normals=True)
            right = out["rgb"][:, :, half:]
        else:
            right = _render_rays_rgb(field, grid, o[~left], d[~left], code)
            right = right.T.reshape(3, camera.height, camera.width - half)
        psnrs.append(psnr(right, image[:, :, half:]))
        if full:
            gt = seq.load_depth(frame)
            gt = F.interpolate(gt[None], size=(camera.height, camera.width), mode="nearest")[0]
            valid = gt[0] > 0
            error = ((right - image[:, :, half:]) ** 2).mean(0)
            squared["surface"].append(error[valid[:, half:]])
            squared["sky"].append(error[~valid[:, half:]])
            sky_opacity.append(out["opacity"][0][~valid])
            depth_err.append((out["depth"][0] - gt[0])[valid].abs())
            n_gt = depth_image_normals(gt, camera)
            n_gt_world = torch.einsum("ij,jhw->ihw", T_wc[:3, :3], n_gt)
            ok = n_gt.abs().sum(0) > 0
            cos = (out["normal"] * n_gt_world).sum(0)[ok].clamp(-1, 1)
            normal_err.append(torch.rad2deg(torch.acos(cos)))
    field.train(was_training)
    result = {"psnr_heldout_db": float(np.mean(psnrs))}
    if full:
        result["depth_median_abs_err_m"] = float(torch.cat(depth_err).median())
        result["normal_median_err_deg"] = float(torch.cat(normal_err).median())
        opacity = torch.cat(sky_opacity)
        result["sky_opacity_mean"] = float(opacity.mean()) if len(opacity) else None
        for name, errors in squared.items():
            pooled = torch.cat(errors)
            result[f"psnr_heldout_{name}_db"] = (
                -10 * math.log10(max(float(pooled.mean()), 1e-12)) if len(pooled) else None
            )
    return result
