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
# # 09c · Appendix: executing a sweep
#
# Notebook 09 says *what* a sweep trains (the run specs of every experiment) and what `run_sweep`
# promises: every spec not yet done is trained, compatible runs train together as one population,
# finished runs are never retrained, and the run folders come back in the order of the specs. This
# appendix is *how*, in the module `pemamoe.sweep_runner`:
#
# * `RunSpec`, a run's name and its folder in the cache, and the run cache: which runs are done
#   (`pending_runs`), how the rest are grouped into populations (`group_specs`), `run_sweep` and
#   `sweep_records`;
# * `execute_population`, what one worker runs for one population;
# * the two backends: a local process pool (`_run_local`) and Ray (`_run_ray`, on a local instance
#   or on a cluster);
# * stopping: the signal handling of the sweep, the workers that die with it, the progress bar and
#   the report of failed runs; a time budget (`hours`), and where a long sweep stands (`--status`).
#
# `pemamoe.experiments` imports this module and re-exports its public names; this module knows nothing of
# the experiments. The command line, `python -m pemamoe sweep`, is appendix 09e.

# %%
#| default_exp sweep_runner

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %%
#| export
import dataclasses
import math
import os
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
import multiprocessing as mp

import numpy as np

from pemamoe.core import BACKENDS, DEFAULT_POPULATION  # re-export: in core, for the command line's options (00b)
from pemamoe.core import REPO_ROOT, Progress, atomic_write_json, check_scale, one_line
from pemamoe.env import compile_step_kernels
from pemamoe.mappo import TrainConfig, population_key
from pemamoe.train_config import training_numerics
from pemamoe.methods import METHOD_REGISTRY, method_spec
from pemamoe.records import (RECORDS_DIR, RecordError, drop_portable_state, find_record, portable_state_path,
                             portable_state_progress, record_files, record_timing, restore_portable_state,
                             verify_record, write_portable_state, write_record)
from pemamoe.runs import verify_done
from pemamoe.store import checked_out, open_store, pull_run, pull_tree, push_paths, refresh_finished

# %% [markdown]
# ## A run, and the run cache
#
# `RunSpec` is a run as notebook 09 describes it; `run_dir` is its folder in the cache,
# `<results_dir>/<scale>/<run name>`, the run name ending in the hash of the resolved config.

# %%
#| export
@dataclass(frozen=True)
class RunSpec:
    """One training run of a sweep; `to_config()` resolves it to a TrainConfig."""

    method: str
    seed: int = 0
    scale: str = "small"
    without: tuple = ()  # phase-controller mechanisms switched off (ablation)
    noise_gamma: float | None = None  # None: the preset's gamma0
    overrides: tuple = ()  # further TrainConfig.for_scale overrides, as sorted (key, value) pairs
    tag: str = field(default="", compare=False)  # which experiment asked for it; not part of the run

    def __post_init__(self):
        try:
            method_spec(self.method)  # the registry (plugins included)
        except ValueError:
            raise ValueError(f"RunSpec.method must be one of {', '.join(METHOD_REGISTRY)}, got {self.method!r}") from None
        check_scale(self.scale)
        if isinstance(self.seed, np.integer):  # e.g. seeds=np.arange(3): plain ints, so JSON can save them
            object.__setattr__(self, "seed", int(self.seed))
        if not isinstance(self.seed, int) or isinstance(self.seed, bool) or self.seed < 0:
            raise ValueError(f"RunSpec.seed must be an int >= 0, got {self.seed!r}")
        if isinstance(self.noise_gamma, np.floating):
            object.__setattr__(self, "noise_gamma", float(self.noise_gamma))
        object.__setattr__(self, "without", tuple(sorted(self.without)))
        object.__setattr__(self, "overrides", tuple(sorted(dict(self.overrides).items())))

    def to_config(self) -> TrainConfig:
        extra = dict(self.overrides)
        if self.without:
            extra["without"] = self.without
        if self.noise_gamma is not None:
            extra["noise_gamma"] = self.noise_gamma
        return TrainConfig.for_scale(self.scale, self.method, self.seed, **extra)

    def with_overrides(self, settings: dict) -> "RunSpec":
        """The same run with `settings` (for_scale overrides, e.g. from `--set`) over its own."""
        return dataclasses.replace(self, overrides=tuple({**dict(self.overrides), **settings}.items()))

    def run_dir(self, results_dir) -> Path:
        """The run's folder on this machine: in the results store's folder, or in its local cache
        when the store is a URL (appendix 09f)."""
        return open_store(results_dir).run_dir(self.scale, self.to_config().run_name())

    def label(self) -> str:
        parts = [self.method, f"seed {self.seed}"]
        if self.without:
            parts.append("without " + "+".join(self.without))
        if self.noise_gamma is not None:
            parts.append(f"gamma {self.noise_gamma:g}")
        return ", ".join(parts)


# %% [markdown]
# `run_sweep` drops finished runs first (`pending_runs`: a run is done when its folder's
# `done.json` verifies, notebook 07b, or its record does, appendix 09d; two specs that resolve to
# one folder train once). The record is looked up by `record_marker`, which takes the newest
# numerics version's record of the config (`find_record`, appendix 09d): after a bump of
# `TRAINING_NUMERICS` the committed records still count as done, and nothing is retrained. The
# run folder, by contrast, is always the current version's: an unfinished run of an older version
# cannot be resumed (appendix 07b), so such a config trains afresh in its new folder, the sweep says
# so (`older_unfinished`), and the old folder and portable state are left untouched. It then
# groups the rest into populations (`group_specs`: runs whose configs differ only in the member
# fields of notebook 07, at most `population` members each), then hands the populations to a
# backend: `local`, a pool of worker processes, or `ray`, Ray tasks on a local
# instance or on a cluster. Each worker trains its population with `train_population` (notebook
# 07), which resumes every member from its checkpoint and reads finished members back. SIGINT or
# SIGTERM stop the sweep without leaving workers behind and raise `SweepInterrupted`; rerunning the
# sweep resumes the killed runs. Both backends return the run folders in the order of the specs.

# %%
#| export
def group_specs(specs, population: int, workers: int = 1) -> list:
    """Pending runs as populations: runs whose configs share everything but the member fields
    (seed, controller settings, force_controller) go together, at most `population` per group,
    in the order they first appear. A compatible set larger than `population` is split into
    groups of near-equal size (21 with a cap of 16: 11 + 10, not 16 + 5: a small population costs
    far more per member, and with no more parts than workers, equal parts finish together). A
    group larger than the others is also split so that `workers` processes get work when there
    are fewer groups than workers."""
    groups = {}
    for spec in specs:
        groups.setdefault(population_key(spec.to_config()), []).append(spec)
    out = []
    for members in groups.values():
        size = population
        if len(groups) < workers:  # fewer populations than workers: spread each one over the workers
            size = min(size, max(1, -(-len(members) // max(1, workers // len(groups)))))
        parts = -(-len(members) // size)
        base, extra = divmod(len(members), parts)
        bounds = [0]
        for i in range(parts):
            bounds.append(bounds[-1] + base + (i < extra))
        out += [members[a:b] for a, b in zip(bounds, bounds[1:])]
    return out


def check_counts(**counts) -> None:
    """Each keyword must be an integer >= 1 (a bool is not): `name must be an integer >= 1, got X`."""
    for name, value in counts.items():
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{name} must be an integer >= 1, got {value!r}")


def pending_runs(specs, results_dir, records_dir=None, retrain: bool = False) -> tuple:
    """({run folder: spec}, the specs still to train: whose folder holds no verified finished run
    and, with records_dir, whose record does not verify either (retrain: records ignored). Two specs
    can resolve to one configuration (the main PE-MAMoE run is also the noise sweep's gamma = 0.005
    point): keyed by run folder, such a run is trained once, not twice at once. results_dir: a
    folder or a results store's URL (appendix 09f; its sealed files are read through the cache)."""
    store = open_store(results_dir)
    records_dir = _local_records(records_dir, specs)[0]
    by_folder = {}
    for spec in specs:
        by_folder.setdefault(spec.run_dir(store), spec)

    def done(folder, spec):
        config = spec.to_config()
        if records_dir is not None and not retrain and verify_record(record_marker(spec, records_dir), config):
            return True
        refresh_finished(store, spec.scale, folder.name)
        return verify_done(folder, config) is not None

    return by_folder, [spec for folder, spec in by_folder.items() if not done(folder, spec)]


def _local_records(records_dir, specs) -> tuple:
    """(a local records folder, the records' store when records_dir is a URL, else None): a URL's
    records of the specs' scales are pulled into its cache first (appendix 09f)."""
    if records_dir is None:
        return None, None
    records = open_store(records_dir)
    if not records.remote:
        return records_dir, None
    for scale in sorted({spec.scale for spec in specs}):
        pull_tree(records, scale)
    return records.folder, records


def record_marker(spec, records_dir=RECORDS_DIR) -> Path:
    """Where the record of `spec`'s run lives (its marker; appendix 09d): the newest numerics
    version's record of its config (`find_record`), else where the current version's will be."""
    return find_record(records_dir, spec.scale, spec.to_config())


def older_unfinished(specs, results_dir, records_dir=None) -> dict:
    """{spec: [paths]} of the specs whose config has unfinished work of an older numerics version
    (appendix 07c) on this machine: a run folder with a checkpoint and no done.json, or, with
    records_dir, a portable state. None of it can be resumed (appendix 07b); the sweep trains the
    config afresh under its current name and leaves these as they are."""
    store = open_store(results_dir)
    out = {}
    for spec in specs:
        names = list(spec.to_config().run_names().values())[1:]  # the older versions' names
        found = [store.run_dir(spec.scale, name) for name in names
                 if (store.run_dir(spec.scale, name) / "checkpoint.pt").exists()
                 and not (store.run_dir(spec.scale, name) / "done.json").exists()]
        if records_dir is not None:
            found += [p for p in (portable_state_path(records_dir, spec.scale, name) for name in names) if p.exists()]
        if found:
            out[spec] = found
    return out


def run_sweep(specs, backend: str = "local", workers: int = 2, results_dir="results", address=None,
              threads_per_run: int = 1, verbose: bool = True, progress: bool | None = None,
              population: int = DEFAULT_POPULATION, hours: float | None = None, records_dir=None,
              retrain: bool = False) -> list:
    """Run every spec not yet done; return all run folders, in the order of `specs`.

    records_dir: also keep the runs' records there (appendix 09d; a folder or a URL, appendix 09f): a run whose record verifies
    counts as done and is not trained (unless retrain), each run's record is written as it
    finishes, and a finished run folder without a record gets one. retrain: ignore the records,
    train into the cache whatever is not in it, and write every record again (byte-identical
    when nothing changed).

    hours: train for at most this long: then every running population checkpoints at the end of
    its current iteration and stops, no queued one starts, and the sweep returns (rerun it to go
    on; nothing is lost but the iteration in flight). The folders of unfinished runs are returned
    too: check them with pemamoe.runs.verify_done, or call pending_runs.

    A run counts as done only when its done.json (or record) verifies (a corrupt or foreign one
    raises). progress: a `Progress` of runs done out of all (cached ones counted), with an ETA;
    None: only when stderr is a terminal. SIGINT or SIGTERM kill the running runs, start no
    queued one and raise SweepInterrupted (rerun to resume)."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    check_counts(workers=workers, threads_per_run=threads_per_run, population=population)
    if hours is not None and not (isinstance(hours, (int, float)) and not isinstance(hours, bool)
                                  and math.isfinite(hours) and hours > 0):
        raise ValueError(f"hours must be a number > 0, got {hours!r}")
    deadline = None if hours is None else time.time() + 3600.0 * hours
    store = open_store(results_dir)  # checks it: a folder path or a URL fsspec knows
    specs = list(specs)
    records_dir, records_store = _local_records(records_dir, specs)
    by_folder, todo = pending_runs(specs, store, records_dir, retrain)
    groups = group_specs(todo, population, workers)
    if verbose:
        print(f"[sweep] {len(by_folder)} runs, {len(by_folder) - len(todo)} cached, {len(todo)} to run "
              f"as {len(groups)} populations on {backend} ({workers} workers)", flush=True)
        stale = older_unfinished(todo, store, records_dir)
        if stale:
            first = next(iter(stale.values()))[0]
            print(f"[sweep] {len(stale)} of them have unfinished work of an older training numerics version (e.g. "
                  f"{first}), which cannot be resumed under version {training_numerics()}: they train afresh under "
                  "their new names, and the old folders and portable states are left as they are", flush=True)
    if todo:
        start = time.perf_counter()
        compile_step_kernels()  # once here, so that the workers load the compiled env rather than race to build it
        runner = _run_local if backend == "local" else _run_ray
        with _progress(len(by_folder), len(by_folder) - len(todo), progress, verbose) as report, _stop_on_signals():
            remote = store.remote or records_store is not None
            if remote and records_dir is not None:  # the workers may be elsewhere: records are written here
                report = _recording(report, store, records_dir, records_store)
            runner(groups, store, workers, address, threads_per_run, report, deadline,
                   None if remote else records_dir)
        left = pending_runs(specs, store, records_dir, retrain)[1]
        if verbose and left:
            print(f"[sweep] stopped after {hours} h ({time.perf_counter() - start:.0f} s): "
                  f"{len(todo) - len(left)} of {len(todo)} runs finished, {len(left)} left, checkpointed; "
                  "rerun the same command to go on", flush=True)
        elif verbose:
            print(f"[sweep] finished {len(todo)} runs in {time.perf_counter() - start:.0f} s", flush=True)
    if records_dir is not None:  # finished folders without a (verified) record, e.g. trained before records
        for folder, spec in by_folder.items():
            config = spec.to_config()
            marker = record_files(records_dir, spec.scale, folder.name)["marker"]  # this version's: the folder's
            if verify_done(folder, config) and (retrain or not _record_ok(marker, config)):
                _write_record_from(store, folder, spec.scale, records_dir, records_store)
    return [s.run_dir(store) for s in specs]


def _write_record_from(store, folder, scale: str, records_dir, records_store=None) -> None:
    """write_record of a finished run folder; from a remote store, after pulling its checkpoint
    (the record keeps the final actor; both callers have just refreshed the sealed files); to a
    records URL, uploaded after, marker last."""
    if store.remote:
        pull_run(store, scale, folder.name, ("checkpoint.pt",))
    write_record(folder, scale, records_dir)
    if records_store is not None:
        files = record_files(records_dir, scale, folder.name)
        push_paths(records_store, [files[k] for k in ("data", "actor", "timing", "marker") if files[k].exists()])


def _recording(report, store, records_dir, records_store=None):
    """report(spec), after writing the record of the run that just finished (remote stores)."""
    def record_then_report(spec):
        folder = spec.run_dir(store)
        refresh_finished(store, spec.scale, folder.name)
        if verify_done(folder, spec.to_config()):
            _write_record_from(store, folder, spec.scale, records_dir, records_store)
        report(spec)

    return record_then_report


def sweep_records(specs, backend: str = "local", workers: int = 2, results_dir="results", address=None,
                  records_dir=RECORDS_DIR, retrain: bool = False, **options) -> list:
    """The record markers of every spec, in order, training only the runs without a record
    (`run_sweep` with records_dir; retrain: ignore the records). What the notebooks read."""
    specs = list(specs)
    run_sweep(specs, backend, workers, results_dir, address, records_dir=records_dir, retrain=retrain, **options)
    return [record_marker(spec, open_store(records_dir).folder) for spec in specs]  # a URL's: in its cache


def _record_ok(marker, config) -> bool:
    try:
        return verify_record(marker, config) is not None
    except RecordError:  # a damaged record of a run whose folder is here: written again from the folder
        return False

# %% [markdown]
# ## One population, in one worker
#
# `execute_population` is what a worker runs: it caps torch at the worker's thread budget,
# resolves a group of compatible specs and calls `train_population` (notebook 07), which resumes
# each member from its checkpoint and reads finished members back. Beside each run it leaves a
# `sweep.json` with the spec that first asked for it, the seconds the population took and its size
# (for the benchmarks; the figures read the run's own `config.json`). The backends hand the
# populations out:
#
# * `local`: a `ProcessPoolExecutor` with the `spawn` start method (no fork of a process that has
#   already started torch threads); with one worker, the populations run in the sweep's own process;
# * `ray`: each population is a Ray task needing one CPU. `ray.init(address=...)` joins a cluster when an
#   address is given (or `RAY_ADDRESS` is set) and starts a local Ray instance otherwise.
#
# Where the run folders live is the **results store** (appendix 09f): a folder (`results/`) or a
# URL such as `s3://bucket/prefix`. Every backend hands a worker the store's URL, never a path that
# only the driver's disk has. With a URL, the worker leases each run of its population, pulls it into
# its own cache, copies the changed files back every `SYNC_SECONDS` while it trains and once more
# when it stops; the driver learns which runs are done from the store's sealed files, and writes the
# records itself, as each population ends (the workers may be on nodes whose disks it never sees).
# A remote store leaves no portable states: the store already outlives the machine.

# %%
#| export
class SweepInterrupted(KeyboardInterrupt):
    """The sweep was stopped by SIGINT or SIGTERM (`signum`); running runs were killed, queued
    ones never started, and a rerun resumes them from their checkpoints."""

    def __init__(self, signum: int):
        self.signum = signum
        super().__init__(f"sweep stopped by {signal.Signals(signum).name}")

    def __reduce__(self):  # pickled with its signal number (a process pool sends exceptions back)
        return type(self), (self.signum,)


class SweepRunError(RuntimeError):
    """A run of the sweep failed (the other populations ran on first): one line naming the run's
    spec (`label`) and what went wrong (`problem`); the first failure is its `__cause__`."""

    def __init__(self, label: str, problem: str, others: int = 0):
        self.label, self.problem, self.others = label, problem, others
        more = f" ({others} other run{'s' if others != 1 else ''} failed too)" if others else ""
        super().__init__(one_line(f"sweep run {label} failed: {problem}{more}"))

    def __reduce__(self):
        return type(self), (self.label, self.problem, self.others)


def execute_population(specs, results_dir, threads: int = 1, deadline: float | None = None,
                       records_dir=None) -> list:
    """Train compatible runs as one population (notebook 07), each in its own folder (resuming or
    skipping as that folder allows); return the folders of the runs that are finished. deadline: a
    `time.time()` after which nothing starts and a running population checkpoints and stops.
    records_dir: write each finished run's record there (appendix 09d), as the population ends;
    resume a run from its portable state there when this machine's folder is behind, and leave a
    portable state for each run the deadline stopped. results_dir: a folder, or a results store's
    URL (appendix 09f): then each run is leased, pulled into this machine's cache, copied back to
    the store while it trains and when it stops, and the lease released."""
    import torch

    if deadline is not None and time.time() >= deadline:
        return []
    torch.set_num_threads(threads)
    specs = list(specs)
    with checked_out(results_dir, [(spec.scale, spec.to_config().run_name()) for spec in specs]) as dirs:
        return _train_checked_out(specs, dirs, threads, deadline, records_dir)


def _train_checked_out(specs, dirs, threads, deadline, records_dir) -> list:
    from pemamoe.mappo import train_population

    if records_dir is not None:
        for spec, run_dir in zip(specs, dirs):
            restore_portable_state(run_dir, spec.scale, records_dir)
    start = time.perf_counter()
    train_population([spec.to_config() for spec in specs], dirs, resume=True, threads=threads, progress=False,
                     deadline=deadline)
    finished = [d for spec, d in zip(specs, dirs) if verify_done(d, spec.to_config())]
    for spec, run_dir in zip(specs, dirs):
        marker = run_dir / "sweep.json"
        if run_dir in finished and not marker.exists():
            atomic_write_json(marker, {"spec": dataclasses.asdict(spec), "seconds": time.perf_counter() - start,
                                       "population": len(specs)})
        if records_dir is None:
            continue
        if run_dir in finished:
            write_record(run_dir, spec.scale, records_dir)
            drop_portable_state(run_dir.name, spec.scale, records_dir)
        else:  # stopped by the deadline: what it has done so far travels with the records
            write_portable_state(run_dir, spec.scale, records_dir)
    return [str(d) for d in finished]


def _report_finished(group, finished, report) -> None:
    """report(spec) for each run of `group` whose folder is among `finished` (paths)."""
    done = {Path(f).name for f in finished}
    for spec in group:
        if spec.to_config().run_name() in done:
            report(spec)

# %% [markdown]
# ## Stopping a sweep
#
# A sweep must stop when asked and must not leave workers behind:
#
# * **SIGINT / SIGTERM** on the sweep raise `SweepInterrupted` in its main thread; the backend then
#   kills the running workers (the process pool's processes; Ray tasks by `ray.cancel(force=True)`)
#   and drops the queue. Killing is safe: every file of a run is written atomically, the OS drops a
#   dead run's lock, and the next sweep resumes the run from its last checkpoint. Workers ignore
#   SIGINT themselves (a Ctrl-C reaches the whole process group), so the sweep alone decides.
# * **SIGKILL of the sweep** cannot be caught, so each worker watches its parent: on Linux the
#   kernel sends it SIGKILL when the parent dies (`prctl(PR_SET_PDEATHSIG)`), and a watchdog thread
#   checks `os.getppid()` twice a second everywhere.
# * A run that **fails** does not stop the others; the first error is raised once they are done.

# %%
#| exporti
def _worker_init(parent_pid: int) -> None:
    """Process-pool worker initializer: leave SIGINT to the sweep, and die with the sweep."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG = 1
        except (OSError, AttributeError):
            pass  # the watchdog below still works
    if os.getppid() != parent_pid:  # the sweep died before we got here
        os._exit(1)

    def watchdog():
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watchdog, name="pemamoe-parent-watchdog", daemon=True).start()


@contextmanager
def _stop_on_signals():
    """In the main thread: SIGINT and SIGTERM raise SweepInterrupted (old handlers restored after;
    nestable, so a backend that installs its own handlers, as ray.init does, can take them back)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    fired = []

    def handler(signum, frame):
        if fired:  # already stopping: a second Ctrl-C must not interrupt the clean-up
            return
        fired.append(signum)
        raise SweepInterrupted(signum)

    old = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    except SweepInterrupted:
        raise
    except KeyboardInterrupt as err:  # Ray turns a signal that arrives inside ray.wait into its own
        raise SweepInterrupted(fired[0] if fired else signal.SIGINT) from err
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


@contextmanager
def _progress(total: int, cached: int, progress, verbose: bool):
    """Yield report(spec): one more run done (a `Progress` of runs, and a line when verbose)."""
    with Progress(total, cached, label="sweep", unit="run", enabled=progress) as bar:
        def report(spec):
            bar.update(1)
            if verbose:
                (bar.write if bar.enabled else print)(f"[sweep] done: {spec.label()}")
                sys.stdout.flush()

        yield report


def _finish(errors: list) -> None:
    if errors:
        group, err = errors[0]
        spec = group[0] if isinstance(group, list) else group
        raise SweepRunError(spec.label(), _problem(err), len(errors) - 1) from err


def _problem(err: BaseException) -> str:
    """What went wrong, for SweepRunError's line: the project's own errors as they say it (each
    names its file, folder or store), any other prefixed with its type; a Ray task's error is
    its cause (Ray's text carries the remote traceback)."""
    from pemamoe.runs import RunFolderError, RunLockedError
    from pemamoe.store import StoreAccessError, StoreLeaseError

    if type(err).__name__.startswith("RayTaskError") and isinstance(getattr(err, "cause", None), BaseException):
        err = err.cause
    if isinstance(err, RunFolderError):  # a sweep has no resume=False: it says what to delete
        return err.message("delete the run folder to train the run again from the start")
    own = (RunLockedError, RecordError, StoreLeaseError, StoreAccessError)
    return str(err) if isinstance(err, own) else f"{type(err).__name__}: {err}"


def _run_local(groups, results_dir, workers, address, threads, report, deadline=None, records_dir=None):
    errors = []
    if workers == 1:  # in this process: a signal interrupts the run itself, its lock is released
        for group in groups:
            try:
                finished = execute_population(group, results_dir, threads, deadline, records_dir)
            except Exception as err:  # noqa: BLE001 - reported after the others ran
                errors.append((group, err))
                continue
            _report_finished(group, finished, report)
        return _finish(errors)
    pool = ProcessPoolExecutor(max_workers=min(workers, len(groups)), mp_context=mp.get_context("spawn"),
                               initializer=_worker_init, initargs=(os.getpid(),))
    try:
        records = None if records_dir is None else str(records_dir)
        futures = {pool.submit(execute_population, group, results_dir, threads, deadline, records): group
                   for group in groups}
        for future in as_completed(futures):
            try:
                finished = future.result()
            except Exception as err:  # noqa: BLE001 - a failed population does not stop the others
                errors.append((futures[future], err))
                continue
            _report_finished(futures[future], finished, report)
    except BaseException:  # SweepInterrupted (or anything else): kill the workers, start nothing more
        _kill_pool(pool)
        raise
    pool.shutdown(wait=True)
    _finish(errors)


def _kill_pool(pool) -> None:
    procs = list((getattr(pool, "_processes", None) or {}).values())
    for p in procs:  # first, so that no idle worker picks up a queued run
        if p.is_alive():
            p.kill()
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        p.join(timeout=10)


def _start_local_ray(workers: int, attempts: int = 3) -> None:
    """ray.init of a local instance. Ray gives its node a fixed 30 s to register and gives up
    otherwise; on a busy 2-core machine that happens now and then, so try again (a fresh node)."""
    import psutil
    import ray

    for attempt in range(attempts):
        before = {p.pid for p in psutil.Process().children(recursive=True)}
        try:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False,
                     runtime_env={"env_vars": {"PYTHONPATH": str(REPO_ROOT)}})
            return
        except Exception as err:  # noqa: BLE001 - Ray raises a bare Exception for this
            ray.shutdown()
            # a failed ray.init leaves the processes it started (GCS, raylet, workers) running
            stray = [p for p in psutil.Process().children(recursive=True) if p.pid not in before]
            for p in stray:
                try:
                    p.kill()
                except psutil.NoSuchProcess:
                    pass
            psutil.wait_procs(stray, timeout=10)
            if "timed out during startup" not in str(err) or attempt == attempts - 1:
                raise
            print(f"[sweep] the local Ray node did not start in time ({attempt + 1}/{attempts}); trying again",
                  flush=True)


def _run_ray(groups, results_dir, workers, address, threads, report, deadline=None, records_dir=None):
    import ray

    address = address or os.environ.get("RAY_ADDRESS")
    started_here = not ray.is_initialized()
    if started_here:
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            _start_local_ray(workers)
    errors, pending = [], []
    try:
        with _stop_on_signals():  # again after ray.init, which may install handlers of its own
            task = ray.remote(num_cpus=threads)(execute_population)
            records = None if records_dir is None else str(Path(records_dir).resolve())
            store = open_store(results_dir)  # a task gets the store's URL, never a path only this node has
            where = store.uri if store.remote else str(store.folder.resolve())
            refs = {task.remote(group, where, threads, deadline, records): group
                    for group in groups}
            pending = list(refs)
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                try:
                    finished = ray.get(done[0])
                except Exception as err:  # noqa: BLE001 - a failed population does not stop the others
                    errors.append((refs[done[0]], err))
                    continue
                _report_finished(refs[done[0]], finished, report)
    except BaseException:  # SweepInterrupted: kill the running tasks, drop the queued ones
        for ref in pending:
            ray.cancel(ref, force=True)
        raise
    finally:
        if started_here:
            ray.shutdown()
    _finish(errors)

# %% [markdown]
# A signal that reaches the sweep becomes `SweepInterrupted` in its main thread, and the old handler
# is back afterwards. A failed run is reported in one line (`SweepRunError`) with its spec's label
# once the others have finished. Both are staged below, so the lines they print (in a `make
# figures` log too) are expected output, and say so:

# %%
if threading.current_thread() is threading.main_thread():  # elsewhere the sweep installs no handler
    _before = signal.getsignal(signal.SIGTERM)
    try:
        with _stop_on_signals():
            signal.raise_signal(signal.SIGTERM)
            time.sleep(1)  # the handler raises before this ends
        raise AssertionError("SIGTERM did not stop the sweep")
    except SweepInterrupted as stop:
        print(f"expected (a staged signal): {stop!r}, signum {stop.signum}")
    assert signal.getsignal(signal.SIGTERM) is _before

try:
    _finish([([RunSpec("mlp", 0, "ci")], ValueError("a staged failure")),
             ([RunSpec("mlp", 1, "ci")], ValueError("a staged failure"))])
except SweepRunError as err:
    print(f"expected (two staged failures, no run trained): {err}")

# %% [markdown]
# ## A sweep that advances a few hours at a time
#
# A campaign longer than one machine's life runs as a series of sweeps of the same command, each
# given a time budget: `python -m pemamoe sweep ... --hours H` (`run_sweep(..., hours=H)`). The
# budget becomes a deadline on the wall clock (`time.time()`, the same on every worker of a
# cluster). Once it passes, no queued population starts, and each running one finishes the
# iteration in flight, writes a checkpoint of every member and returns; the trainer's resume is
# bit for bit (tests/test_sweep.py trains a population through a deadline and compares it with one
# that ran straight through). The command then prints how many runs finished and the `--status`
# table of what is left. The next sweep, here or on another machine that has the run folders,
# picks up where this one stopped.
#
# With `records_dir` (the command line's `--records-dir`, `records/` by default), each worker
# writes the record of every run its population finished (appendix 09d) before it returns, so the
# records of a campaign grow as its populations finish, and a run whose record verifies is never
# trained again (`--retrain` trains it into the cache anyway and writes its record again).
#
# A population the deadline stopped (`--hours`) leaves the portable state of each unfinished run
# in `records/<scale>/in_progress/` (appendix 09d). Committed with the records, it lets the sweep
# go on on another machine: before a population starts, each member whose local folder is behind
# its portable state is resumed from it, and no iteration is trained twice. A campaign that lives
# longer than its machines is then: `sweep --hours H`, commit `records/`, and the same command on
# the next machine.
#
# With a results store at a URL (`--results-dir s3://...`, appendix 09f) the store itself outlives
# the machine: the deadline's last push leaves every unfinished run's checkpoint in the bucket, the
# next sweep, anywhere, pulls it from there, and no portable state is written.

# %% [markdown]
# ## Where a long sweep stands
#
# A `medium` sweep trains for hours, across interruptions. `sweep_status` says where it stands
# without training anything: it groups the unfinished runs into the populations `run_sweep` would
# start now (the same `group_specs` call) and reads each member's `metrics.parquet`, which grows at
# every checkpoint (or, for a run this machine has not restored yet, the iteration of its committed
# portable state). Per population it reports the iteration every member has reached, the seconds
# one iteration of the whole population takes and the hours left at that rate. The rate comes from
# the logged `wall_time` (the run's own clock, which stops between sessions) over the last 500
# iterations, so it includes the checkpoints, whose cost grows with the logs. A process that was
# paused (`kill -STOP`, a suspended laptop) shows up as one very long step; a step longer than five
# times the typical checkpoint step (the median of the largest steps, about two per checkpoint in
# the window) and longer than a minute is taken for a pause and left out. A population that has
# not logged anything yet has no rate, and the summary says how many it leaves out. With W workers
# the sweep needs at least the larger of (hours left)/W and the longest population's
# hours. `python -m pemamoe sweep ... --status` prints it.

# %%
#| export
STATUS_WINDOW = 500  # logged iterations (five checkpoints at the medium preset) that give a population's rate
STATUS_MIN_PAUSE_S = 60.0  # no step shorter than this is taken for a pause


def _logged_progress(run_dir: Path, checkpoint_every: int) -> tuple:
    """(iterations logged, wall seconds per iteration over the last STATUS_WINDOW, pauses left
    out, or None when fewer than two iterations are logged)."""
    from pemamoe.runs import read_parquet

    path = run_dir / "metrics.parquet"
    if not path.is_file():
        return 0, None
    m = read_parquet(path)
    if len(m) < 2 or "wall_time" not in m:
        return len(m), None
    steps = m["wall_time"].tail(STATUS_WINDOW + 1).diff().dropna()
    # members checkpoint one after another, so a checkpoint lengthens two steps of each member's log
    typical_big = steps.nlargest(2 * (len(steps) // checkpoint_every) + 1).median()
    kept = steps[steps <= max(STATUS_MIN_PAUSE_S, 5 * typical_big)]
    return len(m), float(kept.mean())


def sweep_status(specs, results_dir="results", population: int | None = None, workers: int = 2,
                 records_dir=None):
    """Where a sweep stands, without training: one row per population `run_sweep` would start now
    (its methods, members, the iteration all have reached, of how many, wall seconds per population
    iteration, hours left); DataFrame.attrs holds the numbers of finished and of all runs, and
    `spent_hours`, the training compute that the `timed` finished runs' records measured
    (worker-hours; NaN when none has a record with a timing)."""
    import pandas as pd

    population = DEFAULT_POPULATION if population is None else population
    check_counts(population=population, workers=workers)
    results_dir = open_store(results_dir)
    records_dir = _local_records(records_dir, specs)[0]  # a URL's records pulled once, here
    by_folder, todo = pending_runs(specs, results_dir, records_dir)
    rows = []
    for i, group in enumerate(group_specs(todo, population, workers)):
        config = group[0].to_config()
        total = config.iterations
        if results_dir.remote:  # the logs as far as the store has them
            for spec in group:
                pull_run(results_dir, spec.scale, spec.run_dir(results_dir).name, ("metrics.parquet",))
        progress = [_logged_progress(spec.run_dir(results_dir), config.checkpoint_every) for spec in group]
        if records_dir is not None:  # a committed portable state not restored here yet counts as reached,
            # and lends its average rate where this machine has logged none
            carried = [portable_state_progress(records_dir, spec.scale, spec.run_dir(results_dir).name) or (0, None)
                       for spec in group]
            progress = [(max(n, c), rate if rate is not None else c_rate)
                        for (n, rate), (c, c_rate) in zip(progress, carried)]
        reached = min(n for n, _ in progress)
        rates = [r for _, r in progress if r is not None]
        seconds = max(rates) if rates else float("nan")
        rows.append({"group": i, "methods": "+".join(sorted({s.method for s in group})), "members": len(group),
                     "iteration": reached, "of": total, "s_per_iteration": seconds,
                     "hours_left": (total - reached) * seconds / 3600})
    table = pd.DataFrame(rows, columns=["group", "methods", "members", "iteration", "of", "s_per_iteration",
                                        "hours_left"])
    pending = set(todo)  # by_folder's own specs: one per run, however many experiments share it
    timed = [] if records_dir is None else [
        t["member_compute_s"] for spec in by_folder.values() if spec not in pending
        if "member_compute_s" in (t := record_timing(record_marker(spec, records_dir)))]
    table.attrs.update(finished=len(by_folder) - len(todo), runs=len(by_folder), timed=len(timed),
                       spent_hours=sum(timed) / 3600 if timed else float("nan"))
    return table


def status_summary(table, workers: int) -> str:
    """One paragraph for `sweep_status`'s table: finished runs, hours left, a lower bound on the wall time."""
    done = f"{table.attrs['finished']} of {table.attrs['runs']} runs finished"
    if table.attrs.get("timed"):
        done += (f" ({table.attrs['timed']} record{'s' if table.attrs['timed'] != 1 else ''} measured "
                 f"{table.attrs['spent_hours']:.2f} worker-hours of training)")
    if table.empty:
        return f"{done}; nothing left to train."
    known = table.dropna(subset=["hours_left"])
    unknown = len(table) - len(known)
    text = f"{done}; {len(table)} populations to run ({int(table.members.sum())} runs)."
    if known.empty:
        return text + " None has logged an iteration yet, so there is no measured rate."
    hours, longest = float(known.hours_left.sum()), float(known.hours_left.max())
    text += f" Measured rates leave {hours:.2f} worker-hours"
    if unknown:
        text += f", plus {unknown} population{'s' if unknown != 1 else ''} with no rate yet"
    return text + (f"; on {workers} worker{'s' if workers != 1 else ''} at least "
                   f"{max(hours / workers, longest):.2f} h of wall time.")

# %% [markdown]
# The status of this scale's `main` experiment (nothing is trained here):

# %%
from pemamoe.core import repo_path
from pemamoe.experiments import experiment_specs

_status = sweep_status(experiment_specs("main", scale), repo_path("results"), workers=2, records_dir=repo_path("records"))
print(status_summary(_status, workers=2))
_status
