"""A generated world: its meshes (as mapped and changed), route, scanner stations, regions."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from diffloc.io.textured_mesh import TexturedMesh

__all__ = ["WORLD_KINDS", "Region", "World"]

WORLD_KINDS = ("indoor", "outdoor")


@dataclass
class Region:
    """A named axis-aligned box of the world (a room, a corridor, a facade, a building, ...).

    Attributes:
        name: unique name, e.g. ``"f1_room2"``.
        kind: ``"room"``, ``"corridor"``, ``"stair_hall"``, ``"courtyard"``, ``"avenue"``,
            ``"building"`` or ``"facade"``.
        floor: storey index (0 = ground).
        lo: (3,) min corner in metres.
        hi: (3,) max corner in metres.
    """

    name: str
    kind: str
    floor: int
    lo: np.ndarray
    hi: np.ndarray

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: which of the (N, 3) points lie inside the box."""
        return ((points >= self.lo) & (points <= self.hi)).all(axis=1)


@dataclass
class World:
    """A generated world.

    Attributes:
        kind: ``"indoor"`` or ``"outdoor"``.
        seed: the generating seed.
        mesh: the scene as mapped.
        changed_mesh: the same scene with some movable objects moved, removed or added (same
            material list; object ids of added objects are new).
        route: (K, 3) float64 ordered waypoints of the walking / driving path; z is the floor
            height under each waypoint (straight lines between waypoints stay on the floor or
            stair nosing line).
        route_clearance: metres of free space guaranteed on each side of the route at heights up
            to 2 m above it (both scene states).
        tls_stations: (S, 3) float64 free-space positions of a static terrestrial scanner
            (1.3 m above the floor indoors, 1.8 m above the ground outdoors).
        bounds: (2, 3) float64 min and max corner of the world (both scene states).
        regions: rooms, corridors, stair hall (indoor) or courtyard, avenue, buildings, facades
            (outdoor).
        floor_heights: z of each storey's floor (indoor: two storeys; outdoor: ``[0.0]``).
        num_objects: movable objects in ``mesh``.
        num_changes: objects moved, removed or added in ``changed_mesh``.
    """

    kind: str
    seed: int
    mesh: TexturedMesh
    changed_mesh: TexturedMesh
    route: np.ndarray
    route_clearance: float
    tls_stations: np.ndarray
    bounds: np.ndarray
    regions: list[Region] = field(default_factory=list)
    floor_heights: list[float] = field(default_factory=list)
    num_objects: int = 0
    num_changes: int = 0

    @property
    def route_length(self) -> float:
        """Length of the route polyline in metres."""
        return float(np.linalg.norm(np.diff(self.route, axis=0), axis=1).sum())

    def count(self, kind: str) -> int:
        """Number of regions of a kind (``"room"``, ``"facade"``, ...)."""
        return sum(region.kind == kind for region in self.regions)

    def metadata(self) -> dict[str, Any]:
        """JSON-serialisable summary (counts, lengths, bounds) for dataset descriptions."""
        kinds = sorted({region.kind for region in self.regions})
        return {
            "kind": self.kind,
            "seed": int(self.seed),
            "triangles": self.mesh.num_faces,
            "changed_triangles": self.changed_mesh.num_faces,
            "materials": len(self.mesh.material_names),
            "movable_objects": int(self.num_objects),
            "changed_objects": int(self.num_changes),
            "route_waypoints": int(len(self.route)),
            "route_length_m": round(self.route_length, 3),
            "route_clearance_m": float(self.route_clearance),
            "tls_stations": int(len(self.tls_stations)),
            "floor_heights_m": [float(z) for z in self.floor_heights],
            "bounds_m": np.round(self.bounds, 3).tolist(),
            "regions": {kind: self.count(kind) for kind in kinds},
        }


def _mesh_bounds(*meshes: TexturedMesh) -> np.ndarray:
    """(2, 3) float64 min and max corner of all ``meshes`` (:attr:`World.bounds`)."""
    vertices = np.concatenate([m.vertices for m in meshes]).astype(np.float64)
    return np.stack([vertices.min(axis=0), vertices.max(axis=0)])
