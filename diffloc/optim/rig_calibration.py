"""Camera extrinsic and time offset shared by all keyframes, from surfel reprojection.

Beyond seed 1: its Sec. III-B names the lidar-camera extrinsic parameters and time offsets as
the source of keyframe pose error when camera poses are made from lidar (body) poses. Instead
of one free pose per keyframe (:func:`~diffloc.optim.surfel_cost.optimize_keyframe_poses`),
this estimates the two quantities every keyframe shares, from the same residuals (Eq. 3-4).

Model
    Keyframe ``k``'s image has timestamp ``t_k`` and the body (lidar) trajectory ``T_wb`` is
    sampled at known times. The database pose was made with some camera extrinsic ``X_k``
    (normally one ``T_bc`` for all), ``T_wc_k^0 = T_wb(t_k) X_k``, so
    ``X_k = T_wb(t_k)^-1 T_wc_k^0``. With an extrinsic correction ``C`` (``T_bc <- T_bc C``) and
    a time offset ``dt`` (the camera image belongs to body time ``t_k + dt``) the keyframe is::

        T_wc_k(C, dt) = T_wb(t_k + dt) X_k C ~= T_wc_k^0 Exp(dt u_k) C,   u_k = Ad(X_k^-1) v_k

    ``v_k`` is the body twist at ``t_k`` (right-trivialised, ``T_wb(t_k + s) ~= T_wb(t_k)
    Exp(s v_k)``, translation first), from finite differences of the trajectory samples
    (:func:`body_twists`), and ``u_k`` the same motion in the camera frame. The model is
    first order in ``dt``: it neglects ``0.5 dt^2`` times the acceleration (30 ms at 1 m/s^2:
    0.45 mm) and the finite-difference error of ``v_k``.

Jacobians
    A right perturbation ``C Exp(delta)`` moves every keyframe by ``T_wc_k Exp(delta)``, so the
    Jacobian of a pair ``(alpha, beta)`` is ``J_alpha + J_beta`` of
    :meth:`~diffloc.optim.surfel_cost.SurfelReprojectionCost.linearize`; ``dt + eps`` moves
    keyframe ``k`` by ``T_wc_k Exp(eps Ad(C^-1) u_k)``, so
    ``d r / d dt = J_alpha Ad(C^-1) u_alpha + J_beta Ad(C^-1) u_beta``.

Solver
    :func:`~diffloc.optim.lm.levenberg_marquardt` with ``C`` as its one pose and ``dt`` as its
    one extra parameter (none when the time offset is not estimated): robust IRLS on 6x6 or
    7x7 normal equations, one residual block per surfel pair, pairs invalid at the database
    poses masked out. Default kernel: Cauchy 2 px, as ``DatabaseConfig.optim``.
    :func:`corrected_rig` applies the correction to a :class:`~diffloc.geometry.rig.SensorRig`
    (URDF xyz/rpy); the time offset is the caller's to apply to the image timestamps.

Observability and limits
    ``dt`` is separable from ``C`` only where the camera twist ``u_k`` changes between
    keyframes (turns, speed changes): at a constant ``u`` the product ``Exp(dt u) C`` is one
    constant transform. With little variation ``dt`` and the translation of ``C`` along the
    motion are strongly correlated (check ``std`` and ``dt_correlation`` of the result;
    ``std`` counts the residuals as independent noise and is optimistic when the error is a
    bias of the database's associations). The twists need a trajectory sampled well above
    the motion's bandwidth: on the default indoor scene body poses at the 2 Hz image rate
    alias the walking bob and blur the turns (``dt`` off by 2.5 ms of 30, 0.3 deg rotation
    RMSE left per keyframe), at 100 Hz ``dt`` is right to 0.06 ms
    (``experiments/bench_rig_calibration.py``).
    There is no joint mode with free keyframe poses: they would absorb any shared correction
    (a gauge freedom); run :func:`~diffloc.optim.surfel_cost.optimize_keyframe_poses` after the
    calibration for what remains per keyframe.

Example:
    >>> T_wb = se3_exp(torch.tensor([[0.0] * 6, [1.0, 0, 0, 0, 0, 0]], dtype=torch.float64))
    >>> body_twists(T_wb, torch.tensor([0.0, 0.5], dtype=torch.float64))[0]
    tensor([2., 0., 0., 0., 0., 0.], dtype=torch.float64)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import nn

from diffloc.checks import ShapeError, check_finite, check_shape
from diffloc.database.database import VisualDatabase
from diffloc.geometry.rig import SensorRig, rpy_from_rotation
from diffloc.geometry.se3 import adjoint, invert, se3_exp, se3_log
from diffloc.optim.lm import BlockLinearization, LMConfig, levenberg_marquardt
from diffloc.optim.robust import RobustKernel, make_robust_kernel
from diffloc.optim.surfel_cost import SurfelReprojectionCost, pairs_from_database

__all__ = [
    "MIN_KEYFRAMES",
    "RigCalibrationConfig",
    "RigCalibrationCost",
    "RigCalibrationResult",
    "body_twists",
    "calibrate_rig",
    "corrected_rig",
]

MIN_KEYFRAMES = 2
"""Fewest keyframes :func:`calibrate_rig` accepts (a surfel pair needs two observers)."""


def _check_times(times: torch.Tensor, count: int) -> None:
    check_shape(times, f"{count}", "times")
    check_finite(times, "times")
    if bool((torch.diff(times) <= 0).any()):
        raise ValueError("times must be strictly increasing")


def body_twists(T_wb: torch.Tensor, times: torch.Tensor) -> torch.Tensor:
    """Body twists of a sampled trajectory by finite differences.

    With ``f(s) = log(T_i^-1 T(t_i + s))`` and the spacings ``h+ = t_{i+1} - t_i``,
    ``h- = t_i - t_{i-1}``, the twist ``v_i = f'(0)`` is the non-uniform central difference
    ``(h-^2 f(h+) - h+^2 f(-h-)) / (h+ h- (h+ + h-))`` (second order; exact when ``f`` is
    quadratic, e.g. a constant twist), one-sided ``f(h+) / h+`` and ``-f(-h-) / h-`` at the
    first and last samples (first order).

    Args:
        T_wb: (N, 4, 4) body-to-world poses, N >= 2.
        times: (N,) strictly increasing timestamps, seconds.

    Returns:
        (N, 6) twists ``[v, w]`` in the body frame, m/s and rad/s:
        ``T_wb(t_i + s) ~= T_wb[i] @ se3_exp(s * twist[i])``.

    Raises:
        ShapeError: wrong shapes.
        ValueError: fewer than two samples, non-finite values, or times not strictly
            increasing.

    Example:
        >>> xi = torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.2], dtype=torch.float64)
        >>> times = torch.tensor([0.0, 0.3, 1.0], dtype=torch.float64)
        >>> torch.allclose(body_twists(se3_exp(times[:, None] * xi), times), xi.expand(3, 6))
        True
    """
    check_shape(T_wb, "N,4,4", "T_wb")
    count = T_wb.shape[0]
    if count < 2:
        raise ValueError(f"a trajectory needs at least 2 samples for its twists, got {count}")
    check_finite(T_wb, "T_wb")
    _check_times(times, count)
    T_wb, times = T_wb.to(torch.float64), times.to(torch.float64)
    index = torch.arange(count)
    following, preceding = (index + 1).clamp(max=count - 1), (index - 1).clamp(min=0)
    T_bw = invert(T_wb)
    f_next = se3_log(T_bw @ T_wb[following])  # zero at the last sample
    f_prev = se3_log(T_bw @ T_wb[preceding])  # zero at the first sample
    h_next, h_prev = times[following] - times, times - times[preceding]
    # Weights of the forward and backward differences: h- / (h+ + h-) and h+ / (h+ + h-)
    # inside, (1, 0) at the first sample and (0, 1) at the last.
    interior = (index > 0) & (index < count - 1)
    w_next = torch.where(interior, h_prev / torch.where(interior, h_next + h_prev, 1.0), 0.0)
    w_next = torch.where(index == 0, 1.0, w_next)
    forward = f_next / torch.where(h_next > 0, h_next, 1.0)[:, None]
    backward = -f_prev / torch.where(h_prev > 0, h_prev, 1.0)[:, None]
    return w_next[:, None] * forward + (1.0 - w_next)[:, None] * backward


class RigCalibrationCost(nn.Module):
    """Surfel reprojection residuals of keyframes moved by a shared rig correction.

    Keyframe ``k`` is at ``T_wc[k] @ se3_exp(dt * twists[k]) @ T_correction`` (module notes);
    the residuals of pair ``m`` are those of ``cost`` at the keyframes ``alpha[m]`` and
    ``beta[m]``.

    Args:
        cost: the :class:`~diffloc.optim.surfel_cost.SurfelReprojectionCost` of ``M`` pairs.
        alpha: (M,) int64 keyframe of each pair's first observer.
        beta: (M,) int64 keyframe of each pair's other observer.
        T_wc: (K, 4, 4) database keyframe poses, camera-to-world.
        twists: (K, 6) camera twists ``u_k`` (camera frame, m/s and rad/s); zeros when the
            time offset is not modelled.

    Raises:
        ShapeError: inconsistent shapes.
        ValueError: non-finite poses or twists, or keyframe indices out of range.

    Example:
        >>> K = torch.tensor([[500.0, 500.0, 319.5, 239.5]], dtype=torch.float64)
        >>> kp = torch.tensor([[319.5, 239.5]], dtype=torch.float64)
        >>> n = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
        >>> surfel = SurfelReprojectionCost(kp, kp + 1.0, -2 * n, n, K, K)
        >>> T = torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
        >>> one, zero = torch.ones(1, dtype=torch.long), torch.zeros(1, dtype=torch.long)
        >>> rig = RigCalibrationCost(surfel, zero, one, T, torch.zeros(2, 6, dtype=torch.float64))
        >>> rig(torch.eye(4, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64))
        tensor([[-1., -1.]], dtype=torch.float64)
    """

    alpha: torch.Tensor
    beta: torch.Tensor
    T_wc: torch.Tensor
    twists: torch.Tensor

    def __init__(
        self,
        cost: SurfelReprojectionCost,
        alpha: torch.Tensor,
        beta: torch.Tensor,
        T_wc: torch.Tensor,
        twists: torch.Tensor,
    ) -> None:
        super().__init__()
        num_pairs = cost.sigma.shape[0]
        check_shape(alpha, f"{num_pairs}", "alpha")
        check_shape(beta, f"{num_pairs}", "beta")
        check_shape(T_wc, "K,4,4", "T_wc")
        check_shape(twists, f"{T_wc.shape[0]},6", "twists")
        check_finite(T_wc, "T_wc")
        check_finite(twists, "twists")
        indices = torch.cat((alpha, beta))
        if bool(((indices < 0) | (indices >= T_wc.shape[0])).any()):
            raise ValueError(f"alpha and beta must hold keyframe indices in [0, {T_wc.shape[0]})")
        self.cost = cost
        self.register_buffer("alpha", alpha.long())
        self.register_buffer("beta", beta.long())
        self.register_buffer("T_wc", T_wc.to(torch.float64))
        self.register_buffer("twists", twists.to(torch.float64))

    def keyframe_poses(self, T_correction: torch.Tensor, dt: torch.Tensor) -> torch.Tensor:
        """Corrected keyframe poses ``T_wc[k] @ se3_exp(dt * twists[k]) @ T_correction``.

        Args:
            T_correction: (..., 4, 4) extrinsic corrections ``C``.
            dt: (...) time offsets, seconds.

        Returns:
            (..., K, 4, 4) camera-to-world poses.
        """
        check_shape(T_correction, "*,4,4", "T_correction")
        if dt.shape != T_correction.shape[:-2]:
            raise ShapeError(f"dt must have shape {tuple(T_correction.shape[:-2])}, got {dt.shape}")
        motion = se3_exp(dt[..., None, None] * self.twists)  # (..., K, 4, 4)
        return self.T_wc @ motion @ T_correction[..., None, :, :]

    def forward(self, T_correction: torch.Tensor, dt: torch.Tensor) -> torch.Tensor:
        """Whitened residuals at the corrected keyframe poses.

        Args:
            T_correction: (..., 4, 4) extrinsic corrections.
            dt: (...) time offsets, seconds.

        Returns:
            (..., M, 2) residuals, zero for invalid pairs.
        """
        T = self.keyframe_poses(T_correction, dt)
        return self.cost(T[..., self.alpha, :, :], T[..., self.beta, :, :])

    def linearize(self, T_correction: torch.Tensor, dt: torch.Tensor) -> BlockLinearization:
        """Residuals and analytic Jacobians w.r.t. the shared variables (module notes).

        Args:
            T_correction: (..., 4, 4) extrinsic corrections.
            dt: (...) time offsets, seconds.

        Returns:
            :class:`~diffloc.optim.lm.BlockLinearization`: ``residuals`` (..., M, 2), ``jac_a``
            (..., M, 2, 6) w.r.t. ``T_correction @ se3_exp(delta)`` and ``jac_extra``
            (..., M, 2, 1) w.r.t. ``dt``; ``jac_b`` is ``None``.
        """
        T = self.keyframe_poses(T_correction, dt)
        lin = self.cost.linearize(T[..., self.alpha, :, :], T[..., self.beta, :, :])
        ad = adjoint(invert(T_correction))[..., None, :, :]  # (..., 1, 6, 6)
        moved = (ad @ self.twists[:, :, None])[..., 0]  # (..., K, 6) Ad(C^-1) u_k
        jac_dt = lin.jac_a @ moved[..., self.alpha, :, None]
        jac_dt = jac_dt + lin.jac_b @ moved[..., self.beta, :, None]
        return BlockLinearization(lin.residuals, lin.jac_a + lin.jac_b, jac_extra=jac_dt)


@dataclass
class RigCalibrationConfig:
    """Settings of :func:`calibrate_rig`.

    Attributes:
        estimate_time_offset: also estimate the time offset (needs the body trajectory);
            ``False``: the extrinsic correction only (6 unknowns).
        sigma_px: keypoint standard deviation in pixels (whitening).
        kernel: robust kernel on the whitened residuals (Cauchy 2 px, as the database
            optimisation ``DatabaseConfig.optim``).
        lm: Levenberg-Marquardt settings.

    Raises:
        ValueError: non-positive ``sigma_px``.

    Example:
        >>> RigCalibrationConfig().kernel.name
        'cauchy'
    """

    estimate_time_offset: bool = True
    sigma_px: float = 1.0
    kernel: RobustKernel = field(default_factory=lambda: RobustKernel("cauchy", 2.0))
    lm: LMConfig = field(default_factory=lambda: LMConfig(max_iterations=50))

    def __post_init__(self) -> None:
        if not (math.isfinite(self.sigma_px) and self.sigma_px > 0):
            raise ValueError(f"sigma_px must be positive, got {self.sigma_px}")


@dataclass
class RigCalibrationResult:
    """Outcome of :func:`calibrate_rig`.

    Attributes:
        T_correction: (4, 4) float64 extrinsic correction ``C``: the corrected camera
            extrinsic is ``T_bc @ C``.
        dt: time offset correction, seconds: image ``k`` belongs to body time ``t_k + dt``
            (0 when not estimated).
        T_wc: (K, 4, 4) float64 corrected keyframe poses.
        initial_cost: robust cost (:mod:`diffloc.optim.robust` convention) at the database
            poses.
        cost: robust cost at the corrected poses.
        iterations: linear solves of Levenberg-Marquardt.
        converged: stopped by a gradient, step or cost tolerance.
        reason: the stop reason (see :class:`~diffloc.optim.lm.LMResult`).
        num_pairs: surfel pairs used (valid at the database poses).
        std: (6,) or (7,) float64 standard deviations of ``[v, w]`` of ``C`` (metres,
            radians) and of ``dt`` (seconds) from the inverse of the robustly weighted
            Gauss-Newton matrix at the solution, scaled by the residual variance: a
            conditioning diagnostic, optimistic when residuals are correlated.
        dt_correlation: (6,) float64 correlation of ``dt`` with each component of ``C``'s
            tangent (zeros when ``dt`` is not estimated); near +-1: ``dt`` is barely
            separable from the extrinsic (module notes).
    """

    T_correction: torch.Tensor
    dt: float
    T_wc: torch.Tensor
    initial_cost: float
    cost: float
    iterations: int
    converged: bool
    reason: str
    num_pairs: int
    std: torch.Tensor
    dt_correlation: torch.Tensor


def corrected_rig(rig: SensorRig, T_correction: torch.Tensor, camera: str = "camera") -> SensorRig:
    """The sensor rig with the camera extrinsic corrected: ``T_body_camera @ T_correction``.

    Args:
        rig: the rig the database poses were made with.
        T_correction: (4, 4) extrinsic correction (:attr:`RigCalibrationResult.T_correction`).
        camera: name of the camera sensor in the rig.

    Returns:
        A new :class:`~diffloc.geometry.rig.SensorRig` (same body, names and other sensors);
        ``to_urdf()`` writes the calibrated URDF.

    Raises:
        ShapeError: ``T_correction`` not (4, 4).
        ValueError: ``camera`` is not a sensor of the rig.

    Example:
        >>> rig = SensorRig({"camera": ([0.1, 0.0, 0.0], [0.0, 0.0, 0.0])})
        >>> shift = torch.eye(4, dtype=torch.float64)
        >>> shift[0, 3] = 0.02
        >>> corrected_rig(rig, shift).xyz["camera"].detach()
        tensor([0.1200, 0.0000, 0.0000], dtype=torch.float64)
    """
    check_shape(T_correction, "4,4", "T_correction")
    if camera not in rig.sensor_names:
        raise ValueError(f"the rig has no sensor {camera!r}; it has {rig.sensor_names}")
    offsets = {name: (rig.xyz[name].detach(), rig.rpy[name].detach()) for name in rig.sensor_names}
    with torch.no_grad():
        T_bc = rig.T_body_sensor(camera).to(torch.float64) @ T_correction.to(torch.float64)
    offsets[camera] = (T_bc[:3, 3], rpy_from_rotation(T_bc[:3, :3]))
    dtype = rig.xyz[camera].dtype
    return SensorRig(offsets, rig.body, rig.robot_name, rig.joint_names, dtype=dtype)


def _camera_twists(
    T_wc: torch.Tensor,
    T_wb: torch.Tensor | None,
    times: torch.Tensor | None,
    keyframe_indices: torch.Tensor | None,
) -> torch.Tensor:
    """(K, 6) camera twists ``u_k = Ad(X_k^-1) v_k``, ``X_k = T_wb(t_k)^-1 T_wc[k]``."""
    if T_wb is None or times is None:
        raise ValueError(
            "estimating the time offset needs the body trajectory T_wb and its times "
            "(or set estimate_time_offset=False)"
        )
    check_shape(T_wb, "N,4,4", "T_wb")
    num_keyframes, count = T_wc.shape[0], T_wb.shape[0]
    if keyframe_indices is None:
        if count != num_keyframes:
            raise ShapeError(
                f"T_wb holds {count} samples but the database {num_keyframes} keyframes: "
                "pass keyframe_indices"
            )
        keyframe_indices = torch.arange(num_keyframes)
    check_shape(keyframe_indices, f"{num_keyframes}", "keyframe_indices")
    if keyframe_indices.is_floating_point() or keyframe_indices.dtype == torch.bool:
        raise TypeError(f"keyframe_indices must be integers, got {keyframe_indices.dtype}")
    if bool(((keyframe_indices < 0) | (keyframe_indices >= count)).any()):
        raise ValueError(f"keyframe_indices must be in [0, {count})")
    index = keyframe_indices.long()
    v_body = body_twists(T_wb, times)[index]
    T_bc = invert(T_wb[index].to(torch.float64)) @ T_wc
    return (adjoint(invert(T_bc)) @ v_body[:, :, None])[..., 0]


def _covariance_summary(
    rig: RigCalibrationCost,
    T_correction: torch.Tensor,
    dt: torch.Tensor,
    valid: torch.Tensor,
    config: RigCalibrationConfig,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Standard deviations (D,) and ``dt``'s (6,) correlations (:class:`RigCalibrationResult`).

    ``Cov = s^2 H^-1`` with ``H = sum w J^T J`` (IRLS weights ``w`` of the kernel) and
    ``s^2 = sum w ||r||^2 / (2 V - D)`` over the ``V`` valid pairs, ``D`` unknowns.
    """
    lin = rig.linearize(T_correction, dt)
    J = lin.jac_a if not config.estimate_time_offset else torch.cat((lin.jac_a, lin.jac_extra), -1)
    J, r = J[valid], lin.residuals[valid]  # (V, 2, D), (V, 2)
    squared = r.square().sum(-1)
    weight = make_robust_kernel(config.kernel)(squared)[1]
    H = torch.einsum("v,vri,vrj->ij", weight, J, J)
    dof = max(2 * J.shape[0] - J.shape[-1], 1)
    covariance = torch.linalg.pinv(H, hermitian=True) * (weight * squared).sum() / dof
    std = covariance.diagonal().clamp(min=0.0).sqrt()
    if not config.estimate_time_offset:
        return std, std.new_zeros(6)
    scale = std[6] * std[:6]
    return std, torch.where(scale > 0, covariance[6, :6] / torch.where(scale > 0, scale, 1.0), 0.0)


def calibrate_rig(
    db: VisualDatabase,
    surfel_centers: torch.Tensor,
    surfel_normals: torch.Tensor,
    T_wb: torch.Tensor | None = None,
    times: torch.Tensor | None = None,
    keyframe_indices: torch.Tensor | None = None,
    config: RigCalibrationConfig | None = None,
) -> RigCalibrationResult:
    """Estimate the camera extrinsic correction and time offset shared by all keyframes.

    See the module notes for the model. The database is not modified.

    Args:
        db: the visual database; ``db.T_wc`` (K, 4, 4) are the poses made from the body
            trajectory with the extrinsic (and offset) to correct.
        surfel_centers: (S, 3) surfel centres, world frame.
        surfel_normals: (S, 3) surfel normals.
        T_wb: (N, 4, 4) body-to-world poses of the trajectory, N >= 2; needed when
            ``config.estimate_time_offset``, unused otherwise.
        times: (N,) strictly increasing timestamps of ``T_wb``, seconds.
        keyframe_indices: (K,) int64 sample of ``T_wb`` at keyframe ``k``'s image time
            (default ``arange(K)``: ``T_wb`` holds exactly the keyframes' body poses).
        config: settings (default :class:`RigCalibrationConfig`).

    Returns:
        :class:`RigCalibrationResult`.

    Raises:
        ShapeError: wrong shapes.
        TypeError: non-integer ``keyframe_indices``.
        ValueError: fewer than :data:`MIN_KEYFRAMES` keyframes, non-finite poses or times,
            times not strictly increasing, indices out of range, a missing trajectory when
            the time offset is estimated, bad surfels, or no valid surfel pair.

    Example:
        >>> s = torch.zeros(1, 3, dtype=torch.float64)
        >>> calibrate_rig(VisualDatabase(2), s, s)
        Traceback (most recent call last):
        ...
        ValueError: rig calibration needs at least 2 keyframes, the database has 0
    """
    config = config or RigCalibrationConfig()
    num_keyframes = db.num_keyframes
    if num_keyframes < MIN_KEYFRAMES:
        raise ValueError(
            f"rig calibration needs at least {MIN_KEYFRAMES} keyframes, "
            f"the database has {num_keyframes}"
        )
    T_wc = db.T_wc.to(torch.float64)
    check_finite(T_wc, "db.T_wc")
    if config.estimate_time_offset:
        twists = _camera_twists(T_wc, T_wb, times, keyframe_indices)
    else:
        twists = T_wc.new_zeros(num_keyframes, 6)
    pairs = pairs_from_database(db, surfel_centers, surfel_normals)
    sigma = torch.full((len(pairs),), config.sigma_px, dtype=torch.float64)
    surfel_cost = SurfelReprojectionCost.from_pairs(pairs, sigma)
    valid = surfel_cost.residuals_and_valid(T_wc[pairs.alpha], T_wc[pairs.beta])[1]
    if not bool(valid.any()):
        raise ValueError("the database has no valid surfel pairs to calibrate from")
    rig = RigCalibrationCost(surfel_cost, pairs.alpha, pairs.beta, T_wc, twists)
    extra = T_wc.new_zeros(1) if config.estimate_time_offset else None

    def offsets(T_a: torch.Tensor, e: torch.Tensor | None) -> torch.Tensor:
        return T_a.new_zeros(T_a.shape[0]) if e is None else e[:, 0]

    def residual_fn(T_a: torch.Tensor, _: torch.Tensor | None, e: torch.Tensor | None):
        return rig(T_a[:, 0], offsets(T_a, e))  # every block holds the same pose C

    def jacobian_fn(T_a: torch.Tensor, _: torch.Tensor | None, e: torch.Tensor | None):
        lin = rig.linearize(T_a[:, 0], offsets(T_a, e))
        return BlockLinearization(
            lin.residuals, lin.jac_a, jac_extra=None if e is None else lin.jac_extra
        )

    result = levenberg_marquardt(
        torch.eye(4, dtype=torch.float64)[None],
        residual_fn,
        torch.zeros(len(pairs), dtype=torch.long),
        extra=extra,
        jacobian_fn=jacobian_fn,
        mask=valid,
        kernel=config.kernel,
        config=config.lm,
    )
    T_correction = result.T_wc[0]
    dt = result.extra if result.extra is not None else T_wc.new_zeros(1)
    std, correlation = _covariance_summary(rig, T_correction, dt[0], valid, config)
    return RigCalibrationResult(
        T_correction=T_correction,
        dt=float(dt[0]),
        T_wc=rig.keyframe_poses(T_correction, dt[0]),
        initial_cost=float(result.cost_history[0]),
        cost=float(result.cost),
        iterations=int(result.iterations),
        converged=bool(result.converged),
        reason=result.reason[0],
        num_pairs=int(valid.sum()),
        std=std,
        dt_correlation=correlation,
    )
