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
#    iterations and the sha256 of the final logs (and, for the record, the torch thread counts and
#    processors). `verify_done` checks the first three before a run counts as finished
#    (`train(resume=True)`, `load_run`, the sweep's "already done" test, `analysis.load_runs`). A
#    marker from another run, a garbage marker, or logs changed after the seal (e.g. a marker copied
#    beside a run stopped half-way) raise `RunFolderError`.
#    We never guess which file is right.
#    The marker also has to seal a whole run: `write_done` refuses, and `verify_done` rejects, a
#    `metrics.parquet` whose row count (read from the parquet footer, not the rows) is not the
#    run's number of iterations, so a run stopped half-way never counts as finished.
# 4. **Unreadable files are named.** A 0-byte or truncated checkpoint, a garbage `config.json`, a
#    truncated parquet file, a folder where a file should be: each raises `RunFolderError` with the
#    folder, the file and the cause (instead of a bare `EOFError`, `JSONDecodeError`,
#    `ArrowInvalid` or `IsADirectoryError`). A truncated checkpoint is called truncated (the zip
#    archive `torch.save` writes has lost its end), not described by torch's zip reader.
# 5. **A checkpoint is sealed with its own sha256.** `torch.load` does not check the zip's CRCs, so
#    flipped bytes inside a tensor load without complaint. `seal_checkpoint` stores the sha256 of
#    the file as `torch.save` wrote it in the zip archive's comment (the last bytes of the file,
#    which zip readers, torch's included, skip); `load_checkpoint` recomputes it and refuses a
#    mismatch, naming the file. Checkpoints of format 4 and older carry no seal and are read as
#    before. A checkpoint also records the `TRAINING_NUMERICS` version it was computed under
#    (appendix 07c; absent means version 1): resuming it under another version would splice two
#    arithmetics into one run, so `load_checkpoint` refuses, naming both versions. It does not
#    advise starting the folder over: the folder is named for the old version, and its work is the
#    user's. A sweep never meets the refusal, since after a bump a config's folder has a new name
#    (appendix 07c): it trains the config afresh there and leaves the old folder alone.
# 6. **Errors survive a process pool.** `RunFolderError` and `RunLockedError` pickle with their
#    message and attributes intact, so a sweep worker's error reaches the parent as itself instead
#    of a `BrokenProcessPool`.
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
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path

from pemamoe.core import atomic_write_json, cpu_model, one_line

RUN_FILES = ("config.json", "metrics.parquet", "episodes.parquet", "checkpoint.pt", "done.json")
LOG_FILES = ("metrics.parquet", "episodes.parquet")  # sealed by their sha256 in done.json
DONE_FORMAT = 2  # done.json layout; format 1 (no digests) cannot be verified
LOCK_NAME = ".lock"
_START_OVER = "delete the folder, or train with resume=False to start it over"


class PicklableError:
    """Mixin: an exception whose constructor takes other arguments than its message pickles as its
    message (`args`) and attributes, without calling the constructor again (the default pickling
    calls `cls(*args)`, which fails or, in a process pool, breaks the pool)."""

    def __reduce__(self):
        return _rebuild_error, (type(self), self.args, dict(self.__dict__))


def _rebuild_error(cls, args, state):
    err = cls.__new__(cls, *args)
    err.args = args
    err.__dict__.update(state)
    return err


class RunFolderError(PicklableError, ValueError):
    """A file of a run folder cannot be used as it is. The message names the folder, the file and
    what is wrong; `path` is the file."""

    def __init__(self, path, problem: str, hint: str = _START_OVER):
        self.path, self.problem, self.hint = Path(path), problem, hint
        super().__init__(self.message())

    def message(self, start_over: str | None = None) -> str:
        """The message; with `start_over`, that advice replaces the default one (resume=False, how
        the API starts a run over), so that a command can name its own way (`--no-resume`)."""
        hint = start_over if start_over is not None and self.hint == _START_OVER else self.hint
        return f"run folder {self.path.parent}: {self.path.name} {self.problem}" + (f"; {hint}" if hint else "")


class RunLockedError(PicklableError, RuntimeError):
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
    except IsADirectoryError:
        raise RunFolderError(path, "is a directory, not a file") from None
    except OSError as err:
        raise RunFolderError(path, f"cannot be read ({type(err).__name__}: {err})") from None
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

    path = _existing_file(path)
    try:
        return pq.read_table(path, use_threads=False).to_pandas(use_threads=False)
    except (pa.ArrowException, OSError) as err:
        raise RunFolderError(path, f"cannot be read as parquet ({type(err).__name__}: {err})") from None


def read_config(path, cls=None):
    """The TrainConfig stored in `path` (a config.json); RunFolderError when it is not one."""
    if cls is None:
        from pemamoe.train_config import TrainConfig as cls  # runs.py sits below train_config.py
    path = Path(path)
    return _config_from_dict(read_json(path), cls, path)


def load_checkpoint(path, config=None, iteration: int | None = None, resuming: bool = True) -> dict:
    """`torch.load(path, weights_only=True)`, checked: a readable dict with a `config` and an
    `iteration`, whose bytes match the sha256 sealed into it (`seal_checkpoint`; checkpoints of
    format 4 and older have none); with `config`, the stored config must have the same identity
    (see `check_stored_config`), the checkpoint must come from this code's `TRAINING_NUMERICS`
    (absent: version 1) when `resuming` (reading a finished run: any) and hold at most
    `config.iterations` iterations; with `iteration`, exactly that many."""
    import io
    import pickle
    import zipfile

    import torch

    path = _existing_file(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise RunFolderError(path, f"cannot be read ({type(err).__name__}: {err})") from None
    if not data:
        raise RunFolderError(path, "is empty (0 bytes)")
    sealed = _check_seal(data, path)
    try:
        ck = torch.load(io.BytesIO(data), weights_only=True)
    except (EOFError, RuntimeError, pickle.UnpicklingError, zipfile.BadZipFile, OSError, ValueError) as err:
        if not zipfile.is_zipfile(io.BytesIO(data)):  # torch.save writes a zip archive: its end is missing
            raise RunFolderError(path, f"is truncated or damaged: its {len(data):,} bytes are not a whole checkpoint "
                                 "(the zip archive that torch.save writes has no end record)") from None
        cause = one_line(err).split(". ")[0]  # the reader's first sentence, not its advice about itself
        raise RunFolderError(path, f"cannot be read as a checkpoint ({type(err).__name__}: {cause})") from None
    if not isinstance(ck, dict) or not isinstance(ck.get("config"), dict) or "iteration" not in ck:
        raise RunFolderError(path, "is not a training checkpoint (no 'config' and 'iteration')")
    fmt = ck.get("format", 1)  # the first checkpoints recorded none
    if not sealed and not (isinstance(fmt, int) and fmt < SEALED_FORMAT):
        raise RunFolderError(path, f"has format {fmt!r} but no content seal (checkpoints of format "
                             f"{SEALED_FORMAT} and later carry one): it was rewritten or damaged, so it cannot be trusted")
    if config is not None:
        check_stored_config(ck["config"], config, path)
        from pemamoe.train_config import training_numerics

        # Only a resume would mix two arithmetics in one run: a sealed, finished run is read as it is
        # (its folder's identity already carries the numerics it was computed under).
        if resuming and ck.get("numerics", 1) != training_numerics():
            raise RunFolderError(path, f"was computed under training numerics version {ck.get('numerics', 1)!r}, "
                                 f"but this code computes version {training_numerics()}: resuming it would mix two "
                                 "arithmetics in one run",
                                 f"finish it with the code of version {ck.get('numerics', 1)!r}, or train the config "
                                 f"afresh under version {training_numerics()} in its own folder (the sweep does: "
                                 "config.run_name()); this folder is left as it is")
        if not 0 <= int(ck["iteration"]) <= config.iterations:
            raise RunFolderError(path, f"is at iteration {ck['iteration']}, outside 0..{config.iterations}")
    if iteration is not None and int(ck["iteration"]) != iteration:
        raise RunFolderError(path, f"is at iteration {ck['iteration']}, but the run finished at {iteration}")
    return ck


# %% [markdown]
# ## The checkpoint's seal
#
# A zip archive ends with its end-of-central-directory record, whose last two bytes give the length
# of an archive comment that follows it; `torch.save` writes no comment. `seal_checkpoint` hashes
# the file as `torch.save` left it and appends `pemamoe-sha256:<64 hex digits>` as the comment, so
# the checkpoint is still one file, renamed into place in one step, and `torch.load` reads it as
# before. `_check_seal` takes the comment off again, recomputes the hash of what is left and
# compares. Hashing costs a fraction of what writing the file costs (sha256 reads some 1 GB/s).

# %%
#| export
SEALED_FORMAT = 5  # the checkpoint format that introduced the seal (appendix 07e); every later one has it too
CHECKPOINT_SEAL = b"pemamoe-sha256:"  # the zip comment of a sealed checkpoint: this, then the 64 hex digits


def seal_checkpoint(path) -> str:
    """Seal a file just written by `torch.save` (a zip archive without comment) with the sha256
    of its bytes, stored as the archive's comment; returns the digest. Call it before the file is
    renamed into place."""
    path = Path(path)
    with open(path, "r+b") as f:
        f.seek(0, os.SEEK_END)
        if f.tell() < 22:
            raise ValueError(f"{path} is too short to be a zip archive; cannot seal it")
        f.seek(-22, os.SEEK_END)
        end = f.read(22)
        if end[:4] != b"PK\x05\x06" or end[20:] != b"\x00\x00":
            raise ValueError(f"{path} does not end in a zip end-of-central-directory record without comment "
                             "(not written by torch.save?); cannot seal it")
        f.seek(0)
        h = hashlib.sha256()
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
        comment = CHECKPOINT_SEAL + h.hexdigest().encode()
        f.seek(-2, os.SEEK_END)
        f.write(len(comment).to_bytes(2, "little") + comment)
    return h.hexdigest()


# %%
#| exporti
_SEAL_LEN = len(CHECKPOINT_SEAL) + 64


def _check_seal(data: bytes, path) -> bool:
    """Whether `data` (a checkpoint's bytes) carries a seal; RunFolderError naming `path` when the
    seal does not match the bytes."""
    tail = data[-(_SEAL_LEN + 2):]
    if len(data) < _SEAL_LEN + 24 or tail[:2] != _SEAL_LEN.to_bytes(2, "little") or \
            not tail[2:].startswith(CHECKPOINT_SEAL):
        return False
    recorded = tail[2 + len(CHECKPOINT_SEAL):].decode("ascii", errors="replace")
    h = hashlib.sha256(memoryview(data)[:-(_SEAL_LEN + 2)])
    h.update(b"\x00\x00")  # the comment length as torch.save wrote it
    if h.hexdigest() != recorded:
        raise RunFolderError(path, f"fails its content check (sha256 {h.hexdigest()[:12]}... now, {recorded[:12]}... "
                             "when it was written): the file was damaged after it was written (disk, copy or "
                             "edit), and a resumed run would continue from wrong numbers")
    return True


def _existing_file(path) -> Path:
    """`path` as a Path; RunFolderError when it is missing or not a regular file."""
    path = Path(path)
    if path.is_dir():
        raise RunFolderError(path, "is a directory, not a file")
    if not path.is_file():
        raise RunFolderError(path, "is missing")
    return path


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


def file_stamp(path: Path) -> tuple | None:
    """(mtime_ns, size) of a file, None when it is missing: what says it changed since it was copied."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    return st.st_mtime_ns, st.st_size


@contextmanager
def link_snapshot(path):
    """A hard link to `path` (a copy where links fail) that an atomic replace of `path` leaves alone;
    None when `path` is None or missing (the results store uploads from it, appendix 09f). Named
    like a torn atomic write (.*.tmp): a killed upload's link is removed with those when the run's
    folder is next locked."""
    snap = None
    if path is not None:
        snap = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.push.tmp")
        try:
            os.link(path, snap)
        except FileNotFoundError:
            snap = None
        except OSError:
            try:
                shutil.copy2(path, snap)
            except FileNotFoundError:
                snap = None
    try:
        yield snap
    finally:
        if snap is not None:
            snap.unlink(missing_ok=True)


# What a checkpoint or done.json written before processors were recorded says of its sessions.
UNRECORDED_PROCESSOR = "not recorded"


def training_processor() -> str:
    """This machine as a run's provenance names it: the processor's model and the kernels torch
    dispatches to on it (a run's floats differ between processor families)."""
    import torch

    return f"{cpu_model()} ({torch.backends.cpu.get_cpu_capability()})"


def write_done(run_dir, config, **record) -> dict:
    """Seal a finished run: write done.json with the config hash, the number of iterations and the
    sha256 of each log file, plus `record` (e.g. env_steps, torch_threads, processors, wall_time_s).
    RunFolderError when metrics.parquet does not hold one row per iteration (a partial run)."""
    run_dir = Path(run_dir)
    rows = parquet_rows(run_dir / "metrics.parquet")
    if rows != config.iterations:
        raise RunFolderError(run_dir / "done.json", f"cannot seal this run: metrics.parquet holds {rows} rows, "
                             f"the config asks for {config.iterations} iterations (the run is not finished)",
                             "train it to the end, and it writes done.json itself")
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
            raise RunFolderError(path, f"seals {name}, which is missing" + (" (a directory)" if log.is_dir() else ""))
        if marker["digests"].get(name) != file_digest(log):
            raise RunFolderError(path, f"seals a different {name} (sha256 {str(marker['digests'].get(name))[:12]}... "
                                 f"recorded, {file_digest(log)[:12]}... on disk): the logs changed after the "
                                 "run finished, or the marker was copied from elsewhere")
    rows = parquet_rows(run_dir / "metrics.parquet")
    if rows != config.iterations:
        raise RunFolderError(path, f"seals a metrics.parquet of {rows} rows, but the run has {config.iterations} "
                             "iterations: it was sealed before the run finished")
    return marker


def parquet_rows(path) -> int:
    """The number of rows of a parquet file, from its footer (no row is read)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = _existing_file(path)
    try:
        return int(pq.read_metadata(path).num_rows)
    except (pa.ArrowException, OSError) as err:
        raise RunFolderError(path, f"cannot be read as parquet ({type(err).__name__}: {err})") from None


def prepare_run_dir(run_dir, config, resume: bool) -> None:
    """Before a run writes: with resume, check that config.json (if any) holds the same run; without,
    remove the previous run's marker, checkpoint and logs. Then (re)write config.json. Call it
    with the folder's lock held."""
    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.json"
    if resume and cfg_path.exists():
        check_stored_config(read_json(cfg_path), config, cfg_path)
        return
    if resume and (run_dir / "checkpoint.pt").exists():  # no config.json: the checkpoint says whose folder it is
        load_checkpoint(run_dir / "checkpoint.pt", config)  # refuses another run's before anything is written
    for name in ("config.json", "done.json", "checkpoint.pt", *LOG_FILES):
        if (run_dir / name).is_dir():
            raise RunFolderError(run_dir / name, "is a directory, not a file", "remove it by hand")
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
# A folder locked twice, a stale temporary file cleared, an empty checkpoint, a sealed checkpoint
# with one flipped byte, and an error that crosses a process boundary (a pickle round trip).

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
    import pickle

    import torch

    torch.save({"config": {}, "iteration": 0, "format": SEALED_FORMAT, "w": torch.arange(64.0)},
               folder / "checkpoint.pt")
    print("sealed with sha256", seal_checkpoint(folder / "checkpoint.pt")[:12], "...")
    data = bytearray((folder / "checkpoint.pt").read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte in the middle of the file
    (folder / "checkpoint.pt").write_bytes(bytes(data))
    try:
        load_checkpoint(folder / "checkpoint.pt")
    except RunFolderError as err:
        print("flipped byte:", err)
        again = pickle.loads(pickle.dumps(err))
        assert type(again) is RunFolderError and str(again) == str(err) and again.path == err.path
