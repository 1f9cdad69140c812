"""The README's cheap commands run as written, from a fresh folder, on the tiny scene.

The fenced blocks labelled ``sh tiny-scene`` hold commands (``\\`` continues a line, ``#``
starts a comment); plain fenced blocks whose first line is ``$ diffloc ...`` show a command
and exactly what it prints. Both run in the same folder after the tiny-scene commands.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def _blocks(info: str) -> list[str]:
    """The bodies of the README's fenced blocks whose info string is ``info`` (indented
    blocks, e.g. in a list item, lose their indentation)."""
    blocks: list[str] = []
    opened: str | None = None
    for line in README.splitlines():
        text = line.lstrip(" ")
        if opened is None and text.startswith("```"):
            opened, indent, body = text[3:].strip(), len(line) - len(text), []
        elif opened is not None and text == "```":
            if opened == info:
                blocks.append("\n".join(body))
            opened = None
        elif opened is not None:
            body.append(line[indent:])
    return blocks


def tiny_scene_commands() -> list[list[str]]:
    """The commands of the ``sh tiny-scene`` blocks, as argument lists."""
    commands = []
    for block in _blocks("sh tiny-scene"):
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            if words:
                commands.append(words)
    return commands


def shown_sessions() -> list[tuple[list[str], str]]:
    """``(command, output)`` of the plain blocks that start with ``$ diffloc``."""
    sessions = []
    for block in _blocks(""):
        first, _, output = block.partition("\n")
        if first.startswith("$ diffloc "):
            sessions.append((shlex.split(first.removeprefix("$ ")), output.strip()))
    return sessions


def _diffloc(words: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run a ``diffloc ...`` command line with this checkout's package."""
    assert words[0] == "diffloc", words
    return subprocess.run(
        [sys.executable, "-m", "diffloc.cli", *words[1:]],
        capture_output=True,
        text=True,
        env={**os.environ, "CI": "true", "PYTHONPATH": str(ROOT)},
        cwd=cwd,
        timeout=900,
    )


def test_the_readme_shows_cheap_commands():
    commands = tiny_scene_commands()
    assert len(commands) >= 2
    assert all(words[0] == "diffloc" for words in commands)
    assert any("scene.trajectory.max_frames=5" in words for words in commands)
    assert shown_sessions()


def test_the_readme_tiny_scene_commands_run(tmp_path: Path):
    for words in tiny_scene_commands():
        done = _diffloc(words, tmp_path)
        assert done.returncode == 0, (words, done.stderr[-3000:])
    # Where the README says things go.
    assert (tmp_path / "data" / "tiny" / "dataset.json").is_file()
    assert (tmp_path / "data" / "tiny" / "db").is_dir()
    runs = sorted(tmp_path.glob("outputs/*/*/results.json"))
    assert len(runs) == len(tiny_scene_commands())
    assert (runs[0].parent / "diffloc.log").is_file()
    for words, output in shown_sessions():
        done = _diffloc(words, tmp_path)
        assert (done.stdout + done.stderr).strip() == output, words
