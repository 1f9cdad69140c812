"""Render-pose selection on a free-path corridor (seed 2, Sec. III-C) on a constructed building.

The building has two storeys 3 m apart. The ground floor is an L-shaped corridor (2 m wide)
and a room behind a 0.2 m wall, entered through a 1.2 m door, with a table in it; the upper
floor is the L-shaped corridor only. Floors face up, ceilings down, walls inwards, as normals
oriented towards a scanner inside would.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from matplotlib.image import imread
from scipy import ndimage
from scipy.spatial import cKDTree

from diffloc.checks import ShapeError
from diffloc.crossmodal.pose_selection import (
    VIEW_NAMES,
    PoseSelectionConfig,
    select_render_poses,
    view_poses,
    write_floor_plan_figures,
)
from diffloc.crossmodal.trajectory_samples import trajectory_samples

RES = 0.05  # point spacing of the constructed clouds, metres
STOREY_Z = (0.0, 3.0)
CEILING_M = 2.8
CORRIDOR = [(0.0, 12.0, 0.0, 2.0), (10.0, 12.0, 0.0, 10.0)]  # (x0, x1, y0, y1) rectangles
ROOM = [(4.0, 9.8, 4.0, 10.0), (9.8, 10.0, 6.4, 7.6)]  # room + door through the 0.2 m wall
TABLE = (6.0, 7.0, 6.5, 7.5, 0.75)  # x0, x1, y0, y1, top height
SCANNER_XY = (6.0, 1.0)  # a scanner station here does not see the floor within 0.6 m
CONFIG = PoseSelectionConfig()


def _inside(xy: np.ndarray, rects: list[tuple[float, ...]]) -> np.ndarray:
    x, y = xy[..., 0], xy[..., 1]
    return np.any([(x > a) & (x < b) & (y > c) & (y < d) for a, b, c, d in rects], axis=0)


def _storey(rects: list[tuple[float, ...]], z: float) -> tuple[np.ndarray, ...]:
    """Points (K, 3), normals (K, 3) and wall xy (W, 2) of one storey."""
    xs = np.arange(-0.5, 12.5, RES) + RES / 2
    ys = np.arange(-0.5, 10.5, RES) + RES / 2
    grid = np.stack(np.meshgrid(xs, ys), axis=-1)  # (H, W, 2), rows along y
    region = _inside(grid, rects)
    blind = np.linalg.norm(grid - np.array(SCANNER_XY), axis=-1) < 0.6
    floor_xy = grid[region & ~blind]
    walls, wall_normals = [], []
    for axis, step in ((1, 1), (1, -1), (0, 1), (0, -1)):  # neighbour along x (axis 1) or y
        neighbour = np.roll(region, -step, axis=axis)
        edge = region & ~neighbour
        offset = np.zeros(2)
        offset[1 - axis] = step * RES / 2  # axis 1 = columns = x
        walls.append(grid[edge] + offset)
        wall_normals.append(np.tile(-offset / np.linalg.norm(offset), (edge.sum(), 1)))
    wall_xy, wall_n = np.concatenate(walls), np.concatenate(wall_normals)
    levels = z + np.arange(RES, CEILING_M, 2 * RES)
    wall_points = np.concatenate([np.c_[wall_xy, np.full(len(wall_xy), h)] for h in levels])
    n_floor = len(floor_xy)
    points = np.concatenate(
        [
            np.c_[floor_xy, np.full(n_floor, z)],
            np.c_[floor_xy, np.full(n_floor, z + CEILING_M)],
            wall_points,
        ]
    )
    normals = np.concatenate(
        [
            np.tile([0.0, 0.0, 1.0], (n_floor, 1)),
            np.tile([0.0, 0.0, -1.0], (n_floor, 1)),
            np.tile(np.c_[wall_n, np.zeros(len(wall_n))], (len(levels), 1)),
        ]
    )
    return points, normals, wall_xy


def _building() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    ground, ground_n, ground_walls = _storey(CORRIDOR + ROOM, STOREY_Z[0])
    upper, upper_n, upper_walls = _storey(CORRIDOR, STOREY_Z[1])
    x0, x1, y0, y1, top = TABLE
    tx, ty = np.meshgrid(np.arange(x0, x1 + 1e-9, RES), np.arange(y0, y1 + 1e-9, RES))
    table_xy = np.c_[tx.ravel(), ty.ravel()]
    table = np.c_[table_xy, np.full(len(table_xy), top)]
    points = np.concatenate([ground, upper, table])
    normals = np.concatenate([ground_n, upper_n, np.tile([0.0, 0.0, 1.0], (len(table), 1))])
    points += rng.normal(scale=0.002, size=points.shape)
    return {
        "points": points.astype(np.float32),
        "normals": normals.astype(np.float32),
        "obstacles_0": np.concatenate([ground_walls, table_xy]),
        "obstacles_1": upper_walls,
    }


@pytest.fixture(scope="module")
def building() -> dict[str, np.ndarray]:
    return _building()


@pytest.fixture(scope="module")
def selection(building):
    return select_render_poses(building["points"], torch.from_numpy(building["normals"]), CONFIG)


def test_both_floors_found_at_their_heights(selection):
    heights = [plan.height_m for plan in selection.floors]
    np.testing.assert_allclose(heights, STOREY_Z, atol=0.01)
    assert set(selection.floor_index.tolist()) == {0, 1}


def test_samples_lie_in_free_space_with_clearance(building, selection):
    tolerance = CONFIG.cell_size_m  # samples are cell centres, walls lie inside their cells
    for plan, rects in zip(selection.floors, (CORRIDOR + ROOM, CORRIDOR), strict=True):
        xy = plan.samples_xy
        assert len(xy) >= 8
        assert _inside(xy, rects).all()
        clearance, _ = cKDTree(building[f"obstacles_{plan.index}"]).query(xy)
        assert clearance.min() >= CONFIG.min_clearance_m - tolerance, clearance.min()
    ground_room = _inside(selection.floors[0].samples_xy, ROOM[:1]).sum()
    assert ground_room >= 3  # the room is reached through the door
    assert not _inside(selection.floors[1].samples_xy, ROOM[:1]).any()


def test_scanner_blind_spot_is_filled_and_corridors_connect(selection):
    for plan in selection.floors:
        col, row = np.round((np.array(SCANNER_XY) - plan.origin_xy) / CONFIG.cell_size_m)
        assert plan.free[int(row), int(col)]
        assert ndimage.label(plan.corridor, structure=np.ones((3, 3)))[1] == 1


def test_floor_closing_bridges_lidar_ring_gaps(building):
    """A rotating lidar samples the floor in rings: bands 0.4 m wide without floor points
    every metre across the ground floor. Closed by 0.1 m (the default, as the obstacles) the
    free space is 0.6 m stripes with no 0.4 m clearance; a floor closing of 0.3 m restores
    the corridor of the unbroken floor, and its samples stay in free space."""
    points, normals = building["points"], building["normals"]
    on_ground = (normals[:, 2] > 0.5) & (np.abs(points[:, 2] - STOREY_Z[0]) < 0.05)
    in_gap = (np.mod(points[:, 0], 1.0) >= 0.6) & (points[:, 0] < 11.0)  # not at the ends
    keep = ~(on_ground & in_gap)
    points, normals = points[keep], normals[keep]
    wide = replace(CONFIG, floor_closing_radius_m=0.3)
    with pytest.raises(ValueError, match="floor 0 .*empty corridor"):
        select_render_poses(points, normals, replace(CONFIG, floor_closing_radius_m=0.1))
    plan = select_render_poses(points, normals, wide).floors[0]
    whole = select_render_poses(building["points"], building["normals"], wide).floors[0]
    assert ndimage.label(plan.corridor, structure=np.ones((3, 3)))[1] == 1
    assert plan.corridor.sum() >= 0.95 * whole.corridor.sum()
    assert _inside(plan.samples_xy, CORRIDOR + ROOM).all()
    clearance, _ = cKDTree(building["obstacles_0"]).query(plan.samples_xy)
    assert clearance.min() >= wide.min_clearance_m - wide.cell_size_m
    assert abs(len(plan.samples_xy) - len(whole.samples_xy)) <= 1


def test_samples_are_spaced_along_the_skeleton(selection):
    spacing = CONFIG.spacing_m
    for plan in selection.floors:
        xy = plan.samples_xy
        gaps, _ = cKDTree(xy).query(xy, k=2)
        nearest = gaps[:, 1]
        assert nearest.min() >= 0.45 * spacing, nearest.min()
        assert nearest.max() <= 1.5 * spacing, nearest.max()
        assert 0.8 * spacing <= np.median(nearest) <= 1.2 * spacing, np.median(nearest)
        rows, cols = np.nonzero(plan.skeleton)
        uncovered, _ = cKDTree(xy).query(plan.cells_to_xy(rows, cols))
        assert uncovered.max() <= 0.8 * spacing, uncovered.max()


def test_four_orthogonal_horizontal_views_per_sample(selection):
    T_wc = selection.T_wc
    assert T_wc.dtype == torch.float64 and T_wc.shape[1:] == (4, 4)
    n_samples = sum(len(plan.samples_xy) for plan in selection.floors)
    assert len(selection) == 4 * n_samples == len(selection.view_index)
    assert torch.equal(selection.sample_index, torch.arange(n_samples).repeat_interleave(4))
    assert torch.equal(selection.view_index, torch.arange(4).repeat(n_samples))
    assert selection.views_per_sample == 4 and VIEW_NAMES[:4] == (
        "forward",
        "back",
        "left",
        "right",
    )
    R = T_wc[:, :3, :3]
    eye = torch.eye(3, dtype=torch.float64).expand_as(R)
    torch.testing.assert_close(R.transpose(1, 2) @ R, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(len(R), dtype=torch.float64))
    down = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand(len(R), 3)
    torch.testing.assert_close(R[:, :, 1], down)  # camera y (image down) is world down
    looks = R[:, :, 2].reshape(n_samples, 4, 3)  # forward, back, left, right
    assert torch.all(looks[..., 2] == 0)
    dots = looks @ looks.transpose(1, 2)
    expected = torch.tensor(
        [[1.0, -1.0, 0.0, 0.0], [-1.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, -1.0], [0, 0, -1.0, 1.0]],
        dtype=torch.float64,
    )
    torch.testing.assert_close(dots, expected.expand_as(dots), atol=1e-12, rtol=0)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(n_samples, 3)
    left = torch.linalg.cross(up, looks[:, 0])
    torch.testing.assert_close(looks[:, 2], left, atol=1e-12, rtol=0)
    centres = T_wc[:, :3, 3].reshape(n_samples, 4, 3)
    assert torch.equal(centres, centres[:, :1].expand_as(centres))


def test_view_poses_known_answer():
    T_wc, view = view_poses(np.array([[1.0, 2.0, 3.0]]), np.array([[2.0, 0.0]]))
    # Looking along world +x with z up: camera x (right) is world -y, camera y (down) is -z.
    forward = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    torch.testing.assert_close(T_wc[0, :3, :3], forward.double())
    torch.testing.assert_close(T_wc[2, :3, 2], torch.tensor([0.0, 1.0, 0.0]).double())  # left
    torch.testing.assert_close(
        T_wc[:, :3, 3], torch.tensor([[1.0, 2.0, 3.0]]).double().expand(4, 3)
    )
    assert view.tolist() == [0, 1, 2, 3]
    with pytest.raises(ValueError, match="zero-length"):
        view_poses(np.zeros((1, 3)), np.zeros((1, 2)))


def test_eight_views_known_answer_yaws_in_a_straight_corridor():
    """An 8 x 2 m floor along x: the skeleton runs along x from its end at x ~ 0.4 m (the
    root), so the inner samples look forward along +x and their 8 views have the yaws of
    VIEW_NAMES, counter-clockwise from +x seen from above."""
    xy = np.mgrid[0:8:RES, 0:2:RES].reshape(2, -1).T
    points = np.c_[xy, np.zeros(len(xy))]
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    config = replace(CONFIG, views_per_sample=8)
    selection = select_render_poses(points, normals, config)
    samples = len(selection.floors[0].samples_xy)
    assert len(selection) == 8 * samples and selection.views_per_sample == 8
    assert torch.equal(selection.view_index, torch.arange(8).repeat(samples))
    assert torch.equal(selection.sample_index, torch.arange(samples).repeat_interleave(8))
    looks = selection.T_wc[:, :3, 2].reshape(samples, 8, 3)
    yaw = torch.rad2deg(torch.atan2(looks[..., 1], looks[..., 0])) % 360.0
    expected = torch.tensor([0.0, 180.0, 90.0, 270.0, 45.0, 225.0, 135.0, 315.0])
    inner = (selection.floors[0].forward_xy == [1.0, 0.0]).all(axis=1)
    assert inner.sum() >= 2  # the samples between the two ends
    torch.testing.assert_close(
        yaw[torch.from_numpy(inner)],
        expected.double().expand(int(inner.sum()), 8),
        atol=1e-9,
        rtol=0,
    )
    # Every sample: the yaws relative to its forward view, whatever its forward direction.
    relative = (yaw - yaw[:, :1]) % 360.0
    relative = torch.where(relative > 360.0 - 1e-9, relative - 360.0, relative)
    torch.testing.assert_close(relative, expected.double().expand(samples, 8), atol=1e-9, rtol=0)
    R = selection.T_wc[:, :3, :3]
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(len(R), dtype=torch.float64))
    torch.testing.assert_close(looks[..., 2], torch.zeros(samples, 8, dtype=torch.float64))


def test_eight_views_add_the_diagonals_to_the_four(building, selection, tmp_path):
    """The 8-view poses are the 4-view ones (same samples, same first four views, bit for bit)
    plus four views 45 deg between them; the figures draw all eight."""
    config = replace(CONFIG, views_per_sample=8)
    eight = select_render_poses(building["points"], building["normals"], config)
    n = len(selection) // 4
    assert len(eight) == 8 * n
    by_sample = eight.T_wc.reshape(n, 8, 4, 4)
    assert torch.equal(by_sample[:, :4].reshape(-1, 4, 4), selection.T_wc)
    assert torch.equal(eight.floor_index.reshape(n, 8)[:, 0], selection.floor_index[::4])
    looks = by_sample[:, :, :3, 2]
    cosines = (looks[:, 4:, None] * looks[:, None, :4]).sum(-1)  # diagonals x axis views
    half = math.sqrt(0.5)
    # forward-left, back-right, back-left, forward-right against forward, back, left, right
    expected = half * torch.tensor(
        [
            [1.0, -1.0, 1.0, -1.0],
            [-1.0, 1.0, -1.0, 1.0],
            [-1.0, 1.0, 1.0, -1.0],
            [1.0, -1.0, -1.0, 1.0],
        ],
        dtype=torch.float64,
    )
    torch.testing.assert_close(cosines, expected.expand_as(cosines), atol=1e-12, rtol=0)
    paths = write_floor_plan_figures(eight, tmp_path / "figures")
    assert len(paths) == 2 and all(p.stat().st_size > 20_000 for p in paths)


@pytest.mark.parametrize("views", [0, 3, 6, 16, -4, 4.0, True, "8", None])
def test_a_views_per_sample_other_than_4_or_8_is_refused(views):
    with pytest.raises(ValueError, match=r"views_per_sample must be one of \(4, 8\)"):
        PoseSelectionConfig(views_per_sample=views)
    with pytest.raises(ValueError, match=r"views_per_sample must be one of \(4, 8\)"):
        view_poses(np.zeros((1, 3)), np.array([[1.0, 0.0]]), views)


def test_forward_follows_the_corridor(selection):
    """In the long straight corridor legs, forward is along the leg (x or y)."""
    plan = selection.floors[1]
    xy, forward = plan.samples_xy, plan.forward_xy
    leg_a = (xy[:, 0] > 2.0) & (xy[:, 0] < 8.0)
    leg_b = (xy[:, 1] > 4.0) & (xy[:, 1] < 8.0)
    assert leg_a.any() and leg_b.any()
    assert np.all(np.abs(forward[leg_a, 0]) > math.cos(math.radians(10)))
    assert np.all(np.abs(forward[leg_b, 1]) > math.cos(math.radians(10)))


def test_camera_height_above_each_floor(selection):
    floor_z = torch.tensor([plan.height_m for plan in selection.floors], dtype=torch.float64)
    expected = floor_z[selection.floor_index] + CONFIG.camera_height_m
    torch.testing.assert_close(selection.T_wc[:, 2, 3], expected, atol=1e-9, rtol=0)


def test_floor_plan_figures_are_written(selection, tmp_path):
    paths = write_floor_plan_figures(selection, tmp_path / "figures")
    assert [p.name for p in paths] == ["floor_0.png", "floor_1.png"]
    for path in paths:
        assert path.stat().st_size > 20_000
        image = imread(path)
        assert image.shape[0] >= 800 and image.shape[1] >= 1400
        assert image[..., :3].std() > 0.05
    assert not list((tmp_path / "figures").glob("*.tmp*"))


@pytest.mark.parametrize(
    ("change", "error", "match"),
    [
        (lambda p, n: (p[:, :2], n), ShapeError, "points must have shape"),
        (lambda p, n: (p, n[:-1]), ValueError, "one row per point"),
        (lambda p, n: (p[:0], n[:0]), ValueError, "empty"),
        (lambda p, n: (np.where(np.arange(len(p))[:, None] == 5, np.nan, p), n), ValueError, "NaN"),
        (lambda p, n: (p, np.zeros_like(n)), ValueError, "zero-length"),
        (lambda p, n: (p, np.tile(np.float32([1, 0, 0]), (len(n), 1))), ValueError, "no floor"),
        (lambda p, n: (p.astype(np.int64), n), TypeError, "floating point"),
    ],
    ids=["shape", "count", "empty", "nan", "zero-normal", "no-floor", "dtype"],
)
def test_bad_input_raises(building, change, error, match):
    points, normals = change(building["points"], building["normals"])
    with pytest.raises(error, match=match):
        select_render_poses(points, normals, CONFIG)


def test_empty_corridor_raises(building):
    config = PoseSelectionConfig(min_clearance_m=3.5)  # the widest space is 6 m across
    with pytest.raises(ValueError, match="floor 0 .*empty corridor"):
        select_render_poses(building["points"], building["normals"], config)


@pytest.mark.parametrize(
    "field",
    [
        {"spacing_m": 0.0},
        {"cell_size_m": -0.05},
        {"min_clearance_m": math.nan},
        {"floor_max_normal_angle_rad": math.pi / 2},
        {"min_floor_fraction": 0.0},
        {"obstacle_min_height_m": 2.5},
        {"max_floor_hole_m2": -1.0},
        {"floor_closing_radius_m": -0.3},
        {"camera_height_m": True},
        {"trajectory_gap_m": 0.0},
        {"trajectory_gap_m": math.inf},
    ],
)
def test_bad_config_raises(field):
    with pytest.raises(ValueError, match=next(iter(field))):
        PoseSelectionConfig(**field)


def _mid_storey_walk() -> torch.Tensor:
    """(13, 4, 4) cameras walking the lower corridor along +x at z = 3 m, between the two
    storeys' render cameras (1.5 and 4.5 m): a stair the floors' skeletons do not cover."""
    T = torch.eye(4, dtype=torch.float64).repeat(13, 1, 1)
    T[:, :3, :3] = torch.tensor([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=torch.float64)
    T[:, 0, 3] = torch.arange(13, dtype=torch.float64)  # x = 0 .. 12 m
    T[:, 1, 3] = 1.0
    T[:, 2, 3] = 3.0
    return T


def test_trajectory_samples_cover_what_the_skeleton_leaves(building, selection):
    walk = _mid_storey_walk()
    config = replace(CONFIG, trajectory_gap_m=1.0)
    extended = select_render_poses(building["points"], building["normals"], config, walk)
    k = len(selection)
    assert torch.equal(extended.T_wc[:k], selection.T_wc)  # the skeleton's come first, unchanged
    assert bool((extended.floor_index[:k] >= 0).all())
    new = extended.floor_index < 0
    assert int(new.sum()) >= 4 * 4  # at least one sample every 3 m of the 12 m walk
    centres = extended.T_wc[new][::4, :3, 3]
    assert torch.isin(centres[:, 0], walk[:, 0, 3]).all() and bool((centres[:, 2] == 3.0).all())
    assert float(torch.pdist(centres).min()) > 1.0  # spaced by more than the gap
    every = extended.T_wc[::4, :3, 3]
    assert float(torch.cdist(walk[:, :3, 3], every).amin(1).max()) <= 1.0  # the walk is covered
    assert bool((extended.T_wc[new][::4, :3, 2] == torch.tensor([1.0, 0, 0]).double()).all())


def test_trajectory_near_the_skeleton_adds_nothing(building, selection):
    config = replace(CONFIG, trajectory_gap_m=2.0)  # every camera within 1.8 m of a sample
    extended = select_render_poses(
        building["points"], building["normals"], config, _mid_storey_walk()
    )
    assert torch.equal(extended.T_wc, selection.T_wc)


def test_a_trajectory_gap_without_a_trajectory_is_refused(building):
    config = replace(CONFIG, trajectory_gap_m=1.0)
    with pytest.raises(ValueError, match="no trajectory"):
        select_render_poses(building["points"], building["normals"], config)


def test_trajectory_cameras_looking_straight_down_are_skipped():
    T = _mid_storey_walk()[:3]
    T[1, :3, :3] = torch.tensor([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]], dtype=torch.float64)
    positions, forward = trajectory_samples(T, torch.zeros(0, 3), gap_m=0.5)
    assert positions[:, 0].tolist() == [0.0, 2.0] and forward.tolist() == [[1.0, 0.0]] * 2


@pytest.mark.parametrize(
    ("poses", "taken", "gap", "error", "match"),
    [
        (torch.eye(4)[None].repeat(2, 1, 1), torch.zeros(0, 3), 0.0, ValueError, "gap_m"),
        (torch.eye(4)[None].repeat(2, 1, 1), torch.zeros(0, 2), 1.0, ShapeError, "taken"),
        (torch.full((2, 4, 4), math.nan), torch.zeros(0, 3), 1.0, ValueError, "T_wc"),
    ],
)
def test_bad_trajectory_input_raises(poses, taken, gap, error, match):
    with pytest.raises(error, match=match):
        trajectory_samples(poses, taken, gap)
