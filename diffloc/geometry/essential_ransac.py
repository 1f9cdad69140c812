"""Essential-matrix check: a robust essential matrix between a keyframe and a query (LO-RANSAC).

Before 2D-3D matches go to the PnP solver, seed 1 (Sec. III-C) checks them with an essential
matrix between the canonical keyframe ``F_c`` and the query ``F_q``
(:class:`diffloc.reloc.hierarchical.HierarchicalRelocalizer`); the database builder verifies
descriptor matches of a new keyframe against covisible keyframes the same way
(:mod:`diffloc.database.epipolar_matching`), so the check lives in the geometry layer both sit
on. Each match gives a keyframe keypoint (in the relocaliser: the detected keypoint when the
map point is visible in ``F_c``, else the map point projected into ``F_c``) and a query
keypoint. Projected keypoints may lie *outside* the keyframe image; they are used as they are
and kept when they are inliers, so they are never filtered here.

Conventions:

- ``E`` maps keyframe to query: ``x_q^T E x_kf = 0`` for undistorted normalised homogeneous
  coordinates ``x = (X/Z, Y/Z, 1)``, i.e. ``E ~ [t]_x R`` with ``(R, t)`` the rotation and
  translation of ``T_qk = invert(T_wc_query) @ T_wc_kf`` (keyframe camera to query camera).
  It is returned with unit Frobenius norm; its sign is arbitrary.
- Errors are Sampson distances in pixels: the solver works on normalised coordinates and the
  scoring on normalised coordinates scaled by each camera's mean focal length ``(fx + fy) / 2``
  (which is the Sampson distance of the pixel-space fundamental matrix when ``fx == fy`` and
  there is no distortion), so ``threshold_px`` means pixels in both images even when the two
  cameras differ.
- Geometry is float64; every random draw uses the ``torch.Generator`` given.

RANSAC runs the shared core :func:`diffloc.geometry.ransac.ransac` (batched uniform samples,
adaptive number of samples ``k = log(1 - confidence) / log(1 - w^5)`` for the best inlier
ratio ``w``, bail-out test on a random subset of ``bailout_points`` correspondences, local
optimisation of every batch's best candidates). All 5-point samples of a batch are solved at once by
Nister's five-point method (:func:`~diffloc.geometry.epipolar.five_point_essential`, up to
10 real candidates per sample), and all candidates are scored in one batched pass with
:func:`kornia.geometry.epipolar.sampson_epipolar_distance` and the MSAC cost (truncated
squared error). The ``lo_candidates`` best models of every batch are locally optimised
(LO-RANSAC, Chum et al. 2003): Gauss-Newton steps on the Sampson distances of their inliers
over the 5-dof essential manifold, each re-scored and kept only if the MSAC cost drops, and
the best of them becomes the best model if it beats it; the final best model is polished the
same way for up to ``refine_iterations`` steps. (kornia's non-minimal solver, the 5-point
method on the 4-dimensional least-squares null space, was tried for LO first: at 1 px noise
its fits to the true inliers were worse than the best minimal sample.)

On a badly conditioned geometry (small baseline against the depth range) the MSAC optimum
itself can lie a few hundredths (unit-norm Frobenius distance) from the true ``E``; the inlier
set, which is what the relocaliser uses, is much less sensitive.

Example:
    >>> import math
    >>> from diffloc.geometry.camera import PinholeCamera
    >>> from diffloc.geometry.se3 import se3_exp
    >>> cam = PinholeCamera.from_fov(640, 480, math.pi / 2, dtype=torch.float64)
    >>> g = torch.Generator().manual_seed(0)
    >>> X = torch.rand(100, 3, generator=g, dtype=torch.float64) * 4 - 2
    >>> X[:, 2] += 6.0
    >>> T_qk = se3_exp(torch.tensor([0.3, -0.1, 0.2, 0.05, -0.1, 0.08], dtype=torch.float64))
    >>> uv_kf = cam.project(X)[0]
    >>> uv_q = cam.project(X @ T_qk[:3, :3].T + T_qk[:3, 3])[0]
    >>> r = essential_check(uv_kf, uv_q, cam, cam, EssentialCheckConfig(), g)
    >>> r.success, r.num_inliers
    (True, 100)
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch
from kornia.geometry.epipolar import sampson_epipolar_distance

from diffloc.checks import ShapeError, check_finite, check_ransac_settings, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.epipolar import decompose_essential, five_point_essential
from diffloc.geometry.ransac import bailout_keep, bailout_subset, ransac
from diffloc.geometry.se3 import hat, so3_exp
from diffloc.threads import intra_op_threads

__all__ = ["EssentialCheckConfig", "EssentialCheckResult", "essential_check"]

_SAMPLE_SIZE = 5
_GN_DAMPING = 1e-9  # relative to the mean diagonal of J^T J, only against singular steps
_LO_COST_TOL = 1e-6  # LO stops once the inlier set is stable and the cost drops less than this


@dataclass
class EssentialCheckConfig:
    """Settings of :func:`essential_check`.

    Attributes:
        threshold_px: inlier threshold on the Sampson distance in pixels. For keypoint noise
            ``sigma`` in both images the squared Sampson distance is about ``sigma^2`` times a
            chi-square variable with one degree of freedom, so 3 px keeps ~99.7 % of the
            inliers at 1 px noise (OpenCV's default is 1 px, which keeps ~68 %).
        confidence: probability of drawing at least one all-inlier 5-point sample; sets the
            adaptive number of samples.
        min_iterations: fewest 5-point samples drawn; also the size of the first batch. 128
            covers the adaptive count up to ~45 % outliers in one batch (a second, small
            batch costs almost as much as the first: solve, score and LO all run again).
        max_iterations: most 5-point samples drawn.
        batch_size: most samples solved and scored together (each gives up to 10 candidate
            matrices, typically ~4 real ones), except that a remainder of fewer than
            ``min(min_iterations, batch_size)`` samples joins the batch before it.
        min_inliers: the check passes (``success``) only with at least this many inliers.
        bailout_points: size of the random subset every candidate is scored on first; only
            candidates that pass :func:`~diffloc.geometry.ransac.bailout_keep` on it are
            scored on all correspondences. 0 (or fewer than twice as many correspondences)
            scores all candidates on all points.
        lo_rounds: most local-optimisation steps (Gauss-Newton on the Sampson distances of
            the inliers, then a re-score) per locally optimised candidate; 0 disables LO.
        lo_candidates: how many of the best models of every batch are locally optimised
            (the MSAC cost has local minima: LO from the single best sample of a batch ended
            on a worse one than LO from the second or third in tests at 1 px noise).
        refine_iterations: most Gauss-Newton steps (each re-scored, as in LO) polishing the
            final best model; 0 disables it.
        num_threads: torch intra-op threads while solving (restored afterwards); ``None``
            leaves torch's setting alone.

    Raises:
        ValueError: an out-of-range setting.
    """

    threshold_px: float = 3.0
    confidence: float = 0.999
    min_iterations: int = 128
    max_iterations: int = 1024
    batch_size: int = 512
    min_inliers: int = 15
    bailout_points: int = 64
    lo_rounds: int = 3
    lo_candidates: int = 4
    refine_iterations: int = 10
    num_threads: int | None = 1

    def __post_init__(self) -> None:
        check_ransac_settings(self, _SAMPLE_SIZE)
        if self.lo_candidates < 1:
            raise ValueError(f"lo_candidates must be >= 1, got {self.lo_candidates}")


@dataclass(frozen=True)
class EssentialCheckResult:
    """Output of :func:`essential_check`.

    Attributes:
        inliers: (N,) bool, Sampson distance at most ``threshold_px`` under ``E`` (all false
            when no model was found). Keep the matches only if ``success``.
        E: (3, 3) float64 essential matrix with ``x_q^T E x_kf = 0`` and unit Frobenius norm,
            or ``None`` when no model was found (fewer than 5 usable correspondences or only
            degenerate samples).
        num_inliers: ``int(inliers.sum())``.
        iterations: number of 5-point samples drawn.
        success: a model with at least ``min_inliers`` inliers was found.
        sampson_errors_px: (N,) float64 Sampson distances in pixels under ``E`` (all ``inf``
            when no model was found, ``inf`` for keypoints that cannot be undistorted).
    """

    inliers: torch.Tensor
    E: torch.Tensor | None
    num_inliers: int
    iterations: int
    success: bool
    sampson_errors_px: torch.Tensor


@dataclass(frozen=True)
class _Problem:
    """Correspondences in the forms the solver (normalised) and scoring (scaled) use."""

    xy_kf: torch.Tensor  # (M, 2) undistorted normalised keyframe coordinates
    xy_q: torch.Tensor  # (M, 2) same in the query
    scaled_kf: torch.Tensor  # (1, M, 2) xy_kf * f_kf
    scaled_q: torch.Tensor  # (1, M, 2) xy_q * f_q
    homogeneous_kf: torch.Tensor  # (M, 3) (scaled_kf, 1)
    homogeneous_q: torch.Tensor  # (M, 3) (scaled_q, 1)
    subset: torch.Tensor | None  # (S,) indices of the bail-out subset, None: no bail-out
    unscale: torch.Tensor  # (3, 3) elementwise factor turning E into the scaled-space F


@dataclass(frozen=True)
class _Models:
    """K models and their scores on all M correspondences; ``cost`` and ``num_inliers`` are
    those of the first (a :class:`~diffloc.geometry.ransac.RansacModel`)."""

    E: torch.Tensor  # (K, 3, 3)
    err2: torch.Tensor  # (K, M) squared scaled Sampson distances
    inliers: torch.Tensor  # (K, M) bool, err2 at most the squared threshold
    costs: torch.Tensor  # (K,) MSAC costs

    @staticmethod
    def scored(E: torch.Tensor, problem: _Problem, threshold2: float) -> _Models:
        err2 = _score(E, problem)
        return _Models(E, err2, err2 <= threshold2, err2.clamp(max=threshold2).sum(dim=1))

    def __getitem__(self, index: torch.Tensor | slice) -> _Models:
        return _Models(self.E[index], self.err2[index], self.inliers[index], self.costs[index])

    @property
    def cost(self) -> float:
        return float(self.costs[0])

    @property
    def num_inliers(self) -> int:
        return int(self.inliers[0].sum())


def _normalised(keypoints: torch.Tensor, camera: PinholeCamera) -> tuple[torch.Tensor, float]:
    """Undistorted normalised coordinates (N, 2) and the mean focal length in pixels."""
    cam = camera
    if camera.dtype != torch.float64 or camera.device != keypoints.device:
        cam = camera.to(dtype=torch.float64, device=keypoints.device)
    focal = torch.stack((cam.fx, cam.fy))
    centre = torch.stack((cam.cx, cam.cy))
    xy = cam.undistort_normalized((keypoints - centre) / focal)
    return xy, float(focal.mean())


def _as_keypoints(x: torch.Tensor | np.ndarray, name: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor | np.ndarray):
        raise TypeError(f"{name} must be a torch.Tensor or numpy array, got {type(x).__name__}")
    x = torch.as_tensor(x)
    check_shape(x, "N,2", name)
    check_finite(x, name)
    return x.to(torch.float64)


def _score(E: torch.Tensor, problem: _Problem) -> torch.Tensor:
    """Squared pixel Sampson distances (H, M) of H essential matrices (H, 3, 3)."""
    return sampson_epipolar_distance(problem.scaled_kf, problem.scaled_q, E * problem.unscale)


def _candidates(
    E: torch.Tensor, problem: _Problem, threshold2: float, k: int, best_ratio: float
) -> _Models | None:
    """The ``k`` lowest-MSAC-cost models among (H, 10, 3, 3) five-point slots, best first.

    NaN slots (complex roots, degenerate samples) are skipped; with a bail-out subset, only
    the candidates passing :func:`~diffloc.geometry.ransac.bailout_keep` on it are scored on
    all correspondences.
    ``None`` if no candidate is left.
    """
    E = E.reshape(-1, 3, 3)
    E = E[torch.isfinite(E).flatten(1).all(dim=1)]
    if E.shape[0] > k and problem.subset is not None:
        sub = problem.subset
        err2 = sampson_epipolar_distance(
            problem.scaled_kf[:, sub], problem.scaled_q[:, sub], E * problem.unscale
        )
        keep = bailout_keep((err2 <= threshold2).sum(dim=1), len(sub), best_ratio)
        if keep is not None:
            E = E[keep]
    if E.shape[0] == 0:
        return None
    models = _Models.scored(E, problem, threshold2)
    return models[models.costs.topk(min(k, E.shape[0]), largest=False).indices]


def _gauss_newton_step(E: torch.Tensor, problem: _Problem, weights: torch.Tensor) -> torch.Tensor:
    """One Gauss-Newton step per model on its weighted squared Sampson distances.

    ``E = [t]_x R`` is perturbed on the essential manifold: ``R exp([w]_x)`` and
    ``normalize(t + basis d)``, five parameters ``(w, d)``; the signed Sampson distance
    ``x_q^T F x_kf / sqrt(|(F x_kf)_12|^2 + |(F^T x_q)_12|^2)`` is differentiated in closed form.

    Args:
        E: (K, 3, 3) essential matrices.
        problem: the correspondences.
        weights: (K, M) per-model weights (0/1 inlier masks).

    Returns:
        (K, 3, 3) updated essential matrices (unit-norm ``t``).
    """
    R, t, basis = decompose_essential(E)
    eye = torch.eye(3, dtype=E.dtype, device=E.device)
    T = hat(t)  # (K, 3, 3)
    # dE/dw_i = [t]_x R [e_i]_x, dE/dd_j = [b_j]_x R: (K, 5, 3, 3)
    dE = torch.cat((T[:, None] @ R[:, None] @ hat(eye), hat(basis.mT) @ R[:, None]), dim=1)
    F = (T @ R) * problem.unscale
    dF = dE * problem.unscale
    x1, x2 = problem.homogeneous_kf, problem.homogeneous_q  # (M, 3)
    l1 = torch.einsum("kij,mj->kmi", F, x1)  # (K, M, 3) F x1
    l2 = torch.einsum("kji,mj->kmi", F, x2)  # (K, M, 3) F^T x2
    dl1 = torch.einsum("kpij,mj->kpmi", dF, x1)  # (K, 5, M, 3)
    dl2 = torch.einsum("kpji,mj->kpmi", dF, x2)
    num = (x2 * l1).sum(-1)  # (K, M)
    den = l1[..., :2].square().sum(-1) + l2[..., :2].square().sum(-1)
    dnum = (x2 * dl1).sum(-1)  # (K, 5, M)
    dden = 2.0 * (
        (l1[:, None, :, :2] * dl1[..., :2]).sum(-1) + (l2[:, None, :, :2] * dl2[..., :2]).sum(-1)
    )
    used = (weights > 0) & (den > 0)
    inv_sqrt = torch.where(used, den, 1.0).rsqrt()
    residual = torch.where(used, num * inv_sqrt, 0.0)
    J = (dnum - 0.5 * residual[:, None] * inv_sqrt[:, None] * dden) * inv_sqrt[:, None]
    Jw = torch.where(used[:, None], J * weights[:, None], 0.0)
    H = Jw @ J.mT  # (K, 5, 5)
    damping = _GN_DAMPING * H.diagonal(dim1=-2, dim2=-1).mean(-1).clamp(min=1e-300)
    H = H + damping[:, None, None] * torch.eye(5, dtype=E.dtype, device=E.device)
    delta = -torch.linalg.solve(H, (Jw @ residual[..., None]))[..., 0]  # (K, 5)
    R_new = R @ so3_exp(delta[:, :3])
    t_new = torch.nn.functional.normalize(t + (basis @ delta[:, 3:, None])[..., 0], dim=-1)
    return hat(t_new) @ R_new


def _local_optimisation(
    models: _Models, problem: _Problem, threshold2: float, rounds: int
) -> _Models:
    """Gauss-Newton on each model's current inliers, re-scored after every step (LO-RANSAC).

    All K models step together. A model takes a step only if it lowers its MSAC cost (so the
    inlier set may change between steps); a model stops at the first step that does not, or
    once its inlier count is stable and its cost drops by less than a relative
    ``_LO_COST_TOL``. Models with at most 5 inliers are left alone.
    """
    active = models.inliers.sum(dim=1) > _SAMPLE_SIZE
    for _ in range(rounds):
        if not bool(active.any()):
            break
        weights = models.inliers.to(models.E.dtype)
        step = _Models.scored(_gauss_newton_step(models.E, problem, weights), problem, threshold2)
        accept = active & (step.costs < models.costs) & torch.isfinite(step.E).flatten(1).all(1)
        stable = (step.inliers.sum(1) == models.inliers.sum(1)) & (
            models.costs - step.costs < _LO_COST_TOL * models.costs
        )
        models = _Models(
            torch.where(accept[:, None, None], step.E, models.E),
            torch.where(accept[:, None], step.err2, models.err2),
            torch.where(accept[:, None], step.inliers, models.inliers),
            torch.where(accept, step.costs, models.costs),
        )
        active = accept & ~stable
    return models


@dataclass(frozen=True)
class _Search:
    """The check as a :class:`~diffloc.geometry.ransac.RansacProblem`: five-point samples,
    the ``lo_candidates`` best of a batch (:func:`_candidates`), LO by
    :func:`_local_optimisation`."""

    problem: _Problem
    threshold2: float
    config: EssentialCheckConfig
    sample_size: int = _SAMPLE_SIZE
    lo_every_batch: bool = True  # the lo_candidates best of every batch

    @property
    def num_points(self) -> int:
        return self.problem.xy_kf.shape[0]

    def candidates(self, samples: torch.Tensor, best_ratio: float) -> _Models | None:
        E = five_point_essential(self.problem.xy_kf[samples], self.problem.xy_q[samples])
        return _candidates(E, self.problem, self.threshold2, self.config.lo_candidates, best_ratio)

    def local_optimisation(self, candidates: _Models) -> _Models:
        models = _local_optimisation(
            candidates, self.problem, self.threshold2, self.config.lo_rounds
        )
        j = int(models.costs.argmin())
        return models[j : j + 1]


def essential_check(
    keypoints_kf: torch.Tensor | np.ndarray,
    keypoints_query: torch.Tensor | np.ndarray,
    camera_kf: PinholeCamera,
    camera_query: PinholeCamera,
    config: EssentialCheckConfig,
    generator: torch.Generator,
) -> EssentialCheckResult:
    """Robust essential matrix between a keyframe and a query, and the matches it keeps.

    Fewer than 5 usable correspondences, or only degenerate samples, give ``E = None``, an
    all-false mask and ``success = False`` (not an exception). Keyframe keypoints outside the
    keyframe image are used as they are. Keypoints whose undistortion does not converge to a
    finite value (possible only far outside the calibrated field of view of a distorted
    camera) are never sampled and never inliers.

    Args:
        keypoints_kf: (N, 2) pixel coordinates in the keyframe (distorted, as detected or
            projected); may lie outside the image.
        keypoints_query: (N, 2) matching pixel coordinates in the query.
        camera_kf: the keyframe camera (batch shape ``()``); its distortion is removed first.
        camera_query: the query camera (batch shape ``()``).
        config: RANSAC settings.
        generator: the source of all randomness (same seed, same result).

    Returns:
        The :class:`EssentialCheckResult` (tensors on the keypoints' device, float64).

    Raises:
        ShapeError: shapes other than (N, 2) or different N.
        ValueError: NaN or infinite keypoints, or a batched camera.
        TypeError: keypoints that are neither tensors nor arrays.

    Example:
        >>> cam = PinholeCamera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
        >>> r = essential_check(torch.zeros(3, 2), torch.zeros(3, 2), cam, cam,
        ...                     EssentialCheckConfig(), torch.Generator().manual_seed(0))
        >>> r.E is None, r.success, r.inliers.tolist()
        (True, False, [False, False, False])
    """
    uv_kf = _as_keypoints(keypoints_kf, "keypoints_kf")
    uv_q = _as_keypoints(keypoints_query, "keypoints_query").to(uv_kf.device)
    if uv_kf.shape != uv_q.shape:
        raise ShapeError(
            f"keypoints_kf and keypoints_query must both be (N, 2) with the same N, got "
            f"{tuple(uv_kf.shape)} and {tuple(uv_q.shape)}"
        )
    for name, cam in (("camera_kf", camera_kf), ("camera_query", camera_query)):
        if cam.batch_shape != torch.Size([]):
            raise ValueError(f"{name} must be one camera, got batch {tuple(cam.batch_shape)}")
    with intra_op_threads(config.num_threads):
        return _essential_check(uv_kf, uv_q, camera_kf, camera_query, config, generator)


def _essential_check(
    uv_kf: torch.Tensor,
    uv_q: torch.Tensor,
    camera_kf: PinholeCamera,
    camera_query: PinholeCamera,
    config: EssentialCheckConfig,
    generator: torch.Generator,
) -> EssentialCheckResult:
    n = uv_kf.shape[0]
    errors = torch.full((n,), math.inf, dtype=torch.float64, device=uv_kf.device)
    no_model = EssentialCheckResult(
        inliers=torch.zeros(n, dtype=torch.bool, device=uv_kf.device),
        E=None,
        num_inliers=0,
        iterations=0,
        success=False,
        sampson_errors_px=errors,
    )
    if n < _SAMPLE_SIZE:
        return no_model
    xy_kf, f_kf = _normalised(uv_kf, camera_kf)
    xy_q, f_q = _normalised(uv_q, camera_query)
    usable = torch.isfinite(xy_kf).all(dim=1) & torch.isfinite(xy_q).all(dim=1)
    if int(usable.sum()) < _SAMPLE_SIZE:
        return no_model
    xy_kf, xy_q = xy_kf[usable], xy_q[usable]
    # F = diag(1/f_q, 1/f_q, 1) E diag(1/f_kf, 1/f_kf, 1) acts on the scaled coordinates.
    s_kf = torch.tensor([1.0 / f_kf, 1.0 / f_kf, 1.0], dtype=torch.float64, device=uv_kf.device)
    s_q = torch.tensor([1.0 / f_q, 1.0 / f_q, 1.0], dtype=torch.float64, device=uv_kf.device)
    m = xy_kf.shape[0]
    subset = bailout_subset(m, config.bailout_points, generator)
    problem = _Problem(
        xy_kf=xy_kf,
        xy_q=xy_q,
        scaled_kf=(xy_kf * f_kf)[None],
        scaled_q=(xy_q * f_q)[None],
        homogeneous_kf=torch.nn.functional.pad(xy_kf * f_kf, (0, 1), value=1.0),
        homogeneous_q=torch.nn.functional.pad(xy_q * f_q, (0, 1), value=1.0),
        subset=None if subset is None else subset.to(uv_kf.device),
        unscale=s_q[:, None] * s_kf[None, :],
    )
    threshold2 = config.threshold_px**2
    best, drawn = ransac(_Search(problem, threshold2, config), config, generator)
    if best is None:
        return dataclasses.replace(no_model, iterations=drawn)
    best = _local_optimisation(best, problem, threshold2, config.refine_iterations)
    inliers = torch.zeros(n, dtype=torch.bool, device=uv_kf.device)
    inliers[usable] = best.inliers[0]
    errors[usable] = best.err2[0].sqrt()
    num_inliers = int(inliers.sum())
    return EssentialCheckResult(
        inliers=inliers,
        E=best.E[0] / torch.linalg.matrix_norm(best.E[0]),
        num_inliers=num_inliers,
        iterations=drawn,
        success=num_inliers >= config.min_inliers,
        sampson_errors_px=errors,
    )
