"""Sensor rig: a body frame with rigidly attached sensors, via pytorch_kinematics.

A rig is a URDF robot whose root link is the body (e.g. ``base_link``: x forward, y left,
z up) and whose fixed joints lead to sensor links (``"camera"``, ``"lidar"``). Each sensor's
extrinsic ``T_body_sensor`` is stored as URDF parameters ``xyz`` (metres) and ``rpy`` (URDF
fixed-axis roll-pitch-yaw, radians, ``R = Rz(yaw) Ry(pitch) Rx(roll)``) in ``nn.Parameter``s,
so gradients flow to the extrinsics (e.g. for calibration refinement).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from xml.sax.saxutils import quoteattr

import pytorch_kinematics as pk
import torch
from pytorch_kinematics import transforms as pk_tf
from pytorch_kinematics.urdf_parser_py.urdf import URDF
from torch import nn

from diffloc.checks import check_finite, check_shape
from diffloc.geometry.se3 import compose, invert

__all__ = ["SensorRig", "rpy_from_rotation", "rotation_from_rpy"]

Vector3 = Sequence[float] | torch.Tensor

_ORTHONORMAL_TOL = 1e-6


def rotation_from_rpy(rpy: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of URDF roll-pitch-yaw angles, ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

    Uses ``pytorch_kinematics.transforms.euler_angles_to_matrix`` with the intrinsic "ZYX"
    convention on ``(yaw, pitch, roll)``, which equals URDF's fixed-axis X-Y-Z rotation.

    Args:
        rpy: (..., 3) ``(roll, pitch, yaw)`` in radians.

    Returns:
        (..., 3, 3) rotation matrices.

    Example:
        >>> R = rotation_from_rpy(torch.tensor([0.0, 0.0, torch.pi / 2]))
        >>> R @ torch.tensor([1.0, 0.0, 0.0])  # yaw turns x towards y
        tensor([-4.3711e-08,  1.0000e+00,  0.0000e+00])
    """
    check_shape(rpy, "*,3", "rpy")
    return pk_tf.euler_angles_to_matrix(rpy.flip(-1), "ZYX")


def rpy_from_rotation(R: torch.Tensor) -> torch.Tensor:
    """URDF roll-pitch-yaw of rotation matrices, the inverse of :func:`rotation_from_rpy`.

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) ``(roll, pitch, yaw)`` with pitch in ``[-pi/2, pi/2]``.

    Example:
        >>> rpy = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
        >>> torch.allclose(rpy_from_rotation(rotation_from_rpy(rpy)), rpy)
        True
    """
    check_shape(R, "*,3,3", "R")
    return pk_tf.matrix_to_euler_angles(R, "ZYX").flip(-1)


def _transform_from_xyz_rpy(xyz: torch.Tensor, rpy: torch.Tensor) -> torch.Tensor:
    """(4, 4) transform ``[[R(rpy), xyz], [0, 1]]`` (differentiable in xyz and rpy)."""
    R = rotation_from_rpy(rpy)
    top = torch.cat((R, xyz[:, None]), dim=-1)
    bottom = torch.zeros(1, 4, dtype=R.dtype, device=R.device)
    bottom[0, 3] = 1.0
    return torch.cat((top, bottom), dim=0)


def _check_name(name: object, what: str) -> str:
    if not isinstance(name, str) or not name or "." in name:
        raise ValueError(f"{what} must be a non-empty string without '.', got {name!r}")
    return name


def _vector3(value: Vector3, name: str, dtype: torch.dtype) -> torch.Tensor:
    t = torch.as_tensor(value, dtype=dtype).detach().clone()
    check_shape(t, "3", name)
    check_finite(t, name)
    return t


class SensorRig(nn.Module):
    """A body frame with rigidly attached sensors, extrinsics as URDF xyz/rpy parameters.

    Args:
        offsets: ``{sensor_name: (xyz (3,), rpy (3,))}``, the URDF joint origin of each sensor
            relative to the body.
        body: name of the body (root) link.
        robot_name: URDF robot name, kept for :meth:`to_urdf`.
        joint_names: optional ``{sensor_name: joint_name}``; default ``f"{body}_to_{sensor}"``.
        dtype: dtype of the parameters (float64 by default: extrinsics are optimised).

    Attributes:
        xyz: ``nn.ParameterDict`` of (3,) translations per sensor.
        rpy: ``nn.ParameterDict`` of (3,) roll-pitch-yaw per sensor.

    Raises:
        ValueError: no sensors, bad names (empty, containing '.', equal to the body), or
            non-finite offsets.
        ShapeError: offsets that are not 3-vectors.

    Example:
        >>> rig = SensorRig({"camera": ([0.1, 0, 0], [-torch.pi / 2, 0, -torch.pi / 2])})
        >>> rig.T_body_sensor("camera")[:3, 2].detach().round(decimals=9)  # optical z = body x
        tensor([1., 0., 0.], dtype=torch.float64)
    """

    def __init__(
        self,
        offsets: Mapping[str, tuple[Vector3, Vector3]],
        body: str = "body",
        robot_name: str = "rig",
        joint_names: Mapping[str, str] | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        self.body = _check_name(body, "body name")
        self.robot_name = _check_name(robot_name, "robot name")
        if not offsets:
            raise ValueError("a SensorRig needs at least one sensor")
        self.xyz = nn.ParameterDict()
        self.rpy = nn.ParameterDict()
        self.joint_names: dict[str, str] = {}
        joint_names = dict(joint_names or {})
        for sensor, pair in offsets.items():
            _check_name(sensor, "sensor name")
            if sensor == body:
                raise ValueError(f"sensor name {sensor!r} equals the body name")
            if not isinstance(pair, tuple | list) or len(pair) != 2:
                raise ValueError(f"offsets[{sensor!r}] must be a pair (xyz, rpy), got {pair!r}")
            xyz, rpy = pair
            self.xyz[sensor] = nn.Parameter(_vector3(xyz, f"{sensor} xyz", dtype))
            self.rpy[sensor] = nn.Parameter(_vector3(rpy, f"{sensor} rpy", dtype))
            self.joint_names[sensor] = _check_name(
                joint_names.get(sensor, f"{body}_to_{sensor}"), "joint name"
            )

    # ------------------------------------------------------------------ constructors

    @classmethod
    def from_urdf(cls, urdf: str, dtype: torch.dtype = torch.float64) -> SensorRig:
        """Build a rig from a URDF string.

        The kinematic tree comes from ``pytorch_kinematics.build_chain_from_urdf``: its root
        is the body, every other link is a sensor and must be reached through fixed joints.
        Sensors that hang below other sensors (e.g. ``camera_link -> camera_optical``) are
        flattened to body-relative offsets. Offsets are read at full precision from the
        joint origins of the same pytorch_kinematics URDF parse (the chain itself stores
        them in float32), so ``from_urdf(rig.to_urdf())`` reproduces float64 values exactly.

        Args:
            urdf: URDF XML text.
            dtype: dtype of the parameters.

        Returns:
            The rig.

        Raises:
            TypeError: ``urdf`` is not a string.
            ValueError: malformed XML/URDF, no joints, several root links, joints between
                unknown links, non-fixed joints or non-finite origins.

        Example:
            >>> urdf = SensorRig.urdf_from_offsets({"lidar": ([0, 0, 0.3], [0, 0, 0])})
            >>> SensorRig.from_urdf(urdf).sensor_names
            ['lidar']
        """
        if not isinstance(urdf, str):
            raise TypeError(f"urdf must be a str of URDF XML, got {type(urdf).__name__}")
        try:
            robot = URDF.from_xml_string(urdf)
        except Exception as exc:  # lxml / urdf_parser_py raise many types
            raise ValueError(f"malformed URDF: {exc}") from exc
        if not robot.joints:
            raise ValueError("URDF has no joints: a rig needs a body link and sensor links")
        for joint in robot.joints:
            for role, link in (("parent", joint.parent), ("child", joint.child)):
                if link not in robot.link_map:
                    raise ValueError(
                        f"URDF joint {joint.name!r} has {role} link {link!r} that is not defined"
                    )
        try:
            chain = pk.build_chain_from_urdf(urdf)
        except Exception as exc:
            raise ValueError(f"pytorch_kinematics could not build a chain: {exc}") from exc
        frame_names = chain.get_frame_names(exclude_fixed=False)
        if set(frame_names) != set(robot.link_map):
            loose = sorted(set(robot.link_map) - set(frame_names))
            raise ValueError(
                f"URDF links {loose} are not connected to the root link {frame_names[0]!r}"
            )
        body = frame_names[0]
        offsets: dict[str, tuple[list[float], list[float]]] = {}
        joint_names: dict[str, str] = {}
        # Walk the chain: (frame, T_body_parent or None when the parent is the body).
        stack: list[tuple[object, torch.Tensor | None]] = [
            (child, None) for child in chain.find_frame(body).children
        ]
        while stack:
            frame, T_body_parent = stack.pop()
            joint = frame.joint
            if joint.joint_type != "fixed":
                raise ValueError(
                    f"URDF joint {joint.name!r} is {joint.joint_type}; a sensor rig has only "
                    "fixed joints"
                )
            origin = robot.joint_map[joint.name].origin
            xyz = [0.0, 0.0, 0.0] if origin is None or origin.xyz is None else origin.xyz
            rpy = [0.0, 0.0, 0.0] if origin is None or origin.rpy is None else origin.rpy
            xyz = [float(x) for x in xyz]
            rpy = [float(x) for x in rpy]
            T_parent_child = _transform_from_xyz_rpy(
                _vector3(xyz, f"joint {joint.name} xyz", torch.float64),
                _vector3(rpy, f"joint {joint.name} rpy", torch.float64),
            )
            if T_body_parent is None:
                offsets[frame.name] = (xyz, rpy)
                T_body_child = T_parent_child
            else:
                T_body_child = T_body_parent @ T_parent_child
                offsets[frame.name] = (
                    T_body_child[:3, 3].tolist(),
                    rpy_from_rotation(T_body_child[:3, :3]).tolist(),
                )
            joint_names[frame.name] = (
                joint.name if T_body_parent is None else f"{body}_to_{frame.name}"
            )
            stack.extend((child, T_body_child) for child in frame.children)
        order = [name for name in frame_names if name in offsets]
        return cls(
            {name: offsets[name] for name in order},
            body=body,
            robot_name=robot.name or "rig",
            joint_names=joint_names,
            dtype=dtype,
        )

    @classmethod
    def from_transforms(
        cls,
        transforms: Mapping[str, torch.Tensor],
        body: str = "body",
        dtype: torch.dtype = torch.float64,
    ) -> SensorRig:
        """Build a rig from body-to-sensor matrices.

        Args:
            transforms: ``{sensor_name: T_body_sensor (4, 4)}`` rigid transforms.
            body: name of the body link.
            dtype: dtype of the parameters.

        Returns:
            The rig (``rpy`` extracted with pitch in ``[-pi/2, pi/2]``).

        Raises:
            ShapeError: a matrix that is not (4, 4).
            ValueError: non-finite values, a bottom row other than ``[0, 0, 0, 1]`` or a
                rotation block that is not a proper rotation (tolerance 1e-6).

        Example:
            >>> rig = SensorRig.from_transforms({"lidar": torch.eye(4)})
            >>> rig.T_body_sensor("lidar").detach().equal(torch.eye(4, dtype=torch.float64))
            True
        """
        offsets: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
        for sensor, T in transforms.items():
            check_shape(T, "4,4", f"T_body_{sensor}")
            T64 = torch.as_tensor(T).detach().to(torch.float64).cpu()
            check_finite(T64, f"T_body_{sensor}")
            bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
            if not torch.allclose(T64[3], bottom, rtol=0.0, atol=_ORTHONORMAL_TOL):
                raise ValueError(f"T_body_{sensor} bottom row must be [0, 0, 0, 1]")
            R = T64[:3, :3]
            error = (R.T @ R - torch.eye(3, dtype=torch.float64)).abs().max()
            if error > _ORTHONORMAL_TOL or torch.linalg.det(R) <= 0:
                raise ValueError(f"T_body_{sensor} rotation block is not a proper rotation")
            offsets[sensor] = (T64[:3, 3], rpy_from_rotation(R))
        return cls(offsets, body=body, dtype=dtype)

    # ------------------------------------------------------------------ URDF output

    @staticmethod
    def urdf_from_offsets(
        offsets: Mapping[str, tuple[Vector3, Vector3]],
        body: str = "body",
        robot_name: str = "rig",
        joint_names: Mapping[str, str] | None = None,
    ) -> str:
        """URDF text of a rig given as ``{sensor: (xyz, rpy)}`` (numbers at repr precision).

        Args:
            offsets: ``{sensor_name: (xyz (3,), rpy (3,))}``.
            body: name of the body link.
            robot_name: URDF robot name.
            joint_names: optional ``{sensor_name: joint_name}``.

        Returns:
            URDF XML text.

        Example:
            >>> "<origin" in SensorRig.urdf_from_offsets({"lidar": ([0, 0, 1], [0, 0, 0])})
            True
        """
        joint_names = dict(joint_names or {})

        def numbers(values: Vector3) -> str:
            flat = torch.as_tensor(values, dtype=torch.float64).reshape(-1).tolist()
            if len(flat) != 3:
                raise ValueError(f"expected 3 numbers, got {len(flat)}")
            return quoteattr(" ".join(repr(float(x)) for x in flat))

        lines = ['<?xml version="1.0"?>', f"<robot name={quoteattr(robot_name)}>"]
        lines.append(f"  <link name={quoteattr(body)}/>")
        for sensor in offsets:
            lines.append(f"  <link name={quoteattr(sensor)}/>")
        for sensor, (xyz, rpy) in offsets.items():
            joint = joint_names.get(sensor, f"{body}_to_{sensor}")
            lines += [
                f'  <joint name={quoteattr(joint)} type="fixed">',
                f"    <parent link={quoteattr(body)}/>",
                f"    <child link={quoteattr(sensor)}/>",
                f"    <origin xyz={numbers(xyz)} rpy={numbers(rpy)}/>",
                "  </joint>",
            ]
        lines.append("</robot>")
        return "\n".join(lines) + "\n"

    def to_urdf(self) -> str:
        """URDF text of this rig; ``SensorRig.from_urdf(rig.to_urdf())`` reproduces it exactly.

        Returns:
            URDF XML text (a body link, one link and one fixed joint per sensor).

        Example:
            >>> rig = SensorRig({"lidar": ([0.0, 0.0, 0.25], [0.0, 0.0, 0.0])})
            >>> 'xyz="0.0 0.0 0.25"' in rig.to_urdf()
            True
        """
        offsets = {
            name: (self.xyz[name].detach().cpu(), self.rpy[name].detach().cpu())
            for name in self.sensor_names
        }
        return self.urdf_from_offsets(offsets, self.body, self.robot_name, self.joint_names)

    # ------------------------------------------------------------------ transforms

    @property
    def sensor_names(self) -> list[str]:
        """Names of the sensors, in insertion (URDF) order."""
        return list(self.xyz.keys())

    def _check_sensor(self, name: str) -> None:
        if name != self.body and name not in self.xyz:
            raise ValueError(
                f"unknown sensor {name!r}; this rig has body {self.body!r} and sensors "
                f"{self.sensor_names}"
            )

    def T_body_sensor(self, name: str) -> torch.Tensor:
        """Transform from a sensor frame to the body frame, differentiable in xyz/rpy.

        Args:
            name: a sensor name (or the body name, which gives the identity).

        Returns:
            (4, 4) ``T_body_sensor`` in the parameters' dtype.

        Raises:
            ValueError: unknown name.

        Example:
            >>> rig = SensorRig({"lidar": ([0.0, 0.0, 0.25], [0.0, 0.0, 0.0])})
            >>> rig.T_body_sensor("lidar")[2, 3].item()
            0.25
        """
        self._check_sensor(name)
        if name == self.body:
            ref = next(iter(self.xyz.values()))
            return torch.eye(4, dtype=ref.dtype, device=ref.device)
        return _transform_from_xyz_rpy(self.xyz[name], self.rpy[name])

    def T_sensor_sensor(self, a: str, b: str) -> torch.Tensor:
        """Transform from sensor ``b``'s frame to sensor ``a``'s frame.

        Args:
            a: target sensor (or body) name.
            b: source sensor (or body) name.

        Returns:
            (4, 4) ``T_a_b = T_body_a^-1 T_body_b``.

        Example:
            >>> rig = SensorRig({"a": ([1.0, 0, 0], [0, 0, 0]), "b": ([0, 2.0, 0], [0, 0, 0])})
            >>> rig.T_sensor_sensor("a", "b")[:3, 3].tolist()
            [-1.0, 2.0, 0.0]
        """
        return compose(invert(self.T_body_sensor(a)), self.T_body_sensor(b))

    def forward(self, T_world_body: torch.Tensor, name: str) -> torch.Tensor:
        """Sensor poses from body poses: ``T_world_sensor = T_world_body @ T_body_sensor``.

        Args:
            T_world_body: (..., 4, 4) body-to-world transforms.
            name: sensor name.

        Returns:
            (..., 4, 4) sensor-to-world transforms in ``T_world_body``'s dtype.

        Example:
            >>> rig = SensorRig({"lidar": ([0.0, 0.0, 0.25], [0.0, 0.0, 0.0])})
            >>> rig(torch.eye(4).expand(2, 4, 4), "lidar").shape
            torch.Size([2, 4, 4])
        """
        check_shape(T_world_body, "*,4,4", "T_world_body")
        T_body_sensor = self.T_body_sensor(name).to(T_world_body.dtype)
        return compose(T_world_body, T_body_sensor.to(T_world_body.device))
