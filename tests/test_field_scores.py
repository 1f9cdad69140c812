"""diffloc.eval.field_scores: reference normals of depth images (known planes, masked jumps and
holes), PSNR, and the held-out scoring's bad input."""

from __future__ import annotations

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.eval.field_scores import depth_image_normals, heldout_field_scores, psnr
from diffloc.geometry.camera import PinholeCamera


def plane_depth(camera: PinholeCamera, normal: torch.Tensor, offset: float) -> torch.Tensor:
    """(1, H, W) z-depth of the plane ``normal . X = offset`` (camera frame)."""
    uv = camera.pixel_grid(torch.float64)
    rays = torch.stack(
        ((uv[..., 0] - camera.cx) / camera.fx, (uv[..., 1] - camera.cy) / camera.fy),
        dim=-1,
    )
    rays = torch.cat((rays, torch.ones_like(rays[..., :1])), dim=-1)
    return (offset / (rays @ normal))[None].float()


def test_normals_of_a_tilted_plane_are_its_normal_facing_the_camera() -> None:
    camera = PinholeCamera.from_fov(16, 12, 1.0)
    normal = torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64)
    normal = normal / normal.norm()
    depth = plane_depth(camera, normal, 3.0)
    out = depth_image_normals(depth, camera)
    inner = out[:, 1:-1, 1:-1].reshape(3, -1).T
    expected = -normal.float()  # the plane lies in front: the normal facing the camera is -n
    torch.testing.assert_close(inner, expected.expand_as(inner), atol=1e-4, rtol=0)
    assert (out[:, 0] == 0).all() and (out[:, :, -1] == 0).all()


def test_no_normal_across_a_depth_jump_or_beside_a_hole() -> None:
    camera = PinholeCamera.from_fov(10, 8, 1.0)
    depth = torch.full((1, 8, 10), 2.0)
    depth[0, :, 5:] = 4.0  # a step between columns 4 and 5
    depth[0, 2, 2] = 0.0  # no measurement
    ok = depth_image_normals(depth, camera).abs().sum(0) > 0
    assert not ok[1:-1, 4].any() and not ok[1:-1, 5].any()
    assert not ok[2, 2] and not ok[1, 2] and not ok[3, 2] and not ok[2, 1] and not ok[2, 3]
    assert ok[5, 2] and ok[5, 7]


def test_normals_check_the_depth_shape() -> None:
    camera = PinholeCamera.from_fov(10, 8, 1.0)
    with pytest.raises(ShapeError):
        depth_image_normals(torch.ones(1, 10, 8), camera)


def test_psnr_of_known_errors() -> None:
    a = torch.zeros(3, 4, 4)
    assert psnr(a, a + 0.01) == pytest.approx(40.0)
    assert psnr(a, a) == pytest.approx(120.0)  # capped at an MSE of 1e-12


def test_heldout_scores_need_a_held_out_frame() -> None:
    with pytest.raises(ValueError, match="at least one held-out frame"):
        heldout_field_scores(None, None, None, None, [], full=True)
