"""Reading a JSON record (a stage summary, a metadata file) with errors that name the file.

Example:
    >>> from pathlib import Path
    >>> _ = Path("build_map.json").write_text('{"config": {"voxel_size_m": 0.02}}')
    >>> read_json_record("build_map.json")
    {'config': {'voxel_size_m': 0.02}}
    >>> _ = Path("build_map.json").write_text("{")
    >>> read_json_record("build_map.json", "delete it")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ValueError: build_map.json: not valid JSON (...); delete it
"""

from __future__ import annotations

import json
import os
from pathlib import Path

__all__ = ["read_json_record"]


def read_json_record(path: str | os.PathLike, remedy: str = "") -> dict:
    """The JSON object stored in ``path``.

    Args:
        path: the file.
        remedy: what the user should do about a bad file, appended to the message (e.g.
            "delete it and run `diffloc task=build_map` again").

    Returns:
        The decoded object.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not UTF-8 JSON or holds no JSON object; the message names
            the file and the remedy.
    """
    path = Path(path)
    tail = f"; {remedy}" if remedy else ""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise FileNotFoundError(f"{path} is missing{tail}") from exc
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a UTF-8 text file ({exc}){tail}") from exc
    try:
        record = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc}){tail}") from exc
    if not isinstance(record, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(record).__name__}{tail}")
    return record
