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
# # 00 · Index: the paper, notebook by notebook
#
# `pemamoe` rebuilds *PE-MAMoE* (a plasticity-enhanced multi-agent mixture of experts for
# UAV-assisted emergency networks) as a sequence of notebooks that follow the paper's order.
# Each notebook explains one part of the method, implements it, and exports its code into the
# importable package `pemamoe/`. Nothing in `pemamoe/` is written by hand except the exporter:
# the notebooks are the source.
#
# ## Map from the paper to the code
#
# | paper | notebook | module(s) | regenerates |
# |---|---|---|---|
# | III-B channel model | `01_channel.py` | `pemamoe/channel.py` | `channel_*` figures |
# | III-C energy model | `02_energy.py` | `pemamoe/energy.py` | `energy_power_vs_speed` |
# | III-D mobility and phases | `03_mobility_phases.py` | `pemamoe/mobility.py`, `pemamoe/phases.py` | `mobility_*`, `phases_schedules` |
# | III-E objective, "environment-side heuristics" | `04_environment.py` | `pemamoe/env.py`, `pemamoe/env_kernel.py` | reward anatomy table |
# | IV-A MoE architecture, Table "Computational cost" | `05_moe_actor.py` | `pemamoe/nets.py` | `architecture_*`, `cost_table` |
# | IV-B plasticity injection, Algorithm 1 | `06_plasticity.py` | `pemamoe/phase_controller.py`, `pemamoe/diagnostics.py` | schedule figures |
# | VI-A training setup (MAPPO) | `07_mappo.py` | `pemamoe/mappo.py` | training curves |
# | V theoretical analysis | `08_theory_check.py` | `pemamoe/theory.py` | `theory_*` |
# | VI-B to VI-E results | `09_experiments.py` | `pemamoe/sweep.py` | every results figure |
# | VI-F ablations | `10_ablations.py` | | noise sweep, tricks ablation |
#
# `paper_figures/README.md` lists every regenerated file with its paper counterpart, the notebook,
# the scale, the command and the commit.
#
# ## How to run everything
#
# * `make test` builds the pinned environment in `.venv` (first run only), checks that
#   `pemamoe/` matches the notebooks, runs the unit and property tests, and executes every
#   notebook at the `ci` scale.
# * `make figures` (default `SCALE=small`) executes every notebook headlessly with papermill and
#   writes the figures and tables into `paper_figures/`. `SCALE=ci` is a smoke run in seconds;
#   `SCALE=paper` uses the paper's training budget.
# * `make lab` opens JupyterLab, where these `.py` files open as notebooks.
# * `python -m pemamoe sweep --experiment all --scale paper --backend ray --address auto` runs the
#   training behind the figures on a Ray cluster; `make figures SCALE=paper BACKEND=ray` then
#   plots from the cached runs (or trains what is missing, on Ray).
#
# This notebook also exports `pemamoe/core.py`: the few utilities every other notebook shares
# (scales, atomic file writes, figure and table saving, and the headless notebook runner).

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
# suite runs every notebook at this scale), `small` regenerates every figure with real training on
# a 2-core machine within an hour, and `paper` follows the paper's training table. A notebook picks
# its sizes with `by_scale`, so the three sizes sit next to each other in the code.

# %%
#| export
import json
import os
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

SCALES = ("ci", "small", "paper")


def check_scale(scale: str) -> str:
    """Return `scale` if it is one of SCALES, else raise a ValueError naming the allowed values."""
    if scale not in SCALES:
        raise ValueError(f"scale must be one of {', '.join(SCALES)}; got {scale!r}")
    return scale


def by_scale(scale: str, *, ci, small, paper):
    """The value for `scale`: keeps a notebook's three problem sizes side by side."""
    return {"ci": ci, "small": small, "paper": paper}[check_scale(scale)]


# %% [markdown]
# ## Writing files atomically
#
# Long runs get killed. A file that is half written when that happens must never be mistaken for
# a result, so every writer in the project writes to a temporary file in the same folder and
# renames it into place: a rename within one file system is atomic, and the reader sees either the
# old file or the new one.

# %%
#| export
@contextmanager
def atomic_path(path):
    """Yield a temporary path beside `path`; on success rename it onto `path`, else delete it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def atomic_write_text(path, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def atomic_write_json(path, obj) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n")


# %% [markdown]
# ## Saving figures and tables
#
# Figures go out as PNG (for the README and the notebooks) and PDF (for papers). Creation dates
# are left out of the files so that regenerating an unchanged figure gives identical PDF bytes
# and a clean `git diff`. Tables go out as Markdown (readable on GitHub) and CSV (for reuse).

# %%
#| export
def save_figure(fig, name: str, figures_dir, dpi: int = 150) -> list:
    """Write `fig` as `<figures_dir>/<name>.png` and `.pdf`, atomically; return the two paths."""
    out = []
    for ext, meta in (("png", {"Software": None}), ("pdf", {"CreationDate": None, "Producer": None})):
        path = Path(figures_dir) / f"{name}.{ext}"
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format=ext, dpi=dpi, bbox_inches="tight", metadata=meta)
        out.append(path)
    return out


def write_table(df, name: str, figures_dir, floatfmt: str = ".4g") -> list:
    """Write a pandas DataFrame as `<name>.md` (Markdown) and `<name>.csv`, atomically."""
    md = Path(figures_dir) / f"{name}.md"
    csv = Path(figures_dir) / f"{name}.csv"
    atomic_write_text(md, _markdown_table(df, floatfmt) + "\n")
    atomic_write_text(csv, df.to_csv(index=False))
    return [md, csv]


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
# with a per-cell timeout, and saves the executed copy under `build/executed/` (ignored by git),
# where a failing run can be opened to see the traceback in context. The test suite calls it with
# `scale="ci"`; `make figures` calls it with the chosen scale and `figures_dir="paper_figures"`.

# %%
#| export
def _find_repo_root(start: Path) -> Path:
    # Inside the package, __file__ locates the checkout; inside a running notebook there is no
    # __file__, and the kernel's working directory is either the root or notebooks/.
    for folder in (start, *start.parents):
        if (folder / "pyproject.toml").is_file() and (folder / "notebooks").is_dir():
            return folder
    return start


REPO_ROOT = _find_repo_root(Path(__file__).resolve().parent if "__file__" in globals() else Path.cwd())


def run_notebook(notebook, parameters=None, *, output_dir=None, timeout: int = 1800, cwd=None):
    """Execute `notebook` (a notebooks/*.py file) with papermill; return the executed notebook.

    parameters: dict injected after the cell tagged "parameters" (e.g. scale, figures_dir).
    output_dir: where the executed .ipynb goes (default build/executed under the repository).
    timeout:    seconds allowed per cell.
    cwd:        working directory of the kernel (default: the repository root).
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
    )


# %% [markdown]
# ## Regenerating every figure
#
# `make_figures` runs the numbered notebooks in paper order with the same runner, pointing their
# `figures_dir` at `paper_figures/`. It then writes `paper_figures/README.md`, which records for
# every file the notebook that wrote it, its counterpart in the paper, the scale, the command and
# the commit, so each figure can be traced to what produced it. Plotting notebooks read logged
# results; they never retrain what a sweep already cached.

# %%
#| export
# Paper counterpart of each output, by file stem. Stems not listed are illustrations of a model
# that the paper describes in equations only.
PAPER_COUNTERPARTS = {
    "cost_table": "Table 'Computational cost comparison (actor network)'",
    "architecture_actors": "Fig. 'PE-MAMoE architecture' (actor side, drawn by code)",
    "table_parameters": "Table 'Simulation and training parameters'",
    "results_feature_rank": "Fig. 'Evolution of the average expert feature rank'",
    "results_dormant_fraction": "Fig. 'Evolution of the total dormant neuron fraction'",
    "results_mean_return": "Fig. 'Mean return over training'",
    "results_normalised_iqm": "Fig. 'Normalized IQM across five system metrics'",
    "results_probability_of_improvement": "(ours) rliable probability of improvement, no paper counterpart",
    "results_router_policy": "Fig. 'Policy-side expert routing probability'",
    "results_router_value": "Fig. 'Value-side expert routing probability'",
    "results_collisions": "Fig. 'Collisions per episode over training'",
    "results_energy_rate": "Fig. 'Mean UAV energy rate over training'",
    "results_service": "Fig. 'Successfully served users' and 'UAV using rate'",
    "results_mean_action": "Fig. 'Mean action response to phase switches'",
    "ablation_noise_sensitivity": "Fig. 'Effect of noise injection threshold on coverage'",
    "ablation_noise_sweep": "Fig. 'Effect of noise injection threshold' (values)",
    "ablation_tricks": "Fig. 'Ablation study: IQM drop when removing each component'",
    "headline_claims": "(ours) the paper's headline numbers beside ours",
    "headline_reference_iqm": "(ours) per-metric IQM with the k-means reference row",
    "env_reward_anatomy": "(ours) reward anatomy of objective O'",
    "mappo_training_curves": "(ours) one training run per method, notebook 07",
    "plasticity_schedules": "Algorithm 1 switch-time schedules (no paper figure)",
    **{f"theory_{name}": "Section V, measured (no paper figure)" for name in
       ("noise_energy", "routing_stability", "dynamic_regret", "noise_fit", "lipschitz", "regret_fit")},
}


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
    """The numbered notebooks (NN_name.py), in paper order."""
    return sorted((Path(root or REPO_ROOT) / "notebooks").glob("[0-9][0-9]_*.py"))


def make_figures(scale: str = "small", figures_dir=None, notebooks=None, timeout: int = 3600, **extra) -> Path:
    """Execute every notebook at `scale` into `figures_dir`; write its README; return its path.

    extra: further parameters (e.g. backend="ray", workers=2), given to the notebooks that declare them.
    """
    import subprocess
    import time

    check_scale(scale)
    figures_dir = Path(figures_dir or REPO_ROOT / "paper_figures")
    figures_dir.mkdir(parents=True, exist_ok=True)
    notebooks = [Path(n) for n in (notebooks or figure_notebooks())]
    records = {}
    for nb in notebooks:
        before = {p: p.stat().st_mtime_ns for p in figures_dir.iterdir() if p.is_file()}
        start = time.perf_counter()
        print(f"[figures] {nb.name} (scale={scale}) ...", flush=True)
        declared = notebook_parameters(nb)
        params = {"scale": scale, "figures_dir": str(figures_dir), **{k: v for k, v in extra.items() if k in declared}}
        run_notebook(nb, params, timeout=timeout)
        print(f"[figures] {nb.name} done in {time.perf_counter() - start:.1f} s", flush=True)
        for p in figures_dir.iterdir():
            if p.is_file() and p.name != "README.md" and before.get(p) != p.stat().st_mtime_ns:
                records[p.name] = nb.name
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True
        ).stdout.strip() or "unknown"
        # Uncommitted changes to the code mean the commit alone does not reproduce the figure.
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "notebooks", "pemamoe"], cwd=REPO_ROOT,
                               capture_output=True, text=True).stdout.strip()
        commit += "+dirty" if dirty else ""
    except OSError:
        commit = "unknown"
    return write_figures_readme(figures_dir, records, scale=scale, commit=commit)


def write_figures_readme(figures_dir, records: dict, *, scale: str, commit: str) -> Path:
    """Merge `records` (file name -> notebook) into paper_figures/README.md's provenance table."""
    readme = Path(figures_dir) / "README.md"
    rows = _read_provenance(readme)
    command = f"make figures SCALE={scale}"  # the backend does not change results, only where they ran
    for name, nb in records.items():
        stem = name.rsplit(".", 1)[0]
        counterpart = PAPER_COUNTERPARTS.get(stem, "model illustration (no paper figure)")
        rows[name] = [name, counterpart, f"notebooks/{nb}", scale, f"`{command}`", commit]
    lines = [
        "# paper_figures",
        "",
        "Every file here is written by a notebook through `make figures`; none is drawn by hand.",
        "Columns: the file, its counterpart in the paper, the notebook that wrote it, the scale it",
        "ran at, the command, and the commit the code was at.",
        "",
        "| file | paper counterpart | notebook | scale | command | commit |",
        "|---|---|---|---|---|---|",
        *("| " + " | ".join(rows[k]) + " |" for k in sorted(rows)),
    ]
    return atomic_write_text(readme, "\n".join(lines) + "\n")


# %%
#| exporti
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


# %% [markdown]
# ## A quick look
#
# The notebooks below this one are listed with the module each exports. Running this cell in
# JupyterLab shows which notebooks exist today.

# %%
nb_dir = REPO_ROOT / "notebooks"
for path in sorted(nb_dir.glob("[0-9][0-9]_*.py")):
    print(path.name)
print(f"scale={check_scale(scale)!r}; figures go to {figures_dir!r}")
