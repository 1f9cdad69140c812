"""A stage's settings as JSON, with the class of every swap point named.

``dataclasses.asdict`` drops the type of a nested config, so a database built with ORB and one
built with XFeat would record only their settings. :func:`config_record` keeps the types of the
nodes the command line swaps by ``_target_`` (``features=orb``, ``retriever=bow``): each such
node carries its class path under ``_target_``, exactly as its YAML option names it.
"""

from __future__ import annotations

import dataclasses
from typing import Any

__all__ = ["config_record"]


def _json(value: Any, swapped: bool = False) -> Any:
    """``value`` as JSON types; a dataclass held by a field declared ``Any`` (``swapped``)
    gets its class path under ``_target_``."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        record = {
            f.name: _json(getattr(value, f.name), f.type in (Any, "Any"))
            for f in dataclasses.fields(value)
        }
        if swapped:
            cls = type(value)
            return {"_target_": f"{cls.__module__}.{cls.__qualname__}", **record}
        return record
    if isinstance(value, list | tuple):
        return [_json(item) for item in value]
    if isinstance(value, dict):
        return {key: _json(item) for key, item in value.items()}
    return value


def config_record(cfg: Any) -> dict:
    """The fields of the dataclass ``cfg`` as JSON types, recursively (like
    ``dataclasses.asdict``), with ``_target_`` (the class path) on every field declared
    ``Any`` that holds a dataclass: the swap points whose class is the choice.

    Args:
        cfg: a dataclass instance (e.g. a ``DatabaseConfig``).

    Returns:
        A dict of JSON types.

    Example:
        >>> from diffloc.pipeline.database_stage import DatabaseConfig
        >>> from diffloc.features.local import OrbConfig
        >>> record = config_record(DatabaseConfig(features=OrbConfig()))
        >>> record["features"]["_target_"], record["features"]["max_keypoints"]
        ('diffloc.features.local.OrbConfig', 1000)
    """
    if not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
        raise TypeError(f"config_record takes a dataclass instance, got {type(cfg).__name__}")
    return _json(cfg)
