"""Tests of diffloc.geometry.se3: known answers, round trips, gradients, bad inputs."""

from __future__ import annotations

import math

import pytest
import torch
from pytorch_kinematics import transforms as pk_tf
from scipy.spatial.transform import Rotation

from diffloc.checks import ShapeError
from diffloc.geometry.se3 import (
    adjoint,
    cayley_rotation,
    compose,
    hat,
    invert,
    pose_from_translation_quaternion,
    se3_exp,
    se3_log,
    so3_exp,
    so3_log,
    transform_points,
    translation_quaternion_from_pose,
    vee,
)
from diffloc.testing import assert_close, gradcheck, random_points, random_se3

F64 = torch.float64
BATCH_SHAPES = [(), (2,), (1, 2)]
# Angles that exercise every branch: exact zero, Taylor region, thresholds, moderate, near pi.
ANGLES = [
    0.0,
    1e-12,
    1e-8,
    1e-4,
    9.99e-4,
    1.001e-3,
    0.3,
    1.5,
    math.pi / 2,
    2.5,
    3.0,
    math.pi - 1e-3,
    math.pi - 1e-6,
]


def _unit(shape: tuple[int, ...], g: torch.Generator) -> torch.Tensor:
    a = torch.randn(*shape, 3, generator=g, dtype=F64)
    return a / a.norm(dim=-1, keepdim=True)


def _twists(shape: tuple[int, ...], angle: float, g: torch.Generator) -> torch.Tensor:
    w = _unit(shape, g) * angle
    v = torch.randn(*shape, 3, generator=g, dtype=F64)
    return torch.cat((v, w), dim=-1)


def test_hat_is_cross_product_and_vee_inverts_it() -> None:
    g = torch.Generator().manual_seed(0)
    w, x = torch.randn(2, 4, 3, generator=g, dtype=F64)
    assert_close((hat(w) @ x[..., None])[..., 0], torch.linalg.cross(w, x))
    assert_close(vee(hat(w)), w)
    assert_close(hat(w).transpose(-1, -2), -hat(w))


def test_so3_exp_known_answer() -> None:
    R = so3_exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=F64))
    expected = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    assert_close(R, expected, atol=1e-15, rtol=0)


@pytest.mark.parametrize("angle", ANGLES)
def test_so3_exp_matches_pytorch_kinematics_and_is_a_rotation(angle: float) -> None:
    g = torch.Generator().manual_seed(1)
    w = _unit((5,), g) * angle
    R = so3_exp(w)
    reference = pk_tf.quaternion_to_matrix(pk_tf.axis_angle_to_quaternion(w))
    assert_close(R, reference, atol=1e-14, rtol=0)
    assert_close(
        R @ R.transpose(-1, -2), torch.eye(3, dtype=F64).expand(5, 3, 3), atol=1e-14, rtol=0
    )


@pytest.mark.parametrize("shape", BATCH_SHAPES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cayley_rotation_is_so3_exp_at_the_cayley_angle(
    shape: tuple[int, ...], dtype: torch.dtype
) -> None:
    # Cay(w) rotates by 2 atan(|w| / 2) about w: exp of that rotation vector, exactly.
    g = torch.Generator().manual_seed(7)
    w = torch.randn(*shape, 3, generator=g, dtype=F64) * 1.5
    norm = w.norm(dim=-1, keepdim=True)
    expected = so3_exp(w / norm * 2.0 * torch.atan(norm / 2.0))
    R = cayley_rotation(w.to(dtype))
    assert R.shape == (*shape, 3, 3) and R.dtype == dtype
    assert_close(R, expected.to(dtype))
    assert_close(cayley_rotation(torch.zeros(3, dtype=dtype)), torch.eye(3, dtype=dtype))
    assert gradcheck(cayley_rotation, [w])


@pytest.mark.parametrize("angle", [0.3, 1.5, 2.5, 3.0])
def test_so3_log_matches_scipy(angle: float) -> None:
    # (pytorch_kinematics' matrix_to_axis_angle may return angles above pi; scipy does not.)
    g = torch.Generator().manual_seed(2)
    R = so3_exp(_unit((5,), g) * angle)
    reference = torch.from_numpy(Rotation.from_matrix(R.numpy()).as_rotvec())
    assert_close(so3_log(R), reference, atol=1e-12, rtol=0)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
@pytest.mark.parametrize("angle", ANGLES)
def test_se3_round_trips_float64(shape: tuple[int, ...], angle: float) -> None:
    g = torch.Generator().manual_seed(3)
    xi = _twists(shape, angle, g)
    T = se3_exp(xi)
    assert T.shape == (*shape, 4, 4)
    assert (se3_log(T) - xi).abs().max() <= 1e-9
    assert (se3_exp(se3_log(T)) - T).abs().max() <= 1e-9
    assert (so3_exp(so3_log(T[..., :3, :3])) - T[..., :3, :3]).abs().max() <= 1e-9


@pytest.mark.parametrize(
    "axis",
    [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 0.0], [1.0, -2.0, 3.0]],
)
def test_log_at_exactly_pi_is_stable(axis: list[float]) -> None:
    a = torch.tensor(axis, dtype=F64)
    a = a / a.norm()
    xi = torch.cat((torch.tensor([0.3, -0.2, 0.1], dtype=F64), math.pi * a))
    T = se3_exp(xi)
    log = se3_log(T)
    assert torch.isfinite(log).all()
    assert abs(float(log[3:].norm()) - math.pi) <= 1e-12
    assert (se3_exp(log) - T).abs().max() <= 1e-9  # w and -w are both valid at pi


def test_round_trips_float32() -> None:
    g = torch.Generator().manual_seed(4)
    T = random_se3((64,), generator=g, dtype=torch.float32, max_angle=3.0)
    assert T.dtype == torch.float32
    assert_close(se3_exp(se3_log(T)), T, atol=2e-6, rtol=0)
    xi = se3_log(T)
    assert xi.dtype == torch.float32
    assert_close(se3_log(se3_exp(xi)), xi, atol=2e-5, rtol=0)


def test_gradients_at_exact_identity_are_finite_and_correct() -> None:
    zero3 = torch.zeros(3, dtype=F64)
    zero6 = torch.zeros(6, dtype=F64)
    # d exp(w)/dw at 0 are the generators hat(e_i).
    jac = torch.autograd.functional.jacobian(so3_exp, zero3)
    for i in range(3):
        assert_close(jac[..., i], hat(torch.eye(3, dtype=F64)[i]))
    # log(exp(.)) is the identity map: its Jacobian at 0 is I.
    jac = torch.autograd.functional.jacobian(lambda w: so3_log(so3_exp(w)), zero3)
    assert_close(jac, torch.eye(3, dtype=F64))
    jac = torch.autograd.functional.jacobian(lambda xi: se3_log(se3_exp(xi)), zero6)
    assert_close(jac, torch.eye(6, dtype=F64))
    # Gradients of log taken directly w.r.t. the identity matrix are finite.
    T = torch.eye(4, dtype=F64, requires_grad=True)
    se3_log(T).sum().backward()
    assert torch.isfinite(T.grad).all()


@pytest.mark.parametrize("angle", [0.0, 1e-8, 9.99e-4, 1.001e-3, 0.5, 2.0, math.pi - 1e-2])
def test_gradcheck_exp_and_log(angle: float) -> None:
    g = torch.Generator().manual_seed(5)
    xi = _twists((2,), angle, g)
    assert gradcheck(se3_exp, [xi])
    assert gradcheck(so3_exp, [xi[..., 3:]])
    T = se3_exp(xi)
    # Perturb T only along the manifold: log(T exp(d)) as a function of d.
    assert gradcheck(lambda d: se3_log(T @ se3_exp(d)), [torch.zeros(2, 6, dtype=F64)])
    # Also w.r.t. the raw matrix entries (log reads both triangles of R).
    if angle > 1e-3:
        assert gradcheck(se3_log, [T])


def test_log_branches_are_continuous_across_pi_over_2() -> None:
    # cos(angle) changes sign at pi/2, where so3_log switches to the symmetric-part branch.
    a = torch.tensor([0.6, -0.8, 0.0], dtype=F64)
    w_lo = so3_log(so3_exp(a * (math.pi / 2 - 1e-12)))
    w_hi = so3_log(so3_exp(a * (math.pi / 2 + 1e-12)))
    assert (w_hi - w_lo).abs().max() < 1e-11


def test_compose_and_invert() -> None:
    g = torch.Generator().manual_seed(6)
    T = random_se3((3,), generator=g)
    assert_close(invert(T), torch.linalg.inv(T))
    assert_close(compose(T, invert(T)), torch.eye(4, dtype=F64).expand(3, 4, 4))
    # broadcasting of leading dims
    A = random_se3((2, 1), generator=g)
    assert compose(A, T).shape == (2, 3, 4, 4)
    assert_close(compose(A, T), A @ T)
    # T_ac applied to points equals applying T_bc then T_ab.
    p = random_points((5,), generator=g)
    assert_close(
        transform_points(compose(A[0, 0], T[0]), p),
        transform_points(A[0, 0], transform_points(T[0], p)),
    )


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_adjoint_conjugates_twists(shape: tuple[int, ...]) -> None:
    g = torch.Generator().manual_seed(7)
    T = random_se3(shape, generator=g)
    xi = _twists(shape, 0.7, g)
    lhs = T @ se3_exp(xi) @ invert(T)
    rhs = se3_exp((adjoint(T) @ xi[..., None])[..., 0])
    assert_close(lhs, rhs)
    T2 = random_se3(shape, generator=g)
    assert_close(adjoint(T @ T2), adjoint(T) @ adjoint(T2))


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_transform_points_matches_homogeneous_product(shape: tuple[int, ...]) -> None:
    g = torch.Generator().manual_seed(8)
    T = random_se3(shape, generator=g)
    p = random_points((*shape, 7), generator=g)
    homog = torch.cat((p, torch.ones_like(p[..., :1])), dim=-1)
    expected = (T @ homog.transpose(-1, -2)).transpose(-1, -2)[..., :3]
    assert_close(transform_points(T, p), expected)
    # One transform broadcast over a batch of point sets.
    p2 = random_points((4, 7), generator=g)
    T1 = random_se3((), generator=g)
    assert_close(transform_points(T1, p2)[2], transform_points(T1, p2[2]))


def test_tum_known_answer_and_scipy_agreement() -> None:
    s = math.sqrt(0.5)
    T = pose_from_translation_quaternion(
        torch.tensor([1.0, 2.0, 3.0], dtype=F64), torch.tensor([0.0, 0.0, s, s], dtype=F64)
    )
    expected_R = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    assert_close(T[:3, :3], expected_R, atol=1e-15, rtol=0)
    assert_close(T[:3, 3], torch.tensor([1.0, 2.0, 3.0], dtype=F64))
    assert_close(T[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64))
    g = torch.Generator().manual_seed(9)
    q = torch.randn(10, 4, generator=g, dtype=F64)
    R = pose_from_translation_quaternion(torch.zeros(10, 3, dtype=F64), q)[..., :3, :3]
    reference = torch.from_numpy(Rotation.from_quat(q.numpy()).as_matrix())  # scipy is xyzw
    assert_close(R, reference, atol=1e-14, rtol=0)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_tum_round_trip_with_canonical_sign(shape: tuple[int, ...]) -> None:
    g = torch.Generator().manual_seed(10)
    t = torch.randn(*shape, 3, generator=g, dtype=F64)
    q = torch.randn(*shape, 4, generator=g, dtype=F64)
    q = q / q.norm(dim=-1, keepdim=True)
    T = pose_from_translation_quaternion(t, 3.0 * q)  # non-unit input is normalised
    t2, q2 = translation_quaternion_from_pose(T)
    assert (q2[..., 3] >= 0).all()
    assert_close(q2.norm(dim=-1), torch.ones(shape, dtype=F64))
    sign = torch.where(q[..., 3:] < 0, -1.0, 1.0).to(F64)
    assert_close(q2, q * sign, atol=1e-12, rtol=0)
    assert_close(t2, t)
    assert_close(pose_from_translation_quaternion(t2, q2), T, atol=1e-12, rtol=0)
    # q and -q are the same rotation and give identical files.
    _, q3 = translation_quaternion_from_pose(pose_from_translation_quaternion(t, -q))
    assert_close(q3, q2, atol=1e-12, rtol=0)


def test_zero_norm_quaternion_raises() -> None:
    q = torch.tensor([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="zero norm"):
        pose_from_translation_quaternion(torch.zeros(2, 3), q)


def test_non_finite_tum_inputs_raise() -> None:
    with pytest.raises(ValueError, match="NaN"):
        pose_from_translation_quaternion(torch.zeros(3), torch.tensor([0.0, 0, float("nan"), 1]))
    with pytest.raises(ValueError, match="NaN"):
        pose_from_translation_quaternion(torch.tensor([0.0, float("inf"), 0]), torch.rand(4))


@pytest.mark.parametrize(
    ("fn", "bad"),
    [
        (hat, torch.zeros(4)),
        (vee, torch.zeros(3, 4)),
        (so3_exp, torch.zeros(2, 2)),
        (so3_log, torch.zeros(4, 4)),
        (cayley_rotation, torch.zeros(2)),
        (se3_exp, torch.zeros(5)),
        (se3_log, torch.zeros(3, 3)),
        (invert, torch.zeros(3, 4)),
        (adjoint, torch.zeros(4, 3)),
        (translation_quaternion_from_pose, torch.zeros(3, 3)),
    ],
)
def test_wrong_shapes_raise_shape_error(fn, bad: torch.Tensor) -> None:
    with pytest.raises(ShapeError):
        fn(bad)


def test_wrong_shapes_in_binary_functions_raise() -> None:
    with pytest.raises(ShapeError, match="T_bc"):
        compose(torch.eye(4), torch.eye(3))
    with pytest.raises(ShapeError, match="points_b"):
        transform_points(torch.eye(4), torch.zeros(5, 2))
    with pytest.raises(ShapeError, match="q_xyzw"):
        pose_from_translation_quaternion(torch.zeros(3), torch.zeros(3))
