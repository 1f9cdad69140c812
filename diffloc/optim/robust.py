"""Robust kernels on squared residual norms, in the Ceres convention.

A residual block ``r_i`` (already whitened, i.e. multiplied by the square root of its
information matrix) contributes ``0.5 * rho(s_i)`` to the cost, with ``s_i = ||r_i||^2``::

    cost = 0.5 * sum_i rho(||r_i||^2)

For the trivial kernel ``rho(s) = s`` this is the usual least-squares cost. g2o / ORB-SLAM
use ``sum_i rho(s_i)`` with the same ``rho``: the factor 0.5 changes neither the minimiser nor
the thresholds. Every kernel returns ``(rho(s), rho'(s))``; ``rho'(s)`` is the weight of the
iteratively reweighted least-squares (IRLS) step used by :mod:`diffloc.optim.lm`: the
gradient of the cost is ``sum_i rho'(s_i) J_i^T r_i`` and the Gauss-Newton matrix is
``sum_i rho'(s_i) J_i^T J_i`` (no second-order correction of the kernel).

The ``scale`` of a kernel is in units of the residual norm ``sqrt(s)``: Huber with
``delta = sqrt(5.991)`` is quadratic up to ``s = 5.991`` (ORB-SLAM's 95 % chi-square
threshold for two degrees of freedom).

Example:
    >>> kernel = make_robust_kernel(RobustKernel("huber", 1.0))
    >>> rho, weight = kernel(torch.tensor([0.25, 4.0]))
    >>> rho, weight
    (tensor([0.2500, 3.0000]), tensor([1.0000, 0.5000]))
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

__all__ = [
    "KERNEL_NAMES",
    "KernelFn",
    "RobustKernel",
    "cauchy",
    "huber",
    "make_robust_kernel",
    "trivial",
]

KernelFn = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""A kernel with its scale bound: ``s (...) -> (rho(s) (...), rho'(s) (...))``."""


def trivial(s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The identity kernel ``rho(s) = s`` (plain least squares).

    Args:
        s: (...) squared residual norms (>= 0).

    Returns:
        ``(rho, weight)``: (...) ``s`` and (...) ones.

    Example:
        >>> trivial(torch.tensor([2.0]))
        (tensor([2.]), tensor([1.]))
    """
    return s, torch.ones_like(s)


def huber(s: torch.Tensor, delta: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Huber kernel: quadratic below ``delta``, linear in the norm above.

    ``rho(s) = s`` for ``s <= delta^2``, else ``2 delta sqrt(s) - delta^2``;
    ``rho'(s) = min(1, delta / sqrt(s))``. Continuous with a continuous first derivative and
    finite gradients everywhere, including ``s = 0``.

    Args:
        s: (...) squared residual norms (>= 0).
        delta: positive threshold on the residual norm ``sqrt(s)``.

    Returns:
        ``(rho, weight)``, both (...).

    Example:
        >>> huber(torch.tensor([1.0, 9.0]), 1.0)
        (tensor([1., 5.]), tensor([1.0000, 0.3333]))
    """
    d2 = delta * delta
    inside = s <= d2
    root = torch.sqrt(torch.where(inside, torch.full_like(s, d2), s))
    rho = torch.where(inside, s, 2.0 * delta * root - d2)
    weight = torch.where(inside, torch.ones_like(s), delta / root)
    return rho, weight


def cauchy(s: torch.Tensor, c: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Cauchy (Lorentzian) kernel ``rho(s) = c^2 log(1 + s / c^2)``.

    ``rho'(s) = 1 / (1 + s / c^2)``: large residuals are down-weighted more strongly than by
    :func:`huber` (the cost grows only logarithmically).

    Args:
        s: (...) squared residual norms (>= 0).
        c: positive scale on the residual norm.

    Returns:
        ``(rho, weight)``, both (...).

    Example:
        >>> cauchy(torch.tensor([0.0, 1.0]), 1.0)
        (tensor([0.0000, 0.6931]), tensor([1.0000, 0.5000]))
    """
    c2 = c * c
    return c2 * torch.log1p(s / c2), 1.0 / (1.0 + s / c2)


_SCALED_KERNELS: dict[str, Callable[[torch.Tensor, float], tuple[torch.Tensor, torch.Tensor]]] = {
    "huber": huber,
    "cauchy": cauchy,
}
KERNEL_NAMES = ("trivial", *_SCALED_KERNELS)
"""Names accepted by :class:`RobustKernel`."""


@dataclass
class RobustKernel:
    """Configuration of a robust kernel.

    Attributes:
        name: one of :data:`KERNEL_NAMES` (``"trivial"``, ``"huber"``, ``"cauchy"``).
        scale: positive kernel scale in units of the residual norm (Huber's ``delta``,
            Cauchy's ``c``); ignored by ``"trivial"``.

    Raises:
        ValueError: unknown name or non-positive / non-finite scale.

    Example:
        >>> RobustKernel("huber", 5.991**0.5).name
        'huber'
    """

    name: str = "trivial"
    scale: float = 1.0

    def __post_init__(self) -> None:
        if self.name not in KERNEL_NAMES:
            raise ValueError(f"unknown robust kernel {self.name!r}; choose one of {KERNEL_NAMES}")
        scale = self.scale
        if isinstance(scale, bool) or not isinstance(scale, int | float):
            raise ValueError(f"robust kernel scale must be a number, got {scale!r}")
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"robust kernel scale must be positive and finite, got {scale}")


def make_robust_kernel(config: RobustKernel) -> KernelFn:
    """The kernel function described by ``config``.

    Args:
        config: kernel name and scale.

    Returns:
        A function ``s (...) -> (rho(s), rho'(s))``.

    Example:
        >>> make_robust_kernel(RobustKernel("cauchy", 2.0))(torch.tensor([4.0]))[1]
        tensor([0.5000])
    """
    if config.name == "trivial":
        return trivial
    kernel, scale = _SCALED_KERNELS[config.name], float(config.scale)

    def scaled(s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return kernel(s, scale)

    return scaled
