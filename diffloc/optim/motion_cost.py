"""Motion-only pose refinement from 2D-3D matches (seed 1 Eq. 5, ORB-SLAM's pose optimisation).

Cost of one query with camera-to-world pose ``T_wc`` (the optimised variable) and ``N``
matches of world points ``x_i`` to keypoints ``p_i`` with a standard deviation ``sigma_i``
in pixels (information ``I / sigma_i^2``; ORB-SLAM uses ``sigma_i^2 = scale^(2 octave)``)::

    e_i   = p_i - project(T_wc^-1 x_i)          (pixels)
    chi2_i = ||e_i||^2 / sigma_i^2
    c_r   = 0.5 * sum_i rho(chi2_i)              (Huber, delta = sqrt(5.991) by default)

:func:`refine_pose` follows ORB-SLAM's ``PoseOptimization``: ``rounds`` rounds of at most
``lm.max_iterations`` LM iterations on the current inliers, after each round every match is
re-classified (inlier when ``chi2 <= chi2_threshold``, so outliers can come back), and the
robust kernel is dropped after ``robust_rounds`` rounds. Unlike ORB-SLAM each round starts
from the previous round's pose rather than from the initial one. A query left with fewer than
``min_inliers`` inliers stops being optimised and is reported with ``converged = False``: not
localising is a normal result, never an exception. ``B`` queries are refined together (one
batched LM of 6x6 systems); shorter queries are padded and their padding masked out.

Each round is solved by the LM of :mod:`diffloc.optim.lm` (:func:`~diffloc.optim.lm.minimize`,
its damping schedule and stopping rules) on a lean problem of its own, because a query has only
a few hundred matches and every tensor operation costs mostly its fixed overhead: the
round's problem (:class:`_RoundProblem`) linearises the cost in normalised image coordinates
with the Jacobians of a constant map (:class:`_Problem`; the module :class:`MotionOnlyCost` is
the reference implementation of the same cost) into batched 6x6
:class:`~diffloc.optim.lm.PoseSystem` normal equations, and evaluations that cannot matter are
skipped: the rounds before the last stop at ``round_cost_tolerance`` (they only re-classify
the matches), a step too small to matter is not evaluated, and a round with the previous
round's kernel and matches is skipped.

The refined pose is differentiable with respect to the keypoints, the map points and the
sigmas by the implicit function theorem: at the optimum ``G(theta*, x) = dF/dtheta = 0``, so
``d theta* / d x = -H^-1 dG/dx`` with ``H`` the exact Hessian of the final round's cost (final
inlier set and kernel held fixed) in the right-perturbation tangent
``T_wc = T* @ se3_exp(theta)``. This assumes the last round converged.

Example:
    >>> from diffloc.testing import random_points  # (N, 3) points in front of the camera
    >>> cam = PinholeCamera.from_fov(640, 480, 1.2, dtype=torch.float64)
    >>> g = torch.Generator().manual_seed(0)
    >>> points = random_points((50,), generator=g)
    >>> keypoints = cam.project(points)[0]                     # true pose: identity
    >>> T0 = se3_exp(torch.tensor([0.05, 0, 0, 0, 0.02, 0], dtype=torch.float64))
    >>> out = refine_pose(cam, T0, points, keypoints)
    >>> bool(out.converged), int(out.num_inliers)
    (True, 50)
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from diffloc.checks import ShapeError, check_finite, check_positive_int, check_shape
from diffloc.geometry.camera import MIN_DEPTH, PinholeCamera, pose_jacobian_map
from diffloc.geometry.se3 import cayley_rotation, invert, se3_exp
from diffloc.optim.lm import LMConfig, PoseSystem, minimize, solve_spd
from diffloc.optim.robust import KernelFn, RobustKernel, make_robust_kernel

__all__ = ["MotionOnlyCost", "MotionRefineConfig", "RefineResult", "refine_pose"]

CHI2_2DOF_95 = 5.991
"""95 % quantile of the chi-square distribution with 2 degrees of freedom (ORB-SLAM)."""


@dataclass
class MotionRefineConfig:
    """Settings of :func:`refine_pose` (defaults: ORB-SLAM's ``PoseOptimization``).

    Attributes:
        rounds: optimise / re-classify rounds (ORB-SLAM: 4).
        chi2_threshold: a match is an inlier when ``chi2 <= chi2_threshold`` (5.991: 95 % for
            2 degrees of freedom).
        kernel: robust kernel of the first ``robust_rounds`` rounds (Huber, ``sqrt(5.991)``).
        robust_rounds: rounds using ``kernel``; later rounds are plain least squares
            (ORB-SLAM: 3 of 4).
        min_inliers: a query with fewer inliers is no longer optimised and is reported as not
            converged (ORB-SLAM stops below 10 correspondences).
        lm: LM settings of one round; ``lm.max_iterations`` is per round (ORB-SLAM: 10).
        round_cost_tolerance: the rounds before the last only re-classify the matches, so
            they stop once a step lowers the cost by at most this fraction (or by
            ``lm.cost_tolerance`` if larger); the last round uses ``lm``. On the default scene
            1e-6 cuts the iterations by ~40 % and moves the refined poses by < 1e-7 m.

    Raises:
        ValueError: non-positive counts or threshold, or ``robust_rounds > rounds``.

    Example:
        >>> MotionRefineConfig().lm.max_iterations
        10
    """

    rounds: int = 4
    chi2_threshold: float = CHI2_2DOF_95
    kernel: RobustKernel = field(
        default_factory=lambda: RobustKernel("huber", math.sqrt(CHI2_2DOF_95))
    )
    robust_rounds: int = 3
    min_inliers: int = 10
    lm: LMConfig = field(default_factory=lambda: LMConfig(max_iterations=10))
    round_cost_tolerance: float = 1e-6

    def __post_init__(self) -> None:
        check_positive_int(self.rounds, "rounds")
        check_positive_int(self.min_inliers, "min_inliers")
        if not (isinstance(self.robust_rounds, int) and 0 <= self.robust_rounds <= self.rounds):
            raise ValueError(f"robust_rounds must be in [0, rounds], got {self.robust_rounds}")
        for name in ("chi2_threshold", "round_cost_tolerance"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be positive, got {value}")


@dataclass
class RefineResult:
    """Outcome of :func:`refine_pose`; ``(...)`` is ``(B,)`` for batched inputs, else ``()``.

    Attributes:
        T_wc: (..., 4, 4) refined camera-to-world poses (float64), differentiable w.r.t. the
            keypoints, map points and sigmas (implicit function theorem).
        inliers: (..., N) bool, ``chi2 <= chi2_threshold`` at the refined pose.
        chi2: (..., N) ``||e||^2 / sigma^2`` at the refined pose (``inf`` for masked matches
            and points behind the camera).
        iterations: (...) int64 LM iterations over all rounds.
        converged: (...) bool, at least ``min_inliers`` inliers in every round.
    """

    T_wc: torch.Tensor
    inliers: torch.Tensor
    chi2: torch.Tensor
    iterations: torch.Tensor
    converged: torch.Tensor

    @property
    def num_inliers(self) -> torch.Tensor:
        """(...) int64 number of inliers."""
        return self.inliers.sum(-1)


class MotionOnlyCost(nn.Module):
    """Whitened reprojection residuals of seed 1 Eq. 5 for batches of query poses.

    The camera is a plain attribute (not a buffer): ``module.to()`` does not move it.

    Args:
        camera: the query camera; batch shape ``()`` or matching the poses' ``(...)``.

    Example:
        >>> cam = PinholeCamera.from_fov(640, 480, 1.2, dtype=torch.float64)
        >>> cost = MotionOnlyCost(cam)
        >>> X = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64)
        >>> kp = torch.tensor([[320.5, 239.5]], dtype=torch.float64)
        >>> cost(torch.eye(4, dtype=torch.float64), X, kp, torch.ones(1, dtype=torch.float64))
        tensor([[1., 0.]], dtype=torch.float64)
    """

    def __init__(self, camera: PinholeCamera) -> None:
        super().__init__()
        self.camera = camera

    def _residuals(
        self,
        T_wc: torch.Tensor,
        points_world: torch.Tensor,
        keypoints: torch.Tensor,
        sigmas: torch.Tensor,
        mask: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Whitened residuals, camera-frame points and the mask of usable matches."""
        check_shape(T_wc, "*,4,4", "T_wc")
        check_shape(points_world, "*,N,3", "points_world")
        check_shape(keypoints, "*,N,2", "keypoints")
        check_shape(sigmas, "*,N", "sigmas")
        # X_cam = R^T X - R^T t with T_wc = [R | t], computed as (..., 3, N) and viewed as
        # (..., N, 3): with N innermost the camera's element-wise kernels run several times
        # faster, and every result below keeps that layout.
        R_t = T_wc[..., :3, :3].mT
        points_cam = (R_t @ points_world.mT).sub_(R_t @ T_wc[..., :3, 3:]).mT
        uv, in_front = self.camera.project(points_cam)
        keep = in_front if mask is None else in_front & mask
        residuals = (keypoints - uv) / sigmas[..., None]
        return torch.where(keep[..., None], residuals, 0.0), points_cam, keep

    def forward(
        self,
        T_wc: torch.Tensor,
        points_world: torch.Tensor,
        keypoints: torch.Tensor,
        sigmas: torch.Tensor,
        mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Whitened residuals ``(p_i - project(T_wc^-1 x_i)) / sigma_i``.

        Leading dimensions broadcast (``(...)`` below).

        Args:
            T_wc: (..., 4, 4) camera-to-world poses.
            points_world: (..., N, 3) matched map points, world frame.
            keypoints: (..., N, 2) matched keypoints, pixels.
            sigmas: (..., N) keypoint standard deviations in pixels (positive everywhere,
                padding included).
            mask: (..., N) bool, matches to use; default all.

        Returns:
            (..., N, 2) residuals, zero where masked or behind the camera.
        """
        return self._residuals(T_wc, points_world, keypoints, sigmas, mask)[0]

    def linearize(
        self,
        T_wc: torch.Tensor,
        points_world: torch.Tensor,
        keypoints: torch.Tensor,
        sigmas: torch.Tensor,
        mask: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Residuals and their analytic Jacobian w.r.t. ``T_wc <- T_wc @ se3_exp(delta)``.

        The step moves the camera, so ``d e / d delta = +camera.project_jacobian_pose(X_cam)``
        (that method perturbs ``T_cw`` on the left, i.e. ``T_wc`` on the right with the
        opposite sign, and ``e = p - project``).

        Args:
            T_wc: (..., 4, 4) camera-to-world poses.
            points_world: (..., N, 3) map points.
            keypoints: (..., N, 2) keypoints.
            sigmas: (..., N) standard deviations (pixels).
            mask: (..., N) bool or ``None``.

        Returns:
            ``(residuals (..., N, 2), jacobian (..., N, 2, 6))``, zero where not used.
        """
        residuals, points_cam, keep = self._residuals(T_wc, points_world, keypoints, sigmas, mask)
        jacobian = self.camera.project_jacobian_pose(points_cam) / sigmas[..., None, None]
        return residuals, torch.where(keep[..., None, None], jacobian, 0.0)

    def chi2(
        self,
        T_wc: torch.Tensor,
        points_world: torch.Tensor,
        keypoints: torch.Tensor,
        sigmas: torch.Tensor,
        mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Squared whitened errors ``||e_i||^2 / sigma_i^2``.

        Args:
            T_wc: (..., 4, 4) camera-to-world poses.
            points_world: (..., N, 3) map points.
            keypoints: (..., N, 2) keypoints.
            sigmas: (..., N) standard deviations (pixels).
            mask: (..., N) bool or ``None``.

        Returns:
            (..., N) chi-square values, ``inf`` where masked or behind the camera.
        """
        residuals, _, keep = self._residuals(T_wc, points_world, keypoints, sigmas, mask)
        return torch.where(keep, (residuals * residuals).sum(-1), torch.inf)


class _ImplicitPose(torch.autograd.Function):
    """Identity on the optimum ``T*`` whose backward is the implicit-function gradient.

    ``objective(theta (B, 6), *inputs) -> (B,)`` is the minimised cost at
    ``T* @ se3_exp(theta)``; the gradient flows to ``inputs`` only.
    """

    @staticmethod
    def forward(
        ctx: Any,
        T_star: torch.Tensor,
        objective: Callable[..., torch.Tensor],
        *inputs: torch.Tensor,
    ) -> torch.Tensor:
        ctx.objective = objective
        ctx.save_for_backward(T_star, *inputs)
        return T_star.clone()

    @staticmethod
    def backward(ctx: Any, grad_T: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        T_star, *inputs = ctx.saved_tensors
        with torch.enable_grad():
            theta = T_star.new_zeros(*T_star.shape[:-2], 6).requires_grad_(True)
            (grad_theta,) = torch.autograd.grad(T_star @ se3_exp(theta), theta, grad_T)
            leaves = [x.detach().requires_grad_(True) for x in inputs]
            (G,) = torch.autograd.grad(
                ctx.objective(theta, *leaves).sum(), theta, create_graph=True
            )
            rows = [
                torch.autograd.grad(G[..., k].sum(), theta, retain_graph=True)[0] for k in range(6)
            ]
            v = solve_spd(torch.stack(rows, dim=-2).detach(), grad_theta)
            grads = torch.autograd.grad((G * v).sum(), leaves, allow_unused=True)
        return (None, None, *(None if g is None else -g for g in grads))


def _as_batch(x: torch.Tensor | None, batched: bool) -> torch.Tensor | None:
    return x if x is None or batched else x[None]


def _prepare_inputs(
    T_wc: torch.Tensor,
    points_world: torch.Tensor,
    keypoints: torch.Tensor,
    sigmas: torch.Tensor | None,
    mask: torch.Tensor | None,
) -> tuple[bool, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Validate, add the batch dimension, cast to float64 and neutralise masked entries.

    The value checks (finite pose, finite unmasked matches, positive sigmas) are reduced to
    one flag read once; :func:`_raise_value_error` names the culprit when it is false.
    """
    check_shape(T_wc, "*,4,4", "T_wc")
    if T_wc.dim() not in (2, 3):
        raise ShapeError(f"T_wc must have shape (4, 4) or (B, 4, 4), got {tuple(T_wc.shape)}")
    batched = T_wc.dim() == 3
    lead = "B," if batched else ""
    check_shape(points_world, f"{lead}N,3", "points_world")
    B = T_wc.shape[0] if batched else 1
    N = points_world.shape[-2]
    if N == 0:
        raise ValueError("refine_pose needs at least one 2D-3D match, got N = 0")
    expected = {"points_world": (N, 3), "keypoints": (N, 2), "sigmas": (N,), "mask": (N,)}
    given = {"points_world": points_world, "keypoints": keypoints, "sigmas": sigmas, "mask": mask}
    for name, x in given.items():
        shape = (B, *expected[name]) if batched else expected[name]
        if x is not None and tuple(x.shape) != shape:
            raise ShapeError(f"{name} must have shape {shape}, got {tuple(x.shape)}")
    if mask is not None and mask.dtype != torch.bool:
        raise TypeError(f"mask must be a bool tensor, got {mask.dtype}")
    f64 = torch.float64
    T = _as_batch(T_wc, batched).to(f64)
    X = _as_batch(points_world, batched).to(f64)
    kp = _as_batch(keypoints, batched).to(f64)
    sig = None if sigmas is None else _as_batch(sigmas, batched).to(f64)
    use = None if mask is None else _as_batch(mask, batched)
    # The pose and every unmasked value must be finite and every unmasked sigma positive:
    # log(sigma) is finite exactly then, so one finiteness test (x * 0 == 0) checks them all.
    values = torch.cat((X, kp) if sig is None else (X, kp, sig.log()[..., None]), dim=-1)
    if use is not None:
        values = torch.where(use[..., None], values, 0.0)
    values = torch.cat((T.flatten(1), values.flatten(1)), dim=1)
    if not bool((values * 0.0 == 0.0).all()):
        _raise_value_error(T, X, kp, sig, use)
    if use is None:
        use = torch.ones(B, N, dtype=torch.bool, device=X.device)
    else:
        X = torch.where(use[..., None], X, 0.0)
        kp = torch.where(use[..., None], kp, 0.0)
    sig = torch.ones_like(kp[..., 0]) if sig is None else torch.where(use, sig, 1.0)
    return batched, T, X, kp, sig, use


def _raise_value_error(
    T: torch.Tensor,
    X: torch.Tensor,
    kp: torch.Tensor,
    sig: torch.Tensor | None,
    use: torch.Tensor | None,
) -> None:
    """Raise the ``ValueError`` naming the first bad input of :func:`_prepare_inputs` (whose
    combined check failed): a non-finite pose or unmasked value, else a non-positive sigma."""
    check_finite(T, "T_wc")
    for name, x in (("points_world", X), ("keypoints", kp), ("sigmas", sig)):
        if x is not None:
            check_finite(x if use is None else x[use], f"{name} (unmasked entries)")
    raise ValueError("sigmas must be positive for every unmasked match")


@functools.lru_cache(maxsize=8)
def _projection_map(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(14, 16) map from the outer products ``(u u^T).flatten()`` of ``u = (x, y, 1, 1/z)`` to
    the pose Jacobian of the normalised projection ``(x, y)`` and the projection itself, row
    ``7 c + k`` for component ``c`` of ``d (x, y) / d twist_k`` (``k < 6``,
    :func:`~diffloc.geometry.camera.pose_jacobian_map`) and of ``(x, y)`` (``k = 6``: the
    product ``u_c u_2``, exact since ``u_2 = 1``). Cached: never modify it in place."""
    with torch.inference_mode(False):  # an ordinary tensor even if first made in one
        jacobian = pose_jacobian_map(dtype, device).T.unflatten(0, (6, 2)).transpose(0, 1)
        picks = torch.zeros(2, 1, 16, dtype=dtype, device=device)
        picks[0, 0, 2] = picks[1, 0, 6] = 1.0
        return torch.cat((jacobian, picks), dim=1).flatten(0, 1)


@dataclass(frozen=True)
class _Projection:
    """The matches of ``B`` problems projected under their current poses: all the normal
    equations need, whatever the kernel and the matches used.

    The pose is updated by left twists ``delta = [v, w]`` of the world-to-camera transform,
    ``T_cw <- [[Cay(w), v], [0, 1]] @ T_cw`` (:func:`_retract`), which is a right step of
    ``T_wc`` (``T_wc @ se3_exp(-delta)`` to first order).

    Attributes:
        T_cw: (B, 3, 4) the top rows ``[R_cw | t_cw]`` of the world-to-camera poses.
        rows: (B, 2, 7, N) per residual component, rows 0-5: the Jacobian of the
            normalised projection w.r.t. ``delta``; row 6: the normalised errors
            ``projection - xy`` (the residuals negated). One product of each component's rows
            with themselves gives its share of the Hessian and the gradient.
        r2: (B, N) ``||e||^2`` of the whitened pixel residuals (meaningless where not kept).
        front: (B, N) bool, matches in front of the camera.
        valid: (B, N) bool, the problem's valid matches.
    """

    T_cw: torch.Tensor
    rows: torch.Tensor
    r2: torch.Tensor
    front: torch.Tensor
    valid: torch.Tensor

    @property
    def chi2(self) -> torch.Tensor:
        """(B, N) ``r2`` of the valid matches in front of the camera, ``inf`` for the others."""
        return torch.where(self.front & self.valid, self.r2, math.inf)


@dataclass(frozen=True)
class _Linearization(PoseSystem):
    """Robust normal equations of ``B`` one-pose problems at their current poses, in the
    tangent ``delta`` of :class:`_Projection` (``grad = sum w J^T e`` with ``w = rho'(chi2)``
    and ``J`` the Jacobian of the whitened residuals ``e``), with the projection they come
    from and the kernel's ``(rho, rho')`` (B, N) of every match (masked or not), which a
    round with the same kernel reuses."""

    projection: _Projection
    kernel_values: tuple[torch.Tensor, torch.Tensor]


@dataclass(frozen=True)
class _Problem:
    """The matches of ``B`` queries in the solver's layout (matches innermost, float64).

    The solver works on normalised image coordinates: with ``f = (fx, fy)`` and ``c`` the
    principal point, the pixel residual of Eq. 5 is ``f * (xy - distort(x_c / z_c))`` with
    ``xy = (p - c) / f``, so ``chi2 = sum_c scale_c (xy_c - distort(x_c / z_c)_c)^2`` with
    ``scale = f^2 / sigma^2``. :class:`MotionOnlyCost` is the reference implementation of the
    same cost (tests compare the two).

    Attributes:
        camera: the float64 query camera.
        points_h: (B, 4, N) homogeneous map points, world frame.
        xy_t: (B, 2, N) normalised (distorted) keypoints ``(p - c) / f``.
        scale: (B, 2, N) ``f^2 / sigma^2`` per residual component.
        valid: (B, N) bool, matches whose ``chi2`` is reported.
        projection_map: (B, 14, 16) :func:`_projection_map`, expanded.
        zero: () float64 zero, one: () float64 one (``torch.where`` fills that need not be
            made on every call).
    """

    camera: PinholeCamera
    points_h: torch.Tensor
    xy_t: torch.Tensor
    scale: torch.Tensor
    valid: torch.Tensor
    projection_map: torch.Tensor
    zero: torch.Tensor
    one: torch.Tensor

    @staticmethod
    def make(
        camera: PinholeCamera,
        points_world: torch.Tensor,
        keypoints: torch.Tensor,
        sigmas: torch.Tensor,
        valid: torch.Tensor,
    ) -> _Problem:
        """From (B, N, 3) points, (B, N, 2) keypoints, (B, N) sigmas and (B, N) validity."""
        focal = torch.stack((camera.fx, camera.fy), dim=-1).reshape(-1, 2, 1)
        centre = torch.stack((camera.cx, camera.cy), dim=-1).reshape(-1, 2, 1)
        points_h = torch.nn.functional.pad(points_world, (0, 1), value=1.0)
        return _Problem(
            camera=camera,
            points_h=points_h.mT.contiguous(),
            xy_t=(keypoints.mT - centre) / focal,
            scale=(focal / sigmas[:, None]).square_(),
            valid=valid,
            projection_map=_projection_map(points_h.dtype, points_h.device).expand(
                points_h.shape[0], 14, 16
            ),
            zero=points_h.new_zeros(()),
            one=points_h.new_ones(()),
        )

    def project(self, T_cw: torch.Tensor) -> _Projection:
        """The matches projected under the poses ``T_cw`` (B, 3, 4).

        The Jacobian and the projection are one product of a constant map with the outer
        products of ``(x, y, 1, 1/z)`` (:func:`_projection_map`), the Jacobian times the
        distortion Jacobian if any.
        """
        points_cam = torch.bmm(T_cw, self.points_h)  # (B, 3, N)
        z = points_cam[:, 2:]
        front = z > MIN_DEPTH
        inv_z = torch.where(front, z, self.one).reciprocal_()
        # (x, y, 1, 1/z); z / z may round to 1 - 1 ulp, which is harmless here.
        monomials = torch.cat((points_cam.mul_(inv_z), inv_z), dim=1)
        outer = (monomials[:, :, None] * monomials[:, None]).flatten(1, 2)  # (B, 16, N)
        rows = torch.bmm(self.projection_map, outer).unflatten(1, (2, 7))  # (B, 2, 7, N)
        if self.camera.distortion is not None:
            xy_d, D = self.camera._distort_and_jacobian(rows[:, :, 6].mT)  # (B, N, 2), (B, N, 2, 2)
            J = (D.permute(0, 2, 3, 1)[..., None, :] * rows[:, None, :, :6]).sum(2)
            rows = torch.cat((J, xy_d.mT[:, :, None]), dim=2)
        errors = rows[:, :, 6].sub_(self.xy_t)  # (B, 2, N)
        r2 = (errors * self.scale).mul_(errors).sum(1)
        return _Projection(T_cw, rows, r2, front[:, 0], self.valid)

    def normal_equations(
        self,
        projection: _Projection,
        used: torch.Tensor,
        kernel: KernelFn,
        kernel_values: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> _Linearization:
        """The normal equations of the robust cost of the ``used`` (B, N) matches (valid
        ones: a subset of :attr:`valid`); ``kernel_values``: ``kernel`` of ``projection.r2``
        if already known."""
        if kernel_values is None:
            kernel_values = kernel(projection.r2)
        rho, weight = kernel_values
        used = projection.front & used
        weight = torch.where(used, weight, self.zero)
        rows0, rows1 = projection.rows.unbind(1)  # (B, 7, N) each
        weighted0, weighted1 = (
            projection.rows * (self.scale * weight[:, None])[:, :, None]
        ).unbind(1)
        # Summed over the two residual components one after the other, so that every product
        # runs over the matches in order: padding at the end of a batch leaves the sums
        # bitwise unchanged (a batched refinement equals the single ones).
        products = torch.baddbmm(
            torch.bmm(weighted0, rows0.mT), weighted1, rows1.mT
        )  # (B, 7, 7): [[H, grad], [grad^T, sum w e^T e]]
        return _Linearization(
            cost=torch.where(used, rho, self.zero).sum(-1).mul_(0.5),
            grad=products[:, :6, 6],
            hessian=products[:, :6, :6],
            support=weight.sum(-1, keepdim=True).mul_(2.0),
            projection=projection,
            kernel_values=kernel_values,
        )

    def linearize(self, T_cw: torch.Tensor, used: torch.Tensor, kernel: KernelFn) -> _Linearization:
        """:meth:`normal_equations` of the projection under the poses ``T_cw`` (B, 3, 4)."""
        return self.normal_equations(self.project(T_cw), used, kernel)


@dataclass(frozen=True)
class _RoundProblem:
    """One round of :func:`refine_pose` as an :class:`~diffloc.optim.lm.LMProblem`: the
    ``used`` (B, N) matches under ``kernel``; parameters: the poses ``T_cw`` (B, 3, 4).

    Steps are left twists ``delta = [v, w]`` of ``T_cw``: ``[[Cay(w), v], [0, 1]] @ T_cw``
    (the Cayley map :func:`~diffloc.geometry.se3.cayley_rotation` agrees with ``se3_exp`` to
    first order, the convention of the Jacobians).
    """

    problem: _Problem
    used: torch.Tensor
    kernel: KernelFn
    analytic: bool = True

    def linearize(self, T_cw: torch.Tensor) -> _Linearization:
        return self.problem.linearize(T_cw, self.used, self.kernel)

    def evaluate(self, T_cw: torch.Tensor) -> torch.Tensor:
        return self.linearize(T_cw).cost

    def retract(self, T_cw: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        shift = torch.nn.functional.pad(delta[:, :3, None], (3, 0))  # (B, 3, 4): [0 | v]
        return torch.baddbmm(shift, cayley_rotation(delta[:, 3:]), T_cw)


def refine_pose(
    camera: PinholeCamera,
    T_wc: torch.Tensor,
    points_world: torch.Tensor,
    keypoints: torch.Tensor,
    sigmas: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
    config: MotionRefineConfig | None = None,
) -> RefineResult:
    """Refine query poses from 2D-3D matches with robust motion-only LM and outlier rounds.

    Args:
        camera: the query camera; batch shape ``()`` or ``(B,)``.
        T_wc: (4, 4) or (B, 4, 4) initial camera-to-world poses (e.g. from PnP RANSAC).
        points_world: (N, 3) or (B, N, 3) matched map points, world frame.
        keypoints: (N, 2) or (B, N, 2) matched keypoints, pixels.
        sigmas: (N,) or (B, N) keypoint standard deviations in pixels; default 1.
        mask: (N,) or (B, N) bool, valid matches (false for padding or rejected matches);
            masked entries may hold any value, NaN included. Default all valid.
        config: round / kernel / LM settings (default :class:`MotionRefineConfig`).

    Returns:
        :class:`RefineResult`; all tensors float64 / bool / int64.

    Raises:
        ShapeError: shapes that do not match the documented ones.
        TypeError: a non-bool mask.
        ValueError: no matches (``N = 0``), non-finite poses or unmasked inputs, or
            non-positive sigmas.

    Example:
        >>> from diffloc.testing import random_points
        >>> cam = PinholeCamera.from_fov(64, 48, 1.2, dtype=torch.float64)
        >>> X = random_points((20,), generator=torch.Generator().manual_seed(1))
        >>> out = refine_pose(cam, torch.eye(4, dtype=torch.float64), X, cam.project(X)[0])
        >>> bool(out.chi2.max() < 1e-20)
        True
    """
    config = config or MotionRefineConfig()
    batched, T0, X, kp, sig, valid = _prepare_inputs(T_wc, points_world, keypoints, sigmas, mask)
    if camera.dtype != torch.float64:
        camera = camera.to(torch.float64)
    problem = _Problem.make(camera, X.detach(), kp.detach(), sig.detach(), valid)
    # Rounds before the last only re-classify the matches: they stop at a looser tolerance.
    classify_lm = dataclasses.replace(
        config.lm, cost_tolerance=max(config.lm.cost_tolerance, config.round_cost_tolerance)
    )
    projection = problem.project(invert(T0.detach())[:, :3])
    B = T0.shape[0]
    inliers = valid
    iterations, converged = [0] * B, [True] * B
    kernel = used = None
    system, system_kernel = None, None  # the last round's final normal equations, its kernel
    with torch.no_grad():
        for round_index in range(config.rounds):
            previous_kernel, previous_used = kernel, used
            kernel = config.kernel if round_index < config.robust_rounds else RobustKernel()
            enough = [n >= config.min_inliers for n in inliers.sum(-1).tolist()]
            converged = [c and e for c, e in zip(converged, enough, strict=True)]
            used = (
                inliers
                if all(enough)
                else inliers & torch.tensor(enough, device=inliers.device)[:, None]
            )
            # A round with the previous round's kernel and matches would restart at that
            # round's optimum: only the problems whose matches changed are optimised again.
            rerun = enough
            if kernel == previous_kernel:
                changed = (used != previous_used).any(-1).tolist()
                rerun = [r and c for r, c in zip(rerun, changed, strict=True)]
            if not any(rerun):
                if round_index:  # the inliers are those of the unchanged poses already
                    continue
            else:
                kernel_fn = make_robust_kernel(kernel)
                # The previous round ended at these poses: only its weights change (and not
                # the kernel's values if the kernel is the same).
                values = system.kernel_values if kernel == system_kernel else None
                state = problem.normal_equations(projection, used, kernel_fn, values)
                lm_config = config.lm if round_index == config.rounds - 1 else classify_lm
                run = minimize(
                    _RoundProblem(problem, used, kernel_fn),
                    projection.T_cw,
                    lm_config,
                    system=state,
                    active=rerun,
                )
                system, system_kernel = run.system, kernel
                projection = system.projection
                iterations = [i + s for i, s in zip(iterations, run.iterations, strict=True)]
            chi2 = projection.chi2
            inliers = chi2 <= config.chi2_threshold
        T_star = invert(torch.cat((projection.T_cw, T0[:, 3:]), dim=1))
    counts = inliers.sum(-1).tolist()
    converged_t = torch.tensor(
        [c and n >= config.min_inliers for c, n in zip(converged, counts, strict=True)]
    )
    T_out = T_star
    if torch.is_grad_enabled() and (kp.requires_grad or X.requires_grad or sig.requires_grad):
        rho = make_robust_kernel(kernel)

        def objective(
            theta: torch.Tensor, kp_: torch.Tensor, X_: torch.Tensor, sig_: torch.Tensor
        ) -> torch.Tensor:
            r = MotionOnlyCost(camera)(T_star @ se3_exp(theta), X_, kp_, sig_, used)
            return 0.5 * torch.where(used, rho((r * r).sum(-1))[0], 0.0).sum(-1)

        T_out = _ImplicitPose.apply(T_star, objective, kp, X, sig)
    out = RefineResult(T_out, inliers, chi2, torch.tensor(iterations), converged_t)
    if batched:
        return out
    return RefineResult(out.T_wc[0], inliers[0], chi2[0], out.iterations[0], converged_t[0])
