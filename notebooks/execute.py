"""Execute notebooks and store their outputs in place (figures as embedded PNG).

    python3 notebooks/execute.py                      # every notebook in notebooks/
    python3 notebooks/execute.py notebooks/x.ipynb    # some of them

Each notebook runs in a fresh Jupyter kernel (``nbclient``, ``ipykernel``: the ``test``
extra) inside a new temporary folder, so whatever it writes (e.g. ``data/``) is thrown
away; the kernel imports ``diffloc`` from this checkout. The notebooks are committed with
the outputs this writes, so a reader sees the figures without running anything;
``tests/test_notebooks.py`` runs them again and checks that the outputs are there.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import nbformat
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[1]


def execute(path: Path, timeout_s: int = 600) -> float:
    """Run every cell of the notebook at ``path`` and write it back with its outputs.

    Returns:
        The wall time in seconds.
    """
    notebook = nbformat.read(path, as_version=4)
    os.environ["PYTHONPATH"] = os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]
    )
    os.environ.setdefault("CI", "true")  # quiet progress bars
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="diffloc-notebook-") as folder:
        client = NotebookClient(
            notebook,
            timeout=timeout_s,
            kernel_name="python3",
            resources={"metadata": {"path": folder}},
        )
        client.execute()
    elapsed = time.perf_counter() - start
    nbformat.write(notebook, path)
    return elapsed


def main(argv: list[str]) -> None:
    paths = [Path(a) for a in argv] or sorted((ROOT / "notebooks").glob("*.ipynb"))
    for path in paths:
        print(f"{path}: {execute(path):.1f} s", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
