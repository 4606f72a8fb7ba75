"""Usage errors of `figures` and `sweep` (issue 42): a bad flag value is refused while the arguments
are parsed, in one line naming the flag, the value and what is allowed, before anything trains or
any notebook runs; a notebook may be named by its bare file name or stem."""

import re
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
@pytest.mark.parametrize("name", ["08_theory.py", "08_theory", "notebooks/08_theory.py",
                                  str(REPO / "notebooks" / "08_theory.py")])
def test_figures_notebook_by_bare_name_stem_or_path_resolves_under_notebooks(name, figures_calls, tmp_path):
    assert _figures(tmp_path, "--notebook", name) == 0
    (call,) = figures_calls
    assert [Path(n) for n in call["notebooks"]] == [REPO / "notebooks" / "08_theory.py"]
    assert Path(call["notebooks"][0]).is_file()


def test_figures_notebook_repeated_keeps_the_order(figures_calls, tmp_path):
    assert _figures(tmp_path, "--notebook", "09_experiments", "--notebook", "01_channel.py") == 0
    assert [Path(n).name for n in figures_calls[0]["notebooks"]] == ["09_experiments.py", "01_channel.py"]


@pytest.mark.parametrize("name", ["99_nope.py", "08_theo", "notebooks/nope.py", "elsewhere/08_theory.py"])
def test_figures_unknown_notebook_is_a_usage_error_listing_the_notebooks(name, figures_calls, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        _figures(tmp_path, "--notebook", name)
    assert exit_.value.code == 2 and figures_calls == []
    line = _error_line(capsys.readouterr().err)
    assert "--notebook" in line and repr(name) in line
    assert "08_theory" in line and "00_index" in line and "10_ablations" in line  # what is allowed
    assert not (tmp_path / "figures").exists()


# -- figures --workers, --backend --------------------------------------------------------------
@pytest.mark.parametrize("argv, needles", [
    (["--workers", "0"], ["--workers", "'0'", "in [1, 1024]"]),
    (["--workers", "-3"], ["--workers", "'-3'", "in [1, 1024]"]),
    (["--workers", "two"], ["--workers", "'two'", "in [1, 1024]"]),
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
    err = capsys.readouterr().err
    line = _error_line(err)
    assert "--results-dir" in line and str(missing) in line
    assert line.startswith("python -m pemamoe figures: error:") and "usage: python -m pemamoe figures" in err


@pytest.mark.parametrize("argv", [["train", "--bogus"], ["figures", "--scale", "ci", "--bogus"], ["export", "--bogus"]])
def test_an_unknown_option_is_named_by_its_own_commands_usage(argv, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"usage: python -m pemamoe {argv[0]}" in err  # the command's usage, not the top-level one
    assert _error_line(err) == f"python -m pemamoe {argv[0]}: error: unrecognized arguments: --bogus"


# == Issue 41: one-line errors everywhere ====================================================
# Each test runs `python -m pemamoe ...` as a user would and requires a non-zero exit status and
# stderr of exactly one line (or, for a usage error, one `error:` line under argparse's usage)
# that names the problem and the value at fault, never a traceback.
import json  # noqa: E402
import os  # noqa: E402
import socket  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import textwrap  # noqa: E402

HEAVY = ("torch", "numpy", "pandas", "pyarrow", "numba", "pemamoe.mappo", "pemamoe.sweep_runner", "pemamoe.experiments",
         "pemamoe.records", "pemamoe.phase_controller")


def _cli(*args, env=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "pemamoe", *map(str, args)], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout, env={**os.environ, **(env or {})})


def _only_line(proc) -> str:
    """stderr's single line (a runtime error: no usage lines either); exit status non-zero."""
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode != 0, (proc.returncode, proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr and len(lines) == 1, proc.stderr
    return lines[0]


def _usage_error(proc) -> str:
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    return _error_line(proc.stderr)


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _s3_env(tmp_path, endpoint: str, credentials: bool = True) -> dict:
    """An S3 client environment that reads no file of this machine and tries each request once."""
    env = {"AWS_ENDPOINT_URL": endpoint, "AWS_DEFAULT_REGION": "us-east-1", "AWS_MAX_ATTEMPTS": "1",
           "AWS_RETRY_MODE": "standard", "AWS_EC2_METADATA_DISABLED": "true", "AWS_CONFIG_FILE": os.devnull,
           "AWS_SHARED_CREDENTIALS_FILE": os.devnull, "PEMAMOE_CACHE": str(tmp_path / "cache")}
    if credentials:
        env.update(AWS_ACCESS_KEY_ID="testing", AWS_SECRET_ACCESS_KEY="testing")
    return env


def _without_aws_credentials(env: dict) -> dict:
    return {k: v for k, v in {**os.environ, **env}.items()
            if k not in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN", "AWS_PROFILE")}


def _store_command(command: str, url: str, tmp_path) -> list:
    if command == "sweep":
        return ["sweep", "--scale", "ci", "--methods", "mlp", "--seeds", "0", "--workers", "1",
                "--results-dir", url, "--records-dir", tmp_path / "records"]
    if command == "figures":
        return ["figures", "--scale", "ci", "--figures-dir", tmp_path / "figures", "--results-dir", url]
    return ["train", "--scale", "ci", "--method", "mlp", "--results-dir", url]


# -- a, b: a store that cannot be reached -----------------------------------------------------
@pytest.mark.parametrize("command", ["sweep", "train", "figures"])
def test_41ab_an_unreachable_store_endpoint_is_one_line_naming_the_endpoint(command, tmp_path):
    pytest.importorskip("s3fs")
    endpoint = f"http://127.0.0.1:{_closed_port()}"
    proc = _cli(*_store_command(command, "s3://bucket/results", tmp_path), env=_s3_env(tmp_path, endpoint))
    line = _only_line(proc)
    assert line.startswith(f"python -m pemamoe {command}: error: results store s3://bucket/results: ")
    assert f"cannot connect to its endpoint {endpoint}" in line and "AWS_ENDPOINT_URL" in line


@pytest.mark.parametrize("command", ["sweep", "train"])
def test_41ab_no_store_credentials_is_one_line_saying_what_to_set(command, tmp_path):
    pytest.importorskip("s3fs")
    env = _without_aws_credentials(_s3_env(tmp_path, f"http://127.0.0.1:{_closed_port()}", credentials=False))
    proc = subprocess.run([sys.executable, "-m", "pemamoe", *map(str, _store_command(command, "s3://bucket/results", tmp_path))],
                          cwd=REPO, capture_output=True, text=True, timeout=300, env=env)
    line = _only_line(proc)
    assert "results store s3://bucket/results: no credentials found" in line
    assert "AWS_ACCESS_KEY_ID" in line and "AWS_SECRET_ACCESS_KEY" in line


# -- a, c: a bucket that does not exist, named --------------------------------------------------
@pytest.fixture
def s3_endpoint():
    """A moto S3 server on 127.0.0.1 (no bucket in it); yields its URL."""
    pytest.importorskip("s3fs")
    server_mod = pytest.importorskip("moto.server")
    server = server_mod.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    yield f"http://{host}:{port}"
    server.stop()


@pytest.mark.parametrize("command", ["sweep", "train"])
def test_41c_a_missing_bucket_is_named_in_one_line(command, s3_endpoint, tmp_path):
    proc = _cli(*_store_command(command, "s3://no-such-bucket-41/results", tmp_path), env=_s3_env(tmp_path, s3_endpoint))
    line = _only_line(proc)
    assert "results store s3://no-such-bucket-41/results: bucket 'no-such-bucket-41' does not exist" in line
    assert "aws s3 mb s3://no-such-bucket-41" in line
    status = _cli(*_store_command("sweep", "s3://no-such-bucket-41/results", tmp_path), "--status",
                  env=_s3_env(tmp_path, s3_endpoint))  # --status too: it used to print an empty table
    assert "bucket 'no-such-bucket-41' does not exist" in _only_line(status)


# -- a: a run folder locked by another live process --------------------------------------------
def test_41a_sweep_over_a_run_locked_by_another_process_is_one_line(tmp_path):
    from pemamoe.experiments import RunSpec

    results = tmp_path / "results"
    run_dir = RunSpec("mlp", 0, "ci").run_dir(results)
    script = textwrap.dedent(f"""
        import time
        from pemamoe.runs import lock_run
        lock = lock_run({str(run_dir)!r})
        print("locked", flush=True)
        time.sleep(300)
    """)
    holder = subprocess.Popen([sys.executable, "-c", script], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        proc = _cli("sweep", "--scale", "ci", "--methods", "mlp", "--seeds", "0", "--workers", "1",
                    "--results-dir", results, "--records-dir", tmp_path / "records")
    finally:
        holder.kill()
        holder.wait()
    line = _only_line(proc)
    assert proc.returncode == 1
    assert line.startswith("python -m pemamoe sweep: error: sweep run mlp, seed 0 failed: ")
    assert f"run folder {run_dir} is being written by process {holder.pid}" in line


# -- a, d: a damaged portable state ---------------------------------------------------------------
@pytest.fixture(scope="module")
def portable_state(tmp_path_factory):
    """(records folder, the path of a real portable state in it) of a ci MLP run stopped at iteration 2."""
    from pemamoe.mappo import train_population
    from pemamoe.records import write_portable_state
    from pemamoe.experiments import RunSpec

    tmp = tmp_path_factory.mktemp("portable")
    spec = RunSpec("mlp", 0, "ci")
    train_population([spec.to_config()], [spec.run_dir(tmp / "first")], max_iterations=2)
    return tmp / "records", write_portable_state(spec.run_dir(tmp / "first"), "ci", tmp / "records")


def _damaged_copy(portable_state, tmp_path):
    """A copy of the records whose portable state is still a well-formed, decompressible checkpoint
    that torch loads, but with one byte of a tensor changed: only its seal (sha256) tells."""
    import shutil

    import pyarrow as pa

    from pemamoe.records import _PORTABLE_MAGIC, read_portable_state

    records, path = portable_state
    copy = tmp_path / "records"
    shutil.copytree(records, copy)
    target = copy / path.relative_to(records)
    data = bytearray(read_portable_state(path))
    data[len(data) // 2] ^= 0x01  # the middle of the checkpoint: tensor bytes, which torch.load does not check
    target.write_bytes(_PORTABLE_MAGIC + len(data).to_bytes(8, "little")
                       + pa.Codec("zstd").compress(bytes(data), asbytes=True))
    return copy, target


def test_41d_sweep_status_refuses_a_portable_state_whose_seal_fails(portable_state, tmp_path):
    import io

    import torch

    records, target = _damaged_copy(portable_state, tmp_path)
    from pemamoe.records import read_portable_state

    assert torch.load(io.BytesIO(read_portable_state(target)), weights_only=True)["iteration"] == 2  # loads
    proc = _cli("sweep", "--scale", "ci", "--methods", "mlp", "--seeds", "0", "--results-dir", tmp_path / "results",
                "--records-dir", records, "--status")
    line = _only_line(proc)
    assert f"run record {target}: fails its content check" in line and "git checkout" in line


def test_41a_sweep_refuses_a_damaged_portable_state_in_one_line(portable_state, tmp_path):
    records, target = _damaged_copy(portable_state, tmp_path)
    target.write_bytes(b"pemamoe-portable-1\n" + (99).to_bytes(8, "little") + b"\x00" * 40)  # not zstd
    proc = _cli("sweep", "--scale", "ci", "--methods", "mlp", "--seeds", "0", "--workers", "1",
                "--results-dir", tmp_path / "results", "--records-dir", records)
    line = _only_line(proc)
    assert proc.returncode == 1 and "sweep run mlp, seed 0 failed: " in line
    assert f"run record {target}: cannot be decompressed" in line


# -- e, f: the config.json of --out ------------------------------------------------------------
@pytest.mark.parametrize("content, problem", [("garbage{", "is not valid JSON"), ("[1, 2]", "holds a JSON list"),
                                              ('{"lr": "fast"}', "does not hold a valid TrainConfig")])
def test_41e_a_garbage_config_json_is_named_damaged_not_a_different_config(content, problem, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").write_text(content)
    line = _only_line(_cli("train", "--scale", "ci", "--method", "mlp", "--out", out))
    assert f"{out / 'config.json'} is damaged or unreadable: it {problem}" in line
    assert "different config" not in line and "--no-resume" in line


def test_41f_a_different_config_names_the_keys_that_differ(tmp_path):
    from pemamoe.mappo import TrainConfig

    out = tmp_path / "run"
    out.mkdir()
    requested = TrainConfig.for_scale("ci", method="mlp", seed=0)
    stored = TrainConfig.for_scale("ci", method="mlp", seed=0, lr=requested.lr * 10, gamma=0.5)
    (out / "config.json").write_text(json.dumps(stored.to_dict()))
    line = _only_line(_cli("train", "--scale", "ci", "--method", "mlp", "--out", out))
    assert "holds a run with a different config" in line and "--no-resume" in line
    assert f"lr: stored {stored.lr!r}, requested {requested.lr!r}" in line
    assert f"gamma: stored 0.5, requested {requested.gamma!r}" in line


# -- g: a truncated checkpoint ------------------------------------------------------------------
def test_41g_a_truncated_checkpoint_is_one_line_without_the_zip_readers_internals(tmp_path):
    import torch

    from pemamoe.mappo import TrainConfig

    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").write_text(json.dumps(TrainConfig.for_scale("ci", method="mlp", seed=0).to_dict()))
    torch.save({"config": {}, "iteration": 1, "weights": torch.zeros(4096)}, out / "checkpoint.pt")
    whole = (out / "checkpoint.pt").read_bytes()
    (out / "checkpoint.pt").write_bytes(whole[: len(whole) // 2])
    line = _only_line(_cli("train", "--scale", "ci", "--method", "mlp", "--out", out))
    assert f"run folder {out}: checkpoint.pt is truncated or damaged: its {len(whole) // 2:,} bytes" in line
    assert "pass --no-resume" in line
    for internal in ("PytorchStreamReader", "central directory", "miniz", "RuntimeError"):
        assert internal not in line, line


# -- h, i: arguments checked before any heavy import; help and usage errors stay light ------------
def _modules_after(argv) -> tuple:
    """(the heavy modules loaded, stderr) after `main(argv)` in a fresh interpreter."""
    code = textwrap.dedent(f"""
        import sys
        from pemamoe.__main__ import main
        try:
            main({[str(a) for a in argv]!r})
        except SystemExit:
            pass
        print(sorted(m for m in {HEAVY!r} if m in sys.modules))
    """)
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    return proc.stdout.strip().splitlines()[-1], proc.stderr


@pytest.mark.parametrize("argv", [["train", "--seed", 2**63], ["sweep", "--seeds", "0", 2**63]])
def test_41h_a_seed_out_of_range_is_refused_before_the_trainer_is_imported(argv):
    loaded, err = _modules_after(argv)
    assert loaded == "[]", loaded
    assert f"must be an integer in [0, 2**63), got '{2**63}'" in _error_line(err)
    line = _usage_error(_cli(*argv))
    assert "--seed" in line and str(2**63) in line


@pytest.mark.parametrize("argv", [["--help"], ["sweep", "--help"], ["sweep", "--bogus"], ["sweep", "--workers", "0"],
                                  ["train", "--help"], ["train", "--bogus"], ["train", "--without", "nothing"],
                                  ["figures", "--help"], ["figures", "--workers", "0"], ["export", "--help"],
                                  ["check-export", "--help"]], ids=" ".join)
def test_41i_help_and_usage_errors_import_no_heavy_module(argv):
    """What keeps `--help` and a usage error of every command well under half a second (measured
    by benchmarks/bench_cli.py, not here): neither torch nor the experiments are imported."""
    loaded, err = _modules_after(argv)
    assert loaded == "[]", (argv, loaded)
    assert "Traceback" not in err


@pytest.mark.parametrize("argv", [["sweep", "--scale", "ci", "--workers", "0"], ["figures", "--workers", "0"],
                                  ["train", "--iterations", "0"]])
def test_41i_every_command_checks_counts_with_the_same_words(argv, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    line = _error_line(capsys.readouterr().err)  # bounded above too (issue 59), in the same words
    assert re.search(rf"argument {argv[-2]}: must be an integer in \[1, [0-9,]+\], got '0'$", line), line


def test_sweep_resolves_relative_stores_under_the_checkout_from_any_folder(tmp_path):
    """A plugin's sweep run from its own folder reads and writes the repository's results/ and records/,
    the ones `figures` reads: `--status` from another folder reports what it reports from the root."""
    argv = [sys.executable, "-m", "pemamoe", "sweep", "--experiment", "main", "--scale", "medium", "--methods",
            "mlp", "--status"]  # the committed medium MLP records
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    at_root, elsewhere = (subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=300, env=env)
                          for cwd in (REPO, tmp_path))
    assert at_root.returncode == elsewhere.returncode == 0, (at_root.stderr, elsewhere.stderr)
    assert at_root.stdout == elsewhere.stdout and "3 of 3 runs finished" in at_root.stdout
    assert not (tmp_path / "results").exists() and not (tmp_path / "records").exists()
    # a folder the user names is relative to where the command runs: here, an empty new store
    named = subprocess.run([*argv, "--results-dir", "mine", "--records-dir", "mine_records"], cwd=tmp_path,
                           capture_output=True, text=True, timeout=300, env=env)
    assert named.returncode == 0 and "0 of 3 runs finished" in named.stdout, named.stderr


@pytest.mark.parametrize("command, default", [("train", "small"), ("sweep", "small"), ("figures", "medium")])
def test_each_command_help_states_the_scale_default_the_top_level_help_promises(command, default, capsys):
    """One default-scale story: what `--help` says of --scale is what the parser does and what the
    top-level help tells a reader (train and sweep train at small; figures reads medium's records)."""
    with pytest.raises(SystemExit):
        main(["--help"])
    story = " ".join(capsys.readouterr().out.split())
    assert "train and sweep default to small" in story and "figures defaults to medium" in story
    with pytest.raises(SystemExit):
        main([command, "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert f"(default: {default}" in help_text.split("--scale {ci,small,medium,paper}", 2)[-1]


# -- issue 59: every figures failure is one line (PEMAMOE_TRACEBACK=1 shows the traceback) ---------
def test_figures_failing_notebook_is_one_line_naming_it_and_its_executed_copy(tmp_path):
    nb = tmp_path / "98_fails.py"
    nb.write_text('# %% tags=["parameters"]\nscale = "small"\nfigures_dir = "paper_figures"\n\n'
                  '# %%\nraise RuntimeError("this notebook fails")\n')
    argv = ["figures", "--scale", "ci", "--notebook", nb, "--figures-dir", tmp_path / "figs"]
    proc = _cli(*argv)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith("python -m pemamoe figures: error: notebook 98_fails.py failed in its cell"), line
    assert "RuntimeError: this notebook fails" in line and "build/executed/ci/98_fails.ipynb" in line, line
    assert not (tmp_path / "figs").exists()
    shown = _cli(*argv, env={"PEMAMOE_TRACEBACK": "1"})
    assert shown.returncode == 1 and "Traceback (most recent call last)" in shown.stderr


@pytest.mark.parametrize("error, needle", [
    (OSError(28, "No space left on device"), "No space left on device"),
    (KeyboardInterrupt(), "interrupted; the figures folder is as it was"),
])
def test_figures_a_full_disk_or_ctrl_c_is_one_line(error, needle, monkeypatch, tmp_path, capsys):
    import pemamoe.commands

    def failing(*args, **kwargs):
        raise error

    monkeypatch.setattr(pemamoe.commands, "make_figures", failing)
    code = _figures(tmp_path)
    err = capsys.readouterr().err
    assert code == (130 if isinstance(error, KeyboardInterrupt) else 1)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and needle in err, err


def test_figures_a_damaged_record_is_one_line(monkeypatch, tmp_path, capsys):
    import pemamoe.commands
    from pemamoe.records import RecordError

    def failing(*args, **kwargs):
        raise RecordError("records/ci/x.json", "its log's sha256 does not match its marker")

    monkeypatch.setattr(pemamoe.commands, "make_figures", failing)
    assert _figures(tmp_path) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and "sha256 does not match" in err


def test_figures_refuses_a_figures_dir_whose_path_is_not_utf8(figures_calls, tmp_path, capsys):
    bad = os.fsdecode(bytes(tmp_path) + b"/figs\xff")
    with pytest.raises(SystemExit) as exit_:
        main(["figures", "--scale", "ci", "--figures-dir", bad])
    assert exit_.value.code == 2 and figures_calls == []
    line = _error_line(capsys.readouterr().err)
    assert "--figures-dir" in line and "not valid UTF-8" in line
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("command", [["train", "--scale", "ci"], ["sweep", "--scale", "ci", "--status"],
                                     ["figures", "--scale", "ci"]], ids=lambda c: c[0])
def test_a_missing_plugin_is_refused_in_one_line_before_any_heavy_import(command):
    env = {"PEMAMOE_PLUGINS": "no_such_module"}
    proc = _cli(*command, env=env)
    line = _usage_error(proc)
    assert "PEMAMOE_PLUGINS names the module 'no_such_module', which cannot be imported" in line
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    code = textwrap.dedent(f"""
        import os, sys
        os.environ["PEMAMOE_PLUGINS"] = "no_such_module"
        from pemamoe.__main__ import main
        try:
            main({command!r})
        except SystemExit:
            pass
        print(sorted(m for m in {HEAVY!r} if m in sys.modules))
    """)
    loaded = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert loaded.stdout.strip().splitlines()[-1] == "[]", loaded.stdout


def test_load_plugins_names_a_missing_module_in_one_line(monkeypatch):
    from pemamoe.methods import PluginError, load_plugins

    monkeypatch.setenv("PEMAMOE_PLUGINS", "os, no_such_module")
    with pytest.raises(PluginError, match=r"^PEMAMOE_PLUGINS names the module 'no_such_module', which cannot be "
                                          r"imported; name modules importable from PYTHONPATH"):
        load_plugins()


# -- issue 59: refusals in one line, before the trainer is imported; bounds on every number --------
@pytest.mark.parametrize("argv, needles", [
    (["train", "--iterations", "99999999999999999999999"], ["--iterations", "in [1, 10000000]"]),
    (["train", "--noise-gamma", "1e308"], ["--noise-gamma", "<= 10"]),
    (["train", "--method", "mlp", "--without", "kl_anchor"], ["--without", "--method pemamoe", "got --method mlp"]),
    (["train", "--method", "mlp", "--noise-gamma", "0.1"], ["--noise-gamma", "got --method mlp"]),
    (["sweep", "--workers", "99999999999"], ["--workers", "in [1, 1024]"]),
    (["sweep", "--population", "99999999999"], ["--population", "in [1, 1024]"]),
    (["sweep", "--hours", "1e308"], ["--hours", "<= 8760"]),
    (["figures", "--workers", "99999999999"], ["--workers", "in [1, 1024]"]),
], ids=lambda v: " ".join(v) if isinstance(v, list) and v and v[0] in ("train", "sweep", "figures") else "")
def test_an_out_of_bounds_or_inapplicable_number_is_refused_before_any_heavy_import(argv, needles):
    loaded, err = _modules_after(argv)
    assert loaded == "[]", (argv, loaded)
    line = _error_line(err)
    assert all(n in line for n in needles), line


@pytest.mark.skipif(__import__("importlib.util").util.find_spec("torch") is None, reason="needs torch's files")
def test_device_cuda_with_a_cpu_only_torch_is_refused_before_torch_is_imported():
    import importlib.util

    version = (Path(next(iter(importlib.util.find_spec("torch").submodule_search_locations))) / "version.py").read_text()
    if "\ncuda: Optional[str] = None" not in version and "\ncuda = None" not in version:
        pytest.skip("this torch is built for a GPU")
    loaded, err = _modules_after(["train", "--scale", "ci", "--device", "cuda"])
    assert loaded == "[]", loaded
    assert "--device cuda" in _error_line(err) and "torch sees no CUDA device" in err


@pytest.mark.parametrize("command, flag", [("train", "--results-dir"), ("sweep", "--results-dir"),
                                           ("sweep", "--records-dir"), ("figures", "--results-dir")])
def test_a_file_as_a_store_folder_is_refused_naming_the_flag(command, flag, tmp_path):
    target = tmp_path / "a_file"
    target.write_text("mine\n")
    argv = {"train": ["train", "--scale", "ci", "--method", "mlp"], "sweep": ["sweep", "--scale", "ci"],
            "figures": ["figures", "--scale", "ci", "--figures-dir", str(tmp_path / "figs")]}[command]
    loaded, err = _modules_after([*argv, flag, target])
    assert loaded == "[]", loaded
    line = _error_line(err)
    assert f"{flag} {target} is a file, not a folder" in line, line
    assert target.read_text() == "mine\n"


def test_train_refuses_an_out_whose_path_is_not_utf8_and_writes_nothing(tmp_path, capsys):
    bad = os.fsdecode(bytes(tmp_path) + b"/run\xff")
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--scale", "ci", "--method", "mlp", "--out", bad])
    assert exit_.value.code == 2
    assert "--out" in _error_line(capsys.readouterr().err) and os.listdir(tmp_path) == []


@pytest.mark.parametrize("command", ["train", "sweep", "figures"])
def test_pemamoe_traceback_shows_the_traceback_behind_a_one_line_error(command, monkeypatch, tmp_path, capsys):
    import pemamoe.__main__
    import pemamoe.commands

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(pemamoe.__main__, "_train", full_disk)
    monkeypatch.setattr(pemamoe.commands, "_sweep", full_disk)
    monkeypatch.setattr(pemamoe.commands, "make_figures", full_disk)
    argv = {"train": ["train", "--scale", "ci", "--out", str(tmp_path / "run")],
            "sweep": ["sweep", "--scale", "ci", "--records-dir", str(tmp_path / "records")],
            "figures": ["figures", "--scale", "ci", "--figures-dir", str(tmp_path / "figs")]}[command]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "No space left on device" in err and len(err.strip().splitlines()) == 1, err
    monkeypatch.setenv("PEMAMOE_TRACEBACK", "1")
    with pytest.raises(OSError, match="No space left"):
        main(argv)


@pytest.mark.parametrize("cuda, hip, devices, refused", [
    ("None", "None", ["/dev/nvidia0"], "built for CPUs only"),
    ("'12.4'", "None", [], "no GPU device file"),
    ("'12.4'", "None", ["/dev/nvidia0"], None),
    (None, None, [], None),  # a version.py this check cannot read: the trainer decides
])
def test_the_fast_device_check_refuses_only_what_cannot_see_a_gpu(cuda, hip, devices, refused, tmp_path, monkeypatch,
                                                                   capsys):
    import argparse
    import glob
    import importlib.machinery
    import importlib.util

    import pemamoe.__main__ as cli

    torch_dir = tmp_path / "torch"
    torch_dir.mkdir()
    lines = ["__version__ = '9.9'"] + ([f"cuda: Optional[str] = {cuda}", f"hip: Optional[str] = {hip}"] if cuda else [])
    (torch_dir / "version.py").write_text("\n".join(lines) + "\n")
    spec = importlib.machinery.ModuleSpec("torch", None, is_package=True)
    spec.submodule_search_locations = [str(torch_dir)]
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: spec if name == "torch" else None)
    monkeypatch.setattr(glob, "glob", lambda pattern: devices if pattern.startswith("/dev/nvidia") else [])
    monkeypatch.setattr(cli.sys, "platform", "linux")
    parser = argparse.ArgumentParser(prog="t")
    if refused is None:
        cli._check_device("cuda", parser)
        return
    with pytest.raises(SystemExit):
        cli._check_device("cuda", parser)
    assert refused in _error_line(capsys.readouterr().err)
