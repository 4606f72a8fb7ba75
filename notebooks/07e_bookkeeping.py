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
# # 07e · Appendix: the trainer's bookkeeping
#
# What the training loop of notebook 07 keeps while it runs, and a reader of the method can skip,
# in the module `pemamoe.bookkeeping`: the per-environment episode accounting (`EpisodeTracker`),
# the per-iteration log row (`IterationLogger`), the running normaliser of the returns
# (`RunningNorm`, one per member in `ValueNorms`), the encoding of a checkpoint into tensors and
# plain types, the atomic writers, the deterministic-torch context, and the split and merge of a
# population's environment state into one state per member. The run's configuration is appendix
# 07c's; the population that owns these pieces is appendix 07d's.
#
# The module does not import `pemamoe.mappo`; `pemamoe.mappo` imports it and re-exports the names
# callers import from it.

# %%
#| default_exp bookkeeping

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %%
import numpy as np
import pandas as pd
import torch

from pemamoe.train_config import TrainConfig

# %% [markdown]
# ## Episodes and the per-iteration log row
#
# `EpisodeTracker` keeps running sums of each environment's current episode (team return, length,
# the summed costs and the slot-averaged system metrics) and emits one row per finished episode:
# these rows are `episodes.parquet`. For a population of R runs the B·R environments are split into
# R equal blocks, and each block numbers its episodes and environments from 0, exactly as a run
# alone would, so a member's episode log does not depend on its neighbours. At a phase switch the
# environments restart and `discard_running` forgets the unfinished episodes. Its state is part of
# the checkpoint, per member.
#
# `IterationLogger` is what the training loop reports after each iteration, so that the loop itself
# holds no logging code. For each member it builds one row of `metrics.parquet` from the
# iteration's pieces: the episodes that ended in it, the step statistics of the rollout, the
# update's statistics (in `ppo_update`'s order), the explained variance of the critic, the learning
# rate of every parameter group and the schedule the phase controller handed out, the log-std and
# the value normaliser's mean and standard deviation, and, for sparse gating, the share of rollout
# rows routed to each expert. Then come the plasticity method's own columns (a method may not
# reuse a trainer column: that is an error naming them), the diagnostics of appendix 06e on the
# iterations that take them (every `diag_every`-th, each switch and the last) and the timing
# columns. The row joins the member's log, and the episodes that ended join its episode log. For
# the population as a whole it keeps a `Progress` report (appendix 00b: a bar in a terminal, plain
# lines in a log, cleared when the run is interrupted) and, with `verbose`, prints one line per
# iteration. It reads the trainer's objects
# (the `Population` of notebook 07, the `MemberStates` of appendix 07d) by their attributes,
# without importing their modules, which sit above this one.

# %%
#| export
import io
import math
import os
import pickle
import shutil
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from pemamoe.core import Progress, atomic_path
from pemamoe.diagnostics import plasticity_diagnostics
from pemamoe.env import UAVVectorEnv
from pemamoe.runs import seal_checkpoint
from pemamoe.train_config import training_numerics

CHECKPOINT_FORMAT = 5  # 5: sealed with its sha256 and stamped with TRAINING_NUMERICS; 4: rows in chunks (below)
_EPISODE_SUMS = ("qos", "energy", "collision", "overlap", "collisions")
_EPISODE_MEANS = ("coverage", "served_users", "admitted_users", "uav_using_rate", "energy_rate_kj")


class EpisodeTracker:
    """Running sums of each environment's current episode; one row per finished episode.

    With `members` > 1 the environments are split into that many equal blocks (one per run of
    a population): each block numbers its episodes and its environments from 0, exactly as if
    it ran alone, and `update` returns one list of rows per member.
    """

    def __init__(self, num_envs: int, members: int = 1):
        if num_envs % members:
            raise ValueError(f"num_envs={num_envs} must split into members={members} equal blocks")
        self.num_envs, self.members, self.per_member = num_envs, members, num_envs // members
        self.episodes = np.zeros(members, dtype=np.int64)
        self.ret = np.zeros(num_envs)
        self.length = np.zeros(num_envs, dtype=np.int64)
        self.phase_start = np.full(num_envs, -1, dtype=np.int64)
        self.sums = {k: np.zeros(num_envs) for k in _EPISODE_SUMS + _EPISODE_MEANS}

    def update(self, reward, info, terminated, truncated, iteration: int) -> list:
        """Add one step; returns the finished episodes' rows (of every member, in environment order)."""
        return [row for rows in self.update_members(reward, info, terminated, truncated, iteration) for row in rows]

    def update_members(self, reward, info, terminated, truncated, iteration: int) -> list:
        """Add one step; returns one list of finished-episode rows per member."""
        phase = np.asarray(info["phase"], dtype=np.int64)
        self.phase_start = np.where(self.length == 0, phase, self.phase_start)
        self.ret += reward
        self.length += 1
        for k in self.sums:
            self.sums[k] += np.asarray(info[k], dtype=float)
        rows = [[] for _ in range(self.members)]
        for b in np.flatnonzero(terminated | truncated):
            n, r = int(self.length[b]), int(b // self.per_member)
            row = {"episode": int(self.episodes[r]), "iteration": int(iteration), "env": int(b % self.per_member),
                   "phase": int(phase[b]), "phase_start": int(self.phase_start[b]), "return": float(self.ret[b]),
                   "length": n, "terminated": bool(terminated[b]), "truncated": bool(truncated[b] and not terminated[b])}
            row.update({k: float(self.sums[k][b]) for k in _EPISODE_SUMS})
            row.update({k: float(self.sums[k][b] / n) for k in _EPISODE_MEANS})
            rows[r].append(row)
            self.episodes[r] += 1
            self._clear(b)
        return rows

    def _clear(self, b) -> None:
        self.ret[b], self.length[b] = 0.0, 0
        for k in self.sums:
            self.sums[k][b] = 0.0

    def discard_running(self) -> None:
        """Forget every unfinished episode (the environments were restarted)."""
        self._clear(slice(None))

    def member_state(self, r: int) -> dict:
        rows = slice(r * self.per_member, (r + 1) * self.per_member)
        return {"episodes": int(self.episodes[r]), "ret": torch.from_numpy(self.ret[rows].copy()),
                "length": torch.from_numpy(self.length[rows].copy()),
                "phase_start": torch.from_numpy(self.phase_start[rows].copy()),
                "sums": {k: torch.from_numpy(v[rows].copy()) for k, v in self.sums.items()}}

    def load_member_state(self, r: int, state: dict) -> None:
        rows = slice(r * self.per_member, (r + 1) * self.per_member)
        self.episodes[r] = int(state["episodes"])
        self.ret[rows], self.length[rows] = state["ret"].numpy(), state["length"].numpy()
        self.phase_start[rows] = state["phase_start"].numpy()
        for k, v in state["sums"].items():
            self.sums[k][rows] = v.numpy()

    def state_dict(self) -> dict:
        if self.members != 1:
            raise ValueError("state_dict() is for a single run; use member_state(r)")
        return self.member_state(0)

    def load_state_dict(self, state: dict) -> None:
        self.load_member_state(0, state)

# %%
#| export
def explained_variance(pred, target) -> float:
    """1 - Var[target - pred] / Var[target] (nan when the target is constant)."""
    pred, target = torch.as_tensor(pred, dtype=torch.float64), torch.as_tensor(target, dtype=torch.float64)
    var = target.var(unbiased=False)
    return float("nan") if var == 0 else float(1 - (target - pred).var(unbiased=False) / var)


class IterationLogger:
    """The training loop's report of each iteration: per member one row of `metrics.parquet` and
    the episodes that ended; for the population the progress bar and, with `verbose`, one line.

    population: the trainer's Population (its configs, networks, plasticity method, normalisers);
    members: its MemberStates (the log rows it appends to, each member's training seconds); probes:
    per member the fixed (observations, states) batch of the diagnostics; start: the first iteration.
    """

    def __init__(self, population, members, probes: list, start: int, progress: bool | None, verbose: bool):
        self.population, self.members, self.probes, self.verbose = population, members, probes, verbose
        config, R = population.config, len(population.configs)
        self.bar = Progress(config.iterations, start, label=config.method if R == 1 else f"{config.method} x{R}",
                            enabled=progress)

    def record(self, log) -> None:
        """Log one iteration from its IterationLog (notebook 07): every member's row of the trainer's
        columns, the plasticity method's own columns and, at diagnostic iterations, the plasticity
        diagnostics; the timing columns; the finished episodes' rows."""
        pop, members, config = self.population, self.members, self.population.config
        it, sched = log.iteration, log.settings
        diagnose = it % config.diag_every == 0 or log.switch or it == config.iterations - 1
        for r in range(len(pop.configs)):
            row = self._row(r, log)
            own = pop.plasticity.metrics(r)  # the method's own columns (none for most methods)
            if own.keys() & row.keys():
                raise ValueError(f"{type(pop.plasticity).__name__}.metrics names trainer columns: "
                                 f"{sorted(own.keys() & row.keys())}")
            row.update(own)
            t1 = time.perf_counter()
            if diagnose:
                actor, critic = pop.member(r)
                row.update(plasticity_diagnostics(actor, critic, self.probes[r][0], self.probes[r][1],
                                                  sched.members[r].policy_temperature))
            diag_time, seconds = time.perf_counter() - t1, members.seconds(r)
            row.update(sps=config.batch_env_steps / max(log.rollout_time + log.update_time, 1e-9),
                       sps_total=log.global_step / max(seconds, 1e-9), rollout_time=log.rollout_time,
                       update_time=log.update_time, diag_time=diag_time, wall_time=seconds, population=len(pop.configs))
            members.metrics_rows[r].append(row)
            members.episode_rows[r] += log.episodes[r]
        self._show(it, log.phases)

    def _row(self, r, log) -> dict:
        """Member r's row of the trainer's own columns."""
        pop, batch, sched, global_step = self.population, log.batch, log.settings, log.global_step
        actor, norm = pop.actor, pop.norms.norms[r]
        agents = batch.obs.shape[3]  # (R, T, B, U, obs_dim)
        row = {"iteration": log.iteration, "phase": log.phases[r], "switch": log.switch, "env_steps": global_step,
               "agent_steps": global_step * agents}
        episodes, step_stats, update = log.episodes[r], log.step_stats, log.update
        ep = pd.DataFrame(episodes)
        row["episodes"] = len(ep)
        for name, col in (("episode_return", "return"), ("episode_length", "length"), ("coverage", "coverage"),
                          ("served_users", "served_users"), ("uav_using_rate", "uav_using_rate"),
                          ("energy_rate_kj", "energy_rate_kj"), ("collisions_per_episode", "collisions")):
            row[name] = float(ep[col].mean()) if len(ep) else float("nan")
        row.update({k: float(v[r]) for k, v in step_stats.items()})
        row.update({k: v[r] for k, v in update.items()})  # ppo_update's statistics, in its order
        row["explained_variance"] = explained_variance(batch.values[r].reshape(-1), batch.returns[r].reshape(-1))
        s = sched.members[r]
        lr_a, lr_c = float(sched.lr_actor[r]), float(sched.lr_critic[r])
        for name in pop.group_names:
            row[f"lr/{name}"] = 0.0 if (name == "router" and s.router_frozen) else lr_a
        row["lr/critic"] = lr_c
        row.update({"clip_coef": s.clip_coef, "target_kl": float("nan") if s.target_kl is None else s.target_kl,
                    "ent_coef": s.ent_coef, "kl_coef": s.kl_coef,
                    "temperature/policy": s.policy_temperature, "temperature/value": s.value_temperature,
                    "router_frozen": s.router_frozen, "conservative": s.conservative,
                    "noise_epochs_left": s.noise_epochs_left,
                    "log_std_mean": float(actor.params()["log_std"][r].detach().double().mean()),
                    "value_norm/mean": float(norm._mean()), "value_norm/std": float(norm.std)})
        if batch.routing is not None and actor.k < actor.n_experts:
            counts = torch.bincount(batch.routing.experts[r].reshape(-1).cpu(),
                                    minlength=actor.n_experts).double()
            for j, c in enumerate(counts / counts.sum()):
                row[f"rollout/expert_frac{j}"] = float(c)
        return row

    def _show(self, it, phases) -> None:
        """The progress bar's step and, with verbose, a line: the members' mean return of the episodes
        that ended in this iteration, and the update speed of member 0."""
        last = [rows[-1] for rows in self.members.metrics_rows]
        recent = [row["episode_return"] for row in last if np.isfinite(row["episode_return"])]
        recent = float(np.mean(recent)) if recent else float("nan")
        same = len(set(phases)) == 1
        if self.verbose:
            shown = phases[0] if same else "/".join(map(str, phases))
            print(f"it {it:5d} phase {shown} return {recent:9.2f} sps/member {last[0]['sps']:7.0f}", flush=True)
        self.bar.set_postfix(phase=phases[0] if same else "mixed", ret=f"{recent:.1f}", sps=f"{last[0]['sps']:.0f}")
        self.bar.update(1)

    def __enter__(self):
        return self

    def __exit__(self, kind, error, trace) -> None:
        self.bar.close(clear=kind is not None)  # an interrupted run leaves no stale bar under its message

# %% [markdown]
# Two environments of two members, a few random steps: each member's episodes are numbered from 0
# in its own block.

# %%
from pemamoe.env import UAVVectorEnv

_venv = UAVVectorEnv(4, seed)
_tracker = EpisodeTracker(4, members=2)
_venv.reset()
_rng = np.random.default_rng(seed)
_rows = [[], []]
for _ in range(40):
    _obs, _state, _rew, _term, _trunc, _info = _venv.step(_rng.uniform(-1, 1, size=(4, _venv.n_agents, 2)))
    for _r, _done in enumerate(_tracker.update_members(np.asarray(_rew, dtype=float), _info, _term, _trunc, 0)):
        _rows[_r] += _done
assert all([row["episode"] for row in rows] == list(range(len(rows))) for rows in _rows)
assert all(row["env"] in (0, 1) for rows in _rows for row in rows)
pd.DataFrame(_rows[1])[["episode", "env", "phase", "return", "length", "terminated", "truncated"]]

# %% [markdown]
# ## The probe batch of the diagnostics
#
# The plasticity diagnostics of appendix 06e need a **fixed** probe batch, so that a change in
# expert rank or dormant fraction reflects the network and not the data. `collect_probe` draws it
# once per run from a separate copy of the environment (its own seed, random actions, a third of
# the rows from each phase); it depends only on the config, so a resumed run rebuilds the same one.

# %%
#| export
def collect_probe(config, steps_per_phase: int | None = None):
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


# %% [markdown]
# The logged columns of one row: a two-iteration MLP run at the ci scale, its last row.

# %%
from pemamoe.mappo import train

_m = train(TrainConfig.for_scale("ci", method="mlp", seed=seed, iterations=2)).metrics
pd.set_option("display.max_rows", 200)
pd.DataFrame({"column": _m.columns, "last value": [_m[c].iloc[-1] for c in _m.columns]})

# %% [markdown]
# ## The return normaliser
#
# Notebook 07 explains why the critic regresses normalised returns. `RunningNorm` keeps the count,
# mean and variance of every return it has seen, in float64, and absorbs a new batch with the
# parallel update of Chan et al.: with $n_a$ values of mean $\mu_a$ and variance $\sigma_a^2$ so
# far, a batch of $n_b$ values of mean $\mu_b$ and variance $\sigma_b^2$, and $\delta = \mu_b - \mu_a$,
# $$n = n_a + n_b, \qquad \mu = \mu_a + \delta\,\frac{n_b}{n}, \qquad
#   \sigma^2 = \frac{n_a\sigma_a^2 + n_b\sigma_b^2 + \delta^2\,n_a n_b / n}{n}.$$
# With `enabled=False` (`value_norm=False`) it is the identity. Its state is part of the
# checkpoint. `ValueNorms` holds one per member of a population and applies them to tensors whose
# leading axis is the member.

# %%
#| export
import math


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

# %% [markdown]
# Batches absorbed one at a time give the mean and variance of all of them at once:

# %%
_norm = RunningNorm()
_x = torch.randn(1000, dtype=torch.float64, generator=torch.Generator().manual_seed(seed)) * 30 + 500
for _chunk in _x.split(300):
    _norm.update(_chunk)
assert math.isclose(_norm.mean, float(_x.mean()), rel_tol=1e-12)
assert math.isclose(_norm.var, float(_x.var(unbiased=False)), rel_tol=1e-9)
print(f"mean {_norm.mean:.3f}, std {_norm.std:.3f}; normalised first value {float(_norm.normalize(_x[0])):.3f}")

# %% [markdown]
# ## Checkpoints and the run folder
#
# A **checkpoint** holds everything the next iteration reads: both networks, the optimiser (its
# moments and step counts), the return normaliser, the phase controller (its KL reference, noise
# budget and random generator), the torch and numpy random states, the environments' complete
# state including their random streams, the current observations, the running episodes and the
# log rows so far. Everything is stored as tensors, plain numbers, strings and dicts, so
# `torch.load(..., weights_only=True)` reads it without unpickling code: `encode_arrays` turns
# every numpy array of the environment's state into a marked tensor, and `decode_arrays` turns it
# back. Files are written to a temporary name and renamed, so a killed run leaves the previous
# complete file, never a torn one.
#
# The log rows are the bulk of a late checkpoint (a `medium` run's reach 13,200 metric rows of 112
# numbers and some 190,000 episode rows), and `torch.save` pickles every one of those millions of
# numbers through its Python-level pickler: about 3 s per member per checkpoint at 7,000
# iterations, so a 12-member population spent 40 s of every 100 iterations writing checkpoints
# (read from the medium sweep's checkpoint of MoE at iteration 7,100 and its logged wall clock, for
# `5a5f133`; `benchmarks/bench_train.py` times both forms side by side).
# Format 3 (`5a5f133`) had `_pack_rows` pickle the rows with the standard C pickler into one
# `bytes` object (0.2 s of pickling; with `torch.save` storing that object, about 1 s per member at
# the end of a `medium` run, against 4-6 s as lists); `_unpack_rows` reads pickled rows back with an
# unpickler that refuses every class and function, so the rows (plain dicts of numbers, strings and
# booleans) come back as the very objects they were and the file still holds no code. Checkpoints
# of formats 3 and 2 (rows stored as lists) are still read.
#
# Packing all rows at every checkpoint still makes a run's checkpoints cost grow with the square of
# its length: a `medium` run rewrites its rows 132 times, the last time 13,200 metric and some
# 190,000 episode rows. A `RowLog` is a member's list of rows that remembers what it has already
# encoded. Rows are only ever appended, never changed, so each checkpoint pickles only the rows
# added since the previous one and stores the list of pickled chunks (checkpoint format 4). Each
# chunk is a `uint8` tensor: `torch.save` writes a tensor's bytes as they are, but passes a
# `bytes` object through a latin-1 string, about 6x slower. Likewise each log flush turns only the
# new rows into a table and appends it to the table made before: building a `DataFrame` from row
# dicts is most of a parquet write. At the end of a `medium` run this takes one member's
# checkpoint from about 1.0 s to 0.07 s for the rows and its logs from about 2.0 s to 0.6-0.9 s
# (`make bench`, the checkpoint line, which times all the forms side by side; code at the commit
# that introduced format 4). The last write of a finished run, the one `done.json` seals,
# converts all rows at once as before, so a run's final logs are the same bytes however often it
# was checkpointed or resumed; only the logs of an unfinished run come from pieces.
#
# Format 5 keeps format 4's content and adds two safeguards (notebook 07b): `write_checkpoint`
# stamps every checkpoint with `CHECKPOINT_FORMAT` and `TRAINING_NUMERICS`, the version of the
# arithmetic that computed it, which `load_checkpoint` compares with the running code's before a
# run resumes; and it seals the file with its sha256 before the rename (`seal_checkpoint`), which
# `load_checkpoint` verifies, so bytes damaged on disk are refused instead of resumed. A
# `RuntimeError` of torch's zip writer (what a full disk gives, with neither the file nor the
# cause in its message) becomes an `OSError` that names the checkpoint and says the disk may be
# full. Checkpoints of format 4 and older (no seal, numerics version 1) are still read.
#
# A population steps all of its members' environments as one vector environment, but each member
# checkpoints alone, so that its folder is the same as if it had trained by itself.
# `split_env_state` cuts the population's environment state down to one member's rows;
# `merge_env_states` concatenates the members' states again when a population resumes. A phase
# shared by all environments stays one number; per-environment phases (members in different fixed
# phases) are sliced and concatenated like the other arrays.
#
# `DeterministicTorch` holds torch to deterministic algorithms and a fixed thread count for the
# length of a run and restores both afterwards; the thread count is recorded, since results with
# one and two threads differ in the last bits. Appendix 07d writes and reads checkpoints with these
# functions (`write_checkpoint`, `write_rows_parquet`, `encode_arrays`, `decode_arrays`) and runs
# a population inside `DeterministicTorch`; the helpers they call stay private to this module.
#
# Run directory layout:
#
# | file | content |
# |---|---|
# | `config.json` | the resolved `TrainConfig` (`TrainConfig.from_dict` reads it back) |
# | `metrics.parquet` | one row per iteration (`IterationLogger`: the trainer's columns, the plasticity method's, diagnostics and timing) |
# | `episodes.parquet` | one row per finished training episode (`EpisodeTracker`) |
# | `checkpoint.pt` | the resumable state (above) |
# | `done.json` | written last: the run finished, sealed with its config hash, iteration count and the logs' sha256; `train` then returns the stored result once it verifies (notebook 07b) |
# | `.lock` | the writer's lock, holding its PID (notebook 07b) |

# %%
#| export
def encode_arrays(obj):
    """Nested numpy state -> tensors and plain types (torch.load(weights_only=True) safe)."""
    if isinstance(obj, np.ndarray):
        return {"__ndarray__": torch.from_numpy(np.ascontiguousarray(obj).copy())}
    if isinstance(obj, dict):
        return {k: encode_arrays(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(encode_arrays(v) for v in obj)
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def decode_arrays(obj):
    """The inverse of `encode_arrays`: marked tensors back to numpy arrays (copies)."""
    if isinstance(obj, dict):
        if set(obj) == {"__ndarray__"}:
            return obj["__ndarray__"].numpy().copy()
        return {k: decode_arrays(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(decode_arrays(v) for v in obj)
    return obj


class _PlainUnpickler(pickle.Unpickler):
    """Unpickles plain data only: any class or function in the stream is refused."""

    def find_class(self, module, name):
        raise pickle.UnpicklingError(f"checkpoint log rows may hold only plain data, found {module}.{name}")


def _pack_rows(rows: list) -> bytes:
    """Log rows (dicts of plain numbers, strings and booleans) as one pickled bytes object."""
    return pickle.dumps(rows, protocol=pickle.HIGHEST_PROTOCOL)


def _unpack_rows(packed) -> list:
    """The rows of a checkpoint: a list of pickled chunks as uint8 tensors (format 4), one pickled
    bytes object (format 3, `_pack_rows`) or a plain list of rows (format 2); always a new list."""
    if isinstance(packed, (bytes, bytearray)):
        return _PlainUnpickler(io.BytesIO(packed)).load()
    if _is_chunks(packed):
        return [row for chunk in packed for row in _PlainUnpickler(io.BytesIO(chunk.numpy().tobytes())).load()]
    return list(packed)


def _is_chunks(packed) -> bool:
    """Whether a checkpoint's rows are format 4's chunks (an empty list reads the same either way)."""
    return isinstance(packed, list) and bool(packed) and all(torch.is_tensor(chunk) for chunk in packed)


def _chunk(rows: list) -> torch.Tensor:
    # a tensor, not bytes: torch.save writes a tensor's storage as it is, but pickles bytes (protocol
    # 2) through a latin-1 string, about 6x slower
    return torch.frombuffer(bytearray(_pack_rows(rows)), dtype=torch.uint8)


class RowLog(list):
    """One member's log rows (dicts of plain data), appended to and never changed, that remember
    what they have encoded: `packed()` pickles and `frame()` converts only the rows added since
    the last call, so a checkpoint costs what the new rows cost, not what all rows cost."""

    def __init__(self, rows=()):
        super().__init__(rows)
        self.release()

    def _append_only(self, *args, **kwargs):
        raise TypeError("a RowLog is append-only: its encoded rows would go stale")

    __setitem__ = __delitem__ = insert = pop = remove = clear = sort = reverse = _append_only

    def release(self) -> None:
        """Drop the cached encodings (after the last write of a run: they are as large as the rows);
        the next `packed()` and `frame()` encode every row afresh."""
        self._chunks, self._n_packed = [], 0
        self._frame, self._n_framed = pd.DataFrame(), 0

    @classmethod
    def from_checkpoint(cls, packed) -> "RowLog":
        """The rows of a checkpoint's "metrics_rows" or "episode_rows"; format 4's chunks are kept."""
        log = cls(_unpack_rows(packed))
        if _is_chunks(packed):
            log._chunks, log._n_packed = list(packed), len(log)
        return log

    def packed(self) -> list:
        """Every row as a list of pickled chunks (checkpoint format 4): only new rows are pickled."""
        if len(self) > self._n_packed:
            self._chunks.append(_chunk(self[self._n_packed:]))
            self._n_packed = len(self)
        return list(self._chunks)

    def frame(self) -> pd.DataFrame:
        """Every row as a DataFrame: the table made before, extended by one of the new rows."""
        if len(self) > self._n_framed:
            new = pd.DataFrame(self[self._n_framed:])
            self._frame = new if self._n_framed == 0 else pd.concat([self._frame, new], ignore_index=True)
            self._n_framed = len(self)
        return self._frame


def write_checkpoint(obj, path: Path) -> None:
    """Write a checkpoint: `obj` stamped with CHECKPOINT_FORMAT and TRAINING_NUMERICS, saved by
    torch to a temporary file, sealed with its sha256 (pemamoe.runs.seal_checkpoint) and renamed
    onto `path`. A failed write (a full disk, most often) raises OSError naming `path`."""
    path = Path(path)
    with atomic_path(path) as tmp:
        try:
            torch.save({**obj, "format": CHECKPOINT_FORMAT, "numerics": training_numerics()}, tmp)
            seal_checkpoint(tmp)
        except RuntimeError as err:  # torch's writer: "[enforce fail at inline_container.cc:...]", "file write failed"
            if "inline_container" not in str(err) and "write" not in str(err).lower():
                raise
            raise OSError(f"cannot write the checkpoint {path}: torch.save failed ({err}); the disk may be full "
                          f"(no space left on device: {_free_space(path.parent)} free there), or the folder is "
                          "not writable. Free some space; the run resumes from its previous checkpoint") from err
        except OSError as err:
            message = (f"cannot write the checkpoint {path} ({err.strerror or err}); if the disk is full, free some "
                       "space: the run resumes from its previous checkpoint")
            raise (OSError(err.errno, message) if err.errno else OSError(message)) from err


def _free_space(folder: Path) -> str:
    try:
        return f"{shutil.disk_usage(folder).free / 2**20:,.1f} MiB"
    except OSError:
        return "unknown"


def write_rows_parquet(rows, path: Path, final: bool = True) -> None:
    """rows (a list, or a RowLog whose cached tables serve a non-final write) -> a parquet file.
    final: convert every row at once, so that the file does not depend on how it was built."""
    frame = rows.frame() if not final and isinstance(rows, RowLog) else pd.DataFrame(rows)
    with atomic_path(path) as tmp:
        frame.to_parquet(tmp, engine="pyarrow", index=False)


# Deterministic mode also NaN-fills every new uninitialised tensor, a debugging aid that costs about
# 47k fill kernels per paper-preset iteration. The trainer reads no uninitialised memory: a run
# trains to the same bits with the fill on and off (tests/test_numerics.py), so it is off.
FILL_UNINITIALIZED_MEMORY = False


class DeterministicTorch:
    """Single-threaded, deterministic torch for the duration of a run (restored afterwards)."""

    def __init__(self, threads: int | None):
        self.threads = threads

    def __enter__(self):
        fill = torch.utils.deterministic
        self.old = (torch.get_num_threads(), torch.are_deterministic_algorithms_enabled(), fill.fill_uninitialized_memory)
        if self.threads is not None:
            torch.set_num_threads(int(self.threads))
        # cuBLAS needs a fixed workspace for deterministic products on a GPU; read when CUDA starts
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True)
        fill.fill_uninitialized_memory = FILL_UNINITIALIZED_MEMORY
        return self

    def __exit__(self, *exc):
        torch.set_num_threads(self.old[0])
        torch.use_deterministic_algorithms(self.old[1])
        torch.utils.deterministic.fill_uninitialized_memory = self.old[2]
        return False

# %%
#| export
def split_env_state(state: dict, rows) -> dict:
    """The environment state (UAVVectorEnv.state_dict) of environments `rows` only."""
    rows = np.asarray(rows)
    rng = state["rng"]
    return {"arrays": {k: v[rows].copy() for k, v in state["arrays"].items()},
            "rng": {"buffers": {k: v[rows].copy() for k, v in rng["buffers"].items()},
                    "cursor": {k: v[rows].copy() for k, v in rng["cursor"].items()},
                    "generators": [rng["generators"][i] for i in rows]},
            "external_phase": _member_phases(state["external_phase"], rows)}


def merge_env_states(states: list) -> dict:
    """Concatenate member environment states (inverse of split_env_state)."""
    first = states[0]
    return {"arrays": {k: np.concatenate([s["arrays"][k] for s in states]) for k in first["arrays"]},
            "rng": {"buffers": {k: np.concatenate([s["rng"]["buffers"][k] for s in states]) for k in first["rng"]["buffers"]},
                    "cursor": {k: np.concatenate([s["rng"]["cursor"][k] for s in states]) for k in first["rng"]["cursor"]},
                    "generators": [g for s in states for g in s["rng"]["generators"]]},
            "external_phase": _merged_phases([s["external_phase"] for s in states],
                                             [len(s["arrays"]["phase"]) for s in states])}


def _member_phases(external, rows):
    """One phase for all environments stays an int; a per-environment phase array is sliced."""
    return external if np.ndim(external) == 0 else np.asarray(external)[rows].copy()


def _merged_phases(phases: list, sizes: list):
    if all(np.ndim(p) == 0 for p in phases) and len({int(p) for p in phases}) == 1:
        return phases[0]
    return np.concatenate([np.broadcast_to(np.asarray(p, dtype=np.int64), (n,)) for p, n in zip(phases, sizes)])

# %% [markdown]
# Splitting a population's environment state per member and merging it again gives back the same
# state, and the encoded form survives `torch.save` and a `weights_only` load:

# %%
import io


def _same(a, b):
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray):
        return np.array_equal(a, b)
    return a == b


_full = _venv.state_dict()
_parts = [split_env_state(_full, range(0, 2)), split_env_state(_full, range(2, 4))]
assert _same(merge_env_states(_parts), _full)
_buf = io.BytesIO()
torch.save(encode_arrays(_parts[1]), _buf)
_buf.seek(0)
assert _same(decode_arrays(torch.load(_buf, weights_only=True)), _parts[1])
print("split -> merge and encode -> save -> load -> decode give back the same state")
