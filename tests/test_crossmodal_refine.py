"""The refinement stage of ``task=crossmodal`` (``task.refine``) on a synthetic map and queries.

A textured wall and floor strip as a coloured cloud; the queries are its renders at known
poses, written as a query sequence; the localisation is a record whose poses are a few
centimetres off. The stage must bring a pose closer, keep a pose it cannot improve, skip what
was not localised, reuse its result and make it again when a setting changes.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from diffloc.cli import run
from diffloc.config import compose_config, to_object
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import se3_exp
from diffloc.io.calib import Calibration
from diffloc.io.dataset import SequenceWriter, write_dataset_info
from diffloc.optim.render_refine import CloudMaps, RenderRefineConfig
from diffloc.pipeline import crossmodal_refine
from diffloc.pipeline.crossmodal_config import CrossmodalRefineConfig, MeshMapConfig
from diffloc.pipeline.crossmodal_refine import MapSource, refine_sequence
from diffloc.pipeline.crossmodal_task import run_crossmodal
from diffloc.pipeline.stage import StageOutcome
from tests.localization_records import sequence_localization
from tests.test_render_refine import wall_and_floor

CAMERA = PinholeCamera.from_fov(48, 36, 1.2)
SPACING_M = 0.05
CONFIG = CrossmodalRefineConfig(
    enabled=True,
    image_scale=1.0,  # the queries are renders at the camera's size
    render=RenderRefineConfig(levels=(0.5, 1.0), iterations=10, min_correlation=0.7),
    verify=False,
)
# Generic poses (not fronto-parallel to the wall, where coplanar splats tie in depth order).
T_TRUE = se3_exp(
    torch.tensor(
        [[0.1, 0.0, 0.2, 0.05, 0.25, 0.02], [-0.2, 0.05, 0.1, -0.03, -0.2, 0.01]],
        dtype=torch.float64,
    )
)
OFFSET = torch.tensor([[0.02, -0.02, 0.02, 0.01, -0.01, 0.008]], dtype=torch.float64)
"""A right perturbation of 3.5 cm and 0.9 deg."""


def cloud() -> CloudMaps:
    points, colours = wall_and_floor(SPACING_M)
    return CloudMaps(points, colours, SPACING_M, 8.0)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Queries: frame 0 and 2 the cloud seen from ``T_TRUE`` (under another exposure), frame 1
    noise (an image the map does not explain)."""
    root = tmp_path_factory.mktemp("refine") / "synthetic"
    maps = cloud()
    model, _ = maps.model(0, T_TRUE, torch.zeros(0), CAMERA)
    views = model.render(T_TRUE, CAMERA)
    colours = (0.8 * views.rgb / views.alpha.clamp_min(1e-3) + 0.05).clamp(0, 1)
    noise = torch.rand(3, CAMERA.height, CAMERA.width, generator=torch.Generator().manual_seed(0))
    images = [colours[0], 0.3 + 0.4 * noise.double(), colours[1]]
    poses = [T_TRUE[0], T_TRUE[0], T_TRUE[1]]
    with SequenceWriter(root / "query_same", Calibration(CAMERA)) as writer:
        for i, (image, T_wc) in enumerate(zip(images, poses, strict=True)):
            writer.add_frame(float(i), T_wc, image.float())
    write_dataset_info(root, ["query_same"])
    return root


def localization(accepted: list[bool]) -> tuple:
    """The localisation record: every frame 3.5 cm / 0.9 deg off its true pose."""
    T_true = torch.stack((T_TRUE[0], T_TRUE[0], T_TRUE[1]))
    T_wc = (T_true @ se3_exp(OFFSET)).numpy()
    loc = sequence_localization(3, T_wc=T_wc, accepted=np.array(accepted))
    outcome = StageOutcome(None, {"localization.npz": {"sha256": str(accepted)}})
    return loc, outcome


SOURCE = MapSource(cloud, {"sha256": "synthetic cloud"})


def translation_error(T_wc: np.ndarray, T_true: torch.Tensor) -> float:
    return float(np.linalg.norm(T_wc[:3, 3] - T_true[:3, 3].numpy()))


@pytest.fixture(scope="module")
def refined(dataset):
    return refine_sequence(
        dataset, "cloud", "query_same", localization([True, True, False]), SOURCE, CONFIG
    )


def test_a_pose_a_few_cm_off_comes_back_closer(refined) -> None:
    refinement, outcome = refined
    assert refinement.query.tolist() == [0, 1]  # the accepted queries only
    assert bool(refinement.kept[0])
    before = translation_error(refinement.T_wc_start[0], T_TRUE[0])
    after = translation_error(refinement.T_wc[0], T_TRUE[0])
    assert before == pytest.approx(0.0346, abs=1e-3)
    assert after < 0.1 * before
    assert outcome.summary.localised == 2 and outcome.summary.kept == 1
    assert outcome.summary.median_cpu_ms > 0


def test_a_refused_move_keeps_the_localised_pose(refined) -> None:
    refinement, _ = refined
    assert not bool(refinement.kept[1])
    assert np.array_equal(refinement.T_wc[1], refinement.T_wc_start[1])
    assert refinement.correlation[1] < CONFIG.render.min_correlation


def test_the_answers_replace_only_the_kept_poses(refined) -> None:
    refinement, _ = refined
    loc, _ = localization([True, True, False])
    answers = refinement.answers(loc)
    assert np.array_equal(answers[0], refinement.T_wc[0])
    assert np.array_equal(answers[1:], loc.T_wc[1:])


def count_refinements(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Count the queries the stage refines from now on."""
    calls: list[int] = []
    real = crossmodal_refine.refine_query

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(crossmodal_refine, "refine_query", counted)
    return calls


def test_the_result_is_reused_and_made_again_when_a_setting_changes(
    dataset, refined, monkeypatch
) -> None:
    calls = count_refinements(monkeypatch)
    first, _ = refined
    again, outcome = refine_sequence(
        dataset, "cloud", "query_same", localization([True, True, False]), SOURCE, CONFIG
    )
    assert calls == [] and np.array_equal(again.T_wc, first.T_wc)
    changed = replace(CONFIG, render=replace(CONFIG.render, levels=(1.0,), iterations=2))
    refine_sequence(
        dataset, "cloud", "query_same", localization([True, True, False]), SOURCE, changed
    )
    assert len(calls) == 2
    # ... and when the localisation changes
    refine_sequence(
        dataset, "cloud", "query_same", localization([True, False, False]), SOURCE, changed
    )
    assert len(calls) == 3
    # ``enabled`` is no setting of the result
    refine_sequence(
        dataset,
        "cloud",
        "query_same",
        localization([True, False, False]),
        SOURCE,
        replace(changed, enabled=False),
    )
    assert len(calls) == 3


def test_an_unsupported_map_is_refused_before_any_work(tmp_path) -> None:
    task = compose_config(["task=crossmodal", "map=mesh", "task.refine.enabled=true"]).task
    with pytest.raises(
        ValueError, match=r"task.refine supports map=nerf\|tls\|cloud, not map=mesh"
    ):
        run_crossmodal(tmp_path / "none", MeshMapConfig(), to_object(task), tmp_path / "out")
    assert not (tmp_path / "none").exists() and not (tmp_path / "out").exists()


@pytest.mark.parametrize("option", ["images", "hybrid"])
def test_the_cli_refuses_the_refinement_with_the_image_maps(option, tmp_path) -> None:
    cfg = compose_config(
        ["task=crossmodal", f"map={option}", "task.refine.enabled=true", f"dataset={tmp_path}"]
    )
    with pytest.raises(ValueError, match=f"not map={option}"):
        run(cfg)


def test_bad_refine_settings_name_their_key() -> None:
    with pytest.raises(ValueError, match="task.refine.image_scale"):
        CrossmodalRefineConfig(image_scale=0.0)
    with pytest.raises(ValueError, match="task.refine.cloud_spacing_m"):
        CrossmodalRefineConfig(cloud_spacing_m=-1.0)
    assert math.isclose(CrossmodalRefineConfig().render.min_correlation, 0.7)
