"""What `pip install -e .` gives: pyproject.toml declares every third-party module the package imports.

A clean `pip install -e .` once gave a package that could not build the default environment (no
numba), whose `train` then failed on tqdm and on pandas' missing pyarrow: the modules were imported
but never declared. This test reads the imports of pemamoe/*.py with `ast` (nothing is imported)
and the dependencies from pyproject.toml, so it costs milliseconds.
"""

import ast
import importlib.metadata
import re
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())

# Import names whose distribution is named differently, for modules not installed here (installed
# ones are looked up in importlib.metadata.packages_distributions()).
DISTRIBUTION_OF = {"zmq": "pyzmq", "yaml": "PyYAML", "PIL": "pillow", "sklearn": "scikit-learn"}
# Modules that only an optional feature imports (inside the function that needs them), and the
# extra of pyproject.toml that installs them. Every other third-party import is a core dependency.
OPTIONAL = {"jupytext": "figures", "papermill": "figures", "traitlets": "figures", "zmq": "figures",
            "jupyter_client": "figures",
            "rliable": "figures", "ray": "ray", "psutil": "ray", "fsspec": "store"}


def _name(requirement: str) -> str:
    """The normalised distribution name of a requirement string ("pandas<3" -> "pandas")."""
    return re.sub(r"[-_.]+", "-", re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", requirement).group(1)).lower()


def _distribution(module: str) -> str:
    installed = importlib.metadata.packages_distributions().get(module)
    return _name(installed[0] if installed else DISTRIBUTION_OF.get(module, module))


def third_party_imports() -> dict:
    """{top-level module: {(file, 'import time' | 'in a function'), ...}} of every pemamoe/*.py."""
    found = {}
    for path in sorted((ROOT / "pemamoe").glob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        in_function = {id(node) for fn in ast.walk(tree) if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef))
                       for node in ast.walk(fn) if node is not fn}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                modules = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                modules = [node.module]
            else:
                continue
            for module in modules:
                top = module.split(".")[0]
                if top in sys.stdlib_module_names or top == "pemamoe":
                    continue
                when = "in a function" if id(node) in in_function else "import time"
                found.setdefault(top, set()).add((path.name, when))
    return found


def test_the_scan_sees_the_imports_that_a_clean_install_lacked():
    imports = third_party_imports()
    assert {"numba", "tqdm", "pyarrow", "torch", "numpy"} <= set(imports)
    assert ("env_kernel.py", "import time") in imports["numba"]
    assert ("runs.py", "in a function") in imports["pyarrow"]


def test_every_third_party_import_is_declared_in_pyproject():
    core = {_name(r) for r in PYPROJECT["project"]["dependencies"]}
    extras = {extra: {_name(r) for r in reqs} for extra, reqs in PYPROJECT["project"].get("optional-dependencies", {}).items()}
    problems = []
    for module, where in sorted(third_party_imports().items()):
        dist = _distribution(module)
        files = ", ".join(sorted(f"{f} ({w})" for f, w in where))
        extra = OPTIONAL.get(module)
        if extra is None and dist not in core:
            problems.append(f"{module} (distribution {dist}), imported by {files}, is not in [project] dependencies")
        if extra is not None:
            if dist not in extras.get(extra, set()):
                problems.append(f"{module} (distribution {dist}), imported by {files}, is not in the extra {extra!r}")
            if any(w == "import time" for _, w in where):
                problems.append(f"{module} is imported when a module loads ({files}): it must be a core dependency")
    assert not problems, "\n".join(problems)


def test_torch_stays_pinned_and_the_cli_names_the_extras_pyproject_declares():
    from pemamoe.__main__ import FIGURES_MODULES, RAY_MODULES

    assert "torch==2.13.0" in PYPROJECT["project"]["dependencies"]
    extras = PYPROJECT["project"]["optional-dependencies"]
    for modules, extra in ((FIGURES_MODULES, "figures"), (RAY_MODULES, "ray")):
        declared = {_name(r) for r in extras[extra]}
        assert {_distribution(m) for m in modules} <= declared, (extra, modules)


@pytest.mark.parametrize("module", ["numba", "tqdm", "pyarrow", "pandas", "scipy", "gymnasium", "pettingzoo"])
def test_what_train_needs_is_a_core_dependency(module):
    assert _distribution(module) in {_name(r) for r in PYPROJECT["project"]["dependencies"]}
