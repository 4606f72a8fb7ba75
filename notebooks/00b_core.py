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
# # 00b · Appendix: the shared machinery (`pemamoe/core.py`)
#
# Nothing in this notebook is part of the paper. It holds the few utilities every other notebook
# shares, so that the reader of notebooks 01–10 meets physics and learning rather than plumbing:
#
# * **scales**: one `scale` parameter sizes every notebook (`ci`, `small`, `medium`, `paper`);
# * **validation**: `require`, the one checker behind every configuration class;
# * **files**: atomic writes that follow the umask, and figure/table output into the repository's
#   `paper_figures/`, wherever the notebook runs from;
# * **the headless runner**: `run_notebook`, which `make figures` (appendix 09e) calls for every
#   notebook, and the provenance table `paper_figures/README.md`.

# %%
#| default_exp core

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## Scales
#
# Every notebook takes a `scale` parameter. `ci` must finish in seconds to a few minutes (the test
# suite runs every notebook at this scale); `small` regenerates every figure with real but short
# training (about half an hour on a 2-core machine once the learning-budget study is cached; the
# README gives the measured costs of every scale); `medium` trains each phase long enough to learn
# in (notebook 09b) and costs hours; `paper` follows the paper's training table. A notebook picks
# its sizes with `by_scale`, so the sizes sit next to each other in the code; `medium` takes the
# small size unless a notebook gives it its own, since most sizes are not about training.

# %%
#| export
import json
import math
import numbers
import os
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

SCALES = ("ci", "small", "medium", "paper")
# --scale's help for the commands that train (train, sweep): one wording of the default-scale story
TRAINING_SCALE_HELP = ("the preset, trained in minutes at small (default: small); figures defaults to medium, "
                       "whose records are committed")


def check_scale(scale: str) -> str:
    """Return `scale` if it is one of SCALES, else raise a ValueError naming the allowed values."""
    if scale not in SCALES:
        raise ValueError(f"scale must be one of {', '.join(SCALES)}; got {scale!r}")
    return scale


_SAME_AS_SMALL = object()


def by_scale(scale: str, *, ci, small, paper, medium=_SAME_AS_SMALL):
    """The value for `scale`: keeps a notebook's problem sizes side by side. `medium` is a longer
    training budget (notebook 09b); a size that is not about training (a figure's resolution, an
    illustration's sample count) stays at its small value there unless `medium` is given."""
    medium = small if medium is _SAME_AS_SMALL else medium
    return {"ci": ci, "small": small, "medium": medium, "paper": paper}[check_scale(scale)]


# %% [markdown]
# ## One validator for every configuration
#
# Every number of the project lives in a frozen dataclass that checks itself on construction, so
# a bad value fails at once, naming the class, the field, the value and what is allowed, instead
# of deep inside a training run. All of them call one function, `require`, so the rules are the
# same everywhere:
#
# * a field has a **kind**: `"int"`, `"real"`, `"bool"`, `"choice"` (one of `allowed`), `"str"`,
#   or `"reals"` (a tuple of reals, one per phase say);
# * **NumPy scalars** count as the Python numbers they stand for, and are stored as plain `int` /
#   `float`, so a config built from array values still hashes and serialises to JSON;
# * a **bool is never a number** (`episode_steps=True` is not a one-step episode) and a **string
#   is never a number** (`"100"` is not 100 m);
# * **NaN is never allowed**, and **±inf** only where a field says so (`allow_inf=True`);
# * **bounds** are keywords: `gt`, `ge` (lower, open or closed), `lt`, `le` (upper).
#
# It returns the normalised value; `require_field` does the same for a field of a (frozen)
# dataclass and stores the normalised value back. `config_error` builds the same message for a rule
# that involves several fields.
#
# ```python
# require_field(self, "n_uavs", "int", ge=1)                         # an integer >= 1
# require_field(self, "bandwidth_hz", "real", gt=0)                  # a finite float > 0
# require_field(self, "adjacent_leakage", "real", ge=0, lt=1)       # a finite float in [0, 1)
# require_field(self, "use_gae", "bool")                             # True or False
# require_field(self, "phase_clock", "choice", ("env", "external"))  # one of 'env', 'external'
# require_field(self, "min_period", "int", ge=1, optional=True)     # an integer >= 1, or None
# require_field(self, "user_speed_mps", "reals", ge=0, length=3)    # a tuple of 3 finite floats >= 0
# seed = require("make_vector_env", "seed", seed, "int", ge=0, optional=True)
# ```

# %%
#| export
KINDS = ("int", "real", "bool", "choice", "str", "reals")


def config_error(owner: str, field: str, value, allowed: str) -> ValueError:
    """The project's validation error: `<owner>.<field> must be <allowed>, got <value>`."""
    return ValueError(f"{owner}.{field} must be {allowed}, got {_show(value)}")


def require(owner: str, field: str, value, kind: str, allowed=None, *, gt=None, ge=None, lt=None, le=None,
            allow_inf: bool = False, optional: bool = False, length: int | None = None, note: str = ""):
    """Check one setting and return it normalised (Python int / float / bool / str / tuple of floats).

    owner, field: named in the error (`ChannelConfig`, `bandwidth_hz`; or a function and argument).
    kind:         "int" | "real" | "bool" | "choice" | "str" | "reals" (a tuple of reals).
    allowed:      the permitted values, for kind "choice".
    gt, ge, lt, le: bounds for "int", "real" and every element of "reals" (strict: gt, lt).
    allow_inf:    accept +-inf for "real"/"reals" (NaN is never accepted).
    optional:     accept None (returned as None).
    length:       the required number of elements, for "reals".
    note:         a reason appended to the description of what is allowed.
    Raises ValueError (see `config_error`) naming owner, field, value and what is allowed.
    """
    if kind not in KINDS:
        raise ValueError(f"require: kind must be one of {', '.join(KINDS)}, got {kind!r}")
    if kind == "choice" and not allowed:
        raise ValueError("require: kind 'choice' needs the allowed values")
    bounds = {"gt": gt, "ge": ge, "lt": lt, "le": le}
    what = _describe(kind, allowed, bounds, allow_inf, length) + (" or None" if optional else "") + \
        (f" ({note})" if note else "")
    if optional and value is None:
        return None
    ok, normal = _normalise(kind, value, allowed, bounds, allow_inf, length)
    if not ok:
        raise config_error(owner, field, value, what)
    return normal


def require_field(obj, field: str, kind: str, allowed=None, **rules):
    """`require` for a dataclass field: check getattr(obj, field), store the normalised value back
    (frozen dataclasses included) and return it. The error names type(obj).__name__ and `field`."""
    value = require(type(obj).__name__, field, getattr(obj, field), kind, allowed, **rules)
    object.__setattr__(obj, field, value)
    return value


# %%
#| exporti
def _show(value) -> str:
    # NumPy 2 reprs numpy scalars as np.float64(...): show the number and, if not plain, its type.
    if isinstance(value, (bool, int, float, str)) or value is None:
        return repr(value)
    if _is_np_scalar(value):
        return f"{value.item()!r} ({type(value).__name__})"
    return repr(value)


def _is_np_scalar(value) -> bool:
    return type(value).__module__ == "numpy" and hasattr(value, "item") and getattr(value, "ndim", None) == 0


def _fmt(bound) -> str:
    return repr(bound) if isinstance(bound, float) else str(bound)


def _interval(bounds) -> str:
    lo = ("gt", bounds["gt"]) if bounds["gt"] is not None else ("ge", bounds["ge"])
    hi = ("lt", bounds["lt"]) if bounds["lt"] is not None else ("le", bounds["le"])
    if lo[1] is not None and hi[1] is not None:
        return f"in {'(' if lo[0] == 'gt' else '['}{_fmt(lo[1])}, {_fmt(hi[1])}{')' if hi[0] == 'lt' else ']'}"
    symbol = {"gt": ">", "ge": ">=", "lt": "<", "le": "<="}
    for name, bound in (lo, hi):
        if bound is not None:
            return f"{symbol[name]} {_fmt(bound)}"
    return ""


def _describe(kind, allowed, bounds, allow_inf, length) -> str:
    interval = _interval(bounds)
    tail = f" {interval}" if interval else ""
    if kind == "int":
        return "an integer" + tail
    if kind == "real":
        return ("a float (inf allowed)" if allow_inf else "a finite float") + tail
    if kind == "bool":
        return "a bool (True or False)"
    if kind == "str":
        return "a string"
    if kind == "choice":
        return "one of " + ", ".join(repr(a) for a in allowed)
    count = f"{length} " if length is not None else "a non-empty tuple of "
    floats = "floats (inf allowed)" if allow_inf else "finite floats"
    return (f"a tuple of {count}" if length is not None else count) + floats + tail


def _within(x, bounds) -> bool:
    return ((bounds["gt"] is None or x > bounds["gt"]) and (bounds["ge"] is None or x >= bounds["ge"])
            and (bounds["lt"] is None or x < bounds["lt"]) and (bounds["le"] is None or x <= bounds["le"]))


def _as_real(value, bounds, allow_inf):
    # numbers.Real covers int, float, numpy integers and floats; bool is excluded explicitly.
    if isinstance(value, bool) or _is_np_bool(value) or not isinstance(value, numbers.Real):
        return False, None
    x = float(value)
    if math.isnan(x) or (math.isinf(x) and not allow_inf) or not _within(x, bounds):
        return False, None
    return True, x


def _is_np_bool(value) -> bool:
    return type(value).__name__ in ("bool_", "bool") and type(value).__module__ == "numpy"


def _normalise(kind, value, allowed, bounds, allow_inf, length):
    if kind == "int":
        if isinstance(value, bool) or _is_np_bool(value) or not isinstance(value, numbers.Integral):
            return False, None
        value = int(value)
        return _within(value, bounds), value
    if kind == "real":
        return _as_real(value, bounds, allow_inf)
    if kind == "bool":
        if isinstance(value, bool) or _is_np_bool(value):
            return True, bool(value)
        return False, None
    if kind == "str":
        return isinstance(value, str), (str(value) if isinstance(value, str) else None)
    if kind == "choice":
        if _is_np_scalar(value):
            value = value.item()
        # 1 == True and 0 == False in Python: a bool only matches a bool choice, and the reverse.
        matches = [a for a in allowed if a == value and isinstance(a, bool) == isinstance(value, bool)]
        return bool(matches), (matches[0] if matches else None)
    # "reals": a tuple (or list, or 1-D array) of reals, stored as a tuple of floats.
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or getattr(value, "ndim", 1) != 1:
        return False, None
    if (length is not None and len(value) != length) or len(value) == 0:
        return False, None
    out = []
    for item in value:
        ok, x = _as_real(item, bounds, allow_inf)
        if not ok:
            return False, None
        out.append(x)
    return True, tuple(out)


# %% [markdown]
# ## The command line's names and argument checks
#
# `python -m pemamoe COMMAND --help`, and every usage error, must answer at once, so the command
# line builds its parsers before any heavy module (torch, the trainer, the experiments) is
# imported. The names its options offer therefore live here, at the bottom of the package, and the
# modules that own them re-export them: the sweep backends and the default population size
# (appendix 09c), the experiments (notebook 09), the phase controller's mechanisms (notebook 06)
# and the seeds a `TrainConfig` accepts (appendix 07c).
#
# `int_arg` and `real_arg` are argparse's `type=` for every count and number of every command, each
# bounded on both sides: a bad value is refused while the arguments are parsed, naming the flag,
# the value as typed and what is allowed, in `require`'s words (`--workers: must be an integer in
# [1, 1024], got '0'`). `one_line` flattens any error to the single `error:` line a command ends with.

# %%
#| export
BACKENDS = ("local", "ray")  # where a sweep trains (appendix 09c)
DEFAULT_POPULATION = 16  # members per population: throughput rises with R up to here (make bench)
EXPERIMENTS = ("main", "tricks", "noise", "all", "campaign", "campaign_v2", "budget", "gating", "sparse", "tuning", "top2")  # notebook 09's sweeps
READABLE_EXPERIMENTS = ("main", "tricks", "noise", "all", "campaign")  # those whose sparse-actor reading sweep --reading pins
ACTOR_READINGS = ("ours", "paper")  # the sparse actor's two readings (appendix 05d)
MECHANISMS = (  # the phase controller's switch-time mechanisms, each a PhaseControllerConfig switch (notebook 06)
    "kl_anchor",
    "adam_reset",
    "noise_injection",
    "log_std_reset",
    "entropy_reset",
    "lr_drop",
    "conservative_window",
    "router_freeze",
    "temperature_schedule",
)
SEED_LIMIT = 2**63  # seeds are 0 <= seed < 2**63, so every environment's seed + index fits torch's 64-bit seed
ITERATIONS_LIMIT, NOISE_GAMMA_LIMIT = 10**7, 10.0  # upper bounds (issue 59): 926x the paper's 10,800; 2,000x its 0.005
WORKERS_LIMIT, HOURS_LIMIT = 1024, 8760.0  # workers (or runs of one population) of a sweep or figures; --hours: a year


def int_arg(low: int, below: int | None = None, *, le: int | None = None):
    """argparse `type=`: an integer >= low (< below, or <= le), else ArgumentTypeError naming it and what is allowed."""
    allowed = f"in [{low}, {le}]" if le is not None else f">= {low}" if below is None else f"in [{low}, {_bound_text(below)})"
    below = le + 1 if le is not None else below

    def parse(text: str) -> int:
        import argparse

        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < low or (below is not None and value >= below):
            raise argparse.ArgumentTypeError(f"must be an integer {allowed}, got {text!r}")
        return value

    return parse


def real_arg(*, gt: float | None = None, ge: float | None = None, le: float | None = None):
    """argparse `type=`: a finite number > gt (or >= ge; <= le), else ArgumentTypeError naming it and what is allowed."""
    allowed = f" > {gt:g}" if gt is not None else f" >= {ge:g}" if ge is not None else ""
    allowed += (" and" if allowed else "") + f" <= {le:g}" if le is not None else ""

    def parse(text: str) -> float:
        import argparse

        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not math.isfinite(value) or not _within(value, {"gt": gt, "ge": ge, "lt": None, "le": le}):
            raise argparse.ArgumentTypeError(f"must be a finite number{allowed}, got {text!r}")
        return value

    return parse


def one_line(message) -> str:
    """`message` (an exception or text) as one line: its whitespace runs, newlines included, become
    single spaces."""
    return " ".join(str(message).split())


# %%
#| exporti
def _bound_text(bound: int) -> str:
    """A large power of two as `2**k` (the seed limit reads 2**63, not 19 digits)."""
    if bound >= 2**20 and bound & (bound - 1) == 0:
        return f"2**{bound.bit_length() - 1}"
    return str(bound)


# %% [markdown]
# ## Where the repository is, and where outputs go
#
# Outputs belong in the repository's `paper_figures/` (and `results/`), whether a notebook runs
# under papermill (kernel started in the repository root), in JupyterLab (kernel started in
# `notebooks/`), or as a script from anywhere. A relative `figures_dir` such as the notebooks'
# default `"paper_figures"` is therefore read relative to the repository root, never to the
# working directory; an absolute one (tests inject temporary folders) is used as given.
#
# The root is the first folder, going up from this module's file (an editable install or a plain
# checkout both keep `pemamoe/` inside the checkout), then from the working directory, that holds
# `notebooks/` and the `pyproject.toml` of `pemamoe`. The environment variable `PEMAMOE_ROOT`
# overrides the search (for a copy of the package installed outside the checkout).

# %%
#| export
def _is_checkout(folder: Path) -> bool:
    pyproject = folder / "pyproject.toml"
    if not (pyproject.is_file() and (folder / "notebooks").is_dir()):
        return False
    try:
        return 'name = "pemamoe"' in pyproject.read_text(encoding="utf-8")
    except OSError:
        return False


def find_repo_root(*starts) -> Path:
    """The pemamoe checkout above the first of `starts` that lies in one (default: this module's
    folder, then the working directory); $PEMAMOE_ROOT wins; the working directory if none."""
    if os.environ.get("PEMAMOE_ROOT"):
        return Path(os.environ["PEMAMOE_ROOT"]).expanduser().resolve()
    if not starts:
        here = [Path(__file__).resolve().parent] if "__file__" in globals() else []
        starts = (*here, Path.cwd())
    for start in starts:
        start = Path(start).resolve()
        for folder in (start, *start.parents):
            if _is_checkout(folder):
                return folder
    return Path.cwd().resolve()


REPO_ROOT = find_repo_root()


def repo_path(path) -> Path:
    """`path` itself if absolute, else the same path under the repository root."""
    path = Path(path).expanduser()
    return path if path.is_absolute() else REPO_ROOT / path


def checkout_store(text, default: str):
    """A store argument (`--results-dir`, `--records-dir`) as every command reads it: its default
    name (`results`, `records`) is the checkout's folder of that name, wherever the command runs,
    because `figures` reads the checkout's; any other text is returned as given (a folder relative
    to where the command runs, or a URL)."""
    return repo_path(default) if str(text) == default else text


# %% [markdown]
# The stores that `train`, `sweep` and `figures` share follow one rule, `checkout_store`: the
# default name is the checkout's folder (so a sweep started from a plugin's folder fills the
# records that `figures` reads), any other folder is where the user says, and a URL is a URL.

# %%
assert checkout_store("results", "results") == REPO_ROOT / "results"
assert checkout_store("records", "records") == REPO_ROOT / "records"
assert checkout_store("my_results", "results") == "my_results"  # relative to where the command runs
assert checkout_store("s3://bucket/prefix", "records") == "s3://bucket/prefix"


# %% [markdown]
# ## Writing files atomically
#
# Long runs get killed. A file that is half written when that happens must never be mistaken for
# a result, so every writer in the project writes to a temporary file in the same folder and
# renames it into place: a rename within one file system is atomic, and the reader sees either the
# old file or the new one.
#
# `tempfile.mkstemp` creates its file readable by its owner only (0600), whatever the umask says;
# renamed into place, that would make every figure and result private. Before the rename the file
# therefore gets the mode an ordinary `open(path, "w")` would have given it: `0o666 & ~umask`.

# %%
#| export
def current_umask() -> int:
    """The process umask (read from /proc where possible: setting it to read it is not
    thread-safe)."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(path):
    """Yield a temporary path beside `path`; on success rename it onto `path` (with the mode the
    umask gives new files), else delete it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~current_umask())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def atomic_write_text(path, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def atomic_write_bytes(path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_json(path, obj) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n")


# %% [markdown]
# ## Saving figures and tables
#
# Figures go out as PNG (for the README and the notebooks) and PDF (for papers). Creation dates
# are left out of the files so that regenerating an unchanged figure gives identical PDF bytes
# and a clean `git diff`. Tables go out as Markdown (readable on GitHub) and CSV (for reuse).
# Both functions return None, so a notebook cell that ends with them prints nothing.

# %%
#| export
def save_figure(fig, name: str, figures_dir, dpi: int = 150) -> None:
    """Write `fig` as `<figures_dir>/<name>.png` and `.pdf`, atomically (a relative figures_dir is
    under the repository root)."""
    for ext, meta in (("png", {"Software": None}), ("pdf", {"CreationDate": None, "Producer": None})):
        with atomic_path(repo_path(figures_dir) / f"{name}.{ext}") as tmp:
            fig.savefig(tmp, format=ext, dpi=dpi, bbox_inches="tight", metadata=meta)


def write_table(df, name: str, figures_dir, floatfmt: str = ".4g") -> None:
    """Write a pandas DataFrame as `<name>.md` (Markdown) and `<name>.csv`, atomically (a relative
    figures_dir is under the repository root)."""
    folder = repo_path(figures_dir)
    atomic_write_text(folder / f"{name}.md", _markdown_table(df, floatfmt) + "\n")
    atomic_write_text(folder / f"{name}.csv", df.to_csv(index=False))


# %%
#| exporti
def _markdown_table(df, floatfmt: str) -> str:
    # A tiny renderer, so tables do not depend on the optional `tabulate` package.
    def fmt(v):
        if isinstance(v, float):
            return format(v, floatfmt)
        return str(v)

    header = "| " + " | ".join(str(c) for c in df.columns) + " |"
    rule = "|" + "|".join("---" for _ in df.columns) + "|"
    rows = ["| " + " | ".join(fmt(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join([header, rule, *rows])


# %% [markdown]
# ## Running a notebook headlessly
#
# `run_notebook` is the one function that executes a notebook without a browser. Papermill only
# reads JSON notebooks, so the percent-format `.py` file is converted in memory with Jupytext.
# Papermill then injects the given parameters after the cell tagged `parameters`, runs every cell
# with a per-cell timeout, and saves the executed copy under `build/executed/` (git ignores it; `make
# figures` a folder per scale), where a failing run can be opened to see the traceback in context. The test suite calls it with
# `scale="ci"`; `make figures` calls it with the chosen scale and `figures_dir="paper_figures"`.
#
# **Transport encryption.** ipykernel ≥ 7 prints "Kernel is running over TCP without encryption"
# to the terminal at every kernel start unless the kernel manager provisions CurveZMQ keys. We fix
# the cause rather than filter the message: the kernel manager runs with
# `transport_encryption="auto"`, so it hands the kernel a key pair whenever pyzmq has CurveZMQ and
# the kernelspec declares `supported_encryption: curve` (ipykernel's own kernelspec does); the
# kernel then encrypts its sockets and has nothing to warn about. Where either is missing, the
# policy stays "disabled", as before.
#
# **A quiet shutdown.** jupyter_client stops a finished kernel with SIGINT, then a shutdown request;
# a kernel still handling a message logs `KeyboardInterrupt caught in kernel.`, a false alarm (a
# race: a few notebooks per `make figures`). `_quiet_kernel_manager` skips that one interrupt.
#
# **Streaming.** With `stream=True` the notebook's own stdout and stderr (progress lines of a
# sweep, say) are copied to this process's terminal as they arrive (papermill's `stdout_file` /
# `stderr_file`). The test suite leaves it off, so tests print nothing.

# %%
#| export
def run_notebook(notebook, parameters=None, *, output_dir=None, timeout: int = 1800, cwd=None,
                 stream: bool = False):
    """Execute `notebook` (a notebooks/*.py file) with papermill; return the executed notebook.

    parameters: dict injected after the cell tagged "parameters" (e.g. scale, figures_dir).
    output_dir: where the executed .ipynb goes (default build/executed under the repository).
    timeout:    seconds allowed per cell.
    cwd:        working directory of the kernel (default: the repository root).
    stream:     copy the notebook's stdout/stderr to this process's as the cells run.
    """
    import jupytext
    import papermill as pm

    notebook = Path(notebook)
    if not notebook.is_file():
        raise FileNotFoundError(f"notebook not found: {notebook}")
    parameters = dict(parameters or {})
    if "scale" in parameters:
        check_scale(parameters["scale"])
    output_dir = Path(output_dir) if output_dir else REPO_ROOT / "build" / "executed"
    output_dir.mkdir(parents=True, exist_ok=True)
    nb = jupytext.read(notebook)
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    # The kernel must be this interpreter (the project's virtual environment), whatever PATH says.
    os.environ["PATH"] = str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", "")
    os.environ.setdefault("MPLBACKEND", "Agg")
    return pm.execute_notebook(
        nb,
        str(output_dir / f"{notebook.stem}.ipynb"),
        parameters=parameters,
        kernel_name="python3",
        language="python",
        execution_timeout=timeout,
        cwd=str(cwd or REPO_ROOT),
        progress_bar=False,
        stdout_file=sys.stdout if stream else None,
        stderr_file=sys.stderr if stream else None,
        config=_kernel_manager_config(),
        kernel_manager_class=_quiet_kernel_manager(),
    )


# %%
#| exporti
def _quiet_kernel_manager():
    # no SIGINT before the shutdown request of a finished kernel ("A quiet shutdown" above)
    from jupyter_client.manager import AsyncKernelManager

    class QuietShutdownKernelManager(AsyncKernelManager):
        async def _async_interrupt_kernel(self) -> None:
            if self.shutting_down:
                return
            await super()._async_interrupt_kernel()

    return QuietShutdownKernelManager


def _kernel_manager_config():
    # CurveZMQ keys for the kernel (see "Transport encryption" above), when both sides can use them.
    from traitlets.config import Config

    config = Config()
    try:
        import zmq

        if zmq.has("curve"):
            config.KernelManager.transport_encryption = "auto"
    except ImportError:  # pragma: no cover - pyzmq is a dependency of the kernel machinery
        pass
    return config


# %% [markdown]
# ## Progress in a terminal and in a log
#
# Training and sweeps report progress on stderr. In a terminal that knows its width the report is
# a tqdm bar redrawn in place. Where redrawing has no meaning (a CI log, a file, an IDE console
# that reports a width of 0 columns, in which tqdm would draw nothing) the same counts come as
# plain lines: one at the start, then at most one every `every` seconds, and one at the end. When a
# run is interrupted the bar is cleared rather than left behind, so the interrupt message is the
# last thing on the screen. `progress=None` means "only if stderr is a terminal".

# %%
#| export
class Progress:
    """Progress of `total` steps on stderr, starting at `initial`: a tqdm bar in a sized terminal,
    plain lines elsewhere (see above). enabled: True, False or None (only when stderr is a
    terminal). Use as a context manager, or call `close(clear=...)` yourself."""

    def __init__(self, total: int, initial: int = 0, *, label: str, unit: str = "it", enabled: bool | None = None,
                 every: float = 30.0, stream=None):
        import time

        self.stream = sys.stderr if stream is None else stream
        self.enabled = _is_terminal(self.stream) if enabled is None else bool(enabled)
        self.total, self.n, self.label, self.unit, self.every = total, initial, label, unit, every
        self.postfix, self._clock, self._bar = {}, time.monotonic, None
        self._start = self._last = self._clock()
        self._initial, self._reported = initial, None  # the count of the last plain line
        if self.enabled and _terminal_columns(self.stream) > 0:
            from tqdm.auto import tqdm

            self._bar = tqdm(total=total, initial=initial, desc=label, unit=unit, dynamic_ncols=True, leave=True,
                             file=self.stream)
        elif self.enabled:
            self._line()

    def update(self, n: int = 1) -> None:
        self.n += n
        if self._bar is not None:
            self._bar.update(n)
        elif self.enabled and self._clock() - self._last >= self.every:
            self._line()

    def set_postfix(self, **values) -> None:
        """Values shown after the counts (refreshed with the next update)."""
        self.postfix = values
        if self._bar is not None:
            self._bar.set_postfix(refresh=False, **values)

    def write(self, message: str) -> None:
        """A line of text that does not break the bar."""
        if self._bar is not None:
            self._bar.write(message, file=self.stream)
        else:
            print(message, file=self.stream, flush=True)

    def close(self, clear: bool = False) -> None:
        """Stop reporting: the bar (or a last plain line) stays, unless `clear` (an interruption)."""
        if self._bar is not None:
            self._bar.leave = not clear
            self._bar.close()
            self._bar = None
        elif self.enabled and not clear and self.n != self._reported:
            self._line()
        self.enabled = False

    def __enter__(self):
        return self

    def __exit__(self, kind, error, trace) -> None:
        self.close(clear=kind is not None)

    def _line(self) -> None:
        from tqdm import tqdm

        elapsed = self._clock() - self._start
        rate = (self.n - self._initial) / elapsed if elapsed > 0 else None
        post = ", ".join(f"{k}={v}" for k, v in self.postfix.items())
        text = tqdm.format_meter(self.n, self.total, elapsed, prefix=self.label, unit=self.unit, rate=rate,
                                 postfix=post or None,
                                 bar_format="{desc}: {n_fmt}/{total_fmt} {unit} [{elapsed}<{remaining}, {rate_fmt}{postfix}]")
        print(text, file=self.stream, flush=True)
        self._last, self._reported = self._clock(), self.n


# %%
#| exporti
def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # a closed or replaced stream
        return False


def _terminal_columns(stream) -> int:
    """The width of the terminal behind `stream`; 0 when it is none or does not say."""
    if not _is_terminal(stream):
        return 0
    try:
        return os.get_terminal_size(stream.fileno()).columns
    except (OSError, ValueError, AttributeError):
        return 0


# %% [markdown]
# A log, as CI sees it: a start line, a line every `every` seconds (here 0, so each step), the end.

# %%
import io

_log = io.StringIO()
with Progress(3, label="demo", unit="run", enabled=True, every=0.0, stream=_log) as _p:
    for _ in range(3):
        _p.set_postfix(phase=0)
        _p.update()
print(_log.getvalue())
assert _log.getvalue().count("\n") == 4 and "3/3 run" in _log.getvalue()
_log = io.StringIO()
try:
    with Progress(3, label="demo", enabled=True, every=60.0, stream=_log) as _p:
        _p.update()
        raise KeyboardInterrupt
except KeyboardInterrupt:
    pass
assert _log.getvalue().count("\n") == 1  # the start line only: nothing re-printed after the interrupt

# %% [markdown]
# ## Regenerating every figure
#
# `make figures` runs the notebooks in paper order (`figure_notebooks`) with the same runner,
# pointing their `figures_dir` at `paper_figures/`; the command itself, `make_figures`, trains the
# sweeps first and so sits above them, in appendix 09e (`pemamoe.commands`), with what it writes at
# the end: `paper_figures/README.md` (`write_figures_readme`), the provenance of every file. Here
# are the pieces it shares with the notebooks: their parameters, their order, the processor.

# %%
#| export
def notebook_parameters(notebook) -> set:
    """Names assigned in a notebook's cell tagged "parameters" (so callers pass only those)."""
    import ast

    text = Path(notebook).read_text(encoding="utf-8")
    marker = '# %% tags=["parameters"]'
    if marker not in text:
        return set()
    body = text.split(marker, 1)[1].split("\n# %%", 1)[0]
    return {t.id for node in ast.parse(body).body if isinstance(node, ast.Assign)
            for t in node.targets if isinstance(t, ast.Name)}


def figure_notebooks(root=None) -> list:
    """Every notebook, in paper order: the numbered ones (NN_name.py) and their appendices
    (NNx_name.py, e.g. 00b_core.py right after 00_index.py)."""
    folder = Path(root or REPO_ROOT) / "notebooks"
    return sorted({*folder.glob("[0-9][0-9]_*.py"), *folder.glob("[0-9][0-9][a-z]_*.py")},
                  key=lambda p: p.name)


def cpu_model() -> str:
    """The processor's model name (Linux's /proc/cpuinfo), else what `platform` knows. Float
    kernels differ between processor families, so a figure computed at plot time can differ in its
    last digits from one family to another: records and figure folders say where they were made."""
    import platform

    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


# %% [markdown]
# ## A quick look
#
# What the validator and the command line's argument checks say about a few bad values, where this
# kernel thinks the repository is, and the notebooks `make figures` runs, in order.

# %%
for bad in (dict(value=True, kind="int", ge=1), dict(value="100", kind="real", gt=0), dict(value=float("inf"), kind="real",
            gt=0), dict(value="jax", kind="choice", allowed=("compiled", "numpy"))):
    try:
        require("Demo", "field", **bad)
    except ValueError as err:
        print(err)
import argparse

for parse, text in ((int_arg(1), "0"), (int_arg(0, SEED_LIMIT), str(2**63)), (real_arg(gt=0), "nan")):
    try:
        parse(text)
    except argparse.ArgumentTypeError as err:
        print(f"--flag: {err}")
print(one_line("a message\n  over two lines"))
print(f"repository root: {REPO_ROOT}")
print(f"scale={check_scale(scale)!r}; figures go to {repo_path(figures_dir)}")
print("notebooks:", ", ".join(p.name for p in figure_notebooks()))
