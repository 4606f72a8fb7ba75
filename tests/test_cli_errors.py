"""Usage errors of `figures` and `sweep` (issue 42): a bad flag value is refused while the arguments
are parsed, in one line naming the flag, the value and what is allowed, before anything trains or
any notebook runs; a notebook may be named by its bare file name or stem."""

from pathlib import Path

import pytest

from pemamoe.__main__ import main

REPO = Path(__file__).resolve().parents[1]


def _error_line(err: str) -> str:
    """The one `error:` line of an argparse usage error (the usage lines above it aside)."""
    assert "Traceback" not in err, err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == 1, err
    return errors[0]


@pytest.fixture
def figures_calls(monkeypatch, tmp_path):
    """Replace make_figures by a stub that records its arguments (nothing trains, no notebook runs)."""
    import pemamoe.commands

    seen = []

    def fake_make_figures(scale, figures_dir, notebooks, **kwargs):
        seen.append(dict(scale=scale, figures_dir=figures_dir, notebooks=notebooks, **kwargs))
        return tmp_path / "README.md"

    monkeypatch.setattr(pemamoe.commands, "make_figures", fake_make_figures)
    return seen


def _figures(tmp_path, *argv):
    return main(["figures", "--scale", "ci", "--figures-dir", str(tmp_path / "figures"), *argv])


# -- figures --notebook ------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["08_theory_check.py", "08_theory_check", "notebooks/08_theory_check.py",
                                  str(REPO / "notebooks" / "08_theory_check.py")])
def test_figures_notebook_by_bare_name_stem_or_path_resolves_under_notebooks(name, figures_calls, tmp_path):
    assert _figures(tmp_path, "--notebook", name) == 0
    (call,) = figures_calls
    assert [Path(n) for n in call["notebooks"]] == [REPO / "notebooks" / "08_theory_check.py"]
    assert Path(call["notebooks"][0]).is_file()


def test_figures_notebook_repeated_keeps_the_order(figures_calls, tmp_path):
    assert _figures(tmp_path, "--notebook", "09_experiments", "--notebook", "01_channel.py") == 0
    assert [Path(n).name for n in figures_calls[0]["notebooks"]] == ["09_experiments.py", "01_channel.py"]


@pytest.mark.parametrize("name", ["99_nope.py", "08_theory", "notebooks/nope.py", "elsewhere/08_theory_check.py"])
def test_figures_unknown_notebook_is_a_usage_error_listing_the_notebooks(name, figures_calls, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        _figures(tmp_path, "--notebook", name)
    assert exit_.value.code == 2 and figures_calls == []
    line = _error_line(capsys.readouterr().err)
    assert "--notebook" in line and repr(name) in line
    assert "08_theory_check" in line and "00_index" in line and "10_ablations" in line  # what is allowed
    assert not (tmp_path / "figures").exists()


# -- figures --workers, --backend --------------------------------------------------------------
@pytest.mark.parametrize("argv, needles", [
    (["--workers", "0"], ["--workers", "'0'", ">= 1"]),
    (["--workers", "-3"], ["--workers", "'-3'", ">= 1"]),
    (["--workers", "two"], ["--workers", "'two'", ">= 1"]),
    (["--backend", "rya"], ["--backend", "'rya'", "local", "ray"]),
])
def test_figures_bad_workers_or_backend_is_a_usage_error(argv, needles, figures_calls, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        _figures(tmp_path, *argv)
    assert exit_.value.code == 2 and figures_calls == []
    line = _error_line(capsys.readouterr().err)
    assert all(n in line for n in needles), line


def test_figures_good_workers_and_backend_reach_make_figures(figures_calls, tmp_path):
    assert _figures(tmp_path, "--workers", "3", "--backend", "local", "--notebook", "01_channel") == 0
    assert figures_calls[0]["workers"] == 3 and figures_calls[0]["backend"] == "local"


# -- --results-dir whose parent folder does not exist -----------------------------------------
def test_sweep_refuses_a_results_dir_whose_parent_does_not_exist(tmp_path, capsys):
    missing = tmp_path / "nonexistent" / "x"
    with pytest.raises(SystemExit) as exit_:
        main(["sweep", "--scale", "ci", "--methods", "mlp", "--seeds", "0", "--results-dir", str(missing), "--status"])
    assert exit_.value.code == 2
    line = _error_line(capsys.readouterr().err)
    assert "--results-dir" in line and str(missing) in line and str(missing.parent) in line
    assert not missing.parent.exists()


def test_sweep_status_accepts_a_new_results_dir_in_an_existing_folder_and_a_url(tmp_path, capsys):
    new = tmp_path / "new-results"
    # no records either (a checkout that ran `make figures SCALE=ci` holds this run's record in records/ci)
    assert main(["sweep", "--scale", "ci", "--methods", "mlp", "--seeds", "0", "--results-dir", str(new),
                 "--records-dir", str(tmp_path / "records"), "--status"]) == 0
    assert "mlp" in capsys.readouterr().out
    assert main(["sweep", "--scale", "ci", "--methods", "mlp", "--seeds", "0", "--results-dir",
                 "memory://bucket/runs", "--status"]) == 0


def test_sweep_refuses_a_results_url_no_protocol_serves_in_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["sweep", "--scale", "ci", "--results-dir", "nosuch://bucket/runs", "--status"])
    assert exit_.value.code == 2
    line = _error_line(capsys.readouterr().err)
    assert "--results-dir" in line and "'nosuch'" in line


def test_figures_refuses_a_results_dir_whose_parent_does_not_exist(figures_calls, tmp_path, capsys):
    missing = tmp_path / "nonexistent" / "x"
    with pytest.raises(SystemExit) as exit_:
        _figures(tmp_path, "--notebook", "01_channel", "--results-dir", str(missing))
    assert exit_.value.code == 2 and figures_calls == []
    line = _error_line(capsys.readouterr().err)
    assert "--results-dir" in line and str(missing) in line


@pytest.mark.parametrize("argv", [["train", "--bogus"], ["figures", "--scale", "ci", "--bogus"], ["export", "--bogus"]])
def test_an_unknown_option_is_named_by_its_own_commands_usage(argv, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"usage: python -m pemamoe {argv[0]}" in err  # the command's usage, not the top-level one
    assert _error_line(err) == f"python -m pemamoe {argv[0]}: error: unrecognized arguments: --bogus"
