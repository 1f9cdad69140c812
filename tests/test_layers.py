"""Imports only point down: every module of ``diffloc`` imports its own unit or a lower layer.

``LAYERS`` is the one statement of the order; ``diffloc/LAYERS.md`` mirrors it (checked here).
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "diffloc"
DOC = PACKAGE / "LAYERS.md"

# Lowest layer first. A unit is a package or a top-level module of diffloc ("diffloc" itself is
# the package root, ``diffloc/__init__.py``). A module may import its own unit and the units of
# lower layers; units of one layer are independent of each other.
LAYERS: tuple[tuple[str, ...], ...] = (
    (
        "diffloc",
        "diffloc.benchmark",
        "diffloc.checks",
        "diffloc.o3d",
        "diffloc.progress",
        "diffloc.threads",
    ),
    ("diffloc.geometry",),
    ("diffloc.io",),
    ("diffloc.maps",),
    ("diffloc.render", "diffloc.maps.nerf"),
    ("diffloc.features",),
    ("diffloc.database",),
    ("diffloc.crossmodal",),
    ("diffloc.optim",),
    ("diffloc.reloc",),
    ("diffloc.eval",),
    ("diffloc.sim",),
    ("diffloc.pipeline",),
    ("diffloc.config",),
    ("diffloc.cli", "diffloc.testing"),
)
# First-party code outside the package, which the package never imports.
OUTSIDE = ("tests", "experiments")


@dataclass(frozen=True)
class Import:
    """One import statement's target as seen from ``module``, at line ``line``."""

    module: str
    line: int
    target: str


def _module_name(path: Path, package_dir: Path) -> str:
    parts = path.relative_to(package_dir.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules(package_dir: Path) -> dict[str, Path]:
    """Dotted name -> file of every module under ``package_dir``."""
    return {_module_name(p, package_dir): p for p in sorted(package_dir.rglob("*.py"))}


def _imports(module: str, path: Path, modules: dict[str, Path]) -> list[Import]:
    """Every import of ``path`` (module level, in functions, under ``if TYPE_CHECKING:``...).

    ``from a import b`` targets the module ``a.b`` when that is a module, else ``a``; relative
    imports are resolved against the module's package.
    """
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [Import(module, node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([node.module] if node.module else []))
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                target = submodule if submodule in modules else base
                found.append(Import(module, node.lineno, target))
    return sorted(set(found), key=lambda imp: (imp.line, imp.target))


def _rank(name: str, layers: tuple[tuple[str, ...], ...]) -> tuple[int, str] | None:
    """``(layer index, unit)`` of a dotted module name; ``None`` if no unit holds it."""
    root = layers[0][0].split(".")[0]
    best = None
    for index, units in enumerate(layers):
        for unit in units:
            holds = name == unit or (unit != root and name.startswith(unit + "."))
            if holds and (best is None or len(unit) > len(best[1])):
                best = (index, unit)
    return best


def _violations(package_dir: Path, layers: tuple[tuple[str, ...], ...]) -> list[str]:
    """One message per import of a higher layer, a peer unit or code outside the package, and
    per module that no unit of ``layers`` holds."""
    modules = _modules(package_dir)
    root = package_dir.name
    messages = []
    for module, path in modules.items():
        where = path.relative_to(package_dir.parent)
        own = _rank(module, layers)
        if own is None:
            messages.append(f"{where}: module {module} is in no layer of LAYERS")
            continue
        for imp in _imports(module, path, modules):
            top = imp.target.split(".")[0]
            if top in OUTSIDE:
                messages.append(f"{where}:{imp.line}: {module} imports {imp.target} (outside)")
                continue
            if top != root:
                continue
            target = _rank(imp.target, layers)
            if target is None or target[1] == own[1] or target[0] < own[0]:
                continue
            messages.append(
                f"{where}:{imp.line}: {module} (layer {own[0]}, {own[1]}) imports {imp.target} "
                f"(layer {target[0]}, {target[1]})"
            )
    return messages


def _documented_layers(text: str) -> tuple[tuple[str, ...], ...]:
    """The layer table of LAYERS.md: the fenced block after ``## Order``, one
    ``<index> <unit> <unit> ...`` line per layer."""
    block = re.search(r"^## Order\n.*?^```\n(.*?)^```", text, re.MULTILINE | re.DOTALL)
    if block is None:
        raise ValueError(f"{DOC}: no fenced layer table after '## Order'")
    rows = [line.split() for line in block.group(1).splitlines() if line.strip()]
    if [row[0] for row in rows] != [str(i) for i in range(len(rows))]:
        raise ValueError(f"{DOC}: layer rows must be numbered 0, 1, 2, ...")
    return tuple(tuple(row[1:]) for row in rows)


def test_imports_only_point_down() -> None:
    violations = _violations(PACKAGE, LAYERS)
    assert not violations, "layer violations (diffloc/LAYERS.md):\n" + "\n".join(violations)


def test_layers_doc_mirrors_the_constant() -> None:
    assert _documented_layers(DOC.read_text()) == LAYERS


def test_every_unit_of_layers_exists() -> None:
    modules = _modules(PACKAGE)
    missing = [unit for units in LAYERS for unit in units if unit not in modules]
    assert not missing, f"LAYERS names units that do not exist: {missing}"


@pytest.fixture
def fake_package(tmp_path: Path) -> Path:
    """A package ``diffloc`` with ``low`` below ``high``; ``low.bad`` imports upward in every
    form the checker must see."""
    files = {
        "__init__.py": "",
        "low/__init__.py": "",
        "low/ok.py": "import diffloc.low.bad\nfrom . import bad\nimport numpy\n",
        "low/bad.py": (
            "from typing import TYPE_CHECKING\n"
            "if TYPE_CHECKING:\n"
            "    from diffloc.high.thing import Thing\n"
            "def f():\n"
            "    import diffloc.high\n"
            "    from ..high import thing\n"
            "    from tests.conftest import TINY\n"
        ),
        "high/__init__.py": "",
        "high/thing.py": "from diffloc.low import ok\n",
        "stray.py": "",
    }
    for name, text in files.items():
        path = tmp_path / "diffloc" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return tmp_path / "diffloc"


def test_checker_finds_every_form_of_upward_import(fake_package: Path) -> None:
    layers = (("diffloc",), ("diffloc.low",), ("diffloc.high",))
    violations = _violations(fake_package, layers)
    assert violations == [
        "diffloc/low/bad.py:3: diffloc.low.bad (layer 1, diffloc.low) imports "
        "diffloc.high.thing (layer 2, diffloc.high)",
        "diffloc/low/bad.py:5: diffloc.low.bad (layer 1, diffloc.low) imports "
        "diffloc.high (layer 2, diffloc.high)",
        "diffloc/low/bad.py:6: diffloc.low.bad (layer 1, diffloc.low) imports "
        "diffloc.high.thing (layer 2, diffloc.high)",
        "diffloc/low/bad.py:7: diffloc.low.bad imports tests.conftest (outside)",
        "diffloc/stray.py: module diffloc.stray is in no layer of LAYERS",
    ]


def test_units_of_one_layer_may_not_import_each_other(fake_package: Path) -> None:
    violations = _violations(
        fake_package, (("diffloc", "diffloc.stray"), ("diffloc.low", "diffloc.high"))
    )
    assert any("diffloc/high/thing.py:1" in v and "imports diffloc.low.ok" in v for v in violations)


def test_documented_layers_parse_the_numbered_table() -> None:
    text = "# Layers\n\n## Order\n\n```\n0  a  b\n1  c\n```\n"
    assert _documented_layers(text) == (("a", "b"), ("c",))
    with pytest.raises(ValueError, match="numbered"):
        _documented_layers("## Order\n```\n1  a\n```\n")
