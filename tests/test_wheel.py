"""The package as a user installs it: the wheel, built from this checkout, installed with only its
declared dependencies (no lock) into a fresh virtual environment, trains a ci run there. Pip uses
its cache and the configured package index, as a user's pip would."""

import hashlib
import os
import shutil
import subprocess
import sys
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# the installed copy as a user runs it: a PYTHONPATH naming a checkout (as when the suite runs with
# one) would make `python -m pemamoe` import that checkout instead
USER_ENV = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}


def _run(cmd, cwd, timeout):
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=USER_ENV)
    assert proc.returncode == 0, f"{' '.join(map(str, cmd))} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


def test_the_wheel_installs_with_its_declared_dependencies_and_trains(tmp_path):
    source = tmp_path / "source"  # a copy: building in the checkout would leave build/ and egg-info there
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    shutil.copytree(ROOT / "pemamoe", source / "pemamoe", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", tmp_path / "dist", source], tmp_path, 600)
    wheel = next((tmp_path / "dist").glob("pemamoe-*.whl"))

    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    python = env_dir / "bin" / "python"
    _run([python, "-m", "pip", "install", "--quiet", wheel], tmp_path, 900)
    shown = _run([python, "-m", "pip", "show", "pemamoe"], tmp_path, 120).stdout
    assert "Location: " + str(env_dir) in shown  # the installed wheel, not this checkout

    run = tmp_path / "run"
    _run([python, "-m", "pemamoe", "train", "--scale", "ci", "--out", run], tmp_path, 600)
    assert (run / "done.json").exists() and (run / "metrics.parquet").exists()

    # export and check-export belong to a checkout: on the install they refuse in one line and
    # leave every installed module as it was (an export there once deleted them all as "orphans")
    package = Path(_run([python, "-c", "import pemamoe, os; print(os.path.dirname(pemamoe.__file__))"],
                        tmp_path, 120).stdout.strip())
    before = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in package.glob("*.py")}
    for command in ("export", "check-export"):
        proc = subprocess.run([str(python), "-m", "pemamoe", command], cwd=tmp_path, capture_output=True, text=True, env=USER_ENV,
                              timeout=300)
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        assert proc.returncode != 0 and len(lines) == 1 and "checkout" in lines[0], (command, proc.stdout, proc.stderr)
        assert "wrote" not in proc.stdout
    assert {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in package.glob("*.py")} == before
