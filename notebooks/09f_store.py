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
# worst, which resumes exactly like a local folder that was killed between the two writes. The
# files keep the bytes they have in a local folder, each in an object of the generation that wrote
# it (`.g<g>.<name>`, below), named by that generation's lease.
#
# ### Who may write a run: the lease and its generation
#
# Two workers must never train one run. On a local disk the folder's `fcntl` lock says so; an
# object store has no locks. Here each run has **leases**, numbered by a **generation**: the worker
# that checks a run out creates `<run>/.lease-<g>.json`, g one more than the newest lease there,
# with a conditional put (`If-None-Match: *` on S3; fsspec's exclusive-create mode `"xb"`). Of two
# workers that create the same generation at once, exactly one succeeds, on every store that
# implements conditional writes (AWS S3 since 2024, MinIO, moto; `tests/test_store.py` checks it on
# a moto server). Its holder rewrites the lease (the heartbeat) at every sync and marks it released
# when it is done with the run. A lease that is released, or whose heartbeat is older than the
# stale time its holder declared in it (`$PEMAMOE_LEASE_STALE_SECONDS` of the holder, default
# `LEASE_STALE_SECONDS`; its worker died: a killed machine cannot release anything), lets the next
# worker create generation g + 1. The taker's own setting does not shorten a holder's declaration
# (issue 59: it took live leases). Nobody deletes a lease or writes another worker's: a generation
# is never used twice, and a worker learns that it lost a run by seeing a newer lease.
#
# Each holder uploads a run's files to **objects of its own generation**, `<run>/.g<g>.<name>`,
# which no other worker writes, and writes into its lease, at every push, the sha256 of every file
# and the object holding it: its **manifest**. The newest generation that has pushed is the run:
# readers read the objects its manifest names, and a done marker in it is the seal. A generation
# uploads every file once as its own, the ones it pulled unchanged included, so that a sealed
# manifest names only objects its own worker wrote. (Runs stored by earlier versions hold plain
# `<run>/<name>` objects and manifests of digests only; they are read as before, with the fence
# below, and a new generation moves them into objects of its own at its first push.)
#
# What this guarantees, and what it does not:
#
# * **One writer per run while the holder is alive and syncing.** A lease renewed within the stale
#   time refuses every other taker.
# * **Of two takers of one stale lease, only one wins the put.** Both try to create the same
#   generation g + 1, and the conditional put lets one of them. (A single lease object that a taker
#   deletes and creates again does not give this: a slow taker's delete can remove the winner's
#   new lease, and both then hold it.)
# * **Every push is the holder's.** Before each push, the final one included, the worker renews its
#   lease and then lists the run: if a newer generation exists, or a done marker appeared that this
#   worker neither saw at checkout nor wrote, it uploads nothing, stops copying that run for good
#   (one line on stderr, no retries), and the population's end raises `StoreLeaseError`. The check
#   runs again after the files and before the done marker. A holder that stalls past the stale time
#   (a paused process, a frozen VM, a long GC) and then wakes therefore finds the newer lease
#   and writes nothing.
# * **A late upload never touches another generation's run.** A check followed by a put is two
#   requests, and S3 has no put that is conditional on another object: a holder that passes its
#   check and then stalls past the stale time inside its put (issue 59: a paused process) writes
#   after a takeover. Its bytes land in its own generation's objects, which the newer generation's
#   manifest does not name: a run the taker sealed stays byte for byte what it sealed, and is read
#   as finished; the late writer learns at its next lease write that it lost the run.
# * **Readers check every byte.** `pull_run`, `refresh_finished` and `fetch_run` check every file
#   they copy against the manifest that names it: under a done marker every file must be the one
#   the sealing generation listed, and (in a run of the earlier layout, where a late write could
#   land on the plain object) a file listed only by an older generation is refused with one line
#   naming the run and both generations.
#
# What it does not exclude: a stalled holder whose manifest write lands after a takeover, but
# before the taker's first push, is the newest manifest for that while; readers then see the late
# writer's run, whole and consistent (its own objects, its digests), until the taker pushes.
# Staleness compares the taker's clock with the holder's: clocks more than a fraction of the stale
# time apart weaken the first point. Objects of generations that lost a run stay in the store
# (unread) until its folder is deleted.

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
from contextlib import ExitStack, contextmanager
from pathlib import Path

from pemamoe.core import atomic_path, one_line, require
from pemamoe.runs import PicklableError, file_digest, file_stamp, link_snapshot

# The files of a run folder that the store keeps, in upload order: done.json last (it seals the logs).
STORE_FILES = ("config.json", "checkpoint.pt", "metrics.parquet", "episodes.parquet", "sweep.json", "done.json")
SEALED_FILES = ("config.json", "done.json", "metrics.parquet", "episodes.parquet")  # what says a run is finished
LEASE_PREFIX = ".lease-"  # a run's leases in the store: .lease-<generation>.json, one per holder
LEGACY_LEASE = ".lease.json"  # the single lease of earlier versions: still respected while it is live
OBJECT_PREFIX = ".g"  # a generation's own copy of a run file: .g<generation>.<name>, named by its manifest
SYNC_SECONDS = 30.0  # how often a worker copies its runs' changed files to the store and renews its leases
LEASE_STALE_SECONDS = 600.0  # a lease not renewed for this long belongs to a dead worker
CACHE_ENV = "PEMAMOE_CACHE"  # the local cache's root (default ~/.cache/pemamoe)
SYNC_ENV, STALE_ENV = "PEMAMOE_STORE_SYNC_SECONDS", "PEMAMOE_LEASE_STALE_SECONDS"


class StoreLeaseError(PicklableError, RuntimeError):
    """A run in the store is not this worker's to write or read as it is: another live worker holds
    its lease; or (`problem`, the message's text) this worker lost the lease, the run was sealed by
    another, or a reader found a file written by a worker that had lost the lease. One line."""

    def __init__(self, key: str, holder: dict, problem: str | None = None):
        self.key, self.holder, self.problem = key, holder, problem
        if problem is not None:
            super().__init__(f"results store: {problem}")
            return
        age = time.time() - _heartbeat(holder)
        super().__init__(f"results store: {key} is held by {holder.get('host', '?')} (pid {holder.get('pid', '?')}), "
                         f"renewed {age:.0f} s ago; wait for it, or for it to go stale after "
                         f"{holder.get('stale_after', LEASE_STALE_SECONDS):g} s")


def _heartbeat(holder: dict) -> float:
    try:
        return float(holder.get("heartbeat", 0.0))
    except (TypeError, ValueError):
        return 0.0


# %% [markdown]
# ## Naming a store
#
# `open_store` takes what the user typed. A plain path or a `file://` URL is a local store; a URL
# whose protocol fsspec does not know is refused with the protocols it does know, before anything
# is trained. The local cache of a remote store is a folder named after a hash of its URL, so two
# stores never share cached files.

# %%
#| export
ENV_SECONDS_LIMIT = {SYNC_ENV: 86400.0, STALE_ENV: 30 * 86400.0}  # the largest value each setting takes


def _env_seconds(name: str, default: float) -> float:
    text = os.environ.get(name)
    if text is None or text.strip() == "":
        return default
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    return require("environment", name, value, "real", gt=0.0, le=ENV_SECONDS_LIMIT[name])


def check_store_environment() -> None:
    """Read every PEMAMOE_* setting of the store once: a bad one raises ValueError, one line naming
    the variable, its value and what is allowed (the commands call it before anything runs)."""
    for name, default in ((SYNC_ENV, SYNC_SECONDS), (STALE_ENV, LEASE_STALE_SECONDS)):
        _env_seconds(name, default)


def _declared_stale(holder: dict, default: float) -> float:
    value = holder.get("stale_after")
    if isinstance(value, (int, float)) and not isinstance(value, bool) and 0 < value <= ENV_SECONDS_LIMIT[STALE_ENV]:
        return float(value)
    return default


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
        self.protocol = protocol = text.split("://", 1)[0].lower() if "://" in text else "file"
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
# ## Reaching a store
#
# A URL can name a store that cannot be used: no credentials, an endpoint that does not answer, a
# bucket that does not exist, access denied. The client libraries say so in their own words at the
# end of a long traceback (botocore's `NoCredentialsError` or `EndpointConnectionError`; s3fs turns
# a missing bucket into a `FileNotFoundError` that does not name it). `check_access` lists the
# store's top once, before anything trains (a prefix not written yet is fine, its bucket must
# exist), and `store_access_error` translates such an error into a `StoreAccessError`: one line
# naming the store's URL, the value at fault (the endpoint, the bucket) and what to do. The commands
# call `check_access` first; `checked_out` (below) translates the errors of its leases and pulls the
# same way, so a worker's failure reads alike.

# %%
#| export
BUCKET_PROTOCOLS = ("s3", "s3a", "gs", "gcs", "az", "abfs", "abfss", "adl")  # a URL's first component is a bucket


class StoreAccessError(PicklableError, RuntimeError):
    """A remote store cannot be used as named: no credentials, an endpoint that does not answer, a
    bucket that does not exist, access denied. One line naming the store's URL (`uri`) and what is
    wrong (`problem`)."""

    def __init__(self, uri: str, problem: str):
        self.uri, self.problem = uri, problem
        super().__init__(one_line(f"results store {uri}: {problem}"))


def check_access(store) -> "ResultsStore":
    """Reach a remote store once (list its top; where the prefix is not written yet, its bucket);
    return it. StoreAccessError, one line, when it cannot be used; a local store is not checked."""
    store = open_store(store)
    if not store.remote:
        return store
    bucket = _bucket(store)
    with _access_errors(store):
        store.fs.invalidate_cache(store.root)
        try:
            store.fs.ls(store.root, detail=False)
        except FileNotFoundError:  # a prefix nothing was written to yet: fine, if its bucket exists
            if bucket is None:
                return store
            if bucket != store.root:
                store.fs.invalidate_cache(bucket)
                try:
                    store.fs.ls(bucket, detail=False)
                    return store
                except FileNotFoundError:
                    pass
            raise _no_bucket(store, bucket) from None
    return store


def store_access_error(store, err: BaseException) -> "StoreAccessError | None":
    """`err`, raised while using `store`, as a StoreAccessError when it says that the store cannot
    be reached or used (credentials, endpoint, bucket, permission); None for any other error."""
    if isinstance(err, StoreAccessError):
        return err
    store = open_store(store)
    if not store.remote:
        return None
    names = {cls.__name__ for cls in type(err).__mro__}
    protocol = store.protocol
    text = one_line(err) or type(err).__name__
    if names & {"NoCredentialsError", "PartialCredentialsError", "CredentialRetrievalError", "NoAuthTokenError"}:
        hint = ("set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY, or AWS_PROFILE" if protocol in ("s3", "s3a")
                else "configure the credentials of its client library")
        return StoreAccessError(store.uri, f"no credentials found ({text}); {hint}")
    if names & {"EndpointConnectionError", "ConnectTimeoutError", "ConnectionClosedError", "ProxyConnectionError",
                "ClientConnectorError", "ServerDisconnectedError"} or isinstance(err, (ConnectionError, TimeoutError)):
        endpoint = _endpoint(store, err)
        hint = "; check that it is up and that AWS_ENDPOINT_URL names it" if protocol in ("s3", "s3a") else ""
        return StoreAccessError(store.uri, f"cannot connect to its endpoint {endpoint} ({type(err).__name__}){hint}")
    bucket = _bucket(store)
    code = str(getattr(err, "response", {}).get("Error", {}).get("Code", "")) if hasattr(err, "response") else ""
    if bucket is not None and (code == "NoSuchBucket" or isinstance(err, FileNotFoundError)
                               and "bucket" in text.lower()):
        return _no_bucket(store, bucket)
    if isinstance(err, PermissionError) or code in ("AccessDenied", "InvalidAccessKeyId", "SignatureDoesNotMatch"):
        where = f"bucket {bucket!r}" if bucket is not None else "it"
        return StoreAccessError(store.uri, f"access denied ({text}); check that the credentials may read and "
                                           f"write {where}")
    return None


# %%
#| exporti
def _bucket(store) -> "str | None":
    """The bucket of a remote store whose protocol has buckets, else None."""
    protocol = store.protocol
    return store.root.split("/", 1)[0] if protocol in BUCKET_PROTOCOLS and store.root else None


def _no_bucket(store, bucket: str) -> StoreAccessError:
    protocol = store.protocol
    return StoreAccessError(store.uri, f"bucket {bucket!r} does not exist; create it (e.g. `aws s3 mb "
                                       f"{protocol}://{bucket}`) or name an existing bucket")


def _endpoint(store, err) -> str:
    """scheme://host:port of the endpoint the client tried (from the error, the client's settings
    or AWS_ENDPOINT_URL), else the service's default."""
    from urllib.parse import urlsplit

    candidates = [getattr(err, "kwargs", {}).get("endpoint_url") if isinstance(getattr(err, "kwargs", None), dict) else None,
                  (getattr(store.fs, "client_kwargs", None) or {}).get("endpoint_url"),
                  getattr(store.fs, "endpoint_url", None), os.environ.get("AWS_ENDPOINT_URL")]
    for url in candidates:
        if isinstance(url, str) and url:
            parts = urlsplit(url)
            return f"{parts.scheme}://{parts.netloc}" if parts.netloc else url
    return "(the service's default)"


@contextmanager
def _access_errors(store):
    """Raise the StoreAccessError of an error that says `store` cannot be used (others as they are)."""
    try:
        yield
    except Exception as err:
        access = store_access_error(store, err)
        if access is None or access is err:
            raise
        raise access from err


# %% [markdown]
# ## Pull and push
#
# `pull_run` makes the cache folder a copy of what the store holds for a run (the objects the newest
# manifest names, `run_objects`): the store is the truth, so a cached file the store lacks is
# deleted (a done marker left from an earlier try must not seal anything). `names` limits it to some files: the sweep's driver pulls only the sealed
# files to learn whether a run is finished, never the checkpoint. Every file is checked against the
# run's manifests before any of them replaces a cached one (`_Fence` below): a refused pull leaves
# the cache as it was.
#
# `push_run` is the holder's side: it renews and checks the lease, copies the files that changed
# since the last push (by size and modification time), in the order above, to its own objects,
# then the done marker to its own, and writes the manifest into the lease, checking again: the
# manifest that names a done marker is the seal. A file is uploaded
# from a hard link taken just before (training replaces its files by renaming new ones over them,
# which leaves the link alone), so the sha256 in the manifest is that of the bytes uploaded.

# %%
#| export
def pull_run(store: ResultsStore, scale: str, run: str, names=STORE_FILES) -> dict:
    """Copy the run's `names` from the store into store.run_dir; return {name: (mtime_ns, size,
    sha256)} of those now in the cache folder (what push_run need not send back). Raises
    StoreLeaseError, and changes nothing here, when a file was written by a worker that had lost the
    run's lease (see the top of this notebook)."""
    folder = store.run_dir(scale, run)
    folder.mkdir(parents=True, exist_ok=True)
    stored = store.stored_files(scale, run)
    fence, digests = _Fence(store, scale, run, stored), {}
    with ExitStack() as installs:  # every file is checked before any is renamed into place
        for name in names:
            if fence.object(name) is not None:
                tmp = installs.enter_context(atomic_path(folder / name))
                store.fs.get_file(store.key(scale, run, fence.object(name)), str(tmp))
                digests[name] = file_digest(tmp)
                fence.check(name, digests[name])
    for name in names:
        if fence.object(name) is None:
            (folder / name).unlink(missing_ok=True)
    return _stats(folder, digests)


def run_objects(store: ResultsStore, scale: str, run: str) -> dict:
    """{file name: the object of the run folder in the store that holds it} as readers see the run:
    the newest generation's own objects (.g<generation>.<name>), or the plain names of a run stored
    by an earlier version."""
    fence = _Fence(store, scale, run, store.stored_files(scale, run))
    return {name: fence.object(name) for name in STORE_FILES if fence.object(name) is not None}


def push_run(lease: "StoreLease", folder, pushed: dict | None = None) -> dict:
    """As the holder of `lease`: upload the files of the cache `folder` that differ from `pushed`
    ({name: (mtime_ns, size, sha256)}), delete from the store those `pushed` names that are gone
    here, and record the manifest in the lease; return the new `pushed`. The lease is renewed and
    checked first: when it was lost, or a done marker of another appeared, StoreLeaseError is raised
    and nothing is uploaded. done.json goes last, after a second check, and only if it existed when
    the push began."""
    store, scale, run = lease.store, lease.scale, lease.run
    folder, pushed = Path(folder), dict(pushed or {})
    sealed = (folder / "done.json").exists()
    lease.renew(pushed)
    if not sealed and pushed.pop("done.json", None) is not None:  # started over here: unsealed by the manifest
        lease.objects.pop("done.json", None)
        _remove(store, store.key(scale, run, "done.json"))  # and a seal of an earlier version's layout
    for name in STORE_FILES[:-1]:
        stamp = file_stamp(folder / name)
        if stamp is None:
            if pushed.pop(name, None) is not None:  # deleted here since (a run started over): not listed
                lease.objects.pop(name, None)
            continue
        if pushed.get(name, ())[:2] == stamp and name in lease.objects:
            continue  # an unchanged file this generation uploaded: a pulled one goes up once, as its own
        with link_snapshot(folder / name) as snap:
            if snap is None:  # replaced or removed meanwhile: the next push sees it
                continue
            state = (*file_stamp(snap), file_digest(snap))
            store.fs.put_file(str(snap), store.key(scale, run, lease.object_name(name)))
        pushed[name], lease.objects[name] = state, lease.object_name(name)
    seal = folder / "done.json" if sealed and (pushed.get("done.json", ())[:2] != file_stamp(folder / "done.json")
                                               or "done.json" not in lease.objects) else None
    with link_snapshot(seal) as snap:
        state = None if snap is None else (*file_stamp(snap), file_digest(snap))
        if state is not None:  # its own object, which nobody reads until the manifest below names it
            store.fs.put_file(str(snap), store.key(scale, run, lease.object_name("done.json")))
            lease.objects["done.json"] = lease.object_name("done.json")
        lease.files = {name: entry[2] for name, entry in pushed.items() if name in lease.objects} | (
            {"done.json": state[2]} if state else {})
        lease.renew(pushed)  # the manifest (with a done marker: the seal), then: still the holder?
        if state is not None:
            pushed["done.json"] = state
    return pushed


def _remove(store: ResultsStore, key: str) -> None:
    try:
        store.fs.rm_file(key)
    except FileNotFoundError:
        pass


def _stats(folder: Path, digests: dict) -> dict:
    return {name: (*stamp, digest) for name, digest in digests.items() if (stamp := file_stamp(folder / name)) is not None}


def refresh_finished(store: ResultsStore, scale: str, run: str) -> None:
    """For a remote store: bring the cache folder's sealed files up to date with the store, so that
    pemamoe.runs.verify_done on store.run_dir answers for the store (a no-op for a local store).
    Raises StoreLeaseError when a sealed file is not the one its sealer wrote."""
    if not store.remote:
        return
    folder = store.run_dir(scale, run)
    if _Fence(store, scale, run, store.stored_files(scale, run)).sealed:
        pull_run(store, scale, run, SEALED_FILES)
    elif (folder / "done.json").exists():  # the store has no seal: neither may the cache
        (folder / "done.json").unlink()


# %% [markdown]
# ## The lease
#
# `acquire` reads the newest lease of the run (and the single lease of earlier versions, if one is
# there) and creates the next generation; `renew` writes the heartbeat and the manifest, then
# `check`s; `check` lists the run once, which answers both questions: is there a newer lease, and
# is there a done marker that this worker does not know of? `release` marks the lease released,
# only while it is still the newest.

# %%
#| export
def _lease_name(generation: int) -> str:
    return f"{LEASE_PREFIX}{generation}.json"


def object_name(generation: int, name: str) -> str:
    """The object of the run folder in the store that generation `generation` writes `name` to:
    its own, which no other generation writes (a late upload lands there, never over another's)."""
    return f"{OBJECT_PREFIX}{generation}.{name}"


def lease_generations(names) -> list:
    """The generations of the lease objects among a run's stored file `names`, oldest first."""
    found = []
    for name in names:
        middle = name[len(LEASE_PREFIX):-len(".json")] if name.startswith(LEASE_PREFIX) and name.endswith(".json") else ""
        if middle.isdigit():
            found.append(int(middle))
    return sorted(found)


def _read_lease(store: ResultsStore, key: str) -> dict | None:
    try:
        body = json.loads(store.fs.cat_file(key))
    except FileNotFoundError:
        return None
    except (ValueError, UnicodeDecodeError):
        return {"heartbeat": 0.0}  # unreadable: treated as stale
    return body if isinstance(body, dict) else {"heartbeat": 0.0}


class StoreLease:
    """This worker's lease of one run in a remote store (see the top of this notebook): generation
    is its number once acquired, files the manifest it last wrote."""

    def __init__(self, store: ResultsStore, scale: str, run: str, stale_after: float | None = None):
        self.store, self.scale, self.run = store, scale, run
        self.stale_after = stale_after if stale_after is not None else _env_seconds(STALE_ENV, LEASE_STALE_SECONDS)
        self.owner = uuid.uuid4().hex
        self.generation, self.files, self.released = None, None, False
        self.objects = {}  # file name -> the object this generation uploaded it to

    @property
    def label(self) -> str:
        return f"{self.scale}/{self.run}"

    @property
    def key(self) -> str:
        return self._key(self.generation if self.generation is not None else "?")

    def _key(self, generation) -> str:
        return self.store.key(self.scale, self.run, _lease_name(generation))

    def object_name(self, name: str) -> str:
        return object_name(self.generation, name)

    def _body(self) -> bytes:
        return json.dumps({"owner": self.owner, "host": socket.gethostname(), "pid": os.getpid(),
                           "heartbeat": time.time(), "stale_after": self.stale_after, "generation": self.generation,
                           "released": self.released, "files": self.files,
                           "objects": self.objects if self.files is not None else None}).encode()

    def _live(self, holder: dict) -> bool:
        """Whether `holder`'s lease still counts, judged by the stale time its holder declared (its
        own sync interval set it), not this taker's: a taker with a shorter one takes no live lease.
        A lease that declares none, or a value out of bounds, is judged by this taker's."""
        return not holder.get("released") and time.time() - _heartbeat(holder) <= _declared_stale(holder, self.stale_after)

    def acquire(self) -> "StoreLease":
        stored = self.store.stored_files(self.scale, self.run)
        generations = lease_generations(stored)
        newest = generations[-1] if generations else 0
        for key in ([self._key(newest)] if generations else []) + \
                   ([self.store.key(self.scale, self.run, LEGACY_LEASE)] if LEGACY_LEASE in stored else []):
            holder = _read_lease(self.store, key)
            if holder is not None and self._live(holder):
                raise StoreLeaseError(key, holder)
        self.generation = newest + 1  # released, stale or none yet: the next generation
        try:
            with self.store.fs.open(self.key, "xb") as f:  # conditional put: of all takers of it, one wins
                f.write(self._body())
        except FileExistsError:
            key, self.generation = self.key, None
            raise StoreLeaseError(key, _read_lease(self.store, key) or {}) from None
        return self

    def check(self, pushed: dict | None = None) -> set:
        """The run's stored file names, once sure that this worker may still write the run: no newer
        lease exists and (with `pushed`, the files it knows the store holds) no done marker it did not
        see or write. Raises StoreLeaseError, one line, otherwise."""
        stored = self.store.stored_files(self.scale, self.run)
        newer = [g for g in lease_generations(stored) if g > self.generation]
        if newer:
            holder = _read_lease(self.store, self._key(newer[-1])) or {}
            raise StoreLeaseError(self._key(newer[-1]), holder,
                                  f"{self.label}: this worker lost its lease (generation {self.generation}) to generation "
                                  f"{newer[-1]} ({holder.get('host', '?')}, pid {holder.get('pid', '?')}); it writes "
                                  "nothing more to this run, and what it trains of it from now on is discarded")
        if pushed is not None and "done.json" in stored and "done.json" not in pushed:
            raise StoreLeaseError(self.key, {}, f"{self.label}: the run was sealed in the store by another worker "
                                                f"since generation {self.generation} checked it out; nothing goes "
                                                "over its done marker, and this worker writes nothing more to it")
        return stored

    def renew(self, pushed: dict | None = None) -> set:
        """Write the heartbeat (and the manifest), then check (above)."""
        self.store.fs.pipe_file(self.key, self._body())
        return self.check(pushed)

    def release(self) -> None:
        """Mark the lease released, if it is still the run's newest (else it is not ours to touch)."""
        if self.generation is None or self.released:
            return
        try:
            self.check()
        except StoreLeaseError:
            return
        self.released = True
        self.store.fs.pipe_file(self.key, self._body())


class _Fence:
    """What a run's leases say about who wrote which bytes: the newest generation that has pushed
    (`last`) lists the truth; see `check`."""

    def __init__(self, store: ResultsStore, scale: str, run: str, stored: set):
        self.store, self.scale, self.run = store, scale, run
        self.generations, self._files, self._objects = lease_generations(stored), {}, {}
        self.last = next((g for g in reversed(self.generations) if self.files(g) is not None), None)
        # The newest manifest that names its objects is the run; else (an earlier version's layout) the plain names.
        self.objects = self._objects.get(self.last) if self.last is not None else None
        if self.objects is None:
            self.objects = {name: name for name in stored if not name.startswith(".")}
        self.sealed = "done.json" in self.objects

    def files(self, generation: int) -> dict | None:
        if generation not in self._files:
            body = _read_lease(self.store, self.store.key(self.scale, self.run, _lease_name(generation))) or {}
            self._files[generation] = body.get("files") if isinstance(body.get("files"), dict) else None
            objects = body.get("objects")
            if isinstance(objects, dict) and self._files[generation] is not None:
                self._objects[generation] = {name: key for name, key in objects.items()
                                             if key == object_name(generation, name)}  # its own, no other
        return self._files[generation]

    def object(self, name: str) -> str | None:
        """The object readers read `name` from; None when the run has no such file."""
        return self.objects.get(name)

    def check(self, name: str, digest: str) -> None:
        """Refuse a file whose bytes only an older generation lists, and, under a done marker, one
        that the last generation does not list (store without leases of this kind: nothing to check).
        The last generation's own objects only it writes: under its seal, their bytes are its."""
        if self.last is None or self.files(self.last).get(name) == digest:
            return
        if self.last in self._objects and not self.sealed:
            return  # its own object, which it is replacing: the manifest of the new bytes follows
        run, lease, did = f"{self.scale}/{self.run}", self.generations[-1], "sealed" if self.sealed else "wrote"
        key = self.store.key(self.scale, self.run, _lease_name(self.last))
        older = [g for g in self.generations if g < self.last and (self.files(g) or {}).get(name) == digest]
        if older:
            raise StoreLeaseError(key, {}, f"{run}: {name} in the store is from generation {older[-1]}, older than "
                                           f"generation {self.last}, which {did} the run last (lease generation "
                                           f"{lease}): a worker that had lost the lease wrote it; refused (delete "
                                           "the run's folder in the store to train it again)")
        if self.sealed:
            raise StoreLeaseError(key, {}, f"{run}: {name} in the store is not the one generation {self.last} sealed "
                                           f"(no generation lists its bytes; lease generation {lease}): refused "
                                           "(delete the run's folder in the store to train it again)")


# %% [markdown]
# ## Checking runs out of the store
#
# `checked_out` is what one worker wraps around one population: it takes every run's lease, pulls
# each run into the cache, and, while the population trains, a thread pushes the changed files
# (renewing the leases first) every `SYNC_SECONDS`. When the population stops (finished, out of
# time, interrupted or failed), a last push and the release follow. A worker that dies without that
# (SIGKILL, a lost node) leaves the store as it was at its last sync, with stale leases: at most
# `SYNC_SECONDS` plus one checkpoint interval of training is lost.
#
# A push that finds the lease lost, or the run sealed by another, is not retried: the thread stops
# copying that run for good with one line on stderr (and stops altogether once it has lost every
# run), and the last push raises that `StoreLeaseError` after pushing the runs still this worker's.
# Other failures (the network) are retried at the next sync. The population itself trains on to its
# end (training has no hook to be stopped from outside); only its copies in the store are refused.

# %%
#| export
class _Mirror(threading.Thread):
    """Pushes the checked-out runs every `every` seconds; gives up a run for good when its lease is
    lost (`lost`: run index -> the StoreLeaseError), and ends when it has lost them all."""

    def __init__(self, store, folders, leases, pushed, every: float):
        super().__init__(name="pemamoe-store-mirror", daemon=True)
        self.store, self.folders, self.leases, self.pushed = store, folders, leases, pushed
        self.every, self.stop_event, self.lost = every, threading.Event(), {}

    def sync(self) -> None:
        for i, (folder, lease) in enumerate(zip(self.folders, self.leases)):
            if i in self.lost:
                continue
            try:
                self.pushed[i] = push_run(lease, folder, self.pushed[i])
            except StoreLeaseError as err:
                self.lost[i] = err
                print(f"[store] {err}", file=sys.stderr, flush=True)

    def run(self) -> None:
        while len(self.lost) < len(self.leases) and not self.stop_event.wait(self.every):
            try:
                self.sync()
            except Exception as err:  # noqa: BLE001 - training goes on; checked_out's last sync raises if it persists
                print(f"[store] sync to {self.store.uri} failed, retrying: {type(err).__name__}: {err}",
                      file=sys.stderr, flush=True)


@contextmanager
def checked_out(store: ResultsStore, runs: list):
    """Yield the local folders of `runs` ([(scale, run name), ...]) to train in. For a remote store:
    lease, pull, mirror while inside, push and release after (see above); StoreLeaseError after, when
    a run's lease was lost meanwhile."""
    store = open_store(store)
    runs = list(runs)
    if not store.remote:
        yield [store.run_dir(scale, run) for scale, run in runs]
        return
    leases = []
    try:
        with _access_errors(store):  # no credentials, no endpoint, no bucket: one line (above)
            for scale, run in runs:
                leases.append(StoreLease(store, scale, run).acquire())
            folders = [store.run_dir(scale, run) for scale, run in runs]  # their .lock stays local: never pushed
            pushed = [pull_run(store, scale, run) for scale, run in runs]
        mirror = _Mirror(store, folders, leases, pushed, _env_seconds(SYNC_ENV, SYNC_SECONDS))
        mirror.start()
        try:
            yield folders
        finally:
            mirror.stop_event.set()
            mirror.join()
            with _access_errors(store):
                mirror.sync()  # the last push of every run still this worker's: finished or not
            if mirror.lost:
                raise mirror.lost[min(mirror.lost)]
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
    folder itself). What a driver calls to read a run back, e.g. with pemamoe.populations.load_run.
    Raises StoreLeaseError when a file was written by a worker that had lost the run's lease."""
    store = open_store(store)
    if store.remote:
        pull_run(store, scale, run)
    return store.run_dir(scale, run)


# %% [markdown]
# ## Demonstration: a worker that stalls past the stale time
#
# Two workers with caches of their own share one run in an in-memory store (fsspec's `memory://`,
# which implements the exclusive create). A pushes and stalls; B finds A's lease stale, takes the
# run over as generation 2, trains it on and seals it. When A wakes, its push is refused before it
# uploads anything. Then the window no check can close: bytes of A's land anyway, with A's manifest
# of them, as if its check had passed just before the takeover. They land in A's own objects: the
# run a reader reads is still the one B sealed.

# %%
import tempfile

with tempfile.TemporaryDirectory() as tmp:
    url = "memory://fence-demo/results"
    store_a, store_b = ResultsStore(url, cache_dir=Path(tmp) / "a"), ResultsStore(url, cache_dir=Path(tmp) / "b")
    a = StoreLease(store_a, "ci", "demo-run", stale_after=0.05).acquire()
    folder_a = store_a.run_dir("ci", "demo-run")
    folder_a.mkdir(parents=True)
    (folder_a / "config.json").write_text("{}")
    (folder_a / "metrics.parquet").write_bytes(b"A's logs")
    pushed_a = push_run(a, folder_a)
    time.sleep(0.1)  # A stalls past the stale time
    b = StoreLease(store_b, "ci", "demo-run", stale_after=0.05).acquire()
    pushed_b = pull_run(store_b, "ci", "demo-run")
    folder_b = store_b.run_dir("ci", "demo-run")
    (folder_b / "metrics.parquet").write_bytes(b"B's logs, all of them")
    (folder_b / "done.json").write_text("{}")
    push_run(b, folder_b, pushed_b)
    b.release()

    def read_run():
        return {name: store_a.fs.cat_file(store_a.key("ci", "demo-run", key))
                for name, key in run_objects(store_a, "ci", "demo-run").items()}

    sealed = read_run()
    print(f"A generation {a.generation}, B generation {b.generation}; sealed by B:", sealed)
    (folder_a / "metrics.parquet").write_bytes(b"A's later logs")
    try:
        push_run(a, folder_a, pushed_a)
    except StoreLeaseError as err:
        print("A's push:", err)
    assert read_run() == sealed
    store_a.fs.put_file(str(folder_a / "metrics.parquet"), store_a.key("ci", "demo-run", a.object_name("metrics.parquet")))
    a.files = {**a.files, "metrics.parquet": file_digest(folder_a / "metrics.parquet")}
    store_a.fs.pipe_file(a.key, a._body())  # the late write and A's manifest of it
    refresh_finished(store_b, "ci", "demo-run")  # read as B sealed it: no error
    assert read_run() == sealed and (folder_b / "metrics.parquet").read_bytes() == b"B's logs, all of them"
    print("the run's objects after A's late write:", run_objects(store_a, "ci", "demo-run"))
    store_a.fs.rm(store_a.key("ci"), recursive=True)

# %% [markdown]
# ## Demonstration: a ci population through an in-memory store
#
# The same `memory://` filesystem stands in for a bucket here; `tests/test_store.py` runs the same
# code against a real S3 server, with a Ray sweep killed part way and resumed, and with a worker
# paused past the stale time while another takes its run over and seals it. A second worker asking
# for a run that is leased is refused; the population trains in the cache and leaves its run
# folders in the store, their leases released; the sweep's bookkeeping then finds them finished
# there.

# %%
from pemamoe.sweep_runner import RunSpec, execute_population, pending_runs

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
    leases = [json.loads(store.fs.cat_file(p)) for p in store.fs.find(store.root) if Path(p).name.startswith(LEASE_PREFIX)]
    assert not pending_runs(specs, url)[1] and leases and all(lease["released"] for lease in leases)
    del os.environ[CACHE_ENV]
