"""The package must be exactly what the notebooks export: a hand edit or a stale export fails."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pemamoe import literate

ROOT = Path(__file__).resolve().parent.parent


def test_package_matches_notebooks():
    problems = literate.check_all(ROOT)
    assert problems == [], "\n\n".join(problems)


@pytest.fixture
def repo_copy(tmp_path):
    """A throwaway copy of notebooks/ and pemamoe/ to break on purpose."""
    for folder in ("notebooks", "pemamoe"):
        shutil.copytree(ROOT / folder, tmp_path / folder, ignore=shutil.ignore_patterns("__pycache__"))
    return tmp_path


def generated_modules(root):
    return [p for p in sorted((root / "pemamoe").glob("*.py")) if p.read_text().startswith(literate.HEADER_MARKER)]


def test_every_generated_module_detects_a_hand_edit(repo_copy):
    modules = generated_modules(repo_copy)
    assert modules, "no generated module found"
    for module in modules:
        original = module.read_text()
        module.write_text(original.replace("\n", "\n# a hand edit\n", 3))
        problems = literate.check_all(repo_copy)
        assert any(module.name in p and "differs" in p for p in problems), module.name
        module.write_text(original)
    assert literate.check_all(repo_copy) == []


def test_check_cli_fails_on_drift(repo_copy):
    module = generated_modules(repo_copy)[0]
    module.write_text(module.read_text() + "\nx = 1\n")
    run = subprocess.run(
        [sys.executable, "-m", "pemamoe.literate", "check", "--root", str(repo_copy)],
        capture_output=True, text=True,
    )
    assert run.returncode == 1
    assert module.name in run.stderr


def test_missing_and_orphan_modules_are_reported(repo_copy):
    module = generated_modules(repo_copy)[0]
    module.unlink()
    orphan = repo_copy / "pemamoe" / "stale.py"
    orphan.write_text(literate.HEADER_MARKER + "notebooks/gone.py. DO NOT EDIT.\n")
    problems = "\n".join(literate.check_all(repo_copy))
    assert f"pemamoe/{module.name} is missing" in problems
    assert "pemamoe/stale.py is generated but no notebook exports it" in problems
    literate.export_all(repo_copy)
    assert literate.check_all(repo_copy) == []
    assert not orphan.exists()


NOTEBOOK = '''# %% [markdown]
# # Title

# %%
#| default_exp demo

# %%
#| export
from __future__ import annotations
import math

def area(r: float) -> float:
    return math.pi * r**2

RADIUS = 2.0
_hidden = 1

# %%
#| exporti
def _helper():
    return 1

# %%
#| export other
def elsewhere():
    return 2

# %%
print(area(RADIUS))
'''


def test_render_hoists_future_imports_and_computes_all():
    cells = literate.parse_cells(NOTEBOOK, "notebooks/99_demo.py")
    groups = literate.cells_by_module(cells, "notebooks/99_demo.py")
    assert set(groups) == {"demo", "other"}
    text = literate.render_module("notebooks/99_demo.py", groups["demo"])
    lines = text.splitlines()
    assert lines[0].startswith(literate.HEADER_MARKER + "notebooks/99_demo.py")
    assert lines[2] == "from __future__ import annotations"
    assert "__all__ = ['area', 'RADIUS']" in text
    assert "# %% notebooks/99_demo.py, cell 3 (line 7)" in text
    assert "print(area" not in text and "def _helper" in text
    namespace = {}
    exec(compile(text, "demo", "exec"), namespace)
    assert namespace["area"](1.0) == pytest.approx(3.14159, rel=1e-5)


@pytest.mark.parametrize(
    "source, message",
    [
        ("# %%\n#| exprt\nx = 1\n", "unknown directive '#| exprt'"),
        ("# %%\n#| export\nx = 1\n", "no '#| default_exp"),
        ("# %%\n#| default_exp a\n\n# %%\n#| default_exp b\n", "appears 2 times"),
        ("# %%\n#| default_exp Bad-Name\n", "lower-case Python identifier"),
    ],
)
def test_bad_notebooks_get_clear_errors(source, message):
    with pytest.raises(literate.ExportError, match=message.replace("|", r"\|").replace("(", r"\(")):
        cells = literate.parse_cells(source, "nb.py")
        literate.cells_by_module(cells, "nb.py")


REEXPORT_NOTEBOOK = '''# %%
#| default_exp demo

# %%
#| export
import math  # re-exported? no: prose mentioning re-exported names is not the marker
from pathlib import Path
from os.path import (  # re-export: joined paths, with a private alias that stays private
    join, basename as base_name, dirname as _dirname)
from math import pi as PI  # re-export

def area(r):
    return PI * r**2
'''


def test_marked_imports_are_reexported_and_others_are_not():
    cells = literate.parse_cells(REEXPORT_NOTEBOOK, "notebooks/99_demo.py")
    groups = literate.cells_by_module(cells, "notebooks/99_demo.py")
    text = literate.render_module("notebooks/99_demo.py", groups["demo"])
    assert "__all__ = ['join', 'base_name', 'PI', 'area']" in text
    namespace = {}
    exec(compile(text, "demo", "exec"), namespace)
    assert namespace["_dirname"]("a/b") == "a"  # imported, just not exported


@pytest.mark.parametrize(
    "body, message",
    [
        ("from os.path import (\n    join,  # re-export\n    basename)\n", "first line of a top-level"),
        ("import os.path  # re-export\n", "statements only"),
        ("from os.path import *  # re-export\n", "statements only"),
        ("if True:\n    from os.path import join  # re-export\n", "first line of a top-level"),
        ("x = 1  # re-export\n", "first line of a top-level"),
    ],
)
def test_misplaced_reexport_marker_is_an_error(body, message):
    source = "# %%\n#| default_exp demo\n\n# %%\n#| export\n" + body
    cells = literate.parse_cells(source, "nb.py")
    with pytest.raises(literate.ExportError, match=message):
        literate.render_module("nb.py", literate.cells_by_module(cells, "nb.py")["demo"])


def test_reexport_marker_in_exporti_cell_is_an_error():
    source = "# %%\n#| default_exp demo\n\n# %%\n#| exporti\nfrom os.path import join  # re-export\n"
    cells = literate.parse_cells(source, "nb.py")
    with pytest.raises(literate.ExportError, match="exporti"):
        literate.render_module("nb.py", literate.cells_by_module(cells, "nb.py")["demo"])


def test_star_imports_bring_the_appendix_names_the_main_modules_reexport():
    from pemamoe import execution, train_config

    mappo_ns, sweep_ns = {}, {}
    exec("from pemamoe.mappo import *", mappo_ns)
    exec("from pemamoe.sweep import *", sweep_ns)
    assert mappo_ns["TrainConfig"] is train_config.TrainConfig
    assert {"EpisodeTracker", "resolve_device", "train_population"} <= mappo_ns.keys()
    assert sweep_ns["run_sweep"] is execution.run_sweep
    assert {"RunSpec", "SweepInterrupted", "execute_population", "run_sweep", "sweep_records"} <= sweep_ns.keys()
    # private helpers of the marked imports and incidental imports stay out of __all__
    for ns in (mappo_ns, sweep_ns):
        assert not {"_plain", "_progress", "np", "Path", "SCALES", "METHOD_REGISTRY"} & ns.keys()


def test_the_index_maps_every_notebook_and_the_modules_it_exports():
    """00_index's map from the paper to the code names every other notebook and, for each, every
    module that notebook exports (a reader looking for a module finds its notebook there)."""
    from pemamoe.core import figure_notebooks

    index = (ROOT / "notebooks" / "00_index.py").read_text(encoding="utf-8")
    rows = {}
    for line in index.splitlines():
        columns = [c.strip() for c in line[1:].strip().strip("|").split("|")] if line.startswith("# |") else []
        if len(columns) == 4 and columns[1].strip("`").endswith(".py"):  # paper | notebook | module(s) | regenerates
            rows[columns[1].strip("`")] = columns[2]
    for nb in figure_notebooks(ROOT):
        if nb.name == "00_index.py":
            continue
        assert nb.name in rows, f"notebooks/00_index.py's map has no row for {nb.name}"
        rel = nb.relative_to(ROOT).as_posix()
        modules = literate.cells_by_module(literate.parse_cells(nb.read_text(encoding="utf-8"), rel), rel)
        for module in modules:
            assert f"pemamoe/{module}.py" in rows[nb.name], f"00_index's row for {nb.name} does not name pemamoe/{module}.py"
