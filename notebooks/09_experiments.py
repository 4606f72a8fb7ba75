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
# # 09 · Experiments: every comparison figure from real runs
#
# This notebook reproduces section VI of the paper: the four methods (MLP, dense MoE, sparse MoE and
# PE-MAMoE) trained with the same MAPPO pipeline on the phase-switching environment, compared on
# plasticity indicators (feature rank, dormant neurons), task performance (return, normalised IQM),
# routing, and the system metrics (collisions, energy, served users, UAV using rate, mean action).
#
# Compute and plotting are separate. The first half defines **sweeps**: a run is a point
# (method, seed, ablation, noise level, scale) whose resolved training configuration is hashed to
# name its folder under `results/`. A finished run is never trained again, and a run killed
# half-way (Ctrl-C, SIGTERM, even SIGKILL) resumes from its last checkpoint, so rerunning a sweep
# only does the missing work. The second half only *reads* the runs' records and draws; changing a
# plot never retrains.
#
# `run_sweep(specs, backend, workers, results_dir, ...)` trains every spec not yet done and returns
# the run folders in the order of the specs; `sweep_records` does the same and returns the runs'
# record markers, which is what the figures read. Pending runs whose configs differ only in the
# member fields of notebook 07 train together as one population (`train_population`), on a local
# process pool or as Ray tasks. The machinery lives in appendices, so that this notebook reads as
# the experiments and their results: appendix 09c (`pemamoe.sweep_runner`, whose names
# `pemamoe.experiments` re-exports) is the run cache (a run is done when its folder's `done.json` or its
# record verifies), the grouping into populations, the two backends, stopping and `--status`;
# appendix 09d (`pemamoe.records`) is the published record of a finished run and the reading of
# records back into tables; appendix 09e (`pemamoe.commands`) is the command line, `python -m
# pemamoe sweep`, which calls the same `run_sweep`, so a sweep started from the shell is reused here.

# %%
#| default_exp experiments

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0
seeds = None  # None: the scale's default (ci: 1, small: 3, paper: 3)
methods = None  # None: every registered method (pemamoe.methods), in registry order
backend = "local"  # "local" | "ray"
workers = 2
ray_address = None
results_dir = "results"
records_dir = "records"  # the published records (appendix 09d); runs without one are trained
retrain = False  # True: ignore the records, train into results_dir and write the records again

# %%
#| export
from pemamoe.core import (  # re-export: the experiments' names live in core, for the command line (00b)
    ACTOR_READINGS, EXPERIMENTS, READABLE_EXPERIMENTS)
import dataclasses as _dc

from pemamoe.core import by_scale, check_scale
from pemamoe.sweep_runner import (  # re-export: a run's spec, the run cache and the backends (appendix 09c)
    BACKENDS, DEFAULT_POPULATION, RunSpec, SweepInterrupted, check_counts, execute_population, group_specs,
    pending_runs, record_marker, run_sweep, sweep_records)
from pemamoe.mappo import METHODS, TrainConfig
from pemamoe.methods import method_spec

# %% [markdown]
# ## A run, and its place in the cache
#
# `RunSpec(method, seed, scale, without=(), noise_gamma=None, overrides=())` names a run the way an
# experiment table would: the method, the seed, the scale, which phase-controller mechanisms are
# switched off (an ablation), the noise level γ, and any further training overrides. `to_config`
# resolves it to the full `TrainConfig`; the cache key is the hash of that resolved configuration,
# so two specs that mean the same run share one folder, and any change to a default (a new preset,
# say) gives new folders instead of silently reusing stale ones. The class is in appendix 09c.

# %% [markdown]
# ## The paper's experiments as sweeps
#
# * **main**: the four methods, each with every seed;
# * **campaign**: main, with MLP + ReDo and MLP + shrink-and-perturb at the paper scale
#   (`campaign_methods`), which `make figures SCALE=paper` draws (09e); **campaign_v2**: campaign under
#   the readings appendix 10b chooses (`CAMPAIGN_V2_READINGS`), five seeds at the paper scale;
# * **noise**: PE-MAMoE at γ ∈ {0.001, 0.005, 0.01} and MoE at the same γ (see notebook 10 for how
#   noise enters MoE);
# * **tricks**: PE-MAMoE with one mechanism removed at a time: entropy reset/annealing, log-std
#   reset, learning-rate drop and warm-up, noise injection.
#
# `default_seeds` gives the scale's number of seeds. The paper trained one seed per method; we use
# three at every scale but `ci` and report the number on every figure.

# %%
#| export
NOISE_GAMMAS = (0.001, 0.005, 0.01)
TRICKS = {
    "entropy annealing": "entropy_reset",
    "log-std reset": "log_std_reset",
    "LR annealing": "lr_drop",
    "noise injection": "noise_injection",
}


def default_seeds(scale: str) -> tuple:
    return tuple(range(by_scale(scale, ci=1, small=3, paper=3)))


def main_specs(scale: str, seeds=None, methods=METHODS) -> list:
    seeds = default_seeds(scale) if seeds is None else tuple(seeds)
    return [RunSpec(m, s, scale, tag="main") for m in methods for s in seeds]


CAMPAIGN_BASELINES = ("mlp_redo", "mlp_snp")  # what the paper scale adds to the main comparison
CAMPAIGN_V2_READINGS = {"controller.log_std_value": 0.3, "target_kl_check": "epoch"}  # v2's --set (10b: why)


def campaign_methods(scale: str, methods=METHODS) -> tuple:
    """`methods`, and at the paper scale, the only one with the updates per phase in which plasticity
    loss could appear, the two plasticity baselines on MLP (appendix 06c) too."""
    return tuple(methods) + tuple(m for m in CAMPAIGN_BASELINES if scale == "paper" and m not in methods)



def trick_specs(scale: str, seeds=None) -> list:
    seeds = default_seeds(scale) if seeds is None else tuple(seeds)
    return [RunSpec("pemamoe", s, scale, without=(mech,), tag="tricks") for mech in TRICKS.values() for s in seeds]


def noise_specs(scale: str, seeds=None, gammas=NOISE_GAMMAS) -> list:
    """PE-MAMoE at each gamma, and MoE with expert-noise injection alone (every other mechanism off)."""
    from pemamoe.phase_controller import MECHANISMS

    seeds = default_seeds(scale) if seeds is None else tuple(seeds)
    noise_only = tuple(m for m in MECHANISMS if m != "noise_injection")
    return [RunSpec("pemamoe", s, scale, noise_gamma=g, tag="noise") for g in gammas for s in seeds] + [
        RunSpec("moe", s, scale, noise_gamma=g, without=noise_only, overrides=(("force_controller", True),),
                tag="noise") for g in gammas for s in seeds]


# The learning-budget study (notebook 09b): each method in each single, fixed phase for BUDGET_STEPS
# environment steps, with the small preset's update settings, and MLP in phase 0 with the paper's
# update settings to compare the two per second of compute. One study serves every scale (its runs
# live under results/small/); at the ci scale it is a few iterations, so CI executes the notebook.
BUDGET_STEPS = 2_000_000
BUDGET_UPDATES = {  # name -> TrainConfig overrides of the update settings
    "small": {},  # the small preset: 16 envs x 32 slots, 4 epochs x 4 minibatches
    "paper": {"num_envs": 64, "rollout_steps": 32, "update_epochs": 8, "num_minibatches": 32},
}
# The sparse actor's two readings (appendix 05d): ours, which the committed study ran (a
# load-balance loss, one mean head shared by the experts, PPO's ratio on replayed routes), and the
# paper's (no balance loss, a mean head per expert, the ratio on the routes the current parameters
# choose). The gated methods run the study under both; MLP has no router, so it runs once.
_OURS = {"load_balance_coef": 0.01, "expert_heads": "shared", "update_routing": "replay", "top_k": 1}
_PAPERS = {"load_balance_coef": 0.0, "expert_heads": "per_expert", "update_routing": "current", "top_k": 1}
BUDGET_READINGS = dict(zip(ACTOR_READINGS, (_OURS, _PAPERS)))  # name -> NetConfig overrides of the gated methods


def fixed_phase_twin(method: str, methods) -> str | None:
    """The method of `methods` whose fixed-phase runs `method`'s are, bit for bit, or None. The phase
    controller acts only at a phase switch, which a fixed phase never has, so a network plus the
    controller (PE-MAMoE) trains there exactly as the network alone (SMoE): the committed study's
    records agree to the byte, and a test checks it. Fixed-phase experiments run such a method once."""
    spec = method_spec(method)
    if spec.plasticity != "phase_controller":
        return None
    return next((m for m in methods if m != method and method_spec(m).network == spec.network
                 and method_spec(m).plasticity == "none"), None)


def net_reading(net) -> str | None:
    """The name of the reading of BUDGET_READINGS whose fields the NetConfig `net` has, or None."""
    return next((name for name, fields in BUDGET_READINGS.items()
                 if all(getattr(net, key) == value for key, value in fields.items())), None)


def default_reading() -> str:
    """The name of the actor reading the NetConfig defaults are: the one every gated run without
    net overrides (the medium sweep's) trains, so the study that serves as their yardstick."""
    name = net_reading(TrainConfig().net)
    if name is None:
        raise ValueError(f"the NetConfig defaults match none of the study's readings ({', '.join(BUDGET_READINGS)}): "
                         f"{TrainConfig().net}")
    return name


def study_steps(study: str, steps, scale: str, default: int) -> int:
    """A fixed-phase study's environment steps: `steps` (an integer >= 1), else `default` (a few iterations at ci)."""
    steps = (64 * 4 if scale == "ci" else default) if steps is None else steps
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"{study}: steps must be an integer >= 1, got {steps!r}")
    return steps


def fixed_run(iterations: int) -> dict:
    """A fixed-phase study run's length overrides: logged every 1/20 of it, checkpointed every 100 iterations."""
    return {"iterations": iterations, "phase_length_iters": iterations,
            "diag_every": max(1, min(100, iterations // 20)), "checkpoint_every": max(1, min(100, iterations))}


def check_readings(study: str, names, known) -> None:
    for name in (n for n in names if n not in known):
        raise ValueError(f"{study} reading must be one of {', '.join(known)}, got {name!r}")


def budget_specs(scale: str, seeds=None, methods=METHODS, phases=(0, 1, 2), steps: int | None = None,
                 readings=tuple(BUDGET_READINGS)) -> list:
    """The study's runs: every method x phase x seed with the small update settings (the gated
    methods once per actor reading, tagged "budget/small/<reading>" except ours, "budget/small";
    a method with a fixed-phase twin only under ours), then MLP in phase 0 with the paper's
    update settings."""
    check_scale(scale)
    check_readings("budget", readings, BUDGET_READINGS)
    preset = "ci" if scale == "ci" else "small"
    seeds = tuple(range(by_scale(scale, ci=1, small=3, paper=3))) if seeds is None else tuple(seeds)
    steps = study_steps("budget_specs", steps, scale, BUDGET_STEPS)

    base = TrainConfig.for_scale(preset)

    def spec(method, seed, phase, update, reading=None):
        extra = dict(BUDGET_UPDATES[update])
        batch = extra.get("num_envs", base.num_envs) * extra.get("rollout_steps", base.rollout_steps)
        extra.update(fixed_phase=phase, **fixed_run(-(-steps // batch)))
        extra.update(BUDGET_READINGS.get(reading, {}))
        tag = f"budget/{update}" if reading in (None, "ours") else f"budget/{update}/{reading}"
        return RunSpec(method, seed, preset, overrides=tuple(extra.items()), tag=tag)

    def arms(method):  # MLP has no router: one run, whatever the readings
        if method_spec(method).network == "mlp":
            return (None,)
        if fixed_phase_twin(method, methods) is not None:  # its runs are the twin's; the committed ones stay
            return tuple(r for r in readings if r == "ours")
        return readings

    specs = [spec(m, s, p, "small", r) for m in methods for r in arms(m) for p in phases for s in seeds]
    if "mlp" in methods:
        specs += [spec("mlp", s, 0, "paper") for s in seeds]
    return specs


# The gating comparison (notebook 05c): readings of top-1 gating the paper leaves open, each in
# fixed phases 0 and 1 for GATING_STEPS environment steps with the small update settings, beside
# MLP. Every reading names every gating field (noise_std and noise_anneal_portion from GATING_NOISE
# unless it sets them), so a later change of the NetConfig defaults leaves these runs' identities alone.
GATING_STEPS = 700_000
GATING_READINGS = {  # name -> (method, NetConfig overrides)
    "mlp": ("mlp", {"top1_weight": "straight_through", "routing_noise": "off", "noise_std": 1.0,  # inert for MLP;
                    "noise_anneal_portion": 1.0, "critic_gating": "dense"}),  # pinned, so its identity stays
    "st/learned/gated": ("smoe", {"top1_weight": "straight_through", "routing_noise": "learned", "critic_gating": "gated"}),
    "st/off/gated": ("smoe", {"top1_weight": "straight_through", "routing_noise": "off", "critic_gating": "gated"}),
    "st/annealed/gated": ("smoe", {"top1_weight": "straight_through", "routing_noise": "annealed", "critic_gating": "gated"}),
    "switch/learned/gated": ("smoe", {"top1_weight": "switch", "routing_noise": "learned", "critic_gating": "gated"}),
    "st/learned/dense": ("smoe", {"top1_weight": "straight_through", "routing_noise": "learned", "critic_gating": "dense"}),
    "st/off/dense": ("smoe", {"top1_weight": "straight_through", "routing_noise": "off", "critic_gating": "dense"}),
    "switch/off/dense": ("smoe", {"top1_weight": "switch", "routing_noise": "off", "critic_gating": "dense"}),
    "switch/annealed/dense": ("smoe", {"top1_weight": "switch", "routing_noise": "annealed", "critic_gating": "dense"}),
    "paper/off/dense": ("smoe", {"top1_weight": "paper", "routing_noise": "off", "critic_gating": "dense"}),
    # bounded noise that stays: the one reading under which the controller's temperature still moves routing
    "st/fixed0.3/dense": ("smoe", {"top1_weight": "straight_through", "routing_noise": "fixed", "noise_std": 0.3,
                                   "critic_gating": "dense"}),
    "st/fixed1/dense": ("smoe", {"top1_weight": "straight_through", "routing_noise": "fixed", "noise_std": 1.0,
                                 "critic_gating": "dense"}),
}
GATING_NOISE = {"noise_std": 1.0, "noise_anneal_portion": 0.5}  # sigma of "annealed": 1 -> 0 over half the run


def gating_specs(scale: str, seeds=None, readings=None, phases=(0, 1), steps: int | None = None) -> list:
    """The gating comparison's runs: every reading x phase x seed, fixed phase, small update
    settings (a few iterations at ci). Each spec's tag is "gating/<reading>"."""
    check_scale(scale)
    preset = "ci" if scale == "ci" else "small"
    seeds = tuple(range(by_scale(scale, ci=1, small=2, paper=2))) if seeds is None else tuple(seeds)
    readings = tuple(GATING_READINGS) if readings is None else tuple(readings)
    check_readings("gating", readings, GATING_READINGS)
    steps = study_steps("gating_specs", steps, scale, GATING_STEPS)
    iterations = -(-steps // TrainConfig.for_scale(preset).batch_env_steps)
    specs = []
    for name in readings:
        method, net = GATING_READINGS[name]
        gated = {**GATING_NOISE, **_OURS} if method != "mlp" else {}  # the sparse actor it ran: ours (05d), pinned
        extra = {**gated, **net, **fixed_run(iterations)}
        specs += [RunSpec(method, seed, preset, overrides=tuple({**extra, "fixed_phase": phase}.items()),
                          tag=f"gating/{name}") for phase in phases for seed in seeds]
    return specs


# The sparse-actor comparison (appendix 05d): why top-1 SMoE plateaus below MLP and MoE on a fixed
# phase. Each reading changes one part of the sparse actor (or all the paper's at once), in fixed
# phase 0 for SPARSE_STEPS environment steps with the small update settings, 2 seeds. Every reading
# names every field it is about, so a later change of a NetConfig default leaves its identity alone.
SPARSE_STEPS = 1_500_000
SPARSE_READINGS = {  # name -> (method, NetConfig overrides)
    "mlp": ("mlp", {}),
    "moe": ("moe", dict(_OURS)),
    "moe/paper": ("moe", {**_PAPERS}),
    "smoe": ("smoe", dict(_OURS)),  # the sparse actor the committed study ran
    "smoe/1 expert": ("smoe", {**_OURS, "n_experts": 1}),  # routing removed: the sanity check
    "smoe/no balance": ("smoe", {**_OURS, "load_balance_coef": 0.0}),
    "smoe/expert heads": ("smoe", {**_OURS, "expert_heads": "per_expert"}),
    "smoe/re-routed ratio": ("smoe", {**_OURS, "update_routing": "current"}),
    "smoe/paper": ("smoe", dict(_PAPERS)),  # all three of the paper's readings
    "smoe/paper top-2": ("smoe", {**_PAPERS, "top_k": 2}),
}


def sparse_specs(scale: str, seeds=None, readings=None, phase: int = 0, steps: int | None = None) -> list:
    """The sparse-actor comparison's runs: every reading x seed in one fixed phase, small update
    settings (a few iterations at ci). Each spec's tag is "sparse/<reading>"."""
    check_scale(scale)
    preset = "ci" if scale == "ci" else "small"
    seeds = tuple(range(by_scale(scale, ci=1, small=2, paper=2))) if seeds is None else tuple(seeds)
    readings = tuple(SPARSE_READINGS) if readings is None else tuple(readings)
    check_readings("sparse", readings, SPARSE_READINGS)
    steps = study_steps("sparse_specs", steps, scale, SPARSE_STEPS)
    extra = {"fixed_phase": phase, **fixed_run(-(-steps // TrainConfig.for_scale(preset).batch_env_steps))}
    return [RunSpec(method, seed, preset, overrides=tuple({**extra, **net}.items()), tag=f"sparse/{name}")
            for name in readings for method, net in [SPARSE_READINGS[name]] for seed in seeds]


# The tuning grid (its table in appendix 09b): every compared method tuned alike, on the
# learning-budget study's run (fixed phase 0, BUDGET_STEPS environment steps, small update
# settings), over one grid of learning rate x entropy coefficient (the start and end of its
# anneal, scaled together), 2 seeds. The gated methods run the paper's actor readings (appendix
# 05d), the ones the experiments are to use. The grid's centre is the study's own setting, so those
# runs are the study's (the same configuration, the same run).
TUNING_LRS = (1e-4, 3e-4, 1e-3)
TUNING_ENTROPY = ((0.005, 0.0015), (0.01, 0.003), (0.02, 0.006))  # (ent_start, ent_end): x0.5, x1, x2


def tuning_specs(scale: str, seeds=None, methods=METHODS, lrs=TUNING_LRS, entropy=TUNING_ENTROPY,
                 phase: int = 0, steps: int | None = None) -> list:
    """The tuning grid's runs: method x learning rate x entropy x seed, each spec tagged
    "tuning/lr=<lr>/ent=<ent_start>" (a few iterations at ci)."""
    check_scale(scale)
    preset = "ci" if scale == "ci" else "small"
    seeds = tuple(range(by_scale(scale, ci=1, small=2, paper=2))) if seeds is None else tuple(seeds)
    steps = study_steps("tuning_specs", steps, scale, BUDGET_STEPS)
    for lr in lrs:
        if not isinstance(lr, float) or lr <= 0:
            raise ValueError(f"tuning_specs: every learning rate must be a float > 0, got {lr!r}")
    for pair in entropy:
        if len(pair) != 2 or min(pair) < 0:
            raise ValueError(f"tuning_specs: entropy settings are (ent_start, ent_end) pairs >= 0, got {pair!r}")
    extra = {"fixed_phase": phase, **fixed_run(-(-steps // TrainConfig.for_scale(preset).batch_env_steps))}
    specs = []
    for method in (m for m in methods if fixed_phase_twin(m, methods) is None):  # PE-MAMoE takes SMoE's
        net = {} if method_spec(method).network == "mlp" else _PAPERS
        for lr in lrs:
            for ent_start, ent_end in entropy:
                grid = {"lr": lr, "ent_start": ent_start, "ent_end": ent_end}
                specs += [RunSpec(method, seed, preset, overrides=tuple({**extra, **net, **grid}.items()),
                                  tag=f"tuning/lr={lr:g}/ent={ent_start:g}") for seed in seeds]
    return specs


# The top-2 arm (appendix 05d): the sparse methods with two of the three experts active per step, in
# the main experiment's cycling runs, beside their top-1 runs. Their actor reading is the paper's
# (appendix 05d), pinned, with top_k = 2; the study measured top-2 in a fixed phase ("smoe/paper
# top-2" of the sparse-actor comparison), this arm asks what it does across phase switches.
TOP2_METHODS = ("smoe", "pemamoe")


def top2_specs(scale: str, seeds=None) -> list:
    """The top-2 arm's runs: each of TOP2_METHODS x seed at `scale`, tagged "top2"."""
    seeds = default_seeds(scale) if seeds is None else tuple(seeds)
    net = {**_PAPERS, "top_k": 2}
    return [RunSpec(m, s, scale, overrides=tuple(net.items()), tag="top2") for m in TOP2_METHODS for s in seeds]


# The sparse actor's reading of the cycling experiments, pinned (appendix 05d): `reading="paper"` runs
# main, tricks and noise with the gated methods' actor as the paper describes it, whatever
# NetConfig's defaults are, and `reading="ours"` with ours. Pinning a field at its default value
# leaves the run's configuration, hence its name, unchanged, so runs trained pinned are the very
# runs the unpinned experiment asks for once the defaults are that reading. The other experiments
# fix their readings themselves (the names: ACTOR_READINGS and READABLE_EXPERIMENTS, in core).

def with_reading(specs, reading: str) -> list:
    """`specs` with the gated methods' sparse-actor reading pinned ("ours" or "paper", BUDGET_READINGS);
    MLP runs (no router) unchanged."""
    if reading not in BUDGET_READINGS:
        raise ValueError(f"reading must be one of {', '.join(BUDGET_READINGS)}, got {reading!r}")
    net = BUDGET_READINGS[reading]
    return [spec if method_spec(spec.method).network == "mlp"
            else _dc.replace(spec, overrides=tuple({**dict(spec.overrides), **net}.items())) for spec in specs]


def experiment_specs(experiment: str, scale: str, seeds=None, methods=METHODS, reading: str | None = None) -> list:
    """The runs of one experiment ("main", "tricks", "noise"), of "all" three (the paper's 39-run
    sweep), of the paper-scale campaign ("campaign": main with `campaign_methods`; "campaign_v2": it
    under CAMPAIGN_V2_READINGS), the learning-budget study ("budget"), the gating and sparse-actor
    comparisons ("gating", "sparse"), the tuning grid ("tuning") or the top-2 arm ("top2"); only the
    first three are part of "all". reading: None (NetConfig's defaults), "ours" or "paper", the gated
    methods' actor pinned (`with_reading`; READABLE_EXPERIMENTS only)."""
    if reading is not None:
        if experiment not in READABLE_EXPERIMENTS:
            raise ValueError(f"reading applies to the experiments {', '.join(READABLE_EXPERIMENTS)}; "
                             f"{experiment!r} fixes its own actor readings")
        return with_reading(experiment_specs(experiment, scale, seeds, methods), reading)
    makers = {"main": lambda: main_specs(scale, seeds, methods), "tricks": lambda: trick_specs(scale, seeds),
              "noise": lambda: noise_specs(scale, seeds)}
    if experiment == "all":
        return [s for make in makers.values() for s in make()]
    if experiment == "campaign":
        return main_specs(scale, seeds, campaign_methods(scale, methods))
    if experiment == "campaign_v2":  # five seeds at the paper scale
        seeds = tuple(range(by_scale(scale, ci=1, small=3, paper=5))) if seeds is None else seeds
        return [s.with_overrides(CAMPAIGN_V2_READINGS) for s in main_specs(scale, seeds, campaign_methods(scale, methods))]
    if experiment == "budget":
        return budget_specs(scale, seeds, methods)
    if experiment == "gating":
        return gating_specs(scale, seeds)
    if experiment == "sparse":
        return sparse_specs(scale, seeds)
    if experiment == "tuning":
        return tuning_specs(scale, seeds, methods)
    if experiment == "top2":
        return top2_specs(scale, seeds)
    if experiment not in makers:
        raise ValueError(f"experiment must be one of {', '.join(EXPERIMENTS)}, got {experiment!r}")
    return makers[experiment]()


# %% [markdown]
# ## Reading results back
#
# Everything below reads the runs' **records** (appendix 09d), the compact published form of a
# finished run that git keeps under `records/<scale>/`; nothing trains unless a record is missing
# (`sweep_records` trains those runs first). The statistics and plotting helpers the figures use
# (the IQM and its bootstrap intervals, the heuristics' reference levels, the curves over
# training, the routers' experts ordered by use) are appendix 09g's, `pemamoe.analysis`.

# %% [markdown]
# ## Run (or reuse) the main comparison
#
# At the `ci` scale this trains a few iterations per method in seconds; at `small` and `medium`
# (the default of `make figures`) the runs are read from their committed records; finished runs
# under `results/` are reused, never retrained. The parameter `methods = None` means every registered method.

# %%
import dataclasses as _dc

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from pemamoe.analysis import (REFERENCE_POLICIES, SUMMARY_METRICS, bootstrap_iqm, experts_by_usage, is_proposed,
                              load_runs, method_order, normalise_scores, plot_over_training,
                              probability_of_improvement, provenance, reference_levels, run_scores,
                              switch_iterations)
from pemamoe.core import save_figure, write_table
from pemamoe.methods import method_colour, method_label, proposed_method
# Worker processes import what they run by module path, so the sweep must use the package's copies
# of these definitions, not the ones this notebook's cells just created in __main__.
from pemamoe.experiments import campaign_methods, default_seeds, main_specs, sweep_records

# at the paper scale the campaign's plasticity baselines join the comparison
method_list = list(campaign_methods(scale, method_order())) if methods is None else method_order(tuple(methods))
seed_list = default_seeds(scale) if seeds is None else tuple(seeds)
records = sweep_records(main_specs(scale, seed_list, method_list), backend, workers, results_dir, ray_address,
                        records_dir, retrain)
metrics, episodes = load_runs(records)
levels = reference_levels(scale, results_dir)
note = provenance(metrics, scale)
STYLE_NAMES = {":": "dotted", "-.": "dash-dot", "--": "dashed", "-": "solid"}
reference_note = "; ".join(f"{STYLE_NAMES.get(style, style)}: {name}" for name, style in REFERENCE_POLICIES.values())
print(note, "|", len(episodes), "training episodes")
levels.drop(columns="key")


def figure(column, ylabel, name, title, methods_shown=method_list, reference=None):
    fig, ax = plt.subplots(figsize=(8, 3.6))
    plot_over_training(ax, metrics, column, methods_shown, reference=reference)
    ax.set_ylabel(ylabel)
    extra = f"\nblack lines: each phase's level without learning ({reference_note})" if reference is not None else ""
    ax.set_title(f"{title}\n{note}{extra}", fontsize=9)
    # beside the axes: inside, it hid the highest reference levels (k-means in phase 2)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    save_figure(fig, name, figures_dir)
    plt.show()


# %% [markdown]
# ## Plasticity indicators
#
# Feature rank on a fixed probe batch (the MLP: its trunk), mean over experts (appendix 06e): the
# **stable rank** (the paper's footnote) and the **effective rank** (what our tables quote). Dormant
# fraction, mean over layers and experts: the **paper's** (mean |pre-activation| < δ = 0.01) and
# **Sokar et al.'s τ-dormant score** (post-activation score ≤ τ = 0.025).
#
# The paper's fraction is 0 at every logged point of every run, a measurement: a unit counts only
# if its weights and bias have nearly vanished (a ReLU silenced by negative inputs is τ-dormant
# instead). The left panel shows why: each final actor's least active unit, against δ.

# %%
from pemamoe.analysis import plot_least_active_units
from pemamoe.diagnostics import DORMANT_PAPER_DELTA, DORMANT_TAU

fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), layout="constrained")
for ax, (column, label) in zip(axes, (("rank/stable/mean", "stable rank"), ("rank/effective/mean", "effective rank"))):
    plot_over_training(ax, metrics, column, method_list)
    ax.set_title(f"{label} of the expert features (mean over experts)", fontsize=9)
    ax.set_ylabel(label)
axes[1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)  # beside: curves fill it
fig.suptitle(f"Average expert feature rank (left: stable rank, the paper's; right: effective, our tables')\n{note}", fontsize=9)
save_figure(fig, "results_feature_rank", figures_dir)
plt.show()

paper_dnf = metrics["dormant/paper/mean"].dropna()
fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), layout="constrained")
if len(paper_dnf) and (paper_dnf == 0).all():
    least = plot_least_active_units(axes[0], records, method_list)  # appendix 09g
    axes[0].set_title(f"paper's definition (mean |pre-activation| < {DORMANT_PAPER_DELTA:g}): 0 at all {len(paper_dnf)} "
                      f"logged points;\nwhy: each final actor's least active unit (dots: runs; lowest {least:.3f})", fontsize=9)
else:  # some unit fell below δ somewhere: draw the fraction over training
    plot_over_training(axes[0], metrics, "dormant/paper/mean", method_list)
    axes[0].set_title(f"paper's definition: mean |pre-activation| < {DORMANT_PAPER_DELTA:g}", fontsize=9)
    axes[0].set_ylabel("dormant fraction")
plot_over_training(axes[1], metrics, "dormant/tau/mean", method_list)
axes[1].set_title(f"Sokar et al. tau-dormant: post-activation score <= {DORMANT_TAU:g}", fontsize=9)
axes[1].set_ylabel("dormant fraction")
axes[1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)  # beside: bands fill it
fig.suptitle(f"Dormant neurons, two definitions (left: the paper's, right: tau-dormant over training)\n{note}", fontsize=9)
save_figure(fig, "results_dormant_fraction", figures_dir)
plt.show()

# %% [markdown]
# ![Average expert feature rank over training, medium scale](../paper_figures/results_feature_rank.png)
#
# ![Dormant neurons under two definitions, medium scale](../paper_figures/results_dormant_fraction.png)
#
# ![Average expert feature rank over training, paper scale](../paper_figures/paper_scale/results_feature_rank.png)
#
# ![Dormant neurons under two definitions, paper scale](../paper_figures/paper_scale/results_dormant_fraction.png)

# %% [markdown]
# ## Task performance
#
# Return and coverage over training, each phase's level without learning drawn in black; then the
# normalised IQM of five system metrics with 95 % stratified-bootstrap intervals across seeds, and
# the probability that the proposed method beats each baseline. The sentences under the IQM table
# are computed from it.

# %%
figure("episode_return", "mean episode return", "results_mean_return", "Mean return over training", reference=levels)
figure("coverage", "coverage (fraction of users served)", "results_coverage", "Coverage over training", reference=levels)

# %% [markdown]
# ![Mean return over training, medium scale](../paper_figures/results_mean_return.png)
#
# ![Coverage over training, medium scale](../paper_figures/results_coverage.png)
#
# ![Coverage over training, paper scale: every learner below the k-means level in every phase](../paper_figures/paper_scale/results_coverage.png)

# %%
scores = run_scores(episodes)
norm = normalise_scores(scores)
present = [m for m in method_list if m in set(norm.method)]
boot = bootstrap_iqm(norm, present)
fig, ax = plt.subplots(figsize=(8, 3.8))
width = 0.8 / len(boot)
x = np.arange(len(SUMMARY_METRICS))
rows = []
for i, (method, (point, ci)) in enumerate(boot.items()):
    err = np.vstack([point - ci[0], ci[1] - point])
    ax.bar(x + i * width, point, width, yerr=err, capsize=3, color=method_colour(method), label=method_label(method))
    for j, metric in enumerate(SUMMARY_METRICS):
        rows.append({"method": method, "metric": SUMMARY_METRICS[metric][0], "normalised IQM": point[j],
                     "ci_low": ci[0][j], "ci_high": ci[1][j]})
ax.set_xticks(x + width * (len(boot) - 1) / 2, [v[0] for v in SUMMARY_METRICS.values()])
ax.set_ylabel("normalised IQM (higher is better)")
n_seed = int(scores.groupby("method").seed.nunique().min())
ax.set_title("Normalised IQM across five system metrics (energy, collisions: 1 - normalised)\n"
             f"scale={scale}, {n_seed} seeds per method; error bars: 95 % stratified-bootstrap CI across seeds",
             fontsize=9)
# beside the axes: inside, it covered the bars that reach 1 (with six methods, at the paper scale)
ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
save_figure(fig, "results_normalised_iqm", figures_dir)
plt.show()
iqm_table = pd.DataFrame(rows)
write_table(iqm_table.round(3), "results_normalised_iqm", figures_dir)
raw = scores.groupby("method")[list(SUMMARY_METRICS)].mean().reindex(present)
print("per-episode IQM of each metric, mean over seeds (raw units):")
raw.round(3)

# %%
def _iqm_words(table: pd.DataFrame) -> str:
    """Per metric: the leader and which methods' intervals reach its lower bound (computed, not typed)."""
    lines = []
    for metric, g in table.groupby("metric", sort=False):
        best = g.loc[g["normalised IQM"].idxmax()]
        close = [method_label(m) for m, hi in zip(g.method, g.ci_high) if m != best.method and hi >= best.ci_low]
        lines.append(f"* {metric}: {method_label(best.method)} leads ({best['normalised IQM']:.2f}, interval "
                     f"{best.ci_low:.2f} to {best.ci_high:.2f}); "
                     + (f"within reach of it: {', '.join(close)}." if close else "no other interval reaches it."))
    return "\n".join(lines)


from IPython.display import Markdown  # noqa: E402

Markdown(_iqm_words(iqm_table))

# %% [markdown]
# ![Normalised IQM across five system metrics, medium scale](../paper_figures/results_normalised_iqm.png)
#
# ![Normalised IQM across five system metrics, paper scale](../paper_figures/paper_scale/results_normalised_iqm.png)

# %%
proposed = proposed_method()
baselines = [m for m in present if not is_proposed(m)]
if proposed in present and baselines:
    poi = probability_of_improvement(norm, proposed, baselines)
    write_table(poi.round(3), "results_probability_of_improvement", figures_dir)
    print(poi.round(3))

# %% [markdown]
# ## Where the routers send their inputs
#
# Mean routing probability of each expert on the probe batch, for the policy router and the value
# router of every method with more than one expert. Each seed's experts are first ordered by usage
# (usage rank 1 = the expert its router uses most over the whole run); the curves are the mean over
# seeds of the expert of each usage rank, so they show how unequal the routing is and how it moves
# at the switches, not the fate of any particular expert.

# %%
for side in ("policy", "value"):
    ranked = experts_by_usage(metrics, side)
    routed = [m for m in method_list if m in set(ranked.method)]
    if not routed:
        continue
    fig, axes = plt.subplots(1, len(routed), figsize=(4 * len(routed), 3.6), sharey=True, squeeze=False,
                             layout="constrained")
    for ax, method in zip(axes[0], routed):
        sub = ranked[ranked.method == method]
        for rank in sorted(sub.usage_rank.unique()):
            table = sub[sub.usage_rank == rank].pivot_table(index="iteration", columns="seed", values="p")
            ax.plot(table.index, table.mean(axis=1), label=f"usage rank {rank}")
            ax.fill_between(table.index, table.min(axis=1), table.max(axis=1), alpha=0.15, lw=0)
        one = metrics[metrics.method == method]
        for t in sorted(one.loc[one.switch.astype(bool), "iteration"].unique()):
            ax.axvline(t, color="0.5", ls="--", lw=0.7)
        ax.set_title(method_label(method))
        ax.set_xlabel("training iteration")
    axes[0, 0].set_ylabel(f"{side}-router probability")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"{side.capitalize()}-side expert routing probability\neach seed's experts ordered by their mean "
                 f"routing probability over the run (rank 1 = most used) before averaging over seeds\n{note}",
                 fontsize=9)
    save_figure(fig, f"results_router_{side}", figures_dir)
    plt.show()

# %% [markdown]
# ![Policy-side expert routing probability, medium scale](../paper_figures/results_router_policy.png)
#
# ![Value-side expert routing probability, medium scale](../paper_figures/results_router_value.png)

# %% [markdown]
# ## The routing that ran
#
# The router figures above show the noiseless preference of each router on a fixed probe batch.
# Under noisy gating that is not the routing that generated the data. Here, for each top-1 routed
# method: the share of the rollout's agent steps that each expert was selected for (experts
# ordered by usage, as above), and the switch rate: the share of an agent's consecutive steps
# within an episode on which its selected expert changed (2/3 would be random routing over three
# experts; notebook 05c).

# %%
ranked = experts_by_usage(metrics, "rollout")
routed = [m for m in method_list if m in set(ranked.method)]
if routed:
    fig, axes = plt.subplots(2, len(routed), figsize=(4 * len(routed), 5.6), sharex=True, sharey="row",
                             squeeze=False, layout="constrained")
    for col, method in enumerate(routed):
        sub = ranked[ranked.method == method]
        for rank in sorted(sub.usage_rank.unique()):
            table = sub[sub.usage_rank == rank].pivot_table(index="iteration", columns="seed", values="p")
            axes[0, col].plot(table.index, table.mean(axis=1), label=f"usage rank {rank}")
            axes[0, col].fill_between(table.index, table.min(axis=1), table.max(axis=1), alpha=0.15, lw=0)
        axes[0, col].set_title(method_label(method))
        plot_over_training(axes[1, col], metrics, "rollout/switch_rate", [method])
        axes[1, col].axhline(2 / 3, color="grey", ls=":", lw=1)
        for t in switch_iterations(metrics[metrics.method == method]):
            axes[0, col].axvline(t, color="0.5", ls="--", lw=0.7)
    # one x-label for the row of panels: the long label of each panel ran into its neighbour's
    xlabel = axes[1, 0].get_xlabel()
    for ax in axes[1]:
        ax.set_xlabel("")
    fig.supxlabel(xlabel, fontsize=10)
    axes[0, 0].set_ylabel("share of rollout steps")
    axes[1, 0].set_ylabel("switch rate (dotted: random)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"The routing that ran: selected-expert shares and switch rate in the rollouts\n{note}", fontsize=9)
    save_figure(fig, "results_routing_ran", figures_dir)
    plt.show()

# %% [markdown]
# ![Selected-expert shares and switch rate in the rollouts, medium scale](../paper_figures/results_routing_ran.png)
#
# ![Selected-expert shares and switch rate in the rollouts, paper scale](../paper_figures/paper_scale/results_routing_ran.png)

# %% [markdown]
# ## System performance and internal state
#
# How the methods fly, not only how much they cover: collisions and energy per UAV, the users served
# and the share of UAVs in use, and how the mean action on the probe batch answers each switch.

# %%
figure("collisions_per_episode", "collisions per episode", "results_collisions", "Collisions per episode over training",
       reference=levels)
figure("energy_rate_kj", "energy per UAV per slot [kJ]", "results_energy_rate", "Mean UAV energy rate over training",
       reference=levels)

# %% [markdown]
# ![Collisions per episode over training, medium scale](../paper_figures/results_collisions.png)
#
# ![Mean UAV energy rate over training, medium scale](../paper_figures/results_energy_rate.png)

# %%
fig, axes = plt.subplots(2, 1, figsize=(8, 6.4), sharex=True)
plot_over_training(axes[0], metrics, "served_users", method_list, reference=levels)
axes[0].set_ylabel("served users (mean per slot)")
plot_over_training(axes[1], metrics, "uav_using_rate", method_list, reference=levels)
axes[1].set_ylabel("UAV using rate")
axes[0].set_title(f"Served users and UAV using rate over training\n{note}\n"
                  f"black lines: each phase's level without learning ({reference_note})", fontsize=9)
axes[0].legend(fontsize=8, ncol=3)
save_figure(fig, "results_service", figures_dir)
plt.show()

# %% [markdown]
# ![Served users and UAV using rate over training, medium scale](../paper_figures/results_service.png)

# %%
fig, axes = plt.subplots(2, 1, figsize=(8, 6.4), sharex=True)
for ax, comp in zip(axes, ("x", "y")):
    plot_over_training(ax, metrics, f"action/mean_{comp}", method_list, window=1)
    ax.set_ylabel(f"mean action, {comp}")
axes[0].set_title(f"Mean action response to phase switches (probe batch, deterministic)\n{note}", fontsize=9)
axes[0].legend(fontsize=8, ncol=4)
save_figure(fig, "results_mean_action", figures_dir)
plt.show()

# %% [markdown]
# ![Mean action response to phase switches, medium scale](../paper_figures/results_mean_action.png)

# %% [markdown]
# ## Did each phase learn?
#
# The learning-budget study (appendix 09b) trains every method in each single phase, with no switch,
# for 2 million environment steps; the mean coverage over its last 10 % is that method's
# **plateau** in that phase. Here that plateau is the yardstick for the runs above: for every
# method and every phase visit, the coverage over the last 10 % of the visit and its fraction of
# the plateau. The bar a scale has to clear before its comparisons say anything about learning is
# MLP at 85 % or more of its plateau in every visit, and at least 0.65 coverage in phase 0; the
# other methods get the same fraction, whatever it is. A method far below its plateau is a finding,
# not something to tune away. The comparison is not like for like in one respect: a later visit
# starts from a network trained on other phases, which can help or hurt.

# %%
from pemamoe.budget import PLATEAU_FRACTION, phase_learning, study_plateaus, study_specs

# The study covers the built-in methods (a plugin method would need its own 2M-step runs; notebook 09b).
study = sweep_records(study_specs(scale, seed_list, method_list), backend, workers, results_dir, ray_address,
                      records_dir, retrain)
learned = phase_learning(metrics, study_plateaus(study, scale))
mlp_rows = learned[learned.method == "mlp"]
mlp_ok = bool(len(mlp_rows) and (mlp_rows.fraction_of_plateau >= PLATEAU_FRACTION).all()
              and (mlp_rows[mlp_rows.phase == 0].coverage_last_10pct >= 0.65).all())
print(f"scale {scale}: MLP at >= {PLATEAU_FRACTION:.0%} of its plateau in every visit and >= 0.65 in phase 0: "
      f"{'yes' if mlp_ok else 'NO'}")
learned.pivot_table(index=["visit", "phase"], columns="method", values="fraction_of_plateau").round(2)

# %% [markdown]
# ### Is a revisited phase learned worse? Plasticity loss, measured
#
# The fraction of the plateau says whether a visit learned, not whether the network had lost some
# of its ability to learn: the plateau comes from runs scheduled differently (2 million steps in
# one phase), and a visit's end level mixes what the network carried over with what it learned in
# the visit. The paper's premise is sharper: a network that has trained on other phases relearns a
# phase worse than it first learned it. So for every later visit of a phase we compare the
# learning curve **within the visit** with two references over the same number of environment
# steps: the same runs' first visit of that phase, and a fresh network (the study's run of the
# method in that phase, the same update settings, started from scratch; the study has none with
# the paper's update settings and a visit's length, so at that scale only the first visit). Per
# visit: the mean coverage over the visit (the area under the curve per step), the level at its
# end, and the steps to 85 % of the study's plateau; and, at the switch that opens the visit, the
# dormant-unit fraction and the effective feature rank (the diagnostics run at every switch). A
# negative revisit-minus-first or revisit-minus-fresh difference is what plasticity loss looks
# like, and those two differences (mean over the visit and level at its end) are also the last
# columns of the phase-visit table `phase_learning_<scale>` (empty for a first visit). The
# fraction of the plateau there answers "did the visit learn?"; only these comparisons answer "was
# it learned worse?". One caveat: the entropy coefficient of a cycling run anneals over the whole
# run, so a revisit also explores less than a first visit or a fresh run.

# %%
from pemamoe.budget import block_steps, load_study, plasticity_words, revisit_learning
from pemamoe.budget import plot_visits

# the study trains medium's update settings (the paper's for MLP only, 2M steps: shorter than a paper visit)
fresh = load_study(study) if scale != "paper" else load_study(study).iloc[:0]  # PE-MAMoE's is SMoE's run
revisits = revisit_learning(metrics, fresh, study_plateaus(study, scale), bin_steps=block_steps(scale))
write_table(revisits.round(4), f"plasticity_loss_{scale}", figures_dir)
# the phase-visit table carries each revisit's two comparisons beside its fraction of the plateau
against = ["revisit_minus_first_mean", "revisit_minus_first_end", "revisit_minus_fresh_mean", "revisit_minus_fresh_end"]
learned = learned.merge(revisits.reindex(columns=["method", "visit", *against]), on=["method", "visit"], how="left")
write_table(learned.round(4), f"phase_learning_{scale}", figures_dir)

if revisits.empty:  # no phase is visited twice (the ci schedule is one cycle)
    print("no revisits at this scale")
else:
    fig = plot_visits(metrics[metrics.method.isin(set(revisits.method))], fresh, scale)  # appendix 09b
    save_figure(fig, f"plasticity_loss_{scale}", figures_dir)
revisits.filter(["method", "phase", "visit", "revisit_mean", "first_mean", "fresh_mean", "revisit_minus_first_mean",
                 "revisit_minus_fresh_mean", "revisit_end", "first_end", "fresh_end"]).round(3)

# %% [markdown]
# ![Coverage within each phase visit against the first visit and a fresh network, medium scale](../paper_figures/plasticity_loss_medium.png)
# *(`plasticity_loss_<scale>.png`: the `medium` one is shown.)*

# %%
Markdown(plasticity_words(revisits))

# %% [markdown]
# ### The paper's regime: the campaign
#
# `medium` gives a phase visit about a ninth of the paper's gradient steps, and plasticity loss is
# driven by updates. The paper-scale campaign (9 visits of 1,200 iterations, 8 epochs of 32
# minibatches, 18 runs: the four compared methods and the two MLP plasticity baselines, three seeds
# each; `benchmarks/HISTORY.md` for its stages) is committed as records; this cell reads them,
# trains nothing, and measures the same comparisons on them. Revisits are set against first visits:
# the first visit of phase 0 is a fresh network (it has seen nothing else, trained the same way),
# those of phases 1 and 2 have seen only the phases before them. The learning-budget study's fresh
# MLP at the paper's update settings (09b) ran 2M steps of phase 0 only, not a 2.5M-step visit, so
# it is not used here. Three seeds are few, so the differences are shown seed by seed.

# %%
from pemamoe.analysis import plot_seed_differences
from pemamoe.core import repo_path
from pemamoe.methods import METHOD_REGISTRY
from pemamoe.records import verify_record


campaign = [spec for spec in main_specs("paper", default_seeds("paper"), method_order(METHOD_REGISTRY))  # baselines too
            if verify_record(record_marker(spec, repo_path(records_dir)), spec.to_config())]
if not campaign:
    campaign_revisits = pd.DataFrame()
    print("no paper-scale record to read")
else:
    campaign_metrics, _ = load_runs(sweep_records(campaign, "local", 1, results_dir, None, records_dir, False))
    no_plateaus = pd.DataFrame({"method": [], "phase": [], "plateau": []})
    campaign_revisits = pd.concat([revisit_learning(runs, runs.iloc[:0], no_plateaus, bin_steps=block_steps("paper"))
                                   .assign(seed=seed) for seed, runs in campaign_metrics.groupby("seed")])
    campaign_revisits = campaign_revisits[["method", "seed", "phase", "visit", "steps", "revisit_mean", "first_mean",
                                           "revisit_minus_first_mean", "revisit_end", "first_end",
                                           "revisit_minus_first_end", "first_dormant_at_switch",
                                           "revisit_dormant_at_switch", "first_rank_at_switch", "revisit_rank_at_switch"]]
    fig = plot_seed_differences(campaign_revisits)
    if scale == "paper":  # drawn into paper_figures/paper_scale/ only: no copy of it in the medium folder
        write_table(campaign_revisits.round(4), "plasticity_loss_paper_campaign", figures_dir)
        save_figure(fig, "plasticity_loss_paper_campaign", figures_dir)
    plt.show()
campaign_revisits.pivot_table(index=["method", "visit", "phase"], columns="seed",
                              values=["revisit_minus_first_mean", "revisit_minus_first_end"]).round(3) \
    if len(campaign_revisits) else campaign_revisits

# %% [markdown]
# ![Each revisit minus its phase's first visit at the paper's scale, seed by seed](../paper_figures/paper_scale/plasticity_loss_paper_campaign.png)
#
# ![Coverage within each phase visit at the paper's scale, mean over seeds](../paper_figures/paper_scale/plasticity_loss_paper.png)

# %%
from pemamoe.budget import revisit_words

Markdown(revisit_words(campaign_revisits))

# %% [markdown]
# Read on the committed records (`paper_scale/plasticity_loss_paper_campaign.csv` of
# `paper_figures/`), the premise appears at the paper's scale in every network but the MLP with
# shrink-and-perturb ("ends" below: the level over a revisit's last 10 % against the first visit's):
#
# * **MLP, faintly.** A revisit starts higher than the first visit, yet in phase 0 five of six end
#   below it (by 0.028 on average), with almost no dormant units and a feature rank that grows
#   (19 to 21 at a switch): a lower ceiling, not dead units. ReDo, which recycles dormant units,
#   finds few and changes little; shrink-and-perturb lifts it (phase-0 revisits end 0.018 above the
#   first visit on average), the only method whose revisits do not end lower on average.
# * **Dense MoE, clearly.** All six phase-0 revisits end below the first visit, by 0.082, and 13 of
#   its 18 revisits in all, with its units alive (2 % dormant) and its rank flat near 18.
# * **SMoE, with the textbook signatures.** Its first cycle learns as the MLP's does (phase 0: 0.771
#   against 0.772 over the first visit's last 10 %), but in the third cycle two of three seeds
#   collapse (the third visit of phase 1 ends 0.37 and 0.20 below the first), while its dormant
#   fraction at a switch doubles (4 % to 9 %) and its feature rank falls (17 to 14); the third seed
#   ends five of its six revisits above the first visit.
# * **PE-MAMoE** ends 16 of its 18 revisits below their first visit, its rank held near 17. But its
#   first visit of phase 1, which revisits nothing, is already 0.09 below SMoE's: the controller
#   costs at the switch itself (notebook 10), and the loss it is meant to prevent comes on top.
# * **A caveat for both sparse networks.** From the first switch on, their updates stop early: a
#   visit gets 13k to 86k of the 307k gradient steps an MLP's takes (`benchmarks/CONTROLLER_SWITCH.md`;
#   notebook 10 says why), so their shortfall mixes lost plasticity with less training.
#
# Part of every revisit's shortfall is the entropy schedule (it anneals over the run, so a revisit
# explores less); the MLP with shrink-and-perturb, on the same schedule, shows it is not all of it.
