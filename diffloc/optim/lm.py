"""Batched Levenberg-Marquardt over SE(3) poses (and a few Euclidean parameters).

Problem
    ``B`` independent problems (a leading batch dimension) share one block structure. Each
    holds ``P`` camera-to-world poses ``T_wc`` (B, P, 4, 4) and optionally ``E`` extra
    Euclidean parameters (B, E). Residual block ``m`` (of ``M``) is a vector ``r_m`` of size
    ``R`` that depends on pose ``index_a[m]``, optionally on a second pose ``index_b[m]``, and
    on the extra parameters. Residuals are whitened by the caller (multiplied by the square
    root of their information matrix). The cost is (see :mod:`diffloc.optim.robust`)::

        F = 0.5 * sum_m mask_m * rho(||r_m||^2)

Pose update (right, body-frame perturbation)
    ``T_wc <- T_wc @ [[Cay(w), v], [0, 1]]`` with ``delta = [v, w]`` (translation first, as in
    :mod:`diffloc.geometry.se3`) expressed in the camera frame and ``Cay`` the Cayley map
    (:func:`cayley_rotation`). This retraction agrees with ``T_wc @ se3_exp(delta)`` to first
    order (so the Jacobians are the same) and costs a handful of tensor operations instead of
    the exponential's trigonometric branches. Jacobians given by the caller
    must follow this convention: ``J_a = d r(T_a @ se3_exp(d)) / d d`` at ``d = 0``. For a
    reprojection residual ``r = project(T_cw X) - p`` this is
    ``-camera.project_jacobian_pose(X_cam)`` (that method perturbs ``T_cw`` on the left,
    which is ``T_wc`` on the right with the opposite sign). A body-frame step makes the
    damping independent of where the world origin lies. Extra parameters are updated
    additively.

Algorithm
    IRLS Gauss-Newton: ``H = sum w_m J_m^T J_m``, ``g = sum w_m J_m^T r_m`` with
    ``w_m = rho'(||r_m||^2)`` (``g`` is the exact gradient of ``F``). Marquardt damping
    ``(H + lambda * diag(clamp(diag(H), min_diagonal))) delta = -g`` and Nielsen's update of
    ``lambda`` from the gain ratio ``(F - F_new) / (model decrease)`` (accept when positive:
    ``lambda *= max(1/3, 1 - (2 rho - 1)^3)``; reject: ``lambda *= nu, nu *= 2``). A step whose
    predicted decrease is within rounding error of the cost counts as ideal whatever the
    measured change (which is noise there), so problems with non-zero residuals still converge
    to full precision; the cost history may then rise by rounding noise. Every
    problem of the batch has its own ``lambda`` and stops on its own: small gradient
    (``max |g|``); a step whose length (``||delta||``, mixed metres/radians) or predicted
    decrease (relative to the cost) is below ``step_tolerance`` / ``cost_tolerance``, which is
    then not evaluated nor taken (the parameters are within about that much of the optimum;
    the predicted decrease only without step expansions, which can beat it);
    an accepted step that lowered the cost by at most ``cost_tolerance`` of it;
    ``max_iterations`` linear solves; or ``lambda > max_damping`` (failure). A damped system
    Cholesky cannot factor (one-pose problems) counts as a failed step. The pose gauge is
    fixed by holding chosen poses constant (their rows and columns are removed).

One loop, several problems
    :func:`minimize` is the loop; a problem (:class:`LMProblem`) linearizes, evaluates and
    retracts its own parameters, and its normal equations (:class:`LinearSystem`) solve the
    damped step. :func:`levenberg_marquardt` (block-sparse poses and extra parameters) and
    :func:`levenberg_marquardt_single_pose` (batched 6x6 :class:`PoseSystem`) are its front
    ends; :func:`diffloc.optim.motion_cost.refine_pose` plugs in its own lean reprojection
    problem (world-to-camera poses, matches innermost) with :class:`PoseSystem` normal
    equations.

Step expansions (``LMConfig.step_expansions``, off by default)
    Under a redescending kernel (Cauchy) the IRLS model overestimates the curvature of the
    robust cost, so even undamped steps are systematically short (by 2-6x on the surfel
    problem of seed 1) and LM converges slowly. After an accepted step, steps 2, 4, ... times
    as long are tried (residual evaluations only, no solve) while the cost keeps falling. Poses
    whose blocks are mostly down-weighted outliers (``support``, the robust weights on the
    pose summed over its residual components, below ``expansion_min_support``) keep the
    plain step: the robust cost is nearly flat for them, and lengthened steps could carry them
    far away. The damping update still uses the gain ratio of the plain step.

Linear solvers and memory
    The normal equations are assembled block-sparse (one 6x6 block per free pose and per
    pair of poses sharing a residual block), component-major: each entry of the blocks'
    products ``J^T W J`` is computed for all residual blocks at once and scattered by
    ``index_add_`` (no per-block matrix products). ``solver="cholesky"`` then writes the dense
    Jacobi-scaled damped matrix of ``D = 6 * P_free + E`` unknowns per problem in float32
    (``4 * D^2`` bytes: 100 poses: 1.4 MB, 1000 poses: 144 MB, 2000 poses: 576 MB) and
    factors it (``O(D^3)``, about half the float64 time); iterative refinement with float64
    residuals from the blocks brings the step to float64 accuracy. Problems whose float32
    factorization fails or whose refinement stalls (condition number near ``1 / eps_float32``)
    are solved by a float64 Cholesky of the same matrix (another ``8 * D^2`` bytes), which
    falls back to least squares when the damped matrix is not positive definite; after such a
    fallback the rest of the run factors in float64 directly (the conditioning tends to worsen
    as the damping falls). One-pose problems solve their 6x6 systems in float64 throughout.
    ``solver="cg"`` runs block-Jacobi preconditioned conjugate gradients on the block-sparse
    normal equations, with memory and time per CG iteration linear in the number of blocks.
    Limitations: no sparse Cholesky or Schur complement (per-point structure must be
    eliminated by the caller, as in seed 1 Eq. 3, or kept out of the problem), and extra
    parameters form a dense block, meant for a few global parameters such as intrinsics or a
    time offset.

Autodiff Jacobians
    When no analytic ``jacobian_fn`` is given, Jacobians come from :func:`torch.func.jacfwd`
    with respect to a zero tangent shared by all blocks (each block depends only on its own
    gathered poses, so one forward-mode pass per tangent direction gives every block's
    Jacobian). The residual function must then be composable with ``torch.func`` (no Python
    control flow on tensor values, no ``.item()``).

Example:
    >>> targets = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    >>> def residual_fn(T_a, T_b, extra):  # pose translation minus a target
    ...     return T_a[..., :3, 3] - targets
    >>> result = levenberg_marquardt(
    ...     torch.eye(4, dtype=torch.float64)[None], residual_fn, torch.tensor([0]))
    >>> result.T_wc[0, :3, 3].round(decimals=9)
    tensor([1., 2., 3.], dtype=torch.float64)
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Any, Protocol

import torch

from diffloc.checks import ShapeError, check_finite, check_positive_int, check_shape
from diffloc.geometry.se3 import se3_exp
from diffloc.optim.robust import KernelFn, RobustKernel, make_robust_kernel

__all__ = [
    "BlockJacobianFn",
    "BlockLinearization",
    "BlockResidualFn",
    "LMConfig",
    "LMProblem",
    "LMResult",
    "LMRun",
    "LinearSystem",
    "PoseJacobianFn",
    "PoseResidualFn",
    "PoseSystem",
    "SOLVERS",
    "autodiff_linearize",
    "cayley_rotation",
    "levenberg_marquardt",
    "levenberg_marquardt_single_pose",
    "minimize",
    "solve_spd",
]

SOLVERS = ("cholesky", "cg")
"""Linear solvers accepted by :class:`LMConfig`."""

# Stop reasons, indexed by the per-problem status code used inside the solver loop.
_RUNNING, _GRADIENT, _STEP, _COST, _MAX_ITERATIONS, _DAMPING, _INACTIVE = range(7)
_REASONS = ("running", "gradient", "step", "cost", "max_iterations", "damping", "inactive")
_CONVERGED_REASONS = ("gradient", "step", "cost")
_ROUNDOFF_EPS = 16.0
"""Cost changes below this many machine epsilons of the cost are rounding noise."""
_REFINE_TOLERANCE = 1e-10
"""Mixed-precision dense solves refine until ``||b - A x|| <=`` this times ``||b||``."""
_REFINE_CONTRACTION = 0.5
"""Refinement stalls (and falls back to float64) when a pass shrinks the residual less."""
_MAX_REFINEMENTS = 8
"""Most refinement passes of a mixed-precision dense solve."""


@dataclass
class LMConfig:
    """Settings of :func:`levenberg_marquardt` and :func:`levenberg_marquardt_single_pose`.

    Attributes:
        max_iterations: most linear solves (accepted or rejected steps) per problem.
        initial_damping: starting ``lambda`` (relative to ``diag(H)``).
        min_damping: ``lambda`` never drops below this.
        max_damping: a problem whose ``lambda`` exceeds this stops as failed (``"damping"``).
        min_diagonal: floor of ``diag(H)`` in the damping matrix (keeps unobserved directions
            regular).
        gradient_tolerance: stop when ``max |g| <=`` this (``"gradient"``).
        step_tolerance: stop when ``||delta|| <=`` this (``"step"``).
        cost_tolerance: stop when an accepted step lowers the cost by at most this fraction
            of it (``"cost"``).
        solver: ``"cholesky"`` (dense) or ``"cg"`` (block-sparse PCG), see the module notes.
        step_expansions: after an accepted step, also try it 2, 4, ... times as long (at
            most this many doublings, each one residual evaluation) and keep the lowest cost.
            IRLS steps under a redescending kernel (Cauchy) are systematically short: the
            reweighted quadratic model overestimates the curvature of the robust cost. 0 (the
            default): plain Levenberg-Marquardt.
        expansion_min_support: only poses whose blocks' robust weights, times the residual
            size ``R``, sum to at least this are expanded (default 6, the pose's degrees of
            freedom): poses constrained mostly by down-weighted outliers keep the plain step.
        cg_max_iterations: most CG iterations per linear solve.
        cg_tolerance: CG stops when ``||residual|| <= cg_tolerance * ||g||``.

    Raises:
        ValueError: non-positive counts or tolerances, an unknown solver, or
            ``min_damping > initial_damping`` / ``initial_damping >= max_damping``.

    Example:
        >>> LMConfig(max_iterations=10, solver="cg").solver
        'cg'
    """

    max_iterations: int = 50
    initial_damping: float = 1e-4
    min_damping: float = 1e-12
    max_damping: float = 1e12
    min_diagonal: float = 1e-6
    gradient_tolerance: float = 1e-10
    step_tolerance: float = 1e-10
    cost_tolerance: float = 1e-12
    solver: str = "cholesky"
    step_expansions: int = 0
    expansion_min_support: float = 6.0
    cg_max_iterations: int = 200
    cg_tolerance: float = 1e-10

    def __post_init__(self) -> None:
        check_positive_int(self.max_iterations, "max_iterations")
        check_positive_int(self.cg_max_iterations, "cg_max_iterations")
        expansions = self.step_expansions
        if isinstance(expansions, bool) or not isinstance(expansions, int) or expansions < 0:
            raise ValueError(f"step_expansions must be a non-negative integer, got {expansions!r}")
        for field in fields(self):
            value = getattr(self, field.name)
            if isinstance(value, float) and not value > 0.0:
                raise ValueError(f"{field.name} must be positive, got {value}")
        if not self.min_damping <= self.initial_damping < self.max_damping:
            raise ValueError(
                "damping bounds must satisfy min_damping <= initial_damping < max_damping, got "
                f"{self.min_damping}, {self.initial_damping}, {self.max_damping}"
            )
        if self.solver not in SOLVERS:
            raise ValueError(f"unknown solver {self.solver!r}; choose one of {SOLVERS}")


@dataclass
class BlockLinearization:
    """Residual blocks and their Jacobians at the current parameters.

    Attributes:
        residuals: (B, M, R) whitened residuals.
        jac_a: (B, M, R, 6) Jacobians w.r.t. a right perturbation of pose ``index_a[m]``.
        jac_b: (B, M, R, 6) the same for pose ``index_b[m]``, or ``None`` (one-pose blocks).
        jac_extra: (B, M, R, E) Jacobians w.r.t. the extra parameters, or ``None``.
    """

    residuals: torch.Tensor
    jac_a: torch.Tensor
    jac_b: torch.Tensor | None = None
    jac_extra: torch.Tensor | None = None


BlockResidualFn = Callable[[torch.Tensor, torch.Tensor | None, torch.Tensor | None], torch.Tensor]
"""``(T_a (B, M, 4, 4), T_b (B, M, 4, 4) | None, extra (B, E) | None) -> (B, M, R)``: each
block's residual from the poses gathered at ``index_a`` / ``index_b`` (non-contiguous views:
each of the 16 pose entries is contiguous over the blocks)."""

BlockJacobianFn = Callable[
    [torch.Tensor, torch.Tensor | None, torch.Tensor | None], BlockLinearization
]
"""Same inputs as :data:`BlockResidualFn`, returns residuals and analytic Jacobians."""

PoseResidualFn = Callable[[torch.Tensor], torch.Tensor]
"""``T_wc (B, 4, 4) -> (B, N, R)``: residuals of ``B`` single-pose problems."""

PoseJacobianFn = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""``T_wc (B, 4, 4) -> (residuals (B, N, R), jacobians (B, N, R, 6))``, right perturbation."""


@dataclass
class LMResult:
    """Outcome of a Levenberg-Marquardt run.

    Leading dimensions ``(...)`` are ``(B,)`` for a batched call and ``()`` otherwise.

    Attributes:
        T_wc: optimised poses, (..., P, 4, 4) (multi-pose) or (..., 4, 4) (single-pose).
        extra: (..., E) optimised extra parameters, or ``None``.
        cost_history: (..., I + 1) cost before the first and after every iteration (costs of
            problems that stopped early are repeated), ``I`` the most iterations run.
        iterations: (...) int64 linear solves per problem.
        converged: (...) bool, stopped by a gradient, step or cost tolerance.
        reason: per problem (flattened batch order) one of ``"gradient"``, ``"step"``,
            ``"cost"`` (converged), ``"max_iterations"``, ``"damping"``.
    """

    T_wc: torch.Tensor
    extra: torch.Tensor | None
    cost_history: torch.Tensor
    iterations: torch.Tensor
    converged: torch.Tensor
    reason: tuple[str, ...]

    @property
    def cost(self) -> torch.Tensor:
        """(...) final cost."""
        return self.cost_history[..., -1]


# ---------------------------------------------------------------------------- linear algebra


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
    """Rotation matrices of the Cayley map, the cheap retraction of the LM pose updates.

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


def solve_spd(H: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Solve symmetric positive (semi-)definite systems ``H x = b``, batched.

    Cholesky where it succeeds; the batch entries where it fails (not positive definite)
    fall back to a least-squares solve, which gives the minimum-norm solution for singular
    ``H`` (zero for ``H = 0``).

    Args:
        H: (..., D, D) symmetric matrices.
        b: (..., D) right-hand sides.

    Returns:
        (..., D) solutions.

    Example:
        >>> solve_spd(torch.diag(torch.tensor([2.0, 4.0])), torch.tensor([2.0, 2.0]))
        tensor([1.0000, 0.5000])
    """
    check_shape(H, "*,D,D", "H")
    check_shape(b, "*,D", "b")
    L, info = torch.linalg.cholesky_ex(H)
    y = torch.linalg.solve_triangular(L, b[..., None], upper=False)
    x = torch.linalg.solve_triangular(L.mT, y, upper=True)[..., 0]
    failed = info != 0
    if bool(failed.any()):
        fallback = torch.linalg.lstsq(H[failed], b[failed][..., None], driver="gelsd")
        x[failed] = fallback.solution[..., 0]
    return x


def _pcg(
    matvec: Callable[[torch.Tensor], torch.Tensor],
    precondition: Callable[[torch.Tensor], torch.Tensor],
    b: torch.Tensor,
    max_iterations: int,
    tolerance: float,
) -> torch.Tensor:
    """Batched preconditioned conjugate gradients for SPD systems, ``b``: (B, D)."""

    def dot(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return (x * y).sum(-1)

    def safe_ratio(num: torch.Tensor, den: torch.Tensor) -> torch.Tensor:
        return torch.where(den > 0, num / torch.where(den > 0, den, 1.0), 0.0)

    x = torch.zeros_like(b)
    r = b.clone()
    z = precondition(r)
    p = z.clone()
    rz = dot(r, z)
    threshold = tolerance * torch.linalg.vector_norm(b, dim=-1)
    for _ in range(max_iterations):
        if bool((torch.linalg.vector_norm(r, dim=-1) <= threshold).all()):
            break
        Ap = matvec(p)
        alpha = safe_ratio(rz, dot(p, Ap))
        x = x + alpha[:, None] * p
        r = r - alpha[:, None] * Ap
        z = precondition(r)
        rz_new = dot(r, z)
        p = z + safe_ratio(rz_new, rz)[:, None] * p
        rz = rz_new
    return x


# ---------------------------------------------------------------------------- structure


@functools.lru_cache(maxsize=8)
def _upper_to_full(device: torch.device) -> torch.Tensor:
    """(36,) position in the row-major upper triangle (21 entries, ``i <= j``) of every
    entry ``(i, j)`` of a symmetric 6x6 matrix, row-major. Never modified in place."""
    with torch.inference_mode(False):  # an ordinary tensor even if first made in one
        position = torch.zeros(6, 6, dtype=torch.long, device=device)
        rows, cols = torch.triu_indices(6, 6, device=device)
        position[rows, cols] = position[cols, rows] = torch.arange(21, device=device)
    return position.flatten()


def _block_flat_index(rows: torch.Tensor, cols: torch.Tensor, size: int) -> torch.Tensor:
    """(N * 36,) flat indices into a (size, size) matrix of the 6x6 blocks at slot ``rows``
    (N,), ``cols`` (N,), entries row-major within each block."""
    eye6 = torch.arange(6, device=rows.device)
    row_index = (6 * rows[:, None, None] + eye6[None, :, None]) * size
    return (row_index + 6 * cols[:, None, None] + eye6[None, None, :]).flatten()


@dataclass
class _Structure:
    """Static sparsity of the normal equations, computed once per solve.

    Free poses get slots ``0 .. P_free - 1`` and fixed poses the extra slot ``P_free``, whose
    contributions the assembly drops. ``H`` is stored as one 6x6 diagonal block per free pose
    and ``K`` upper off-diagonal blocks, one per unordered pair of distinct free poses sharing
    a residual block: block ``k`` sits at slot row ``off_rows[k] <`` column ``off_cols[k]``
    and its transpose below the diagonal. Per residual block (M,): ``a_slot`` / ``b_slot``
    are the slots of its poses (``b_slot`` is ``P_free`` for a block whose two poses are the
    same: its Jacobians add up on ``a``), ``off_index`` its upper block (``K``: none),
    ``swap`` whether pose ``a`` is that block's column, ``same`` whether both poses are one.
    ``None``: one-pose blocks (``b_slot``, ``off_index``) or all false (``swap``, ``same``).
    """

    free: torch.Tensor  # (P_free,) pose index of each slot
    num_extra: int
    off_rows: torch.Tensor  # (K,)
    off_cols: torch.Tensor  # (K,)
    a_slot: torch.Tensor
    b_slot: torch.Tensor | None = None
    off_index: torch.Tensor | None = None
    swap: torch.Tensor | None = None
    same: torch.Tensor | None = None

    @property
    def num_free(self) -> int:
        return int(self.free.numel())

    @property
    def size(self) -> int:
        """Number of unknowns ``D = 6 P_free + E``."""
        return 6 * self.num_free + self.num_extra

    @functools.cached_property
    def dense_index(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Flat (D * D) positions of the diagonal blocks (P_free * 36,), the upper blocks
        (K * 36,) and their transposes (K * 36,, entry ``(k, i, j)`` at ``(col j, row i)``)."""
        diag = torch.arange(self.num_free, device=self.free.device)
        rows, cols, size = self.off_rows, self.off_cols, self.size
        upper = _block_flat_index(rows, cols, size)
        lower = _block_flat_index(cols, rows, size).view(-1, 6, 6).mT.flatten()
        return _block_flat_index(diag, diag, size), upper, lower

    @classmethod
    def from_blocks(
        cls,
        num_poses: int,
        index_a: torch.Tensor,
        index_b: torch.Tensor | None,
        is_fixed: torch.Tensor,
        num_extra: int,
    ) -> _Structure:
        device = index_a.device
        free = torch.nonzero(~is_fixed.to(device))[:, 0]
        n_free = int(free.numel())
        slot_of = torch.full((num_poses,), n_free, dtype=torch.long, device=device)
        slot_of[free] = torch.arange(n_free, device=device)
        a_slot = slot_of[index_a]
        empty = torch.zeros(0, dtype=torch.long, device=device)
        if index_b is None:
            return cls(free, num_extra, empty, empty, a_slot)
        same = index_a == index_b
        b_slot = torch.where(same, n_free, slot_of[index_b])
        paired = (a_slot < n_free) & (b_slot < n_free)
        key = torch.minimum(a_slot, b_slot) * n_free + torch.maximum(a_slot, b_slot)
        unique, inverse = torch.unique(key[paired], return_inverse=True)
        off_index = torch.full_like(a_slot, unique.numel())
        off_index[paired] = inverse
        swap = paired & (a_slot > b_slot)
        return cls(
            free=free,
            num_extra=num_extra,
            off_rows=torch.div(unique, n_free, rounding_mode="floor"),
            off_cols=unique % n_free,
            a_slot=a_slot,
            b_slot=b_slot,
            off_index=off_index,
            swap=swap if bool(swap.any()) else None,
            same=same if bool(same.any()) else None,
        )


# ---------------------------------------------------------------------------- normal equations


@dataclass
class _System:
    """Block-sparse normal equations of ``B`` problems at the current parameters.

    ``diag_blocks`` (B, P_free, 6, 6) and ``off_blocks`` (B, K, 6, 6) are the diagonal and
    upper off-diagonal pose blocks of ``H`` (see :class:`_Structure`), ``H_pe``
    (B, P_free, 6, E) and ``H_ee`` (B, E, E) the extra-parameter parts, ``grad`` (B, D) the
    gradient, ``cost`` (B,) the cost and ``support`` (B, P_free) the sum over the blocks on
    each pose of their robust weight times ``R`` (how many residual components effectively
    constrain the pose).
    """

    cost: torch.Tensor
    grad: torch.Tensor
    diag_blocks: torch.Tensor
    off_blocks: torch.Tensor
    H_pe: torch.Tensor
    H_ee: torch.Tensor
    support: torch.Tensor
    structure: _Structure

    def where(self, mask: torch.Tensor, other: _System) -> _System:
        """Per problem: ``other`` where ``mask`` (B,) is true, else ``self``."""

        def pick(new: torch.Tensor, old: torch.Tensor) -> torch.Tensor:
            return torch.where(mask.reshape(-1, *[1] * (new.dim() - 1)), new, old)

        return _System(
            pick(other.cost, self.cost),
            pick(other.grad, self.grad),
            pick(other.diag_blocks, self.diag_blocks),
            pick(other.off_blocks, self.off_blocks),
            pick(other.H_pe, self.H_pe),
            pick(other.H_ee, self.H_ee),
            pick(other.support, self.support),
            self.structure,
        )

    def diagonal(self) -> torch.Tensor:
        """(B, D) diagonal of ``H``."""
        pose = self.diag_blocks.diagonal(dim1=-2, dim2=-1).flatten(1)
        return torch.cat((pose, self.H_ee.diagonal(dim1=-2, dim2=-1)), dim=1)

    def dense(self, scale: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """(B, D, D) dense ``S H S`` in ``dtype`` (a new tensor), ``S = diag(scale)`` (B, D).

        Scaled block by block, before the (much larger) dense matrix is written.
        """
        s = self.structure
        B, n6, D = self.grad.shape[0], 6 * s.num_free, s.size
        s_p = scale[:, :n6].reshape(B, s.num_free, 6)
        diag = self.diag_blocks * s_p[..., :, None] * s_p[..., None, :]
        off = self.off_blocks * s_p[:, s.off_rows, :, None] * s_p[:, s.off_cols, None, :]
        off = off.flatten(1).to(dtype)
        H = self.grad.new_zeros(B, D, D, dtype=dtype)
        diag_index, upper_index, lower_index = s.dense_index
        flat = H.view(B, -1)
        flat[:, diag_index] = diag.flatten(1).to(dtype)
        flat[:, upper_index] = off
        flat[:, lower_index] = off
        if s.num_extra:
            s_e = scale[:, n6:]
            H_pe = self.H_pe * s_p[..., None] * s_e[:, None, None, :]
            H_pe = H_pe.reshape(B, n6, s.num_extra).to(dtype)
            H[:, :n6, n6:] = H_pe
            H[:, n6:, :n6] = H_pe.transpose(1, 2)
            H[:, n6:, n6:] = (self.H_ee * s_e[:, :, None] * s_e[:, None, :]).to(dtype)
        return H

    def matvec(self, x: torch.Tensor) -> torch.Tensor:
        """(B, D) product ``H x`` from the blocks, ``x``: (B, D)."""
        s = self.structure
        n6 = 6 * s.num_free
        x_p = x[:, :n6].reshape(x.shape[0], s.num_free, 6, 1)
        y_p = (self.diag_blocks @ x_p)[..., 0]
        if s.off_rows.numel():
            y_p.index_add_(1, s.off_rows, (self.off_blocks @ x_p[:, s.off_cols])[..., 0])
            y_p.index_add_(1, s.off_cols, (self.off_blocks.mT @ x_p[:, s.off_rows])[..., 0])
        if not s.num_extra:
            return y_p.flatten(1)
        x_e = x[:, n6:]
        y_p = y_p + (self.H_pe @ x_e[:, None, :, None])[..., 0]
        y_e = torch.einsum("bpie,bpi->be", self.H_pe, x_p[..., 0])
        y_e = y_e + (self.H_ee @ x_e[..., None])[..., 0]
        return torch.cat((y_p.flatten(1), y_e), dim=1)

    def model_change(self, delta: torch.Tensor) -> torch.Tensor:
        """(B,) change of the quadratic model, ``g.delta + delta.H.delta / 2``, delta (B, D)."""
        return (torch.add(self.grad, self.matvec(delta), alpha=0.5) * delta).sum(-1)

    def expandable(self, min_support: float) -> torch.Tensor:
        """(B, D) bool: the unknowns step expansions may scale (well-supported poses and the
        extra parameters)."""
        supported = (self.support >= min_support).repeat_interleave(6, dim=1)
        return torch.cat((supported, supported.new_ones(len(supported), self.H_ee.shape[-1])), 1)

    def solve(
        self, damping: torch.Tensor, config: LMConfig, mixed_precision: bool = True
    ) -> tuple[torch.Tensor, None, bool]:
        """Step of ``(H + damping * diag(clamp(diag H))) delta = -g``, damping (B,).

        Returns:
            ``(delta, None, float64)``: the (B, D) step, no failure flags (the dense solver
            falls back to float64 and least squares, CG always returns a step) and whether
            the dense solver factored in float64 (``mixed_precision=False``, or a fallback of
            :meth:`_solve_dense`).
        """
        diagonal = self.diagonal()
        scaled = damping[:, None] * diagonal.clamp(min=config.min_diagonal)
        if config.solver == "cholesky":
            return self._solve_dense(diagonal + scaled, scaled, mixed_precision)
        return self._solve_cg(scaled, config), None, False

    def _solve_dense(
        self, damped_diagonal: torch.Tensor, scaled: torch.Tensor, mixed_precision: bool
    ) -> tuple[torch.Tensor, None, bool]:
        """Dense Cholesky solve, ``damped_diagonal`` and ``scaled`` (B, D), see :meth:`solve`.

        With the Jacobi scaling ``S = diag(damped_diagonal)^(-1/2)`` the damped matrix
        ``A = S (H + diag(scaled)) S`` has a unit diagonal. In mixed precision a float32
        Cholesky factor of ``A`` (half the time of a float64 one) gives a first solution,
        which iterative refinement with float64 residuals ``-g - (H + diag(scaled)) delta``
        (block products) brings to float64 accuracy when ``cond(A)`` is well below
        ``1 / eps_float32``. Problems whose float32 factorization fails or whose refinement
        stalls, or all without ``mixed_precision``, are solved in float64 (:func:`solve_spd`).
        """
        scale = damped_diagonal.rsqrt()
        b = -self.grad
        if mixed_precision:
            delta, failed = self._solve_refined_float32(b, scale, scaled)
        else:
            delta = torch.zeros_like(b)
            failed = torch.ones(b.shape[0], dtype=torch.bool, device=b.device)
        if bool(failed.any()):
            A = self.dense(scale, b.dtype)[failed]
            A.diagonal(dim1=-2, dim2=-1).fill_(1.0)  # (H_ii + scaled_i) * scale_i^2
            delta[failed] = solve_spd(A, b[failed] * scale[failed]) * scale[failed]
        return delta, None, bool(failed.any())

    def _solve_refined_float32(
        self, b: torch.Tensor, scale: torch.Tensor, scaled: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The mixed-precision solve of :meth:`_solve_dense`: (B, D) solutions and (B,) bool,
        true where the factorization failed or the refinement missed its target."""
        A = self.dense(scale, torch.float32)
        A.diagonal(dim1=-2, dim2=-1).fill_(1.0)  # (H_ii + scaled_i) * scale_i^2
        L, info = torch.linalg.cholesky_ex(A)

        def correction(residual: torch.Tensor) -> torch.Tensor:
            y = (residual * scale).to(torch.float32)[..., None]
            y = torch.linalg.solve_triangular(L, y, upper=False)
            y = torch.linalg.solve_triangular(L.mT, y, upper=True)[..., 0]
            return y.to(b.dtype) * scale

        target = _REFINE_TOLERANCE * torch.linalg.vector_norm(b, dim=-1)
        delta = correction(b)
        previous = torch.full_like(target, math.inf)
        for passes in range(_MAX_REFINEMENTS + 1):
            residual = b - self.matvec(delta) - scaled * delta
            norm = torch.linalg.vector_norm(residual, dim=-1)
            # Refine only the problems still short of the target and contracting.
            refine = (norm > target) & (norm < _REFINE_CONTRACTION * previous)
            if passes == _MAX_REFINEMENTS or not bool(refine.any()):
                break
            delta = torch.where(refine[:, None], delta + correction(residual), delta)
            previous = torch.where(refine, norm, previous)
        return delta, (info != 0) | ~(norm <= target)

    def _solve_cg(self, scaled: torch.Tensor, config: LMConfig) -> torch.Tensor:
        s = self.structure
        B, n6 = scaled.shape[0], 6 * s.num_free
        diag_blocks = self.diag_blocks + torch.diag_embed(scaled[:, :n6].reshape(B, s.num_free, 6))
        inv_pose = torch.linalg.inv(diag_blocks)
        H_ee = self.H_ee + torch.diag_embed(scaled[:, n6:])
        inv_extra = torch.linalg.inv(H_ee) if s.num_extra else H_ee

        def precondition(r: torch.Tensor) -> torch.Tensor:
            z_p = (inv_pose @ r[:, :n6].reshape(B, s.num_free, 6, 1)).flatten(1)
            return torch.cat((z_p, (inv_extra @ r[:, n6:, None])[..., 0]), dim=1)

        def matvec(x: torch.Tensor) -> torch.Tensor:
            return self.matvec(x) + scaled * x

        return _pcg(matvec, precondition, -self.grad, config.cg_max_iterations, config.cg_tolerance)


@dataclass(frozen=True)
class PoseSystem:
    """Normal equations of ``B`` one-pose problems (6 unknowns each) at their current poses.

    What :func:`minimize` needs of a linearization with one pose per problem; a problem may
    subclass it to carry what it computed along (more dataclass fields, tensors with the
    leading dimension ``B``, or dataclasses of those: :meth:`where` picks them too).

    Attributes:
        cost: (B,) cost ``0.5 * sum rho``.
        grad: (B, 6) gradient w.r.t. the pose step.
        hessian: (B, 6, 6) Gauss-Newton matrix ``sum w J^T J``.
        support: (B, 1) robust weights on the pose summed over its residual components (see
            :attr:`LMConfig.expansion_min_support`).
    """

    cost: torch.Tensor
    grad: torch.Tensor
    hessian: torch.Tensor
    support: torch.Tensor

    def where(self, mask: torch.Tensor, other: PoseSystem) -> PoseSystem:
        """Per problem: ``other`` where ``mask`` (B,) is true, else ``self``."""
        return _select(mask, other, self)

    def model_change(self, delta: torch.Tensor) -> torch.Tensor:
        """(B,) change of the quadratic model, ``g.delta + delta.H.delta / 2``, delta (B, 6)."""
        half = torch.baddbmm(self.grad[:, None], delta[:, None], self.hessian, alpha=0.5)
        return half[:, 0].mul_(delta).sum(-1)

    def expandable(self, min_support: float) -> torch.Tensor:
        """(B, 6) bool: poses whose steps may be expanded."""
        return (self.support >= min_support).expand(-1, 6)

    def solve(
        self, damping: torch.Tensor, config: LMConfig, mixed_precision: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, bool]:
        """Step of ``(H + damping * diag(clamp(diag H))) delta = -g`` in float64, damping (B,).

        Returns:
            ``(delta, failed, True)``: the (B, 6) steps and (B,) non-zero where Cholesky could
            not factor the damped matrix (that step is meaningless and counts as failed).
        """
        damped = self.hessian.clone()
        diagonal = damped.diagonal(dim1=-2, dim2=-1)
        diagonal.addcmul_(diagonal.clamp(min=config.min_diagonal), damping[:, None])
        L, info = torch.linalg.cholesky_ex(damped)
        return torch.cholesky_solve(self.grad[..., None], L)[..., 0].neg_(), info, True


def _robust_weights(
    residuals: torch.Tensor, mask: torch.Tensor, kernel: KernelFn
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-problem cost (B,) and IRLS weights (B, M) of masked residuals (B, M, R)."""
    rho, weight = kernel((residuals * residuals).sum(-1))
    cost = 0.5 * torch.where(mask, rho, 0.0).sum(-1)
    return cost, torch.where(mask, weight, 0.0)


def _masked(x: torch.Tensor | None, mask: torch.Tensor) -> torch.Tensor | None:
    """Zero the blocks ``mask`` (B, M) excludes, so NaN in padded blocks cannot leak."""
    if x is None:
        return None
    return torch.where(mask.reshape(*mask.shape, *[1] * (x.dim() - 2)), x, 0.0)


def _add_products(
    out: torch.Tensor,
    index: torch.Tensor | None,
    left: torch.Tensor,
    right: torch.Tensor,
    upper: bool = False,
) -> None:
    """Add the entries of the per-block products ``left_m^T right_m`` to ``out`` in place.

    Entry ``(i, j)`` of block ``m`` is ``sum_r left[:, i, r, m] * right[:, j, r, m]``: one
    (B, M) multiply-add per residual component over all blocks at once (a Python loop over
    the ``I`` rows only). Each row of entries goes through one small reused buffer into
    ``out[:, entries, index[m]]`` by ``index_add_``, which keeps the temporaries in cache.

    Args:
        out: (B, C, S) sums, entries row-major over ``(i, j)``: ``C = I J``, or
            ``I (I + 1) / 2`` with ``upper``.
        index: (M,) int64 destination in ``[0, S)`` of every block, or ``None``: sum over
            the blocks (``S = 1``).
        left: (B, I, R, M) components of the left factors.
        right: (B, J, R, M) components of the right factors.
        upper: only the entries ``i <= j`` (``left`` and ``right`` of the same size ``I``).
    """
    R = left.shape[2]
    buffer = left.new_empty(left.shape[0], right.shape[1], left.shape[3])
    start = 0
    for i in range(left.shape[1]):
        cols = right[:, i:] if upper else right
        entries = buffer[:, : cols.shape[1]]
        torch.mul(left[:, i, None, 0], cols[:, :, 0], out=entries)
        for k in range(1, R):
            entries.addcmul_(left[:, i, None, k], cols[:, :, k])
        sums = out[:, start : start + cols.shape[1]]
        if index is None:
            sums += entries.sum(-1, keepdim=True)
        else:
            sums.index_add_(2, index, entries)
        start += cols.shape[1]


def _assemble(
    lin: BlockLinearization, mask: torch.Tensor, kernel: KernelFn, structure: _Structure
) -> _System:
    """Normal equations of the masked, robustly weighted blocks (no loop over blocks).

    Component-major: the residuals and Jacobians are read through permuted views (B, R, M)
    and (B, 6, R, M) with the blocks innermost (free when the linearization was made in that
    layout, as :meth:`~diffloc.optim.surfel_cost.SurfelReprojectionCost.linearize` does), where
    torch's element-wise kernels are fastest. Each entry of the blocks' 6x6 products
    ``J_x^T W J_y`` is a multiply-add over all blocks at once (:func:`_add_products`: the 21
    upper entries of the diagonal contributions, all 36 of the off-diagonal ones), added to
    its destination blocks by ``index_add_``.
    """
    s = structure
    keep, zero = mask[:, None, :], lin.residuals.new_zeros(())  # (B, 1, M)
    r = torch.where(keep, lin.residuals.transpose(1, 2), zero)  # (B, R, M)
    rho, weight = kernel((r * r).sum(1))
    cost = torch.where(mask, rho, zero).sum(-1).mul_(0.5)
    weight = torch.where(mask, weight, zero)[:, None, None]  # (B, 1, 1, M)

    def component_major(J: torch.Tensor) -> torch.Tensor:  # (B, M, R, N) -> (B, N, R, M)
        return torch.where(keep[:, None], J.permute(0, 3, 2, 1), zero)

    J_a = component_major(lin.jac_a)
    J_b = None if lin.jac_b is None else component_major(lin.jac_b)
    if s.same is not None:  # both poses are one: the block depends on it through both
        J_a = J_a + torch.where(s.same, J_b, zero)
    B, F, dtype, device = r.shape[0], s.num_free, r.dtype, r.device
    diag = torch.zeros(B, 21, F + 1, dtype=dtype, device=device)  # + the fixed-pose slot
    grad_p = torch.zeros(B, 6, F + 1, dtype=dtype, device=device)
    J_e = None if lin.jac_extra is None else component_major(lin.jac_extra)
    E = s.num_extra
    H_pe = torch.zeros(B, 6 * E, F + 1, dtype=dtype, device=device)
    weighted = []
    for J, slot in ((J_a, s.a_slot), (J_b, s.b_slot)):
        if J is None:
            continue
        WJ = J * weight
        weighted.append(WJ)
        _add_products(diag, slot, WJ, J, upper=True)
        _add_products(grad_p, slot, r[:, None], WJ)  # one row of 6 entries: J^T W r
        if J_e is not None:
            _add_products(H_pe, slot, WJ, J_e)
    K = s.off_rows.numel()
    off = torch.zeros(B, 36, K + 1, dtype=dtype, device=device)
    if K:
        left, right = weighted[0], J_b
        if s.swap is not None:  # pose a is the column: the block is (W J_b)^T J_a
            left, right = torch.where(s.swap, weighted[1], left), torch.where(s.swap, J_a, right)
        _add_products(off, s.off_index, left, right)
    H_ee = torch.zeros(B, E * E, 1, dtype=dtype, device=device)
    grad_e = torch.zeros(B, E, 1, dtype=dtype, device=device)
    if J_e is not None:
        WJ_e = J_e * weight
        _add_products(H_ee, None, WJ_e, J_e)
        _add_products(grad_e, None, r[:, None], WJ_e)
    diag_blocks = diag[:, _upper_to_full(device), :F].permute(0, 2, 1).reshape(B, F, 6, 6)
    # Support: the robust weights of the blocks on each pose, in residual components.
    support = torch.zeros(B, F + 1, dtype=dtype, device=device)
    block_weight = weight[:, 0, 0] * r.shape[1]
    for slot in (s.a_slot, s.b_slot):
        if slot is not None:
            support.index_add_(1, slot, block_weight)
    return _System(
        cost=cost,
        grad=torch.cat((grad_p[..., :F].transpose(1, 2).flatten(1), grad_e[..., 0]), dim=1),
        diag_blocks=diag_blocks,
        off_blocks=off[..., :K].permute(0, 2, 1).reshape(B, K, 6, 6),
        H_pe=H_pe[..., :F].reshape(B, 6, E, F).permute(0, 3, 1, 2),
        H_ee=H_ee.view(B, E, E),
        support=support[:, :F],
        structure=s,
    )


def _pose_system(
    residuals: torch.Tensor, jacobian: torch.Tensor, mask: torch.Tensor, kernel: KernelFn
) -> PoseSystem:
    """Normal equations of one-pose problems from residuals (B, M, R) and Jacobians
    (B, M, R, 6) of masked (B, M) blocks.

    Read through permuted views with the blocks innermost (free when the residual function
    produced them in that layout), where torch's element-wise and reduction kernels are
    several times faster than on (..., R) rows. The products are summed over the R residual
    components one by one, so every reduction runs over the blocks in order: padding blocks at
    the end of a batch leave the sums bitwise unchanged.
    """
    R = residuals.shape[2]
    keep, zero = mask[:, None, :], residuals.new_zeros(())  # (B, 1, M)
    r = torch.where(keep, residuals.transpose(1, 2), zero)  # (B, R, M)
    rho, weight = kernel((r * r).sum(1))
    cost = torch.where(mask, rho, zero).sum(-1).mul_(0.5)
    weight = torch.where(mask, weight, zero)
    J = torch.where(keep[:, None], jacobian.permute(0, 3, 2, 1), zero)  # (B, 6, R, M)
    WJ = J * weight[:, None, None]
    H = torch.bmm(WJ[:, :, 0], J[:, :, 0].mT)
    grad = torch.bmm(WJ[:, :, 0], r[:, 0, :, None])
    for i in range(1, R):
        H = torch.baddbmm(H, WJ[:, :, i], J[:, :, i].mT)
        grad = torch.baddbmm(grad, WJ[:, :, i], r[:, i, :, None])
    return PoseSystem(cost, grad[..., 0], H, weight.sum(-1, keepdim=True).mul_(R))


# ---------------------------------------------------------------------------- autodiff


def autodiff_linearize(
    residual_fn: BlockResidualFn,
    T_a: torch.Tensor,
    T_b: torch.Tensor | None = None,
    extra: torch.Tensor | None = None,
) -> BlockLinearization:
    """Residuals and Jacobians of ``residual_fn`` by forward-mode autodiff.

    Differentiates ``residual_fn(T_a @ se3_exp(d_a), T_b @ se3_exp(d_b), extra + d_e)`` at
    ``d = 0`` with one tangent ``(d_a, d_b, d_e)`` shared by all blocks and problems: since a
    block depends only on its own poses and its own problem's extra parameters, this gives
    every block's Jacobian in ``6 (+ 6) + E`` forward-mode passes (``torch.func.jacfwd``).

    Args:
        residual_fn: the block residual function (must be composable with ``torch.func``).
        T_a: (B, M, 4, 4) first pose of every block (``(B, 4, 4)`` for single-pose problems).
        T_b: (B, M, 4, 4) second pose of every block, or ``None``.
        extra: (B, E) extra parameters, or ``None``.

    Returns:
        The linearization: residuals (B, M, R) and Jacobians (B, M, R, 6) / (B, M, R, E).

    Example:
        >>> T = torch.eye(4, dtype=torch.float64).expand(1, 2, 4, 4)
        >>> lin = autodiff_linearize(lambda Ta, Tb, e: Ta[..., :3, 3], T)
        >>> lin.jac_a[0, 0, :, :3]
        tensor([[1., 0., 0.],
                [0., 1., 0.],
                [0., 0., 1.]], dtype=torch.float64)
    """
    n_pose = 6 if T_b is None else 12
    n_extra = 0 if extra is None else extra.shape[-1]

    def perturbed(tangent: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        Ta = T_a @ se3_exp(tangent[:6])
        Tb = None if T_b is None else T_b @ se3_exp(tangent[6:12])
        e = None if extra is None else extra + tangent[n_pose:]
        r = residual_fn(Ta, Tb, e)
        return r, r

    zero = torch.zeros(n_pose + n_extra, dtype=T_a.dtype, device=T_a.device)
    jac, residuals = torch.func.jacfwd(perturbed, has_aux=True)(zero)
    return BlockLinearization(
        residuals=residuals,
        jac_a=jac[..., :6],
        jac_b=None if T_b is None else jac[..., 6:12],
        jac_extra=None if extra is None else jac[..., n_pose:],
    )


# ---------------------------------------------------------------------------- solver core


def _right_step(T: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """``T @ [[Cay(w), v], [0, 1]]`` for poses (..., 4, 4) and steps ``d = [v, w]`` (..., 6)."""
    top = torch.cat((cayley_rotation(d[..., 3:]), d[..., :3, None]), dim=-1)  # (..., 3, 4)
    return T @ torch.cat((top, T[..., 3:, :]), dim=-2)


def _retract(
    T: torch.Tensor, extra: torch.Tensor | None, delta: torch.Tensor, structure: _Structure
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Apply a step: ``T_p <- T_p @ [[Cay(w_p), v_p], [0, 1]]`` for free poses (the retraction
    of the module notes), ``extra += delta_e``."""
    s = structure
    n6 = 6 * s.num_free
    d = delta[:, :n6].reshape(delta.shape[0], s.num_free, 6)
    T_new = T.index_copy(1, s.free, _right_step(T[:, s.free], d))
    return T_new, None if extra is None else extra + delta[:, n6:]


def _check_linearization(lin: BlockLinearization, batch: int, num_blocks: int | None) -> None:
    r = lin.residuals
    check_shape(r, "B,M,R", "residuals")
    if r.shape[0] != batch or (num_blocks is not None and r.shape[1] != num_blocks):
        expected = f"({batch}, {'M' if num_blocks is None else num_blocks}, R)"
        raise ShapeError(f"residuals must have shape {expected}, got {tuple(r.shape)}")
    for name in ("jac_a", "jac_b"):
        J = getattr(lin, name)
        if J is not None and J.shape != (*r.shape, 6):
            raise ShapeError(f"{name} must have shape {(*r.shape, 6)}, got {tuple(J.shape)}")
    if lin.jac_extra is not None and lin.jac_extra.shape[:3] != r.shape:
        raise ShapeError(
            f"jac_extra must have shape {(*r.shape, 'E')}, got {tuple(lin.jac_extra.shape)}"
        )


class LinearSystem(Protocol):
    """The normal equations of ``B`` problems at their current parameters, as :func:`minimize`
    uses them (:class:`PoseSystem` for one pose per problem; the block-sparse system of
    :func:`levenberg_marquardt` otherwise)."""

    cost: torch.Tensor  # (B,)
    grad: torch.Tensor  # (B, D)

    def where(self, mask: torch.Tensor, other: Any) -> Any: ...

    def model_change(self, delta: torch.Tensor) -> torch.Tensor: ...

    def expandable(self, min_support: float) -> torch.Tensor: ...

    def solve(
        self, damping: torch.Tensor, config: LMConfig, mixed_precision: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None, bool]: ...


class LMProblem(Protocol):
    """A problem for :func:`minimize`: its parameters (any value: a pose tensor, a tuple of
    tensors) are linearized, evaluated and updated by these.

    Attributes:
        analytic: ``linearize`` is cheap enough to call on every candidate step (analytic
            Jacobians): it then replaces ``evaluate``, which saves a residual pass per
            accepted step (unless step expansions evaluate several candidates).
    """

    analytic: bool

    def linearize(self, params: Any) -> LinearSystem:
        """The normal equations at ``params``."""
        ...

    def evaluate(self, params: Any) -> torch.Tensor:
        """(B,) costs at ``params``."""
        ...

    def retract(self, params: Any, delta: torch.Tensor) -> Any:
        """``params`` moved by the steps ``delta`` (B, D) (zero rows: unchanged)."""
        ...


@dataclass
class LMRun:
    """What :func:`minimize` returns.

    Attributes:
        params: the final parameters.
        system: the normal equations at ``params``.
        iterations: per problem, the linear solves (accepted, rejected or failed steps).
        reason: per problem, why it stopped (``"gradient"``, ``"step"``, ``"cost"``:
            converged; ``"max_iterations"``, ``"damping"``; ``"inactive"``: not optimised).
        cost_history: the costs (B per entry) before the first and after every iteration.
    """

    params: Any
    system: Any
    iterations: list[int]
    reason: tuple[str, ...]
    cost_history: list[list[float]]

    @property
    def converged(self) -> list[bool]:
        """Per problem, stopped by a gradient, step or cost tolerance."""
        return [reason in _CONVERGED_REASONS for reason in self.reason]


def _select(mask: torch.Tensor, new: Any, old: Any) -> Any:
    """Per problem: ``new`` where ``mask`` (B,) is true, else ``old``. Values are tensors
    (leading dimension ``B``), ``None``, and tuples or dataclasses (field by field) of those."""
    if new is None:
        return None
    if isinstance(new, tuple):
        return tuple(_select(mask, n, o) for n, o in zip(new, old, strict=True))
    if dataclasses.is_dataclass(new):
        picked = {
            f.name: _select(mask, getattr(new, f.name), getattr(old, f.name)) for f in fields(new)
        }
        return dataclasses.replace(old, **picked)
    return torch.where(mask.view(-1, *[1] * (new.dim() - 1)), new, old)


def minimize(
    problem: LMProblem,
    params: Any,
    config: LMConfig,
    system: LinearSystem | None = None,
    active: Sequence[bool] | None = None,
) -> LMRun:
    """Batched Levenberg-Marquardt: the loop every front end of this module shares.

    Runs the damping schedule and the stopping rules of the module notes on ``B`` problems
    at once. The linear algebra is batched; the per-problem scalars (damping, gain ratio,
    stopping tests) are plain Python floats read once or twice per iteration, since a torch
    operation on a (B,) tensor costs far more than the arithmetic itself. Call it under
    ``torch.no_grad()``.

    Args:
        problem: linearizes, evaluates and updates the parameters.
        params: the initial parameters.
        config: solver settings.
        system: the normal equations at ``params`` if already known (else linearized here).
        active: per problem, whether to optimise it; the others keep their parameters and
            report ``"inactive"``. Default all.

    Returns:
        The final parameters and normal equations, iterations and stop reasons.

    Raises:
        ValueError: a non-finite cost or gradient at the initial parameters of an active
            problem.
    """
    if system is None:
        system = problem.linearize(params)
    cost, grad_max = _cost_and_gradient_norm(system)
    B, dtype, device = len(cost), system.cost.dtype, system.cost.device
    status = [_RUNNING if active is None or active[b] else _INACTIVE for b in range(B)]
    for b in range(B):
        if status[b] == _RUNNING and not math.isfinite(cost[b] + grad_max[b]):
            raise ValueError("the residuals or Jacobians are not finite at the initial parameters")
    roundoff = _ROUNDOFF_EPS * torch.finfo(dtype).eps
    damping, nu, iterations = [config.initial_damping] * B, [2.0] * B, [0] * B
    history = [list(cost)]
    linearize_candidates = problem.analytic and not config.step_expansions
    # The model's predicted decrease bounds a plain step's; an expanded step can do several
    # times better (module notes), so with expansions only the measured decrease stops.
    pre_stop_on_cost = not config.step_expansions
    mixed_precision = True
    for _ in range(config.max_iterations):
        for b in range(B):
            if status[b] == _RUNNING and grad_max[b] <= config.gradient_tolerance:
                status[b] = _GRADIENT
        running = [code == _RUNNING for code in status]
        if not any(running):
            break
        damping_t = torch.tensor(damping, dtype=dtype, device=device)
        delta, failed, float64 = system.solve(damping_t, config, mixed_precision)
        mixed_precision = mixed_precision and not float64  # fell back once: stay in float64
        scalars = [system.model_change(delta), torch.linalg.vector_norm(delta, dim=-1)]
        if failed is not None:
            scalars.append(failed.to(dtype))
        model_change, step_norm, *failed_ = torch.stack(scalars).tolist()
        # Steps that cannot matter stop their problem before they are evaluated.
        trying = list(running)
        for b in range(B):
            if not running[b]:
                continue
            iterations[b] += 1
            if failed_ and failed_[0][b]:
                trying[b] = False
            elif step_norm[b] <= config.step_tolerance:
                status[b], trying[b] = _STEP, False
            elif pre_stop_on_cost and -model_change[b] <= config.cost_tolerance * cost[b]:
                status[b], trying[b] = _COST, False
        accept = [False] * B
        if any(trying):
            if not all(trying):
                delta = torch.where(torch.tensor(trying, device=device)[:, None], delta, 0.0)
            new_params = problem.retract(params, delta)
            candidate = None
            if linearize_candidates:
                candidate = problem.linearize(new_params)
                new_cost, new_grad_max = _cost_and_gradient_norm(candidate)
            else:
                new_cost = problem.evaluate(new_params).tolist()
                new_grad_max = [0.0] * B
            gain, expand = [0.0] * B, [False] * B
            for b in range(B):
                if not trying[b]:
                    continue
                finite = math.isfinite(new_cost[b]) and math.isfinite(new_grad_max[b])
                predicted = -model_change[b]
                # A step whose predicted decrease is below the rounding error of the cost
                # cannot be judged by the measured (noisy) change, but the quadratic model is
                # exact at that scale: it counts as ideal.
                in_noise = finite and abs(predicted) <= roundoff * abs(cost[b])
                if in_noise:
                    gain[b] = 1.0
                elif finite and predicted > 0:
                    gain[b] = (cost[b] - new_cost[b]) / predicted
                else:
                    gain[b] = -1.0
                accept[b] = gain[b] > 0
                expand[b] = accept[b] and not in_noise
            if config.step_expansions and any(expand):
                expanded, new_cost = _expand_step(
                    problem, params, delta, system, new_cost, expand, config
                )
                if expanded is not delta:
                    new_params = problem.retract(params, expanded)
            for b in range(B):  # an accepted step (outside rounding noise) that barely helped
                if expand[b] and cost[b] - new_cost[b] <= config.cost_tolerance * cost[b]:
                    status[b] = _COST
            if any(accept):
                everywhere = all(accept)
                accepted = None if everywhere else torch.tensor(accept, device=device)
                if candidate is None:  # residual-only evaluation: linearize the accepted
                    params_lin = new_params if everywhere else _select(accepted, new_params, params)
                    candidate = problem.linearize(params_lin)
                if everywhere:
                    params, system = new_params, candidate
                else:
                    params = _select(accepted, new_params, params)
                    system = system.where(accepted, candidate)
                if linearize_candidates:
                    for b in range(B):
                        if accept[b]:
                            cost[b], grad_max[b] = new_cost[b], new_grad_max[b]
                else:
                    cost, grad_max = _cost_and_gradient_norm(system)
        for b in range(B):
            if not running[b] or (status[b] != _RUNNING and not trying[b]):
                continue  # stopped before evaluating its step
            if accept[b]:
                damping[b] *= max(1.0 - (2.0 * gain[b] - 1.0) ** 3, 1.0 / 3.0)
                nu[b] = 2.0
            else:
                damping[b] *= nu[b]
                nu[b] *= 2.0
            damping[b] = max(damping[b], config.min_damping)
            if status[b] == _RUNNING and damping[b] > config.max_damping:
                status[b] = _DAMPING
        history.append(list(cost))
    status = [_MAX_ITERATIONS if code == _RUNNING else code for code in status]
    return LMRun(params, system, iterations, tuple(_REASONS[code] for code in status), history)


def _expand_step(
    problem: LMProblem,
    params: Any,
    delta: torch.Tensor,
    system: LinearSystem,
    cost: list[float],
    expand: list[bool],
    config: LMConfig,
) -> tuple[torch.Tensor, list[float]]:
    """Lengthen accepted steps while the cost keeps decreasing.

    The problems in ``expand`` scale their step by 2, 4, ... (at most
    ``config.step_expansions`` doublings, one batched residual evaluation each) and keep the
    last scale that lowered the cost. Only the unknowns ``system.expandable`` allows are
    scaled (poses with robust support of at least ``config.expansion_min_support``, and the
    extra parameters): a pose whose blocks are mostly down-weighted outliers sits on a nearly
    flat stretch of the robust cost, where lengthened steps can carry it away from any
    sensible solution.

    Args:
        problem: the problem (residual evaluations and retraction).
        params: the parameters before the step.
        delta: (B, D) step.
        system: normal equations at ``params``.
        cost: per problem, the cost after the step ``delta``.
        expand: per problem, whether to try longer steps.
        config: solver settings.

    Returns:
        ``(step, cost)``: the (B, D) chosen steps (``delta`` itself when no scale helped) and
        their costs per problem.
    """
    scalable = system.expandable(config.expansion_min_support)
    chosen, scale, best, active = delta, [1.0] * len(cost), list(cost), list(expand)
    for _ in range(config.step_expansions):
        trial = [2.0 * t if a else t for t, a in zip(scale, active, strict=True)]
        factor = torch.tensor(trial, dtype=delta.dtype, device=delta.device)[:, None]
        trial_delta = torch.where(scalable, delta * factor, delta)
        trial_cost = problem.evaluate(problem.retract(params, trial_delta)).tolist()
        improved = [a and value < b for a, value, b in zip(active, trial_cost, best, strict=True)]
        if not any(improved):
            break
        for b, better in enumerate(improved):
            if better:
                scale[b], best[b] = trial[b], trial_cost[b]
        chosen = torch.where(
            torch.tensor(improved, device=delta.device)[:, None], trial_delta, chosen
        )
        active = improved
    return chosen, best


def _cost_and_gradient_norm(system: LinearSystem) -> tuple[list[float], list[float]]:
    """Per problem: the cost and ``max |g|``, as Python floats (NaN if any entry is)."""
    norm = torch.linalg.vector_norm(system.grad, ord=math.inf, dim=-1)
    cost, grad_max = torch.stack((system.cost, norm)).tolist()
    return cost, grad_max


# ---------------------------------------------------------------------------- front ends


def _check_poses(T_wc: torch.Tensor, spec: str, name: str) -> None:
    check_shape(T_wc, spec, name)
    if not T_wc.is_floating_point():
        raise TypeError(f"{name} must be a floating point tensor, got {T_wc.dtype}")
    check_finite(T_wc, name)


def _check_index(index: torch.Tensor, num_poses: int, name: str) -> None:
    check_shape(index, "M", name)
    if index.dtype not in (torch.int32, torch.int64):
        raise TypeError(f"{name} must be an integer tensor, got {index.dtype}")
    if index.numel() == 0:
        raise ValueError(f"{name} is empty: the problem has no residual blocks")
    if bool((index < 0).any() | (index >= num_poses).any()):
        raise ValueError(f"{name} must hold pose indices in [0, {num_poses}), got out-of-range")


def _batched_mask(mask: torch.Tensor | None, batch: int, size: int) -> torch.Tensor | None:
    if mask is None:
        return None
    if mask.dtype != torch.bool:
        raise TypeError(f"mask must be a bool tensor, got {mask.dtype}")
    if mask.shape not in ((size,), (batch, size)):
        raise ShapeError(f"mask must have shape ({size},) or ({batch}, {size}), got {mask.shape}")
    return mask.expand(batch, size)


def _fixed_mask(fixed: torch.Tensor | Sequence[int] | None, num_poses: int) -> torch.Tensor:
    is_fixed = torch.zeros(num_poses, dtype=torch.bool)
    if fixed is None:
        return is_fixed
    index = torch.as_tensor(fixed, dtype=torch.long).reshape(-1)
    if bool((index < 0).any() | (index >= num_poses).any()):
        raise ValueError(f"fixed pose indices must be in [0, {num_poses}), got {index.tolist()}")
    is_fixed[index] = True
    return is_fixed


def _robust_cost(residuals: torch.Tensor, mask: torch.Tensor, kernel: KernelFn) -> torch.Tensor:
    """(B,) robust cost of residuals (B, M, R) of the masked (B, M) blocks (NaN-safe)."""
    return _robust_weights(_masked(residuals, mask), mask, kernel)[0]


@dataclass
class _BlockProblem:
    """The :class:`LMProblem` of :func:`levenberg_marquardt`: parameters ``(T, extra)``."""

    residual_fn: BlockResidualFn
    jacobian_fn: BlockJacobianFn | None
    index_a: torch.Tensor
    index_b: torch.Tensor | None
    mask: torch.Tensor  # (B, M)
    kernel: KernelFn
    structure: _Structure

    @property
    def analytic(self) -> bool:
        return self.jacobian_fn is not None

    def gather(self, T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The poses of every block, (B, M, 4, 4) views of (4, 4, B, M) tensors whose 16
        entries are each contiguous over the blocks (a cheap gather, and what component-wise
        residual functions such as SurfelReprojectionCost read without a transposing copy)."""
        B, P = T.shape[:2]
        M = self.index_a.shape[0]
        T_cm = T.permute(2, 3, 0, 1).reshape(16 * B, P)  # a small copy

        def take(index: torch.Tensor) -> torch.Tensor:
            rows = torch.gather(T_cm, 1, index.expand(16 * B, M))
            return rows.view(4, 4, B, M).permute(2, 3, 0, 1)

        return take(self.index_a), None if self.index_b is None else take(self.index_b)

    def linearize(self, params: tuple[torch.Tensor, torch.Tensor | None]) -> _System:
        T, extra = params
        if self.jacobian_fn is not None:
            lin = self.jacobian_fn(*self.gather(T), extra)
        else:
            lin = autodiff_linearize(self.residual_fn, *self.gather(T), extra)
        _check_linearization(lin, *self.mask.shape)
        return _assemble(lin, self.mask, self.kernel, self.structure)

    def evaluate(self, params: tuple[torch.Tensor, torch.Tensor | None]) -> torch.Tensor:
        T, extra = params
        return _robust_cost(self.residual_fn(*self.gather(T), extra), self.mask, self.kernel)

    def retract(
        self, params: tuple[torch.Tensor, torch.Tensor | None], delta: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        return _retract(*params, delta, self.structure)


def levenberg_marquardt(
    T_wc: torch.Tensor,
    residual_fn: BlockResidualFn,
    index_a: torch.Tensor,
    index_b: torch.Tensor | None = None,
    *,
    extra: torch.Tensor | None = None,
    jacobian_fn: BlockJacobianFn | None = None,
    mask: torch.Tensor | None = None,
    fixed: torch.Tensor | Sequence[int] | None = None,
    kernel: RobustKernel | None = None,
    config: LMConfig | None = None,
) -> LMResult:
    """Minimise a robust sum of residual blocks over poses (and extra parameters).

    See the module docstring for the cost, the pose update and the stopping rules. The
    residual functions receive the poses gathered per block, ``T_a = T_wc[:, index_a]``, and
    must return whitened residuals; their Jacobians follow the right-perturbation convention.

    Args:
        T_wc: (P, 4, 4) or (B, P, 4, 4) initial camera-to-world poses (float64 advised).
        residual_fn: ``(T_a (B, M, 4, 4), T_b (B, M, 4, 4) | None, extra (B, E) | None)
            -> (B, M, R)``: cost evaluations and autodiff Jacobians
            (:func:`autodiff_linearize`); with ``jacobian_fn`` given, called only to evaluate
            candidate steps when ``config.step_expansions > 0``.
        index_a: (M,) int64 pose index of every block's first pose.
        index_b: (M,) int64 pose index of every block's second pose, or ``None``.
        extra: (E,) or (B, E) initial extra parameters, or ``None``.
        jacobian_fn: same inputs, returns a :class:`BlockLinearization` with analytic
            Jacobians; then each candidate step is linearized directly (which saves a
            residual pass after each accepted step), unless step expansions evaluate several
            candidates per iteration: then only the chosen one is linearized.
        mask: (M,) or (B, M) bool, blocks to use (padding, outliers); default all.
        fixed: indices of poses held constant (the gauge), default none.
        kernel: robust kernel (default trivial: least squares).
        config: solver settings (default :class:`LMConfig`).

    Returns:
        :class:`LMResult` with ``T_wc`` of the input's shape.

    Raises:
        ShapeError: inputs or residual-function outputs of the wrong shape.
        TypeError: non-float poses or non-integer indices.
        ValueError: non-finite poses or initial residuals, empty or out-of-range indices, or
            nothing left to optimise (all poses fixed and no extra parameters).

    Example:
        >>> T0 = torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
        >>> goal = torch.tensor([[0.0, 0, 0], [1.0, 0, 0]], dtype=torch.float64)
        >>> fn = lambda Ta, Tb, e: Ta[..., :3, 3] - goal   # one block per pose
        >>> out = levenberg_marquardt(T0, fn, torch.tensor([0, 1]), fixed=[0])
        >>> out.T_wc[1, :3, 3].round(decimals=9), out.converged
        (tensor([1., 0., 0.], dtype=torch.float64), tensor(True))
    """
    _check_poses(T_wc, "*,P,4,4", "T_wc")
    if T_wc.dim() not in (3, 4):
        raise ShapeError(f"T_wc must have shape (P, 4, 4) or (B, P, 4, 4), got {T_wc.shape}")
    batched = T_wc.dim() == 4
    T = T_wc if batched else T_wc[None]
    B, P = T.shape[:2]
    _check_index(index_a, P, "index_a")
    M = index_a.shape[0]
    if index_b is not None:
        _check_index(index_b, P, "index_b")
        if index_b.shape != index_a.shape:
            raise ShapeError(f"index_b must have shape ({M},), got {tuple(index_b.shape)}")
    if extra is not None:
        check_shape(extra, "*,E", "extra")
        if extra.shape[:-1] not in ((), (B,) if batched else ()):
            raise ShapeError(f"extra must have shape (E,) or (B, E), got {tuple(extra.shape)}")
        check_finite(extra, "extra")
        extra = extra.to(T.dtype).expand(B, extra.shape[-1]).detach()
    is_fixed = _fixed_mask(fixed, P)
    if bool(is_fixed.all()) and extra is None:
        raise ValueError("every pose is fixed and there are no extra parameters to optimise")
    num_extra = 0 if extra is None else extra.shape[-1]
    index_a, index_b = index_a.long(), None if index_b is None else index_b.long()
    mask_b = _batched_mask(mask, B, M)
    problem = _BlockProblem(
        residual_fn,
        jacobian_fn,
        index_a,
        index_b,
        torch.ones(B, M, dtype=torch.bool) if mask_b is None else mask_b,
        make_robust_kernel(kernel or RobustKernel()),
        _Structure.from_blocks(P, index_a, index_b, is_fixed, num_extra),
    )
    with torch.no_grad():
        run = minimize(problem, (T.detach(), extra), config or LMConfig())
    T_out, extra_out = run.params
    return _lm_result(run, T_out, extra_out, batched)


@dataclass
class _PoseProblem:
    """The :class:`LMProblem` of :func:`levenberg_marquardt_single_pose`: poses (B, 4, 4)."""

    residual_fn: PoseResidualFn
    jacobian_fn: PoseJacobianFn | None
    mask: torch.Tensor | None  # (B, N), or None: all
    kernel: KernelFn

    @property
    def analytic(self) -> bool:
        return self.jacobian_fn is not None

    def _mask(self, residuals: torch.Tensor) -> torch.Tensor:
        if self.mask is not None:
            return self.mask
        return torch.ones(residuals.shape[:2], dtype=torch.bool, device=residuals.device)

    def linearize(self, T: torch.Tensor) -> PoseSystem:
        if self.jacobian_fn is not None:
            lin = BlockLinearization(*self.jacobian_fn(T))
        else:
            lin = autodiff_linearize(lambda T_a, _b, _e: self.residual_fn(T_a), T)
        num_blocks = None if self.mask is None else self.mask.shape[1]
        _check_linearization(lin, T.shape[0], num_blocks)
        return _pose_system(lin.residuals, lin.jac_a, self._mask(lin.residuals), self.kernel)

    def evaluate(self, T: torch.Tensor) -> torch.Tensor:
        residuals = self.residual_fn(T)
        return _robust_cost(residuals, self._mask(residuals), self.kernel)

    def retract(self, T: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        return _right_step(T, delta)


def levenberg_marquardt_single_pose(
    T_wc: torch.Tensor,
    residual_fn: PoseResidualFn,
    *,
    jacobian_fn: PoseJacobianFn | None = None,
    mask: torch.Tensor | None = None,
    kernel: RobustKernel | None = None,
    config: LMConfig | None = None,
) -> LMResult:
    """Solve ``B`` independent one-pose problems at once (batched 6x6 systems).

    The loop of :func:`levenberg_marquardt` (:func:`minimize`) on :class:`PoseSystem`
    normal equations, without gathering poses per block.

    Args:
        T_wc: (4, 4) or (B, 4, 4) initial camera-to-world poses (float64 advised).
        residual_fn: ``T_wc (B, 4, 4) -> (B, N, R)`` whitened residuals (always called with a
            leading batch dimension, ``B = 1`` for an unbatched input); with ``jacobian_fn``
            given, called only when ``config.step_expansions > 0``.
        jacobian_fn: ``T_wc (B, 4, 4) -> ((B, N, R), (B, N, R, 6))`` residuals and analytic
            Jacobians w.r.t. ``T_wc <- T_wc @ se3_exp(delta)``; default autodiff.
        mask: (N,) or (B, N) bool, residuals to use (padding, outliers); default all.
        kernel: robust kernel (default trivial).
        config: solver settings (default :class:`LMConfig`).

    Returns:
        :class:`LMResult` with ``T_wc`` of the input's shape.

    Raises:
        ShapeError: inputs or residual-function outputs of the wrong shape.
        ValueError: non-finite poses or initial residuals.

    Example:
        >>> goal = torch.tensor([[[1.0, 2.0, 3.0]]], dtype=torch.float64)
        >>> out = levenberg_marquardt_single_pose(
        ...     torch.eye(4, dtype=torch.float64), lambda T: T[:, None, :3, 3] - goal)
        >>> out.T_wc[:3, 3].round(decimals=9)
        tensor([1., 2., 3.], dtype=torch.float64)
    """
    _check_poses(T_wc, "*,4,4", "T_wc")
    if T_wc.dim() not in (2, 3):
        raise ShapeError(f"T_wc must have shape (4, 4) or (B, 4, 4), got {tuple(T_wc.shape)}")
    batched = T_wc.dim() == 3
    T = T_wc if batched else T_wc[None]
    B = T.shape[0]
    mask_b = None if mask is None else _batched_mask(mask, B, mask.shape[-1])
    kernel_fn = make_robust_kernel(kernel or RobustKernel())
    problem = _PoseProblem(residual_fn, jacobian_fn, mask_b, kernel_fn)
    with torch.no_grad():
        run = minimize(problem, T.detach(), config or LMConfig())
    return _lm_result(run, run.params, None, batched)


def _lm_result(run: LMRun, T: torch.Tensor, extra: torch.Tensor | None, batched: bool) -> LMResult:
    """The :class:`LMResult` of a run (batch dimension removed unless ``batched``)."""
    device = T.device
    result = LMResult(
        T_wc=T,
        extra=extra,
        cost_history=torch.tensor(run.cost_history, dtype=T.dtype, device=device).T.contiguous(),
        iterations=torch.tensor(run.iterations, dtype=torch.long, device=device),
        converged=torch.tensor(run.converged, device=device),
        reason=run.reason,
    )
    if batched:
        return result
    return LMResult(
        T_wc=result.T_wc[0],
        extra=None if extra is None else extra[0],
        cost_history=result.cost_history[0],
        iterations=result.iterations[0],
        converged=result.converged[0],
        reason=result.reason,
    )
