"""VisualDatabase: adding, removing, covisibility, descriptor fusion and file round trips."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from diffloc.database.database import VisualDatabase
from diffloc.geometry.camera import PinholeCamera

CAMERA = PinholeCamera.from_fov(64, 48, 1.0)


def make_database(observers: list[list[int]], dim: int = 4, global_dim: int | None = None):
    """A database whose point ``p`` is observed by keyframes ``observers[p]``.

    Keyframe ``k`` gets one keypoint per point it observes (in point order) plus one
    unobserved keypoint; descriptors are seeded random.
    """
    generator = torch.Generator().manual_seed(0)
    num_keyframes = max(max(kfs) for kfs in observers) + 1
    db = VisualDatabase(dim, global_dim=global_dim)
    ids = db.add_points(
        torch.rand(len(observers), 3, generator=generator, dtype=torch.float64),
        torch.rand(len(observers), dim, generator=generator),
        torch.arange(len(observers)) * 10,
    )
    for k in range(num_keyframes):
        seen = [p for p, kfs in enumerate(observers) if k in kfs]
        n = len(seen) + 1
        neighbours = torch.tensor(seen + [-1])[:, None].expand(n, 2).clone()
        neighbours[:, 1] = -1
        g = None if global_dim is None else torch.rand(global_dim, generator=generator)
        db.add_keyframe(
            torch.eye(4, dtype=torch.float64),
            CAMERA,
            torch.rand(n, 2, generator=generator) * 40,
            torch.rand(n, dim, generator=generator),
            torch.full((n,), 8.0),
            keypoint_surfels=torch.tensor([p * 10 for p in seen] + [-1]),
            neighbour_surfels=neighbours * 10,
            global_descriptor=g,
        )
        db.add_observations(k, torch.arange(len(seen)), ids[seen])
    return db


def assert_same(a: VisualDatabase, b: VisualDatabase) -> None:
    assert a.metric == b.metric
    for name, value in vars(a).items():
        if name.startswith("_"):  # buffers and caches, not state
            continue
        other = getattr(b, name)
        if isinstance(value, torch.Tensor):
            assert value.dtype == other.dtype, name
            assert torch.equal(value, other), name
        else:
            assert value == other, name


def test_stats_and_observations():
    db = make_database([[0, 1], [0, 1, 2], [2]])
    stats = db.stats()
    assert stats["keyframes"] == 3 and stats["map_points"] == 3
    assert stats["observations"] == 6 and stats["mean_observations_per_point"] == 2.0
    assert db.observation_counts().tolist() == [2, 3, 1]
    assert db.points_observed_by(torch.tensor([2])).tolist() == [1, 2]
    assert db.keyframes_observing(torch.tensor([20, -1])).tolist() == [2]
    assert db.keyframes_observing(torch.tensor([0, 20])).tolist() == [0, 1, 2]
    surfels, offsets, keyframes = db.surfel_keyframes()
    assert surfels.tolist() == [0, 10, 20]
    assert offsets.tolist() == [0, 2, 5, 6]
    assert keyframes.tolist() == [0, 1, 0, 1, 2, 2]


def test_keyframe_rows_and_best_observing_keyframes():
    db = make_database([[0, 1], [0, 1, 2], [2]])  # keypoints on surfels (0, 10), (0, 10), (10, 20)
    assert db.keyframe_rows(torch.tensor([2, 0])).tolist() == [6, 7, 8, 0, 1, 2]
    assert db.keyframe_rows(torch.tensor([], dtype=torch.int64)).tolist() == []
    surfels = torch.tensor([10, 20])  # one keypoint of keyframes 0 and 1, two of keyframe 2
    assert db.keyframes_observing(surfels, top_n=1).tolist() == [2]
    assert db.keyframes_observing(surfels, top_n=2).tolist() == [0, 2]
    assert db.keyframes_observing(surfels, top_n=5).tolist() == [0, 1, 2]


def test_appends_after_load_and_removal_match_a_fresh_database(tmp_path: Path):
    db = make_database([[0, 1], [0, 1, 2], [2]], global_dim=3)
    db.save(tmp_path / "db")
    loaded = VisualDatabase.load(tmp_path / "db")
    keypoints_before = db.keypoints
    copy_before = keypoints_before.clone()
    for target in (db, loaded):
        target.remove_points(torch.tensor([1]))
        k = target.add_keyframe(
            torch.eye(4, dtype=torch.float64),
            CAMERA,
            torch.ones(2, 2),
            torch.ones(2, 4),
            torch.ones(2),
            global_descriptor=torch.ones(3),
        )
        ids = target.add_points(torch.zeros(1, 3), torch.ones(1, 4), torch.tensor([7]))
        target.add_observations(k, torch.tensor([1]), ids)
    assert_same(db, loaded)
    assert torch.equal(keypoints_before, copy_before)  # appends write past its end only
    assert db.keypoint_points[-2:].tolist() == [-1, 2]


def test_covisibility_weights_count_shared_points():
    db = make_database([[0, 1], [0, 1, 2], [2], [1, 2], [3]])
    expected = torch.tensor([[0, 2, 1, 0], [2, 0, 2, 0], [1, 2, 0, 0], [0, 0, 0, 0]])
    assert torch.equal(db.covisibility().to_dense(), expected)
    keyframes, weights = db.covisible_keyframes(1)
    assert keyframes.tolist() == [0, 2] and weights.tolist() == [2, 2]
    assert db.covisible_keyframes(2, top_n=1)[0].tolist() == [1]
    assert len(db.covisible_keyframes(3)[0]) == 0


def test_remove_points_compacts_ids():
    db = make_database([[0, 1], [0, 1, 2], [2]])
    position2 = db.point_positions[2].clone()
    db.remove_points(torch.tensor([1]))
    assert db.num_points == 2
    assert torch.equal(db.point_positions[1], position2)
    assert db.observation_counts().tolist() == [2, 1]
    assert db.keypoint_points.max() == 1


def test_remove_keyframes_drops_keypoints_and_orphan_points():
    db = make_database([[0, 1], [0, 1, 2], [2], [0]])
    kept_keypoints = db.keypoints[db.keyframe_slice(2)].clone()
    db.remove_keyframes(torch.tensor([0]))
    assert db.num_keyframes == 2 and db.num_points == 3  # point 3 lost its only observer
    assert torch.equal(db.keypoints[db.keyframe_slice(1)], kept_keypoints)
    assert db.keypoint_offsets.tolist() == [0, 3, 6]
    assert db.neighbour_offsets[-1] == len(db.neighbour_surfels) == 4
    assert db.observation_counts().tolist() == [1, 2, 1]


def test_fused_descriptor_is_the_most_central_observation():
    db = VisualDatabase(2)
    ids = db.add_points(torch.zeros(1, 3), torch.zeros(1, 2), torch.tensor([0]))
    descriptors = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.1, 0.0], [5.0, 0.0]])
    for k, desc in enumerate(descriptors):
        db.add_keyframe(torch.eye(4), CAMERA, torch.zeros(1, 2), desc[None], torch.ones(1))
        db.add_observations(k, torch.tensor([0]), ids)
    db.fuse_descriptors(ids)
    # Median distances to the others: 1.1, 1.0, 1.1, 4.0.
    assert torch.equal(db.point_descriptors[0], descriptors[1])
    db.remove_keyframes(torch.tensor([1]))
    db.fuse_descriptors(ids)
    # Now 1.1, 1.1, 3.9: ties go to the earlier observation.
    assert torch.equal(db.point_descriptors[0], descriptors[0])


def test_binary_descriptors_fuse_with_hamming():
    db = VisualDatabase(1, descriptor_dtype=torch.uint8)
    ids = db.add_points(torch.zeros(1, 3), torch.zeros(1, 1, dtype=torch.uint8), torch.tensor([0]))
    for k, byte in enumerate([0b0000, 0b0001, 0b0011, 0b1111_0000]):
        desc = torch.tensor([[byte]], dtype=torch.uint8)
        db.add_keyframe(torch.eye(4), CAMERA, torch.zeros(1, 2), desc, torch.ones(1))
        db.add_observations(k, torch.tensor([0]), ids)
    db.fuse_descriptors(ids)
    assert db.metric == "hamming" and int(db.point_descriptors[0, 0]) == 0b0001


def test_a_point_cannot_be_observed_twice_by_one_keyframe():
    db = make_database([[0], [0]])
    with pytest.raises(ValueError, match="observed twice"):
        db.add_observations(0, torch.tensor([1]), torch.tensor([0]))


def test_save_load_round_trip_is_exact(tmp_path: Path):
    db = make_database([[0, 1], [0, 1, 2], [2]], global_dim=3)
    db.save(tmp_path / "db")
    assert_same(db, VisualDatabase.load(tmp_path / "db"))
    db.remove_keyframes(torch.tensor([1]))
    db.save(tmp_path / "db")  # overwrite
    assert_same(db, VisualDatabase.load(tmp_path / "db"))
    meta = json.loads((tmp_path / "db" / "database.json").read_text())
    assert meta["format_version"] == 1 and meta["counts"]["keyframes"] == 2


def test_empty_database_round_trip(tmp_path: Path):
    db = VisualDatabase(32, descriptor_dtype=torch.uint8)
    db.save(tmp_path / "db")
    assert_same(db, VisualDatabase.load(tmp_path / "db"))


@pytest.fixture()
def saved(tmp_path: Path) -> Path:
    make_database([[0, 1], [0, 1, 2], [2]]).save(tmp_path / "db")
    return tmp_path / "db"


def test_missing_database_raises_file_not_found(tmp_path: Path, saved: Path):
    with pytest.raises(FileNotFoundError, match="database.json"):
        VisualDatabase.load(tmp_path / "nothing")
    (saved / "arrays.npz").unlink()
    with pytest.raises(FileNotFoundError, match="arrays.npz"):
        VisualDatabase.load(saved)


def test_truncated_archive_raises_value_error(saved: Path):
    npz = saved / "arrays.npz"
    npz.write_bytes(npz.read_bytes()[:200])
    with pytest.raises(ValueError, match="arrays.npz"):
        VisualDatabase.load(saved)


def test_missing_array_raises_value_error(saved: Path):
    npz = saved / "arrays.npz"
    with np.load(npz) as archive:
        arrays = {name: archive[name] for name in archive.files if name != "sizes"}
    np.savez(npz, **arrays)
    with pytest.raises(ValueError, match=r"arrays.npz.*missing arrays \['sizes'\]"):
        VisualDatabase.load(saved)


def test_inconsistent_shapes_raise_value_error(saved: Path):
    npz = saved / "arrays.npz"
    with np.load(npz) as archive:
        arrays = {name: archive[name] for name in archive.files}
    arrays["sizes"] = arrays["sizes"][:-1]
    np.savez(npz, **arrays)
    with pytest.raises(ValueError, match="arrays.npz.*sizes"):
        VisualDatabase.load(saved)


def test_wrong_format_version_raises_value_error(saved: Path):
    meta_path = saved / "database.json"
    meta = json.loads(meta_path.read_text())
    meta["format_version"] = 99
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="database.json.*format_version 99"):
        VisualDatabase.load(saved)


def test_foreign_files_raise_value_error(saved: Path):
    npz = saved / "arrays.npz"
    np.savez(npz, points=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="arrays.npz.*missing arrays"):
        VisualDatabase.load(saved)
    with zipfile.ZipFile(npz, "w") as archive:
        archive.writestr("readme.txt", "hello")
    with pytest.raises(ValueError, match="arrays.npz"):
        VisualDatabase.load(saved)
    (saved / "database.json").write_text('{"kind": "something-else"}')
    with pytest.raises(ValueError, match="database.json.*not a diffloc visual database"):
        VisualDatabase.load(saved)
    (saved / "database.json").write_text("not json")
    with pytest.raises(ValueError, match="database.json.*not valid JSON"):
        VisualDatabase.load(saved)


def test_bad_inputs_are_rejected():
    db = VisualDatabase(4)
    with pytest.raises(ValueError, match="descriptors must be"):
        db.add_points(torch.zeros(1, 3), torch.zeros(1, 4, dtype=torch.uint8), torch.zeros(1))
    with pytest.raises(ValueError, match="T_wc"):
        nan_pose = torch.full((4, 4), float("nan"))
        db.add_keyframe(nan_pose, CAMERA, torch.zeros(1, 2), torch.zeros(1, 4), torch.ones(1))
    with pytest.raises(ValueError, match="metric"):
        VisualDatabase(4, metric="hamming")
