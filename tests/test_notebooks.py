"""Every notebook in notebooks/ runs top to bottom at the `tiny` budget without a cell error.

Each notebook is executed in memory (the committed .ipynb files are never written) by a fresh
kernel whose working directory is notebooks/ (Jupyter's default) and whose environment has
CDRL_NOTEBOOK_BUDGET=tiny; the notebooks then write only under notebooks/runs/tiny/.
The kernel inherits the test session's XLA compilation cache (tests/conftest.py), so a
program that another test or notebook compiled is not compiled again.
"""
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"
PATHS = sorted(NOTEBOOKS.glob("*.ipynb"))
# Seconds a single cell may run at the tiny budget (most of it is XLA compilation).
CELL_TIMEOUT = 600


def test_there_are_notebooks():
    assert [p.name for p in PATHS][:3] == ["01_quickstart.ipynb", "02_variants.ipynb", "03_controller.ipynb"]


@pytest.mark.parametrize("path", PATHS, ids=[p.stem for p in PATHS])
def test_notebook_runs_at_tiny_budget(path, monkeypatch):
    monkeypatch.setenv("CDRL_NOTEBOOK_BUDGET", "tiny")  # the kernel inherits this process's environment
    before = path.read_bytes()
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=CELL_TIMEOUT, kernel_name="python3",
                                     resources={"metadata": {"path": str(NOTEBOOKS)}})
    client.execute()  # raises CellExecutionError, naming the cell, on the first error
    assert path.read_bytes() == before
    errors = [out for cell in nb.cells if cell.cell_type == "code" for out in cell.get("outputs", [])
              if out.get("output_type") == "error"]
    assert not errors
