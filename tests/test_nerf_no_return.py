"""Lidar rays without a return (the spinning lidar's grid minus its returns) and the
empty-space loss on them."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from diffloc.geometry.camera import PinholeCamera
from diffloc.io.calib import Calibration
from diffloc.io.dataset import SequenceWriter, read_sequence, read_sequence_dir
from diffloc.maps.nerf.data import SubmapDataConfig, build_submap_rays
from diffloc.maps.nerf.field import FieldConfig, RadianceField
from diffloc.maps.nerf.losses import empty_space_loss
from diffloc.maps.nerf.module import NerfDataModule, NerfLossConfig, NerfTrainConfig
from diffloc.maps.nerf.no_return import (
    LidarPattern,
    NoReturnRays,
    no_return_mask,
    no_return_rays,
)
from diffloc.maps.nerf.renderer import render_rays
from diffloc.maps.nerf.sampler import DensityGrid, SamplerConfig
from diffloc.maps.nerf.train import fit_submap
from diffloc.render.raycast import MeshRaycaster
from diffloc.sim.lidar import SpinningLidarConfig, simulate_sweep, spinning_lidar_directions
from diffloc.sim.primitives import MeshBuilder
from diffloc.testing import gradcheck

LIDAR = SpinningLidarConfig(beams=4, vfov_min_deg=-15.0, vfov_max_deg=15.0, azimuth_steps=16)
PATTERN = LidarPattern(4, -15.0, 15.0, 16, LIDAR.max_range_m)


def test_the_pattern_is_the_simulated_lidars_grid() -> None:
    # simulator ray a * beams + b is beam b at azimuth step a
    sim = spinning_lidar_directions(LIDAR).reshape(16, 4, 3).transpose(1, 0, 2)
    np.testing.assert_allclose(PATTERN.directions(), sim, atol=1e-12)


def test_known_returns_leave_exactly_the_other_cells_empty() -> None:
    rng = np.random.default_rng(0)
    hit = rng.random((4, 16)) < 0.6
    ranges = rng.uniform(0.5, 29.0, int(hit.sum()))
    points = PATTERN.directions()[hit] * ranges[:, None]
    points = points[rng.permutation(len(points))].astype(np.float32)  # any order, float32
    np.testing.assert_array_equal(no_return_mask(points, PATTERN, "sweep"), ~hit)
    assert no_return_mask(np.zeros((0, 3)), PATTERN, "sweep").all()


def test_a_simulated_sweep_over_a_floor_has_no_return_above_the_horizon() -> None:
    builder = MeshBuilder(["concrete"])
    builder.add_box([-60, -60, -3], [60, 60, -2], "concrete", object_id=0)  # floor 2 m below
    mesh = builder.build([np.full((4, 4, 3), 0.5, dtype=np.float32)])
    points = simulate_sweep(MeshRaycaster(mesh), np.eye(4), LIDAR, np.random.default_rng(0))
    empty = no_return_mask(points, PATTERN, "sweep")
    # beams at -15 and -5 deg hit the floor (7.5 m and 23 m away), those at +5 and +15 miss
    np.testing.assert_array_equal(empty, np.repeat([[False], [False], [True], [True]], 16, 1))


def test_returns_off_the_recorded_grid_are_refused() -> None:
    points = 10.0 * PATTERN.directions().reshape(-1, 3)
    wrong_beams = dataclasses.replace(PATTERN, beams=3)  # -15, 0, 15 deg: -5 and 5 are off
    with pytest.raises(ValueError, match="off the recorded lidar grid"):
        no_return_mask(points, wrong_beams, "sweep 3")
    wrong_steps = dataclasses.replace(PATTERN, azimuth_steps=10)
    with pytest.raises(ValueError, match="off the recorded lidar grid"):
        no_return_mask(points, wrong_steps, "sweep 3")


def test_an_unknown_pattern_is_refused() -> None:
    with pytest.raises(ValueError, match="records no lidar pattern"):
        LidarPattern.from_calibration(None, "sequence 'x'")
    with pytest.raises(ValueError, match=r"lacks \['azimuth_steps'\]"):
        LidarPattern.from_calibration(
            {"beams": 4, "vfov_min_deg": -15, "vfov_max_deg": 15, "max_range_m": 30}, "x"
        )


def _sequence(tmp_path: Path, lidar: dict | None):
    camera = PinholeCamera(fx=8.0, fy=8.0, cx=3.5, cy=2.5, width=8, height=6)
    T_wl = torch.eye(4, dtype=torch.float64)
    T_wl[:3, :3] = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # 90 deg about z
    T_wl[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    hit = np.ones((4, 16), dtype=bool)
    hit[3, 0] = hit[2, 4] = False
    points = 5.0 * PATTERN.directions()[hit]
    with SequenceWriter(tmp_path / "mapping", Calibration(camera, lidar=lidar)) as writer:
        for i in range(2):
            writer.add_frame(float(i), torch.eye(4), torch.zeros(3, 6, 8))
        writer.add_sweep(0.0, T_wl, points)
    return read_sequence_dir(tmp_path / "mapping"), T_wl.numpy()


def test_no_return_rays_are_the_empty_cells_in_the_world_frame(tmp_path: Path) -> None:
    lidar = dataclasses.asdict(LIDAR)
    seq, T_wl = _sequence(tmp_path, lidar)
    rays = no_return_rays(seq, [0])
    expected = PATTERN.directions()[[2, 3], [4, 0]] @ T_wl[:3, :3].T
    np.testing.assert_allclose(rays.directions.numpy(), expected, atol=1e-6)
    np.testing.assert_allclose(rays.origins.numpy(), np.tile([1.0, 2.0, 3.0], (2, 1)))
    built = build_submap_rays(seq, [0, 1], SubmapDataConfig(holdout_every=0), no_return=True)
    assert len(built.no_return) == 2
    assert build_submap_rays(seq, [0, 1], SubmapDataConfig(holdout_every=0)).no_return is None


def test_no_return_rays_need_the_pattern_in_the_calibration(tmp_path: Path) -> None:
    seq, _ = _sequence(tmp_path, None)
    with pytest.raises(ValueError, match="records no lidar pattern"):
        build_submap_rays(seq, [0, 1], SubmapDataConfig(holdout_every=0), no_return=True)
    rays = build_submap_rays(seq, [0, 1], SubmapDataConfig(holdout_every=0))
    config = NerfTrainConfig(loss=NerfLossConfig(empty_weight=0.1))
    with pytest.raises(ValueError, match="were not built"):
        NerfDataModule(rays, config)
    with pytest.raises(ValueError, match="empty_weight"):
        NerfLossConfig(empty_weight=-0.1)


def test_empty_space_loss_values_and_gradcheck() -> None:
    density = torch.tensor([[0.0, 0.0], [1.0, 2.0]], dtype=torch.float64)
    deltas = torch.tensor([[1.0, 5.0], [0.5, 2.0]], dtype=torch.float64)
    expected = (0.0 + math.log1p(0.5 + 4.0)) / 2
    assert abs(float(empty_space_loss(density, deltas)) - expected) < 1e-12
    d = torch.rand(3, 5, dtype=torch.float64, requires_grad=True)
    gradcheck(empty_space_loss, [d, torch.rand(3, 5, dtype=torch.float64)])


def test_empty_space_loss_keeps_its_gradient_on_an_opaque_ray() -> None:
    density = torch.full((1, 4), 5.0, dtype=torch.float64, requires_grad=True)
    deltas = torch.ones(1, 4, dtype=torch.float64)  # optical depth 20, opacity 1 - 2e-9
    (grad,) = torch.autograd.grad(empty_space_loss(density, deltas), density)
    assert torch.allclose(grad, torch.full_like(grad, 1.0 / 21.0))


def test_the_loss_empties_a_fields_rays() -> None:
    torch.manual_seed(0)
    field = RadianceField(
        FieldConfig(triplane_resolutions=[8, 16], triplane_channels=4, hidden=16),
        -torch.ones(3),
        torch.ones(3),
        num_images=1,
    )
    grid = DensityGrid(SamplerConfig(skip_density=0.0, importance_samples=0, uniform_samples=16))
    origins = torch.zeros(32, 3)
    directions = torch.nn.functional.normalize(torch.randn(32, 3), dim=-1)
    optimiser = torch.optim.Adam(field.parameters(), lr=1e-2)

    def loss() -> torch.Tensor:
        out = render_rays(field, grid, origins, directions, torch.Generator().manual_seed(0))
        return empty_space_loss(out.density, out.deltas)

    with torch.no_grad():
        start = float(loss())
    for _ in range(30):
        optimiser.zero_grad()
        loss().backward()
        optimiser.step()
    with torch.no_grad():
        assert float(loss()) < 0.2 * start


def test_training_with_the_empty_space_loss_logs_it(tiny_indoor_dataset: Path, tmp_path) -> None:
    seq = read_sequence(tiny_indoor_dataset, "mapping")
    data = SubmapDataConfig(holdout_every=0, lidar_stride=8)
    rays = build_submap_rays(seq, list(range(len(seq))), data, no_return=True)
    if not len(rays.no_return):  # a closed room returns everywhere: rays through its roof
        up = torch.tensor([[0.0, 0.0, 1.0]]).expand(8, 3)
        rays.no_return = NoReturnRays(rays.lidar.origins[:8].clone(), up.clone())
    config = NerfTrainConfig(
        field=FieldConfig(triplane_resolutions=[16], triplane_channels=4, hidden=16),
        sampler=SamplerConfig(grid_resolution=16, coarse_samples=16, importance_samples=4),
        loss=NerfLossConfig(empty_weight=0.1),
        ray_batch=64,
        lidar_batch=32,
        normal_batch=8,
        empty_batch=16,
        steps_per_epoch=2,
    )
    module = fit_submap(rays, config, tmp_path, epochs=1, show_progress=False)
    metrics = (tmp_path / "logs" / "version_0" / "metrics.csv").read_text()
    assert len(module.losses) == 2 and "loss_empty" in metrics
