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
# # 06b · Appendix: plasticity methods for a population of runs
#
# Notebook 06 gives the phase controller's mechanisms and the controller itself, `PhaseController`,
# read for one run; all of it is one module, `pemamoe/phase_controller.py`. This appendix holds
# what every plasticity method shares, which the trainer of notebook 07 needs and a reader of the
# method can skip, in `pemamoe/plasticity.py`: the PPO schedule (`RunSettings`), the
# **interface** every plasticity method implements, the baselines' `NoPlasticity`, the registry
# (`register_plasticity`, `plasticity_method`) through which the trainer and plug-ins find a
# method by name, and `population_method`, which builds a method on a population outside the
# trainer (notebook 06's demonstrations, the theory check of notebook 08, the tests). The
# optimizer over the run axis (`RunAdamW`) is appendix 06d's, the plasticity diagnostics appendix
# 06e's.
#
# The demonstrations check that a member's switch and schedules do not depend on the population
# it trains in, and show a switch on a real actor with the diagnostics before and after.

# %%
#| default_exp plasticity

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %%
#| export
import math
from dataclasses import dataclass

import numpy as np
import torch

from pemamoe.core import require_field
from pemamoe.methods import load_plugins
from pemamoe.optim import RunAdamW, group_index
from pemamoe.popnets import PopulationActor, PopulationCritic

# %% [markdown]
# ## Plasticity methods for a population of runs
#
# The trainer (notebook 07) trains R runs at once, their parameters stacked on a leading run
# axis (appendix 05b). Everything that changes the optimisation at a
# phase switch is a **plasticity method**: a small object with a fixed set of hooks that the
# trainer calls, which acts on each member separately and only ever touches that member's row of
# the parameters and of the optimizer state.
#
# | hook | when | returns |
# |---|---|---|
# | `on_switch(iteration)` | before the first rollout of a new phase | nothing |
# | `begin_iteration(iteration)` | every iteration, before the rollout | `PopulationSettings`: per-member learning rates, clip, target KL, entropy weight, temperatures, router freeze |
# | `extra_loss(batch)` | every minibatch | an (R,) loss added to PPO's, or `None` for none |
# | `after_minibatch(stepped)` | after each optimizer step | nothing |
# | `after_epoch(expert_counts, stepped)` | after each update epoch | number of experts perturbed per member |
# | `metrics(r)` | every iteration, after the update | named numbers for member r's log row (`{}`: none) |
# | `state_dict(r)` / `load_state_dict(r, state)` | checkpoints | member r's state |
#
# A method that needs data at a switch sets `probe_rows`: the trainer then hands it each
# rollout's observations (`observe_rollout`), of which it keeps that many agent rows per member,
# evenly spaced (no random draw, so no other number of the run moves), and `probe_batch(r)` gives
# member r's rows from the latest rollout, which at a switch is the last one of the phase that
# ends. They are checkpointed with the method, so a run resumed at a switch sees the same rows.
# The names `metrics(r)` returns become columns of `metrics.parquet` (prefixed with the method's
# name, so they cannot clash with the trainer's); a method that logs nothing adds no column.
#
# `NoPlasticity` is what the baselines use: the shared PPO schedule and nothing else.
# `PhaseController` (notebook 06, module `pemamoe.phase_controller`) is PE-MAMoE's phase controller,
# the nine mechanisms each still switchable for the ablations. A new method subclasses
# `NoPlasticity`, overrides the hooks it needs and registers itself with `register_plasticity`;
# CONTRIBUTING.md shows shrink-and-perturb in a dozen lines.

# %% [markdown]
# ## The shared PPO schedule
#
# `RunSettings` holds what every method shares with PPO (paper training table: learning rate,
# clip, target KL, entropy schedule, run and phase lengths, the router temperature); the trainer
# builds it from its own PPO config (`TrainConfig.base_schedule()`, notebook 07) so there is one
# source for each number, and the phase controller of notebook 06 modifies its values after a
# switch. Without a controller the entropy coefficient is annealed linearly from `ent_start` to
# `ent_end` over the first `ent_anneal_portion` of the run (`base_entropy_coef`; notebook 06's
# `entropy_coef` re-anneals it within each phase instead). `IterationSettings` is what one member
# trains with in one iteration, the method's answer for that member.

# %%
#| export
@dataclass(frozen=True)
class RunSettings:
    """The PPO values every method shares (paper training table); the phase controller modifies them."""

    lr: float = 3e-4
    clip_coef: float = 0.15
    target_kl: float | None = 0.1  # None: no early stopping
    ent_start: float = 0.01
    ent_end: float = 0.003
    ent_anneal_portion: float = 0.3  # of the whole run (baselines)
    total_iterations: int = 10800  # 22,118,400 steps / 2048 per iteration
    phase_length: int = 1200  # iterations per phase (9 phases)
    temperature: float = 1.0  # router temperature outside the controller's schedule

    def __post_init__(self):
        require_field(self, "lr", "real", gt=0)
        require_field(self, "clip_coef", "real", gt=0)
        require_field(self, "target_kl", "real", gt=0, optional=True)
        for name in ("ent_start", "ent_end"):
            require_field(self, name, "real", ge=0)
        require_field(self, "ent_anneal_portion", "real", gt=0, le=1)
        for name in ("total_iterations", "phase_length"):
            require_field(self, name, "int", ge=1)
        require_field(self, "temperature", "real", gt=0)


def linear_anneal(step, span, start: float, end: float):
    """start -> end linearly over `span` steps, then flat at `end`."""
    frac = np.clip(np.asarray(step, dtype=float) / span, 0.0, 1.0)
    return start + (end - start) * frac


def base_entropy_coef(iteration, base: RunSettings):
    """Entropy coefficient of the shared schedule: start -> end over the first ent_anneal_portion of the run."""
    span = max(base.ent_anneal_portion * base.total_iterations, 1e-12)
    return linear_anneal(iteration, span, base.ent_start, base.ent_end)


@dataclass(frozen=True)
class IterationSettings:
    """What one member trains with in one iteration (one per member in PopulationSettings.members)."""

    iteration: int
    since_switch: int | None  # iterations since the last switch (None before the first)
    lr: dict  # {"head": the actor's rate} and, once the controller acts, "router" (0 while frozen)
    clip_coef: float
    target_kl: float | None
    ent_coef: float
    kl_coef: float  # 0 when off, before the first switch, or once released
    policy_temperature: float
    value_temperature: float
    router_frozen: bool
    conservative: bool
    noise_epochs_left: int


# %% [markdown]
# ## Per-member schedules
#
# `begin_iteration` returns one `PopulationSettings`: each number of the members' `IterationSettings` as an
# (R,) tensor over the members (`PopulationSettings.stack`), which the update reads without a Python loop,
# and the members' `IterationSettings` themselves for the logs.

# %%
#| export
@dataclass(frozen=True)
class PopulationSettings:
    """What the trainer uses in one iteration, per member (tensors of shape (R,))."""

    lr_actor: torch.Tensor
    lr_critic: torch.Tensor
    router_frozen: torch.Tensor  # bool
    clip_coef: torch.Tensor
    target_kl: torch.Tensor  # inf: no early stop
    ent_coef: torch.Tensor
    kl_coef: torch.Tensor
    policy_temperature: torch.Tensor
    value_temperature: torch.Tensor
    members: tuple  # one IterationSettings per member (for the logs)

    @classmethod
    def stack(cls, settings: list, critic_lrs: list, device) -> "PopulationSettings":
        """The members' IterationSettings (and the critics' learning rates) as (R,) tensors on `device`."""
        def col(values, dtype=torch.float64):
            return torch.tensor(values, dtype=dtype, device=device)

        return cls(
            lr_actor=col([s.lr.get("head", 0.0) for s in settings]),
            lr_critic=col(critic_lrs),
            router_frozen=col([s.router_frozen for s in settings], torch.bool),
            clip_coef=col([s.clip_coef for s in settings], torch.float32),
            target_kl=col([math.inf if s.target_kl is None else s.target_kl for s in settings], torch.float32),
            ent_coef=col([s.ent_coef for s in settings], torch.float32),
            kl_coef=col([s.kl_coef for s in settings], torch.float32),
            policy_temperature=col([s.policy_temperature for s in settings], torch.float32),
            value_temperature=col([s.value_temperature for s in settings], torch.float32),
            members=tuple(settings),
        )


# %% [markdown]
# ## The interface, the registry and the baselines' method
#
# `NoPlasticity` is both the interface (every hook, doing nothing) and the baselines' method: the
# shared PPO schedule of `RunSettings` above, entropy annealed over the run. Its helpers
# serve subclasses: `member_generator(r)` (member r's own checkpointed random stream),
# `expert_indices()` (where each expert's trunk lives in a flat row; the phase controller's
# `perturb_experts` noises them), `fresh_parameters(r)` (a newly initialised actor's row, drawn
# from member r's stream) and `probe_batch(r)`. For partial edits of one member,
# `self.actor.member_param(r, name)` is member r's parameter as a view shaped like it,
# `self.actor.layout.indices(name)` its flat positions (shaped likewise), which
# `self.actor_opt.reset(r, mask)` takes to reset the matching moments.
# `PhaseController` lives in notebook 06's module, `pemamoe.phase_controller`, which imports this
# one. A method registers when its module is imported: the trainer imports the controller's module
# and appendix 06c's baselines; for a name it does not know, `plasticity_method` first loads the
# plug-ins named in `$PEMAMOE_PLUGINS`.

# %%
#| export
PLASTICITY_METHODS: dict = {}


def register_plasticity(cls):
    """Class decorator: make a plasticity method available by its `name`."""
    if not isinstance(getattr(cls, "name", None), str) or not cls.name:
        raise ValueError(f"a plasticity method needs a non-empty string `name`, got {getattr(cls, 'name', None)!r}")
    PLASTICITY_METHODS[cls.name] = cls
    return cls


def plasticity_method(name: str):
    """The registered plasticity method class called `name` (plug-ins are loaded if needed).
    Methods register when their module is imported: PE-MAMoE's `PhaseController` with
    `pemamoe.phase_controller` (notebook 06), ReDo and shrink-and-perturb with
    `pemamoe.plasticity_baselines` (appendix 06c); the trainer imports both."""
    if name not in PLASTICITY_METHODS:
        load_plugins()
    if name not in PLASTICITY_METHODS:
        raise ValueError(f"plasticity method must be one of {', '.join(sorted(PLASTICITY_METHODS))}, got {name!r} "
                         "(a method registers when its module is imported: pemamoe.phase_controller, "
                         "pemamoe.plasticity_baselines, or a plugin)")
    return PLASTICITY_METHODS[name]


@register_plasticity
class NoPlasticity:
    """The interface, and the baselines' method: the shared PPO schedule, no switch-time action.

    configs: one config per member with .base_schedule(), .controller, .controller_enabled and
    .seed (TrainConfig); actor/critic: PopulationActor/PopulationCritic; actor_opt/critic_opt:
    RunAdamW. Subclasses override the hooks they need and keep the others.
    """

    name = "none"

    def __init__(self, configs, actor, critic, actor_opt, critic_opt):
        self.configs = list(configs)
        self.R = len(self.configs)
        self.actor, self.critic = actor, critic
        self.actor_opt, self.critic_opt = actor_opt, critic_opt
        self.bases = [c.base_schedule() for c in self.configs]
        self.device = actor.flat.device

    def member_settings(self, r: int, iteration: int) -> IterationSettings:
        b = self.bases[r]
        return IterationSettings(
            iteration=int(iteration), since_switch=None, lr={"head": b.lr}, clip_coef=b.clip_coef,
            target_kl=b.target_kl, ent_coef=float(base_entropy_coef(iteration, b)),
            kl_coef=0.0, policy_temperature=b.temperature, value_temperature=b.temperature,
            router_frozen=False, conservative=False, noise_epochs_left=0)

    def on_switch(self, iteration: int) -> None:
        pass

    def begin_iteration(self, iteration: int) -> PopulationSettings:
        settings = [self.member_settings(r, iteration) for r in range(self.R)]
        return PopulationSettings.stack(settings, [b.lr for b in self.bases], self.device)

    def extra_loss(self, batch: dict) -> torch.Tensor | None:
        """(R,) added to each member's loss; None when nothing is added (saves the work)."""
        return None

    def after_minibatch(self, stepped: torch.Tensor) -> None:
        pass

    def after_epoch(self, expert_counts: torch.Tensor | None, stepped: torch.Tensor) -> list:
        return [0] * self.R

    def metrics(self, r: int) -> dict:
        """{name: number} added to member r's log row of this iteration (names prefixed with the
        method's name); {} adds no column."""
        return {}

    def state_dict(self, r: int) -> dict:
        gens, recent = getattr(self, "_generators", None), getattr(self, "_recent_obs", None)
        state = {} if gens is None else {"generator": gens[r].get_state()}
        if recent is not None:
            state["recent_obs"] = recent[r].detach().cpu().clone()
        return state

    def load_state_dict(self, r: int, state: dict) -> None:
        if "generator" in state:
            self.member_generator(r).set_state(state["generator"])
        if "recent_obs" in state:
            rows = state["recent_obs"]
            if getattr(self, "_recent_obs", None) is None:
                self._recent_obs = torch.zeros(self.R, *rows.shape, dtype=rows.dtype, device=self.device)
            self._recent_obs[r] = rows.to(self.device)

    # data for switch-time actions ---------------------------------------------------------------
    probe_rows = 0  # agent observations kept per member for probe_batch (0: none kept, none asked)

    @torch.no_grad()
    def observe_rollout(self, obs: torch.Tensor) -> None:
        """The trainer's call after every rollout, obs (R, N, U, obs_dim): keep `probe_rows` agent
        rows per member, evenly spaced over the rollout (deterministic: no random stream is drawn)."""
        if not self.probe_rows:
            return
        rows = obs.reshape(self.R, -1, obs.shape[-1])
        n = rows.shape[1]
        k = min(int(self.probe_rows), n)
        pick = torch.arange(k, device=rows.device) * n // k
        self._recent_obs = rows[:, pick].to(self.device, copy=True)

    def probe_batch(self, r: int) -> torch.Tensor:
        """(n, obs_dim): member r's observations from the latest rollout (at a switch, the last of
        the phase that ends), n = min(probe_rows, rows in a rollout)."""
        recent = getattr(self, "_recent_obs", None)
        if recent is None:
            raise RuntimeError(f"{type(self).__name__}.probe_batch: no rollout observed yet (a method that reads "
                               "probe batches sets probe_rows > 0; the trainer fills them after every rollout)")
        return recent[r]

    # helpers for subclasses ---------------------------------------------------------------------
    generator_seed_offset = 11  # member r's generator starts from its config's seed + this

    def member_generator(self, r: int) -> torch.Generator:
        """Member r's own random generator (seeded from its config's seed; checkpointed)."""
        if getattr(self, "_generators", None) is None:
            self._generators = [torch.Generator().manual_seed(int(c.seed) + self.generator_seed_offset)
                                for c in self.configs]
        return self._generators[r]

    def expert_indices(self) -> list:
        """Flat indices of each expert's trunk parameters in a member's row: [(E_i,) long]."""
        if not hasattr(self, "_expert_idx"):
            layout, by_expert = self.actor.layout, {}
            for name, e in self.actor.template.trunk_parameters():
                idx = torch.arange(*layout.span(name)) if e is None else layout.expert_index(name, e)
                by_expert.setdefault(0 if e is None else e, []).append(idx)
            self._expert_idx = [torch.cat(by_expert[e]).to(self.device) for e in sorted(by_expert)]
        return self._expert_idx

    @torch.no_grad()
    def fresh_parameters(self, r: int) -> torch.Tensor:
        """(P,) the parameters of a newly initialised actor of the population's kind (built as
        cls(obs_dim, act_dim, cfg), as every built-in kind is), seeded from member r's generator;
        the global torch generator is left as it was, so no other number of the run moves."""
        seed = int(torch.randint(0, 2**62, (1,), generator=self.member_generator(r)))
        template = self.actor.template
        with torch.random.fork_rng(devices=[]):
            torch.random.default_generator.manual_seed(seed)
            fresh = type(template)(template.obs_dim, template.act_dim, template.cfg)
        return self.actor.layout.flatten([fresh])[0].to(self.device, self.actor.flat.dtype)


# %% [markdown]
# ## A method outside the trainer
#
# The trainer builds its population from its `TrainConfig`s (notebook 07). Notebook 06's
# demonstrations, the theory check of notebook 08 and the tests drive a method without the
# trainer: `population_method` stacks single-run actors (and critics) into a population with a
# `RunAdamW` for each, as the trainer does, and builds the named method on them, given one config
# per member (a `TrainConfig`, or notebook 06's `MemberConfig`, which holds the four things a
# plasticity method reads of a member's config). One actor gives R = 1: one run.

# %%
#| export
def population_method(name: str, configs, actors, critics=None, betas=(0.9, 0.999), eps: float = 1e-5,
                      weight_decay: float = 0.0):
    """Plasticity method `name` on the population stacked from single-run `actors` (and `critics`,
    or none), with a RunAdamW for each as the trainer builds them; one config per member."""
    actors = list(actors)
    actor = PopulationActor(actors)
    critic = None if critics is None else PopulationCritic(list(critics))
    group_of, names = group_index(actors[0], actor.layout)
    actor_opt = RunAdamW(actor.flat, group_of, len(names), betas, eps, weight_decay)
    critic_opt = None if critic is None else RunAdamW(
        critic.flat, torch.zeros(critic.layout.size, dtype=torch.long), 1, betas, eps, weight_decay)
    return plasticity_method(name)(list(configs), actor, critic, actor_opt, critic_opt)


# %% [markdown]
# ## Checks on a small population
#
# Three members of the SMoE network kind: PE-MAMoE, PE-MAMoE without noise injection, and a
# baseline (the controller off).

# %%
import copy

import numpy as np
import pandas as pd
import torch.nn.functional as F

from pemamoe.core import by_scale
from pemamoe.nets import make_actor, make_critic
from pemamoe.phase_controller import MemberConfig, PhaseController, PhaseControllerConfig

register_plasticity(PhaseController)  # run as a notebook, the cells above made a registry of their own

obs_dim, state_dim = by_scale(scale, ci=24, small=64, paper=177), by_scale(scale, ci=32, small=96, paper=240)
demo_base = RunSettings(total_iterations=300, phase_length=100)
members = [MemberConfig(base=demo_base, seed=0),
           MemberConfig(PhaseControllerConfig().without("noise_injection"), demo_base, seed=1),
           MemberConfig(base=demo_base, controller_enabled=False, seed=2)]
R = len(members)


def population():
    """Each member's actor and critic from its own seed, stacked, with a RunAdamW for each."""
    singles = []
    for m in members:
        torch.manual_seed(m.seed)
        singles.append((make_actor("smoe", obs_dim), make_critic("smoe", state_dim)))
    actor = PopulationActor([a for a, _ in singles])
    critic = PopulationCritic([c for _, c in singles])
    group_of, names = group_index(singles[0][0], actor.layout)
    actor_opt = RunAdamW(actor.flat, group_of, len(names), eps=1e-5, weight_decay=1e-4)
    critic_opt = RunAdamW(critic.flat, torch.zeros(critic.layout.size, dtype=torch.long), 1, eps=1e-5, weight_decay=1e-4)
    return singles, actor, critic, actor_opt, critic_opt, names

# %% [markdown]
# **A switch acts on its own member only.** The moments are filled with ones and the log-stds
# narrowed first, so that the resets show; then one switch.

# %%
singles, actor, critic, actor_opt, critic_opt, names = population()
method = plasticity_method("phase_controller")(members, actor, critic, actor_opt, critic_opt)
trunk = torch.cat(method.expert_indices())
ls = slice(*actor.layout.span("log_std"))
with torch.no_grad():
    actor.flat[:, ls] -= 0.5
for opt in (actor_opt, critic_opt):
    opt.exp_avg.fill_(1.0)
before = actor.flat.detach().clone()
method.on_switch(demo_base.phase_length)
after = actor.flat.detach()
table = pd.DataFrame({
    "controller": [m.controller_enabled for m in members],
    "trunk noised": [bool((after[r, trunk] != before[r, trunk]).any()) for r in range(R)],
    "log-std reset": [bool(torch.allclose(after[r, ls], torch.tensor(math.log(0.3)))) for r in range(R)],
    "actor moments reset": [bool((actor_opt.exp_avg[r] == 0).all()) for r in range(R)],
    "critic moments kept": [bool((critic_opt.exp_avg[r] == 1).all()) for r in range(R)],
})
print(table.to_string())
assert table["trunk noised"].tolist() == [True, False, False]
assert table["log-std reset"].tolist() == table["actor moments reset"].tolist() == [True, True, False]
assert table["critic moments kept"].all()

# %% [markdown]
# **A member's schedules do not depend on its population.** Three phases of 100 iterations: the
# population of three against each member alone (R = 1) on the same clock. Every number the trainer
# reads of `PopulationSettings` agrees bit for bit, and so do the parameters after the switches' noise.

# %%
singles, actor, critic, actor_opt, critic_opt, names = population()
method = PhaseController(members, actor, critic, actor_opt, critic_opt)
alone = [population_method("phase_controller", [m], [copy.deepcopy(a)], [copy.deepcopy(c)]) for m, (a, c) in zip(members, singles)]
read = ("lr_actor", "lr_critic", "router_frozen", "clip_coef", "target_kl", "ent_coef", "kl_coef",
        "policy_temperature", "value_temperature")
for t in range(demo_base.total_iterations):
    if t > 0 and t % demo_base.phase_length == 0:
        for m in (method, *alone):
            m.on_switch(t)
    sched = method.begin_iteration(t)
    for r, one in enumerate(alone):
        s = one.begin_iteration(t)
        assert all(torch.equal(getattr(sched, f)[r:r + 1], getattr(s, f)) for f in read), (t, r)
        assert sched.members[r] == s.members[0]
assert all(torch.equal(method.actor.flat[r], one.actor.flat[0]) for r, one in enumerate(alone))
print(f"{R} members: schedules and switch-time noise equal each member's alone over {demo_base.total_iterations} iterations")

# %% [markdown]
# **The registry.** The trainer finds a method by the name a `MethodSpec` gives (appendix 05e);
# an unknown name is an error listing the known ones.

# %%
print({name: cls.__name__ for name, cls in PLASTICITY_METHODS.items()})
assert plasticity_method("none") is NoPlasticity and plasticity_method("phase_controller") is PhaseController
try:
    plasticity_method("no_such_method")
except ValueError as err:
    print(err)
else:
    raise AssertionError("an unknown plasticity method must be refused")

# %% [markdown]
# ## A switch on a real actor, and the diagnostics around it
#
# A fresh actor and critic from notebook 05 as a population of one, random probe observations, a
# few gradient steps on a dummy objective so the optimizer has state, then a switch. We check which
# parameters moved (only the expert trunks, by exactly the noise; the log-std jumped back to
# $\log 0.3$) and compare the diagnostics before and after.

# %%
from pemamoe import diagnostics as dg

cfg = PhaseControllerConfig()
g = torch.Generator().manual_seed(seed)
n_probe = by_scale(scale, ci=256, small=1024, paper=2048)
probe_obs = torch.randn(n_probe, obs_dim, generator=g)
probe_state = torch.randn(n_probe, state_dim, generator=g)

torch.manual_seed(seed)
ctl = population_method("phase_controller", [MemberConfig(cfg, demo_base, seed=seed)], [make_actor("smoe", obs_dim)],
                        [make_critic("smoe", state_dim)], weight_decay=1e-4)
pop, opt = ctl.actor, ctl.actor_opt
group_names = group_index(pop.template, pop.layout)[1]
router_mask = torch.tensor([group_names[i] == "router" for i in opt.group_of.tolist()])
log_std_span = slice(*pop.layout.span("log_std"))


def update(sched, obs, target):
    """One gradient step of the member on a dummy regression objective, the router frozen as the
    trainer freezes it (no gradient, no Adam step, no weight decay). Returns the experts chosen."""
    _, _, routing = pop.act(obs[None], sched.policy_temperature, [g])
    logp, ent, lb, mean, log_std, chosen = pop.evaluate(obs[None], target[None], routing)
    loss = -logp.mean(1) - sched.ent_coef * ent + pop.lb_coef * lb
    kl = ctl.extra_loss({"obs": obs[None], "tau": routing.temperature, "noise": routing.noise, "experts": chosen,
                         "mean": mean, "log_std": log_std})
    (loss if kl is None else loss + kl).sum().backward()
    frozen = None
    if bool(sched.router_frozen[0]):
        frozen = torch.tensor([[name == "router" for name in group_names]])
        pop.flat.grad.masked_fill_(router_mask, 0.0)
    opt.step(sched.lr_actor, torch.ones(1, dtype=torch.bool), frozen)
    return chosen


target = torch.randn(n_probe, 2, generator=g).clamp(-1, 1)
n_steps = by_scale(scale, ci=20, small=200, paper=200)
for t in range(n_steps):
    update(ctl.begin_iteration(t), probe_obs, target)
    with torch.no_grad():
        pop.flat[0, log_std_span] -= 0.002  # pretend the policy narrowed, so the reset has something to undo

before, before_diag = pop.member(0), dg.plasticity_diagnostics(pop.member(0), ctl.critic.member(0), probe_obs, probe_state)
ctl.on_switch(n_steps)
after, after_diag = pop.member(0), dg.plasticity_diagnostics(pop.member(0), ctl.critic.member(0), probe_obs, probe_state)

rows = []
for (n, p0), p1 in zip(before.named_parameters(), after.parameters()):
    d = (p1 - p0).detach()
    if n.startswith("gate.experts."):
        for j in range(d.shape[0]):
            rows.append({"parameter": f"{n}[{j}]", "changed": bool(d[j].abs().sum() > 0), "rms change": float(d[j].pow(2).mean().sqrt())})
    else:
        rows.append({"parameter": n, "changed": bool(d.abs().sum() > 0), "rms change": float(d.pow(2).mean().sqrt())})
changes = pd.DataFrame(rows)
print(changes.to_string(index=False))
print("Adam moments after the reset:", float(opt.exp_avg.abs().sum()), "; step counts", opt.steps.tolist(),
      "; log-std now", after.log_std.data.tolist())
assert not changes[~changes.parameter.str.startswith(("gate.experts", "log_std"))].changed.any()

# %% [markdown]
# Every expert trunk moved by an RMS close to $\gamma_0 = 0.005$ (all three experts are noised at
# the switch); the router, noise gate and head are bit-identical; the log-std was set back.
# Next, one iteration after the switch with a real update: the router is frozen, and the
# after-epoch noise goes to the experts the batch used, in proportion to their share of it.

# %%
s = ctl.begin_iteration(n_steps)
row_before = pop.flat[0].detach().clone()
chosen = update(s, probe_obs[:8], target[:8])  # a tiny batch: maybe not every expert is used
counts = F.one_hot(chosen.reshape(1, -1), pop.n_experts).sum(1).float()
ctl.after_epoch(counts, torch.ones(1, dtype=torch.bool))
print("settings:", {k: v for k, v in vars(s.members[0]).items() if k != "lr"}, "\nLRs:", s.members[0].lr)
print("expert shares of the batch:", (counts[0] / counts.sum()).tolist(), "-> noise std per expert:", ctl.last_noise[0])
assert torch.equal(pop.flat[0, router_mask], row_before[router_mask])
print("router unchanged during the freeze: True")

table = pd.DataFrame({"before switch": before_diag, "after switch": after_diag})
table = table[~table.index.str.contains("/expert.*/layer")]
print(table.to_string(float_format=lambda v: f"{v:.4g}"))

# %% [markdown]
# The noise is small: the ranks and dormant fractions move a little, the mean action barely; the
# visible change at the switch is the action spread, back at 0.3. The paper's claim is about what
# these perturbations do *over training* (rank peaks and dormant-fraction oscillations in sync with
# the switches); that is measured by the trainer, which logs `plasticity_diagnostics` every
# iteration, in notebooks 07 and 09.
