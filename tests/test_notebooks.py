"""Every notebook executes headlessly through papermill at the ci scale, as `make figures` would."""

from pathlib import Path

import pytest

from pemamoe.core import figure_notebooks, notebook_parameters, run_notebook

NOTEBOOKS = figure_notebooks()


def test_notebooks_exist():
    assert NOTEBOOKS, "no notebooks/NN_*.py found"


@pytest.mark.notebook
@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_at_ci_scale(notebook: Path, tmp_path):
    figures = tmp_path / "figures"
    params = {"scale": "ci", "figures_dir": str(figures)}
    if "results_dir" in notebook_parameters(notebook):  # experiments train into a throwaway cache
        params["results_dir"] = str(tmp_path / "results")
    if "records_dir" in notebook_parameters(notebook):  # ... and write their records beside it
        params["records_dir"] = str(tmp_path / "records")
    nb = run_notebook(
        notebook,
        params,
        output_dir=tmp_path / "executed",
        timeout=600,
    )
    errors = [o for c in nb.cells for o in c.get("outputs", []) if o.get("output_type") == "error"]
    assert not errors
