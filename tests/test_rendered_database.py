"""RGB-D maps (point cloud, mesh) and the RGB-D database: known renders, round trip, bad input."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.crossmodal.database import (
    DatabaseConfig,
    RenderedDatabase,
    build_database,
    render_database,
)
from diffloc.crossmodal.synthesize import (
    RGBD,
    MeshMap,
    PointCloudMap,
    hole_fraction,
    render_views,
)
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.dataset import read_sequence
from diffloc.io.mesh_obj import read_textured_mesh_obj
from diffloc.io.textured_mesh import TexturedMesh
from diffloc.render.point_sizes import PointSizes

CAMERA = PinholeCamera.from_fov(64, 48, math.pi / 2)
SMALL_DB = DatabaseConfig(max_keypoints=256, netvlad_clusters=4, samples_per_image=50)


def _quad(z: float, half: float, color: float) -> TexturedMesh:
    """A square of side ``2 half`` at world z = ``z`` facing -z (towards the origin)."""
    vertices = np.array(
        [[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], np.float32
    )
    triangles = np.array([[0, 2, 1], [0, 3, 2]], np.int32)
    return TexturedMesh(
        vertices=vertices,
        triangles=triangles,
        corner_uvs=np.zeros((2, 3, 2), np.float32),
        material_ids=np.zeros(2, np.int32),
        object_ids=np.zeros(2, np.int32),
        textures=[np.full((4, 4, 3), color, np.float32)],
        material_names=["flat"],
    )


@pytest.fixture(scope="module")
def tiny_mesh_views(tiny_indoor_dataset):
    """The tiny scene's mesh and its mapping poses / camera (160x120)."""
    mesh = read_textured_mesh_obj(tiny_indoor_dataset / "map" / "mesh" / "scene.obj")
    mapping = read_sequence(tiny_indoor_dataset, "mapping")
    return MeshMap(mesh), mapping.T_wc, mapping.camera


@pytest.fixture(scope="module")
def tiny_database(tiny_mesh_views):
    mesh_map, T_wc, camera = tiny_mesh_views
    return render_database(mesh_map, T_wc[:3], camera, SMALL_DB, "tiny mesh")


def test_point_cloud_map_renders_a_point_at_its_depth_and_colour():
    cloud = PointCloudMap(
        torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[0.2, 0.4, 0.6]]), PointSizes.fixed(3)
    )
    out = cloud.render(torch.eye(4)[None], CAMERA)
    assert out.rgb.shape == (1, 3, 48, 64) and out.depth.shape == (1, 1, 48, 64)
    hit = out.depth[0, 0] > 0
    assert int(hit.sum()) == 9
    assert torch.allclose(out.depth[0, 0][hit], torch.tensor(2.0))
    assert torch.allclose(out.rgb[0][:, hit].T, torch.tensor([0.2, 0.4, 0.6]).expand(9, 3))
    assert torch.allclose(hole_fraction(out.depth), torch.tensor([1 - 9 / (48 * 64)]))


def test_mesh_map_renders_a_plane_at_its_depth_and_albedo():
    out = MeshMap(_quad(3.0, 10.0, 0.25)).render(torch.eye(4)[None], CAMERA)
    assert torch.allclose(out.depth, torch.full_like(out.depth, 3.0), atol=1e-5)
    assert torch.allclose(out.rgb, torch.full_like(out.rgb, 0.25), atol=1e-3)
    assert float(hole_fraction(out.depth)) == 0.0


def test_mesh_map_clamps_the_albedo_to_one_and_keeps_the_renderer_depth():
    mesh_map = MeshMap(_quad(3.0, 10.0, 1.5))  # a texture brighter than 1
    T_wc = torch.eye(4)[None].repeat(2, 1, 1)
    T_wc[1, 0, 3] = 0.5  # two views: the clamp works on the batch's own buffer
    out = mesh_map.render(T_wc, CAMERA)
    albedo, depth = mesh_map.renderer.render_rgbd(T_wc, CAMERA)
    assert torch.equal(out.rgb, albedo.clamp(0.0, 1.0)) and torch.equal(out.depth, depth)
    assert float(out.rgb.max()) == 1.0


def test_mesh_map_leaves_holes_where_nothing_is_hit():
    out = MeshMap(_quad(3.0, 10.0, 0.25)).render(torch.eye(4)[None], CAMERA)
    behind = torch.eye(4)[None].clone()
    behind[0, 2, 2] = -1.0  # looking along -z (a proper rotation: x flipped too)
    behind[0, 0, 0] = -1.0
    empty = MeshMap(_quad(3.0, 10.0, 0.25)).render(behind, CAMERA)
    assert float(hole_fraction(empty.depth)) == 1.0
    assert float(empty.rgb.abs().max()) == 0.0
    assert float(hole_fraction(out.depth)) == 0.0


def test_render_views_batches_give_the_same_images(tiny_mesh_views):
    mesh_map, T_wc, camera = tiny_mesh_views
    one = render_views(mesh_map, T_wc, camera, batch_size=len(T_wc))
    batched = render_views(mesh_map, T_wc, camera, batch_size=2)
    assert torch.equal(one.rgb, batched.rgb) and torch.equal(one.depth, batched.depth)


def test_hole_fraction_counts_pixels_without_depth():
    depth = torch.tensor([[[[0.0, 2.0], [1.0, 0.0]]], [[[1.0, 1.0], [1.0, 1.0]]]])
    assert torch.equal(hole_fraction(depth), torch.tensor([0.5, 0.0]))


def test_empty_point_cloud_is_rejected():
    with pytest.raises(ValueError, match="empty"):
        PointCloudMap(torch.zeros(0, 3), torch.zeros(0, 3), PointSizes())


def test_nan_points_are_rejected():
    with pytest.raises(ValueError, match="points"):
        PointCloudMap(torch.tensor([[0.0, math.nan, 1.0]]), torch.zeros(1, 3), PointSizes())


def test_render_views_rejects_nan_poses(tiny_mesh_views):
    mesh_map, T_wc, camera = tiny_mesh_views
    bad = T_wc[:2].clone()
    bad[1, 0, 3] = math.nan
    with pytest.raises(ValueError, match="T_wc"):
        render_views(mesh_map, bad, camera)


def test_render_views_rejects_no_poses(tiny_mesh_views):
    mesh_map, _, camera = tiny_mesh_views
    with pytest.raises(ShapeError, match="at least one pose"):
        render_views(mesh_map, torch.zeros(0, 4, 4), camera)


def test_database_holds_features_descriptors_and_holes(tiny_database):
    db = tiny_database
    assert db.num_images == 3 and len(db.features) == 3
    assert db.global_descriptors.shape == (3, db.netvlad.output_dim)
    assert torch.allclose(db.global_descriptors.norm(dim=1), torch.ones(3))
    assert all(0 < len(f) <= 256 for f in db.features)
    assert torch.equal(db.holes, hole_fraction(db.depth))


def test_database_round_trip(tiny_database, tmp_path):
    db = tiny_database
    loaded = RenderedDatabase.load(db.save(tmp_path / "db"))
    assert torch.equal(loaded.T_wc, db.T_wc)
    assert torch.equal(loaded.depth, db.depth)
    assert (loaded.rgb - db.rgb).abs().max() <= 0.5 / 255 + 1e-6
    assert torch.equal(loaded.global_descriptors, db.global_descriptors)
    for a, b in zip(loaded.features, db.features, strict=True):
        for name in ("keypoints", "scores", "descriptors", "sizes"):
            assert torch.equal(getattr(a, name), getattr(b, name))
    for key, value in db.netvlad.state_dict().items():
        assert torch.equal(loaded.netvlad.state_dict()[key], value)
    assert torch.equal(loaded.camera.K, db.camera.K)
    assert (loaded.camera.width, loaded.camera.height) == (db.camera.width, db.camera.height)
    assert loaded.source == "tiny mesh"
    meta = json.loads((tmp_path / "db" / "database.json").read_text())
    assert meta["format_version"] == 1 and meta["num_images"] == 3
    assert loaded.real.tolist() == [False, False, False]  # renders


def test_real_image_flags_round_trip_and_older_files_read_as_renders(tiny_database, tmp_path):
    flags = torch.tensor([True, False, True])
    marked = dataclasses.replace(tiny_database, real=flags)
    assert torch.equal(RenderedDatabase.load(marked.save(tmp_path / "db")).real, flags)
    npz = tmp_path / "db" / "database.npz"
    arrays = dict(np.load(npz))
    del arrays["real"]  # a database written before the flags existed
    np.savez(npz, **arrays)
    assert RenderedDatabase.load(tmp_path / "db").real.tolist() == [False, False, False]
    with pytest.raises(ShapeError, match="real"):
        dataclasses.replace(tiny_database, real=flags[:2])
    with pytest.raises(ValueError, match="real must be a bool tensor"):
        dataclasses.replace(tiny_database, real=flags.long())


def test_save_does_not_overwrite(tiny_database, tmp_path):
    tiny_database.save(tmp_path / "db")
    with pytest.raises(FileExistsError):
        tiny_database.save(tmp_path / "db")


def test_load_names_a_missing_file(tiny_database, tmp_path):
    path = tiny_database.save(tmp_path / "db")
    (path / "database.npz").unlink()
    with pytest.raises(FileNotFoundError, match="database.npz"):
        RenderedDatabase.load(path)


def test_load_rejects_another_format_version(tiny_database, tmp_path):
    path = tiny_database.save(tmp_path / "db")
    meta = json.loads((path / "database.json").read_text())
    (path / "database.json").write_text(json.dumps({**meta, "format_version": 99}))
    with pytest.raises(ValueError, match="format_version"):
        RenderedDatabase.load(path)


def test_load_rejects_counts_that_disagree(tiny_database, tmp_path):
    path = tiny_database.save(tmp_path / "db")
    meta = json.loads((path / "database.json").read_text())
    (path / "database.json").write_text(json.dumps({**meta, "num_images": 4}))
    with pytest.raises(ValueError, match="database.npz.*4 images"):
        RenderedDatabase.load(path)


def test_load_rejects_nan_poses(tiny_database, tmp_path):
    path = tiny_database.save(tmp_path / "db")
    with np.load(path / "database.npz") as archive:
        arrays = dict(archive)
    arrays["T_wc"][1, 0, 3] = np.nan
    np.savez(path / "database.npz", **arrays)
    with pytest.raises(ValueError, match="database.npz.*NaN"):
        RenderedDatabase.load(path)


def test_empty_database_is_rejected(tiny_database):
    db = tiny_database
    views = RGBD(db.rgb[:0], db.depth[:0])
    with pytest.raises(ValueError, match="empty"):
        build_database(views, db.T_wc[:0], db.camera, SMALL_DB)


def test_database_rejects_nan_poses(tiny_database):
    db = tiny_database
    bad = db.T_wc.clone()
    bad[0, 1, 3] = math.nan
    with pytest.raises(ValueError, match="NaN"):
        build_database(RGBD(db.rgb, db.depth), bad, db.camera, SMALL_DB)


def test_database_rejects_missing_depth(tiny_database):
    db = tiny_database
    with pytest.raises(ShapeError, match="depth"):
        RenderedDatabase(
            db.T_wc, db.rgb, db.depth[:2], db.camera, db.features, db.global_descriptors, db.netvlad
        )


def test_database_rejects_negative_depth(tiny_database):
    db = tiny_database
    with pytest.raises(ValueError, match="depth"):
        RenderedDatabase(
            db.T_wc, db.rgb, -db.depth, db.camera, db.features, db.global_descriptors, db.netvlad
        )
