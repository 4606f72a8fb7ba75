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
# # 07 · The MAPPO trainer (paper section IV-B, Algorithm 1, training table)
#
# This notebook turns the pieces of the previous ones into a learning system: the vectorised
# environment of notebook 04, the actors and critics of notebook 05 and the phase controller of
# notebook 06 are wired into one PPO loop, `train(config)`, that every experiment of the paper
# runs (the four methods MLP, MoE, SMoE and PE-MAMoE, the noise sweep and the tricks ablation).
#
# The run's configuration object and the trainer's bookkeeping (episode accounting, the log row,
# checkpoint encoding) are in appendix 07c, and run folders in 07b, so what remains here is the
# method. The notebook is still longer than about 800 lines because the rollout, the update and
# the training loop are the algorithm and read best top to bottom, in one place.
#
# **Centralised training, decentralised execution (CTDE).** Each of the $U = 3$ UAVs acts on its
# *own* local observation: the actor never sees the other UAVs' observations or the global state,
# so it can run on board. One set of actor weights is shared by all UAVs (parameter sharing): the
# $U$ agents are simply $U$ more rows of the same batch. The critic only exists during training,
# so it may look at everything: it reads the global state $s_t$ (all UAVs and all users) and
# estimates the value of the team. Because every agent receives the same team reward and the state
# is the same for all of them, one value per environment step serves all $U$ agents. This is the
# MAPPO recipe (Yu et al., 2022): PPO with a centralised value function.
#
# **One iteration** of the loop:
#
# 1. the phase clock decides the regime $\phi = \lfloor t / L \rfloor \bmod 3$ and tells the
#    environment; at a switch ($t > 0$, $t \bmod L = 0$) the phase controller acts
#    (`on_switch`), then hands out this iteration's learning rates, clip range, KL budget,
#    entropy weight, KL-anchor weight and router temperatures (`begin_iteration`);
# 2. **rollout**: `num_envs` environments advance `rollout_steps` slots with the current policy;
#    we keep observations, global states, actions, log-probabilities, values, team rewards,
#    episode ends and, for gated networks, the random routing choices of every forward pass;
# 3. **advantages** by GAE on the critic's values, bootstrapping through episode *truncations*
#    but not through *terminations*;
# 4. **update**: `update_epochs` passes over the data in `num_minibatches` shuffled minibatches,
#    each a clipped-surrogate policy step plus a value regression, entropy bonus, load-balance
#    loss and (after a switch) the KL anchor; after each epoch the controller may inject noise;
# 5. **logging** of every number the paper's figures need, and a checkpoint from which the run
#    continues bit-for-bit.
#
# Everything in a run follows from one frozen `TrainConfig` and its seed: the same config gives
# the same run, interrupted or not.
#
# ## The run as a tensor axis
#
# A paper-scale comparison is dozens of runs (methods x seeds x ablations), and each run's
# networks are tiny: a PPO minibatch step on 192 agent rows spends most of its time in fixed
# per-call costs, not in arithmetic. So the trainer trains a **population** of R runs in one
# process, the way PureJaxRL vectorises seeds: `train_population(configs, run_dirs)` steps R x B
# environments and updates R networks with one set of tensor operations whose leading axis is the
# run. `train(config, run_dir)` is simply the population of one; there is no second loop.
#
# ```
#                      shared by all members                       per member r (row r of every tensor)
#   phase clock  ──►  set_phase / switch / iteration count     ─►  environments r*B .. r*B+B-1 (own seeds, own streams)
#   method, network kind, sizes, rollout and update settings   ─►  parameters flat[r] (actor, critic), AdamW moments and steps
#                                                               ─►  action / gate noise generator, minibatch permutations
#   one batched matmul per layer over (R, rows, features)      ─►  learning rate, clip, target KL, entropy, temperature,
#   one optimizer step over (R, P)                              ─►  phase-controller state (anchor, noise budget, freeze)
#                                                               ─►  run folder: config, metrics, episodes, checkpoint, done
# ```
#
# Members may differ in their seed, their phase-controller settings (ablation switches, noise
# gamma) and `force_controller`; `check_population` refuses anything else, naming the field.
#
# **Why a member's result does not depend on its neighbours.** Every operation of the loop is
# one of three kinds: elementwise (activations, the optimizer's update, clipping by a per-member
# factor), a reduction within one member's slice (losses, advantage normalisation, gradient norms,
# the KL early stop), or a batched matrix product whose batch entries are computed separately.
# Each member draws its randomness from its own generators, in the order a run alone would, and a
# member that stopped early at its target KL keeps its parameters, moments, step counts and
# random streams untouched while the others continue. One operation did depend on the population:
# torch computes a batched product with a single output column (the value head) through a
# different matrix-vector path for one batch entry than for several, which changed the last bit
# of the values; the value head is therefore a product and a row sum. The tests train the same
# member alone, in populations of two and three, in different orders and next to members with
# other ablations, and compare metrics, episodes and checkpoints bit for bit.
#
# **Devices.** `TrainConfig.device` ("cpu", "cuda" or "auto") places the networks, the buffers and
# the update; the environment stays on the CPU. A CUDA run is not bit-identical to a CPU run, so
# the resolved device is part of the run's identity (its hash).
#
# **What it buys, and where it stops.** `make bench` measures it (figures in the README; the rates
# with the training code of `8ca3ef6`, the profile with the benchmark of `be55e3e`): on one core, a 16-member PE-MAMoE population at the paper preset trains 3,039
# member environment steps per second, 3.7x a lone run, well short of the 10,000 the population
# issue asked for. The same benchmark profiles a 16-member iteration: the matrix products alone
# take 29 % of it, so even with every other cost removed the population could not pass about
# 10,150 steps per second. Going further needs fewer or faster products. The gated networks
# compute all three experts for every row and keep one, because no top-1 formulation has yet kept
# a member's bits independent of its neighbours; and the router and noise-gate products (149
# inputs, 3 outputs) run far below the core's speed, while fusing them into the experts' product
# changes their last bits and with them every cached result.

# %%
#| default_exp mappo

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0
results_dir = "results"

# %%
#| export
import dataclasses
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd
import torch
import torch.nn as nn
import torch.nn.functional as F

from pemamoe.bookkeeping import (  # re-export (public names only): the bookkeeping of appendix 07c
    EpisodeTracker, _Determinism, _decode, _encode, _iteration_row, _member_phases, _merged_phases, _progress_bar,
    RowLog, _torch_save_atomic, _write_parquet_atomic, explained_variance, merge_env_states, split_env_state)
from pemamoe.core import SCALES
from pemamoe.diagnostics import plasticity_diagnostics
from pemamoe.env import EnvConfig, UAVVectorEnv, observation_dim, state_dim, vector_seeds
from pemamoe.methods import METHOD_REGISTRY, method_spec
from pemamoe.nets import (NetConfig, PopulationActor, PopulationCritic, RoutingSample, make_actor, make_critic,
                          routing_noise_std)
from pemamoe.phase_controller import (
    MECHANISMS,
    BaseSchedule,
    PhaseControllerConfig,
)
from pemamoe.population_plasticity import (
    RunAdamW,
    group_index,
    plasticity_method,
)
from pemamoe.phases import PhaseSchedule
from pemamoe.runs import (check_run_dir, load_checkpoint, lock_run, prepare_run_dir, read_config, read_parquet,
                          verify_done, write_done)
# the configuration (appendix 07c): callers import TrainConfig and the presets from here
from pemamoe.train_config import (  # re-export (public names only)
    DEVICES, MEDIUM_PHASE_ITERS, METHODS, PAPER_PHASE_LENGTH, PAPER_UPDATE_EPOCHS, TIMING_COLUMNS, TrainConfig,
    _is_int, _plain, resolve_device, scale_controller)

# %% [markdown]
# ## What the paper fixes, and what we had to choose
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
#
# **Value normalisation.** A slot's team reward is a QoS sum of up to several hundred minus
# energy, collision and overlap penalties, so discounted returns reach the thousands and change
# scale at each phase switch (the class rewards go 5 → 10 → 20). A critic regressing such targets
# directly produces huge value-loss gradients. We use MAPPO's remedy: a running mean and standard
# deviation of the returns (`RunningNorm`, checkpointed with the run); the critic predicts
# normalised values, the rollout de-normalises them for GAE, and the value loss compares
# normalised predictions with normalised targets. Switch it off with `value_norm=False`.
#
# **Separate gradient clipping.** With one optimiser over actor and critic, a single global norm
# clip would let the critic's gradient eat the actor's budget (or the reverse). MAPPO keeps two
# optimisers and clips each; we keep one AdamW (the phase controller needs one optimiser with named
# parameter groups) and clip the two networks' gradients separately, each at `max_grad_norm`.

# %% [markdown]
# ## The configuration
#
# `TrainConfig` holds every number of a run. Four presets come from `TrainConfig.for_scale`:
#
# * **paper**: the training table exactly (10,800 iterations of 2048 environment steps).
# * **small**: the budget of `make figures`: 39 runs (four methods × three seeds, the ablations
#   and the noise sweep); the sweep took 18 min 34 s on two cores with two worker processes
#   (measured at `dc5e4d6`, README).
#   The rollout shrinks to 16 environments × 32 slots (512 environment steps), each phase lasts
#   60 iterations (540 iterations, 276k environment steps in all) and the update runs 4 epochs of
#   4 minibatches. What a run costs is measured by `make bench` (`benchmarks/bench_train.py`),
#   which prints the throughput of populations of 1, 4 and 16 runs and the projected sweep times;
#   the README quotes its latest figures with the commit that measured them.
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
#   its two-hour budget (README); two cycles still show every switch the paper is about: each phase
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
# The code behind these presets, and `TrainConfig` itself (its fields and their checks, `to_dict`
# and `from_dict` for `config.json`, the identity and hash that name a run's folder), is in the
# appendix notebook 07c (`pemamoe.train_config`); this notebook's module imports it from there and
# re-exports it.

# %% [markdown]
# The presets side by side (the columns that differ, and the rescaled controller windows):

# %%
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
# ## The phase clock
#
# The trainer owns the phase: iteration $t$ runs in phase $\lfloor t/L \rfloor \bmod 3$, and a
# switch happens at every $t > 0$ with $t \bmod L = 0$ (Algorithm 1's "iteration mod L"). The
# same `PhaseSchedule` object of notebook 03 drives the stand-alone environment's own step clock,
# here counted in iterations instead of slots. The environment is built with
# `phase_clock="external"` and told the phase with `set_phase` before each rollout; the phase
# index never enters an observation.

# %%
#| export
def phase_schedule(config: TrainConfig) -> PhaseSchedule:
    """The iteration-counted phase clock of a run."""
    return PhaseSchedule(period=config.phase_length_iters, n_phases=config.n_phases)

# %% [markdown]
# ## GAE, truncation and termination
#
# With values $V(s_t)$ from the critic, the one-step TD error is
# $$\delta_t = r_t + \gamma\, \hat V_{t+1} - V(s_t),$$
# where $\hat V_{t+1}$ is the value of *what follows* step $t$:
#
# * inside an episode: $V(s_{t+1})$, the next stored value (or, after the last rollout step,
#   the value of the state the next rollout will start from);
# * when the episode was **truncated** at the 32-slot limit: the value of the final state
#   $s^{\text{final}}$ that the environment returned before resetting. The task itself does
#   not end there, we only stop simulating, so the future still counts;
# * when the episode **terminated** (a UAV's battery ran out): $0$; nothing follows.
#
# GAE then sums the TD errors with weights $(\gamma\lambda)^k$ and stops at every episode end:
# $$A_t = \delta_t + \gamma\lambda\,(1 - d_t)\,A_{t+1}, \qquad \hat R_t = A_t + V(s_t),$$
# with $d_t = 1$ when the episode ended at step $t$ (either way). The vectorised environment
# resets finished episodes inside `step`, so the observation it returns after an ending already
# belongs to the next episode; the final state is in `info["final_state"]`, and that is what the
# truncation bootstrap evaluates. (The global state carries the elapsed fraction of the
# episode, so $s^{\text{final}}$ shows a time feature of 1, a value the critic never trains on: the
# bootstrap extrapolates slightly. This is the paper's choice and the usual one.)

# %%
#| export
def bootstrap_values(values, last_value, dones, final_values):
    """The value that follows each step, (T, B).

    values (T, B): V(s_t); last_value (B,): V of the state after the last step;
    dones (T, B): 1 where the episode ended at step t; final_values (T, B): the value used at an
    ending (V(final state) on truncation, 0 on termination), ignored elsewhere.
    """
    values = torch.as_tensor(values, dtype=torch.float64)
    following = torch.cat([values[1:], torch.as_tensor(last_value, dtype=torch.float64)[None]], 0)
    dones = torch.as_tensor(dones, dtype=torch.bool)
    return torch.where(dones, torch.as_tensor(final_values, dtype=torch.float64), following)


def compute_gae(rewards, values, next_values, dones, gamma: float, gae_lambda: float):
    """Generalised advantage estimates over the leading time axis.

    rewards, values, next_values, dones: (T, ...). next_values from `bootstrap_values`.
    Returns (advantages, returns), float64 tensors of the same shape; returns = advantages + values.
    """
    rewards = torch.as_tensor(rewards, dtype=torch.float64)
    values = torch.as_tensor(values, dtype=torch.float64)
    next_values = torch.as_tensor(next_values, dtype=torch.float64)
    keep = 1.0 - torch.as_tensor(dones, dtype=torch.float64)
    delta = rewards + gamma * next_values - values
    adv = torch.zeros_like(values)
    last = torch.zeros_like(values[0])
    for t in reversed(range(values.shape[0])):
        last = delta[t] + gamma * gae_lambda * keep[t] * last
        adv[t] = last
    return adv, adv + values

# %% [markdown]
# A hand-computed check with one environment, $\gamma = 0.9$, $\lambda = 0.5$: three steps where
# the episode is truncated after step 0 (bootstrap value 10) and terminated after step 2.

# %%
_r = torch.tensor([[1.0], [2.0], [3.0]])
_v = torch.tensor([[0.5], [1.0], [2.0]])
_d = torch.tensor([[1.0], [0.0], [1.0]])
_final = torch.tensor([[10.0], [0.0], [0.0]])  # V(final state) on the truncation; 0 on termination
_nv = bootstrap_values(_v, torch.tensor([99.0]), _d, _final)
_adv, _ret = compute_gae(_r, _v, _nv, _d, gamma=0.9, gae_lambda=0.5)
# step 2: 3 + 0 - 2 = 1; step 1: (2 + 0.9*2 - 1) + 0.45*1 = 3.25; step 0: 1 + 0.9*10 - 0.5 = 9.5
assert torch.allclose(_adv.squeeze(), torch.tensor([9.5, 3.25, 1.0], dtype=torch.float64))
_adv.squeeze().tolist()

# %% [markdown]
# ## Value normalisation
#
# `RunningNorm` keeps the count, mean and variance of every return it has seen (the parallel
# Welford update of Chan et al., in float64). Before each update it absorbs the new batch of
# returns; the critic then regresses $(\hat R - \mu)/\sigma$ and the rollout reads values back as
# $\mu + \sigma\,\hat v$. With `value_norm=False` it is the identity.

# %%
#| export
class RunningNorm:
    """Running mean / variance of scalar targets (float64); identity when enabled=False."""

    def __init__(self, enabled: bool = True, eps: float = 1e-8):
        self.enabled, self.eps = bool(enabled), float(eps)
        self.count, self.mean, self.var = 0.0, 0.0, 1.0

    @property
    def std(self) -> float:
        return math.sqrt(self.var + self.eps) if self.enabled and self.count > 0 else 1.0

    def _mean(self) -> float:
        return self.mean if self.enabled and self.count > 0 else 0.0

    def update(self, x) -> None:
        if not self.enabled:
            return
        x = torch.as_tensor(x, dtype=torch.float64).reshape(-1)
        n, m, v = float(x.numel()), float(x.mean()), float(x.var(unbiased=False))
        if self.count == 0:
            self.count, self.mean, self.var = n, m, v
            return
        tot = self.count + n
        delta = m - self.mean
        self.mean += delta * n / tot
        self.var = (self.var * self.count + v * n + delta**2 * self.count * n / tot) / tot
        self.count = tot

    def normalize(self, x):
        return (x - self._mean()) / self.std

    def denormalize(self, x):
        return x * self.std + self._mean()

    def state_dict(self) -> dict:
        return {"enabled": self.enabled, "count": self.count, "mean": self.mean, "var": self.var}

    def load_state_dict(self, state: dict) -> None:
        self.enabled = bool(state["enabled"])
        self.count, self.mean, self.var = float(state["count"]), float(state["mean"]), float(state["var"])

# %% [markdown]
# ## Rollout
#
# The shared actor sees the $B\cdot U$ agent rows of a step as one batch. For gated actors
# `act` returns a `RoutingSample` (the gate noise, the chosen experts and the temperature); we
# keep it so that the update can *replay* the same routing: PPO's ratio
# $\pi_\theta(a|o)/\pi_{\text{old}}(a|o)$ only means something if numerator and denominator route
# the observation through the same experts. The critic's routing is stored too, for the same
# reason. Actions are stored unclipped (the log-probability belongs to the sampled Gaussian
# action); the environment clips them to $[-1, 1]^2$ and reports it in `info`.
#
# `EpisodeTracker` (appendix 07c) accumulates each environment's running episode (team return and
# the system metrics) and emits one row per finished episode.

# %%
#| export
_STEP_KEYS = ("reward", "qos", "energy", "collision", "overlap", "collisions", "coverage", "served_users",
              "admitted_users", "uav_using_rate", "energy_rate_kj")
_AGENT_FLAGS = ("action_clipped", "move_infeasible", "battery_depleted")


class Rollout(NamedTuple):
    """One iteration's data of a population; leading axes (R, T, B) = (members, rollout_steps, num_envs)."""

    obs: torch.Tensor  # (R, T, B, U, obs_dim)
    states: torch.Tensor  # (R, T, B, state_dim)
    actions: torch.Tensor  # (R, T, B, U, act_dim), unclipped samples
    logprobs: torch.Tensor  # (R, T, B, U)
    values: torch.Tensor  # (R, T, B) V(s_t), de-normalised, float64
    rewards: torch.Tensor  # (R, T, B) team reward, float64
    dones: torch.Tensor  # (R, T, B) the episode ended at step t (terminated or truncated)
    next_values: torch.Tensor  # (R, T, B) value that follows step t (see bootstrap_values)
    actor_routing: RoutingSample | None  # leading (R, T, B, U)


def _member_view(x, R: int):
    """(R*B, ...) numpy -> (R, B, ...) tensor (a view)."""
    t = torch.from_numpy(x)
    return t.reshape(R, t.shape[0] // R, *t.shape[1:])


@torch.no_grad()
def collect_rollout(venv, actor, critic, norms: "ValueNorms", obs, state, steps: int, sched, tracker: EpisodeTracker,
                    iteration: int, generators, device=None, noise_std=None):
    """Run `steps` slots of every environment of a population of R = actor.R members.

    venv holds R*B environments, member r's in rows r*B..(r+1)*B-1. Values come from the critic
    with noiseless gating (they enter GAE; see above). Returns (Rollout, next obs, next state,
    per-member step statistics {key: (R,) array}, per-member lists of finished-episode rows).
    """
    R, U = actor.R, venv.n_agents
    B = venv.num_envs // R
    device = device or actor.flat.device
    tau_pi, tau_v = sched.policy_temperature.to(device), sched.value_temperature.to(device)
    buf = {k: [] for k in ("obs", "states", "actions", "logprobs", "values", "rewards", "dones", "final")}
    routes, episode_rows = [], [[] for _ in range(R)]
    step_sums = {k: np.zeros(R) for k in _STEP_KEYS + _AGENT_FLAGS}
    for _ in range(steps):
        o, s = _member_view(obs, R), _member_view(state, R)
        od, sd = o.to(device), s.to(device)
        action, logp, routing = actor.act(od.reshape(R, B * U, -1), tau_pi, generators, noise_std=noise_std)
        v, _, _ = critic(sd, tau_v)
        obs, state, reward, terminated, truncated, info = venv.step(action.reshape(R * B, U, -1).cpu().numpy())
        done = terminated | truncated
        final = torch.zeros(R * B, dtype=torch.float64)
        boot = truncated & ~terminated
        if boot.any():  # V(final state) for truncated episodes, every member's rows at once
            rows = np.asarray(info["final_rows"])
            fs = np.zeros_like(state)
            fs[rows] = np.asarray(info["final_state"])
            fv, _, _ = critic(_member_view(fs, R).to(device), tau_v)
            fv = norms.denormalize(fv.double().cpu()).reshape(-1)
            pick = rows[boot[rows]]
            final[pick] = fv[pick]
        buf["obs"].append(o), buf["states"].append(s)
        buf["actions"].append(action.reshape(R, B, U, -1)), buf["logprobs"].append(logp.reshape(R, B, U))
        buf["values"].append(norms.denormalize(v.double().cpu()))
        buf["rewards"].append(torch.as_tensor(reward, dtype=torch.float64).reshape(R, B))
        buf["dones"].append(torch.as_tensor(done).reshape(R, B)), buf["final"].append(final.reshape(R, B))
        if routing is not None:
            routes.append(routing.reshape(R, 1, B, U))
        for k in _STEP_KEYS + _AGENT_FLAGS:
            step_sums[k] += np.asarray(info[k], dtype=float).reshape(R, -1).mean(axis=1)
        finished = tracker.update_members(np.asarray(reward, dtype=float), info, terminated, truncated, iteration)
        for r in range(R):
            episode_rows[r] += finished[r]
    last_v, _, _ = critic(_member_view(state, R).to(device), tau_v)

    def stack(name, dev=None):
        t = torch.stack(buf[name], 1)
        return t if dev is None else t.to(dev)

    values, dones = stack("values"), stack("dones")
    next_values = bootstrap_values(values.transpose(0, 1), norms.denormalize(last_v.double().cpu()),
                                   dones.transpose(0, 1), stack("final").transpose(0, 1)).transpose(0, 1)
    rollout = Rollout(
        obs=stack("obs", device), states=stack("states", device), actions=stack("actions"), logprobs=stack("logprobs"),
        values=values, rewards=stack("rewards"), dones=dones, next_values=next_values,
        actor_routing=RoutingSample.cat(routes, dim=1) if routes else None,
    )
    stats = {f"step/{k}": v / steps for k, v in step_sums.items()}
    stats.update(actor.routing_readings(rollout.obs, rollout.actor_routing, rollout.dones, noise_std))
    return rollout, obs, state, stats, episode_rows


# %% [markdown]
# ## The update: clipped surrogate, value regression, per-minibatch KL stop
#
# For an agent row with stored action $a$, behaviour log-probability $\log\pi_{\text{old}}(a|o)$
# and advantage $A$ (the team advantage of its environment step, normalised per minibatch), the
# policy loss is PPO's pessimistic bound
# $$\mathcal L_\text{PPO} = \mathbb E\big[\max\big(-A\,\rho,\; -A\,\operatorname{clip}(\rho, 1-\epsilon, 1+\epsilon)\big)\big],
# \qquad \rho = \exp\big(\log\pi_\theta(a|o) - \log\pi_\text{old}(a|o)\big),$$
# with $\epsilon$ the controller's clip range of this iteration (0.15, or 0.10 in PE-MAMoE's
# conservative window). $\log\pi_\theta$ comes from `actor.evaluate` with the stored routing and
# temperature replayed, so before the first gradient step $\rho = 1$ *exactly* (the tests check
# this bit for bit for every method). The full loss of a minibatch is
# $$\mathcal L = \mathcal L_\text{PPO} + \lambda_V\,\mathbb E[(\hat v_\psi(s) - \tilde R)^2]
#   - \lambda_\text{ent}\,\mathbb E[\mathcal H(\pi_\theta)] + \lambda_\text{kl}\,\mathbb E[\mathrm{KL}(\pi_\theta\|\pi_\text{ref})]
#   + c_\text{lb}\,(\text{load balance of actor and critic}),$$
# where $\tilde R$ is the normalised return, $\lambda_\text{ent}$ and $\lambda_\text{kl}$ come from
# the controller (the KL term is zero for the baselines and once the anchor is released), and the
# load-balance term is zero for the MLP.
#
# **Minibatches** are drawn over *environment steps*: a permutation of the $T\cdot B$ steps is
# cut into `num_minibatches` pieces, and a piece brings all $U$ agent rows of its steps to the
# actor and its $T\cdot B/M$ global states to the critic. Since all agents share one state value
# and one advantage, this is the same estimator as shuffling agent rows, without evaluating each
# state $U$ times.
#
# **Per-minibatch KL stop.** Before each gradient step we estimate the KL between the behaviour
# policy and the current one on the minibatch with CleanRL's low-variance estimator
# $\widehat{\mathrm{KL}} = \mathbb E[(\rho - 1) - \log\rho]$; once it exceeds the iteration's
# target KL, the update stops (that minibatch gets no step, and no further epoch runs), as in
# Stable-Baselines3. CleanRL checks the same quantity only at epoch ends; checking every minibatch
# keeps the policy inside the trust region at a finer grain.
#
# **Parameter groups.** The optimiser has five named groups, `router`, `experts`, `head`,
# `log_std` (actor) and `critic`, built by `build_param_groups`. The phase controller sets each
# group's learning rate every iteration (the LR drop and warm-up after a switch, learning rate 0 for
# the router while it is frozen), clears Adam's moments at a switch, and perturbs the expert
# group's weights; the trainer never touches a learning rate itself (except for the optional
# `anneal_lr` factor). **Where the controller enters an iteration:** `on_switch(t)` before the
# rollout at a switch, `begin_iteration(t)` for the iteration's settings, `kl_penalty` inside every
# minibatch loss, and `after_epoch(selected experts)` after each update epoch. A plasticity method
# may also keep rows of each rollout for its next switch (`observe_rollout`, appendix 06b) and add
# columns of its own to the log row (`metrics`); nothing else.

# %%
#| export
class ValueNorms:
    """One RunningNorm per member, applied to (R, ...) tensors (member on the leading axis)."""

    def __init__(self, configs):
        self.norms = [RunningNorm(c.value_norm) for c in configs]

    def _column(self, values, like):
        t = torch.tensor(values, dtype=torch.float64)
        return t.reshape(-1, *([1] * (like.ndim - 1)))

    def normalize(self, x):
        return (x - self._column([n._mean() for n in self.norms], x)) / self._column([n.std for n in self.norms], x)

    def denormalize(self, x):
        return x * self._column([n.std for n in self.norms], x) + self._column([n._mean() for n in self.norms], x)

    def update(self, returns) -> None:
        """returns (R, ...): each member's norm sees its own slice."""
        for r, n in enumerate(self.norms):
            n.update(returns[r])


_UPDATE_STATS = ("policy_loss", "value_loss", "entropy", "kl_ref", "load_balance", "critic_load_balance",
                 "approx_kl", "clip_frac", "grad_norm_actor", "grad_norm_critic")


def _clip_rows(grad: torch.Tensor, max_norm: float) -> torch.Tensor:
    """Clip each member's gradient row to norm max_norm (torch's clip_grad_norm_ rule); returns
    the norms before clipping, (R,)."""
    norm = torch.linalg.vector_norm(grad, dim=1)
    grad.mul_((max_norm / (norm + 1e-6)).clamp(max=1.0).unsqueeze(1))
    return norm


def _take_flat(x, flat_idx, R: int):
    """x (R*N, ...) flattened over (member, step), flat_idx (R*m,) = r*N + step -> (R, m, ...)."""
    return x.index_select(0, flat_idx).reshape(R, -1, *x.shape[1:])


def ppo_update(actor, critic, actor_opt, critic_opt, plasticity, sched, data: dict, norms: ValueNorms,
               config, rngs, frozen_groups=None) -> dict:
    """`update_epochs` x `num_minibatches` PPO steps for every member of a population at once.

    data (member axis R, then N = T*B environment steps): obs (R, N, U, obs_dim), actions
    (R, N, U, A), logprobs (R, N, U), advantages (R, N), returns (R, N), values (R, N)
    de-normalised, states (R, N, S), actor_routing (leading (R, N, U)) or None.
    Each member stops at its own target KL (its later minibatches leave it untouched, bit for
    bit); statistics are summed as tensors and read once, at the end. Returns {stat: (R,) list}.
    """
    obs, actions, old_logp = data["obs"], data["actions"], data["logprobs"]
    R, N, U, obs_dim = obs.shape
    act_dim = actions.shape[-1]
    device = actor.flat.device
    mb = N // config.num_minibatches
    rows = torch.arange(R, device=device).unsqueeze(1)
    target = norms.normalize(data["returns"]).float().to(device)
    old_v = norms.normalize(data["values"]).float().to(device)
    adv_all = data["advantages"].float().to(device)
    actions, old_logp, states = actions.to(device), old_logp.to(device), data["states"].to(device)
    route = data["actor_routing"]
    per_step = [obs, actions, old_logp, adv_all, states, target, old_v]  # (R, N, ...) each
    if route is not None:
        per_step += [route.noise, route.experts, route.temperature]
    per_step = [x.reshape(R * N, *x.shape[2:]) for x in per_step]
    offsets = torch.arange(R, device=device).unsqueeze(1) * N
    clip = sched.clip_coef.to(device).unsqueeze(1)
    target_kl, ent_coef = sched.target_kl.to(device), sched.ent_coef.to(device)
    tau_v = sched.value_temperature.to(device)
    lr_a, lr_c = sched.lr_actor.to(device), sched.lr_critic.to(device)
    frozen_rows = None
    if frozen_groups is not None:
        frozen_rows = frozen_groups.index_select(1, actor_opt.group_of)  # (R, P) True where frozen
    sums = torch.zeros(len(_UPDATE_STATS), R, dtype=torch.float64, device=device)  # rows in _UPDATE_STATS order
    no_kl = torch.zeros(R, device=device)  # kl_ref when the plasticity adds none (sums stay 0, as before)
    steps = torch.zeros(R, dtype=torch.long, device=device)
    stopped = torch.zeros(R, dtype=torch.bool, device=device)
    early_stop_epoch = torch.full((R,), -1, dtype=torch.long, device=device)
    first_ratio_dev = None
    noised = [0] * R
    sparse = actor.gated and actor.k < actor.n_experts
    for epoch in range(config.update_epochs):
        live = (~stopped).tolist()  # one host sync per epoch: stopped members draw no permutation
        perm = torch.from_numpy(np.stack([rngs[r].permutation(N) if live[r] else np.arange(N) for r in range(R)]))
        perm = perm.to(device)
        counts = torch.zeros(R, actor.n_experts, device=device) if sparse else None
        stepped_epoch = torch.zeros(R, dtype=torch.bool, device=device)
        flat_perm = perm + offsets  # rows of the (R*N, ...) flattened per-step tensors
        for k in range(config.num_minibatches):
            # one index_select per tensor on its flattened (R*N, ...) view: the same numbers as
            # x[rows, idx], through a cheaper kernel (contiguous, cache-warm minibatch copies)
            fi = flat_perm[:, k * mb:(k + 1) * mb].reshape(-1)
            o_p, a_p, lp_p, adv_p, st_p, tg_p, ov_p, *r_p = [_take_flat(x, fi, R) for x in per_step]
            o = o_p.reshape(R, mb * U, obs_dim)
            a = a_p.reshape(R, mb * U, act_dim)
            r_sel = None if route is None else RoutingSample(
                r_p[0].reshape(R, mb * U, -1), r_p[1].reshape(R, mb * U, -1), r_p[2].reshape(R, mb * U))
            new_logp, entropy, lb, mean, log_std, chosen = actor.evaluate(o, a, r_sel)
            logratio = new_logp - lp_p.reshape(R, mb * U)
            ratio = logratio.exp()
            with torch.no_grad():
                approx_kl = ((ratio - 1) - logratio).mean(1)
                clip_frac = ((ratio - 1.0).abs() > clip).float().mean(1)
                if first_ratio_dev is None:
                    first_ratio_dev = (ratio - 1.0).abs().amax(1)
                over = approx_kl > target_kl
                early_stop_epoch = torch.where(over & ~stopped, epoch, early_stop_epoch)
                stopped = stopped | over
                stepping = ~stopped
            mb_adv = adv_p.unsqueeze(2).expand(R, mb, U).reshape(R, mb * U)
            if config.norm_adv:
                mb_adv = (mb_adv - mb_adv.mean(1, keepdim=True)) / (mb_adv.std(1, keepdim=True) + 1e-8)
            pg_loss = torch.max(-mb_adv * ratio, -mb_adv * torch.clamp(ratio, 1 - clip, 1 + clip)).mean(1)

            v, c_lb, _ = critic(st_p, tau_v)
            t_mb = tg_p
            if config.clip_vloss:
                ov = ov_p
                v_clipped = ov + torch.clamp(v - ov, -clip, clip)
                v_loss = torch.max((v - t_mb) ** 2, (v_clipped - t_mb) ** 2).mean(1)
            else:
                v_loss = ((v - t_mb) ** 2).mean(1)
            kl_ref = plasticity.extra_loss({"obs": o, "tau": None if r_sel is None else r_sel.temperature,
                                            "noise": None if r_sel is None else r_sel.noise,
                                            "experts": chosen if sparse else None, "mean": mean, "log_std": log_std})
            loss = (pg_loss + config.vf_coef * v_loss - ent_coef * entropy
                    + actor.lb_coef * lb + critic.lb_coef * c_lb)
            if kl_ref is not None:
                loss = loss + kl_ref
            (loss * stepping.to(loss.dtype)).sum().backward()
            with torch.no_grad():
                if frozen_rows is not None:
                    actor.flat.grad.masked_fill_(frozen_rows, 0.0)
                gn_a = _clip_rows(actor.flat.grad, config.max_grad_norm)
                gn_c = _clip_rows(critic.flat.grad, config.max_grad_norm)
            actor_opt.step(lr_a, stepping, frozen_groups)
            critic_opt.step(lr_c, stepping)
            plasticity.after_minibatch(stepping)
            with torch.no_grad():
                steps += stepping.long()
                stepped_epoch |= stepping
                # the ten statistics in one (10, R) accumulation, each element as `sum += value * w`
                stat = torch.stack([pg_loss, v_loss, entropy, no_kl if kl_ref is None else kl_ref, lb, c_lb,
                                    approx_kl, clip_frac, gn_a, gn_c]).double()
                sums.add_(stat * stepping.to(torch.float64))
                if counts is not None:
                    counts += F.one_hot(chosen.reshape(R, -1), actor.n_experts).sum(1).float() * stepping.unsqueeze(1)
        for r, n in enumerate(plasticity.after_epoch(counts, stepped_epoch)):
            noised[r] += n
        if bool(stopped.all()):
            break
    n_steps = steps.double().clamp(min=1)
    means = torch.where(steps > 0, sums / n_steps, torch.nan).tolist()
    out = dict(zip(_UPDATE_STATS, means))
    out.update(early_stop_epoch=early_stop_epoch.tolist(), gradient_steps=steps.tolist(),
               first_ratio_dev=first_ratio_dev.double().tolist(), noised_experts=noised)
    return out

# %% [markdown]
# ## Probe batch, checkpoints and the training loop
#
# The plasticity diagnostics of appendix 06b need a **fixed** probe batch, so that a change in
# expert rank or dormant fraction reflects the network and not the data. `collect_probe` draws it
# once per run from a separate copy of the environment (its own seed, random actions, a third of
# the rows from each phase); it depends only on the config, so a resumed run rebuilds the same one.
#
# A **checkpoint** holds everything the next iteration reads (both networks, the optimiser's
# moments and step counts, the return normaliser, the phase controller, the random states, the
# environments' complete state, the current observations, the running episodes and the log rows
# so far), so a run resumed from it continues bit for bit. How a checkpoint is encoded, the run
# folder's files and the columns of the per-iteration log row are in appendix 07c; how a folder is
# locked, sealed and checked before it is trusted, in appendix 07b.

# %%
#| export
def collect_probe(config: TrainConfig, steps_per_phase: int | None = None):
    """Fixed probe batch for the diagnostics: (probe_obs (P, obs_dim), probe_state (Q, state_dim)).

    Random-action rollouts of a separate 8-environment copy (seed + 1_000_003), a third of the
    steps in each phase; P = probe_size agent rows, Q = min(probe_size, steps) global states.
    """
    env_cfg = config.env_config()
    n_env = 8
    venv = UAVVectorEnv(n_env, config.seed + 1_000_003, cfg=env_cfg)
    rng = np.random.default_rng(config.seed + 1_000_003)
    per_phase = math.ceil(config.probe_size / config.n_phases)
    steps = steps_per_phase or max(1, math.ceil(per_phase / (n_env * venv.n_agents)))
    obs_rows, state_rows = [], []
    for phase in range(config.n_phases):
        venv.set_phase(phase)
        venv.reset()
        for _ in range(steps):
            obs, state, *_ = venv.step(rng.uniform(-1, 1, size=(n_env, venv.n_agents, 2)))
            obs_rows.append(obs.reshape(-1, venv.obs_dim)), state_rows.append(state)
    obs_all, state_all = np.concatenate(obs_rows), np.concatenate(state_rows)
    pick_o = np.sort(rng.permutation(len(obs_all))[:config.probe_size])
    pick_s = np.sort(rng.permutation(len(state_all))[:min(config.probe_size, len(state_all))])
    return torch.from_numpy(obs_all[pick_o].copy()), torch.from_numpy(state_all[pick_s].copy())


@dataclass
class RunResult:
    """What `train` returns (also rebuilt from a finished run directory by `load_run`)."""

    config: TrainConfig
    metrics: pd.DataFrame  # one row per iteration
    episodes: pd.DataFrame  # one row per finished training episode
    actor: nn.Module
    critic: nn.Module
    run_dir: Path | None = None
    finished: bool = True  # False when stopped early by max_iterations
    resumed_from: int | None = None  # iteration the run continued from, if it resumed
    from_cache: bool = False  # True when done.json was found and nothing was recomputed


def _build(config: TrainConfig, obs_dim: int, state_dim: int):
    """One member's single-run actor and critic, initialised from its seed alone."""
    torch.manual_seed(config.seed)
    kind = config.method_spec().network
    return make_actor(kind, obs_dim, 2, config.net), make_critic(kind, state_dim, config.net)


def load_run(run_dir) -> RunResult:
    """The stored result of a run directory (metrics, episodes, networks from the last checkpoint).
    finished is True only when done.json verifies (pemamoe.runs.verify_done; a bad one raises)."""
    run_dir = check_run_dir(run_dir)
    config = read_config(run_dir / "config.json", TrainConfig)
    done = verify_done(run_dir, config)
    ckpt = load_checkpoint(run_dir / "checkpoint.pt", config, iteration=config.iterations if done else None,
                           resuming=done is None)
    env_cfg = config.env_config()
    actor, critic = _build(config, observation_dim(env_cfg), state_dim(env_cfg))
    actor.load_state_dict(ckpt["actor"])
    critic.load_state_dict(ckpt["critic"])
    return RunResult(config, read_parquet(run_dir / "metrics.parquet"), read_parquet(run_dir / "episodes.parquet"),
                     actor, critic, run_dir, finished=done is not None, from_cache=True)


# Fields that members of one population may set differently; every other field is shared.
# (fixed_phase: members may sit in different fixed phases, but either all cycle or none does.)
MEMBER_FIELDS = ("seed", "controller", "force_controller", "fixed_phase")


def population_key(config: TrainConfig) -> str:
    """What members of one population must share: the run identity without MEMBER_FIELDS."""
    ident = {k: v for k, v in config.identity().items() if k not in MEMBER_FIELDS}
    ident["phase_fixed"] = config.fixed_phase is not None
    return json.dumps(ident, sort_keys=True, separators=(",", ":"))


def check_population(configs) -> None:
    """Raise ValueError naming the first field on which two members disagree in a shared setting."""
    if not configs:
        raise ValueError("a population needs at least one TrainConfig")
    for c in configs:
        if not isinstance(c, TrainConfig):
            raise ValueError(f"population members must be TrainConfig objects, got {type(c).__name__}")
    ref = configs[0].identity()
    for c in configs[1:]:
        other = c.identity()
        for key in sorted(set(ref) | set(other)):
            if key in MEMBER_FIELDS:
                continue
            if ref.get(key) != other.get(key):
                raise ValueError(f"population members must share {key!r}: {ref.get(key)!r} (seed {configs[0].seed}) "
                                 f"vs {other.get(key)!r} (seed {c.seed}); members may differ only in "
                                 f"{', '.join(MEMBER_FIELDS)}")
    fixed = {c.fixed_phase is not None for c in configs}
    if len(fixed) > 1:
        raise ValueError("population members must share whether 'fixed_phase' is set: members with a fixed "
                         "phase cannot train next to members whose phases cycle")
    names = {plasticity_name(c) for c in configs}
    if len(names - {"none", "phase_controller"}) > 0 and len(names) > 1:
        raise ValueError(f"population members must share one plasticity method, got {sorted(names)}")


def plasticity_name(config: TrainConfig) -> str:
    spec = config.method_spec()
    return "phase_controller" if (config.force_controller and spec.plasticity == "none") else spec.plasticity



# %% [markdown]
# ### `train`
#
# The loop below is the whole algorithm; read it top to bottom. `max_iterations` stops a run
# early with a checkpoint (it simulates an interruption; `train(..., resume=True)` continues it).

# %%
#| export
def train(config: TrainConfig, run_dir=None, resume: bool = True, *, max_iterations: int | None = None,
          threads: int | None = 1, verbose: bool = False, progress: bool | None = None,
          deadline: float | None = None) -> RunResult:
    """Run MAPPO for `config`: the population of one (see `train_population`).

    run_dir: where config.json, metrics.parquet, episodes.parquet, checkpoint.pt and done.json go
    (None: nothing is written). resume: continue from run_dir's checkpoint (or return the stored
    result when done.json exists). max_iterations: stop after this many iterations in total,
    checkpointing, without done.json. threads: torch threads during the run (restored after).
    progress: a progress bar (None: only when stderr is a terminal). deadline: a `time.time()` after
    which the run checkpoints at the end of its current iteration and stops (finished False).
    """
    return train_population([config], None if run_dir is None else [run_dir], resume, max_iterations=max_iterations,
                            threads=threads, verbose=verbose, progress=progress, deadline=deadline)[0]


def train_population(configs: list, run_dirs: list | None = None, resume: bool = True, *,
                     max_iterations: int | None = None, threads: int | None = 1, verbose: bool = False,
                     progress: bool | None = None, deadline: float | None = None) -> list:
    """Train R runs in one process as one population (the run is a tensor axis).

    configs: TrainConfigs that differ only in MEMBER_FIELDS (seed, controller settings such as
    ablation switches and noise gamma, force_controller). run_dirs: one folder per member (or
    None). Every member's result is bit-identical to training its config alone: same files, same
    metrics. Members with a finished folder are read back. Members whose checkpoints stopped at
    different iterations start as sub-populations: the one furthest behind trains up to the next
    one's iteration, checkpoints, and joins it (a killed sweep resumes as one population again,
    not as a queue of small ones; this needs the lagging members' folders, so with run_dir None
    they train to the end first). deadline: a `time.time()` at which training stops at the end of
    the current iteration with a checkpoint of every member (a resume continues bit for bit);
    members that had not started by then are None. Returns one RunResult per config.
    """
    configs = list(configs)
    check_population(configs)
    if threads is not None and (not _is_int(threads) or threads < 1):
        raise ValueError(f"train: threads must be an int >= 1 or None, got {threads!r}")
    if max_iterations is not None and (not _is_int(max_iterations) or max_iterations < 1):
        raise ValueError(f"train: max_iterations must be an int >= 1 or None, got {max_iterations!r}")
    if run_dirs is not None and len(run_dirs) != len(configs):
        raise ValueError(f"run_dirs has {len(run_dirs)} entries for {len(configs)} configs")
    dirs = [None if d is None else check_run_dir(d) for d in (run_dirs or [None] * len(configs))]
    named = [d.resolve() for d in dirs if d is not None]
    if len(set(named)) != len(named):
        raise ValueError("two members of a population share one run_dir")
    results, pending, locks = [None] * len(configs), {}, []
    try:
        for r, (config, run_dir) in enumerate(zip(configs, dirs)):
            ckpt = None
            if run_dir is not None:
                if resume and verify_done(run_dir, config):  # a finished run is read without the lock
                    results[r] = dataclasses.replace(load_run(run_dir), config=config)
                    continue
                locks.append(lock_run(run_dir))  # one writer per folder, for the member's whole run
                prepare_run_dir(run_dir, config, resume)
                if resume and verify_done(run_dir, config):  # finished between the check and the lock
                    results[r] = dataclasses.replace(load_run(run_dir), config=config)
                    continue
                path = run_dir / "checkpoint.pt"
                if resume and path.exists():
                    ckpt = load_checkpoint(path, config)  # refuses another run's checkpoint, names a torn one
            start = 0 if ckpt is None else int(ckpt["iteration"])
            pending.setdefault(start, []).append((r, ckpt))
        first_start = {r: start for start, members in pending.items() for r, _ in members}
        with _Determinism(threads):
            while pending:
                start = min(pending)
                members = pending.pop(start)
                # Catch up with the next sub-population, then train as one (members are independent
                # of their neighbours, so this changes no bit). Needs every member's folder to reload.
                catch_up = bool(pending) and all(dirs[r] is not None for r, _ in members)
                after = min(pending) if catch_up else None
                stop = max_iterations if after is None else min(after, max_iterations or after)
                group = _train_group([configs[r] for r, _ in members], [dirs[r] for r, _ in members],
                                     [ck for _, ck in members], stop, verbose, progress, deadline)
                if deadline is not None and time.time() >= deadline:  # out of time: start nothing more
                    for (r, _), res in zip(members, group):
                        results[r] = dataclasses.replace(res, resumed_from=first_start[r] or None)
                    break
                if catch_up and stop == after and stop < configs[members[0][0]].iterations:
                    joined = [(r, load_checkpoint(dirs[r] / "checkpoint.pt", configs[r])) for r, _ in members]
                    pending[stop] = sorted(pending[stop] + joined, key=lambda m: m[0])
                    continue
                for (r, _), res in zip(members, group):
                    results[r] = dataclasses.replace(res, resumed_from=first_start[r] or None)
    finally:
        for lock in locks:
            lock.release()
    return results


def _train_group(configs: list, run_dirs: list, ckpts: list, max_iterations, verbose, progress, deadline=None) -> list:
    """The training loop for members that start at the same iteration (read top to bottom)."""
    wall_start = time.perf_counter()
    c0, R = configs[0], len(configs)
    device = resolve_device(c0.device)
    # --- construction: every member from its own config and seed ----------------------------------
    env_cfg = c0.env_config()
    B = c0.num_envs
    venv = UAVVectorEnv(seeds=[s for c in configs for s in vector_seeds(c.seed, B)], cfg=env_cfg)
    U = venv.n_agents
    singles = [_build(c, venv.obs_dim, venv.state_dim) for c in configs]
    actor = PopulationActor([a for a, _ in singles]).to(device)
    critic = PopulationCritic([c for _, c in singles]).to(device)
    group_of, group_names = group_index(singles[0][0], actor.layout)
    actor_opt = RunAdamW(actor.flat, group_of, len(group_names), c0.adam_betas, c0.adam_eps, c0.weight_decay)
    critic_opt = RunAdamW(critic.flat, torch.zeros(critic.layout.size, dtype=torch.long), 1, c0.adam_betas,
                          c0.adam_eps, c0.weight_decay)
    router_group = group_names.index("router") if "router" in group_names else None
    names = {plasticity_name(c) for c in configs}
    # check_population lets only "none" and "phase_controller" mix; the controller serves both
    # (a member with the controller off behaves exactly as NoPlasticity)
    method_cls = plasticity_method(names.pop() if len(names) == 1 else "phase_controller")
    plasticity = method_cls(configs, actor, critic, actor_opt, critic_opt)
    norms = ValueNorms(configs)
    tracker = EpisodeTracker(R * B, members=R)
    clock = phase_schedule(c0)
    probes = [collect_probe(c) for c in configs]
    generators = [torch.Generator(device=device).manual_seed(int(c.seed)) for c in configs]
    rngs = [np.random.default_rng(int(c.seed)) for c in configs]  # minibatch permutations
    fixed = c0.fixed_phase is not None  # all members or none (check_population)
    member_phase = [c.fixed_phase for c in configs]
    venv.set_phase(np.repeat(member_phase, B) if fixed else clock.phase_at(0))
    obs, state, _ = venv.reset()
    start, global_step, resumed_from = 0, 0, None
    metrics_rows, episode_rows, elapsed = [RowLog() for _ in range(R)], [RowLog() for _ in range(R)], [0.0] * R
    torch_threads = [{torch.get_num_threads()} for _ in range(R)]  # recorded: results with 1 and 2 threads differ

    if any(ck is not None for ck in ckpts):  # every member of a group resumes from the same iteration
        env_states = []
        for r, ck in enumerate(ckpts):
            with torch.no_grad():
                a, c = singles[r]
                a.load_state_dict(ck["actor"]), c.load_state_dict(ck["critic"])
                actor.flat[r] = actor.layout.flatten([a])[0].to(device)
                critic.flat[r] = critic.layout.flatten([c])[0].to(device)
            actor_opt.load_member_state(r, ck["optimizer"]["actor"])
            critic_opt.load_member_state(r, ck["optimizer"]["critic"])
            plasticity.load_state_dict(r, ck["plasticity"])
            norms.norms[r].load_state_dict(ck["value_norm"])
            tracker.load_member_state(r, ck["tracker"])
            env_states.append(_decode(ck["env"]))
            obs[r * B:(r + 1) * B], state[r * B:(r + 1) * B] = ck["obs"].numpy(), ck["state"].numpy()
            generators[r].set_state(ck["torch_rng"])
            rngs[r].bit_generator.state = ck["numpy_rng"]
            global_step, elapsed[r] = int(ck["global_step"]), float(ck["elapsed"])
            metrics_rows[r] = RowLog.from_checkpoint(ck["metrics_rows"])
            episode_rows[r] = RowLog.from_checkpoint(ck["episode_rows"])
            torch_threads[r].update(ck.get("torch_threads", ()))
            start = resumed_from = int(ck["iteration"])
        venv.load_state_dict(merge_env_states(env_states))

    def save(r, iteration, env_state):
        """Member r's checkpoint and logs; env_state: the whole population's (taken once per checkpoint)."""
        if run_dirs[r] is None:
            return
        env_state = split_env_state(env_state, range(r * B, (r + 1) * B))
        _torch_save_atomic({  # stamped with the checkpoint format and TRAINING_NUMERICS, and sealed (appendix 07c)
            "config": configs[r].to_dict(), "iteration": iteration, "global_step": global_step,
            "elapsed": elapsed[r] + time.perf_counter() - wall_start,
            "actor": actor.member(r, singles[r][0]).state_dict(), "critic": critic.member(r, singles[r][1]).state_dict(),
            "optimizer": {"actor": actor_opt.member_state(r), "critic": critic_opt.member_state(r)},
            "plasticity": plasticity.state_dict(r), "value_norm": norms.norms[r].state_dict(),
            "tracker": tracker.member_state(r), "env": _encode(env_state),
            "obs": torch.from_numpy(obs[r * B:(r + 1) * B].copy()), "state": torch.from_numpy(state[r * B:(r + 1) * B].copy()),
            "torch_rng": generators[r].get_state(), "numpy_rng": rngs[r].bit_generator.state,
            "metrics_rows": metrics_rows[r].packed(), "episode_rows": episode_rows[r].packed(),
            "torch_threads": sorted(torch_threads[r]),
        }, run_dirs[r] / "checkpoint.pt")
        final = iteration == configs[r].iterations  # the logs done.json seals: every row converted at once
        _write_parquet_atomic(metrics_rows[r], run_dirs[r] / "metrics.parquet", final)
        _write_parquet_atomic(episode_rows[r], run_dirs[r] / "episodes.parquet", final)
        if final:
            metrics_rows[r].release(), episode_rows[r].release()

    stop = c0.iterations if max_iterations is None else min(c0.iterations, max_iterations)
    label = c0.method if R == 1 else f"{c0.method} x{R}"
    bar = _progress_bar(c0.iterations, start, progress, label)
    for it in range(start, stop):
        # --- 1. phase clock and plasticity method: the new phase from the switch's first slot -----
        phase = member_phase if fixed else [int(clock.phase_at(it))] * R
        switch = False if fixed else bool(clock.is_switch(it))
        if not fixed:
            venv.set_phase(phase[0])
        if switch:
            obs, state, _ = venv.reset()  # episodes restart under the new phase (Algorithm 1's order)
            tracker.discard_running()
            plasticity.on_switch(it)
        sched = plasticity.begin_iteration(it)
        if c0.anneal_lr:
            frac = 1.0 - it / c0.iterations
            sched = dataclasses.replace(sched, lr_actor=sched.lr_actor * frac, lr_critic=sched.lr_critic * frac)
        frozen = None
        if router_group is not None and bool(sched.router_frozen.any()):
            frozen = torch.zeros(R, len(group_names), dtype=torch.bool, device=device)
            frozen[:, router_group] = sched.router_frozen.to(device)

        # --- 2. rollout of every member's environments -------------------------------------------
        t0 = time.perf_counter()
        noise_std = None  # sigma of fixed or annealed routing noise, per member (a learned scale is the network's)
        if actor.noise_mode in ("fixed", "annealed"):
            noise_std = torch.tensor([routing_noise_std(c.net, it, c.iterations) for c in configs], device=device)
        ro, obs, state, step_stats, new_episodes = collect_rollout(
            venv, actor, critic, norms, obs, state, c0.rollout_steps, sched, tracker, it, generators, device, noise_std)
        global_step += c0.batch_env_steps
        rollout_time = time.perf_counter() - t0

        # --- 3. advantages (GAE) per member and return normalisers --------------------------------
        t0 = time.perf_counter()
        adv, ret = compute_gae(ro.rewards.transpose(0, 1), ro.values.transpose(0, 1), ro.next_values.transpose(0, 1),
                               ro.dones.transpose(0, 1), c0.gamma, c0.gae_lambda)
        adv, ret = adv.transpose(0, 1).contiguous(), ret.transpose(0, 1).contiguous()  # (R, T, B)
        norms.update(ret)
        N = c0.batch_env_steps
        data = {
            "obs": ro.obs.reshape(R, N, U, -1), "actions": ro.actions.reshape(R, N, U, -1),
            "logprobs": ro.logprobs.reshape(R, N, U), "advantages": adv.reshape(R, N), "returns": ret.reshape(R, N),
            "values": ro.values.reshape(R, N), "states": ro.states.reshape(R, N, -1),
            "actor_routing": None if ro.actor_routing is None else ro.actor_routing.reshape(R, N, U).to(device),
        }
        plasticity.observe_rollout(data["obs"])  # rows for the next switch's probe batch, if the method keeps any

        # --- 4. PPO update of every member ------------------------------------------------------
        upd = ppo_update(actor, critic, actor_opt, critic_opt, plasticity, sched, data, norms, c0, rngs, frozen)
        update_time = time.perf_counter() - t0

        # --- 5. logging, diagnostics and checkpoints, per member ---------------------------------
        diag = it % c0.diag_every == 0 or switch or it == c0.iterations - 1
        out_of_time = deadline is not None and time.time() >= deadline and it + 1 < stop
        checkpoint = (it + 1) % c0.checkpoint_every == 0 or it == stop - 1 or out_of_time
        env_state = venv.state_dict() if checkpoint and any(d is not None for d in run_dirs) else None
        for r in range(R):
            row = _iteration_row(configs[r], r, it, phase[r], switch, global_step, sched, group_names, actor, norms,
                                 step_stats, new_episodes[r], upd, ro, ret, U)
            own = plasticity.metrics(r)  # the method's own columns (none for most methods)
            if own.keys() & row.keys():
                raise ValueError(f"{type(plasticity).__name__}.metrics names trainer columns: {sorted(own.keys() & row.keys())}")
            row.update(own)
            t1 = time.perf_counter()
            if diag:
                a_r, c_r = actor.member(r, singles[r][0]), critic.member(r, singles[r][1])
                row.update(plasticity_diagnostics(a_r, c_r, probes[r][0], probes[r][1],
                                                  sched.members[r].policy_temperature))
            now = time.perf_counter()
            row.update(sps=c0.batch_env_steps / max(rollout_time + update_time, 1e-9),
                       sps_total=global_step / max(elapsed[r] + now - wall_start, 1e-9),
                       rollout_time=rollout_time, update_time=update_time, diag_time=now - t1,
                       wall_time=elapsed[r] + now - wall_start, population=R)
            metrics_rows[r].append(row)
            episode_rows[r] += new_episodes[r]
            if checkpoint:
                save(r, it + 1, env_state)
        recent = [m[-1]["episode_return"] for m in metrics_rows if np.isfinite(m[-1]["episode_return"])]
        recent = float(np.mean(recent)) if recent else float("nan")
        if verbose:
            shown = phase[0] if len(set(phase)) == 1 else "/".join(map(str, phase))
            print(f"it {it:5d} phase {shown} return {recent:9.2f} sps/member {metrics_rows[0][-1]['sps']:7.0f}", flush=True)
        bar.set_postfix(phase=phase[0] if len(set(phase)) == 1 else "mixed", ret=f"{recent:.1f}", sps=f"{metrics_rows[0][-1]['sps']:.0f}", refresh=False)
        bar.update(1)
        if out_of_time:  # the checkpoint above holds everything: a resume continues bit for bit
            stop = it + 1
            break
    bar.close()

    finished = stop == c0.iterations
    results = []
    env_state = venv.state_dict() if finished and start >= stop else None
    for r, config in enumerate(configs):
        run_dir = run_dirs[r]
        if run_dir is not None and finished:
            if start >= stop:  # nothing ran (a finished checkpoint without done.json): rewrite the logs
                save(r, stop, env_state)
            final = pd.DataFrame(metrics_rows[r])
            write_done(run_dir, config, env_steps=global_step, torch_threads=sorted(torch_threads[r]),
                       wall_time_s=elapsed[r] + time.perf_counter() - wall_start,
                       final_episode_return=float(final["episode_return"].tail(config.phase_length_iters).mean()))
        results.append(RunResult(config, pd.DataFrame(metrics_rows[r]), pd.DataFrame(episode_rows[r]),
                                 actor.member(r, singles[r][0]), critic.member(r, singles[r][1]), run_dir,
                                 finished=finished, resumed_from=resumed_from))
    return results


# %% [markdown]
# ## Deterministic evaluation
#
# For figures that need a policy's behaviour rather than its training curve, `evaluate_policy`
# runs fresh episodes in a given phase with the **mean** action and returns one row per episode.
# A gated actor is evaluated with noiseless gating by default (the execution-time policy: each row
# goes to the router's own choice); `routing="trained"` keeps the routing noise it trained with.
# The two differ for an actor that came to rely on the noise (notebook 05).

# %%
#| export
EVAL_ROUTINGS = ("noiseless", "trained")


@torch.no_grad()
def evaluate_policy(actor, env_cfg: EnvConfig | None = None, episodes: int = 8, seed: int = 0, phase: int = 0,
                    num_envs: int | None = None, temperature: float = 1.0, routing: str = "noiseless") -> pd.DataFrame:
    """Evaluation with the mean action: `episodes` episodes in `phase`; one row per episode (team
    return, length, the system metrics, mean |action|). routing="noiseless" routes each row to the
    router's own top choice (no torch randomness); "trained" keeps the routing noise the actor
    trained with (its config's sigma for fixed noise), drawn from a generator seeded by `seed`:
    a gated actor that learned to rely on the noise behaves differently under the two."""
    if routing not in EVAL_ROUTINGS:
        raise ValueError(f"routing must be one of {', '.join(EVAL_ROUTINGS)}, got {routing!r}")
    env_cfg = dataclasses.replace(env_cfg or EnvConfig(), phase_clock="external")
    num_envs = num_envs or min(int(episodes), 16)
    venv = UAVVectorEnv(num_envs, seed, cfg=env_cfg)
    venv.set_phase(phase)
    obs, _, _ = venv.reset()
    tracker = EpisodeTracker(num_envs)
    rows, action_abs = [], np.zeros(num_envs)
    B, U = num_envs, venv.n_agents
    with torch.random.fork_rng(devices=[]):  # the trained noise draws leave the global generator as it was
        torch.manual_seed(seed)
        while len(rows) < episodes:
            x = torch.from_numpy(obs).reshape(B * U, -1)
            dist, _ = actor(x, temperature, None, deterministic_gate=routing == "noiseless")
            obs = _evaluation_step(venv, tracker, dist.mean.reshape(B, U, -1).numpy(), action_abs, rows)
    df = pd.DataFrame(rows[:episodes]).drop(columns=["iteration"])
    df["episode"] = np.arange(len(df))
    df["routing"] = routing
    return df


def _evaluation_step(venv, tracker, action, action_abs, rows):
    """One step of every evaluation env with `action` (B, U, A); finished episodes go to `rows`."""
    action_abs += np.abs(np.clip(action, -1, 1)).mean(axis=(1, 2))
    obs, _, reward, term, trunc, info = venv.step(action)
    for r in tracker.update(np.asarray(reward, dtype=float), info, term, trunc, 0):
        r["mean_abs_action"] = float(action_abs[r["env"]] / r["length"])
        action_abs[r["env"]] = 0.0
        rows.append(r)
    return obs

# %% [markdown]
# ## Demonstration: one PE-MAMoE run and one MLP run
#
# At the notebook's scale we train PE-MAMoE and the MLP baseline with the same seed. Runs go to
# `results/<scale>/<method>-s<seed>-<config hash>/`, the folders the sweep of notebook 09 uses for
# the same runs, so `make figures` (which trains the sweep first) finds them there; a finished run
# is read back instead of retrained.

# %%
from pemamoe.core import repo_path

run_root = repo_path(results_dir) / scale
results = {}
for method in ("pemamoe", "mlp"):
    cfg = TrainConfig.for_scale(scale, method=method, seed=seed)
    t0 = time.perf_counter()
    results[method] = train(cfg, run_root / cfg.run_name())
    print(f"{method:8s} {cfg.iterations} iterations, {cfg.total_env_steps} env steps, "
          f"{time.perf_counter() - t0:6.1f} s (cached: {results[method].from_cache})")

# %%
import matplotlib.pyplot as plt

from pemamoe.analysis import plot_reference_levels, reference_levels
from pemamoe.core import save_figure


def _smooth(y, w):
    return pd.Series(y).rolling(w, min_periods=1).mean().to_numpy()


cfg0 = results["pemamoe"].config
w = max(1, cfg0.phase_length_iters // 8)
# Each phase's level without learning (random policy dotted, k-means heuristic dash-dot; notebook 09).
levels = reference_levels(scale, repo_path(results_dir))
panels = [("episode_return", "team return per episode"), ("served_users", "served users (mean per slot)"),
          ("collisions_per_episode", "collisions per episode"), ("rank/stable/mean", "expert stable rank (probe)")]
fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.2))
for ax, (col, title) in zip(axes, panels):
    for method, res in results.items():
        m = res.metrics
        sel = m[col].notna()
        y = m.loc[sel, col].to_numpy()
        ax.plot(m.loc[sel, "iteration"], _smooth(y, w) if col != "rank/stable/mean" else y, label=method)
    plot_reference_levels(ax, results["pemamoe"].metrics.assign(run="pemamoe"), levels, col)
    for s in range(cfg0.phase_length_iters, cfg0.iterations, cfg0.phase_length_iters):
        ax.axvline(s, color="grey", ls="--", lw=0.8)
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("iteration")
axes[0].legend(fontsize=8)
fig.suptitle(f"MAPPO training at scale '{scale}' (seed {seed}, 1 seed; dashed: phase switches; black: each phase's "
             "random-policy (dotted) and k-means (dash-dot) level)", fontsize=10)
fig.tight_layout()
save_figure(fig, "mappo_training_curves", figures_dir)
plt.show()

# %% [markdown]
# The logged columns of one iteration row (PE-MAMoE, the last iteration):

# %%
_m = results["pemamoe"].metrics
pd.set_option("display.max_rows", 200)
pd.DataFrame({"column": _m.columns, "last value": [_m[c].iloc[-1] for c in _m.columns]})

# %% [markdown]
# A per-phase summary of the two runs (mean over the iterations of each phase occurrence):

# %%
_summary = []
for method, res in results.items():
    m = res.metrics.assign(block=res.metrics["iteration"] // res.config.phase_length_iters)
    g = m.groupby("block").agg(phase=("phase", "first"), episode_return=("episode_return", "mean"),
                               served_users=("served_users", "mean"), approx_kl=("approx_kl", "mean"),
                               clip_frac=("clip_frac", "mean"), explained_variance=("explained_variance", "mean"))
    _summary.append(g.assign(method=method).reset_index())
pd.concat(_summary).round(3)

# %% [markdown]
# **What this run shows, honestly.** At `ci` scale the runs last six iterations: they only prove
# that the loop executes end to end, that the phase switches fire at iterations 2 and 4 (the
# controller's KL weight, LR drop and log-std reset appear in the logged columns), and that every
# column the figures need is produced.
#
# At the larger scales the table above is the place to look, phase by phase. Two things help in
# reading it. Raw returns compare only *within* a phase type: the class reward per served user
# rises from phase to phase (5, 10, 20), so the return curve is a staircase that follows the
# phases whether or not the policy improves. And the PPO statistics say whether the updates are
# healthy (an approximate KL far below the early-stop budget and clip fractions of a few per cent
# mean small, stable steps; an explained variance near 0 means the critic has not yet learned the
# return). The expert-rank panel is not a like-for-like comparison (the MLP's single trunk against
# the mean of three experts). One seed shows what a run looks like, not which method is better:
# the comparison over seeds, with IQM intervals and each phase's plateau as the yardstick, is
# notebook 09's.
#
# Quick checks of the invariants the trainer promises (they also live in `tests/test_mappo.py`):

# %%
for method, res in results.items():
    m = res.metrics
    # 1 up to float rounding: some CPUs' BLAS changes the last bit with the row count (about 1e-6)
    assert (m["first_ratio_dev"] <= 1e-5).all(), "the ratio must be 1 before the first gradient step"
    switches = m.loc[m["switch"], "iteration"].tolist()
    assert switches == list(range(res.config.phase_length_iters, res.config.iterations, res.config.phase_length_iters))
print("ratio == 1 (to 1e-5) before every iteration's first step; switches at", switches)
