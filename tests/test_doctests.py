"""The docstring examples in ``diffloc/`` are part of the test suite and none is skipped.

``python3 -m pytest`` (the README's and CI's command) runs them through ``--doctest-modules``
over ``testpaths``; this file checks that set-up and that nobody parks an example with
``# doctest: +SKIP`` (an example that cannot run cheaply is written as a plain ``Usage::``
block instead).
"""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_pytest_collects_the_package_docstrings():
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    pytest_config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]
    options = pytest_config["ini_options"]
    assert "diffloc" in options["testpaths"] and "tests" in options["testpaths"]
    assert "--doctest-modules" in options["addopts"].split()


def test_no_docstring_example_is_skipped():
    skipped = [
        f"{path.relative_to(ROOT)}:{number}"
        for path in sorted((ROOT / "diffloc").rglob("*.py"))
        for number, line in enumerate(path.read_text().splitlines(), start=1)
        if "doctest:" in line and "SKIP" in line
    ]
    assert not skipped, f"skipped docstring examples: {skipped}"


def test_every_example_block_checks_an_output():
    """A docstring whose examples print nothing checks nothing (assertions aside)."""
    finder = doctest.DocTestFinder()
    silent = []
    for path in sorted((ROOT / "diffloc").rglob("*.py")):
        if ">>>" not in path.read_text():
            continue
        parts = path.relative_to(ROOT).with_suffix("").parts
        module = importlib.import_module(".".join(p for p in parts if p != "__init__"))
        for test in finder.find(module):
            if test.examples and not any(
                e.want.strip() or "assert" in e.source for e in test.examples
            ):
                silent.append(test.name)
    assert not silent, f"examples without an expected output: {silent}"
