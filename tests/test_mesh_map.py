"""Textured mesh maps of a simulated dataset: built from the point map only, and rendered."""

import math
import shutil

import numpy as np
import pytest
import torch
import trimesh

from diffloc.crossmodal import mesh_map
from diffloc.crossmodal.mesh_map import TexturedMeshConfig, textured_mesh_from_dataset
from diffloc.geometry.camera import PinholeCamera
from diffloc.io import mesh_obj
from diffloc.io.dataset import read_sequence
from diffloc.io.exposure import EXPOSURE_FILE
from diffloc.io.ply import read_point_cloud, write_point_cloud
from diffloc.io.textured_mesh import TexturedMesh
from diffloc.maps.mesh import MeshReconstructionConfig
from diffloc.render.raycast import MeshRenderer
from tests.conftest import copy_dataset

CFG = TexturedMeshConfig(
    reconstruction=MeshReconstructionConfig(poisson_depth=7, target_faces=6000),
    atlas_size=256,
)
TRAIN = np.array([0, 1, 3, 4])


@pytest.fixture(scope="module")
def built(tiny_indoor_dataset):
    return textured_mesh_from_dataset(tiny_indoor_dataset, "lidar_map", CFG, frames=TRAIN)


def test_mesh_map_never_reads_the_ground_truth_mesh_or_exposures(
    built, tiny_indoor_dataset, tmp_path_factory, monkeypatch
):
    root = copy_dataset(tiny_indoor_dataset, tmp_path_factory, "no_truth")
    shutil.rmtree(root / "map" / "mesh")
    (root / "map" / "mesh_changed" / "scene.obj").write_text("poison: not an OBJ\n")
    (root / "mapping" / EXPOSURE_FILE).write_text("poison: not exposures\n")

    def refuse(*args, **kwargs):
        raise AssertionError("the mesh map read the simulator's ground-truth mesh")

    monkeypatch.setattr(mesh_obj, "read_textured_mesh_obj", refuse)
    again = textured_mesh_from_dataset(root, "lidar_map", CFG, frames=TRAIN)
    np.testing.assert_array_equal(again.mesh.vertices, built.mesh.vertices)
    np.testing.assert_array_equal(again.mesh.triangles, built.mesh.triangles)
    np.testing.assert_array_equal(again.mesh.corner_uvs, built.mesh.corner_uvs)  # one atlas
    torch.testing.assert_close(again.exposures, built.exposures, rtol=2e-3, atol=0)
    seq = read_sequence(tiny_indoor_dataset, "mapping")
    first = MeshRenderer(built.mesh).render(seq.T_wc, seq.camera)
    second = MeshRenderer(again.mesh).render(seq.T_wc, seq.camera)
    covered = first.depth > 0
    difference = (first.albedo - second.albedo).abs().mean(dim=1, keepdim=True)[covered]
    assert float(difference.mean()) < 0.01 and float(difference.quantile(0.9)) < 0.03


def test_rendered_mesh_map_resembles_a_held_out_image(built, tiny_indoor_dataset):
    seq = read_sequence(tiny_indoor_dataset, "mapping")
    render = MeshRenderer(built.mesh).render(seq.T_wc[2:3], seq.camera)
    covered = render.depth[0, 0] > 0
    assert float(covered.float().mean()) > 0.25  # five frames map only part of the view
    real = seq.load_rgb(2)[:, covered]
    rendered = render.albedo[0][:, covered]
    psnr = -10 * math.log10(float(((real - rendered) ** 2).mean()))
    assert psnr > 17.0  # a flat grey texture scores about 11 dB here
    grey = torch.full_like(real, float(real.mean()))
    assert psnr > -10 * math.log10(float(((real - grey) ** 2).mean())) + 4.0


def test_exposures_are_estimated_for_the_texturing_frames(built):
    assert built.estimate is not None and bool(built.estimate.linked.all())
    assert built.exposures.shape == (len(TRAIN),)
    # The tiny scene has a fixed exposure: the estimates agree to a few per cent.
    assert float((built.exposures - 1).abs().max()) < 0.05
    assert 0.2 < built.textured_fraction <= 1.0


def test_unknown_point_map_is_refused(tiny_indoor_dataset):
    with pytest.raises(ValueError, match="lidar_map"):
        textured_mesh_from_dataset(tiny_indoor_dataset, "mesh", CFG)


def test_missing_point_map_is_named(tiny_indoor_dataset, tmp_path_factory):
    root = copy_dataset(tiny_indoor_dataset, tmp_path_factory, "no_map")
    (root / "map" / "tls_map.ply").unlink()
    with pytest.raises(FileNotFoundError, match="tls_map.ply"):
        textured_mesh_from_dataset(root, "tls_map", CFG)


def test_point_map_without_normals_is_refused(tiny_indoor_dataset, tmp_path_factory):
    root = copy_dataset(tiny_indoor_dataset, tmp_path_factory, "no_normals")
    path = root / "map" / "lidar_map.ply"
    write_point_cloud(path, read_point_cloud(path).points)
    with pytest.raises(ValueError, match="no normals"):
        textured_mesh_from_dataset(root, "lidar_map", CFG)


def test_frames_outside_the_sequence_are_refused(tiny_indoor_dataset):
    with pytest.raises(ValueError, match="frames"):
        textured_mesh_from_dataset(tiny_indoor_dataset, "lidar_map", CFG, frames=np.array([9]))


def test_views_that_see_no_surface_are_refused(built, tiny_indoor_dataset):
    seq = read_sequence(tiny_indoor_dataset, "mapping")
    away = seq.T_wc[:1].clone()
    away[:, :3, 3] += 1000.0  # far outside the building
    images = torch.zeros(1, 3, seq.camera.height, seq.camera.width)
    geometry = trimesh.Trimesh(built.mesh.vertices, built.mesh.triangles, process=False)
    with pytest.raises(ValueError, match="no mapping image sees the mesh"):
        mesh_map.texture_mesh(geometry, images, away, seq.camera, CFG, "none")


def test_rays_that_miss_the_mesh_have_no_colour_and_no_depth():
    quad = TexturedMesh(  # a 2 x 2 m grey square 5 m ahead: the middle of a 90 deg view
        vertices=np.array([[-1, -1, 5], [1, -1, 5], [1, 1, 5], [-1, 1, 5]], np.float32),
        triangles=np.array([[0, 2, 1], [0, 3, 2]], dtype=np.int32),
        corner_uvs=np.zeros((2, 3, 2), dtype=np.float32),
        material_ids=np.zeros(2, dtype=np.int32),
        object_ids=np.zeros(2, dtype=np.int32),
        textures=[np.full((4, 4, 3), 0.5, dtype=np.float32)],
        material_names=["grey"],
    )
    out = MeshRenderer(quad).render(torch.eye(4)[None], PinholeCamera.from_fov(40, 40, math.pi / 2))
    hit = out.depth[0, 0] > 0
    assert 0.0 < float(hit.float().mean()) < 0.2  # the square covers the centre only
    assert bool((out.albedo[0][:, hit] == 0.5).all()) and bool((out.albedo[0][:, ~hit] == 0).all())
