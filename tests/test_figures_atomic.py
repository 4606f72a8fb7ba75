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


# --- issue 59: nothing the user made is removed or replaced; stale staging is cleaned -------------
def test_a_file_as_figures_dir_is_refused_and_left_as_it_is(tmp_path):
    """Issue 59 (major): a regular file named as the figures folder was moved aside and deleted."""
    from pemamoe.commands import FiguresDirError

    target = tmp_path / "figs"
    target.write_text("the user's own file\n")
    with pytest.raises(FiguresDirError, match=r"figures folder .*figs is a file, not a folder; it is left as it is"):
        make_figures(scale="ci", figures_dir=target, notebooks=_notebooks(tmp_path, ("98_atomic_writes.py", WRITES)),
                     precompute=False, stream=False)
    assert target.read_text() == "the user's own file\n"
    assert _beside(tmp_path) == ["figs"]


def test_figures_cli_refuses_a_file_as_figures_dir_in_one_line_and_keeps_it(tmp_path):
    import subprocess
    import sys

    target = tmp_path / "figs"
    target.write_text("keep me\n")
    proc = subprocess.run([sys.executable, "-m", "pemamoe", "figures", "--scale", "ci", "--notebook", "01_channel",
                           "--figures-dir", str(target)], cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    (line,) = [x for x in proc.stderr.splitlines() if "error:" in x]
    assert "--figures-dir" in line and "is a file, not a folder" in line
    assert target.read_text() == "keep me\n" and _beside(tmp_path) == ["figs"]


def test_a_mount_point_as_figures_dir_is_refused_and_leaves_nothing_beside(tmp_path, monkeypatch):
    import pemamoe.commands as commands

    figs = _figures(tmp_path)
    real = os.path.ismount
    monkeypatch.setattr(commands.os.path, "ismount", lambda p: Path(p) == figs or real(p))
    with pytest.raises(commands.FiguresDirError, match="is a mount point.*name a folder inside it"):
        make_figures(scale="ci", figures_dir=figs, notebooks=_notebooks(tmp_path, ("98_atomic_writes.py", WRITES)),
                     precompute=False, stream=False)
    assert _beside(tmp_path) == ["figs"]


def test_a_failed_rename_aside_leaves_no_empty_old_folder(tmp_path, monkeypatch):
    """A folder that cannot be renamed (a mount point the check did not see: EBUSY) is left as it was,
    with no empty `*.old-*` folder beside it."""
    import errno

    figs = _figures(tmp_path)
    before = _snapshot(figs)
    rename = Path.rename

    def busy(self, target):
        if self == figs:
            raise OSError(errno.EBUSY, "Device or resource busy", str(self))
        return rename(self, target)

    monkeypatch.setattr(Path, "rename", busy)
    with pytest.raises(OSError, match="busy"):
        make_figures(scale="ci", figures_dir=figs, notebooks=_notebooks(tmp_path, ("98_atomic_writes.py", WRITES)),
                     precompute=False, stream=False)
    assert _snapshot(figs) == before and _beside(tmp_path) == ["figs"]


def _dead_pid() -> int:
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _mark(top: Path, pid: int, listed=None) -> None:
    import json
    import socket

    from pemamoe.commands import STAGING_MARK

    top.mkdir()
    (top / STAGING_MARK).write_text(json.dumps({"pid": pid, "host": socket.gethostname(), "started": None,
                                                "listed": listed or {}}))


def test_staging_left_by_a_killed_run_is_cleaned_by_the_next_and_nothing_else(tmp_path):
    """SIGKILL leaves `figs.partial-*` (and, between the two renames, `figs.old-*`); the next run
    removes ours whose process is gone, and leaves a live run's and anything unmarked alone."""
    figs = _figures(tmp_path)
    dead = _dead_pid()
    _mark(tmp_path / "figs.partial-dead1", dead)
    (tmp_path / "figs.partial-dead1" / "figs").mkdir()
    _mark(tmp_path / "figs.old-dead2", dead)  # swapped already: the aside copy is the previous figures
    (tmp_path / "figs.old-dead2" / "figs").mkdir()
    _mark(tmp_path / "figs.partial-live", os.getppid())  # a live process's: not ours to touch
    (tmp_path / "figs.partial-users").mkdir()  # unmarked: the user's, whatever its name says
    (tmp_path / "figs.partial-users" / "notes.txt").write_text("mine\n")
    make_figures(scale="ci", figures_dir=figs, notebooks=_notebooks(tmp_path, ("98_atomic_writes.py", WRITES)),
                 precompute=False, stream=False)
    assert _beside(tmp_path) == ["figs", "figs.partial-live", "figs.partial-users"]
    assert (tmp_path / "figs.partial-users" / "notes.txt").read_text() == "mine\n"


def test_a_run_killed_between_its_two_renames_gets_its_folder_back(tmp_path):
    from pemamoe.commands import clean_stale_staging

    _mark(tmp_path / "figs.old-dead", _dead_pid())
    (tmp_path / "figs.old-dead" / "figs").mkdir()
    (tmp_path / "figs.old-dead" / "figs" / "kept.txt").write_text("the user's figures\n")
    assert clean_stale_staging(tmp_path / "figs") == [tmp_path / "figs.old-dead"]
    assert (tmp_path / "figs" / "kept.txt").read_text() == "the user's figures\n" and _beside(tmp_path) == ["figs"]


def test_a_file_saved_in_the_figures_folder_during_the_run_is_kept(tmp_path, capsys):
    """The user saves notes.txt (new) and atomic_table.csv (which the run rewrites too) into the
    figures folder while the notebooks run: notes.txt is in the new folder; the user's
    atomic_table.csv, which has a namesake there, stays aside, named, never deleted."""
    figs = _figures(tmp_path)
    user = PARAMETERS + f'''# %%
from pathlib import Path
Path({str(figs)!r}, "notes.txt").write_text("saved during the run\\n")
Path({str(figs)!r}, "atomic_table.csv").write_text("the user's table\\n")
'''
    make_figures(scale="ci", figures_dir=figs,
                 notebooks=_notebooks(tmp_path, ("98_user_saves.py", user), ("98_atomic_writes.py", WRITES)),
                 precompute=False, stream=False)
    assert (figs / "notes.txt").read_text() == "saved during the run\n"
    assert (figs / "atomic_table.csv").read_text() == "scale\nci\n"
    (aside,) = [p for p in tmp_path.iterdir() if p.name.startswith("figs.old-")]
    assert (aside / "figs" / "atomic_table.csv").read_text() == "the user's table\n"
    assert str(aside / "figs") in capsys.readouterr().err


def test_sigterm_during_figures_leaves_no_staging_and_the_folder_as_it_was(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    figs = _figures(tmp_path)
    before = _snapshot(figs)
    slow = PARAMETERS + '''# %%
import time
time.sleep(120)
'''
    (nb,) = _notebooks(tmp_path, ("98_slow.py", slow))
    proc = subprocess.Popen([sys.executable, "-m", "pemamoe", "figures", "--scale", "ci", "--notebook", str(nb),
                             "--figures-dir", str(figs)], cwd=REPO_ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 120
        while not any(p.name.startswith("figs.partial-") for p in tmp_path.iterdir()):
            assert time.time() < deadline and proc.poll() is None, proc.communicate()
            time.sleep(0.2)
        time.sleep(3)  # the kernel is running the notebook
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, err
    # the command's own line last, no traceback of it. The killed kernel is another process on the same
    # stderr: under load its own shutdown log ("[IPKernelApp] WARNING | Parent appears to have exited")
    # can land after the command's line, so the command's last line is the last one not the kernel's.
    ours = [line for line in err.strip().splitlines() if not line.startswith("[IPKernelApp]")]
    assert "terminated (SIGTERM); the figures folder is as it was" in ours[-1], err
    assert "KeyboardInterrupt" not in err and "pemamoe/" not in err, err
    assert _snapshot(figs) == before and _beside(tmp_path) == ["figs"]
