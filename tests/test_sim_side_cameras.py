"""Side cameras of the simulated rig (scene.rig.side_camera_yaw_deg): layout, poses, and the
rest of the dataset unchanged."""

import json
import math

import numpy as np
import pytest
import torch

from diffloc.io.dataset import read_dataset_info, read_sequence
from diffloc.sim.dataset import simulate_dataset
from diffloc.sim.side_cameras import side_camera_extrinsic, side_sequence_names
from tests.conftest import TINY, digests, scene_config


def test_side_camera_extrinsic_known_answer():
    # The default front camera: optical z along body x, optical x along body -y, at x = 0.1.
    front = torch.tensor(
        [[0.0, 0.0, 1.0, 0.1], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0, 0, 0, 1]],
        dtype=torch.float64,
    )
    left = torch.tensor(
        [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.1], [0.0, -1.0, 0.0, 0.0], [0, 0, 0, 1]],
        dtype=torch.float64,
    )
    torch.testing.assert_close(side_camera_extrinsic(front, 90.0), left, atol=1e-12, rtol=0)
    right = side_camera_extrinsic(front, -90.0)
    torch.testing.assert_close(right[:3, 2], torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(right[:3, 3], torch.tensor([0.0, -0.1, 0.0], dtype=torch.float64))
    back = side_camera_extrinsic(front, 180.0)
    torch.testing.assert_close(back[:3, 2], torch.tensor([-1.0, 0.0, 0.0], dtype=torch.float64))


@pytest.mark.parametrize(
    ("yaws", "message"),
    [
        ([0.0], "front camera"),
        ([90.0, 90.0], "repeats"),
        ([200.0], r"\(-180, 180\]"),
        ([-180.0], r"\(-180, 180\]"),
        ([math.nan], "finite"),
        (["left"], "finite number"),
        ([True], "finite number"),
    ],
)
def test_bad_yaw_list_is_a_clear_error(yaws, message):
    with pytest.raises(ValueError, match=rf"side_camera_yaw_deg.*{message}"):
        side_sequence_names("mapping", yaws)


def test_bad_yaw_list_is_refused_before_writing(tmp_path):
    cfg = scene_config(TINY + ["scene.rig.side_camera_yaw_deg=[90,0]"])
    with pytest.raises(ValueError, match=r"side_camera_yaw_deg\[1\] is 0"):
        simulate_dataset(cfg, tmp_path / "out", show_progress=False)
    assert not (tmp_path / "out").exists()


def test_side_sequence_clashing_with_a_simulated_one_is_refused(tmp_path):
    cfg = scene_config(TINY + ["scene.rig.side_camera_yaw_deg=[90]"])
    cfg.sequences[1].name = "mapping_left"
    with pytest.raises(ValueError, match="mapping_left"):
        simulate_dataset(cfg, tmp_path / "out", show_progress=False)


def test_side_sequences_are_standard_sequences(tiny_indoor_side_dataset):
    info = read_dataset_info(tiny_indoor_side_dataset)
    assert info["sequences"][-2:] == ["mapping_left", "mapping_right"]
    assert info["side_cameras"] == {
        "mapping_left": {"of": "mapping", "yaw_deg": 90.0},
        "mapping_right": {"of": "mapping", "yaw_deg": -90.0},
    }
    front = read_sequence(tiny_indoor_side_dataset, "mapping")
    T_wb = front.T_wc @ torch.linalg.inv(front.T_body_camera)
    for name, yaw in (("mapping_left", 90.0), ("mapping_right", -90.0)):
        side = read_sequence(tiny_indoor_side_dataset, name)
        assert not (tiny_indoor_side_dataset / name / "lidar").exists() and side.lidar_paths == []
        np.testing.assert_array_equal(side.timestamps, front.timestamps)
        assert side.camera.width == front.camera.width and side.camera.fx == front.camera.fx
        extrinsic = side_camera_extrinsic(front.T_body_camera, yaw)
        torch.testing.assert_close(side.T_body_camera, extrinsic, atol=1e-12, rtol=0)
        torch.testing.assert_close(side.T_wc, T_wb @ extrinsic, atol=1e-6, rtol=0)
        # The optical axis is the body's y axis (left) or -y (right).
        sign = 1.0 if yaw > 0 else -1.0
        torch.testing.assert_close(side.T_wc[:, :3, 2], sign * T_wb[:, :3, 1], atol=1e-6, rtol=0)
        rgb = side.load_rgb(0)
        assert rgb.shape == front.load_rgb(0).shape and rgb.std() > 0.05
        assert not torch.equal(rgb, front.load_rgb(0))
        assert side.info["calib"].rig_urdf is not None


def test_rest_of_the_dataset_is_that_of_the_same_seed_without_side_cameras(
    tiny_indoor_side_dataset, tiny_indoor_dataset
):
    without = digests(tiny_indoor_dataset)
    with_sides = digests(tiny_indoor_side_dataset)
    sides = {k for k in with_sides if k.startswith(("mapping_left/", "mapping_right/"))}
    assert sides and set(with_sides) - sides == set(without)
    differing = sorted(k for k in without if with_sides[k] != without[k])
    assert differing == ["dataset.json"]
    info = json.loads((tiny_indoor_side_dataset / "dataset.json").read_text())
    plain = json.loads((tiny_indoor_dataset / "dataset.json").read_text())
    assert info["config"]["rig"].pop("side_camera_yaw_deg") == [90.0, -90.0]
    assert "side_camera_yaw_deg" not in plain["config"]["rig"]
    info["sequences"] = info["sequences"][:-2]
    del info["side_cameras"]
    assert info == plain
