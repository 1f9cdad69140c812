"""Root configuration schema of the ``diffloc`` app and its registration with Hydra.

YAML files in ``conf/`` name these schemas in their defaults lists, so every key is typed and
a misspelt key is an error rather than silently ignored.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from diffloc.maps.surfel import SurfelMapConfig
from diffloc.pipeline.build_map import BuildMapConfig
from diffloc.pipeline.database_stage import DatabaseConfig
from diffloc.sim.config import IndoorSceneConfig, OutdoorSceneConfig


@dataclass
class SimulateTaskConfig:
    """``task=simulate``: write a simulated dataset folder."""

    name: str = "simulate"
    overwrite: bool = False


@dataclass
class DatabaseTaskConfig:
    """``task=build_db`` / ``task=optimize_db``: the settings live in the root ``db`` node."""

    name: str = "build_db"


@dataclass
class DifflocConfig:
    """The app's root: which task, which scene, where the dataset lives, map settings."""

    task: Any = MISSING
    scene: Any = MISSING
    surfel: SurfelMapConfig = MISSING
    out_dir: str = MISSING
    dataset: str = MISSING
    db: DatabaseConfig = field(default_factory=DatabaseConfig)
    progress: bool = True


def register_configs() -> None:
    """Store the schemas in Hydra's ConfigStore (idempotent)."""
    store = ConfigStore.instance()
    store.store(name="diffloc_schema", node=DifflocConfig)
    store.store(group="task", name="schema_simulate", node=SimulateTaskConfig)
    store.store(group="task", name="schema_build_map", node=BuildMapConfig)
    store.store(group="task", name="schema_database", node=DatabaseTaskConfig)
    store.store(group="surfel", name="schema_surfel", node=SurfelMapConfig)
    store.store(group="scene", name="schema_indoor", node=IndoorSceneConfig)
    store.store(group="scene", name="schema_outdoor", node=OutdoorSceneConfig)
