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
from pemamoe.runs import training_processor

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
    here = [training_processor()]  # and where: float kernels differ between processor families
    assert done["processors"] == here == torch.load(d / "checkpoint.pt", weights_only=True)["processors"]
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
    from pemamoe.records import write_record

    d = copy("finished")
    m = pd.read_parquet(d / "metrics.parquet")
    m.loc[0, "approx_kl"] += 1.0
    m.to_parquet(d / "metrics.parquet", index=False)
    with pytest.raises(ValueError, match=r"seals a different metrics.parquet"):
        write_record(d, "ci", d.parent / "records")  # a record is made only from a verified folder


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
    assert (d / "config.json").exists() == keep_config_json  # refused before the requested config was written


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
    with pytest.raises(ValueError, match=r"partial: checkpoint.pt is truncated or damaged: its [\d,]+ bytes are not a whole checkpoint"):
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

    runpy.run_path(str(ROOT / "notebooks" / "07b_runs.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "(this process: one folder per run)" in out and "checkpoint.pt is empty (0 bytes)" in out


# --- errors cross process boundaries (issue 28) -------------------------------------------------
def _error_samples():
    """Every exception class defined in the package, with constructor arguments for one instance."""
    import importlib
    import inspect
    import signal

    samples = {"RunFolderError": (ROOT / "results" / "run" / "done.json", "is broken", "a hint"),
               "RunLockedError": (ROOT / "results" / "run", 4321),
               "ExportError": ("notebooks/x.py: unknown directive",),
               "NoNotebooksError": ("no notebooks/ beside the package at /site-packages",),
               "NotACheckoutError": ("/site-packages is not a pemamoe checkout",),
               "FiguresDirError": ("figures folder /x is a file, not a folder",),
               "PluginError": ("PEMAMOE_PLUGINS names the module 'x', which cannot be imported",),
               "SweepInterrupted": (signal.SIGTERM,),
               "RecordError": (ROOT / "records" / "ci" / "run.json", "differs from the file it sealed"),
               "TheoryRecordError": (ROOT / "records" / "medium" / "theory" / "noise.json", "a table's sha256 differs"),
               "StoreLeaseError": ("bucket/results/ci/run/.lease.json", {"host": "node-2", "pid": 77, "heartbeat": 0.0}),
               "StoreAccessError": ("s3://no-such-bucket/results", "bucket 'no-such-bucket' does not exist"),
               "SweepRunError": ("mlp, seed 0", "run folder results/ci/run is being written by process 4321", 2)}
    found = []
    for path in sorted((ROOT / "pemamoe").glob("*.py")):
        if path.stem == "__main__":
            continue
        module = importlib.import_module(f"pemamoe.{path.stem}" if path.stem != "__init__" else "pemamoe")
        for name, cls in vars(module).items():
            if inspect.isclass(cls) and issubclass(cls, BaseException) and cls.__module__ == module.__name__:
                found.append(pytest.param(cls, samples.get(name), id=name))
    return found


@pytest.mark.parametrize("cls, args", _error_samples())
def test_every_exception_of_the_package_survives_pickle(cls, args):
    import pickle

    assert args is not None, f"add constructor arguments for {cls.__name__} to _error_samples"
    err = cls(*args)
    again = pickle.loads(pickle.dumps(err))
    assert type(again) is cls and str(again) == str(err) and again.args == err.args
    assert vars(again) == vars(err)


def _raise_run_folder_error(path):
    from pemamoe.runs import RunFolderError

    raise RunFolderError(path, "is damaged")


def test_a_run_folder_error_in_a_process_pool_reaches_the_parent_as_itself(tmp_path):
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from pemamoe.runs import RunFolderError

    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork")) as pool:
        error = pool.submit(_raise_run_folder_error, tmp_path / "checkpoint.pt").exception(timeout=60)
    assert type(error) is RunFolderError and error.path == tmp_path / "checkpoint.pt"  # not BrokenProcessPool


# --- the checkpoint's seal and numerics version (issue 28) ---------------------------------------
def _rewrite(ck, path, seal=True):
    """Save a changed checkpoint as the trainer would (sealed), or as an older trainer did."""
    from pemamoe.runs import seal_checkpoint

    torch.save(ck, path)
    if seal:
        seal_checkpoint(path)


def test_checkpoints_are_format_5_sealed_and_stamped_with_the_numerics_version(copy):
    import zipfile

    from pemamoe.bookkeeping import CHECKPOINT_FORMAT
    from pemamoe.train_config import TRAINING_NUMERICS

    path = copy("partial") / "checkpoint.pt"
    ck = torch.load(path, weights_only=True)
    assert ck["format"] == CHECKPOINT_FORMAT == 5 and ck["numerics"] == TRAINING_NUMERICS
    assert zipfile.ZipFile(path).comment.startswith(b"pemamoe-sha256:")


@pytest.mark.parametrize("name", ["partial", "finished"])
def test_flipped_bytes_in_the_actor_weights_are_refused(copy, name):
    from pemamoe.runs import load_checkpoint

    d = copy(name)
    path = d / "checkpoint.pt"
    ck = torch.load(path, weights_only=True)
    key, weight = max(ck["actor"].items(), key=lambda kv: kv[1].numel())
    data = bytearray(path.read_bytes())
    at = data.find(weight.contiguous().numpy().tobytes())
    assert at > 0 and weight.numel() * weight.element_size() >= 96
    for i in range(at + 64, at + 80):  # 16 bytes inside the weights
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))
    damaged = torch.load(path, weights_only=True)  # the zip still reads: torch checks no CRC
    assert not torch.equal(damaged["actor"][key], weight)
    with pytest.raises(ValueError, match=rf"{name}: checkpoint.pt fails its content check"):
        train(ci(), d)
    with pytest.raises(ValueError, match=r"checkpoint.pt fails its content check"):
        load_checkpoint(path)
    if name == "partial":
        assert not (d / "done.json").exists()  # nothing was resumed, nothing sealed


def test_an_unsealed_checkpoint_is_read_only_in_the_formats_before_the_seal(copy, store):
    from pemamoe.train_config import TRAINING_NUMERICS

    d = copy("partial")
    path = d / "checkpoint.pt"
    ck = torch.load(path, weights_only=True)
    _rewrite(ck, path, seal=False)  # format 5 without its seal: rewritten by hand
    with pytest.raises(ValueError, match=r"checkpoint.pt has format 5 but no content seal"):
        train(ci(), d)
    _rewrite({**ck, "format": 4, "numerics": TRAINING_NUMERICS}, path, seal=False)  # as format 4 was written
    resumed = train(ci(), d)
    assert resumed.resumed_from == 4 and resumed.finished
    assert (d / "episodes.parquet").read_bytes() == (store / "finished" / "episodes.parquet").read_bytes()


@pytest.mark.parametrize("stored", ["absent", "other"])
def test_a_checkpoint_of_another_numerics_version_is_refused(copy, stored):
    from pemamoe.train_config import TRAINING_NUMERICS

    d = copy("partial")
    path = d / "checkpoint.pt"
    ck = torch.load(path, weights_only=True)
    if stored == "absent":  # written before checkpoints recorded it: version 1
        del ck["numerics"]
        version = 1
    else:
        version = ck["numerics"] = TRAINING_NUMERICS + 1
    _rewrite(ck, path)
    if version == TRAINING_NUMERICS:
        assert train(ci(), d).resumed_from == 4
        return
    with pytest.raises(ValueError, match=rf"partial: checkpoint.pt was computed under training numerics version "
                                         rf"{version}, but this code computes version {TRAINING_NUMERICS}"):
        train(ci(), d)  # run_dir given explicitly, config.json matching
    assert not (d / "done.json").exists()


# --- done.json seals whole runs only (issue 28) ---------------------------------------------------
def test_a_partial_run_cannot_be_sealed_nor_pass_for_finished(copy):
    from pemamoe.records import write_record
    from pemamoe.runs import LOG_FILES, file_digest, verify_done, write_done

    d = copy("partial")  # 4 of 6 iterations
    with pytest.raises(ValueError, match=r"partial: done.json cannot seal this run: metrics.parquet holds 4 rows, "
                                         r"the config asks for 6 iterations"):
        write_done(d, ci())
    assert not (d / "done.json").exists()
    # the marker write_done wrote before it checked: right hash, iterations and digests
    marker = {"format": 2, "finished": True, "config_hash": ci().config_hash(), "iterations": 6,
              "digests": {name: file_digest(d / name) for name in LOG_FILES}}
    (d / "done.json").write_text(json.dumps(marker))
    for read in (verify_done, load_run, lambda d: write_record(d, "ci", d.parent / "records"), lambda d: train(ci(), d)):
        with pytest.raises(ValueError, match=r"done.json seals a metrics.parquet of 4 rows, but the run has 6 "
                                             r"iterations"):
            read(d)


# --- a directory where a file should be (issue 28) ------------------------------------------------
def test_a_directory_in_place_of_a_run_file_is_named(copy):
    d = copy("finished")
    (d / "done.json").unlink()
    (d / "done.json").mkdir()
    with pytest.raises(ValueError, match=r"finished: done.json is a directory, not a file"):
        train(ci(), d)
    with pytest.raises(ValueError, match=r"finished: done.json is a directory, not a file"):
        load_run(d)
    d = copy("partial")
    (d / "checkpoint.pt").unlink()
    (d / "checkpoint.pt").mkdir()
    with pytest.raises(ValueError, match=r"partial: checkpoint.pt is a directory, not a file"):
        train(ci(), d)
    with pytest.raises(ValueError, match=r"partial: checkpoint.pt is a directory, not a file; remove it by hand"):
        train(ci(), d, resume=False)


# --- a failed checkpoint write (issue 28) ----------------------------------------------------------
def test_a_full_disk_names_the_checkpoint_and_says_the_disk_may_be_full(tmp_path, monkeypatch):
    import re

    import pemamoe.bookkeeping as bookkeeping

    def full_disk(obj, f, *args, **kwargs):  # what torch.save raised when the disk filled up
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 8823616 vs 8823510")

    monkeypatch.setattr(bookkeeping.torch, "save", full_disk)
    run = tmp_path / "run"
    with pytest.raises(OSError, match=rf"cannot write the checkpoint {re.escape(str(run / 'checkpoint.pt'))}: "
                                      r".*inline_container.*the disk may be full \(no space left on device"):
        train(ci(iterations=2, checkpoint_every=1), run)
    assert not (run / "checkpoint.pt").exists() and not list(run.glob(".*.tmp"))
