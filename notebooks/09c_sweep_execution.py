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
# appendix is *how* the runs get executed, in the module `pemamoe.execution`:
#
# * `execute_population`, what one worker runs for one population;
# * the two backends: a local process pool (`_run_local`) and Ray (`_run_ray`, on a local instance
#   or on a cluster);
# * stopping: the signal handling of the sweep, the workers that die with it, the progress bar and
#   the report of failed runs;
# * the command line, `python -m pemamoe sweep`.
#
# The module does not import `pemamoe.sweep` at load time (the command line imports it when it
# runs); `pemamoe.sweep` imports this module and re-exports `SweepInterrupted`,
# `execute_population` and `sweep_cli`, so `from pemamoe.sweep import sweep_cli` keeps working.

# %%
#| default_exp execution

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %%
#| export
import dataclasses
import os
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from pathlib import Path
import multiprocessing as mp

from pemamoe.core import REPO_ROOT, atomic_write_json, check_scale
from pemamoe.methods import METHOD_REGISTRY, compared_methods, method_spec
from pemamoe.records import PORTABLE_DIR, drop_portable_state, restore_portable_state, write_portable_state, write_record
from pemamoe.runs import verify_done

BACKENDS = ("local", "ray")

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


def execute_population(specs, results_dir, threads: int = 1, deadline: float | None = None,
                       records_dir=None) -> list:
    """Train compatible runs as one population (notebook 07), each in its own folder (resuming or
    skipping as that folder allows); return the folders of the runs that are finished. deadline: a
    `time.time()` after which nothing starts and a running population checkpoints and stops.
    records_dir: write each finished run's record there (appendix 09d), as the population ends;
    resume a run from its portable state there when this machine's folder is behind, and leave a
    portable state for each run the deadline stopped."""
    import torch

    from pemamoe.mappo import train_population

    if deadline is not None and time.time() >= deadline:
        return []
    torch.set_num_threads(threads)
    specs = list(specs)
    dirs = [spec.run_dir(results_dir) for spec in specs]
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
    """Yield report(spec): one more run done (a tqdm bar, and a line when verbose)."""
    from tqdm.auto import tqdm

    if progress is None:
        progress = sys.stderr.isatty()
    bar = tqdm(total=total, initial=cached, desc="sweep", unit="run", disable=not progress, dynamic_ncols=True)

    def report(spec):
        bar.update(1)
        if verbose:
            (bar.write if progress else print)(f"[sweep] done: {spec.label()}")
            sys.stdout.flush()

    try:
        yield report
    finally:
        bar.close()


def _finish(errors: list) -> None:
    if errors:
        group, err = errors[0]
        spec = group[0] if isinstance(group, list) else group
        more = f" ({len(errors) - 1} other runs failed too)" if len(errors) > 1 else ""
        raise RuntimeError(f"sweep run {spec.label()} failed: {type(err).__name__}: {err}{more}") from err


def _run_local(groups, results_dir, workers, address, threads, report, deadline=None, records_dir=None):
    errors = []
    if workers == 1:  # in this process: a signal interrupts the run itself, its lock is released
        for group in groups:
            try:
                finished = execute_population(group, str(results_dir), threads, deadline, records_dir)
            except Exception as err:  # noqa: BLE001 - reported after the others ran
                errors.append((group, err))
                continue
            _report_finished(group, finished, report)
        return _finish(errors)
    pool = ProcessPoolExecutor(max_workers=min(workers, len(groups)), mp_context=mp.get_context("spawn"),
                               initializer=_worker_init, initargs=(os.getpid(),))
    try:
        records = None if records_dir is None else str(records_dir)
        futures = {pool.submit(execute_population, group, str(results_dir), threads, deadline, records): group
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
            refs = {task.remote(group, str(Path(results_dir).resolve()), threads, deadline, records): group
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
# is back afterwards. A failed run is reported with its spec's label once the others have finished:

# %%
from pemamoe.sweep import RunSpec

if threading.current_thread() is threading.main_thread():  # elsewhere the sweep installs no handler
    _before = signal.getsignal(signal.SIGTERM)
    try:
        with _stop_on_signals():
            signal.raise_signal(signal.SIGTERM)
            time.sleep(1)  # the handler raises before this ends
        raise AssertionError("SIGTERM did not stop the sweep")
    except SweepInterrupted as stop:
        print(f"{stop!r}, signum {stop.signum}")
    assert signal.getsignal(signal.SIGTERM) is _before

try:
    _finish([([RunSpec("mlp", 0, "ci")], ValueError("out of memory")),
             ([RunSpec("mlp", 1, "ci")], ValueError("out of memory"))])
except RuntimeError as err:
    print(err)

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

# %% [markdown]
# ## Where a long sweep stands
#
# A `medium` sweep trains for hours, across interruptions. `sweep_status` says where it stands
# without training anything: it groups the unfinished runs into the populations `run_sweep` would
# start now (the same `group_specs` call) and reads each member's `metrics.parquet`, which grows at
# every checkpoint. Per population it reports the iteration every member has reached, the seconds
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
    iteration, hours left); DataFrame.attrs holds the numbers of finished and of all runs."""
    import pandas as pd

    from pemamoe.sweep import DEFAULT_POPULATION, check_counts, group_specs, pending_runs  # the sweep imports this module

    population = DEFAULT_POPULATION if population is None else population
    check_counts(population=population, workers=workers)
    results_dir = Path(results_dir)
    by_folder, todo = pending_runs(specs, results_dir, records_dir)
    rows = []
    for i, group in enumerate(group_specs(todo, population, workers)):
        config = group[0].to_config()
        total = config.iterations
        progress = [_logged_progress(spec.run_dir(results_dir), config.checkpoint_every) for spec in group]
        reached = min(n for n, _ in progress)
        rates = [r for _, r in progress if r is not None]
        seconds = max(rates) if rates else float("nan")
        rows.append({"group": i, "methods": "+".join(sorted({s.method for s in group})), "members": len(group),
                     "iteration": reached, "of": total, "s_per_iteration": seconds,
                     "hours_left": (total - reached) * seconds / 3600})
    table = pd.DataFrame(rows, columns=["group", "methods", "members", "iteration", "of", "s_per_iteration",
                                        "hours_left"])
    table.attrs.update(finished=len(by_folder) - len(todo), runs=len(by_folder))
    return table


def status_summary(table, workers: int) -> str:
    """One paragraph for `sweep_status`'s table: finished runs, hours left, a lower bound on the wall time."""
    done = f"{table.attrs['finished']} of {table.attrs['runs']} runs finished"
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
from pemamoe.sweep import experiment_specs

_status = sweep_status(experiment_specs("main", scale), repo_path("results"), workers=2)
print(status_summary(_status, workers=2))
_status

# %% [markdown]
# ## Command line
#
# `python -m pemamoe sweep --experiment main --scale small --backend ray` runs one of the
# experiments of notebook 09; `--address` joins a Ray cluster. It calls the same `run_sweep` as the
# notebooks, so a sweep started from the shell is reused by the notebooks. Counts and method
# names are checked while the arguments are parsed, so a typo fails with a usage message before
# anything trains.

# %%
#| export
def sweep_cli(argv=None) -> int:
    import argparse

    from pemamoe.sweep import DEFAULT_POPULATION, experiment_specs, pending_runs, run_sweep  # the sweep imports this module

    parser = argparse.ArgumentParser(prog="python -m pemamoe sweep")
    parser.add_argument("--experiment", default="main", choices=["main", "tricks", "noise", "all", "budget", "gating"])
    parser.add_argument("--scale", default="small")
    parser.add_argument("--seeds", type=_count(0), nargs="+", default=None, metavar="SEED",
                        help="one or more seeds (default: the scale's)")
    parser.add_argument("--methods", nargs="+", default=None, type=_method, metavar="METHOD",
                        help=f"one or more registered methods ({', '.join(METHOD_REGISTRY)}, or a plugin's; "
                             f"default: {', '.join(compared_methods())})")
    parser.add_argument("--backend", default="local", choices=BACKENDS)
    parser.add_argument("--workers", type=_count(1), default=2)
    parser.add_argument("--population", type=_count(1), default=DEFAULT_POPULATION,
                        help=f"at most this many compatible runs train together in one process (default {DEFAULT_POPULATION})")
    parser.add_argument("--address", default=None, help="Ray cluster address (ray backend)")
    parser.add_argument("--results-dir", default="results")
    parser.add_argument("--records-dir", default="records",
                        help="the run records (appendix 09d): a recorded run is not trained again, and each run's "
                             "record is written as it finishes (default: records/)")
    parser.add_argument("--retrain", action="store_true",
                        help="ignore the records: train into --results-dir whatever is not there, rewrite the records")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                        help="progress bar (default: when stderr is a terminal)")
    parser.add_argument("--hours", type=_hours, default=None, metavar="H",
                        help="train for at most H hours, then checkpoint every running population, stop, and "
                             "print what finished and what is left (rerun to go on)")
    parser.add_argument("--status", action="store_true",
                        help="print where the sweep stands (populations, iterations, hours left) and train nothing")
    args = parser.parse_args(argv)
    try:
        check_scale(args.scale)
    except ValueError as err:
        parser.error(str(err))
    if str(args.results_dir).strip() == "":
        parser.error("--results-dir must be a folder path")
    if str(args.records_dir).strip() == "":
        parser.error("--records-dir must be a folder path")
    methods = tuple(args.methods) if args.methods else compared_methods()
    specs = experiment_specs(args.experiment, args.scale, args.seeds, methods)
    if args.status:
        import pandas as pd

        table = sweep_status(specs, args.results_dir, args.population, args.workers, args.records_dir)
        with pd.option_context("display.width", 120, "display.max_columns", 10):
            print(table.round({"s_per_iteration": 3, "hours_left": 2}).to_string(index=False))
        print(status_summary(table, args.workers))
        return 0
    try:
        run_sweep(specs, args.backend, args.workers, args.results_dir, args.address, progress=args.progress,
                  population=args.population, hours=args.hours, records_dir=args.records_dir, retrain=args.retrain)
        if args.hours is not None and pending_runs(specs, args.results_dir, args.records_dir)[1]:
            import pandas as pd

            table = sweep_status(specs, args.results_dir, args.population, args.workers, args.records_dir)
            with pd.option_context("display.width", 120, "display.max_columns", 10):
                print(table.round({"s_per_iteration": 3, "hours_left": 2}).to_string(index=False))
            print(status_summary(table, args.workers))
            moved = sorted(Path(args.records_dir).glob(f"*/{PORTABLE_DIR}/*.pt.zst"))
            if moved:
                print(f"[sweep] {len(moved)} unfinished runs left their portable state in "
                      f"{moved[0].parent}: commit it with the records to go on on another machine", flush=True)
    except SweepInterrupted as stop:
        print(f"[sweep] {stop}: running runs were stopped; rerun the same command to resume them", flush=True)
        return 128 + stop.signum
    return 0


def _hours(text: str) -> float:
    import argparse
    import math

    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a number of hours > 0, got {text!r}")
    return value


def _method(text: str) -> str:
    import argparse

    try:
        return method_spec(text).name
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _count(low: int):
    def parse(text: str) -> int:
        import argparse

        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {value}")
        return value

    return parse

# %% [markdown]
# The checks, without training anything:

# %%
import argparse

for _parse, _text in ((_count(1), "0"), (_count(0), "two"), (_method, "nope")):
    try:
        _parse(_text)
    except argparse.ArgumentTypeError as err:
        print(f"{_text!r}: {err}")
try:
    sweep_cli(["--scale", "huge"])
except SystemExit as stop:
    assert stop.code == 2
