"""The command line, `python -m pemamoe ...`: a real ci-scale training run through a subprocess, the
flags' mapping onto TrainConfig (with the trainer replaced by a stub), and the errors for bad input."""

import dataclasses
import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import pandas as pd
import pytest
import torch

from pemamoe import mappo
from pemamoe.__main__ import main
from pemamoe.core import SCALES
from pemamoe.phase_controller import MECHANISMS

REPO = Path(__file__).resolve().parents[1]
COMMANDS = ("figures", "sweep", "train", "export", "check-export")


def run_cli(*args, timeout=300):
    """`python -m pemamoe ARGS` from the repository root (so this checkout's package is imported)."""
    return subprocess.run([sys.executable, "-m", "pemamoe", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


# -- a real run --------------------------------------------------------------------------------
def test_ci_training_run_from_the_command_line(tmp_path, capsys):
    out = tmp_path / "run"
    proc = run_cli("train", "--method", "pemamoe", "--scale", "ci", "--seed", "0", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    for name in ("config.json", "metrics.parquet", "episodes.parquet", "checkpoint.pt"):
        assert (out / name).is_file(), name
    config = mappo.TrainConfig.from_dict(json.loads((out / "config.json").read_text()))
    assert config == mappo.TrainConfig.for_scale("ci", method="pemamoe", seed=0)
    metrics = pd.read_parquet(out / "metrics.parquet")
    assert len(metrics) == config.iterations
    # the summary reports the run's own numbers
    final = metrics.tail(config.phase_length_iters)
    assert re.search(rf"final return\s+{final['episode_return'].mean():.2f}\b", proc.stdout), proc.stdout
    assert re.search(rf"coverage\s+{final['coverage'].mean():.3f}\b", proc.stdout)
    assert re.search(rf"served users\s+{final['served_users'].mean():.2f}\b", proc.stdout)
    assert re.search(r"wall time\s+[\d.]+ s", proc.stdout) and re.search(r"SPS\s+[\d,]+", proc.stdout)
    assert "%|" not in proc.stderr and "it/s" not in proc.stderr  # no progress bar when not a terminal

    # again (in this process, to save an interpreter start): the stored result, nothing recomputed
    assert main(["train", "--method", "pemamoe", "--scale", "ci", "--seed", "0", "--out", str(out)]) == 0
    assert "finished earlier" in capsys.readouterr().out


def test_bad_method_exits_nonzero_naming_the_value_and_the_choices(tmp_path):
    proc = run_cli("train", "--method", "transformer", "--scale", "ci", "--out", str(tmp_path / "run"))
    assert proc.returncode != 0
    assert "'transformer'" in proc.stderr
    assert all(f"'{m}'" in proc.stderr for m in mappo.METHODS), proc.stderr
    assert not (tmp_path / "run").exists()


def test_help_lists_every_command_on_one_line(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    for command in COMMANDS:
        assert re.search(rf"^\s+{command}\s+\S.*$", text, re.M), f"{command} has no one-line help:\n{text}"


# -- flags -> TrainConfig (the trainer is a stub) ----------------------------------------------------
@pytest.fixture
def calls(monkeypatch):
    """Replace mappo.train by a stub that records its arguments and returns a one-row result."""
    seen = []

    def fake_train(config, run_dir=None, resume=True, **kwargs):
        seen.append(SimpleNamespace(config=config, run_dir=run_dir, resume=resume, **kwargs))
        metrics = pd.DataFrame({"env_steps": [64], "episode_return": [1.0], "coverage": [0.5], "served_users": [2.0],
                                "sps": [100.0], "wall_time": [0.1]})
        return SimpleNamespace(config=config, metrics=metrics, from_cache=False, resumed_from=None)

    monkeypatch.setattr(mappo, "train", fake_train)
    return seen


def test_flags_reach_the_config(calls, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", "--method", "pemamoe", "--scale", "ci", "--seed", "3", "--iterations", "4",
                 "--without", "adam_reset", "--without", "lr_drop", "--noise-gamma", "0.02", "--out", str(out)]) == 0
    (call,) = calls
    expected = mappo.TrainConfig.for_scale("ci", method="pemamoe", seed=3, iterations=4,
                                           without=("adam_reset", "lr_drop"), noise_gamma=0.02)
    assert call.config == expected
    assert not call.config.controller.adam_reset and not call.config.controller.lr_drop
    assert call.config.controller.kl_anchor  # the others stay on
    assert call.run_dir == out and call.resume is True and call.progress is None
    assert "final return" in capsys.readouterr().out


def test_defaults_and_no_resume(calls, tmp_path):
    main(["train", "--out", str(tmp_path), "--no-resume", "--method", "mlp"])
    (call,) = calls
    assert call.config == mappo.TrainConfig.for_scale("small", method="mlp", seed=0)
    assert call.resume is False


def test_default_out_is_named_after_the_run(calls, tmp_path, monkeypatch):
    """In the checkout's results/ (the default store, as sweep and figures read it) from any folder."""
    monkeypatch.chdir(tmp_path)
    main(["train", "--scale", "ci"])
    (call,) = calls
    assert call.run_dir == REPO / "results" / "train" / call.config.run_name()


@pytest.mark.skipif("device" not in {f.name for f in dataclasses.fields(mappo.TrainConfig)},
                    reason="TrainConfig has no device field yet")
@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA GPU (without one, --device cuda is refused)")), "auto"])
def test_device_flag_reaches_the_config(calls, tmp_path, device):
    main(["train", "--scale", "ci", "--device", device, "--out", str(tmp_path)])
    assert calls[0].config.device == device


def test_without_device_flag_the_config_default_is_kept(calls, tmp_path):
    main(["train", "--scale", "ci", "--out", str(tmp_path)])
    assert calls[0].config == mappo.TrainConfig.for_scale("ci")


@pytest.mark.parametrize(
    "argv, needles",
    [
        (["--method", "gpt"], ["--method", "'gpt'", *mappo.METHODS]),
        (["--scale", "huge"], ["--scale", "'huge'", *SCALES]),
        (["--iterations", "0"], ["--iterations", "'0'", "in [1, 10000000]"]),
        (["--iterations", "two"], ["--iterations", "'two'"]),
        (["--seed", "-1"], ["--seed", "'-1'", "in [0, 2**63)"]),
        (["--without", "dropout"], ["--without", "'dropout'", *MECHANISMS]),
        (["--noise-gamma", "-0.1"], ["--noise-gamma", "'-0.1'", ">= 0"]),
        (["--device", "tpu"], ["--device", "'tpu'", "cpu", "cuda", "auto"]),
        (["--method", "mlp", "--without", "adam_reset"], ["--method pemamoe", "mlp"]),
    ],
)
def test_bad_input_is_rejected_naming_the_value_and_what_is_allowed(calls, capsys, tmp_path, argv, needles):
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--scale", "ci", "--out", str(tmp_path / "run"), *argv])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    for needle in needles:
        assert needle in err, (needle, err)
    assert not calls


def test_out_holding_another_config_is_refused_unless_no_resume(calls, capsys, tmp_path):
    (tmp_path / "config.json").write_text(json.dumps(mappo.TrainConfig.for_scale("ci", seed=1).to_dict()))
    with pytest.raises(SystemExit):
        main(["train", "--scale", "ci", "--seed", "0", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert "different config" in err and "--no-resume" in err and not calls
    main(["train", "--scale", "ci", "--seed", "0", "--out", str(tmp_path), "--no-resume"])
    assert calls[0].resume is False


# -- the progress bar (train's own keyword) ----------------------------------------------------
def test_train_progress_bar_only_on_request_or_a_terminal(capsys):
    config = mappo.TrainConfig.for_scale("ci", iterations=2)
    mappo.train(config, progress=True)
    err = capsys.readouterr().err
    assert "2/2" in err and "phase=" in err and "sps=" in err
    mappo.train(config)  # progress=None: stderr is not a terminal here
    assert capsys.readouterr().err == ""


# -- the rough edges of issue 28: each a one-line error, never a traceback ----------------------------
def _one_line_error(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert "Traceback" not in err and len(lines) == 1, err
    return lines[0]


def test_an_empty_out_is_refused_and_nothing_is_written(calls, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for argv in (["--out="], ["--out", ""]):
        with pytest.raises(SystemExit) as exit_:
            main(["train", "--scale", "ci", *argv])
        assert exit_.value.code == 2
        assert "--out must name a folder, got an empty string" in capsys.readouterr().err
    assert not calls and list(tmp_path.iterdir()) == []  # no training into the current directory


def test_an_out_that_is_a_file_is_refused(calls, capsys, tmp_path):
    target = tmp_path / "notes.txt"
    target.write_text("mine")
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--scale", "ci", "--out", str(target)])
    assert exit_.value.code == 2 and not calls
    assert f"--out {target} is a file, not a folder" in capsys.readouterr().err
    assert target.read_text() == "mine"


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the machine without a GPU")
def test_device_cuda_without_a_gpu_is_one_line(calls, capsys, tmp_path):
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--scale", "ci", "--device", "cuda", "--out", str(tmp_path / "run")])
    assert exit_.value.code == 2 and not calls
    assert "torch sees no CUDA device" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_a_seed_outside_the_range_is_refused_before_anything_is_written(calls, capsys, tmp_path):
    seed = "12345678901234567890"  # 20 digits: > 2**63
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--scale", "ci", "--seed", seed, "--out", str(tmp_path / "run")])
    assert exit_.value.code == 2 and not calls
    err = capsys.readouterr().err  # refused while the arguments are parsed (finding 41.h)
    assert f"argument --seed: must be an integer in [0, 2**63), got '{seed}'" in err
    assert not (tmp_path / "run").exists()


def test_a_lock_held_by_another_process_is_one_line(tmp_path, capsys):
    out = tmp_path / "run"
    script = textwrap.dedent(f"""
        import time
        from pemamoe.runs import lock_run
        lock = lock_run({str(out)!r})
        print("locked", flush=True)
        time.sleep(120)
    """)
    holder = subprocess.Popen([sys.executable, "-c", script], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        assert main(["train", "--scale", "ci", "--out", str(out)]) == 1
    finally:
        holder.kill()
        holder.wait()
    line = _one_line_error(capsys.readouterr().err)
    assert f"error: run folder {out} is being written by process {holder.pid}" in line


def test_a_bad_run_folder_and_a_failed_write_are_one_line(tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    (out / "done.json").mkdir(parents=True)
    assert main(["train", "--scale", "ci", "--out", str(out)]) == 1
    assert "done.json is a directory, not a file" in _one_line_error(capsys.readouterr().err)

    def full_disk(*args, **kwargs):
        raise OSError(f"cannot write the checkpoint {out / 'checkpoint.pt'}: ...; the disk may be full")

    monkeypatch.setattr(mappo, "train", full_disk)
    assert main(["train", "--scale", "ci", "--out", str(tmp_path / "other")]) == 1
    assert "the disk may be full" in _one_line_error(capsys.readouterr().err)


def test_ctrl_c_during_train_is_one_line_that_says_the_run_resumes(tmp_path):
    import signal
    import time

    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "pemamoe", "train", "--scale", "ci", "--method", "mlp",
                             "--iterations", "100000", "--out", str(out)], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            # a shell's background job starts with SIGINT ignored, and Python then keeps it so
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 240
        while not (out / "checkpoint.pt").exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    line = _one_line_error(err)
    assert "interrupted; the run in" in line and "can be resumed" in line
    assert (out / "checkpoint.pt").is_file() and not (out / "done.json").exists()


def test_an_argument_error_imports_neither_torch_nor_the_trainer():
    code = textwrap.dedent("""
        import sys
        from pemamoe.__main__ import main
        try:
            main(["train", "--seed", "x"])
        except SystemExit as exit_:
            assert exit_.code == 2
        print(sorted(m for m in ("torch", "numba", "pandas", "pemamoe.mappo", "pemamoe.phase_controller")
                     if m in sys.modules))
    """)
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"
    assert "--seed: must be an integer in [0, 2**63), got 'x'" in proc.stderr


def test_train_help_still_lists_the_mechanisms(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--help"])
    assert exit_.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert all(m in text for m in MECHANISMS) and all(m in text for m in mappo.METHODS)


def test_figures_defaults_to_the_scale_make_figures_runs(capsys):
    """`python -m pemamoe figures` and `make figures` regenerate the same committed set."""
    makefile = (Path(__file__).resolve().parents[1] / "Makefile").read_text()
    make_default = re.search(r"^SCALE \?= (\w+)$", makefile, re.M).group(1)
    with pytest.raises(SystemExit):
        main(["figures", "--help"])
    assert make_default == "medium" and f"(default: {make_default}," in " ".join(capsys.readouterr().out.split())


def test_figures_refuses_a_results_url_no_protocol_serves_before_any_notebook(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["figures", "--scale", "ci", "--figures-dir", str(tmp_path), "--results-dir", "nosuch://bucket/runs"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "--results-dir" in err and "'nosuch'" in err and "s3" in err
    assert list(tmp_path.iterdir()) == []  # nothing ran


def test_figures_results_dir_as_a_file_url_is_the_folder_where_the_command_runs(tmp_path, monkeypatch):
    from pemamoe.__main__ import _results_dir

    monkeypatch.chdir(tmp_path)
    assert _results_dir("file://runs") == _results_dir("runs") == str(tmp_path / "runs")
    from pemamoe.core import REPO_ROOT

    # the default is the checkout's store wherever the command runs (core.checkout_store), a URL is itself
    assert _results_dir("results") == str((REPO_ROOT / "results").resolve()) and _results_dir("memory://b/r") == "memory://b/r"
