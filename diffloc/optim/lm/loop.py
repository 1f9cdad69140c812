"""The batched Levenberg-Marquardt loop that every front end shares (:func:`minimize`).

The damping schedule and the stopping rules are those of :mod:`diffloc.optim.lm`.

Step expansions (``LMConfig.step_expansions``, off by default)
    Under a redescending kernel (Cauchy) the IRLS model overestimates the curvature of the
    robust cost, so even undamped steps are systematically short (by 2-6x on the surfel
    problem of seed 1) and LM converges slowly. After an accepted step, steps 2, 4, ... times
    as long are tried (residual evaluations only, no solve) while the cost keeps falling. Poses
    whose blocks are mostly down-weighted outliers (``support``, the robust weights on the
    pose summed over its residual components, below ``expansion_min_support``) keep the
    plain step: the robust cost is nearly flat for them, and lengthened steps could carry them
    far away. The damping update still uses the gain ratio of the plain step.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch

from diffloc.optim.lm.config import LMConfig
from diffloc.optim.lm.problem import LinearSystem, LMProblem, _select

__all__ = ["LMRun", "minimize"]


# Stop reasons, indexed by the per-problem status code used inside the solver loop.
_RUNNING, _GRADIENT, _STEP, _COST, _MAX_ITERATIONS, _DAMPING, _INACTIVE = range(7)
_REASONS = ("running", "gradient", "step", "cost", "max_iterations", "damping", "inactive")
_CONVERGED_REASONS = ("gradient", "step", "cost")
_ROUNDOFF_EPS = 16.0
"""Cost changes below this many machine epsilons of the cost are rounding noise."""


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


def minimize(
    problem: LMProblem,
    params: Any,
    config: LMConfig,
    system: LinearSystem | None = None,
    active: Sequence[bool] | None = None,
) -> LMRun:
    """Batched Levenberg-Marquardt: the loop every front end of this module shares.

    Runs the damping schedule and the stopping rules of :mod:`diffloc.optim.lm` on ``B`` problems
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
