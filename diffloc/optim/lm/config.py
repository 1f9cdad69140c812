"""Settings of the batched Levenberg-Marquardt solver (:mod:`diffloc.optim.lm`)."""

from __future__ import annotations

from dataclasses import dataclass, fields

from diffloc.checks import check_positive_int

__all__ = ["SOLVERS", "LMConfig"]


SOLVERS = ("cholesky", "cg")
"""Linear solvers accepted by :class:`LMConfig`."""


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
        solver: ``"cholesky"`` (dense) or ``"cg"`` (block-sparse PCG), see
            :mod:`diffloc.optim.lm.block_system`.
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
