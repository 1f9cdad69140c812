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
    (:func:`diffloc.geometry.se3.cayley_rotation`). This retraction agrees with
    ``T_wc @ se3_exp(delta)`` to first order (so the Jacobians are the same) and costs a
    handful of tensor operations instead of the exponential's trigonometric branches.
    Jacobians given by the caller must follow this convention:
    ``J_a = d r(T_a @ se3_exp(d)) / d d`` at ``d = 0``. For a
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

Layout
    :mod:`~diffloc.optim.lm.config` (:class:`LMConfig`), :mod:`~diffloc.optim.lm.linearize`
    (residual and Jacobian function types, autodiff Jacobians),
    :mod:`~diffloc.optim.lm.retraction` (the pose update),
    :mod:`~diffloc.optim.lm.structure`, :mod:`~diffloc.optim.lm.block_assembly` and
    :mod:`~diffloc.optim.lm.block_system` (block-sparse normal equations, their memory and
    solvers), :mod:`~diffloc.optim.lm.pose_system` (batched 6x6 normal equations),
    :mod:`~diffloc.optim.lm.linalg` (dense and CG solvers), :mod:`~diffloc.optim.lm.problem`
    and :mod:`~diffloc.optim.lm.loop` (the loop, step expansions),
    :mod:`~diffloc.optim.lm.block_front_end`, :mod:`~diffloc.optim.lm.pose_front_end` and
    their :mod:`~diffloc.optim.lm.inputs`, :mod:`~diffloc.optim.lm.cost` and
    :mod:`~diffloc.optim.lm.result`.

Example:
    >>> import torch
    >>> targets = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    >>> def residual_fn(T_a, T_b, extra):  # pose translation minus a target
    ...     return T_a[..., :3, 3] - targets
    >>> result = levenberg_marquardt(
    ...     torch.eye(4, dtype=torch.float64)[None], residual_fn, torch.tensor([0]))
    >>> result.T_wc[0, :3, 3].round(decimals=9)
    tensor([1., 2., 3.], dtype=torch.float64)
"""

from diffloc.optim.lm.block_front_end import levenberg_marquardt
from diffloc.optim.lm.config import SOLVERS, LMConfig
from diffloc.optim.lm.linalg import solve_spd
from diffloc.optim.lm.linearize import (
    BlockJacobianFn,
    BlockLinearization,
    BlockResidualFn,
    PoseJacobianFn,
    PoseResidualFn,
    autodiff_linearize,
)
from diffloc.optim.lm.loop import LMRun, minimize
from diffloc.optim.lm.pose_front_end import levenberg_marquardt_single_pose
from diffloc.optim.lm.pose_system import PoseSystem
from diffloc.optim.lm.problem import LinearSystem, LMProblem
from diffloc.optim.lm.result import LMResult

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
    "levenberg_marquardt",
    "levenberg_marquardt_single_pose",
    "minimize",
    "solve_spd",
]
