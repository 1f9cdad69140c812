"""Multi-view texture blending of seed 2 Eq. 3-4, exposure compensated.

Seed 2 colours each texel ``(u, v)`` of facet ``T_i`` from the n = 5 nearest mapping images:
``I_i(u, v) = 1 / sigma_bar * sum_j sigma_j I_j(pi(R_j, t_j, P))`` with
``sigma_bar = 1/n sum_j sigma_j`` and ``P = A^-1(u, v)``. As printed this is n times the
sigma-weighted mean, and it multiplies by the exposure where compensation must divide.

**Reading used here.** Images are linearised with the camera response (``I_lin = I^gamma``;
the response is a calibration a user has), view j's radiance estimate is ``I_lin,j / sigma_j``
and the views are averaged with weights ``sigma_j`` (the paper's weights; a longer exposure
collects more light, so its estimate is less noisy):

    L_i(u, v) = sum_j sigma_j (I_lin,j / sigma_j) / sum_j sigma_j = sum_j I_lin,j / sum_j sigma_j

which is the maximum-likelihood radiance under shot noise. The texture stores
``L^(1/gamma)``, the appearance at the reference exposure (the gauge of the exposures,
geometric mean 1 over the mapping images). With all ``sigma_j = 1`` ("none") it is the plain
mean of the views.

**Views.** For each texel the candidates are all mapping images in which its surface point
projects inside the image (``border_px`` from the edge), in front of the camera, on the
facet's outer side (``cos(normal, to camera) > min_cos_incidence``) and unoccluded: its depth
is at most the depth ray-cast from that camera against the reconstructed mesh at that pixel
plus a tolerance. Of these, the ``views_per_texel`` with the nearest camera centres are
blended (Eq. 3's "n nearest viewing cameras").

**Exposures.** ``sigma_j`` is estimated from the images alone (:mod:`diffloc.render.exposure`)
on the same texel observations: never from recorded exposures. Known exposures can be passed
in instead (an oracle when they come from the simulator's ground truth).

The texturer is in ``render/`` (not ``maps/``) because the occlusion test ray casts with
:class:`~diffloc.render.raycast.MeshRaycaster`, and ``maps`` sits below ``render``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from diffloc.checks import check_finite, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.progress import progress
from diffloc.render.exposure import ExposureEstimate, estimate_exposures
from diffloc.render.raycast import MeshRaycaster, camera_rays

__all__ = [
    "TextureBlendConfig",
    "TexelColors",
    "TexelViews",
    "blend_texels",
    "select_texel_views",
    "texture_texels",
    "view_depths",
]


@dataclass
class TextureBlendConfig:
    """Settings of the Eq. 3-4 blend.

    Attributes:
        views_per_texel: n, the nearest unoccluded views blended per texel (5 in seed 2).
        depth_tolerance_m: absolute slack of the occlusion test, metres.
        depth_tolerance_rel: slack proportional to the depth.
        min_cos_incidence: smallest cosine between the facet normal and the direction to the
            camera (rejects grazing and back-facing views).
        border_px: texels projecting closer than this to the image edge are not sampled.
        gamma: camera response, ``linear = image ** gamma``.
        dark_limit: samples darker than this (encoded grey) do not estimate exposures.
        bright_limit: samples with a channel brighter than this (encoded; may be clipped) do
            not either.
        min_pair_samples: view pairs sharing fewer samples do not constrain exposures.
        views_per_batch: cameras ray cast together for the occlusion depth maps.
    """

    views_per_texel: int = 5
    depth_tolerance_m: float = 0.03
    depth_tolerance_rel: float = 0.02
    min_cos_incidence: float = 0.15
    border_px: float = 1.0
    gamma: float = 2.2
    dark_limit: float = 0.04
    bright_limit: float = 0.96
    min_pair_samples: int = 20
    views_per_batch: int = 8

    def __post_init__(self) -> None:
        if self.views_per_texel < 1:
            raise ValueError(f"views_per_texel must be >= 1, got {self.views_per_texel}")
        if self.gamma <= 0:
            raise ValueError(f"gamma must be > 0, got {self.gamma}")


@dataclass
class TexelViews:
    """The views chosen per texel, nearest first.

    Attributes:
        view_ids: (T, n) int64 image indices, -1 where fewer than n views see the texel.
        uv: (T, n, 2) float32 pixel coordinates of the texel in those images.
        distance: (T, n) float32 camera-to-texel distances, inf where no view.
    """

    view_ids: torch.Tensor
    uv: torch.Tensor
    distance: torch.Tensor


@dataclass
class TexelColors:
    """Blended texel colours.

    Attributes:
        colors: (T, 3) float32 encoded colours in [0, 1], NaN where no view sees the texel.
        view_count: (T,) int64 views blended per texel.
        exposures: (V,) float64 exposures used (ones for "none").
        estimate: the exposure estimate when exposures were estimated, else ``None``.
    """

    colors: torch.Tensor
    view_count: torch.Tensor
    exposures: torch.Tensor
    estimate: ExposureEstimate | None


def view_depths(
    raycaster: MeshRaycaster, T_wc: torch.Tensor, camera: PinholeCamera, views_per_batch: int = 8
) -> torch.Tensor:
    """z-depth maps of the mesh seen from V cameras (ray cast), 0 where nothing is hit.

    Args:
        raycaster: the reconstructed mesh.
        T_wc: (V, 4, 4) camera-to-world poses.
        camera: the unbatched camera (H, W).
        views_per_batch: cameras cast at once.

    Returns:
        (V, H, W) float32 depths in metres.
    """
    check_shape(T_wc, "V,4,4", "T_wc")
    depths = []
    for batch in torch.split(T_wc, views_per_batch):
        origins, directions = camera_rays(camera, batch)
        hits = raycaster.cast(origins.reshape(-1, 3), directions.reshape(-1, 3))
        cos_axis = (directions * batch[:, None, :3, 2].to(torch.float32)).sum(-1).reshape(-1)
        depth = torch.where(hits.hit, hits.distance * cos_axis, torch.zeros_like(cos_axis))
        depths.append(depth.reshape(len(batch), camera.height, camera.width))
    return torch.cat(depths)


def select_texel_views(
    points: torch.Tensor,
    normals: torch.Tensor,
    depths: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    cfg: TextureBlendConfig,
    show_progress: bool = False,
) -> TexelViews:
    """The ``cfg.views_per_texel`` nearest cameras that see each texel unoccluded.

    Args:
        points: (T, 3) texel surface points, world frame.
        normals: (T, 3) unit outward normals of their facets.
        depths: (V, H, W) ray-cast depth maps of the mesh (:func:`view_depths`).
        T_wc: (V, 4, 4) camera-to-world poses.
        camera: the unbatched camera.
        cfg: the blend settings.
        show_progress: progress bar over the views.

    Returns:
        The :class:`TexelViews`, nearest first.
    """
    check_shape(points, "T,3", "points")
    check_shape(normals, f"{points.shape[0]},3", "normals")
    check_shape(T_wc, "V,4,4", "T_wc")
    check_shape(depths, f"{T_wc.shape[0]},{camera.height},{camera.width}", "depths")
    check_finite(T_wc, "T_wc")
    n, count = cfg.views_per_texel, points.shape[0]
    points32, normals32 = points.to(torch.float32), normals.to(torch.float32)
    cam32 = camera.to(torch.float32)
    T32 = T_wc.to(torch.float32)
    best_d = torch.full((count, n), float("inf"))
    best_v = torch.full((count, n), -1, dtype=torch.int64)
    best_uv = torch.zeros(count, n, 2)
    width, height = camera.width, camera.height
    for view in progress(range(len(T_wc)), "texel views", show_progress):
        centre = T32[view, :3, 3]
        z = (points32 - centre) @ T32[view, :3, 2]
        idx = torch.nonzero(z > 1e-3)[:, 0]
        points_cam = (points32[idx] - centre) @ T32[view, :3, :3]
        uv, _ = cam32.project(points_cam)
        b = cfg.border_px
        inside = (uv[:, 0] >= b - 0.5) & (uv[:, 0] <= width - 0.5 - b)
        inside &= (uv[:, 1] >= b - 0.5) & (uv[:, 1] <= height - 0.5 - b)
        idx, uv = idx[inside], uv[inside]
        col = uv[:, 0].round().long().clamp(0, width - 1)
        row = uv[:, 1].round().long().clamp(0, height - 1)
        surface = depths[view, row, col]
        depth = z[idx]
        seen = (surface > 0) & (
            depth <= surface + cfg.depth_tolerance_m + cfg.depth_tolerance_rel * surface
        )
        to_camera = centre - points32[idx]
        distance = to_camera.norm(dim=1)
        facing = (normals32[idx] * to_camera).sum(dim=1) > cfg.min_cos_incidence * distance
        keep = seen & facing
        keep &= distance < best_d[idx, -1]
        idx, uv, distance = idx[keep], uv[keep], distance[keep]
        cand_d = torch.cat([best_d[idx], distance[:, None]], dim=1)
        cand_v = torch.cat([best_v[idx], torch.full_like(idx, view)[:, None]], dim=1)
        cand_uv = torch.cat([best_uv[idx], uv[:, None]], dim=1)
        order = torch.argsort(cand_d, dim=1)[:, :n]
        best_d[idx] = torch.gather(cand_d, 1, order)
        best_v[idx] = torch.gather(cand_v, 1, order)
        best_uv[idx] = torch.gather(cand_uv, 1, order[..., None].expand(-1, -1, 2))
    return TexelViews(view_ids=best_v, uv=best_uv, distance=best_d)


def sample_views(images: torch.Tensor, views: TexelViews) -> torch.Tensor:
    """Bilinear colours (T, n, 3) of every chosen view at its texel's pixel (0 for no view).

    Args:
        images: (V, 3, H, W) float32 encoded images in [0, 1].
        views: the texels' views.
    """
    check_shape(images, "V,3,H,W", "images")
    _, _, height, width = images.shape
    flat = images.permute(0, 2, 3, 1).reshape(-1, 3)
    view = views.view_ids.clamp_min(0)
    xy0 = torch.floor(views.uv)
    frac = views.uv - xy0
    x0 = xy0[..., 0].long().clamp(0, width - 1)
    y0 = xy0[..., 1].long().clamp(0, height - 1)
    x1, y1 = (x0 + 1).clamp(max=width - 1), (y0 + 1).clamp(max=height - 1)
    base = view * height * width

    def at(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return flat[(base + y * width + x).reshape(-1)].reshape(*view.shape, 3)

    fx, fy = frac[..., 0:1], frac[..., 1:2]
    top = at(y0, x0) * (1 - fx) + at(y0, x1) * fx
    bottom = at(y1, x0) * (1 - fx) + at(y1, x1) * fx
    colors = top * (1 - fy) + bottom * fy
    return torch.where((views.view_ids >= 0)[..., None], colors, torch.zeros_like(colors))


def blend_texels(
    samples: torch.Tensor, view_ids: torch.Tensor, exposures: torch.Tensor, gamma: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 3 as read in the module docstring: ``(sum_j I_lin,j / sum_j sigma_j)^(1/gamma)``.

    Args:
        samples: (T, n, 3) encoded colours of the chosen views.
        view_ids: (T, n) their images, -1 for none.
        exposures: (V,) exposure of every image.
        gamma: camera response.

    Returns:
        (T, 3) float32 encoded colours (NaN where no view) and (T,) int64 view counts.
    """
    check_shape(samples, "T,N,3", "samples")
    check_shape(view_ids, f"{samples.shape[0]},{samples.shape[1]}", "view_ids")
    valid = view_ids >= 0
    sigma = torch.where(valid, exposures.to(torch.float32)[view_ids.clamp_min(0)], 0.0)
    linear = samples.clamp(0.0, 1.0) ** gamma * valid[..., None]
    radiance = linear.sum(dim=1) / sigma.sum(dim=1, keepdim=True)
    colors = radiance.clamp(0.0, 1.0) ** (1.0 / gamma)
    return colors.to(torch.float32), valid.sum(dim=1)


def texture_texels(
    points: torch.Tensor,
    normals: torch.Tensor,
    raycaster: MeshRaycaster,
    images: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    cfg: TextureBlendConfig,
    exposures: str | torch.Tensor = "estimated",
    show_progress: bool = False,
) -> TexelColors:
    """Colour texels from mapping images (Eq. 3-4), exposure compensated.

    Args:
        points: (T, 3) texel surface points ``A^-1(u, v)``.
        normals: (T, 3) unit outward facet normals.
        raycaster: the reconstructed mesh, for the occlusion test.
        images: (V, 3, H, W) float32 mapping images in [0, 1].
        T_wc: (V, 4, 4) their camera-to-world poses.
        camera: the unbatched camera of the images.
        cfg: blend settings.
        exposures: ``"estimated"`` (from the images), ``"none"`` (all 1), or a (V,) tensor of
            known exposures (normalised here to geometric mean 1).
        show_progress: progress bar over the views.

    Returns:
        The :class:`TexelColors`.

    Usage (needs a ray caster of the mesh and posed images; ``tests/test_mesh_texturing.py``
    runs it on small scenes)::

        colors = texture_texels(points, normals, caster, images, T_wc, cam, cfg)
    """
    check_shape(images, f"{T_wc.shape[0]},3,{camera.height},{camera.width}", "images")
    depths = view_depths(raycaster, T_wc, camera, cfg.views_per_batch)
    views = select_texel_views(points, normals, depths, T_wc, camera, cfg, show_progress)
    samples = sample_views(images, views)
    estimate = None
    if isinstance(exposures, torch.Tensor):
        check_shape(exposures, f"{len(T_wc)}", "exposures")
        if not bool((exposures > 0).all()):
            raise ValueError("known exposures must be > 0")
        sigma = exposures.to(torch.float64)
        sigma = sigma / sigma.log().mean().exp()
    elif exposures == "none":
        sigma = torch.ones(len(T_wc), dtype=torch.float64)
    elif exposures == "estimated":
        grey = samples.mean(dim=2)
        usable = (grey > cfg.dark_limit) & (samples.amax(dim=2) < cfg.bright_limit)
        intensity = torch.where(usable, grey.clamp_min(1e-6) ** cfg.gamma, 0.0)
        estimate = estimate_exposures(views.view_ids, intensity, len(T_wc), cfg.min_pair_samples)
        sigma = estimate.exposures
    else:
        raise ValueError(
            f"exposures must be 'estimated', 'none' or a tensor of exposures, got {exposures!r}"
        )
    colors, count = blend_texels(samples, views.view_ids, sigma, cfg.gamma)
    return TexelColors(colors=colors, view_count=count, exposures=sigma, estimate=estimate)
