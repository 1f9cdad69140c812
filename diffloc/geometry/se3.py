"""Batched SO(3) / SE(3) Lie-group operations in pure torch.

Conventions (see ``ARCHITECTURE.md``):

- ``T_ab`` is a ``(..., 4, 4)`` homogeneous transform mapping points in frame ``b`` to frame
  ``a``: ``p_a = R_ab p_b + t_ab``.
- A twist is ``xi = [v, w]`` of shape ``(..., 6)``: translation part ``v`` first, rotation
  part ``w`` (axis-angle, radians) last. ``se3_exp(xi) = [[exp(hat(w)), V(w) v], [0, 1]]``.
- ``cayley_rotation`` is the cheap retraction of the pose updates of the optimisers: an exact
  rotation that agrees with ``so3_exp`` to second order.
- All functions broadcast over any leading dimensions ``(...)``, work in float32 and float64
  and are differentiable, including at the identity (Taylor expansions, no NaN gradients) and
  at rotation angles close to pi (the log uses the symmetric part of ``R`` there).
"""

from __future__ import annotations

import functools

import torch
from pytorch_kinematics import transforms as pk_tf

from diffloc.checks import check_finite, check_shape

__all__ = [
    "adjoint",
    "cayley_rotation",
    "compose",
    "hat",
    "invert",
    "pose_from_translation_quaternion",
    "se3_exp",
    "se3_log",
    "so3_exp",
    "so3_log",
    "transform_points",
    "translation_quaternion_from_pose",
    "vee",
]


def _small_angle_sq(dtype: torch.dtype) -> float:
    """Squared angle below which Taylor expansions replace the closed forms.

    The Taylor series are truncated after the ``theta^4`` term, so their error is of order
    ``theta^6``: below the precision of the dtype at these thresholds.
    """
    return 1e-6 if dtype == torch.float64 else 1e-4


def hat(w: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrix of a 3-vector, ``hat(w) @ x == cross(w, x)``.

    Args:
        w: (..., 3) vectors.

    Returns:
        (..., 3, 3) skew-symmetric matrices.

    Example:
        >>> hat(torch.tensor([0.0, 0.0, 1.0]))[0, 1]
        tensor(-1.)
    """
    check_shape(w, "*,3", "w")
    x, y, z = w.unbind(-1)
    zero = torch.zeros_like(x)
    rows = (zero, -z, y, z, zero, -x, -y, x, zero)
    return torch.stack(rows, dim=-1).reshape(*w.shape[:-1], 3, 3)


def vee(W: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`hat`: the 3-vector of a skew-symmetric matrix.

    Only the lower triangle is read (``W[2,1], W[0,2], W[1,0]``).

    Args:
        W: (..., 3, 3) skew-symmetric matrices.

    Returns:
        (..., 3) vectors.

    Example:
        >>> vee(hat(torch.tensor([1.0, 2.0, 3.0])))
        tensor([1., 2., 3.])
    """
    check_shape(W, "*,3,3", "W")
    return torch.stack((W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]), dim=-1)


def _exp_coefficients(
    theta_sq: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``A = sin(t)/t``, ``B = (1-cos t)/t^2``, ``C = (t - sin t)/t^3`` from ``t^2``.

    Stable and with finite gradients for all ``t^2 >= 0``.
    """
    small = theta_sq < _small_angle_sq(theta_sq.dtype)
    t2 = theta_sq
    # Taylor branch (a polynomial in t^2: smooth at 0).
    a_taylor = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
    b_taylor = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
    c_taylor = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
    # Closed forms, evaluated on a safe input so that the unused branch has finite gradients.
    theta = torch.sqrt(torch.where(small, torch.ones_like(t2), t2))
    sin_t = torch.sin(theta)
    half_sinc = torch.sin(0.5 * theta) / (0.5 * theta)
    a_closed = sin_t / theta
    b_closed = 0.5 * half_sinc * half_sinc  # 2 sin^2(t/2) / t^2, no cancellation
    c_closed = (theta - sin_t) / (theta * theta * theta)
    return (
        torch.where(small, a_taylor, a_closed),
        torch.where(small, b_taylor, b_closed),
        torch.where(small, c_taylor, c_closed),
    )


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of an axis-angle vector (Rodrigues' formula).

    Args:
        w: (..., 3) axis-angle vectors (radians).

    Returns:
        (..., 3, 3) rotation matrices.

    Example:
        >>> R = so3_exp(torch.tensor([0.0, 0.0, torch.pi / 2]))
        >>> torch.allclose(R @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]),
        ...                atol=1e-6)
        True
    """
    check_shape(w, "*,3", "w")
    a, b, _ = _exp_coefficients((w * w).sum(-1))
    W = hat(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + a[..., None, None] * W + b[..., None, None] * (W @ W)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Axis-angle vector of a rotation matrix, angle in ``[0, pi]``.

    Three branches, all with finite gradients: a Taylor expansion near the identity, the
    usual ``vee(R - R^T)`` formula for moderate angles, and for angles above pi/2 an axis
    read from the symmetric part ``(R + R^T)/2 = cos(t) I + (1 - cos t) a a^T``, which stays
    accurate up to and including ``t = pi`` (where the sign of the axis is arbitrary).

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) axis-angle vectors ``w`` with ``so3_exp(w) == R``.

    Example:
        >>> so3_log(so3_exp(torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)))
        tensor([ 0.1000, -0.2000,  0.3000], dtype=torch.float64)
    """
    check_shape(R, "*,3,3", "R")
    s = 0.5 * vee(R - R.transpose(-1, -2))  # sin(t) * axis
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    c = 0.5 * (trace - 1.0)  # cos(t)
    n2 = (s * s).sum(-1)  # sin(t)^2
    one = torch.ones_like(n2)

    near_zero = (n2 < _small_angle_sq(R.dtype)) & (c > 0.0)
    near_pi = c < 0.0

    # Near zero: t / sin(t) = asin(n)/n = 1 + n^2/6 + 3 n^4/40 + O(n^6).
    w_small = s * (1.0 + n2 / 6.0 + 0.075 * n2 * n2)[..., None]

    # Moderate angles: t = atan2(sin t, cos t), w = s * t / sin t.
    n_reg = torch.sqrt(torch.where(near_zero | near_pi, one, n2))
    c_reg = torch.where(near_zero | near_pi, one, c)
    w_reg = s * (torch.atan2(n_reg, c_reg) / n_reg)[..., None]

    # Near pi: axis from the symmetric part, the column with the largest diagonal entry.
    c_pi = torch.where(near_pi, c, -one)
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    aat = (0.5 * (R + R.transpose(-1, -2)) - c_pi[..., None, None] * eye) / (
        1.0 - c_pi[..., None, None]
    )
    diag = torch.diagonal(aat, dim1=-2, dim2=-1)
    k = diag.argmax(dim=-1, keepdim=True)  # (..., 1)
    col = torch.take_along_dim(aat, k[..., None, :], dim=-1)[..., 0]  # (..., 3) = a * a_k
    a_k2 = torch.take_along_dim(diag, k, dim=-1)[..., 0]  # a_k^2 >= 1/3 when selected
    axis = col / torch.sqrt(torch.where(near_pi, a_k2, one))[..., None]
    sign = torch.where((axis * s).sum(-1) < 0.0, -one, one)
    has_sin = n2 > 0.0
    n_pi = torch.where(has_sin, torch.sqrt(torch.where(has_sin, n2, one)), torch.zeros_like(n2))
    theta_pi = torch.atan2(n_pi, c_pi)
    w_pi = axis * (sign * theta_pi)[..., None]

    out = torch.where(near_pi[..., None], w_pi, w_reg)
    return torch.where(near_zero[..., None], w_small, out)


@functools.lru_cache(maxsize=8)
def _cayley_coefficients(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(16, 10) map from the outer product ``q q^T`` (flattened) of ``q = (s, x, y, z)`` to
    the nine entries of ``|q|^2 R(q)`` (row-major) and ``|q|^2``. Never modified in place."""
    terms = (
        ((0, 0, 1), (1, 1, 1), (2, 2, -1), (3, 3, -1)),  # R00 = ss + xx - yy - zz
        ((1, 2, 2), (0, 3, -2)),  # R01 = 2 (xy - sz)
        ((1, 3, 2), (0, 2, 2)),  # R02 = 2 (xz + sy)
        ((1, 2, 2), (0, 3, 2)),  # R10 = 2 (xy + sz)
        ((0, 0, 1), (1, 1, -1), (2, 2, 1), (3, 3, -1)),  # R11
        ((2, 3, 2), (0, 1, -2)),  # R12 = 2 (yz - sx)
        ((1, 3, 2), (0, 2, -2)),  # R20 = 2 (xz - sy)
        ((2, 3, 2), (0, 1, 2)),  # R21 = 2 (yz + sx)
        ((0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, 1)),  # R22
        ((0, 0, 1), (1, 1, 1), (2, 2, 1), (3, 3, 1)),  # |q|^2
    )
    with torch.inference_mode(False):  # an ordinary tensor even if first made in one
        coefficients = torch.zeros(16, len(terms), dtype=dtype, device=device)
        for column, entries in enumerate(terms):
            for a, b, value in entries:
                coefficients[4 * a + b, column] = value
    return coefficients


def cayley_rotation(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of the Cayley map, a cheap retraction onto SO(3).

    ``Cay(w) = ((1 - |c|^2) I + 2 hat(c) + 2 c c^T) / (1 + |c|^2)`` with ``c = w / 2`` is the
    rotation of the quaternion ``(1, c)``: an exact rotation that agrees with
    ``so3_exp(w)`` up to second order (angle ``2 atan(|w| / 2)`` about ``w``), computed with
    a handful of tensor operations (one outer product and one small matrix product).

    Args:
        w: (..., 3) rotation vectors (radians).

    Returns:
        (..., 3, 3) rotation matrices.

    Example:
        >>> R = cayley_rotation(torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64))
        >>> torch.allclose(R @ R.mT, torch.eye(3, dtype=torch.float64))
        True
        >>> round(float(torch.atan2(R[1, 0], R[0, 0])), 4)  # 2 atan(0.25), not 0.5
        0.49
    """
    if not isinstance(w, torch.Tensor) or w.shape[-1:] != (3,):  # checked only if wrong
        check_shape(w, "*,3", "w")
    q = torch.nn.functional.pad(w, (1, 0), value=2.0)  # 2 (1, w / 2): the scale cancels
    outer = (q[..., :, None] * q[..., None, :]).flatten(-2)
    m = outer @ _cayley_coefficients(w.dtype, w.device)
    return (m[..., :9] / m[..., 9:]).unflatten(-1, (3, 3))


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Exponential map from a twist ``xi = [v, w]`` to a homogeneous transform.

    Args:
        xi: (..., 6) twists, translation part ``v`` first, rotation part ``w`` last.

    Returns:
        (..., 4, 4) transforms ``[[exp(hat(w)), V v], [0, 1]]`` with
        ``V = I + B hat(w) + C hat(w)^2``.

    Example:
        >>> T = se3_exp(torch.tensor([1.0, 2.0, 3.0, 0.0, 0.0, 0.0]))
        >>> T[:3, 3]
        tensor([1., 2., 3.])
    """
    check_shape(xi, "*,6", "xi")
    v, w = xi[..., :3], xi[..., 3:]
    a, b, c = _exp_coefficients((w * w).sum(-1))
    W = hat(w)
    W2 = W @ W
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    R = eye + a[..., None, None] * W + b[..., None, None] * W2
    V = eye + b[..., None, None] * W + c[..., None, None] * W2
    t = (V @ v[..., None])[..., 0]
    return _assemble(R, t)


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """Logarithm of a homogeneous transform, the inverse of :func:`se3_exp`.

    Args:
        T: (..., 4, 4) rigid transforms (rotation angle in ``[0, pi]`` is returned).

    Returns:
        (..., 6) twists ``[v, w]``.

    Example:
        >>> xi = torch.tensor([0.1, 0.2, 0.3, 0.4, 0.5, 0.6], dtype=torch.float64)
        >>> torch.allclose(se3_log(se3_exp(xi)), xi)
        True
    """
    check_shape(T, "*,4,4", "T")
    R, t = T[..., :3, :3], T[..., :3, 3]
    w = so3_log(R)
    t2 = (w * w).sum(-1)
    small = t2 < _small_angle_sq(T.dtype)
    # V^-1 = I - W/2 + D W^2 with D = 1/t^2 - cot(t/2) / (2 t).
    d_taylor = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    t2_safe = torch.where(small, torch.ones_like(t2), t2)
    theta = torch.sqrt(t2_safe)
    half = 0.5 * theta
    d_closed = 1.0 / t2_safe - torch.cos(half) / (torch.sin(half) * 2.0 * theta)
    d = torch.where(small, d_taylor, d_closed)
    W = hat(w)
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    V_inv = eye - 0.5 * W + d[..., None, None] * (W @ W)
    v = (V_inv @ t[..., None])[..., 0]
    return torch.cat((v, w), dim=-1)


def _assemble(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) transform from a rotation (..., 3, 3) and a translation (..., 3)."""
    batch = torch.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    top = torch.cat((R.expand(*batch, 3, 3), t.expand(*batch, 3)[..., None]), dim=-1)
    bottom = torch.zeros(*batch, 1, 4, dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat((top, bottom), dim=-2)


def compose(T_ab: torch.Tensor, T_bc: torch.Tensor) -> torch.Tensor:
    """Chain two transforms: ``T_ac = T_ab @ T_bc`` (leading dimensions broadcast).

    Args:
        T_ab: (..., 4, 4) transform from frame b to frame a.
        T_bc: (..., 4, 4) transform from frame c to frame b.

    Returns:
        (..., 4, 4) transform from frame c to frame a.

    Example:
        >>> T = se3_exp(torch.tensor([1.0, 0.0, 0.0, 0.0, 0.0, 0.5]))
        >>> torch.allclose(compose(T, invert(T)), torch.eye(4), atol=1e-6)
        True
    """
    check_shape(T_ab, "*,4,4", "T_ab")
    check_shape(T_bc, "*,4,4", "T_bc")
    return T_ab @ T_bc


def invert(T: torch.Tensor) -> torch.Tensor:
    """Closed-form inverse of a rigid transform: ``[[R^T, -R^T t], [0, 1]]``.

    Args:
        T: (..., 4, 4) transform ``T_ab``.

    Returns:
        (..., 4, 4) transform ``T_ba``.

    Example:
        >>> invert(se3_exp(torch.tensor([1.0, 2.0, 3.0, 0.0, 0.0, 0.0])))[:3, 3]
        tensor([-1., -2., -3.])
    """
    check_shape(T, "*,4,4", "T")
    R_t = T[..., :3, :3].transpose(-1, -2)
    t = T[..., :3, 3]
    return _assemble(R_t, -(R_t @ t[..., None])[..., 0])


def adjoint(T: torch.Tensor) -> torch.Tensor:
    """Adjoint matrix of a transform for twists ordered ``[v, w]``.

    ``Ad_T = [[R, hat(t) R], [0, R]]``, so that ``T @ se3_exp(xi) @ invert(T) ==
    se3_exp(Ad_T @ xi)``.

    Args:
        T: (..., 4, 4) transforms.

    Returns:
        (..., 6, 6) adjoint matrices.

    Example:
        >>> adjoint(torch.eye(4)).shape
        torch.Size([6, 6])
    """
    check_shape(T, "*,4,4", "T")
    R = T[..., :3, :3]
    tR = hat(T[..., :3, 3]) @ R
    top = torch.cat((R, tR), dim=-1)
    bottom = torch.cat((torch.zeros_like(R), R), dim=-1)
    return torch.cat((top, bottom), dim=-2)


def transform_points(T_ab: torch.Tensor, points_b: torch.Tensor) -> torch.Tensor:
    """Map points from frame b to frame a: ``p_a = R_ab p_b + t_ab``.

    Args:
        T_ab: (..., 4, 4) transforms; leading dimensions broadcast with those of ``points_b``.
        points_b: (..., N, 3) points in frame b.

    Returns:
        (..., N, 3) points in frame a.

    Example:
        >>> T = se3_exp(torch.tensor([1.0, 0.0, 0.0, 0.0, 0.0, 0.0]))
        >>> transform_points(T, torch.zeros(1, 3))
        tensor([[1., 0., 0.]])
    """
    check_shape(T_ab, "*,4,4", "T_ab")
    check_shape(points_b, "*,N,3", "points_b")
    R = T_ab[..., :3, :3]
    t = T_ab[..., None, :3, 3]
    return points_b @ R.transpose(-1, -2) + t


def pose_from_translation_quaternion(t: torch.Tensor, q_xyzw: torch.Tensor) -> torch.Tensor:
    """Transform from a translation and a quaternion in TUM order ``(qx, qy, qz, qw)``.

    The quaternion is normalised first. Rotation conversion is pytorch_kinematics'
    ``quaternion_to_matrix`` (which takes ``wxyz``).

    Args:
        t: (..., 3) translations (metres).
        q_xyzw: (..., 4) quaternions, scalar last, any non-zero norm.

    Returns:
        (..., 4, 4) transforms (leading dimensions of ``t`` and ``q_xyzw`` broadcast).

    Raises:
        ShapeError: wrong shapes.
        ValueError: non-finite inputs or a quaternion of (near) zero norm.

    Example:
        >>> T = pose_from_translation_quaternion(torch.zeros(3), torch.tensor([0.0, 0, 0, 2]))
        >>> torch.equal(T, torch.eye(4))
        True
    """
    check_shape(t, "*,3", "t")
    check_shape(q_xyzw, "*,4", "q_xyzw")
    check_finite(t, "t")
    check_finite(q_xyzw, "q_xyzw")
    norm = torch.linalg.vector_norm(q_xyzw, dim=-1, keepdim=True)
    if bool((norm <= torch.finfo(q_xyzw.dtype).tiny ** 0.5).any()):
        raise ValueError("q_xyzw has a quaternion of zero norm; it cannot be normalised")
    q_wxyz = pk_tf.xyzw_to_wxyz(q_xyzw / norm)
    R = pk_tf.quaternion_to_matrix(q_wxyz)
    return _assemble(R, t.to(R.dtype))


def translation_quaternion_from_pose(T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Translation and unit quaternion ``(qx, qy, qz, qw)`` of a transform, with ``qw >= 0``.

    The sign is canonical (``qw >= 0``) so that written trajectory files are reproducible.
    Rotation conversion is pytorch_kinematics' ``matrix_to_quaternion``.

    Args:
        T: (..., 4, 4) rigid transforms.

    Returns:
        ``(t, q_xyzw)``: (..., 3) translations and (..., 4) unit quaternions.

    Example:
        >>> t, q = translation_quaternion_from_pose(torch.eye(4))
        >>> q
        tensor([0., 0., 0., 1.])
    """
    check_shape(T, "*,4,4", "T")
    q_wxyz = pk_tf.standardize_quaternion(pk_tf.matrix_to_quaternion(T[..., :3, :3]))
    q_wxyz = q_wxyz / torch.linalg.vector_norm(q_wxyz, dim=-1, keepdim=True)
    return T[..., :3, 3], pk_tf.wxyz_to_xyzw(q_wxyz)
