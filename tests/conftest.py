"""Shared fixtures: configs composed from the packaged ``diffloc/conf/`` tree, tiny datasets."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from diffloc.cli import run
from diffloc.config import compose_config
from diffloc.maps.surfel import SurfelMapConfig
from diffloc.pipeline.build_map import BuildMapConfig, build_maps
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


TINY_NERF = [
    "nerf.epochs=2",
    "nerf.submaps.num_submaps=2",
    "nerf.data.holdout_every=0",
    "nerf.data.lidar_stride=8",
    "nerf.train.field.triplane_resolutions=[16]",
    "nerf.train.field.triplane_channels=4",
    "nerf.train.field.hidden=16",
    "nerf.train.sampler.grid_resolution=16",
    "nerf.train.sampler.coarse_samples=16",
    "nerf.train.sampler.importance_samples=8",
    "nerf.train.ray_batch=64",
    "nerf.train.lidar_batch=32",
    "nerf.train.normal_batch=8",
    "nerf.train.steps_per_epoch=2",
]
"""``task=train_nerf`` settings that train submap 0 of the tiny scene in seconds (2 epochs of 2
steps, so a checkpoint is written before training ends)."""

FINE_SURFELS = SurfelMapConfig(voxel_size_m=0.02, mean_radius_m=0.02, normal_radius_m=0.08)
"""Surfel map settings fine enough for the 160x120 tiny scene."""


def scene_config(overrides: list[str]):
    """The typed scene config (a dataclass instance) for some overrides."""
    return OmegaConf.to_object(compose_config(overrides).scene)


@pytest.fixture(scope="session")
def tiny_indoor_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny simulated indoor dataset (seed 0), made once per test session."""
    out = tmp_path_factory.mktemp("sim") / "indoor_seed0"
    return simulate_dataset(scene_config(TINY + ["scene=indoor"]), out, show_progress=False)


@pytest.fixture(scope="session")
def tiny_indoor_mapped(tiny_indoor_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny indoor dataset with its surfel map (no point maps), made once per test session.

    Tests that write into a dataset folder take a copy (:func:`copy_dataset`)."""
    root = tmp_path_factory.mktemp("mapped") / "indoor_seed0"
    shutil.copytree(tiny_indoor_dataset, root)
    build_maps(
        root, BuildMapConfig(point_maps=[], preview_frames=1), FINE_SURFELS, show_progress=False
    )
    return root


SIDE_CAMERAS = ["scene.rig.side_camera_yaw_deg=[90,-90]"]
"""A left and a right camera on the tiny scene's mapping run (``mapping_left``, ``_right``)."""


@pytest.fixture(scope="session")
def tiny_indoor_side_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny indoor dataset (seed 0) simulated with :data:`SIDE_CAMERAS`, made once."""
    out = tmp_path_factory.mktemp("side") / "indoor_seed0_side"
    cfg = scene_config(TINY + ["scene=indoor", *SIDE_CAMERAS])
    return simulate_dataset(cfg, out, show_progress=False)


@pytest.fixture(scope="session")
def tiny_indoor_side_mapped(
    tiny_indoor_side_dataset: Path, tmp_path_factory: pytest.TempPathFactory
) -> Path:
    """:func:`tiny_indoor_side_dataset` with its surfel map (as :func:`tiny_indoor_mapped`)."""
    root = tmp_path_factory.mktemp("side_mapped") / "indoor_seed0_side"
    shutil.copytree(tiny_indoor_side_dataset, root)
    build_maps(
        root, BuildMapConfig(point_maps=[], preview_frames=1), FINE_SURFELS, show_progress=False
    )
    return root


def digests(root: Path) -> dict[str, str]:
    """sha256 of every file under ``root``, by its path relative to ``root``."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def copy_dataset(source: Path, tmp_path_factory: pytest.TempPathFactory, name: str) -> Path:
    """A private copy of the dataset folder ``source`` in a new temporary folder ``name``."""
    root = tmp_path_factory.mktemp(name) / source.name
    shutil.copytree(source, root)
    return root


def run_task(task: str, dataset: Path, *overrides: str) -> dict:
    """``diffloc task=<task> dataset=<dataset> <overrides>`` on the tiny scene settings."""
    return run(compose_config(TINY + [f"task={task}", f"dataset={dataset}", *overrides]))
