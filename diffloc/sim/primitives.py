"""Closed solids and the props built from them (furniture, cars, trees, ...) for procedural worlds.

Every solid added by :class:`MeshBuilder` is closed: each edge is shared by exactly two of the
solid's triangles, in opposite directions, and triangles are counter-clockwise seen from outside
(``cross(v1 - v0, v2 - v0)`` points out). Solids may touch or overlap each other; the union is
still seen from outside as front faces only, which is what free-space checks rely on.

Texture coordinates come in two modes, chosen per call by ``repeat_m``:

- world mode (``repeat_m > 0``): each face projects world coordinates onto its own right and up
  axes (right = up x normal for walls, up = +z; east/north for floors) divided by ``repeat_m``.
  Texel density is the same everywhere and textures run on seamlessly across adjacent solids.
- fit mode (``repeat_m == 0``): every face shows the whole texture once, upright and unmirrored
  when seen from outside (posters, windows, doors, book rows).

``repeat_m=None`` takes the material's catalogue value (:func:`material_repeat_m`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from diffloc.checks import check_shape
from diffloc.io.textured_mesh import TexturedMesh
from diffloc.sim.textures import material_repeat_m

__all__ = ["PROPS", "Frame", "MeshBuilder", "Prop", "rotation_z", "wall_panel", "window_unit"]


def rotation_z(yaw: float) -> np.ndarray:
    """(3, 3) rotation by ``yaw`` radians about +z."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _box_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Constant tables of the unit box [-1, 1]^3.

    Returns:
        corners (8, 3), triangle corner indices (12, 3), per-triangle local right axis (12, 3),
        local up axis (12, 3) and local corner coordinates (12, 3, 3).
    """
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    up_z = np.array([0.0, 0.0, 1.0])
    faces = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            normal = np.zeros(3)
            normal[axis] = sign
            if axis < 2:
                up = up_z
                right = np.cross(up, normal)
            else:
                up = np.array([0.0, 1.0, 0.0])
                right = np.array([sign, 0.0, 0.0])
            faces.append((normal, right, up))
    tri_index, tri_right, tri_up = [], [], []
    for normal, right, up in faces:
        quad = [normal + s1 * right + s2 * up for s1, s2 in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        ids = [int(np.flatnonzero((corners == q).all(axis=1))[0]) for q in quad]
        for tri in ((0, 1, 2), (0, 2, 3)):
            tri_index.append([ids[k] for k in tri])
            tri_right.append(right)
            tri_up.append(up)
    tri_index = np.array(tri_index)
    return corners, tri_index, np.array(tri_right), np.array(tri_up), corners[tri_index]


_CUBE, _BOX_TRIS, _BOX_RIGHT, _BOX_UP, _BOX_LOCAL = _box_tables()


@dataclass
class MeshBuilder:
    """Accumulates closed solids into one :class:`TexturedMesh`.

    Args:
        material_names: the world's material list; solids name their material from it.

    Example:
        >>> builder = MeshBuilder(["concrete"])
        >>> builder.add_box([0, 0, 0], [1, 1, 1], "concrete", object_id=0)
        >>> builder.num_faces
        12
    """

    material_names: Sequence[str]
    _vertices: list[np.ndarray] = field(default_factory=list)
    _triangles: list[np.ndarray] = field(default_factory=list)
    _uvs: list[np.ndarray] = field(default_factory=list)
    _materials: list[np.ndarray] = field(default_factory=list)
    _objects: list[np.ndarray] = field(default_factory=list)
    _vertex_count: int = 0
    _face_count: int = 0

    def __post_init__(self) -> None:
        self._ids = {name: i for i, name in enumerate(self.material_names)}

    @property
    def num_faces(self) -> int:
        return self._face_count

    def _material(self, name: str) -> tuple[int, float]:
        if name not in self._ids:
            raise ValueError(
                f"material {name!r} is not in this world's materials {list(self._ids)}"
            )
        return self._ids[name], material_repeat_m(name)

    def _append(
        self,
        vertices: np.ndarray,
        triangles: np.ndarray,
        uvs: np.ndarray,
        material: int,
        object_ids: np.ndarray,
    ) -> None:
        self._vertices.append(vertices.reshape(-1, 3))
        self._triangles.append(triangles.reshape(-1, 3) + self._vertex_count)
        self._uvs.append(uvs.reshape(-1, 3, 2))
        faces = self._triangles[-1].shape[0]
        self._materials.append(np.full(faces, material, np.int32))
        self._objects.append(np.broadcast_to(object_ids, faces).astype(np.int32))
        self._vertex_count += vertices.reshape(-1, 3).shape[0]
        self._face_count += faces

    def add_boxes(
        self,
        centers: np.ndarray,
        half_sizes: np.ndarray,
        material: str,
        object_id: int | np.ndarray,
        rotations: np.ndarray | None = None,
        repeat_m: float | None = None,
    ) -> None:
        """Add N boxes (12 triangles and 8 vertices each).

        Args:
            centers: (N, 3) box centres in the world frame.
            half_sizes: (N, 3) positive half extents along the box's own axes.
            material: material name.
            object_id: one id or (N,) ids.
            rotations: (N, 3, 3) box-to-world rotations; ``None`` for axis-aligned boxes.
            repeat_m: metres per texture repeat (0 = fit); ``None`` = the material's default.
        """
        centers = np.asarray(centers, float).reshape(-1, 3)
        half = np.asarray(half_sizes, float).reshape(-1, 3)
        check_shape(half, f"{len(centers)},3", "half_sizes")
        if (half <= 0).any():
            raise ValueError("box half sizes must be positive")
        count = len(centers)
        if rotations is None:
            rotations = np.broadcast_to(np.eye(3), (count, 3, 3))
        rotations = np.asarray(rotations, float).reshape(count, 3, 3)
        material_id, default_repeat = self._material(material)
        repeat = default_repeat if repeat_m is None else float(repeat_m)
        local = _CUBE[None] * half[:, None, :]  # (N, 8, 3)
        vertices = centers[:, None, :] + np.einsum("nij,nkj->nki", rotations, local)
        if repeat > 0:
            positions = vertices[:, _BOX_TRIS]  # (N, 12, 3, 3)
            right = np.einsum("nij,fj->nfi", rotations, _BOX_RIGHT)
            up = np.einsum("nij,fj->nfi", rotations, _BOX_UP)
            u = np.einsum("nfci,nfi->nfc", positions, right) / repeat
            v = -np.einsum("nfci,nfi->nfc", positions, up) / repeat
        else:
            u = (np.einsum("fci,fi->fc", _BOX_LOCAL, _BOX_RIGHT) + 1.0) / 2.0
            v = (1.0 - np.einsum("fci,fi->fc", _BOX_LOCAL, _BOX_UP)) / 2.0
            u, v = np.broadcast_to(u, (count, 12, 3)), np.broadcast_to(v, (count, 12, 3))
        triangles = _BOX_TRIS[None] + 8 * np.arange(count)[:, None, None]
        object_ids = np.repeat(np.broadcast_to(np.asarray(object_id), count), 12)
        self._append(vertices, triangles, np.stack([u, v], axis=-1), material_id, object_ids)

    def add_box(
        self,
        lo: Sequence[float],
        hi: Sequence[float],
        material: str,
        object_id: int,
        repeat_m: float | None = None,
    ) -> None:
        """Add one axis-aligned box between corners ``lo`` (3,) and ``hi`` (3,)."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        self.add_boxes(
            (lo + hi)[None] / 2, (hi - lo)[None] / 2, material, object_id, repeat_m=repeat_m
        )

    def add_prism(
        self,
        polygon: np.ndarray,
        origin: Sequence[float],
        axes: np.ndarray,
        length: float,
        material: str,
        object_id: int,
        top_scale: float = 1.0,
        repeat_m: float | None = None,
    ) -> None:
        """Add a convex polygon extruded along an axis (a prism, or a frustum if ``top_scale < 1``).

        Args:
            polygon: (P, 3 <= P) convex polygon, counter-clockwise in the (a, b) plane.
            origin: (3,) world position of the polygon's (0, 0) at the bottom cap.
            axes: (3, 3) rows a, b, w: orthonormal with a x b = w; the prism runs along w.
            length: extrusion length along w (> 0).
            material: material name.
            object_id: object id of all its triangles.
            top_scale: the top cap is the polygon scaled by this (> 0) about the axis.
            repeat_m: metres per texture repeat (0 = fit); ``None`` = the material's default.
        """
        polygon = np.asarray(polygon, float)
        check_shape(polygon, "P,2", "polygon")
        if len(polygon) < 3 or length <= 0 or top_scale <= 0:
            raise ValueError("a prism needs >= 3 polygon corners, length > 0 and top_scale > 0")
        a, b, w = np.asarray(axes, float)
        origin = np.asarray(origin, float)
        count = len(polygon)
        flat = polygon[:, :1] * a + polygon[:, 1:] * b
        bottom = origin + flat
        top = origin + length * w + top_scale * flat
        vertices = np.concatenate([bottom, top])
        i = np.arange(count)
        j = (i + 1) % count
        sides = np.concatenate(
            [np.stack([i, j, count + j], 1), np.stack([i, count + j, count + i], 1)]
        )
        fan = np.arange(1, count - 1)
        top_cap = np.stack([np.full_like(fan, count), count + fan, count + fan + 1], 1)
        bottom_cap = np.stack([np.zeros_like(fan), fan + 1, fan], 1)
        triangles = np.concatenate([sides, top_cap, bottom_cap])
        material_id, default_repeat = self._material(material)
        repeat = default_repeat if repeat_m is None else float(repeat_m)
        edge = np.linalg.norm(np.roll(polygon, -1, axis=0) - polygon, axis=1)
        arc_start = np.concatenate([[0.0], np.cumsum(edge)[:-1]])
        arc_end = arc_start + edge
        # Per side-triangle corner: arc length along the perimeter and height along w.
        arc = np.concatenate(
            [
                np.stack([arc_start, arc_end, arc_end], 1),
                np.stack([arc_start, arc_end, arc_start], 1),
            ]
        )
        height = np.concatenate(
            [np.tile([0.0, 0.0, 1.0], (count, 1)), np.tile([0.0, 1.0, 1.0], (count, 1))]
        )
        cap_xy = np.concatenate([polygon, top_scale * polygon])[
            np.concatenate([top_cap, bottom_cap])
        ]
        if repeat > 0:
            base_height = float(origin @ w)
            side_u = arc / repeat
            side_v = -(base_height + height * length) / repeat
            cap_u = (cap_xy[..., 0] + origin @ a) / repeat
            cap_v = -(cap_xy[..., 1] + origin @ b) / repeat
        else:
            side_u = arc / edge.sum()
            side_v = 1.0 - height
            low, high = polygon.min(axis=0), polygon.max(axis=0)
            cap_u = (cap_xy[..., 0] - low[0]) / (high[0] - low[0])
            cap_v = 1.0 - (cap_xy[..., 1] - low[1]) / (high[1] - low[1])
        uvs = np.concatenate([np.stack([side_u, side_v], -1), np.stack([cap_u, cap_v], -1)])
        self._append(vertices, triangles, uvs, material_id, np.asarray(object_id))

    def add_cylinder(
        self,
        base: Sequence[float],
        axis: Sequence[float],
        radius: float,
        length: float,
        material: str,
        object_id: int,
        segments: int = 12,
        top_scale: float = 1.0,
        repeat_m: float | None = None,
    ) -> None:
        """Add a closed cylinder (or frustum) of ``segments`` sides from ``base`` along ``axis``.

        Args:
            base: (3,) centre of the bottom cap.
            axis: (3,) direction of the axis (normalised here).
            radius: radius of the bottom cap (> 0).
            length: length along the axis (> 0).
            material: material name.
            object_id: object id.
            segments: number of sides (>= 3).
            top_scale: top radius / bottom radius (> 0).
            repeat_m: metres per texture repeat (0 = fit); ``None`` = the material's default.
        """
        w = np.asarray(axis, float)
        w = w / np.linalg.norm(w)
        helper = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        a = np.cross(helper, w)
        a /= np.linalg.norm(a)
        b = np.cross(w, a)
        angles = 2 * np.pi * np.arange(segments) / segments
        polygon = radius * np.stack([np.cos(angles), np.sin(angles)], 1)
        self.add_prism(
            polygon, base, np.stack([a, b, w]), length, material, object_id, top_scale, repeat_m
        )

    def build(self, textures: Sequence[np.ndarray]) -> TexturedMesh:
        """The accumulated solids as one mesh using ``textures`` (one per material)."""
        if len(textures) != len(self.material_names):
            raise ValueError(
                f"got {len(textures)} textures for {len(self.material_names)} materials"
            )
        if not self._triangles:
            raise ValueError("the builder holds no solids")
        return TexturedMesh(
            vertices=np.concatenate(self._vertices).astype(np.float32),
            triangles=np.concatenate(self._triangles).astype(np.int32),
            corner_uvs=np.concatenate(self._uvs).astype(np.float32),
            material_ids=np.concatenate(self._materials),
            object_ids=np.concatenate(self._objects),
            textures=list(textures),
            material_names=list(self.material_names),
        )


@dataclass(frozen=True)
class Frame:
    """A local frame on the ground: ``origin`` (3,) in the world, x/y rotated by ``yaw`` about z.

    Props are modelled in their own frame (x to the right, y to the front, z up, metres) and
    placed by a frame.
    """

    origin: np.ndarray
    yaw: float

    @property
    def rotation(self) -> np.ndarray:
        return rotation_z(self.yaw)

    def point(self, local: Sequence[float]) -> np.ndarray:
        """World position (3,) of a local point (3,)."""
        return np.asarray(self.origin, float) + self.rotation @ np.asarray(local, float)

    def box(
        self,
        builder: MeshBuilder,
        lo: Sequence[float],
        hi: Sequence[float],
        material: str,
        object_id: int,
        repeat_m: float | None = None,
    ) -> None:
        """Add a box given by its local corners ``lo`` (3,) and ``hi`` (3,)."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        builder.add_boxes(
            self.point((lo + hi) / 2)[None],
            ((hi - lo) / 2)[None],
            material,
            object_id,
            self.rotation[None],
            repeat_m,
        )

    def rod(
        self,
        builder: MeshBuilder,
        start: Sequence[float],
        end: Sequence[float],
        thickness: float,
        material: str,
        object_id: int,
    ) -> None:
        """Add a square bar of side ``thickness`` between two local points (3,)."""
        start, end = self.point(start), self.point(end)
        direction = end - start
        length = float(np.linalg.norm(direction))
        y_axis = direction / length
        side = np.cross(y_axis, [0.0, 0.0, 1.0])
        if np.linalg.norm(side) < 1e-6:
            side = self.rotation[:, 0]
        x_axis = side / np.linalg.norm(side)
        z_axis = np.cross(x_axis, y_axis)
        rotation = np.stack([x_axis, y_axis, z_axis], axis=1)
        half = np.array([thickness / 2, length / 2, thickness / 2])
        builder.add_boxes(
            ((start + end) / 2)[None], half[None], material, object_id, rotation[None]
        )

    def cylinder(
        self,
        builder: MeshBuilder,
        base: Sequence[float],
        axis: Sequence[float],
        radius: float,
        length: float,
        material: str,
        object_id: int,
        segments: int = 12,
        top_scale: float = 1.0,
        repeat_m: float | None = None,
    ) -> None:
        """Add a cylinder with local base (3,) and local axis (3,)."""
        builder.add_cylinder(
            self.point(base),
            self.rotation @ np.asarray(axis, float),
            radius,
            length,
            material,
            object_id,
            segments,
            top_scale,
            repeat_m,
        )


def wall_panel(
    builder: MeshBuilder,
    frame: Frame,
    width: float,
    z_range: tuple[float, float],
    material: str,
    object_id: int,
    depth: float = 0.02,
    trim: str | None = None,
    trim_width: float = 0.04,
) -> None:
    """A flat panel on a wall (poster, board, window pane), its face stretched over the texture.

    The frame's origin is on the wall face at floor level, local +y points out of the wall.

    Args:
        builder: receives the solids.
        frame: the wall frame.
        width: panel width along local x, centred on the origin.
        z_range: (bottom, top) heights above the frame origin.
        material: panel material (fit mode).
        object_id: object id.
        depth: how far the panel stands out of the wall.
        trim: optional material of a surrounding frame, ``trim_width`` wide and 1 cm proud.
        trim_width: width of the frame bars.
    """
    z0, z1 = z_range
    frame.box(
        builder, (-width / 2, 0.0, z0), (width / 2, depth, z1), material, object_id, repeat_m=0.0
    )
    if trim is None:
        return
    t, d = trim_width, depth + 0.01
    bars = (
        ((-width / 2 - t, 0.0, z0 - t), (-width / 2, d, z1 + t)),
        ((width / 2, 0.0, z0 - t), (width / 2 + t, d, z1 + t)),
        ((-width / 2, 0.0, z0 - t), (width / 2, d, z0)),
        ((-width / 2, 0.0, z1), (width / 2, d, z1 + t)),
    )
    for lo, hi in bars:
        frame.box(builder, lo, hi, trim, object_id)


def window_unit(
    builder: MeshBuilder,
    frame: Frame,
    width: float,
    z_range: tuple[float, float],
    glass: str,
    trim: str,
    object_id: int = 0,
    pediment: bool = False,
) -> None:
    """A facade window: glass pane, surround, sill and an optional pediment (outdoors).

    The frame's origin is on the facade at ground level, local +y points out of the facade.
    """
    z0, z1 = z_range
    wall_panel(
        builder, frame, width, z_range, glass, object_id, depth=0.05, trim=trim, trim_width=0.16
    )
    frame.box(
        builder,
        (-width / 2 - 0.25, 0.0, z0 - 0.28),
        (width / 2 + 0.25, 0.3, z0 - 0.16),
        trim,
        object_id,
    )
    if pediment:
        frame.box(
            builder,
            (-width / 2 - 0.3, 0.0, z1 + 0.2),
            (width / 2 + 0.3, 0.35, z1 + 0.4),
            trim,
            object_id,
        )


# --------------------------------------------------------------------------- props


@dataclass(frozen=True)
class Prop:
    """A movable object model.

    Attributes:
        footprint: (x0, y0, x1, y1) rectangle of its local frame it stands on (metres).
        height: overall height (metres).
        against_wall: placed with local y = footprint y0 against a wall, facing +y.
        build: ``build(builder, frame, object_id, variant)`` adds its solids.
    """

    footprint: tuple[float, float, float, float]
    height: float
    against_wall: bool
    build: Callable[[MeshBuilder, Frame, int, int], None]


def _chair(
    b: MeshBuilder, f: Frame, oid: int, x: float, y: float, facing: float, fabric: str
) -> None:
    """An office chair centred at local (x, y) whose seat faces local direction ``facing`` (rad)."""
    g = Frame(f.point((x, y, 0.0)), f.yaw + facing)
    g.cylinder(b, (0, 0, 0), (0, 0, 1), 0.28, 0.07, "metal_dark", oid, segments=5)
    g.cylinder(b, (0, 0, 0.07), (0, 0, 1), 0.03, 0.36, "metal", oid, segments=6)
    g.box(b, (-0.24, -0.22, 0.43), (0.24, 0.22, 0.5), fabric, oid)
    g.box(b, (-0.23, -0.27, 0.5), (0.23, -0.2, 0.98), fabric, oid)


def _desk(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    top = ("wood", "wood_dark", "metal")[variant % 3]
    fabric = ("fabric_blue", "fabric_green")[variant % 2]
    f.box(b, (-0.7, 0.0, 0.72), (0.7, 0.72, 0.76), top, oid)
    for x0 in (-0.68, 0.64):
        f.box(b, (x0, 0.04, 0.0), (x0 + 0.04, 0.68, 0.72), "metal_dark", oid)
    f.box(b, (-0.64, 0.04, 0.3), (0.64, 0.07, 0.72), "metal_dark", oid)
    f.box(b, (-0.05, 0.12, 0.76), (0.05, 0.22, 0.9), "metal_dark", oid)
    f.box(b, (-0.32, 0.15, 0.9), (0.32, 0.2, 1.26), "metal_dark", oid)
    f.box(b, (-0.22, 0.38, 0.76), (0.22, 0.52, 0.785), "metal", oid)
    f.box(b, (0.32, 0.3, 0.76), (0.6, 0.66, 0.8), "cardboard", oid, repeat_m=0.0)
    _chair(b, f, oid, 0.0, 1.05, np.pi, fabric)


def _bookcase(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    wood = ("wood", "wood_dark", "metal")[variant % 3]
    f.box(b, (-0.5, 0.0, 0.0), (-0.48, 0.36, 1.95), wood, oid)
    f.box(b, (0.48, 0.0, 0.0), (0.5, 0.36, 1.95), wood, oid)
    f.box(b, (-0.48, 0.0, 0.0), (0.48, 0.02, 1.95), wood, oid)
    f.box(b, (-0.48, 0.02, 1.93), (0.48, 0.36, 1.95), wood, oid)
    f.box(b, (-0.48, 0.02, 0.0), (0.48, 0.36, 0.08), wood, oid)
    for z in (0.5, 0.95, 1.4):
        f.box(b, (-0.48, 0.02, z), (0.48, 0.36, z + 0.02), wood, oid)
    for z in (0.08, 0.52, 0.97, 1.42):
        f.box(b, (-0.47, 0.04, z), (0.47, 0.3, z + 0.34), "books", oid, repeat_m=0.0)


def _cabinet(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    body = ("metal", "wood")[variant % 2]
    f.box(b, (-0.4, 0.0, 0.0), (0.4, 0.45, 1.1), body, oid)
    for x0 in (-0.39, 0.01):
        f.box(b, (x0, 0.45, 0.05), (x0 + 0.38, 0.47, 1.05), "door_wood", oid, repeat_m=0.0)
    for x0 in (-0.06, 0.04):
        f.box(b, (x0, 0.47, 0.5), (x0 + 0.02, 0.5, 0.7), "metal_dark", oid)


def _locker(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    f.box(b, (-0.45, 0.0, 0.0), (0.45, 0.5, 1.9), "metal", oid)
    for k in range(3):
        x0 = -0.44 + 0.2933 * k
        f.box(b, (x0, 0.5, 0.1), (x0 + 0.28, 0.52, 1.85), "metal_dark", oid)
        f.box(b, (x0 + 0.2, 0.52, 0.9), (x0 + 0.24, 0.55, 1.05), "metal", oid)
        for z in (1.55, 1.6, 1.65):
            f.box(b, (x0 + 0.06, 0.52, z), (x0 + 0.22, 0.53, z + 0.02), "metal", oid)


def _meeting_table(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    top = ("wood", "wood_dark")[variant % 2]
    f.box(b, (-1.2, -0.55, 0.72), (1.2, 0.55, 0.77), top, oid)
    for x in (-1.05, 1.0):
        for y in (-0.45, 0.4):
            f.box(b, (x, y, 0.0), (x + 0.05, y + 0.05, 0.72), "metal_dark", oid)
    for x in (-0.75, 0.0, 0.75):
        _chair(b, f, oid, x, 0.9, 0.0, "fabric_blue")
        _chair(b, f, oid, x, -0.9, np.pi, "fabric_blue")


def _plant(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    f.cylinder(
        b, (0, 0, 0), (0, 0, 1), 0.2, 0.42, ("concrete", "paint_red")[variant % 2], oid, 10, 1.15
    )
    f.cylinder(b, (0, 0, 0.42), (0, 0, 1), 0.36, 0.6, "foliage", oid, 8, 1.1)
    f.cylinder(b, (0, 0, 1.02), (0, 0, 1), 0.4, 0.5, "foliage", oid, 8, 0.35)


def _boxes(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    shapes = np.random.default_rng(variant).uniform(0.25, 0.34, (3, 3))
    z = 0.0
    for k in range(1 + variant % 3):
        hx, hy, hz = shapes[k] * (1.0, 1.0, 0.9)
        g = Frame(f.point((0.03 * k, -0.02 * k, 0.0)), f.yaw + 0.15 * (k - 1))
        g.box(b, (-hx, -hy, z), (hx, hy, z + 2 * hz), "cardboard", oid, repeat_m=0.0)
        z += 2 * hz


def _sofa(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    fabric = ("fabric_green", "fabric_blue")[variant % 2]
    f.box(b, (-0.9, 0.1, 0.1), (0.9, 0.85, 0.42), fabric, oid)
    f.box(b, (-0.9, 0.0, 0.1), (0.9, 0.22, 0.85), fabric, oid)
    for x0 in (-0.9, 0.75):
        f.box(b, (x0, 0.22, 0.42), (x0 + 0.15, 0.85, 0.62), fabric, oid)
    for x0 in (-0.85, 0.8):
        f.box(b, (x0, 0.15, 0.0), (x0 + 0.05, 0.8, 0.1), "metal_dark", oid)


def _vending(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    f.box(b, (-0.45, 0.0, 0.0), (0.45, 0.8, 1.85), "paint_red", oid)
    f.box(b, (-0.4, 0.8, 0.55), (0.2, 0.82, 1.75), "poster_coffee", oid, repeat_m=0.0)
    f.box(b, (0.24, 0.8, 1.0), (0.4, 0.83, 1.5), "metal_dark", oid)
    f.box(b, (-0.35, 0.8, 0.15), (0.35, 0.84, 0.4), "metal_dark", oid)


def _copier(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    f.box(b, (-0.35, 0.0, 0.0), (0.35, 0.6, 0.95), "metal", oid)
    f.box(b, (-0.33, 0.02, 0.95), (0.33, 0.55, 1.02), "metal_dark", oid)
    f.box(b, (-0.3, 0.6, 0.3), (0.3, 0.62, 0.8), "metal_dark", oid)
    f.box(b, (0.35, 0.1, 0.55), (0.55, 0.5, 0.62), "metal", oid)


def _extinguisher(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    f.box(b, (-0.12, 0.0, 0.55), (0.12, 0.03, 1.2), "metal", oid)
    f.cylinder(b, (0, 0.12, 0.6), (0, 0, 1), 0.08, 0.5, "paint_red", oid, 10)
    f.cylinder(b, (0, 0.12, 1.1), (0, 0, 1), 0.03, 0.08, "metal_dark", oid, 6)


def _car(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    paint = ("car_red", "car_blue", "car_silver")[variant % 3]
    f.box(b, (-0.9, -2.2, 0.32), (0.9, 2.2, 0.95), paint, oid)
    f.box(b, (-0.8, -1.25, 0.95), (0.8, 0.85, 1.48), "car_glass", oid, repeat_m=0.0)
    f.box(b, (-0.78, -1.15, 1.48), (0.78, 0.75, 1.52), paint, oid)
    for y0 in (-2.25, 2.15):
        f.box(b, (-0.85, y0, 0.35), (0.85, y0 + 0.1, 0.55), "metal_dark", oid)
    for x0 in (-0.75, 0.5):
        f.box(b, (x0, 2.2, 0.7), (x0 + 0.25, 2.23, 0.82), "metal", oid)
    for x in (-0.92, 0.7):
        for y in (-1.4, 1.4):
            f.cylinder(b, (x, y, 0.33), (1, 0, 0), 0.33, 0.22, "rubber", oid, 12)


def _bike(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    paint = ("paint_red", "car_blue", "metal_dark")[variant % 3]
    for y in (-0.52, 0.52):
        f.cylinder(b, (-0.02, y, 0.34), (1, 0, 0), 0.34, 0.04, "rubber", oid, 14)
    f.rod(b, (0, -0.28, 0.8), (0, 0.36, 0.82), 0.04, paint, oid)
    f.rod(b, (0, 0.36, 0.8), (0, -0.04, 0.36), 0.04, paint, oid)
    f.rod(b, (0, -0.3, 0.36), (0, -0.3, 0.92), 0.035, paint, oid)
    f.rod(b, (0, -0.3, 0.38), (0, -0.52, 0.34), 0.03, paint, oid)
    f.rod(b, (0, 0.52, 0.34), (0, 0.4, 0.95), 0.03, paint, oid)
    f.box(b, (-0.25, 0.38, 0.95), (0.25, 0.42, 0.99), "metal_dark", oid)
    f.box(b, (-0.07, -0.42, 0.92), (0.07, -0.2, 0.97), "metal_dark", oid)


def _bench(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    wood = ("wood", "wood_dark")[variant % 2]
    f.box(b, (-0.9, 0.05, 0.42), (0.9, 0.5, 0.47), wood, oid)
    f.box(b, (-0.9, 0.0, 0.5), (0.9, 0.06, 0.88), wood, oid)
    for x0 in (-0.75, 0.7):
        f.box(b, (x0, 0.05, 0.0), (x0 + 0.05, 0.5, 0.42), "metal_dark", oid)
        f.box(b, (x0, 0.0, 0.0), (x0 + 0.05, 0.05, 0.88), "metal_dark", oid)


def _lamp_post(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    f.box(b, (-0.18, -0.18, 0.0), (0.18, 0.18, 0.45), "metal_dark", oid)
    f.cylinder(b, (0, 0, 0.45), (0, 0, 1), 0.07, 3.8, "metal_dark", oid, 8, 0.7)
    f.box(b, (-0.2, -0.2, 4.25), (0.2, 0.2, 4.75), "light_panel", oid, repeat_m=0.0)
    f.cylinder(b, (0, 0, 4.75), (0, 0, 1), 0.3, 0.2, "metal_dark", oid, 8, 0.2)


def _bollard(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    f.cylinder(b, (0, 0, 0), (0, 0, 1), 0.12, 0.85, "metal_dark", oid, 10)
    f.cylinder(b, (0, 0, 0.85), (0, 0, 1), 0.13, 0.08, "metal", oid, 10, 0.5)


def _bin(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    f.cylinder(
        b, (0, 0, 0), (0, 0, 1), 0.28, 0.92, ("metal_dark", "paint_red")[variant % 2], oid, 12
    )
    f.cylinder(b, (0, 0, 0.92), (0, 0, 1), 0.3, 0.12, "metal", oid, 12, 0.6)


def _tree(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    scale = 0.85 + 0.1 * (variant % 4)
    f.cylinder(b, (0, 0, 0), (0, 0, 1), 0.24, 3.0 * scale, "bark", oid, 8, 0.7)
    f.cylinder(b, (0, 0, 2.3 * scale), (0, 0, 1), 1.6, 1.2 * scale, "foliage", oid, 8, 1.25)
    f.cylinder(b, (0, 0, 3.5 * scale), (0, 0, 1), 2.0, 2.2 * scale, "foliage", oid, 8, 0.45)
    f.cylinder(b, (0, 0, 5.7 * scale), (0, 0, 1), 0.9, 1.2 * scale, "foliage", oid, 8, 0.15)


def _statue(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    f.box(b, (-0.6, -0.6, 0.0), (0.6, 0.6, 0.3), "stone_trim", oid)
    f.box(b, (-0.45, -0.45, 0.3), (0.45, 0.45, 1.6), "facade_stone", oid)
    f.box(b, (-0.55, -0.55, 1.6), (0.55, 0.55, 1.75), "stone_trim", oid)
    f.cylinder(b, (0, 0, 1.75), (0, 0, 1), 0.28, 1.3, "metal_dark", oid, 10, 0.8)
    f.box(b, (-0.45, -0.08, 2.55), (0.45, 0.08, 2.7), "metal_dark", oid)
    f.cylinder(b, (0, 0, 3.05), (0, 0, 1), 0.14, 0.3, "metal_dark", oid, 8, 0.8)


def _sign(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    f.cylinder(b, (0, 0, 0), (0, 0, 1), 0.05, 2.5, "metal", oid, 8)
    f.box(b, (-0.45, 0.05, 1.75), (0.45, 0.09, 2.45), "sign_text", oid, repeat_m=0.0)


_COLUMN_POSTERS = (
    "poster_rocket",
    "poster_astronaut",
    "poster_hubble",
    "poster_motorcycle",
    "poster_coins",
)


def _ad_column(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    poster = _COLUMN_POSTERS[variant % len(_COLUMN_POSTERS)]
    f.cylinder(b, (0, 0, 0), (0, 0, 1), 0.65, 0.3, "metal_dark", oid, 16)
    f.cylinder(b, (0, 0, 0.3), (0, 0, 1), 0.6, 2.5, poster, oid, 16, repeat_m=0.0)
    f.cylinder(b, (0, 0, 2.8), (0, 0, 1), 0.7, 0.35, "metal_dark", oid, 16, 0.3)


def _planter(b: MeshBuilder, f: Frame, oid: int, variant: int) -> None:
    f.box(b, (-0.6, -0.3, 0.0), (0.6, 0.3, 0.6), "concrete", oid)
    f.box(b, (-0.55, -0.25, 0.6), (0.55, 0.25, 1.0), "foliage", oid)


PROPS: dict[str, Prop] = {
    # indoor furniture
    "desk": Prop((-0.7, 0.0, 0.7, 1.35), 1.26, True, _desk),
    "bookcase": Prop((-0.5, 0.0, 0.5, 0.36), 1.95, True, _bookcase),
    "cabinet": Prop((-0.4, 0.0, 0.4, 0.5), 1.1, True, _cabinet),
    "locker": Prop((-0.45, 0.0, 0.45, 0.55), 1.9, True, _locker),
    "meeting_table": Prop((-1.3, -1.25, 1.3, 1.25), 0.98, False, _meeting_table),
    "plant": Prop((-0.42, -0.42, 0.42, 0.42), 1.52, False, _plant),
    "boxes": Prop((-0.42, -0.42, 0.42, 0.42), 1.8, False, _boxes),
    "sofa": Prop((-0.9, 0.0, 0.9, 0.85), 0.85, True, _sofa),
    "vending_machine": Prop((-0.45, 0.0, 0.45, 0.84), 1.85, True, _vending),
    "copier": Prop((-0.35, 0.0, 0.55, 0.62), 1.02, True, _copier),
    "extinguisher": Prop((-0.12, 0.0, 0.12, 0.2), 1.2, True, _extinguisher),
    # outdoor clutter
    "car": Prop((-0.95, -2.25, 0.95, 2.25), 1.52, False, _car),
    "bike": Prop((-0.27, -0.86, 0.27, 0.86), 0.99, False, _bike),
    "bench": Prop((-0.9, 0.0, 0.9, 0.5), 0.88, True, _bench),
    "lamp_post": Prop((-0.3, -0.3, 0.3, 0.3), 4.95, False, _lamp_post),
    "bollard": Prop((-0.13, -0.13, 0.13, 0.13), 0.93, False, _bollard),
    "bin": Prop((-0.3, -0.3, 0.3, 0.3), 1.04, False, _bin),
    "tree": Prop((-2.5, -2.5, 2.5, 2.5), 8.0, False, _tree),
    "statue": Prop((-0.6, -0.6, 0.6, 0.6), 3.35, False, _statue),
    "sign": Prop((-0.45, -0.05, 0.45, 0.09), 2.45, False, _sign),
    "ad_column": Prop((-0.7, -0.7, 0.7, 0.7), 3.15, False, _ad_column),
    "planter": Prop((-0.6, -0.3, 0.6, 0.3), 1.0, False, _planter),
}
