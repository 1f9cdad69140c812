"""``experiments/run_tables.sh`` runs end to end, and every command it runs is valid.

The full script takes hours, so it runs here with recording stand-ins for ``diffloc`` and
``python3`` on ``PATH``: the shell logic (functions, quoting, ``set -euo pipefail``) runs for
real, and the recorded commands are then checked. Each ``diffloc`` command composes into typed
settings at every value of every axis it sweeps (one axis at a time, the others at their first
value); each Python command names a script that exists and options its argparse parsers declare.
"""

from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf

from diffloc.config import CONF_DIR, compose_config, to_object

ROOT = Path(__file__).resolve().parents[1]

# A stand-in command: appends "<name> NUL <argc> NUL <arg> NUL ..." to $RUN_TABLES_LOG, so
# arguments holding newlines (the tables' --command headers) or nothing at all survive.
_RECORDER = """#!/usr/bin/env bash
{ printf '%s\\0%d\\0' "$(basename "$0")" "$#"; printf '%s\\0' "$@"; } >> "$RUN_TABLES_LOG"
"""


def _read_log(path: Path) -> list[list[str]]:
    """The recorded commands, each ``[name, arg, ...]``."""
    fields = path.read_bytes().decode().split("\0")
    commands, i = [], 0
    while i < len(fields) - 1:
        name, count = fields[i], int(fields[i + 1])
        commands.append([name, *fields[i + 2 : i + 2 + count]])
        i += 2 + count
    return commands


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> list[list[str]]:
    """The commands of ``bash experiments/run_tables.sh`` (no arguments: every table)."""
    work = tmp_path_factory.mktemp("run_tables")
    (work / "experiments" / "results").mkdir(parents=True)
    shutil.copy(ROOT / "experiments" / "run_tables.sh", work / "experiments")
    # The one output the script reads with shell commands (seed 1's protocol run).
    protocol = work / "experiments" / "runs" / "seed1_protocol"
    protocol.mkdir(parents=True)
    (protocol / "results.md").write_text("| sequence |\n")
    (protocol / "results.json").write_text("{}\n")
    bin_dir = work / "bin"
    bin_dir.mkdir()
    for name in ("diffloc", "python3"):
        (bin_dir / name).write_text(_RECORDER)
        (bin_dir / name).chmod(0o755)
    log = work / "commands.log"
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    env["RUN_TABLES_LOG"] = str(log)
    done = subprocess.run(
        ["bash", "experiments/run_tables.sh"], cwd=work, env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    assert (
        (work / "experiments" / "results" / "seed1_protocol.md").read_text().startswith("Made by:")
    )
    return _read_log(log)


def _sweep_axes(words: list[str]) -> tuple[list[str], dict[str, list[str]]]:
    """A ``diffloc`` command's fixed overrides (``hydra.*`` left out) and the axes it sweeps:
    comma lists on the command line and its experiment's ``hydra.sweeper.params``."""
    multirun = "-m" in words or "--multirun" in words
    parser = OverridesParser.create()
    overrides = [w for w in words if w not in ("-m", "--multirun") and not w.startswith("hydra.")]
    axes: dict[str, list[str]] = {}
    for name in re.findall(r"\+experiment=(\S+)", " ".join(overrides)):
        params = OmegaConf.select(
            OmegaConf.load(CONF_DIR / "experiment" / f"{name}.yaml"), "hydra.sweeper.params"
        )
        if params is not None and multirun:
            parsed = parser.parse_overrides([f"{k}={v}" for k, v in params.items()])
            axes.update({o.get_key_element(): list(o.sweep_string_iterator()) for o in parsed})
    fixed = []
    for override, word in zip(parser.parse_overrides(overrides), overrides, strict=True):
        if override.is_sweep_override():
            assert multirun, f"a sweep without -m: {word}"
            axes[override.get_key_element()] = list(override.sweep_string_iterator())
        else:
            fixed.append(word)
    return fixed, axes


def _compose(words: list[str], overrides: list[str]) -> None:
    """Compose ``overrides`` and build the typed settings of every top-level node they set
    (``db.noise_sigma=0.2`` builds ``db``, ``scene=outdoor`` builds ``scene``; an experiment's
    own settings are built by tests/test_config_groups.py); a failure names the command."""
    try:
        cfg = compose_config(overrides)
        for node in {o.lstrip("+").split("=")[0].split(".")[0].split("/")[0] for o in overrides}:
            if OmegaConf.is_config(cfg.get(node)):  # not plain values such as `dataset`
                to_object(cfg[node])
    except Exception as error:
        raise AssertionError(f"diffloc {' '.join(words)}: {overrides}: {error}") from error


def test_every_diffloc_command_composes_at_every_swept_value(recorded):
    """Each command's first job composes; every other swept value once (a value several sweeps
    share, such as a scene seed, in the first of them), the command's other axes at their first
    value."""
    commands = [words[1:] for words in recorded if words[0] == "diffloc"]
    assert sum("-m" in words for words in commands) >= 10
    composed: set[tuple[str, ...]] = set()
    swept: set[tuple[str, str]] = set()
    for words in commands:
        fixed, axes = _sweep_axes(words)
        first = {key: values[0] for key, values in axes.items()}
        points = [first]
        for key, values in axes.items():
            fresh = [value for value in values[1:] if (key, value) not in swept]
            swept.update((key, value) for value in fresh)
            points += [{**first, key: value} for value in fresh]
        for point in points:
            overrides = [*fixed, *(f"{k}={v}" for k, v in point.items())]
            if tuple(overrides) not in composed:
                composed.add(tuple(overrides))
                _compose(words, overrides)
    assert ("scene.seed", "5") in swept and len(composed) > 40


def test_every_python_command_names_a_script_and_its_options(recorded):
    options: dict[str, set[str]] = {}
    for words in recorded:
        if words[0] == "python3":
            used = {w.split("=")[0] for w in words[2:] if w.startswith("--")}
            options.setdefault(words[1], set()).update(used)
    assert "experiments/tables.py" in options and "experiments/heldout.py" in options
    for script, used in sorted(options.items()):
        assert (ROOT / script).is_file(), f"run_tables.sh runs a missing script: {script}"
        unknown = used - _declared_options(ROOT / script)
        assert not unknown, f"{script} declares no option {sorted(unknown)} run_tables.sh gives"


def _declared_options(script: Path) -> set[str]:
    """The ``--options`` a script's argparse parsers declare (every ``add_argument`` call)."""
    declared = set()
    for node in ast.walk(ast.parse(script.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_argument":
            declared |= {
                arg.value
                for arg in node.args
                if isinstance(arg, ast.Constant) and str(arg.value).startswith("--")
            }
    return declared
