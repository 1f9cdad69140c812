"""diffloc.eval.field_regions: labels of a synthetic street view (ground, a near wall, a far
wall, sky) and the pooled per-region errors."""

from __future__ import annotations

import math

import pytest
import torch

from diffloc.eval.field_regions import REGIONS, pixel_regions, region_summary
from diffloc.geometry.camera import PinholeCamera

# camera x right, y down, z forward -> world x forward, y left, z up; 1.5 m above the ground
T_WC = torch.eye(4)
T_WC[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
T_WC[2, 3] = 1.5


def street_depth(camera: PinholeCamera) -> torch.Tensor:
    """(1, H, W) z-depth: ground 1.5 m below a level camera (lower half), nothing above it
    (sky), a wall 5 m ahead in columns 0-4 and one 40 m ahead in the last 5 columns."""
    uv = camera.pixel_grid(torch.float32)
    ray_y = (uv[..., 1] - camera.cy) / camera.fy
    depth = torch.where(ray_y > 0, 1.5 / ray_y.clamp_min(1e-6), torch.zeros_like(ray_y))
    depth[:, :5] = 5.0
    depth[:, -5:] = 40.0
    return depth[None]


def test_street_pixels_get_their_regions() -> None:
    camera = PinholeCamera.from_fov(20, 16, 1.2)
    labels = pixel_regions(street_depth(camera), camera, T_WC, far_m=15.0)
    name = {i: r for i, r in enumerate(REGIONS)}
    assert name[int(labels[2, 10])] == "sky"
    assert name[int(labels[13, 10])] == "ground"
    assert name[int(labels[8, 2])] == "facade"
    assert name[int(labels[8, 17])] == "far"
    assert name[int(labels[2, 17])] == "far"  # far wins over the normal
    assert name[int(labels[15, 2])] == "ground"  # the foot of the near wall
    # a level camera: the ground is the lower half between the walls, up to the far mark
    assert (labels[9:, 5:-5] == REGIONS.index("ground")).all()
    assert (labels[8, 5:-5] == REGIONS.index("far")).all()  # 44 m of ground
    assert (labels[:8, 5:-5] == REGIONS.index("sky")).all()


def test_a_raised_camera_sees_the_same_plane_as_not_ground() -> None:
    camera = PinholeCamera.from_fov(20, 16, 1.2)
    depth = street_depth(camera)
    raised = T_WC.clone()
    raised[2, 3] = 3.0  # the same depth image seen from 3 m: the plane is 1.5 m up
    assert int(pixel_regions(depth, camera, T_WC, far_m=15.0)[13, 10]) == REGIONS.index("ground")
    labels = pixel_regions(depth, camera, raised, far_m=15.0)
    assert int(labels[13, 10]) == REGIONS.index("facade")
    assert int(labels[13, 2]) == REGIONS.index("facade")


def test_region_summary_pools_errors() -> None:
    squared = torch.tensor([0.01, 0.01, 0.001, 0.0, 0.02])
    labels = torch.tensor([0, 0, 1, 1, 3])
    out = region_summary(squared, labels)
    assert out["sky"]["psnr_db"] == pytest.approx(20.0, abs=1e-5)
    assert out["ground"]["psnr_db"] == pytest.approx(-10 * math.log10(0.0005), abs=1e-5)
    assert out["facade"] == {"pixels": 0, "pixel_share": 0.0, "error_share": 0.0, "psnr_db": None}
    assert out["far"]["pixel_share"] == pytest.approx(0.2)
    assert sum(r["error_share"] for r in out.values()) == pytest.approx(1.0)
    assert out["far"]["error_share"] == pytest.approx(0.02 / 0.041, rel=1e-5)


def test_bad_input_is_refused() -> None:
    camera = PinholeCamera.from_fov(20, 16, 1.2)
    depth = street_depth(camera)
    with pytest.raises(ValueError, match="far_m"):
        pixel_regions(depth, camera, T_WC, far_m=0.0)
    with pytest.raises(ValueError, match="far_m"):
        pixel_regions(depth, camera, T_WC, far_m=float("nan"))
    with pytest.raises(ValueError):
        pixel_regions(depth, camera, T_WC[:3], far_m=15.0)
    with pytest.raises(ValueError):
        pixel_regions(depth[:, :-1], camera, T_WC, far_m=15.0)
    with pytest.raises(ValueError):
        region_summary(torch.zeros(3), torch.zeros(4, dtype=torch.int64))
