"""The notebooks in examples/notebooks/ execute top to bottom (their cells assert their claims),
and each is its jupytext source (``NAME.py``, percent format) converted, cell for cell. The tour
runs in a Jupyter kernel; the others run their source's cells in the test process (no kernel
start-up, and compiled solvers shared with the test modules).

They switch float64 on themselves, so they run in the float64 pass only, each in its own kernel."""

from __future__ import annotations

import pathlib

import pytest

from helpers import X64, execute_notebook, run_notebook_in_process

ROOT = pathlib.Path(__file__).parent.parent
NOTEBOOKS = sorted((ROOT / "examples" / "notebooks").glob("*.ipynb"))
# Executed by the test module whose fixtures compile the same solvers, which the notebook then
# reuses: test_optimal_control.py.
ELSEWHERE = {"wheel_slew.ipynb"}
pytestmark = pytest.mark.skipif(not X64, reason="notebooks run in float64 by design; once per make test")


def test_there_are_notebooks():
    assert {p.name for p in NOTEBOOKS} >= {"tour.ipynb", "slew.ipynb"} | ELSEWHERE


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_is_its_jupytext_source(path):
    """Edit the ``.py``; ``jupytext --to ipynb examples/notebooks/NAME.py`` writes the notebook."""
    nbformat = pytest.importorskip("nbformat")
    jupytext = pytest.importorskip("jupytext")
    source = jupytext.read(path.with_suffix(".py"))
    notebook = nbformat.read(path, as_version=4)
    assert [(c.cell_type, c.source) for c in notebook.cells] == [(c.cell_type, c.source) for c in source.cells]
    assert all(not c.get("outputs") for c in notebook.cells if c.cell_type == "code")  # committed without outputs


def test_a_notebook_executes_in_a_jupyter_kernel():
    """The tour, through nbclient and an IPython kernel as a user runs it (the others run their
    cells in the test process: below)."""
    pytest.importorskip("nbclient")
    execute_notebook(ROOT / "examples" / "notebooks" / "tour.ipynb")


@pytest.mark.parametrize(
    "path", [p for p in NOTEBOOKS if p.name not in ELSEWHERE | {"tour.ipynb"}], ids=lambda p: p.name
)
def test_notebook_cells_run(path):
    """Each notebook's cells, top to bottom, in this process (they assert their claims)."""
    run_notebook_in_process(path)
