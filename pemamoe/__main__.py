"""Command line: `python -m pemamoe <command>` (hand-written dispatcher; the work is in modules)."""

import argparse
import sys
from pathlib import Path

from pemamoe.core import one_line  # light (as every module this file imports before a command runs)

TRAIN_HELP = "train one MAPPO run; logs and checkpoint go to --out"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m pemamoe", description="The PE-MAMoE companion's commands (`python -m pemamoe COMMAND --help` for a command's options).",
        epilog="Scales, smallest first: ci, small, medium, paper. train and sweep default to small (they train, in "
               "minutes); figures defaults to medium (it reads the committed records and trains nothing).",
        formatter_class=lambda prog: argparse.HelpFormatter(prog, max_help_position=20, width=100))
    sub = parser.add_subparsers(dest="command", required=True, title="commands")
    fig = sub.add_parser("figures", help="execute every notebook and regenerate paper_figures/")
    from pemamoe.core import BACKENDS, SCALES, WORKERS_LIMIT, int_arg  # light: the parsers are built without torch

    fig.add_argument("--scale", default="medium", choices=SCALES,
                     help="the preset scale (default: medium, whose run records are committed)")
    fig.add_argument("--figures-dir", default=None,
                     help="output folder (default: paper_figures/; for --scale paper, which draws only the campaign's "
                          "notebooks 09 and 10, paper_figures/paper_scale/)")
    fig.add_argument("--retrain", action="store_true",
                     help="ignore the committed run records (records/), train every run into results/ and write "
                          "the records again")
    fig.add_argument("--notebook", action="append", type=_figure_notebook, metavar="NOTEBOOK",
                     help="run only these notebooks (repeatable): a notebook of notebooks/ by file name or stem "
                          "(08_theory.py, 08_theory), or a path to one")
    fig.add_argument("--backend", default="local", choices=BACKENDS,
                     help="sweep backend: local | ray (default: local)")
    fig.add_argument("--workers", type=int_arg(1, le=WORKERS_LIMIT), default=2, help="parallel training runs (default: 2)")
    fig.add_argument("--ray-address", default=None, help="Ray cluster address (backend ray)")
    fig.add_argument("--results-dir", default="results",
                     help="the results store the runs without a record train into: a folder or a URL such as "
                          "s3://bucket/prefix (appendix 09f; default: results/)")
    sub.add_parser("sweep", help="run experiment sweeps (see notebook 09)", add_help=False)
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] in (["train"], ["sweep"], ["figures"]):
        _check_environment(parser)
    if argv[:1] == ["train"]:  # built only for train (its --without choices load the phase controller lazily)
        _add_train_parser(sub)
    else:
        sub.add_parser("train", help=TRAIN_HELP, add_help=False)
    for name, text in (("export", "write pemamoe/ from the notebooks' exported cells"),
                       ("check-export", "fail if pemamoe/ differs from what the notebooks export")):
        sub.add_parser(name, help=text).add_argument(
            "--root", default=None, metavar="CHECKOUT",
            help="the pemamoe checkout (default: the one this package is in)")
    if argv[:1] == ["sweep"]:  # the sweep command owns its own options
        if _option_value(argv[1:], "--backend") == "ray":
            _require_extra("python -m pemamoe sweep --backend ray", RAY_MODULES, "ray", parser)
        from pemamoe.commands import sweep_cli

        return sweep_cli(argv[1:])
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # named by the command's own usage line, not the top-level one
        sub.choices[args.command].error(f"unrecognized arguments: {' '.join(unknown)}")

    if args.command in ("export", "check-export"):
        from pemamoe import literate

        root = ["--root", args.root] if args.root is not None else []
        return literate.main(["export" if args.command == "export" else "check", *root])
    if args.command == "figures":
        from pemamoe.core import check_scale

        try:
            check_scale(args.scale)
        except ValueError as err:
            fig.error(str(err))
        _require_extra("python -m pemamoe figures", FIGURES_MODULES, "figures", fig)
        if args.backend == "ray":
            _require_extra("python -m pemamoe figures --backend ray", RAY_MODULES, "ray", fig)
        # A relative --figures-dir is relative to where the command runs (make_figures alone would
        # read it under the repository root, as the notebooks do).
        figures_dir = Path(args.figures_dir).resolve() if args.figures_dir else None
        _check_figures_dir(figures_dir, args.scale, fig)
        if str(args.results_dir).strip() == "":
            fig.error("--results-dir must be a folder path or a URL, got an empty string")
        try:
            results_dir = _results_dir(args.results_dir)
        except ValueError as err:
            fig.error(f"--results-dir: {err}")
        _check_parent_folder("--results-dir", args.results_dir, fig)
        from pemamoe.store import StoreAccessError, check_access

        try:
            check_access(results_dir)  # a URL: its credentials, endpoint and bucket, before any notebook runs
        except StoreAccessError as err:
            fig.exit(1, f"{fig.prog}: error: {err}\n")
        from pemamoe.commands import make_figures  # after the checks: it imports the trainer

        try:
            readme = make_figures(args.scale, figures_dir, args.notebook, backend=args.backend,
                                  workers=args.workers, ray_address=args.ray_address, retrain=args.retrain,
                                  results_dir=results_dir)
        except KeyboardInterrupt as stop:  # Ctrl-C, or SIGTERM (make_figures raises it for both)
            if _traceback_wanted():
                raise
            print(f"\n{fig.prog}: {str(stop) or 'interrupted'}; the figures folder is as it was before the run "
                  "(run the same command again to draw them)", file=sys.stderr)
            return 143 if "SIGTERM" in str(stop) else 130
        except Exception as err:
            from pemamoe.commands import figures_error_line

            line = figures_error_line(err, [results_dir])
            if line is None or _traceback_wanted():
                raise
            print(f"{fig.prog}: error: {line}", file=sys.stderr)
            return 1
        print(f"[figures] provenance written to {readme}")
        return 0
    if args.command == "train":
        return train_command(args, args.train_parser)
    return 2


def _check_environment(parser) -> None:
    """The PEMAMOE_* settings a command reads, checked before anything is imported or runs: the
    store's intervals (bounded numbers) and $PEMAMOE_PLUGINS (every module it names is there; found,
    not imported). One line naming the variable, its value and what is allowed."""
    from importlib.util import find_spec

    from pemamoe.methods import missing_plugin_error, plugin_modules
    from pemamoe.store import check_store_environment

    try:
        check_store_environment()
        for module in plugin_modules():
            try:
                found = find_spec(module)
            except (ImportError, ValueError) as err:  # a dotted name whose package is not there
                raise missing_plugin_error(module, f" ({one_line(err)})") from None
            if found is None:
                raise missing_plugin_error(module)
    except ValueError as err:
        parser.exit(2, f"{parser.prog}: error: {one_line(err)}\n")


def _traceback_wanted() -> bool:
    from pemamoe.commands import traceback_wanted  # $PEMAMOE_TRACEBACK

    return traceback_wanted()


def _check_figures_dir(figures_dir, scale: str, parser) -> None:
    """--figures-dir (or the default) is a folder make_figures may replace: refused here, one line,
    before any notebook runs (make_figures checks it again: nothing the user made is replaced)."""
    from pemamoe.commands import FiguresDirError, check_figures_dir, figures_plan

    try:
        check_figures_dir(figures_plan(scale, figures_dir, [])[0])
    except FiguresDirError as err:
        parser.error(f"--figures-dir: {err}")


def _results_dir(text: str) -> str:
    """--results-dir as the notebooks need it: a remote store's URL as it is, a folder (or file://
    URL) other than the default relative to where the command runs (the default, results/, is the
    repository's). A URL no installed fsspec protocol serves fails here, before any notebook runs."""
    from pemamoe.core import checkout_store
    from pemamoe.store import open_store

    store = open_store(checkout_store(text, "results"))
    return text if store.remote else str(store.folder.resolve())


def _check_parent_folder(flag: str, text: str, parser) -> None:
    """A local store folder may be new, but its parent folder must exist (a typo in the path is
    refused here, before anything trains, rather than creating a tree of folders); URLs pass."""
    from pemamoe.store import open_store

    store = open_store(text)
    if store.remote:
        return
    _check_store_folder(flag, text, store, parser)
    parent = store.folder.absolute().parent
    if not parent.is_dir():
        parser.error(f"{flag} {text}: its parent folder {parent} does not exist; name a folder in an existing "
                     "folder (the folder itself is created if missing) or a URL such as s3://bucket/prefix")


# -- figures -----------------------------------------------------------------------------------
def _figure_notebook(text: str) -> str:
    """--notebook: a notebook of notebooks/ named by its file name (08_theory.py), its stem
    (08_theory) or its path in the repository (notebooks/08_theory.py); or a path to an
    existing notebook file. Anything else fails here, naming the notebooks allowed."""
    from pemamoe.core import REPO_ROOT, figure_notebooks

    path = Path(text).expanduser()
    if path.suffix == ".py" and path.is_file():
        return str(path.resolve())
    notebooks = figure_notebooks()
    if path.parent in (Path("."), Path("notebooks")):
        for nb in notebooks:
            if path.name in (nb.name, nb.stem):
                return str(nb)
    allowed = ", ".join(nb.stem for nb in notebooks) or "none found"
    raise argparse.ArgumentTypeError(f"no notebook {text!r}; name one of {REPO_ROOT / 'notebooks'} by file name or "
                                     f"stem ({allowed}) or give a path to a notebook file")


# -- optional dependencies (pyproject.toml's extras) --------------------------------------------
FIGURES_MODULES = ("jupytext", "papermill", "ipykernel", "rliable")  # the extra "figures"
RAY_MODULES = ("ray", "psutil")  # the extra "ray"


def _require_extra(what: str, modules, extra: str, parser) -> None:
    """Exit with a one-line error naming the extra to install when one of `modules` is missing."""
    from importlib.util import find_spec

    missing = [m for m in modules if find_spec(m) is None]
    if missing:
        parser.exit(2, f"{parser.prog}: error: {what} needs {', '.join(missing)}, which {'is' if len(missing) == 1 else 'are'} not installed: "
                       f"pip install 'pemamoe[{extra}]' (or install environment.lock)\n")


def _option_value(argv, option: str):
    """The value given to `option` in argv (`--opt v` or `--opt=v`), the last one wins; None if absent."""
    value = None
    for i, arg in enumerate(argv):
        if arg == option and i + 1 < len(argv):
            value = argv[i + 1]
        elif arg.startswith(option + "="):
            value = arg.split("=", 1)[1]
    return value


# -- train -------------------------------------------------------------------------------------
def _add_train_parser(sub) -> argparse.ArgumentParser:
    # Light modules only (no torch): --help and an argument error must not wait for the trainer to
    # import. Every value is checked here, while the arguments are parsed (the seed's range too).
    from pemamoe.core import MECHANISMS, SCALES, SEED_LIMIT, TRAINING_SCALE_HELP, int_arg, real_arg
    from pemamoe.commands import SET_HELP
    from pemamoe.core import ITERATIONS_LIMIT, NOISE_GAMMA_LIMIT
    from pemamoe.methods import METHOD_REGISTRY, load_plugins, proposed_method

    load_plugins()  # methods registered by $PEMAMOE_PLUGINS, as the trainer would see them
    methods = tuple(METHOD_REGISTRY)
    p = sub.add_parser("train", help=TRAIN_HELP, description=(
        "Train one MAPPO run with the same code path as pemamoe.mappo.train(config, run_dir). "
        "A progress bar is shown when stderr is a terminal; a summary is printed at the end. "
        "Ctrl-C stops it; the same command resumes it from its last checkpoint."))
    default = proposed_method()
    p.add_argument("--method", default=default, choices=methods,
                   help=f"a registered method: network kind and plasticity method (default: {default})")
    p.add_argument("--scale", default="small", choices=SCALES, help=TRAINING_SCALE_HELP)
    p.add_argument("--seed", type=int_arg(0, SEED_LIMIT), default=0,
                   help="random seed, an integer in [0, 2**63) (default: 0)")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="run directory (default: <results-dir>/train/<method>-s<seed>-<config hash>)")
    p.add_argument("--results-dir", default="results", metavar="STORE",
                   help="the results store the default run directory is in: a folder or a URL such as "
                        "s3://bucket/prefix, where the run is leased, trained in a local cache and copied back "
                        "(appendix 09f; default: results/)")
    p.add_argument("--without", action="append", default=[], choices=MECHANISMS, metavar="MECHANISM",
                   help="switch a phase-controller mechanism off (repeatable; methods with the phase controller "
                        "only): %(choices)s")
    p.add_argument("--noise-gamma", type=real_arg(ge=0, le=NOISE_GAMMA_LIMIT), default=None, metavar="GAMMA",
                   help="expert noise scale of the phase controller (methods with the phase controller only; default: the preset's)")
    p.add_argument("--device", default=None, choices=("cpu", "cuda", "auto"),
                   help="torch device (default: the config's)")
    p.add_argument("--iterations", type=int_arg(1, le=ITERATIONS_LIMIT), default=None, metavar="N",
                   help="training iterations, overriding the preset's")
    p.add_argument("--no-resume", action="store_true",
                   help="start afresh even if --out holds a checkpoint or a finished run of this config")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="FIELD=VALUE",
                   help=SET_HELP)
    p.set_defaults(train_parser=p)
    return p


def train_command(args, parser: argparse.ArgumentParser) -> int:
    """Build the TrainConfig from the flags, run pemamoe.mappo.train, print a summary. Errors of the
    run folder (a lock held by another process, a damaged or foreign file, a failed write), of the
    store (no credentials, no endpoint, no bucket) and Ctrl-C end it with one line on stderr and a
    non-zero status, not a traceback."""
    from pemamoe.commands import error_line  # light: no torch
    from pemamoe.core import checkout_store
    from pemamoe.store import check_access, open_store  # light: fsspec only for a URL

    if args.out is not None and args.out.strip() == "":
        parser.error("--out must name a folder, got an empty string (--out . is the current directory)")
    _check_out(args.out, parser)
    _check_controller_flags(args, parser)  # what needs no trainer is checked before it is imported
    _check_device(args.device, parser)
    try:
        args.store = open_store(checkout_store(args.results_dir, "results"))
    except ValueError as err:
        parser.error(f"--results-dir: {err}")
    _check_store_folder("--results-dir", args.results_dir, args.store, parser)
    if args.store.remote and args.out is not None:
        parser.error(f"--out names a local folder and --results-dir {args.results_dir} a remote store; the run "
                     "goes to <store>/train/<run name>: pass one of them")
    try:
        check_access(args.store)  # a URL: its credentials, endpoint and bucket, before the trainer is imported
        return _train(args, parser)
    except KeyboardInterrupt:
        where = f" in {args.run_dir}" if getattr(args, "run_dir", None) is not None else ""
        print(f"\n{parser.prog}: interrupted; the run{where} can be resumed: run the same command again to "
              "continue from its last checkpoint (--no-resume starts it over)", file=sys.stderr)
        return 130
    except Exception as err:
        line = error_line(err, [args.store], start_over="delete the folder, or pass --no-resume to start it over")
        if line is None or _traceback_wanted():
            raise
        print(f"{parser.prog}: error: {line}", file=sys.stderr)
        return 1


def _check_out(out, parser) -> None:
    if out is not None:
        _check_utf8("--out", out, parser)
    if out is not None and Path(out).exists() and not Path(out).is_dir():
        parser.error(f"--out {out} is a file, not a folder; name a folder (it is created if missing)")


def _check_utf8(flag: str, path, parser) -> None:
    """A path the run folder's files name as text (config.json, done.json, records) must be UTF-8."""
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        parser.error(f"{flag} {ascii(str(path))}: the path is not valid UTF-8 (the run's files name it as "
                     "text); name a folder whose path is UTF-8")


def _check_store_folder(flag: str, text: str, store, parser) -> None:
    """A local store named by `flag` is a folder, or not there yet (it is created): a file there is
    refused here, naming the flag, rather than as "Not a directory" once the trainer runs."""
    if store.remote:
        return
    _check_utf8(flag, text, parser)
    if store.folder.exists() and not store.folder.is_dir():
        parser.error(f"{flag} {text} is a file, not a folder; name a folder (it is created if missing) or a URL "
                     "such as s3://bucket/prefix")


def _check_controller_flags(args, parser) -> None:
    """--without and --noise-gamma configure the phase controller: refused, before the trainer is
    imported, for a method without it."""
    from pemamoe.methods import METHOD_REGISTRY, method_spec

    if not (args.without or args.noise_gamma is not None) or method_spec(args.method).plasticity == "phase_controller":
        return
    with_controller = " or ".join(f"--method {m}" for m, spec in METHOD_REGISTRY.items()
                                  if spec.plasticity == "phase_controller")
    parser.error(f"--without and --noise-gamma configure the phase controller, which only {with_controller} "
                 f"uses; got --method {args.method}")


def _check_device(device, parser) -> None:
    """--device cuda on a machine whose torch cannot see a GPU, told without importing torch (10 s
    here): a torch built for CPUs only (its version.py says cuda = None and hip = None), or no GPU
    driver's device file. The trainer checks again (resolve_device) where this cannot tell."""
    from importlib.util import find_spec

    if device != "cuda":
        return
    spec = find_spec("torch")
    if spec is None or not spec.submodule_search_locations:
        return
    try:
        text = (Path(next(iter(spec.submodule_search_locations))) / "version.py").read_text()
    except OSError:
        return
    import re

    builds = {key: re.search(rf"^{key}\b[^=\n]*=\s*(.+)$", text, re.M) for key in ("cuda", "hip", "__version__")}
    if builds["cuda"] is None or builds["hip"] is None:
        return
    version = builds["__version__"].group(1).strip().strip("'\"") if builds["__version__"] else "?"
    if builds["cuda"].group(1).strip() == "None" and builds["hip"].group(1).strip() == "None":
        parser.error(f"--device cuda: this machine's torch {version} is built for CPUs only, so torch sees no CUDA "
                     "device; use --device cpu or --device auto")
    import glob

    if sys.platform.startswith("linux") and not (glob.glob("/dev/nvidia[0-9]*") or Path("/dev/kfd").exists() or Path("/dev/dxg").exists()):
        parser.error("--device cuda: no GPU device file on this machine (no /dev/nvidia*), so torch sees no CUDA "
                     "device; use --device cpu or --device auto")


def _train(args, parser: argparse.ArgumentParser) -> int:
    from pemamoe import mappo
    from pemamoe.train_config import parse_settings

    try:
        overrides = parse_settings(args.settings)
    except ValueError as err:
        parser.error(f"--set: {err}")
    if args.iterations is not None:
        overrides["iterations"] = args.iterations
    if args.without:
        overrides["without"] = tuple(args.without)
    if args.noise_gamma is not None:
        overrides["noise_gamma"] = args.noise_gamma
    if args.device is not None:
        overrides["device"] = args.device
    try:
        config = mappo.TrainConfig.for_scale(args.scale, method=args.method, seed=args.seed, **overrides)
        mappo.resolve_device(config.device)  # --device cuda on a machine whose torch sees no GPU
    except ValueError as err:
        parser.error(str(err))
    if args.store.remote:
        from pemamoe.store import checked_out

        with checked_out(args.store, [("train", config.run_name())]) as (out,):
            return _train_in(out, config, args, parser)
    out = Path(args.out) if args.out is not None else args.store.run_dir("train", config.run_name())
    return _train_in(out, config, args, parser)


def _train_in(out: Path, config, args, parser) -> int:
    from pemamoe import mappo
    from pemamoe.runs import RunFolderError, check_stored_config, read_config, read_json

    _check_out(out, parser)
    stored = out / "config.json"
    if not args.no_resume and stored.exists():
        try:  # garbage (not JSON, not an object, not a TrainConfig) is named as such
            read_config(stored, mappo.TrainConfig)
        except RunFolderError as err:
            parser.exit(2, one_line(f"{parser.prog}: error: --out {out}: {stored} is damaged or unreadable: it "
                                    f"{err.problem}; remove it, choose another --out, or pass --no-resume to start "
                                    "a new run there") + "\n")
        try:  # another run's config: named by the keys that differ
            check_stored_config(read_json(stored), config, stored)
        except RunFolderError as err:
            parser.exit(2, one_line(f"{parser.prog}: error: --out {out}: {stored.name} {err.problem}; choose another "
                                    "--out, or pass --no-resume to overwrite it") + "\n")
    out.mkdir(parents=True, exist_ok=True)
    args.run_dir = out  # named if the run is interrupted
    result = mappo.train(config, out, resume=not args.no_resume, progress=None)
    print_summary(result, out)
    return 0


def print_summary(result, out: Path) -> None:
    config, m = result.config, result.metrics
    final = m.tail(config.phase_length_iters)  # the last phase, as done.json's final_episode_return
    how = "loaded, finished earlier (--no-resume retrains)" if result.from_cache else (
        f"resumed at iteration {result.resumed_from}" if result.resumed_from else "trained")
    print(f"[train] {config.method}, seed {config.seed}: {len(m)} iterations, "
          f"{int(m['env_steps'].iloc[-1]):,} env steps ({how})")
    print(f"  final return   {final['episode_return'].mean():10.2f}  (mean over the last {len(final)} iterations)")
    print(f"  coverage       {final['coverage'].mean():10.3f}")
    print(f"  served users   {final['served_users'].mean():10.2f}")
    print(f"  wall time      {m['wall_time'].iloc[-1]:10.1f} s")
    print(f"  SPS            {m['sps'].median():10,.0f}  (median per iteration)")
    print(f"  run directory  {out}")


if __name__ == "__main__":
    sys.exit(main())
