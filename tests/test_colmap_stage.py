"""``diffloc task=export_colmap`` on the tiny scene: composes, runs, reads back in pycolmap."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch

from diffloc.config import to_object
from diffloc.database.colmap import reprojection_errors
from diffloc.database.database import VisualDatabase
from diffloc.geometry.se3 import invert
from diffloc.maps.surfel import SurfelMap
from diffloc.pipeline.colmap_stage import ExportColmapTaskConfig
from tests.conftest import compose_config, copy_dataset, run_task


@pytest.fixture(scope="module")
def built(tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "colmap")
    run_task("build_db", root)
    return root


def _export(root: Path, *overrides: str) -> dict:
    return run_task("export_colmap", root, *overrides)


def test_task_config_composes_with_documented_defaults():
    cfg = to_object(compose_config(["task=export_colmap"]))
    assert cfg.task == ExportColmapTaskConfig()
    assert (cfg.task.database, cfg.task.out_dir, cfg.task.overwrite) == ("database", "", False)


def test_unknown_database_name_is_refused():
    with pytest.raises(ValueError, match="database must be"):
        to_object(compose_config(["task=export_colmap", "task.database=best"]))


def test_export_task_writes_the_built_database_as_a_colmap_model(built: Path):
    summary = _export(built)
    db = VisualDatabase.load(summary["database"])
    model = pycolmap.Reconstruction(summary["model"])
    assert Path(summary["model"]) == Path(summary["database"]).parent / "colmap" / "database"
    assert len(model.images) == db.num_keyframes == summary["images"]
    assert summary["colors"] == "grey (the surfel map has no colours)"
    assert len(model.points3D) == summary["points"] == int((db.observation_counts() > 0).sum())
    assert sum(p.track.length() for p in model.points3D.values()) == summary["observations"]
    T_cw = invert(db.T_wc).numpy()
    for k in range(db.num_keyframes):
        image = model.images[k + 1]
        assert (built / image.name).is_file()  # names are relative to the dataset folder
        np.testing.assert_allclose(image.cam_from_world().matrix(), T_cw[k, :3], atol=1e-9)
    errors = []
    for point in model.points3D.values():
        for element in point.track.elements:
            image = model.images[element.image_id]
            projected = image.camera.img_from_cam(image.cam_from_world() * point.xyz)
            errors.append(np.linalg.norm(projected - image.points2D[element.point2D_idx].xy))
    assert np.mean(errors) == pytest.approx(float(reprojection_errors(db).mean()), abs=1e-6)


def test_export_into_a_non_empty_folder_needs_task_overwrite(built: Path, tmp_path: Path):
    out = tmp_path / "sparse"
    _export(built, f"task.out_dir={out}")
    before = (out / "points3D.txt").read_bytes()
    with pytest.raises(FileExistsError, match=r"not empty.*task\.overwrite=true"):
        _export(built, f"task.out_dir={out}")
    summary = _export(built, f"task.out_dir={out}", "task.overwrite=true")
    assert summary["model"] == str(out)
    assert (out / "points3D.txt").read_bytes() == before


def test_export_of_a_database_not_made_says_which_task_to_run(built: Path):
    with pytest.raises(FileNotFoundError, match="task=optimize_db"):
        _export(built, "task.database=optimized")


def test_points_take_the_colours_of_their_anchor_surfels(built: Path, tmp_path: Path):
    root = tmp_path / "coloured"
    shutil.copytree(built, root)
    surfel_path = root / "map" / "surfel_map.ply"
    surfels = SurfelMap.load(surfel_path)
    rgb = torch.rand(surfels.centers.shape[0], 3, generator=torch.Generator().manual_seed(0))
    replace(surfels, colors=rgb).save(surfel_path)
    summary = _export(root, "task.overwrite=true")  # the copy holds the first export
    assert summary["colors"] == f"anchor surfels of {surfel_path}"
    db = VisualDatabase.load(summary["database"])
    model = pycolmap.Reconstruction(summary["model"])
    for point_id, point in model.points3D.items():
        anchor = int(db.point_surfels[point_id - 1])
        expected = np.rint(rgb[anchor].double().numpy() * 255) if anchor >= 0 else [128] * 3
        np.testing.assert_array_equal(point.color, expected)
