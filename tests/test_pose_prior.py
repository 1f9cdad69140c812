"""The pose prior of a query sequence (beyond seed 2): the database images near the last
accepted pose are tried before the retrieval's.

Known answers on constructed poses for :func:`prior_references`; the sequence loop with a
fake localiser (it records what it was given and answers from a script), so the tests run in
milliseconds; the candidate order through the real localiser on the tiny scene; bad settings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import pytest
import torch

from diffloc.checks import ShapeError
from diffloc.config import compose_config, to_object
from diffloc.crossmodal.database import DatabaseConfig, render_database
from diffloc.crossmodal.synthesize import MeshMap
from diffloc.geometry.camera import PinholeCamera
from diffloc.io.dataset import read_sequence
from diffloc.io.mesh_obj import read_textured_mesh_obj
from diffloc.reloc.pose_prior import PosePriorConfig, prior_references
from diffloc.reloc.rendered import (
    RenderedDatabaseLocalizer,
    RenderedLocalization,
    RenderedLocalizerConfig,
)
from diffloc.reloc.sequence_prior import SequencePrior, localize_in_order
from diffloc.reloc.stage_clock import STAGES

F64 = torch.float64


def _yaw(deg: float) -> torch.Tensor:
    """(3, 3) rotation about the world z axis (the optical axis turns in the x-z plane of a
    camera whose axis is world x after this)."""
    a = math.radians(deg)
    return torch.tensor(
        [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]],
        dtype=F64,
    )


def _poses(centres: list[list[float]], yaws_deg: list[float]) -> torch.Tensor:
    """(N, 4, 4) poses at ``centres`` whose optical axes (camera z) lie in the world x-y
    plane at the given yaws (0: along world x)."""
    base = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=F64)
    T = torch.eye(4, dtype=F64).repeat(len(centres), 1, 1)
    for i, (c, y) in enumerate(zip(centres, yaws_deg, strict=True)):
        T[i, :3, :3] = _yaw(y) @ base
        T[i, :3, 3] = torch.tensor(c, dtype=F64)
    return T


PRIOR = _poses([[0.0, 0.0, 0.0]], [0.0])[0]


def test_prior_references_keep_near_images_looking_alike_nearest_first():
    # index: 0 at 3 m, 1 at 0.5 m, 2 at 1 m turned 50 deg, 3 at 1.5 m turned 80 deg,
    # 4 at 0.2 m looking back, 5 at 2.5 m (outside 2 m)
    T_db = _poses(
        [[3.0, 0, 0], [0, 0.5, 0], [1.0, 0, 0], [0, -1.5, 0], [0.2, 0, 0], [0, 0, 2.5]],
        [0.0, 10.0, 50.0, -80.0, 180.0, 0.0],
    )
    refs = prior_references(T_db, PRIOR, 2.0, 60.0)
    assert refs.dtype == torch.int64
    assert refs.tolist() == [1, 2]
    assert prior_references(T_db, PRIOR, 2.0, 90.0).tolist() == [1, 2, 3]
    assert prior_references(T_db, PRIOR, 3.0, 90.0).tolist() == [1, 2, 3, 5, 0]
    assert prior_references(T_db, PRIOR, 2.0, 180.0).tolist() == [4, 1, 2, 3]
    assert prior_references(T_db, PRIOR, 3.0, 180.0, max_images=2).tolist() == [4, 1]


def test_the_angle_is_between_optical_axes_and_the_cut_is_inclusive():
    T_db = _poses([[0.0, 0, 0], [0.0, 0, 0]], [45.0, 45.5])
    assert prior_references(T_db, PRIOR, 0.0, 45.0).tolist() == [0]
    # a roll about the optical axis changes nothing
    rolled = T_db.clone()
    roll = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    rolled[:, :3, :3] = rolled[:, :3, :3] @ roll
    assert prior_references(rolled, PRIOR, 0.0, 45.0).tolist() == [0]


def test_an_empty_result_and_ties_keep_the_index_order():
    T_db = _poses([[5.0, 0, 0], [0, 1.0, 0], [1.0, 0, 0]], [0.0, 0.0, 0.0])
    empty = prior_references(T_db, PRIOR, 0.5, 10.0)
    assert empty.shape == (0,) and empty.dtype == torch.int64
    assert prior_references(T_db, PRIOR, 1.0, 10.0).tolist() == [1, 2]


def test_prior_references_refuse_bad_input():
    T_db = _poses([[1.0, 0, 0]], [0.0])
    with pytest.raises(ShapeError):
        prior_references(T_db[0], PRIOR, 1.0, 10.0)
    with pytest.raises(ShapeError):
        prior_references(T_db, PRIOR[:3], 1.0, 10.0)
    bad = PRIOR.clone()
    bad[0, 3] = math.nan
    with pytest.raises(ValueError, match="T_wc_prior"):
        prior_references(T_db, bad, 1.0, 10.0)
    with pytest.raises(ValueError, match="radius_m"):
        prior_references(T_db, PRIOR, -1.0, 10.0)
    with pytest.raises(ValueError, match="max_angle_deg"):
        prior_references(T_db, PRIOR, 1.0, 190.0)


@dataclass
class FakeLocalizer:
    """Answers from ``script`` (accepted, x position) per call and records the ``prior``
    it was given."""

    script: list[tuple[bool, float]]
    given: list[torch.Tensor | None] = field(default_factory=list)

    def localize(self, image, camera, references=None, prior=None) -> RenderedLocalization:
        accepted, x = self.script[len(self.given)]
        self.given.append(prior)
        T = torch.eye(4, dtype=F64)
        T[0, 3] = x
        empty = torch.zeros(0, dtype=torch.int64)
        times = dict.fromkeys(STAGES, 0.0)
        return RenderedLocalization(
            T,
            accepted,
            accepted,
            0,
            empty,
            empty,
            False,
            (),
            0,
            0,
            0,
            math.nan,
            accepted,
            0,
            0,
            empty,
            times,
            times,
        )


CAMERA = PinholeCamera(fx=10.0, fy=10.0, cx=1.5, cy=1.5, width=4, height=4)
# database images every 2 m along x, all looking the same way
T_LINE = torch.eye(4, dtype=F64).repeat(6, 1, 1)
T_LINE[:, 0, 3] = torch.arange(6, dtype=F64) * 2.0


def _run(script, times, config):
    fake = FakeLocalizer(script)
    images = [torch.zeros(3, 4, 4)] * len(script)
    prior = SequencePrior(config, T_LINE)
    results = list(localize_in_order(fake, images, times, CAMERA, prior))
    assert len(results) == len(script)
    return [None if g is None else g.tolist() for g in fake.given]


def test_the_loop_uses_the_prior_only_after_an_accepted_pose():
    config = PosePriorConfig(radius_m=1.0, growth_mps=0.5, max_age_s=100.0)
    # rejected pose at x=4 (ignored), accepted at x=4.2, rejected at x=10, then again
    script = [(False, 4.0), (True, 4.2), (False, 10.0), (True, 0.0), (False, 0.0)]
    given = _run(script, [0.0, 1.0, 2.0, 6.0, 7.0], config)
    assert given[0] is None and given[1] is None  # nothing accepted before
    assert given[2] == [2]  # 1 s after x=4.2: radius 1.5 m -> image at 4 m only
    assert given[3] == [2, 3, 1]  # 5 s: radius 3.5 m; the rejected x=10 changed nothing
    assert given[4] == [0]  # 1 s after the accepted x=0


def test_the_loop_drops_the_prior_after_max_age():
    config = PosePriorConfig(radius_m=1.0, growth_mps=0.0, max_age_s=3.0)
    script = [(True, 2.0), (False, 0.0), (False, 0.0), (False, 0.0)]
    given = _run(script, [0.0, 3.0, 3.5, 10.0], config)
    assert given == [None, [1], None, None]


def test_the_loop_without_a_prior_gives_none_and_refuses_unordered_times():
    fake = FakeLocalizer([(True, 0.0), (True, 0.0)])
    list(localize_in_order(fake, [torch.zeros(3, 4, 4)] * 2, [0.0, 1.0], CAMERA, None))
    assert fake.given == [None, None]
    prior = SequencePrior(PosePriorConfig(growth_mps=1.0), T_LINE)
    prior.update(5.0, True, torch.eye(4, dtype=F64))
    with pytest.raises(ValueError, match="time order"):
        prior.references(4.0)


def test_a_prior_without_growth_is_refused():
    with pytest.raises(ValueError, match="growth_mps"):
        SequencePrior(PosePriorConfig(), T_LINE)


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"radius_m": 0.0}, "task.localizer.prior.radius_m"),
        ({"growth_mps": -1.0}, "task.localizer.prior.growth_mps"),
        ({"max_angle_deg": 0.0}, "task.localizer.prior.max_angle_deg"),
        ({"max_angle_deg": 181.0}, "task.localizer.prior.max_angle_deg"),
        ({"max_images": 0}, "task.localizer.prior.max_images"),
        ({"max_age_s": math.inf}, "task.localizer.prior.max_age_s"),
    ],
)
def test_bad_prior_settings_name_their_key(settings, message):
    with pytest.raises(ValueError, match=message):
        PosePriorConfig(**settings)


def test_the_hydra_group_turns_the_prior_on_with_the_scene_growth_and_checks_values():
    base = ["task=crossmodal", "map=mesh", "scene=indoor"]
    assert to_object(compose_config(base).task).localizer.prior is None
    on = base + ["+task/localizer/prior=sequence"]
    task = to_object(compose_config([*on, "task.localizer.prior.max_images=3"]).task)
    prior = task.localizer_for("mesh").prior
    assert (prior.max_images, prior.growth_mps) == (3, 1.0)
    outdoor = to_object(compose_config([*on, "scene=outdoor"]).task)
    assert outdoor.localizer_for("mesh").prior.growth_mps == 6.0
    with pytest.raises(ValueError, match="task.localizer.prior.max_angle_deg"):
        to_object(compose_config([*on, "task.localizer.prior.max_angle_deg=200"]).task)
    with pytest.raises(ValueError, match="task.prior_growth_mps"):
        to_object(compose_config([*base, "task.prior_growth_mps=-1"]).task)


@pytest.fixture(scope="module")
def tiny(tiny_indoor_dataset):
    mesh = read_textured_mesh_obj(tiny_indoor_dataset / "map" / "mesh" / "scene.obj")
    mapping = read_sequence(tiny_indoor_dataset, "mapping")
    small = DatabaseConfig(netvlad_clusters=4, samples_per_image=50)
    db = render_database(MeshMap(mesh), mapping.T_wc, mapping.camera, small, "mesh")
    return db, mapping


def test_the_localizer_tries_the_prior_first_then_the_retrieval_without_repeats(tiny):
    db, mapping = tiny
    config = RenderedLocalizerConfig(top_k=3, rerank=None, stop_inliers=None)
    localizer = RenderedDatabaseLocalizer(db, config)
    image = db.rgb[2]
    plain = localizer.localize(image, mapping.camera)
    assert plain.prior.shape == (0,) and not plain.from_prior
    retrieved = plain.retrieved.tolist()
    prior = torch.tensor([retrieved[1], 0 if retrieved[1] != 0 else 1])
    result = localizer.localize(image, mapping.camera, prior=prior)
    tried = [c.reference for c in result.candidates]
    assert tried[:2] == prior.tolist()
    assert tried[2:] == [r for r in retrieved if r not in prior.tolist()]
    assert result.retrieved.tolist() == retrieved
    assert result.from_prior == (result.reference in prior.tolist())
    with pytest.raises(IndexError, match="prior"):
        localizer.localize(image, mapping.camera, prior=torch.tensor([db.num_images]))


def test_stop_inliers_applies_to_the_prior_images(tiny):
    db, mapping = tiny
    config = RenderedLocalizerConfig(top_k=3, rerank=None, stop_inliers=6, validation=None)
    result = RenderedDatabaseLocalizer(db, config).localize(
        db.rgb[2], mapping.camera, prior=torch.tensor([2])
    )
    assert [c.reference for c in result.candidates] == [2]
    assert result.accepted and result.from_prior
