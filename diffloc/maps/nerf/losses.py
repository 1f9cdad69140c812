"""Training losses of the radiance field (seed 2 III-D3): photometric, Eq. 6 depth, Eq. 7 normal.

Depth (Eq. 6, DS-NeRF form, Deng et al. 2022): the ray termination distribution ``w(t)``
should match a normal distribution ``N(D, sigma_hat)`` around the lidar range ``D``::

    KL[N || w] = -H(N) - integral N(t; D, sigma_hat) log w(t) dt
               ~ -0.5 log(2 pi e sigma_hat^2) - sum_i N(t_i; D, sigma_hat) log(w_i/delta_i) delta_i

with ``w_i`` the Eq. 5 weights, ``delta_i`` the sample intervals and ``w_i / delta_i`` the
termination density at ``t_i``. The entropy term is constant; it makes the loss zero when the
two distributions agree. ``sigma_hat`` is the lidar's range noise: 0.01 m for diffloc's
simulated lidar (``diffloc.sim.lidar.LidarConfig.range_noise_std_m``), the datasheet range
accuracy on a real sensor. It is a setting, never read from the data at run time. Training
starts wider and shrinks towards it (``NerfLossConfig``), as nerfstudio's depth-nerfacto does.

Normal (Eq. 7, MonoSDF form): ``|N_hat - N_bar|_1 + |1 - N_hat^T N_bar|`` per ray, with
``N_hat`` the rendered normal (weights times the normalised negative density gradient) and
``N_bar`` the normal of the lidar surface.
"""

from __future__ import annotations

import math

import torch

from diffloc.checks import check_shape

__all__ = ["depth_kl_loss", "normal_loss", "photometric_loss"]


def photometric_loss(rgb: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared colour error: rgb, target (R, 3) -> scalar."""
    check_shape(rgb, "R,3", "rgb")
    check_shape(target, "R,3", "target")
    return ((rgb - target) ** 2).mean()


def depth_kl_loss(
    weights: torch.Tensor,
    t: torch.Tensor,
    deltas: torch.Tensor,
    depth: torch.Tensor,
    sigma: float,
    eps: float = 1e-6,
) -> torch.Tensor:
    """Eq. 6: mean over rays of ``KL[N(D, sigma) || w(t)]`` (see the module docstring).

    Args:
        weights: (R, S) Eq. 5 weights.
        t: (R, S) sample distances.
        deltas: (R, S) sample interval lengths.
        depth: (R,) measured ranges D along the rays (metres).
        sigma: sigma_hat, metres (> 0).
        eps: floor of the termination density inside the log.

    Returns:
        Scalar loss.

    Example:
        >>> t = torch.linspace(0.5, 1.5, 201)[None]
        >>> d = torch.full_like(t, 0.005)
        >>> w = torch.exp(-0.5 * ((t - 1) / 0.05) ** 2); w = w / w.sum()
        >>> float(depth_kl_loss(w, t, d, torch.tensor([1.0]), 0.05)) < 1e-3
        True
    """
    check_shape(weights, "R,S", "weights")
    check_shape(t, "R,S", "t")
    check_shape(deltas, "R,S", "deltas")
    check_shape(depth, "R", "depth")
    if not sigma > 0:
        raise ValueError(f"sigma must be positive, got {sigma}")
    gauss = torch.exp(-0.5 * ((t - depth[:, None]) / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi))
    cross = -(gauss * torch.log(weights / deltas.clamp_min(1e-9) + eps) * deltas).sum(dim=-1)
    entropy = 0.5 * math.log(2 * math.pi * math.e * sigma**2)
    return (cross - entropy).mean()


def normal_loss(normal: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Eq. 7: mean over rays of ``|N_hat - N_bar|_1 + |1 - N_hat^T N_bar|``.

    Args:
        normal: (R, 3) rendered normals N_hat.
        target: (R, 3) unit lidar normals N_bar.

    Returns:
        Scalar loss (zero when the normals agree).
    """
    check_shape(normal, "R,3", "normal")
    check_shape(target, "R,3", "target")
    l1 = (normal - target).abs().sum(dim=-1)
    return (l1 + (1.0 - (normal * target).sum(dim=-1)).abs()).mean()
