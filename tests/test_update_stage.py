"""The database update stage on the tiny scene: counts, culling, files and relocalisation."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from diffloc.database.database import VisualDatabase
from diffloc.features.local import OrbConfig
from diffloc.io.dataset import read_sequence
from diffloc.pipeline.database_select import check_database_name, select_database, updated_dir
from diffloc.pipeline.database_stage import DatabaseConfig, db_overrides, perturb_positions
from diffloc.pipeline.reloc_stage import RelocStageConfig
from diffloc.pipeline.update_stage import UpdateSummary, UpdateTaskConfig
from diffloc.reloc.retrieval import load_retriever
from tests.conftest import copy_dataset
from tests.conftest import run_task as _run


@pytest.fixture(scope="module")
def built(tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny dataset with its surfel map and built database (no noise)."""
    root = copy_dataset(tiny_indoor_mapped, tmp_path_factory, "update")
    _run("build_db", root)
    return root


@pytest.fixture(scope="module")
def updated(built: Path) -> dict:
    return _run("update_db", built, "task.sequence=query_lane")


def test_update_adds_keyframes_and_points_and_records_the_saved_counts(built: Path, updated: dict):
    base = VisualDatabase.load(select_database(built, DatabaseConfig(), "database").path)
    stage = updated_dir(built, DatabaseConfig(), "query_lane")
    db = VisualDatabase.load(stage / "database")
    images = len(read_sequence(built, "query_lane"))
    before, added, after = updated.before, updated.after_adding, updated.after_culling
    culled = updated.culled
    assert updated.images == images
    assert before == {"keyframes": base.num_keyframes, "map_points": base.num_points}
    assert added["keyframes"] == base.num_keyframes + images
    assert added["map_points"] > base.num_points
    assert after == {"keyframes": db.num_keyframes, "map_points": db.num_points}
    assert after["keyframes"] == added["keyframes"] - culled["keyframes"]
    removed = culled["points_unconfirmed"] + culled["points_of_culled_keyframes"]
    assert after["map_points"] == added["map_points"] - removed
    assert db.num_keyframes > base.num_keyframes and db.num_points > base.num_points
    assert updated.stats == db.stats()
    assert UpdateSummary.from_record(json.loads((stage / "update_db.json").read_text())) == updated
    # Every keyframe's pose is the pose of the frame it names (no noise: the true pose).
    sources = updated.keyframe_sources
    assert len(sources) == db.num_keyframes
    poses = {name: read_sequence(built, name).T_wc for name in ("mapping", "query_lane")}
    assert torch.equal(db.T_wc, torch.stack([poses[name][frame] for name, frame in sources]))
    assert {name for name, _ in sources} == {"mapping", "query_lane"}
    assert updated.kf_pos_rmse_m == 0.0
    assert set(updated.timings_ms) == {"load", "features", "update", "save"}


def test_the_update_matches_points_of_the_original_database(built: Path, updated: dict):
    db = VisualDatabase.load(updated.database)
    base_keyframes = sum(name == "mapping" for name, _ in updated.keyframe_sources)
    obs = db.observations()
    old = torch.unique(obs[obs[:, 0] < base_keyframes, 2])
    new_obs = obs[obs[:, 0] >= base_keyframes]
    assert int(torch.isin(new_obs[:, 2], old).sum()) > 20


def test_the_updated_database_round_trips_through_save_and_load(updated: dict, tmp_path: Path):
    db = VisualDatabase.load(updated.database)
    db.save(tmp_path / "again")
    again = VisualDatabase.load(tmp_path / "again")
    for name, value in vars(db).items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(value, getattr(again, name)), name
    assert again.stats() == updated.stats


def test_updating_with_the_database_sequence_again_culls_its_duplicates(built: Path):
    """The same images at the same poses make every point observed by many keyframes: the
    90 %/3-observer rule must remove keyframes, including ones of the original database."""
    summary = _run("update_db", built, "task.sequence=mapping")
    culled = summary.culled
    assert culled["keyframes"] >= 1 and culled["keyframes_of_base"] >= 1
    assert summary.after_culling["keyframes"] < summary.after_adding["keyframes"]
    frames = [frame for _, frame in summary.keyframe_sources]
    assert len(frames) == VisualDatabase.load(summary.database).num_keyframes


def test_noisy_update_poses_come_from_their_own_seed(built: Path):
    noisy = ("db.noise_sigma=0.05", "db.builder.association=epipolar")
    _run("build_db", built, *noisy)
    summary = _run("update_db", built, *noisy, "task.sequence=query_lane", "task.noise_seed=7")
    db = VisualDatabase.load(summary.database)
    truth = read_sequence(built, "query_lane").T_wc
    expected = perturb_positions(truth, 0.05, torch.Generator().manual_seed(7))
    added = [k for k, (name, _) in enumerate(summary.keyframe_sources) if name == "query_lane"]
    frames = [summary.keyframe_sources[k][1] for k in added]
    assert added and torch.equal(db.T_wc[added], expected[frames])
    assert summary.kf_pos_rmse_m > 0.01


def test_a_missing_database_names_the_command_with_the_users_overrides(built: Path):
    with pytest.raises(FileNotFoundError, match=r"task=build_db dataset=\S+ db.noise_sigma=0.3"):
        _run("update_db", built, "db.noise_sigma=0.3")
    with pytest.raises(FileNotFoundError, match="task=update_db .*task.sequence=query_same"):
        select_database(built, DatabaseConfig(), "updated_query_same")
    with pytest.raises(ValueError, match="no sequence .query_missing."):
        _run("update_db", built, "task.sequence=query_missing")


def test_database_names_are_validated():
    for name in ("database", "optimized", "updated_query_lane"):
        assert check_database_name(name) == name
        assert RelocStageConfig(database=name).database == name
    for name in ("updated_", "updated_a/b", "optimised", ""):
        with pytest.raises(ValueError, match="updated_<sequence>"):
            RelocStageConfig(database=name)
    with pytest.raises(ValueError, match="task.sequence"):
        UpdateTaskConfig(sequence="")
    orb = DatabaseConfig(features=OrbConfig(), pose_prior_sigma_m=0.2)
    assert db_overrides("d", orb) == (
        "dataset=d",
        "db.pose_prior_sigma_m=0.2",
        "features=orb",
    )


def test_relocalisation_against_the_updated_database(built: Path, updated: dict, tmp_path: Path):
    out = tmp_path / "reloc"
    results = _run(
        "relocalize",
        built,
        "reloc.database=updated_query_lane",
        "reloc.sequences=[query_same]",
        f"task.out_dir={out}",
    )
    assert results["database"] == updated.database
    assert results["queries"] == len(read_sequence(built, "query_same"))
    stage = updated_dir(built, DatabaseConfig(), "query_lane")
    retriever = json.loads((stage / "retriever_netvlad" / "retriever.json").read_text())
    assert retriever["kind"] == "netvlad"
    keyframes = VisualDatabase.load(stage / "database").num_keyframes
    assert load_retriever(stage / "retriever_netvlad").index.descriptors.shape[0] == keyframes
