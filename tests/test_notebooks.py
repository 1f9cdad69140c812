"""Every notebook in ``notebooks/`` runs top to bottom (code cells executed in order), and is
committed with its outputs: a code cell that draws a figure holds an embedded PNG, one that
prints holds its text, so a reader sees them without running anything
(``python3 notebooks/execute.py`` stores them).
"""

import re
import time
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import nbformat
import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
DRAWS = re.compile(r"\bplt\.(show|figure|subplots|imshow|plot|scatter|hist|bar)\b")


def test_there_are_notebooks():
    assert NOTEBOOKS, "notebooks/ holds no notebook"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    matplotlib.use("Agg")
    monkeypatch.chdir(tmp_path)
    notebook = nbformat.read(path, as_version=4)
    namespace: dict = {}
    start = time.perf_counter()
    try:
        for cell in notebook.cells:
            if cell.cell_type == "code":
                exec(compile(cell.source, f"{path.name}:cell", "exec"), namespace)
    finally:
        plt.close("all")
    print(f"{path.name}: {time.perf_counter() - start:.1f} s")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_is_committed_with_its_outputs(path: Path):
    notebook = nbformat.read(path, as_version=4)
    nbformat.validate(notebook)
    code = [cell for cell in notebook.cells if cell.cell_type == "code"]
    assert code, f"{path.name} has no code cell"
    for number, cell in enumerate(code, start=1):
        outputs = cell.get("outputs", [])
        assert not any(o.output_type == "error" for o in outputs), (
            f"{path.name} code cell {number} was committed with an error"
        )
        images = [o for o in outputs if "image/png" in o.get("data", {})]
        if DRAWS.search(cell.source):
            assert images, f"{path.name} code cell {number} draws a figure but holds no PNG"
        if "print(" in cell.source:
            assert any(o.output_type == "stream" for o in outputs), (
                f"{path.name} code cell {number} prints but holds no output"
            )
