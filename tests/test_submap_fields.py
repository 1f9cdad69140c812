"""Radiance-field submaps as one RGB-D map: each pose rendered by its serving submap."""

from __future__ import annotations

import pytest
import torch

from diffloc.crossmodal.nerf_map import RadianceFieldMap
from diffloc.crossmodal.submap_fields import SubmapFieldMap, write_submap_fields
from diffloc.geometry.camera import PinholeCamera
from diffloc.maps.nerf.export import export_field
from diffloc.maps.nerf.field import FieldConfig, RadianceField
from diffloc.maps.nerf.sampler import DensityGrid, SamplerConfig
from diffloc.maps.nerf.submaps import Submap, SubmapConfig

CAMERA = PinholeCamera.from_fov(8, 6, 1.2)
CONFIG = SubmapConfig(num_submaps=2)


def _field(seed: int) -> RadianceFieldMap:
    """A random field around the origin, seen as an RGB-D map (code 0, low opacity cut)."""
    torch.manual_seed(seed)
    cfg = FieldConfig(triplane_resolutions=[8], triplane_channels=4, hidden=16, init_std=1.0)
    field = RadianceField(cfg, -2 * torch.ones(3), 2 * torch.ones(3), 2)
    grid = DensityGrid(SamplerConfig(grid_resolution=8, coarse_samples=16, importance_samples=8))
    grid.refresh(field.density, field.normalise, torch.Generator().manual_seed(seed))
    return RadianceFieldMap(field, grid, torch.zeros(cfg.appearance_dim), min_opacity=0.05)


def _at(x: float) -> torch.Tensor:
    """(4, 4) camera at (x, 0, -1.5) looking along +z."""
    pose = torch.eye(4, dtype=torch.float64)
    pose[0, 3], pose[2, 3] = x, -1.5
    return pose


MAPPING = torch.stack([_at(-0.6), _at(-0.4), _at(0.4), _at(0.6)])
SUBMAPS = [
    Submap(0, [0, 1], [0, 1], [-4.0] * 3, [4.0] * 3),
    Submap(1, [2, 3], [2, 3], [-4.0] * 3, [4.0] * 3),
]
POSES = torch.stack([_at(0.5), _at(-0.5), _at(0.45)])
"""Served by submaps 1, 0, 1 (nearest core frames)."""


def test_each_pose_is_rendered_by_the_field_of_its_serving_submap() -> None:
    fields = {0: _field(0), 1: _field(1)}
    rgbd_map = SubmapFieldMap(fields, SUBMAPS, CONFIG, MAPPING)
    assert rgbd_map.serving(POSES).tolist() == [1, 0, 1]
    views = rgbd_map.render(POSES, CAMERA)
    for b, k in enumerate([1, 0, 1]):
        alone = fields[k].render(POSES[b : b + 1], CAMERA)
        other = fields[1 - k].render(POSES[b : b + 1], CAMERA)
        torch.testing.assert_close(views.rgb[b], alone.rgb[0])
        torch.testing.assert_close(views.depth[b], alone.depth[0])
        assert not torch.allclose(views.rgb[b], other.rgb[0])  # the fields differ


def test_the_folder_round_trip_renders_the_same_images(tmp_path) -> None:
    fields = {0: _field(0), 1: _field(1)}
    files = {}
    for k, f in fields.items():
        folder = export_field(tmp_path / f"export_{k}", f.field, f.grid)
        files[k] = {p.name: p.read_bytes() for p in folder.iterdir()}
    write_submap_fields(tmp_path / "map", SUBMAPS, CONFIG, MAPPING, files, min_opacity=0.05)
    loaded = SubmapFieldMap.from_folder(tmp_path / "map")
    assert sorted(loaded.fields) == [0, 1] and loaded.fields[0].min_opacity == 0.05
    torch.testing.assert_close(loaded.mapping_T_wc, MAPPING)
    # The loaded fields render with the mean of their training codes, as RadianceFieldMap does.
    direct = SubmapFieldMap(
        {
            k: RadianceFieldMap(f.field, f.grid, loaded.fields[k].appearance, 0.05)
            for k, f in fields.items()
        },
        SUBMAPS,
        CONFIG,
        MAPPING,
    ).render(POSES, CAMERA)
    again = loaded.render(POSES, CAMERA)
    torch.testing.assert_close(again.rgb, direct.rgb)
    torch.testing.assert_close(again.depth, direct.depth)


def test_a_pose_served_by_an_absent_field_is_a_clear_error() -> None:
    rgbd_map = SubmapFieldMap({0: _field(0)}, SUBMAPS, CONFIG, MAPPING)
    with pytest.raises(ValueError, match=r"served by submaps \[1\], whose fields this map lacks"):
        rgbd_map.render(POSES, CAMERA)


def test_a_field_of_a_submap_the_clustering_lacks_is_refused(tmp_path) -> None:
    with pytest.raises(ValueError, match=r"fields of submaps \[5\]"):
        SubmapFieldMap({5: _field(0)}, SUBMAPS, CONFIG, MAPPING)
    with pytest.raises(ValueError, match=r"fields of submaps \[5\]"):
        write_submap_fields(tmp_path, SUBMAPS, CONFIG, MAPPING, {5: {}}, 0.5)


def test_a_folder_without_its_render_record_names_the_file(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match="render.json does not exist"):
        SubmapFieldMap.from_folder(tmp_path)
