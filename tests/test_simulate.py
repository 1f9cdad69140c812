"""End-to-end simulation of tiny datasets: layout, determinism, caching, atomicity, errors."""

import json

import numpy as np
import pytest
import torch

from diffloc.io.dataset import read_dataset_info, read_sequence
from diffloc.render.raycast import MeshRaycaster
from diffloc.sim import dataset as sim_dataset
from diffloc.sim.dataset import DatasetSimulator, simulate_dataset
from diffloc.sim.placement import check_free_space
from diffloc.sim.scene import generate_world
from tests.conftest import TINY, digests, scene_config

SEQUENCES = ["mapping", "query_same", "query_lane", "query_reverse", "changed"]


def test_dataset_layout(tiny_indoor_dataset):
    root = tiny_indoor_dataset
    info = json.loads((root / "dataset.json").read_text())
    assert info["format_version"] == 1 and info["sequences"] == SEQUENCES
    for name in SEQUENCES:
        seq = root / name
        for item in ("rgb", "depth", "lidar", "poses.txt", "calib.yaml", "lidar/poses.txt"):
            assert (seq / item).exists(), seq / item
        assert len(list((seq / "rgb").glob("*.png"))) == 5
        assert len(list((seq / "lidar").glob("*.ply"))) >= 1
    for item in ("lidar_map.ply", "tls_map.ply", "mesh/scene.obj", "mesh_changed/scene.obj"):
        assert (root / "map" / item).exists()
    assert (root / "preview.png").stat().st_size > 10_000


def test_dataset_records_how_far_each_sequence_is_from_the_mapping_run(tiny_indoor_dataset):
    info = read_dataset_info(tiny_indoor_dataset)
    offsets = info["nearest_mapping_pose"]
    assert set(offsets) == set(info["sequences"])
    assert offsets["mapping"]["distance_p90_m"] == 0.0
    for name in ("query_same", "query_lane", "query_reverse", "changed"):
        entry = offsets[name]
        assert 0.0 < entry["distance_median_m"] <= entry["distance_p90_m"]
        assert 0.0 < entry["angle_median_deg"] <= entry["angle_p90_deg"] <= 180.0
    assert offsets["query_reverse"]["angle_median_deg"] > 150.0


def test_sequences_read_back_consistently(tiny_indoor_dataset):
    seq = read_sequence(tiny_indoor_dataset, "mapping")
    assert len(seq) == 5 and seq.camera.width == 160 and seq.camera.height == 120
    rgb = seq.load_rgb(0)
    depth = seq.load_depth(0)
    assert rgb.shape == (3, 120, 160) and depth.shape == (1, 120, 160)
    assert rgb.std() > 0.05, "images must be textured"
    assert (depth > 0).float().mean() > 0.99, "indoor views are closed: depth everywhere"
    # Depth PNG agrees with a fresh ray cast at the stored pose (1 mm quantisation).
    world = generate_world("indoor", 0, scene_config(TINY).layout)
    caster = MeshRaycaster(world.mesh)
    pixels = torch.tensor([[80.0, 60.0], [10.0, 10.0], [150.0, 100.0]], dtype=torch.float64)
    rays = seq.camera.to(torch.float64).unproject(pixels)
    T = seq.T_wc[0]
    directions = (rays / rays.norm(dim=1, keepdim=True)) @ T[:3, :3].T
    hits = caster.cast(T[:3, 3].expand(3, 3), directions)
    expected = hits.distance.double() * (rays[:, 2] / rays.norm(dim=1))
    got = depth[0, pixels[:, 1].long(), pixels[:, 0].long()].double()
    torch.testing.assert_close(got, expected, atol=1.5e-3, rtol=0)


def test_same_seed_gives_byte_identical_dataset(tiny_indoor_dataset, tmp_path):
    again = simulate_dataset(scene_config(TINY), tmp_path / "again", show_progress=False)
    assert digests(again) == digests(tiny_indoor_dataset)


def test_other_seed_gives_other_layout(tmp_path):
    a = generate_world("indoor", 0, scene_config(TINY).layout)
    b = generate_world("indoor", 1, scene_config(TINY).layout)
    assert a.mesh.vertices.shape != b.mesh.vertices.shape or not np.array_equal(
        a.mesh.vertices, b.mesh.vertices
    )


def test_existing_dataset_is_reused_and_other_config_refused(tiny_indoor_dataset):
    before = {p: p.stat().st_mtime_ns for p in tiny_indoor_dataset.rglob("*")}
    simulate_dataset(scene_config(TINY), tiny_indoor_dataset, show_progress=False)
    assert {p: p.stat().st_mtime_ns for p in tiny_indoor_dataset.rglob("*")} == before
    with pytest.raises(FileExistsError, match="overwrite"):
        simulate_dataset(scene_config(TINY + ["scene.seed=5"]), tiny_indoor_dataset)
    assert {p: p.stat().st_mtime_ns for p in tiny_indoor_dataset.rglob("*")} == before


def test_failure_midway_leaves_nothing(tmp_path, monkeypatch):
    def broken_sweep(*args, **kwargs):
        raise RuntimeError("lidar broke")

    monkeypatch.setattr(sim_dataset, "simulate_sweep", broken_sweep)
    with pytest.raises(RuntimeError, match="lidar broke"):
        simulate_dataset(scene_config(TINY), tmp_path / "out", show_progress=False)
    assert [p.name for p in tmp_path.iterdir()] == [".out.diffloc.lock"]  # its lock file only


def test_outdoor_dataset_simulates(tmp_path):
    cfg = scene_config(TINY + ["scene=outdoor", "scene.trajectory.max_frames=3"])
    root = simulate_dataset(cfg, tmp_path / "outdoor", show_progress=False)
    seq = read_sequence(root, "query_lane")
    assert len(seq) == 3
    assert seq.load_rgb(0).std() > 0.05


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("scene.camera.width=0", "width"),
        ("scene.camera.height=-4", "height"),
        ("scene.camera.hfov_deg=0", "hfov"),
        ("scene.map.lidar_sequence=nowhere", "lidar_sequence"),
        ("scene.sequences.1.frame_rate_hz=-1", "sequences.1.frame_rate_hz"),
        ("scene.sequences.2.speed_mps=-0.5", "sequences.2.speed_mps"),
        ("scene.sequences.3.start_offset_m=nan", "sequences.3.start_offset_m"),
    ],
)
def test_bad_config_values_are_refused_before_writing(tmp_path, override, message):
    with pytest.raises(ValueError, match=message):
        simulate_dataset(scene_config(TINY + [override]), tmp_path / "out", show_progress=False)
    assert not (tmp_path / "out").exists()


def test_non_integer_seed_through_the_api():
    cfg = scene_config(TINY)
    cfg.seed = 1.5
    with pytest.raises(ValueError, match="seed"):
        DatasetSimulator(cfg, show_progress=False)


def test_unknown_scene_kind():
    with pytest.raises(ValueError, match="indoor"):
        generate_world("moon_base", 0, scene_config(TINY).layout)


def test_camera_inside_a_wall_or_outside_the_world_is_refused():
    world = generate_world("indoor", 0, scene_config(TINY).layout)
    caster = MeshRaycaster(world.mesh)
    start = torch.from_numpy(world.route[:1]).double() + torch.tensor([0.0, 0.0, 1.5])
    check_free_space(caster, world.bounds, start)  # a route point is free
    outside = torch.from_numpy(world.bounds[1]).double()[None] + 5.0
    with pytest.raises(ValueError, match="outside the world"):
        check_free_space(caster, world.bounds, outside)
    # The middle of the lowest floor slab is inside a solid.
    faces = world.mesh.vertices[world.mesh.triangles[world.mesh.object_ids == 0]]
    inside = torch.tensor([[*start[0, :2].tolist(), float(world.route[0, 2]) - 0.05]])
    with pytest.raises(ValueError, match="inside a wall|from a surface"):
        check_free_space(caster, world.bounds, inside.double())
    assert len(faces)


def test_empty_map_is_refused():
    world = generate_world("indoor", 0, scene_config(TINY).layout)
    empty = world.mesh.select_faces(np.zeros(world.mesh.num_faces, dtype=bool))
    with pytest.raises(ValueError, match="empty"):
        MeshRaycaster(empty)
