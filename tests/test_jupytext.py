"""Opening a notebook in JupyterLab and saving it unchanged must not change a byte of it.

JupyterLab reads and writes notebooks/*.py through Jupytext's contents manager, configured by
jupytext.toml at the repository root. Without that configuration every save added version lines
to the header, which shifted every `# %% notebooks/..., cell N (line L)` reference pemamoe/ then
carried and broke `make check-export` (the references now name exported cells, not lines: issue 61).
These tests drive the same contents manager on a copy of the repo.
"""

import asyncio
import json
import shutil
import subprocess
from pathlib import Path

import pytest

jupytext = pytest.importorskip("jupytext")

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.py"))

# The header every notebook is committed with, byte for byte (see CONTRIBUTING.md).
CANONICAL_HEADER = """\
# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
"""


@pytest.fixture
def lab_root(tmp_path):
    """A copy of what Lab's contents manager sees: notebooks/ and the root jupytext.toml."""
    shutil.copytree(ROOT / "notebooks", tmp_path / "notebooks", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "jupytext.toml", tmp_path / "jupytext.toml")
    return tmp_path


def sync_manager(root):
    return jupytext.TextFileContentsManager(root_dir=str(root))


class AsyncManager:
    """The async contents manager (the one jupyter_server 2 uses) behind a synchronous face."""

    def __init__(self, root):
        self._cm = jupytext.AsyncTextFileContentsManager(root_dir=str(root))

    def get(self, path, **kwargs):
        return asyncio.run(self._cm.get(path, **kwargs))

    def save(self, model, path):
        return asyncio.run(self._cm.save(model, path))


MANAGERS = {"sync": sync_manager, "async": AsyncManager}


def open_and_save(cm, rel, edit=None):
    model = cm.get(rel, content=True, type="notebook")
    if edit is not None:
        edit(model["content"])
    cm.save(dict(type="notebook", content=model["content"]), rel)


def test_every_notebook_has_the_canonical_header():
    assert NOTEBOOKS
    for nb in NOTEBOOKS:
        assert nb.read_text(encoding="utf-8").startswith(CANONICAL_HEADER), nb.name


@pytest.mark.parametrize("manager", sorted(MANAGERS))
def test_open_and_save_leaves_every_notebook_unchanged(lab_root, manager):
    cm = MANAGERS[manager](lab_root)
    for nb in sorted((lab_root / "notebooks").glob("*.py")):
        rel = nb.relative_to(lab_root).as_posix()
        before = nb.read_bytes()
        open_and_save(cm, rel)  # first save: creates the paired .ipynb
        assert nb.read_bytes() == before, f"{rel} changed on the first save"
        paired = lab_root / "build" / "notebooks" / f"{nb.stem}.ipynb"
        assert paired.is_file(), f"{rel} was not paired with build/notebooks/{paired.name}"
        open_and_save(cm, rel)  # second save: now reads through the pair
        assert nb.read_bytes() == before, f"{rel} changed when saved through its paired .ipynb"


def test_a_running_kernel_does_not_change_the_header(lab_root):
    """Lab rewrites the kernelspec from the running kernel and adds language_info; neither may
    reach the .py. The committed display name must be the installed python3 kernel's."""
    from jupyter_client.kernelspec import KernelSpecManager

    spec = KernelSpecManager().get_kernel_spec("python3")
    cm = sync_manager(lab_root)
    rel = "notebooks/01_channel.py"
    before = (lab_root / rel).read_bytes()

    def as_lab_does(nb):
        nb["metadata"]["kernelspec"] = {"display_name": spec.display_name, "language": spec.language, "name": "python3"}
        nb["metadata"]["language_info"] = {"name": "python", "version": "3.11.0", "file_extension": ".py"}

    open_and_save(cm, rel, as_lab_does)
    assert (lab_root / rel).read_bytes() == before


def test_outputs_survive_in_the_paired_notebook(lab_root):
    cm = sync_manager(lab_root)
    rel = "notebooks/01_channel.py"
    before = (lab_root / rel).read_bytes()
    output = {"output_type": "stream", "name": "stdout", "text": "kept\n"}

    def run_last_cell(nb):
        cell = [c for c in nb["cells"] if c["cell_type"] == "code"][-1]
        cell["outputs"], cell["execution_count"] = [output], 3

    open_and_save(cm, rel, run_last_cell)
    assert (lab_root / rel).read_bytes() == before, "outputs must never reach the .py"
    reopened = cm.get(rel, content=True, type="notebook")["content"]
    assert [c for c in reopened["cells"] if c["cell_type"] == "code"][-1]["outputs"] == [output]
    stored = json.loads((lab_root / "build" / "notebooks" / "01_channel.ipynb").read_text())
    assert any(c.get("outputs") for c in stored["cells"])


def test_paired_notebooks_are_not_tracked():
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    ignored = subprocess.run(["git", "check-ignore", "-q", "build/notebooks/01_channel.ipynb"], cwd=ROOT)
    assert ignored.returncode == 0, "build/ must be in .gitignore"


def test_a_real_lab_server_saves_every_notebook_back_unchanged(lab_root, tmp_path):
    """End to end: `jupyter lab` (headless, with the Jupytext server extension as installed) serves
    a copy of the notebooks; every notebook is fetched and PUT back through the REST API, twice
    (the second time through the paired .ipynb), as Lab's autosave does."""
    pytest.importorskip("jupyterlab")
    import os
    import socket
    import sys
    import time
    import urllib.request

    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()
    env = dict(os.environ, JUPYTER_CONFIG_DIR=str(tmp_path / "config"), JUPYTER_RUNTIME_DIR=str(tmp_path / "runtime"))
    cmd = [sys.executable, "-m", "jupyterlab", "--no-browser", "--ServerApp.token=x", "--ServerApp.ip=127.0.0.1",
           f"--ServerApp.port={port}", f"--ServerApp.root_dir={lab_root}"]
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        cmd.append("--allow-root")
    log = open(tmp_path / "lab.log", "w")
    server = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)

    def call(method, path, body=None):
        request = urllib.request.Request(
            f"http://127.0.0.1:{port}/api/contents/{path}", method=method,
            data=None if body is None else json.dumps(body).encode(),
            headers={"Authorization": "token x", "Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=60) as response:
            return json.loads(response.read())

    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                call("GET", "notebooks")
                break
            except OSError:
                if server.poll() is not None or time.monotonic() > deadline:
                    pytest.fail(f"jupyter lab did not start:\n{(tmp_path / 'lab.log').read_text()}")
                time.sleep(0.5)
        notebooks = sorted((lab_root / "notebooks").glob("*.py"))
        before = {nb: nb.read_bytes() for nb in notebooks}
        for _ in range(2):
            for nb in notebooks:
                rel = nb.relative_to(lab_root).as_posix()
                model = call("GET", f"{rel}?type=notebook&content=1")
                assert model["type"] == "notebook", rel
                call("PUT", rel, {"type": "notebook", "format": "json", "content": model["content"]})
        changed = [nb.name for nb in notebooks if nb.read_bytes() != before[nb]]
        assert changed == [], f"saved through jupyter lab, these notebooks changed: {changed}"
        assert len(list((lab_root / "build" / "notebooks").glob("*.ipynb"))) == len(notebooks)
    finally:
        server.terminate()
        server.wait(timeout=30)
        log.close()
