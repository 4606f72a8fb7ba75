"""Shared utilities: scales, atomic writes, figure and table output, provenance README."""

import os
import re
import stat
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pandas as pd
import pytest

from pemamoe import core


def test_by_scale_picks_and_rejects():
    assert core.by_scale("ci", ci=1, small=2, paper=3) == 1
    assert core.by_scale("paper", ci=1, small=2, paper=3) == 3
    assert core.by_scale("medium", ci=1, small=2, paper=3) == 2  # a size not about training: small's
    assert core.by_scale("medium", ci=1, small=2, paper=3, medium=5) == 5
    with pytest.raises(ValueError, match="scale must be one of ci, small, medium, paper; got 'huge'"):
        core.by_scale("huge", ci=1, small=2, paper=3)


def test_atomic_write_leaves_old_file_when_writer_fails(tmp_path):
    target = tmp_path / "result.json"
    core.atomic_write_json(target, {"a": 1})
    with pytest.raises(RuntimeError):
        with core.atomic_path(target) as tmp:
            tmp.write_text("half written")
            raise RuntimeError("killed")
    assert target.read_text() == '{\n  "a": 1\n}\n'
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]


def test_save_figure_and_table(tmp_path):
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    assert core.save_figure(fig, "demo", tmp_path) is None  # a cell ending with it prints nothing
    plt.close(fig)
    assert (tmp_path / "demo.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "demo.pdf").read_bytes()[:4] == b"%PDF"
    assert core.write_table(pd.DataFrame({"method": ["mlp"], "params": [6820]}), "t", tmp_path) is None
    md, csv = tmp_path / "t.md", tmp_path / "t.csv"
    assert md.read_text().splitlines() == ["| method | params |", "|---|---|", "| mlp | 6820 |"]
    assert pd.read_csv(csv).to_dict("list") == {"method": ["mlp"], "params": [6820]}


def test_figures_readme_keeps_rows_of_untouched_files(tmp_path):
    from pemamoe import commands

    (tmp_path / "a.png").write_bytes(b"x")
    (tmp_path / "cost_table.md").write_text("x")
    commands.write_figures_readme(tmp_path, {"a.png": "01_channel.py"}, scale="ci",
                              inputs={"01_channel.py": "abc", "package": "p1", "records": "r1"})
    commands.write_figures_readme(tmp_path, {"cost_table.md": "05_nets.py"}, scale="small",
                              inputs={"05_nets.py": "def", "package": "p2", "records": "r2"})
    text = (tmp_path / "README.md").read_text()
    assert "| a.png | model illustration (no paper figure) | notebooks/01_channel.py | ci |" in text
    assert "| cost_table.md | Table 'Computational cost comparison (actor network)' |" in text
    assert "`make figures SCALE=small` | def |" in text and "`make figures SCALE=ci` | abc |" in text
    assert "package's code at digest p2 and the committed records at digest r2" in text  # the last run's
    assert f"ran on {core.cpu_model()}:" in text  # where it was made: plot-time values depend on the processor
    assert core.cpu_model().strip() and "\n" not in core.cpu_model()


def test_figures_readme_names_the_scale_a_studys_runs_have_not_the_commands(tmp_path):
    from pemamoe import commands

    for name in ("tuning.md", "results_coverage.png"):
        (tmp_path / name).write_text("x")
    commands.write_figures_readme(tmp_path, {"tuning.md": "09b_budget.py", "results_coverage.png": "09_experiments.py"},
                              scale="medium", inputs={})
    text = (tmp_path / "README.md").read_text()
    assert "| notebooks/09b_budget.py | small (at every scale) |" in text  # the study's small settings
    assert "| results_coverage.png | (ours) coverage over training, with each phase's random and k-means levels | " \
           "notebooks/09_experiments.py | medium |" in text
    assert "(no paper figure)" not in text  # the studies name what they are
    commands.write_figures_readme(tmp_path, {"tuning.md": "09b_budget.py"}, scale="ci", inputs={})
    assert "| notebooks/09b_budget.py | ci |" in (tmp_path / "README.md").read_text()  # ci shrinks every study


def test_run_notebook_rejects_unknown_scale(tmp_path):
    with pytest.raises(ValueError, match="got 'tiny'"):
        core.run_notebook(core.figure_notebooks()[0], {"scale": "tiny"}, output_dir=tmp_path)


# ---------------------------------------------------------------- files follow the umask


@pytest.mark.parametrize("umask", [0o022, 0o027, 0o077])
def test_atomic_writes_get_the_mode_the_umask_gives_new_files(tmp_path, umask):
    old = os.umask(umask)
    try:
        assert core.current_umask() == umask
        core.atomic_write_json(tmp_path / "r.json", {"a": 1})
        fig, ax = plt.subplots()
        core.save_figure(fig, "f", tmp_path)
        plt.close(fig)
        core.write_table(pd.DataFrame({"a": [1]}), "t", tmp_path)
        with open(tmp_path / "plain.txt", "w") as fh:  # what an ordinary open() gives
            fh.write("x")
    finally:
        os.umask(old)
    expected = stat.S_IMODE((tmp_path / "plain.txt").stat().st_mode)
    assert expected == 0o666 & ~umask
    for name in ("r.json", "f.png", "f.pdf", "t.md", "t.csv"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == expected, name


# ---------------------------------------------------------------- outputs under the repository root

ROOT = Path(__file__).resolve().parent.parent


def test_repo_root_is_found_from_the_package_the_notebooks_folder_and_the_working_directory(tmp_path, monkeypatch):
    monkeypatch.delenv("PEMAMOE_ROOT", raising=False)
    assert core.find_repo_root(Path(core.__file__).parent) == ROOT  # editable install or checkout
    assert core.find_repo_root(ROOT / "notebooks") == ROOT  # a JupyterLab kernel's cwd
    monkeypatch.chdir(ROOT / "notebooks")
    assert core.find_repo_root(tmp_path, Path.cwd()) == ROOT  # a package outside any checkout
    monkeypatch.chdir(tmp_path)
    assert core.find_repo_root(tmp_path) == tmp_path  # no checkout anywhere: the working directory
    monkeypatch.setenv("PEMAMOE_ROOT", str(ROOT))
    assert core.find_repo_root(tmp_path) == ROOT


def test_relative_figure_dirs_are_under_the_repo_root_whatever_the_cwd(tmp_path, monkeypatch):
    root = tmp_path / "checkout"
    (root / "notebooks").mkdir(parents=True)
    monkeypatch.setattr(core, "REPO_ROOT", root)
    monkeypatch.chdir(root / "notebooks")  # as in JupyterLab
    fig, ax = plt.subplots()
    core.save_figure(fig, "x", "paper_figures")
    core.save_figure(fig, "y", tmp_path / "injected")  # absolute: as given (tests, make_figures)
    plt.close(fig)
    core.write_table(pd.DataFrame({"a": [1]}), "t", "paper_figures")
    assert sorted(p.name for p in (root / "paper_figures").iterdir()) == ["t.csv", "t.md", "x.pdf", "x.png"]
    assert not (root / "notebooks" / "paper_figures").exists()
    assert sorted(p.name for p in (tmp_path / "injected").iterdir()) == ["y.pdf", "y.png"]


# ---------------------------------------------------------------- the headless runner

TINY = '''# %%
import sys

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"

# %%
print("progress-from-inside", scale)
print("stderr-from-inside", file=sys.stderr)
'''


def test_appendix_notebook_is_run_by_make_figures_and_the_notebook_tests():
    names = [p.name for p in core.figure_notebooks()]
    assert names[:3] == ["00_index.py", "00b_core.py", "01_channel.py"]
    assert names == sorted(names)


@pytest.mark.notebook
def test_runner_streams_progress_without_kernel_warnings_and_is_silent_by_default(tmp_path, capfd):
    nb = tmp_path / "99_tiny.py"
    nb.write_text(TINY)
    core.run_notebook(nb, {"scale": "ci"}, output_dir=tmp_path / "exec")
    quiet = capfd.readouterr()
    assert quiet.out == "" and quiet.err == ""  # no "Kernel is running over TCP without encryption"
    from pemamoe import commands  # make_figures sits above the sweep (appendix 09e)

    readme = commands.make_figures("ci", tmp_path / "figs", [nb], stream=True)
    loud = capfd.readouterr()
    assert "without encryption" not in loud.out + loud.err
    lines = loud.out.splitlines()
    assert lines[0].startswith("[figures] 1/1 99_tiny.py (scale=ci) started, 0:00:0")
    assert "progress-from-inside ci" in lines[1]
    assert re.match(r"\[figures\] 1/1 99_tiny.py done in \d:\d\d:\d\d, \d:\d\d:\d\d elapsed", lines[-2])
    # one closing line (issue 60); a fresh folder: its README is new, so it counts as changed
    assert lines[-1] == "[figures] 1 notebook, 0 runs trained, 1 file written (README.md included), 1 changed: README.md"
    assert "KeyboardInterrupt" not in loud.err  # no SIGINT to a finished kernel (appendix 00b)
    assert "stderr-from-inside" in loud.err
    assert readme == tmp_path / "figs" / "README.md"


# -- the command line's argument checks and names (issue 41: one set, in core, without torch) ------
@pytest.mark.parametrize("parse, text, message", [
    (core.int_arg(1), "0", "must be an integer >= 1, got '0'"),
    (core.int_arg(1), "two", "must be an integer >= 1, got 'two'"),
    (core.int_arg(1), "1.0", "must be an integer >= 1, got '1.0'"),
    (core.int_arg(0, core.SEED_LIMIT), str(2**63), f"must be an integer in [0, 2**63), got '{2**63}'"),
    (core.int_arg(0, core.SEED_LIMIT), "-1", "must be an integer in [0, 2**63), got '-1'"),
    (core.int_arg(0, 10), "10", "must be an integer in [0, 10), got '10'"),
    (core.real_arg(gt=0), "0", "must be a finite number > 0, got '0'"),
    (core.real_arg(gt=0), "inf", "must be a finite number > 0, got 'inf'"),
    (core.real_arg(ge=0), "-0.1", "must be a finite number >= 0, got '-0.1'"),
    (core.real_arg(ge=0), "nan", "must be a finite number >= 0, got 'nan'"),
])
def test_command_line_checks_name_the_value_as_typed_and_what_is_allowed(parse, text, message):
    import argparse

    with pytest.raises(argparse.ArgumentTypeError) as err:
        parse(text)
    assert str(err.value) == message


def test_command_line_checks_return_the_value():
    assert core.int_arg(0, core.SEED_LIMIT)(str(2**63 - 1)) == 2**63 - 1 and core.int_arg(1)(" 3 ") == 3
    assert core.real_arg(gt=0)("1e-7") == 1e-7 and core.real_arg(ge=0)("0") == 0.0


def test_one_line_flattens_every_whitespace_run():
    assert core.one_line(ValueError("a\n  b\tc \n")) == "a b c"


def test_the_command_lines_names_are_the_owning_modules_own():
    from dataclasses import fields

    from pemamoe import experiments, phase_controller, sweep_runner, train_config

    assert phase_controller.MECHANISMS is core.MECHANISMS and experiments.EXPERIMENTS is core.EXPERIMENTS
    assert experiments.ACTOR_READINGS is core.ACTOR_READINGS and experiments.READABLE_EXPERIMENTS is core.READABLE_EXPERIMENTS
    assert sweep_runner.BACKENDS is core.BACKENDS and sweep_runner.DEFAULT_POPULATION == core.DEFAULT_POPULATION
    assert train_config.SEED_LIMIT == core.SEED_LIMIT == 2**63
    switches = {f.name for f in fields(phase_controller.PhaseControllerConfig) if f.type in (bool, "bool")}
    assert set(core.MECHANISMS) <= switches  # each names an on/off switch of the controller
