"""Render-and-compare pose refinement (diffloc.optim.render_refine)."""

from __future__ import annotations

import math

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.features.local import Features, LocalFeatureExtractor, XFeatConfig, XFeatExtractor
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import invert, se3_exp, se3_log
from diffloc.maps.nerf.field import FieldConfig, RadianceField
from diffloc.maps.nerf.rays import camera_rays
from diffloc.maps.nerf.renderer import render_rays
from diffloc.maps.nerf.sampler import DensityGrid, SamplerConfig
from diffloc.optim.render_refine import (
    MatchCheckConfig,
    RenderRefineConfig,
    compared_residuals,
    crop_to_view,
    fit_query_appearance,
    match_alignment_check,
    point_cloud_map,
    radiance_field_map,
    refine_pose_by_rendering,
)
from diffloc.optim.render_refine.linearization import DifferentiableMap
from diffloc.render.soft_splat import SoftRender, soft_render_points

CAMERA = PinholeCamera.from_fov(48, 36, 1.2)
# A generic pose (not fronto-parallel to the wall: there the depth order of coplanar splats is
# a tie that any rotation breaks).
T_TRUE = se3_exp(torch.tensor([[0.1, 0.0, 0.2, 0.05, 0.25, 0.02]], dtype=torch.float64))


SHORT = RenderRefineConfig(levels=(1.0,), iterations=5)
"""One level, few iterations: enough for the tests of the acceptance rule."""


def wall_and_floor(spacing: float = 0.05) -> tuple[torch.Tensor, torch.Tensor]:
    """A textured wall 3 m ahead and a floor strip 1 m below the camera (float64)."""
    g = torch.arange(-3.5, 3.5, spacing, dtype=torch.float64)
    a, b = (t.flatten() for t in torch.meshgrid(g, g, indexing="ij"))
    wall = torch.stack((a, b, torch.full_like(a, 3.0)), 1)
    strip = (b + 3.5 > 1.2) & (b + 3.5 < 3.0)
    floor = torch.stack((a, torch.full_like(a, 1.0), b + 3.5), 1)[strip]
    p = torch.cat((wall, floor))
    colors = 0.5 + 0.2 * torch.sin(4 * p + 2 * p[:, [1, 2, 0]])
    return p, (colors + 0.15 * torch.cos(9 * p[:, [2, 0, 1]] - 5 * p)).clamp(0, 1)


def perturbation(metres: float, degrees: float) -> torch.Tensor:
    """(1, 6) a fixed right perturbation of the given translation and rotation sizes."""
    v = torch.tensor([[0.03, -0.03, 0.03]], dtype=torch.float64)
    w = torch.tensor([[0.02, -0.02, 0.015]], dtype=torch.float64)
    return torch.cat((v * metres / v.norm(), w * math.radians(degrees) / w.norm()), 1)


def errors(T: torch.Tensor, T_ref: torch.Tensor) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of ``T_ref^-1 T`` (1, 4, 4)."""
    xi = se3_log(invert(T_ref) @ T)[0]
    return float(xi[:3].norm()), math.degrees(float(xi[3:].norm()))


def colour_of(render) -> torch.Tensor:
    return render.rgb / render.alpha.clamp_min(1e-3)


@pytest.fixture(scope="module")
def cloud():
    points, colors = wall_and_floor()
    return point_cloud_map(points, colors, 0.04)


def test_point_cloud_refinement_converges_back_to_the_true_pose(cloud) -> None:
    # The query sees the map under another exposure: a gain and a bias.
    query = 0.8 * colour_of(cloud.render(T_TRUE, CAMERA)) + 0.05
    T_start = T_TRUE @ se3_exp(perturbation(0.05, 2.0))
    result = refine_pose_by_rendering(cloud, query, T_start, CAMERA)
    assert bool(result.accepted[0])
    t_err, r_err = errors(result.T_wc, T_TRUE)
    assert t_err < 0.01
    assert r_err < 0.2


def tiny_field() -> tuple[RadianceField, DensityGrid]:
    """A random tri-plane field (float64) with random appearance codes: textured density and
    colour at known weights, so its own renders are exact queries."""
    torch.manual_seed(0)
    cfg = FieldConfig(
        triplane_resolutions=[8, 16],
        triplane_channels=4,
        hidden=16,
        appearance_dim=4,
        init_std=1.0,
    )
    field = RadianceField(cfg, -2 * torch.ones(3), 2 * torch.ones(3), 3).double()
    with torch.no_grad():
        field.appearance.weight.normal_(0, 1.0)
    sampler = SamplerConfig(
        grid_resolution=8, coarse_samples=32, importance_samples=8, uniform_samples=8
    )
    grid = DensityGrid(sampler).double()
    grid.refresh(field.density, field.normalise, torch.Generator().manual_seed(0))
    return field, grid


FIELD_CAMERA = PinholeCamera.from_fov(32, 24, 1.0)
FIELD_POSE = torch.eye(4, dtype=torch.float64)[None]
FIELD_POSE[0, 2, 3] = -3.0


def test_radiance_field_refinement_converges_back_to_the_true_pose() -> None:
    field, grid = tiny_field()
    model = radiance_field_map(field, grid, field.appearance.weight[1].detach())
    query = colour_of(model.render(FIELD_POSE, FIELD_CAMERA))
    T_start = FIELD_POSE @ se3_exp(perturbation(0.05, 2.0))
    config = RenderRefineConfig(levels=(1.0,), min_alpha=0.3)
    result = refine_pose_by_rendering(model, query, T_start, FIELD_CAMERA, config=config)
    assert bool(result.accepted[0])
    t_err, r_err = errors(result.T_wc, FIELD_POSE)
    assert t_err < 0.01
    assert r_err < 0.2


def test_radiance_field_tangents_are_the_autograd_jacobian_of_the_render() -> None:
    field, grid = tiny_field()
    code = field.appearance.weight[2].detach()
    camera = PinholeCamera.from_fov(6, 4, 1.0)
    uv = camera.pixel_grid(torch.float64).reshape(-1, 2)

    def rays(delta: torch.Tensor) -> torch.Tensor:  # (P, 5) rgb, depth, opacity
        pose = (FIELD_POSE @ se3_exp(delta[None]))[0]
        o, d, z = camera_rays(camera.to(torch.float64), pose, uv)
        out = render_rays(field, grid, o, d, None, code.expand(len(uv), -1))
        return torch.cat((out.rgb, (out.range * z)[:, None], out.opacity[:, None]), 1)

    jac = torch.autograd.functional.jacobian(rays, torch.zeros(6, dtype=torch.float64))
    _, tangents = radiance_field_map(field, grid, code).linearize(FIELD_POSE, camera)
    stacked = torch.cat((tangents.rgb, tangents.depth, tangents.alpha), 2)[:, 0]
    expected = jac.permute(2, 1, 0).reshape(6, 5, camera.height, camera.width)
    assert float(expected.abs().max()) > 0.1
    torch.testing.assert_close(stacked, expected, rtol=1e-9, atol=1e-9)


def test_the_fitted_appearance_code_explains_the_query_better_than_the_mean_code() -> None:
    field, grid = tiny_field()
    truth = radiance_field_map(field, grid, field.appearance.weight[1].detach())
    # The field is fitted to (and renders) colour composited over black.
    query = truth.render(FIELD_POSE, FIELD_CAMERA).rgb
    code = fit_query_appearance(field, grid, query, FIELD_POSE, FIELD_CAMERA, steps=40)
    mean = field.appearance.weight.detach().mean(0)

    def error(c: torch.Tensor) -> float:
        render = radiance_field_map(field, grid, c).render(FIELD_POSE, FIELD_CAMERA)
        return float((render.rgb - query).abs().mean())

    assert error(code[0]) < 0.5 * error(mean)


def test_photometric_residual_gradcheck_float64() -> None:
    g = torch.linspace(-0.6, 0.6, 7, dtype=torch.float64)
    a, b = (t.flatten() for t in torch.meshgrid(g, g, indexing="ij"))
    points = torch.stack((a, b, 2.0 + 0.3 * a), 1)
    colors = torch.stack((0.5 + 0.4 * torch.sin(5 * a), 0.5 + 0.3 * b, 0.4 + 0.2 * a * b), 1)
    camera = PinholeCamera.from_fov(12, 10, 1.0)
    T = se3_exp(torch.tensor([[0.01, -0.02, 0.0, 0.02, 0.01, -0.01]], dtype=torch.float64))
    query = 0.5 + 0.3 * torch.rand(
        1, 3, 10, 12, dtype=torch.float64, generator=torch.Generator().manual_seed(1)
    )
    config = RenderRefineConfig()

    def residuals(delta: torch.Tensor) -> torch.Tensor:
        out = soft_render_points(points, colors, 0.08, T @ se3_exp(delta), camera, min_sigma_px=0.8)
        return compared_residuals(out, query, mask, config)

    with torch.no_grad():
        mask = soft_render_points(points, colors, 0.08, T, camera, min_sigma_px=0.8).alpha > 0.5
    assert int(mask.sum()) > 20
    delta = torch.zeros(1, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(residuals, (delta,), check_forward_ad=True)


CHECK_CAMERA = PinholeCamera.from_fov(192, 144, 1.2)
"""The match check's camera: CAMERA's field of view at four times its size."""


def test_the_match_check_refuses_a_move_the_held_out_evidence_does_not_confirm(cloud) -> None:
    # Two copies of one refinement: the fitted 48x36 query is the render at T_TRUE, so the
    # fitted cost falls to ~0 as the pose returns there. The check's 192x144 evidence is the
    # render at T_TRUE for the first copy (it confirms the move) and at the start for the
    # second (it says the start was right: the move must be refused though the cost fell).
    query = colour_of(cloud.render(T_TRUE, CAMERA)).expand(2, -1, -1, -1)
    T_start = (T_TRUE @ se3_exp(perturbation(0.05, 2.0))).expand(2, -1, -1)
    evidence = colour_of(cloud.render(torch.cat((T_TRUE, T_start[:1])), CHECK_CAMERA))
    verify = match_alignment_check(
        cloud,
        evidence.clamp(0, 1),
        CHECK_CAMERA,
        XFeatExtractor(XFeatConfig(max_keypoints=1024)),
        MatchCheckConfig(width=CHECK_CAMERA.width),
    )
    config = RenderRefineConfig(levels=(0.5, 1.0), iterations=10)
    result = refine_pose_by_rendering(cloud, query, T_start, CAMERA, config=config, verify=verify)
    assert bool((result.cost_after < 0.5 * result.cost_before).all())
    assert errors(result.T_refined[:1], T_TRUE)[0] < 0.01
    aligned_before, aligned_after = result.evidence.inliers_before, result.evidence.inliers_after
    assert int(aligned_after[0]) > 2 * int(aligned_before[0])  # confirmed
    assert int(aligned_after[1]) < int(aligned_before[1])  # contradicted
    assert result.evidence.passed.tolist() == [True, False]
    assert result.accepted.tolist() == [True, False]
    assert torch.equal(result.T_wc[0], result.T_refined[0])
    assert torch.equal(result.T_wc[1], T_start[1])


class ScriptedFeatures(LocalFeatureExtractor):
    """Returns the query's features first, then one scripted render's features per call."""

    def __init__(self, keypoints: list[torch.Tensor]) -> None:
        self.keypoints = keypoints

    def _extract_batch(self, images: torch.Tensor) -> list[Features]:
        uv = self.keypoints.pop(0)
        n = len(uv)
        return [Features(uv, torch.ones(n), torch.eye(n), torch.ones(n))]


def scripted_check(aligned_before: int, aligned_after: int, matches: int) -> bool:
    """Whether the match check passes when ``aligned_*`` of ``matches`` matches lie 0.5 px
    from their query keypoint at the initial / refined pose and the rest 9 px."""
    query = torch.stack((torch.arange(matches) * 20.0, torch.full((matches,), 50.0)), 1)

    def render_keypoints(aligned: int) -> torch.Tensor:
        shift = torch.where(torch.arange(matches) < aligned, 0.5, 9.0)
        return query + torch.stack((shift, torch.zeros(matches)), 1)

    camera = PinholeCamera.from_fov(64, 48, 1.0)
    flat = SoftRender(
        torch.full((1, 3, 48, 64), 0.5), torch.ones(1, 1, 48, 64), torch.ones(1, 1, 48, 64)
    )
    model = DifferentiableMap(lambda T, cam: flat, lambda T, cam: (flat, flat))
    extractor = ScriptedFeatures(
        [query, render_keypoints(aligned_before), render_keypoints(aligned_after)]
    )
    image = torch.zeros(1, 3, 48, 64)
    config = MatchCheckConfig(
        width=64, inlier_px=2.0, min_inliers=20, min_fraction=0.25, min_gain=1.5
    )
    verify = match_alignment_check(model, image, camera, extractor, config)
    evidence = verify(torch.eye(4)[None], torch.eye(4)[None])
    assert evidence.inliers_before.tolist() == [aligned_before]
    assert evidence.inliers_after.tolist() == [aligned_after]
    return bool(evidence.passed[0])


@pytest.mark.parametrize(
    ("before", "after", "matches", "passes"),
    [
        (10, 60, 100, True),  # 60 aligned, 60 %, 6x the start's
        (10, 19, 30, False),  # fewer than 20 aligned
        (10, 24, 100, False),  # 24 % of the matches aligned
        (40, 59, 100, False),  # less than 1.5x the start's
        (40, 60, 100, True),  # exactly 1.5x
    ],
)
def test_each_part_of_the_match_rule_refuses_on_its_own(
    before: int, after: int, matches: int, passes: bool
) -> None:
    assert scripted_check(before, after, matches) is passes


def test_a_start_at_the_true_pose_is_not_made_worse(cloud) -> None:
    query = colour_of(cloud.render(T_TRUE, CAMERA))
    result = refine_pose_by_rendering(cloud, query, T_TRUE, CAMERA, config=SHORT)
    t_err, r_err = errors(result.T_wc, T_TRUE)
    assert t_err < 1e-6
    assert r_err < 1e-4


def test_an_unrelated_query_leaves_the_pose_unchanged(cloud) -> None:
    noise = torch.rand(
        1, 3, CAMERA.height, CAMERA.width, generator=torch.Generator().manual_seed(0)
    )
    query = 0.3 + 0.4 * noise.double()
    T_start = T_TRUE @ se3_exp(perturbation(0.05, 2.0))
    result = refine_pose_by_rendering(cloud, query, T_start, CAMERA, config=SHORT)
    assert not bool(result.accepted[0])
    assert float(result.correlation[0]) < RenderRefineConfig().min_correlation
    assert torch.equal(result.T_wc, T_start)


def test_a_pose_that_sees_no_map_is_left_alone(cloud) -> None:
    T_away = T_TRUE.clone()
    T_away[0, :3, :3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))
    query = torch.full((1, 3, CAMERA.height, CAMERA.width), 0.5, dtype=torch.float64)
    result = refine_pose_by_rendering(cloud, query, T_away, CAMERA)
    assert not bool(result.accepted[0])
    assert math.isinf(float(result.cost_before[0]))
    assert torch.equal(result.T_wc, T_away)


def test_crop_keeps_the_points_in_view_and_in_range() -> None:
    points = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, -2.0], [0.0, 0.0, 50.0], [30.0, 0, 1]])
    kept = crop_to_view(points, torch.eye(4)[None], CAMERA, max_depth_m=20.0)
    assert kept.tolist() == [0]


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"levels": ()}, "levels"),
        ({"levels": (0.5, 2.0)}, "levels"),
        ({"iterations": 0}, "iterations"),
        ({"step_expansions": -1}, "step_expansions"),
        ({"photometric_sigma": 0.0}, "photometric_sigma"),
        ({"kernel_scale": float("nan")}, "kernel_scale"),
        ({"min_alpha": 1.0}, "min_alpha"),
        ({"depth_weight": -1.0}, "depth_weight"),
        ({"min_pixels": 0}, "min_pixels"),
        ({"min_improvement": 1.0}, "min_improvement"),
        ({"min_correlation": 2.0}, "min_correlation"),
    ],
)
def test_bad_settings_are_clear_errors(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        RenderRefineConfig(**kwargs)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"width": 16}, "width"),
        ({"inlier_px": 0.0}, "inlier_px"),
        ({"min_inliers": -1}, "min_inliers"),
        ({"min_fraction": 1.5}, "min_fraction"),
        ({"min_gain": float("nan")}, "min_gain"),
    ],
)
def test_bad_match_check_settings_are_clear_errors(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        MatchCheckConfig(**kwargs)


def test_an_image_of_the_wrong_shape_is_a_clear_error() -> None:
    points, colors = wall_and_floor(0.3)
    model = point_cloud_map(points, colors, 0.1)
    image = torch.zeros(1, 3, CAMERA.height, CAMERA.width - 1, dtype=torch.float64)
    with pytest.raises(ShapeError, match=r"image .*camera's size.*got \(1, 3, 36, 47\)"):
        refine_pose_by_rendering(model, image, T_TRUE, CAMERA)


def test_a_nan_pose_is_a_clear_error() -> None:
    points, colors = wall_and_floor(0.3)
    model = point_cloud_map(points, colors, 0.1)
    image = torch.zeros(1, 3, CAMERA.height, CAMERA.width, dtype=torch.float64)
    with pytest.raises(ValueError, match="T_wc contains NaN"):
        refine_pose_by_rendering(model, image, T_TRUE * float("nan"), CAMERA)


def test_a_depth_of_the_wrong_shape_is_a_clear_error() -> None:
    points, colors = wall_and_floor(0.3)
    model = point_cloud_map(points, colors, 0.1)
    image = torch.zeros(1, 3, CAMERA.height, CAMERA.width, dtype=torch.float64)
    with pytest.raises(ShapeError, match="depth"):
        refine_pose_by_rendering(model, image, T_TRUE, CAMERA, depth=image)
