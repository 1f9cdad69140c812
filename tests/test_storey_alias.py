"""Storey aliases: floors of the render poses, alias poses, the rule, and the test on a
two-storey copy of the tiny scene (the same room stacked 10 m higher: every view has a perfect
alias) against the one-storey scene (none)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from diffloc.crossmodal.synthesize import MeshMap
from diffloc.io.dataset import read_sequence
from diffloc.io.mesh_obj import read_textured_mesh_obj
from diffloc.io.textured_mesh import TexturedMesh
from diffloc.pipeline.crossmodal_alias import SequenceAliases
from diffloc.pipeline.crossmodal_pose_checks import StoreyAliasConfig
from diffloc.pipeline.crossmodal_stage import SequenceLocalization
from diffloc.reloc.rendered import RenderedLocalizerConfig, localizer_networks
from diffloc.reloc.storey_alias import (
    AliasEvidence,
    alias_poses,
    floor_heights,
    is_storey_alias,
    storey_alias_evidence,
)

LIFT_M = 10.0
"""Height of the copy above the tiny room (more than the room is tall)."""


def _stacked(mesh: TexturedMesh) -> TexturedMesh:
    """``mesh`` and a copy of it ``LIFT_M`` higher."""
    lifted = mesh.vertices + np.array([0.0, 0.0, LIFT_M], dtype=np.float32)
    return TexturedMesh(
        vertices=np.concatenate([mesh.vertices, lifted]),
        triangles=np.concatenate([mesh.triangles, mesh.triangles + len(mesh.vertices)]),
        corner_uvs=np.concatenate([mesh.corner_uvs, mesh.corner_uvs]),
        material_ids=np.concatenate([mesh.material_ids, mesh.material_ids]),
        object_ids=np.concatenate([mesh.object_ids, mesh.object_ids]),
        textures=mesh.textures,
        material_names=mesh.material_names,
    )


def test_floor_heights_take_the_median_camera_height_per_floor():
    T = torch.eye(4, dtype=torch.float64).repeat(5, 1, 1)
    T[:, 2, 3] = torch.tensor([4.4, 1.5, 1.7, 4.6, 20.0], dtype=torch.float64)
    heights = floor_heights(T, torch.tensor([1, 0, 0, 1, -1]))
    assert heights.tolist() == pytest.approx([1.6, 4.5])
    assert len(floor_heights(T, torch.full((5,), -1))) == 0


def test_alias_poses_move_only_the_height_to_every_other_floor():
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T[:3, 3] = torch.tensor([2.0, -1.0, 4.3])
    moved = alias_poses(T, torch.tensor([1.5, 4.5, 7.5], dtype=torch.float64))
    assert moved[:, 2, 3].tolist() == pytest.approx([1.3, 7.3])
    for m in moved:
        assert torch.equal(m[:3, :3], T[:3, :3]) and torch.equal(m[:2, 3], T[:2, 3])
    assert alias_poses(T, torch.tensor([1.5], dtype=torch.float64)).shape == (0, 4, 4)


@pytest.mark.parametrize(
    ("evidence", "alias"),
    [
        (AliasEvidence(250, (445,), (2.96,)), True),  # the other floor explains it better
        (AliasEvidence(250, (250,), (3.0,)), True),  # as well: ambiguous
        (AliasEvidence(250, (249,), (3.0,)), False),
        (AliasEvidence(250, (400,), (0.5,)), False),  # its pose came back to the pose found
        (AliasEvidence(250, (0,), (float("nan"),)), False),  # no pose on the other floor
        (AliasEvidence(0, (20,), (3.0,)), True),  # the own render gave no pose at all
        (AliasEvidence(250, (), ()), False),  # one floor
    ],
)
def test_the_alias_rule(evidence, alias):
    assert is_storey_alias(evidence, min_distance_m=1.0, ratio=1.0) == alias


@pytest.fixture(scope="module")
def room(tiny_indoor_dataset):
    """(one-storey map, two-storey map, query image, its pose, camera)."""
    mesh = read_textured_mesh_obj(tiny_indoor_dataset / "map" / "mesh" / "scene.obj")
    mapping = read_sequence(tiny_indoor_dataset, "mapping")
    T = mapping.T_wc[0]
    image = MeshMap(mesh).render(T[None], mapping.camera).rgb[0]
    return MeshMap(mesh), MeshMap(_stacked(mesh)), image, T, mapping.camera


def test_a_view_repeated_on_another_floor_is_an_alias_and_a_unique_one_is_not(room):
    single, stacked, image, T, camera = room
    config = RenderedLocalizerConfig()
    networks = localizer_networks(config)
    view = (image, networks[0].extract(image), camera)
    heights = torch.tensor([float(T[2, 3]), float(T[2, 3]) + LIFT_M], dtype=torch.float64)
    twin = storey_alias_evidence(stacked, T, heights, camera, view, networks, config)
    assert twin.own_inliers >= 50
    assert twin.alias_inliers[0] == twin.own_inliers  # the same render, the same RANSAC
    assert twin.alias_distance_m[0] == pytest.approx(LIFT_M, abs=0.05)
    assert is_storey_alias(twin, 1.0, StoreyAliasConfig().ratio)
    one_floor = storey_alias_evidence(single, T, heights[:1], camera, view, networks, config)
    assert one_floor == AliasEvidence(-1, (), ()) and not is_storey_alias(one_floor, 1.0, 1.0)
    alone = storey_alias_evidence(single, T, heights, camera, view, networks, config)
    assert alone.own_inliers == twin.own_inliers
    assert alone.alias_inliers[0] < 0.5 * alone.own_inliers
    assert not is_storey_alias(alone, 1.0, StoreyAliasConfig().ratio)


def test_applying_the_aliases_refuses_only_them():
    arrays = {name: np.zeros(4) for name in SequenceLocalization.__dataclass_fields__}
    loc = SequenceLocalization(**{**arrays, "accepted": np.array([True, False, True, True])})
    aliases = SequenceAliases(
        query=np.array([0, 2, 3]),
        own_inliers=np.array([300, 200, 250]),
        alias_inliers=np.array([[10], [260], [0]]),
        alias_distance_m=np.array([[3.0], [3.0], [np.nan]]),
        alias=np.array([False, True, False]),
        cpu_ms=np.zeros(3),
    )
    assert aliases.apply(loc).accepted.tolist() == [True, False, False, True]
    assert loc.accepted.tolist() == [True, False, True, True]  # the record is not changed


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"maps": ["nerf"]}, "not one of the maps"), ({"ratio": 0.0}, "ratio")],
)
def test_bad_storey_alias_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        StoreyAliasConfig(**kwargs)
