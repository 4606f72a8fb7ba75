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
# # 07c · Appendix: the run's configuration
#
# Notebook 07 is the method: the phase clock, GAE, the rollout, the PPO update and the loop that
# ties them together. This appendix holds the object every run is a function of, in the module
# `pemamoe.train_config`: the `TrainConfig` dataclass (its fields, the checks of `__post_init__`,
# the derived quantities), how a config is written to `config.json` and read back (`to_dict`,
# `from_dict`), the identity that names a run's folder (`identity`, `config_hash`, `run_name`),
# the code of the presets (`for_scale`, `scale_controller`, `MEDIUM_PHASE_ITERS`), why the presets
# hold the numbers they hold, and the device choice (`resolve_device`). What the trainer keeps
# while it runs (episodes, log rows, normalisers, checkpoints) is appendix 07e's.
#
# The module does not import `pemamoe.mappo`; `pemamoe.mappo` imports it and re-exports the names
# callers import from it (`from pemamoe.mappo import TrainConfig` works, as does
# `from pemamoe.train_config import TrainConfig`).

# %%
#| default_exp train_config

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## The paper's training table, and what we had to choose
#
# The paper's training table gives most of the numbers; the rest are ours, each a field of
# `TrainConfig` so that nothing is hidden in the code.
#
# | quantity | paper | our value / reading |
# |---|---|---|
# | total steps, rollout | 22,118,400 steps, rollout 2048 | 2048 **environment** steps per iteration (64 envs × 32 slots, one episode each), 10,800 iterations |
# | phases | 3 phases × 3 cycles; Algorithm 1 switches at "iteration mod L" | $L = 10{,}800 / 9 = 1200$ iterations |
# | epochs, minibatches | 8, 32 | 8, 32; a minibatch is 1/32 of the **environment steps** with all $U$ agents of each step |
# | optimiser | Adam, weight decay $10^{-4}$, betas (0.9, 0.999) | **AdamW** (decoupled decay), $\epsilon = 10^{-5}$ (CleanRL's PPO value) |
# | lr, annealing | $3\times10^{-4}$, no annealing | same; `anneal_lr=True` gives CleanRL's linear decay for experiments |
# | $\gamma$, $\lambda$, clip | 0.99, 0.95, 0.15 | same |
# | value loss | $\lambda_V\,\mathbb E[(V-\hat V)^2]$, $\lambda_V = 2$ | the same squared error (no ½), **no value clipping** by default, on **normalised** returns |
# | entropy | 0.01 → 0.003 over the first 30 % | same for the baselines; PE-MAMoE re-anneals within each phase (notebook 06) |
# | target KL | 0.1 | checked on **every minibatch** before its gradient step; exceeding it ends the update |
# | grad norm | 0.5 | clipped separately for the actor and for the critic (MAPPO's two optimisers) |
# | advantages | – | normalised per minibatch (CleanRL) |
#
# **Adam or AdamW?** The table lists "Adam" and "weight decay" side by side. PyTorch's `Adam`
# would add the decay to the gradient (an L2 penalty), which Adam's per-parameter scaling then
# distorts; `AdamW` shrinks the weights directly. We take AdamW, the usual meaning of "weight
# decay" with Adam today. At $\text{lr}\times\text{wd} = 3\times10^{-8}$ per step the decay is
# tiny either way; it also applies to the log-std, pulling it towards 0 by a negligible amount.

# %% [markdown]
# ## `TrainConfig`: one frozen object per run
#
# A run is a function of its `TrainConfig` and nothing else. The fields carry the paper's training
# table as defaults; every one is checked in `__post_init__` with `pemamoe.core.require_field`
# (notebook 00b), so a bad value fails when the config is built, naming the field, the value and
# what is allowed, rather than some iterations into a run. Three checks go beyond a single field:
# the minibatch count must divide the environment steps of an iteration, the environment overrides
# must build a valid `EnvConfig`, and they may not take the phase clock away from the trainer.
# Numpy scalars in the overrides become Python numbers, so the config always serialises.
#
# `TIMING_COLUMNS` names the logged columns that describe how a run was executed (speed, population
# size) rather than what it computed; comparisons of two executions of one run leave them out.

# %%
#| export
import dataclasses
import hashlib
import json
from dataclasses import asdict, dataclass, field, fields

import numpy as np
import torch

from pemamoe.core import SEED_LIMIT  # re-export: in core, so that the command line checks --seed without torch (00b)
from pemamoe.core import by_scale, check_scale, config_error, require, require_field
from pemamoe.core import ITERATIONS_LIMIT
from pemamoe.env import EnvConfig
from pemamoe.methods import METHOD_REGISTRY, method_spec, compared_methods, network_kind
from pemamoe.nets import NetConfig
from pemamoe.phase_controller import MECHANISMS, PhaseControllerConfig
from pemamoe.plasticity import RunSettings

# %% [markdown]
# **Serialisation and identity.** `to_dict` is the content of `config.json`: the dataclass as
# plain JSON types, with sorted keys (nested `NetConfig` and `PhaseControllerConfig` as dicts), and
# `from_dict` rebuilds the same object from it. The folder a run writes to is named
# `<method>-s<seed>-<hash>`, where the hash is the first 12 hex digits of the sha256 of the run's
# **identity**: `to_dict` with three adjustments, each so that two configs share a hash exactly
# when they compute the same thing.
#
# * A baseline's phase-controller settings are dropped, since they cannot change its run (three
#   noise levels given to a baseline without `force_controller` are one run, not three).
# * The fully resolved `EnvConfig` is added, so a changed environment default (or step engine)
#   gives new folders instead of silently reusing results computed under the old one.
# * `device` is replaced by the device it resolves to (a CUDA run is not bit-identical to a CPU
#   run), and `fixed_phase` is left out while it is `None`, so that adding the field kept every
#   cycling run's hash, and with it every cached result.
# * `TRAINING_NUMERICS`, the version of the training arithmetic, is added once it is above 1. The
#   config alone cannot tell a run made before a change of the trainer, the networks or the
#   environment's step code from one made after it, yet the two hold different numbers; bumping
#   this constant with such a change gives every run a new folder, so an old result is never
#   served as a new one. Version 1 is the arithmetic of every run made before the constant existed
#   and leaves the identity as it was. A test (`tests/test_numerics.py`) trains a short population
#   of every method and compares it with a stored fingerprint, so a change that moves the numbers
#   without a bump fails the suite.
#
# A bump renames the *folders* a new training writes to; it does not disown the records already
# made. A finished record is evidence produced by the code that made it, like a record made on
# another processor, and it keeps its numerics stamp. So `identity`, `config_hash` and `run_name`
# take an optional `numerics`: the name the same config had under an earlier version (version 1
# still leaves the key out), and `run_names()` lists them all, newest first. The record lookup
# (appendix 09d, `find_record`) tries them in that order, so after a bump the figures read, and
# the sweep counts as done, the newest record a config has, of whichever version. What stays
# refused is *resuming* a checkpoint across versions (appendix 07b): one run would then mix two
# arithmetics. An unfinished run of an older version is left where it is, and the sweep trains the
# config afresh under the new version, in its new folder. `training_numerics()` reads the constant
# when called, and every module that stamps or checks a version asks it, so a test simulates a bump
# by setting `pemamoe.train_config.TRAINING_NUMERICS` alone (`tests/test_numerics_lookup.py`).
#
# **Presets.** `for_scale(scale, method, seed, **overrides)` starts from the scale's numbers, takes
# the method's controller preset from the registry, rescales its windows with `scale_controller`
# and then applies the overrides, which may name a field of `TrainConfig`, of
# `PhaseControllerConfig` or of `NetConfig`, or switch mechanisms off with `without=(...)`.
#
# The four presets, and why they hold these numbers:
#
# * **paper**: the training table exactly (10,800 iterations of 2048 environment steps).
# * **small**: short training, 39 runs (four methods × three seeds, the ablations
#   and the noise sweep); the sweep took 18 min 34 s on two cores with two worker processes
#   (measured at `dc5e4d6`, `benchmarks/HISTORY.md`).
#   The rollout shrinks to 16 environments × 32 slots (512 environment steps), each phase lasts
#   60 iterations (540 iterations, 276k environment steps in all) and the update runs 4 epochs of
#   4 minibatches. What a run costs is measured by `make bench` (`benchmarks/bench_train.py`),
#   which prints the throughput of populations of 1, 4 and 16 runs and the projected sweep times;
#   `benchmarks/RESULTS.md` holds the latest figures with the commit that measured them.
# * **medium**: the scale at which learning is visible. It keeps the small update settings and
#   gives each phase `MEDIUM_PHASE_ITERS` iterations, three phases twice over (six phases). Both
#   numbers come from the learning-budget study of notebook 09b, which trains every method in each
#   single phase for two million steps; that notebook states what the study found and whether this
#   phase length lets every method get close to its plateau. The study also picks the update
#   settings: per compute second the small ones and the paper's (64 environments, 8 epochs x 32
#   minibatches) are close, but the paper's cost about twice as much per environment step and level
#   off no higher (`paper_figures/learning_budget_compute.md` and `learning_budget.md`, study runs
#   at `d02f78f`), and a phase is counted in environment steps. Two cycles instead of the paper's
#   three, because a third would add half again to a sweep that already runs several times over
#   its two-hour budget (`benchmarks/HISTORY.md`); two cycles still show every switch the paper is about: each phase
#   is entered cold, left, and entered again.
# * **ci**: a handful of iterations crossing two phase switches, seconds per run.
#
# **Time-compressed schedules.** The phase controller's windows are counted in iterations
# (LR warm-up 200, conservative window 80, router freeze 30, KL-anchor decay 0.985 per iteration,
# temperature decay rate $\beta = 0.05$ per iteration) or in update epochs (noise for 30 epochs),
# all relative to a 1200-iteration phase of 8-epoch updates. A small run with 60-iteration phases
# would otherwise spend several phases in one LR warm-up. `for_scale` therefore rescales each
# window by the ratio of phase lengths (at least one iteration or epoch when the paper's window is
# non-zero), so a window covers the same *fraction of a phase* as in the paper. Explicit
# overrides win over the rescaling.
#
# The controller runs only for `method="pemamoe"`; `force_controller=True` runs it for a baseline
# as well (the noise sweep's "MoE with expert noise alone" uses it). A baseline's controller
# settings are left out of its config hash, since they cannot change its run.
#
# A table at the end of this section compares the presets.

# %%
#| export
METHODS = compared_methods()  # the methods the experiments compare by default (pemamoe.methods)
DEVICES = ("cpu", "cuda", "auto")
PAPER_PHASE_LENGTH = 1200  # iterations per phase in the paper (10,800 / 9)
PAPER_UPDATE_EPOCHS = 8
# The version of the training arithmetic (see the identity above): bump it with any change that
# alters the numbers a run computes for the same config, and refresh tests/numerics_fingerprint.json.
TRAINING_NUMERICS = 3  # 3: the update's gradient written out (appendix 05h), leaner AdamW and mixing; 2: the controller inert before the first switch, gating choices


def training_numerics() -> int:
    """The version of the training arithmetic this code computes: `TRAINING_NUMERICS`, read when
    called. Every module that stamps or checks a version asks here, so a test can simulate a bump by
    setting `pemamoe.train_config.TRAINING_NUMERICS` alone."""
    return TRAINING_NUMERICS


def check_numerics(numerics) -> int:
    """`numerics` (None: the current version) as a version this code can name a run under: an int
    from 1 (the runs made before the version existed) to the current one."""
    current = training_numerics()
    if numerics is None:
        return current
    if type(numerics) is not int or not 1 <= numerics <= current:
        raise ValueError(f"numerics must be an int from 1 to {current} (this code's TRAINING_NUMERICS), got {numerics!r}")
    return numerics
# Columns that describe how a run was executed (speed, population size), not what it computed:
# they differ between two executions of the same run and are left out of every comparison.
TIMING_COLUMNS = ("sps", "sps_total", "rollout_time", "update_time", "diag_time", "wall_time", "population")


# An MLP reads only these NetConfig fields. Every other one (the gating settings) is written into
# an MLP run's identity at the value it had when MLP runs were first recorded, so a later change of
# a gating default (or a new gating field) leaves the MLP runs, and their records, where they are.
MLP_NET_FIELDS = ("hidden", "init_log_std", "gain_hidden", "gain_policy", "gain_value")
MLP_INERT_NET_IDENTITY = {"n_experts": 3, "top_k": 1, "load_balance_coef": 0.01, "top1_weight": "straight_through",
                          "routing_noise": "off", "noise_std": 1.0, "noise_anneal_portion": 1.0,
                          "critic_gating": "dense", "expert_impl": "auto", "masked_min_batch": 512,
                          "gain_router": 0.01}
# NetConfig fields added after runs were first recorded, with the value those runs computed under:
# a run that keeps it has the identity it had before the field existed.
NET_FIELDS_ADDED = {"expert_heads": "shared", "update_routing": "replay"}
# TrainConfig fields added after runs were first recorded, likewise.
TRAIN_FIELDS_ADDED = {"target_kl_check": "minibatch"}
# Where the target-KL early stop reads its estimate (see the field `target_kl_check`).
TARGET_KL_CHECKS = ("minibatch", "epoch")


def resolve_device(name: str) -> torch.device:
    """"cpu", "cuda" or "auto" (CUDA when available) -> torch.device."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("TrainConfig.device is 'cuda' but torch sees no CUDA device; use 'cpu' or 'auto'")
    return torch.device(name)


def _plain(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, (tuple, list)):
        return type(v)(_plain(x) for x in v)
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v


@dataclass(frozen=True)
class TrainConfig:
    """Every number of one MAPPO run (defaults: the paper's training table; see notebook 07)."""

    method: str = "pemamoe"  # a name in pemamoe.methods.METHOD_REGISTRY: network kind and plasticity method
    force_controller: bool = False  # True: run the phase controller for a baseline too (e.g. MoE + noise only)
    seed: int = 0
    # budget and phase clock
    num_envs: int = 64
    rollout_steps: int = 32  # slots per environment per iteration (64 x 32 = 2048 env steps)
    iterations: int = 10800
    phase_length_iters: int = 1200  # L: the phase advances every L iterations
    n_phases: int = 3
    # None: the phases cycle (the paper). An int: every iteration is in that phase and there is no
    # switch (the learning-budget study, notebook 09); members of a population may hold different ones.
    fixed_phase: int | None = None
    # PPO update
    update_epochs: int = 8
    num_minibatches: int = 32
    lr: float = 3e-4
    weight_decay: float = 1e-4  # decoupled (AdamW)
    adam_betas: tuple = (0.9, 0.999)
    adam_eps: float = 1e-5
    anneal_lr: bool = False
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_coef: float = 0.15
    clip_vloss: bool = False
    vf_coef: float = 2.0
    ent_start: float = 0.01
    ent_end: float = 0.003
    ent_anneal_portion: float = 0.3  # of the whole run (baselines)
    target_kl: float | None = 0.1  # None disables the early stop
    # "minibatch": before each minibatch's step, on that minibatch's estimate (a reading of ours);
    # "epoch": after each full epoch, on its last minibatch's estimate (CleanRL's continuous PPO)
    target_kl_check: str = "minibatch"
    max_grad_norm: float = 0.5
    norm_adv: bool = True
    value_norm: bool = True
    # environment, networks, phase controller
    env_overrides: dict = field(default_factory=dict)
    net: NetConfig = field(default_factory=NetConfig)
    controller: PhaseControllerConfig = field(default_factory=PhaseControllerConfig)
    # diagnostics, logging, checkpoints
    probe_size: int = 512  # rows of the fixed probe batch for the plasticity diagnostics
    diag_every: int = 50  # iterations between diagnostics (also at switches and at the end)
    checkpoint_every: int = 100  # iterations between checkpoints and log flushes
    device: str = "cpu"  # networks and the update: "cpu", "cuda" or "auto"; the environment stays on the CPU

    def __post_init__(self):
        own = "TrainConfig"
        if isinstance(self.method, str):
            try:
                method_spec(self.method)  # loads $PEMAMOE_PLUGINS on an unknown name
            except ValueError:
                pass
        require_field(self, "method", "choice", tuple(METHOD_REGISTRY))
        require_field(self, "device", "choice", DEVICES)
        require_field(self, "seed", "int", ge=0, lt=SEED_LIMIT,
                      note="torch and numpy take 64-bit seeds, and each environment adds its index to the seed")
        for name in ("num_envs", "rollout_steps", "iterations", "phase_length_iters", "update_epochs",
                     "num_minibatches", "probe_size", "diag_every", "checkpoint_every"):
            require_field(self, name, "int", ge=1)
        require_field(self, "iterations", "int", ge=1, le=ITERATIONS_LIMIT)
        require_field(self, "n_phases", "int", ge=1, le=3)
        require_field(self, "fixed_phase", "int", ge=0, lt=self.n_phases, optional=True,
                      note=f"a phase index below n_phases = {self.n_phases}, or None to cycle")
        batch = self.num_envs * self.rollout_steps
        if batch % self.num_minibatches or self.num_minibatches > batch:
            raise config_error(own, "num_minibatches", self.num_minibatches,
                               f"a divisor of num_envs * rollout_steps = {batch}")
        require_field(self, "lr", "real", gt=0)
        require_field(self, "weight_decay", "real", ge=0)
        require_field(self, "adam_betas", "reals", ge=0, lt=1, length=2)
        require_field(self, "adam_eps", "real", gt=0)
        require_field(self, "gamma", "real", ge=0, le=1)
        require_field(self, "gae_lambda", "real", ge=0, le=1)
        require_field(self, "clip_coef", "real", gt=0)
        require_field(self, "vf_coef", "real", ge=0)
        for name in ("ent_start", "ent_end"):
            require_field(self, name, "real", ge=0)
        require_field(self, "ent_anneal_portion", "real", gt=0, le=1)
        require_field(self, "target_kl", "real", gt=0, optional=True)
        require_field(self, "target_kl_check", "choice", TARGET_KL_CHECKS)
        require_field(self, "max_grad_norm", "real", gt=0)
        for name in ("force_controller", "anneal_lr", "clip_vloss", "norm_adv", "value_norm"):
            require_field(self, name, "bool")
        if not isinstance(self.net, NetConfig):
            raise config_error(own, "net", self.net, "a NetConfig")
        if not isinstance(self.controller, PhaseControllerConfig):
            raise config_error(own, "controller", self.controller, "a PhaseControllerConfig")
        if not isinstance(self.env_overrides, dict):
            raise config_error(own, "env_overrides", self.env_overrides, "a dict of EnvConfig overrides")
        if self.env_overrides.get("phase_clock", "external") != "external":
            raise config_error(own, "env_overrides", self.env_overrides,
                               "free of phase_clock other than 'external' (the trainer owns the phase clock)")
        try:
            self.env_config()
        except (ValueError, TypeError) as err:
            raise ValueError(f"TrainConfig.env_overrides is invalid: {err}") from err
        # numpy scalars -> Python numbers, so that to_dict / config_hash never meet a type JSON cannot write
        object.__setattr__(self, "env_overrides", {k: _plain(v) for k, v in self.env_overrides.items()})

    # -- derived quantities ---------------------------------------------------------------------
    @property
    def batch_env_steps(self) -> int:
        """Environment steps per iteration (num_envs * rollout_steps)."""
        return self.num_envs * self.rollout_steps

    @property
    def total_env_steps(self) -> int:
        return self.iterations * self.batch_env_steps

    @property
    def controller_enabled(self) -> bool:
        return self.method_spec().plasticity == "phase_controller" or self.force_controller

    def method_spec(self):
        """The registry entry of this run's method (network kind, plasticity method, label)."""
        return method_spec(self.method)

    def env_config(self) -> EnvConfig:
        """The environment's config, with the phase clock owned by the trainer."""
        return EnvConfig.from_overrides(**{**self.env_overrides, "phase_clock": "external"})

    def base_schedule(self) -> RunSettings:
        return RunSettings(
            lr=self.lr, clip_coef=self.clip_coef, target_kl=self.target_kl, ent_start=self.ent_start,
            ent_end=self.ent_end, ent_anneal_portion=self.ent_anneal_portion,
            total_iterations=self.iterations, phase_length=self.phase_length_iters)

    # -- copies ------------------------------------------------------------------------------------
    def replace(self, **changes) -> "TrainConfig":
        return dataclasses.replace(self, **changes)

    def without(self, *mechanisms: str) -> "TrainConfig":
        """The same run with phase-controller mechanisms switched off (ablations)."""
        ctrl = self.controller
        for m in mechanisms:
            ctrl = ctrl.without(m)
        return self.replace(controller=ctrl)

    # -- serialisation -------------------------------------------------------------------------
    def to_dict(self) -> dict:
        d = asdict(self)
        d["adam_betas"] = list(self.adam_betas)
        return json.loads(json.dumps(d, sort_keys=True))  # plain JSON types only

    def label(self) -> str:
        """Display label of this run's variant: the method's label, plus any ablation or gamma."""
        parts = [self.method_spec().label]
        if self.controller_enabled:
            off = [m for m in MECHANISMS if not getattr(self.controller, m)]
            if off:
                parts.append("w/o " + "+".join(off))
            if self.force_controller:
                parts.append("+ controller")
        return " ".join(parts)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        d = dict(d)
        # a config written before a NetConfig field existed computed under that field's value then
        d["net"] = NetConfig(**{**NET_FIELDS_ADDED, **d.get("net", {})})
        d = {**TRAIN_FIELDS_ADDED, **d}
        d["controller"] = PhaseControllerConfig(**d.get("controller", {}))
        d["adam_betas"] = tuple(d.get("adam_betas", (0.9, 0.999)))
        d.pop("label", None)
        return cls(**d)

    def identity(self, numerics: int | None = None) -> dict:
        """What determines the computation: to_dict() without the phase controller for the
        baselines, which never use it (so a noise sweep over the MoE baseline is one run), plus
        the fully resolved environment, so a changed environment default (or step engine) can
        never reuse results computed under the old one, plus TRAINING_NUMERICS once it is above 1.
        numerics: the identity this config had under that earlier version of the arithmetic (None:
        the current one), what the record lookup of appendix 09d names older records by."""
        numerics = check_numerics(numerics)
        d = self.to_dict()
        if not self.controller_enabled:
            d.pop("controller")
        if network_kind(self.method) == "mlp":  # the gating fields are inert for an MLP: pinned, see below
            d["net"] = {**{k: v for k, v in d["net"].items() if k in MLP_NET_FIELDS}, **MLP_INERT_NET_IDENTITY}
        for name, value in NET_FIELDS_ADDED.items():  # at the value every earlier run had: absent, as then
            if d["net"].get(name) == value:
                d["net"].pop(name)
        for name, value in TRAIN_FIELDS_ADDED.items():
            if d.get(name) == value:
                d.pop(name)
        d["env"] = json.loads(json.dumps(asdict(self.env_config()), sort_keys=True))
        d["device"] = str(resolve_device(self.device).type)  # "auto" is whatever it resolves to
        if self.fixed_phase is None:  # the default leaves the identity (and the cache) of cycling runs unchanged
            d.pop("fixed_phase")
        if numerics != 1:  # version 1 is every run made before the version existed
            d["numerics"] = numerics
        return d

    def config_hash(self, numerics: int | None = None) -> str:
        """12 hex digits identifying the run (for result caches); see `identity` (and its
        `numerics`: the hash of the same config under an earlier version)."""
        text = json.dumps(self.identity(numerics), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:12]

    def run_name(self, numerics: int | None = None) -> str:
        return f"{self.method}-s{self.seed}-{self.config_hash(numerics)}"

    def run_names(self) -> dict:
        """{numerics version: run name} of this config under every version of the arithmetic,
        newest (the current one) first: where the record lookup of appendix 09d looks, in order."""
        return {n: self.run_name(n) for n in range(training_numerics(), 0, -1)}

    # -- presets --------------------------------------------------------------------------------
    @classmethod
    def for_scale(cls, scale: str, method: str = "pemamoe", seed: int = 0, **overrides) -> "TrainConfig":
        """Preset for scale "ci" | "small" | "medium" | "paper", then `overrides`.

        An override may name a TrainConfig field, a PhaseControllerConfig field (e.g.
        noise_gamma=0.01), a NetConfig field, or `without=("noise_injection", ...)`; a dotted name
        says which config it is in ("controller.log_std_value", "net.top_k", "env.n_users" for an
        environment override). Controller windows are rescaled to the preset's phase length unless
        overridden.
        """
        check_scale(scale)
        preset = by_scale(
            scale,
            ci=dict(num_envs=4, rollout_steps=16, iterations=6, phase_length_iters=2, update_epochs=2,
                    num_minibatches=2, probe_size=48, diag_every=2, checkpoint_every=2),
            small=dict(num_envs=16, rollout_steps=32, iterations=540, phase_length_iters=60, update_epochs=4,
                       num_minibatches=4, probe_size=256, diag_every=5, checkpoint_every=40),
            # the small update settings, each phase long enough to learn in (notebook 09b), 3 phases x 2 cycles
            medium=dict(num_envs=16, rollout_steps=32, iterations=6 * MEDIUM_PHASE_ITERS,
                        phase_length_iters=MEDIUM_PHASE_ITERS, update_epochs=4, num_minibatches=4, probe_size=256,
                        diag_every=20, checkpoint_every=100),
            paper=dict(num_envs=64, rollout_steps=32, iterations=10800, phase_length_iters=1200, update_epochs=8,
                       num_minibatches=32, probe_size=512, diag_every=50, checkpoint_every=100),
        )
        own = {f.name for f in fields(cls)}
        ctrl_names = {f.name for f in fields(PhaseControllerConfig)}
        net_names = {f.name for f in fields(NetConfig)}
        top, ctrl_over, net_over, without = {}, {}, {}, ()
        env_over = {}
        for key, value in overrides.items():
            part, _, name = key.rpartition(".")
            if part:
                {"controller": ctrl_over, "net": net_over, "env": env_over}[_setting_part(key)][name] = value
            elif key == "without":
                without = (value,) if isinstance(value, str) else tuple(value)
            elif key in own:
                top[key] = value
            elif key in ctrl_names:
                ctrl_over[key] = value
            elif key in net_names:
                net_over[key] = value
            else:
                raise ValueError(
                    f"TrainConfig.for_scale: unknown override {key!r}; use a field of TrainConfig, "
                    f"PhaseControllerConfig or NetConfig, or without=(mechanisms...)")
        settings = {**preset, **top}
        if env_over:
            settings["env_overrides"] = {**settings.get("env_overrides", {}), **env_over}
        preset = PhaseControllerConfig(**dict(method_spec(method).plasticity_preset))  # the method's preset
        ctrl = settings.pop("controller", None) or scale_controller(
            preset, settings["phase_length_iters"], settings["update_epochs"])
        if ctrl_over:
            ctrl = dataclasses.replace(ctrl, **ctrl_over)
        for m in without:
            ctrl = ctrl.without(m)
        net = settings.pop("net", None) or NetConfig()
        if net_over:
            net = dataclasses.replace(net, **net_over)
        return cls(method=method, seed=seed, controller=ctrl, net=net, **settings)


# The medium phase: 2,200 iterations x 512 = 1,126,400 environment steps. In the learning-budget
# study (notebook 09b; records committed at 6ead1c1) the slowest case, MoE in phase 1, first
# reached 85 % of its plateau after 1.1M steps; every other method and phase needed 900k or fewer.
MEDIUM_PHASE_ITERS = 2200


def scale_controller(ctrl: PhaseControllerConfig, phase_length_iters: int, update_epochs: int) -> PhaseControllerConfig:
    """Rescale the controller's windows from the paper's 1200-iteration, 8-epoch phases to
    `phase_length_iters` iterations of `update_epochs` epochs (each window >= 1 if non-zero)."""
    # checked here too: for_scale rescales before TrainConfig validates its fields
    phase_length_iters = require("TrainConfig", "phase_length_iters", phase_length_iters, "int", ge=1)
    update_epochs = require("TrainConfig", "update_epochs", update_epochs, "int", ge=1)
    r = phase_length_iters / PAPER_PHASE_LENGTH
    r_epochs = r * update_epochs / PAPER_UPDATE_EPOCHS

    def window(n, ratio):
        return 0 if n == 0 else max(1, int(round(n * ratio)))

    if r == 1 and r_epochs == 1:
        return ctrl
    return dataclasses.replace(
        ctrl,
        lr_warmup_iters=window(ctrl.lr_warmup_iters, r),
        conservative_iters=window(ctrl.conservative_iters, r),
        router_freeze_iters=window(ctrl.router_freeze_iters, r),
        noise_epochs=window(ctrl.noise_epochs, r if ctrl.noise_window_unit == "iterations" else r_epochs),
        kl_decay=float(ctrl.kl_decay ** (1.0 / r)),
        tau_beta=float(ctrl.tau_beta / r),
    )

# %% [markdown]
# **Any field, by name.** A reading the paper leaves open is tried by changing one field, so every
# field can be set from the command line: `train` and `sweep` take `--set FIELD=VALUE`, repeatable.
# `FIELD` is a `TrainConfig` field (`target_kl=0.15`), or a dotted name for the nested configs:
# `controller.log_std_value=0.3`, `net.top_k=2`, `env.n_users=30` (an environment override).
# `VALUE` is read as JSON (`0.3`, `true`, `[0.9, 0.99]`), `none` is `None`, anything else is a
# string (`target_kl_check=epoch`); an integer given to a float field becomes a float, a list
# given to a tuple field a tuple. The config's own validators then check the value, so `--set`
# refuses exactly what the Python API refuses, and the changed field is part of the run's identity
# like any other. The method and the seed keep their own flags.

# %%
#| export
SETTING_PARTS = {"controller": PhaseControllerConfig, "net": NetConfig, "env": EnvConfig}
_OWN_FLAGS = ("method", "seed")


def _setting_part(key: str) -> str:
    """The nested config a dotted setting names ("controller", "net" or "env"); ValueError otherwise."""
    part, _, name = key.rpartition(".")
    if part not in SETTING_PARTS or not name:
        raise ValueError(f"setting {key!r}: a dotted name must be controller.FIELD, net.FIELD or env.FIELD")
    return part


def _setting_field(key: str):
    """The dataclass field a setting names (None for an environment setting, which EnvConfig checks)."""
    part, _, name = key.rpartition(".")
    if part == "env":
        return None
    owner = SETTING_PARTS[_setting_part(key)] if part else TrainConfig
    by_name = {f.name: f for f in fields(owner)}
    nested = () if part else tuple(SETTING_PARTS) + ("env_overrides",)
    if name not in by_name or name in nested or (not part and name in _OWN_FLAGS):
        allowed = sorted(set(by_name) - set(nested) - (set() if part else set(_OWN_FLAGS)))
        where = f"{owner.__name__} field" if part else "TrainConfig field, or controller.FIELD, net.FIELD, env.FIELD"
        raise ValueError(f"setting {key!r}: not a {where}; allowed{' ' + part + '.' if part else ''}: "
                         f"{', '.join(allowed)}" + ("; --method and --seed have flags of their own"
                                                    if name in _OWN_FLAGS and not part else ""))
    return by_name[name]


def parse_setting(text: str) -> tuple:
    """"FIELD=VALUE" -> (FIELD, value), for `TrainConfig.for_scale`'s overrides (see above).
    ValueError naming the text when it is not FIELD=VALUE or FIELD names no field; the value
    itself is checked by the config it lands in."""
    key, sep, raw = str(text).partition("=")
    key = key.strip()
    if not sep or not key:
        raise ValueError(f"setting {text!r} is not FIELD=VALUE (e.g. controller.log_std_value=0.3)")
    field_ = _setting_field(key)
    if raw.strip().lower() in ("none", "null"):
        return key, None
    try:
        value = json.loads(raw)
    except ValueError:
        value = {"True": True, "False": False}.get(raw.strip(), raw)
    kind = "" if field_ is None else str(field_.type)
    if "float" in kind and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if "tuple" in kind and isinstance(value, list):
        value = tuple(value)
    return key, value


def parse_settings(texts) -> dict:
    """Every "FIELD=VALUE" of `texts` (the last one wins for a field named twice) as overrides."""
    return dict(parse_setting(t) for t in texts or ())


# %% [markdown]
# A config survives its own file, and a bad value is refused with a message that says what to
# change:

# %%
_cfg = TrainConfig.for_scale("ci", method="pemamoe", seed=seed)
assert TrainConfig.from_dict(json.loads(json.dumps(_cfg.to_dict()))) == _cfg
_widened = TrainConfig.for_scale("ci", "pemamoe", seed, **parse_settings(["controller.log_std_value=0.3",
                                                                         "target_kl_check=epoch"]))
assert _widened.controller.log_std_value == 0.3 and _widened.target_kl_check == "epoch"
assert _widened.config_hash() != _cfg.config_hash()
try:
    TrainConfig.for_scale("ci", num_minibatches=3)
except ValueError as err:
    print(err)
print(_cfg.run_name())

# %% [markdown]
# What enters the hash. A baseline ignores the controller, so its controller settings leave the
# hash alone; PE-MAMoE's do not. A fixed phase names a different run; the default (cycling) adds
# nothing to the identity.

# %%
_mlp = TrainConfig.for_scale("ci", method="mlp", seed=seed)
assert _mlp.replace(controller=_mlp.controller.without("noise_injection")).config_hash() == _mlp.config_hash()
assert _cfg.without("noise_injection").config_hash() != _cfg.config_hash()
assert "fixed_phase" not in _cfg.identity() and _cfg.replace(fixed_phase=1).config_hash() != _cfg.config_hash()
assert TrainConfig.for_scale("paper").total_env_steps == 22_118_400
assert TrainConfig.for_scale("paper").controller == PhaseControllerConfig()
{k: v for k, v in _cfg.identity().items() if k not in ("env", "controller", "net")}

# %% [markdown]
# The presets side by side (the columns that differ, and the rescaled controller windows):

# %%
import pandas as pd

from pemamoe.core import SCALES

_rows = []
for _s in SCALES:
    _c = TrainConfig.for_scale(_s)
    _rows.append({"scale": _s, "num_envs": _c.num_envs, "rollout_steps": _c.rollout_steps,
                  "env steps/iter": _c.batch_env_steps, "iterations": _c.iterations, "L": _c.phase_length_iters,
                  "epochs": _c.update_epochs, "minibatches": _c.num_minibatches,
                  "total env steps": _c.total_env_steps, "lr warm-up": _c.controller.lr_warmup_iters,
                  "conservative": _c.controller.conservative_iters, "freeze": _c.controller.router_freeze_iters,
                  "noise epochs": _c.controller.noise_epochs, "kl decay": round(_c.controller.kl_decay, 4)})
pd.DataFrame(_rows)

# %% [markdown]
# ## The paper's parameter table, generated from the configuration objects
#
# Every number of the simulation and of training, read from `EnvConfig` and the `paper` preset of
# `TrainConfig`, so the table cannot drift from the code.

# %%
import dataclasses as _dc

from pemamoe.core import write_table
from pemamoe.env import EnvConfig
from pemamoe.methods import proposed_method


def flatten(obj, prefix=""):
    out = {}
    for f in _dc.fields(obj):
        value = getattr(obj, f.name)
        if _dc.is_dataclass(value):
            out.update(flatten(value, f"{prefix}{f.name}."))
        elif not f.name.startswith("_"):
            out[f"{prefix}{f.name}"] = value
    return out


params = {**{f"env.{k}": v for k, v in flatten(EnvConfig()).items()},
          **{f"train.{k}": v for k, v in flatten(TrainConfig.for_scale("paper", proposed_method(), 0)).items()
             if k not in ("method", "seed")}}
param_table = pd.DataFrame({"parameter": list(params), "value": [str(v) for v in params.values()]})
write_table(param_table, "table_parameters", figures_dir)
print(len(param_table), "parameters")
