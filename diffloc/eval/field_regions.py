"""Where a radiance field's image error sits: pixels labelled sky / ground / facade / far from a
ground-truth depth image (scoring only), and the squared colour error pooled per label.

Labels (:data:`REGIONS`, index = label value): ``sky`` (no ground-truth depth), ``far``
(depth beyond ``far_m``, e.g. outside an outdoor field's full-resolution box), ``ground``
(within ``far_m``, surface point at most ``ground_max_z_m`` above the world's z = 0),
``facade`` (every other pixel within ``far_m``: walls, objects).

Example:
    >>> labels = torch.tensor([0, 1, 1, 3])  # sky, ground, ground, far
    >>> summary = region_summary(torch.tensor([0.01, 0.0, 0.0, 0.04]), labels)
    >>> round(summary["sky"]["psnr_db"], 3), round(summary["far"]["error_share"], 3)
    (20.0, 0.8)
    >>> summary["ground"]["pixels"], summary["facade"]["psnr_db"]
    (2, None)
"""

from __future__ import annotations

import math

import torch

from diffloc.checks import check_number, check_shape
from diffloc.geometry.camera import PinholeCamera

__all__ = ["REGIONS", "pixel_regions", "region_summary"]

REGIONS = ("sky", "ground", "facade", "far")
"""Region names; a label image holds their indices."""


def pixel_regions(
    depth: torch.Tensor,
    camera: PinholeCamera,
    T_wc: torch.Tensor,
    far_m: float,
    ground_max_z_m: float = 0.2,
) -> torch.Tensor:
    """Label each pixel of a ground-truth depth image with its region (:data:`REGIONS`).

    Args:
        depth: (1, H, W) ground-truth z-depth in metres (0: no return, the sky).
        camera: its pinhole camera (H, W the image size).
        T_wc: (4, 4) camera-to-world pose (world z up, the ground at z = 0 as in
            ``diffloc.sim``).
        far_m: pixels deeper than this are ``far``.
        ground_max_z_m: a pixel within ``far_m`` whose surface point lies at most this high
            (world z) is ``ground``. (Not by the depth image's normal: at grazing angles the
            ground's depth steps between rows by more than the normals' jump test allows.)

    Returns:
        (H, W) int64 labels, indices into :data:`REGIONS`.

    Raises:
        ValueError: ``far_m`` not positive, or a shape mismatch.
    """
    check_shape(depth, f"1,{camera.height},{camera.width}", "depth")
    check_shape(T_wc, "4,4", "T_wc")
    check_number(far_m, "far_m", 0.0, open_low=True)
    check_number(ground_max_z_m, "ground_max_z_m")
    d = depth[0].float()
    uv = camera.pixel_grid(torch.float32)
    points_cam = torch.stack(
        ((uv[..., 0] - camera.cx) / camera.fx * d, (uv[..., 1] - camera.cy) / camera.fy * d, d),
        dim=-1,
    )
    T = T_wc.float()
    z_world = points_cam @ T[2, :3] + T[2, 3]
    labels = torch.full(d.shape, REGIONS.index("facade"), dtype=torch.int64)
    labels[z_world <= ground_max_z_m] = REGIONS.index("ground")
    labels[d > far_m] = REGIONS.index("far")
    labels[d <= 0] = REGIONS.index("sky")
    return labels


def region_summary(squared_error: torch.Tensor, labels: torch.Tensor) -> dict[str, dict]:
    """Pool per-pixel squared colour errors by region.

    Args:
        squared_error: (N,) squared error of each pixel (mean over the colour channels).
        labels: (N,) int64 region labels (:func:`pixel_regions`).

    Returns:
        Per region name: ``pixels``, ``pixel_share`` (of all N), ``error_share`` (its part of
        the summed squared error) and ``psnr_db`` (of its pooled mean squared error; ``None``
        when it has no pixel).
    """
    check_shape(squared_error, "N", "squared_error")
    check_shape(labels, f"{len(squared_error)}", "labels")
    total = float(squared_error.sum())
    out = {}
    for index, name in enumerate(REGIONS):
        errors = squared_error[labels == index]
        mse = float(errors.mean()) if len(errors) else None
        out[name] = {
            "pixels": len(errors),
            "pixel_share": len(errors) / max(len(squared_error), 1),
            "error_share": float(errors.sum()) / total if total > 0 else 0.0,
            "psnr_db": None if mse is None else -10 * math.log10(max(mse, 1e-12)),
        }
    return out
