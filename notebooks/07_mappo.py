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
# This notebook is the method, to be read top to bottom: the rollout, the advantages, the update
# and the training loop. The machinery around it is in four appendices: run folders in 07b, the
# run's configuration in 07c, populations of runs, resuming and reading a run back in 07d, and the
# trainer's bookkeeping (episode accounting, the log row, checkpoint encoding) in 07e.
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
# A comparison is dozens of runs of tiny networks, whose minibatch steps cost mostly fixed per-call
# overhead. So the trainer trains a **population** of R runs in one process, the leading axis R of
# the tensors below: `train_population(configs, run_dirs)` steps R x B environments and updates R
# networks with one set of tensor operations, and `train(config, run_dir)` is the population of
# one. Every member's result is bit-identical to training its config alone; how, and how members
# resume and catch up, is appendix 07d's.

# %%
#| default_exp mappo

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0
results_dir = "results"
records_dir = "records"
retrain = False

# %%
#| export
import dataclasses
import math
import sys
import time
from typing import NamedTuple

import numpy as np
import pandas as pd
import torch

import pemamoe.backprop as backprop  # the networks' gradients, written out (appendix 05h)
from pemamoe.bookkeeping import (  # re-export (public names only): the bookkeeping of appendix 07e
    EpisodeTracker, RowLog, RunningNorm, ValueNorms, collect_probe, explained_variance, merge_env_states,
    split_env_state)
from pemamoe.bookkeeping import IterationLogger  # the log rows, progress bar and verbose line (appendix 07e)
from pemamoe.env import EnvConfig, UAVVectorEnv, observation_dim, state_dim, vector_seeds
from pemamoe.methods import METHOD_REGISTRY, method_spec
from pemamoe.nets import NetConfig, PopulationActor, PopulationCritic, RoutingSample, routing_noise_std
from pemamoe.optim import RunAdamW, group_index
from pemamoe.phase_controller import MECHANISMS, PhaseControllerConfig  # importing it registers PhaseController (06)
from pemamoe.plasticity import RunSettings, plasticity_method
import pemamoe.plasticity_baselines  # noqa: F401, E402  registers ReDo and shrink-and-perturb (appendix 06c)
from pemamoe.phases import PhaseClock
from pemamoe.populations import (  # re-export (public names only): populations, resuming, evaluation (appendix 07d)
    EVAL_ROUTINGS, MEMBER_FIELDS, MemberStates, Population, RunResult, build_population, check_population,
    TrainState, evaluate_policy, load_run, member_networks, phase_clock_of, plasticity_name, population_key,
    train_members)
from pemamoe.runs import write_done
# the configuration (appendix 07c): callers import TrainConfig and the presets from here
from pemamoe.train_config import (  # re-export (public names only)
    DEVICES, MEDIUM_PHASE_ITERS, METHODS, PAPER_PHASE_LENGTH, PAPER_UPDATE_EPOCHS, TIMING_COLUMNS, TrainConfig,
    resolve_device, scale_controller)

# %% [markdown]
# ## What the paper fixes, and what we had to choose
#
# The paper's training table gives most numbers; the rest are ours, each a `TrainConfig` field.
# Appendix 07c sets the two side by side and says why "Adam with weight decay" is AdamW here.
#
# **Separate gradient clipping.** With one optimiser over actor and critic, a single global norm
# clip would let the critic's gradient eat the actor's budget (or the reverse). MAPPO keeps two
# optimisers and clips each; we keep one AdamW (the phase controller needs one optimiser with named
# parameter groups) and clip the two networks' gradients separately, each at `max_grad_norm`.

# %% [markdown]
# ## The configuration
#
# `TrainConfig` holds every number of a run, and `TrainConfig.for_scale(scale, method, seed)`
# gives four presets: **paper**, the training table exactly (10,800 iterations of 2048 environment
# steps); **medium**, the scale at which learning is visible (longer phases, three phases twice
# over; the default of `make figures`); **small**, short training; and **ci**, a handful of
# iterations crossing two phase switches, seconds per run. Appendix 07c (`pemamoe.train_config`,
# re-exported here) says why the smaller presets hold their numbers and holds `TrainConfig`'s code.
#
# **Time-compressed schedules.** The phase controller's windows (LR warm-up, conservative window,
# router freeze, KL-anchor decay, noise epochs) are counted relative to the paper's 1200-iteration
# phases of 8-epoch updates; `for_scale` rescales them so that each covers the same fraction of a
# phase at every scale (appendix 07c). The controller runs only for `method="pemamoe"` unless
# `force_controller=True` (the noise sweep's "MoE with expert noise alone").

# %% [markdown]
# ## The phase clock
#
# The trainer owns the phase: iteration $t$ runs in phase $\lfloor t/L \rfloor \bmod 3$, and a
# switch happens at every $t > 0$ with $t \bmod L = 0$ (Algorithm 1's "iteration mod L"), counted
# by notebook 03's `PhaseClock` (`phase_clock_of(config)`, built by the driver of appendix 07d);
# the environment is told the phase (`set_phase`), never observes it. At the paper's scale:

# %%
_clock = phase_clock_of(TrainConfig.for_scale("paper"))
assert [bool(_clock.is_switch(t)) for t in (0, 1199, 1200)] == [False, False, True]
[int(_clock.phase_at(t)) for t in (0, 1200, 2400, 3600)]

# %% [markdown]
# ## What learns: the population
#
# Everything that learns, and everything the update reads, is built once by
# `build_population(configs)` and kept in one object, a `Population`, the way CleanRL builds its
# agent and optimiser at the top of its script: every member's actor and critic (from its own
# seed alone) stacked into a `PopulationActor` and a `PopulationCritic` (appendix 05b), one
# `RunAdamW` per network with named parameter groups the phase controller can set, freeze and
# reset (appendix 06d), the members' plasticity method, each member's return normaliser and random
# streams. Its code is appendix 07d's (`pemamoe.populations`). The update,
# `ppo_update(population, settings, data)`, reads it whole; the training loop adds what does not
# learn: the environments, the phase clock, the running episodes and the logs.

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
# A slot's team reward is a QoS sum of up to several hundred minus energy, collision and overlap
# penalties, so discounted returns reach the thousands and change scale at each phase switch (the
# class rewards go 5 → 10 → 20). A critic regressing such targets directly produces huge
# value-loss gradients. MAPPO's remedy: a running mean $\mu$ and deviation $\sigma$ of all returns
# so far (updated before each update); the critic regresses $(\hat R - \mu)/\sigma$ and the rollout
# reads values back as $\mu + \sigma\,\hat v$ for GAE (`value_norm=False` switches it off; the
# bookkeeping, `RunningNorm` and `ValueNorms`, is appendix 07e's).

# %% [markdown]
# ## Rollout
#
# The shared actor sees the $B\cdot U$ agent rows of a step as one batch. For gated actors
# `act` returns a `RoutingSample` (the gate noise, the chosen experts and the temperature); we
# keep it for the update. With `update_routing="current"` (the default, notebook 05) the update
# replays the stored noise and temperature and lets the current router choose the experts again,
# so a change of route is a change of policy that PPO's ratio $\pi_\theta(a|o)/\pi_{\text{old}}(a|o)$
# sees and clips; `"replay"` also reuses the rollout's experts. The critic's routing is stored too.
# Actions are stored unclipped (their log-probability is the Gaussian's); the environment clips.
#
# `EpisodeTracker` (appendix 07e) accumulates each environment's running episode (team return and
# the system metrics) and emits one row per finished episode.
#
# **One `Batch` from rollout to minibatch.** The rollout is a `Batch` with leading axes (R, T, B);
# `with_gae` adds each member's advantages and returns; `for_update` keeps what the update reads,
# normalises returns and values by each member's normaliser and `flatten`s member and step into one
# axis; `take(rows)` draws a minibatch of every member at once, (R, m, ...). The type never changes
# on the way, only the leading axes (PureJaxRL's `Transition`, reshaped and split).

# %%
#| export
_STEP_KEYS = ("reward", "qos", "energy", "collision", "overlap", "collisions", "coverage", "served_users",
              "admitted_users", "uav_using_rate", "energy_rate_kj")
_AGENT_FLAGS = ("action_clipped", "move_infeasible", "battery_depleted")


class Batch(NamedTuple):
    """One iteration's data of a population, the one type from rollout to minibatch. The member axis
    R leads, then the step axes: (R, T, B) as collected (T = rollout_steps, B = num_envs); one
    (R*N,) axis once `flatten`ed over member and step (N = T*B); (R, m) in a minibatch (`take`).
    Agent rows (U) follow where a field has them. advantages and returns are None until `with_gae`;
    a field the update does not read is None in its flattened batch (`for_update`)."""

    obs: torch.Tensor  # (R, T, B, U, obs_dim)
    states: torch.Tensor  # (R, T, B, state_dim)
    actions: torch.Tensor  # (R, T, B, U, act_dim), unclipped samples
    logprobs: torch.Tensor  # (R, T, B, U) behaviour log-probabilities
    values: torch.Tensor  # (R, T, B) V(s_t), de-normalised, float64 (for the update: normalised, float32)
    rewards: torch.Tensor | None  # (R, T, B) team reward, float64
    dones: torch.Tensor | None  # (R, T, B) the episode ended at step t (terminated or truncated)
    next_values: torch.Tensor | None  # (R, T, B) value that follows step t (see bootstrap_values)
    routing: RoutingSample | None  # leading (R, T, B, U): the rollout's routing, replayed in the update
    advantages: torch.Tensor | None = None  # (R, T, B) GAE
    returns: torch.Tensor | None = None  # (R, T, B) advantages + values (for the update: normalised, float32)

    def with_gae(self, gamma: float, gae_lambda: float) -> "Batch":
        """The batch with each member's GAE advantages and returns (compute_gae over the time axis)."""
        adv, ret = compute_gae(*(x.transpose(0, 1) for x in (self.rewards, self.values, self.next_values,
                                                               self.dones)), gamma, gae_lambda)
        return self._replace(advantages=adv.transpose(0, 1).contiguous(), returns=ret.transpose(0, 1).contiguous())

    def for_update(self, norms, device) -> "Batch":
        """What PPO's update reads, flattened, on `device`: returns and values normalised by each
        member's normaliser (the critic's targets, and where value clipping starts), float32."""
        return self._replace(
            actions=self.actions.to(device), logprobs=self.logprobs.to(device),
            values=norms.normalize(self.values).float().to(device), rewards=None, dones=None, next_values=None,
            routing=None if self.routing is None else self.routing.to(device),
            advantages=self.advantages.float().to(device), returns=norms.normalize(self.returns).float().to(device),
        ).flatten()

    def flatten(self) -> "Batch":
        """(R, T, B, ...) -> (R*N, ...), member by member: the rows `take` draws minibatches from."""
        R, T, B = self.obs.shape[:3]
        return self._map(lambda x: x.reshape(R * T * B, *x.shape[3:]))

    def take(self, rows: torch.Tensor, R: int) -> "Batch":
        """The minibatch of a flattened batch's rows `rows` (R*m,) = member * N + step, member by member:
        (R, m, ...)."""
        return self._map(lambda x: x.index_select(0, rows).reshape(R, -1, *x.shape[1:]))

    def _map(self, f) -> "Batch":
        def apply(x):
            if isinstance(x, RoutingSample):
                return RoutingSample(*(f(t) for t in x))
            return None if x is None else f(x)

        return Batch(*(apply(x) for x in self))


def _member_view(x, R: int):
    """(R*B, ...) numpy -> (R, B, ...) tensor (a view)."""
    t = torch.from_numpy(x)
    return t.reshape(R, t.shape[0] // R, *t.shape[1:])


def routing_noise_stds(population, iteration: int) -> torch.Tensor | None:
    """Per member the sigma of fixed or annealed routing noise at `iteration` (R,), or None (no
    routing noise, or a learned scale, which is the network's own)."""
    if population.actor.noise_mode not in ("fixed", "annealed"):
        return None
    return torch.tensor([routing_noise_std(c.net, iteration, c.iterations) for c in population.configs],
                        device=population.device)


@torch.no_grad()
def collect_rollout(population, venv, obs, state, settings, tracker: EpisodeTracker, iteration: int,
                    steps: int | None = None):
    """Run `steps` (default: the config's rollout_steps) slots of every environment of a population.

    venv holds R*B environments, member r's in rows r*B..(r+1)*B-1. Values come from the critic
    with noiseless gating (they enter GAE; see above). Returns (Batch (R, T, B), next obs, next state,
    per-member step statistics {key: (R,) array}, per-member lists of finished-episode rows).
    """
    actor, critic, norms, generators = population.actor, population.critic, population.norms, population.generators
    device, steps = population.device, population.config.rollout_steps if steps is None else steps
    noise_std = routing_noise_stds(population, iteration)
    R, U = actor.R, venv.n_agents
    B = venv.num_envs // R
    tau_pi, tau_v = settings.policy_temperature.to(device), settings.value_temperature.to(device)
    buf = {k: [] for k in ("obs", "states", "actions", "logprobs", "values", "rewards", "dones", "final")}
    routes, episode_rows = [], [[] for _ in range(R)]
    step_sums = {k: np.zeros(R) for k in _STEP_KEYS + _AGENT_FLAGS}
    for _ in range(steps):
        o, s = _member_view(obs, R), _member_view(state, R)
        od, sd = o.to(device), s.to(device)
        sample = actor.act(od.reshape(R, B * U, -1), tau_pi, generators, noise_std=noise_std)
        v, _, _ = critic(sd, tau_v)
        obs, state, reward, terminated, truncated, info = venv.step(sample.action.reshape(R * B, U, -1).cpu().numpy())
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
        buf["actions"].append(sample.action.reshape(R, B, U, -1))
        buf["logprobs"].append(sample.log_prob.reshape(R, B, U))
        buf["values"].append(norms.denormalize(v.double().cpu()))
        buf["rewards"].append(torch.as_tensor(reward, dtype=torch.float64).reshape(R, B))
        buf["dones"].append(torch.as_tensor(done).reshape(R, B)), buf["final"].append(final.reshape(R, B))
        if sample.routing is not None:
            routes.append(sample.routing.reshape(R, 1, B, U))
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
    batch = Batch(
        obs=stack("obs", device), states=stack("states", device), actions=stack("actions"), logprobs=stack("logprobs"),
        values=values, rewards=stack("rewards"), dones=dones, next_values=next_values,
        routing=RoutingSample.cat(routes, dim=1) if routes else None,
    )
    stats = {f"step/{k}": v / steps for k, v in step_sums.items()}
    stats.update(actor.routing_readings(batch.obs, batch.routing, batch.dones, noise_std))
    return batch, obs, state, stats, episode_rows


# %% [markdown]
# ## The update: clipped surrogate, value regression, KL stop
#
# For an agent row with stored action $a$, behaviour log-probability $\log\pi_{\text{old}}(a|o)$
# and advantage $A$ (the team advantage of its environment step, normalised per minibatch), the
# policy loss is PPO's pessimistic bound
# $$\mathcal L_\text{PPO} = \mathbb E\big[\max\big(-A\,\rho,\; -A\,\operatorname{clip}(\rho, 1-\epsilon, 1+\epsilon)\big)\big],
# \qquad \rho = \exp\big(\log\pi_\theta(a|o) - \log\pi_\text{old}(a|o)\big),$$
# with $\epsilon$ the controller's clip range of this iteration (0.15, or 0.10 in PE-MAMoE's
# conservative window). $\log\pi_\theta$ comes from `actor.evaluate` with the stored noise and
# temperature replayed (and, under `"replay"`, the stored experts), so before the first gradient
# step the router chooses what it chose in the rollout and $\rho = 1$ *exactly* (the tests check
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
# **KL stop.** The KL between behaviour and current policy on a minibatch is estimated, before
# that minibatch's step, with CleanRL's $\widehat{\mathrm{KL}} = \mathbb E[(\rho - 1) - \log\rho]$.
# Where the estimate is read is a reading (the paper's Algorithm 1 draws no stop; its table names
# a target KL, in CleanRL's words), set per run by `target_kl_check`: `"minibatch"` checks before
# every step and stops at once past the target (no step on that minibatch, no further epoch; SB3
# does this, at 1.5 times its target); `"epoch"` checks after each full epoch, on its last
# minibatch's estimate, and skips the remaining epochs (CleanRL's continuous PPO); `target_kl=None`
# never stops. A top-1 sparse actor's ratio is taken on the current routes, so a row moved to
# another expert jumps in probability: at the paper's scale such rows tripped every per-minibatch
# stop notebook 10's probe examined after the first switch.
#
# **Parameter groups.** `RunAdamW` (appendix 06d, `pemamoe.optim`) knows five named groups,
# `router`, `experts`, `head`, `log_std` (actor) and `critic` (`group_index`). The phase controller
# sets each group's learning rate every iteration (the LR drop and warm-up after a switch, a frozen
# router), clears Adam's moments at a switch and perturbs the experts; the trainer never sets a
# learning rate itself (but for the optional `anneal_lr` factor). **Where the controller enters:** `on_switch(t)`
# before the rollout at a switch, `begin_iteration(t)` for the settings, `extra_loss(batch)` in
# every minibatch loss, `after_epoch(expert_counts, stepped)` after each epoch. A method may also
# keep rollout rows for its next switch (`observe_rollout`) and log columns (`metrics`).
#
# **How the code reads.** `ppo_update(population, settings, batch)` takes the `Population` above, the
# iteration's settings and the rollout's `Batch`, and has the shape of CleanRL's update loop. Each
# epoch draws one permutation per member; each minibatch is gathered for every member at once
# (`Batch.take`), scored and differentiated (`_minibatch_loss` returns the loss of each member, the
# statistics it logs and its gradient), checked against the KL budget (`_KLStop`: a member over it
# takes no step now, nor later in this update), clipped and stepped (`_gradient_step`), and added to
# the sums of the logged statistics (`_UpdateStatistics`). A member's gradient depends on its own
# loss alone, so another member's stop changes none of its bits; a member that stops is simply not
# stepped. The sums stay tensors and are read once, at the end of the update, because every read
# of a number waits for the device.
#
# **The gradient, by hand.** The networks run once per minibatch without autograd, keeping what
# their backward pass reads, and the gradient is written out: here the loss's gradient in what the
# networks output (the policy mean and log-std, the values), in appendix 05h (`pemamoe.backprop`)
# the networks' own, block by block. A minibatch is 192 agent rows, so a step costs almost nothing
# in arithmetic and almost everything in the number of tensor operations dispatched, and autograd
# records and replays several for each one written. The tests compare both parts with autograd on
# the same forward pass, for every network kind and gate setting. A plasticity method's loss term
# (`extra_loss`, PE-MAMoE's KL anchor) stays a plain function of the policy's outputs: autograd
# differentiates it in those outputs alone, and the networks' backward carries it on.

# %%
#| export
_UPDATE_STATS = ("policy_loss", "value_loss", "entropy", "kl_ref", "load_balance", "critic_load_balance",
                 "approx_kl", "clip_frac", "grad_norm_actor", "grad_norm_critic")


@torch.no_grad()  # the gradient is written out below and in appendix 05h: no autograd graph
def _minibatch_loss(population: Population, settings, batch: Batch) -> tuple:
    """PPO's loss on one minibatch `batch` (R, m, ...), per member (R,), the statistics it logs
    ({name: (R,) tensor}: `_UPDATE_STATS` but the gradient norms, and "ratio" (R, m*U) and the
    chosen "experts"), and its gradient in the actor's and the critic's parameters, (R, P) and
    (R, Q). The actor sees the m*U agent rows of the minibatch's m steps."""
    actor, critic, config = population.actor, population.critic, population.config
    R, steps, U = batch.logprobs.shape
    rows, clip = steps * U, settings.clip_coef.unsqueeze(1)  # each member's clip range, (R, 1)
    route = None if batch.routing is None else batch.routing.reshape(R, rows)
    saved_actor, saved_critic = {}, {}  # what the backward reads
    action = batch.actions.reshape(R, rows, -1)
    new = actor.evaluate(batch.obs.reshape(R, rows, -1), action, route, saved=saved_actor)
    logratio = new.log_prob - batch.logprobs.reshape(R, rows)
    ratio = logratio.exp()
    # every agent row of a step takes the step's team advantage, normalised over the member's minibatch
    adv = batch.advantages.unsqueeze(2).expand(R, steps, rows // steps).reshape(R, rows)
    if config.norm_adv:
        adv = (adv - adv.mean(1, keepdim=True)) / (adv.std(1, keepdim=True) + 1e-8)
    unclipped, clipped = -adv * ratio, -adv * torch.clamp(ratio, 1 - clip, 1 + clip)
    pg_loss = torch.max(unclipped, clipped).mean(1)

    v, c_lb, _ = critic(batch.states, settings.value_temperature, saved=saved_critic)
    err = v - batch.returns
    if config.clip_vloss:
        v_clipped = batch.values + torch.clamp(v - batch.values, -clip, clip)
        err_clipped = v_clipped - batch.returns
        v_loss = torch.max(err ** 2, err_clipped ** 2).mean(1)
    else:
        v_loss = (err ** 2).mean(1)
    sparse = actor.gated and actor.k < actor.n_experts
    with torch.enable_grad():  # a plasticity method's loss term is differentiated by autograd, in the policy's outputs only
        mean, log_std = new.mean.detach().requires_grad_(True), new.log_std.detach().requires_grad_(True)
        kl_ref = population.plasticity.extra_loss({
            "obs": batch.obs.reshape(R, rows, -1), "tau": None if route is None else route.temperature,
            "noise": None if route is None else route.noise, "experts": new.experts if sparse else None,
            "mean": mean, "log_std": log_std})
        extra = None if kl_ref is None else torch.autograd.grad(kl_ref.sum(), (mean, log_std), allow_unused=True)
    loss = (pg_loss + config.vf_coef * v_loss - settings.ent_coef * new.entropy + actor.lb_coef * new.load_balance
            + critic.lb_coef * c_lb)
    if kl_ref is not None:
        kl_ref = kl_ref.detach()
        loss = loss + kl_ref

    # The loss's gradient in what the networks output. The surrogate's max takes the unclipped
    # term's gradient, -A * rho, where that term is the larger (where they tie, inside the clip
    # range, autograd's half of each is the same); log-density: d/d mean = (a - mean) / sigma^2,
    # d/d log sigma = (a - mean)^2 / sigma^2 - 1; the entropy's, -ent_coef per action dimension.
    g_logp = torch.where(unclipped >= clipped, -adv * ratio, 0.0) / rows
    diff = saved_actor["diff"]  # a - mean
    g_mean = g_logp.unsqueeze(-1) * diff * saved_actor["inv_var"]
    g_log_std = (g_mean * diff).sum(1) - g_logp.sum(1, keepdim=True) - settings.ent_coef.unsqueeze(1)
    if config.clip_vloss:  # the larger square's; the clipped one's only where the clamp passes v through
        inside = (v - batch.values).abs() <= clip
        g_value = torch.where(err ** 2 >= err_clipped ** 2, err, err_clipped * inside)
    else:
        g_value = err
    g_value = g_value * (2 * config.vf_coef / v.shape[1])
    if extra is not None:
        g_mean = g_mean if extra[0] is None else g_mean + extra[0]
        g_log_std = g_log_std if extra[1] is None else g_log_std + extra[1]
    grads = backprop.actor_grads(actor, saved_actor, g_mean, g_log_std), backprop.critic_grads(critic, saved_critic, g_value)
    stats = {"policy_loss": pg_loss, "value_loss": v_loss, "entropy": new.entropy,
             "kl_ref": torch.zeros(R, device=loss.device) if kl_ref is None else kl_ref,  # 0 when none is added
             "load_balance": new.load_balance, "critic_load_balance": c_lb,
             "approx_kl": ((ratio - 1) - logratio).mean(1),  # CleanRL's low-variance estimator
             "clip_frac": ((ratio - 1.0).abs() > clip).float().mean(1),
             "ratio": ratio, "experts": new.experts}
    return loss, stats, grads


class _KLStop:
    """Each member's early stop at its target KL, read where its `target_kl_check` says (above):
    per minibatch, before the step (`check`), or per epoch, on its last minibatch (`end_epoch`)."""

    def __init__(self, target_kl: torch.Tensor, per_epoch: torch.Tensor):
        self.target_kl, self.per_epoch, self.any_per_epoch = target_kl, per_epoch, bool(per_epoch.any())
        self.stopped = torch.zeros(target_kl.shape, dtype=torch.bool, device=target_kl.device)
        self.epoch = torch.full(target_kl.shape, -1, dtype=torch.long, device=target_kl.device)  # -1: never stopped

    @torch.no_grad()
    def _stop(self, over: torch.Tensor, epoch: int) -> torch.Tensor:
        self.epoch = torch.where(over & ~self.stopped, epoch, self.epoch)
        self.stopped = self.stopped | over
        return ~self.stopped

    def check(self, approx_kl: torch.Tensor, epoch: int) -> torch.Tensor:
        """The members that step on this minibatch, (R,) bool."""
        over = approx_kl > self.target_kl
        return self._stop(over & ~self.per_epoch if self.any_per_epoch else over, epoch)

    def end_epoch(self, last_approx_kl: torch.Tensor, epoch: int) -> None:
        if self.any_per_epoch:
            self._stop((last_approx_kl > self.target_kl) & self.per_epoch, epoch)


class _UpdateStatistics:
    """The update's `_UPDATE_STATS`, summed per member over the minibatches it stepped on. They stay
    tensors and are read once, at the end: one host sync per update instead of one per minibatch."""

    def __init__(self, R: int, device):
        self.sums = torch.zeros(len(_UPDATE_STATS), R, dtype=torch.float64, device=device)  # rows in _UPDATE_STATS order
        self.steps = torch.zeros(R, dtype=torch.long, device=device)  # gradient steps per member

    @torch.no_grad()
    def add(self, stats: dict, stepping: torch.Tensor) -> None:
        self.steps += stepping.long()
        # the ten statistics in one (10, R) accumulation, each element as `sum += value * w`
        self.sums.add_(torch.stack([stats[name] for name in _UPDATE_STATS]).double() * stepping.to(torch.float64))

    def means(self) -> dict:
        """{stat: (R,) list} of means over each member's steps (nan for a member that took none)."""
        means = torch.where(self.steps > 0, self.sums / self.steps.double().clamp(min=1), torch.nan).tolist()
        return dict(zip(_UPDATE_STATS, means))


def _clip_rows(grad: torch.Tensor, max_norm: float) -> torch.Tensor:
    """Clip each member's gradient row to norm max_norm (torch's clip_grad_norm_ rule); returns
    the norms before clipping, (R,)."""
    norm = torch.linalg.vector_norm(grad, dim=1)
    grad.mul_((max_norm / (norm + 1e-6)).clamp(max=1.0).unsqueeze(1))
    return norm


def _gradient_step(population: Population, settings, stepping, frozen, frozen_rows) -> tuple:
    """Clip each member's actor and critic gradients and step the members in `stepping` (none of a
    group in `frozen` (R, G), whose entries `frozen_rows` (R, P) get no gradient either). Returns
    the gradient norms before clipping, (R,) each."""
    actor, critic, max_norm = population.actor, population.critic, population.config.max_grad_norm
    with torch.no_grad():
        if frozen_rows is not None:
            actor.flat.grad.masked_fill_(frozen_rows, 0.0)
        norms = _clip_rows(actor.flat.grad, max_norm), _clip_rows(critic.flat.grad, max_norm)
    population.actor_opt.step(settings.lr_actor, stepping, frozen)
    population.critic_opt.step(settings.lr_critic, stepping)
    return norms


def ppo_update(population: Population, settings, batch: Batch) -> dict:
    """`update_epochs` x `num_minibatches` PPO steps for every member of a population at once.

    settings: the iteration's PopulationSettings (from the plasticity method's `begin_iteration`); batch: the
    iteration's Batch (R, T, B) with its advantages and returns. Each member stops at its own target
    KL (its later minibatches leave it untouched, bit for bit). Returns {stat: (R,) list}.
    """
    config, actor, plasticity = population.config, population.actor, population.plasticity
    R, N = batch.obs.shape[0], batch.obs.shape[1] * batch.obs.shape[2]
    device, mb = population.device, N // config.num_minibatches
    steps = batch.for_update(population.norms, device)
    frozen = population.frozen_groups(settings)
    frozen_rows = None if frozen is None else frozen.index_select(1, population.actor_opt.group_of)  # (R, P)
    per_epoch = torch.tensor([c.target_kl_check == "epoch" for c in population.configs], device=device)
    stats, kl_stop = _UpdateStatistics(R, device), _KLStop(settings.target_kl, per_epoch)
    first_ratio_dev, noised = None, [0] * R
    sparse = actor.gated and actor.k < actor.n_experts
    offsets = torch.arange(R, device=device).unsqueeze(1) * N  # member r's steps are rows r*N.. of `steps`
    for epoch in range(config.update_epochs):
        live = (~kl_stop.stopped).tolist()  # one host sync per epoch: stopped members draw no permutation
        perm = np.stack([population.rngs[r].permutation(N) if live[r] else np.arange(N) for r in range(R)])
        flat_perm = torch.from_numpy(perm).to(device) + offsets
        counts = torch.zeros(R, actor.n_experts, device=device) if sparse else None  # experts chosen by stepped rows
        stepped_epoch = torch.zeros(R, dtype=torch.bool, device=device)
        for k in range(config.num_minibatches):
            loss, mb_stats, (actor.flat.grad, population.critic.flat.grad) = _minibatch_loss(
                population, settings, steps.take(flat_perm[:, k * mb:(k + 1) * mb].reshape(-1), R))
            with torch.no_grad():
                if first_ratio_dev is None:  # 0 up to rounding: the rollout's routing is replayed
                    first_ratio_dev = (mb_stats["ratio"] - 1.0).abs().amax(1)
                stepping = kl_stop.check(mb_stats["approx_kl"], epoch)  # checked before the step it would take
            mb_stats["grad_norm_actor"], mb_stats["grad_norm_critic"] = _gradient_step(
                population, settings, stepping, frozen, frozen_rows)
            plasticity.after_minibatch(stepping)
            with torch.no_grad():
                stats.add(mb_stats, stepping)
                stepped_epoch |= stepping
                if counts is not None:  # each stepping member's routing slots, added to its experts' counts
                    slots = mb_stats["experts"].reshape(R, -1)
                    counts.scatter_add_(1, slots, stepping.float().unsqueeze(1).expand(slots.shape))
        kl_stop.end_epoch(mb_stats["approx_kl"], epoch)
        for r, n in enumerate(plasticity.after_epoch(counts, stepped_epoch)):
            noised[r] += n
        if bool(kl_stop.stopped.all()):
            break
    out = stats.means()
    out.update(early_stop_epoch=kl_stop.epoch.tolist(), gradient_steps=stats.steps.tolist(),
               first_ratio_dev=first_ratio_dev.double().tolist(), noised_experts=noised)
    return out

# %% [markdown]
# ## Probe batch, checkpoints and the training loop
#
# The diagnostics of appendix 06e read a **fixed** probe batch (so rank or dormancy changes are the
# network's): `collect_probe` (07e) draws it from the config alone, the same after a resume.
#
# A **checkpoint** holds everything the next iteration reads (networks, optimiser moments and step
# counts, return normaliser, phase controller, random states, the environments' full state, current
# observations, running episodes, log rows), so a resumed run continues bit for bit. Its encoding,
# the folder's files and the log row's columns are in appendix 07e; `MemberStates` and resuming
# members that catch up with each other in 07d; locking, sealing and checking a folder in 07b.

# %% [markdown]
# ### One iteration, and `train`
#
# `iteration_step(state)` is one iteration of Algorithm 1 for every member, read top to bottom: the
# phase clock and the plasticity method's switch, the rollout, GAE and the return normalisers, the
# PPO update. It takes the `TrainState` (the population, its environments, the phase clock, the
# running episodes, the current observations, the iteration and the environment steps so far) and
# returns the next one with the iteration's `IterationLog`, PureJaxRL's `_update_step` with the
# population axis. Everything around it is the driver's (`train_members`, appendix 07d): building
# the population from its configs, resuming from checkpoints, the loop `state, log = step(state)`,
# the log rows and diagnostics (`IterationLogger`, 07e), checkpoints and the deadline.
# `max_iterations` stops a run early with a checkpoint (`resume` continues it).

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
    ablation switches and noise gamma, force_controller, fixed_phase). run_dirs: one folder per
    member (or None). Every member's result is bit-identical to training its config alone: same
    files, same metrics. Members with a finished folder are read back; members whose checkpoints
    stopped at different iterations catch up with each other and join (`train_members`, appendix
    07d). deadline: a `time.time()` at which training stops at the end of the current iteration
    with a checkpoint of every member; members that had not started by then are None. Returns one
    RunResult per config.
    """
    return train_members(configs, run_dirs, resume, iteration_step, max_iterations=max_iterations,
                         threads=threads, verbose=verbose, progress=progress, deadline=deadline)


class IterationLog(NamedTuple):
    """What one iteration hands the log (appendix 07e's IterationLogger), every member at once."""

    iteration: int
    phases: list  # each member's phase
    switch: bool  # the phase switched at this iteration's first slot
    global_step: int  # environment steps so far, per member
    settings: object  # the iteration's PopulationSettings
    batch: Batch  # the rollout (R, T, B), with advantages and returns
    step_stats: dict  # {key: (R,)}: the rollout's per-step means and routing readings
    episodes: list  # per member, the rows of the episodes that finished
    update: dict  # ppo_update's statistics, {stat: (R,) list}
    rollout_time: float  # seconds
    update_time: float  # seconds: GAE and the update


def iteration_step(ts: TrainState) -> tuple:
    """One iteration of every member: (the next TrainState, this iteration's IterationLog)."""
    pop, venv, it, c0 = ts.population, ts.venv, ts.iteration, ts.population.config
    obs, state = ts.obs, ts.state
    # --- 1. phase clock and plasticity method: the new phase from the switch's first slot -----------
    switch = ts.fixed_phases is None and bool(ts.clock.is_switch(it))
    phases = ts.fixed_phases or [int(ts.clock.phase_at(it))] * len(pop.configs)
    if ts.fixed_phases is None:
        venv.set_phase(phases[0])
    if switch:
        obs, state, _ = venv.reset()  # episodes restart under the new phase (Algorithm 1's order)
        ts.tracker.discard_running()
        pop.plasticity.on_switch(it)
    settings = pop.plasticity.begin_iteration(it)
    if c0.anneal_lr:
        frac = 1.0 - it / c0.iterations
        settings = dataclasses.replace(settings, lr_actor=settings.lr_actor * frac, lr_critic=settings.lr_critic * frac)

    # --- 2. rollout of every member's environments ----------------------------------------------------
    t0 = time.perf_counter()
    batch, obs, state, step_stats, episodes = collect_rollout(pop, venv, obs, state, settings, ts.tracker, it)
    rollout_time, t0 = time.perf_counter() - t0, time.perf_counter()

    # --- 3. advantages (GAE) per member, then the return normalisers ------------------------------------
    batch = batch.with_gae(c0.gamma, c0.gae_lambda)
    pop.norms.update(batch.returns)
    agent_rows = batch.obs.flatten(1, 2)  # (R, N, U, obs_dim)
    pop.plasticity.observe_rollout(agent_rows)  # rows for the next switch's probe batch, if it keeps any

    # --- 4. PPO update of every member --------------------------------------------------------------------
    update = ppo_update(pop, settings, batch)
    update_time = time.perf_counter() - t0
    routes = None if batch.routing is None else batch.routing.reshape(*agent_rows.shape[:3]).to(pop.device)
    step_stats.update(pop.actor.reroute_readings(agent_rows, routes))  # {} unless the update re-chooses routes

    global_step = ts.global_step + c0.batch_env_steps
    log = IterationLog(it, phases, switch, global_step, settings, batch, step_stats, episodes, update,
                       rollout_time, update_time)
    return ts._replace(obs=obs, state=state, iteration=it + 1, global_step=global_step), log

# %% [markdown]
# ## Demonstration: one PE-MAMoE run and one MLP run
#
# At the notebook's scale we train PE-MAMoE and the MLP baseline with the same seed. Runs go to
# `results/<scale>/<method>-s<seed>-<config hash>/`, the folders the sweep of notebook 09 uses for
# the same runs, so `make figures` (which trains the sweep first) finds them there; a finished run
# is read back instead of retrained.
#
# Where the run is already published as a record (appendix 09d: what a finished run keeps for
# the figures, committed for every scale but `ci`), the demonstration reads the record instead:
# a `medium` run is hours of training, and a fresh clone has no run folders. A record holds the
# same columns as the log, averaged over blocks of iterations in long runs (one row per
# iteration at `ci` and `small`), so the figure, the tables and the checks below read it
# unchanged. `retrain=True` trains (or reads the cached run folder) instead.

# %%
from pemamoe.core import repo_path

from types import SimpleNamespace

from pemamoe.records import find_record, read_record, verify_record

run_root = repo_path(results_dir) / scale
results = {}
for method in ("pemamoe", "mlp"):
    cfg = TrainConfig.for_scale(scale, method=method, seed=seed)
    t0 = time.perf_counter()
    marker = find_record(repo_path(records_dir), scale, cfg)  # the newest numerics version's record (appendix 09d)
    if not retrain and verify_record(marker, cfg) is not None:  # a damaged or foreign record raises, naming it
        results[method] = SimpleNamespace(config=cfg, metrics=read_record(marker)[1], from_cache="record")
    else:
        results[method] = train(cfg, run_root / cfg.run_name())
    print(f"{method:8s} {cfg.iterations} iterations, {cfg.total_env_steps} env steps, "
          f"{time.perf_counter() - t0:6.1f} s (cached: {results[method].from_cache}, "
          f"{len(results[method].metrics)} log rows)")

# %%
import matplotlib.pyplot as plt

from pemamoe.analysis import plot_reference_levels, reference_levels
from pemamoe.core import save_figure


def _smooth(y, w):
    return pd.Series(y).rolling(w, min_periods=1).mean().to_numpy()


cfg0 = results["pemamoe"].config
_block = int(results["pemamoe"].metrics.get("iterations", pd.Series([1])).iloc[0])  # iterations per row (a record's block)
w = max(1, cfg0.phase_length_iters // 8 // _block)  # smooth over an eighth of a phase
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
# ![MAPPO training curves, one seed per method, medium scale](../paper_figures/mappo_training_curves.png)

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
# **What this run shows, honestly.** At `ci` scale six iterations prove only that the loop runs,
# the switches fire at iterations 2 and 4 (the controller's settings show in the logged columns)
# and every column the figures need is produced.
#
# At larger scales read the table phase by phase. Raw returns compare only *within* a phase type
# (the class reward per served user rises 5, 10, 20 from phase to phase, so the return is a
# staircase whether or not the policy improves). A small approximate KL and clip fractions of a
# few per cent mean healthy updates; an explained variance near 0, a critic that has not learned
# the return. The MLP's rank (one trunk) is not like for like with the mean of three experts. One
# seed shows what a run looks like; which method is better is notebook 09's question.
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
