"""The notebooks run top to bottom (at the small size CI asks for with
PRKMK_NOTEBOOK_SMALL=1, their code cells in this process, from the notebook
folder) and are committed with the outputs of a full run."""

from pathlib import Path

import nbformat
import pytest

from helpers import run_as_script

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
EXPECTED = [
    "01_paper_section5",
    "02_fit_inertia",
    "03_batch_tumbling",
    "04_where_methods_fail",
    "05_choosing_a_method",
    "06_fit_control_torque",
    "07_fit_over_a_long_horizon",
    "08_fit_a_satellite",
]


def test_the_notebooks_are_there():
    assert [p.stem for p in NOTEBOOKS] == EXPECTED


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_committed_with_outputs_question_and_answer(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    first, code = nb.cells[0], [c for c in nb.cells if c.cell_type == "code"]
    assert first.cell_type == "markdown" and "**Question.**" in first.source
    assert any(c.cell_type == "markdown" and c.source.startswith("## Answer") for c in nb.cells)
    # Every code cell ran, in order, without an error; the last one prints the answer.
    assert [c.execution_count for c in code] == list(range(1, len(code) + 1))
    assert not [o for c in code for o in c.outputs if o.output_type == "error"]
    assert any(o.output_type == "stream" and o.text.strip() for o in code[-1].outputs)
    assert any("image/png" in o.get("data", {}) for c in code for o in c.outputs)


@pytest.mark.end_to_end
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, monkeypatch):
    monkeypatch.setenv("PRKMK_NOTEBOOK_SMALL", "1")
    monkeypatch.chdir(NOTEBOOK_DIR)
    nb = nbformat.read(path, as_version=4)
    cells = [c.source for c in nb.cells if c.cell_type == "code"]
    assert not [c for c in cells if c.lstrip().startswith(("%", "!"))], "a notebook's cells are plain Python"
    # `display` is the one name a notebook has that a script lacks.
    run_as_script("from IPython.display import display\n" + "\n\n".join(cells), str(path))
