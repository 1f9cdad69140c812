"""Shared fixtures: configs composed from the real ``conf/`` tree, tiny simulated datasets."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

from diffloc.cli import CONF_DIR
from diffloc.sim.dataset import simulate_dataset

# Small enough that a whole dataset simulates in seconds on 2 cores.
TINY = [
    "scene.camera.width=160",
    "scene.camera.height=120",
    "scene.trajectory.max_frames=5",
    "scene.lidar.azimuth_steps=256",
    "scene.tls.elevation_steps=48",
    "scene.tls.azimuth_steps=96",
    "progress=false",
]


def compose_config(overrides: list[str]) -> DictConfig:
    """Compose ``conf/config.yaml`` with command-line style overrides."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


def scene_config(overrides: list[str]):
    """The typed scene config (a dataclass instance) for some overrides."""
    return OmegaConf.to_object(compose_config(overrides).scene)


@pytest.fixture(scope="session")
def tiny_indoor_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny simulated indoor dataset (seed 0), made once per test session."""
    out = tmp_path_factory.mktemp("sim") / "indoor_seed0"
    return simulate_dataset(scene_config(TINY + ["scene=indoor"]), out, show_progress=False)
