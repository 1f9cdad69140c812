"""Surfel reprojection constraints between keyframes (seed 1 Sec. III-B, Eq. 1-4).

A map point observed at keypoint ``p_a`` of keyframe ``alpha`` is anchored to a surfel with
centre ``x_S`` and unit normal ``n_S``, i.e. to the plane ``n_S^T x + d_S = 0`` with
``d_S = -n_S^T x_S``. Lifting the keypoint onto that plane (Eq. 1) gives::

    x_W = R_a * m_a / rho_a + t_a,    m_a = ((u - cx) / fx, (v - cy) / fy, 1)   (unit plane)
    rho_a = -(n_S^T R_a m_a) / (n_S^T t_a + d_S)                                  (Eq. 2)

with ``T_wc = [R_a | t_a]`` the camera-to-world pose of ``alpha`` and ``rho_a`` the inverse
depth (``z``, not range) of the point in ``alpha``. The residual of a second observer
``beta`` with keypoint ``p_b`` is the reprojection error (Eq. 3), whitened by the keypoint's
standard deviation ``sigma`` (pixels)::

    e = (project(R_b^T (x_W - t_b)) - p_b) / sigma

Eq. 4 sums ``||e||^2`` over every surfel and every pair ``(alpha, beta)`` where ``alpha`` is
the first keyframe observing the map point and ``beta`` any other observer. ``x_W`` is a
function of the pose of ``alpha``, so the only variables are keyframe poses, optimised by
:func:`diffloc.optim.lm.levenberg_marquardt` with the analytic Jacobians of
:meth:`SurfelReprojectionCost.linearize` (tested against forward-mode autodiff). Afterwards
every map point is re-placed by Eq. 1 from its first observer (:func:`replace_map_points`).

Degenerate lifts (a ray parallel to the plane, the plane behind the camera, or the camera on
the plane) and points behind ``beta`` are reported as invalid; their outputs are finite
(never NaN) and their residuals zero.

Example:
    >>> kp = torch.tensor([[319.5, 239.5]], dtype=torch.float64)
    >>> f, cx, cy = (torch.tensor([v], dtype=torch.float64) for v in (500.0, 319.5, 239.5))
    >>> centers = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64)
    >>> normals = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
    >>> T = torch.eye(4, dtype=torch.float64)[None]
    >>> lift_to_surfel(kp, T, f, f, cx, cy, centers, normals)[0]
    tensor([[0., 0., 2.]], dtype=torch.float64)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from dataclasses import fields as dataclass_fields
from typing import NamedTuple

import torch
from torch import nn

from diffloc.checks import ShapeError, check_finite, check_shape
from diffloc.database.database import VisualDatabase
from diffloc.geometry.camera import MIN_DEPTH
from diffloc.optim.lm import BlockLinearization, LMConfig, LMResult, levenberg_marquardt
from diffloc.optim.motion_cost import CHI2_2DOF_95
from diffloc.optim.robust import RobustKernel

__all__ = [
    "SurfelOptimConfig",
    "SurfelPairs",
    "SurfelReprojectionCost",
    "first_observers",
    "lift_to_surfel",
    "optimize_keyframe_poses",
    "pairs_from_database",
    "replace_map_points",
    "surfel_inverse_depth",
]

MIN_COS = 1e-9
"""Smallest ``|cos|`` of the angle between a ray and a surfel normal for a valid lift."""


def _pair_count(name: str, x: torch.Tensor, spec: str) -> int:
    """Check ``x`` against ``spec`` (e.g. ``"*,M,3"``) and return its pair count ``M``."""
    check_shape(x, spec, name)
    trailing = len(spec.split(",")) - spec.split(",").index("M")
    return x.shape[-trailing]


def _check_same_count(**counts: int) -> int:
    values = set(counts.values())
    if len(values) != 1:
        raise ShapeError(f"inputs must hold the same number of pairs M, got {counts}")
    return values.pop()


def surfel_inverse_depth(
    rays_cam: torch.Tensor, T_wc: torch.Tensor, centers: torch.Tensor, normals: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse depth of rays hitting surfel planes (seed 1 Eq. 2).

    ``rho = -(n^T R m) / (n^T t + d)`` with ``d = -n^T x_S``: the plane point on the ray
    ``t + s R m`` has ``s = 1 / rho`` (its ``z`` in the camera when ``m_z = 1``).

    Args:
        rays_cam: (..., M, 3) rays ``m`` in the camera frame (on the unit plane ``z = 1``).
        T_wc: (..., M, 4, 4) camera-to-world poses.
        centers: (..., M, 3) surfel centres ``x_S``, world frame.
        normals: (..., M, 3) surfel normals ``n_S`` (any length), world frame.

    Returns:
        ``(rho, valid)``: (..., M) inverse depths (1 where invalid) and (..., M) bool, true
        where the plane is hit in front of the camera (``0 < 1 / rho < inf``, the ray not
        within ``MIN_COS`` of parallel to the plane).

    Example:
        >>> m = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
        >>> n = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
        >>> surfel_inverse_depth(m, torch.eye(4, dtype=torch.float64)[None], -4 * n, n)[0]
        tensor([0.2500], dtype=torch.float64)
    """
    rho, valid, _, _ = _inverse_depth_terms(rays_cam, T_wc, centers, normals)
    return rho, valid


def _inverse_depth_terms(
    rays_cam: torch.Tensor, T_wc: torch.Tensor, centers: torch.Tensor, normals: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`surfel_inverse_depth` plus its intermediates ``R m`` (..., M, 3) and
    ``n^T R m`` (..., M), shared with :func:`lift_to_surfel`."""
    rays_world = (T_wc[..., :3, :3] @ rays_cam[..., None])[..., 0]
    n_dot_ray = (normals * rays_world).sum(-1)
    distance = (normals * (T_wc[..., :3, 3] - centers)).sum(-1)  # n^T t + d
    scale = torch.linalg.vector_norm(normals, dim=-1) * torch.linalg.vector_norm(rays_cam, dim=-1)
    hits = (n_dot_ray.abs() > MIN_COS * scale) & (distance != 0)
    rho = -n_dot_ray / torch.where(hits, distance, 1.0)
    valid = hits & (rho > 0) & (rho < 1.0 / MIN_DEPTH)
    return torch.where(valid, rho, 1.0), valid, rays_world, n_dot_ray


def lift_to_surfel(
    keypoints: torch.Tensor,
    T_wc: torch.Tensor,
    fx: torch.Tensor,
    fy: torch.Tensor,
    cx: torch.Tensor,
    cy: torch.Tensor,
    centers: torch.Tensor,
    normals: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Lift keypoints onto their surfel planes (seed 1 Eq. 1 with the inverse depth of Eq. 2).

    ``x_W = R m / rho + t``, ``m = ((u - cx) / fx, (v - cy) / fy, 1)``: the intersection of
    the keypoint's viewing ray with the plane through ``centers`` orthogonal to ``normals``.
    Differentiable in every floating input; leading dimensions ``(...)`` broadcast.

    Args:
        keypoints: (..., M, 2) pixel coordinates ``(u, v)`` (ideal pinhole).
        T_wc: (..., M, 4, 4) camera-to-world poses of the observing cameras.
        fx: (..., M) focal lengths along u, pixels.
        fy: (..., M) focal lengths along v.
        cx: (..., M) principal points u.
        cy: (..., M) principal points v.
        centers: (..., M, 3) surfel centres, world frame.
        normals: (..., M, 3) surfel normals, world frame (any non-zero length).

    Returns:
        ``(points_world, valid)``: (..., M, 3) plane points and (..., M) bool, false where the
        ray misses the plane in front of the camera (see :func:`surfel_inverse_depth`);
        ``points_world`` is then finite but meaningless (the point at depth 1).

    Raises:
        ShapeError: shapes that do not match or do not hold the same number of pairs.

    Example:
        >>> one = torch.ones(1, dtype=torch.float64)
        >>> kp = torch.tensor([[1.0, 0.0]], dtype=torch.float64)  # x = 1 on the unit plane
        >>> n = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
        >>> T = torch.eye(4, dtype=torch.float64)[None]
        >>> lift_to_surfel(kp, T, one, one, 0 * one, 0 * one, -3 * n, n)[0]
        tensor([[3., 0., 3.]], dtype=torch.float64)
    """
    _check_same_count(
        keypoints=_pair_count("keypoints", keypoints, "*,M,2"),
        T_wc=_pair_count("T_wc", T_wc, "*,M,4,4"),
        fx=_pair_count("fx", fx, "*,M"),
        fy=_pair_count("fy", fy, "*,M"),
        cx=_pair_count("cx", cx, "*,M"),
        cy=_pair_count("cy", cy, "*,M"),
        centers=_pair_count("centers", centers, "*,M,3"),
        normals=_pair_count("normals", normals, "*,M,3"),
    )
    x = (keypoints[..., 0] - cx) / fx
    y = (keypoints[..., 1] - cy) / fy
    rays_cam = torch.stack((x, y, torch.ones_like(x)), dim=-1)
    rho, valid, rays_world, _ = _inverse_depth_terms(rays_cam, T_wc, centers, normals)
    return rays_world / rho[..., None] + T_wc[..., :3, 3], valid


@dataclass
class SurfelPairs:
    """Observation pairs ``(alpha, beta)`` of map points anchored to surfels (Eq. 4 terms).

    Attributes:
        points: (M,) int64 map point of each pair.
        alpha: (M,) int64 first keyframe observing the point.
        beta: (M,) int64 another keyframe observing it.
        keypoints_alpha: (M, 2) float64 keypoint of the point in ``alpha``, pixels.
        keypoints_beta: (M, 2) float64 keypoint in ``beta``.
        centers: (M, 3) float64 centre of the point's surfel, world frame.
        normals: (M, 3) float64 normal of the point's surfel.
        intrinsics_alpha: (M, 4) float64 ``fx, fy, cx, cy`` of ``alpha``.
        intrinsics_beta: (M, 4) float64 ``fx, fy, cx, cy`` of ``beta``.
    """

    points: torch.Tensor
    alpha: torch.Tensor
    beta: torch.Tensor
    keypoints_alpha: torch.Tensor
    keypoints_beta: torch.Tensor
    centers: torch.Tensor
    normals: torch.Tensor
    intrinsics_alpha: torch.Tensor
    intrinsics_beta: torch.Tensor

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def select(self, keep: torch.Tensor) -> SurfelPairs:
        """The pairs where ``keep`` (an (M,) bool mask or an index tensor) holds."""
        kept = {f.name: getattr(self, f.name)[keep] for f in dataclass_fields(self)}
        return SurfelPairs(**kept)


class SurfelReprojectionCost(nn.Module):
    """Whitened surfel reprojection residuals (seed 1 Eq. 3) of ``M`` keyframe pairs.

    The per-pair data are buffers (``module.to()`` moves them); the poses are the inputs.

    Args:
        keypoints_alpha: (M, 2) keypoints in the first observer ``alpha``, pixels.
        keypoints_beta: (M, 2) keypoints of the same map points in ``beta``.
        centers: (M, 3) surfel centres, world frame.
        normals: (M, 3) surfel normals, world frame.
        intrinsics_alpha: (M, 4) ``fx, fy, cx, cy`` of ``alpha``.
        intrinsics_beta: (M, 4) ``fx, fy, cx, cy`` of ``beta``.
        sigma: (M,) keypoint standard deviations in ``beta``, pixels (positive); default 1.

    Raises:
        ShapeError: shapes that do not match or hold different numbers of pairs.
        ValueError: non-finite inputs or non-positive sigmas.

    Example:
        >>> K = torch.tensor([[500.0, 500.0, 319.5, 239.5]], dtype=torch.float64)
        >>> kp = torch.tensor([[319.5, 239.5]], dtype=torch.float64)
        >>> n = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
        >>> cost = SurfelReprojectionCost(kp, kp + 1.0, -2 * n, n, K, K)
        >>> T = torch.eye(4, dtype=torch.float64)[None]
        >>> cost(T, T)
        tensor([[-1., -1.]], dtype=torch.float64)
    """

    keypoints_alpha: torch.Tensor
    keypoints_beta: torch.Tensor
    centers: torch.Tensor
    normals: torch.Tensor
    intrinsics_alpha: torch.Tensor
    intrinsics_beta: torch.Tensor
    sigma: torch.Tensor
    columns: torch.Tensor  # (16, M) the same data, component-major (derived, not saved)

    def __init__(
        self,
        keypoints_alpha: torch.Tensor,
        keypoints_beta: torch.Tensor,
        centers: torch.Tensor,
        normals: torch.Tensor,
        intrinsics_alpha: torch.Tensor,
        intrinsics_beta: torch.Tensor,
        sigma: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        inputs = {
            "keypoints_alpha": (keypoints_alpha, "M,2"),
            "keypoints_beta": (keypoints_beta, "M,2"),
            "centers": (centers, "M,3"),
            "normals": (normals, "M,3"),
            "intrinsics_alpha": (intrinsics_alpha, "M,4"),
            "intrinsics_beta": (intrinsics_beta, "M,4"),
        }
        if sigma is None:
            sigma = torch.ones_like(keypoints_alpha[..., 0])
        inputs["sigma"] = (sigma, "M")
        _check_same_count(**{k: _pair_count(k, x, s) for k, (x, s) in inputs.items()})
        for name, (x, _) in inputs.items():
            check_finite(x, name)
            self.register_buffer(name, x)
        if not bool((sigma > 0).all()):
            raise ValueError("sigma must be positive")
        columns = _component_columns(*(x for x, _ in inputs.values()))
        self.register_buffer("columns", columns, persistent=False)

    @classmethod
    def from_pairs(
        cls, pairs: SurfelPairs, sigma: torch.Tensor | None = None
    ) -> SurfelReprojectionCost:
        """The cost of :class:`SurfelPairs` (e.g. from :func:`pairs_from_database`).

        Args:
            pairs: the ``M`` pairs.
            sigma: (M,) keypoint standard deviations in pixels; default 1.

        Returns:
            A :class:`SurfelReprojectionCost`.
        """
        return cls(
            pairs.keypoints_alpha,
            pairs.keypoints_beta,
            pairs.centers,
            pairs.normals,
            pairs.intrinsics_alpha,
            pairs.intrinsics_beta,
            sigma,
        )

    def residuals_and_valid(
        self, T_alpha: torch.Tensor, T_beta: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Whitened residuals and their validity.

        Args:
            T_alpha: (..., M, 4, 4) camera-to-world poses of the first observers.
            T_beta: (..., M, 4, 4) camera-to-world poses of the other observers.

        Returns:
            ``(residuals, valid)``: (..., M, 2), zero where invalid, and (..., M) bool, true
            where the lift in ``alpha`` is valid and the point is in front of ``beta``.
        """
        self._check_poses(T_alpha, T_beta)
        # Component-major, as linearize (several times faster than on (..., M, 3) rows).
        (res_u, res_v), valid, _ = _residual_components(
            _pose_components(T_alpha), _pose_components(T_beta), self._pair_columns()
        )
        residuals = torch.where(valid, torch.stack((res_u, res_v)), 0.0)
        return residuals.movedim(0, -1), valid

    def forward(self, T_alpha: torch.Tensor, T_beta: torch.Tensor) -> torch.Tensor:
        """Whitened residuals ``(project(T_beta^-1 x_W(T_alpha)) - p_beta) / sigma``.

        Args:
            T_alpha: (..., M, 4, 4) camera-to-world poses of the first observers.
            T_beta: (..., M, 4, 4) camera-to-world poses of the other observers.

        Returns:
            (..., M, 2) residuals, zero for invalid pairs (see :meth:`residuals_and_valid`).
        """
        return self.residuals_and_valid(T_alpha, T_beta)[0]

    def linearize(self, T_alpha: torch.Tensor, T_beta: torch.Tensor) -> BlockLinearization:
        """Whitened residuals and their analytic Jacobians w.r.t. both poses.

        The Jacobians follow :mod:`diffloc.optim.lm`'s convention: derivatives w.r.t. right
        perturbations ``T <- T @ se3_exp([v, w])`` (translation ``v`` first, both in the
        camera frame). With ``m`` the keypoint ray of ``alpha``, ``s = 1 / rho`` its depth,
        ``p_a = s m`` and ``p_b = R_b^T (x_W - t_b)`` the point in both cameras and
        ``J_p = d r / d p_b`` (2x3, the pinhole derivative over ``sigma``)::

            J_beta  = J_p [-I, hat(p_b)]
            J_alpha = J_p R_b^T P R_a [I, -hat(p_a)],   P = I - (R_a m) n^T / (n^T R_a m)

        ``P`` projects along the viewing ray onto the surfel plane: moving ``alpha`` moves the
        lifted point only within the plane. Invalid pairs get zero residuals and Jacobians.

        Args:
            T_alpha: (..., M, 4, 4) camera-to-world poses of the first observers.
            T_beta: (..., M, 4, 4) camera-to-world poses of the other observers.

        Returns:
            :class:`~diffloc.optim.lm.BlockLinearization` with ``residuals`` (..., M, 2) (as
            :meth:`forward`) and ``jac_a`` / ``jac_b`` (..., M, 2, 6) w.r.t. the tangents
            ``[v, w]`` of ``T_alpha`` / ``T_beta``.

        Raises:
            ShapeError: poses of the wrong shape or pair count.

        Example:
            >>> K = torch.tensor([[500.0, 500.0, 319.5, 239.5]], dtype=torch.float64)
            >>> kp = torch.tensor([[319.5, 239.5]], dtype=torch.float64)
            >>> n = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
            >>> cost = SurfelReprojectionCost(kp, kp, -2 * n, n, K, K)
            >>> T = torch.eye(4, dtype=torch.float64)[None]
            >>> lin = cost.linearize(T, T)  # the point is 2 m in front of both cameras
            >>> lin.jac_b[0, 0, 0]  # moving beta right by 1 m moves u left by f / z pixels
            tensor(-250., dtype=torch.float64)
            >>> lin.jac_a[0, 0, 0]  # moving alpha moves the lifted point along with it
            tensor(250., dtype=torch.float64)
        """
        self._check_poses(T_alpha, T_beta)
        # Component-major layout: every quantity is a (..., M) tensor with the pairs innermost,
        # where torch's element-wise kernels run several times faster than on (..., M, 3)
        # rows; the outputs are permuted views of one (26, ..., M) tensor.
        rows, valid = _linearize_components(
            _pose_components(T_alpha), _pose_components(T_beta), self._pair_columns()
        )
        out = torch.stack(rows).masked_fill_(~valid, 0.0)  # zero the invalid pairs in place
        out = out.movedim(0, -1).unflatten(-1, (2, 13))  # (..., M, 2, 13)
        return BlockLinearization(residuals=out[..., 0], jac_a=out[..., 1:7], jac_b=out[..., 7:13])

    def _check_poses(self, T_alpha: torch.Tensor, T_beta: torch.Tensor) -> None:
        """Raise :class:`ShapeError` unless both are (..., M, 4, 4) with this cost's ``M``."""
        _check_same_count(
            pairs=self.sigma.shape[0],
            T_alpha=_pair_count("T_alpha", T_alpha, "*,M,4,4"),
            T_beta=_pair_count("T_beta", T_beta, "*,M,4,4"),
        )

    def _pair_columns(self) -> _PairColumns:
        """The per-pair data, component-major: views of the ``columns`` buffer."""
        c = self.columns.unbind(0)
        return _PairColumns(c[0], c[1], c[2], c[3:6], c[6:9], c[9:11], c[11:15], c[15])


def _component_columns(
    keypoints_alpha: torch.Tensor,
    keypoints_beta: torch.Tensor,
    centers: torch.Tensor,
    normals: torch.Tensor,
    intrinsics_alpha: torch.Tensor,
    intrinsics_beta: torch.Tensor,
    sigma: torch.Tensor,
) -> torch.Tensor:
    """(16, M) per-pair data in the order of :class:`_PairColumns` (inputs as the cost's)."""
    fx, fy, cx, cy = intrinsics_alpha.T
    ray_x = (keypoints_alpha[:, 0] - cx) / fx  # as lift_to_surfel
    ray_y = (keypoints_alpha[:, 1] - cy) / fy
    rays_cam = torch.stack((ray_x, ray_y, torch.ones_like(ray_x)), dim=-1)
    scale = torch.linalg.vector_norm(normals, dim=-1) * torch.linalg.vector_norm(rays_cam, dim=-1)
    min_n_dot_ray = MIN_COS * scale  # as _inverse_depth_terms
    return torch.cat(
        (
            torch.stack((ray_x, ray_y, min_n_dot_ray)),
            centers.T,
            normals.T,
            keypoints_beta.T,
            intrinsics_beta.T,
            sigma[None],
        )
    )


class _PairColumns(NamedTuple):
    """Per-pair data of :class:`SurfelReprojectionCost` as (M,) components."""

    ray_x: torch.Tensor  # keypoint ray m = (ray_x, ray_y, 1) of alpha
    ray_y: torch.Tensor
    min_n_dot_ray: torch.Tensor  # MIN_COS |n| |m|: smaller |n . R_a m| is a parallel ray
    centers: tuple[torch.Tensor, ...]  # x, y, z
    normals: tuple[torch.Tensor, ...]  # x, y, z
    keypoints_beta: tuple[torch.Tensor, ...]  # u, v
    intrinsics_beta: tuple[torch.Tensor, ...]  # fx, fy, cx, cy
    sigma: torch.Tensor


def _pose_components(T_wc: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The 12 (..., M) components of the top 3x4 blocks of (..., M, 4, 4) poses, row-major."""
    return T_wc[..., :3, :].flatten(-2).movedim(-1, 0).contiguous().unbind(0)


class _Intermediates(NamedTuple):
    """Quantities of the residual pass that the Jacobians reuse, as (..., M) components."""

    ray: list[torch.Tensor]  # R_a m, world frame
    n_dot_ray: torch.Tensor  # n . R_a m, 1 where the lift is invalid
    depth: torch.Tensor  # 1 / rho, depth of the point in alpha
    z: torch.Tensor  # depth of the point in beta, 1 where behind
    x: torch.Tensor  # normalised image coordinates of the point in beta
    y: torch.Tensor


def _residual_components(
    pose_a: Sequence[torch.Tensor], pose_b: Sequence[torch.Tensor], pairs: _PairColumns
) -> tuple[tuple[torch.Tensor, torch.Tensor], torch.Tensor, _Intermediates]:
    """Whitened residuals of :class:`SurfelReprojectionCost`, one scalar at a time.

    The validity tests and the lift are those of :func:`_inverse_depth_terms` and
    :func:`lift_to_surfel` (with a pinhole projection: the reference, compared in the tests),
    on (..., M) components instead of (..., M, 3) rows.

    Args:
        pose_a: 12 (..., M) components of the top 3x4 block of ``T_alpha``, row-major.
        pose_b: the same for ``T_beta``.
        pairs: the per-pair data.

    Returns:
        ``((res_u, res_v), valid, intermediates)``: the (..., M) u and v residuals (finite
        but meaningless where invalid), the (..., M) bool validity and what the Jacobians
        reuse.
    """
    Ra = (pose_a[0:3], pose_a[4:7], pose_a[8:11])  # Ra[i][j]
    ta = (pose_a[3], pose_a[7], pose_a[11])
    Rb = (pose_b[0:3], pose_b[4:7], pose_b[8:11])
    tb = (pose_b[3], pose_b[7], pose_b[11])
    mx, my, n, sigma = pairs.ray_x, pairs.ray_y, pairs.normals, pairs.sigma

    # Lift (Eq. 1-2): x_W = R_a m / rho + t_a, rho = -(n . R_a m) / (n . (t_a - c)).
    ray = [Ra[i][0] * mx + Ra[i][1] * my + Ra[i][2] for i in range(3)]  # R_a m
    n_dot_ray = _dot(n, ray)
    distance = _dot(n, [ta[i] - pairs.centers[i] for i in range(3)])
    hits = (n_dot_ray.abs() > pairs.min_n_dot_ray) & (distance != 0)
    rho = -n_dot_ray / torch.where(hits, distance, 1.0)
    lifted = hits & (rho > 0) & (rho < 1.0 / MIN_DEPTH)
    rho = torch.where(lifted, rho, 1.0)
    offset = [ray[i] / rho + ta[i] - tb[i] for i in range(3)]  # x_W - t_b

    # Reprojection (Eq. 3) in beta: p_b = R_b^T (x_W - t_b), r = (f p_b / z + c - p) / sigma.
    pb = [Rb[0][j] * offset[0] + Rb[1][j] * offset[1] + Rb[2][j] * offset[2] for j in range(3)]
    in_front = pb[2] > MIN_DEPTH
    z = torch.where(in_front, pb[2], 1.0)
    x, y = pb[0] / z, pb[1] / z
    fx, fy, cx, cy = pairs.intrinsics_beta
    res_u = (x * fx + cx - pairs.keypoints_beta[0]) / sigma
    res_v = (y * fy + cy - pairs.keypoints_beta[1]) / sigma
    n_dot_ray = torch.where(lifted, n_dot_ray, 1.0)
    return (res_u, res_v), lifted & in_front, _Intermediates(ray, n_dot_ray, 1.0 / rho, z, x, y)


def _linearize_components(
    pose_a: Sequence[torch.Tensor], pose_b: Sequence[torch.Tensor], pairs: _PairColumns
) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Residuals and Jacobians of :meth:`SurfelReprojectionCost.linearize`, one scalar at a time.

    Args:
        pose_a: 12 (..., M) components of the top 3x4 block of ``T_alpha``, row-major.
        pose_b: the same for ``T_beta``.
        pairs: the per-pair data.

    Returns:
        ``(rows, valid)``: 26 (..., M) tensors, for the u then the v residual: the residual
        (as :func:`_residual_components`), its 6 derivatives w.r.t. the tangent ``[v, w]`` of
        ``alpha`` and its 6 w.r.t. ``beta`` (finite but meaningless where invalid); and the
        (..., M) bool validity.
    """
    (res_u, res_v), valid, inter = _residual_components(pose_a, pose_b, pairs)
    Ra = (pose_a[0:3], pose_a[4:7], pose_a[8:11])  # Ra[i][j]
    Rb = (pose_b[0:3], pose_b[4:7], pose_b[8:11])
    mx, my, n, sigma = pairs.ray_x, pairs.ray_y, pairs.normals, pairs.sigma
    x, y = inter.x, inter.y

    # Beta: J_p [-I, hat(p_b)] with J_p = d r / d p_b = diag(g_u, g_v) [[1, 0, -x], [0, 1, -y]],
    # g = f / (sigma z); a row j of J_p maps hat(p_b) to j x p_b (p_b = z (x, y, 1)).
    fx, fy = pairs.intrinsics_beta[:2]
    a_u, a_v = fx / sigma, fy / sigma
    g_u, g_v = a_u / inter.z, a_v / inter.z
    xy = x * y
    zero = torch.zeros_like(g_u)
    beta_u = [-g_u, zero, g_u * x, a_u * xy, -a_u * (1.0 + x * x), a_u * y]
    beta_v = [zero, -g_v, g_v * y, a_v * (1.0 + y * y), -a_v * xy, -a_v * x]

    # Alpha: J_p R_b^T P R_a [I, -hat(p_a)], P = I - (R_a m) n^T / (n . R_a m). A row j of
    # J_p becomes w = R_b j (world), then w - (w . R_a m) / (n . R_a m) n (onto the plane),
    # then R_a^T of that (translation part) and p_a x it (rotation part, p_a = m / rho).
    inv_n_dot_ray = 1.0 / inter.n_dot_ray
    rows = []
    for res, g, coord, col, beta in ((res_u, g_u, x, 0, beta_u), (res_v, g_v, y, 1, beta_v)):
        w = [g * (Rb[i][col] - coord * Rb[i][2]) for i in range(3)]
        along = _dot(w, inter.ray) * inv_n_dot_ray
        w = [w[i] - along * n[i] for i in range(3)]
        alpha_v = [Ra[0][j] * w[0] + Ra[1][j] * w[1] + Ra[2][j] * w[2] for j in range(3)]
        m_cross = (my * alpha_v[2] - alpha_v[1], alpha_v[0] - mx * alpha_v[2])
        m_cross += (mx * alpha_v[1] - my * alpha_v[0],)  # m x alpha_v, m = (mx, my, 1)
        rows += [res, *alpha_v, *(inter.depth * c for c in m_cross), *beta]
    return rows, valid


def _dot(a: Sequence[torch.Tensor], b: Sequence[torch.Tensor]) -> torch.Tensor:
    """Dot product of two 3-vectors given as (..., M) components."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@dataclass
class SurfelOptimConfig:
    """Settings of :func:`optimize_keyframe_poses`.

    Attributes:
        fix_first_keyframe: hold keyframe 0 constant. The surfel planes anchor the world
            frame and the metric scale, so with enough non-parallel planes all poses are
            observable and ``False`` (every pose free) is also well posed.
        min_pairs: keyframes in fewer valid pairs (as first observer or as the other
            observer) are held constant: their pose would follow a handful of tracks, and a
            few wrong or distant ones move it freely (the outdoor drive's last keyframes, seen
            by nothing later, share ~20 tracks with the rest and drifted by up to 2 m at
            exact initial poses). ``0`` frees every keyframe.
        sigma_px: keypoint standard deviation in pixels (whitening).
        kernel: robust kernel on the whitened residuals (Huber, ``sqrt(5.991)``).
        lm: Levenberg-Marquardt settings. Defaults: at most 100 iterations, three step
            expansions (up to 8x the plain step: under a Cauchy kernel the IRLS steps are
            2-6x short, see :mod:`diffloc.optim.lm.loop`) and a relative cost tolerance of 1e-3:
            on the default indoor scene (position noise 0.2 / 0.4 m) this stops after 11 / 13
            iterations with the keyframe position RMSE within 5 % of its value at full
            convergence (``cost_tolerance=1e-12``: 214 / 106 iterations).

    Example:
        >>> SurfelOptimConfig().kernel.name
        'huber'
    """

    fix_first_keyframe: bool = True
    min_pairs: int = 50
    sigma_px: float = 1.0
    kernel: RobustKernel = field(
        default_factory=lambda: RobustKernel("huber", math.sqrt(CHI2_2DOF_95))
    )
    lm: LMConfig = field(
        default_factory=lambda: LMConfig(max_iterations=100, step_expansions=3, cost_tolerance=1e-3)
    )

    def __post_init__(self) -> None:
        if self.min_pairs < 0:
            raise ValueError(f"min_pairs must be >= 0, got {self.min_pairs}")
        if not (math.isfinite(self.sigma_px) and self.sigma_px > 0):
            raise ValueError(f"sigma_px must be positive, got {self.sigma_px}")


def _check_surfels(
    db: VisualDatabase, surfel_centers: torch.Tensor, surfel_normals: torch.Tensor
) -> None:
    """Shapes of the surfels, their ids in ``db`` and the finiteness of the referenced ones
    (a map has millions of surfels, its database points reference a few percent of them)."""
    check_shape(surfel_centers, "S,3", "surfel_centers")
    check_shape(surfel_normals, f"{surfel_centers.shape[0]},3", "surfel_normals")
    if bool((db.point_surfels >= surfel_centers.shape[0]).any()):
        raise ValueError(
            f"database map points reference surfels beyond the {surfel_centers.shape[0]} given"
        )
    used = db.point_surfels[db.point_surfels >= 0]
    check_finite(surfel_centers[used], "surfel_centers")
    check_finite(surfel_normals[used], "surfel_normals")


def first_observers(db: VisualDatabase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Observations sorted by map point then keyframe, and which ones are first.

    Keyframes are numbered in insertion order, so the first observer of a map point is the
    observing keyframe of lowest index.

    Args:
        db: the visual database.

    Returns:
        ``(observations, first_row, is_first)``: (O, 3) int64 rows ``(keyframe, keypoint,
        point)`` sorted by ``(point, keyframe)``, (O,) int64 row of each observation's first
        observation of the same point, and (O,) bool, true on first observations.

    Example:
        >>> first_observers(VisualDatabase(2))[0].shape
        torch.Size([0, 3])
    """
    observations = db.observations()
    key = observations[:, 2] * max(db.num_keyframes, 1) + observations[:, 0]
    observations = observations[torch.argsort(key)]
    _, counts = torch.unique_consecutive(observations[:, 2], return_counts=True)
    starts = torch.cumsum(counts, 0) - counts
    first_row = torch.repeat_interleave(starts, counts)
    return observations, first_row, first_row == torch.arange(len(first_row))


def pairs_from_database(
    db: VisualDatabase, surfel_centers: torch.Tensor, surfel_normals: torch.Tensor
) -> SurfelPairs:
    """All Eq. 4 pairs: for each surfel-anchored map point, its first observer and each other.

    Map points without a surfel (``point_surfels == -1``) give no pairs.

    Args:
        db: the visual database (keypoints, observations, ``point_surfels``, intrinsics).
        surfel_centers: (S, 3) surfel centres of the map, world frame.
        surfel_normals: (S, 3) surfel normals.

    Returns:
        :class:`SurfelPairs` sorted by map point then ``beta``.

    Raises:
        ShapeError: wrong surfel shapes.
        ValueError: non-finite surfels referenced by map points, or point surfel ids beyond
            ``S``.

    Example:
        >>> s = torch.zeros(1, 3, dtype=torch.float64)
        >>> len(pairs_from_database(VisualDatabase(2), s, s))
        0
    """
    _check_surfels(db, surfel_centers, surfel_normals)
    observations, first_row, is_first = first_observers(db)
    surfels = db.point_surfels[observations[:, 2]]
    use = ~is_first & (surfels >= 0)
    alpha_obs, beta_obs = observations[first_row[use]], observations[use]
    surfels = surfels[use]
    f64 = torch.float64
    return SurfelPairs(
        points=beta_obs[:, 2],
        alpha=alpha_obs[:, 0],
        beta=beta_obs[:, 0],
        keypoints_alpha=db.keypoints[alpha_obs[:, 1]].to(f64),
        keypoints_beta=db.keypoints[beta_obs[:, 1]].to(f64),
        centers=surfel_centers[surfels].to(f64),
        normals=surfel_normals[surfels].to(f64),
        intrinsics_alpha=db.intrinsics[alpha_obs[:, 0]].to(f64),
        intrinsics_beta=db.intrinsics[beta_obs[:, 0]].to(f64),
    )


def optimize_keyframe_poses(
    db: VisualDatabase,
    surfel_centers: torch.Tensor,
    surfel_normals: torch.Tensor,
    config: SurfelOptimConfig | None = None,
    points: torch.Tensor | None = None,
) -> tuple[torch.Tensor, LMResult]:
    """Optimise the keyframe poses of a database by surfel reprojection (seed 1 Eq. 4).

    Pairs whose lift or reprojection is invalid at the initial poses are masked out. The
    database is not modified: assign the returned poses to ``db.T_wc`` and call
    :func:`replace_map_points` to finish seed 1's optimisation step.

    Args:
        db: the visual database; ``db.T_wc`` gives the initial poses.
        surfel_centers: (S, 3) surfel centres, world frame.
        surfel_normals: (S, 3) surfel normals.
        config: settings (default :class:`SurfelOptimConfig`).
        points: (P,) bool, the map points whose pairs enter the cost (default: all), e.g.
            the training tracks of :mod:`diffloc.optim.holdout`.

    Returns:
        ``(T_wc, result)``: (K, 4, 4) float64 optimised poses and the :class:`LMResult`.

    Raises:
        ShapeError: wrong surfel shapes or ``points`` not of shape (P,).
        ValueError: no valid pair (nothing to optimise), no keyframe in ``min_pairs`` valid
            pairs, or bad surfels.

    Example:
        >>> s = torch.zeros(1, 3, dtype=torch.float64)
        >>> optimize_keyframe_poses(VisualDatabase(2), s, s)
        Traceback (most recent call last):
        ...
        ValueError: the database has no valid surfel pairs to optimise
    """
    config = config or SurfelOptimConfig()
    pairs = pairs_from_database(db, surfel_centers, surfel_normals)
    if points is not None:
        check_shape(points, f"{db.num_points}", "points")
        pairs = pairs.select(points.to(torch.bool)[pairs.points])
    sigma = torch.full((len(pairs),), config.sigma_px, dtype=torch.float64)
    cost = SurfelReprojectionCost.from_pairs(pairs, sigma)
    T0 = db.T_wc.to(torch.float64)
    valid = cost.residuals_and_valid(T0[pairs.alpha], T0[pairs.beta])[1]
    if not bool(valid.any()):
        raise ValueError("the database has no valid surfel pairs to optimise")
    used = torch.cat([pairs.alpha[valid], pairs.beta[valid]])
    counts = torch.bincount(used, minlength=db.num_keyframes)
    fixed = counts < config.min_pairs
    if bool(fixed.all()):
        raise ValueError(
            f"no keyframe is in min_pairs={config.min_pairs} valid surfel pairs "
            f"(most: {int(counts.max())}); lower min_pairs to optimise"
        )
    if config.fix_first_keyframe:
        fixed[0] = True
    result = levenberg_marquardt(
        T0,
        lambda T_a, T_b, extra: cost(T_a, T_b),
        pairs.alpha,
        pairs.beta,
        jacobian_fn=lambda T_a, T_b, extra: cost.linearize(T_a, T_b),
        mask=valid,
        fixed=torch.nonzero(fixed).flatten(),
        kernel=config.kernel,
        config=config.lm,
    )
    return result.T_wc, result


def replace_map_points(
    db: VisualDatabase, surfel_centers: torch.Tensor, surfel_normals: torch.Tensor
) -> torch.Tensor:
    """Re-place map points on their surfel planes from their first observer (seed 1 Eq. 1).

    Points without observations or surfel, or whose lift is invalid, keep their position.

    Args:
        db: the visual database (poses ``db.T_wc``, keypoints, observations).
        surfel_centers: (S, 3) surfel centres, world frame.
        surfel_normals: (S, 3) surfel normals.

    Returns:
        (P, 3) float64 new map point positions (the database is not modified).

    Raises:
        ShapeError: wrong surfel shapes.
        ValueError: non-finite surfels referenced by map points, or point surfel ids beyond
            ``S``.

    Example:
        >>> s = torch.zeros(1, 3, dtype=torch.float64)
        >>> replace_map_points(VisualDatabase(2), s, s).shape
        torch.Size([0, 3])
    """
    _check_surfels(db, surfel_centers, surfel_normals)
    observations, _, is_first = first_observers(db)
    first = observations[is_first]
    surfels = db.point_surfels[first[:, 2]]
    first, surfels = first[surfels >= 0], surfels[surfels >= 0]
    f64 = torch.float64
    points_world, valid = lift_to_surfel(
        db.keypoints[first[:, 1]].to(f64),
        db.T_wc[first[:, 0]].to(f64),
        *db.intrinsics[first[:, 0]].to(f64).unbind(-1),
        surfel_centers[surfels].to(f64),
        surfel_normals[surfels].to(f64),
    )
    positions = db.point_positions.to(f64).clone()
    positions[first[valid, 2]] = points_world[valid]
    return positions
