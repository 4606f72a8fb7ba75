"""Chaos: kill training and sweeps at random moments (SIGKILL, SIGTERM), write one folder from two
processes, corrupt and swap run files; then every finished run must equal an uninterrupted
reference run bit for bit, and no process may be left running.

The random choices come from CHAOS_SEED (default: a fresh one, printed on failure)."""

import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import psutil
import pytest
import torch

from pemamoe.bookkeeping import _unpack_rows
from pemamoe.mappo import TIMING_COLUMNS, train
from pemamoe.runs import RunLockedError, holder_pid, load_checkpoint, read_parquet, verify_done
from pemamoe.experiments import RunSpec, run_sweep

ROOT = Path(__file__).resolve().parent.parent
SPECS = [RunSpec("mlp", 0, "ci"), RunSpec("mlp", 1, "ci")]

TRAIN_SCRIPT = """
import sys
from pemamoe.experiments import RunSpec
from pemamoe.mappo import train
train(RunSpec("mlp", 0, "ci").to_config(), sys.argv[1], verbose=True)
"""


def _wait_for(predicate, timeout, what):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _tensors(obj, prefix=""):
    """Every tensor of a nested checkpoint, by path."""
    if isinstance(obj, torch.Tensor):
        yield prefix, obj
    elif isinstance(obj, dict):
        for k, v in obj.items():
            if k not in ("metrics_rows", "episode_rows"):  # log rows: chunked as checkpoints fell, compared as rows
                yield from _tensors(v, f"{prefix}/{k}")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _tensors(v, f"{prefix}/{i}")


def assert_same_run(folder: Path, reference: Path):
    assert verify_done(folder) is not None, f"{folder} is not finished"
    drop = lambda df: df.drop(columns=[c for c in TIMING_COLUMNS if c in df.columns])  # noqa: E731
    pd.testing.assert_frame_equal(drop(read_parquet(folder / "metrics.parquet")),
                                  drop(read_parquet(reference / "metrics.parquet")))
    pd.testing.assert_frame_equal(read_parquet(folder / "episodes.parquet"), read_parquet(reference / "episodes.parquet"))
    got_ck, want_ck = load_checkpoint(folder / "checkpoint.pt"), load_checkpoint(reference / "checkpoint.pt")
    for key in ("metrics_rows", "episode_rows"):
        pd.testing.assert_frame_equal(drop(pd.DataFrame(_unpack_rows(got_ck[key]))),
                                      drop(pd.DataFrame(_unpack_rows(want_ck[key]))))
    got, want = dict(_tensors(got_ck)), dict(_tensors(want_ck))
    assert got.keys() == want.keys() and len(want) > 10
    for name, tensor in want.items():
        assert torch.equal(got[name], tensor), f"{folder.name}: checkpoint tensor {name} differs"


def _cmdline(proc) -> list:
    try:
        return proc.cmdline()
    except psutil.Error:
        return []


def _tree(pid: int) -> list:
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def test_kills_two_writers_and_corrupt_files(tmp_path):
    seed = int(os.environ.get("CHAOS_SEED", random.SystemRandom().randrange(10**6)))
    rng = random.Random(seed)
    note = f"(CHAOS_SEED={seed})"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    references = {spec: spec.run_dir(tmp_path / "reference") for spec in SPECS}
    for spec, folder in references.items():
        train(spec.to_config(), folder)  # uninterrupted, in this process
    watched = []  # every process started below, with its descendants

    # --- 1. a training process, killed at a random iteration; a second writer meanwhile ------------
    # (it has no handler: SIGTERM and SIGKILL both end it at once, so one of them, at random)
    folder = SPECS[0].run_dir(tmp_path / "train")
    for sig in [rng.choice([signal.SIGKILL, signal.SIGTERM])]:
        proc = subprocess.Popen([sys.executable, "-c", TRAIN_SCRIPT, str(folder)], cwd=ROOT, env=env,
                                stdout=subprocess.PIPE, text=True)
        watched.append(psutil.Process(proc.pid))
        line = proc.stdout.readline()  # "it N ..." after each iteration it runs
        if line.startswith("it "):
            start = time.monotonic()
            with pytest.raises(RunLockedError, match=rf"being written by process {proc.pid}"):
                train(SPECS[0].to_config(), folder)  # the second writer fails at once, naming the first
            assert time.monotonic() - start < 5, note
            time.sleep(rng.uniform(0, 0.5))
            proc.send_signal(sig)
        proc.stdout.read()
        rc = proc.wait(timeout=120)
        assert rc in (-sig, 0), f"training exited {rc} after {sig!r} {note}"
    train(SPECS[0].to_config(), folder)  # the next attempt finishes the run
    assert_same_run(folder, references[SPECS[0]])

    # --- 2. a 2-worker sweep, killed by SIGKILL and by SIGTERM (random order and moment) ----------
    results = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "pemamoe", "sweep", "--scale", "ci", "--methods", "mlp", "--seeds", "0", "1",
           "--workers", "2", "--results-dir", str(results), "--records-dir", str(tmp_path / "records"),
           "--no-progress"]
    for sig in rng.sample([signal.SIGKILL, signal.SIGTERM], 2):
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        watched.append(psutil.Process(proc.pid))
        # until a worker holds a run's lock (it is training), then a random moment later
        _wait_for(lambda: any(holder_pid(s.run_dir(results)) in {p.pid for p in _tree(proc.pid)} for s in SPECS)
                  or proc.poll() is not None, 240, "a sweep worker to start training")
        time.sleep(rng.uniform(0, 2))
        tree = _tree(proc.pid)
        watched.extend(tree)
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=60)
        assert proc.returncode in (-sig, 128 + sig, 0), f"sweep exited {proc.returncode} after {sig!r} {note}\n{out}"
        gone, alive = psutil.wait_procs(tree, timeout=15)  # workers die with the sweep, whatever killed it
        assert not alive, f"left running after {sig!r}: {alive} {note}"
    folders = run_sweep(SPECS, "local", workers=1, results_dir=results, verbose=False)  # resumes both
    for spec, folder in zip(SPECS, folders):
        assert_same_run(folder, references[spec])

    # --- 3. foreign and corrupt files are refused, naming the file -------------------------------
    mine, other = folders
    shutil.copy(other / "done.json", mine / "done.json")  # another run's seal
    with pytest.raises(ValueError, match=rf"{mine.name}: done.json belongs to a run with a different config"):
        run_sweep(SPECS, "local", workers=1, results_dir=results, verbose=False)
    (mine / "done.json").unlink()
    shutil.copy(other / "checkpoint.pt", mine / "checkpoint.pt")  # another run's checkpoint
    with pytest.raises(ValueError, match=rf"{mine.name}: checkpoint.pt holds a run with a different config \(seed"):
        train(SPECS[0].to_config(), mine)
    (mine / "checkpoint.pt").write_bytes((other / "checkpoint.pt").read_bytes()[:1000])
    with pytest.raises(ValueError, match=rf"{mine.name}: checkpoint.pt is truncated or damaged"):
        train(SPECS[0].to_config(), mine)

    # --- 4. nothing is left running ---------------------------------------------------------------
    ours = [p for p in _tree(os.getpid()) if "resource_tracker" not in " ".join(_cmdline(p))]  # tracker: a singleton
    gone, alive = psutil.wait_procs(watched + ours, timeout=15)
    assert not alive, f"left running: {alive} {note}"
