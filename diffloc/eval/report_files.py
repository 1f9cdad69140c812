"""The files an experiment leaves: a Markdown report beside its JSON, or one benchmark JSON.

Every script under ``experiments/`` ends in one of these two calls, so results are written
the same way everywhere: parents created, each file written atomically (a crash leaves the
previous file or none, never half of one), JSON indented for diffs and ending in a newline.
"""

from __future__ import annotations

import json
from pathlib import Path

from diffloc.io.atomic import atomic_write_text

__all__ = ["made_by_lines", "write_benchmark", "write_report"]


def made_by_lines(commands: list[str] | str) -> list[str]:
    """The lines that open a report: "Made by:" and the commands in a bash block, then a blank.

    Example:

        >>> made_by_lines(["diffloc task=main", "python3 experiments/tables.py runs/x"])[2:]
        ['```bash', 'diffloc task=main', 'python3 experiments/tables.py runs/x', '```', '']
    """
    commands = [commands] if isinstance(commands, str) else list(commands)
    return ["Made by:", "", "```bash", *commands, "```", ""]


def write_report(out: Path, markdown: str, data: object) -> tuple[Path, Path]:
    """Write ``<out>.md`` (``markdown``) and ``<out>.json`` (``data``); returns both paths.

    ``out`` may carry a suffix (it is replaced). Example:

        >>> import tempfile
        >>> root = Path(tempfile.mkdtemp())
        >>> md, js = write_report(root / "table", "| a |\\n", [{"a": 1}])
        >>> md.name, js.name, json.loads(js.read_text())
        ('table.md', 'table.json', [{'a': 1}])
    """
    out = Path(out)
    json_text = json.dumps(data, indent=2) + "\n"  # fails before either file is touched
    out.parent.mkdir(parents=True, exist_ok=True)
    md_path, json_path = out.with_suffix(".md"), out.with_suffix(".json")
    atomic_write_text(md_path, markdown if markdown.endswith("\n") else markdown + "\n")
    atomic_write_text(json_path, json_text)
    return md_path, json_path


def write_benchmark(out: Path, result: dict, *, sort_keys: bool = False) -> str:
    """Write a benchmark's ``result`` to ``out`` (indented JSON); returns it as one JSON line.

    The benchmark scripts print the returned line last, so a caller can read the figures from
    stdout without opening the file. Example:

        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "results" / "bench.json"
        >>> write_benchmark(path, {"ms": 1.5, "a": 2}, sort_keys=True)
        '{"a": 2, "ms": 1.5}'
        >>> json.loads(path.read_text())["ms"]
        1.5
    """
    out = Path(out)
    text = json.dumps(result, indent=2, sort_keys=sort_keys) + "\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, text)
    return json.dumps(result, sort_keys=sort_keys)
