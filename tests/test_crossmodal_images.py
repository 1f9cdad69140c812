"""``diffloc task=crossmodal map=images``: the mapping images with surfel-map depth as the
database of Algorithm 1 (seed 2's real-image rows), on the tiny mapped scene (5 frames per
sequence, 160x120, fine surfels). Its 5 sparse lidar sweeps leave most pixels without a surfel,
so a right pose has only 15-30 PnP inliers: the localiser's validation (150 inliers at 320x240)
is off and every pose found is the answer, as in seed 2's Algorithm 1."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from diffloc.cli import run
from diffloc.config import compose_config
from diffloc.crossmodal.database import RenderedDatabase
from diffloc.crossmodal.real_images import surfel_depth_views
from diffloc.io.dataset import read_sequence
from diffloc.maps.surfel import SurfelMap
from diffloc.pipeline import crossmodal_images
from diffloc.pipeline.hints import MissingStageError
from tests.conftest import TINY

TASK = [
    *TINY,
    "task=crossmodal",
    "map=images",
    "map.every=2",
    "task.image_scale=1.0",
    "task.sequences=[query_same]",
    "task.localizer.validation=null",  # every pose found is the answer (seed 2)
]
RECORD = Path("crossmodal/images/database/rgbd_database.json")


def _run(dataset: Path, out: Path, *overrides: str) -> dict:
    return run(compose_config([*TASK, f"dataset={dataset}", f"task.out_dir={out}", *overrides]))


@pytest.fixture(scope="module")
def dataset(tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("images") / tiny_indoor_mapped.name
    shutil.copytree(tiny_indoor_mapped, root)
    return root


@pytest.fixture(scope="module")
def first(dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    return _run(dataset, tmp_path_factory.mktemp("first_run"))


def test_surfel_depth_matches_the_true_depth_where_the_map_covers_the_image(tiny_indoor_mapped):
    mapping = read_sequence(tiny_indoor_mapped, "mapping")
    surfels = SurfelMap.load(tiny_indoor_mapped / "map" / "surfel_map.ply")
    frames = [0, 3]
    images = torch.stack([mapping.load_rgb(i) for i in frames])
    views = surfel_depth_views(images, mapping.T_wc[frames], mapping.camera, surfels, 1)
    assert views.rgb.shape == (2, 3, 120, 160) and torch.equal(views.rgb, images)
    depth = views.depth[:, 0]
    covered = depth > 0
    # The tiny scene's 5 sparse lidar sweeps give surfels on 10-15 % of each image.
    assert bool(torch.isfinite(depth).all())
    assert bool((covered.flatten(1).float().mean(1) > 0.05).all())
    truth = torch.stack([mapping.load_depth(i)[0] for i in frames])  # the check only
    error = (depth - truth)[covered & (truth > 0)].abs()
    assert float(error.median()) < 0.02


def test_the_task_localizes_queries_in_the_mapping_images(dataset, first):
    assert first["map"] == "images" and first["database_images"] == 3  # frames 0, 2, 4 of 5
    summary = first["stages"]["database"]
    assert summary["images"] == 3 and summary["every"] == 2
    assert 0.0 < first["hole_share"] < 1.0
    assert set(first["stages"]) == {"database", "localize_query_same"}
    entry = first["sequences"]["query_same"]
    assert entry["queries"] == entry["found"] == entry["accepted"] == 5
    assert entry["rates"]["1m_30deg"] >= 0.4 and entry["retrieval_rate"] >= 0.4
    record = json.loads((dataset / RECORD).read_text())
    assert record["images"] == 3 and "mapping/poses.txt" in record["stage"]["key"]["inputs"]
    assert not any("query_same" in name for name in record["stage"]["key"]["inputs"])


def test_a_second_run_reuses_the_database(dataset, first, tmp_path, monkeypatch):
    before = (dataset / RECORD).read_bytes()

    def refuse(*args, **kwargs):
        raise AssertionError("the database was built again although it was reusable")

    monkeypatch.setattr(crossmodal_images, "surfel_depth_views", refuse)
    again = _run(dataset, tmp_path)
    assert (dataset / RECORD).read_bytes() == before
    assert again["sequences"] == {
        name: {**entry, "files": again["sequences"][name]["files"]}
        for name, entry in first["sequences"].items()
    }


def test_a_dataset_without_a_surfel_map_names_the_build_map_command(tiny_indoor_dataset, tmp_path):
    root = tmp_path / tiny_indoor_dataset.name
    shutil.copytree(tiny_indoor_dataset, root, ignore=shutil.ignore_patterns("surfel_map.ply"))
    with pytest.raises(MissingStageError, match="diffloc task=build_map"):
        _run(root, tmp_path / "out")
    assert not (root / "crossmodal" / "images" / "database" / "rgbd").exists()


def test_a_bad_frame_step_names_its_key():
    with pytest.raises(ValueError, match="map.every must be a positive integer, got 0"):
        run(compose_config(["task=crossmodal", "map=images", "map.every=0"]))


def test_images_of_another_size_than_the_camera_are_refused(tiny_indoor_mapped):
    mapping = read_sequence(tiny_indoor_mapped, "mapping")
    surfels = SurfelMap.load(tiny_indoor_mapped / "map" / "surfel_map.ply")
    with pytest.raises(ValueError, match="images"):
        surfel_depth_views(torch.zeros(1, 3, 60, 80), mapping.T_wc[:1], mapping.camera, surfels)


def test_the_front_camera_database_keeps_its_key(dataset, first):
    record = json.loads((dataset / RECORD).read_text())
    assert record["stage"]["key"]["config"]["images"] == {"every": 2}


def test_a_database_of_the_front_and_side_cameras(tiny_indoor_side_mapped, tmp_path):
    root = tmp_path / tiny_indoor_side_mapped.name
    shutil.copytree(tiny_indoor_side_mapped, root)
    sides = ["mapping", "mapping_left", "mapping_right"]
    results = _run(root, tmp_path / "out", f"map.sequences=[{','.join(sides)}]")
    assert results["database_images"] == 9 and results["map_settings"]["sequences"] == sides
    record = json.loads((root / RECORD).read_text())
    key = record["stage"]["key"]
    assert key["config"]["images"] == {"every": 2, "sequences": sides}
    assert {f"{name}/poses.txt" for name in sides} <= set(key["inputs"])
    db = RenderedDatabase.load(root / RECORD.parent / "rgbd")
    expected = torch.cat([read_sequence(root, name).T_wc[[0, 2, 4]] for name in sides])
    torch.testing.assert_close(db.T_wc.to(expected.dtype), expected, atol=1e-5, rtol=0)
    # The side cameras look where the front one does not: other images.
    assert not torch.equal(db.rgb[0], db.rgb[3]) and not torch.equal(db.rgb[3], db.rgb[6])
    assert results["sequences"]["query_same"]["queries"] == 5
    # The front camera alone again: another key, the database of 3 images made again.
    again = _run(root, tmp_path / "front")
    assert again["database_images"] == 3
    assert json.loads((root / RECORD).read_text())["stage"]["key"]["config"]["images"] == {
        "every": 2
    }


def test_a_missing_sequence_names_it_and_how_to_simulate_side_cameras(dataset, tmp_path):
    with pytest.raises(FileNotFoundError, match=r"no sequence 'mapping_left'.*side_camera_yaw"):
        _run(dataset, tmp_path, "map.sequences=[mapping,mapping_left]")


@pytest.mark.parametrize(
    ("sequences", "message"), [("[]", "at least one"), ("[mapping,mapping]", "repeats")]
)
def test_bad_sequence_lists_are_refused(sequences, message):
    with pytest.raises(ValueError, match=f"map.sequences.*{message}|{message}"):
        run(compose_config(["task=crossmodal", "map=images", f"map.sequences={sequences}"]))
