"""Screen-space visibility of point splats (issue 18): a sparse wall in front of another hides
it, small holes close, silhouettes and large holes stay; the vectorised filter equals a
pixel-by-pixel reference; bad input is refused."""

from __future__ import annotations

import math

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.crossmodal.synthesize import PointCloudMap
from diffloc.geometry.camera import PinholeCamera
from diffloc.pipeline.crossmodal_config import PointMapConfig
from diffloc.render.point_render import render_points
from diffloc.render.point_sizes import PointSizes
from diffloc.render.screen_space import ScreenSpaceVisibility, hide_enclosed
from diffloc.render.zbuffer import _EMPTY_KEY, _pack_keys, _unpack_keys

CAMERA = PinholeCamera(fx=40.0, fy=40.0, cx=39.5, cy=29.5, width=80, height=60)
"""80 x 60 pixels, 40 px per unit of x / z: a point spacing ``s`` at depth ``z`` is
``40 s / z`` pixels apart."""
FILTER = ScreenSpaceVisibility(radius=6, min_sectors=7, depth_ratio=0.9)


def _wall(z: float, half_x: float, half_y: float, spacing: float) -> torch.Tensor:
    """(N, 3) grid of points on the plane at depth ``z`` within ``|x| <= half_x``,
    ``|y| <= half_y``, ``spacing`` apart."""
    xs = torch.arange(-half_x, half_x + 1e-6, spacing)
    ys = torch.arange(-half_y, half_y + 1e-6, spacing)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)
    return torch.cat([grid, torch.full((len(grid), 1), z)], 1)


def _render(points: torch.Tensor, visibility: ScreenSpaceVisibility | None, size: int = 2):
    colors = torch.full_like(points, 0.5)
    T_wc = torch.eye(4)[None]
    return render_points(points, colors, T_wc, CAMERA, PointSizes.fixed(size), visibility)


def _reference(keys: torch.Tensor, visibility: ScreenSpaceVisibility) -> torch.Tensor:
    """The filter pixel by pixel, as the module docstring states it: sectors of 45 deg
    centred on E, SE, S, ... (image rows grow downwards)."""
    out = keys.clone()
    batch, height, width = keys.shape
    _, depth = _unpack_keys(keys)
    for b in range(batch):
        for v in range(height):
            for u in range(width):
                own = math.inf if keys[b, v, u] == _EMPTY_KEY else float(depth[b, v, u])
                found = [_EMPTY_KEY] * 8
                r = visibility.radius
                for dv in range(-r, r + 1):
                    for du in range(-r, r + 1):
                        inside = 0 <= v + dv < height and 0 <= u + du < width
                        if not inside or not 0 < dv * dv + du * du <= r * r:
                            continue
                        angle = math.degrees(math.atan2(dv, du)) % 360.0  # 0: E, 90: S
                        sector = int(((angle + 22.5) % 360.0) // 45.0)
                        found[sector] = min(found[sector], int(keys[b, v + dv, u + du]))
                nearer = 0
                for key in found:
                    if key != _EMPTY_KEY:
                        _, d = _unpack_keys(torch.tensor(key))
                        nearer += float(d) < visibility.depth_ratio * own
                if nearer >= visibility.min_sectors:
                    out[b, v, u] = sorted(found)[3]
    return out


def test_a_sparse_wall_hides_the_wall_behind_it():
    """A wall at 2 m whose 2-px splats lie 4 px apart (gaps of 2 px) in front of a dense wall
    at 6 m: unfiltered, the far wall shows through the gaps; filtered, every pixel of the near
    wall's footprint has the near depth, and outside it the render is unchanged (silhouettes
    do not grow)."""
    near = _wall(2.0, 0.5, 0.4, 0.2)  # 40 * 0.2 / 2 = 4 px apart
    far = _wall(6.0, 6.0, 5.0, 0.1)  # 40 * 0.1 / 6 < 1 px apart: dense with 2-px splats
    points = torch.cat([near, far])
    plain, filtered = _render(points, None), _render(points, FILTER)
    footprint = torch.zeros(CAMERA.height, CAMERA.width, dtype=torch.bool)
    footprint[24:36, 32:48] = True  # the near wall's splats (rows 21-38, columns 29-50)
    # less its outermost gaps, which lie on its silhouette
    depth, plain_depth = filtered.depth[0, 0], plain.depth[0, 0]
    assert (plain_depth[footprint] == 6.0).sum() > 50  # the gaps show the far wall
    assert torch.all(depth[footprint] == 2.0)
    outside = torch.ones_like(footprint)
    outside[17:41, 28:52] = False  # the near wall's splats and a pixel around them
    assert torch.equal(depth[outside], plain_depth[outside])
    assert torch.all(depth[outside] == 6.0)
    ids = filtered.ids[0][footprint]
    assert torch.all(ids < len(near))  # the hidden pixels take near-wall points


def test_a_small_hole_closes_and_a_large_one_stays():
    """A dense wall at 2 m with a 10 x 10 cm hole (2 x 2 px) and a 1 x 1 m hole (20 px,
    beyond the 6-px radius in every direction from its centre): the small hole takes the
    wall's depth, the centre of the large one stays empty."""
    wall = _wall(2.0, 1.9, 1.4, 0.02)
    x, y = wall[:, 0], wall[:, 1]
    small = ((x - 0.5).abs() < 0.05) & ((y - 0.5).abs() < 0.05)
    large = ((x + 0.9).abs() < 0.5) & (y.abs() < 0.5)
    wall = wall[~small & ~large]
    plain, filtered = _render(wall, None, size=1), _render(wall, FILTER, size=1)
    hole = (slice(39, 41), slice(49, 51))  # x, y = 0.5 m -> (u, v) = (49.5, 39.5)
    assert torch.all(plain.depth[0, 0][hole] == 0.0)
    assert torch.all(filtered.depth[0, 0][hole] == 2.0)
    assert torch.all(filtered.mask[0, 0][hole])
    centre = filtered.depth[0, 0, 27:32, 19:24]  # x = -0.9 m, y = 0 m
    assert torch.all(centre == 0.0)


def test_a_silhouette_keeps_its_background():
    """The half image left of a vertical edge is near (1 m), the right half far (5 m): no
    pixel changes, since every far pixel sees the near half in at most 3 directions."""
    depth = torch.full((1, 9, 12), 5.0)
    depth[:, :, :6] = 1.0
    keys = _pack_keys(depth, torch.arange(9 * 12).view(1, 9, 12))
    assert torch.equal(hide_enclosed(keys, ScreenSpaceVisibility(radius=4)), keys)


def test_one_nearer_stray_point_does_not_win():
    """A far pixel inside a wall at 2 m with one stray point at 0.5 m on one of its rays takes
    a wall point (the lower median), not the stray one."""
    depth = torch.full((1, 7, 7), 2.0)
    depth[0, 3, 3] = 8.0
    depth[0, 3, 5] = 0.5
    keys = _pack_keys(depth, torch.arange(49).view(1, 7, 7))
    _, out = _unpack_keys(hide_enclosed(keys, ScreenSpaceVisibility(radius=3)))
    assert float(out[0, 3, 3]) == 2.0


@pytest.mark.parametrize("batch", [1, 2])
@pytest.mark.parametrize("visibility", [ScreenSpaceVisibility(2, 5, 0.9), FILTER])
def test_the_vectorised_filter_equals_the_pixel_reference(batch, visibility):
    generator = torch.Generator().manual_seed(batch)
    depth = torch.rand(batch, 9, 11, generator=generator) * 5.0 + 0.5
    ids = torch.randint(0, 1000, (batch, 9, 11), generator=generator)
    keys = _pack_keys(depth, ids)
    keys[torch.rand(batch, 9, 11, generator=generator) < 0.3] = _EMPTY_KEY
    assert torch.equal(hide_enclosed(keys, visibility), _reference(keys, visibility))


def test_the_cloud_map_renders_with_the_filter():
    """``PointCloudMap`` passes its filter to the renderer (the database renders)."""
    points = torch.cat([_wall(2.0, 0.5, 0.4, 0.2), _wall(6.0, 6.0, 5.0, 0.1)])
    colors = torch.full_like(points, 0.5)
    cloud = PointCloudMap(points, colors, PointSizes.fixed(2), FILTER)
    out = cloud.render(torch.eye(4)[None], CAMERA)
    assert torch.equal(out.depth, _render(points, FILTER).depth)


def test_bad_input_is_refused():
    keys = torch.zeros(4, 5, dtype=torch.int64)
    with pytest.raises(ShapeError):
        hide_enclosed(keys, FILTER)
    with pytest.raises(TypeError, match="int64"):
        hide_enclosed(keys[None].float(), FILTER)
    for bad in ({"radius": 0}, {"min_sectors": 4}, {"min_sectors": 9}, {"depth_ratio": 0.0}):
        with pytest.raises(ValueError):
            ScreenSpaceVisibility(**bad)
    with pytest.raises(ValueError, match="visibility_radius"):
        PointMapConfig(visibility_radius=-1)
    with pytest.raises(ValueError, match="min_sectors"):
        PointMapConfig(visibility_radius=8, visibility_sectors=4)
    assert PointMapConfig().visibility() is None
