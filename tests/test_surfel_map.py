"""SurfelMap: construction from a plane + box scene, validation, selection and file round trips."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.io.ply import write_point_cloud
from diffloc.maps.pointcloud import PointMap
from diffloc.maps.surfel import SURFEL_MAP_FORMAT_VERSION, SurfelMap, SurfelMapConfig
from diffloc.o3d import open3d

SENSOR_A = np.array([1.5, 1.5, 1.5])
SENSOR_B = np.array([-1.5, -1.5, 1.5])
CONFIG = SurfelMapConfig()  # indoor defaults: voxel 0.02 m, mean radius 0.02 m
OFFSET = 0.01  # puts the surfaces mid-voxel, so 1 mm noise does not split them into two layers


def plane_and_box(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points on a 4 x 4 m floor (z = 0) and the top and sides of a 1 m box at the centre.

    Everything is shifted by ``OFFSET`` along every axis and has 1 mm Gaussian noise.

    Returns (points (P, 3), per-point sensor origins (P, 3)): every point is given the one of
    two sensors that sees the outer side of its surface.
    """
    rng = np.random.default_rng(seed)
    n_floor = int(0.7 * n)
    floor = np.c_[rng.uniform(-2, 2, (n_floor, 2)), np.zeros(n_floor)]
    floor = floor[(np.abs(floor[:, :2]) > 0.5).any(axis=1)]  # nothing under the box
    n_box = n - n_floor
    box = rng.uniform(-0.5, 0.5, (n_box, 3))
    face = rng.integers(0, 5, n_box)  # 0..3: -x, +x, -y, +y sides; 4: top
    rows, axis = np.arange(n_box), np.where(face < 4, face // 2, 2)
    side = np.where((face % 2 == 0) & (face < 4), -1.0, 1.0)
    box[rows, axis] = 0.5 * side
    box[:, 2] += 0.5
    outward = np.zeros((n_box, 3))
    outward[rows, axis] = side
    normals = np.r_[np.tile([0.0, 0.0, 1.0], (len(floor), 1)), outward]
    points = np.r_[floor, box] + rng.normal(0, 0.001, (len(floor) + n_box, 3)) + OFFSET
    facing_a = (normals * (SENSOR_A - points)).sum(axis=1) > 0
    origins = np.where(facing_a[:, None], SENSOR_A, SENSOR_B)
    return points, origins


@pytest.fixture(scope="module")
def scene() -> tuple[np.ndarray, np.ndarray]:
    return plane_and_box(150_000)


@pytest.fixture(scope="module")
def surfels(scene) -> SurfelMap:
    points, origins = scene
    return SurfelMap.from_points(points, origins, CONFIG)


def random_map(n: int, colors: bool, confidence: bool, seed: int = 0) -> SurfelMap:
    g = torch.Generator().manual_seed(seed)
    normals = torch.randn(n, 3, generator=g)
    return SurfelMap(
        centers=torch.randn(n, 3, generator=g) * 10,
        normals=normals / normals.norm(dim=1, keepdim=True),
        radii=torch.rand(n, generator=g) * 0.1 + 1e-6,
        colors=torch.rand(n, 3, generator=g) if colors else None,
        confidence=torch.rand(n, generator=g) * 50 if confidence else None,
    )


def assert_maps_equal(a: SurfelMap, b: SurfelMap) -> None:
    for name in ("centers", "normals", "radii", "colors", "confidence"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.dtype == y.dtype == torch.float32, name
            assert torch.equal(x, y), f"{name} differs"


# ---------------------------------------------------------------- construction


def test_normals_face_the_sensor_on_every_surface(surfels: SurfelMap):
    c, n = surfels.centers.numpy(), surfels.normals.numpy()
    floor = (c[:, 2] < 0.05) & (np.abs(c[:, :2]) > 0.7).any(1) & (np.abs(c[:, :2]) < 1.8).all(1)
    top = (c[:, 2] > 0.95) & (np.abs(c[:, :2]) < 0.4).all(1)
    side_interior = (np.abs(c[:, 2] - 0.5) < 0.4) & (np.abs(c[:, :2]) < 0.4).any(1)
    plus_x = side_interior & (c[:, 0] > 0.45) & (np.abs(c[:, 1]) < 0.4)
    minus_y = side_interior & (c[:, 1] < -0.45) & (np.abs(c[:, 0]) < 0.4)
    for mask, axis, sign in ((floor, 2, 1), (top, 2, 1), (plus_x, 0, 1), (minus_y, 1, -1)):
        assert mask.sum() > 100
        assert (sign * n[mask, axis] > 0.99).all()
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)


def test_one_origin_below_the_floor_flips_floor_normals(scene):
    points, _ = scene
    away_from_box = (np.abs(points[:, :2] - OFFSET) > 0.6).any(axis=1)
    floor_points = points[(points[:, 2] < 0.05) & away_from_box]
    surfels = SurfelMap.from_points(floor_points, np.array([0.0, 0.0, -1.0]), CONFIG)
    assert (surfels.normals[:, 2] < -0.99).all()


def test_radii_are_clamped_around_the_mean_and_follow_density():
    rng = np.random.default_rng(1)
    dense = np.c_[rng.uniform(-2, 0, (200_000, 2)), np.zeros(200_000)]  # ~ 25 per voxel
    sparse = np.c_[rng.uniform(0, 2, (3_000, 2)), np.zeros(3_000)]  # ~ 0.4 per voxel
    points = np.r_[dense, sparse] + [0.0, 0.0, 1e-3] * rng.standard_normal((203_000, 3)) + OFFSET
    config = SurfelMapConfig(normal_radius_m=0.15)
    surfels = SurfelMap.from_points(points, np.array([0.0, 0.0, 2.0]), config)
    radii = surfels.radii.numpy()
    low, high = 0.02 * config.radius_min_factor, 0.02 * config.radius_max_factor
    assert radii.min() >= low and radii.max() <= high
    assert abs(radii.mean() - config.mean_radius_m) < 0.1 * config.mean_radius_m
    x = surfels.centers[:, 0].numpy()
    assert np.median(radii[x > 0.1]) > 2 * np.median(radii[x < -0.1])


def test_isolated_outliers_are_removed(scene):
    points, origins = scene
    outliers = np.array([[0, 0, 3.0], [1.9, -1.9, 2.5], [-3, 0, 1], [0, 4, 0.5], [1, 1, 1.8]])
    with_outliers = np.r_[points, outliers]
    surfels = SurfelMap.from_points(with_outliers, np.r_[origins, outliers * 0], CONFIG)
    distance = torch.cdist(torch.from_numpy(outliers).float(), surfels.centers).min(dim=1).values
    assert (distance > 0.1).all()
    cells = np.unique(np.floor(points / CONFIG.voxel_size_m), axis=0)
    assert len(surfels) > 0.95 * len(cells), "the scene itself must survive outlier removal"


def test_at_most_one_surfel_per_voxel_and_confidence_counts_points(surfels, scene):
    cells = np.floor(surfels.centers.double().numpy() / CONFIG.voxel_size_m)
    assert len(np.unique(cells, axis=0)) == len(surfels)
    confidence = surfels.confidence.numpy()
    assert (confidence >= 1).all() and confidence.sum() <= len(scene[0])
    coarse = SurfelMap.from_points(*scene, SurfelMapConfig(voxel_size_m=0.05, mean_radius_m=0.05))
    assert len(coarse) < 0.25 * len(surfels)


def test_colors_are_averaged_per_voxel(scene):
    points, origins = scene
    colors = np.clip((points + 2.0) / 4.0, 0.0, 1.0)  # linear in position
    surfels = SurfelMap.from_points(points, origins, CONFIG, colors=colors)
    expected = np.clip((surfels.centers.double().numpy() + 2.0) / 4.0, 0.0, 1.0)
    np.testing.assert_allclose(surfels.colors.numpy(), expected, atol=1e-5)


def test_one_million_points():
    points, origins = plane_and_box(1_000_000, seed=2)
    surfels = SurfelMap.from_points(torch.from_numpy(points), torch.from_numpy(origins))
    cells = np.floor(points / CONFIG.voxel_size_m).astype(np.int64)
    occupied = len(np.unique((cells[:, 0] * 1000 + cells[:, 1]) * 1000 + cells[:, 2]))
    assert 0.95 * occupied < len(surfels) <= occupied
    assert float(surfels.confidence.sum()) > 0.95 * len(points)
    assert surfels.centers.dtype == torch.float32


# ---------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("points", "origins", "error", "message"),
    [
        (np.full((100, 3), np.nan), np.zeros(3), ValueError, "NaN"),
        (np.zeros((0, 3)), np.zeros(3), ValueError, "empty"),
        (np.zeros((100, 2)), np.zeros(3), ShapeError, "points"),
        (np.zeros((100, 3)), np.zeros((99, 3)), ShapeError, "sensor_origins"),
        (np.zeros((100, 3)), np.zeros(3), ValueError, "only 1 points"),
        (np.c_[np.arange(30.0), np.zeros((30, 2))], np.zeros(3), ValueError, "two neighbours"),
    ],
)
def test_from_points_rejects_bad_input(points, origins, error, message):
    with pytest.raises(error, match=message):
        SurfelMap.from_points(points, origins, CONFIG)


def test_from_points_rejects_bad_colors(scene):
    points, origins = scene
    with pytest.raises(ValueError, match="colors"):
        SurfelMap.from_points(points, origins, CONFIG, colors=np.full(points.shape, 2.0))


@pytest.mark.parametrize(
    "change",
    [
        {"voxel_size_m": 0.0},
        {"mean_radius_m": float("nan")},
        {"radius_min_factor": 2.0, "radius_max_factor": 1.0},
        {"normal_max_nn": 2},
        {"density_neighbours": 0},
        {"outlier_std_ratio": -1.0},
    ],
)
def test_config_rejects_bad_values(change):
    with pytest.raises(ValueError, match=next(iter(change))):
        SurfelMapConfig(**change)


def test_constructor_rejects_invalid_surfels():
    good = random_map(4, colors=True, confidence=True)
    with pytest.raises(ValueError, match="radii must be positive"):
        SurfelMap(good.centers, good.normals, torch.tensor([0.1, 0.0, 0.1, 0.1]))
    with pytest.raises(ValueError, match="unit vectors"):
        SurfelMap(good.centers, good.normals * 1.1, good.radii)
    with pytest.raises(ShapeError, match="normals"):
        SurfelMap(good.centers, good.normals[:3], good.radii)
    with pytest.raises(ValueError, match="centers contains NaN"):
        SurfelMap(good.centers.clone().fill_(float("nan")), good.normals, good.radii)
    with pytest.raises(ValueError, match="colors must lie in"):
        SurfelMap(good.centers, good.normals, good.radii, colors=good.colors + 1.0)
    with pytest.raises(ValueError, match="confidence must lie in"):
        SurfelMap(good.centers, good.normals, good.radii, confidence=-good.confidence)
    with pytest.raises(TypeError, match="floating-point"):
        SurfelMap(good.centers.long(), good.normals, good.radii)


def test_select_and_to_keep_every_field():
    surfels = random_map(10, colors=True, confidence=False)
    mask = torch.arange(10) % 3 == 0
    picked = surfels.select(mask)
    assert len(picked) == 4 and picked.confidence is None
    assert torch.equal(picked.colors, surfels.colors[mask])
    by_index = surfels.select(np.array([9, 0, 0]))
    assert torch.equal(by_index.centers, surfels.centers[[9, 0, 0]])
    assert len(surfels.select(slice(2, 5))) == 3
    assert_maps_equal(surfels.to("cpu"), surfels)
    with pytest.raises(ShapeError, match="mask"):
        surfels.select(torch.ones(9, dtype=torch.bool))


# ---------------------------------------------------------------- files


@pytest.mark.parametrize("suffix", [".ply", ".npz"])
@pytest.mark.parametrize(("colors", "confidence"), [(True, True), (False, False), (True, False)])
def test_round_trip_is_bit_exact(tmp_path: Path, suffix: str, colors: bool, confidence: bool):
    surfels = random_map(500, colors, confidence)
    path = tmp_path / f"map{suffix}"
    surfels.save(path)
    assert_maps_equal(SurfelMap.load(path), surfels)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "temporary file left"


def test_empty_map_round_trips(tmp_path: Path):
    empty = random_map(3, colors=True, confidence=True).select(torch.zeros(3, dtype=torch.bool))
    for suffix in (".ply", ".npz"):
        empty.save(tmp_path / f"empty{suffix}")
        assert_maps_equal(SurfelMap.load(tmp_path / f"empty{suffix}"), empty)


def test_ply_is_readable_by_open3d(tmp_path: Path):
    surfels = random_map(50, colors=True, confidence=True)
    surfels.save_ply(tmp_path / "map.ply")
    cloud = open3d().io.read_point_cloud(str(tmp_path / "map.ply"))
    np.testing.assert_array_equal(np.asarray(cloud.points, np.float32), surfels.centers.numpy())
    np.testing.assert_allclose(np.asarray(cloud.colors), surfels.colors.numpy(), atol=0.5 / 255)


def test_missing_files_raise_file_not_found(tmp_path: Path):
    for suffix in (".ply", ".npz"):
        with pytest.raises(FileNotFoundError, match=f"absent{suffix}"):
            SurfelMap.load(tmp_path / f"absent{suffix}")


def test_unknown_suffix_is_rejected(tmp_path: Path):
    with pytest.raises(ValueError, match="unknown map file type"):
        random_map(2, False, False).save(tmp_path / "map.txt")


def good_arrays(n: int = 5) -> dict[str, np.ndarray]:
    surfels = random_map(n, colors=True, confidence=False)
    return {
        "format_version": np.array(SURFEL_MAP_FORMAT_VERSION),
        "kind": np.array("diffloc-surfel-map"),
        "centers": surfels.centers.numpy(),
        "normals": surfels.normals.numpy(),
        "radii": surfels.radii.numpy(),
    }


def truncated(path: Path) -> None:
    random_map(200, colors=True, confidence=True).save_npz(path)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def single_npy(path: Path) -> None:
    with path.open("wb") as handle:
        np.save(handle, np.zeros(3, np.float32))


def savez(**arrays):
    return lambda path: np.savez(path, **arrays)


def without(key: str) -> dict[str, np.ndarray]:
    arrays = good_arrays()
    del arrays[key]
    return arrays


def replaced(**changes) -> dict[str, np.ndarray]:
    return {**good_arrays(), **changes}


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (truncated, "npz"),
        (lambda path: path.write_bytes(b"not a zip file at all"), "npz"),
        (single_npy, "single .npy"),
        (savez(a=np.zeros(3), b=np.ones(2)), "format_version"),
        (savez(**without("radii")), r"missing entries \['radii'\]"),
        (savez(**replaced(format_version=np.array(99))), "format_version 99"),
        (savez(**replaced(kind=np.array("diffloc-point-map"))), "expected a diffloc-surfel-map"),
        (savez(**replaced(radii=np.ones((5, 1), np.float32))), "radii must have shape"),
        (savez(**replaced(radii=np.ones(5))), "float32"),
        (savez(**replaced(extra=np.ones(5, np.float32))), r"unknown entries \['extra'\]"),
        (savez(**replaced(radii=np.array([{"a": 1}] * 5, dtype=object))), "pickle"),
    ],
    ids=[
        "truncated", "not-zip", "npy", "foreign", "missing-key", "version", "kind",
        "shape", "dtype", "unknown-key", "pickle",
    ],
)  # fmt: skip
def test_corrupt_npz_raises_value_error_naming_the_file(tmp_path: Path, make, message):
    path = tmp_path / "corrupt_map.npz"
    make(path)
    with pytest.raises(ValueError, match=message) as info:
        SurfelMap.load(path)
    assert str(path) in str(info.value)


def test_point_map_file_is_not_a_surfel_map(tmp_path: Path):
    PointMap(torch.zeros(3, 3), torch.zeros(3, 3)).save_npz(tmp_path / "points.npz")
    with pytest.raises(ValueError, match=re.escape(str(tmp_path / "points.npz"))):
        SurfelMap.load_npz(tmp_path / "points.npz")


def test_ply_without_radius_or_with_bad_values_raises_naming_the_file(tmp_path: Path):
    surfels = random_map(5, colors=False, confidence=False)
    path = tmp_path / "plain.ply"
    write_point_cloud(path, surfels.centers, surfels.normals)
    with pytest.raises(ValueError, match=r"plain\.ply.*radius"):
        SurfelMap.load_ply(path)
    negative = {"radius": -surfels.radii.numpy()}
    write_point_cloud(path, surfels.centers, surfels.normals, extra=negative)
    with pytest.raises(ValueError, match=r"plain\.ply.*radii must be positive"):
        SurfelMap.load_ply(path)
