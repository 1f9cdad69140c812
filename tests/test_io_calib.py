"""calib.yaml: exact round trip and one test per validation rule."""

from pathlib import Path

import pytest
import torch
import yaml

from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import pose_from_translation_quaternion
from diffloc.io.calib import Calibration, read_calib, write_calib

URDF = '<robot name="rig">\n  <link name="body"/>\n  <link name="camera"/>\n</robot>\n'


def make_calib(distortion: bool = True) -> Calibration:
    camera = PinholeCamera(
        fx=torch.tensor(458.654321987, dtype=torch.float64),
        fy=torch.tensor(457.296, dtype=torch.float64),
        cx=torch.tensor(367.215, dtype=torch.float64),
        cy=torch.tensor(248.375, dtype=torch.float64),
        width=752,
        height=480,
        distortion=torch.tensor(
            [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05], dtype=torch.float64
        )
        if distortion
        else None,
    )
    g = torch.Generator().manual_seed(0)
    T_bc = pose_from_translation_quaternion(
        torch.randn(3, generator=g, dtype=torch.float64),
        torch.randn(4, generator=g, dtype=torch.float64),
    )
    T_bl = pose_from_translation_quaternion(
        torch.randn(3, generator=g, dtype=torch.float64),
        torch.randn(4, generator=g, dtype=torch.float64),
    )
    return Calibration(
        camera=camera,
        depth_scale=1000.0,
        T_body_camera=T_bc,
        T_body_lidar=T_bl,
        rig_urdf=URDF,
        lidar={"channels": 16, "fov_deg": [-15.0, 15.0], "name": "spinning", "noise_m": 0.01},
    )


def assert_same(a: Calibration, b: Calibration) -> None:
    for key in ("fx", "fy", "cx", "cy"):
        assert getattr(a.camera, key).item() == getattr(b.camera, key).item(), key
    assert (a.camera.width, a.camera.height) == (b.camera.width, b.camera.height)
    if a.camera.distortion is None:
        assert b.camera.distortion is None
    else:
        assert torch.equal(a.camera.distortion, b.camera.distortion)
    assert a.depth_scale == b.depth_scale
    for key in ("T_body_camera", "T_body_lidar"):
        x, y = getattr(a, key), getattr(b, key)
        assert (x is None and y is None) or torch.equal(x, y), key
    assert a.rig_urdf == b.rig_urdf and a.lidar == b.lidar


def test_round_trip_is_exact(tmp_path: Path):
    calib = make_calib()
    write_calib(tmp_path / "calib.yaml", calib)
    got = read_calib(tmp_path / "calib.yaml")
    assert_same(calib, got)
    assert got.camera.fx.dtype == torch.float64 and got.T_body_camera.dtype == torch.float64
    text = (tmp_path / "calib.yaml").read_text()
    write_calib(tmp_path / "again.yaml", got)
    assert (tmp_path / "again.yaml").read_text() == text


def test_round_trip_with_nulls(tmp_path: Path):
    calib = Calibration(camera=make_calib(distortion=False).camera, depth_scale=5000.0)
    write_calib(tmp_path / "calib.yaml", calib)
    data = yaml.safe_load((tmp_path / "calib.yaml").read_text())
    assert data["camera"]["distortion"] is None and data["lidar"] is None
    assert data["rig"] == {"T_body_camera": None, "T_body_lidar": None, "urdf": None}
    assert_same(calib, read_calib(tmp_path / "calib.yaml"))


def write_modified(tmp_path: Path, change) -> Path:
    write_calib(tmp_path / "calib.yaml", make_calib())
    data = yaml.safe_load((tmp_path / "calib.yaml").read_text())
    change(data)
    (tmp_path / "calib.yaml").write_text(yaml.safe_dump(data))
    return tmp_path / "calib.yaml"


def _set(path: list, value):
    def change(data):
        node = data
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value

    return change


def _delete(path: list):
    def change(data):
        node = data
        for key in path[:-1]:
            node = node[key]
        del node[path[-1]]

    return change


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (_delete(["camera", "fx"]), r"camera.*missing 'fx'"),
        (_delete(["depth_scale"]), "missing 'depth_scale'"),
        (_delete(["rig", "T_body_camera"]), r"rig.*missing 'T_body_camera'"),
        (_set(["camera", "width"], -640), "camera.width.*positive integer"),
        (_set(["camera", "height"], 0), "camera.height.*positive integer"),
        (_set(["camera", "width"], 640.5), "camera.width.*positive integer"),
        (_set(["camera", "fx"], -1.0), "camera.fx.*positive"),
        (_set(["camera", "cy"], "middle"), "camera.cy.*number"),
        (_set(["camera", "model"], "fisheye"), "camera.model"),
        (_set(["camera", "distortion", "model"], "equidistant"), "distortion.model"),
        (_set(["camera", "distortion", "k3"], 0.1), "unknown keys 'k3'"),
        (_set(["format_version"], 2), "format_version.*unknown version 2"),
        (_delete(["format_version"]), "missing 'format_version'"),
        (_set(["depth_scale"], 0.0), "depth_scale.*positive"),
        (
            _set(
                ["rig", "T_body_camera"], [[2.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
            ),
            "T_body_camera.*not a rigid",
        ),
        (_set(["rig", "T_body_lidar"], [[1.0, 0, 0]]), "T_body_lidar.*4x4"),
        (_set(["rig", "urdf"], 5), "urdf.*string"),
        (_set(["lidar"], [1, 2]), "lidar.*mapping"),
        (_set(["camers"], {}), "unknown keys 'camers'"),
    ],
)
def test_bad_calib_names_file_and_key(tmp_path: Path, change, message: str):
    path = write_modified(tmp_path, change)
    with pytest.raises(ValueError, match=message) as info:
        read_calib(path)
    assert "calib.yaml" in str(info.value)


def test_not_yaml_and_missing(tmp_path: Path):
    (tmp_path / "calib.yaml").write_text("camera: [unclosed\n")
    with pytest.raises(ValueError, match="calib.yaml.*YAML"):
        read_calib(tmp_path / "calib.yaml")
    with pytest.raises(FileNotFoundError, match="other.yaml"):
        read_calib(tmp_path / "other.yaml")


def test_calibration_rejects_bad_values():
    camera = make_calib().camera
    with pytest.raises(ValueError, match="depth_scale"):
        Calibration(camera=camera, depth_scale=-1.0)
    with pytest.raises(ValueError, match="rigid"):
        Calibration(camera=camera, T_body_camera=2 * torch.eye(4, dtype=torch.float64))
