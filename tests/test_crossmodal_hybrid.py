"""``map=hybrid``: real images plus the renders no real image covers, one NetVLAD over both.

Coverage is checked on constructed poses (known answers at the bounds); the database stage on
small synthetic parts (three "real" and four "rendered" 64x48 images): which renders it keeps,
that features and descriptors are those of a database built from the union directly, reuse,
and the refusal of parts with different cameras.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from diffloc.config import compose_config, to_object
from diffloc.crossmodal.database import DatabaseConfig, RenderedDatabase, build_database
from diffloc.crossmodal.hybrid import uncovered_views
from diffloc.crossmodal.synthesize import RGBD
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.identity import identity
from diffloc.pipeline import crossmodal_hybrid
from diffloc.pipeline.crossmodal_config import CrossmodalTaskConfig, HybridMapConfig
from diffloc.pipeline.crossmodal_task import run_crossmodal
from diffloc.pipeline.stage import StageOutcome


def _pose(x: float, yaw_deg: float) -> torch.Tensor:
    """Camera at (x, 0, 0) looking along +z turned by ``yaw_deg`` about the y axis."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64)
    T[0, 3] = x
    return T


def test_a_view_is_covered_within_both_bounds_inclusive():
    real = torch.stack([_pose(0.0, 0.0), _pose(10.0, 90.0)])
    views = torch.stack(
        [
            _pose(2.0, 0.0),  # at the distance bound: covered
            _pose(2.01, 0.0),  # just beyond it
            _pose(0.0, 45.0),  # at the angle bound: covered
            _pose(0.0, 46.0),  # just beyond it
            _pose(10.5, 60.0),  # near the second image, 30 deg off: covered
            _pose(5.0, 0.0),  # between them, near neither
        ]
    )
    got = uncovered_views(views, real, max_distance_m=2.0, max_angle_deg=45.0)
    assert got.tolist() == [False, True, False, True, False, True]
    assert uncovered_views(views, real[:0], 2.0, 45.0).all()  # no real image covers nothing
    assert not uncovered_views(views, real, 20.0, 180.0).any()  # the widest bounds cover all


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"max_distance_m": 0.0}, "max_distance_m must be a positive number"),
        ({"max_distance_m": math.nan}, "max_distance_m must be a positive number"),
        ({"max_angle_deg": 0.0}, r"max_angle_deg must be in \(0, 180\]"),
        ({"max_angle_deg": 181.0}, r"max_angle_deg must be in \(0, 180\]"),
    ],
)
def test_bad_bounds_are_refused(kwargs, message):
    bounds = {"max_distance_m": 2.0, "max_angle_deg": 45.0, **kwargs}
    with pytest.raises(ValueError, match=message):
        uncovered_views(_pose(0.0, 0.0)[None], _pose(0.0, 0.0)[None], **bounds)


def test_bad_poses_are_refused():
    nan = _pose(0.0, 0.0)[None].clone()
    nan[0, 0, 3] = math.nan
    with pytest.raises(ValueError, match="real_T_wc"):
        uncovered_views(_pose(0.0, 0.0)[None], nan, 2.0, 45.0)
    with pytest.raises(ValueError, match="T_wc"):
        uncovered_views(torch.eye(4)[None, :3], torch.eye(4)[None], 2.0, 45.0)


def test_bad_hybrid_settings_name_their_key():
    with pytest.raises(ValueError, match="max_angle_deg must be in"):
        HybridMapConfig(max_angle_deg=200.0)
    cfg = compose_config(["task=crossmodal", "map=hybrid", "scene=outdoor"])
    assert to_object(cfg.map).max_distance_m == 4.0  # the outdoor render spacing
    assert to_object(compose_config(["task=crossmodal", "map=hybrid"]).map).max_distance_m == 2.0


CAMERA = PinholeCamera(fx=40.0, fy=40.0, cx=32.0, cy=24.0, width=64, height=48)
SETTINGS = DatabaseConfig(netvlad_clusters=2, samples_per_image=20, kmeans_iterations=2)


def _part(tmp_path: Path, name: str, poses: list[torch.Tensor], seed: int, camera=CAMERA):
    """A database of random images at ``poses`` as its stage gives it (saved and loaded, so
    colours are 8-bit) and an outcome naming its folder."""
    generator = torch.Generator().manual_seed(seed)
    m = len(poses)
    views = RGBD(
        torch.rand(m, 3, camera.height, camera.width, generator=generator),
        torch.rand(m, 1, camera.height, camera.width, generator=generator) * 5.0,
    )
    db = build_database(views, torch.stack(poses), camera, SETTINGS, name)
    folder = db.save(tmp_path / name)
    return RenderedDatabase.load(folder), StageOutcome(None, {"rgbd": identity(folder)})


@pytest.fixture
def parts(tmp_path: Path):
    real = _part(tmp_path, "real", [_pose(0.0, 0.0), _pose(1.0, 0.0), _pose(2.0, 0.0)], 0)
    renders = [_pose(1.0, 0.0), _pose(1.0, 180.0), _pose(1.0, 90.0), _pose(8.0, 0.0)]
    return real, _part(tmp_path, "rendered", renders, 1)


def test_the_database_holds_every_real_image_and_the_uncovered_renders(
    tmp_path, parts, monkeypatch
):
    real, rendered = parts
    dataset = tmp_path / "dataset"
    config = HybridMapConfig(max_distance_m=2.0, max_angle_deg=45.0)
    db, outcome = crossmodal_hybrid.build_hybrid_database(dataset, config, SETTINGS, real, rendered)
    summary = outcome.summary
    assert (summary.images, summary.real_images, summary.rendered_images, summary.renders) == (
        6,
        3,
        3,
        4,
    )
    keep = [1, 2, 3]  # the render facing back, the one facing sideways, the far one
    assert torch.equal(db.T_wc, torch.cat([real[0].T_wc, rendered[0].T_wc[keep]]))
    assert torch.equal(db.rgb, torch.cat([real[0].rgb, rendered[0].rgb[keep]]))
    assert torch.equal(db.depth, torch.cat([real[0].depth, rendered[0].depth[keep]]))
    union = build_database(RGBD(db.rgb, db.depth), db.T_wc, CAMERA, SETTINGS)
    assert torch.allclose(db.global_descriptors, union.global_descriptors)
    pairs = zip(db.features, union.features, strict=True)
    assert all(torch.equal(a.keypoints, b.keypoints) for a, b in pairs)
    record = dataset / "crossmodal" / "hybrid" / "database" / "rgbd_database.json"
    before = record.read_bytes()

    def refuse(*args, **kwargs):
        raise AssertionError("the hybrid database was built again although it was reusable")

    monkeypatch.setattr(crossmodal_hybrid, "build_database", refuse)
    again, outcome_again = crossmodal_hybrid.build_hybrid_database(
        dataset, config, SETTINGS, real, rendered
    )
    assert record.read_bytes() == before and outcome_again == outcome
    assert torch.equal(again.T_wc, db.T_wc)


def test_a_changed_coverage_bound_builds_the_database_again(tmp_path, parts):
    real, rendered = parts
    dataset = tmp_path / "dataset"
    wide = HybridMapConfig(max_distance_m=10.0, max_angle_deg=45.0)
    crossmodal_hybrid.build_hybrid_database(dataset, HybridMapConfig(), SETTINGS, real, rendered)
    _, outcome = crossmodal_hybrid.build_hybrid_database(dataset, wide, SETTINGS, real, rendered)
    assert outcome.summary.rendered_images == 2  # the far render is now covered too


def test_parts_with_different_cameras_are_refused_and_nothing_is_written(tmp_path, parts):
    real, _ = parts
    small = PinholeCamera(fx=40.0, fy=40.0, cx=32.0, cy=32.0, width=64, height=64)
    rendered = _part(tmp_path, "small", [_pose(5.0, 180.0)], 2, camera=small)
    dataset = tmp_path / "dataset"
    with pytest.raises(ValueError, match="map=hybrid: the real-image and rendered databases"):
        crossmodal_hybrid.build_hybrid_database(
            dataset, HybridMapConfig(), SETTINGS, real, rendered
        )
    assert not (dataset / "crossmodal").exists()


def test_the_database_marks_its_real_images(tmp_path, parts):
    real, rendered = parts
    assert bool(real[0].real.all()) is False  # the parts here are built as renders
    db, _ = crossmodal_hybrid.build_hybrid_database(
        tmp_path / "dataset", HybridMapConfig(), SETTINGS, real, rendered
    )
    assert db.real.tolist() == [True, True, True, False, False, False]


def test_retrieval_tuning_with_the_hybrid_map_is_refused_before_any_work(tmp_path):
    task = CrossmodalTaskConfig(tune_retrieval=True)
    with pytest.raises(ValueError, match="map=hybrid holds the mapping images themselves"):
        run_crossmodal(tmp_path / "dataset", HybridMapConfig(), task, tmp_path / "out")
    assert list(tmp_path.iterdir()) == []
