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
# # 09g · Appendix: reading results, statistics and figure helpers
#
# The figures of notebooks 09, 09b and 10 read finished runs and summarise them the same way.
# This appendix holds that shared reading, in the module `pemamoe.analysis`: the order and labels
# of methods, the paper's summary statistic (the interquartile mean) with rliable's bootstrap
# intervals and probability of improvement, the reference levels of the two heuristics, and the
# helpers that draw a metric over training with its phase switches. It trains nothing.

# %%
#| default_exp analysis

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## Reading results back
#
# Everything below reads the runs' **records** (appendix 09d), the compact published form of a
# finished run that git keeps under `records/<scale>/`; nothing trains unless a record is missing
# (`sweep_records` trains those runs first). `load_runs` (appendix 09d, re-exported here) stacks the
# records of a list of runs into two tidy frames, the per-iteration log and the rows in which
# episodes ended; every row carries its run's labels (`RUN_COLUMNS`: the method, the seed, the
# mechanisms switched off, the noise scale γ, a short `variant`, the display `label`), read from
# that run's own config.
#
# Which methods exist, in which order, with which label and colour, comes from the method registry
# (`pemamoe.methods`, appendix 05e): a method registered by outside code (a plugin) appears in every
# figure below without a change here.

# %%
#| export
import dataclasses
import hashlib
import json
import re
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from pemamoe.core import atomic_write_text, by_scale
from pemamoe.methods import (METHOD_REGISTRY, compared_methods, load_plugins, method_colour, method_label,
                             proposed_method)
from pemamoe.records import (  # re-export: reading records back into frames (appendix 09d)
    RECORD_EPISODE_COLUMNS, RUN_COLUMNS, load_runs, run_labels)


def method_order(names=None) -> list:
    """Method names in the figures' order: registered methods in registration order, then any
    unregistered name, sorted. names None: every method compared by default (plugins loaded)."""
    if names is None:
        load_plugins()
        return list(compared_methods())
    names = set(names)
    return [m for m in METHOD_REGISTRY if m in names] + sorted(names - set(METHOD_REGISTRY))


def is_proposed(name: str) -> bool:
    """Whether `name` is the registry's proposed method (the headline comparisons are against it)."""
    return name in METHOD_REGISTRY and METHOD_REGISTRY[name].proposed


# %% [markdown]
# ## The paper's summary statistic, and its uncertainty across seeds
#
# The paper summarises each method by the **interquartile mean** (IQM) of the per-episode values
# of a metric recorded during training: sort them, drop the lowest and highest quarter, average the
# rest. Our records keep each iteration's mean over the episodes that ended in it (a block's, in a
# long run), not every episode (those would not fit the records' budget), so our IQM is taken over
# those means: a slightly smoother quantity than the paper's, with the same centre. For the bar chart across five metrics it then min–max normalises each metric across the
# methods, and plots energy and collisions as one minus the normalised value so that taller is
# better everywhere. We follow that protocol per run, and add what a single seed cannot give: for
# several seeds, the stratified bootstrap confidence intervals of rliable (IQM across runs), and
# the probability that the proposed method improves on each baseline.

# %%
#| export
# Metric of the per-episode log -> (label, higher is better)
SUMMARY_METRICS = {
    "coverage": ("Coverage", True),
    "return": ("Return", True),
    "served_users": ("Served users", True),
    "energy_rate_kj": ("Energy use", False),
    "collisions": ("Collisions", False),
}


def iqm(values) -> float:
    """Interquartile mean: the mean of the middle 50 % of the sorted values."""
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    return float(stats.trim_mean(values, 0.25)) if values.size else float("nan")


def run_scores(episodes: pd.DataFrame, metrics=tuple(SUMMARY_METRICS)) -> pd.DataFrame:
    """One row per run: the IQM of each metric over the run's episode means (load_runs; the paper
    takes it over the episodes themselves)."""
    return episodes.groupby(list(RUN_COLUMNS))[list(metrics)].agg(iqm).reset_index()


def normalise_scores(scores: pd.DataFrame, metrics=tuple(SUMMARY_METRICS)) -> pd.DataFrame:
    """Min-max normalise each metric over all rows; lower-is-better metrics become 1 - value."""
    out = scores.copy()
    for m in metrics:
        lo, hi = scores[m].min(), scores[m].max()
        norm = (scores[m] - lo) / (hi - lo) if hi > lo else scores[m] * 0.0 + 0.5
        out[m] = norm if SUMMARY_METRICS[m][1] else 1.0 - norm
    return out


@contextmanager
def _rliable_seeded(seed: int):
    """rliable 1.2.0's stratified bootstraps draw their resampling indices from numpy's global
    generator (`np.random.choice`), not from the `random_state` they are given, so without this
    a second `make figures` printed other intervals. Seed the global generator for the call and
    put its state back afterwards. rliable hands the RandomState on to arch's bootstrap, which
    warns that the argument is deprecated: that one warning is silenced here, since rliable 1.2.0
    offers no other way to seed it."""
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="random_state is deprecated", category=FutureWarning)
            yield np.random.RandomState(seed)
    finally:
        np.random.set_state(saved)


def bootstrap_iqm(norm_scores: pd.DataFrame, methods, metrics=tuple(SUMMARY_METRICS), reps: int = 2000, seed: int = 0):
    """rliable stratified-bootstrap IQM across runs, per metric: {method: (point (M,), ci (2, M))}."""
    from rliable import library as rly
    from rliable import metrics as rmetrics

    score_dict = {m: norm_scores.loc[norm_scores.method == m, list(metrics)].to_numpy() for m in methods}

    def per_metric_iqm(s):
        return np.array([rmetrics.aggregate_iqm(s[:, [j]]) for j in range(s.shape[1])])

    with _rliable_seeded(seed) as random_state:
        point, ci = rly.get_interval_estimates(score_dict, per_metric_iqm, reps=reps, random_state=random_state)
    return {m: (point[m], ci[m]) for m in methods}


def probability_of_improvement(norm_scores: pd.DataFrame, method: str, baselines, metrics=tuple(SUMMARY_METRICS),
                               reps: int = 2000, seed: int = 0) -> pd.DataFrame:
    """P(method > baseline) over runs and metrics (rliable), with a bootstrap interval."""
    from rliable import library as rly
    from rliable import metrics as rmetrics

    mine = norm_scores.loc[norm_scores.method == method, list(metrics)].to_numpy()
    pairs = {b: [mine, norm_scores.loc[norm_scores.method == b, list(metrics)].to_numpy()] for b in baselines}
    with _rliable_seeded(seed) as random_state:
        point, ci = rly.get_interval_estimates(pairs, rmetrics.probability_of_improvement, reps=reps,
                                               random_state=random_state)

    def scalar(x):  # rliable returns length-1 arrays for a scalar statistic
        return float(np.ravel(x)[0])

    return pd.DataFrame([{"baseline": b, "P(improvement)": scalar(point[b]), "ci_low": scalar(ci[b][0]),
                          "ci_high": scalar(ci[b][1])} for b in baselines])


def relative_change(scores: pd.DataFrame, metric: str, a_mask, b_mask, reps: int = 2000, seed: int = 0):
    """(point, low, high) of 100 * (IQM_a - IQM_b) / |IQM_b| over runs, bootstrapping runs within each group."""
    a = scores.loc[a_mask, metric].to_numpy(float)
    b = scores.loc[b_mask, metric].to_numpy(float)
    rng = np.random.default_rng(seed)

    def change(x, y):
        base = iqm(y)
        return 100.0 * (iqm(x) - base) / abs(base) if base != 0 else float("nan")

    boot = [change(rng.choice(a, a.size), rng.choice(b, b.size)) for _ in range(reps)]
    low, high = np.nanpercentile(boot, [2.5, 97.5])
    return change(a, b), float(low), float(high)


def claim_verdict(ci_low: float, ci_high: float, paper_value: float) -> str:
    """A claim is reproduced when our whole interval lies on the paper's side of zero. An interval
    of zero width (one seed per group: the bootstrap has nothing to resample) decides nothing."""
    if not (np.isfinite(ci_low) and np.isfinite(ci_high)) or not np.isfinite(paper_value) or paper_value == 0:
        return "undefined (no finite estimate, or no direction to compare with)"
    if ci_low == ci_high:
        return "not resolved (no interval: one seed)"
    if ci_low > 0 and paper_value > 0 or ci_high < 0 and paper_value < 0:
        return "reproduced (same direction)"
    if ci_low > 0 or ci_high < 0:
        return "contradicted (opposite direction)"
    return "not resolved (interval contains 0)"


# %% [markdown]
# ## What no learning gives: reference levels of the heuristics
#
# A curve of served users says little until one knows what a policy that learns nothing gets. The
# environment of notebook 04 has two such policies: the **random** policy (uniform actions) and the
# **k-means heuristic** (each UAV flies to the centroid of the users it owns). `heuristic_episodes`
# runs one of them for a few episodes in one phase and summarises each episode exactly as the
# trainer's episode log does (return and collisions summed over the episode, the other metrics
# averaged over its slots, under the same names as `episodes.parquet`). `reference_levels` averages
# them per phase, renames the columns to those of the training curves (`metrics.parquet`:
# `episode_return`, `collisions_per_episode`, ...) and caches the small table as
# `results/<scale>/reference_levels.csv` (keyed by a hash of the environment and of the rollout
# budget, so a changed environment recomputes it). The figures draw each phase's level as a short
# horizontal segment over that phase's blocks of iterations.

# %%
#| export
# The heuristics drawn as reference levels: name in pemamoe.env.HEURISTICS -> (legend, line style)
REFERENCE_POLICIES = {"random": ("random policy", ":"), "kmeans": ("k-means heuristic", "-.")}
# Per-episode log column (episodes.parquet) -> training-curve column (metrics.parquet)
CURVE_COLUMNS = {"return": "episode_return", "coverage": "coverage", "served_users": "served_users",
                 "uav_using_rate": "uav_using_rate", "energy_rate_kj": "energy_rate_kj",
                 "collisions": "collisions_per_episode"}
_EPISODE_SUMS = ("return", "collisions")


def heuristic_episodes(policy: str, config, phase: int, n_envs: int, episodes: int, seed: int = 0) -> pd.DataFrame:
    """Per-episode metrics of a heuristic (pemamoe.env.HEURISTICS) in one phase of `config`'s
    environment: one row per (episode, environment), columns named as in episodes.parquet."""
    from pemamoe.env import rollout_heuristic

    T = config.env_config().episode_steps
    # The vector env restarts every env after T slots, so the log splits into whole episodes.
    logs = rollout_heuristic(policy, n_envs, episodes * T, seed=seed, phase=phase, **config.env_overrides)
    per = {k: v.reshape(episodes, T, n_envs) for k, v in logs.items()}
    per["return"] = per["reward"]
    values = {k: per[k].sum(1) if k in _EPISODE_SUMS else per[k].mean(1) for k in CURVE_COLUMNS}
    e, b = np.meshgrid(np.arange(episodes), np.arange(n_envs), indexing="ij")
    return pd.DataFrame({"policy": policy, "phase": phase, "episode": e.ravel(), "env": b.ravel(),
                         **{k: v.astype(float).ravel() for k, v in values.items()}})


def reference_levels(scale: str, results_dir="results", policies=tuple(REFERENCE_POLICIES)) -> pd.DataFrame:
    """Mean per-episode metric of each heuristic in each phase at `scale`, one row per (policy,
    phase), columns named as the training curves; cached in <results_dir>/<scale>/reference_levels.csv
    (for a results store at a URL, in its local cache: appendix 09f)."""
    from pemamoe.mappo import TrainConfig
    from pemamoe.store import open_store

    config = TrainConfig.for_scale(scale, proposed_method(), 0)
    n_envs, episodes = by_scale(scale, ci=(4, 1), small=(16, 2), paper=(32, 4))
    identity = {"env": dataclasses.asdict(config.env_config()), "n_phases": config.n_phases,
                "policies": list(policies), "n_envs": n_envs, "episodes": episodes, "version": 1}
    key = hashlib.sha256(json.dumps(identity, sort_keys=True, default=str).encode()).hexdigest()[:16]
    path = open_store(results_dir).folder / scale / "reference_levels.csv"
    if path.is_file():
        cached = pd.read_csv(path)
        if "key" in cached and (cached["key"] == key).all() and len(cached) == len(policies) * config.n_phases:
            return cached
    rows = []
    for phase in range(config.n_phases):
        for policy in policies:  # the same environment seeds for every policy: common random numbers
            eps = heuristic_episodes(policy, config, phase, n_envs, episodes, seed=7919 + phase)
            rows.append({"policy": policy, "phase": phase,
                         **{CURVE_COLUMNS[k]: float(eps[k].mean()) for k in CURVE_COLUMNS},
                         "episodes": len(eps), "key": key})
    atomic_write_text(path, pd.DataFrame(rows).to_csv(index=False))
    return pd.read_csv(path)  # what a later call reads from the cache, to the last bit


# %% [markdown]
# ## Time-series figures
#
# Every curve is the mean over seeds with a band from the lowest to the highest seed, phase
# switches are dashed vertical lines, and the figure says how many seeds and which scale it shows.
# Curves are smoothed with a short moving average (stated on the axis, in iterations: a `medium`
# record's row is a block of iterations) because per-iteration values of a few episodes are noisy. A system metric also shows the heuristics' level in each phase
# (`reference=`; dotted: random policy, dash-dot: k-means heuristic).
#
# **Routers.** Which expert is "expert 0" is an accident of each seed's initialisation, so
# averaging expert 0 over seeds mixes unrelated experts. `experts_by_usage` renames each run's
# experts by how much its router uses them (usage rank 1: the highest mean routing probability on
# the probe batch over the whole run) before anything is averaged over seeds.

# %%
#| export
def smooth(values, window: int):
    return pd.Series(values).rolling(window, min_periods=1).mean().to_numpy()


def switch_iterations(metrics: pd.DataFrame) -> list:
    one_run = metrics[metrics.run == metrics.run.iloc[0]]
    return sorted(one_run.loc[one_run.switch.astype(bool), "iteration"].tolist())


def phase_visits(metrics: pd.DataFrame) -> list:
    """[(first, last, phase)] of the phase schedule (of the first run): each visit of a phase, its
    first and last logged iteration, both inclusive."""
    one_run = metrics[metrics.run == metrics.run.iloc[0]].sort_values("iteration")
    its, phases = one_run.iteration.to_numpy(), one_run.phase.to_numpy()
    starts = [0] + [i for i in range(1, len(its)) if phases[i] != phases[i - 1]]
    lasts = [s - 1 for s in starts[1:]] + [len(its) - 1]
    return [(int(its[a]), int(its[b]), int(phases[a])) for a, b in zip(starts, lasts)]


def phase_blocks(metrics: pd.DataFrame) -> list:
    """[(start, end, phase)] for drawing: each visit from its first iteration to the next visit's
    first (so that segments join), the last one to its last iteration."""
    visits = phase_visits(metrics)
    ends = [first for first, _, _ in visits[1:]] + [visits[-1][1]]
    return [(first, end, phase) for (first, _, phase), end in zip(visits, ends)]


def plot_reference_levels(ax, metrics: pd.DataFrame, levels: pd.DataFrame, column: str) -> None:
    """Each heuristic's level of `column` in each phase, as a horizontal segment over every block
    of that phase."""
    if levels is None or column not in levels:
        return
    blocks = phase_blocks(metrics)
    for policy, (name, style) in REFERENCE_POLICIES.items():
        level = levels[levels.policy == policy].set_index("phase")[column]
        for i, (start, end, phase) in enumerate(blocks):
            if phase in level.index:
                ax.hlines(level[phase], start, end, colors="black", linestyles=style, lw=1.0,
                          label=f"{name} (per phase)" if i == 0 else None)


def plot_over_training(ax, metrics: pd.DataFrame, column: str, methods=None, window: int = 5,
                       label_fn=None, reference: pd.DataFrame | None = None):
    """Mean over seeds and min-max band of `column` against iteration, one curve per method
    (methods None: every method in `metrics`, in registry order); reference: reference_levels()."""
    for method in method_order(set(metrics.method) if methods is None else methods):
        sub = metrics[metrics.method == method]
        if sub.empty or column not in sub:
            continue
        table = sub.pivot_table(index="iteration", columns="seed", values=column)
        table = table.apply(lambda c: pd.Series(smooth(c.to_numpy(), window), index=c.index))
        mean, lo, hi = table.mean(axis=1), table.min(axis=1), table.max(axis=1)
        colour = method_colour(method)
        ax.plot(mean.index, mean.to_numpy(), color=colour, lw=1.4, label=(label_fn or method_label)(method))
        ax.fill_between(mean.index, lo.to_numpy(), hi.to_numpy(), color=colour, alpha=0.15, lw=0)
    plot_reference_levels(ax, metrics, reference, column)
    for t in switch_iterations(metrics):
        ax.axvline(t, color="0.5", ls="--", lw=0.7)
    per_row = int(metrics["iterations"].iloc[0]) if "iterations" in metrics else 1  # rows of a long run: blocks
    ax.set_xlabel(f"training iteration (curves: {window * per_row}-iteration moving average)")


def experts_by_usage(metrics: pd.DataFrame, side: str = "policy") -> pd.DataFrame:
    """Router probabilities of each run with its experts ordered by usage: usage_rank 1 is the
    expert with the highest mean probability of router/<side>/p<j> over the run (ties: lower j).
    side="rollout": the share of the rollout's rows each expert was selected for
    (rollout/expert_frac<j>, the routing that ran) instead of the probe's noiseless probabilities.
    Long frame: run, method, seed, iteration, usage_rank, expert (the run's own index), p.
    Runs with fewer than two experts (the MLP logs p0 = 1) are left out."""
    pattern = re.compile(r"rollout/expert_frac(\d+)" if side == "rollout" else rf"router/{side}/p(\d+)")
    cols = sorted((c for c in metrics.columns if pattern.fullmatch(c)), key=lambda c: int(pattern.fullmatch(c)[1]))
    out = []
    for run, sub in metrics.groupby("run", sort=True):
        probs = sub.set_index("iteration")[cols].dropna(axis=1, how="all").dropna(axis=0, how="any")
        if probs.shape[1] < 2:
            continue
        usage = probs.mean()
        order = sorted(probs.columns, key=lambda c: (-usage[c], int(pattern.fullmatch(c)[1])))
        for rank, col in enumerate(order, start=1):
            out.append(pd.DataFrame({"run": run, "method": sub.method.iloc[0], "seed": sub.seed.iloc[0],
                                     "iteration": probs.index.to_numpy(), "usage_rank": rank,
                                     "expert": int(pattern.fullmatch(col)[1]), "p": probs[col].to_numpy()}))
    columns = ["run", "method", "seed", "iteration", "usage_rank", "expert", "p"]
    return pd.concat(out, ignore_index=True) if out else pd.DataFrame(columns=columns)


def provenance(metrics: pd.DataFrame, scale: str) -> str:
    seeds = metrics.groupby("method").seed.nunique()
    n = seeds.min() if len(seeds) else 0
    return f"scale={scale}, {n} seed{'s' if n != 1 else ''} per method; band: min-max over seeds; dashed: phase switches"

# %% [markdown]
# ## A quick check
#
# The IQM drops the lowest and the highest quarter: of 1..8 it averages 3, 4, 5 and 6. A metric
# where lower is better is flipped by the normalisation, so that taller is better in every bar.

# %%
assert iqm(np.arange(1, 9)) == 4.5
_scores = pd.DataFrame({"method": ["a", "b"], "seed": [0, 0], "coverage": [0.2, 0.6],
                        "energy_rate_kj": [10.0, 30.0]})
_norm = normalise_scores(_scores, metrics=("coverage", "energy_rate_kj"))
print(_norm)
assert list(_norm.coverage) == [0.0, 1.0] and list(_norm.energy_rate_kj) == [1.0, 0.0]
assert method_order(["zzz", "mlp", "pemamoe"])[:2] == ["mlp", "pemamoe"]

# %% [markdown]
# ## Figures of notebook 09's plasticity section
#
# Helpers that notebook 09 calls (the learning curves within each phase visit, `plot_visits`, are
# appendix 09b's, beside the visit curves they draw): the paper-scale revisits against first visits
# seed by seed (`plot_seed_differences`), and the least active unit of each recorded final actor
# (`smallest_preactivation`, drawn by `plot_least_active_units`): why the paper's dormant fraction is 0.

# %%
#| export
def plot_seed_differences(revisits: pd.DataFrame):
    """Each revisit's coverage minus its phase's first visit, seed by seed: one column of panels
    per phase, the mean over the visit (top) and the level over its last 10 % (bottom); per
    method one point per seed and revisit (circles: second visit, squares: third). Returns the figure."""
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    revisits = revisits.assign(nth=revisits.groupby(["method", "seed", "phase"]).visit.rank(method="first")
                               .astype(int) + 1)
    methods_here = [m for m in method_order(revisits.method) if m in set(revisits.method)]
    phases_here = sorted(revisits.phase.unique())
    fig, axes = plt.subplots(2, len(phases_here), figsize=(4.6 * len(phases_here), 6.4), sharex=True, sharey="row",
                             squeeze=False)
    markers = {2: "o", 3: "s"}
    for row, (column, what) in enumerate((("revisit_minus_first_mean", "mean over the visit"),
                                          ("revisit_minus_first_end", "level over its last 10 %"))):
        for col, phase in enumerate(phases_here):
            ax = axes[row][col]
            ax.axhline(0, color="black", lw=0.8)
            for i, method in enumerate(methods_here):
                for nth in sorted(revisits.nth.unique()):
                    g = revisits[(revisits.method == method) & (revisits.phase == phase) & (revisits.nth == nth)]
                    offset = 0.18 * (nth - 2.5) * 2
                    ax.plot(i + offset + 0.04 * (g.seed.to_numpy() - 1), g[column], markers.get(nth, "^"),
                            color=method_colour(method), ms=5, mfc="none" if nth == 3 else method_colour(method))
            ax.set_xticks(range(len(methods_here)), [method_label(m) for m in methods_here], rotation=25, ha="right",
                          fontsize=8)
            if row == 0:
                ax.set_title(f"phase {phase}", fontsize=10)
            if col == 0:
                ax.set_ylabel(f"revisit minus first visit,\n{what}", fontsize=9)
    axes[0][0].legend([Line2D([], [], ls="none", marker=markers.get(nth, "^"), color="0.3",
                              mfc="none" if nth == 3 else "0.3") for nth in sorted(revisits.nth.unique())],
                      [f"visit {nth}" for nth in sorted(revisits.nth.unique())], fontsize=8)
    n_seeds = revisits.groupby("method").seed.nunique().min()
    fig.suptitle("Plasticity loss at the paper's scale, seed by seed: coverage of each revisit of a phase minus its first "
                 f"visit\n{n_seeds} seeds per method, one point each (below 0: the revisit learned worse)", fontsize=10)
    fig.tight_layout()
    return fig


def smallest_preactivation(marker) -> float:
    """The smallest mean |pre-activation| over the probe batch of any unit (any layer, any expert)
    of a recorded run's final actor, on the run's own probe batch: the paper's dormant-unit
    definition (appendix 06e) counts a unit below its δ."""
    from pemamoe.bookkeeping import collect_probe
    from pemamoe.records import read_marker, read_record_actor
    from pemamoe.train_config import TrainConfig

    config = TrainConfig.from_dict(read_marker(marker)["config"])
    probe = read_record_actor(marker).probe(collect_probe(config)[0])
    return min(float(layer.abs().double().mean(1).min()) for layer in probe["preact"])


def plot_least_active_units(ax, records, methods) -> float:
    """On `ax`, per method (x) one dot per run: smallest_preactivation of its final actor (log scale),
    with the paper's δ as a dashed line; returns the smallest value over the runs."""
    from pemamoe.diagnostics import DORMANT_PAPER_DELTA
    from pemamoe.records import read_marker

    smallest = pd.DataFrame([{"method": read_marker(m)["config"]["method"], "value": smallest_preactivation(m)}
                             for m in records])
    for i, method in enumerate(methods):
        vals = smallest.loc[smallest.method == method, "value"]
        ax.plot(np.full(len(vals), i), vals, "o", color=method_colour(method))
    ax.axhline(DORMANT_PAPER_DELTA, color="black", ls="--", lw=1, label=f"δ = {DORMANT_PAPER_DELTA:g}")
    ax.set_yscale("log")
    ax.set_xticks(range(len(methods)), [method_label(m) for m in methods], rotation=20, ha="right", fontsize=8)
    ax.set_ylabel("smallest mean |pre-activation|")
    ax.legend(fontsize=8, loc="center right")
    return float(smallest.value.min())
