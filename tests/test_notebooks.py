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


@pytest.mark.notebook
def test_ablations_notebook_with_its_ablations_off_draws_the_campaigns_claims_only(tmp_path):
    """What `make figures SCALE=paper` asks of notebook 10 (`ablations` off, the paper-scale
    campaign's reading), exercised at the ci scale: the claims of the main comparison and the
    controller-alone table, no ablation figure or table, and no ablation run trained."""
    import pandas as pd

    notebook = next(nb for nb in NOTEBOOKS if nb.name == "10_ablations.py")
    figures, results = tmp_path / "figures", tmp_path / "results"
    run_notebook(notebook, {"scale": "ci", "figures_dir": str(figures), "results_dir": str(results),
                            "records_dir": str(tmp_path / "records"), "ablations": False},
                 output_dir=tmp_path / "executed", timeout=600)
    written = {p.stem for p in figures.iterdir()}
    assert {"headline_claims", "headline_controller_alone", "headline_reference_iqm"} <= written
    assert not {"ablation_tricks", "ablation_noise_sweep", "ablation_noise_sensitivity"} & written
    assert len(pd.read_csv(figures / "headline_claims.csv")) == 3  # return, served users, collisions
    import json

    cycling = [p for p in (results / "ci").glob("pemamoe-*")  # the budget study's runs hold one phase
               if json.loads((p / "config.json").read_text())["fixed_phase"] is None]
    assert len(cycling) == 1  # the main comparison's PE-MAMoE: no noise or tricks variant trained
