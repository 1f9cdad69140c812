"""EuRoC ASL layout: exact write/read round trip, real sensor.yaml, interpolation, errors."""

from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest
import torch

from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import invert, pose_from_translation_quaternion
from diffloc.io.euroc import read_euroc, write_euroc
from diffloc.io.images import read_rgb
from diffloc.io.ply import read_point_cloud
from diffloc.io.trajectory import interpolate_poses

W, H, N = 16, 12, 6

# cam0/sensor.yaml as shipped with the EuRoC Vicon-room sequences.
REAL_SENSOR_YAML = """\
# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""


def random_poses(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return pose_from_translation_quaternion(
        torch.randn(n, 3, generator=g, dtype=torch.float64),
        torch.randn(n, 4, generator=g, dtype=torch.float64),
    )


def edit_line(text: str, index: int, change) -> str:
    lines = text.splitlines()
    lines[index] = change(lines[index])
    return "\n".join(lines) + "\n"


def make_sequence(seed: int = 0, start: float = 1403715273.25, step: float = 0.0625) -> dict:
    rng = np.random.default_rng(seed)
    camera = PinholeCamera(
        fx=torch.tensor(11.123456789, dtype=torch.float64),
        fy=torch.tensor(11.5, dtype=torch.float64),
        cx=torch.tensor(7.25, dtype=torch.float64),
        cy=torch.tensor(5.5, dtype=torch.float64),
        width=W,
        height=H,
        distortion=torch.tensor(
            [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05], dtype=torch.float64
        ),
    )
    return {
        # By default exactly representable in float64 and in integer nanoseconds.
        "times": start + np.arange(N) * step,
        "T_wc": random_poses(N, seed),
        "T_BS": random_poses(1, seed + 1)[0],
        "camera": camera,
        "images": [rng.integers(0, 256, (H, W, 3)).astype(np.uint8) for _ in range(N)],
        "points": rng.standard_normal((20, 3)).astype(np.float32),
    }


def write(tmp_path: Path, data: dict) -> Path:
    return write_euroc(
        tmp_path / "V1_01_easy" / "mav0",
        data["times"],
        data["T_wc"],
        data["camera"],
        data["images"],
        T_body_camera=data["T_BS"],
        points_world=data["points"],
    )


@pytest.mark.parametrize(("start", "step"), [(1403715273.25, 0.0625), (1403636579.763555, 0.05)])
def test_round_trip_is_exact(tmp_path: Path, start: float, step: float):
    data = make_sequence(start=start, step=step)
    mav0 = write(tmp_path, data)
    assert (mav0 / "cam0" / "data.csv").read_text().startswith("#timestamp [ns],filename\n")
    gt_lines = (mav0 / "state_groundtruth_estimate0" / "data.csv").read_text().splitlines()
    assert len(gt_lines[1].split(",")) == 17
    seq = read_euroc(tmp_path / "V1_01_easy")  # the folder holding mav0 works too
    assert seq.name == "V1_01_easy" and len(seq) == N and seq.info["dropped_images"] == 0
    np.testing.assert_array_equal(seq.timestamps, data["times"])
    torch.testing.assert_close(seq.T_wc, data["T_wc"], rtol=0, atol=1e-9)
    assert torch.equal(seq.T_body_camera, data["T_BS"])
    for key in ("fx", "fy", "cx", "cy"):
        assert getattr(seq.camera, key).item() == getattr(data["camera"], key).item()
    assert torch.equal(seq.camera.distortion, data["camera"].distortion)
    assert (seq.camera.width, seq.camera.height) == (W, H)
    for i in range(N):
        expected = torch.from_numpy(data["images"][i].transpose(2, 0, 1).astype(np.float32) / 255)
        assert torch.equal(seq.load_rgb(i), expected)
        assert torch.equal(read_rgb(seq.rgb_paths[i]), expected)
    assert seq.depth_paths is None and seq.lidar_paths == []
    np.testing.assert_array_equal(read_point_cloud(seq.pointcloud_path).points, data["points"])
    ns = seq.info["timestamps_ns"]
    assert ns.dtype == np.int64
    exact = [int((Decimal(t) * 10**9).to_integral_value()) for t in data["times"].tolist()]
    np.testing.assert_array_equal(ns, exact)  # nearest ns of the exact float64 value


def test_real_sensor_yaml(tmp_path: Path):
    data = make_sequence()
    mav0 = write(tmp_path, data)
    (mav0 / "cam0" / "sensor.yaml").write_text(REAL_SENSOR_YAML)
    seq = read_euroc(mav0)
    assert (seq.camera.width, seq.camera.height) == (752, 480)
    assert [
        seq.camera.fx.item(),
        seq.camera.fy.item(),
        seq.camera.cx.item(),
        seq.camera.cy.item(),
    ] == [458.654, 457.296, 367.215, 248.375]
    assert seq.camera.distortion.tolist() == [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
    assert seq.T_body_camera[0, 1].item() == -0.999880929698
    # T_wc = T_wb @ T_BS with the body poses that were written.
    T_wb = data["T_wc"] @ invert(data["T_BS"])
    torch.testing.assert_close(seq.T_wc, T_wb @ seq.T_body_camera, rtol=0, atol=1e-9)


def test_interpolation_and_dropped_images(tmp_path: Path):
    data = make_sequence()
    mav0 = write(tmp_path, data)
    gt = mav0 / "state_groundtruth_estimate0" / "data.csv"
    lines = gt.read_text().splitlines()
    # Remove the first and last ground-truth rows (2 images fall outside) and an inner one.
    gt.write_text("\n".join([lines[0]] + lines[2:3] + lines[4:-1]) + "\n")
    seq = read_euroc(mav0)
    assert seq.info["dropped_images"] == 2 and len(seq) == N - 2
    T_wb = data["T_wc"] @ invert(data["T_BS"])
    t = data["times"] - data["times"][0]
    expected_wb = interpolate_poses(t[[1, 3, 4]], T_wb[[1, 3, 4]], t[1:5])
    torch.testing.assert_close(seq.T_wc, expected_wb @ data["T_BS"], rtol=0, atol=1e-9)
    torch.testing.assert_close(seq.T_wc[[0, 2, 3]], data["T_wc"][[1, 3, 4]], rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    ("file", "edit", "error", "message"),
    [
        (
            "state_groundtruth_estimate0/data.csv",
            lambda s: edit_line(s, 1, lambda r: r[:40]),
            ValueError,
            r"data.csv, line 2: expected at least 8 columns",
        ),
        ("state_groundtruth_estimate0/data.csv", lambda s: s + "1,2,3\n", ValueError, "line 8"),
        (
            "cam0/data.csv",
            lambda s: s.replace("\n1", "\n1.5", 1),
            ValueError,
            "line 2: timestamp.*not an integer",
        ),
        (
            "cam0/sensor.yaml",
            lambda s: s.replace("radial-tangential", "equidistant"),
            ValueError,
            "distortion_model",
        ),
        (
            "cam0/sensor.yaml",
            lambda s: s.replace("resolution: [16, 12]", ""),
            ValueError,
            "'resolution' is missing",
        ),
        (
            "cam0/sensor.yaml",
            lambda s: s.replace("[11.123456789", "[-11.1"),
            ValueError,
            "positive focal",
        ),
    ],
)
def test_malformed_files(tmp_path: Path, file, edit, error, message):
    mav0 = write(tmp_path, make_sequence())
    path = mav0 / file
    path.write_text(edit(path.read_text()))
    with pytest.raises(error, match=message):
        read_euroc(mav0)


@pytest.mark.parametrize(
    "missing",
    ["cam0/sensor.yaml", "cam0/data.csv", "state_groundtruth_estimate0/data.csv", "image"],
)
def test_missing_files(tmp_path: Path, missing: str):
    mav0 = write(tmp_path, make_sequence())
    target = sorted((mav0 / "cam0" / "data").iterdir())[2] if missing == "image" else mav0 / missing
    target.unlink()
    with pytest.raises(FileNotFoundError, match=target.name):
        read_euroc(mav0)


def test_write_refuses_bad_input(tmp_path: Path):
    data = make_sequence()
    with pytest.raises(ValueError, match="images"):
        write_euroc(
            tmp_path / "mav0", data["times"], data["T_wc"], data["camera"], data["images"][:-1]
        )
    with pytest.raises(ValueError, match="increasing"):
        write_euroc(tmp_path / "mav0", np.zeros(N), data["T_wc"], data["camera"], data["images"])
    write(tmp_path, data)
    with pytest.raises(FileExistsError):
        write(tmp_path, data)
