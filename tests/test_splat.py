"""Hard splatting: surfel index maps and point splats (Eq. 2, multi-pass).

Fast paths are compared against the slow, obviously-correct references of
:mod:`diffloc.render._reference`: a dense float64 ray-disk intersection of every pixel with
every surfel, and a per-point loop that paints squares into a z-buffer.
"""

from __future__ import annotations

import math

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.database.neighbours import keypoint_disk_mask
from diffloc.geometry.camera import MIN_DEPTH, PinholeCamera
from diffloc.geometry.se3 import invert, se3_exp, transform_points
from diffloc.render._reference import reference_points, reference_surfels
from diffloc.render.pixel_mask import _summed_area
from diffloc.render.point_render import render_points, see_through_fraction
from diffloc.render.point_sizes import PointSizes
from diffloc.render.surfel_cull import _frustum_candidates, _SurfelCells
from diffloc.render.surfel_raster import _make_window_basis
from diffloc.render.surfel_render import SurfelIndexRenderer, render_surfel_index
from diffloc.render.view import _rigid_columns, _views
from diffloc.render.zbuffer import _MAX_SURFELS, _tie_breakers
from diffloc.testing import assert_close


def look_at(eye, target, down=(0.0, 1.0, 0.0)):
    """(4, 4) float64 OpenCV camera-to-world pose at ``eye`` looking at ``target``."""
    eye, target = torch.tensor(eye, dtype=torch.float64), torch.tensor(target, dtype=torch.float64)
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(torch.tensor(down, dtype=torch.float64), z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


@pytest.fixture
def camera():
    return PinholeCamera.from_fov(64, 48, math.radians(60.0))


def identity(batch=1):
    return torch.eye(4).expand(batch, 4, 4).clone()


# ---------------------------------------------------------------------------- surfels


def test_head_on_disk_exact_depth_and_footprint(camera):
    centers = torch.tensor([[0.031, -0.017, 2.0]])
    normals = torch.tensor([[0.0, 0.0, -1.0]])
    radii = torch.tensor([0.21])
    out = render_surfel_index(centers, normals, radii, identity(), camera)
    ref_ids, ref_depth, margin = reference_surfels(centers, normals, radii, identity(), camera)
    assert margin.abs().min() > 1e-3  # no pixel centre close to the rim
    assert torch.equal(out.ids, ref_ids)
    assert int(out.mask.sum()) > 100
    assert torch.equal(out.depth[out.mask], torch.full_like(out.depth[out.mask], 2.0))
    assert torch.equal(out.depth[~out.mask], torch.zeros_like(out.depth[~out.mask]))
    assert out.ids.dtype == torch.int64 and out.depth.dtype == torch.float32
    assert out.normals.shape == (1, 3, 48, 64)
    assert torch.equal(out.normals[0, :, 24, 32], torch.tensor([0.0, 0.0, -1.0]))
    assert torch.equal(out.normals[0, :, 0, 0], torch.zeros(3))


def test_fronto_parallel_plane_constant_depth(camera):
    grid = torch.stack(torch.meshgrid(torch.arange(-20, 21), torch.arange(-15, 16), indexing="ij"))
    xy = grid.reshape(2, -1).T.float() * 0.1
    centers = torch.cat((xy, torch.full((len(xy), 1), 3.0)), dim=-1)
    normals = torch.tensor([[0.0, 0.0, -1.0]]).expand_as(centers)
    radii = torch.full((len(xy),), 0.08)  # overlapping disks, no gaps
    out = render_surfel_index(centers, normals, radii, identity(), camera)
    assert bool(out.mask.all())
    assert torch.equal(out.depth, torch.full_like(out.depth, 3.0))


def test_tilted_disk_ray_plane_depths(camera):
    tilt = math.radians(50.0)
    centers = torch.tensor([[-0.07, 0.05, 1.5]])
    normals = torch.tensor([[math.sin(tilt), 0.2, -math.cos(tilt)]])
    radii = torch.tensor([0.3])
    out = render_surfel_index(centers, normals, radii, identity(), camera)
    ref_ids, ref_depth, margin = reference_surfels(centers, normals, radii, identity(), camera)
    safe = margin.abs() > 1e-4
    assert torch.equal(out.ids[safe], ref_ids[safe])
    assert int(out.mask.sum()) > 100
    assert_close(out.depth, ref_depth.float())
    assert out.depth[out.mask].std() > 0.05  # depth really varies over the tilted disk


def test_random_surfels_match_dense_reference_batched():
    g = torch.Generator().manual_seed(3)
    n = 60
    centers = torch.rand(n, 3, generator=g) * torch.tensor([2.0, 2.0, 2.0]) - 1.0
    normals = torch.randn(n, 3, generator=g)
    radii = 0.05 + 0.25 * torch.rand(n, generator=g)
    T_wc = torch.stack(
        (look_at((0.3, -0.2, -3.0), (0.0, 0.0, 0.0)), look_at((2.5, 0.5, -1.5), (0.0, 0.1, 0.0)))
    ).float()
    camera = PinholeCamera(
        fx=torch.tensor([40.0, 55.0]),
        fy=torch.tensor([42.0, 50.0]),
        cx=torch.tensor([23.5, 20.0]),
        cy=torch.tensor([17.5, 19.0]),
        width=48,
        height=36,
    )
    out = render_surfel_index(centers, normals, radii, T_wc, camera)
    ref_ids, ref_depth, margin = reference_surfels(centers, normals, radii, T_wc, camera)
    safe = margin.abs() > 1e-4
    assert safe.float().mean() > 0.97
    assert torch.equal(out.ids[safe], ref_ids[safe])
    assert_close(out.depth[safe], ref_depth[safe].float())
    assert 0.2 < float(out.mask.float().mean()) < 0.95
    for b in range(2):  # a batch renders like its cameras one at a time
        single = render_surfel_index(centers, normals, radii, T_wc[b : b + 1], camera[b])
        assert torch.equal(single.ids[0], out.ids[b])


def test_disk_crossing_the_camera_plane(camera):
    # A floor-like disk 10 cm below the camera, reaching behind it, over a far wall.
    centers = torch.tensor([[0.0, 0.1, 0.05], [0.0, 0.0, 2.0]])
    normals = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    radii = torch.tensor([0.4, 3.0])
    out = render_surfel_index(centers, normals, radii, identity(), camera)
    ref_ids, ref_depth, margin = reference_surfels(centers, normals, radii, identity(), camera)
    safe = margin.abs() > 1e-4
    assert torch.equal(out.ids[safe], ref_ids[safe])
    assert 0.1 < float((out.ids == 0).float().mean()) < 0.9
    assert_close(out.depth[safe], ref_depth[safe].float())


def test_nearest_surfel_wins_in_any_order(camera):
    centers = torch.tensor([[0.0, 0.0, 3.0], [0.05, 0.0, 2.0], [0.0, 0.04, 2.5]])
    normals = torch.tensor([[0.0, 0.0, -1.0]]).expand(3, 3)
    radii = torch.tensor([0.5, 0.2, 0.3])
    out = render_surfel_index(centers, normals, radii, identity(), camera)
    assert int(out.ids[0, 24, 32]) == 1
    for perm in ([2, 0, 1], [1, 2, 0], [2, 1, 0]):
        perm = torch.tensor(perm)
        other = render_surfel_index(centers[perm], normals[perm], radii[perm], identity(), camera)
        remapped = torch.where(other.ids >= 0, perm[other.ids.clamp_min(0)], -1)
        assert torch.equal(remapped, out.ids)
        assert torch.equal(other.depth, out.depth)


def test_backface_culling_and_camera_frame_normals(camera):
    centers = torch.tensor([[0.0, 0.0, 2.0]])
    away = torch.tensor([[0.0, 0.0, 1.0]])
    radii = torch.tensor([0.3])
    assert int(render_surfel_index(centers, away, radii, identity(), camera).mask.sum()) > 0
    culled = render_surfel_index(centers, away, radii, identity(), camera, cull_backfaces=True)
    assert int(culled.mask.sum()) == 0
    # Rotate the camera about its z axis: the world normal (1, 0, 0) appears rotated.
    T_wc = se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, math.pi / 2]))[None]
    tilted = torch.tensor([[0.6, 0.0, -0.8]])
    out = render_surfel_index(transform_points(T_wc[0], centers), tilted, radii, T_wc, camera)
    assert_close(out.normals[0, :, 24, 32], (tilted @ T_wc[0, :3, :3])[0])


def test_surfel_bad_inputs(camera):
    c, n, r = torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[0.0, 0.0, -1.0]]), torch.tensor([0.1])
    with pytest.raises(ValueError, match="radii"):
        render_surfel_index(c, n, torch.tensor([0.0]), identity(), camera)
    with pytest.raises(ValueError, match="normals"):
        render_surfel_index(c, torch.zeros(1, 3), r, identity(), camera)
    with pytest.raises(ShapeError):
        render_surfel_index(c, n, r, torch.zeros(0, 4, 4), camera)
    with pytest.raises(ShapeError):
        render_surfel_index(c, n, r, torch.eye(4), camera)
    with pytest.raises(ShapeError):
        render_surfel_index(c[:, :2], n, r, identity(), camera)
    with pytest.raises(ShapeError):
        render_surfel_index(c, n, torch.tensor([0.1, 0.2]), identity(), camera)
    with pytest.raises(ShapeError):
        batch3 = PinholeCamera.from_fov(64, 48, torch.full((3,), 1.0))
        render_surfel_index(c, n, r, identity(2), batch3)
    with pytest.raises(ValueError, match="T_wc"):
        render_surfel_index(c, n, r, torch.full((1, 4, 4), math.nan), camera)
    distorted = PinholeCamera.from_fov(64, 48, 1.0, distortion=torch.tensor([0.1, 0, 0, 0]))
    with pytest.raises(ValueError, match="pinhole"):
        render_surfel_index(c, n, r, identity(), distorted)


def test_surfel_missing_values_and_empty_map_are_culled(camera):
    c = torch.tensor([[0.0, 0.0, 2.0], [math.nan, 0.0, 1.0], [0.0, math.inf, 1.0]])
    n = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, math.nan, -1.0]])
    r = torch.tensor([0.1, 0.5, math.inf])
    out = render_surfel_index(c, n, r, identity(), camera)
    clean = render_surfel_index(c[:1], n[:1], r[:1], identity(), camera)
    assert torch.equal(out.ids, clean.ids) and torch.equal(out.depth, clean.depth)
    behind = render_surfel_index(-c[:1], n[:1], r[:1], identity(), camera)
    assert int(behind.mask.sum()) == 0
    empty = render_surfel_index(
        torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0), identity(2), camera
    )
    assert torch.equal(empty.ids, torch.full((2, 48, 64), -1))
    assert torch.equal(empty.depth, torch.zeros(2, 48, 64))
    assert torch.equal(empty.normals, torch.zeros(2, 3, 48, 64))


def random_surfel_scene(generator, count):
    """Disks of very different sizes (1-pixel to image-filling windows) around a unit box.

    Some reach past the image border, some straddle the camera plane of the poses below.
    """
    centers = torch.rand(count, 3, generator=generator) * torch.tensor([3.0, 2.4, 3.0]) - 1.5
    normals = torch.randn(count, 3, generator=generator)
    radii = torch.exp(
        torch.empty(count).uniform_(math.log(0.004), math.log(0.6), generator=generator)
    )
    return centers, normals, radii


@pytest.mark.parametrize("cull_backfaces", [False, True])
def test_many_mixed_size_surfels_match_dense_reference(cull_backfaces):
    g = torch.Generator().manual_seed(11)
    centers, normals, radii = random_surfel_scene(g, 400)
    T_wc = torch.stack(
        (
            look_at((0.2, -0.1, -2.6), (0.0, 0.0, 0.0)),
            look_at((1.2, 0.4, -1.2), (0.0, 0.0, 0.3)),  # inside the cloud: near-plane disks
            look_at((-0.3, 0.2, -0.4), (0.1, 0.0, 1.0)),
        )
    ).float()
    camera = PinholeCamera.from_fov(72, 56, math.radians(75.0))
    out = render_surfel_index(centers, normals, radii, T_wc, camera, cull_backfaces=cull_backfaces)
    if cull_backfaces:  # the reference draws two-sided disks: give it the front faces only
        per_pose = []
        for b in range(len(T_wc)):
            T_cw = invert(T_wc[b].double())
            facing = normals.double() @ T_cw[:3, :3].T * transform_points(T_cw, centers.double())
            front = torch.nonzero(facing.sum(-1) < 0)[:, 0]
            ids, depth, margin = reference_surfels(
                centers[front], normals[front], radii[front], T_wc[b : b + 1], camera
            )
            per_pose.append((torch.where(ids >= 0, front[ids.clamp_min(0)], -1), depth, margin))
        ref_ids, ref_depth, margin = (torch.cat(x) for x in zip(*per_pose, strict=True))
    else:
        ref_ids, ref_depth, margin = reference_surfels(centers, normals, radii, T_wc, camera)
    safe = margin.abs() > 1e-4
    assert safe.float().mean() > 0.97
    assert 0.3 < float(out.mask.float().mean()) < 0.99
    assert torch.equal(out.ids[safe], ref_ids[safe])
    assert_close(out.depth[safe], ref_depth[safe].float())
    # Normals: the winning surfel's unit normal, rotated into each camera.
    n_w = normals / normals.norm(dim=-1, keepdim=True)
    expected = torch.einsum("bji,bhwj->bihw", T_wc[:, :3, :3], n_w[out.ids.clamp_min(0)])
    expected = torch.where(out.mask[:, None], expected, 0.0)
    assert_close(out.normals, expected, atol=1e-5, rtol=1e-5)


def test_equal_depths_go_to_the_lowest_index_in_any_order(camera):
    # Surfels 1 and 3 are the same disk; it lies in front of the others.
    centers = torch.tensor([[0.0, 0.0, 3.0], [0.02, 0.01, 2.0], [0.1, 0.0, 2.5], [0.02, 0.01, 2.0]])
    normals = torch.tensor([[0.0, 0.0, -1.0], [0.3, 0.1, -1.0], [0.0, 0.0, -1.0], [0.3, 0.1, -1.0]])
    radii = torch.tensor([0.9, 0.25, 0.4, 0.25])
    out = render_surfel_index(centers, normals, radii, identity(), camera)
    assert int((out.ids == 1).sum()) > 50
    assert int((out.ids == 3).sum()) == 0
    for perm in ([3, 0, 2, 1], [2, 3, 1, 0], [1, 3, 0, 2]):
        perm = torch.tensor(perm)
        other = render_surfel_index(centers[perm], normals[perm], radii[perm], identity(), camera)
        lowest = torch.nonzero((perm == 1) | (perm == 3))[0, 0]  # new index of the first twin
        assert torch.equal(other.ids == lowest, out.ids == 1)
        assert torch.equal(other.depth, out.depth)


def test_surfels_straddling_the_frustum_planes(camera):
    # Centres just outside each image edge and just behind the camera, radii reaching in.
    z = 2.0
    half_w = (camera.width / 2) / float(camera.fx) * z
    half_h = (camera.height / 2) / float(camera.fy) * z
    centers = torch.tensor(
        [
            [-half_w - 0.05, 0.0, z],
            [half_w + 0.05, 0.1, z],
            [0.1, -half_h - 0.05, z],
            [-0.2, half_h + 0.05, z],
            [0.0, 0.3, -0.05],  # behind the camera, reaching in front: culled (centre rule)
            [3.0, 0.0, z],  # far outside: culled
        ]
    )
    normals = torch.tensor([[0.0, 0.0, -1.0]]).expand(6, 3)
    radii = torch.tensor([0.2, 0.2, 0.2, 0.2, 0.5, 0.2])
    out = render_surfel_index(centers, normals, radii, identity(), camera)
    ref_ids, ref_depth, margin = reference_surfels(centers, normals, radii, identity(), camera)
    safe = margin.abs() > 1e-4
    assert torch.equal(out.ids[safe], ref_ids[safe])
    assert set(out.ids.unique().tolist()) == {-1, 0, 1, 2, 3}


def test_bad_surfel_anywhere_in_the_map_raises(camera):
    g = torch.Generator().manual_seed(2)
    centers = torch.randn(1000, 3, generator=g)
    centers[:, 2] -= 10.0  # all behind the camera: nothing would be drawn
    normals = torch.randn(1000, 3, generator=g)
    radii = torch.full((1000,), 0.1)
    render_surfel_index(centers, normals, radii, identity(), camera)
    with pytest.raises(ValueError, match="normals"):
        render_surfel_index(
            centers, normals.index_fill(0, torch.tensor([500]), 0.0), radii, identity(), camera
        )
    with pytest.raises(ValueError, match="radii"):
        render_surfel_index(
            centers, normals, radii.index_fill(0, torch.tensor([700]), 0.0), identity(), camera
        )


def _assert_same_render(a, b):
    assert torch.equal(a.ids, b.ids)
    assert torch.equal(a.depth.view(torch.int32), b.depth.view(torch.int32))
    assert torch.equal(a.normals.view(torch.int32), b.normals.view(torch.int32))


@pytest.mark.parametrize("cell_size_m", [0.05, 0.3, 100.0])
def test_renderer_with_cells_matches_the_plain_render(cell_size_m):
    g = torch.Generator().manual_seed(5)
    centers, normals, radii = random_surfel_scene(g, 3000)
    centers[7, 1] = math.nan  # a missing entry
    # A disk facing the first camera close in front of it, and its duplicate (a tie).
    centers[3], normals[3], radii[3] = (
        torch.tensor([0.2, -0.1, -2.0]),
        torch.tensor([0, 0, -1]),
        0.05,
    )
    centers[11], normals[11], radii[11] = centers[3], normals[3], radii[3]
    T_wc = torch.stack(
        (
            look_at((0.2, -0.1, -2.6), (0.0, 0.0, 0.0)),
            look_at((1.2, 0.4, -1.2), (0.0, 0.0, 0.3)),
            look_at((-0.3, 0.2, -0.4), (0.1, 0.0, 1.0)),
            look_at((0.0, 0.0, 4.0), (0.0, 0.0, 10.0)),  # looking away: nothing in view
        )
    ).float()
    camera = PinholeCamera.from_fov(72, 56, math.radians(75.0))
    renderer = SurfelIndexRenderer(centers, normals, radii, cell_size_m=cell_size_m)
    assert len(renderer) == 3000
    for cull_backfaces in (False, True):
        plain = render_surfel_index(
            centers, normals, radii, T_wc, camera, cull_backfaces=cull_backfaces
        )
        _assert_same_render(renderer.render(T_wc, camera, cull_backfaces=cull_backfaces), plain)
    assert int((plain.ids == 3).sum()) > 0 and int((plain.ids == 11).sum()) == 0
    assert int((plain.ids == 7).sum()) == 0
    assert not bool(plain.mask[3].any())


def _masked_scene():
    """Mixed-size surfels (occlusions, near-plane disks), a duplicated disk (a tie) and four
    poses (one looking away), with two exactly coplanar overlapping disks."""
    g = torch.Generator().manual_seed(13)
    centers, normals, radii = random_surfel_scene(g, 2000)
    centers[3], normals[3], radii[3] = (
        torch.tensor([0.2, -0.1, -2.0]),
        torch.tensor([0, 0, -1]),
        0.05,
    )
    centers[11], normals[11], radii[11] = centers[3], normals[3], radii[3]
    centers[12], normals[12], radii[12] = torch.tensor([0.23, -0.1, -2.0]), normals[3], 0.05
    T_wc = torch.stack(
        (
            look_at((0.2, -0.1, -2.6), (0.0, 0.0, 0.0)),
            look_at((1.2, 0.4, -1.2), (0.0, 0.0, 0.3)),
            look_at((-0.3, 0.2, -0.4), (0.1, 0.0, 1.0)),
            look_at((0.0, 0.0, 4.0), (0.0, 0.0, 10.0)),
        )
    ).float()
    return centers, normals, radii, T_wc, PinholeCamera.from_fov(72, 56, math.radians(75.0))


@pytest.mark.parametrize("cell_size_m", [None, 0.3])
def test_masked_render_is_the_full_render_at_the_masked_pixels(cell_size_m):
    centers, normals, radii, T_wc, camera = _masked_scene()
    renderer = SurfelIndexRenderer(centers, normals, radii, cell_size_m=cell_size_m)
    g = torch.Generator().manual_seed(3)
    masks = []
    for count in (40, 3, 1, 0):  # keypoint disks, a few, one, none
        keypoints = torch.rand(count, 2, generator=g) * torch.tensor([72.0, 56.0]) - 0.5
        radius = torch.rand(count, generator=g) * 6.0
        masks.append(keypoint_disk_mask(keypoints, radius, 56, 72))
    pixels = torch.stack(masks)
    for cull_backfaces in (False, True):
        full = renderer.render(T_wc, camera, cull_backfaces=cull_backfaces)
        part = renderer.render(T_wc, camera, cull_backfaces=cull_backfaces, pixels=pixels)
        assert torch.equal(part.ids[pixels], full.ids[pixels])
        assert torch.equal(
            part.depth[pixels].view(torch.int32), full.depth[pixels].view(torch.int32)
        )
        normals_at = lambda r: r.normals.permute(1, 0, 2, 3)[:, pixels].view(torch.int32)  # noqa: E731
        assert torch.equal(normals_at(part), normals_at(full))
        assert bool((part.ids[~pixels] == -1).all() and (part.depth[~pixels] == 0).all())
        assert not bool(part.normals.permute(1, 0, 2, 3)[:, ~pixels].any())
        everything = renderer.render(
            T_wc, camera, cull_backfaces=cull_backfaces, pixels=torch.ones_like(pixels)
        )
        _assert_same_render(everything, full)
    assert int((full.ids[0][pixels[0]] == 3).sum()) > 0  # the tie is in the mask
    assert int((full.ids == 11).sum()) == 0
    assert int(pixels[0].sum()) > 500 and not bool(part.mask[3].any())


def test_masked_render_checks_the_mask(camera):
    renderer = SurfelIndexRenderer(torch.zeros(1, 3), torch.ones(1, 3), torch.ones(1))
    with pytest.raises(ShapeError):
        renderer.render(
            identity(), camera, pixels=torch.ones(camera.height, camera.width, dtype=torch.bool)
        )
    with pytest.raises(ValueError, match="bool"):
        renderer.render(identity(), camera, pixels=torch.ones(1, camera.height, camera.width))


@pytest.mark.parametrize("cell_size_m", [None, 0.3])
def test_masked_candidates_keep_every_surfel_that_covers_a_masked_pixel(cell_size_m):
    """Masked renders drop a cell or surfel only if no ray through a pixel to render hits a
    disk in it (dense float64 check), and drop most of those far from the mask."""
    centers, normals, radii, T_wc, camera = _masked_scene()
    renderer = SurfelIndexRenderer(centers, normals, radii, cell_size_m=cell_size_m)
    g = torch.Generator().manual_seed(9)
    keypoints = torch.rand(12, 2, generator=g) * torch.tensor([72.0, 56.0])
    pixels = keypoint_disk_mask(keypoints, torch.full((12,), 3.0), 56, 72)
    uv = torch.nonzero(pixels).flip(1).double()  # (P, 2) masked pixel centres (u, v)
    dropped = 0
    for b, view in enumerate(_views(T_wc[:3], camera.to(torch.float32))):
        surfels = renderer._candidates(view, 56, 72, None)
        kept = renderer._candidates(view, 56, 72, _summed_area(pixels)).ids
        c, n = surfels.centers.double(), surfels.normals.double()  # (3, M) camera frame
        rays = torch.stack(
            ((uv[:, 0] - view.cx) / view.fx, (uv[:, 1] - view.cy) / view.fy, torch.ones(len(uv)))
        )  # (3, P)
        t = (n * c).sum(0)[:, None] / (n.T @ rays)  # (M, P) hit depths
        hit = t[:, None] * rays[None] - c.T[:, :, None]  # (M, 3, P)
        covers = (hit.norm(dim=1) <= surfels.radii.double()[:, None]) & (t > MIN_DEPTH)
        covers &= (c[2] > MIN_DEPTH)[:, None]
        assert bool(torch.isin(surfels.ids[covers.any(1)], kept).all()), f"view {b}"
        dropped += len(surfels.ids) - len(kept)
    assert dropped > 1000


def test_surfels_that_win_nowhere_change_no_pixel(camera):
    """A surfel is drawn bit for bit alike whatever else is drawn: many more disks hidden
    behind a wall (other window buckets, other merges) leave the render unchanged."""
    g = torch.Generator().manual_seed(21)
    centers, normals, radii = random_surfel_scene(g, 1500)
    centers[:, 2] = centers[:, 2] * 0.5 + 2.2  # in front of the wall, 1.45 .. 2.95 m
    radii *= 0.3
    wall = (torch.tensor([[0.0, 0.0, 3.5]]), torch.tensor([[0.0, 0.0, -1.0]]), torch.tensor([50.0]))
    hidden = random_surfel_scene(g, 3000)
    hidden[0][:, 2] += 6.0  # behind the wall
    scene = [torch.cat(parts) for parts in zip((centers, normals, radii), wall, strict=True)]
    more = [torch.cat(parts) for parts in zip(scene, hidden, strict=True)]
    T_wc = torch.stack((identity()[0], look_at((0.3, -0.2, 0.2), (0.0, 0.1, 3.0)).float()))
    for cell_size_m in (None, 0.3):
        one = SurfelIndexRenderer(*scene, cell_size_m=cell_size_m).render(T_wc, camera)
        two = SurfelIndexRenderer(*more, cell_size_m=cell_size_m).render(T_wc, camera)
        _assert_same_render(one, two)
        assert bool((one.ids == 1500).any()) and int((one.ids < 1500).sum()) > 1000
    assert float(render_surfel_index(*hidden, T_wc, camera).mask.float().mean()) > 0.4


def test_camera_frame_transform_rounds_alike_for_any_number_of_surfels():
    """A (3, 3) x (3, M) matrix product rounds differently for small and large M; the
    renderer's transform must not, or a surfel would differ between renders of subsets."""
    g = torch.Generator().manual_seed(6)
    R = se3_exp(torch.randn(6, generator=g, dtype=torch.float64))[:3, :3].float()
    t = torch.randn(3, 1, generator=g)
    x = torch.randn(3, 100_000, generator=g) * 5.0
    everything = _rigid_columns(R, x, t)
    assert_close(everything, torch.addmm(t, R, x), atol=1e-5, rtol=1e-6)
    for m in (1, 7, 100, 5000, 40_000):
        assert torch.equal(_rigid_columns(R, x[:, :m], t), everything[:, :m])
        assert torch.equal(_rigid_columns(R, x[:, -m:]), _rigid_columns(R, x)[:, -m:])


def test_cells_cull_the_same_surfels_as_the_plain_frustum_test():
    g = torch.Generator().manual_seed(8)
    centers = torch.rand(20000, 3, generator=g) * 10.0 - 5.0
    normals = torch.randn(20000, 3, generator=g)
    radii = torch.rand(20000, generator=g) * 0.2 + 0.01
    cells = _SurfelCells.build(centers, normals, radii, 0.5)
    assert torch.equal(cells.ids.sort().values, torch.arange(20000))
    camera = PinholeCamera.from_fov(80, 60, math.radians(70.0))
    T_wc = torch.stack([look_at((0.0, 0.0, -1.0), (1.0, 0.5, 3.0)), look_at((4, 4, 4), (0, 0, 0))])
    for view in _views(T_wc.float(), camera.to(torch.float32)):
        expected = _frustum_candidates(centers, radii, view, 60, 80)
        found = cells.ids.index_select(0, cells.cull(view, 60, 80))
        assert 0 < len(expected) < 20000
        assert torch.equal(found.sort().values, expected)


def test_renderer_validates_once_and_checks_its_inputs(camera):
    centers, normals = torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    with pytest.raises(ValueError, match="radii"):
        SurfelIndexRenderer(centers, normals, torch.tensor([0.0]))
    with pytest.raises(ValueError, match="cell_size_m"):
        SurfelIndexRenderer(centers, normals, torch.tensor([0.1]), cell_size_m=0.0)
    empty = SurfelIndexRenderer(torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0))
    out = empty.render(identity(2), camera)
    assert out.ids.shape == (2, camera.height, camera.width) and not bool(out.mask.any())
    with pytest.raises(ShapeError):
        empty.render(torch.eye(4), camera)


def test_tie_breakers_survive_the_window_product():
    """The z-buffer tie-breaker is a float32 constant term of a matrix product (see
    ``_rasterise_surfels``): it must come out bit for bit at every pixel of the largest window."""
    local = torch.tensor([0, 1, 2, 1000, 2**24 + 1, _MAX_SURFELS - 1])
    ties = _tie_breakers(local)
    assert bool((ties >= torch.finfo(torch.float32).tiny).all() and torch.isfinite(ties).all())
    assert bool((ties.view(torch.int32).diff() < 0).all())  # lower surfel, larger key
    basis, _ = _make_window_basis(640, 480, 640, torch.device("cpu"))
    zero = torch.zeros_like(ties)
    values = basis[:, 3:] @ torch.stack((zero, zero, ties))  # (i, j, 1) monomials
    assert torch.equal(values.view(torch.int32), ties.view(torch.int32).expand_as(values))


# ---------------------------------------------------------------------------- points


def test_point_square_splat_pixels(camera):
    out = render_points(
        torch.tensor([[0.0, 0.0, 2.0]]),
        torch.tensor([[0.2, 0.4, 0.6]]),
        identity(),
        camera,
        PointSizes.fixed(3),
    )
    # cx = 31.5, cy = 23.5: a 3x3 square centred there covers u in 30..32 and v in 22..24.
    expected = torch.zeros(48, 64, dtype=torch.bool)
    expected[22:25, 30:33] = True
    assert torch.equal(out.mask[0, 0], expected)
    assert torch.equal(out.depth[0, 0][expected], torch.full((9,), 2.0))
    assert_close(out.rgb[0, :, 23, 31], torch.tensor([0.2, 0.4, 0.6]))
    assert torch.equal(out.rgb[0, :, 0, 0], torch.zeros(3))
    assert out.rgb.shape == (1, 3, 48, 64) and out.depth.shape == (1, 1, 48, 64)
    assert out.ids.shape == (1, 48, 64) and out.mask.shape == (1, 1, 48, 64)


def test_point_zbuffer_nearer_wins_regardless_of_order(camera):
    points = torch.tensor([[0.0, 0.0, 4.0], [0.01, 0.0, 2.0]])
    colors = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    for order in ([0, 1], [1, 0]):
        out = render_points(points[order], colors[order], identity(), camera, PointSizes.fixed(5))
        assert float(out.depth[0, 0, 23, 31]) == 2.0
        assert_close(out.rgb[0, :, 23, 31], torch.tensor([0.0, 1.0, 0.0]))


def test_inverse_depth_sizes_near_points_bigger(camera):
    sizes = PointSizes.inverse_depth(1.0, 6.0)
    near = render_points(
        torch.tensor([[0.0, 0.0, 0.8]]), torch.ones(1, 3), identity(), camera, sizes
    )
    mid = render_points(
        torch.tensor([[0.0, 0.0, 2.0]]), torch.ones(1, 3), identity(), camera, sizes
    )
    far = render_points(
        torch.tensor([[0.0, 0.0, 9.0]]), torch.ones(1, 3), identity(), camera, sizes
    )
    assert int(near.mask.sum()) == 36  # rho = clamp(6 / 0.8) = 6
    assert int(mid.mask.sum()) == 9  # rho = 3
    assert int(far.mask.sum()) == 1  # rho = clamp(0.67, 1, 6) = 1


@pytest.mark.parametrize(
    "sizes",
    [
        PointSizes.fixed(1),
        PointSizes.fixed(4),
        PointSizes.inverse_depth(1.0, 7.0),
        PointSizes.inverse_depth(0.3, 2.6),
        PointSizes.multi_pass(1.0, 8.0, (2, 5, 8)),
    ],
)
def test_points_match_slow_reference(sizes):
    g = torch.Generator().manual_seed(7)
    points = torch.rand(150, 3, generator=g) * torch.tensor([3.0, 2.0, 6.0]) - torch.tensor(
        [1.5, 1.0, 1.0]
    )
    colors = torch.rand(150, 3, generator=g)
    T_wc = torch.stack((torch.eye(4, dtype=torch.float64), look_at((1.0, 0.0, -0.5), (0, 0, 3.0))))
    camera = PinholeCamera(
        fx=torch.tensor([30.0, 36.0]),
        fy=30.0,
        cx=torch.tensor([19.5, 17.0]),
        cy=14.5,
        width=40,
        height=30,
    )
    out = render_points(points, colors, T_wc.float(), camera, sizes)
    ref_ids, ref_depth = reference_points(points, colors, T_wc.float(), camera, sizes)
    assert torch.equal(out.ids, ref_ids)
    assert_close(out.depth[:, 0], ref_depth.float())
    assert_close(
        out.rgb, torch.where(out.mask, colors[ref_ids.clamp_min(0)].permute(0, 3, 1, 2), 0.0)
    )


def test_points_with_distortion_match_reference():
    distortion = torch.tensor([-0.2, 0.05, 0.001, -0.002])
    camera = PinholeCamera.from_fov(40, 30, 1.2, distortion=distortion)
    points = torch.rand(80, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1
    points[:, 2] += 3.0
    sizes = PointSizes.inverse_depth(1.0, 6.0)
    out = render_points(points, torch.rand(80, 3), identity(), camera, sizes)
    ref_ids, _ = reference_points(points, None, identity(), camera, sizes)
    assert torch.equal(out.ids, ref_ids)


def test_multi_pass_with_one_level_equals_fixed_size(camera):
    points = torch.rand(300, 3, generator=torch.Generator().manual_seed(2)) * 2 - 1
    points[:, 2] += 2.5
    colors = torch.rand(300, 3)
    fixed = render_points(points, colors, identity(), camera, PointSizes(3.0, 3.0))
    single = render_points(points, colors, identity(), camera, PointSizes.multi_pass(1, 9, (3,)))
    assert torch.equal(fixed.ids, single.ids)
    assert torch.equal(fixed.depth, single.depth)


def test_multi_pass_merges_passes_by_nearest_depth(camera):
    points = torch.rand(400, 3, generator=torch.Generator().manual_seed(4)) * 2 - 1
    points[:, 2] = 0.5 + 4.0 * points[:, 2].abs()
    colors = torch.rand(400, 3)
    sizes = PointSizes.multi_pass(1.0, 6.0, (1, 3, 6))
    merged = render_points(points, colors, identity(), camera, sizes)
    # Render each pass alone with its fixed size, then keep the nearest depth per pixel.
    level = sizes.level_index(points[:, 2])
    depth = torch.full((1, 48, 64), math.inf)
    ids = torch.full((1, 48, 64), -1)
    for index, size in enumerate(sizes.pass_sizes()):
        members = (level == index).nonzero()[:, 0]
        one = render_points(
            points[members], colors[members], identity(), camera, PointSizes.fixed(size)
        )
        d = torch.where(one.mask[:, 0], one.depth[:, 0], math.inf)
        better = d < depth
        depth = torch.where(better, d, depth)
        ids = torch.where(better, members[one.ids.clamp_min(0)], ids)
    assert torch.equal(merged.ids, ids)
    assert len(set(sizes.level_index(points[:, 2]).tolist())) == 3


def see_through_scene():
    """A wall of points 1 m away (2 cm spacing) and a background wall at 6 m."""
    grid = torch.stack(torch.meshgrid(torch.arange(-40, 41), torch.arange(-30, 31), indexing="ij"))
    wall = grid.reshape(2, -1).T.float() * 0.02
    wall = torch.cat((wall, torch.ones(len(wall), 1)), dim=-1)
    background = torch.rand(20000, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    background = background * torch.tensor([6.0, 5.0, 0.0]) + torch.tensor([0.0, 0.0, 6.0])
    return torch.cat((wall, background))


def test_inverse_depth_sizes_reduce_see_through():
    camera = PinholeCamera.from_fov(160, 120, math.radians(60.0))
    points = see_through_scene()
    colors = torch.rand(len(points), 3)
    fixed = render_points(points, colors, identity(), camera, PointSizes.fixed(1))
    adaptive = render_points(points, colors, identity(), camera, PointSizes.inverse_depth(1.0, 4.0))
    # The wall spans |x| <= 0.8 m at 1 m, i.e. the central pixels of this 60 deg view.
    region = torch.zeros(120, 160, dtype=torch.bool)
    region[20:100, 20:140] = True
    fixed_frac = float(see_through_fraction(fixed.depth, 1.5, region)[0])
    adaptive_frac = float(see_through_fraction(adaptive.depth, 1.5, region)[0])
    assert fixed_frac > 0.3
    assert adaptive_frac < 0.01
    assert adaptive_frac < fixed_frac


def test_see_through_fraction_values():
    depth = torch.tensor([[[1.0, 0.0], [5.0, 1.0]]])
    assert_close(see_through_fraction(depth, 2.0), torch.tensor([0.5]))
    region = torch.tensor([[True, False], [False, True]])
    assert_close(see_through_fraction(depth[:, None], 2.0, region), torch.tensor([0.0]))


def test_points_bad_values_are_culled_and_empty_map(camera):
    good = torch.tensor([[0.0, 0.0, 2.0]])
    bad = torch.tensor(
        [
            [math.nan, 0.0, 1.0],
            [0.0, math.inf, 1.0],
            [0.0, 0.0, math.inf],
            [0.0, 0.0, -1.0],
            [0.0, 0.0, 0.0],
        ]
    )
    sizes = PointSizes.inverse_depth(1.0, 4.0)
    clean = render_points(good, torch.ones(1, 3), identity(), camera, sizes)
    mixed = render_points(torch.cat((bad, good)), torch.ones(6, 3), identity(), camera, sizes)
    assert torch.equal(torch.where(mixed.ids >= 0, mixed.ids - 5, -1), clean.ids)
    empty = render_points(torch.zeros(0, 3), torch.zeros(0, 3), identity(2), camera, sizes)
    assert torch.equal(empty.ids, torch.full((2, 48, 64), -1))
    assert not bool(empty.mask.any())
    assert torch.equal(empty.rgb, torch.zeros(2, 3, 48, 64))


def test_points_bad_shapes(camera):
    with pytest.raises(ShapeError):
        render_points(torch.zeros(3, 3), torch.zeros(2, 3), identity(), camera)
    with pytest.raises(ShapeError):
        render_points(torch.zeros(3, 2), torch.zeros(3, 3), identity(), camera)
    with pytest.raises(ShapeError):
        render_points(torch.zeros(3, 3), torch.zeros(3, 3), torch.zeros(0, 4, 4), camera)
    with pytest.raises(ValueError, match="T_wc"):
        render_points(torch.zeros(3, 3), torch.zeros(3, 3), torch.full((1, 4, 4), math.inf), camera)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"rho_min": 0.0},
        {"rho_min": 2.0, "rho_max": 1.0},
        {"rho_max": math.nan},
        {"levels": ()},
        {"levels": (3, 2)},
        {"levels": (1.5,)},
        {"levels": (0, 1)},
    ],
)
def test_point_sizes_validation(kwargs):
    with pytest.raises(ValueError, match="PointSizes"):
        PointSizes(**kwargs)


def test_point_sizes_passes():
    assert PointSizes().pass_sizes() == (1,)
    assert PointSizes.inverse_depth(0.2, 4.4).pass_sizes() == (1, 2, 3, 4)
    assert PointSizes.inverse_depth(1.5, 3.5).pass_sizes() == (2, 3, 4)
    sizes = PointSizes.multi_pass(1.0, 10.0, (1, 4, 10))  # midpoints 2.5 and 7
    z = torch.tensor([0.5, 1.0, 1.25, 2.0, 4.0, 5.0, 100.0])  # rho = 10, 10, 8, 5, 2.5, 2, 1
    assert sizes.level_index(z).tolist() == [2, 2, 2, 1, 1, 0, 0]
