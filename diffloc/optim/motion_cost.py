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

The refined pose is differentiable with respect to the keypoints, the map points and the
sigmas by the implicit function theorem: at the optimum ``G(theta*, x) = dF/dtheta = 0``, so
``d theta* / d x = -H^-1 dG/dx`` with ``H`` the exact Hessian of the final round's cost (final
inlier set and kernel held fixed) in the right-perturbation tangent
``T_wc = T* @ se3_exp(theta)``. This assumes the last round converged.

Example:
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

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from diffloc.checks import ShapeError, check_finite, check_positive_int, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import se3_exp
from diffloc.optim.lm import LMConfig, levenberg_marquardt_single_pose, solve_spd
from diffloc.optim.robust import RobustKernel, make_robust_kernel

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

    def __post_init__(self) -> None:
        check_positive_int(self.rounds, "rounds")
        check_positive_int(self.min_inliers, "min_inliers")
        if not (isinstance(self.robust_rounds, int) and 0 <= self.robust_rounds <= self.rounds):
            raise ValueError(f"robust_rounds must be in [0, rounds], got {self.robust_rounds}")
        if not (math.isfinite(self.chi2_threshold) and self.chi2_threshold > 0):
            raise ValueError(f"chi2_threshold must be positive, got {self.chi2_threshold}")


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
        check: bool = True,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Whitened residuals, camera-frame points and the mask of usable matches.

        ``check=False`` skips the shape checks (for :func:`refine_pose`, which validated its
        inputs once, and calls this every LM iteration).
        """
        if check:
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
        return self._linearize(T_wc, points_world, keypoints, sigmas, mask, check=True)

    def _linearize(
        self,
        T_wc: torch.Tensor,
        points_world: torch.Tensor,
        keypoints: torch.Tensor,
        sigmas: torch.Tensor,
        mask: torch.Tensor | None,
        check: bool,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`linearize`, with the shape checks optional (see :meth:`_residuals`)."""
        residuals, points_cam, keep = self._residuals(
            T_wc, points_world, keypoints, sigmas, mask, check
        )
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
        return self._chi2(T_wc, points_world, keypoints, sigmas, mask, check=True)

    def _chi2(
        self,
        T_wc: torch.Tensor,
        points_world: torch.Tensor,
        keypoints: torch.Tensor,
        sigmas: torch.Tensor,
        mask: torch.Tensor | None,
        check: bool,
    ) -> torch.Tensor:
        """:meth:`chi2`, with the shape checks optional (see :meth:`_residuals`)."""
        residuals, _, keep = self._residuals(T_wc, points_world, keypoints, sigmas, mask, check)
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
    """Validate, add the batch dimension, cast to float64 and neutralise masked entries."""
    check_shape(T_wc, "*,4,4", "T_wc")
    if T_wc.dim() not in (2, 3):
        raise ShapeError(f"T_wc must have shape (4, 4) or (B, 4, 4), got {tuple(T_wc.shape)}")
    check_finite(T_wc, "T_wc")
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
    use = _as_batch(mask, batched) if mask is not None else torch.ones(B, N, dtype=torch.bool)
    X = _as_batch(points_world, batched).to(f64)
    kp = _as_batch(keypoints, batched).to(f64)
    sig = torch.ones_like(kp[..., 0]) if sigmas is None else _as_batch(sigmas, batched).to(f64)
    for name, x in (("points_world", X), ("keypoints", kp), ("sigmas", sig)):
        check_finite(x[use], f"{name} (unmasked entries)")
    if not bool((sig[use] > 0).all()):
        raise ValueError("sigmas must be positive for every unmasked match")
    X = torch.where(use[..., None], X, 0.0)
    kp = torch.where(use[..., None], kp, 0.0)
    sig = torch.where(use, sig, 1.0)
    return batched, T, X, kp, sig, use


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
        >>> cam = PinholeCamera.from_fov(64, 48, 1.2, dtype=torch.float64)
        >>> X = random_points((20,), generator=torch.Generator().manual_seed(1))
        >>> refine_pose(cam, torch.eye(4, dtype=torch.float64), X, cam.project(X)[0]).chi2.max()
        tensor(0., dtype=torch.float64)
    """
    config = config or MotionRefineConfig()
    batched, T0, X, kp, sig, valid = _prepare_inputs(T_wc, points_world, keypoints, sigmas, mask)
    cost = MotionOnlyCost(camera.to(torch.float64))
    # Keypoints stored (B, 2, N) and viewed as (B, N, 2), the layout of the projections (see
    # MotionOnlyCost._residuals), so the residual arithmetic keeps N innermost.
    Xd, kpd, sigd = X.detach(), kp.detach().mT.contiguous().mT, sig.detach()
    T = T0.detach()
    inliers = valid
    iterations = torch.zeros(T.shape[0], dtype=torch.long)
    converged = torch.ones(T.shape[0], dtype=torch.bool)
    for round_index in range(config.rounds):
        kernel = config.kernel if round_index < config.robust_rounds else RobustKernel()
        enough = inliers.sum(-1) >= config.min_inliers
        converged &= enough
        used = inliers & enough[:, None]
        result = levenberg_marquardt_single_pose(
            T,
            lambda T_cur, used=used: cost(T_cur, Xd, kpd, sigd, used),
            jacobian_fn=lambda T_cur, used=used: cost._linearize(T_cur, Xd, kpd, sigd, used, False),
            mask=used,
            kernel=kernel,
            config=config.lm,
        )
        T, iterations = result.T_wc, iterations + result.iterations
        chi2 = cost._chi2(T, Xd, kpd, sigd, valid, check=False)
        inliers = chi2 <= config.chi2_threshold
    converged &= inliers.sum(-1) >= config.min_inliers
    rho = make_robust_kernel(kernel)
    T_star = T

    def objective(
        theta: torch.Tensor, kp_: torch.Tensor, X_: torch.Tensor, sig_: torch.Tensor
    ) -> torch.Tensor:
        r = cost(T_star @ se3_exp(theta), X_, kp_, sig_, used)
        return 0.5 * torch.where(used, rho((r * r).sum(-1))[0], 0.0).sum(-1)

    T_out = _ImplicitPose.apply(T_star, objective, kp, X, sig)
    out = RefineResult(T_out, inliers, chi2, iterations, converged)
    if batched:
        return out
    return RefineResult(out.T_wc[0], inliers[0], chi2[0], iterations[0], converged[0])
