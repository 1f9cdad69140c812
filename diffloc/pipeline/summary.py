"""Typed stage results: what a stage returns and stores at the top level of its record.

Each stage declares a frozen dataclass deriving from :class:`StageSummary` (``MapSummary``,
``BuiltDatabase``, ...). :meth:`diffloc.pipeline.stage.StageRun.commit` writes it into the
record as JSON and hands back the same type read from that JSON, and
:meth:`~diffloc.pipeline.stage.StageRun.reusable` reads a reused record into it, so a fresh
and a reused run return equal values (tuples come back as lists, numbers as JSON keeps them).

Example:
    >>> from dataclasses import dataclass
    >>> @dataclass(frozen=True)
    ... class NoteSummary(StageSummary):
    ...     chars: int
    ...     words: list[str]
    >>> summary = NoteSummary(chars=5, words=("hello",))
    >>> summary.to_json()
    {'chars': 5, 'words': ['hello']}
    >>> NoteSummary.from_record({"chars": 5, "words": ["hello"], "stage": {}})
    NoteSummary(chars=5, words=['hello'])
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

__all__ = ["StageSummary"]

S = TypeVar("S", bound="StageSummary")


def _json_default(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"a stage summary holds {type(value).__name__!r}, which JSON cannot store")


@dataclasses.dataclass(frozen=True)
class StageSummary:
    """Base of a stage's typed summary (a frozen dataclass of JSON-storable fields)."""

    def to_json(self) -> dict:
        """The fields as JSON types (tuples become lists, paths strings)."""
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return json.loads(json.dumps(fields, default=_json_default))

    @classmethod
    def from_record(cls: type[S], record: Mapping, source: str | Path = "the record") -> S:
        """The summary stored at the top level of a stage record (other entries ignored).

        Raises:
            ValueError: a field is missing from the record (an older diffloc wrote it); the
                message names ``source`` and the fields.
        """
        names = [f.name for f in dataclasses.fields(cls)]
        missing = [name for name in names if name not in record]
        if missing:
            raise ValueError(
                f"{source} lacks {', '.join(missing)} of a {cls.__name__}: it was written by "
                "another diffloc version; run the stage again"
            )
        return cls(**{name: record[name] for name in names})

    def round_trip(self: S) -> S:
        """This summary as it reads back from its JSON (what a reused run returns)."""
        return type(self).from_record(self.to_json())
