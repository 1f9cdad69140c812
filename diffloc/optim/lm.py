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
    (``max |g|``), small step (``||delta||``, mixed metres/radians), small relative cost
    decrease, ``max_iterations`` linear solves, or ``lambda > max_damping`` (failure). The
    pose gauge is fixed by holding chosen poses constant (their rows and columns are removed).

Linear solvers and memory
    ``solver="cholesky"`` assembles the dense normal equations of ``D = 6 * P_free + E``
    unknowns per problem: ``8 * D^2`` bytes in float64 (100 poses: 2.9 MB, 1000 poses:
    288 MB, 2000 poses: 1.15 GB) and ``O(D^3)`` time per solve; it falls back to least squares
    when the damped matrix is not positive definite. ``solver="cg"`` runs block-Jacobi
    preconditioned conjugate gradients on the block-sparse normal equations (one 6x6 block per
    pair of poses sharing a residual), with memory and time per CG iteration linear in the
    number of such pairs. Limitations: no sparse Cholesky or Schur complement (per-point
    structure must be eliminated by the caller, as in seed 1 Eq. 3, or kept out of the
    problem), and extra parameters form a dense block, meant for a few global parameters such
    as intrinsics or a time offset.

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

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields

import torch

from diffloc.checks import ShapeError, check_finite, check_positive_int, check_shape
from diffloc.geometry.se3 import se3_exp
from diffloc.optim.robust import KernelFn, RobustKernel, make_robust_kernel

__all__ = [
    "SOLVERS",
    "BlockJacobianFn",
    "BlockLinearization",
    "BlockResidualFn",
    "LMConfig",
    "LMResult",
    "PoseJacobianFn",
    "PoseResidualFn",
    "autodiff_linearize",
    "cayley_rotation",
    "levenberg_marquardt",
    "levenberg_marquardt_single_pose",
    "solve_spd",
]

SOLVERS = ("cholesky", "cg")
"""Linear solvers accepted by :class:`LMConfig`."""

# Stop reasons, indexed by the per-problem status code used inside the solver loop.
_RUNNING, _GRADIENT, _STEP, _COST, _MAX_ITERATIONS, _DAMPING = range(6)
_REASONS = ("running", "gradient", "step", "cost", "max_iterations", "damping")
_CONVERGED = (_GRADIENT, _STEP, _COST)
_ROUNDOFF_EPS = 16.0
"""Cost changes below this many machine epsilons of the cost are rounding noise."""


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
    cg_max_iterations: int = 200
    cg_tolerance: float = 1e-10

    def __post_init__(self) -> None:
        check_positive_int(self.max_iterations, "max_iterations")
        check_positive_int(self.cg_max_iterations, "cg_max_iterations")
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
block's residual from the poses gathered at ``index_a`` / ``index_b``."""

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
    x = torch.cholesky_solve(b[..., None], L)[..., 0]
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


@dataclass
class _Structure:
    """Static sparsity of the normal equations, computed once per solve.

    Free poses get slots ``0 .. P_free - 1``. ``K`` distinct (row slot, col slot) pose pairs
    hold a 6x6 block each; every free pose has its diagonal pair. The ``*_sel`` tensors pick
    the blocks whose pose is free (``None``: all blocks), ``*_slot`` give their slots and
    ``*_pair`` the pair receiving their contribution (``None``: slot / pair 0 for all, the
    single-pose case).
    """

    free: torch.Tensor  # (P_free,) pose index of each slot
    num_extra: int
    pair_rows: torch.Tensor  # (K,)
    pair_cols: torch.Tensor  # (K,)
    diag_pairs: torch.Tensor  # (P_free,)
    a_sel: torch.Tensor | None
    a_slot: torch.Tensor | None
    a_pair: torch.Tensor | None
    b_sel: torch.Tensor | None = None
    b_slot: torch.Tensor | None = None
    b_pair: torch.Tensor | None = None
    ab_sel_a: torch.Tensor | None = None  # positions in a_sel of blocks with both poses free
    ab_sel_b: torch.Tensor | None = None  # the same blocks' positions in b_sel
    ab_pair: torch.Tensor | None = None
    ba_pair: torch.Tensor | None = None
    single: bool = False  # one free pose, every block on it, no extra parameters

    @property
    def num_free(self) -> int:
        return int(self.free.numel())

    @property
    def size(self) -> int:
        """Number of unknowns ``D = 6 P_free + E``."""
        return 6 * self.num_free + self.num_extra

    @classmethod
    def single_pose(cls, device: torch.device) -> _Structure:
        zero = torch.zeros(1, dtype=torch.long, device=device)
        return cls(zero, 0, zero, zero, zero, None, None, None, single=True)

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
        slot_of = torch.full((num_poses,), -1, dtype=torch.long, device=device)
        slot_of[free] = torch.arange(n_free, device=device)
        a_slot_all = slot_of[index_a]
        a_sel = torch.nonzero(a_slot_all >= 0)[:, 0]
        a_slot = a_slot_all[a_sel]
        diag = torch.arange(n_free, device=device)
        keys = [diag * n_free + diag, a_slot * n_free + a_slot]
        b_sel = b_slot = ab_sel_a = ab_sel_b = None
        if index_b is not None:
            b_slot_all = slot_of[index_b]
            b_sel = torch.nonzero(b_slot_all >= 0)[:, 0]
            b_slot = b_slot_all[b_sel]
            both = (a_slot_all >= 0) & (b_slot_all >= 0)
            position_a = torch.cumsum(a_slot_all >= 0, 0) - 1
            position_b = torch.cumsum(b_slot_all >= 0, 0) - 1
            ab_sel_a, ab_sel_b = position_a[both], position_b[both]
            ab_a, ab_b = a_slot_all[both], b_slot_all[both]
            keys += [b_slot * n_free + b_slot, ab_a * n_free + ab_b, ab_b * n_free + ab_a]
        unique, inverse = torch.unique(torch.cat(keys), return_inverse=True)
        pair_ids = list(torch.split(inverse, [int(k.numel()) for k in keys]))
        return cls(
            free=free,
            num_extra=num_extra,
            pair_rows=torch.div(unique, n_free, rounding_mode="floor"),
            pair_cols=unique % n_free,
            diag_pairs=pair_ids[0],
            a_sel=a_sel,
            a_slot=a_slot,
            a_pair=pair_ids[1],
            b_sel=b_sel,
            b_slot=b_slot,
            b_pair=pair_ids[2] if index_b is not None else None,
            ab_sel_a=ab_sel_a,
            ab_sel_b=ab_sel_b,
            ab_pair=pair_ids[3] if index_b is not None else None,
            ba_pair=pair_ids[4] if index_b is not None else None,
        )


def _select(x: torch.Tensor, sel: torch.Tensor | None) -> torch.Tensor:
    """``x[:, sel]``, or ``x`` itself when ``sel`` is ``None`` (all blocks)."""
    return x if sel is None else x[:, sel]


def _scatter_products(
    out: torch.Tensor, index: torch.Tensor | None, left: torch.Tensor, right: torch.Tensor
) -> None:
    """``out[:, index[m]] += left[:, m]^T @ right[:, m]`` in place.

    ``left``: (B, M, R, i), ``right``: (B, M, R, j), ``out``: (B, S, i, j). ``index=None``
    adds every block to slot 0 as one (B, i, M R) @ (B, M R, j) product (single pose).
    """
    if index is None:
        out[:, 0] += left.flatten(1, 2).transpose(1, 2) @ right.flatten(1, 2)
    else:
        out.index_add_(1, index, left.transpose(-1, -2) @ right)


# ---------------------------------------------------------------------------- normal equations


@dataclass
class _System:
    """Block-sparse normal equations of ``B`` problems at the current parameters.

    ``blocks`` (B, K, 6, 6) are the pose-pose blocks of ``H`` for the pairs of the structure,
    ``H_pe`` (B, P_free, 6, E) and ``H_ee`` (B, E, E) the extra-parameter parts, ``grad``
    (B, D) the gradient and ``cost`` (B,) the cost.
    """

    cost: torch.Tensor
    grad: torch.Tensor
    blocks: torch.Tensor
    H_pe: torch.Tensor
    H_ee: torch.Tensor
    structure: _Structure

    def where(self, mask: torch.Tensor, other: _System) -> _System:
        """Per problem: ``other`` where ``mask`` (B,) is true, else ``self``."""

        def pick(new: torch.Tensor, old: torch.Tensor) -> torch.Tensor:
            return torch.where(mask.reshape(-1, *[1] * (new.dim() - 1)), new, old)

        return _System(
            pick(other.cost, self.cost),
            pick(other.grad, self.grad),
            pick(other.blocks, self.blocks),
            pick(other.H_pe, self.H_pe),
            pick(other.H_ee, self.H_ee),
            self.structure,
        )

    def diagonal(self) -> torch.Tensor:
        """(B, D) diagonal of ``H``."""
        if self.structure.single:
            return self.blocks[:, 0].diagonal(dim1=-2, dim2=-1)
        pose = self.blocks[:, self.structure.diag_pairs].diagonal(dim1=-2, dim2=-1)
        extra = self.H_ee.diagonal(dim1=-2, dim2=-1)
        return torch.cat((pose.flatten(1), extra), dim=1)

    def dense(self) -> torch.Tensor:
        """(B, D, D) dense ``H`` (a new tensor)."""
        s = self.structure
        if s.single:
            return self.blocks[:, 0].clone()
        B, n6, D = self.grad.shape[0], 6 * s.num_free, s.size
        H = self.grad.new_zeros(B, D, D)
        eye6 = torch.arange(6, device=H.device)
        rows = (6 * s.pair_rows[:, None, None] + eye6[None, :, None]) * D
        flat = rows + 6 * s.pair_cols[:, None, None] + eye6[None, None, :]
        H.view(B, -1)[:, flat.flatten()] = self.blocks.flatten(1)
        if s.num_extra:
            H_pe = self.H_pe.reshape(B, n6, s.num_extra)
            H[:, :n6, n6:] = H_pe
            H[:, n6:, :n6] = H_pe.transpose(1, 2)
            H[:, n6:, n6:] = self.H_ee
        return H

    def matvec(self, x: torch.Tensor) -> torch.Tensor:
        """(B, D) product ``H x`` from the blocks, ``x``: (B, D)."""
        s = self.structure
        if s.single:
            return torch.bmm(self.blocks[:, 0], x[..., None])[..., 0]
        n6 = 6 * s.num_free
        x_p = x[:, :n6].reshape(x.shape[0], s.num_free, 6)
        y_p = torch.zeros_like(x_p)
        y_p.index_add_(1, s.pair_rows, (self.blocks @ x_p[:, s.pair_cols, :, None])[..., 0])
        if not s.num_extra:
            return y_p.flatten(1)
        x_e = x[:, n6:]
        y_p = y_p + (self.H_pe @ x_e[:, None, :, None])[..., 0]
        y_e = torch.einsum("bpie,bpi->be", self.H_pe, x_p) + (self.H_ee @ x_e[..., None])[..., 0]
        return torch.cat((y_p.flatten(1), y_e), dim=1)

    def solve(self, damping: torch.Tensor, config: LMConfig) -> torch.Tensor:
        """(B, D) step ``delta`` of ``(H + damping * diag(clamp(diag H))) delta = -g``."""
        scaled = damping[:, None] * self.diagonal().clamp(min=config.min_diagonal)
        if config.solver == "cholesky":
            H = self.dense()
            H.diagonal(dim1=-2, dim2=-1).add_(scaled)
            return solve_spd(H, -self.grad)
        return self._solve_cg(scaled, config)

    def _solve_cg(self, scaled: torch.Tensor, config: LMConfig) -> torch.Tensor:
        s = self.structure
        B, n6 = scaled.shape[0], 6 * s.num_free
        diag_blocks = self.blocks[:, s.diag_pairs] + torch.diag_embed(
            scaled[:, :n6].reshape(B, s.num_free, 6)
        )
        inv_pose = torch.linalg.inv(diag_blocks)
        H_ee = self.H_ee + torch.diag_embed(scaled[:, n6:])
        inv_extra = torch.linalg.inv(H_ee) if s.num_extra else H_ee

        def precondition(r: torch.Tensor) -> torch.Tensor:
            z_p = (inv_pose @ r[:, :n6].reshape(B, s.num_free, 6, 1)).flatten(1)
            return torch.cat((z_p, (inv_extra @ r[:, n6:, None])[..., 0]), dim=1)

        def matvec(x: torch.Tensor) -> torch.Tensor:
            return self.matvec(x) + scaled * x

        return _pcg(matvec, precondition, -self.grad, config.cg_max_iterations, config.cg_tolerance)


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


def _assemble(
    lin: BlockLinearization, mask: torch.Tensor, kernel: KernelFn, structure: _Structure
) -> _System:
    """Normal equations of the masked, robustly weighted blocks (no loop over blocks)."""
    s = structure
    if s.single and lin.jac_b is None and lin.jac_extra is None:
        return _assemble_single(lin.residuals, lin.jac_a, mask, kernel, s)
    r = _masked(lin.residuals, mask)
    cost, weights = _robust_weights(r, mask, kernel)
    B, dtype, device = r.shape[0], r.dtype, r.device
    blocks = torch.zeros(B, s.pair_rows.numel(), 6, 6, dtype=dtype, device=device)
    grad_p = torch.zeros(B, s.num_free, 6, dtype=dtype, device=device)
    H_pe = torch.zeros(B, s.num_free, 6, s.num_extra, dtype=dtype, device=device)
    J_e = _masked(lin.jac_extra, mask)
    weighted = {}  # name -> (W J, J) of the blocks whose pose is free
    for name, J, sel, slot, pair in (
        ("a", lin.jac_a, s.a_sel, s.a_slot, s.a_pair),
        ("b", lin.jac_b, s.b_sel, s.b_slot, s.b_pair),
    ):
        if J is None or (sel is not None and sel.numel() == 0):
            continue
        J = _select(_masked(J, mask), sel)
        WJ = J * _select(weights, sel)[..., None, None]
        weighted[name] = (WJ, J)
        _scatter_products(blocks, pair, WJ, J)
        _scatter_products(grad_p[..., None], slot, WJ, _select(r, sel)[..., None])
        if J_e is not None:
            _scatter_products(H_pe, slot, WJ, _select(J_e, sel))
    if s.ab_pair is not None and s.ab_pair.numel():
        cross = weighted["a"][0][:, s.ab_sel_a].transpose(-1, -2) @ weighted["b"][1][:, s.ab_sel_b]
        blocks.index_add_(1, s.ab_pair, cross)
        blocks.index_add_(1, s.ba_pair, cross.transpose(-1, -2))
    if J_e is None:
        H_ee = torch.zeros(B, 0, 0, dtype=dtype, device=device)
        grad_e = torch.zeros(B, 0, dtype=dtype, device=device)
    else:
        WJ_e = J_e * weights[..., None, None]
        H_ee = WJ_e.flatten(1, 2).transpose(1, 2) @ J_e.flatten(1, 2)
        grad_e = (WJ_e.flatten(1, 2).transpose(1, 2) @ r.flatten(1, 2)[..., None])[..., 0]
    grad = torch.cat((grad_p.flatten(1), grad_e), dim=1)
    return _System(cost, grad, blocks, H_pe, H_ee, s)


def _assemble_single(
    residuals: torch.Tensor,
    jacobian: torch.Tensor,
    mask: torch.Tensor,
    kernel: KernelFn,
    structure: _Structure,
) -> _System:
    """:func:`_assemble` for one pose and no extra parameters, in (B, ., M) layout.

    The residuals (B, M, R) and Jacobians (B, M, R, 6) are read through permuted views with
    the blocks innermost (free when the residual function produced them in that layout),
    where torch's element-wise and reduction kernels are several times faster than on
    (..., R) rows. The products are summed over the R residual components one by one, so
    every reduction runs over the blocks in order: padding blocks at the end of a batch
    leave the sums bitwise unchanged.
    """
    R = residuals.shape[2]
    keep, zero = mask[:, None, :], residuals.new_zeros(())  # (B, 1, M)
    r = torch.where(keep, residuals.transpose(1, 2), zero)  # (B, R, M)
    rho, weight = kernel((r * r).sum(1))
    cost = torch.where(mask, rho, zero).sum(-1).mul_(0.5)
    J = torch.where(keep[:, None], jacobian.permute(0, 3, 2, 1), zero)  # (B, 6, R, M)
    WJ = J * torch.where(mask, weight, zero)[:, None, None]
    H = torch.bmm(WJ[:, :, 0], J[:, :, 0].mT)
    grad = torch.bmm(WJ[:, :, 0], r[:, 0, :, None])
    for i in range(1, R):
        H = torch.baddbmm(H, WJ[:, :, i], J[:, :, i].mT)
        grad = torch.baddbmm(grad, WJ[:, :, i], r[:, i, :, None])
    empty = r.new_zeros(r.shape[0], 1, 6, 0)
    return _System(cost, grad[..., 0], H[:, None], empty, empty[:, 0, :0], structure)


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


def _retract(
    T: torch.Tensor, extra: torch.Tensor | None, delta: torch.Tensor, structure: _Structure
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Apply a step: ``T_p <- T_p @ [[Cay(w_p), v_p], [0, 1]]`` for free poses (the retraction
    of the module notes), ``extra += delta_e``."""
    s = structure
    n6 = 6 * s.num_free
    d = delta[:, :n6].reshape(delta.shape[0], s.num_free, 6)
    top = torch.cat((cayley_rotation(d[..., 3:]), d[..., :3, None]), dim=-1)  # (B, F, 3, 4)
    step = torch.cat((top, T[:, :1, 3:].expand(*top.shape[:2], 1, 4)), dim=-2)
    T_new = T @ step if s.single else T.index_copy(1, s.free, T[:, s.free] @ step)
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


@dataclass
class _Problem:
    """What the solver core needs to know about a problem, built by the two front ends."""

    linearize: Callable[[torch.Tensor, torch.Tensor | None], BlockLinearization]
    # Residuals alone, when much cheaper than linearize (autodiff); None: candidates are
    # linearized directly, which saves the residual pass after every accepted step.
    evaluate: Callable[[torch.Tensor, torch.Tensor | None], torch.Tensor] | None
    structure: _Structure | None  # None: single pose, built once M is known
    num_blocks: int | None
    mask: torch.Tensor | None  # (B, M)


def _minimize(
    T: torch.Tensor,
    extra: torch.Tensor | None,
    problem: _Problem,
    kernel: KernelFn,
    config: LMConfig,
) -> LMResult:
    """The shared batched LM loop on poses (B, P, 4, 4) and extra (B, E).

    The linear algebra is batched over the B problems; the per-problem scalars (damping,
    gain ratio, stopping tests) are plain Python floats, read once per iteration, since a
    torch operation on a (B,) tensor costs far more than the arithmetic itself.
    """
    B = T.shape[0]
    lin = problem.linearize(T, extra)
    _check_linearization(lin, B, problem.num_blocks)
    M = lin.residuals.shape[1]
    structure = problem.structure or _Structure.single_pose(T.device)
    mask = problem.mask if problem.mask is not None else torch.ones(B, M, dtype=torch.bool)
    mask = mask.to(T.device).expand(B, M)
    system = _assemble(lin, mask, kernel, structure)
    cost, grad_max = _cost_and_gradient_norm(system)
    if not all(map(math.isfinite, cost + grad_max)):
        raise ValueError("the residuals or Jacobians are not finite at the initial parameters")

    dtype, device = system.cost.dtype, T.device
    roundoff = _ROUNDOFF_EPS * torch.finfo(dtype).eps
    damping = [config.initial_damping] * B
    nu = [2.0] * B
    status = [_RUNNING] * B
    iterations = [0] * B
    history = [list(cost)]
    for _ in range(config.max_iterations):
        for b in range(B):
            if status[b] == _RUNNING and grad_max[b] <= config.gradient_tolerance:
                status[b] = _GRADIENT
        running = [code == _RUNNING for code in status]
        if not any(running):
            break
        delta = system.solve(torch.tensor(damping, dtype=dtype, device=device), config)
        if not all(running):
            delta = torch.where(torch.tensor(running, device=device)[:, None], delta, 0.0)
        T_new, extra_new = _retract(T, extra, delta, structure)
        candidate = None
        if problem.evaluate is None:
            candidate = _assemble(problem.linearize(T_new, extra_new), mask, kernel, structure)
            new_cost = candidate.cost
            # A non-finite gradient fails the step too: the cost plus the sum of the gradient
            # is finite iff both are (or, harmlessly, when the sum overflows).
            check = candidate.cost + candidate.grad.sum(-1)
        else:
            residuals = _masked(problem.evaluate(T_new, extra_new), mask)
            new_cost = check = _robust_weights(residuals, mask, kernel)[0]
        # Minus the decrease of the quadratic model, g.delta + delta.H.delta / 2.
        model_change = (torch.add(system.grad, system.matvec(delta), alpha=0.5) * delta).sum(-1)
        step_norm = torch.linalg.vector_norm(delta, dim=-1)
        new_cost_, check_, model_change_, step_norm_ = torch.stack(
            (new_cost, check, model_change, step_norm)
        ).tolist()

        accept = [False] * B
        for b in range(B):
            if not running[b]:
                continue
            iterations[b] += 1
            finite_b = math.isfinite(check_[b])
            actual, predicted = cost[b] - new_cost_[b], -model_change_[b]
            # A step whose predicted decrease is below the rounding error of the cost cannot
            # be judged by the measured (noisy) change, but it is harmlessly small and the
            # quadratic model is exact at that scale: count it as ideal so LM reaches full
            # precision.
            in_noise = finite_b and abs(predicted) <= roundoff * abs(cost[b])
            ok = finite_b and predicted > 0
            gain = 1.0 if in_noise else (actual / predicted if ok else -1.0)
            accept[b] = in_noise or (ok and gain > 0)
            if accept[b]:
                damping[b] *= max(1.0 - (2.0 * gain - 1.0) ** 3, 1.0 / 3.0)
                nu[b] = 2.0
            else:
                damping[b] *= nu[b]
                nu[b] *= 2.0
            damping[b] = max(damping[b], config.min_damping)
            if step_norm_[b] <= config.step_tolerance:
                status[b] = _STEP
            elif accept[b] and not in_noise and actual <= config.cost_tolerance * cost[b]:
                status[b] = _COST
            elif damping[b] > config.max_damping:
                status[b] = _DAMPING

        if any(accept):
            if candidate is None:  # residual-only evaluation: linearize the accepted poses
                T_lin = T_new if all(accept) else _pick(accept, T_new, T)
                extra_lin = extra_new if all(accept) else _pick(accept, extra_new, extra)
                candidate = _assemble(problem.linearize(T_lin, extra_lin), mask, kernel, structure)
            if all(accept):
                T, extra, system = T_new, extra_new, candidate
            else:
                accepted = torch.tensor(accept, device=device)
                T, extra = _pick(accept, T_new, T), _pick(accept, extra_new, extra)
                system = system.where(accepted, candidate)
            cost, grad_max = _cost_and_gradient_norm(system)
        history.append(list(cost))
    status = [_MAX_ITERATIONS if code == _RUNNING else code for code in status]
    return LMResult(
        T_wc=T,
        extra=extra,
        cost_history=torch.tensor(history, dtype=dtype, device=device).T.contiguous(),
        iterations=torch.tensor(iterations, dtype=torch.long, device=device),
        converged=torch.tensor([code in _CONVERGED for code in status], device=device),
        reason=tuple(_REASONS[code] for code in status),
    )


def _cost_and_gradient_norm(system: _System) -> tuple[list[float], list[float]]:
    """Per problem: the cost and ``max |g|``, as Python floats."""
    norm = torch.linalg.vector_norm(system.grad, ord=math.inf, dim=-1)
    cost, grad_max = torch.stack((system.cost, norm)).tolist()
    return cost, grad_max


def _pick(accept: list[bool], new: torch.Tensor | None, old: torch.Tensor | None):
    """Per problem (leading dimension): ``new`` where ``accept``, else ``old``."""
    if new is None or old is None:
        return new
    mask = torch.tensor(accept, device=new.device).view(-1, *[1] * (new.dim() - 1))
    return torch.where(mask, new, old)


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
            (:func:`autodiff_linearize`); not called when ``jacobian_fn`` is given.
        index_a: (M,) int64 pose index of every block's first pose.
        index_b: (M,) int64 pose index of every block's second pose, or ``None``.
        extra: (E,) or (B, E) initial extra parameters, or ``None``.
        jacobian_fn: same inputs, returns a :class:`BlockLinearization` with analytic
            Jacobians; then used for every evaluation (each candidate step is linearized,
            which saves a residual pass after each accepted step).
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
        extra = extra.to(T.dtype).expand(B, extra.shape[-1])
    is_fixed = _fixed_mask(fixed, P)
    if bool(is_fixed.all()) and extra is None:
        raise ValueError("every pose is fixed and there are no extra parameters to optimise")
    num_extra = 0 if extra is None else extra.shape[-1]
    structure = _Structure.from_blocks(
        P, index_a.long(), None if index_b is None else index_b.long(), is_fixed, num_extra
    )

    def gather(T_cur: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        return T_cur[:, index_a], None if index_b is None else T_cur[:, index_b]

    def linearize(T_cur: torch.Tensor, e: torch.Tensor | None) -> BlockLinearization:
        if jacobian_fn is not None:
            return jacobian_fn(*gather(T_cur), e)
        return autodiff_linearize(residual_fn, *gather(T_cur), e)

    def evaluate(T_cur: torch.Tensor, e: torch.Tensor | None) -> torch.Tensor:
        return residual_fn(*gather(T_cur), e)

    problem = _Problem(
        linearize,
        evaluate if jacobian_fn is None else None,
        structure,
        M,
        _batched_mask(mask, B, M),
    )
    with torch.no_grad():
        result = _minimize(
            T.detach(),
            None if extra is None else extra.detach(),
            problem,
            make_robust_kernel(kernel or RobustKernel()),
            config or LMConfig(),
        )
    return _unbatch(result, batched)


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

    The same solver core as :func:`levenberg_marquardt` (one pose per problem, every residual
    block depending on it), without gathering poses per block.

    Args:
        T_wc: (4, 4) or (B, 4, 4) initial camera-to-world poses (float64 advised).
        residual_fn: ``T_wc (B, 4, 4) -> (B, N, R)`` whitened residuals (always called with a
            leading batch dimension, ``B = 1`` for an unbatched input); not called when
            ``jacobian_fn`` is given.
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
    T = (T_wc if batched else T_wc[None])[:, None]

    def linearize(T_cur: torch.Tensor, _: torch.Tensor | None) -> BlockLinearization:
        if jacobian_fn is not None:
            return BlockLinearization(*jacobian_fn(T_cur[:, 0]))
        return autodiff_linearize(lambda Ta, _b, _e: residual_fn(Ta), T_cur[:, 0])

    def evaluate(T_cur: torch.Tensor, _: torch.Tensor | None) -> torch.Tensor:
        return residual_fn(T_cur[:, 0])

    B = T.shape[0]
    num_blocks = None if mask is None else mask.shape[-1]
    mask_b = None if mask is None else _batched_mask(mask, B, num_blocks)
    problem = _Problem(
        linearize, evaluate if jacobian_fn is None else None, None, num_blocks, mask_b
    )
    with torch.no_grad():
        result = _minimize(
            T.detach(),
            None,
            problem,
            make_robust_kernel(kernel or RobustKernel()),
            config or LMConfig(),
        )
    result.T_wc = result.T_wc[:, 0]
    return _unbatch(result, batched)


def _unbatch(result: LMResult, batched: bool) -> LMResult:
    if batched:
        return result
    return LMResult(
        T_wc=result.T_wc[0],
        extra=None if result.extra is None else result.extra[0],
        cost_history=result.cost_history[0],
        iterations=result.iterations[0],
        converged=result.converged[0],
        reason=result.reason,
    )
