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

Empty space (lidar rays without a return, :mod:`diffloc.maps.nerf.no_return`): a ray along which
the lidar measured nothing should pass the whole field, ``log(1 + tau)`` per ray with
``tau = sum_i sigma_i delta_i`` the optical depth from the near to the far bound
(:func:`empty_space_loss`).
"""

from __future__ import annotations

import math

import torch

from diffloc.checks import check_shape

__all__ = ["depth_kl_loss", "empty_space_loss", "normal_loss", "photometric_loss"]


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


def empty_space_loss(density: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """Mean over rays of ``log(1 + tau)``, ``tau = sum_i sigma_i delta_i`` the ray's optical
    depth over all its samples, for rays that should pass the field unhit.

    Why this form: the probability that a ray passes every sample is the transmittance
    ``T = exp(-tau)``, so ``-log T = tau`` is the negative log-likelihood of "no return", the
    no-return counterpart of Eq. 6's cross-entropy; ``log(1 + tau)`` equals it for small
    ``tau`` and grows only logarithmically for opaque rays, so a sky painted with density early
    on does not swamp the photometric loss, while its gradient ``1 / (1 + tau)`` per unit of
    optical depth never vanishes. The opacity ``1 - T`` (the obvious alternative) has gradient
    ``T``: about 1e-3 on the opaque sky the field paints outdoors (mean sky opacity 0.998),
    i.e. none where it is needed. Why the whole ray, to the contracted far bound
    (``SamplerConfig.far_m``) rather than to the lidar's maximum range: the sky the camera
    sees is explained either by density somewhere along the ray or by the background colour,
    and only an empty ray leaves the transmittance that gives the background its gradient;
    emptied only to the maximum range, the field could keep painting the sky beyond it.
    What lies beyond the sensor's range along such a ray (a far facade, on a real site) is
    then left to the background colour.

    Args:
        density: (R, S) densities of the rays' samples (zero where not evaluated), 1/m.
        deltas: (R, S) sample interval lengths, metres.

    Returns:
        Scalar loss (zero for empty rays).

    Example:
        >>> empty_space_loss(torch.zeros(2, 3), torch.ones(2, 3))
        tensor(0.)
    """
    check_shape(density, "R,S", "density")
    check_shape(deltas, "R,S", "deltas")
    return torch.log1p((density * deltas).sum(dim=-1)).mean()
