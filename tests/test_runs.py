"""Run folders (notebook 07b, pemamoe.runs): the writer lock, the verified done marker, checked
checkpoints and configs, errors that name the file, and the parquet reader."""

import json
import os
import shutil
import subprocess
import sys
import textwrap
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from pemamoe.mappo import TrainConfig, load_run, train

ROOT = Path(__file__).resolve().parent.parent


def ci(method="mlp", **kw):
    return TrainConfig.for_scale("ci", method, **kw)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """Folders trained once for the module: a finished run, a run stopped at iteration 4 of 6, and
    a seed-1 run stopped at iteration 2. Tests work on copies."""
    base = tmp_path_factory.mktemp("runs")
    train(ci(), base / "finished")
    train(ci(), base / "partial", max_iterations=4)
    train(ci(seed=1), base / "seed1", max_iterations=2)
    return base


@pytest.fixture
def copy(store, tmp_path):
    def make(name):
        return Path(shutil.copytree(store / name, tmp_path / name))

    return make


# --- the done marker is verified -----------------------------------------------------------------
def test_done_marker_records_hash_iterations_digests_and_threads(copy):
    import hashlib

    d = copy("finished")
    done = json.loads((d / "done.json").read_text())
    cfg = ci()
    assert done["finished"] and done["config_hash"] == cfg.config_hash() and done["iterations"] == cfg.iterations
    for name in ("metrics.parquet", "episodes.parquet"):
        assert done["digests"][name] == hashlib.sha256((d / name).read_bytes()).hexdigest()
    assert done["torch_threads"] == [1]  # recorded in the done marker (and in the checkpoint)
    assert torch.load(d / "checkpoint.pt", weights_only=True)["torch_threads"] == [1]
    assert train(cfg, d).from_cache


def test_done_marker_of_another_run_is_rejected(copy):
    d = copy("finished")
    done = json.loads((d / "done.json").read_text())
    (d / "done.json").write_text(json.dumps({**done, "config_hash": "0123456789ab"}))
    with pytest.raises(ValueError, match=r"done.json belongs to a run with a different config"):
        train(ci(), d)
    with pytest.raises(ValueError, match=r"finished: done.json"):
        load_run(d)


def test_garbage_done_marker_is_rejected(copy):
    d = copy("finished")
    (d / "done.json").write_text("{finished: yes")
    with pytest.raises(ValueError, match=r"done.json is not valid JSON"):
        train(ci(), d)
    (d / "done.json").write_text('{"finished": true}')  # an old-style flag, no digest
    with pytest.raises(ValueError, match=r"done.json has format 1.*cannot be verified"):
        load_run(d)


def test_done_marker_copied_beside_a_stopped_run_is_rejected(copy, store):
    d = copy("partial")  # stopped at iteration 4 of 6
    shutil.copy(store / "finished" / "done.json", d / "done.json")
    with pytest.raises(ValueError, match=r"done.json seals a different metrics.parquet"):
        train(ci(), d)
    with pytest.raises(ValueError, match=r"done.json seals a different metrics.parquet"):
        load_run(d)


def test_logs_changed_after_the_seal_are_rejected(copy):
    from pemamoe.analysis import load_runs

    d = copy("finished")
    m = pd.read_parquet(d / "metrics.parquet")
    m.loc[0, "approx_kl"] += 1.0
    m.to_parquet(d / "metrics.parquet", index=False)
    with pytest.raises(ValueError, match=r"seals a different metrics.parquet"):
        load_runs([d])


# --- a checkpoint is resumed only by its own run ---------------------------------------------------
@pytest.mark.parametrize("keep_config_json", [True, False])
def test_foreign_checkpoint_is_refused(copy, keep_config_json):
    d = copy("partial")
    shutil.copy(copy("seed1") / "checkpoint.pt", d / "checkpoint.pt")
    if not keep_config_json:
        (d / "config.json").unlink()
    with pytest.raises(ValueError, match=r"partial: checkpoint.pt holds a run with a different config "
                                         r"\(seed: stored 1, requested 0\)"):
        train(ci(), d)


def test_other_config_in_config_json_names_the_keys(copy):
    d = copy("partial")
    with pytest.raises(ValueError, match=r"config.json holds a run with a different config \(.*lr: stored 0.0003"):
        train(ci(lr=1e-3), d)


# --- unreadable files are named -------------------------------------------------------------------
def test_empty_and_torn_checkpoints_are_named(copy):
    d = copy("partial")
    (d / "checkpoint.pt").write_bytes(b"")
    with pytest.raises(ValueError, match=r"partial: checkpoint.pt is empty \(0 bytes\)"):
        train(ci(), d)
    good = copy("seed1") / "checkpoint.pt"
    (d / "checkpoint.pt").write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ValueError, match=r"checkpoint.pt cannot be read as a checkpoint"):
        train(ci(), d)


def test_garbage_config_json_is_named(copy):
    d = copy("partial")
    (d / "config.json").write_text("{\"method\": ")
    with pytest.raises(ValueError, match=r"partial: config.json is not valid JSON"):
        train(ci(), d)
    with pytest.raises(ValueError, match=r"config.json is not valid JSON"):
        load_run(d)
    (d / "config.json").write_text('{"method": "mlp", "bogus": 1}')
    with pytest.raises(ValueError, match=r"config.json does not hold a valid TrainConfig"):
        load_run(d)


def test_truncated_parquet_is_named(copy):
    d = copy("partial")  # no done marker: the logs are read as they are
    data = (d / "metrics.parquet").read_bytes()
    (d / "metrics.parquet").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"partial: metrics.parquet cannot be read as parquet"):
        load_run(d)


# --- arguments --------------------------------------------------------------------------------
def test_bad_train_arguments_are_rejected(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match="run_dir must be a non-empty folder path"):
        train(ci(), "")
    assert list(tmp_path.iterdir()) == []  # nothing written into the current folder
    with pytest.raises(ValueError, match=r"threads must be an int >= 1 or None, got 2.5"):
        train(ci(), tmp_path / "a", threads=2.5)
    with pytest.raises(ValueError, match=r"max_iterations must be an int >= 1 or None, got -3"):
        train(ci(), tmp_path / "b", max_iterations=-3)


def test_numpy_seed_saves(tmp_path):
    cfg = TrainConfig.for_scale("ci", seed=np.int64(1))
    res = train(cfg, tmp_path, max_iterations=1)  # failed: "Object of type int64 is not JSON serializable"
    assert not res.finished and json.loads((tmp_path / "config.json").read_text())["seed"] == 1
    assert type(cfg.seed) is int and cfg == TrainConfig.for_scale("ci", seed=1)


# --- the lock -------------------------------------------------------------------------------------
def test_lock_names_the_holder_and_is_per_folder(tmp_path):
    from pemamoe.runs import RunLockedError, holder_pid, lock_run

    (tmp_path / "a").mkdir()
    (tmp_path / "a" / ".metrics.parquet.x1.tmp").write_bytes(b"torn")
    (tmp_path / "a" / "keep.txt").write_text("not a temporary file")
    locks = [lock_run(tmp_path / name) for name in ("a", "b", "c")]  # one process, many folders
    assert all(lock.held for lock in locks)
    assert not list((tmp_path / "a").glob(".*.tmp")) and (tmp_path / "a" / "keep.txt").exists()
    assert holder_pid(tmp_path / "a") == os.getpid()
    with pytest.raises(RunLockedError, match=rf"being written by process {os.getpid()} \(this process"):
        lock_run(tmp_path / "a")
    with pytest.raises(RunLockedError, match=rf"process {os.getpid()}"):
        train(ci(), tmp_path / "a")
    locks[0].release()
    assert holder_pid(tmp_path / "a") is None
    with lock_run(tmp_path / "a"):
        pass
    for lock in locks[1:]:
        lock.release()


def test_lock_of_a_killed_process_is_free_and_other_processes_are_refused(tmp_path):
    from pemamoe.runs import RunLockedError, lock_run

    script = textwrap.dedent(f"""
        import sys, time
        from pemamoe.runs import lock_run
        lock = lock_run({str(tmp_path)!r})
        print("locked", flush=True)
        time.sleep(120)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "locked"
        with pytest.raises(RunLockedError, match=rf"being written by process {proc.pid};"):
            lock_run(tmp_path)
    finally:
        proc.kill()
        proc.wait()
    with lock_run(tmp_path):  # the OS dropped the dead holder's lock
        assert (tmp_path / ".lock").read_text().strip() == str(os.getpid())


# --- reading results in a script that imports torch --------------------------------------------
def test_a_torch_script_reading_results_exits_cleanly(store):
    """pandas.read_parquet after `import torch` aborted at exit (status 134) in ~15 % of runs."""
    script = textwrap.dedent(f"""
        import torch
        from pemamoe.runs import read_parquet
        folder = {str(store / 'finished')!r}
        assert len(read_parquet(folder + "/metrics.parquet")) == 6
        read_parquet(folder + "/episodes.parquet")
    """)

    def once(_):
        run = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300)
        return run.returncode, run.stderr[-500:]

    # 20 runs catch a 15 % abort with probability 1 - 0.85**20 = 96 % (30 runs: 99 %, at half
    # again the cost of the suite's slowest test)
    with ThreadPoolExecutor(max_workers=4) as pool:  # more only thrashes 2 cores
        results = list(pool.map(once, range(20)))
    failures = [r for r in results if r[0] != 0]
    assert not failures, f"{len(failures)} of 20 exited non-zero, e.g. {failures[0]}"


def test_appendix_notebook_runs(capsys):
    """07b is not a figure notebook (figure_notebooks() lists NN_*.py only): run it as a script here."""
    import runpy

    runpy.run_path(str(ROOT / "notebooks" / "07b_run_folders.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "(this process: one folder per run)" in out and "checkpoint.pt is empty (0 bytes)" in out
