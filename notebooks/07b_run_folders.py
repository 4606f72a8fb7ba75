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
# # 07b · Appendix: run folders you can trust
#
# Every training run of notebook 07 lives in one folder (`config.json`, `metrics.parquet`,
# `episodes.parquet`, `checkpoint.pt`, `done.json`), and every figure of notebooks 09 and 10 is
# drawn from such folders. This appendix holds the rules that make a folder trustworthy, in one
# small module, `pemamoe.runs`, that a trainer calls once per run (or once per member of a
# population trained in one process):
#
# 1. **One writer.** `lock_run(run_dir)` takes an operating-system lock (`fcntl.flock` on
#    `run_dir/.lock`) for the life of the run and writes the holder's PID into the file. A second
#    writer fails at once, naming that PID. The kernel drops the lock when the holder dies, however
#    it dies (SIGKILL included), so a lock is never stale; readers never take it. Leftover
#    `.*.tmp` files of interrupted atomic writes are removed when the lock is taken (nobody else
#    can be writing then). One process may hold the locks of many folders at once.
# 2. **A checkpoint is resumed only by the run that wrote it.** It stores its `config`; before
#    resuming, `load_checkpoint(path, config)` compares `TrainConfig.identity()` of the stored and
#    the requested config (whether or not `config.json` is still there) and refuses, naming the
#    folder, the file and the keys that differ.
# 3. **`done.json` is a seal, not a flag.** `write_done` records the config hash, the number of
#    iterations, the torch thread counts and the sha256 of the final logs. `verify_done` checks all
#    of them before a run counts as finished (`train(resume=True)`, `load_run`, the sweep's "already
#    done" test, `analysis.load_runs`). A marker from another run, a garbage marker, or logs changed
#    after the seal (e.g. a marker copied beside a run stopped half-way) raise `RunFolderError`.
#    We never guess which file is right.
# 4. **Unreadable files are named.** A 0-byte or truncated checkpoint, a garbage `config.json`, a
#    truncated parquet file: each raises `RunFolderError` with the folder, the file and the cause
#    (instead of a bare `EOFError`, `JSONDecodeError` or `ArrowInvalid`).
#
# Results are read with `read_parquet` (pyarrow's `read_table(...).to_pandas()`, single-threaded):
# a script that imports torch and then reads a run with `pandas.read_parquet` sometimes aborted at
# exit ("terminate called without an active exception", exit status 134).

# %%
#| default_exp runs

# %% tags=["parameters"]
scale = "small"  # `make figures` passes these to every notebook; this one draws no figure
figures_dir = "paper_figures"

# %%
#| export
import fcntl
import hashlib
import json
import os
from pathlib import Path

from pemamoe.core import atomic_write_json

RUN_FILES = ("config.json", "metrics.parquet", "episodes.parquet", "checkpoint.pt", "done.json")
LOG_FILES = ("metrics.parquet", "episodes.parquet")  # sealed by their sha256 in done.json
DONE_FORMAT = 2  # done.json layout; format 1 (no digests) cannot be verified
LOCK_NAME = ".lock"
_START_OVER = "delete the folder, or train with resume=False to start it over"


class RunFolderError(ValueError):
    """A file of a run folder cannot be used as it is. The message names the folder, the file and
    what is wrong; `path` is the file."""

    def __init__(self, path, problem: str, hint: str = _START_OVER):
        self.path = Path(path)
        super().__init__(f"run folder {self.path.parent}: {self.path.name} {problem}" + (f"; {hint}" if hint else ""))


class RunLockedError(RuntimeError):
    """Another live process (its PID in `pid`, None when unknown) is writing this run folder."""

    def __init__(self, run_dir, pid):
        self.run_dir, self.pid = Path(run_dir), pid
        who = f"process {pid}" if pid is not None else "another process (PID not yet written)"
        own = " (this process: one folder per run)" if pid == os.getpid() else ""
        super().__init__(f"run folder {self.run_dir} is being written by {who}{own}; "
                         f"wait for it to finish or stop it (the lock is {self.run_dir / LOCK_NAME})")


def check_run_dir(run_dir) -> Path:
    """`run_dir` as a Path; rejects "" (which would mean the current directory) and non-paths."""
    if not isinstance(run_dir, (str, os.PathLike)) or str(run_dir).strip() == "":
        raise ValueError(f"run_dir must be a non-empty folder path (or None for no folder), got {run_dir!r}")
    return Path(run_dir)


# %% [markdown]
# ## Reading the files, with errors that name them

# %%
#| export
def read_json(path) -> dict:
    """A JSON object from `path`; RunFolderError (naming the file) when missing, empty or garbage."""
    path = Path(path)
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RunFolderError(path, "is missing") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise RunFolderError(path, f"is not valid JSON ({err})") from None
    if not isinstance(obj, dict):
        raise RunFolderError(path, f"holds a JSON {type(obj).__name__}, not an object")
    return obj


def read_parquet(path):
    """A parquet file as a pandas DataFrame, read by pyarrow without its thread pool.

    Use this (not `pandas.read_parquet`) for run logs: see the introduction."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    if not path.is_file():
        raise RunFolderError(path, "is missing")
    try:
        return pq.read_table(path, use_threads=False).to_pandas(use_threads=False)
    except (pa.ArrowException, OSError) as err:
        raise RunFolderError(path, f"cannot be read as parquet ({type(err).__name__}: {err})") from None


def read_config(path, cls=None):
    """The TrainConfig stored in `path` (a config.json); RunFolderError when it is not one."""
    if cls is None:
        from pemamoe.mappo import TrainConfig as cls  # runs.py sits below mappo.py
    path = Path(path)
    return _config_from_dict(read_json(path), cls, path)


def load_checkpoint(path, config=None, iteration: int | None = None) -> dict:
    """`torch.load(path, weights_only=True)`, checked: a readable dict with a `config` and an
    `iteration`; with `config`, the stored config must have the same identity (see
    `check_stored_config`) and at most `config.iterations` iterations; with `iteration`, exactly
    that many."""
    import pickle
    import zipfile

    import torch

    path = Path(path)
    if not path.is_file():
        raise RunFolderError(path, "is missing")
    if path.stat().st_size == 0:
        raise RunFolderError(path, "is empty (0 bytes)")
    try:
        ck = torch.load(path, weights_only=True)
    except (EOFError, RuntimeError, pickle.UnpicklingError, zipfile.BadZipFile, OSError, ValueError) as err:
        raise RunFolderError(path, f"cannot be read as a checkpoint ({type(err).__name__}: {err})") from None
    if not isinstance(ck, dict) or not isinstance(ck.get("config"), dict) or "iteration" not in ck:
        raise RunFolderError(path, "is not a training checkpoint (no 'config' and 'iteration')")
    if config is not None:
        check_stored_config(ck["config"], config, path)
        if not 0 <= int(ck["iteration"]) <= config.iterations:
            raise RunFolderError(path, f"is at iteration {ck['iteration']}, outside 0..{config.iterations}")
    if iteration is not None and int(ck["iteration"]) != iteration:
        raise RunFolderError(path, f"is at iteration {ck['iteration']}, but the run finished at {iteration}")
    return ck


# %% [markdown]
# ## Same run or not: the config's identity
#
# `TrainConfig.identity()` is what determines the computation (appendix 07c); two configs with the
# same identity give the same run. A stored config is compared by identity, and a mismatch lists
# the differing keys with both values, e.g. `seed: stored 1, requested 0`.

# %%
#| export
def config_difference(stored: dict, requested: dict, limit: int = 6) -> str:
    """The keys where two identity dicts differ, as `key: stored X, requested Y` (nested keys
    dotted, at most `limit` of them); "" when equal."""
    diffs = []

    def walk(a, b, prefix):
        for key in sorted(set(a) | set(b), key=str):
            name = f"{prefix}{key}"
            if isinstance(a.get(key), dict) and isinstance(b.get(key), dict):
                walk(a[key], b[key], name + ".")
            elif key not in a or key not in b or a[key] != b[key]:
                diffs.append(f"{name}: stored {_short(a.get(key, '<absent>'))}, "
                             f"requested {_short(b.get(key, '<absent>'))}")

    walk(stored, requested, "")
    more = f" (and {len(diffs) - limit} more)" if len(diffs) > limit else ""
    return "; ".join(diffs[:limit]) + more


def check_stored_config(stored: dict, config, path) -> None:
    """Raise RunFolderError naming `path` unless the config dict `stored` (as written by
    `config.to_dict()`) has the same identity as `config`."""
    path = Path(path)
    other = _config_from_dict(stored, type(config), path)
    diff = config_difference(other.identity(), config.identity())
    if diff:
        raise RunFolderError(path, f"holds a run with a different config ({diff})",
                             "use another run_dir, or resume=False to overwrite it")


# %%
#| exporti
def _short(value, width: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= width else text[:width - 3] + "..."


def _config_from_dict(d, cls, path):
    try:
        return cls.from_dict(d)
    except (TypeError, ValueError, KeyError, AttributeError) as err:
        raise RunFolderError(path, f"does not hold a valid {cls.__name__} ({type(err).__name__}: {err})") from None


# %% [markdown]
# ## The done marker
#
# `write_done` is the last write of a run. `verify_done` returns the marker of a finished run,
# `None` when there is no marker (the run is not finished), and raises otherwise.

# %%
#| export
def file_digest(path) -> str:
    """sha256 of a file's bytes, as hex."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_done(run_dir, config, **record) -> dict:
    """Seal a finished run: write done.json with the config hash, the number of iterations and the
    sha256 of each log file, plus `record` (e.g. env_steps, torch_threads, wall_time_s)."""
    run_dir = Path(run_dir)
    marker = {**record, "format": DONE_FORMAT, "finished": True, "config_hash": config.config_hash(),
              "iterations": int(config.iterations),
              "digests": {name: file_digest(run_dir / name) for name in LOG_FILES}}
    atomic_write_json(run_dir / "done.json", marker)
    return marker


def verify_done(run_dir, config=None) -> dict | None:
    """The done marker of a finished run, after checking it; None when there is none.

    config: the requested TrainConfig (None: the one in config.json). Raises RunFolderError
    naming the file when the marker is garbage, from an older format, from another config, for
    another number of iterations, or when a log file differs from the one that was sealed."""
    run_dir = Path(run_dir)
    path = run_dir / "done.json"
    if not path.exists():
        return None
    marker = read_json(path)
    if config is None:
        config = read_config(run_dir / "config.json")
    elif (run_dir / "config.json").exists():  # names the keys that differ, if the folder is another run
        check_stored_config(read_json(run_dir / "config.json"), config, run_dir / "config.json")
    if marker.get("format") != DONE_FORMAT or not isinstance(marker.get("digests"), dict):
        raise RunFolderError(path, f"has format {marker.get('format', 1)!r}, not {DONE_FORMAT}: it records no "
                             "content digest, so the run cannot be verified")
    if marker.get("finished") is not True:
        raise RunFolderError(path, "does not say finished: true")
    if marker.get("config_hash") != config.config_hash():
        raise RunFolderError(path, f"belongs to a run with a different config: config hash {marker.get('config_hash')!r}, "
                             f"the requested config has {config.config_hash()!r}")
    if marker.get("iterations") != config.iterations:
        raise RunFolderError(path, f"records {marker.get('iterations')!r} iterations, the config asks for "
                             f"{config.iterations}")
    for name in LOG_FILES:
        log = run_dir / name
        if not log.is_file():
            raise RunFolderError(path, f"seals {name}, which is missing")
        if marker["digests"].get(name) != file_digest(log):
            raise RunFolderError(path, f"seals a different {name} (sha256 {str(marker['digests'].get(name))[:12]}... "
                                 f"recorded, {file_digest(log)[:12]}... on disk): the logs changed after the "
                                 "run finished, or the marker was copied from elsewhere")
    return marker


def prepare_run_dir(run_dir, config, resume: bool) -> None:
    """Before a run writes: with resume, check that config.json (if any) holds the same run; without,
    remove the previous run's marker, checkpoint and logs. Then (re)write config.json. Call it
    with the folder's lock held."""
    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.json"
    if resume and cfg_path.exists():
        check_stored_config(read_json(cfg_path), config, cfg_path)
        return
    if not resume:
        for name in ("done.json", "checkpoint.pt", *LOG_FILES):  # the marker first: never a seal on new files
            (run_dir / name).unlink(missing_ok=True)
    atomic_write_json(cfg_path, config.to_dict())


# %% [markdown]
# ## The lock
#
# `flock` locks belong to an open file description: the kernel releases them when the last
# descriptor closes, which includes the death of the process. Two `lock_run` calls on one folder
# conflict even inside one process (each opens the file anew), so a population trainer that
# mistakenly gives two members one folder fails too. The descriptor is not inherited by child
# processes (Python opens files non-inheritable), so a subprocess never keeps a dead run's lock.

# %%
#| export
class RunLock:
    """The exclusive writer lock of one run folder (a context manager; see `lock_run`)."""

    def __init__(self, run_dir):
        self.run_dir = check_run_dir(run_dir)
        self.path = self.run_dir / LOCK_NAME
        self._fd = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> "RunLock":
        if self._fd is not None:
            return self
        self.run_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise RunLockedError(self.run_dir, holder_pid(self.run_dir)) from None
        except BaseException:
            os.close(fd)
            raise
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd
        for tmp in self.run_dir.glob(".*.tmp"):  # torn atomic writes of a killed writer
            if tmp.is_file():
                tmp.unlink(missing_ok=True)
        return self

    def release(self) -> None:
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        try:
            os.ftruncate(fd, 0)  # no PID: nobody holds it (the file stays; removing it would race)
        finally:
            os.close(fd)

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc) -> bool:
        self.release()
        return False

    def __repr__(self) -> str:
        return f"RunLock({str(self.run_dir)!r}, held={self.held})"


def lock_run(run_dir) -> RunLock:
    """Take the writer lock of `run_dir` now (creating the folder), or raise RunLockedError naming
    the holder's PID. Use as `with lock_run(d): ...`, or keep the returned RunLock and call
    `release()` (a population trainer holds one per member)."""
    return RunLock(run_dir).acquire()


def holder_pid(run_dir) -> int | None:
    """PID written by the current holder of `run_dir`'s lock (None: unknown or not held)."""
    try:
        text = (Path(run_dir) / LOCK_NAME).read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


# %% [markdown]
# ## Demonstration
#
# A folder locked twice, a stale temporary file cleared, and a done marker that no longer matches
# its logs.

# %%
import tempfile

import pandas as pd

with tempfile.TemporaryDirectory() as tmp:
    folder = Path(tmp) / "run"
    folder.mkdir()
    (folder / ".metrics.parquet.abc.tmp").write_bytes(b"torn")
    with lock_run(folder) as lock:
        print(lock, "| stale tmp files left:", list(folder.glob(".*.tmp")))
        try:
            lock_run(folder)
        except RunLockedError as err:
            print("second writer:", err)
    pd.DataFrame({"x": [1, 2]}).to_parquet(folder / "metrics.parquet")
    print(read_parquet(folder / "metrics.parquet"))
    (folder / "checkpoint.pt").write_bytes(b"")
    try:
        load_checkpoint(folder / "checkpoint.pt")
    except RunFolderError as err:
        print("empty checkpoint:", err)
