"""Volume rendering along rays (NeRF quadrature, seed 2 Eq. 5).

``w_i = exp(-sum_{j<i} delta_j sigma_j) (1 - exp(-delta_i sigma_i))`` with ``delta_i`` the
length of sample i's interval. Expected colour, range and normal are ``sum_i w_i x_i``.
"""

from __future__ import annotations

import torch

from diffloc.checks import check_shape

__all__ = ["composite", "render_weights"]


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
