"""Root configuration schema of the ``diffloc`` app and its registration with Hydra.

The YAML tree ships inside the package, in ``diffloc/conf/`` (:data:`CONF_DIR`), so an
installed ``diffloc`` finds it from any folder. Its files name these schemas in their defaults
lists, so every key is typed and a misspelt key is an error rather than silently ignored.

Example:
    >>> cfg = compose_config(["task=simulate", "scene.seed=3"])
    >>> cfg.out_dir
    'data/indoor_seed3'
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.errors import InstantiationException
from hydra.utils import get_class, instantiate
from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf

from diffloc.io.lock import LockConfig
from diffloc.maps.surfel import SurfelMapConfig
from diffloc.optim.rig_calibration import RigCalibrationConfig
from diffloc.pipeline.build_map import BuildMapConfig
from diffloc.pipeline.colmap_stage import ExportColmapTaskConfig
from diffloc.pipeline.crossmodal_config import (
    CrossmodalTaskConfig,
    HybridMapConfig,
    ImageMapConfig,
    MeshMapConfig,
    NerfMapConfig,
    PointMapConfig,
)
from diffloc.pipeline.database_stage import DatabaseConfig
from diffloc.pipeline.nerf_config import TrainNerfConfig
from diffloc.pipeline.reloc_stage import RelocStageConfig
from diffloc.pipeline.update_stage import UpdateTaskConfig
from diffloc.sim.config import IndoorSceneConfig, OutdoorSceneConfig

CONF_DIR = Path(__file__).resolve().parent / "conf"
"""The Hydra config tree of the ``diffloc`` app (``config.yaml`` and its groups)."""


@dataclass
class SimulateTaskConfig:
    """``task=simulate``: write a simulated dataset folder."""

    name: str = "simulate"
    overwrite: bool = False


@dataclass
class DatabaseTaskConfig:
    """``task=build_db`` / ``task=optimize_db``: the settings live in the root ``db`` node
    (its ``features`` and ``optim`` from the groups of those names)."""

    name: str = "build_db"


@dataclass
class RigCalibrationTaskConfig:
    """``task=calibrate_rig``: the database comes from the root ``db`` node.

    Attributes:
        calibration: settings of :func:`~diffloc.optim.rig_calibration.calibrate_rig`.
    """

    name: str = "calibrate_rig"
    calibration: RigCalibrationConfig = field(default_factory=RigCalibrationConfig)


@dataclass
class TrainNerfTaskConfig:
    """``task=train_nerf``: the settings live in the root ``nerf`` node."""

    name: str = "train_nerf"


@dataclass
class RelocalizeTaskConfig:
    """``task=relocalize``: the settings live in the root ``reloc`` node (its ``retriever``
    and ``method`` matching from the ``retriever`` and ``matcher`` groups).

    Attributes:
        out_dir: where results go; empty: the Hydra run folder (``<dataset>/reloc`` outside
            a Hydra run).
    """

    name: str = "relocalize"
    out_dir: str = ""


@dataclass
class MainTaskConfig:
    """``task=main``: the whole pipeline on the selected scene, each stage cached.

    simulate (unless ``dataset`` exists) -> surfel map -> database -> optimisation ->
    relocalisation of ``reloc.sequences`` -> metrics table and plots.

    Attributes:
        out_dir: where results go (as in :class:`RelocalizeTaskConfig`).
        build_map: the map stage; only the surfel map by default (the coloured point maps
            serve the rendered-database localisation, not this pipeline).
        optimize: run the surfel optimisation (and relocalise in the optimised database).
    """

    name: str = "main"
    out_dir: str = ""
    build_map: BuildMapConfig = field(
        default_factory=lambda: BuildMapConfig(point_maps=[], preview_frames=2)
    )
    optimize: bool = True


@dataclass
class DifflocConfig:
    """The app's root: which task, which scene, where the dataset lives, the map, the
    database, the relocalisation and the radiance-field settings.

    The groups fill it: ``task/`` (and ``task/scene/``, a task's settings that follow the
    scene kind), ``scene/``, ``map/`` (the surfel map of the seed 1 pipeline; the coloured TLS
    / lidar clouds, the textured mesh and the radiance-field submaps of ``task=crossmodal``),
    ``features/`` (``db.features``), ``optim/`` (``db.optim``, ``db.optim_check``), ``retriever/``
    (``reloc.retriever``), ``matcher/`` (the relocaliser's matching, in ``reloc.method``) and
    ``experiment/`` (named setups of the committed tables).

    Attributes:
        stage: what a run does when a stage folder it needs is in use by another run
            (``stage.wait=false`` refuses at once, ``stage.timeout_s=60`` waits at most a
            minute; default: wait as long as it takes).
    """

    task: Any = MISSING
    scene: Any = MISSING
    map: Any = MISSING  # typed by map/<option>.yaml (surfel, tls, cloud, mesh, images, nerf)
    out_dir: str = MISSING
    dataset: str = MISSING
    db: DatabaseConfig = field(default_factory=DatabaseConfig)
    reloc: Any = MISSING  # a RelocStageConfig, typed by reloc/<scene>.yaml (its retriever swaps)
    nerf: TrainNerfConfig = field(default_factory=TrainNerfConfig)
    progress: bool = True
    stage: LockConfig = field(default_factory=LockConfig)


GROUP_SCHEMAS: dict[str, type] = {
    "schema_task_simulate": SimulateTaskConfig,
    "schema_task_build_map": BuildMapConfig,
    "schema_task_database": DatabaseTaskConfig,
    "schema_task_update_db": UpdateTaskConfig,
    "schema_task_relocalize": RelocalizeTaskConfig,
    "schema_task_calibrate_rig": RigCalibrationTaskConfig,
    "schema_task_export_colmap": ExportColmapTaskConfig,
    "schema_task_main": MainTaskConfig,
    "schema_task_train_nerf": TrainNerfTaskConfig,
    "schema_task_crossmodal": CrossmodalTaskConfig,
    "schema_map_surfel": SurfelMapConfig,
    "schema_map_tls": PointMapConfig,
    "schema_map_cloud": PointMapConfig,
    "schema_map_mesh": MeshMapConfig,
    "schema_map_images": ImageMapConfig,
    "schema_map_nerf": NerfMapConfig,
    "schema_map_hybrid": HybridMapConfig,
    "schema_reloc": RelocStageConfig,
    "schema_scene_indoor": IndoorSceneConfig,
    "schema_scene_outdoor": OutdoorSceneConfig,
}
"""The schemas of the group YAML files, by the name their defaults lists give them."""

SWAP_POINTS: dict[str, tuple[str, ...]] = {
    "diffloc_schema": ("db.features",),
    "schema_reloc": ("retriever",),
}
"""Nodes of a schema that a group option fills with a ``_target_`` node (``features/*.yaml``,
``retriever/*.yaml``): the stored schema leaves them empty, so the option's class, not the
dataclass default's, types them."""


def _schema(name: str, node: type) -> DictConfig:
    """The schema ``node`` as Hydra stores it: its swap points (:data:`SWAP_POINTS`) empty,
    and writable (OmegaConf marks the nodes of frozen settings dataclasses read-only, which
    would refuse every override; the instance built from the node is frozen again)."""
    schema = OmegaConf.structured(node)
    for key in SWAP_POINTS.get(name, ()):
        OmegaConf.update(schema, key, MISSING, merge=False)
    for _, child in _walk(schema, ""):
        OmegaConf.set_readonly(child, None)
    return schema


@functools.cache
def register_configs() -> None:
    """Store the schemas in Hydra's ConfigStore, once per process (a third of a composition's
    time went to rebuilding them on every call).

    The group schemas (:data:`GROUP_SCHEMAS`) are stored at the top level and named by the
    YAML files with an absolute path (``- /schema_task_main@_here_``), so they are not
    choices of their group: ``diffloc --help`` and the "available options" of a misspelt
    choice list only real tasks, scenes, maps, features, retrievers, ...
    """
    store = ConfigStore.instance()
    for name, node in {"diffloc_schema": DifflocConfig, **GROUP_SCHEMAS}.items():
        store.store(name=name, node=_schema(name, node))


def compose_config(overrides: Sequence[str] = ()) -> DictConfig:
    """Compose the app's ``config.yaml`` with command-line style overrides, outside a Hydra run.

    Args:
        overrides: e.g. ``["task=simulate", "scene.seed=3"]``, as on the command line.

    Returns:
        The composed config (interpolations unresolved, as the ``diffloc`` command gets it).

    Raises:
        UnknownKeyError: an override added a key no schema declares (``+scene.max_frames=5``).
        hydra.errors.ConfigCompositionException: other bad overrides (a misspelt key without
            ``+``, an unknown choice, a value of the wrong type).
    """
    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=list(overrides))
    check_known_keys(cfg)
    return cfg


def to_object(node: DictConfig) -> Any:
    """The dataclass instance of a composed node, its swap points built from their
    ``_target_`` (``db.features`` becomes an ``XFeatConfig`` or ``OrbConfig``).

    Args:
        node: a typed node of a composed config, e.g. ``cfg.db``.

    Returns:
        The dataclass instance; its ``__post_init__`` checks have run.

    Raises:
        ValueError: a setting out of range, as the settings class raised it (Hydra's
            ``InstantiationException`` wrapper is removed, so the message is the class's own).

    Example:
        >>> to_object(compose_config(["features=orb"]).db).features.kind
        'orb'
    """
    try:
        return instantiate(node, _convert_="object")
    except InstantiationException as exc:
        cause = exc.__cause__
        while isinstance(cause, InstantiationException) and cause.__cause__ is not None:
            cause = cause.__cause__
        if isinstance(cause, ValueError):
            raise cause from None
        raise


class UnknownKeyError(ValueError):
    """A config key that no schema declares, e.g. one added on the command line with ``+``."""


def nerf_settings(scene: str, overrides: Sequence[str] = ()) -> TrainNerfConfig:
    """The ``nerf`` node ``diffloc task=train_nerf scene=<scene> <overrides>`` trains with
    (clustering, data and training settings; ``nerf/scene/silvr_<scene>.yaml`` where it
    exists), for scripts that train, profile or score a submap outside the task.

    Example:
        >>> nerf_settings("outdoor", ["nerf.submap=2"]).train.field.contracted
        True
    """
    return to_object(compose_config([f"scene={scene}", "task=train_nerf", *overrides])).nerf


def _walk(node: DictConfig | ListConfig, prefix: str) -> Iterator[tuple[str, DictConfig]]:
    """``(full key, node)`` of every dict node under ``node`` (itself included), skipping
    missing and interpolated values."""
    if isinstance(node, DictConfig):
        yield prefix, node
        children = ((_join(prefix, key), key) for key in node.keys())
    else:
        children = ((f"{prefix}.{index}", index) for index in range(len(node)))
    for path, key in children:
        if OmegaConf.is_missing(node, key) or OmegaConf.is_interpolation(node, key):
            continue
        child = node[key]
        if isinstance(child, DictConfig | ListConfig):
            yield from _walk(child, path)


def check_known_keys(cfg: DictConfig) -> None:
    """Refuse keys that no schema declares.

    Hydra refuses a misspelt key on the command line (``scene.max_frame=5``), but with ``+``
    (``+scene.max_frames=5``) it adds the key to the typed node, and the dataclass built from
    it ignores it: the run would go ahead without the setting. This walks every node typed by
    a dataclass and checks its keys against the dataclass fields.

    Args:
        cfg: a composed config (e.g. from :func:`compose_config`).

    Raises:
        UnknownKeyError: the first unknown key, with the known key of the same name if there
            is one (``scene.trajectory.max_frames``) or close field names of its node.
    """
    typed = [(path, node, fields) for path, node in _walk(cfg, "") if (fields := _fields(node))]
    for path, node, fields in typed:
        for key in node.keys():
            if key in fields:
                continue
            unknown = _join(path, key)
            same_name = [_join(where, key) for where, _, known in typed if key in known]
            close = [_join(path, k) for k in difflib.get_close_matches(str(key), fields, n=2)]
            advice = (
                f"did you mean {' or '.join((same_name or close)[:3])}?"
                if same_name or close
                else f"the keys of {path or 'the root'} are {', '.join(fields)}"
            )
            schema = _schema_class(node).__name__
            raise UnknownKeyError(
                f"unknown config key {unknown}: {schema} has no field {key!r} ({advice})"
            )


def _schema_class(node: DictConfig) -> type | None:
    """The dataclass that types ``node``: its ``_target_`` if it has one, else its schema."""
    if "_target_" in node:
        return get_class(node._target_)
    return OmegaConf.get_type(node)


def _fields(node: DictConfig) -> list[str]:
    """The keys a node may hold: the fields of its dataclass (and ``_target_`` if it is one
    of a swap point); empty for a node no dataclass types."""
    cls = _schema_class(node)
    if not dataclasses.is_dataclass(cls):
        return []
    names = [f.name for f in dataclasses.fields(cls)]
    return ["_target_", *names] if "_target_" in node else names


def _join(path: str, key: object) -> str:
    """The full key of ``key`` under the node at ``path`` (``""`` is the root)."""
    return f"{path}.{key}" if path else str(key)
