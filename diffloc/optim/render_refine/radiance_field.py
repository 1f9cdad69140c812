"""A trained radiance field as a differentiable map, and its query appearance codes.

Rendering is :func:`~diffloc.maps.nerf.renderer.render_rays` with deterministic samples
(strata centres) and a fixed appearance code per query. The encodings interpolate with
``grid_sample``, which has no forward-mode autodiff rule, so the pose linearisation is built
from reverse mode instead: a ray's outputs depend only on its own origin ``o`` and direction
``d``, so one backward pass of ``sum_rays y`` gives ``dy/do`` and ``dy/dd`` of every ray at once
(five passes: r, g, b, depth, opacity). For the right perturbation ``T_wc @ se3_exp([v, w])``,
``do/dv_k = R e_k`` and ``dd/dw_k = (R e_k) x d`` (``R`` the camera-to-world rotation), the
other derivatives being zero.

The query's appearance code is fitted NeRF-W style (:func:`fit_query_appearance`): the field
frozen, Adam on the code over the query's pixels rendered at the initial (localised) pose,
starting from the mean training code. The package's affine colour fit stays on top of it.
"""

from __future__ import annotations

import torch

from diffloc.checks import check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.maps.nerf.appearance import fit_appearance_code
from diffloc.maps.nerf.field import RadianceField
from diffloc.maps.nerf.rays import camera_rays
from diffloc.maps.nerf.renderer import render_rays
from diffloc.maps.nerf.sampler import DensityGrid
from diffloc.optim.render_refine.linearization import DifferentiableMap
from diffloc.render.soft_splat import SoftRender

__all__ = ["fit_query_appearance", "radiance_field_map"]


def _rays(
    field: RadianceField, camera: PinholeCamera, T_wc: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Origins, directions (P, 3) and z per metre (P,) of all pixels, in the field's dtype."""
    dtype = field.appearance.weight.dtype
    uv = camera.pixel_grid(dtype).reshape(-1, 2)
    return camera_rays(camera.to(dtype), T_wc.to(dtype), uv)


def _images(values: torch.Tensor, camera: PinholeCamera) -> SoftRender:
    """(..., P, 5) per-ray rgb, depth, opacity -> a :class:`SoftRender` (..., C, H, W)."""
    images = values.movedim(-1, -2).unflatten(-1, (camera.height, camera.width))
    return SoftRender(images[..., :3, :, :], images[..., 3:4, :, :], images[..., 4:, :, :])


def radiance_field_map(
    field: RadianceField, grid: DensityGrid, appearance: torch.Tensor, chunk: int = 4096
) -> DifferentiableMap:
    """A trained field rendered with one appearance code per query (module doc).

    Args:
        field: the trained field (``load_field``).
        grid: its density grid.
        appearance: (B, A) appearance codes of the ``B`` queries (:func:`fit_query_appearance`)
            or (A,) one for all.
        chunk: rays per render pass.

    Returns:
        The :class:`DifferentiableMap`; renders and tangents come in the field's dtype.

    Raises:
        ShapeError: codes of the wrong length.

    Usage::

        field, grid = load_field("nerf/submap_0/field")
        codes = fit_query_appearance(field, grid, images, T_wc, camera)
        result = refine_pose_by_rendering(radiance_field_map(field, grid, codes), images,
                                          T_wc, camera)
    """
    check_shape(appearance, f"*,{field.config.appearance_dim}", "appearance")

    def code(b: int, rays: int) -> torch.Tensor:
        row = appearance if appearance.dim() == 1 else appearance[b]
        return row.to(field.appearance.weight).expand(rays, -1)

    def per_ray(
        origins: torch.Tensor, directions: torch.Tensor, z: torch.Tensor, codes: torch.Tensor
    ) -> torch.Tensor:
        out = render_rays(field, grid, origins, directions, None, codes)
        return torch.cat((out.rgb, (out.range * z)[:, None], out.opacity[:, None]), dim=-1)

    def render(T_wc: torch.Tensor, camera: PinholeCamera) -> SoftRender:
        views = []
        with torch.no_grad():
            for b, pose in enumerate(T_wc):
                o, d, z = _rays(field, camera, pose)
                parts = [
                    per_ray(o[s], d[s], z[s], code(b, len(z[s])))
                    for s in torch.arange(len(z)).split(chunk)
                ]
                views.append(torch.cat(parts))
        return _images(torch.stack(views), camera)

    def linearize(T_wc: torch.Tensor, camera: PinholeCamera) -> tuple[SoftRender, SoftRender]:
        values, tangents = [], []
        for b, pose in enumerate(T_wc):
            o, d, z = _rays(field, camera, pose)
            axes = pose[:3, :3].to(d).T  # (3, 3) rows: R e_k
            value, tangent = [], []
            for s in torch.arange(len(z)).split(chunk):
                with torch.enable_grad():
                    origins = o[s].detach().clone().requires_grad_(True)
                    directions = d[s].detach().clone().requires_grad_(True)
                    y = per_ray(origins, directions, z[s], code(b, len(s)))
                    grads = [
                        torch.autograd.grad(y[:, c].sum(), (origins, directions), retain_graph=True)
                        for c in range(5)
                    ]
                g_o = torch.stack([g[0] for g in grads], -1)  # (P, 3, 5)
                g_d = torch.stack([g[1] for g in grads], -1)
                moved = torch.linalg.cross(axes[:, None, :], directions.detach()[None], dim=-1)
                translation = torch.einsum("pjc,kj->pck", g_o, axes)
                rotation = torch.einsum("pjc,kpj->pck", g_d, moved)
                value.append(y.detach())
                tangent.append(torch.cat((translation, rotation), -1))  # (P, 5, 6)
            values.append(torch.cat(value))
            tangents.append(torch.cat(tangent))
        tangent_images = _images(torch.stack(tangents).permute(3, 0, 1, 2), camera)
        return _images(torch.stack(values), camera), tangent_images

    return DifferentiableMap(render, linearize)


def fit_query_appearance(
    field: RadianceField,
    grid: DensityGrid,
    image: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    steps: int = 60,
    batch: int = 1024,
    lr: float = 0.05,
) -> torch.Tensor:
    """Appearance codes of query images at their initial poses (NeRF-W test-time fit).

    Args:
        field: the trained field.
        grid: its density grid.
        image: (B, 3, H, W) query images at ``camera``'s size.
        T_wc: (B, 4, 4) initial poses.
        camera: the query camera.
        steps: Adam steps per query.
        batch: rays per step.
        lr: Adam learning rate.

    Returns:
        (B, A) codes (A = 0 for a field without codes: the affine colour fit alone then
        absorbs the query's exposure).
    """
    check_shape(T_wc, "B,4,4", "T_wc")
    check_shape(image, f"{T_wc.shape[0]},3,{camera.height},{camera.width}", "image")
    codes = []
    for pose, rgb in zip(T_wc, image, strict=True):
        o, d, _ = _rays(field, camera, pose)
        colours = rgb.reshape(3, -1).T.to(o)
        codes.append(fit_appearance_code(field, grid, o, d, colours, steps, batch, lr))
    return torch.stack(codes)
