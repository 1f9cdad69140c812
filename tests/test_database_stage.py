"""The database stages on the tiny scene: build (with and without pose noise) and optimise."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from torch.testing import assert_close

from diffloc.config import to_object
from diffloc.database.builder import BuilderConfig
from diffloc.database.database import VisualDatabase
from diffloc.features.local import OrbConfig
from diffloc.geometry.rig import SensorRig
from diffloc.geometry.se3 import invert, se3_exp
from diffloc.io.calib import read_calib, write_calib
from diffloc.io.dataset import read_sequence
from diffloc.maps.surfel import SurfelMap
from diffloc.optim.rig_calibration import calibrate_rig
from diffloc.optim.surfel_cost import replace_map_points
from diffloc.pipeline.build_map import BuildMapConfig, build_maps
from diffloc.pipeline.config_record import config_record
from diffloc.pipeline.database_stage import (
    DatabaseConfig,
    OptimisationRejectedWarning,
    database_dir,
    database_poses,
    keyframe_position_rmse,
    perturb_positions,
)
from diffloc.pipeline.database_summary import BuiltDatabase, OptimizedDatabase
from diffloc.pipeline.hints import Command
from diffloc.pipeline.rig_stage import RigCalibrationSummary
from diffloc.pipeline.stage import open_stage
from diffloc.sim.dataset import simulate_dataset
from tests.conftest import FINE_SURFELS, TINY, compose_config, copy_dataset, scene_config
from tests.conftest import run_task as _run


@pytest.fixture(scope="module")
def mapped(tiny_indoor_mapped: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return copy_dataset(tiny_indoor_mapped, tmp_path_factory, "db")


def test_perturb_positions_moves_positions_only_by_the_requested_sigma():
    T = torch.eye(4, dtype=torch.float64).repeat(20000, 1, 1)
    noisy = perturb_positions(T, 0.2, torch.Generator().manual_seed(0))
    assert torch.equal(noisy[:, :3, :3], T[:, :3, :3])
    assert abs(float(noisy[:, :3, 3].std()) - 0.2) < 0.01
    assert keyframe_position_rmse(T, T) == 0.0
    with pytest.raises(ValueError, match="noise_sigma"):
        perturb_positions(T, -1.0, torch.Generator())


def test_build_db_without_noise_keeps_the_true_poses(mapped: Path):
    summary = _run("build_db", mapped)
    assert summary.keyframes >= 2 and summary.map_points > 20
    assert summary.kf_pos_rmse_m == 0.0
    db = VisualDatabase.load(summary.database)
    truth = read_sequence(mapped, "mapping").T_wc[summary.keyframe_frames]
    assert torch.equal(db.T_wc, truth)


def test_gates_follow_the_pose_prior_and_not_the_injected_noise():
    floor = BuilderConfig()
    assert floor.epipolar.max_point_distance_m is not None
    same_prior = [DatabaseConfig(noise_sigma=s, pose_prior_sigma_m=0.2) for s in (0.0, 0.4)]
    gates = [cfg.builder_config() for cfg in same_prior]
    assert gates[0] == gates[1]
    assert gates[0].guided_radius_px == pytest.approx(floor.guided_radius_px + 0.2 * 110.0)
    assert gates[0].epipolar.max_point_distance_m == pytest.approx(
        floor.epipolar.max_point_distance_m + 0.2 * 4.0
    )
    noisy_exact = DatabaseConfig(noise_sigma=0.4).builder_config()
    assert noisy_exact == floor  # prior 0: the builder's own floors, whatever the noise
    wider = DatabaseConfig(noise_sigma=0.4, pose_prior_sigma_m=0.4).builder_config()
    assert wider.guided_radius_px > gates[0].guided_radius_px
    assert wider.epipolar.max_point_distance_m > gates[0].epipolar.max_point_distance_m
    folders = {
        database_dir("d", DatabaseConfig(noise_sigma=0.2, pose_prior_sigma_m=p)).name
        for p in (0.0, 0.2, 0.4)
    }
    assert folders == {f"xfeat_sigma_0.2_prior_{p}" for p in ("0", "0.2", "0.4")}


@pytest.mark.parametrize("prior", [-0.1, float("nan"), float("inf"), True])
def test_bad_pose_prior_is_refused(prior: float):
    with pytest.raises(ValueError, match=r"db\.pose_prior_sigma_m"):
        DatabaseConfig(pose_prior_sigma_m=prior)


def test_bad_pose_prior_override_is_refused(mapped: Path):
    with pytest.raises(ValueError, match=r"db\.pose_prior_sigma_m"):
        _run("build_db", mapped, "db.pose_prior_sigma_m=-0.2")


def test_stage_reuse_needs_the_same_pose_prior(mapped: Path):
    overrides = ("db.noise_sigma=0.05", "db.pose_prior_sigma_m=0.1")
    built = _run("build_db", mapped, *overrides)
    cfg = DatabaseConfig(noise_sigma=0.05, pose_prior_sigma_m=0.1)
    summary = database_dir(mapped, cfg) / "build_db.json"
    assert built.pose_prior_sigma_m == 0.1
    record = json.loads(summary.read_text())
    assert record["stage"]["key"]["config"] == json.loads(json.dumps(config_record(cfg)))
    assert built.config["features"]["_target_"] == "diffloc.features.local.XFeatConfig"
    before = summary.stat().st_mtime_ns
    assert _run("build_db", mapped, *overrides) == built
    assert summary.stat().st_mtime_ns == before
    other = replace(cfg, pose_prior_sigma_m=0.2)
    assert database_dir(mapped, other) != database_dir(mapped, cfg)


def test_build_then_optimize_with_noisy_poses(mapped: Path):
    overrides = ("db.noise_sigma=0.05", "db.builder.association=epipolar")
    built = _run("build_db", mapped, *overrides)
    assert built.kf_pos_rmse_m > 0.01
    # The user believes their poses exact (prior 0): the gates stay at the builder's floors.
    floor = BuilderConfig()
    assert built.pose_prior_sigma_m == 0.0
    assert built.guided_radius_px == floor.guided_radius_px
    assert built.point_gate_m == floor.epipolar.max_point_distance_m
    with pytest.raises(ValueError, match="min_pairs"):  # a tiny database: few pairs each
        _run("optimize_db", mapped, *overrides, "db.optim.min_pairs=100000")
    overrides += ("db.optim.min_pairs=5",)
    with pytest.warns(OptimisationRejectedWarning):  # exact poses (prior 0) allow no move
        optimized = _run("optimize_db", mapped, *overrides)
    assert not optimized.accepted and optimized.check_max_move_limit_m == 0.0
    assert optimized.kf_pos_rmse_before_m == pytest.approx(built.kf_pos_rmse_m)
    assert optimized.kf_pos_rmse_after_m == optimized.kf_pos_rmse_before_m
    assert torch.isfinite(torch.tensor(optimized.kf_pos_rmse_optimized_m))
    cfg = DatabaseConfig(noise_sigma=0.05, builder=BuilderConfig(association="epipolar"))
    out = database_dir(mapped, cfg)
    assert out.name == "xfeat_sigma_0.05_prior_0_epipolar"
    assert OptimizedDatabase.from_record(json.loads((out / "optimize_db.json").read_text())) == (
        optimized
    )
    assert VisualDatabase.load(out / "optimized").num_keyframes == built.keyframes


def test_an_optimisation_that_drifts_is_rejected_and_the_built_poses_kept(mapped: Path):
    """The tiny scene's 5 frames look down a corridor: the surfel planes barely hold the
    keyframes, which drift together by ~1.5 m (1.3 m along the corridor) while the held-out
    reprojection errors fall (ground truth: 0.35 -> 1.5 m). The move check (RMS within
    3 x the 0.2 m prior) refuses it."""
    overrides = (
        "db.noise_sigma=0.2",
        "db.pose_prior_sigma_m=0.2",
        "db.builder.association=epipolar",
        "db.optim.min_pairs=5",
        "db.optim_check.min_holdout_pairs=10",
    )
    built = _run("build_db", mapped, *overrides)
    with pytest.warns(OptimisationRejectedWarning, match="db.optim_check.accept=always"):
        optimized = _run("optimize_db", mapped, *overrides)
    assert not optimized.accepted and not optimized.check_improved
    assert optimized.check_rms_move_m > optimized.check_rms_move_limit_m
    assert "pose_prior_sigma_m" in optimized.check_reason
    for key in ("check_inlier_fraction_before", "check_inlier_fraction_after"):
        assert 0.0 <= getattr(optimized, key) <= 1.0
    folder = database_dir(mapped, to_object(compose_config([*overrides]).db))
    kept, as_built = (VisualDatabase.load(folder / name) for name in ("optimized", "database"))
    assert torch.equal(kept.T_wc, as_built.T_wc)
    # the map points are re-placed at the built poses, not at the rejected ones
    surfels = SurfelMap.load(mapped / "map" / "surfel_map.ply")
    replaced = replace_map_points(as_built, surfels.centers.double(), surfels.normals.double())
    assert torch.equal(kept.point_positions, replaced.to(kept.point_positions.dtype))
    assert optimized.kf_pos_rmse_after_m == built.kf_pos_rmse_m
    # Scoring only: ground truth agrees that the optimised poses were worse.
    assert optimized.kf_pos_rmse_optimized_m > 2 * built.kf_pos_rmse_m
    with pytest.warns(OptimisationRejectedWarning, match="kept anyway"):
        forced = _run("optimize_db", mapped, *overrides, "db.optim_check.accept=always")
    assert forced.accepted and not forced.check_improved
    assert forced.kf_pos_rmse_after_m == forced.kf_pos_rmse_optimized_m
    assert not torch.equal(VisualDatabase.load(folder / "optimized").T_wc, as_built.T_wc)


@pytest.fixture(scope="module")
def corridor_and_corner(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small scene the optimisation can fix: 25 frames (10 m of the default walk, into its
    first corner) at 240x180, mapping sequence only, with its surfel map."""
    cfg = scene_config(
        TINY
        + [
            "scene=indoor",
            "scene.trajectory.max_frames=25",
            "scene.camera.width=240",
            "scene.camera.height=180",
        ]
    )
    cfg.sequences = [s for s in cfg.sequences if s.name == "mapping"]
    root = simulate_dataset(cfg, tmp_path_factory.mktemp("db") / "small", show_progress=False)
    build_maps(
        root, BuildMapConfig(point_maps=[], preview_frames=1), FINE_SURFELS, show_progress=False
    )
    return root


def test_optimisation_of_a_noisy_database_is_accepted_and_cuts_the_rmse(
    corridor_and_corner: Path,
):
    """0.2 m noise, prior 0.2 m: the check accepts and the keyframe position RMSE falls by
    at least a third (measured: 0.364 -> 0.213 m, held-out inliers 10 -> 76 %)."""
    overrides = (
        "db.noise_sigma=0.2",
        "db.pose_prior_sigma_m=0.2",
        "db.builder.association=epipolar",
    )
    built = _run("build_db", corridor_and_corner, *overrides)
    optimized = _run("optimize_db", corridor_and_corner, *overrides)
    assert optimized.accepted and optimized.check_improved, optimized.check_reason
    gain = optimized.check_inlier_fraction_after - optimized.check_inlier_fraction_before
    assert gain > 0.3, f"held-out inlier fraction gain {gain:.3f}"
    before, after = optimized.kf_pos_rmse_before_m, optimized.kf_pos_rmse_after_m
    assert before == built.kf_pos_rmse_m > 0.25
    assert after <= before * 2 / 3, (
        f"keyframe position RMSE after optimisation {after:.3f} m is not a third below "
        f"{before:.3f} m"
    )


def test_missing_inputs_are_clear_errors(tmp_path: Path, mapped: Path, tiny_indoor_dataset: Path):
    with pytest.raises(FileNotFoundError, match="task=simulate"):
        _run("build_db", tmp_path)
    with pytest.raises(FileNotFoundError, match="build_map"):
        _run("build_db", tiny_indoor_dataset)
    with pytest.raises(FileNotFoundError, match="build_db"):
        _run("optimize_db", mapped, "db.noise_sigma=0.3")
    with pytest.raises(FileNotFoundError, match="build_db"):
        _run("calibrate_rig", mapped, "db.noise_sigma=0.3")


def test_orb_databases_live_beside_the_xfeat_ones(mapped: Path):
    built = _run("build_db", mapped, "features=orb")
    folder = database_dir(mapped, DatabaseConfig(features=OrbConfig()))
    assert built.database == str(folder / "database")
    db = VisualDatabase.load(folder / "database")
    assert db.metric == "hamming" and db.descriptors.dtype == torch.uint8


def test_features_that_are_no_extractor_config_are_refused():
    with pytest.raises(ValueError, match="db.features must be a local feature config"):
        DatabaseConfig(features="superpoint")


def _commit_built_database(folder: Path, db: VisualDatabase) -> None:
    """Replace the built database of ``folder`` by ``db`` through the stage commit, as if
    ``build_db`` had made it (a stage trusts no database its record does not describe)."""
    record = json.loads((folder / "build_db.json").read_text())
    summary = BuiltDatabase.from_record(record)
    with open_stage(folder, "build_db", Command("build_db")) as stage:
        db.save(stage.workdir() / "database")
        stage.commit(record["stage"]["key"], summary, ["database"])


def test_calibrate_rig_stage_runs_the_calibration_and_writes_the_rig(mapped: Path):
    """The stage calibrates the database against the sequence's body poses and writes the
    summary and the corrected URDF. (Accuracy is tested on model data in
    test_rig_calibration.py: the tiny scene's 5 keyframes leave the extrinsic unobservable.)"""
    association = "db.builder.association=epipolar"  # a database no other test reads
    _run("build_db", mapped, association)
    folder = database_dir(mapped, DatabaseConfig(builder=BuilderConfig(association="epipolar")))
    db = VisualDatabase.load(folder / "database")
    E = se3_exp(torch.tensor([0.03, -0.02, 0.01, 0.005, -0.01, 0.008], dtype=torch.float64))
    db.T_wc = db.T_wc @ E  # a wrong camera extrinsic
    _commit_built_database(folder, db)
    summary = _run("calibrate_rig", mapped, association)
    assert summary.cost < summary.initial_cost and summary.num_pairs > 0
    record = json.loads((folder / "rig_calibration.json").read_text())
    assert RigCalibrationSummary.from_record(record) == summary
    seq = read_sequence(mapped, "mapping")
    T_bc = seq.T_body_camera.double()
    frames = torch.tensor(json.loads((folder / "build_db.json").read_text())["keyframe_frames"])
    surfels = SurfelMap.load(mapped / "map" / "surfel_map.ply")
    direct = calibrate_rig(
        db,
        surfels.centers.double(),
        surfels.normals.double(),
        seq.T_wc.double() @ invert(T_bc),
        torch.as_tensor(seq.timestamps, dtype=torch.float64),
        frames,
    )
    assert summary.T_correction == direct.T_correction.tolist()
    assert summary.dt_s == direct.dt
    rig = SensorRig.from_urdf(Path(summary.urdf).read_text())
    corrected = torch.tensor(summary.T_body_camera_corrected, dtype=torch.float64)
    assert_close(corrected, T_bc @ direct.T_correction, rtol=0.0, atol=1e-12)
    assert_close(rig.T_body_sensor("camera").detach(), corrected, rtol=0.0, atol=1e-9)


def test_calibrate_rig_stage_takes_the_body_trajectory_from_the_noisy_poses(mapped: Path):
    """With ``db.noise_sigma > 0`` the body trajectory (the source of the twists that carry the
    time offset) is made of the poses the database was built from, noise included, never of
    the sequence's clean poses: the stage's result is the calibration against the noisy
    trajectory, bit for bit, and differs from the one against the clean trajectory."""
    noise = "db.noise_sigma=0.05"  # projection association: a database no other test reads
    _run("build_db", mapped, noise)
    summary = _run("calibrate_rig", mapped, noise)
    cfg = DatabaseConfig(noise_sigma=0.05)
    folder = database_dir(mapped, cfg)
    db = VisualDatabase.load(folder / "database")
    seq = read_sequence(mapped, "mapping")
    T_bc = seq.T_body_camera.double()
    frames = torch.tensor(json.loads((folder / "build_db.json").read_text())["keyframe_frames"])
    noisy = database_poses(seq.T_wc, cfg)
    assert torch.equal(db.T_wc, noisy[frames].to(db.T_wc.dtype))  # what the database has
    surfels = SurfelMap.load(mapped / "map" / "surfel_map.ply")
    times = torch.as_tensor(seq.timestamps, dtype=torch.float64)

    def fit(T_wc: torch.Tensor):
        T_wb = T_wc.double() @ invert(T_bc)
        return calibrate_rig(
            db, surfels.centers.double(), surfels.normals.double(), T_wb, times, frames
        )

    from_noisy, from_clean = fit(noisy), fit(seq.T_wc)
    assert summary.T_correction == from_noisy.T_correction.tolist()
    assert summary.dt_s == from_noisy.dt
    assert from_clean.dt != from_noisy.dt


def test_database_poses_are_the_sequence_poses_with_the_configured_noise():
    T = se3_exp(torch.randn(6, 6, generator=torch.Generator().manual_seed(1), dtype=torch.float64))
    cfg = DatabaseConfig(noise_sigma=0.2, noise_seed=4)
    expected = perturb_positions(T, 0.2, torch.Generator().manual_seed(4))
    assert torch.equal(database_poses(T, cfg), expected)
    assert torch.equal(database_poses(T, DatabaseConfig()), T)


def test_calibrate_rig_needs_a_camera_extrinsic(mapped: Path, tmp_path: Path):
    root = tmp_path / "no_rig"
    shutil.copytree(mapped / "mapping", root / "mapping")
    shutil.copy(mapped / "dataset.json", root / "dataset.json")
    calib = read_calib(root / "mapping" / "calib.yaml")
    calib.T_body_camera = None
    write_calib(root / "mapping" / "calib.yaml", calib)
    with pytest.raises(ValueError, match="rig.T_body_camera"):
        _run("calibrate_rig", root)
