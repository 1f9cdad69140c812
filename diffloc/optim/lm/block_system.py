"""Block-sparse normal equations of multi-pose problems and their damped step.

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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from diffloc.optim.lm.config import LMConfig
from diffloc.optim.lm.linalg import _pcg, solve_spd
from diffloc.optim.lm.structure import _Structure

_REFINE_TOLERANCE = 1e-10
"""Mixed-precision dense solves refine until ``||b - A x|| <=`` this times ``||b||``."""
_REFINE_CONTRACTION = 0.5
"""Refinement stalls (and falls back to float64) when a pass shrinks the residual less."""
_MAX_REFINEMENTS = 8
"""Most refinement passes of a mixed-precision dense solve."""


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
