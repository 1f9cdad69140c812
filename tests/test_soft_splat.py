"""Soft splatting: forward values and gradients against the dense all-points x all-pixels
reference (:mod:`diffloc.render._reference`), float64 gradcheck w.r.t. the pose perturbation,
the points and the colours."""

from __future__ import annotations

import math

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import se3_exp
from diffloc.render._reference import reference_soft_points
from diffloc.render.soft_splat import ALPHA_MAX, soft_render_points
from diffloc.testing import assert_close, gradcheck

WINDOW = 5
MIN_SIGMA = 0.5
OPACITY = 0.9


def scene(batch, dtype=torch.float64, n=20, seed=0):
    g = torch.Generator().manual_seed(seed)
    points = torch.rand(n, 3, generator=g, dtype=torch.float64)
    points = points * torch.tensor([1.6, 1.2, 0.8], dtype=torch.float64) - torch.tensor(
        [0.8, 0.6, -1.8], dtype=torch.float64
    )  # x in [-0.8, 0.8], y in [-0.6, 0.6], z in [1.8, 2.6]
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    radii = 0.07 + 0.04 * torch.rand(n, generator=g, dtype=torch.float64)
    xi_pose = 0.05 * torch.randn(batch, 6, generator=g, dtype=torch.float64)
    T_wc = se3_exp(xi_pose)
    xi = 0.01 * torch.randn(batch, 6, generator=g, dtype=torch.float64)
    camera = PinholeCamera.from_fov(16, 12, math.radians(60.0), dtype=torch.float64)
    return [t.to(dtype) for t in (points, colors, radii, T_wc, xi)] + [camera.to(dtype)]


def render(points, colors, radii, T_wc, camera, xi):
    out = soft_render_points(
        points,
        colors,
        radii,
        T_wc,
        camera,
        xi,
        window=WINDOW,
        min_sigma_px=MIN_SIGMA,
        opacity=OPACITY,
    )
    return out.rgb, out.depth, out.alpha


@pytest.mark.parametrize("batch", [1, 2])
def test_forward_matches_dense_reference(batch):
    points, colors, radii, T_wc, xi, camera = scene(batch)
    fast = render(points, colors, radii, T_wc, camera, xi)
    slow = reference_soft_points(
        points, colors, radii, T_wc, camera, xi, WINDOW, MIN_SIGMA, OPACITY
    )
    for a, b in zip(fast, slow, strict=True):
        assert_close(a, b)
    assert float(fast[2].max()) > 0.5  # the scene covers the image substantially
    assert float((fast[2] > 0).float().mean()) > 0.5


@pytest.mark.parametrize("batch", [1, 2])
def test_gradients_match_dense_reference(batch):
    points, colors, radii, T_wc, xi, camera = scene(batch, seed=1)
    g = torch.Generator().manual_seed(9)
    weights = [
        torch.randn(s, generator=g, dtype=torch.float64)
        for s in ((batch, 3, 12, 16), (batch, 1, 12, 16), (batch, 1, 12, 16))
    ]

    def grads(fn):
        inputs = [t.clone().requires_grad_(True) for t in (points, colors, xi)]
        outputs = fn(inputs[0], inputs[1], radii, T_wc, camera, inputs[2])
        loss = sum((o * w).sum() for o, w in zip(outputs, weights, strict=True))
        return torch.autograd.grad(loss, inputs)

    fast = grads(render)
    slow = grads(
        lambda p, c, r, T, cam, x: reference_soft_points(
            p, c, r, T, cam, x, WINDOW, MIN_SIGMA, OPACITY
        )
    )
    for a, b in zip(fast, slow, strict=True):
        assert_close(a, b)
        assert float(a.abs().max()) > 0


@pytest.fixture
def single_thread():
    """Tiny autograd graphs run faster on one thread (and much faster on a busy machine)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize("batch", [1, 2])
def test_gradcheck_pose_points_colors(batch, single_thread):
    points, colors, radii, T_wc, xi, camera = scene(batch, seed=2)
    assert gradcheck(lambda x, p, c: render(p, c, radii, T_wc, camera, x), [xi, points, colors])


def test_float32_forward_matches_float64():
    points, colors, radii, T_wc, xi, camera = scene(2, seed=3)
    high = render(points, colors, radii, T_wc, camera, xi)
    low = render(
        *(t.float() for t in (points, colors, radii, T_wc)), camera.to(torch.float32), xi.float()
    )
    for a, b in zip(low, high, strict=True):
        assert a.dtype == torch.float32
        assert_close(a, b, rtol=1e-4, atol=1e-4)


def test_single_splat_known_values():
    camera = PinholeCamera.from_fov(16, 12, math.radians(60.0), dtype=torch.float64)
    points = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64)
    out = soft_render_points(
        points,
        torch.tensor([[1.0, 0.5, 0.25]], dtype=torch.float64),
        0.1,
        torch.eye(4, dtype=torch.float64)[None],
        camera,
    )
    sigma = float(camera.fx) * 0.1 / 2.0  # ~0.69 px, inside [0.5, 5 / 6]
    # The projection (7.5, 5.5) is half a pixel from its four nearest pixel centres.
    expected = math.exp(-0.5 * 2 * (0.5 / sigma) ** 2)
    assert_close(out.alpha[0, 0, 6, 8], torch.tensor(expected, dtype=torch.float64))
    assert_close(
        out.rgb[0, :, 5, 7], expected * torch.tensor([1.0, 0.5, 0.25], dtype=torch.float64)
    )
    assert_close(out.depth[0, 0, 5, 7], torch.tensor(2.0, dtype=torch.float64))
    assert float(out.alpha[0, 0, 0, 0]) == 0.0 and float(out.depth[0, 0, 0, 0]) == 0.0
    assert int((out.alpha > 0).sum()) == 25  # one 5 x 5 window


def test_nearer_splat_occludes():
    camera = PinholeCamera.from_fov(16, 12, math.radians(60.0), dtype=torch.float64)
    # Both project onto the centre of pixel (u, v) = (8, 6).
    offset = [0.5 / float(camera.fx), 0.5 / float(camera.fy), 1.0]
    points = torch.tensor([[3.0], [2.0]], dtype=torch.float64) * torch.tensor(offset)
    colors = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    T = torch.eye(4, dtype=torch.float64)[None]
    for order in ([0, 1], [1, 0]):
        out = soft_render_points(points[order], colors[order], 0.1, T, camera)
        rgb = out.rgb[0, :, 6, 8]
        expected = torch.tensor([ALPHA_MAX * (1 - ALPHA_MAX), ALPHA_MAX, 0.0], dtype=torch.float64)
        assert_close(rgb, expected)
        assert 2.0 < float(out.depth[0, 0, 6, 8]) < 2.02


def test_pose_gradient_descends_photometric_loss():
    points, colors, radii, T_wc, _, camera = scene(1, seed=4, n=40)
    target = render(points, colors, radii, T_wc, camera, torch.zeros(1, 6, dtype=torch.float64))
    xi = torch.tensor([[0.02, -0.015, 0.0, 0.0, 0.01, 0.0]], dtype=torch.float64)
    xi.requires_grad_(True)

    def loss_at(x):
        out = render(points, colors, radii, T_wc, camera, x)
        return sum(((o - t) ** 2).sum() for o, t in zip(out[::2], target[::2], strict=True))

    start = loss_at(xi)
    (grad,) = torch.autograd.grad(start, xi)
    step = xi.detach() - 1e-3 * grad / grad.norm()
    assert float(loss_at(step)) < float(start.detach())


def test_culling_and_empty():
    camera = PinholeCamera.from_fov(16, 12, math.radians(60.0))
    T = torch.eye(4)[None]
    bad = torch.tensor([[math.nan, 0.0, 2.0], [0.0, 0.0, -2.0], [0.0, math.inf, 1.0]])
    out = soft_render_points(bad, torch.ones(3, 3), 0.1, T, camera)
    assert float(out.alpha.abs().sum()) == 0.0 and bool(torch.isfinite(out.rgb).all())
    empty = soft_render_points(torch.zeros(0, 3), torch.zeros(0, 3), 0.1, T.expand(2, 4, 4), camera)
    assert empty.rgb.shape == (2, 3, 12, 16) and float(empty.depth.abs().sum()) == 0.0


def test_bad_inputs():
    camera = PinholeCamera.from_fov(16, 12, math.radians(60.0))
    p, c, T = torch.zeros(2, 3), torch.zeros(2, 3), torch.eye(4)[None]
    with pytest.raises(ShapeError):
        soft_render_points(p, c[:1], 0.1, T, camera)
    with pytest.raises(ShapeError):
        soft_render_points(p, c, 0.1, torch.zeros(0, 4, 4), camera)
    with pytest.raises(ShapeError):
        soft_render_points(p, c, 0.1, T, camera, torch.zeros(2, 6))
    with pytest.raises(ShapeError):
        soft_render_points(p, c, torch.ones(3), T, camera)
    with pytest.raises(ValueError, match="radii"):
        soft_render_points(p, c, torch.tensor([0.1, -0.1]), T, camera)
    with pytest.raises(ValueError, match="T_wc"):
        soft_render_points(p, c, 0.1, torch.full((1, 4, 4), math.nan), camera)
    with pytest.raises(ValueError, match="window"):
        soft_render_points(p, c, 0.1, T, camera, window=4)
    with pytest.raises(ValueError, match="min_sigma_px"):
        soft_render_points(p, c, 0.1, T, camera, min_sigma_px=0.0)
    with pytest.raises(ValueError, match="opacity"):
        soft_render_points(p, c, 0.1, T, camera, opacity=1.5)
