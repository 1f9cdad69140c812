"""Per-frame auto exposure in the simulator: off by default (datasets unchanged), recorded."""

import json
import math

import numpy as np
import pytest
import torch

from diffloc.io.dataset import read_sequence
from diffloc.io.exposure import EXPOSURE_FILE, read_exposures, write_exposures
from diffloc.sim.dataset import simulate_dataset
from diffloc.sim.imaging import AutoExposureConfig, auto_exposure_scales
from tests.conftest import TINY, digests, scene_config


def test_auto_exposure_is_off_by_default_and_at_unit_gain_changes_no_byte(
    tiny_indoor_dataset, tmp_path
):
    """Off by default: no exposure record, no setting in dataset.json. On, with the controller
    held at a gain of exactly 1, the mapping run's files are byte-identical to the default
    run's: the feature touches nothing but the gain (frames, noise draws, depth, lidar and poses
    are the same). (A digest of the tiny dataset pinned on the commit before auto exposure
    existed stopped matching with the libraries of a fresh install on 2026-11-27, at that
    commit's code too: bytes can be pinned within one environment only.)"""
    assert not list(tiny_indoor_dataset.rglob(EXPOSURE_FILE))
    info = json.loads((tiny_indoor_dataset / "dataset.json").read_text())
    assert all("auto_exposure" not in s for s in info["config"]["sequences"])
    unit = [f"scene.sequences.0.auto_exposure.{k}" for k in ("enabled", "min_scale", "max_scale")]
    overrides = TINY + ["scene=indoor", f"{unit[0]}=true", f"{unit[1]}=1.0", f"{unit[2]}=1.0"]
    root = simulate_dataset(scene_config(overrides), tmp_path / "unit", show_progress=False)
    _, exposures = read_exposures(root / "mapping" / EXPOSURE_FILE)
    np.testing.assert_array_equal(exposures, np.ones_like(exposures))
    auto_exposed = digests(root / "mapping")
    del auto_exposed[EXPOSURE_FILE]
    assert auto_exposed == digests(tiny_indoor_dataset / "mapping")


def reference_scales(metered: torch.Tensor, previous: float, cfg: AutoExposureConfig) -> list:
    """The controller written as the recurrence it is, frame after frame."""
    scales, log_scale = [], math.log(previous)
    for m in metered.tolist():
        wanted = min(max(cfg.target_mean / m, cfg.min_scale), cfg.max_scale)
        log_scale = (1 - cfg.adaptation) * log_scale + cfg.adaptation * math.log(wanted)
        scales.append(math.exp(log_scale))
    return scales


@pytest.mark.parametrize("adaptation", [0.3, 1.0])
def test_controller_matches_the_frame_by_frame_recurrence(adaptation):
    cfg = AutoExposureConfig(enabled=True, adaptation=adaptation)
    metered = torch.tensor([0.05, 0.4, 0.18, 0.01, 0.9])
    got = auto_exposure_scales(metered, 1.3, cfg)
    np.testing.assert_allclose(got.numpy(), reference_scales(metered, 1.3, cfg), rtol=1e-12)
    assert float(got.min()) >= cfg.min_scale and float(got.max()) <= cfg.max_scale


def test_controller_refuses_a_bad_adaptation():
    with pytest.raises(ValueError, match="adaptation"):
        auto_exposure_scales(torch.ones(2), 1.0, AutoExposureConfig(adaptation=0.0))


def test_controller_refuses_bad_bounds():
    with pytest.raises(ValueError, match="min_scale"):
        auto_exposure_scales(torch.ones(2), 1.0, AutoExposureConfig(min_scale=2.0, max_scale=1.0))


def test_exposure_file_round_trips(tmp_path):
    times, exposures = np.array([0.0, 0.5, 1.25]), np.array([1.0, 0.731, 2.5e-1])
    write_exposures(tmp_path / EXPOSURE_FILE, times, exposures)
    got_times, got_exposures = read_exposures(tmp_path / EXPOSURE_FILE)
    np.testing.assert_array_equal(got_times, times)
    np.testing.assert_array_equal(got_exposures, exposures)


def test_exposure_file_refuses_a_non_positive_exposure(tmp_path):
    with pytest.raises(ValueError, match="> 0"):
        write_exposures(tmp_path / EXPOSURE_FILE, np.zeros(1), np.zeros(1))


def test_missing_exposure_file_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="auto exposure"):
        read_exposures(tmp_path / EXPOSURE_FILE)


def test_corrupt_exposure_line_is_named(tmp_path):
    (tmp_path / EXPOSURE_FILE).write_text("# timestamp exposure\n0.0 1.0\n0.5 nan\n")
    with pytest.raises(ValueError, match=r"exposure.txt:3"):
        read_exposures(tmp_path / EXPOSURE_FILE)


def test_auto_exposed_mapping_run_records_its_varying_exposures(tiny_indoor_dataset, tmp_path):
    overrides = TINY + ["scene=indoor", "scene.sequences.0.auto_exposure.enabled=true"]
    cfg = scene_config(overrides)
    root = simulate_dataset(cfg, tmp_path / "auto", show_progress=False)
    times, exposures = read_exposures(root / "mapping" / EXPOSURE_FILE)
    mapping = read_sequence(root, "mapping")
    np.testing.assert_allclose(times, mapping.timestamps)
    assert exposures.std() > 0.01
    assert not (root / "query_same" / EXPOSURE_FILE).exists()
    # Other sequences are untouched; the mapping images differ by their exposure.
    base = read_sequence(tiny_indoor_dataset, "mapping")
    np.testing.assert_array_equal(
        read_sequence(root, "query_same").load_rgb(0).numpy(),
        read_sequence(tiny_indoor_dataset, "query_same").load_rgb(0).numpy(),
    )
    brighter = mapping.load_rgb(0).mean() > base.load_rgb(0).mean()
    assert bool(brighter) == bool(exposures[0] > 1.0)
