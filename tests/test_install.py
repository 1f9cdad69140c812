"""The installed package carries its Hydra configs and finds them from any folder."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import diffloc
from diffloc.config import CONF_DIR

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = Path(diffloc.__file__).resolve().parent


def test_configs_live_inside_the_package():
    assert CONF_DIR == PACKAGE / "conf"
    assert (CONF_DIR / "config.yaml").is_file()
    assert not (ROOT / "conf").exists()


def test_package_data_ships_every_config_file():
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"
    ]["diffloc"]
    shipped = {path for pattern in patterns for path in PACKAGE.glob(pattern)}
    configs = {path for path in CONF_DIR.rglob("*") if path.is_file()}
    assert configs and configs <= shipped, sorted(configs - shipped)


def test_the_cli_finds_its_configs_from_another_folder(tmp_path):
    env = {**os.environ, "CI": "true", "PYTHONPATH": str(ROOT)}
    done = subprocess.run(
        [sys.executable, "-m", "diffloc.cli", "--info", "searchpath"],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"file://{CONF_DIR}" in done.stdout
    assert not list(tmp_path.iterdir())  # nothing written to the start folder
