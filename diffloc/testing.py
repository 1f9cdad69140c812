"""Shared test helpers: per-dtype tolerances, a float64 gradcheck and random synthetic data.

Used by the test suite and by benchmark scripts; nothing here is needed at run time.

Example:
    >>> g = torch.Generator().manual_seed(0)
    >>> T = random_se3((2,), generator=g, dtype=torch.float64)
    >>> assert_close(T @ torch.linalg.inv(T), torch.eye(4, dtype=torch.float64).expand(2, 4, 4))
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from pytorch_kinematics import transforms as pk_tf

from diffloc.features.local import Features
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import hat, invert, transform_points
from diffloc.optim.lm import BlockLinearization

__all__ = [
    "TOLERANCES",
    "TransferBlocks",
    "assert_close",
    "gradcheck",
    "random_points",
    "random_rotation",
    "random_se3",
    "tiled_floor",
    "tolerance",
]

# (rtol, atol) per dtype for comparing results of the same computation done two ways.
TOLERANCES: dict[torch.dtype, tuple[float, float]] = {
    torch.float64: (1e-9, 1e-9),
    torch.float32: (1e-4, 1e-5),
    torch.float16: (1e-2, 1e-2),
    torch.bfloat16: (3e-2, 3e-2),
}


def tolerance(dtype: torch.dtype) -> tuple[float, float]:
    """``(rtol, atol)`` for comparing values of ``dtype``.

    Args:
        dtype: a floating point dtype.

    Returns:
        ``(rtol, atol)``.

    Raises:
        ValueError: ``dtype`` is not a floating point type listed in :data:`TOLERANCES`.
    """
    if dtype not in TOLERANCES:
        raise ValueError(f"no tolerance defined for dtype {dtype}")
    return TOLERANCES[dtype]


def assert_close(
    actual: torch.Tensor,
    expected: torch.Tensor,
    *,
    rtol: float | None = None,
    atol: float | None = None,
    msg: str | None = None,
) -> None:
    """``torch.testing.assert_close`` with the tolerances of :func:`tolerance` by default.

    The tolerance is chosen from the lower-precision dtype of the two tensors; ``expected``
    is cast to ``actual``'s dtype and device before comparing.

    Args:
        actual: tensor under test.
        expected: reference tensor (broadcast to ``actual``'s shape is *not* done).
        rtol: relative tolerance override.
        atol: absolute tolerance override.
        msg: extra message on failure.
    """
    dtypes = [t.dtype for t in (actual, expected) if t.is_floating_point()]
    if dtypes:
        worst = max(dtypes, key=lambda d: tolerance(d)[0])
        default_rtol, default_atol = tolerance(worst)
    else:
        default_rtol, default_atol = 0.0, 0.0
    torch.testing.assert_close(
        actual,
        expected.to(dtype=actual.dtype, device=actual.device),
        rtol=default_rtol if rtol is None else rtol,
        atol=default_atol if atol is None else atol,
        msg=msg,
    )


def gradcheck(
    fn: Callable[..., torch.Tensor | Sequence[torch.Tensor]],
    inputs: Sequence[torch.Tensor],
    *,
    eps: float = 1e-6,
    atol: float = 1e-6,
    rtol: float = 1e-4,
) -> bool:
    """Float64 ``torch.autograd.gradcheck`` of ``fn`` at ``inputs``.

    Floating point inputs are copied to float64 leaf tensors that require grad; other inputs
    are passed through unchanged. Raises ``GradcheckError`` on a mismatch.

    Args:
        fn: function of the inputs returning a tensor or a tuple of tensors.
        inputs: the point at which to check the gradients.
        eps: finite-difference step.
        atol: absolute tolerance.
        rtol: relative tolerance.

    Returns:
        ``True`` when the analytic and numeric Jacobians agree.

    Example:
        >>> gradcheck(torch.sin, [torch.tensor([0.5])])
        True
    """
    prepared = tuple(
        x.detach().to(torch.float64).requires_grad_(True) if x.is_floating_point() else x
        for x in inputs
    )
    return torch.autograd.gradcheck(fn, prepared, eps=eps, atol=atol, rtol=rtol)


def random_rotation(
    shape: Sequence[int] = (),
    *,
    generator: torch.Generator,
    dtype: torch.dtype = torch.float64,
    max_angle: float = math.pi,
) -> torch.Tensor:
    """Random rotation matrices (uniform on SO(3) when ``max_angle == pi``).

    Args:
        shape: leading batch shape ``(...)``.
        generator: source of randomness (CPU generator).
        dtype: output dtype.
        max_angle: largest rotation angle in radians; below pi the angle is drawn uniformly
            in ``[0, max_angle]`` around a uniformly random axis.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    shape = tuple(shape)
    if max_angle >= math.pi:
        q = torch.randn(*shape, 4, generator=generator, dtype=torch.float64)
        q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
        return pk_tf.quaternion_to_matrix(q).to(dtype)
    axis = torch.randn(*shape, 3, generator=generator, dtype=torch.float64)
    axis = axis / torch.linalg.vector_norm(axis, dim=-1, keepdim=True)
    angle = max_angle * torch.rand(*shape, 1, generator=generator, dtype=torch.float64)
    q = pk_tf.axis_angle_to_quaternion(axis * angle)
    return pk_tf.quaternion_to_matrix(q).to(dtype)


def random_se3(
    shape: Sequence[int] = (),
    *,
    generator: torch.Generator,
    dtype: torch.dtype = torch.float64,
    max_angle: float = math.pi,
    max_translation: float = 1.0,
) -> torch.Tensor:
    """Random rigid transforms.

    Args:
        shape: leading batch shape ``(...)``.
        generator: source of randomness (CPU generator).
        dtype: output dtype.
        max_angle: largest rotation angle (radians), see :func:`random_rotation`.
        max_translation: translations are uniform in ``[-max_translation, max_translation]^3``.

    Returns:
        (..., 4, 4) transforms.
    """
    shape = tuple(shape)
    R = random_rotation(shape, generator=generator, dtype=torch.float64, max_angle=max_angle)
    t = max_translation * (
        2.0 * torch.rand(*shape, 3, generator=generator, dtype=torch.float64) - 1
    )
    T = torch.zeros(*shape, 4, 4, dtype=torch.float64)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T.to(dtype)


def random_points(
    shape: Sequence[int],
    *,
    generator: torch.Generator,
    dtype: torch.dtype = torch.float64,
    low: Sequence[float] = (-1.0, -1.0, 2.0),
    high: Sequence[float] = (1.0, 1.0, 5.0),
) -> torch.Tensor:
    """Points uniform in an axis-aligned box (by default in front of an OpenCV camera).

    Args:
        shape: leading shape, e.g. ``(B, N)``.
        generator: source of randomness (CPU generator).
        dtype: output dtype.
        low: (3,) lower corner.
        high: (3,) upper corner.

    Returns:
        (*shape, 3) points.
    """
    lo = torch.tensor(low, dtype=torch.float64)
    hi = torch.tensor(high, dtype=torch.float64)
    u = torch.rand(*tuple(shape), 3, generator=generator, dtype=torch.float64)
    return (lo + (hi - lo) * u).to(dtype)


@dataclass
class TransferBlocks:
    """Two-pose reprojection blocks for LM tests and benchmarks (seed 1 Eq. 3-like).

    Block ``m`` is a point ``points_a[m]`` fixed in camera a, observed at ``keypoints_b[m]``
    in camera b: ``r = project(T_b^-1 T_a X_a) - p_b``. Poses update on the right
    (``T <- T exp(delta)``), as in :mod:`diffloc.optim.lm`.

    Attributes:
        camera: the camera of both views.
        points_a: (M, 3) points in camera a.
        keypoints_b: (M, 2) observations in camera b.
    """

    camera: PinholeCamera
    points_a: torch.Tensor
    keypoints_b: torch.Tensor

    def residual_fn(
        self, T_a: torch.Tensor, T_b: torch.Tensor | None, extra: torch.Tensor | None
    ) -> torch.Tensor:
        """(..., M, 2) residuals for (..., M, 4, 4) poses ``T_a``, ``T_b``."""
        points_b = transform_points(invert(T_b) @ T_a, self.points_a[:, None, :])[..., 0, :]
        return self.camera.project(points_b)[0] - self.keypoints_b

    def jacobian_fn(
        self, T_a: torch.Tensor, T_b: torch.Tensor | None, extra: torch.Tensor | None
    ) -> BlockLinearization:
        """Residuals with analytic (..., M, 2, 6) Jacobians w.r.t. both poses."""
        X_a = self.points_a
        points_b = transform_points(invert(T_b) @ T_a, X_a[:, None, :])[..., 0, :]
        j_point = self.camera.project_jacobian_point(points_b[..., None, :])[..., 0, :, :]
        eye = torch.eye(3, dtype=X_a.dtype).expand(*X_a.shape[:-1], 3, 3)
        rotation = T_b[..., :3, :3].transpose(-1, -2) @ T_a[..., :3, :3]
        jac_a = j_point @ rotation @ torch.cat((eye, -hat(X_a)), dim=-1)
        jac_b = -self.camera.project_jacobian_pose(points_b[..., None, :])[..., 0, :, :]
        return BlockLinearization(self.residual_fn(T_a, T_b, extra), jac_a, jac_b)


@dataclass(frozen=True)
class TiledFloor:
    """A query camera above a floor whose texture repeats along x (:func:`tiled_floor`).

    Attributes:
        T_wc: (4, 4) float64 the query's true pose (camera-to-world).
        rivals: (0, 4, 4) float64 no other candidate poses.
        inliers: (N, 2) int64 ``(keypoint, map point)``: the query's inliers at the true pose
            (keypoint ``i`` is the projection of the ``i``-th map point it sees).
        features: the query's keypoints (the seen points projected) and their descriptors.
        camera: the query camera.
        positions: (P, 3) float64 map points on the floor plane z = 0.
        descriptors: (P, 32) float32 their L2-normalised descriptors.
    """

    T_wc: torch.Tensor
    rivals: torch.Tensor
    inliers: torch.Tensor
    features: Features
    camera: PinholeCamera
    positions: torch.Tensor
    descriptors: torch.Tensor


def tiled_floor(period_m: float = 1.0, marking_m: float = 0.0, seed: int = 0) -> TiledFloor:
    """A floor of map points every 0.1 m whose descriptors repeat every ``period_m`` along x
    (each copy perturbed a little, less than the query's descriptors are), seen straight down
    from 2 m by a 160 x 120 camera; a square of half-width ``marking_m`` under the camera has
    descriptors of its own (a marking that does not repeat). Query keypoints are the seen
    points' exact projections, their descriptors the points' with a little noise.

    Example:
        >>> floor = tiled_floor()
        >>> len(floor.features) == len(floor.inliers) > 400
        True
    """
    g = torch.Generator().manual_seed(seed)
    step = 0.1
    xs = torch.arange(-60, 61, dtype=torch.float64) * step
    ys = torch.arange(-40, 41, dtype=torch.float64) * step
    gx, gy = torch.meshgrid(xs, ys, indexing="ij")
    positions = torch.stack([gx, gy, torch.zeros_like(gx)], -1).reshape(-1, 3)
    columns = round(period_m / step)
    pattern = torch.randn(columns, len(ys), 32, generator=g)
    ix = torch.arange(len(xs))[:, None].expand(-1, len(ys)) % columns
    iy = torch.arange(len(ys))[None].expand(len(xs), -1)
    descriptors = pattern[ix, iy].reshape(-1, 32)  # the copies of a spot look alike
    descriptors = descriptors + 0.01 * torch.randn(descriptors.shape, generator=g)
    centre = torch.tensor([0.3, 0.2], dtype=torch.float64)
    marked = ((positions[:, :2] - centre).abs() <= marking_m).all(1)
    descriptors[marked] = torch.randn(int(marked.sum()), 32, generator=g)
    descriptors = torch.nn.functional.normalize(descriptors, dim=1)
    T_wc = torch.eye(4, dtype=torch.float64)
    T_wc[:3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    T_wc[:2, 3], T_wc[2, 3] = centre, 2.0
    camera = PinholeCamera.from_fov(160, 120, 1.2, dtype=torch.float64)
    uv, valid = camera.project(transform_points(invert(T_wc), positions))
    inliers = torch.nonzero(valid & camera.in_image(uv)).flatten()
    noisy = descriptors[inliers] + 0.1 * torch.randn(len(inliers), 32, generator=g)
    n = len(inliers)
    features = Features(
        uv[inliers].float(),
        torch.ones(n),
        torch.nn.functional.normalize(noisy, dim=1),
        torch.ones(n),
    )
    rivals = torch.zeros(0, 4, 4, dtype=torch.float64)
    matches = torch.stack([torch.arange(n), inliers], 1)
    return TiledFloor(T_wc, rivals, matches, features, camera, positions, descriptors)
