"""Tests of diffloc.geometry.camera: known answers, OpenCV agreement, Jacobians, bad inputs."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.geometry.camera import MIN_DEPTH, PinholeCamera
from diffloc.geometry.se3 import invert, se3_exp, transform_points
from diffloc.testing import assert_close, gradcheck, random_points, random_se3

F64 = torch.float64
EUROC = torch.tensor([-0.28, 0.07, 2e-4, 2e-5], dtype=F64)
BATCH_SHAPES = [(), (2,), (1, 2)]


def euroc_camera(distortion: bool = True) -> PinholeCamera:
    """The EuRoC cam0 intrinsics (752x480) with or without its distortion."""
    return PinholeCamera(
        fx=torch.tensor(458.654, dtype=F64),
        fy=torch.tensor(457.296, dtype=F64),
        cx=torch.tensor(367.215, dtype=F64),
        cy=torch.tensor(248.375, dtype=F64),
        width=752,
        height=480,
        distortion=EUROC if distortion else None,
    )


def batched_camera(shape: tuple[int, ...], distortion: bool) -> PinholeCamera:
    """Cameras with different intrinsics per batch element."""
    n = math.prod(shape)
    ramp = torch.linspace(0.0, 1.0, n, dtype=F64).reshape(shape)
    dist = (EUROC * (1.0 + 0.2 * ramp[..., None])) if distortion else None
    return PinholeCamera(
        fx=300.0 + 20.0 * ramp,
        fy=310.0 - 10.0 * ramp,
        cx=159.5 + ramp,
        cy=119.5 - ramp,
        width=320,
        height=240,
        distortion=dist,
    )


# ---------------------------------------------------------------- construction and validation


@pytest.mark.parametrize(
    ("field", "value"), [("width", 0), ("width", -3), ("height", 0), ("height", -1), ("width", 2.5)]
)
def test_non_positive_image_size_raises(field: str, value: object) -> None:
    kwargs = {"fx": 1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0, "width": 4, "height": 4}
    kwargs[field] = value
    with pytest.raises(ValueError, match=f"{field} must be a positive integer"):
        PinholeCamera(**kwargs)


@pytest.mark.parametrize(
    ("fx", "fy"), [(0.0, 1.0), (1.0, -2.0), (float("nan"), 1.0), (1.0, float("inf"))]
)
def test_bad_focal_lengths_raise(fx: float, fy: float) -> None:
    with pytest.raises(ValueError, match="f[xy]|focal"):
        PinholeCamera(fx=fx, fy=fy, cx=0.0, cy=0.0, width=4, height=4)


def test_non_finite_principal_point_raises() -> None:
    with pytest.raises(ValueError, match="cx"):
        PinholeCamera(fx=1.0, fy=1.0, cx=float("nan"), cy=0.0, width=4, height=4)


def test_bad_distortion_raises() -> None:
    with pytest.raises(ShapeError, match="distortion"):
        PinholeCamera(fx=1.0, fy=1.0, cx=0.0, cy=0.0, width=4, height=4, distortion=torch.zeros(5))
    with pytest.raises(ValueError, match="distortion"):
        PinholeCamera(
            fx=1.0,
            fy=1.0,
            cx=0.0,
            cy=0.0,
            width=4,
            height=4,
            distortion=torch.tensor([0.0, float("nan"), 0.0, 0.0]),
        )


def test_batch_shapes_that_do_not_broadcast_raise() -> None:
    with pytest.raises(ValueError, match="broadcast"):
        PinholeCamera(fx=torch.ones(2), fy=torch.ones(3), cx=0.0, cy=0.0, width=4, height=4)


@pytest.mark.parametrize("hfov", [0.0, -0.1, math.pi, 4.0, float("nan")])
def test_from_fov_rejects_bad_field_of_view(hfov: float) -> None:
    with pytest.raises(ValueError, match="hfov"):
        PinholeCamera.from_fov(64, 48, hfov)


def test_from_fov_known_answer() -> None:
    cam = PinholeCamera.from_fov(640, 480, math.radians(90.0), dtype=F64)
    assert cam.dtype == F64 and cam.batch_shape == ()
    assert_close(cam.fx, torch.tensor(320.0, dtype=F64))
    assert_close(cam.fy, cam.fx)
    assert float(cam.cx) == 319.5 and float(cam.cy) == 239.5
    # A ray at half the horizontal field of view hits the outer edge of the outer pixel.
    uv, _ = cam.project(torch.tensor([[1.0, 0.0, 1.0], [-1.0, 0.0, 1.0]], dtype=F64))
    assert_close(uv[:, 0], torch.tensor([639.5, -0.5], dtype=F64))
    expected_K = torch.tensor([[320.0, 0, 319.5], [0, 320.0, 239.5], [0, 0, 1]], dtype=F64)
    assert_close(cam.K, expected_K)
    assert_close(PinholeCamera.from_K(cam.K, 640, 480).K, cam.K, atol=0, rtol=0)


def test_dtype_follows_distortion_and_to_casts() -> None:
    cam = PinholeCamera.from_fov(64, 48, 1.0, distortion=EUROC)
    assert cam.dtype == F64 and cam.distortion.dtype == F64
    cam32 = cam.to(torch.float32)
    assert cam32.fx.dtype == torch.float32 and cam32.distortion.dtype == torch.float32
    assert (cam32.width, cam32.height) == (64, 48)
    assert PinholeCamera.from_fov(64, 48, 1.0).dtype == torch.get_default_dtype()
    assert cam32.to(torch.float32) is cam32  # nothing to change
    back = cam32.to(torch.float64)
    assert back.dtype == F64 and torch.equal(back.K, cam32.K.double())
    with pytest.raises(ValueError, match="fx"):  # other dtypes are checked: float16 overflows
        PinholeCamera.from_fov(64, 48, 1e-6).to(torch.float16)


def test_indexing_a_camera_batch() -> None:
    cams = batched_camera((1, 2), distortion=True)
    assert cams.batch_shape == (1, 2)
    one = cams[0, 1]
    assert one.batch_shape == () and one.distortion.shape == (4,)
    assert_close(one.fx, cams.fx[0, 1])
    assert_close(one.distortion, cams.distortion[0, 1])
    assert cams[..., 0].distortion.shape == (1, 4)
    with pytest.raises(IndexError):
        one[0]


def test_scaled_camera_matches_resized_pixel_grid() -> None:
    cam = euroc_camera()
    small = cam.scaled(0.5)
    assert (small.width, small.height) == (376, 240)
    g = torch.Generator().manual_seed(0)
    points = random_points((50,), generator=g)
    uv, _ = cam.project(points)
    uv_small, _ = small.project(points)
    # Pixel-centre convention: the edge -0.5 maps to -0.5, centres scale about it.
    assert_close(uv_small, (uv + 0.5) * 0.5 - 0.5)
    assert_close(small.distortion, cam.distortion)


@pytest.mark.parametrize("factor", [0.0, -1.0, float("nan"), 1e-4])
def test_scaled_rejects_bad_factor(factor: float) -> None:
    with pytest.raises(ValueError, match="factor|no pixels"):
        euroc_camera().scaled(factor)


# ---------------------------------------------------------------- distortion


def test_distort_known_answer() -> None:
    cam = euroc_camera()
    k1, k2, p1, p2 = EUROC.tolist()
    x, y = 0.3, -0.2
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    expected = [
        x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
        y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
    ]
    got = cam.distort(torch.tensor([[x, y]], dtype=F64))
    assert_close(got, torch.tensor([expected], dtype=F64), atol=1e-15, rtol=0)


def test_project_matches_opencv() -> None:
    cam = euroc_camera()
    g = torch.Generator().manual_seed(1)
    points = random_points((200,), generator=g)
    uv, valid = cam.project(points)
    assert valid.all()
    dist = np.array([*EUROC.tolist(), 0.0])
    ref, _ = cv2.projectPoints(points.numpy(), np.zeros(3), np.zeros(3), cam.K.numpy(), dist)
    assert_close(uv, torch.from_numpy(ref[:, 0, :]), atol=1e-9, rtol=0)


def test_undistort_converges_over_full_euroc_image() -> None:
    cam = euroc_camera()
    uv = cam.pixel_grid().reshape(-1, 2)
    xy_d = (uv - torch.stack((cam.cx, cam.cy))) / torch.stack((cam.fx, cam.fy))
    xy = cam.undistort_normalized(xy_d)
    assert (cam.distort(xy) - xy_d).abs().max() <= 1e-10
    # and the other way round, from ideal coordinates
    assert (cam.undistort_normalized(cam.distort(xy)) - xy).abs().max() <= 1e-10
    # agrees with OpenCV's (iterative, less accurate) undistortion
    dist = np.array([*EUROC.tolist(), 0.0])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    ref = cv2.undistortPointsIter(
        uv.numpy()[:, None, :], cam.K.numpy(), dist, np.eye(3), np.eye(3), criteria
    )[:, 0, :]
    assert_close(xy, torch.from_numpy(ref), atol=1e-6, rtol=0)


def test_undistort_points_keeps_the_same_K() -> None:
    cam = euroc_camera()
    g = torch.Generator().manual_seed(2)
    points = random_points((30,), generator=g)
    uv_distorted, _ = cam.project(points)
    uv_ideal, _ = euroc_camera(distortion=False).project(points)
    assert_close(cam.undistort_points(uv_distorted), uv_ideal)


def test_undistort_gradients_are_implicit_function_gradients() -> None:
    g = torch.Generator().manual_seed(3)
    xy_d = 0.4 * torch.rand(2, 5, 2, generator=g, dtype=F64) - 0.2

    def undistort(xy: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
        cam = PinholeCamera(
            fx=400.0, fy=400.0, cx=100.0, cy=80.0, width=200, height=160, distortion=dist
        )
        return cam.undistort_normalized(xy)

    assert gradcheck(undistort, [xy_d, EUROC])


# ---------------------------------------------------------------- projection


@pytest.mark.parametrize("distortion", [False, True])
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_project_unproject_round_trip(shape: tuple[int, ...], distortion: bool) -> None:
    cam = batched_camera(shape, distortion)
    g = torch.Generator().manual_seed(4)
    points = random_points((*shape, 40), generator=g)
    uv, valid = cam.project(points)
    assert uv.shape == (*shape, 40, 2) and valid.shape == (*shape, 40) and valid.all()
    assert_close(cam.unproject(uv, points[..., 2]), points)
    rays = cam.unproject(uv)
    assert_close(rays, points / points[..., 2:])


@pytest.mark.parametrize("shape", [(2,), (1, 2)])
def test_camera_batch_equals_per_camera_results(shape: tuple[int, ...]) -> None:
    cams = batched_camera(shape, distortion=True)
    g = torch.Generator().manual_seed(5)
    points = random_points((7,), generator=g)  # shared points broadcast over the cameras
    uv, _ = cams.project(points)
    flat_uv = uv.reshape(-1, 7, 2)
    flat_cams = cams[0] if len(shape) == 2 else cams
    for i in range(shape[-1]):
        assert_close(flat_uv[i], flat_cams[i].project(points)[0])


def test_project_validity_and_finiteness_behind_camera() -> None:
    cam = euroc_camera()
    points = torch.tensor(
        [
            [0.1, 0.2, 1.0],
            [0.1, 0.2, 0.0],
            [0.1, 0.2, -2.0],
            [0.0, 0.0, MIN_DEPTH],
            [0.0, 0.0, 2 * MIN_DEPTH],
        ],
        dtype=F64,
    )
    uv, valid = cam.project(points)
    assert valid.tolist() == [True, False, False, False, True]
    assert torch.isfinite(uv).all()
    points.requires_grad_(True)
    cam.project(points)[0].sum().backward()
    assert torch.isfinite(points.grad).all()


def test_project_world_uses_camera_to_world_pose() -> None:
    cam = euroc_camera()
    g = torch.Generator().manual_seed(6)
    T_wc = random_se3((3,), generator=g, max_translation=0.2, max_angle=0.3)
    points_cam = random_points((3, 10), generator=g)
    points_world = transform_points(T_wc, points_cam)
    uv, valid = cam.project_world(points_world, T_wc)
    assert_close(uv, cam.project(points_cam)[0])
    assert valid.all()
    assert_close(
        cam.project_world(points_world, T_wc)[0],
        cam.project(transform_points(invert(T_wc), points_world))[0],
    )


def test_project_gradcheck_through_intrinsics_and_points() -> None:
    g = torch.Generator().manual_seed(7)
    points = random_points((2, 4), generator=g)

    def fn(pts: torch.Tensor, fx: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
        cam = PinholeCamera(
            fx=fx, fy=fx * 1.01, cx=150.0, cy=100.0, width=300, height=200, distortion=dist
        )
        return cam.project(pts)[0]

    assert gradcheck(fn, [points, torch.tensor(250.0), EUROC])


def test_pixel_grid_and_in_image() -> None:
    cam = PinholeCamera.from_fov(5, 3, 1.0, dtype=F64)
    grid = cam.pixel_grid()
    assert grid.shape == (3, 5, 2) and grid.dtype == F64
    assert grid[2, 4].tolist() == [4.0, 2.0] and grid[0, 0].tolist() == [0.0, 0.0]
    assert cam.pixel_grid(torch.float32).dtype == torch.float32
    assert cam.in_image(grid.reshape(-1, 2)).all()
    uv = torch.tensor(
        [[-0.5, -0.5], [-0.51, 0.0], [4.49, 2.49], [4.5, 0.0], [0.0, 2.5], [float("nan"), 0.0]],
        dtype=F64,
    )
    assert cam.in_image(uv).tolist() == [True, False, True, False, False, False]


@pytest.mark.parametrize(
    ("method", "bad"),
    [
        ("project", torch.zeros(4, 2)),
        ("project_jacobian_point", torch.zeros(4, 2)),
        ("project_jacobian_pose", torch.zeros(3)),
        ("unproject", torch.zeros(4, 3)),
        ("undistort_points", torch.zeros(4, 3)),
        ("distort", torch.zeros(4, 3)),
        ("undistort_normalized", torch.zeros(2)),
        ("in_image", torch.zeros(4, 1)),
    ],
)
def test_wrong_point_shapes_raise(method: str, bad: torch.Tensor) -> None:
    with pytest.raises(ShapeError):
        getattr(euroc_camera(), method)(bad)


def test_wrong_shapes_in_project_world_and_depth_raise() -> None:
    cam = euroc_camera()
    with pytest.raises(ShapeError, match="T_wc"):
        cam.project_world(torch.zeros(4, 3, dtype=F64), torch.eye(3, dtype=F64))
    with pytest.raises(ShapeError, match="depth"):
        cam.unproject(torch.zeros(4, 2, dtype=F64), torch.zeros(4, 1, dtype=F64))


# ---------------------------------------------------------------- Jacobians


@pytest.mark.parametrize("distortion", [False, True])
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_project_jacobian_point_matches_autograd(shape: tuple[int, ...], distortion: bool) -> None:
    cam = batched_camera(shape, distortion)
    g = torch.Generator().manual_seed(8)
    points = random_points((*shape, 6), generator=g)
    jac = cam.project_jacobian_point(points)
    assert jac.shape == (*shape, 6, 2, 3)
    ref = torch.func.jacrev(lambda p: cam.project(p)[0])(points)  # (..., 6, 2, ..., 6, 3)
    # every uv depends only on its own point: keep the diagonal blocks
    m = math.prod(shape) * 6
    ref = ref.reshape(m, 2, m, 3)[torch.arange(m), :, torch.arange(m)]
    assert_close(jac, ref.reshape(*shape, 6, 2, 3), atol=1e-9, rtol=1e-9)


@pytest.mark.parametrize("distortion", [False, True])
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_project_jacobian_pose_matches_autograd(shape: tuple[int, ...], distortion: bool) -> None:
    cam = batched_camera(shape, distortion)
    g = torch.Generator().manual_seed(9)
    points = random_points((*shape, 5), generator=g)
    jac = cam.project_jacobian_pose(points)
    assert jac.shape == (*shape, 5, 2, 6)

    def perturbed(delta: torch.Tensor) -> torch.Tensor:  # (..., 6) -> (..., 5, 2)
        return cam.project(transform_points(se3_exp(delta), points))[0]

    delta0 = torch.zeros(*shape, 6, dtype=F64)
    ref = torch.func.jacrev(perturbed)(delta0)  # (..., 5, 2, ..., 6)
    # keep only the diagonal batch blocks: output batch index == input batch index
    n_batch = math.prod(shape)
    ref = ref.reshape(n_batch, 5, 2, n_batch, 6)
    ref = ref[torch.arange(n_batch), :, :, torch.arange(n_batch)].reshape(*shape, 5, 2, 6)
    assert_close(jac, ref, atol=1e-9, rtol=1e-9)
