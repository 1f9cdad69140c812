"""``diffloc task=export_colmap`` on the tiny scene: composes, runs, reads back in pycolmap,
reuses an up-to-date export and exports a changed database again (kills:
``test_colmap_kill.py``)."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
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
from diffloc.io.ply import read_point_cloud, write_point_cloud
from diffloc.maps._storage import EXACT_COLOR_PROPERTIES
from diffloc.maps.surfel import SurfelMap
from diffloc.pipeline.build_map import MapSummary
from diffloc.pipeline.colmap_stage import ColmapExport, ColmapSummary, ExportColmapTaskConfig
from diffloc.pipeline.database_stage import DatabaseConfig, database_dir
from diffloc.pipeline.database_summary import BuiltDatabase
from diffloc.pipeline.hints import Command, StaleStageError
from diffloc.pipeline.stage import open_stage, verified_record
from tests.conftest import compose_config, copy_dataset, run_task


@pytest.fixture(scope="module")
def built(tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "colmap")
    run_task("build_db", root)
    return root


def _export(root: Path, *overrides: str) -> ColmapExport:
    return run_task("export_colmap", root, *overrides)


def test_task_config_composes_with_documented_defaults():
    cfg = to_object(compose_config(["task=export_colmap"]))
    assert cfg.task == ExportColmapTaskConfig()
    assert (cfg.task.database, cfg.task.out_dir, cfg.task.overwrite) == ("database", "", False)


def test_unknown_database_name_is_refused():
    with pytest.raises(ValueError, match="database must be"):
        to_object(compose_config(["task=export_colmap", "task.database=best"]))


def test_export_task_writes_the_built_database_as_a_colmap_model(built: Path):
    export = _export(built)
    summary = export.summary
    db = VisualDatabase.load(export.database)
    model = pycolmap.Reconstruction(export.model)
    assert Path(export.model) == Path(export.database).parent / "colmap" / "database"
    assert len(model.images) == db.num_keyframes == summary.images
    assert summary.colors == "grey (the surfel map has no colours)"
    assert len(model.points3D) == summary.points == int((db.observation_counts() > 0).sum())
    assert sum(p.track.length() for p in model.points3D.values()) == summary.observations
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


def test_a_rerun_reuses_the_export_and_its_record(built: Path, tmp_path: Path):
    out = tmp_path / "sparse"
    first = _export(built, f"task.out_dir={out}")
    record = tmp_path / "export_colmap_sparse.json"
    before = {p.name: p.read_bytes() for p in [record, *out.iterdir()]}
    again = _export(built, f"task.out_dir={out}")
    assert (first.reused, again.reused) == (False, True)
    assert again.summary == first.summary and again.model == str(out)
    assert {p.name: p.read_bytes() for p in [record, *out.iterdir()]} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        ".diffloc.lock",
        "export_colmap_sparse.json",
        "sparse",
    ]


def test_a_database_changed_since_the_export_is_exported_again(
    built: Path, tmp_path_factory: pytest.TempPathFactory
):
    root = copy_dataset(built, tmp_path_factory, "changed_db")
    _export(root, "task.overwrite=true")  # the copy holds the fixture's export
    folder = database_dir(root, DatabaseConfig())
    record = folder / "colmap" / "export_colmap_database.json"
    first = json.loads(record.read_text())
    db = VisualDatabase.load(folder / "database")
    observed = int(torch.nonzero(db.observation_counts() > 0)[0, 0])
    db.point_positions[observed] *= 1.01
    _recommit(folder, "build_db", "database", db.save)
    second = _export(root)
    assert not second.reused
    inputs = json.loads(record.read_text())["stage"]["key"]["inputs"]
    assert inputs["database"] != first["stage"]["key"]["inputs"]["database"]
    model = pycolmap.Reconstruction(second.model)
    np.testing.assert_allclose(
        model.points3D[observed + 1].xyz, db.point_positions[observed].double().numpy()
    )
    verified = verified_record(folder / "colmap", "export_colmap_database", Command("x"))
    assert ColmapSummary.from_record(verified) == second.summary


def test_export_into_a_foreign_non_empty_folder_needs_task_overwrite(built: Path, tmp_path: Path):
    out = tmp_path / "sparse"
    out.mkdir()
    (out / "notes.txt").write_text("not an export")
    with pytest.raises(FileExistsError, match=r"holds no export.*task\.overwrite=true"):
        _export(built, f"task.out_dir={out}")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert _export(built, f"task.out_dir={out}", "task.overwrite=true").model == str(out)
    assert sorted(p.name for p in out.iterdir()) == ["cameras.txt", "images.txt", "points3D.txt"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(FileExistsError, match=r"file exists and is not a folder"):
        _export(built, f"task.out_dir={tmp_path / 'file'}")


def test_export_of_a_database_not_made_says_which_task_to_run(built: Path):
    with pytest.raises(FileNotFoundError, match="task=optimize_db"):
        _export(built, "task.database=optimized")


SUMMARIES = {"build_map": MapSummary, "build_db": BuiltDatabase}


def _recommit(folder: Path, stage: str, rel: str, write: Callable[[Path], None]) -> None:
    """Commit a new output ``rel`` of ``stage`` in ``folder`` through the stage framework,
    under the record's key and with its other outputs (as a stage that wrote it would)."""
    record = verified_record(folder, stage, Command(stage))
    with open_stage(folder, stage, Command(stage)) as run:
        for other in record["stage"]["outputs"]:
            if other != rel:
                copy = shutil.copytree if (folder / other).is_dir() else shutil.copy
                copy(folder / other, run.workdir() / other)
        write(run.workdir() / rel)
        summary = SUMMARIES[stage].from_record(record)
        run.commit(record["stage"]["key"], summary, list(record["stage"]["outputs"]))


def _coloured(surfels: SurfelMap) -> SurfelMap:
    rgb = torch.rand(surfels.centers.shape[0], 3, generator=torch.Generator().manual_seed(0))
    return replace(surfels, colors=rgb)


def test_points_take_the_colours_of_their_anchor_surfels(
    built: Path, tmp_path_factory: pytest.TempPathFactory
):
    root = copy_dataset(built, tmp_path_factory, "coloured")
    surfel_path = root / "map" / "surfel_map.ply"
    surfels = _coloured(SurfelMap.load(surfel_path))
    _recommit(root / "map", "build_map", "surfel_map.ply", surfels.save)
    run_task("build_db", root)  # on the coloured map
    export = _export(root, "task.overwrite=true")  # the copy holds the first export
    assert export.summary.colors == "anchor surfels of map/surfel_map.ply"
    db = VisualDatabase.load(export.database)
    model = pycolmap.Reconstruction(export.model)
    for point_id, point in model.points3D.items():
        anchor = int(db.point_surfels[point_id - 1])
        expected = (
            np.rint(surfels.colors[anchor].double().numpy() * 255) if anchor >= 0 else [128] * 3
        )
        np.testing.assert_array_equal(point.color, expected)


def test_a_surfel_map_edited_after_its_record_is_refused(
    built: Path, tmp_path_factory: pytest.TempPathFactory
):
    root = copy_dataset(built, tmp_path_factory, "edited_map")
    path = root / "map" / "surfel_map.ply"
    _coloured(SurfelMap.load(path)).save(path)
    with pytest.raises(StaleStageError, match=r"surfel_map\.ply is not the file .*build_map"):
        _export(root, "task.overwrite=true")


def test_a_surfel_map_built_again_after_the_database_is_refused(
    built: Path, tmp_path_factory: pytest.TempPathFactory
):
    """The anchors index the map the database was built on: another map's colours would be
    the wrong ones."""
    root = copy_dataset(built, tmp_path_factory, "newer_map")
    path = root / "map" / "surfel_map.ply"
    _recommit(root / "map", "build_map", "surfel_map.ply", _coloured(SurfelMap.load(path)).save)
    with pytest.raises(StaleStageError, match=r"built on another surfel map .*task=build_db"):
        _export(root, "task.overwrite=true")


def test_nan_surfel_colours_are_refused_naming_the_file_and_field(
    built: Path, tmp_path_factory: pytest.TempPathFactory
):
    root = copy_dataset(built, tmp_path_factory, "nan_colours")
    path = root / "map" / "surfel_map.ply"
    cloud = read_point_cloud(path)
    n = cloud.points.shape[0]
    colours = np.full((n, 3), 0.5, dtype=np.float32)
    colours[0, 1] = np.nan
    extra = {**cloud.extra, **dict(zip(EXACT_COLOR_PROPERTIES, colours.T, strict=True))}

    def write(target: Path) -> None:
        write_point_cloud(target, cloud.points, cloud.normals, extra=extra)

    _recommit(root / "map", "build_map", "surfel_map.ply", write)
    with pytest.raises(ValueError, match=rf"{path}: .*colors"):
        _export(root, "task.overwrite=true")


def test_anchor_ids_outside_the_surfel_map_are_refused_naming_the_field(
    built: Path, tmp_path_factory: pytest.TempPathFactory
):
    root = copy_dataset(built, tmp_path_factory, "bad_anchor")
    folder = database_dir(root, DatabaseConfig())
    db = VisualDatabase.load(folder / "database")
    db.point_surfels[0] = SurfelMap.load(root / "map" / "surfel_map.ply").centers.shape[0] + 3
    _recommit(folder, "build_db", "database", db.save)
    with pytest.raises(ValueError, match=r"database/arrays\.npz: field 'point_surfels'"):
        _export(root, "task.overwrite=true")


def test_a_keyframe_beyond_its_sequence_is_refused_naming_the_record(
    built: Path, tmp_path_factory: pytest.TempPathFactory
):
    root = copy_dataset(built, tmp_path_factory, "bad_frame")
    record_path = database_dir(root, DatabaseConfig()) / "build_db.json"
    record = json.loads(record_path.read_text())
    record["keyframe_frames"][0] = 10_000
    record_path.write_text(json.dumps(record))
    with pytest.raises(ValueError, match=r"build_db\.json: keyframe frame 10000 of sequence"):
        _export(root, "task.overwrite=true")
