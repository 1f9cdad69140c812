"""``diffloc task=crossmodal``: end to end on a tiny scene, stage reuse, bad map options.

The scene is the tiny indoor scene with 8 frames per sequence and a denser terrestrial scan
than the shared fixture's (whose 48 x 96 scan leaves only scanner-station disks as free
space). At 160x120 a correct pose has 40-70 PnP inliers, so the validation's inlier threshold
(150, chosen at 320x240 on the default scene) is lowered to 30 here, and the photometric
threshold of map=tls (0.4, chosen there too) to 0.2: the tiny scene's coarse textures score
lower (0.32 for the right pose at 160x120). The splats keep their size from before the indoor
TLS default became 12 px at 1 m (``map/scene/tls_indoor.yaml``, chosen at 320x240): sizes are
pixels of the render camera, so 12 px at 160x120 would be twice as coarse, and 0 of the 4
queries were accepted with it. The screen-space visibility filter (on for the indoor TLS map,
radius 8) is off here for the same reason: its radius is pixels too.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from diffloc.cli import run
from diffloc.config import compose_config, to_object
from diffloc.io.dataset import read_sequence
from diffloc.io.exposure import EXPOSURE_FILE
from diffloc.io.trajectory import read_tum
from diffloc.pipeline import (
    crossmodal_alias,
    crossmodal_rerender,
    crossmodal_retrieval,
    crossmodal_stage,
)
from diffloc.pipeline.crossmodal_alias import SequenceAliases
from diffloc.pipeline.crossmodal_rerender import SequenceRerender
from diffloc.pipeline.crossmodal_stage import SequenceLocalization
from diffloc.reloc.stage_clock import STAGES
from diffloc.sim.dataset import simulate_dataset
from tests.conftest import TINY, scene_config

SCENE = [
    *TINY,
    "scene=indoor",
    "scene.trajectory.max_frames=8",
    "scene.tls.elevation_steps=120",
    "scene.tls.azimuth_steps=240",
]
TASK = [
    "task=crossmodal",
    "map=tls",
    "task.image_scale=1.0",
    "task.sequences=[query_same]",
    "task.every=2",
    "task.localizer.validation.theta_in=30",
    "task.validation.tls.min_photometric=0.2",
    "map.rho_max=8",
    "map.visibility_radius=0",
]
MESH = [
    "map.texture.reconstruction.poisson_depth=7",
    "map.texture.reconstruction.target_faces=6000",
    "map.texture.atlas_size=256",
]
"""A small mesh (as in ``tests/test_mesh_map.py``)."""
STAGE_RECORDS = (
    "poses_tls_map/render_poses.json",
    "tls/map/crossmodal_map.json",
    "tls/database/rgbd_database.json",
)
LOCALIZE_RECORD = "tls/localize_query_same/localize.json"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("crossmodal") / "indoor_seed0"
    return simulate_dataset(scene_config(SCENE), out, show_progress=False)


def _run(dataset: Path, out: Path, *overrides: str) -> dict:
    return run(
        compose_config([*SCENE, *TASK, f"dataset={dataset}", f"task.out_dir={out}", *overrides])
    )


def _records(dataset: Path) -> dict[str, tuple[bytes, int]]:
    """Content and modification time of every stage record."""
    root = dataset / "crossmodal"
    return {
        rel: ((root / rel).read_bytes(), (root / rel).stat().st_mtime_ns)
        for rel in (*STAGE_RECORDS, LOCALIZE_RECORD)
    }


UPSTREAM = ("select_render_poses", "colored_point_map", "render_database")
"""What the poses, map and database stages compute with."""


def _refuse(monkeypatch: pytest.MonkeyPatch, names: tuple[str, ...]) -> None:
    """Make the computations ``names`` of the stage module fail."""

    def refuse(*args, **kwargs):
        raise AssertionError("a stage computed again although its result was reusable")

    for name in names:
        monkeypatch.setattr(crossmodal_stage, name, refuse)


@pytest.fixture(scope="module")
def first(dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    out = tmp_path_factory.mktemp("first_run")
    return _run(dataset, out), out


def test_the_task_localizes_queries_in_the_rendered_tls_database(dataset, first):
    results, out = first
    entry = results["sequences"]["query_same"]
    assert entry["queries"] == 4
    assert entry["accepted"] >= 1 and entry["precision"] == 1.0
    assert entry["rates"]["1m_30deg"] == entry["accepted"] / entry["queries"]
    assert results["database_images"] == results["stages"]["poses"]["poses"] > 0
    assert 0.0 < results["hole_share"] < 1.0
    database = results["stages"]["database"]
    assert database["images"] == results["database_images"]
    assert database["seconds"] > 0.0 and database["cpu_seconds"] > 0.0
    times, poses = read_tum(out / "trajectory_query_same.tum")
    assert len(times) == entry["accepted"] and poses.shape == (entry["accepted"], 4, 4)
    for name in ("results.md", "retrieved_query_same.png", "trajectory_query_same.png"):
        assert (out / name).stat().st_size > 0
    assert "| query_same | 4 |" in (out / "results.md").read_text()
    assert json.loads((out / "results.json").read_text())["sequences"] == results["sequences"]
    floors = dataset / "crossmodal" / "poses_tls_map" / "floors"
    assert sorted(p.name for p in floors.iterdir()) == ["floor_0.png", "floor_1.png"]


def test_the_time_of_every_stage_and_candidate_is_recorded_and_summarised(dataset, first):
    results, out = first
    loc = SequenceLocalization.load(
        dataset / "crossmodal" / "tls" / "localize_query_same" / "localization.npz"
    )
    assert loc.stage_ms.shape == loc.stage_cpu_ms.shape == (4, len(STAGES))
    per_query = np.bincount(loc.candidate_query, weights=loc.candidate_match_ms, minlength=4)
    np.testing.assert_allclose(loc.stage_ms[:, STAGES.index("matching")], per_query)
    assert (loc.stage_ms.sum(1) <= loc.time_ms).all() and (loc.cpu_ms > 0).all()
    assert (loc.candidate_rerank_matches > 0).all() and (loc.candidate_match_cpu_ms > 0).all()
    time = results["sequences"]["query_same"]["time"]
    assert time["median_ms"] == results["sequences"]["query_same"]["median_ms_per_query"]
    assert time["median_cpu_ms"] == float(np.median(loc.cpu_ms))
    assert time["candidates"]["mean"] == len(loc.candidate_query) / 4
    matching = time["stages"]["matching"]["mean_cpu_ms"]
    assert matching == float(loc.stage_cpu_ms[:, STAGES.index("matching")].mean()) > 0
    assert time["match_cpu_ms"] == float(np.median(loc.candidate_match_cpu_ms))
    assert "| query_same | " + f"{time['median_ms']:.0f} |" in (out / "results.md").read_text()


def test_a_second_run_reuses_every_stage(dataset, first, tmp_path, monkeypatch):
    before = _records(dataset)
    _refuse(monkeypatch, (*UPSTREAM, "RenderedDatabaseLocalizer"))
    again = _run(dataset, tmp_path)
    assert _records(dataset) == before
    assert again["sequences"]["query_same"]["rates"] == first[0]["sequences"]["query_same"]["rates"]


def test_the_storey_alias_test_runs_after_the_localization_and_is_reused(
    dataset, first, tmp_path, monkeypatch
):
    results, _ = first  # scene=indoor: task.storey_alias.maps=[tls]
    folder = dataset / "crossmodal" / "tls"
    loc = SequenceLocalization.load(folder / "localize_query_same" / "localization.npz")
    aliases = SequenceAliases.load(folder / "alias_query_same" / "alias.npz")
    stage = results["stages"]["alias_query_same"]
    assert stage["floors"] == 2 and stage["checked"] == loc.accepted.sum() >= 1
    assert aliases.alias_inliers.shape == (stage["checked"], 1)
    assert (aliases.own_inliers > 0).all() and (aliases.cpu_ms > 0).all()
    accepted = results["sequences"]["query_same"]["accepted"]
    assert (
        accepted
        == loc.accepted.sum() - aliases.alias.sum()
        == loc.accepted.sum() - stage["aliases"]
    )

    def refuse(*args, **kwargs):
        raise AssertionError("the storey-alias test ran again although it was reusable")

    _refuse(monkeypatch, (*UPSTREAM, "RenderedDatabaseLocalizer"))
    monkeypatch.setattr(crossmodal_alias, "storey_alias_evidence", refuse)
    assert _run(dataset, tmp_path / "again")["stages"]["alias_query_same"] == stage
    off = _run(dataset, tmp_path / "off", "task.storey_alias.maps=[]")
    assert "alias_query_same" not in off["stages"]
    assert off["sequences"]["query_same"]["accepted"] == loc.accepted.sum()


def test_the_rerender_check_looks_again_at_refused_poses_before_the_alias_test(
    dataset, first, tmp_path, monkeypatch
):
    _refuse(monkeypatch, (*UPSTREAM, "RenderedDatabaseLocalizer"))
    results = _run(dataset, tmp_path / "on", "task.rerender.maps=[tls]")
    folder = dataset / "crossmodal" / "tls"
    loc = SequenceLocalization.load(folder / "localize_query_same" / "localization.npz")
    checked = SequenceRerender.load(folder / "rerender_query_same" / "rerender.npz")
    stage = results["stages"]["rerender_query_same"]
    refused = loc.success & ~loc.accepted.astype(bool)
    assert checked.query.tolist() == np.flatnonzero(refused).tolist()  # only refused poses
    assert stage["checked"] == refused.sum() >= 1 and (checked.cpu_ms > 0).all()
    assert stage["accepted"] == checked.accepted.sum()
    assert not (checked.accepted & ~checked.success).any()
    answers = checked.apply(loc)
    kept = loc.accepted.astype(bool)
    np.testing.assert_array_equal(answers.T_wc[kept], loc.T_wc[kept])  # accepted: as found
    assert answers.accepted.sum() == kept.sum() + checked.accepted.sum()
    alias = results["stages"]["alias_query_same"]  # tests the answers after the second look
    assert alias["checked"] == answers.accepted.sum()
    entry = results["sequences"]["query_same"]
    assert entry["accepted"] == answers.accepted.sum() - alias["aliases"]
    assert entry["precision"] == 1.0

    def refuse(*args, **kwargs):
        raise AssertionError("the re-render check ran again although it was reusable")

    monkeypatch.setattr(crossmodal_rerender, "rerender_candidate", refuse)
    again = _run(dataset, tmp_path / "again", "task.rerender.maps=[tls]")
    assert again["stages"]["rerender_query_same"] == stage
    assert again["sequences"]["query_same"]["rates"] == entry["rates"]


def test_the_refinement_runs_after_the_localization_and_is_reported(
    dataset, first, tmp_path, monkeypatch
):
    _refuse(monkeypatch, UPSTREAM)
    settings = (
        "task.refine.enabled=true",
        "task.refine.image_scale=0.5",
        "task.refine.verify=false",
    )
    results = _run(dataset, tmp_path, *settings)
    entry = results["sequences"]["query_same"]
    refine = entry["refine"]
    assert refine["localised"] == refine["refined"] == entry["accepted"] >= 1
    assert 0 <= refine["kept"] <= refine["refined"] and refine["median_cpu_ms"] > 0
    assert refine["rates_before"] == entry["rates"]
    assert results["stages"]["refine_query_same"]["localised"] == entry["accepted"]
    assert results["refine"]["image_scale"] == 0.5
    times, poses = read_tum(tmp_path / "trajectory_query_same_refined.tum")
    assert len(times) == entry["accepted"] and np.isfinite(poses).all()
    assert (
        "Render-and-compare refinement of the accepted poses"
        in (tmp_path / "results.md").read_text()
    )
    assert (dataset / "crossmodal" / "tls" / "refine_query_same" / "refine.json").is_file()


def test_a_changed_localizer_setting_runs_only_the_localization(
    dataset, first, tmp_path, monkeypatch
):
    before = _records(dataset)
    _refuse(monkeypatch, UPSTREAM)
    _run(dataset, tmp_path, "task.top_k.tls=3")  # scene=indoor: task.top_k.tls=10
    after = _records(dataset)
    assert all(after[rel] == before[rel] for rel in STAGE_RECORDS)
    record = json.loads(after[LOCALIZE_RECORD][0])
    assert record["stage"]["key"]["config"]["localizer"]["top_k"] == 3


def test_the_pose_prior_is_used_after_an_accepted_pose_and_recorded(
    dataset, first, tmp_path, monkeypatch
):
    _refuse(monkeypatch, UPSTREAM)
    results = _run(dataset, tmp_path, "+task/localizer/prior=sequence")
    assert results["prior"]["growth_mps"] == 1.0  # the indoor scene's
    folder = dataset / "crossmodal" / "tls" / "localize_query_same"
    loc = crossmodal_stage.SequenceLocalization.load(folder / "localization.npz")
    times = read_sequence(dataset, "query_same").timestamps[loc.frames]
    accepted = loc.accepted.astype(bool)
    assert accepted.any()
    for q in range(len(loc.frames)):
        earlier = times[:q][accepted[:q]]
        active = len(earlier) and times[q] - earlier[-1] <= results["prior"]["max_age_s"]
        assert (loc.prior_images[q] > 0) == bool(active)
        assert loc.prior_images[q] <= results["prior"]["max_images"]
    assert not loc.from_prior[loc.prior_images == 0].any()
    entry = results["sequences"]["query_same"]
    assert entry["accepted_from_prior"] == int((accepted & loc.from_prior).sum())
    assert "pose prior on" in (tmp_path / "results.md").read_text()


def test_an_empty_corridor_names_the_map_and_the_settings(dataset, first, tmp_path):
    before = _records(dataset)
    with pytest.raises(ValueError, match=r"tls_map.ply: .*empty corridor.*task\.poses"):
        _run(dataset, tmp_path, "task.poses.min_clearance_m=30")
    assert _records(dataset) == before  # the failed run left the results in place


@pytest.mark.parametrize(
    ("task", "option"), [("crossmodal", "surfel"), ("main", "tls"), ("build_map", "mesh")]
)
def test_a_map_option_the_task_cannot_use_is_refused_before_any_work(task, option, tmp_path):
    cfg = compose_config([f"task={task}", f"map={option}", f"dataset={tmp_path / 'none'}"])
    with pytest.raises(
        ValueError,
        match=f"task={task} cannot use map={option}: task=crossmodal "
        "takes map=tls, map=cloud, map=mesh, map=images, map=nerf or map=hybrid; "
        "every other task takes map=surfel",
    ):
        run(cfg)
    assert not (tmp_path / "none").exists()


def test_views_per_sample_is_part_of_the_render_pose_key(dataset, tmp_path):
    root = tmp_path / dataset.name
    # the point maps and the mapping run (its trajectory adds render samples): no cached stage
    for part in ("map", "mapping"):
        shutil.copytree(dataset / part, root / part)
    shutil.copy(dataset / "dataset.json", root / "dataset.json")

    def poses(*overrides: str) -> tuple[torch.Tensor, dict]:
        config = to_object(compose_config([*SCENE, *TASK, *overrides])).task.poses_for("tls_map")
        T_wc, outcome = crossmodal_stage.render_pose_stage(root, "tls_map", config, "tls")
        record = root / "crossmodal" / "poses_tls_map" / "render_poses.json"
        return T_wc, json.loads(record.read_text())

    four, record_four = poses()
    eight, record_eight = poses("task.poses.views_per_sample=8")
    assert record_four["stage"]["key"]["config"]["poses"]["views_per_sample"] == 4
    assert record_eight["stage"]["key"]["config"]["poses"]["views_per_sample"] == 8
    assert record_eight["samples"] == record_four["samples"] > 0
    assert record_eight["poses"] == 2 * record_four["poses"] == len(eight)
    assert record_eight["stage"]["outputs"] != record_four["stage"]["outputs"]
    assert torch.equal(eight.reshape(-1, 8, 4, 4)[:, :4].reshape(-1, 4, 4), four)
    again, record_again = poses()  # back to 4 views: made again, not the 8-view result
    assert torch.equal(again, four) and record_again["stage"] == record_four["stage"]


def test_the_mapping_trajectory_is_an_input_of_the_render_poses_when_used(dataset, tmp_path):
    root = tmp_path / dataset.name
    shutil.copytree(dataset / "map", root / "map")
    shutil.copytree(dataset / "mapping", root / "mapping")
    shutil.copy(dataset / "dataset.json", root / "dataset.json")
    record = root / "crossmodal" / "poses_tls_map" / "render_poses.json"

    def poses(*overrides: str) -> tuple[torch.Tensor, dict]:  # the tiny lidar map has no corridor
        task = to_object(compose_config([*SCENE, *TASK, *overrides])).task
        T_wc, _ = crossmodal_stage.render_pose_stage(
            root, "tls_map", task.poses_for("tls_map"), "tls"
        )
        return T_wc, json.loads(record.read_text())

    skeleton, plain = poses("~task.trajectory_gap_m.tls_map")  # indoors it is on: 1 m
    walked, with_walk = poses("task.trajectory_gap_m.tls_map=0.5")
    assert "mapping/poses.txt" not in plain["stage"]["key"]["inputs"]
    assert "mapping/poses.txt" in with_walk["stage"]["key"]["inputs"]
    assert plain["trajectory_samples"] == 0 < with_walk["trajectory_samples"]
    assert len(walked) == len(skeleton) + 4 * with_walk["trajectory_samples"]
    assert torch.equal(walked[: len(skeleton)], skeleton)
    mapping = read_sequence(root, "mapping").T_wc
    new = walked[len(skeleton) :: 4, :3, 3]
    assert bool((torch.cdist(new, mapping[:, :3, 3]).amin(1) == 0).all())  # mapping cameras
    poses_file = root / "mapping" / "poses.txt"
    poses_file.write_text(poses_file.read_text() + "\n")  # a changed input: made again
    _, again = poses("task.trajectory_gap_m.tls_map=0.5")
    assert again["stage"]["key"]["inputs"] != with_walk["stage"]["key"]["inputs"]


def test_a_views_per_sample_other_than_4_or_8_is_refused_before_any_work(tmp_path):
    overrides = ["task=crossmodal", "map=tls", f"dataset={tmp_path / 'none'}"]
    cfg = compose_config([*overrides, "task.poses.views_per_sample=6"])
    with pytest.raises(ValueError, match=r"task.poses.views_per_sample must be one of \(4, 8\)"):
        run(cfg)
    assert not (tmp_path / "none").exists()


def test_bad_map_settings_name_their_key():
    cfg = compose_config(["task=crossmodal", "map=cloud", "map.passes=triple"])
    with pytest.raises(ValueError, match="map.passes must be one of"):
        run(cfg)


def test_occlusion_sizes_below_the_smallest_splat_are_refused():
    with pytest.raises(ValueError, match="occlusion_rho_max must be a finite number >= rho_min"):
        to_object(compose_config(["task=crossmodal", "map=tls", "map.occlusion_rho_max=0.5"]))


def test_the_mesh_map_stage_never_reads_the_ground_truth(dataset, tmp_path, monkeypatch):
    root = tmp_path / dataset.name
    shutil.copytree(dataset, root, ignore=shutil.ignore_patterns("crossmodal"))
    shutil.rmtree(root / "map" / "mesh")
    (root / "map" / "mesh_changed" / "scene.obj").write_text("poison: not an OBJ\n")
    (root / "mapping" / EXPOSURE_FILE).write_text("poison: not exposures\n")
    config = to_object(compose_config([*TASK[:1], "map=mesh", *MESH])).map
    mesh_map, outcome = crossmodal_stage.build_rgbd_map(root, config, 1.0)
    folder = root / "crossmodal" / "mesh" / "map" / "mesh"
    assert sorted(p.suffix for p in folder.iterdir()) == [".mtl", ".obj", ".ply", ".png"]
    assert outcome.summary.faces > 1000 and outcome.summary.textured_fraction > 0.05
    mapping = read_sequence(root, "mapping")
    view = mesh_map.render(mapping.T_wc[:1], mapping.camera)
    seen = view.depth[0, 0] > 0
    assert float(seen.float().mean()) > 0.25  # 8 lidar sweeps mesh a third of the first view
    # The texture came from the mapping images: the render matches the image where seen.
    error = (view.rgb[0][:, seen] - mapping.load_rgb(0)[:, seen]).abs().median()
    assert float(error) < 0.1
    _refuse(monkeypatch, ("build_textured_mesh",))
    assert crossmodal_stage.build_rgbd_map(root, config, 1.0)[1] == outcome


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("+task.validation.lidar.theta_in=50", r"task.validation.lidar: not a map option"),
        ("+task.validation.mesh.theta=50", r"task.validation.mesh.theta: not a validation setting"),
        ("task.validation.mesh.max_plane_share=1.5", r"task.validation.mesh: .*max_plane_share"),
        ("+task.top_k.lidar=10", r"task.top_k.lidar: not a map option"),
        ("task.top_k.tls=0", r"task.top_k.tls must be"),
    ],
)
def test_a_per_map_threshold_of_an_unknown_map_or_setting_or_out_of_range_is_refused(
    override, message
):
    cfg = compose_config(["scene=indoor", "task=crossmodal", "map=tls", override])
    with pytest.raises(ValueError, match=message):
        run(cfg)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("+task.floor_closing_m.mesh=0.3", r"task.floor_closing_m.mesh: not a point map"),
        (
            "task.floor_closing_m.lidar_map=-0.3",
            r"task.floor_closing_m.lidar_map: floor_closing_radius_m must be a finite number",
        ),
        ("+task.trajectory_gap_m.mesh=1.0", r"task.trajectory_gap_m.mesh: not a point map"),
        (
            "task.trajectory_gap_m.lidar_map=0",
            r"task.trajectory_gap_m.lidar_map: trajectory_gap_m must be a positive",
        ),
    ],
)
def test_a_bad_floor_closing_of_a_point_map_is_refused(override, message):
    cfg = compose_config(["scene=indoor", "task=crossmodal", "map=cloud", override])
    with pytest.raises(ValueError, match=message):
        run(cfg)


TUNE = [
    "task.tune_retrieval=true",
    "task.retrieval.finetune.epochs=1",
    "task.retrieval.finetune.triplets.negative_distance_m=1.0",
]
"""NetVLAD tuned on the tiny scene's 8 mapping images (renders beyond 1 m are negatives)."""


def test_tuned_retrieval_is_a_stage_the_localization_keys_on(dataset, first, tmp_path, monkeypatch):
    before = _records(dataset)
    _refuse(monkeypatch, UPSTREAM)
    results = _run(dataset, tmp_path / "tuned", *TUNE)
    assert all(_records(dataset)[rel] == before[rel] for rel in STAGE_RECORDS)
    tuning = results["stages"]["retrieval"]
    assert tuning["mapping_images"] == 8 and tuning["tuples"] > 0
    assert (dataset / "crossmodal" / "tls" / "retrieval" / "netvlad.safetensors").is_file()
    record = json.loads((dataset / "crossmodal" / LOCALIZE_RECORD).read_text())
    assert "retrieval" in record["stage"]["key"]["inputs"]
    tuned = _records(dataset)
    monkeypatch.setattr(crossmodal_retrieval, "tune_render_retrieval", None)  # must not run
    monkeypatch.setattr(crossmodal_stage, "RenderedDatabaseLocalizer", None)
    again = _run(dataset, tmp_path / "again", *TUNE)
    assert _records(dataset) == tuned
    assert again["sequences"] == {
        name: {**entry, "files": again["sequences"][name]["files"]}
        for name, entry in results["sequences"].items()
    }


def test_the_visibility_filter_renders_the_database_again_and_keeps_the_map(
    dataset, first, tmp_path, monkeypatch
):
    """``map.visibility_radius`` (issue 18) is a key of the database only, and only when on,
    so the records of the renders without it stay valid."""
    before = _records(dataset)
    assert "visibility" not in json.loads(before[STAGE_RECORDS[2]][0])["stage"]["key"]["config"]
    _refuse(monkeypatch, ("select_render_poses", "colored_point_map"))
    _run(dataset, tmp_path, "map.visibility_radius=4")
    after = _records(dataset)
    assert all(after[rel] == before[rel] for rel in STAGE_RECORDS[:2])
    record = json.loads(after[STAGE_RECORDS[2]][0])
    assert record["stage"]["key"]["config"]["visibility"] == {
        "radius": 4,
        "min_sectors": 7,
        "depth_ratio": 0.9,
    }
    assert record["hole_share"] < json.loads(before[STAGE_RECORDS[2]][0])["hole_share"]
