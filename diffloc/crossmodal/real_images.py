"""Real posed images as an RGB-D database: depth rendered from the surfel map.

Seed 2 compares its rendered databases with a database of the mapping run's own images,
localised by the same Algorithm 1. Algorithm 1 lifts the reference keypoints with the
database's depth, so each real image needs depth: here it is the z-depth of the surfel map
(:class:`~diffloc.maps.surfel.SurfelMap`, built from the mapping run's lidar) rendered at the
image's pose with the exact ray-disk z-buffer of seed 1
(:class:`~diffloc.render.surfel_render.SurfelIndexRenderer`), 0 where no surfel is hit (a
hole). The simulator's depth images are never read. The result goes to
:func:`~diffloc.crossmodal.database.build_database` like a render.

Example:
    One image of a surfel 2 m ahead; the pixels whose rays hit its 0.75 m disk get depth 2, the
    others none:

    >>> import torch
    >>> from diffloc.geometry.camera import PinholeCamera
    >>> from diffloc.maps.surfel import SurfelMap
    >>> surfels = SurfelMap(
    ...     torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[0.0, 0.0, -1.0]]),
    ...     torch.tensor([0.75]))
    >>> camera = PinholeCamera(fx=4.0, fy=4.0, cx=2.0, cy=2.0, width=5, height=5)
    >>> views = surfel_depth_views(torch.full((1, 3, 5, 5), 0.5), torch.eye(4)[None], camera,
    ...                            surfels)
    >>> views.depth[0, 0]
    tensor([[0., 0., 0., 0., 0.],
            [0., 2., 2., 2., 0.],
            [0., 2., 2., 2., 0.],
            [0., 2., 2., 2., 0.],
            [0., 0., 0., 0., 0.]])
"""

from __future__ import annotations

import torch

from diffloc.checks import check_finite, check_positive_int, check_shape
from diffloc.crossmodal.synthesize import RGBD
from diffloc.geometry.camera import PinholeCamera
from diffloc.maps.surfel import SurfelMap
from diffloc.progress import progress
from diffloc.render.surfel_render import SurfelIndexRenderer

__all__ = ["surfel_depth_views"]


def surfel_depth_views(
    images: torch.Tensor,
    T_wc: torch.Tensor,
    camera: PinholeCamera,
    surfel_map: SurfelMap,
    batch_size: int = 8,
    show_progress: bool = False,
) -> RGBD:
    """Real images with z-depth rendered from ``surfel_map`` at their poses.

    Args:
        images: (M, 3, H, W) float32 colours in [0, 1], M >= 1.
        T_wc: (M, 4, 4) camera-to-world poses of the images, in the surfel map's frame.
        camera: the images' (unbatched, undistorted) camera, size W x H.
        surfel_map: the surfel map the depth is rendered from (at least one surfel).
        batch_size: images per render call.
        show_progress: progress bar over the batches (quiet when ``CI=true``).

    Returns:
        :class:`~diffloc.crossmodal.synthesize.RGBD`: the images and depth (M, 1, H, W)
        float32 in metres, 0 where no surfel is hit.

    Raises:
        ShapeError: ``images`` not (M, 3, H, W) of the camera's size, ``T_wc`` not (M, 4, 4).
        ValueError: no images, NaN/inf poses, an empty surfel map, a non-positive
            ``batch_size``, a distorted camera.
    """
    check_shape(images, "M,3,H,W", "images")
    m = images.shape[0]
    if m == 0:
        raise ValueError("no images: a real-image database needs at least one")
    check_shape(images, f"{m},3,{camera.height},{camera.width}", "images")
    check_shape(T_wc, f"{m},4,4", "T_wc")
    check_finite(T_wc, "T_wc")
    check_positive_int(batch_size, "batch_size")
    if len(surfel_map) == 0:
        raise ValueError("the surfel map is empty: it gives no depth")
    renderer = SurfelIndexRenderer(surfel_map.centers, surfel_map.normals, surfel_map.radii)
    camera32 = camera.to(torch.float32)
    batches = T_wc.to(torch.float32).split(batch_size)
    depth = torch.cat(
        [renderer.render(T, camera32).depth for T in progress(batches, "depth", show_progress)]
    )
    return RGBD(images.to(torch.float32), depth[:, None].to(torch.float32))
