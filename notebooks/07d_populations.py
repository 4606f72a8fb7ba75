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
# # 07d · Appendix: populations of runs, resuming, reading a run back and evaluating it
#
# Notebook 07 is the method: the rollout, GAE, the PPO update and the loop that ties them
# together. That loop trains a *population* of runs at once, and a run can stop and resume from
# its checkpoint. This appendix holds the machinery around the loop that a reader of the method
# can skip, in one module, `pemamoe.populations`:
#
# * which runs may share a population (`MEMBER_FIELDS`, `check_population`, `population_key`,
#   the sweep's grouping key) and which plasticity method a member runs (`plasticity_name`);
# * what a run returns (`RunResult`) and how a finished run folder is read back (`load_run`);
# * `train_members`, the bookkeeping of `train_population` around the loop: argument checks,
#   finished members read back, folders locked and prepared, checkpoints loaded, and members that
#   stopped at different iterations caught up and joined into one population;
# * `MemberStates`, the parts of the members that a checkpoint stores, with the code that writes
#   one member's checkpoint and logs and reads every member's checkpoint back;
# * `evaluate_policy`, fresh episodes with a trained actor's mean action (no learning).
#
# The module does not import `pemamoe.mappo`: `train_population` hands its training loop to
# `train_members` as an argument, and `pemamoe.mappo` re-exports the names callers import from it
# (`from pemamoe.mappo import load_run` works, as does `from pemamoe.populations import load_run`).
# The run folders' rules are in appendix 07b, the configuration in 07c, the checkpoint encoding in 07e.
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
# gamma), `force_controller` and `fixed_phase` (different fixed phases, but either all members
# cycle or none does); `check_population` refuses anything else, naming the field.
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
# **What it buys, and where it stops.** `make bench` measures it (figures in `benchmarks/RESULTS.md`; the rates
# with the training code of `8ca3ef6`, the profile with the benchmark of `be55e3e`): on one
# core, a 16-member PE-MAMoE population at the paper preset trains 3,039 member environment steps
# per second, 3.7x a lone run. The same benchmark profiles a 16-member iteration: the matrix
# products alone take 29 % of it, so even with every other cost removed the population could not
# pass about 10,150 steps per second. Going further needs fewer or faster products. The gated networks
# compute all three experts for every row and keep one, because no top-1 formulation has yet kept
# a member's bits independent of its neighbours; and the router and noise-gate products (149
# inputs, 3 outputs) run far below the core's speed, while fusing them into the experts' product
# changes their last bits and with them every cached result.

# %%
#| default_exp populations

# %% tags=["parameters"]
scale = "small"  # `make figures` passes these to every notebook; this one draws no figure
figures_dir = "paper_figures"

# %%
#| export
import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd
import torch
import torch.nn as nn

import pemamoe.phase_controller  # noqa: F401  registers PhaseController (notebook 06)
import pemamoe.plasticity_baselines  # noqa: F401  registers ReDo and shrink-and-perturb (appendix 06c)
from pemamoe.bookkeeping import (DeterministicTorch, EpisodeTracker, RowLog, ValueNorms, decode_arrays,
                                  encode_arrays, merge_env_states, split_env_state, write_checkpoint,
                                  write_rows_parquet)
from pemamoe.bookkeeping import IterationLogger, collect_probe  # the log rows and the probe batch (appendix 07e)
from pemamoe.env import EnvConfig, UAVVectorEnv, observation_dim, state_dim, vector_seeds
from pemamoe.phases import PhaseClock
from pemamoe.nets import PopulationActor, PopulationCritic, make_actor, make_critic
from pemamoe.optim import RunAdamW, group_index
from pemamoe.plasticity import plasticity_method
from pemamoe.runs import (UNRECORDED_PROCESSOR, check_run_dir, load_checkpoint, lock_run, prepare_run_dir,
                          read_config, read_parquet, training_processor, verify_done, write_done)
from pemamoe.train_config import TrainConfig, resolve_device

# %% [markdown]
# ## Who may share a population
#
# Members of one population share everything that shapes the tensors and the loop (method,
# network sizes, rollout and update settings, the environment) and may differ only in
# `MEMBER_FIELDS`. `population_key` is what they must share, as a string: the sweep groups its runs
# by it. `check_population` names the first shared field on which two members disagree.
# `plasticity_name` is the plasticity method a member runs: its method's, or the phase controller
# for a baseline with `force_controller`. Members with no plasticity method and members with the
# phase controller may mix: the controller serves both, and a member for which it is off behaves
# exactly as one with no plasticity method.

# %%
#| export
# Fields that members of one population may set differently; every other field is shared.
# (fixed_phase: members may sit in different fixed phases, but either all cycle or none does;
# lr, the entropy anneal and the target KL reach the update only through each member's schedule,
# and target_kl_check through a per-member mask, so a grid over them trains as one population.)
MEMBER_FIELDS = ("seed", "controller", "force_controller", "fixed_phase", "lr", "ent_start", "ent_end", "target_kl",
                 "target_kl_check")


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
# ## The result of a run, and reading it back
#
# `train` returns a `RunResult`: the config, the metrics and episode logs as tables, and the two
# networks as single-run modules. `load_run` rebuilds the same object from a finished folder
# (`from_cache=True`): the networks come from the last checkpoint, and the folder counts as
# finished only when its `done.json` verifies (appendix 07b). `member_networks` makes one member's
# actor and critic from its seed alone; `build_population` (below) builds every member with it
# before stacking them into a population.

# %%
#| export
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


def member_networks(config: TrainConfig) -> tuple:
    """One member's single-run (actor, critic), initialised from its seed alone (the global torch
    generator is seeded with it first, so nothing drawn before changes them)."""
    env_cfg = config.env_config()
    torch.manual_seed(config.seed)
    kind = config.method_spec().network
    return (make_actor(kind, observation_dim(env_cfg), 2, config.net),
            make_critic(kind, state_dim(env_cfg), config.net))


def load_run(run_dir) -> RunResult:
    """The stored result of a run directory (metrics, episodes, networks from the last checkpoint).
    finished is True only when done.json verifies (pemamoe.runs.verify_done; a bad one raises)."""
    run_dir = check_run_dir(run_dir)
    config = read_config(run_dir / "config.json", TrainConfig)
    done = verify_done(run_dir, config)
    ckpt = load_checkpoint(run_dir / "checkpoint.pt", config, iteration=config.iterations if done else None,
                           resuming=done is None)
    actor, critic = member_networks(config)
    actor.load_state_dict(ckpt["actor"])
    critic.load_state_dict(ckpt["critic"])
    return RunResult(config, read_parquet(run_dir / "metrics.parquet"), read_parquet(run_dir / "episodes.parquet"),
                     actor, critic, run_dir, finished=done is not None, from_cache=True)

# %% [markdown]
# ## What learns: `Population` and `build_population`
#
# The trainer of notebook 07 keeps everything that learns in one `Population` (notebook 07 lists
# what it holds), built by `build_population` from every member's own config and seed:
# `member_networks` per member, stacked; a `RunAdamW` per network; the members' plasticity method
# (the controller serves a population that mixes members with and without it, since a member with
# the controller off behaves exactly as `NoPlasticity`); the return normalisers; each member's
# random streams.

# %%
#| export
@dataclasses.dataclass
class Population:
    """What learns in a population of R runs, and what the update reads (see `build_population`)."""

    configs: list  # one TrainConfig per member; they share every field but MEMBER_FIELDS
    singles: list  # per member its (actor, critic) single-run modules: a row's layout, what a checkpoint holds
    actor: PopulationActor  # every member's actor, parameters in actor.flat (R, P)
    critic: PopulationCritic  # every member's critic, parameters in critic.flat (R, Q)
    actor_opt: RunAdamW  # AdamW per member over actor.flat, the parameters in named groups (group_names)
    critic_opt: RunAdamW  # AdamW per member over critic.flat, one group
    group_names: list  # the actor's parameter groups in actor_opt's order, e.g. ["router", "experts", ...]
    plasticity: object  # the members' plasticity method (NoPlasticity, PhaseController, ReDo, ...)
    norms: ValueNorms  # each member's return normaliser
    generators: list  # each member's torch generator: actions and gate noise
    rngs: list  # each member's numpy generator: minibatch permutations
    device: torch.device  # where the networks, the optimisers and the update live

    @property
    def config(self) -> TrainConfig:
        """The settings every member shares (the first member's config)."""
        return self.configs[0]

    def member(self, r: int) -> tuple:
        """Member r's (actor, critic) as single-run modules holding its current parameters."""
        actor, critic = self.singles[r]
        return self.actor.member(r, actor), self.critic.member(r, critic)

    def frozen_groups(self, sched) -> torch.Tensor | None:
        """(R, G) True where a member's parameter group takes no step this iteration (a router the
        phase controller froze), or None when nothing is frozen."""
        if "router" not in self.group_names or not bool(sched.router_frozen.any()):
            return None
        frozen = torch.zeros(len(self.configs), len(self.group_names), dtype=torch.bool, device=self.device)
        frozen[:, self.group_names.index("router")] = sched.router_frozen.to(self.device)
        return frozen


def build_population(configs: list) -> Population:
    """The population of `configs` (TrainConfigs that may differ only in MEMBER_FIELDS), every member
    built from its own config and seed alone, on the device the configs name."""
    check_population(configs)
    c0 = configs[0]
    device = resolve_device(c0.device)
    singles = [member_networks(c) for c in configs]
    actor = PopulationActor([a for a, _ in singles]).to(device)
    critic = PopulationCritic([c for _, c in singles]).to(device)
    group_of, group_names = group_index(singles[0][0], actor.layout)
    actor_opt = RunAdamW(actor.flat, group_of, len(group_names), c0.adam_betas, c0.adam_eps, c0.weight_decay)
    critic_opt = RunAdamW(critic.flat, torch.zeros(critic.layout.size, dtype=torch.long), 1, c0.adam_betas,
                          c0.adam_eps, c0.weight_decay)
    names = {plasticity_name(c) for c in configs}
    # check_population lets only "none" and "phase_controller" mix; the controller serves both
    # (a member with the controller off behaves exactly as NoPlasticity)
    method = plasticity_method(names.pop() if len(names) == 1 else "phase_controller")
    plasticity = method(configs, actor, critic, actor_opt, critic_opt)
    generators = [torch.Generator(device=device).manual_seed(int(c.seed)) for c in configs]
    rngs = [np.random.default_rng(int(c.seed)) for c in configs]
    return Population(list(configs), singles, actor, critic, actor_opt, critic_opt, group_names, plasticity,
                      ValueNorms(configs), generators, rngs, device)


# %% [markdown]
# ## Resume and catch-up
#
# `train_population(configs, run_dirs)` checks its arguments and hands everything but the loop to
# `train_members`. A member whose folder holds a verified `done.json` is read back, not retrained.
# Every other member's folder is locked for the whole run (one writer per folder) and prepared, and
# its checkpoint, if there is one, is loaded; `load_checkpoint` refuses another run's checkpoint
# and names a torn one.
#
# Members then start from the iteration of their checkpoint, and members of one population may
# have stopped at different iterations (a sweep killed while its members were checkpointing). They
# do not train as a queue of small populations: the group furthest behind trains up to the next
# group's iteration, checkpoints, and is loaded again into that group, and so on until all train as
# one. Since a member's numbers do not depend on its neighbours, this changes no bit; it needs every
# lagging member's folder to reload from, so without folders the laggards train to the end first.
# A `deadline` stops every group at the end of its current iteration with a checkpoint of each
# member; members that had not started by then are `None`.

# %%
#| export
def _is_int(value) -> bool:
    """An int or a numpy integer, and not a bool (which Python counts as an int)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def train_members(configs: list, run_dirs: list | None, resume: bool, step, *, max_iterations: int | None,
                  threads: int | None, verbose: bool, progress: bool | None, deadline: float | None) -> list:
    """`train_population`'s driver around one iteration `step` (the trainer's `iteration_step`, notebook 07).

    Checks the arguments, reads back finished members, locks and prepares every other member's
    folder, loads its checkpoint, and trains members grouped by the iteration they start from: the
    group furthest behind trains up to the next group's iteration, checkpoints and joins it.
    Each group trains in `_train_group`, iteration after iteration of `step(TrainState) ->
    (TrainState, IterationLog)`. Returns one RunResult per config.
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
        with DeterministicTorch(threads):
            while pending:
                start = min(pending)
                members = pending.pop(start)
                # Catch up with the next sub-population, then train as one (members are independent
                # of their neighbours, so this changes no bit). Needs every member's folder to reload.
                catch_up = bool(pending) and all(dirs[r] is not None for r, _ in members)
                after = min(pending) if catch_up else None
                stop = max_iterations if after is None else min(after, max_iterations or after)
                group = _train_group(step, [configs[r] for r, _ in members], [dirs[r] for r, _ in members],
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


# %% [markdown]
# ## The driver: one group of members, iteration after iteration
#
# `_train_group` is everything around the algorithm for members that start at one iteration: it
# builds the population, its environments (member r's in rows r·B..(r+1)·B−1) and the phase clock,
# restores the members' checkpoints, and then calls the trainer's `step` once per iteration:
# `state, log = step(state)` over a `TrainState`. After each step it records the log
# (`IterationLogger`, appendix 07e), writes every member's checkpoint every `checkpoint_every`
# iterations, at the stop and when the deadline has passed (the checkpoint holds everything, so a
# resume continues bit for bit), and at the end each member's result.

# %%
#| export
class TrainState(NamedTuple):
    """What one iteration of a population reads and advances (notebook 07's `iteration_step`)."""

    population: Population
    venv: UAVVectorEnv  # R*B environments, member r's in rows r*B..(r+1)*B-1
    clock: PhaseClock  # the iteration-counted phase clock
    fixed_phases: list | None  # each member's fixed phase, or None: the phases cycle
    tracker: EpisodeTracker  # running episodes of all R*B environments
    obs: np.ndarray  # (R*B, U, obs_dim) current observations
    state: np.ndarray  # (R*B, state_dim) current global states
    iteration: int  # the next iteration to run
    global_step: int  # environment steps so far, per member


def phase_clock_of(config: TrainConfig) -> PhaseClock:
    """The iteration-counted phase clock of a run."""
    return PhaseClock(period=config.phase_length_iters, n_phases=config.n_phases)


def _train_group(step, configs: list, run_dirs: list, ckpts: list, max_iterations, verbose, progress,
                 deadline=None) -> list:
    """Train members that start at one iteration up to `max_iterations` (or their end), one `step`
    per iteration; returns one RunResult per member."""
    wall_start = time.perf_counter()
    c0, R, B = configs[0], len(configs), configs[0].num_envs
    pop = build_population(configs)
    venv = UAVVectorEnv(seeds=[s for c in configs for s in vector_seeds(c.seed, B)], cfg=c0.env_config())
    fixed = None if c0.fixed_phase is None else [c.fixed_phase for c in configs]  # all members or none
    clock = phase_clock_of(c0)
    venv.set_phase(clock.phase_at(0) if fixed is None else np.repeat(fixed, B))
    obs, state, _ = venv.reset()
    members = MemberStates(pop, EpisodeTracker(R * B, members=R), wall_start)  # what a checkpoint adds
    start, global_step, resumed_from = 0, 0, None
    if any(ck is not None for ck in ckpts):  # every member of a group resumes from the same iteration
        start, global_step = members.restore(ckpts, venv, obs, state)
        resumed_from = start
    ts = TrainState(pop, venv, clock, fixed, members.tracker, obs, state, start, global_step)
    stop = c0.iterations if max_iterations is None else min(c0.iterations, max_iterations)
    with IterationLogger(pop, members, [collect_probe(c) for c in configs], start, progress, verbose) as logger:
        while ts.iteration < stop:
            ts, log = step(ts)
            logger.record(log)
            out_of_time = deadline is not None and time.time() >= deadline and ts.iteration < stop
            if ts.iteration % c0.checkpoint_every == 0 or ts.iteration == stop or out_of_time:
                members.save_all(run_dirs, venv, ts.iteration, ts.global_step, ts.obs, ts.state)
            if out_of_time:
                stop = ts.iteration
    finished = stop == c0.iterations
    if finished and start >= stop:  # nothing ran (a finished checkpoint without done.json): rewrite the logs
        members.save_all(run_dirs, venv, stop, ts.global_step, ts.obs, ts.state)
    return members.results(run_dirs, finished, ts.global_step, resumed_from)


# %% [markdown]
# ## A member's checkpoint, written and read back
#
# The training loop holds what learns in one object, the trainer's `Population` (notebook 07:
# networks, optimisers, plasticity method, return normalisers, random streams). `MemberStates` adds
# what else a checkpoint stores: the running episodes, each member's log rows, its training seconds
# before this process, and the torch thread counts and processors it ran with. Writing and reading a
# checkpoint live here rather than in the loop. `save` writes one member's checkpoint (what it
# holds: appendix 07e), then its `metrics.parquet` and `episodes.parquet`; the last write of a
# finished run converts every row at once and releases the rows (the logs `done.json` seals).
# `restore` loads every member's checkpoint back into the population, in the same order of fields,
# so that the next iteration reads exactly what it would have read without the interruption. The
# loop reads the log lists from here, and `restore` fills them in place.

# %%
#| export
@dataclass
class MemberStates:
    """What a checkpoint stores of a population's members besides the `Population` itself (lists:
    one entry per member)."""

    population: object  # the trainer's Population (notebook 07): what learns, and its random streams
    tracker: EpisodeTracker  # running episodes of all R*B environments
    wall_start: float  # time.perf_counter() when this process started training the members
    metrics_rows: list = field(init=False)  # RowLog of metrics rows
    episode_rows: list = field(init=False)  # RowLog of episode rows
    elapsed: list = field(init=False)  # training seconds before this process
    torch_threads: list = field(init=False)  # sets of the torch thread counts used
    processors: list = field(init=False)  # sets of the processors that trained each member

    def __post_init__(self):
        R = len(self.population.configs)
        self.metrics_rows, self.episode_rows = [RowLog() for _ in range(R)], [RowLog() for _ in range(R)]
        self.elapsed = [0.0] * R
        self.torch_threads = [{torch.get_num_threads()} for _ in range(R)]  # recorded: results with 1 and 2 threads differ
        here = training_processor()  # recorded: float kernels differ between processor families
        self.processors = [{here} for _ in range(R)]

    def seconds(self, r: int) -> float:
        """Member r's training seconds so far: before this process and in it."""
        return self.elapsed[r] + time.perf_counter() - self.wall_start

    def restore(self, ckpts, venv, obs, state) -> tuple:
        """Load every member's checkpoint (all of one iteration) into the population, the vector
        environment `venv` and the current `obs` and `state` arrays (in place).
        Returns (iteration, global_step) of the checkpoints."""
        pop = self.population
        B = pop.configs[0].num_envs
        env_states = []
        for r, ck in enumerate(ckpts):
            with torch.no_grad():
                a, c = pop.singles[r]
                a.load_state_dict(ck["actor"]), c.load_state_dict(ck["critic"])
                pop.actor.flat[r] = pop.actor.layout.flatten([a])[0].to(pop.device)
                pop.critic.flat[r] = pop.critic.layout.flatten([c])[0].to(pop.device)
            pop.actor_opt.load_member_state(r, ck["optimizer"]["actor"])
            pop.critic_opt.load_member_state(r, ck["optimizer"]["critic"])
            pop.plasticity.load_state_dict(r, ck["plasticity"])
            pop.norms.norms[r].load_state_dict(ck["value_norm"])
            self.tracker.load_member_state(r, ck["tracker"])
            env_states.append(decode_arrays(ck["env"]))
            obs[r * B:(r + 1) * B], state[r * B:(r + 1) * B] = ck["obs"].numpy(), ck["state"].numpy()
            pop.generators[r].set_state(ck["torch_rng"])
            pop.rngs[r].bit_generator.state = ck["numpy_rng"]
            global_step, self.elapsed[r] = int(ck["global_step"]), float(ck["elapsed"])
            self.metrics_rows[r] = RowLog.from_checkpoint(ck["metrics_rows"])
            self.episode_rows[r] = RowLog.from_checkpoint(ck["episode_rows"])
            self.torch_threads[r].update(ck.get("torch_threads", ()))
            self.processors[r].update(ck.get("processors", (UNRECORDED_PROCESSOR,)))
            start = int(ck["iteration"])
        venv.load_state_dict(merge_env_states(env_states))
        return start, global_step

    def save(self, r, run_dir, iteration, global_step, env_state, obs, state) -> None:
        """Member r's checkpoint and logs in run_dir. env_state: the whole population's environment
        state (taken once per checkpoint); obs, state: the population's current observations and
        global states."""
        pop = self.population
        B = pop.configs[r].num_envs
        env_state = split_env_state(env_state, range(r * B, (r + 1) * B))
        actor, critic = pop.member(r)
        write_checkpoint({  # stamped with the checkpoint format and TRAINING_NUMERICS, and sealed (appendix 07e)
            "config": pop.configs[r].to_dict(), "iteration": iteration, "global_step": global_step,
            "elapsed": self.seconds(r), "actor": actor.state_dict(), "critic": critic.state_dict(),
            "optimizer": {"actor": pop.actor_opt.member_state(r), "critic": pop.critic_opt.member_state(r)},
            "plasticity": pop.plasticity.state_dict(r), "value_norm": pop.norms.norms[r].state_dict(),
            "tracker": self.tracker.member_state(r), "env": encode_arrays(env_state),
            "obs": torch.from_numpy(obs[r * B:(r + 1) * B].copy()),
            "state": torch.from_numpy(state[r * B:(r + 1) * B].copy()),
            "torch_rng": pop.generators[r].get_state(), "numpy_rng": pop.rngs[r].bit_generator.state,
            "metrics_rows": self.metrics_rows[r].packed(), "episode_rows": self.episode_rows[r].packed(),
            "torch_threads": sorted(self.torch_threads[r]), "processors": sorted(self.processors[r]),
        }, run_dir / "checkpoint.pt")
        final = iteration == pop.configs[r].iterations  # the logs done.json seals: every row converted at once
        write_rows_parquet(self.metrics_rows[r], run_dir / "metrics.parquet", final)
        write_rows_parquet(self.episode_rows[r], run_dir / "episodes.parquet", final)
        if final:
            self.metrics_rows[r].release(), self.episode_rows[r].release()

    def save_all(self, run_dirs, venv, iteration, global_step, obs, state) -> None:
        """Every member's checkpoint and logs at `iteration`, in its folder (none without one)."""
        if any(d is not None for d in run_dirs):
            env_state = venv.state_dict()  # the whole population's, taken once per checkpoint
            for r, run_dir in enumerate(run_dirs):
                if run_dir is not None:
                    self.save(r, run_dir, iteration, global_step, env_state, obs, state)

    def results(self, run_dirs, finished: bool, global_step: int, resumed_from) -> list:
        """One RunResult per member; each member that finished gets its done.json."""
        pop = self.population
        results = []
        for r, (config, run_dir) in enumerate(zip(pop.configs, run_dirs)):
            metrics = pd.DataFrame(self.metrics_rows[r])
            if run_dir is not None and finished:
                write_done(run_dir, config, env_steps=global_step, torch_threads=sorted(self.torch_threads[r]),
                           processors=sorted(self.processors[r]),
                           wall_time_s=self.seconds(r),
                           final_episode_return=float(metrics["episode_return"].tail(config.phase_length_iters).mean()))
            actor, critic = pop.member(r)
            results.append(RunResult(config, metrics, pd.DataFrame(self.episode_rows[r]), actor, critic, run_dir,
                                     finished=finished, resumed_from=resumed_from))
        return results

# %% [markdown]
# ## Deterministic evaluation
#
# For figures that need a policy's behaviour rather than its training curve (notebook 05c),
# `evaluate_policy` runs fresh episodes in a given phase with the **mean** action and returns one
# row per episode. A gated actor is evaluated with noiseless gating by default (the execution-time
# policy: each row goes to the router's own choice); `routing="trained"` keeps the routing noise it
# trained with. The two differ for an actor that came to rely on the noise (notebook 05).

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


@torch.no_grad()
def action_switch_readings(actor, env_cfg: EnvConfig | None = None, steps: int = 200, num_envs: int = 16,
                           seed: int = 0, phase: int = 0, temperature: float = 1.0) -> dict:
    """How the deterministic policy (mean action, noiseless routing) moves, over `steps` steps of
    `num_envs` environments in `phase`: "jump_at_switch" and "jump_otherwise", the mean distance
    between an agent's mean actions on consecutive steps of an episode when its selected expert
    changed and when it did not (nan where no such step); "switch_rate", the share of those steps
    on which the expert changed; "outside_box", the share of mean actions with a coordinate
    outside the action box [-1, 1] (the environment clips them). An actor without experts (MLP)
    has no switches: all its steps count as "otherwise"."""
    env_cfg = dataclasses.replace(env_cfg or EnvConfig(), phase_clock="external")
    venv = UAVVectorEnv(num_envs, seed, cfg=env_cfg)
    venv.set_phase(phase)
    obs, _, _ = venv.reset()
    B, U = num_envs, venv.n_agents
    previous = None  # (mean (B, U, A), experts (B, U, k) or None, alive (B,))
    at_switch, otherwise, outside, rows = [], [], 0, 0
    for _ in range(steps):
        dist, routing = actor(torch.from_numpy(obs).reshape(B * U, -1), temperature, None, deterministic_gate=True)
        mean = dist.mean.reshape(B, U, -1).numpy()
        experts = None if routing is None else routing.experts.reshape(B, U, -1).sort(-1).values.numpy()
        outside += int((np.abs(mean) > 1).any(-1).sum())
        rows += B * U
        if previous is not None:
            jump = np.linalg.norm(mean - previous[0], axis=-1)[previous[2]]  # (alive agents,)
            switched = (np.zeros(jump.shape, bool) if experts is None
                        else (experts != previous[1]).any(-1)[previous[2]])
            at_switch.append(jump[switched])
            otherwise.append(jump[~switched])
        obs, _, _, term, trunc, _ = venv.step(mean)
        done = (np.asarray(term, bool) | np.asarray(trunc, bool)).reshape(B, -1).any(1)
        previous = (mean, experts, ~done)  # a finished episode's next observation starts a new one
    at_switch, otherwise = np.concatenate(at_switch), np.concatenate(otherwise)
    pairs = len(at_switch) + len(otherwise)
    return {"jump_at_switch": float(at_switch.mean()) if len(at_switch) else float("nan"),
            "jump_otherwise": float(otherwise.mean()) if len(otherwise) else float("nan"),
            "switch_rate": len(at_switch) / max(pairs, 1), "outside_box": outside / max(rows, 1)}

# %% [markdown]
# ## Demonstration
#
# Two members that differ in a shared setting are refused, naming it; two seeds of one run share a
# population key. Then, at the `ci` preset whatever the notebook's scale (this is bookkeeping, not
# learning): one member is interrupted after two iterations, and a population of three resumes it
# next to two fresh members. The fresh ones train up to iteration 2, join it, and the three finish
# as one population; reading the finished folders back recomputes nothing. Last, member 0's
# actor, read back from its folder, is evaluated for two episodes in phase 1.

# %%
import tempfile

_ci = lambda seed, **kw: TrainConfig.for_scale("ci", method="mlp", seed=seed, **kw)  # noqa: E731
try:
    check_population([_ci(0), _ci(1, num_envs=8)])
except ValueError as err:
    print("refused:", err)
assert population_key(_ci(0)) == population_key(_ci(1)) != population_key(_ci(0, num_envs=8))

# %%
from pemamoe.mappo import train, train_population

with tempfile.TemporaryDirectory() as tmp:
    folders = [Path(tmp) / f"m{s}" for s in range(3)]
    configs = [_ci(s, checkpoint_every=1) for s in range(3)]
    first = train(configs[0], folders[0], max_iterations=2)
    print(f"member 0 stopped at iteration {len(first.metrics)} of {configs[0].iterations} (finished: {first.finished})")
    out = train_population(configs, folders)
    print("resumed_from:", [r.resumed_from for r in out], "| finished:", [r.finished for r in out])
    back = [load_run(f) for f in folders]
    assert all(b.from_cache and b.finished for b in back)
    assert all(b.metrics["episode_return"].equals(r.metrics["episode_return"]) for b, r in zip(back, out))
    actor = back[0].actor

evaluate_policy(actor, configs[0].env_config(), episodes=2, seed=0, phase=1)
