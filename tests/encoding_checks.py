"""Shared checks of the NeRF encodings for tests: sample points and the fast path against
its reference implementation."""

from __future__ import annotations

import torch

from diffloc.testing import assert_close


def encoding_points(n: int, seed: int = 0) -> torch.Tensor:
    """(n, 3) points in [-1.1, 1.1]^3: inside the unit cube and a little beyond it."""
    return torch.rand(n, 3, generator=torch.Generator().manual_seed(seed)) * 2.2 - 1.1


def assert_matches_reference(encoding: torch.nn.Module, x: torch.Tensor) -> None:
    """The encoding's fast forward equals ``forward_reference`` at ``x`` (N, 3), and so do
    the gradients of a random weighting of the features for ``x`` and every parameter."""
    fast, ref = encoding(x), encoding.forward_reference(x)
    assert_close(fast, ref)
    w = torch.randn_like(fast)
    g_fast = torch.autograd.grad((fast * w).sum(), [x, *encoding.parameters()])
    g_ref = torch.autograd.grad((ref * w).sum(), [x, *encoding.parameters()])
    for a, b in zip(g_fast, g_ref, strict=True):
        assert_close(a, b)
