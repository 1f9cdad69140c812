"""The map stage: surfel map, coloured point maps and preview from a dataset folder."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch

from diffloc.cli import run
from diffloc.config import to_object
from diffloc.io.dataset import read_sequence
from diffloc.maps.pointcloud import PointMap
from diffloc.maps.surfel import SurfelMap
from diffloc.pipeline.build_map import BuildMapConfig, build_maps, render_views
from tests.conftest import FINE_SURFELS, TINY, compose_config


@pytest.fixture(scope="module")
def built(tiny_indoor_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("build") / "indoor"
    shutil.copytree(tiny_indoor_dataset, root)
    build_maps(root, BuildMapConfig(), FINE_SURFELS, show_progress=False)
    return root


def test_writes_surfel_map_point_maps_and_preview(built: Path):
    surfels = SurfelMap.load(built / "map" / "surfel_map.ply")
    assert len(surfels) > 10_000
    assert (surfels.radii >= 0.01 - 1e-6).all() and (surfels.radii <= 0.04 + 1e-6).all()
    for name in ("point_map", "tls_point_map"):
        cloud = PointMap.load(built / "map" / f"{name}.ply")
        assert len(cloud) > 1000
        assert ((cloud.colors >= 0) & (cloud.colors <= 1)).all()
    assert (built / "map" / "surfel_preview.png").stat().st_size > 10_000


def test_rendered_surfel_depth_matches_the_true_depth(built: Path):
    surfels = SurfelMap.load(built / "map" / "surfel_map.ply")
    seq = read_sequence(built, "mapping")
    camera = seq.camera.to(torch.float32)
    _, depth = render_views(surfels, seq.T_wc, camera, batch=4)
    truth = torch.stack([seq.load_depth(i) for i in range(len(seq))])
    both = (depth > 0) & (truth > 0)
    assert int(both.sum()) > 5000  # the tiny dataset's lidar is sparse: ~13% of pixels
    error = (depth - truth).abs()[both]
    assert float(error.median()) <= 0.02


def test_second_run_reuses_the_maps(built: Path):
    summary_file = built / "map" / "build_map.json"
    before = summary_file.stat().st_mtime_ns
    build_maps(built, BuildMapConfig(), FINE_SURFELS, show_progress=False)
    assert summary_file.stat().st_mtime_ns == before


def test_build_map_task_from_the_command_line_config(built: Path, tmp_path: Path):
    root = tmp_path / "copy"
    shutil.copytree(built, root)
    (root / "map" / "build_map.json").unlink()
    cfg = compose_config(
        TINY + ["task=build_map", f"dataset={root}", "task.point_maps=[]", "task.preview_frames=1"]
    )
    summary = run(cfg)
    assert summary.surfels > 1000
    assert to_object(cfg.map).mean_radius_m == 0.03
    assert "point_map" not in summary.point_maps


def test_a_dataset_without_lidar_is_a_clear_error(built: Path, tmp_path: Path):
    root = tmp_path / "nolidar"
    shutil.copytree(built, root)
    shutil.rmtree(root / "mapping" / "lidar")
    (root / "mapping" / "lidar").mkdir()
    with pytest.raises((ValueError, FileNotFoundError)):
        build_maps(
            root, BuildMapConfig(use_sweeps=True, clouds=[], overwrite=True), FINE_SURFELS, False
        )


def test_surfel_ids_are_stable_under_sub_pixel_pose_changes(built: Path):
    surfels = SurfelMap.load(built / "map" / "surfel_map.ply")
    seq = read_sequence(built, "mapping")
    camera = seq.camera.to(torch.float32).scaled(4.0)  # 640x480, as the pipeline renders
    T_wc = seq.T_wc[:2].to(torch.float32)
    # A quarter-pixel rotation about the camera's y axis plus a millimetre of translation.
    angle = 0.25 / float(camera.fx)
    nudge = torch.eye(4)
    nudge[0, 0] = nudge[2, 2] = torch.cos(torch.tensor(angle))
    nudge[0, 2], nudge[2, 0] = torch.sin(torch.tensor(angle)), -torch.sin(torch.tensor(angle))
    nudge[:3, 3] = torch.tensor([0.001, 0.0, 0.0])
    ids, _ = render_views(surfels, T_wc, camera, batch=2)
    moved, _ = render_views(surfels, T_wc @ nudge, camera, batch=2)
    both = (ids >= 0) & (moved >= 0)
    assert int(both.sum()) > 1000
    same = float((ids == moved)[both].float().mean())
    jump = (surfels.centers[ids[both]] - surfels.centers[moved[both]]).norm(dim=-1)
    adjacent = float((jump <= 2 * surfels.radii.max()).float().mean())
    assert same > 0.8, same
    assert adjacent > 0.95, adjacent
