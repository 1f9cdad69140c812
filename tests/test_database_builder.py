"""DatabaseBuilder on the tiny simulated indoor scene (seed 1 Sec. III-A)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import diffloc.database.builder as builder_module
from diffloc.database.builder import ASSOCIATIONS, BuilderConfig, DatabaseBuilder
from diffloc.database.database import VisualDatabase
from diffloc.database.epipolar_matching import EpipolarMatchingConfig, match_epipolar
from diffloc.features.local import XFeatConfig, make_extractor
from diffloc.geometry.se3 import invert, transform_points
from diffloc.io.dataset import read_sequence
from diffloc.maps.surfel import SurfelMap
from diffloc.pipeline.database_stage import perturb_positions

EXTRACTOR = XFeatConfig(max_keypoints=512)


@pytest.fixture(scope="module")
def scene(tiny_indoor_mapped: Path) -> Path:
    return tiny_indoor_mapped


@pytest.fixture(scope="module")
def surfels(scene: Path) -> SurfelMap:
    return SurfelMap.load(scene / "map" / "surfel_map.ply")


def build(scene: Path, surfels: SurfelMap, names: tuple[str, ...]) -> VisualDatabase:
    builder = DatabaseBuilder(BuilderConfig(), surfels, make_extractor(EXTRACTOR))
    for name in names:
        db = builder.build(read_sequence(scene, name), show_progress=False)
    return db


@pytest.fixture(scope="module")
def database(scene: Path, surfels: SurfelMap) -> VisualDatabase:
    return build(scene, surfels, ("mapping",))


def test_map_points_lie_on_the_true_surface(scene: Path, database: VisualDatabase):
    seq = read_sequence(scene, "mapping")
    stats = database.stats()
    assert stats["keyframes"] >= 3 and stats["map_points"] > 100
    assert stats["mean_observations_per_point"] > 1.0
    obs = database.observations()
    first = torch.full((database.num_points,), database.num_keyframes).scatter_reduce(
        0, obs[:, 2], obs[:, 0], reduce="amin"
    )
    errors = []
    for k in range(database.num_keyframes):
        frame = int(torch.nonzero((seq.T_wc == database.T_wc[k]).all(-1).all(-1))[0])
        points = torch.nonzero(first == k).flatten()
        camera = database.camera(k)
        uv, valid = camera.project_world(database.point_positions[points], database.T_wc[k])
        z = transform_points(invert(database.T_wc[k]), database.point_positions[points])[:, 2]
        truth = seq.load_depth(frame).double().reshape(camera.height, camera.width)
        u = uv[:, 0].round().long().clamp(0, camera.width - 1)
        v = uv[:, 1].round().long().clamp(0, camera.height - 1)
        depth = truth[v, u]
        ok = valid & (depth > 0)
        errors.append((z - depth)[ok].abs())
    errors = torch.cat(errors)
    assert len(errors) > 50
    assert float(errors.median()) < 0.02 + 0.01  # surfel radius plus a small tolerance


def test_every_map_point_is_anchored_to_a_surfel(database: VisualDatabase, surfels: SurfelMap):
    assert (database.point_surfels >= 0).all()
    centres = surfels.centers[database.point_surfels].double()
    assert torch.equal(database.point_positions, centres)
    assert (database.observation_counts() >= 1).all()


def test_repeated_build_gives_the_same_database(
    scene: Path, surfels: SurfelMap, database: VisualDatabase, tmp_path: Path
):
    again = build(scene, surfels, ("mapping",))
    for name, value in vars(database).items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(value, getattr(again, name)), name
    again.save(tmp_path / "db")
    loaded = VisualDatabase.load(tmp_path / "db")
    assert loaded.stats() == database.stats()


def test_update_with_a_second_sequence_matches_existing_points(
    scene: Path, surfels: SurfelMap, database: VisualDatabase
):
    both = build(scene, surfels, ("mapping", "query_same"))
    before = database.num_keyframes
    assert both.num_keyframes > before
    obs = both.observations()
    new_keyframe_obs = obs[obs[:, 0] >= before]
    # Points first created by the mapping keyframes and re-observed by query_same keyframes.
    old_points = torch.unique(obs[obs[:, 0] < before, 2])
    matched_old = torch.isin(new_keyframe_obs[:, 2], old_points)
    # The tiny query_same starts 0.23 m along the route and walks past the mapping run's end,
    # so only its first frames overlap the mapping frames (20 re-observed points on seed 0).
    assert int(matched_old.sum()) >= 15


def true_world_points(db: VisualDatabase, seq, truth: torch.Tensor) -> torch.Tensor:
    """(N, 3) world point of every keypoint: lifted with the true depth at the true pose
    (keyframe ``k`` is frame ``k``: nothing is culled on the tiny scene); NaN without depth."""
    keyframes = db.keypoint_keyframes()
    world = torch.full((len(keyframes), 3), float("nan"), dtype=torch.float64)
    for k in range(db.num_keyframes):
        rows = keyframes == k
        camera = db.camera(k)
        uv = db.keypoints[rows].double()
        depth = seq.load_depth(k).double().reshape(camera.height, camera.width)
        u = uv[:, 0].round().long().clamp(0, camera.width - 1)
        v = uv[:, 1].round().long().clamp(0, camera.height - 1)
        z = torch.where(depth[v, u] > 0, depth[v, u], torch.nan)
        world[rows] = transform_points(truth[k], camera.unproject(uv, z))
    return world


def track_errors_px(db: VisualDatabase, seq, truth: torch.Tensor) -> torch.Tensor:
    """(M,) reprojection error (pixels) under the true geometry of every observation of a map
    point except its first: the first observer's keypoint, lifted with the true depth at its
    true pose, projected at the observing keyframe's true pose."""
    assert db.num_keyframes == len(truth)
    world = true_world_points(db, seq, truth)
    obs = db.observations()
    first = torch.full((db.num_points,), len(world)).scatter_reduce(
        0, obs[:, 2], obs[:, 1], reduce="amin"
    )
    later = obs[obs[:, 1] != first[obs[:, 2]]]
    errors = []
    for k in range(db.num_keyframes):
        rows = later[later[:, 0] == k]
        uv, _ = db.camera(k).project_world(world[first[rows[:, 2]]], truth[k])
        errors.append((uv - db.keypoints[rows[:, 1]].double()).norm(dim=-1))
    errors = torch.cat(errors)
    return errors[errors.isfinite()]


def test_epipolar_association_is_not_steered_by_noisy_poses(scene: Path, surfels: SurfelMap):
    """With 0.3 m noise on the positions the guided search around the (wrong) projections
    makes wrong tracks; descriptor matching verified by essential matrices does not use the
    poses, so its tracks stay as accurate as when built at the true poses."""
    seq = read_sequence(scene, "mapping")
    truth = seq.T_wc.double().clone()
    noisy = perturb_positions(truth, 0.3, torch.Generator().manual_seed(0))
    gate = EpipolarMatchingConfig(max_point_distance_m=0.5 + 4 * 0.3)
    median_px, tracks = {}, {}
    for association in ASSOCIATIONS:
        for name, poses in (("true", truth), ("noisy", noisy)):
            seq.T_wc = poses
            config = BuilderConfig(association=association, epipolar=gate)
            db = DatabaseBuilder(config, surfels, make_extractor(EXTRACTOR)).build(
                seq, show_progress=False
            )
            errors = track_errors_px(db, seq, truth)
            median_px[association, name], tracks[association, name] = errors.median(), len(errors)
    assert tracks["epipolar", "true"] > 50
    assert tracks["epipolar", "noisy"] >= 0.8 * tracks["epipolar", "true"]
    assert median_px["epipolar", "noisy"] < 3.0
    assert median_px["epipolar", "noisy"] < 1.25 * median_px["epipolar", "true"]
    assert median_px["projection", "noisy"] > 2 * median_px["epipolar", "noisy"]


def test_epipolar_build_renders_only_the_keypoint_disks_and_matches_the_full_render(
    scene: Path, surfels: SurfelMap, monkeypatch: pytest.MonkeyPatch
):
    """The epipolar association reads the index map only at the keypoints and in their disks:
    rendering those pixels alone gives the database of the full render."""
    seq = read_sequence(scene, "mapping")
    config = BuilderConfig(association="epipolar")
    masks = []
    builder = DatabaseBuilder(config, surfels, make_extractor(EXTRACTOR))
    render = builder.renderer.render
    monkeypatch.setattr(
        builder.renderer,
        "render",
        lambda *a, pixels: masks.append(pixels) or render(*a, pixels=pixels),
    )
    masked = builder.build(seq, show_progress=False)
    monkeypatch.undo()
    monkeypatch.setattr(builder_module, "_keypoint_pixels", lambda features, camera: None)
    full = DatabaseBuilder(config, surfels, make_extractor(EXTRACTOR)).build(
        seq, show_progress=False
    )
    assert masks and all(0 < float(m.float().mean()) < 0.9 for m in masks)
    for name, value in vars(full).items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(value, getattr(masked, name)), name


def test_epipolar_candidates_come_from_at_most_candidate_keyframes(
    scene: Path, surfels: SurfelMap, monkeypatch: pytest.MonkeyPatch
):
    """``epipolar.candidate_keyframes`` bounds the covisible keyframes whose map points are
    match candidates (which ones: ``VisualDatabase.keyframes_observing``'s ``top_n``)."""
    sizes = []

    def spy(db, covisible, *args, **kwargs):
        sizes.append(len(covisible))
        return match_epipolar(db, covisible, *args, **kwargs)

    monkeypatch.setattr(builder_module, "match_epipolar", spy)
    config = BuilderConfig(association="epipolar", epipolar=EpipolarMatchingConfig(2))
    db = DatabaseBuilder(config, surfels, make_extractor(EXTRACTOR)).build(
        read_sequence(scene, "mapping"), show_progress=False
    )
    assert max(sizes) == 2 and db.stats()["observations"] > db.num_points
    with pytest.raises(ValueError, match="candidate_keyframes"):
        EpipolarMatchingConfig(candidate_keyframes=0)


def test_epipolar_3d_gate_keeps_only_points_near_the_keypoint_surfels(
    scene: Path, surfels: SurfelMap, monkeypatch: pytest.MonkeyPatch
):
    """With ``max_point_distance_m`` every epipolar match's map point lies within that distance
    of a surfel its keypoint sees; without the gate some matches are farther."""
    seq = read_sequence(scene, "mapping")
    distances: dict[float | None, list[torch.Tensor]] = {None: [], 0.25: []}
    for gate, found in distances.items():

        def spy(db, covisible, features, *args, found=found, **kwargs):
            kp, pts = match_epipolar(db, covisible, features, *args, **kwargs)
            seen = kwargs["keypoint_surfels"][kp]
            centres = kwargs["surfel_centers"][seen.clamp(min=0)].double()
            offsets = (centres - db.point_positions[pts, None]).norm(dim=-1)
            found.append(torch.where(seen >= 0, offsets, torch.inf).amin(-1))
            return kp, pts

        monkeypatch.setattr(builder_module, "match_epipolar", spy)
        config = BuilderConfig(
            association="epipolar", epipolar=EpipolarMatchingConfig(max_point_distance_m=gate)
        )
        DatabaseBuilder(config, surfels, make_extractor(EXTRACTOR)).build(seq, show_progress=False)
    gated, free = torch.cat(distances[0.25]), torch.cat(distances[None])
    assert len(gated) > 50 and bool((gated <= 0.25).all())
    assert bool((free > 0.25).any())
    with pytest.raises(ValueError, match="max_point_distance_m"):
        EpipolarMatchingConfig(max_point_distance_m=0.0)
    features = make_extractor(EXTRACTOR).extract(seq.load_rgb(0))
    no_candidates = torch.zeros(0, dtype=torch.int64)
    with pytest.raises(ValueError, match="keypoint_surfels"):
        match_epipolar(
            VisualDatabase(64),
            no_candidates,
            features,
            seq.camera,
            EpipolarMatchingConfig(),
            torch.Generator(),
        )


def test_builder_culls_a_keyframe_whose_points_are_observed_by_three_others(
    scene: Path, surfels: SurfelMap
):
    """The same image at the same pose, added again and again: each copy observes the first
    copy's points, so once three others see them the oldest judged copy is redundant."""
    seq = read_sequence(scene, "mapping")
    image, T_wc = seq.load_rgb(0), seq.T_wc[0]
    builder = DatabaseBuilder(BuilderConfig(), surfels, make_extractor(EXTRACTOR))
    copies = 6
    for _ in range(copies):
        builder.add_image(image, T_wc, seq.camera)
    db = builder.database
    counts = builder.counts
    # From the 4th copy on, each insertion culls one judged copy (the copies then have two
    # other observers each, below the three of the rule, so no more go).
    assert counts.keyframes_added == copies
    assert counts.keyframes_culled == copies - 3
    assert builder.keyframe_ids.tolist() == [3, 4, 5]
    assert db.num_keyframes == 3
    assert counts.points_created - counts.points_unconfirmed - counts.points_orphaned == (
        db.num_points
    )


def test_builder_updating_a_database_numbers_its_keyframes_first(
    scene: Path, surfels: SurfelMap, database: VisualDatabase, tmp_path: Path
):
    database.save(tmp_path / "db")
    db = VisualDatabase.load(tmp_path / "db")  # a copy: the fixture stays as built
    keyframes, points = db.num_keyframes, db.num_points
    builder = DatabaseBuilder(BuilderConfig(), surfels, make_extractor(EXTRACTOR), database=db)
    assert builder.keyframe_ids.tolist() == list(range(keyframes))
    seq = read_sequence(scene, "query_same")
    builder.build(seq, show_progress=False)
    counts = builder.counts
    ids = builder.keyframe_ids
    assert len(ids) == db.num_keyframes == keyframes + len(seq) - counts.keyframes_culled
    assert bool((ids.diff() > 0).all()) and int(ids.max()) < keyframes + len(seq)
    removed = counts.points_unconfirmed + counts.points_orphaned
    assert db.num_points == points + counts.points_created - removed
    # The added keyframes are the query_same frames at their poses, in order.
    added = ids >= keyframes
    assert torch.equal(db.T_wc[added], seq.T_wc[ids[added] - keyframes])
