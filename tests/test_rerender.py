"""Re-rendering the map at a pose found (diffloc/reloc/rerender.py), known answers on the tiny
simulated scene's mesh: a query rendered from the mesh, a start pose 16 cm and 3 deg away from
it; the render at the start pose gives the query's own pose back."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from diffloc.crossmodal.synthesize import MeshMap
from diffloc.eval.metrics import pose_errors
from diffloc.geometry.se3 import se3_exp
from diffloc.io.dataset import read_sequence
from diffloc.io.mesh_obj import read_textured_mesh_obj
from diffloc.reloc.rendered import RenderedLocalizerConfig, localizer_networks
from diffloc.reloc.rerender import RERENDER_STAGES, rerender_candidate
from diffloc.reloc.stage_clock import StageClock

OFFSET = torch.tensor([0.1, -0.05, 0.12, 0.02, 0.05, -0.03], dtype=torch.float64)
"""The query = the start pose composed with exp(OFFSET): 16.4 cm and 3.4 deg away."""


@pytest.fixture(scope="module")
def setup(tiny_indoor_dataset):
    mesh_map = MeshMap(read_textured_mesh_obj(tiny_indoor_dataset / "map" / "mesh" / "scene.obj"))
    mapping = read_sequence(tiny_indoor_dataset, "mapping")
    config = RenderedLocalizerConfig()
    return mesh_map, mapping, config, localizer_networks(config)


def _rerender(setup, frame: int):
    mesh_map, mapping, config, networks = setup
    T_start = mapping.T_wc[frame]
    T_query = T_start @ se3_exp(OFFSET)
    image = mesh_map.render(T_query[None], mapping.camera).rgb[0]
    query = networks[0].extract(image)
    result = rerender_candidate(
        mesh_map,
        T_start,
        mapping.camera,
        image,
        query,
        mapping.camera,
        networks,
        config,
        torch.Generator().manual_seed(0),
    )
    return result, T_query


@pytest.mark.parametrize("frame", [0, 3])
def test_the_render_at_a_nearby_pose_gives_the_query_pose_back(setup, frame):
    result, T_query = _rerender(setup, frame)
    candidate = result.candidate
    assert candidate.success and candidate.reference == -1
    assert candidate.num_inliers >= 50 and candidate.coverage >= 0.5
    errors = pose_errors(candidate.T_wc[None].numpy(), T_query[None].numpy(), np.array([True]))
    assert errors.translation_m[0] < 0.05 and errors.rotation_deg[0] < 1.0
    assert result.photometric > 0.8  # the render warped to the right pose matches the query
    assert set(result.wall_ms) == set(RERENDER_STAGES) == set(result.cpu_ms)
    assert all(result.wall_ms[step] > 0.0 for step in RERENDER_STAGES)


def test_bad_poses_and_images_are_refused(setup):
    mesh_map, mapping, config, networks = setup
    image = torch.rand(3, mapping.camera.height, mapping.camera.width)
    query = networks[0].extract(image)
    bad = mapping.T_wc[0].clone()
    bad[0, 3] = math.nan
    args = (mapping.camera, image, query, mapping.camera, networks, config, torch.Generator())
    with pytest.raises(ValueError, match="T_wc"):
        rerender_candidate(mesh_map, bad, *args)
    with pytest.raises(ValueError, match="T_wc"):
        rerender_candidate(mesh_map, mapping.T_wc[0, :3], *args)
    with pytest.raises(ValueError, match="image"):
        rerender_candidate(mesh_map, mapping.T_wc[0], mapping.camera, image[:, 1:], *args[2:])


def test_a_stage_clock_times_the_stages_it_is_given():
    clock = StageClock(("render", "pnp"))
    with clock.measure("render"):
        pass
    assert set(clock.wall_ms) == {"render", "pnp"}
    with pytest.raises(KeyError, match="render"):
        with clock.measure("features"):
            pass
