"""Tests of diffloc.geometry.rig: URDF parsing and writing, FK agreement, gradients, errors."""

from __future__ import annotations

import math

import pytest
import pytorch_kinematics as pk
import torch

from diffloc.checks import ShapeError
from diffloc.geometry.rig import SensorRig, rotation_from_rpy, rpy_from_rotation
from diffloc.geometry.se3 import invert, transform_points
from diffloc.testing import assert_close, gradcheck, random_points, random_se3

F64 = torch.float64
HALF_PI = math.pi / 2

NESTED_URDF = """<?xml version="1.0"?>
<robot name="car">
  <link name="base_link"/>
  <link name="camera_link"/>
  <link name="camera_optical"/>
  <link name="velodyne"/>
  <joint name="base_to_camera" type="fixed">
    <parent link="base_link"/>
    <child link="camera_link"/>
    <origin xyz="1.2 0.05 1.5" rpy="0.01 -0.02 0.03"/>
  </joint>
  <joint name="camera_to_optical" type="fixed">
    <parent link="camera_link"/>
    <child link="camera_optical"/>
    <origin xyz="0 0 0" rpy="-1.5707963267948966 0 -1.5707963267948966"/>
  </joint>
  <joint name="base_to_velodyne" type="fixed">
    <parent link="base_link"/>
    <child link="velodyne"/>
    <origin xyz="0.3 0 1.9"/>
  </joint>
</robot>
"""


def _rot(axis: str, angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    matrices = {
        "x": [[1, 0, 0], [0, c, -s], [0, s, c]],
        "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]],
        "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]],
    }
    return torch.tensor(matrices[axis], dtype=F64)


def _random_rig(seed: int) -> SensorRig:
    g = torch.Generator().manual_seed(seed)
    offsets = {}
    for name in ("camera", "lidar", "imu"):
        xyz = torch.randn(3, generator=g, dtype=F64)
        rpy = (torch.rand(3, generator=g, dtype=F64) * 2 - 1) * torch.tensor(
            [math.pi, HALF_PI, math.pi], dtype=F64
        )
        offsets[name] = (xyz, rpy)
    return SensorRig(offsets, body="base_link", robot_name="test_rig")


def _pk_fk(urdf: str) -> dict[str, torch.Tensor]:
    """Link poses from pytorch_kinematics' own forward kinematics (no movable joints)."""
    chain = pk.build_chain_from_urdf(urdf).to(dtype=F64)
    fk = chain.forward_kinematics(torch.zeros(chain.n_joints, dtype=F64))
    return {name: t.get_matrix()[0] for name, t in fk.items()}


def test_rpy_matches_urdf_fixed_axis_convention() -> None:
    roll, pitch, yaw = 0.3, -0.7, 2.1
    expected = _rot("z", yaw) @ _rot("y", pitch) @ _rot("x", roll)
    got = rotation_from_rpy(torch.tensor([roll, pitch, yaw], dtype=F64))
    assert_close(got, expected, atol=1e-15, rtol=0)
    assert_close(rpy_from_rotation(got), torch.tensor([roll, pitch, yaw], dtype=F64))


def test_optical_frame_known_answer() -> None:
    rig = SensorRig({"camera": ([0.1, 0.0, 0.0], [-HALF_PI, 0.0, -HALF_PI])})
    T = rig.T_body_sensor("camera").detach()
    # camera z (forward) -> body x, camera x (right) -> body -y, camera y (down) -> body -z
    assert_close(T[:3, 2], torch.tensor([1.0, 0.0, 0.0], dtype=F64), atol=1e-15, rtol=0)
    assert_close(T[:3, 0], torch.tensor([0.0, -1.0, 0.0], dtype=F64), atol=1e-15, rtol=0)
    assert_close(T[:3, 1], torch.tensor([0.0, 0.0, -1.0], dtype=F64), atol=1e-15, rtol=0)
    assert_close(T[:3, 3], torch.tensor([0.1, 0.0, 0.0], dtype=F64))
    # a point 2 m ahead of the camera is 2.1 m ahead of the body
    p = transform_points(T, torch.tensor([[0.0, 0.0, 2.0]], dtype=F64))
    assert_close(p, torch.tensor([[2.1, 0.0, 0.0]], dtype=F64))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_agrees_with_pytorch_kinematics_forward_kinematics(seed: int) -> None:
    rig = _random_rig(seed)
    urdf = rig.to_urdf()
    fk = _pk_fk(urdf)
    assert set(fk) == {"base_link", *rig.sensor_names}
    assert_close(fk["base_link"], torch.eye(4, dtype=F64))
    for name in rig.sensor_names:
        # the chain stores offsets in float32, hence the tolerance
        assert_close(rig.T_body_sensor(name).detach(), fk[name], atol=1e-6, rtol=0)


def test_nested_sensors_are_flattened_and_match_fk() -> None:
    rig = SensorRig.from_urdf(NESTED_URDF)
    assert rig.body == "base_link" and rig.robot_name == "car"
    assert sorted(rig.sensor_names) == ["camera_link", "camera_optical", "velodyne"]
    assert rig.joint_names["camera_link"] == "base_to_camera"
    fk = _pk_fk(NESTED_URDF)
    for name in rig.sensor_names:
        assert_close(rig.T_body_sensor(name).detach(), fk[name], atol=1e-6, rtol=0)
    expected = rig.T_body_sensor("camera_link") @ SensorRig(
        {"o": ([0.0, 0.0, 0.0], [-HALF_PI, 0.0, -HALF_PI])}
    ).T_body_sensor("o")
    assert_close(rig.T_body_sensor("camera_optical"), expected, atol=1e-12, rtol=0)
    assert_close(rig.xyz["velodyne"].detach(), torch.tensor([0.3, 0.0, 1.9], dtype=F64))
    assert rig.rpy["velodyne"].detach().abs().max() == 0.0


@pytest.mark.parametrize("seed", [3, 4])
def test_urdf_round_trip_is_exact(seed: int) -> None:
    rig = _random_rig(seed)
    text = rig.to_urdf()
    back = SensorRig.from_urdf(text)
    assert back.body == "base_link" and back.robot_name == "test_rig"
    assert back.sensor_names == rig.sensor_names
    assert back.joint_names == rig.joint_names
    for name in rig.sensor_names:
        assert (back.xyz[name] - rig.xyz[name]).abs().max() <= 1e-12
        assert (back.rpy[name] - rig.rpy[name]).abs().max() <= 1e-12
        assert (back.T_body_sensor(name) - rig.T_body_sensor(name)).abs().max() <= 1e-12
    assert back.to_urdf() == text


def test_urdf_from_offsets_matches_constructor() -> None:
    offsets = {
        "camera": ([0.1, 0.0, 0.0], [-HALF_PI, 0.0, -HALF_PI]),
        "lidar": ([0.0, 0.0, 0.25], [0.0, 0.0, 0.0]),
    }
    rig = SensorRig.from_urdf(SensorRig.urdf_from_offsets(offsets))
    assert rig.body == "body" and rig.sensor_names == ["camera", "lidar"]
    assert rig.to_urdf() == SensorRig(offsets).to_urdf()


def test_from_transforms_round_trip() -> None:
    g = torch.Generator().manual_seed(5)
    T = random_se3((2,), generator=g)
    rig = SensorRig.from_transforms({"camera": T[0], "lidar": T[1]})
    assert_close(rig.T_body_sensor("camera").detach(), T[0], atol=1e-12, rtol=0)
    assert_close(rig.T_body_sensor("lidar").detach(), T[1], atol=1e-12, rtol=0)
    assert rig.xyz["camera"].dtype == F64


def test_sensor_to_sensor_and_forward() -> None:
    rig = _random_rig(6)
    T_cl = rig.T_sensor_sensor("camera", "lidar").detach()
    T_bc = rig.T_body_sensor("camera").detach()
    T_bl = rig.T_body_sensor("lidar").detach()
    g = torch.Generator().manual_seed(6)
    p_lidar = random_points((8,), generator=g)
    assert_close(
        transform_points(T_cl, p_lidar),
        transform_points(invert(T_bc), transform_points(T_bl, p_lidar)),
    )
    assert_close(rig.T_sensor_sensor("base_link", "lidar").detach(), T_bl)
    assert_close(rig.T_body_sensor("base_link"), torch.eye(4, dtype=F64))
    for shape in [(), (2,), (1, 2)]:
        T_wb = random_se3(shape, generator=g)
        T_ws = rig(T_wb, "camera")
        assert T_ws.shape == (*shape, 4, 4)
        assert_close(T_ws.detach(), T_wb @ T_bc)
    assert rig(random_se3((), generator=g, dtype=torch.float32), "lidar").dtype == torch.float32


def test_gradients_flow_to_extrinsics() -> None:
    rig = _random_rig(7)
    rig(torch.eye(4, dtype=F64), "camera")[:3, 3].sum().backward()
    assert rig.xyz["camera"].grad is not None
    assert_close(rig.xyz["camera"].grad, torch.ones(3, dtype=F64))
    assert rig.xyz["lidar"].grad is None
    assert {n for n, _ in rig.named_parameters()} == {
        f"{kind}.{name}" for kind in ("xyz", "rpy") for name in ("camera", "lidar", "imu")
    }


@pytest.mark.parametrize("seed", [8, 9])
def test_gradcheck_T_body_sensor(seed: int) -> None:
    rig = _random_rig(seed)
    T_wb = random_se3((2,), generator=torch.Generator().manual_seed(seed))

    def fn(xyz: torch.Tensor, rpy: torch.Tensor) -> torch.Tensor:
        params = {"xyz.lidar": xyz, "rpy.lidar": rpy}
        return torch.func.functional_call(rig, params, args=(T_wb, "lidar"))

    assert gradcheck(fn, [rig.xyz["lidar"], rig.rpy["lidar"]])


# ---------------------------------------------------------------- bad inputs


@pytest.mark.parametrize(
    ("urdf", "message"),
    [
        ("<robot", "malformed URDF"),
        ("not xml at all", "malformed URDF"),
        ('<robot name="r"><link name="body"/></robot>', "no joints"),
        (
            '<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="fixed">'
            '<parent link="a"/><child link="b"/><origin xyz="1 2"/></joint></robot>',
            "malformed URDF",
        ),
        (
            '<robot name="r"><link name="a"/><joint name="j" type="fixed">'
            '<parent link="a"/><child link="ghost"/></joint></robot>',
            "not defined",
        ),
        (
            '<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="revolute">'
            '<parent link="a"/><child link="b"/><axis xyz="0 0 1"/>'
            '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>',
            "fixed joints",
        ),
        (
            '<robot name="r"><link name="a"/><link name="b"/><link name="loose"/>'
            '<joint name="j" type="fixed"><parent link="a"/><child link="b"/></joint></robot>',
            "not connected",
        ),
        (
            '<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="fixed">'
            '<parent link="a"/><child link="b"/><origin xyz="0 0 nan"/></joint></robot>',
            "NaN",
        ),
    ],
)
def test_malformed_urdf_raises_value_error(urdf: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        SensorRig.from_urdf(urdf)


def test_non_string_urdf_raises_type_error() -> None:
    with pytest.raises(TypeError, match="str"):
        SensorRig.from_urdf(b"<robot/>")


def test_unknown_sensor_name_raises() -> None:
    rig = _random_rig(10)
    with pytest.raises(ValueError, match="unknown sensor 'radar'.*camera"):
        rig.T_body_sensor("radar")
    with pytest.raises(ValueError, match="unknown sensor"):
        rig(torch.eye(4, dtype=F64), "radar")
    with pytest.raises(ValueError, match="unknown sensor"):
        rig.T_sensor_sensor("camera", "radar")


def test_bad_constructor_arguments_raise() -> None:
    with pytest.raises(ValueError, match="at least one sensor"):
        SensorRig({})
    with pytest.raises(ValueError, match="sensor name"):
        SensorRig({"cam.left": ([0, 0, 0], [0, 0, 0])})
    with pytest.raises(ValueError, match="equals the body"):
        SensorRig({"body": ([0, 0, 0], [0, 0, 0])})
    with pytest.raises(ShapeError, match="camera xyz"):
        SensorRig({"camera": ([0, 0], [0, 0, 0])})
    with pytest.raises(ValueError, match="camera rpy"):
        SensorRig({"camera": ([0, 0, 0], [0, float("inf"), 0])})


def test_from_transforms_rejects_non_rigid_matrices() -> None:
    scaled = torch.eye(4, dtype=F64)
    scaled[0, 0] = 2.0
    with pytest.raises(ValueError, match="proper rotation"):
        SensorRig.from_transforms({"camera": scaled})
    reflected = torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0], dtype=F64))
    with pytest.raises(ValueError, match="proper rotation"):
        SensorRig.from_transforms({"camera": reflected})
    bottom = torch.eye(4, dtype=F64)
    bottom[3, 0] = 1.0
    with pytest.raises(ValueError, match="bottom row"):
        SensorRig.from_transforms({"camera": bottom})
    with pytest.raises(ShapeError):
        SensorRig.from_transforms({"camera": torch.eye(3, dtype=F64)})
    nan = torch.eye(4, dtype=F64)
    nan[0, 3] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        SensorRig.from_transforms({"camera": nan})
