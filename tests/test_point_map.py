"""PointMap: colourisation from posed RGB-D views (known answers), validation and files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import invert, transform_points
from diffloc.io.ply import write_point_cloud
from diffloc.maps.pointcloud import ColorizeConfig, PointMap

PLANE_Z = 4.0
# Odd image size: the principal point is a pixel centre, so a looked-at point hits it exactly.
CAMERA = PinholeCamera.from_fov(41, 31, 1.2, dtype=torch.float64)


def look_at(position: tuple[float, ...], target: tuple[float, ...]) -> torch.Tensor:
    """(4, 4) float64 T_wc of an OpenCV camera at ``position`` looking at ``target``."""
    position_t = torch.tensor(position, dtype=torch.float64)
    z = torch.tensor(target, dtype=torch.float64) - position_t
    z = z / z.norm()
    x = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), z)
    x = x / x.norm()
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.stack((x, torch.linalg.cross(z, x), z), dim=1)
    T[:3, 3] = position_t
    return T


def albedo(xy: torch.Tensor) -> torch.Tensor:
    """(..., 3) colour of 1 m tiles of the plane: constant per tile, different between tiles."""
    tile = torch.floor(xy).remainder(4)
    red, green = 0.1 + 0.2 * tile[..., 0], 0.1 + 0.2 * tile[..., 1]
    return torch.stack((red, green, torch.full_like(red, 0.5)), dim=-1)


def render_plane(T_wc: torch.Tensor, gain: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact image (3, H, W) (``gain * albedo``) and z-depth (1, H, W) of the plane z = 4."""
    rays_cam = CAMERA.unproject(CAMERA.pixel_grid().reshape(-1, 2))  # z = 1
    directions = rays_cam @ T_wc[:3, :3].T
    t = (PLANE_Z - T_wc[2, 3]) / directions[:, 2]
    hit = t > 0
    xy = T_wc[:2, 3] + t[:, None] * directions[:, :2]
    color = torch.where(hit[:, None], gain * albedo(xy), 0.0)
    depth = torch.where(hit, t, 0.0)
    shape = (CAMERA.height, CAMERA.width)
    return color.T.reshape(3, *shape).float(), depth.reshape(1, *shape).float()


def expected_color(point: list[float], gain: float) -> torch.Tensor:
    return (gain * albedo(torch.tensor(point[:2], dtype=torch.float64))).float()


NEAR_GAIN, FAR_GAIN, GRAZING_GAIN = 1.0, 0.5, 0.25
T_NEAR = look_at((0.0, 0.0, 0.0), (0.0, 0.0, 1.0))  # plane at 4 m
T_FAR = look_at((0.0, 0.0, -2.0), (0.0, 0.0, 1.0))  # plane at 6 m

VISIBLE_NEAR = [[0.5, 0.5, PLANE_Z], [-0.5, -1.5, PLANE_Z]]
OCCLUDED_NEAR = [-0.5, 0.5, PLANE_Z]
OUTSIDE_NEAR = [3.5, 0.5, PLANE_Z]  # beyond the near view's field of view, inside the far one
UNSEEN = [[0.0, 0.0, -5.0], [0.5, -0.5, 3.0], [10.0, 0.5, PLANE_Z]]  # behind, floating, outside


@pytest.fixture(scope="module")
def two_views() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Images (2, 3, H, W), depths (2, 1, H, W) and T_wc (2, 4, 4); an occluder in view 0."""
    near_image, near_depth = render_plane(T_NEAR, NEAR_GAIN)
    far_image, far_depth = render_plane(T_FAR, FAR_GAIN)
    uv, _ = CAMERA.project(
        transform_points(invert(T_NEAR), torch.tensor([OCCLUDED_NEAR], dtype=torch.float64))
    )
    u, v = (int(round(float(c))) for c in uv[0])
    near_depth[:, v - 2 : v + 3, u - 2 : u + 3] = 2.0  # a white box 2 m in front of the camera
    near_image[:, v - 2 : v + 3, u - 2 : u + 3] = 1.0
    images = torch.stack((near_image, far_image))
    depths = torch.stack((near_depth, far_depth))
    return images, depths, torch.stack((T_NEAR, T_FAR))


def all_points() -> torch.Tensor:
    return torch.tensor(VISIBLE_NEAR + [OCCLUDED_NEAR, OUTSIDE_NEAR] + UNSEEN)


def test_colorize_known_answer_with_occlusion(two_views):
    images, depths, T_wc = two_views
    point_map, seen = PointMap.colorize(all_points(), images, T_wc, CAMERA, depths)
    assert seen.tolist() == [True, True, True, True, False, False, False]
    expected = torch.stack(
        [expected_color(p, NEAR_GAIN) for p in VISIBLE_NEAR]
        + [expected_color(OCCLUDED_NEAR, FAR_GAIN), expected_color(OUTSIDE_NEAR, FAR_GAIN)]
    )
    assert torch.equal(point_map.colors, expected)
    assert torch.equal(point_map.positions, all_points()[seen])
    assert point_map.normals is None


def test_chunking_and_per_view_cameras_do_not_change_the_result(two_views):
    images, depths, T_wc = two_views
    reference, seen = PointMap.colorize(all_points(), images, T_wc, CAMERA, depths)
    one_view_chunks = ColorizeConfig(max_pairs_per_chunk=1)
    per_view_camera = PinholeCamera.from_fov(41, 31, torch.full((2,), 1.2, dtype=torch.float64))
    for camera, config in ((CAMERA, one_view_chunks), (per_view_camera, None)):
        point_map, seen_again = PointMap.colorize(
            all_points(), images, T_wc, camera, depths, config=config
        )
        assert torch.equal(seen_again, seen)
        assert torch.equal(point_map.colors, reference.colors)


def test_view_angle_weighting_prefers_a_farther_frontal_view():
    point = [0.5, 0.5, PLANE_Z]
    angle = math.radians(75.0)  # grazing view at 3 m: distance / cos = 11.6 m > 6 m frontal
    position = (0.5 + 3 * math.sin(angle), 0.5, PLANE_Z - 3 * math.cos(angle))
    T_grazing = look_at(position, tuple(point))
    renders = [render_plane(T_grazing, GRAZING_GAIN), render_plane(T_FAR, FAR_GAIN)]
    images = torch.stack([image for image, _ in renders])
    depths = torch.stack([depth for _, depth in renders])
    T_wc = torch.stack((T_grazing, T_FAR))
    points = torch.tensor([point])
    normals = torch.tensor([[0.0, 0.0, -1.0]])

    nearest, _ = PointMap.colorize(points, images, T_wc, CAMERA, depths)
    assert torch.equal(nearest.colors[0], expected_color(point, GRAZING_GAIN))
    for sign in (1.0, -1.0):  # the normal's sign does not matter
        weighted, _ = PointMap.colorize(
            points, images, T_wc, CAMERA, depths, normals=sign * normals
        )
        assert torch.equal(weighted.colors[0], expected_color(point, FAR_GAIN))
        assert torch.equal(weighted.normals, sign * normals)
    strict = ColorizeConfig(max_view_angle_rad=math.radians(70.0))
    grazing_only = (images[:1], T_wc[:1], CAMERA, depths[:1])
    _, seen = PointMap.colorize(points, *grazing_only, config=strict, normals=normals)
    assert not seen.any(), "views beyond max_view_angle_rad are not used"


def test_no_view_sees_any_point_gives_an_empty_map(two_views):
    images, depths, T_wc = two_views
    point_map, seen = PointMap.colorize(torch.tensor(UNSEEN), images, T_wc, CAMERA, depths)
    assert len(point_map) == 0 and not seen.any()


def test_depth_zero_means_no_measurement(two_views):
    images, depths, T_wc = two_views
    _, seen = PointMap.colorize(all_points(), images, T_wc, CAMERA, torch.zeros_like(depths))
    assert not seen.any()


@pytest.mark.parametrize(
    ("change", "error", "message"),
    [
        ({"images": torch.zeros(2, 3, 30, 41)}, ShapeError, "depths"),
        ({"T_wc": torch.eye(4).expand(3, 4, 4)}, ShapeError, "T_wc"),
        ({"points": torch.tensor([[math.nan, 0.0, 1.0]])}, ValueError, "NaN"),
        ({"images": torch.full((2, 3, 31, 41), 1.5)}, ValueError, "images must lie in"),
        ({"depths": torch.full((2, 1, 31, 41), -1.0)}, ValueError, "depths must lie in"),
        ({"camera": PinholeCamera.from_fov(40, 31, 1.2)}, ShapeError, "camera"),
        ({"camera": PinholeCamera.from_fov(41, 31, torch.ones(3))}, ShapeError, "one per view"),
        ({"normals": torch.ones(7, 3)}, ValueError, "unit vectors"),
    ],
)
def test_colorize_rejects_bad_input(two_views, change, error, message):
    images, depths, T_wc = two_views
    inputs = {"points": all_points(), "images": images, "T_wc": T_wc, "camera": CAMERA}
    inputs["depths"] = depths
    inputs.update(change)
    with pytest.raises(error, match=message):
        PointMap.colorize(**inputs)


def test_colorize_config_rejects_bad_values():
    with pytest.raises(ValueError, match="occlusion_tolerance_m"):
        ColorizeConfig(occlusion_tolerance_m=0.0)
    with pytest.raises(ValueError, match="max_view_angle_rad"):
        ColorizeConfig(max_view_angle_rad=2.0)
    with pytest.raises(ValueError, match="max_pairs_per_chunk"):
        ColorizeConfig(max_pairs_per_chunk=0)


# ---------------------------------------------------------------- validation and files


def random_point_map(n: int, normals: bool) -> PointMap:
    g = torch.Generator().manual_seed(3)
    directions = torch.randn(n, 3, generator=g)
    return PointMap(
        positions=torch.randn(n, 3, generator=g) * 20,
        colors=torch.rand(n, 3, generator=g),
        normals=directions / directions.norm(dim=1, keepdim=True) if normals else None,
    )


def test_constructor_rejects_invalid_points():
    good = random_point_map(4, normals=True)
    with pytest.raises(ValueError, match="colors must lie in"):
        PointMap(good.positions, -good.colors)
    with pytest.raises(ShapeError, match="colors"):
        PointMap(good.positions, good.colors[:, :2])
    with pytest.raises(ValueError, match="unit vectors"):
        PointMap(good.positions, good.colors, good.normals * 2)
    with pytest.raises(ValueError, match="positions contains NaN"):
        PointMap(good.positions * math.nan, good.colors)


@pytest.mark.parametrize("suffix", [".ply", ".npz"])
@pytest.mark.parametrize("normals", [True, False])
def test_round_trip_is_bit_exact(tmp_path: Path, suffix: str, normals: bool):
    point_map = random_point_map(300, normals)
    point_map.save(tmp_path / f"cloud{suffix}")
    loaded = PointMap.load(tmp_path / f"cloud{suffix}")
    assert torch.equal(loaded.positions, point_map.positions)
    assert torch.equal(loaded.colors, point_map.colors)
    assert (loaded.normals is None) == (point_map.normals is None)
    if normals:
        assert torch.equal(loaded.normals, point_map.normals)


def test_foreign_ply_with_byte_colors_loads(tmp_path: Path):
    colors = np.array([[0, 128, 255], [255, 0, 1]], dtype=np.uint8)
    write_point_cloud(tmp_path / "scan.ply", np.zeros((2, 3)), colors=colors)
    loaded = PointMap.load(tmp_path / "scan.ply")
    assert torch.equal(loaded.colors, torch.from_numpy(colors).float() / 255)


def test_bad_files_raise_naming_the_file(tmp_path: Path):
    write_point_cloud(tmp_path / "grey.ply", np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"grey\.ply.*red, green, blue"):
        PointMap.load(tmp_path / "grey.ply")
    (tmp_path / "broken.npz").write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(ValueError, match=r"broken\.npz"):
        PointMap.load(tmp_path / "broken.npz")
    with pytest.raises(FileNotFoundError, match=r"absent\.ply"):
        PointMap.load(tmp_path / "absent.ply")
