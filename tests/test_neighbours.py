"""Neighbouring surfel sets of keypoints (seed 1) and the keypoint-disk pixel masks, against
brute-force scans of every pixel."""

from __future__ import annotations

import math

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.database.neighbours import keypoint_disk_mask, neighbour_surfels
from diffloc.geometry.camera import PinholeCamera
from diffloc.render.surfel_render import render_surfel_index


def test_keypoint_disk_mask_is_what_neighbour_surfels_reads():
    g = torch.Generator().manual_seed(4)
    keypoints = torch.rand(30, 2, generator=g) * torch.tensor([40.0, 30.0]) - 2.0
    radius = torch.rand(30, generator=g) * 5.0
    mask = keypoint_disk_mask(keypoints, radius, 30, 40)
    v, u = torch.meshgrid(torch.arange(30.0), torch.arange(40.0), indexing="ij")
    inside = (u[None] - keypoints[:, 0, None, None]).square() + (
        v[None] - keypoints[:, 1, None, None]
    ).square() <= radius[:, None, None].square()
    assert torch.equal(mask, inside.any(0))
    ids = torch.randint(-1, 50, (30, 40), generator=g)
    hidden = torch.where(mask, ids, torch.randint(-1, 50, (30, 40), generator=g))
    assert torch.equal(
        neighbour_surfels(hidden, keypoints, radius), neighbour_surfels(ids, keypoints, radius)
    )
    assert not bool(keypoint_disk_mask(torch.zeros(0, 2), 3.0, 30, 40).any())


def brute_force_neighbours(ids, keypoint, radius):
    h, w = ids.shape
    found = set()
    for v in range(h):
        for u in range(w):
            if (u - keypoint[0]) ** 2 + (v - keypoint[1]) ** 2 <= radius**2 and ids[v, u] >= 0:
                found.add(int(ids[v, u]))
    return sorted(found)


def test_neighbour_surfels_constructed_map():
    ids = torch.full((12, 16), -1)
    ids[2:5, 3:7] = 4
    ids[3, 8] = 9
    ids[6:9, 2:4] = 1
    ids[10, 15] = 2
    keypoints = torch.tensor([[5.0, 3.0], [3.2, 7.4], [15.0, 10.0], [12.0, 1.0], [40.0, 3.0]])
    radii = torch.tensor([3.0, 1.5, 0.0, 2.0, 5.0])
    out = neighbour_surfels(ids, keypoints, radii)
    assert out.dtype == torch.int64 and out.shape == (5, 2)
    assert out.tolist() == [[4, 9], [1, -1], [2, -1], [-1, -1], [-1, -1]]
    for k in range(5):
        row = [int(x) for x in out[k] if x >= 0]
        assert row == brute_force_neighbours(ids, keypoints[k].tolist(), float(radii[k]))


def test_neighbour_surfels_random_batched_against_brute_force():
    g = torch.Generator().manual_seed(5)
    ids = torch.randint(-3, 20, (2, 20, 24), generator=g).clamp_min(-1)
    keypoints = torch.rand(2, 7, 2, generator=g) * torch.tensor([24.0, 20.0])
    radii = torch.rand(2, 7, generator=g) * 4
    out = neighbour_surfels(ids, keypoints, radii)
    assert out.shape[:2] == (2, 7)
    for b in range(2):
        for k in range(7):
            row = [int(x) for x in out[b, k] if x >= 0]
            assert row == brute_force_neighbours(
                ids[b], keypoints[b, k].tolist(), float(radii[b, k])
            )
    scalar = neighbour_surfels(ids, keypoints, 2.0)
    per_point = neighbour_surfels(ids, keypoints, torch.full((7,), 2.0))
    assert torch.equal(scalar, per_point)


def float32_disk_neighbours(ids, keypoint, radius):
    """Sorted distinct ids of the pixels passing the float32 disk test (exact boundaries)."""
    h, w = ids.shape
    v, u = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    ku, kv = keypoint.float()
    inside = (u - ku).square() + (v - kv).square() <= radius.float().square()
    return torch.unique(ids[inside & (ids >= 0)]).tolist()


def test_neighbour_surfels_mixed_sizes_against_reference():
    """ORB-like radii from 0 to beyond the image in one call: every keypoint gets the set of
    its own disk, decided on the boundary exactly as the float32 test decides it."""
    g = torch.Generator().manual_seed(11)
    height, width = 30, 41
    blobs = torch.randint(0, 9, (height // 3 + 1, width // 2 + 1), generator=g)
    ids = blobs.repeat_interleave(3, 0).repeat_interleave(2, 1)[:height, :width].clone()
    ids[torch.rand(height, width, generator=g) < 0.2] = -1  # holes and runs of equal ids
    ids[ids >= 0] += torch.randint(0, 3, (int((ids >= 0).sum()),), generator=g) * 10
    random_kp = torch.rand(40, 2, generator=g) * torch.tensor([width + 10.0, height + 10.0]) - 5
    exact_kp = torch.tensor([[10.0, 10.0], [5.5, 20.5], [0.0, 0.0], [40.0, 29.0], [20.0, 14.5]])
    keypoints = torch.cat([random_kp, exact_kp, torch.tensor([[-60.0, 5.0], [1e6, -1e6]])])
    random_r = torch.rand(40, generator=g) * torch.tensor([0.5, 2, 8, 25]).repeat(10)
    exact_r = torch.tensor([5.0, 2.5, 3.0, 13.0, 2.0])  # boundary pixels at exactly r
    radii = torch.cat([random_r, exact_r, torch.tensor([61.0, 3.0])])
    out = neighbour_surfels(ids, keypoints, radii)
    expected = [float32_disk_neighbours(ids, kp, r) for kp, r in zip(keypoints, radii, strict=True)]
    assert out.shape == (len(keypoints), max(len(e) for e in expected))
    for row, e in zip(out.tolist(), expected, strict=True):
        assert row == e + [-1] * (out.shape[1] - len(e))
    batched = neighbour_surfels(
        torch.stack([ids, ids.flip(1)]), torch.stack([keypoints, keypoints]), radii
    )
    flipped = neighbour_surfels(ids.flip(1), keypoints, radii)
    assert torch.equal(batched[0, :, : out.shape[1]], out)
    assert torch.equal(batched[1, :, : flipped.shape[1]], flipped)
    assert (batched[0, :, out.shape[1] :] == -1).all()


def test_neighbour_surfels_edge_cases():
    ids = torch.zeros(4, 5, dtype=torch.int64)
    assert neighbour_surfels(ids, torch.zeros(0, 2), 2.0).shape == (0, 0)
    assert neighbour_surfels(torch.full((4, 5), -1), torch.ones(3, 2), 2.0).shape == (3, 0)
    with pytest.raises(ValueError, match="radius"):
        neighbour_surfels(ids, torch.ones(1, 2), -1.0)
    with pytest.raises(ValueError, match="keypoints"):
        neighbour_surfels(ids, torch.full((1, 2), math.nan), 1.0)
    with pytest.raises(ShapeError):
        neighbour_surfels(ids, torch.ones(1, 3), 1.0)
    with pytest.raises(ShapeError):
        neighbour_surfels(ids, torch.ones(2, 2), torch.ones(3))
    with pytest.raises(ShapeError):
        neighbour_surfels(ids[None].expand(2, 4, 5), torch.ones(3, 1, 2), 1.0)


def test_surfel_index_to_neighbours_round_trip():
    """The index map feeds the neighbour sets: a keypoint on a disk sees that disk."""
    camera = PinholeCamera.from_fov(64, 48, math.radians(60.0))
    centers = torch.tensor([[-0.3, 0.0, 2.0], [0.3, 0.0, 2.0]])
    normals = torch.tensor([[0.0, 0.0, -1.0]]).expand(2, 3)
    out = render_surfel_index(
        centers, normals, torch.tensor([0.3, 0.3]), torch.eye(4)[None], camera
    )
    u_left = float(camera.fx * -0.3 / 2.0 + camera.cx)
    keypoints = torch.tensor([[u_left, 23.5], [31.5, 23.5]])
    sets = neighbour_surfels(out.ids[0], keypoints, torch.tensor([2.0, 6.0]))
    assert sets.tolist() == [[0, -1], [0, 1]]
