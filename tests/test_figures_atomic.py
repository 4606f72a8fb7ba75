"""`make_figures` is all or nothing (issue 41): the notebooks write into a copy of the figures
folder, swapped in only when every notebook succeeded; a failure leaves the folder as it was."""

import os
from pathlib import Path

import pytest

from pemamoe.commands import make_figures
from pemamoe.core import REPO_ROOT, current_umask

pytestmark = pytest.mark.notebook

PARAMETERS = '''# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"

'''
WRITES = PARAMETERS + '''# %%
import pandas as pd
from pemamoe.core import write_table

write_table(pd.DataFrame({"scale": [scale]}), "atomic_table", figures_dir)
'''
FAILS = PARAMETERS + '''# %%
raise RuntimeError("this notebook fails")
'''


def _notebooks(tmp_path: Path, *sources) -> list:
    folder = tmp_path / "notebooks"
    folder.mkdir(exist_ok=True)
    paths = []
    for name, text in sources:
        (folder / name).write_text(text)
        paths.append(folder / name)
    return paths


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(folder.rglob("*"))
            if p.is_file()}


def _figures(tmp_path: Path) -> Path:
    """A figures folder as an earlier `make figures` left it: a README, a table a notebook rewrites, a
    file no notebook writes."""
    figs = tmp_path / "figs"
    figs.mkdir()
    (figs / "README.md").write_text("# paper_figures\n\n| file | paper counterpart | notebook | scale | command | "
                                    "commit |\n|---|---|---|---|---|---|\n| kept.txt | x | notebooks/old.py | small "
                                    "| `make figures SCALE=small` | abc1234 |\n")
    (figs / "atomic_table.csv").write_text("scale\nsmall\n")
    (figs / "kept.txt").write_text("from an earlier run\n")
    return figs


def _beside(tmp_path: Path) -> list:
    return sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("figs"))


def test_a_failing_notebook_leaves_the_figures_folder_byte_for_byte_as_it_was(tmp_path):
    figs = _figures(tmp_path)
    before = _snapshot(figs)
    notebooks = _notebooks(tmp_path, ("98_atomic_writes.py", WRITES), ("98_atomic_fails.py", FAILS))
    with pytest.raises(Exception, match="this notebook fails"):
        make_figures(scale="ci", figures_dir=figs, notebooks=notebooks, precompute=False, stream=False)
    assert _snapshot(figs) == before  # the first notebook's rewritten table never reached it
    assert _beside(tmp_path) == ["figs"]  # no staging folder left


def test_when_every_notebook_succeeds_the_new_files_replace_the_folder(tmp_path):
    figs = _figures(tmp_path)
    notebooks = _notebooks(tmp_path, ("98_atomic_writes.py", WRITES))
    readme = make_figures(scale="ci", figures_dir=figs, notebooks=notebooks, precompute=False, stream=False)
    assert readme == figs / "README.md"
    assert (figs / "atomic_table.csv").read_text() == "scale\nci\n" and (figs / "atomic_table.md").is_file()
    assert (figs / "kept.txt").read_text() == "from an earlier run\n"  # a file no notebook wrote is kept
    text = readme.read_text()
    assert "| atomic_table.csv |" in text and "notebooks/98_atomic_writes.py | ci |" in text
    assert "| kept.txt | x | notebooks/old.py | small |" in text  # the provenance merge saw the old README
    assert _beside(tmp_path) == ["figs"]


def test_each_scale_keeps_its_own_executed_notebooks(tmp_path):
    """A paper-scale `make figures` must not overwrite the executed copies of the medium one."""
    executed = REPO_ROOT / "build" / "executed"
    for path in (executed / "98_atomic_writes.ipynb", executed / "ci" / "98_atomic_writes.ipynb"):
        path.unlink(missing_ok=True)
    make_figures(scale="ci", figures_dir=_figures(tmp_path), notebooks=_notebooks(tmp_path, ("98_atomic_writes.py", WRITES)),
                 precompute=False, stream=False)
    assert (executed / "ci" / "98_atomic_writes.ipynb").is_file()
    assert not (executed / "98_atomic_writes.ipynb").exists()


def test_a_new_figures_folder_gets_the_mode_mkdir_gives(tmp_path):
    figs = tmp_path / "figs"
    make_figures(scale="ci", figures_dir=figs, notebooks=_notebooks(tmp_path, ("98_atomic_writes.py", WRITES)),
                 precompute=False, stream=False)
    assert (figs / "atomic_table.csv").read_text() == "scale\nci\n"
    assert os.stat(figs).st_mode & 0o777 == 0o777 & ~current_umask()
    assert _beside(tmp_path) == ["figs"]


def test_provenance_names_the_inputs_by_content_not_by_commit(tmp_path):
    """paper_figures/README.md names the figures' inputs by digests of their content
    (`figure_inputs`): a fresh clone gives the same digests whatever commit it is at, so
    regenerating the figures there rewrites nothing. Prose, comments, docstrings, the figures
    themselves and a campaign's portable states change no digest; a notebook's code changes its own
    digest only, and a record the records' digest."""
    import shutil
    import subprocess

    from pemamoe.commands import figure_inputs

    repo = Path(__file__).resolve().parents[1]
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "--quiet", "--depth", "1", f"file://{repo}", str(clone)], check=True)
    for folder in ("pemamoe", "notebooks"):  # the code under test, as in the working tree
        shutil.copytree(repo / folder, clone / folder, dirs_exist_ok=True, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.rmtree(clone / "records")
    shutil.copytree(repo / "records", clone / "records", ignore=shutil.ignore_patterns("ci", "in_progress"))
    before = figure_inputs(clone)
    assert before == figure_inputs(repo)  # content only: the checkout's path and commit do not count
    assert set(before) == {"package", "records", *(nb.name for nb in (repo / "notebooks").glob("*.py"))}

    (clone / "paper_figures" / "README.md").write_text("regenerated\n")
    state = clone / "records" / "paper" / "in_progress"
    state.mkdir(parents=True, exist_ok=True)
    (state / "run.pt.zst").write_bytes(b"state")  # no figure reads a portable state
    nb = clone / "notebooks" / "01_channel.py"
    nb.write_text(nb.read_text() + "\n# %% [markdown]\n# More prose.\n\n# %%\n# a comment only\n")
    module = clone / "pemamoe" / "channel.py"
    module.write_text(module.read_text().replace("# %% notebooks/01_channel.py, cell", "# %% notebooks/01_channel.py,  cell"))
    (clone / "pemamoe" / "__main__.py").write_text("print('the command line computes no figure')\n")
    assert figure_inputs(clone) == before

    nb.write_text(nb.read_text() + "\nx = 1\n")
    changed = figure_inputs(clone)
    assert {k for k in before if changed[k] != before[k]} == {"01_channel.py"}
    module.write_text(module.read_text() + "\nY = 2\n")
    assert figure_inputs(clone)["package"] != before["package"]
    marker = next((clone / "records" / "paper").glob("*.timing.json"))
    marker.write_text(marker.read_text() + " ")
    assert figure_inputs(clone)["records"] != before["records"]


def test_code_digest_ignores_layout_comments_and_docstrings():
    from pemamoe.commands import code_digest

    a = 'def f(x):\n    """Doc."""\n    return x + 1  # one more\n'
    b = "def f(x):\n\n    return (x +\n            1)\n"
    assert code_digest(a) == code_digest(b) != code_digest("def f(x):\n    return x + 2\n")
    assert code_digest("%matplotlib inline") == code_digest("%matplotlib inline") != code_digest("%pwd")


def test_the_paper_scale_draws_its_campaign_into_its_own_folder():
    """`make figures SCALE=paper` trains the campaign (the main comparison and, at the paper scale,
    MLP + ReDo and MLP + shrink-and-perturb) and runs only notebooks 09, 10 and 10b, into
    paper_figures/paper_scale/; every other scale keeps paper_figures/ and every notebook."""
    from pemamoe.commands import PAPER_SCALE_NOTEBOOKS, figures_plan
    from pemamoe.core import REPO_ROOT, figure_notebooks
    from pemamoe.experiments import experiment_specs

    folder, notebooks, experiments = figures_plan("paper")
    assert folder == REPO_ROOT / "paper_figures" / "paper_scale"
    assert [nb.name for nb in notebooks] == list(PAPER_SCALE_NOTEBOOKS) == ["09_experiments.py", "10_ablations.py",
                                                                          "10b_readings.py"]
    assert experiments == ("campaign", "budget")
    campaign = experiment_specs("campaign", "paper")
    assert sorted({s.method for s in campaign}) == ["mlp", "mlp_redo", "mlp_snp", "moe", "pemamoe", "smoe"]
    assert len(campaign) == 18 and {s.scale for s in campaign} == {"paper"} and {s.tag for s in campaign} == {"main"}
    # the campaign's specs are the main comparison's plus the baselines: the same runs, not new ones
    assert set(experiment_specs("main", "paper")) < set(campaign)
    assert {s.method for s in experiment_specs("campaign", "medium")} == {"mlp", "moe", "smoe", "pemamoe"}
    folder, notebooks, experiments = figures_plan("medium")
    assert folder == REPO_ROOT / "paper_figures" and notebooks == figure_notebooks()
    assert experiments == ("all", "budget", "gating", "sparse")
    folder, notebooks, experiments = figures_plan("paper", notebooks=["x.py"])
    assert [nb.name for nb in notebooks] == ["x.py"] and experiments is None


def test_a_nested_folder_left_by_a_killed_run_is_not_copied_into_the_new_figures(tmp_path):
    """A killed `make figures SCALE=paper` leaves paper_figures/paper_scale.partial-*: the next run of
    the enclosing folder must not publish it."""
    figs = _figures(tmp_path)
    for leftover in ("paper_scale.partial-x1", "paper_scale.old-x2"):
        (figs / leftover).mkdir()
        (figs / leftover / "half_written.csv").write_text("a\n")
    (figs / "paper_scale").mkdir()
    (figs / "paper_scale" / "kept.csv").write_text("b\n")
    make_figures(scale="ci", figures_dir=figs, notebooks=_notebooks(tmp_path, ("98_atomic_writes.py", WRITES)),
                 precompute=False, stream=False)
    assert sorted(p.name for p in figs.iterdir() if p.is_dir()) == ["paper_scale"]
    assert (figs / "paper_scale" / "kept.csv").read_text() == "b\n"
