"""Robust kernels: values, IRLS weights = rho', smoothness, config validation."""

from __future__ import annotations

import pytest
import torch

from diffloc.optim.robust import RobustKernel, cauchy, huber, make_robust_kernel, trivial
from diffloc.testing import assert_close, gradcheck

F64 = torch.float64


def test_known_values() -> None:
    s = torch.tensor([0.0, 1.0, 4.0, 9.0], dtype=F64)
    rho, weight = huber(s, 2.0)
    assert_close(rho, torch.tensor([0.0, 1.0, 4.0, 8.0], dtype=F64))
    assert_close(weight, torch.tensor([1.0, 1.0, 1.0, 2.0 / 3.0], dtype=F64))
    rho, weight = cauchy(s, 1.0)
    assert_close(rho, torch.log1p(s))
    assert_close(weight, 1.0 / (1.0 + s))
    rho, weight = trivial(s)
    assert_close(rho, s)
    assert_close(weight, torch.ones_like(s))


@pytest.mark.parametrize("name", ["trivial", "huber", "cauchy"])
def test_weight_is_derivative_of_rho(name: str) -> None:
    kernel = make_robust_kernel(RobustKernel(name, 1.5))
    s = torch.linspace(0.0, 20.0, 41, dtype=F64).requires_grad_(True)
    rho, weight = kernel(s)
    (drho,) = torch.autograd.grad(rho.sum(), s)
    assert_close(drho, weight.detach())
    assert gradcheck(lambda x: kernel(x)[0], [torch.tensor([0.0, 0.3, 2.0, 7.0])])


def test_huber_is_continuous_at_threshold() -> None:
    delta = 1.7
    s = torch.tensor([delta**2 * (1 - 1e-12), delta**2 * (1 + 1e-12)], dtype=F64)
    rho, weight = huber(s, delta)
    assert abs(float(rho[1] - rho[0])) < 1e-9
    assert abs(float(weight[1] - weight[0])) < 1e-9


def test_kernels_down_weight_large_residuals() -> None:
    s = torch.tensor([100.0], dtype=F64)
    w_huber = huber(s, 1.0)[1]
    w_cauchy = cauchy(s, 1.0)[1]
    assert float(w_cauchy) < float(w_huber) < 1.0


@pytest.mark.parametrize(
    ("name", "scale"), [("tukey", 1.0), ("huber", 0.0), ("huber", -1.0), ("cauchy", float("nan"))]
)
def test_bad_config_raises(name: str, scale: float) -> None:
    with pytest.raises(ValueError, match="kernel"):
        RobustKernel(name, scale)
