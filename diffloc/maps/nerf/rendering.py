"""Volume rendering along rays (NeRF quadrature, seed 2 Eq. 5).

``w_i = exp(-sum_{j<i} delta_j sigma_j) (1 - exp(-delta_i sigma_i))`` with ``delta_i`` the
length of sample i's interval. Expected colour, range and normal are ``sum_i w_i x_i``; with a
background colour ``c_bg`` the colour is ``sum_i w_i c_i + T_final c_bg`` with the transmittance
left at the end of the ray ``T_final = 1 - sum_i w_i`` (:func:`composite_over`). Range and
opacity keep their meaning (the background adds colour only).
"""

from __future__ import annotations

import torch

from diffloc.checks import check_shape

__all__ = ["composite", "composite_over", "render_weights"]


def render_weights(density: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """Eq. 5 weights.

    Args:
        density: (R, S) non-negative densities in 1/m.
        deltas: (R, S) interval lengths in metres.

    Returns:
        (R, S) weights; each row sums to the ray's opacity (<= 1).

    Example:
        >>> render_weights(torch.tensor([[0.0, 1e9]]), torch.tensor([[1.0, 1.0]]))
        tensor([[0., 1.]])
    """
    check_shape(density, "R,S", "density")
    check_shape(deltas, "R,S", "deltas")
    tau = density * deltas
    before = torch.cat((torch.zeros_like(tau[:, :1]), torch.cumsum(tau, dim=-1)[:, :-1]), dim=-1)
    transmittance = torch.exp(-before)
    return transmittance * (1.0 - torch.exp(-tau))


def composite(weights: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``sum_i w_i values_i`` per ray: weights (R, S), values (R, S, C) or (R, S) -> (R, C) or
    (R,)."""
    check_shape(weights, "R,S", "weights")
    if values.dim() == 2:
        return (weights * values).sum(dim=-1)
    return (weights[..., None] * values).sum(dim=-2)


def composite_over(
    weights: torch.Tensor, colours: torch.Tensor, background: torch.Tensor
) -> torch.Tensor:
    """Colour ``sum_i w_i c_i + (1 - sum_i w_i) c_bg`` per ray: the samples' colours composited
    over a background colour with the transmittance left after the last sample. Colour only:
    range and opacity are unchanged by a background.

    Args:
        weights: (R, S) Eq. 5 weights.
        colours: (R, S, 3) sample colours.
        background: (R, 3) background colour per ray.

    Returns:
        (R, 3) colours.

    Example:
        >>> composite_over(torch.zeros(1, 2), torch.ones(1, 2, 3), torch.tensor([[0.2, 0.4, 0.6]]))
        tensor([[0.2000, 0.4000, 0.6000]])
    """
    check_shape(background, "R,3", "background")
    transmittance = 1.0 - weights.sum(dim=-1, keepdim=True)
    return composite(weights, colours) + transmittance * background
