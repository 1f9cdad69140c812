"""diffloc's dataset folder format: SequenceWriter, read_sequence, SequenceData and errors."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import pose_from_translation_quaternion
from diffloc.io.atomic import atomic_directory
from diffloc.io.calib import Calibration
from diffloc.io.dataset import (
    SequenceWriter,
    map_paths,
    read_dataset_info,
    read_sequence,
    write_dataset_info,
)
from diffloc.io.ply import write_point_cloud
from diffloc.io.sequence import SequenceData

W, H, N, M = 16, 12, 4, 3


def random_poses(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return pose_from_translation_quaternion(
        torch.randn(n, 3, generator=g, dtype=torch.float64),
        torch.randn(n, 4, generator=g, dtype=torch.float64),
    )


def make_calib() -> Calibration:
    camera = PinholeCamera.from_fov(
        W, H, 1.2, distortion=torch.tensor([0.01, -0.002, 0.0003, 0.0001], dtype=torch.float64)
    )
    return Calibration(
        camera=camera,
        depth_scale=1000.0,
        T_body_camera=random_poses(1, 5)[0],
        T_body_lidar=random_poses(1, 6)[0],
        rig_urdf="<robot/>",
        lidar={"channels": 8},
    )


def make_data(seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "times": 100.0 + np.arange(N) * 0.1,
        "T_wc": random_poses(N, seed),
        "rgb": [
            torch.from_numpy(rng.integers(0, 256, (3, H, W)).astype(np.float32) / 255)
            for _ in range(N)
        ],
        "depth": [torch.from_numpy(rng.integers(0, 20000, (H, W)) / 1000.0) for _ in range(N)],
        "sweep_times": 100.0 + np.arange(M) * 0.15,
        "T_wl": random_poses(M, seed + 100),
        "points": [rng.standard_normal((50 + k, 3)).astype(np.float32) for k in range(M)],
    }


def write_dataset(root: Path, data: dict, depth: bool = True) -> None:
    with SequenceWriter(root / "seq0", make_calib()) as writer:
        for i in range(N):
            writer.add_frame(
                data["times"][i],
                data["T_wc"][i],
                data["rgb"][i],
                data["depth"][i] if depth else None,
            )
        for j in range(M):
            writer.add_sweep(data["sweep_times"][j], data["T_wl"][j], data["points"][j])
    write_dataset_info(root, ["seq0"], {"generator": "test"})


def test_sequence_round_trip(tmp_path: Path):
    data = make_data()
    write_dataset(tmp_path, data)
    info = read_dataset_info(tmp_path)
    assert info["sequences"] == ["seq0"] and info["generator"] == "test"
    seq = read_sequence(tmp_path, "seq0")
    assert len(seq) == N and seq.name == "seq0"
    np.testing.assert_allclose(seq.timestamps, data["times"], rtol=0, atol=1e-9)
    torch.testing.assert_close(seq.T_wc, data["T_wc"], rtol=0, atol=1e-9)
    calib = make_calib()
    assert seq.camera.fx.item() == calib.camera.fx.item()
    assert torch.equal(seq.camera.distortion, calib.camera.distortion)
    assert torch.equal(seq.T_body_camera, calib.T_body_camera)
    assert torch.equal(seq.T_body_lidar, calib.T_body_lidar)
    assert seq.depth_scale == 1000.0
    for i in range(N):
        assert torch.equal(seq.load_rgb(i), data["rgb"][i])
        torch.testing.assert_close(
            seq.load_depth(i), data["depth"][i].float()[None], rtol=0, atol=1e-6
        )
    np.testing.assert_allclose(seq.lidar_timestamps, data["sweep_times"], rtol=0, atol=1e-9)
    torch.testing.assert_close(seq.T_wl, data["T_wl"], rtol=0, atol=1e-9)
    for j in range(M):
        points = seq.load_lidar(j)
        assert points.dtype == torch.float32
        assert torch.equal(points, torch.from_numpy(data["points"][j]))
    assert [p.name for p in seq.rgb_paths] == [f"{i:06d}.png" for i in range(N)]


def test_sequence_without_depth(tmp_path: Path):
    write_dataset(tmp_path, make_data(), depth=False)
    seq = read_sequence(tmp_path, "seq0")
    assert seq.depth_paths is None
    with pytest.raises(ValueError, match="no depth"):
        seq.load_depth(0)


def test_map_paths(tmp_path: Path):
    write_dataset(tmp_path, make_data())
    assert map_paths(tmp_path) == {}
    write_point_cloud(tmp_path / "map" / "lidar_map.ply", np.zeros((3, 3)))
    assert map_paths(tmp_path) == {"lidar_map": tmp_path / "map" / "lidar_map.ply"}


def test_count_mismatch_names_the_folder(tmp_path: Path):
    write_dataset(tmp_path, make_data())
    (tmp_path / "seq0" / "rgb" / "000002.png").unlink()
    with pytest.raises(ValueError, match=r"seq0/rgb.*3 \.png files.*poses.txt has 4"):
        read_sequence(tmp_path, "seq0")


def test_depth_and_lidar_count_mismatch(tmp_path: Path):
    write_dataset(tmp_path, make_data())
    (tmp_path / "seq0" / "depth" / "000003.png").unlink()
    with pytest.raises(ValueError, match="seq0/depth"):
        read_sequence(tmp_path, "seq0")
    shutil.rmtree(tmp_path / "seq0" / "depth")
    (tmp_path / "seq0" / "lidar" / "000000.ply").unlink()
    with pytest.raises(ValueError, match="seq0/lidar"):
        read_sequence(tmp_path, "seq0")


def test_unexpected_frame_names(tmp_path: Path):
    write_dataset(tmp_path, make_data())
    rgb = tmp_path / "seq0" / "rgb"
    (rgb / "000003.png").rename(rgb / "frame_3.png")
    with pytest.raises(ValueError, match="frame_3.png"):
        read_sequence(tmp_path, "seq0")


@pytest.mark.parametrize("missing", ["calib.yaml", "poses.txt", "rgb", "lidar/poses.txt"])
def test_missing_files_are_named(tmp_path: Path, missing: str):
    write_dataset(tmp_path, make_data())
    target = tmp_path / "seq0" / missing
    shutil.rmtree(target) if target.is_dir() else target.unlink()
    with pytest.raises(FileNotFoundError, match=missing.split("/")[-1]):
        read_sequence(tmp_path, "seq0")


def test_dataset_json_errors(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="dataset.json"):
        read_dataset_info(tmp_path)
    write_dataset(tmp_path, make_data())
    with pytest.raises(ValueError, match="no sequence 'other'"):
        read_sequence(tmp_path, "other")
    info = json.loads((tmp_path / "dataset.json").read_text())
    (tmp_path / "dataset.json").write_text(json.dumps({**info, "format_version": 9}))
    with pytest.raises(ValueError, match="dataset.json.*format_version 9"):
        read_sequence(tmp_path, "seq0")
    (tmp_path / "dataset.json").write_text(json.dumps({**info, "kind": "other"}))
    with pytest.raises(ValueError, match="kind"):
        read_dataset_info(tmp_path)
    (tmp_path / "dataset.json").write_text("{not json")
    with pytest.raises(ValueError, match="dataset.json.*JSON"):
        read_dataset_info(tmp_path)
    with pytest.raises(FileNotFoundError, match="seq1"):
        write_dataset_info(tmp_path, ["seq0", "seq1"])
        read_sequence(tmp_path, "seq1")


def test_malformed_poses_file_is_reported(tmp_path: Path):
    write_dataset(tmp_path, make_data())
    poses = tmp_path / "seq0" / "poses.txt"
    lines = poses.read_text().splitlines()
    lines[1] = lines[1].replace(" ", " x", 1)
    poses.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match="poses.txt, line 2: not a number"):
        read_sequence(tmp_path, "seq0")


def test_writer_rejects_bad_frames(tmp_path: Path):
    data = make_data()
    writer = SequenceWriter(tmp_path / "seq", make_calib())
    with pytest.raises(ShapeError, match="rgb"):
        writer.add_frame(0.0, data["T_wc"][0], torch.zeros(3, H + 1, W))
    writer.add_frame(0.0, data["T_wc"][0], data["rgb"][0], data["depth"][0])
    with pytest.raises(ValueError, match="increase"):
        writer.add_frame(0.0, data["T_wc"][1], data["rgb"][1], data["depth"][1])
    with pytest.raises(ValueError, match="every frame has a depth"):
        writer.add_frame(1.0, data["T_wc"][1], data["rgb"][1], None)
    with pytest.raises(ValueError, match="rigid"):
        writer.add_frame(1.0, 2 * data["T_wc"][1], data["rgb"][1], data["depth"][1])
    writer.close()
    with pytest.raises(RuntimeError, match="closed"):
        writer.add_frame(2.0, data["T_wc"][1], data["rgb"][1], data["depth"][1])
    with pytest.raises(FileExistsError, match="not empty"):
        SequenceWriter(tmp_path / "seq", make_calib())
    with pytest.raises(ValueError, match="at least one frame"):
        SequenceWriter(tmp_path / "empty", make_calib()).close()


def test_failure_midway_leaves_nothing(tmp_path: Path):
    data = make_data()
    with (
        pytest.raises(RuntimeError, match="renderer crashed"),
        atomic_directory(tmp_path / "dataset") as tmp,
    ):
        writer = SequenceWriter(tmp / "seq0", make_calib())
        writer.add_frame(0.0, data["T_wc"][0], data["rgb"][0], data["depth"][0])
        raise RuntimeError("renderer crashed")
    assert list(tmp_path.iterdir()) == []


def test_sequence_data_validates_lengths():
    camera = make_calib().camera
    T = random_poses(3, 0)
    with pytest.raises(ValueError, match="3 timestamps but 2 rgb_paths"):
        SequenceData("s", np.arange(3.0), T, camera, [Path("a"), Path("b")])
    with pytest.raises(ValueError, match="depth_paths"):
        SequenceData("s", np.arange(3.0), T, camera, ["a", "b", "c"], depth_paths=["a"])
    with pytest.raises(ValueError, match="poses T_wc"):
        SequenceData("s", np.arange(2.0), T, camera, ["a", "b"])
    with pytest.raises(ValueError, match="lidar_timestamps"):
        SequenceData(
            "s",
            np.arange(3.0),
            T,
            camera,
            ["a", "b", "c"],
            lidar_paths=["l"],
            lidar_timestamps=np.zeros(2),
            T_wl=T[:1],
        )
    with pytest.raises(ValueError, match="no poses T_wl"):
        SequenceData(
            "s",
            np.arange(3.0),
            T,
            camera,
            ["a", "b", "c"],
            lidar_paths=["l"],
            lidar_timestamps=np.zeros(1),
        )
    with pytest.raises(ValueError, match="NaN"):
        SequenceData("s", np.array([0.0, np.nan, 1.0]), T, camera, ["a", "b", "c"])
