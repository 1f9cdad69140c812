"""Appearance codes of images the field was not trained on (NeRF-W's test-time protocol):
optimise a code, field frozen, on some pixels of the image."""

from __future__ import annotations

import torch

from diffloc.checks import check_shape
from diffloc.maps.nerf.field import RadianceField
from diffloc.maps.nerf.losses import photometric_loss
from diffloc.maps.nerf.renderer import render_rays
from diffloc.maps.nerf.sampler import DensityGrid

__all__ = ["fit_appearance_code"]


def fit_appearance_code(
    field: RadianceField,
    grid: DensityGrid,
    origins: torch.Tensor,
    directions: torch.Tensor,
    rgb: torch.Tensor,
    steps: int,
    batch: int,
    lr: float,
    seed: int = 0,
) -> torch.Tensor:
    """Fit one appearance code to pixels with the field frozen.

    Args:
        field: the trained field.
        grid: its density grid.
        origins: (P, 3) rays of the pixels the code may see.
        directions: (P, 3) unit directions.
        rgb: (P, 3) their colours.
        steps: Adam steps.
        batch: rays per step.
        lr: Adam learning rate.
        seed: seed of the ray batches and sample jitter.

    Returns:
        (A,) the code, starting from the mean of the training codes.
    """
    check_shape(rgb, "P,3", "rgb")
    g = torch.Generator().manual_seed(seed)
    code = field.appearance.weight.detach().mean(dim=0).clone().requires_grad_(True)
    optimiser = torch.optim.Adam([code], lr=lr)
    for _ in range(steps):
        pick = torch.randint(len(rgb), (min(batch, len(rgb)),), generator=g)
        out = render_rays(
            field, grid, origins[pick], directions[pick], g, code.expand(len(pick), -1)
        )
        loss = photometric_loss(out.rgb, rgb[pick])
        (grad,) = torch.autograd.grad(loss, code)
        optimiser.zero_grad()
        code.grad = grad
        optimiser.step()
    return code.detach()
