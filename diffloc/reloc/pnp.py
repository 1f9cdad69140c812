"""Perspective-n-Point: LO-RANSAC around Lambda Twist P3P, EPnP and Levenberg-Marquardt.

Conventions:

- Results are camera-to-world poses ``T_wc`` (ARCHITECTURE.md); internally the solvers work on
  the world-to-camera rotation and translation ``(R_cw, t_cw)``, the transform that projects.
- Keypoints are pixels of a :class:`~diffloc.geometry.camera.PinholeCamera`. They are
  undistorted once, and every error below (RANSAC threshold, refinement cost, the returned
  ``reprojection_errors``) is measured in *undistorted* pixels: ``fx (X/Z - x_n)``,
  ``fy (Y/Z - y_n)`` with ``x_n`` the undistorted normalised keypoint. Without distortion these
  are the ordinary pixel errors; with distortion they differ by the local scale of the
  distortion map (a few percent at most for usual lenses).
- All optimised geometry is float64. Every random draw uses the ``torch.Generator`` given.

RANSAC (seed 1, Sec. III-C: "PnP with RANSAC to find a rough camera pose") runs the shared core
:func:`diffloc.geometry.ransac.ransac` (batched uniform samples, adaptive number of samples
``k = log(1 - confidence) / log(1 - w^3)`` for the best inlier ratio ``w``, bail-out test on a
random subset of ``bailout_points`` correspondences, local optimisation of every batch's best
candidate) and solves Lambda Twist P3P for all samples of a batch at once. Both scorings (on
the bail-out subset, then on all correspondences) project the points under all candidates with
one GEMM; only the winner is then projected again keeping its normalised coordinates and
inverse depths, which its first Gauss-Newton step needs. Scores are MSAC (truncated squared
error). Local optimisation (LO-RANSAC, Chum et al. 2003) takes Gauss-Newton steps on the
inliers, each re-scored and kept only if the MSAC cost drops (so the inlier set is re-estimated
after every step), until the inlier count is stable. The best model is finally refined the same
way until the next step would be below 1e-6 (m, rad), a step that is then not taken, or until a
step below 3e-4 leaves the inlier count unchanged (Gauss-Newton converges quadratically here,
typically with steps of 1e-2, 1e-3 and 1e-6, so the next step would be below 1e-6): the pose is
within ~1e-6 of the least-squares optimum on its inliers, orders of magnitude below the error
due to the keypoint noise, and its ``inliers`` and ``reprojection_errors`` are those of the
returned pose.

The non-minimal :func:`solve_pnp` (EPnP + Levenberg-Marquardt) and :func:`refine_pnp` (LM)
are batched over problems and take per-correspondence weights.

Speed: for the few hundred hypotheses and ~1000 points of a query every torch operation costs
far more in fixed overhead than in arithmetic, so the code minimises operations: RANSAC runs
in ``torch.inference_mode``, one projection per Gauss-Newton step serves both its score and
the next step's normal equations, the Jacobians are one product of a constant matrix with the
outer products of ``(x, y, 1, 1/z)`` (:func:`~diffloc.geometry.camera.pose_jacobian_map`),
updates use the Cayley retraction (:func:`~diffloc.geometry.se3.cayley_rotation`), and the
arrays keep the points innermost (``(B, k, N)``), where torch's kernels are fastest.

Example:
    >>> import math
    >>> from diffloc.geometry.camera import PinholeCamera
    >>> cam = PinholeCamera.from_fov(640, 480, math.pi / 2, dtype=torch.float64)
    >>> g = torch.Generator().manual_seed(0)
    >>> X = torch.rand(100, 3, generator=g, dtype=torch.float64) * 4 - 2
    >>> X[:, 2] += 6.0
    >>> uv, _ = cam.project(X)
    >>> result = solve_pnp_ransac(X, uv, cam, PnPRansacConfig(), generator=g)
    >>> result.success, torch.allclose(result.T_wc, torch.eye(4, dtype=torch.float64))
    (True, True)
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch

from diffloc.checks import ShapeError, check_finite, check_ransac_settings, check_shape
from diffloc.geometry.camera import MIN_DEPTH, PinholeCamera, pose_jacobian_map
from diffloc.geometry.ransac import bailout_keep, bailout_subset, ransac
from diffloc.geometry.se3 import cayley_rotation, invert
from diffloc.optim.lm import LMConfig, PoseSystem, minimize
from diffloc.reloc.epnp import epnp_flat
from diffloc.reloc.p3p import p3p_flat
from diffloc.threads import intra_op_threads

__all__ = [
    "PnPRansacConfig",
    "PnPResult",
    "refine_pnp",
    "solve_pnp",
    "solve_pnp_ransac",
]

_SAMPLE_SIZE = 3
_REFINE_STEP_TOL = 1e-6  # Gauss-Newton on inliers stops before a step this small (m, rad)
# ... or after a step this small that leaves the inlier count unchanged: Gauss-Newton converges
# so fast here that the next step would be below _REFINE_STEP_TOL (at most 2.1e-7 over 300
# bench_pnp problems at 0.25 / 0.5 / 0.75 outliers).
_CONVERGED_STEP = 3e-4
_P3P_REFINE_ITERATIONS = 0  # Newton steps on the P3P depths inside RANSAC (models are refined)


@dataclass
class PnPRansacConfig:
    """Settings of :func:`solve_pnp_ransac`.

    Attributes:
        threshold_px: inlier threshold on the (undistorted) reprojection error in pixels. The
            default 4 px is ~4 sigma for 1 px keypoint noise (a 2-D inlier is lost with
            probability exp(-8) ~ 3e-4); for a 95 % chi-square gate use
            ``sqrt(5.991) * sigma``.
        confidence: probability of drawing at least one all-inlier sample; sets the adaptive
            number of samples.
        min_iterations: fewest minimal samples drawn; also the size of the first batch.
        max_iterations: most minimal samples drawn.
        batch_size: most minimal samples solved and scored together, except that a
            remainder of fewer than ``min(min_iterations, batch_size)`` samples joins the
            batch before it. After the first batch, each batch draws the samples still needed
            by the adaptive criterion; a torch operation costs about as much for one
            hypothesis as for hundreds, so few large batches are fastest.
        min_inliers: a pose with fewer inliers is reported with ``success = False``.
        lo_rounds: most local-optimisation steps (Gauss-Newton on the inliers + re-score)
            per batch's best candidate; 0 disables LO.
        refine_iterations: most Gauss-Newton steps of the final refinement on the inliers of
            the best model (re-scored after each); 0 disables it.
        bailout_points: size of the random subset every candidate is scored on first; 0 (or
            fewer than twice as many correspondences) scores all candidates on all points.
        num_threads: torch intra-op threads while solving (the caller's setting is restored
            afterwards); ``None`` leaves torch's setting alone. The tensors are small, so one
            thread is fastest: more only add synchronisation, which costs tens of times the
            work itself when another process holds a core.

    Raises:
        ValueError: an out-of-range setting.
    """

    threshold_px: float = 4.0
    confidence: float = 0.9999
    min_iterations: int = 100
    max_iterations: int = 10_000
    batch_size: int = 512
    min_inliers: int = 12
    lo_rounds: int = 4
    refine_iterations: int = 20
    bailout_points: int = 64
    num_threads: int | None = 1

    def __post_init__(self) -> None:
        check_ransac_settings(self, 4)


@dataclass(frozen=True)
class PnPResult:
    """Output of :func:`solve_pnp_ransac`.

    Attributes:
        T_wc: (4, 4) float64 camera-to-world pose of the best model (identity if no model
            was found; meaningless unless ``success``).
        inliers: (N,) bool, reprojection error below the threshold under ``T_wc``.
        num_inliers: ``int(inliers.sum())``.
        iterations: number of minimal samples drawn.
        success: a model with at least ``min_inliers`` inliers was found.
        reprojection_errors: (N,) float64 undistorted-pixel errors under ``T_wc``; ``inf``
            for points behind the camera (all ``inf`` when no model was found).
    """

    T_wc: torch.Tensor
    inliers: torch.Tensor
    num_inliers: int
    iterations: int
    success: bool
    reprojection_errors: torch.Tensor


@dataclass(frozen=True)
class _PointSet:
    """Correspondences laid out for the scoring GEMM: (4, n) homogeneous points and (2, n)
    ``f * xy``."""

    points_h: torch.Tensor
    uv_t: torch.Tensor


@dataclass(frozen=True)
class _Residuals:
    """Least-squares data of B problems in row layout: points (B, 3, N), keypoints (B, 2, N).

    ``focal2`` (B, 2, 1) holds ``(fx^2, fy^2)``: pixel residuals are ``f * (proj - xy)``, so
    squared focals weight the normalised residuals and Jacobians.
    """

    points_t: torch.Tensor
    xy_t: torch.Tensor
    focal2: torch.Tensor

    @staticmethod
    def from_points(
        points_world: torch.Tensor, xy: torch.Tensor, focal: torch.Tensor
    ) -> _Residuals:
        """From (B, N, 3) points, (B, N, 2) keypoints and (B, 1, 2) or (1, 2) focals."""
        focal2 = (focal * focal).reshape(-1, 2, 1)
        return _Residuals(
            points_world.transpose(-1, -2).contiguous(), xy.transpose(-1, -2).contiguous(), focal2
        )


@dataclass(frozen=True)
class _Problem:
    """One PnP problem in the form the solvers use (all float64)."""

    points_world: torch.Tensor  # (N, 3)
    bearings: torch.Tensor  # (N, 3) unit rays of the undistorted keypoints
    scale: torch.Tensor  # (3, 1) fx, fy, 1
    points: _PointSet  # all correspondences
    subset: _PointSet | None  # the bail-out subset
    residuals: _Residuals  # B = 1 layout for scoring and Gauss-Newton


@dataclass(frozen=True)
class _Model:
    """A RANSAC model and its score."""

    R: torch.Tensor  # (1, 3, 3) R_cw
    t: torch.Tensor  # (1, 3) t_cw
    err2: torch.Tensor  # (1, N) squared pixel errors
    inliers: torch.Tensor  # (1, N) bool, err2 below the squared threshold
    cost: float  # MSAC cost
    num_inliers: int
    projection: _Projection  # where err2 came from
    refined: bool  # the result of a Gauss-Newton step


# ---------------------------------------------------------------------------- inputs


def _check_correspondences(points_world: torch.Tensor, keypoints: torch.Tensor) -> None:
    check_shape(points_world, "*,N,3", "points_world")
    check_shape(keypoints, "*,N,2", "keypoints")
    if points_world.shape[:-1] != keypoints.shape[:-1]:
        raise ShapeError(
            f"points_world (..., N, 3) and keypoints (..., N, 2) must agree in (..., N), got "
            f"{tuple(points_world.shape)} and {tuple(keypoints.shape)}"
        )
    # One cheap test (a sum is NaN or infinite if any term is); the named checks only when
    # it fails, which includes the harmless case of an overflowing sum of finite values.
    if not math.isfinite(float(points_world.sum() + keypoints.sum())):
        check_finite(points_world, "points_world")
        check_finite(keypoints, "keypoints")


def _normalise_keypoints(
    keypoints: torch.Tensor, camera: PinholeCamera
) -> tuple[torch.Tensor, torch.Tensor]:
    """Undistorted normalised coordinates (..., N, 2) and focal lengths (..., 1, 2)."""
    cam = camera
    if camera.dtype != torch.float64 or camera.device != keypoints.device:
        cam = camera.to(dtype=torch.float64, device=keypoints.device)
    focal = torch.stack((cam.fx, cam.fy), dim=-1)[..., None, :]
    centre = torch.stack((cam.cx, cam.cy), dim=-1)[..., None, :]
    xy = cam.undistort_normalized((keypoints.to(torch.float64) - centre) / focal)
    return xy, focal


def _make_problem(
    points_world: torch.Tensor,
    keypoints: torch.Tensor,
    camera: PinholeCamera,
    bailout_points: int,
    generator: torch.Generator,
) -> _Problem:
    xy, focal = _normalise_keypoints(keypoints, camera)
    X = points_world.to(dtype=torch.float64, device=keypoints.device)
    xy_t = xy.t().contiguous()
    focal_t = focal.view(2, 1)
    n = X.shape[0]
    points = _PointSet(
        torch.nn.functional.pad(X, (0, 1), value=1.0).t().contiguous(), xy_t * focal_t
    )
    subset = None
    pick = bailout_subset(n, bailout_points, generator)
    if pick is not None:
        pick = pick.to(X.device)
        subset = _PointSet(points.points_h.index_select(1, pick), points.uv_t.index_select(1, pick))
    rays = torch.nn.functional.pad(xy, (0, 1), value=1.0)
    return _Problem(
        points_world=X,
        bearings=rays / torch.linalg.vector_norm(rays, dim=-1, keepdim=True),
        scale=torch.nn.functional.pad(focal_t, (0, 0, 0, 1), value=1.0),
        points=points,
        subset=subset,
        residuals=_Residuals(X.t().contiguous()[None], xy_t[None], focal_t.square()[None]),
    )


# ---------------------------------------------------------------------------- scoring


def _scaled_rows(R: torch.Tensor, t: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """(M, 3, 4) rows ``[R | t]`` of M poses (M, 3, 3), (M, 3) scaled by ``(fx, fy, 1)``."""
    return torch.cat((R, t[..., None]), dim=-1).mul_(scale)


def _squared_errors(rows: torch.Tensor, points: _PointSet) -> torch.Tensor:
    """Squared pixel errors (M, n) of n points under M poses given by their scaled rows
    (M, 3, 4) (:func:`_scaled_rows`); ``inf`` behind the camera.

    One GEMM projects every point under every pose: the scaled rows are stacked into a
    (3M, 4) matrix multiplied with the (4, n) homogeneous points.
    """
    M = rows.shape[0]
    xyz = (rows.view(3 * M, 4) @ points.points_h).view(M, 3, -1)
    z = xyz[:, 2]
    err2 = xyz[:, :2].div_(z[:, None]).sub_(points.uv_t).square_().sum(1)
    return err2.masked_fill_(z <= MIN_DEPTH, math.inf)


def _msac(err2: torch.Tensor, threshold2: float) -> torch.Tensor:
    """MSAC cost (M,) (lower is better) from squared errors (M, n)."""
    return err2.clamp(max=threshold2).sum(-1)


# ---------------------------------------------------------------------------- refinement


@dataclass(frozen=True)
class _Projection:
    """The points of B problems projected under one pose each: all that the cost and the
    normal equations need.

    ``monomials`` (B, 4, N) are ``(x, y, 1, 1/z)`` (normalised projection and inverse depth),
    ``residuals`` (B, 2, N) the normalised residuals ``xy - (x, y)`` (keypoint minus
    projection), ``behind`` (B, N) the points not in front of the camera and ``err2`` (B, N)
    the squared pixel errors (``inf`` behind the camera).
    """

    monomials: torch.Tensor
    residuals: torch.Tensor
    behind: torch.Tensor
    err2: torch.Tensor


def _project(R: torch.Tensor, t: torch.Tensor, data: _Residuals) -> _Projection:
    """Project the points of B problems under (B, 3, 3) ``R_cw`` and (B, 3) ``t_cw`` (or of
    one problem under B poses)."""
    pc = torch.baddbmm(t[..., None], R, data.points_t.expand(R.shape[0], -1, -1))
    z = pc[:, 2]
    behind = z <= MIN_DEPTH
    iz = z.clamp(min=MIN_DEPTH).reciprocal_()[:, None]
    monomials = torch.cat((pc.mul_(iz), iz), dim=1)
    residuals = torch.sub(data.xy_t, monomials[:, :2])
    err2 = residuals.square().mul_(data.focal2).sum(1)
    return _Projection(monomials, residuals, behind, err2.masked_fill_(behind, math.inf))


def _normal_equations(
    proj: _Projection, weights: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``J^T W J`` (B, 6, 6) and ``J^T W r`` (B, 6, 1) of the residuals ``r = xy - (x, y)``
    for a left twist ``[v, w]`` of T_cw (``J = d (x, y) / d twist``), from a projection and
    weights (B, 2, N) per residual (zero behind the camera). The Gauss-Newton step solves
    ``J^T W J delta = J^T W r``.

    The Jacobian is built as (B, 6, 2N) rows (parameter-major) by one product of a constant
    matrix with the outer products of the monomials, so both products are single GEMMs.
    """
    u = proj.monomials
    B, N = u.shape[0], u.shape[-1]
    outer = (u[:, :, None] * u[:, None]).view(B, 16, N)
    J = _jacobian_map_t(u.dtype, u.device) @ outer  # (B, 12, N), row 2 k + c
    Jw = (J.view(B, 6, 2, N) * weights[:, None]).view(B, 6, 2 * N)
    return Jw @ J.view(B, 6, 2 * N).transpose(-1, -2), Jw @ proj.residuals.view(B, 2 * N, 1)


@functools.lru_cache(maxsize=8)
def _jacobian_map_t(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(12, 16) transposed :func:`~diffloc.geometry.camera.pose_jacobian_map`, contiguous
    (never modified in place)."""
    with torch.inference_mode(False):  # an ordinary tensor even if first made in RANSAC
        return pose_jacobian_map(dtype, device).T.contiguous()


def _step(H: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Solve ``(H + D) delta = g`` for (B, 6) Gauss-Newton steps, with ``H`` (B, 6, 6) and
    ``g`` (B, 6, 1) from :func:`_normal_equations`.

    ``D = 1e-12 max(diag(H)) + 1e-300``: the relative and absolute floors keep rank-deficient
    systems (too few or degenerate inliers) positive definite, with a zero step for
    directions the data do not constrain, so a Cholesky solve suffices (a non-finite ``H``
    gives a non-finite step, which the callers' cost tests reject). ``H`` is overwritten.
    """
    diag = H.diagonal(dim1=-2, dim2=-1)
    diag.add_(diag.amax(-1, keepdim=True).mul_(1e-12).add_(1e-300))
    return torch.cholesky_solve(g, torch.linalg.cholesky_ex(H)[0])[..., 0]


def _retract(
    R: torch.Tensor, t: torch.Tensor, delta: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Apply a step ``[v, w]`` (B, 6): ``R <- Cay(w) R``, ``t <- Cay(w) t + v``.

    :func:`~diffloc.geometry.se3.cayley_rotation` is an exact rotation that agrees with
    ``exp(hat(w))`` to second order, i.e. a retraction whose first-order term is the left
    twist the Jacobian is taken for.
    """
    C = cayley_rotation(delta[:, 3:])
    return C @ R, torch.baddbmm(delta[:, :3, None], C, t[..., None])[..., 0]


@dataclass(frozen=True)
class _WeightedReprojection:
    """The :class:`~diffloc.optim.lm.LMProblem` of :func:`refine_pnp` and :func:`solve_pnp`:
    half the weighted squared pixel error of B problems, parameters ``(R_cw (B, 3, 3),
    t_cw (B, 3))`` updated by left twists (:func:`_retract`); points behind the camera weigh
    nothing.

    Attributes:
        data: the B problems.
        weights: (B, N) non-negative weights.
    """

    data: _Residuals
    weights: torch.Tensor
    analytic: bool = True

    def linearize(self, params: tuple[torch.Tensor, torch.Tensor]) -> PoseSystem:
        proj = _project(*params, self.data)
        w = self.weights.masked_fill(proj.behind, 0.0)
        H, Jr = _normal_equations(proj, w[:, None] * self.data.focal2)
        cost = proj.err2.masked_fill(proj.behind, 0.0).mul_(w).sum(-1).mul_(0.5)
        return PoseSystem(cost, Jr[..., 0].neg_(), H, w.sum(-1, keepdim=True).mul_(2.0))

    def evaluate(self, params: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        return self.linearize(params).cost

    def retract(
        self, params: tuple[torch.Tensor, torch.Tensor], delta: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return _retract(*params, delta)


def _lm(
    R: torch.Tensor,
    t: torch.Tensor,
    data: _Residuals,
    weights: torch.Tensor,
    iterations: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Levenberg-Marquardt (:func:`~diffloc.optim.lm.minimize`) on the weighted squared pixel
    error, batched over B problems; problems with a non-finite start are left as they are.

    Args:
        R: (B, 3, 3) initial R_cw.
        t: (B, 3) initial t_cw.
        data: the B problems.
        weights: (B, N) non-negative weights.
        iterations: most iterations (linear solves).

    Returns:
        Refined ``(R, t)`` (see :func:`_retract` for the update).
    """
    problem = _WeightedReprojection(data, weights)
    system = problem.linearize((R, t))
    finite = torch.isfinite(torch.cat((system.cost[:, None], system.grad), -1)).all(-1)
    run = minimize(
        problem, (R, t), LMConfig(max_iterations=iterations), system, active=finite.tolist()
    )
    return run.params


# ---------------------------------------------------------------------------- RANSAC


def _projected_model(
    R: torch.Tensor, t: torch.Tensor, data: _Residuals, threshold2: float, refined: bool
) -> _Model:
    """A model (1, 3, 3), (1, 3) scored from its projection (kept for Gauss-Newton)."""
    proj = _project(R, t, data)
    inliers = proj.err2 < threshold2
    cost = float(_msac(proj.err2, threshold2))
    return _Model(R, t, proj.err2, inliers, cost, int(inliers.sum()), proj, refined)


def _optimise(
    model: _Model,
    problem: _Problem,
    threshold2: float,
    steps: int,
    step_tol: float,
    until_stable: bool = False,
) -> _Model:
    """Gauss-Newton on the current inliers of ``model``, re-scoring after every step.

    A step is kept only if it lowers the MSAC cost (so the inlier set may change between
    steps, as in LO-RANSAC); iteration stops at the first step that does not, or once a step
    leaves the number of inliers unchanged and either ``until_stable`` or the step had every
    twist component below ``_CONVERGED_STEP``, or once the next step of a model that has
    already taken one has every twist component below ``step_tol``: that step is not taken
    (nor scored). Either way the pose is then within about ``step_tol`` of the optimum on
    its inliers. One projection per step serves both the score of the new pose and the
    normal equations of the next step.
    """
    data = problem.residuals
    for _ in range(steps):
        weights = model.inliers.unsqueeze(1) * data.focal2
        delta = _step(*_normal_equations(model.projection, weights))
        size = float(torch.linalg.vector_norm(delta, ord=math.inf))
        if model.refined and size < step_tol:
            break
        R, t = _retract(model.R, model.t, delta)
        candidate = _projected_model(R, t, data, threshold2, refined=True)
        if not candidate.cost < model.cost:
            break
        stable = candidate.num_inliers == model.num_inliers
        model = candidate
        if stable and (until_stable or size < _CONVERGED_STEP):
            break
    return model


def _best_of_batch(
    R: torch.Tensor, t: torch.Tensor, problem: _Problem, threshold2: float, best_ratio: float
) -> _Model | None:
    """Best candidate (MSAC) of a batch of poses (M, 3, 3), (M, 3), with the bail-out test.

    The candidates that pass it are scored on all points by the scoring GEMM; the winner is
    then projected (:func:`_project`), which gives its score and the data of its first
    Gauss-Newton step.
    """
    rows = _scaled_rows(R, t, problem.scale)
    keep = None
    if problem.subset is not None:
        counts = (_squared_errors(rows, problem.subset) < threshold2).sum(-1)
        keep = bailout_keep(counts, problem.subset.uv_t.shape[1], best_ratio)
        if keep is not None:
            if keep.shape[0] == 0:
                return None
            rows = rows.index_select(0, keep)
    j = int(_msac(_squared_errors(rows, problem.points), threshold2).argmin())
    if keep is not None:
        j = int(keep[j])
    return _projected_model(R[j : j + 1], t[j : j + 1], problem.residuals, threshold2, False)


@dataclass(frozen=True)
class _Search:
    """A PnP problem as a :class:`~diffloc.geometry.ransac.RansacProblem`: P3P on minimal
    samples, the best candidate of a batch (:func:`_best_of_batch`), LO by :func:`_optimise`."""

    problem: _Problem
    threshold2: float
    lo_rounds: int
    sample_size: int = _SAMPLE_SIZE
    lo_every_batch: bool = False  # a single best candidate per batch; _solve refines the last

    @property
    def num_points(self) -> int:
        return self.problem.points_world.shape[0]

    def candidates(self, samples: torch.Tensor, best_ratio: float) -> _Model | None:
        count = samples.shape[0]
        idx = samples.view(-1)
        R, t, valid = p3p_flat(
            self.problem.bearings.index_select(0, idx).view(count, 3, 3),
            self.problem.points_world.index_select(0, idx).view(count, 3, 3),
            _P3P_REFINE_ITERATIONS,
        )
        solutions = torch.nonzero(valid.view(-1))[:, 0]
        if solutions.shape[0] == 0:
            return None
        R = R.view(-1, 3, 3).index_select(0, solutions)
        t = t.view(-1, 3).index_select(0, solutions)
        return _best_of_batch(R, t, self.problem, self.threshold2, best_ratio)

    def local_optimisation(self, candidates: _Model) -> _Model:
        return _optimise(
            candidates,
            self.problem,
            self.threshold2,
            self.lo_rounds,
            _REFINE_STEP_TOL,
            until_stable=True,
        )


def solve_pnp_ransac(
    points_world: torch.Tensor,
    keypoints: torch.Tensor,
    camera: PinholeCamera,
    config: PnPRansacConfig,
    generator: torch.Generator,
) -> PnPResult:
    """Robust camera pose from 2D-3D matches with outliers (LO-RANSAC + P3P + LM).

    Fewer correspondences than ``max(4, config.min_inliers)`` give ``success = False`` (not
    an exception): "could not localise" is a normal outcome.

    Args:
        points_world: (N, 3) world points.
        keypoints: (N, 2) matching pixel coordinates (distorted, as detected).
        camera: one camera (batch shape ``()``); its distortion is removed first.
        config: RANSAC settings.
        generator: the source of all randomness (same seed, same result).

    Returns:
        The :class:`PnPResult` (``T_wc`` float64).

    Raises:
        ShapeError: shapes other than (N, 3) / (N, 2) or different N.
        ValueError: NaN or infinite inputs, or a batched camera.

    Example:
        >>> cam = PinholeCamera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
        >>> X = torch.tensor([[0.0, 0, 4], [1, 0, 5], [0, 1, 6], [1, 1, 4], [-1, 0, 7]])
        >>> r = solve_pnp_ransac(X, cam.project(X)[0], cam, PnPRansacConfig(min_inliers=4),
        ...                      torch.Generator().manual_seed(0))
        >>> r.success, r.num_inliers
        (True, 5)
    """
    check_shape(points_world, "N,3", "points_world")
    check_shape(keypoints, "N,2", "keypoints")
    _check_correspondences(points_world, keypoints)
    if camera.batch_shape != torch.Size([]):
        raise ValueError(
            f"solve_pnp_ransac takes one camera, got batch {tuple(camera.batch_shape)}"
        )
    n = points_world.shape[0]
    with intra_op_threads(config.num_threads):
        # RANSAC is not differentiable: inference mode saves autograd bookkeeping on every
        # one of its many small operations. The outputs are made outside it, as ordinary
        # tensors.
        with torch.inference_mode():
            problem = _make_problem(
                points_world, keypoints, camera, config.bailout_points, generator
            )
            best, drawn = _solve(problem, config, generator)
        if best is None:
            device = problem.bearings.device
            return PnPResult(
                T_wc=torch.eye(4, dtype=torch.float64, device=device),
                inliers=torch.zeros(n, dtype=torch.bool, device=device),
                num_inliers=0,
                iterations=drawn,
                success=False,
                reprojection_errors=torch.full((n,), math.inf, dtype=torch.float64, device=device),
            )
        err2 = best.err2[0]
        R_wc = best.R[0].T
        T_wc = torch.cat((R_wc, -(R_wc @ best.t[0])[:, None]), dim=1)
        return PnPResult(
            T_wc=torch.cat((T_wc, _homogeneous_row(T_wc.dtype, T_wc.device)), dim=0),
            inliers=err2 < config.threshold_px**2,
            num_inliers=best.num_inliers,
            iterations=drawn,
            success=best.num_inliers >= config.min_inliers,
            reprojection_errors=err2.sqrt(),
        )


def _solve(
    problem: _Problem, config: PnPRansacConfig, generator: torch.Generator
) -> tuple[_Model | None, int]:
    """RANSAC and the final refinement; returns (best model or None, samples drawn)."""
    if problem.points_world.shape[0] < max(4, config.min_inliers):
        return None, 0
    threshold2 = config.threshold_px**2
    best, drawn = ransac(_Search(problem, threshold2, config.lo_rounds), config, generator)
    if best is not None and config.refine_iterations > 0:
        best = _optimise(best, problem, threshold2, config.refine_iterations, _REFINE_STEP_TOL)
    return best, drawn


@functools.lru_cache(maxsize=8)
def _homogeneous_row(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The (1, 4) last row ``[0, 0, 0, 1]`` of a transform (never modified in place)."""
    with torch.inference_mode(False):  # an ordinary tensor even if first made in RANSAC
        return torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=dtype, device=device)


# ---------------------------------------------------------------------------- non-minimal


def _batched_inputs(
    points_world: torch.Tensor,
    keypoints: torch.Tensor,
    camera: PinholeCamera,
    weights: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Flat float64 (B, N, 3) points, (B, N, 2) xy, (B, 1, 2) focal, (B, N) weights."""
    _check_correspondences(points_world, keypoints)
    batch, n = keypoints.shape[:-2], keypoints.shape[-2]
    if weights is None:
        weights = torch.ones(keypoints.shape[:-1], dtype=torch.float64, device=keypoints.device)
    if weights.shape != keypoints.shape[:-1]:
        raise ShapeError(
            f"weights must have shape {tuple(keypoints.shape[:-1])}, got {tuple(weights.shape)}"
        )
    check_finite(weights, "weights")
    if bool((weights < 0).any()):
        raise ValueError("weights must be non-negative")
    try:
        shape = torch.broadcast_shapes(batch, camera.batch_shape)
    except RuntimeError as exc:
        raise ShapeError(
            f"camera batch {tuple(camera.batch_shape)} does not broadcast with {tuple(batch)}"
        ) from exc
    if shape != batch:
        raise ShapeError(
            f"camera batch {tuple(camera.batch_shape)} must broadcast to {tuple(batch)}"
        )
    xy, focal = _normalise_keypoints(keypoints, camera)
    X = points_world.to(dtype=torch.float64, device=keypoints.device).reshape(-1, n, 3)
    focal = focal.expand(*batch, 1, 2).reshape(-1, 1, 2)
    w = weights.to(dtype=torch.float64, device=keypoints.device).reshape(-1, n)
    return X, xy.expand(*batch, n, 2).reshape(-1, n, 2), focal, w


def _to_T_wc(R: torch.Tensor, t: torch.Tensor, batch: torch.Size) -> torch.Tensor:
    T_cw = torch.zeros(R.shape[0], 4, 4, dtype=R.dtype, device=R.device)
    T_cw[:, :3, :3] = R
    T_cw[:, :3, 3] = t
    T_cw[:, 3, 3] = 1.0
    return invert(T_cw).reshape(*batch, 4, 4)


def refine_pnp(
    T_wc: torch.Tensor,
    points_world: torch.Tensor,
    keypoints: torch.Tensor,
    camera: PinholeCamera,
    weights: torch.Tensor | None = None,
    iterations: int = 20,
) -> torch.Tensor:
    """Levenberg-Marquardt on the weighted squared (undistorted) pixel reprojection error.

    Args:
        T_wc: (..., 4, 4) initial camera-to-world poses.
        points_world: (..., N, 3) world points.
        keypoints: (..., N, 2) pixels.
        camera: camera(s) with batch shape broadcasting to ``(...)``.
        weights: optional (..., N) non-negative weights (e.g. an inlier mask as float).
        iterations: most LM iterations (stops earlier once the step vanishes).

    Returns:
        (..., 4, 4) refined float64 ``T_wc``.

    Raises:
        ShapeError: inconsistent shapes.
        ValueError: non-finite inputs or negative weights.

    Example:
        >>> cam = PinholeCamera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
        >>> X = torch.tensor([[0.0, 0, 4], [1, 0, 5], [0, 1, 6], [1, 1, 4]], dtype=torch.float64)
        >>> T0 = torch.eye(4, dtype=torch.float64)
        >>> T0[0, 3] = 0.05
        >>> T = refine_pnp(T0, X, cam.project(X)[0], cam)
        >>> torch.allclose(T, torch.eye(4, dtype=torch.float64), atol=1e-9)
        True
    """
    check_shape(T_wc, "*,4,4", "T_wc")
    check_finite(T_wc, "T_wc")
    if T_wc.shape[:-2] != keypoints.shape[:-2]:
        raise ShapeError(
            f"T_wc batch {tuple(T_wc.shape[:-2])} must equal the keypoint batch "
            f"{tuple(keypoints.shape[:-2])}"
        )
    X, xy, focal, w = _batched_inputs(points_world, keypoints, camera, weights)
    T_cw = invert(T_wc.to(dtype=torch.float64, device=X.device).reshape(-1, 4, 4))
    data = _Residuals.from_points(X, xy, focal)
    R, t = _lm(T_cw[:, :3, :3], T_cw[:, :3, 3], data, w, iterations)
    return _to_T_wc(R, t, T_wc.shape[:-2])


def solve_pnp(
    points_world: torch.Tensor,
    keypoints: torch.Tensor,
    camera: PinholeCamera,
    weights: torch.Tensor | None = None,
    refine_iterations: int = 20,
) -> torch.Tensor:
    """Camera pose from N >= 4 outlier-free correspondences: EPnP, then LM (batched).

    Args:
        points_world: (..., N, 3) world points.
        keypoints: (..., N, 2) pixels.
        camera: camera(s) with batch shape broadcasting to ``(...)``.
        weights: optional (..., N) non-negative weights, e.g. an inlier mask as float.
        refine_iterations: LM iterations after EPnP (0: plain EPnP).

    Returns:
        (..., 4, 4) float64 camera-to-world poses ``T_wc``.

    Raises:
        ShapeError: inconsistent shapes.
        ValueError: fewer than 4 points, non-finite inputs or negative weights.

    Example:
        >>> cam = PinholeCamera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
        >>> X = torch.tensor([[0.0, 0, 4], [1, 0, 5], [0, 1, 6], [1, 1, 4], [-1, 0, 7]]).double()
        >>> T_wc = solve_pnp(X, cam.project(X)[0], cam)
        >>> torch.allclose(T_wc, torch.eye(4, dtype=torch.float64), atol=1e-9)
        True
    """
    check_shape(keypoints, "*,N,2", "keypoints")
    if keypoints.shape[-2] < 4:
        raise ValueError(f"solve_pnp needs at least 4 correspondences, got {keypoints.shape[-2]}")
    X, xy, focal, w = _batched_inputs(points_world, keypoints, camera, weights)
    T_cw = epnp_flat(X, xy, w)
    R, t = T_cw[:, :3, :3], T_cw[:, :3, 3]
    if refine_iterations > 0:
        R, t = _lm(R, t, _Residuals.from_points(X, xy, focal), w, refine_iterations)
    return _to_T_wc(R, t, keypoints.shape[:-2])
