"""Known answers of the dominant-plane share (diffloc.geometry.plane_share)."""

from __future__ import annotations

import math

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.geometry.plane_share import dominant_plane_share
from diffloc.geometry.se3 import so3_exp


def _plane_points(n: int, seed: int) -> torch.Tensor:
    """(n, 3) points on a tilted wall about 5 m in front of a camera."""
    g = torch.Generator().manual_seed(seed)
    u, v = torch.rand(n, generator=g) * 4 - 2, torch.rand(n, generator=g) * 3 - 1.5
    return torch.stack([u, v, 5.0 + 0.5 * u], dim=1).double()


def test_points_on_one_plane_have_share_one_in_any_pose():
    wall = _plane_points(200, 0)
    R = so3_exp(torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64))
    assert dominant_plane_share(wall) == 1.0
    assert dominant_plane_share(wall @ R.T + torch.tensor([0.5, 0.0, 1.0])) == 1.0


@pytest.mark.parametrize("on_wall", [10, 50, 90])
def test_share_of_a_wall_and_scattered_points(on_wall: int):
    g = torch.Generator().manual_seed(1)
    scattered = torch.rand(100 - on_wall, 3, generator=g, dtype=torch.float64) * 2 + 1.0
    points = torch.cat([_plane_points(on_wall, 2), scattered])
    share = dominant_plane_share(points)
    if on_wall >= 50:  # the wall is found; a few scattered points may lie near it
        assert on_wall / 100 <= share <= on_wall / 100 + 0.05
    else:  # some plane through three scattered points still holds more than three
        assert 0.03 <= share <= 0.5


def test_tolerance_grows_with_depth():
    wall = _plane_points(100, 3)
    noisy = wall + torch.randn(100, 3, generator=torch.Generator().manual_seed(4)) * 0.04
    noisy = noisy.double()
    # 4 cm noise at 5 m: within 2 % of the depth (10 cm), not within 1 cm
    assert dominant_plane_share(noisy) >= 0.9
    assert dominant_plane_share(noisy, tolerance_m=0.01, relative_tolerance=0.0) < 0.5


def test_same_points_same_share():
    g = torch.Generator().manual_seed(5)
    points = torch.rand(300, 3, generator=g, dtype=torch.float64) * 5
    assert dominant_plane_share(points) == dominant_plane_share(points.clone())


def test_degenerate_inputs():
    assert dominant_plane_share(torch.zeros(0, 3)) == 1.0
    assert dominant_plane_share(torch.rand(3, 3)) == 1.0
    line = torch.stack([torch.arange(10.0), torch.zeros(10), torch.full((10,), 4.0)], dim=1)
    assert dominant_plane_share(line) == 1.0  # every plane through the line holds it


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"points": torch.zeros(5, 2)}, ShapeError, "points"),
        ({"tolerance_m": -0.1}, ValueError, "tolerance"),
        ({"relative_tolerance": -1.0}, ValueError, "tolerance"),
        ({"hypotheses": 0}, ValueError, "hypotheses"),
    ],
)
def test_bad_input_is_a_clear_error(kwargs, error, match):
    args = {"points": torch.rand(10, 3), **kwargs}
    with pytest.raises(error, match=match):
        dominant_plane_share(**args)


def test_share_is_a_fraction_of_the_points():
    g = torch.Generator().manual_seed(6)
    share = dominant_plane_share(torch.rand(37, 3, generator=g) * 3)
    assert math.isclose(share * 37, round(share * 37))
