"""Photometric consistency of relocalised poses (diffloc.reloc.photometric) and its use in
pose validation."""

from __future__ import annotations

import math

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import transform_points
from diffloc.maps.surfel import SurfelMap
from diffloc.reloc.photometric import PhotometricCheck, PhotometricConfig, cell_ncc, warped_ncc
from diffloc.reloc.validation import PoseEvidence, PoseValidator, ValidationConfig

CAMERA = PinholeCamera.from_fov(96, 72, 1.2)
WALL_Z = 3.0


def texture(points: torch.Tensor, phase: float = 0.0) -> torch.Tensor:
    """(N,) grey value of the wall at world points (N, 3): a non-periodic pattern."""
    x, y = points[:, 0], points[:, 1]
    return 0.5 + 0.2 * torch.sin(5 * x + phase) * torch.cos(3 * y) + 0.2 * torch.sin(2.3 * x * y)


def pose(x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> torch.Tensor:
    """(4, 4) float64 camera-to-world pose at (x, y, 0) looking along +z, turned by ``yaw``."""
    c, s = math.cos(yaw), math.sin(yaw)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)
    T[0, 3], T[1, 3] = x, y
    return T


def wall_hits(T_wc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World points (H * W, 3) of the wall z = WALL_Z seen through every pixel from ``T_wc``
    (exact ray casting) and their (H, W) z-depth in the camera."""
    rows, cols = torch.meshgrid(
        torch.arange(CAMERA.height), torch.arange(CAMERA.width), indexing="ij"
    )
    uv = torch.stack((cols, rows), -1).reshape(-1, 2).double()
    rays = transform_points(T_wc, CAMERA.to(torch.float64).unproject(uv)) - T_wc[:3, 3]
    t = (WALL_Z - T_wc[2, 3]) / rays[:, 2]
    return T_wc[:3, 3] + t[:, None] * rays, t.reshape(CAMERA.height, CAMERA.width).float()


def image_of_wall(T_wc: torch.Tensor, phase: float = 0.0) -> torch.Tensor:
    """(3, H, W) image of the textured wall z = WALL_Z seen from ``T_wc``."""
    grey = texture(wall_hits(T_wc)[0], phase).reshape(CAMERA.height, CAMERA.width).float()
    return grey.expand(3, -1, -1).clone()


@pytest.fixture(scope="module")
def wall_map() -> SurfelMap:
    """Surfels tiling the wall z = WALL_Z, normals towards the cameras."""
    g = torch.arange(-4.0, 4.0, 0.04)
    x, y = (t.flatten() for t in torch.meshgrid(g, g, indexing="ij"))
    centers = torch.stack((x, y, torch.full_like(x, WALL_Z)), 1)
    normals = torch.tensor([0.0, 0.0, -1.0]).expand_as(centers)
    return SurfelMap(centers=centers, normals=normals, radii=torch.full_like(x, 0.035))


def make_check(wall_map: SurfelMap, keyframe_phase: float = 0.0) -> PhotometricCheck:
    poses = torch.stack([pose(0.0), pose(0.5, 0.2, 0.1), pose(0.0, 0.0, math.pi)])
    images = [image_of_wall(poses[k], keyframe_phase) for k in range(2)] + [
        torch.zeros(3, CAMERA.height, CAMERA.width)
    ]
    return PhotometricCheck(
        wall_map, poses, lambda k: CAMERA, lambda k: images[k], PhotometricConfig(width_px=48)
    )


def test_the_true_pose_scores_near_one_and_a_wrong_pose_low(wall_map):
    check = make_check(wall_map)
    T_query = pose(0.3, -0.1, 0.05)
    image = image_of_wall(T_query)
    right = check.score(image, T_query, CAMERA, 0)
    wrong = check.score(image, pose(0.6, -0.1, 0.05), CAMERA, 0)
    assert right > 0.95
    assert wrong < 0.6
    assert check.score(image, T_query, CAMERA, 1) > 0.95  # another keyframe sees it too


def test_another_place_with_the_same_geometry_scores_low(wall_map):
    """The keyframes show a different pattern on the same wall: a repeated room whose
    furniture differs; the pose is geometrically right, the content is not."""
    check = make_check(wall_map, keyframe_phase=2.0)
    T_query = pose(0.3, -0.1, 0.05)
    assert check.score(image_of_wall(T_query), T_query, CAMERA, 0) < 0.6


def test_no_overlap_with_the_keyframe_gives_nan(wall_map):
    check = make_check(wall_map)
    T_query = pose(0.3, -0.1, 0.05)
    assert math.isnan(check.score(image_of_wall(T_query), T_query, CAMERA, 2))


def test_a_gain_and_offset_change_of_the_query_does_not_matter(wall_map):
    check = make_check(wall_map)
    T_query = pose(0.3, -0.1, 0.05)
    image = image_of_wall(T_query)
    assert check.score(0.3 + 0.5 * image, T_query, CAMERA, 0) == pytest.approx(
        check.score(image, T_query, CAMERA, 0), abs=1e-3
    )


def test_cell_ncc_matches_a_direct_computation():
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(200, generator=g), torch.rand(200, generator=g)
    cell = torch.randint(0, 4, (200,), generator=g)
    ncc = cell_ncc(a, b, cell, 5, 10)
    for c in range(4):
        x, y = a[cell == c].double(), b[cell == c].double()
        expected = torch.corrcoef(torch.stack((x, y)))[0, 1]
        assert float(ncc[c]) == pytest.approx(float(expected), abs=1e-9)
    assert math.isnan(float(ncc[4]))  # an empty cell


def test_bad_inputs_are_refused(wall_map):
    check = make_check(wall_map)
    T = pose()
    image = image_of_wall(T)
    with pytest.raises(ShapeError):
        check.score(image[0], T, CAMERA, 0)
    with pytest.raises(ValueError, match="T_wc"):
        check.score(image, torch.full((4, 4), math.nan, dtype=torch.float64), CAMERA, 0)
    with pytest.raises(IndexError, match="keyframe 7"):
        check.score(image, T, CAMERA, 7)


def test_an_rgbd_reference_is_warped_by_its_own_depth():
    """A rendered (or real RGB-D) reference needs no surfel map: its own depth lifts it."""
    T_ref, T_query = pose(0.0), pose(0.3, -0.1, 0.05)
    grey, depth = image_of_wall(T_ref)[0], wall_hits(T_ref)[1]
    image, config = image_of_wall(T_query), PhotometricConfig(width_px=48)
    right = warped_ncc(grey, depth, CAMERA, T_ref, image, CAMERA, T_query, config)
    wrong = warped_ncc(grey, depth, CAMERA, T_ref, image, CAMERA, pose(0.6, -0.1, 0.05), config)
    holes = torch.zeros_like(depth)  # a reference without depth has nothing to compare
    assert right > 0.95
    assert wrong < 0.6
    assert math.isnan(warped_ncc(grey, holes, CAMERA, T_ref, image, CAMERA, T_query, config))


def test_a_reference_depth_of_another_size_is_refused():
    T = pose()
    grey, depth = image_of_wall(T)[0], wall_hits(T)[1]
    with pytest.raises(ShapeError, match="reference_depth"):
        warped_ncc(grey, depth[:-1], CAMERA, T, image_of_wall(T), CAMERA, T, PhotometricConfig())


@pytest.mark.parametrize(
    "kwargs, key",
    [
        ({"width_px": 0}, "width_px"),
        ({"cells": 0}, "cells"),
        ({"min_cells": 20}, "min_cells"),
        ({"depth_tolerance": -1.0}, "depth_tolerance"),
    ],
)
def test_bad_settings_name_the_key(kwargs, key):
    with pytest.raises(ValueError, match=f"photometric.{key}"):
        PhotometricConfig(**kwargs)


def evidence(photometric: float | None) -> PoseEvidence:
    return PoseEvidence(
        torch.zeros(3, dtype=torch.float64), 100, 200, 1.0, ((100, 0.0),), photometric
    )


def test_validation_refuses_low_and_unmeasurable_consistency():
    validator = PoseValidator(ValidationConfig(temporal=False, min_photometric=0.5))
    assert validator.validate_evidence(evidence(0.8), 0.0)
    assert not validator.validate_evidence(evidence(0.3), 1.0)
    assert not validator.validate_evidence(evidence(math.nan), 2.0)  # no overlap
    with pytest.raises(ValueError, match="min_photometric"):
        validator.validate_evidence(evidence(None), 3.0)
    seed1 = PoseValidator(ValidationConfig(temporal=False, min_photometric=0.5).seed1_rule())
    assert seed1.validate_evidence(evidence(0.3), 0.0)
    assert PoseValidator(ValidationConfig(temporal=False)).validate_evidence(evidence(None), 0.0)


def test_records_carry_the_consistency_and_no_overlap():
    record = {
        "found": True,
        "position_m": [0.0, 0.0, 0.0],
        "candidates": [{"inliers": 50, "matches": 80, "coverage": 0.8, "distance_to_chosen_m": 0}],
    }
    assert PoseEvidence.from_record(record).photometric is None
    assert PoseEvidence.from_record({**record, "photometric": 0.7}).photometric == 0.7
    assert math.isnan(PoseEvidence.from_record({**record, "photometric": None}).photometric)


@pytest.mark.parametrize("value", [1.5, math.nan])
def test_a_bad_threshold_is_refused(value):
    with pytest.raises(ValueError, match="min_photometric"):
        ValidationConfig(min_photometric=value)
