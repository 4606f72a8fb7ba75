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
# # 09f · Appendix: the results store, run folders addressed by a URI
#
# A sweep's run folders (appendix 07b) are the training cache: config, logs, checkpoint and done
# marker of every run. By default they live in `results/` on this machine. That is fine on one
# workstation and wrong in two common cases: a preemptible cloud machine, whose disk goes away
# with it, and a Ray cluster, whose tasks run on other nodes and would each write to their own
# node's disk, where the driver never sees them.
#
# The **results store** is where run folders live, named by one setting (`--results-dir` of
# `sweep`, `results_dir` of `run_sweep` and of the notebooks, `make figures RESULTS=...`):
#
# * a local path (`results/`, the default) or a `file://` URL: the folders are on this disk, as
#   before, and nothing below applies: the folder's own lock (appendix 07b) guards it;
# * any other fsspec URL (`s3://bucket/prefix`, `gs://...`, `memory://...` in this notebook): the
#   store is an object store. Each worker trains a run in a **local cache** folder (under
#   `$PEMAMOE_CACHE`, default `~/.cache/pemamoe`), which it fills from the store before the run
#   starts and copies back to the store while it trains and when it stops. Nothing is kept on local
#   disk but that cache: a fresh machine, or another node, resumes from the store.
#
# The records folder (`--records-dir`, appendix 09d) may be a URL too: the sweep then pulls the
# records of its scales into the records' own cache first, and the driver uploads each record it
# writes, marker last. Workers never write records or portable states when either setting is a
# URL (a worker may run on a node whose disk the driver never sees); with the run folders in a
# bucket, the bucket is what carries work in progress from one machine to the next.
#
# Credentials and endpoints come from the usual places of each fsspec backend (for S3: the AWS
# environment variables and files, `AWS_ENDPOINT_URL` for a server that is not AWS).
#
# ### What goes through the store, and in what order
#
# A run folder holds `config.json`, the checkpoint (which carries the logs' rows too, so it alone is
# enough to resume), the two parquet logs, `sweep.json` and, last, `done.json`. `push_run` uploads
# the files that changed since the last push in that order, and uploads `done.json` only when it
# was already there at the start of the push: the logs it seals were written before it, so the
# store never holds a seal over older logs. One object is one PUT, so a reader sees a whole old
# file or a whole new one. A push cut off half way leaves a checkpoint newer than the logs at
# worst, which resumes exactly like a local folder that was killed between the two writes.
#
# ### Who may write a run: the lease
#
# Two workers must never train one run. On a local disk the folder's `fcntl` lock says so; an
# object store has no locks. Here each run has a **lease**, an object `<run>/.lease.json` created
# with a conditional put (`If-None-Match: *` on S3; fsspec's exclusive-create mode `"xb"`): of two
# workers that create it at once, exactly one succeeds, on every store that implements
# conditional writes (AWS S3 since 2024, MinIO, moto; `tests/test_store.py` checks it on a moto
# server). The holder rewrites its heartbeat at every sync. A lease whose heartbeat is older than
# `LEASE_STALE_SECONDS` belongs to a worker that died (a killed machine cannot release it); the
# next worker deletes it and creates its own. The guarantee is therefore: **one writer per run while
# the holder is alive and syncing**; two workers that find the same stale lease in the same
# instant may both delete it, but only one of them then wins the conditional put. What it cannot
# exclude is a holder that stalls for longer than the stale time and then writes again; the stale
# time (10 minutes by default) is many times the sync interval for that reason.

# %%
#| default_exp store

# %% tags=["parameters"]
scale = "ci"
figures_dir = "paper_figures"
seed = 0

# %%
#| export
import hashlib
import json
import os
import socket
import sys
import threading
import time
import uuid
from contextlib import contextmanager
from pathlib import Path

from pemamoe.core import atomic_path, require
from pemamoe.runs import _PicklableError

# The files of a run folder that the store keeps, in upload order: done.json last (it seals the logs).
STORE_FILES = ("config.json", "checkpoint.pt", "metrics.parquet", "episodes.parquet", "sweep.json", "done.json")
SEALED_FILES = ("config.json", "done.json", "metrics.parquet", "episodes.parquet")  # what says a run is finished
LEASE_NAME = ".lease.json"
SYNC_SECONDS = 30.0  # how often a worker copies its runs' changed files to the store and renews its leases
LEASE_STALE_SECONDS = 600.0  # a lease not renewed for this long belongs to a dead worker
CACHE_ENV = "PEMAMOE_CACHE"  # the local cache's root (default ~/.cache/pemamoe)
SYNC_ENV, STALE_ENV = "PEMAMOE_STORE_SYNC_SECONDS", "PEMAMOE_LEASE_STALE_SECONDS"


class StoreLeaseError(_PicklableError, RuntimeError):
    """Another live worker holds the lease of this run in the store."""

    def __init__(self, key: str, holder: dict):
        self.key, self.holder = key, holder
        age = time.time() - float(holder.get("heartbeat", 0.0))
        super().__init__(f"results store: {key} is held by {holder.get('host', '?')} (pid {holder.get('pid', '?')}), "
                         f"renewed {age:.0f} s ago; wait for it, or for it to go stale after "
                         f"{holder.get('stale_after', LEASE_STALE_SECONDS):g} s")


# %% [markdown]
# ## Naming a store
#
# `open_store` takes what the user typed. A plain path or a `file://` URL is a local store; a URL
# whose protocol fsspec does not know is refused with the protocols it does know, before anything
# is trained. The local cache of a remote store is a folder named after a hash of its URL, so two
# stores never share cached files.

# %%
#| export
def _env_seconds(name: str, default: float) -> float:
    text = os.environ.get(name)
    if text is None or text.strip() == "":
        return default
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    return require("environment", name, value, "real", gt=0.0)


def cache_root() -> Path:
    """The local cache's root: $PEMAMOE_CACHE, else ~/.cache/pemamoe."""
    text = os.environ.get(CACHE_ENV, "").strip()
    return Path(text).expanduser() if text else Path.home() / ".cache" / "pemamoe"


class ResultsStore:
    """Where run folders live: a local folder, or an fsspec URL with a local cache (see above).

    run_dir(scale, run) is the folder a run trains in on this machine: the store's own folder when
    local, the cache's when remote. Everything else (pull, push, lease, checkout) only does something
    for a remote store."""

    def __init__(self, uri="results", cache_dir=None):
        if isinstance(uri, ResultsStore):
            uri = uri.uri
        if not isinstance(uri, (str, os.PathLike)) or str(uri).strip() == "":
            raise ValueError(f"results store must be a folder path or a URL such as s3://bucket/prefix, got {uri!r}")
        text = os.fspath(uri)
        protocol = text.split("://", 1)[0].lower() if "://" in text else "file"
        if protocol in ("file", "local"):
            self.remote, self.fs = False, None
            self.folder = Path(text.split("://", 1)[1] if "://" in text else text)
            self.uri = str(self.folder)
            return
        import fsspec
        from fsspec.registry import known_implementations, registry

        if protocol not in known_implementations and protocol not in registry:
            raise ValueError(f"results store {text!r}: fsspec knows no protocol {protocol!r}; use a folder path "
                             f"or one of {', '.join(sorted(set(known_implementations) | set(registry)))}")
        try:
            self.fs, self.root = fsspec.core.url_to_fs(text)
        except ImportError as err:
            raise ValueError(f"results store {text!r} needs a package that is not installed: {err}") from None
        self.remote, self.uri = True, text.rstrip("/")
        self.root = self.root.rstrip("/")
        digest = hashlib.sha256(self.uri.encode()).hexdigest()[:12]
        self.folder = Path(cache_dir) if cache_dir is not None else cache_root() / "store" / f"{protocol}-{digest}"

    def __repr__(self) -> str:
        return f"ResultsStore({self.uri!r}" + (f", cache {self.folder})" if self.remote else ")")

    def __reduce__(self):  # a store travels to workers as its URL: each opens its own connection and cache
        return ResultsStore, (self.uri,)

    def run_dir(self, scale: str, run: str) -> Path:
        return self.folder / scale / run

    def key(self, scale: str, run: str = "", name: str = "") -> str:
        return "/".join(p for p in (self.root, scale, run, name) if p)

    def stored_files(self, scale: str, run: str) -> set:
        """The names of the run's files in the store (empty when the run has none)."""
        folder = self.key(scale, run)
        self.fs.invalidate_cache(folder)  # fsspec caches listings; another worker may have written since
        try:
            return {Path(p).name for p in self.fs.ls(folder, detail=False)}
        except FileNotFoundError:
            return set()


def open_store(results="results") -> ResultsStore:
    """A ResultsStore from a path, a URL or a ResultsStore (returned as it is)."""
    return results if isinstance(results, ResultsStore) else ResultsStore(results)


# %% [markdown]
# ## Pull and push
#
# `pull_run` makes the cache folder a copy of what the store holds for a run: the store is the
# truth, so a cached file the store lacks is deleted (a done marker left from an earlier try must
# not seal anything). `names` limits it to some files: the sweep's driver pulls only the sealed
# files to learn whether a run is finished, never the checkpoint. `push_run` copies back the files
# that changed since the last push (by size and modification time), in the order above.

# %%
#| export
def pull_run(store: ResultsStore, scale: str, run: str, names=STORE_FILES) -> dict:
    """Copy the run's `names` from the store into store.run_dir; return {name: (mtime_ns, size)} of
    the files now in the cache folder (what push_run need not send back)."""
    folder = store.run_dir(scale, run)
    folder.mkdir(parents=True, exist_ok=True)
    stored = store.stored_files(scale, run)
    for name in names:
        local = folder / name
        if name in stored:
            with atomic_path(local) as tmp:
                store.fs.get_file(store.key(scale, run, name), str(tmp))
        else:
            local.unlink(missing_ok=True)
    return _stats(folder)


def push_run(store: ResultsStore, folder, scale: str, run: str, pushed: dict | None = None) -> dict:
    """Upload the files of the cache `folder` that differ from `pushed` ({name: (mtime_ns, size)}),
    and delete from the store those `pushed` names that are gone here; return the new `pushed`.
    done.json goes last, and only if it existed when the push began."""
    folder, pushed = Path(folder), dict(pushed or {})
    sealed = (folder / "done.json").exists()
    for name in STORE_FILES:
        if name == "done.json" and not sealed:
            continue
        stamp = _stamp(folder / name)
        if stamp is None:
            if pushed.pop(name, None) is not None:  # deleted here since (a run started over): there too
                try:
                    store.fs.rm_file(store.key(scale, run, name))
                except FileNotFoundError:
                    pass
            continue
        if pushed.get(name) != stamp:
            store.fs.put_file(str(folder / name), store.key(scale, run, name))
            pushed[name] = stamp
    return pushed


def _stamp(path: Path) -> tuple | None:
    """(mtime_ns, size) of a file, None when it is missing: what says it changed since a push."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    return st.st_mtime_ns, st.st_size


def _stats(folder: Path) -> dict:
    return {name: stamp for name in STORE_FILES if (stamp := _stamp(folder / name)) is not None}


def refresh_finished(store: ResultsStore, scale: str, run: str) -> None:
    """For a remote store: bring the cache folder's sealed files up to date with the store, so that
    pemamoe.runs.verify_done on store.run_dir answers for the store (a no-op for a local store)."""
    if not store.remote:
        return
    folder = store.run_dir(scale, run)
    if "done.json" in store.stored_files(scale, run):
        pull_run(store, scale, run, SEALED_FILES)
    elif (folder / "done.json").exists():  # the store has no seal: neither may the cache
        (folder / "done.json").unlink()


# %% [markdown]
# ## The lease

# %%
#| export
class StoreLease:
    """The lease of one run in a remote store (see the top of this notebook)."""

    def __init__(self, store: ResultsStore, scale: str, run: str, stale_after: float | None = None):
        self.store, self.key = store, store.key(scale, run, LEASE_NAME)
        self.stale_after = stale_after if stale_after is not None else _env_seconds(STALE_ENV, LEASE_STALE_SECONDS)
        self.owner = uuid.uuid4().hex

    def _body(self) -> bytes:
        return json.dumps({"owner": self.owner, "host": socket.gethostname(), "pid": os.getpid(),
                           "heartbeat": time.time(), "stale_after": self.stale_after}).encode()

    def _create(self) -> bool:
        try:
            with self.store.fs.open(self.key, "xb") as f:  # conditional put: fails if the object exists
                f.write(self._body())
            return True
        except FileExistsError:
            return False

    def holder(self) -> dict | None:
        try:
            return json.loads(self.store.fs.cat_file(self.key))
        except FileNotFoundError:
            return None
        except (ValueError, UnicodeDecodeError):
            return {"heartbeat": 0.0}  # unreadable: treated as stale

    def acquire(self) -> "StoreLease":
        if self._create():
            return self
        holder = self.holder()
        if holder is not None and time.time() - float(holder.get("heartbeat", 0.0)) <= self.stale_after:
            raise StoreLeaseError(self.key, holder)
        try:  # stale (or released meanwhile): take it over; of several takers, one wins the put
            self.store.fs.rm_file(self.key)
        except FileNotFoundError:
            pass
        if not self._create():
            raise StoreLeaseError(self.key, self.holder() or {})
        return self

    def renew(self) -> None:
        holder = self.holder()
        if holder is None or holder.get("owner") != self.owner:
            raise StoreLeaseError(self.key, holder or {"host": "nobody (the lease is gone)"})
        self.store.fs.pipe_file(self.key, self._body())

    def release(self) -> None:
        holder = self.holder()
        if holder is not None and holder.get("owner") == self.owner:
            self.store.fs.rm_file(self.key)


# %% [markdown]
# ## Checking runs out of the store
#
# `checked_out` is what one worker wraps around one population: it takes every run's lease, pulls
# each run into the cache, and, while the population trains, a thread pushes the changed files and
# renews the leases every `SYNC_SECONDS`. When the population stops (finished, out of time,
# interrupted or failed), a last push and the release follow. A worker that dies without that
# (SIGKILL, a lost node) leaves the store as it was at its last sync, with stale leases: at most
# `SYNC_SECONDS` plus one checkpoint interval of training is lost.

# %%
#| export
class _Mirror(threading.Thread):
    """Pushes the checked-out runs and renews their leases every `every` seconds."""

    def __init__(self, store, runs, folders, leases, pushed, every: float):
        super().__init__(name="pemamoe-store-mirror", daemon=True)
        self.store, self.runs, self.folders, self.leases, self.pushed = store, runs, folders, leases, pushed
        self.every, self.stop_event = every, threading.Event()

    def sync(self) -> None:
        for i, ((scale, run), folder, lease) in enumerate(zip(self.runs, self.folders, self.leases)):
            self.pushed[i] = push_run(self.store, folder, scale, run, self.pushed[i])
            lease.renew()

    def run(self) -> None:
        while not self.stop_event.wait(self.every):
            try:
                self.sync()
            except Exception as err:  # noqa: BLE001 - training goes on; checked_out's last sync raises if it persists
                print(f"[store] sync to {self.store.uri} failed, retrying: {type(err).__name__}: {err}",
                      file=sys.stderr, flush=True)


@contextmanager
def checked_out(store: ResultsStore, runs: list):
    """Yield the local folders of `runs` ([(scale, run name), ...]) to train in. For a remote store:
    lease, pull, mirror while inside, push and release after (see above)."""
    store = open_store(store)
    runs = list(runs)
    if not store.remote:
        yield [store.run_dir(scale, run) for scale, run in runs]
        return
    leases = []
    try:
        for scale, run in runs:
            leases.append(StoreLease(store, scale, run).acquire())
        folders = [store.run_dir(scale, run) for scale, run in runs]  # their .lock stays local: never pushed
        pushed = [pull_run(store, scale, run) for scale, run in runs]
        mirror = _Mirror(store, runs, folders, leases, pushed, _env_seconds(SYNC_ENV, SYNC_SECONDS))
        mirror.start()
        try:
            yield folders
        finally:
            mirror.stop_event.set()
            mirror.join()
            mirror.sync()  # the last push: whatever the population left, finished or not
    finally:
        for lease in leases:
            try:
                lease.release()
            except Exception as err:  # noqa: BLE001 - a lease left behind goes stale; never hide the real error
                print(f"[store] could not release {lease.key}: {err}", file=sys.stderr, flush=True)


def pull_tree(store: ResultsStore, prefix: str) -> Path:
    """Copy every file under `prefix` of a remote store into its cache folder; return that folder.
    What a sweep does with a records folder at a URL (appendix 09c): records are small."""
    top = store.key(prefix)
    store.fs.invalidate_cache(top)
    try:
        paths = store.fs.find(top)
    except FileNotFoundError:
        paths = []
    for path in paths:
        with atomic_path(store.folder / path[len(store.root) + 1:]) as tmp:
            store.fs.get_file(path, str(tmp))
    return store.folder / prefix


def push_paths(store: ResultsStore, paths) -> None:
    """Upload files of a remote store's cache folder to their place in the store, in the given order
    (a record's marker last: it seals the others)."""
    for path in paths:
        relative = Path(path).resolve().relative_to(store.folder.resolve()).as_posix()
        store.fs.put_file(str(path), f"{store.root}/{relative}")


def fetch_run(store, scale: str, run: str) -> Path:
    """The local folder of a run with every file the store holds for it (for a local store: the
    folder itself). What a driver calls to read a run back, e.g. with pemamoe.populations.load_run."""
    store = open_store(store)
    if store.remote:
        pull_run(store, scale, run)
    return store.run_dir(scale, run)


# %% [markdown]
# ## Demonstration: a ci population through an in-memory store
#
# fsspec's `memory://` filesystem stands in for a bucket here (it lives in this process, and it
# implements the exclusive create the lease needs); `tests/test_store.py` runs the same code against
# a real S3 server, with a Ray sweep killed part way and resumed. A second worker asking for a run
# that is leased is refused; the population trains in the cache and leaves its run folders in the
# store; the sweep's bookkeeping then finds them finished there.

# %%
import tempfile

from pemamoe.execution import RunSpec, execute_population, pending_runs

with tempfile.TemporaryDirectory() as tmp:
    os.environ[CACHE_ENV] = tmp
    url = "memory://demo-bucket/results"
    store = open_store(url)
    specs = [RunSpec("mlp", 0, "ci"), RunSpec("mlp", 1, "ci")]
    name = specs[0].to_config().run_name()
    held = StoreLease(store, "ci", name).acquire()
    try:
        StoreLease(store, "ci", name).acquire()
    except StoreLeaseError as err:
        print("second worker refused:", str(err)[:90], "...")
    held.release()
    finished = execute_population(specs, url)
    print(f"{len(finished)} runs finished, trained in the cache {Path(finished[0]).parent}")
    for path in sorted(store.fs.find(store.root)):
        print("  in the store:", path[len(store.root) + 1:])
    print("still to train:", [s.label() for s in pending_runs(specs, url)[1]] or "nothing")
    assert not pending_runs(specs, url)[1] and not any(p.endswith(LEASE_NAME) for p in store.fs.find(store.root))
    del os.environ[CACHE_ENV]
