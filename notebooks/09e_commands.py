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
# # 09e · Appendix: the commands `python -m pemamoe sweep` and `python -m pemamoe figures`
#
# Two commands sit on top of everything else. The sweep command runs one of the experiments of
# notebook 09 from the shell; `make figures` trains every run the notebooks read and then executes
# every notebook. Both need the experiments (`pemamoe.experiments`), so they live here, in the module
# `pemamoe.commands`, above the sweep and above everything the sweep imports. The hand-written
# `pemamoe/__main__.py` parses the top-level command and calls them.
#
# The module itself loads only light modules (no torch, numpy or pandas): `sweep --help` and a
# usage error answer in a fraction of a second, because the parser's choices and defaults come
# from `pemamoe.core` (appendix 00b) and the experiments, the run cache and the records are
# imported by the functions that use them, once the arguments are checked.

# %%
#| default_exp commands

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %%
#| export
import os
import signal
import sys
import time
from contextlib import contextmanager
from pathlib import Path

from pemamoe.core import (ACTOR_READINGS, BACKENDS, DEFAULT_POPULATION, EXPERIMENTS, READABLE_EXPERIMENTS, REPO_ROOT,
                          SCALES, SEED_LIMIT, TRAINING_SCALE_HELP, WORKERS_LIMIT, HOURS_LIMIT, check_scale, checkout_store,
                          current_umask, figure_notebooks, int_arg, notebook_parameters, one_line, real_arg, repo_path,
                          run_notebook, atomic_write_text, cpu_model)
from pemamoe.methods import METHOD_REGISTRY, compared_methods, method_spec
from pemamoe.runs import RunFolderError, RunLockedError
from pemamoe.store import StoreAccessError, StoreLeaseError, check_access, open_store, store_access_error

# %% [markdown]
# ## The sweep command
#
# `python -m pemamoe sweep --experiment main --scale small --backend ray` runs one of the
# experiments of notebook 09; `--address` joins a Ray cluster. It calls the same `run_sweep` as the
# notebooks, so a sweep started from the shell is reused by the notebooks. Counts and method
# names are checked while the arguments are parsed, and so is `--results-dir` (a URL fsspec serves,
# or a folder that may be new but whose parent folder exists), so a typo fails with a usage message
# before anything trains. `--status` prints `sweep_status` (appendix 09c) and trains nothing.
#
# What goes wrong later ends the command in one line on stderr, naming the problem and the value
# at fault, and exit status 1, never a traceback: a store that cannot be reached (no credentials,
# no endpoint, no bucket: `check_access`, appendix 09f, before anything else), a run folder locked
# by another live process or holding files that cannot be trusted, a damaged record or portable
# state, a failed run (`SweepRunError`, appendix 09c). `error_line` says which errors those are
# and gives their line; `train` (in `__main__`) uses it too. Anything else is a bug, and keeps its
# traceback.

# %%
#| export
SET_HELP = ("set any config field (repeatable), part of the run's identity: a TrainConfig field (target_kl=0.15, "
            "target_kl_check=epoch) or a dotted nested one (controller.log_std_value=0.3, net.top_k=2, env.n_users=30); "
            "VALUE is JSON, none, or a string (notebook 07c)")


def sweep_cli(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m pemamoe sweep",
        description="Train the runs of one experiment (notebook 09) that are neither finished in --results-dir nor "
                    "recorded in --records-dir, compatible runs together as populations, on a local process pool "
                    "or on Ray. Rerun the same command to resume; --status says where it stands.")
    parser.add_argument("--experiment", default="main", choices=EXPERIMENTS,
                        help="main: the four methods; tricks: the controller's ablations; noise: the noise scale; "
                             "all: main, tricks and noise; budget: the learning-budget study (09b); gating: the "
                             "gating readings (05c); sparse: the sparse-actor readings (05d); tuning: learning rate x entropy "
                             "for every method alike (09b); top2: the top-2 arm beside top-1 (05d, 10); campaign: main "
                             "with MLP + ReDo and MLP + shrink-and-perturb, the paper scale's comparison; campaign_v2: campaign "
                             "under the readings appendix 10b chooses, 5 seeds at the paper scale (default: main)")
    parser.add_argument("--scale", default="small", choices=SCALES, help=TRAINING_SCALE_HELP)
    parser.add_argument("--reading", default=None, choices=ACTOR_READINGS,
                        help=f"pin the gated methods' sparse-actor reading (appendix 05d) in {', '.join(READABLE_EXPERIMENTS)} "
                             "(default: the network's defaults)")
    parser.add_argument("--seeds", type=int_arg(0, SEED_LIMIT), nargs="+", default=None, metavar="SEED",
                        help="one or more seeds, integers in [0, 2**63) (default: the scale's)")
    parser.add_argument("--methods", nargs="+", default=None, type=_method, metavar="METHOD",
                        help=f"one or more registered methods ({', '.join(METHOD_REGISTRY)}, or a plugin's; "
                             f"default: {', '.join(compared_methods())})")
    parser.add_argument("--backend", default="local", choices=BACKENDS,
                        help="local: a process pool on this machine; ray: Ray tasks (default: local)")
    parser.add_argument("--workers", type=int_arg(1, le=WORKERS_LIMIT), default=2,
                        help="populations trained at once, one core each (default: 2)")
    parser.add_argument("--population", type=int_arg(1, le=WORKERS_LIMIT), default=DEFAULT_POPULATION,
                        help=f"at most this many compatible runs train together in one process (default {DEFAULT_POPULATION})")
    parser.add_argument("--address", default=None, help="Ray cluster address (ray backend)")
    parser.add_argument("--results-dir", default="results",
                        help="the results store, the training cache of one run folder per run: a folder or a URL "
                             "such as s3://bucket/prefix, appendix 09f (default: results/)")
    parser.add_argument("--records-dir", default="records",
                        help="the run records (appendix 09d): a recorded run is not trained again, and each run's "
                             "record is written as it finishes: a folder or a URL (default: records/)")
    parser.add_argument("--retrain", action="store_true",
                        help="ignore the records: train into --results-dir whatever is not there, rewrite the records")
    parser.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                        help="progress bar (default: when stderr is a terminal)")
    parser.add_argument("--hours", type=real_arg(gt=0, le=HOURS_LIMIT), default=None, metavar="H",
                        help="train for at most H hours, then checkpoint every running population, stop, and "
                             "print what finished and what is left (rerun to go on)")
    parser.add_argument("--status", action="store_true",
                        help="print where the sweep stands (populations, iterations, hours left) and train nothing")
    parser.add_argument("--set", dest="settings", action="append", default=[], metavar="FIELD=VALUE",
                        help=SET_HELP + "; applied to every run of the experiment")
    args = parser.parse_args(argv)  # --scale's choices are SCALES: argparse refuses any other
    args.parser = parser
    if args.reading is not None and args.experiment not in READABLE_EXPERIMENTS:
        parser.error(f"--reading applies to the experiments {', '.join(READABLE_EXPERIMENTS)}; "
                     f"{args.experiment!r} fixes its own actor readings")
    if str(args.results_dir).strip() == "":
        parser.error("--results-dir must be a folder path or a URL, got an empty string")
    if str(args.records_dir).strip() == "":
        parser.error("--records-dir must be a folder path or a URL, got an empty string")
    _check_store_arg(parser, "--results-dir", args.results_dir)
    _check_store_arg(parser, "--records-dir", args.records_dir)
    args.results_dir = checkout_store(args.results_dir, "results")  # from a plugin's folder too
    args.records_dir = checkout_store(args.records_dir, "records")
    stores = (args.results_dir, args.records_dir)
    try:
        for store in stores:
            check_access(store)  # a URL: its credentials, endpoint and bucket, before anything is imported or trained
        return _sweep(args)
    except KeyboardInterrupt as stop:  # SweepInterrupted (SIGINT or SIGTERM), or Ctrl-C before the sweep began
        print(f"[sweep] {str(stop) or 'interrupted'}: running runs were stopped; rerun the same command to resume them",
              flush=True)
        return 128 + getattr(stop, "signum", signal.SIGINT)
    except Exception as err:
        line = error_line(err, stores, start_over="delete the run folder to train the run again from the start")
        if line is None or traceback_wanted():
            raise
        print(f"{parser.prog}: error: {line}", file=sys.stderr, flush=True)
        return 1


def _sweep(args) -> int:
    """The sweep command once its arguments are checked: --status's table, or run_sweep."""
    from pemamoe.experiments import experiment_specs, pending_runs, run_sweep

    methods = tuple(args.methods) if args.methods else compared_methods()
    specs = experiment_specs(args.experiment, args.scale, args.seeds, methods, args.reading)
    if args.settings:
        from pemamoe.train_config import parse_settings

        try:
            settings = parse_settings(args.settings)
            specs = [spec.with_overrides(settings) for spec in specs]
            for spec in specs:
                spec.to_config()  # the config's own validators, before anything trains
        except ValueError as err:
            args.parser.error(f"--set: {err}")
    if args.status:
        _print_status(specs, args)
        return 0
    run_sweep(specs, args.backend, args.workers, args.results_dir, args.address, progress=args.progress,
              population=args.population, hours=args.hours, records_dir=args.records_dir, retrain=args.retrain)
    if args.hours is not None and pending_runs(specs, args.results_dir, args.records_dir)[1]:
        from pemamoe.records import portable_state_path

        _print_status(specs, args)
        moved = [p for p in (portable_state_path(args.records_dir, spec.scale, spec.to_config().run_name())
                             for spec in specs) if p.exists()]  # this sweep's runs, no other's
        if moved:
            print(f"[sweep] {len(moved)} unfinished runs left their portable state in "
                  f"{moved[0].parent}: commit it with the records to go on on another machine", flush=True)
    return 0


def _print_status(specs, args) -> None:
    import pandas as pd

    from pemamoe.sweep_runner import status_summary, sweep_status

    table = sweep_status(specs, args.results_dir, args.population, args.workers, args.records_dir)
    if not table.empty:  # a finished sweep has no populations left to list
        with pd.option_context("display.width", 120, "display.max_columns", 10):
            print(table.round({"s_per_iteration": 3, "hours_left": 2}).to_string(index=False))
    print(status_summary(table, args.workers))


def error_line(err: BaseException, stores=(), start_over: str | None = None) -> str | None:
    """The one line a command ends with on `err`, or None when `err` is none of the errors a command
    reports in one line (a bug keeps its traceback). stores: the command's stores, whose client
    errors say which store cannot be used (`store_access_error`, appendix 09f); start_over: the
    command's own way to start a run over, in place of RunFolderError's resume=False."""
    for store in stores:
        access = store_access_error(store, err)
        if access is not None:
            return str(access)
    if isinstance(err, RunFolderError):
        return one_line(err.message(start_over))
    # An error of a module not loaded cannot have been raised: importing one here would cost seconds.
    loaded = [getattr(sys.modules[m], name) for m, name in (("pemamoe.records", "RecordError"),
                                                             ("pemamoe.sweep_runner", "SweepRunError"))
              if m in sys.modules]
    if isinstance(err, (RunLockedError, StoreLeaseError, StoreAccessError, OSError, *loaded)):
        return one_line(err)
    return None


TRACEBACK_ENV = "PEMAMOE_TRACEBACK"  # set (to anything but 0): a command's one-line errors show their traceback


def traceback_wanted() -> bool:
    """Whether $PEMAMOE_TRACEBACK asks the commands for the traceback behind their one-line errors."""
    return os.environ.get(TRACEBACK_ENV, "").strip() not in ("", "0")


def figures_error_line(err: BaseException, stores=()) -> str | None:
    """The one line `python -m pemamoe figures` ends with on `err` (None: a bug, whose traceback is
    shown): a notebook that failed is named with its cell, its error and its executed copy (which
    holds the traceback); the folder it draws into is always as it was."""
    failed = getattr(err, "figures_notebook", None)
    if failed is not None and type(err).__name__ == "PapermillExecutionError":
        name, executed = failed
        what = f"{err.ename}: {err.evalue}" if getattr(err, "ename", None) else one_line(err)[:300]
        return one_line(f"notebook {name} failed in its cell {getattr(err, 'exec_count', '?')} ({what}); its executed "
                        f"copy, with the traceback, is {executed}; the figures folder is as it was")
    line = error_line(err, stores)
    if line is None and isinstance(err, (FiguresDirError, TimeoutError)):
        line = one_line(err)
    if line is not None and failed is not None:
        line = f"notebook {failed[0]}: {line}"
    return None if line is None else f"{line} (the figures folder is as it was)"


def _check_store_arg(parser, flag: str, text: str) -> None:
    """A store flag names a URL fsspec serves, or a local folder that may be new but whose parent
    folder exists: a typo in the path is a usage error, not a tree of new folders."""
    try:
        store = open_store(text)
    except ValueError as err:
        parser.error(f"{flag}: {err}")
    if not store.remote:
        try:
            text.encode("utf-8")
        except UnicodeEncodeError:
            parser.error(f"{flag} {ascii(text)}: the path is not valid UTF-8; name a folder whose path is UTF-8")
        if store.folder.exists() and not store.folder.is_dir():
            parser.error(f"{flag} {text} is a file, not a folder; name a folder (it is created if missing) or a URL "
                         "such as s3://bucket/prefix")
        parent = store.folder.absolute().parent
        if not parent.is_dir():
            parser.error(f"{flag} {text}: its parent folder {parent} does not exist; name a folder in an existing "
                         "folder (the folder itself is created if missing) or a URL such as s3://bucket/prefix")


def _method(text: str) -> str:
    import argparse

    try:
        return method_spec(text).name
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None

# %% [markdown]
# The checks, without training anything:

# %%
import argparse

for _parse, _text in ((int_arg(1), "0"), (int_arg(0, SEED_LIMIT), "two"), (_method, "nope")):
    try:
        _parse(_text)
    except argparse.ArgumentTypeError as err:
        print(f"{_text!r}: {err}")
for _argv in (["--scale", "huge"], ["--results-dir", "/nonexistent/x", "--status"]):
    try:
        sweep_cli(_argv)
    except SystemExit as stop:
        assert stop.code == 2
    else:
        raise AssertionError(f"sweep_cli({_argv}) was accepted")

# %% [markdown]
# ## Regenerating every figure
#
# `make_figures` runs the notebooks in paper order (`pemamoe.core.figure_notebooks`) with the
# headless runner of appendix 00b, pointing their `figures_dir` at `paper_figures/`, and then
# writes the provenance table `paper_figures/README.md` (`write_figures_readme`, below).
# When it runs every notebook it first trains, as one sweep, every run the notebooks read, so that
# compatible runs of different experiments share populations and no notebook trains for hours
# under its cell timeout.
#
# A full run takes from minutes (`ci`) to hours (`paper`), so it reports as it goes: one line when
# notebook *i* of *N* starts and one when it ends, with the time spent on it and in total, and in
# between the notebook's own output, streamed. These are plain lines rather than a progress bar,
# because the streamed output would tear a bar apart, and plain lines read the same in a log file.
#
# It is all or nothing. The notebooks write into a copy of the folder made beside it, which replaces
# the folder only once every notebook has succeeded; when one fails, the error propagates, the copy
# is deleted, and `paper_figures/` is left byte for byte as it was, its README still true of it.
#
# Nothing the user made is removed or replaced on the way (issue 59). A file, a symbolic link or a
# mount point where the folder should be is refused before anything runs (`check_figures_dir`): a
# rename cannot put a folder in its place without moving the user's file. A file the user saves in
# the folder while the notebooks run is carried into the new folder at the swap; one with a
# namesake among the new files keeps the earlier folder aside, named on stderr. SIGTERM unwinds as
# Ctrl-C does, and both leave the folder as it was and no copy behind. What a killed run (SIGKILL,
# a power cut) leaves beside the folder, `<name>.partial-*` and `<name>.old-*`, carries a mark
# naming its process; the next run removes those whose process is gone (finishing or undoing the
# swap the dead run was in), and leaves anything unmarked or a live run's alone.
#
# The paper scale is a campaign, not a rerun of everything: its runs cost hours each, so it trains
# the main comparison with the two plasticity baselines (the experiment `campaign`, notebook 09)
# and draws only what reads them, notebooks 09, 10 and 10b (`PAPER_SCALE_NOTEBOOKS`; notebook 10
# without its ablations; 10b, the readings table). Its figures go to `paper_figures/paper_scale/`, beside the medium
# scale's, which stay what every other notebook draws (`figures_plan`).

# %%
#| export
# what reads the paper-scale campaigns
PAPER_SCALE_NOTEBOOKS = ("09_experiments.py", "10_ablations.py", "10b_readings.py")
PAPER_SCALE_FIGURES = "paper_figures/paper_scale"


def figures_plan(scale: str, figures_dir=None, notebooks=None) -> tuple:
    """(figures folder, notebooks, the experiments trained first or None) of `make_figures` at
    `scale`: by default paper_figures/ and every notebook after one sweep of everything they read;
    at the paper scale paper_figures/paper_scale/ and PAPER_SCALE_NOTEBOOKS after the campaign.
    Named notebooks train nothing first (the notebooks train what they miss themselves)."""
    paper = scale == "paper"
    folder = repo_path(figures_dir or (PAPER_SCALE_FIGURES if paper else "paper_figures"))
    if notebooks is not None:
        return folder, [Path(n) for n in notebooks], None
    if paper:
        chosen = [nb for nb in figure_notebooks() if nb.name in PAPER_SCALE_NOTEBOOKS]
        return folder, chosen, ("campaign", "budget")
    return folder, figure_notebooks(), ("all", "budget", "gating", "sparse")


def make_figures(scale: str = "small", figures_dir=None, notebooks=None, timeout: int = 3600,
                 stream: bool = True, precompute: bool | None = None, **extra) -> Path:
    """Execute every notebook at `scale` into `figures_dir`; write its README; return its path.

    figures_dir: default paper_figures/, paper_figures/paper_scale/ at the paper scale (a relative
                 path is under the repository root; see figures_plan).
    stream:      print progress lines and the notebooks' own output (False: silent).
    precompute:  first train every run the notebooks read (the scale's 39-run sweep of notebooks
                 09 and 10, the learning-budget study of 09b, the gating comparison of 05c, the sparse-actor readings of 05d) as one sweep, so that compatible
                 runs of different experiments share populations, no notebook trains for hours
                 under its timeout, and the notebooks only read results (None: when all notebooks run).
    extra:       further parameters (e.g. backend="ray", workers=2, retrain=True), given to the
                 notebooks that declare them. retrain=True: ignore the committed records (appendix
                 09d), train every run into the cache and write the records again.
    """
    import shutil

    from pemamoe.experiments import experiment_specs, run_sweep

    check_scale(scale)
    figures_dir, notebooks, experiments = figures_plan(scale, figures_dir, notebooks)
    check_figures_dir(figures_dir)
    figures_dir.parent.mkdir(parents=True, exist_ok=True)
    clean_stale_staging(figures_dir)
    say = (lambda msg: print(msg, flush=True)) if stream else (lambda msg: None)
    records, t0 = {}, time.perf_counter()
    if scale == "paper" and experiments is not None:
        say(f"[figures] the paper scale draws its campaign ({', '.join(nb.name for nb in notebooks)}) into "
            f"{figures_dir}; every other figure is the medium scale's")
    with _terminate_as_interrupt():  # SIGTERM unwinds as Ctrl-C does: the copy below is removed
        if precompute if precompute is not None else experiments is not None:
            say(f"[figures] training the {scale} runs that have no record first (cached runs are skipped)")
            run_sweep([spec for name in experiments or figures_plan(scale)[2] for spec in experiment_specs(name, scale)],
                      extra.get("backend", "local"), extra.get("workers", 2),
                      _results_store(extra.get("results_dir", "results")), extra.get("ray_address"),
                      records_dir=repo_path(extra.get("records_dir", "records")), retrain=extra.get("retrain", False))
            say(f"[figures] sweep done, {_clock(time.perf_counter() - t0)} elapsed")
        # All or nothing: the notebooks write into a copy, swapped in only when every one succeeded, so
        # that a failure never leaves new files under a README that names the old scale and inputs.
        records_dir = repo_path(extra.get("records_dir", "records"))
        markers_before = _record_markers(records_dir)
        staging, listed = _staging_copy(figures_dir)
        try:
            for i, nb in enumerate(notebooks, start=1):
                before = {p: p.stat().st_mtime_ns for p in staging.iterdir() if p.is_file()}
                start = time.perf_counter()
                say(f"[figures] {i}/{len(notebooks)} {nb.name} (scale={scale}) started, {_clock(start - t0)} elapsed")
                declared = notebook_parameters(nb)
                params = {"scale": scale, "figures_dir": str(staging), **{k: v for k, v in extra.items() if k in declared}}
                # one folder per scale: a paper-scale run must not overwrite the medium scale's executed copies
                executed = REPO_ROOT / "build" / "executed" / scale
                try:
                    run_notebook(nb, params, timeout=timeout, stream=stream, output_dir=executed)
                except Exception as err:  # named by the command's one line (figures_error_line)
                    err.figures_notebook = (nb.name, executed / f"{nb.stem}.ipynb")
                    raise
                now = time.perf_counter()
                say(f"[figures] {i}/{len(notebooks)} {nb.name} done in {_clock(now - start)}, {_clock(now - t0)} elapsed")
                for p in staging.iterdir():
                    if p.is_file() and p.name != "README.md" and before.get(p) != p.stat().st_mtime_ns:
                        records[p.name] = nb.name
            write_figures_readme(staging, records, scale=scale, inputs=figure_inputs())
            changed = _changed_files(staging, figures_dir)
            trained = _record_markers(records_dir) - markers_before
            _swap_in(staging, figures_dir, listed)
        finally:
            shutil.rmtree(staging.parent, ignore_errors=True)  # the staging folder's own parent: ours alone
    shown = ", ".join(changed[:6]) + (f" and {len(changed) - 6} more" if len(changed) > 6 else "")

    def count(n: int, noun: str) -> str:
        return f"{n} {noun}{'' if n == 1 else 's'}"

    say(f"[figures] {count(len(notebooks), 'notebook')}, {count(len(trained), 'run')} trained, "
        f"{count(len(records) + 1, 'file')} written (README.md included), {len(changed)} changed"
        f"{': ' + shown if changed else ''}")
    return figures_dir / "README.md"


# Paper counterpart of each output, by file stem; a stem not listed illustrates a model given in equations.
PAPER_COUNTERPARTS = {
    "cost_table": "Table 'Computational cost comparison (actor network)'",
    "architecture_actors": "Fig. 'PE-MAMoE architecture' (actor side, drawn by code)",
    "table_parameters": "Table 'Simulation and training parameters'",
    "results_feature_rank": "Fig. 'Evolution of the average expert feature rank'",
    "results_dormant_fraction": "Fig. 'Evolution of the total dormant neuron fraction'",
    "results_mean_return": "Fig. 'Mean return over training'",
    "results_coverage": "(ours) coverage over training, with each phase's random and k-means levels",
    "results_normalised_iqm": "Fig. 'Normalized IQM across five system metrics'",
    "results_probability_of_improvement": "(ours) rliable probability of improvement, no paper counterpart",
    "results_router_policy": "Fig. 'Policy-side expert routing probability'",
    "results_router_value": "Fig. 'Value-side expert routing probability'",
    "results_routing_ran": "(ours) selected-expert shares and switch rate in the rollouts",
    "gating_readings": "(ours) top-1 gating readings in fixed phases; chose the gating defaults",
    "gating_evaluation": "(ours) the gating readings' final policies, noiseless and trained routing",
    "sparse_actor": "(ours) the sparse actor's readings in fixed phase 0: why top-1 plateaus lower",
    "sparse_actor_study": "(ours) the study's final actors: action jumps at expert switches, actions outside the box",
    "results_collisions": "Fig. 'Collisions per episode over training'",
    "results_energy_rate": "Fig. 'Mean UAV energy rate over training'",
    "results_service": "Fig. 'Successfully served users' and 'UAV using rate'",
    "results_mean_action": "Fig. 'Mean action response to phase switches'",
    "ablation_noise_sensitivity": "Fig. 'Effect of noise injection threshold on coverage'",
    "ablation_noise_sweep": "Fig. 'Effect of noise injection threshold' (values)",
    "ablation_tricks": "Fig. 'Ablation study: IQM drop when removing each component'",
    "headline_claims": "(ours) the paper's headline numbers beside ours",
    "headline_reference_iqm": "(ours) per-metric IQM with the k-means reference row",
    "headline_controller_alone": "(ours) PE-MAMoE against SMoE: the phase controller alone",
    "headline_plasticity_baselines": "(ours) PE-MAMoE against ReDo and shrink-and-perturb on MLP (paper scale)",
    "top2_arm": "(ours) the sparse methods kept at top-2 beside their top-1 runs (notebook 05d's arm)",
    "env_reward_anatomy": "(ours) reward anatomy of objective O'",
    "mappo_training_curves": "(ours) one training run per method, notebook 07",
    "plasticity_schedules": "Algorithm 1 switch-time schedules (no paper figure)",
    "learning_budget": "(ours) learning curves in each fixed phase; sets the medium phase length",
    "learning_budget_compute": "(ours) MLP's two update settings per compute second",
    "learning_budget_readings": "(ours) the study under both sparse-actor readings: the plateau gap to MLP",
    "tuning": "(ours) learning rate x entropy, the same grid for every method; each one's chosen setting",
    **{f"phase_learning_{scale}": "(ours) each phase visit against the study's plateau" for scale in SCALES},
    **{f"plasticity_loss_{scale}": "(ours) each revisit of a phase against its first visit"
       + (" and a fresh network" if scale != "paper" else "") for scale in SCALES},
    "plasticity_loss_paper_campaign": "(ours) paper-scale revisits against first visits, seed by seed",
    **{f"theory_{name}": "Section V, measured (no paper figure)" for name in
       ("noise_energy", "routing_stability", "dynamic_regret", "noise_fit", "lipschitz", "regret_fit")},
}
# Outputs whose runs keep their own settings at every scale but ci: the studies of 05c, 05d and 09b
# train the small settings. (The paper campaign's seed-by-seed plasticity figure is written at the
# paper scale only, into paper_figures/paper_scale/: no copy of it sits in paper_figures/.)
FIXED_SCALE_OUTPUTS = dict.fromkeys(("gating_readings", "gating_evaluation", "sparse_actor", "sparse_actor_study",
                                     "learning_budget", "learning_budget_compute", "learning_budget_readings",
                                     "tuning"), "small")


def write_figures_readme(figures_dir, records: dict, *, scale: str, inputs: dict) -> Path:
    """Merge `records` (file name -> notebook) into paper_figures/README.md's provenance table;
    `inputs` is figure_inputs() of the code and records that made them."""
    readme = repo_path(figures_dir) / "README.md"
    rows = _read_provenance(readme)
    command = f"make figures SCALE={scale}"  # the backend does not change results, only where they ran
    for name, nb in records.items():
        stem = name.rsplit(".", 1)[0]
        counterpart = PAPER_COUNTERPARTS.get(stem, "model illustration (no paper figure)")
        fixed = FIXED_SCALE_OUTPUTS.get(stem, scale) if scale != "ci" else scale
        shown = scale if fixed == scale else f"{fixed} (at every scale)"
        rows[name] = [name, counterpart, f"notebooks/{nb}", shown, f"`{command}`", inputs.get(nb, "unknown")]
    lines = [
        "# paper_figures",
        "",
        "Every file here is written by a notebook through `make figures`; none is drawn by hand.",
        "Columns: the file, its counterpart in the paper, the notebook that wrote it, the scale it",
        "ran at, the command, and a digest of the notebook's code cells (prose cells, comments and",
        "docstrings left out; `pemamoe.commands.figure_inputs`). The last `make figures` that wrote here",
        f"read the package's code at digest {inputs.get('package', 'unknown')} and the committed records at "
        f"digest {inputs.get('records', 'unknown')}:",
        "the same inputs write the same files, whatever commit the checkout is at.",
        f"It ran on {cpu_model()}: on the same kind of processor it",
        "rewrites every file byte for byte; on another, values computed at plot time may differ in",
        "their last reported digit or a few pixels (the repository's README says which).",
        "",
        "| file | paper counterpart | notebook | scale | command | notebook code |",
        "|---|---|---|---|---|---|",
        *("| " + " | ".join(rows[k]) + " |" for k in sorted(rows)),
    ]
    return atomic_write_text(readme, "\n".join(lines) + "\n")


def _read_provenance(readme: Path) -> dict:
    # Keep rows of files that this run did not touch (a partial rerun must not forget them).
    rows = {}
    if readme.is_file():
        for line in readme.read_text(encoding="utf-8").splitlines():
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if line.startswith("| ") and len(cells) == 6 and cells[0] not in ("file",):
                if (readme.parent / cells[0]).is_file():
                    rows[cells[0]] = cells
    return rows


def code_digest(source: str) -> str:
    """sha256 (10 hex digits) of Python source's syntax tree without docstrings: comments, blank
    lines, layout and docstrings do not count. Source that does not parse is hashed as text."""
    import ast
    import hashlib

    try:
        tree = ast.parse(source)
    except SyntaxError:
        return hashlib.sha256(source.encode("utf-8")).hexdigest()[:10]
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body
                and isinstance(body[0], ast.Expr) and isinstance(getattr(body[0], "value", None), ast.Constant)
                and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return hashlib.sha256(ast.dump(tree).encode("utf-8")).hexdigest()[:10]


def notebook_code(notebook) -> str:
    """The code cells of a Jupytext percent-format notebook, in order (markdown cells left out)."""
    cells, keep = [], False
    for line in Path(notebook).read_text(encoding="utf-8").splitlines():
        if line.startswith("# %%"):
            keep = "[markdown]" not in line
            cells.append([])
        elif keep and cells:
            cells[-1].append(line)
    return "\n\n".join("\n".join(c) for c in cells if c)


# the package's modules that compute no figure: the command line and the exporter
NOT_FIGURE_CODE = ("__main__.py", "literate.py")


def figure_inputs(root=None) -> dict:
    """Digests of what the figures are computed from: {"package": its code (every module but
    NOT_FIGURE_CODE, by code_digest), "records": the committed run records (sha256 over each file's
    path and bytes under records/, ci and in_progress folders left out), and each notebook's name:
    the code_digest of its code cells}. Content only: a fresh clone gives the same digests."""
    import hashlib

    root = Path(root or REPO_ROOT)
    package = hashlib.sha256()
    for module in sorted((root / "pemamoe").glob("*.py")):
        if module.name not in NOT_FIGURE_CODE:
            package.update(f"{module.name}:{code_digest(module.read_text(encoding='utf-8'))}\n".encode())
    records = hashlib.sha256()
    folder = root / "records"
    for path in sorted(folder.rglob("*")) if folder.is_dir() else []:
        rel = path.relative_to(folder)
        if path.is_file() and rel.parts[0] != "ci" and "in_progress" not in rel.parts[:-1]:
            records.update(f"{rel.as_posix()}:{hashlib.sha256(path.read_bytes()).hexdigest()}\n".encode())
    return {"package": package.hexdigest()[:10], "records": records.hexdigest()[:10],
            **{nb.name: code_digest(notebook_code(nb)) for nb in figure_notebooks(root)}}


def _record_markers(records_dir: Path) -> set:
    """(marker, modification time) of every run record under `records_dir`: a run trained, or
    trained again, writes its marker, so the pairs that appear during a call count its runs."""
    if not records_dir.is_dir():
        return set()
    return {(p, p.stat().st_mtime_ns) for p in records_dir.glob("*/*.json")
            if not p.name.endswith(".timing.json") and p.parent.name != "ci"}


def _changed_files(staging: Path, folder: Path) -> list:
    """Names of the files of `staging` that `folder` lacks or holds with other bytes."""
    import filecmp

    return sorted(p.name for p in staging.iterdir() if p.is_file()
                  and not ((folder / p.name).is_file() and filecmp.cmp(p, folder / p.name, shallow=False)))


class FiguresDirError(ValueError):
    """A figures folder that `make_figures` cannot replace as a whole: a file, a mount point, a path
    that is not UTF-8. One line naming it and what is allowed."""


def check_figures_dir(folder) -> Path:
    """`folder` as make_figures needs it: missing (it is created) or a folder that a rename can
    move aside, named by a UTF-8 path. FiguresDirError otherwise, before anything runs: a file
    there is the user's, and is never moved, replaced or removed."""
    folder = Path(folder)
    try:
        str(folder).encode("utf-8")
    except UnicodeEncodeError:
        raise FiguresDirError(f"figures folder {ascii(str(folder))}: its path is not valid UTF-8 (the notebooks "
                              "and the provenance README name it as text); name a folder whose path is UTF-8") from None
    if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
        raise FiguresDirError(f"figures folder {folder} is a {'symbolic link' if folder.is_symlink() else 'file'}, "
                              "not a folder; it is left as it is: name a folder (it is created if missing)")
    if folder.is_dir() and os.path.ismount(folder):
        raise FiguresDirError(f"figures folder {folder} is a mount point, which cannot be replaced as a whole; "
                              "name a folder inside it")
    return folder


STAGING_MARK = ".pemamoe-figures-staging.json"  # in each staging and aside folder make_figures creates


def _staging_copy(folder: Path) -> tuple:
    """(staging, listing): a new folder beside `folder` (the same file system, so that a rename can
    swap it in) holding a copy of its contents, modification times kept, without the staging and
    aside folders a killed run of a nested output folder (paper_figures/paper_scale) left inside
    it; and what was copied ({relative path: (mtime_ns, size)}), so that a file the user saves in
    `folder` meanwhile is carried over at the swap. The staging folder is
    `<folder>.partial-*/<folder name>`, its parent marked as this process's (clean_stale_staging)."""
    import shutil
    import tempfile

    top = Path(tempfile.mkdtemp(dir=folder.parent, prefix=f"{folder.name}.partial-"))
    staging = top / folder.name
    try:
        _mark(top, {})
        if folder.is_dir():
            listed = _listing(folder)
            shutil.copytree(folder, staging, symlinks=True,  # folder's mode too
                            ignore=lambda at, names: [n for n in names if Path(at) == folder and (folder / n).is_dir()
                                                      and (".partial-" in n or ".old-" in n)])
        else:
            listed = {}
            staging.mkdir()  # the mode mkdir gives
    except BaseException:
        shutil.rmtree(top, ignore_errors=True)
        raise
    return staging, listed


def _swap_in(staging: Path, folder: Path, listed: dict) -> None:
    """Put `staging` in place of `folder`: the old folder renamed aside, the new one renamed in,
    the files the user saved in the old one during the run carried over, the old one removed (on
    a failed rename the old one is put back). SIGINT and SIGTERM wait until it is done."""
    import shutil
    import tempfile

    blocked = {signal.SIGINT, signal.SIGTERM}
    signal.pthread_sigmask(signal.SIG_BLOCK, blocked)
    try:
        if not folder.exists():
            staging.rename(folder)
            return
        aside = Path(tempfile.mkdtemp(dir=folder.parent, prefix=f"{folder.name}.old-"))
        try:
            _mark(aside, listed)
            folder.rename(aside / folder.name)
        except BaseException:
            shutil.rmtree(aside, ignore_errors=True)  # only our mark in it: the folder did not move
            raise
        try:
            staging.rename(folder)
        except BaseException:
            (aside / folder.name).rename(folder)
            shutil.rmtree(aside, ignore_errors=True)
            raise
        _finish_aside(aside, folder, listed)
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, blocked)


def _finish_aside(aside: Path, folder: Path, listed: dict) -> None:
    """The old folder, renamed aside, once the new one is in place: every file in it that the run
    did not copy (saved or changed by the user since the copy) moves into the new folder; one the
    new folder also has stays aside, and so does the aside folder, named on stderr. Otherwise the
    aside folder is removed."""
    import shutil

    old, kept = aside / folder.name, []
    if old.exists():
        for rel, stamp in _listing(old).items():
            if listed.get(rel) == stamp:
                continue
            target = folder / rel
            if target.exists() or target.is_symlink():
                kept.append(rel)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            os.rename(old / rel, target)
    if kept:
        print(one_line(f"[figures] {len(kept)} files saved in {folder} during the run have a new namesake there "
                       f"({', '.join(kept[:3])}{', ...' if len(kept) > 3 else ''}); the earlier folder, with "
                       f"them, is kept in {old}"), file=sys.stderr, flush=True)
        return
    shutil.rmtree(aside, ignore_errors=True)


def _listing(folder: Path) -> dict:
    """{path relative to folder: (mtime_ns, size)} of every file and symbolic link under `folder`
    (links not followed), without the staging and aside folders of nested output folders."""
    found = {}
    for at, dirs, files in os.walk(folder):
        if Path(at) == folder:
            dirs[:] = [d for d in dirs if ".partial-" not in d and ".old-" not in d]
        for name in files + [d for d in dirs if os.path.islink(os.path.join(at, d))]:
            st = os.lstat(os.path.join(at, name))
            found[os.path.relpath(os.path.join(at, name), folder)] = (st.st_mtime_ns, st.st_size)
    return found


def _process_start(pid: int) -> str | None:
    """The start time of process `pid` (Linux: /proc/<pid>/stat's 22nd field), None where unknown:
    with the pid it names one process, not a later one that reuses the number."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rfind(")") + 2:].split()
    return fields[19] if len(fields) > 19 else None


def _mark(top: Path, listed: dict) -> None:
    import json
    import socket

    (top / STAGING_MARK).write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                                                "started": _process_start(os.getpid()), "listed": listed}))


def _dead_owner(top: Path) -> dict | None:
    """The mark of a staging or aside folder whose process (on this host) is gone, else None: not
    ours, unreadable, of another host or of a live process."""
    import json
    import socket

    try:
        mark = json.loads((top / STAGING_MARK).read_text())
        pid, host = int(mark["pid"]), mark["host"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if host != socket.gethostname() or pid == os.getpid():
        return None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return mark
    except PermissionError:
        pass
    started = _process_start(pid)
    return mark if started is not None and mark.get("started") not in (None, started) else None


def clean_stale_staging(folder) -> list:
    """Remove what killed runs of make_figures for `folder` left beside it (SIGKILL, a power cut):
    its `<name>.partial-*` staging folders, and its `<name>.old-*` aside folders after carrying the
    user's files over as the run would have (or, when the run died between its two renames, putting
    the old folder back). Only folders marked by a make_figures process of this host that is gone;
    anything else is left alone. Returns the folders removed."""
    import glob
    import shutil

    folder, removed = Path(folder), []
    for top in sorted(folder.parent.glob(f"{glob.escape(folder.name)}.*-*")):
        kind = top.name[len(folder.name):].split("-", 1)[0]
        if kind not in (".partial", ".old") or top.is_symlink() or not top.is_dir():
            continue
        mark = _dead_owner(top)
        if mark is None:
            continue
        if kind == ".old":
            if not folder.exists() and (top / folder.name).is_dir():
                (top / folder.name).rename(folder)  # killed between the renames: the old folder back
            elif folder.is_dir():
                listed = {k: tuple(v) for k, v in (mark.get("listed") or {}).items()}
                _finish_aside(top, folder, listed)
                if top.exists():
                    continue  # kept, and said so
            else:
                continue
        shutil.rmtree(top, ignore_errors=True)
        removed.append(top)
    return removed


@contextmanager
def _terminate_as_interrupt():
    """In the main thread: SIGTERM raises KeyboardInterrupt, as Ctrl-C does (the old handler back after)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        raise KeyboardInterrupt("terminated (SIGTERM)")

    old = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


# %%
#| exporti
def _results_store(results):
    """A local results store under the repository root (as the notebooks resolve it); a URL as it is."""
    store = open_store(results)
    return store if store.remote else repo_path(store.folder)


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"

# %% [markdown]
# The notebooks `make figures` runs, in order, and the parameters each one declares (the ones
# `make_figures` passes on to it):

# %%
for _nb in figure_notebooks():
    print(f"{_nb.name:32s} {', '.join(sorted(notebook_parameters(_nb)))}")
print(f"_clock(3725) = {_clock(3725)}")
