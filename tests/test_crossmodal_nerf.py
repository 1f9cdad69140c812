"""``diffloc task=crossmodal map=nerf``: the trained submap fields as the rendered database's map.

Tiny scene (160x120, 5 frames a sequence), two submaps trained for 4 steps each with the tiny
field of ``TINY_NERF`` (about a second each); render poses on the TLS map (the tiny lidar map
has no free corridor), renders at 80x60. Stage reuse, a retrained field, a missing or stale
submap, and the one-line error of the ``diffloc`` command.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import pytest
import torch

from diffloc.cli import run
from diffloc.config import compose_config, to_object
from diffloc.crossmodal.database import RenderedDatabase
from diffloc.maps.nerf.renderer import render_image
from diffloc.pipeline import crossmodal_nerf, crossmodal_stage
from diffloc.pipeline.crossmodal_config import NerfMapConfig
from diffloc.pipeline.hints import MissingStageError, StaleStageError
from diffloc.pipeline.nerf_stage import train_nerf_submap
from diffloc.pipeline.stage import output_identity
from tests.conftest import TINY, TINY_NERF, copy_dataset
from tests.test_cli import _diffloc

TASK = [
    "task=crossmodal",
    "map=nerf",
    "map.point_map=tls_map",
    "task.image_scale=0.5",
    "task.sequences=[query_same]",
    "task.every=5",
]
MAP_RECORD = "nerf/map/crossmodal_map.json"
DB_RECORD = "nerf/database/rgbd_database.json"


def _config(dataset: Path, nerf_dir: Path, *overrides: str):
    return compose_config(
        [*TINY, *TASK, *TINY_NERF, f"dataset={dataset}", f"nerf.out_dir={nerf_dir}", *overrides]
    )


def _train(dataset: Path, nerf_dir: Path, submaps: tuple[int, ...], *overrides: str) -> None:
    nerf = to_object(_config(dataset, nerf_dir, *overrides)).nerf
    for k in submaps:
        train_nerf_submap(dataset, dataclasses.replace(nerf, submap=k), False)


def _run(dataset: Path, nerf_dir: Path, out: Path, *overrides: str) -> dict:
    return run(_config(dataset, nerf_dir, f"task.out_dir={out}", *overrides))


def _refuse(*args, **kwargs):
    raise AssertionError("a stage computed although it must not")


def _record(dataset: Path, rel: str) -> dict:
    return json.loads((dataset / "crossmodal" / rel).read_text())


@pytest.fixture(scope="module")
def dataset(tiny_indoor_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return copy_dataset(tiny_indoor_dataset, tmp_path_factory, "crossmodal_nerf")


@pytest.fixture(scope="module")
def nerf_dir(dataset: Path) -> Path:
    _train(dataset, dataset.parent / "nerf", (0, 1))
    return dataset.parent / "nerf"


@pytest.fixture(scope="module")
def first(dataset: Path, nerf_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    return _run(dataset, nerf_dir, tmp_path_factory.mktemp("first"))


def test_map_nerf_composes_and_only_task_crossmodal_takes_it() -> None:
    cfg = to_object(compose_config(["task=crossmodal", "map=nerf", "map.min_opacity=0.3"]))
    assert cfg.map == NerfMapConfig(point_map="lidar_map", min_opacity=0.3)
    with pytest.raises(ValueError, match="task=main cannot use map=nerf"):
        run(compose_config(["task=main", "map=nerf"]))
    with pytest.raises(ValueError, match=r"map.min_opacity must be in \(0, 1\]"):
        run(compose_config(["task=crossmodal", "map=nerf", "map.min_opacity=0"]))


def test_the_database_has_a_render_per_pose_with_depth_where_the_field_is_opaque(
    dataset, nerf_dir, first
):
    stages = first["stages"]
    assert first["database_images"] == stages["poses"]["poses"] == stages["database"]["images"]
    assert stages["map"]["served"] == [0, 1]
    assert sum(stages["map"]["poses_served"]) == first["database_images"]
    assert stages["map"]["field_steps"] == [4, 4]
    assert first["image_size"] == "80x60" and 0.0 < first["hole_share"] < 1.0
    assert first["sequences"]["query_same"]["queries"] == 1
    db = RenderedDatabase.load(dataset / "crossmodal" / "nerf" / "database" / "rgbd")
    assert bool(torch.isfinite(db.depth).all())
    rgbd_map = crossmodal_nerf.SubmapFieldMap.from_folder(
        dataset / "crossmodal" / "nerf" / "map" / "fields"
    )
    serving = rgbd_map.serving(db.T_wc)
    for i in range(0, db.num_images, 12):  # the database depth is the serving field's
        field = rgbd_map.fields[int(serving[i])]
        ref = render_image(field.field, field.grid, db.camera, db.T_wc[i], field.appearance)
        opaque = ref["opacity"] >= 0.5
        torch.testing.assert_close(db.depth[i][opaque], ref["depth"][opaque])
        assert bool((db.depth[i][~opaque] == 0).all())


def test_a_second_run_reuses_every_stage(dataset, nerf_dir, first, tmp_path, monkeypatch):
    before = {rel: _record(dataset, rel) for rel in (MAP_RECORD, DB_RECORD)}
    monkeypatch.setattr(crossmodal_nerf, "write_submap_fields", _refuse)
    monkeypatch.setattr(crossmodal_stage, "render_database", _refuse)
    monkeypatch.setattr(crossmodal_stage, "RenderedDatabaseLocalizer", _refuse)
    again = _run(dataset, nerf_dir, tmp_path)
    assert {rel: _record(dataset, rel) for rel in before} == before
    assert again["sequences"] == {
        name: {**entry, "files": again["sequences"][name]["files"]}
        for name, entry in first["sequences"].items()
    }


def test_a_missing_submap_stops_before_rendering_and_names_the_training(
    dataset, first, tmp_path, monkeypatch
):
    partial = tmp_path / "nerf"
    _train(dataset, partial, (1,))  # submap 0 serves a render pose but is not trained
    before = _record(dataset, MAP_RECORD)
    monkeypatch.setattr(crossmodal_nerf, "write_submap_fields", _refuse)
    monkeypatch.setattr(crossmodal_stage, "render_database", _refuse)
    expected = re.escape(
        f"{partial}/submap_0/train_nerf.json is missing: run "
        f"`diffloc task=train_nerf dataset={dataset} nerf.submap=0` first"
    )
    with pytest.raises(MissingStageError, match=expected):
        _run(dataset, partial, tmp_path / "out")
    assert _record(dataset, MAP_RECORD) == before


def test_a_field_trained_with_other_settings_is_refused(dataset, nerf_dir, first, tmp_path):
    with pytest.raises(
        StaleStageError,
        match=r"submap_0/train_nerf.json holds a field trained with other nerf\.\* settings.*"
        r"`diffloc task=train_nerf .*nerf\.submap=0`",
    ):
        _run(dataset, nerf_dir, tmp_path, "nerf.epochs=3")


def test_a_retrained_field_makes_the_map_and_the_database_again(dataset, first, tmp_path):
    other = tmp_path / "nerf"
    _train(dataset, other, (0, 1), "nerf.train.seed=1")
    before = {rel: _record(dataset, rel) for rel in (MAP_RECORD, DB_RECORD)}
    _run(dataset, other, tmp_path / "out", "nerf.train.seed=1")
    after = {rel: _record(dataset, rel) for rel in before}
    field = json.loads((other / "submap_1" / "train_nerf.json").read_text())
    assert after[MAP_RECORD]["stage"]["key"]["inputs"]["field_1"] == output_identity(field, "field")
    assert after[MAP_RECORD]["stage"]["key"] != before[MAP_RECORD]["stage"]["key"]
    fields = output_identity(after[MAP_RECORD], "fields")
    assert fields != output_identity(before[MAP_RECORD], "fields")
    assert after[DB_RECORD]["stage"]["key"]["inputs"]["map"] == fields


def test_the_command_prints_the_training_to_run_in_one_line(dataset, tmp_path):
    args = [*TINY, *TASK, *TINY_NERF, f"dataset={dataset}", f"nerf.out_dir={tmp_path / 'none'}"]
    done = _diffloc(*args, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert done.returncode == 1
    assert done.stderr.count("\n") == 1 and done.stderr.startswith("error: "), done.stderr
    line = done.stderr
    assert "is missing: run `diffloc task=train_nerf " in line and "nerf.submap=0` first" in line
    assert "map=nerf" not in line and "map.point_map" not in line and "task." not in line
    assert f"nerf.out_dir={tmp_path / 'none'}" in line and "nerf.epochs=2" in line
