"""Eq. 3-4 texturing: view selection with occlusion, exposure estimation, the blend."""

import math

import numpy as np
import pytest
import torch

from diffloc.geometry.camera import PinholeCamera
from diffloc.io.textured_mesh import TexturedMesh
from diffloc.render.exposure import estimate_exposures
from diffloc.render.mesh_texturing import (
    TextureBlendConfig,
    blend_texels,
    select_texel_views,
    texture_texels,
    view_depths,
)
from diffloc.render.raycast import MeshRaycaster


def quad(x0: float, x1: float, y0: float, y1: float, z: float) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles spanning [x0, x1] x [y0, y1] at depth z, facing -z (the cameras)."""
    vertices = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float32)
    return vertices, np.array([[0, 2, 1], [0, 3, 2]], np.int32)


def scene_mesh() -> TexturedMesh:
    """A small occluder at z = 2 in front of a wide wall at z = 4."""
    front_v, front_f = quad(-0.5, 0.5, -0.5, 0.5, 2.0)
    back_v, back_f = quad(-6.0, 6.0, -6.0, 6.0, 4.0)
    faces = np.concatenate([front_f, back_f + 4])
    return TexturedMesh(
        vertices=np.concatenate([front_v, back_v]),
        triangles=faces,
        corner_uvs=np.zeros((4, 3, 2), np.float32),
        material_ids=np.zeros(4, np.int32),
        object_ids=np.zeros(4, np.int32),
        textures=[np.zeros((2, 2, 3), np.float32)],
        material_names=["atlas"],
    )


def pose_at(x: float) -> torch.Tensor:
    """Camera at (x, 0, 0) looking along +z (OpenCV frame = world frame)."""
    T = torch.eye(4, dtype=torch.float64)
    T[0, 3] = x
    return T


CAMERA = PinholeCamera.from_fov(64, 48, math.pi / 2)
CFG = TextureBlendConfig(views_per_texel=2)


def test_views_are_the_nearest_that_see_the_texel_unoccluded():
    caster = MeshRaycaster(scene_mesh())
    T_wc = torch.stack([pose_at(0.0), pose_at(3.0)])  # view 0 at x = 0, view 1 at x = 3
    depths = view_depths(caster, T_wc, CAMERA)
    points = torch.tensor([[0.0, 0.0, 4.0], [2.0, 0.0, 4.0], [0.0, 0.0, 2.0]])
    toward = torch.tensor([0.0, 0.0, -1.0]).expand(3, 3)
    views = select_texel_views(points, toward, depths, T_wc, CAMERA, CFG)
    # Behind the occluder for view 0: only view 1 sees it.
    assert views.view_ids[0].tolist() == [1, -1]
    # Seen by both; view 1 is nearer (sqrt(17) < sqrt(20)).
    assert views.view_ids[1].tolist() == [1, 0]
    torch.testing.assert_close(views.distance[1], torch.tensor([17**0.5, 20**0.5]))
    # The occluder's centre is outside view 1's field of view (90 degrees).
    assert views.view_ids[2].tolist() == [0, -1]


def test_back_facing_texels_get_no_view():
    caster = MeshRaycaster(scene_mesh())
    T_wc = torch.stack([pose_at(0.0), pose_at(3.0)])
    depths = view_depths(caster, T_wc, CAMERA)
    away = torch.tensor([[0.0, 0.0, 1.0]])
    views = select_texel_views(torch.tensor([[2.0, 0.0, 4.0]]), away, depths, T_wc, CAMERA, CFG)
    assert views.view_ids.tolist() == [[-1, -1]]


def test_texel_colours_come_from_the_projected_pixels():
    caster = MeshRaycaster(scene_mesh())
    T_wc = torch.stack([pose_at(0.0), pose_at(3.0)])
    u = torch.arange(CAMERA.width, dtype=torch.float32)
    ramp = (u / CAMERA.width).expand(CAMERA.height, -1)  # intensity = column / width
    images = torch.stack([ramp.expand(3, -1, -1)] * 2)
    point = torch.tensor([[2.0, 0.0, 4.0]])
    cfg = TextureBlendConfig(views_per_texel=1, gamma=1.0)
    texels = texture_texels(
        point, torch.tensor([[0.0, 0.0, -1.0]]), caster, images, T_wc, CAMERA, cfg, "none"
    )
    # View 1 (x = 3) sees x = 2 at u = cx + f * (-1 / 4).
    expected_u = float(CAMERA.cx) + float(CAMERA.fx) * (-1.0 / 4.0)
    torch.testing.assert_close(texels.colors[0], torch.full((3,), expected_u / CAMERA.width))
    assert texels.view_count.tolist() == [1]


def synthetic_observations(seed: int = 0, outliers: float = 0.05):
    """Points seen by 3 of 8 views with known exposures, 1 % noise and some outliers."""
    gen = torch.Generator().manual_seed(seed)
    views, count = 8, 3000
    exposures = torch.exp(torch.randn(views, generator=gen, dtype=torch.float64) * 0.4)
    radiance = torch.rand(count, generator=gen, dtype=torch.float64) * 0.3 + 0.05
    first = torch.randint(0, views - 2, (count,), generator=gen)
    view_ids = torch.stack([first, first + 1, first + 2], dim=1)
    noise = 1 + 0.01 * torch.randn(count, 3, generator=gen, dtype=torch.float64)
    intensity = exposures[view_ids] * radiance[:, None] * noise
    wrong = torch.rand(count, 3, generator=gen) < outliers
    intensity = torch.where(
        wrong, torch.rand(count, 3, generator=gen, dtype=torch.float64), intensity
    )
    return view_ids, intensity, exposures


def test_exposures_are_recovered_up_to_the_gauge():
    view_ids, intensity, exposures = synthetic_observations()
    estimate = estimate_exposures(view_ids, intensity, 8)
    truth = exposures / exposures.log().mean().exp()
    torch.testing.assert_close(estimate.exposures, truth, rtol=0.01, atol=0)
    assert float(estimate.exposures.log().mean()) == pytest.approx(0.0, abs=1e-9)
    assert bool(estimate.linked.all()) and estimate.pairs == 13  # (k, k+1) and (k, k+2)


def test_views_without_shared_samples_keep_exposure_one():
    view_ids, intensity, _ = synthetic_observations()
    estimate = estimate_exposures(view_ids, intensity, 10)  # views 8 and 9 never observed
    assert estimate.linked.tolist()[8:] == [False, False]
    assert estimate.exposures[8:].tolist() == [1.0, 1.0]


def test_exposure_view_ids_beyond_the_views_are_refused():
    view_ids, intensity, _ = synthetic_observations()
    with pytest.raises(ValueError, match="num_views"):
        estimate_exposures(view_ids, intensity, 4)


def test_blend_divides_each_view_by_its_exposure():
    gamma = 2.2
    radiance = torch.tensor([[0.1, 0.2, 0.3], [0.02, 0.5, 0.04]])
    exposures = torch.tensor([0.5, 1.0, 2.0])
    view_ids = torch.tensor([[0, 1, 2], [2, 0, -1]])
    linear = exposures[view_ids.clamp_min(0)][..., None] * radiance[:, None, :]
    samples = linear ** (1 / gamma)
    colors, count = blend_texels(samples, view_ids, exposures, gamma)
    torch.testing.assert_close(colors, radiance ** (1 / gamma))
    assert count.tolist() == [3, 2]
    # Without compensation the texel is the plain mean of the views, not the radiance.
    plain, _ = blend_texels(samples, view_ids, torch.ones(3), gamma)
    assert not torch.allclose(plain, colors, atol=1e-3)


def test_texel_no_view_sees_is_nan():
    colors, count = blend_texels(torch.zeros(1, 2, 3), torch.full((1, 2), -1), torch.ones(1), 2.2)
    assert bool(colors.isnan().all()) and count.tolist() == [0]


def test_unknown_exposure_mode_is_refused():
    caster = MeshRaycaster(scene_mesh())
    T_wc = pose_at(0.0)[None]
    images = torch.zeros(1, 3, CAMERA.height, CAMERA.width)
    point, normal = torch.tensor([[2.0, 0.0, 4.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    with pytest.raises(ValueError, match="'estimated', 'none'"):
        texture_texels(point, normal, caster, images, T_wc, CAMERA, CFG, "recorded")


def test_non_positive_known_exposures_are_refused():
    caster = MeshRaycaster(scene_mesh())
    T_wc = pose_at(0.0)[None]
    images = torch.zeros(1, 3, CAMERA.height, CAMERA.width)
    point, normal = torch.tensor([[2.0, 0.0, 4.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    with pytest.raises(ValueError, match="> 0"):
        texture_texels(point, normal, caster, images, T_wc, CAMERA, CFG, torch.zeros(1))
