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
# # 06c · Appendix: two plasticity baselines, ReDo and shrink-and-perturb
#
# PE-MAMoE's Phase Controller (notebook 06) is one answer to the loss of plasticity at a phase
# switch. Two simpler answers from the literature make natural baselines, and each is one small
# plasticity method here, built only on the public hooks of appendix 06b, so that they can be read
# and compared side by side:
#
# * **ReDo** (Sokar et al., 2023, "The Dormant Neuron Phenomenon in Deep RL") recycles the units
#   that have gone quiet. At every switch it measures, on a batch of recent observations, each
#   hidden unit's $\tau$-dormant score $s_u = \mathbb E|h_u| / \big(\tfrac1d\sum_k \mathbb E|h_k|\big)$
#   (the score that appendix 06e defines and the trainer logs as `dormant/tau`), and for every unit with $s_u \le \tau$ it
#   re-initialises the unit's incoming weights and bias, zeroes its outgoing weights, and resets
#   the Adam moments of both. The zeroed outgoing weights leave the network's output as it was at
#   the moment of recycling; the fresh incoming weights let the unit learn again.
# * **Shrink-and-perturb** (Ash & Adams, 2020, "On Warm-Starting Neural Network Training") moves
#   every weight towards a fresh initialisation: at every switch
#   $\theta \leftarrow \lambda\,\theta + \sigma\,\varepsilon$, where $\varepsilon$ is the parameter
#   vector of a newly initialised network of the same kind. Shrinking restores the gradient scale
#   that large weights lose; the noise restores some of the initial diversity.
#
# Both act on the actor, as the Phase Controller's switch-time actions do (the critic keeps
# learning as it is), leave the log-std alone (it is not a weight of the representation), and
# otherwise train with the shared PPO schedule of the baselines. Each acts on every member of a
# population through that member's row only, with draws from the member's own generator, so a
# member trains bit for bit as it would alone.
#
# The registry (appendix 05e) pairs each with the MLP and with the SMoE network: `mlp_redo`,
# `smoe_redo`, `mlp_snp` and `smoe_snp`. They are registered with `compared=False`: a sweep runs
# them when named (`python -m pemamoe sweep --methods smoe_redo smoe_snp pemamoe`), and the
# paper's comparison stays the paper's four methods.

# %%
#| default_exp plasticity_baselines

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %%
#| export
from dataclasses import dataclass

import torch

from pemamoe.core import require_field
from pemamoe.diagnostics import DORMANT_TAU
from pemamoe.plasticity import NoPlasticity, register_plasticity

# %% [markdown]
# ## The numbers
#
# Each method's numbers live in a frozen config. They are not fields of the run's `TrainConfig`, so
# they are not part of a run's identity: changing a default changes what a cached run of these
# methods would compute, which is a change of the training arithmetic (bump `TRAINING_NUMERICS`,
# notebook 07c; the numerics fingerprint test trains every registered method and would notice). A
# different setting is best registered as a method of its own (a subclass with another `config`).
#
# * ReDo's threshold is the diagnostics' $\tau = 0.025$, so the units it recycles are the units the
#   `dormant/tau` curves count (Sokar et al. tune $\tau$ per domain). Its batch is 512 agent
#   observations of the last rollout before the switch, as many as the diagnostics' probe batch.
# * Shrink-and-perturb's $\lambda = 0.8$ and $\sigma = 0.2$ are a mild setting of our choosing
#   (Ash & Adams tune both): a weight keeps 80 % of itself, and the noise is a fifth of an initial
#   weight's size.

# %%
#| export
@dataclass(frozen=True)
class ReDoConfig:
    """ReDo at each switch: recycle the units whose tau-dormant score on recent observations is <= tau."""

    tau: float = DORMANT_TAU
    probe_rows: int = 512  # agent observations of the last rollout on which the scores are measured

    def __post_init__(self):
        require_field(self, "tau", "real", ge=0)
        require_field(self, "probe_rows", "int", ge=1)


@dataclass(frozen=True)
class ShrinkAndPerturbConfig:
    """Shrink-and-perturb at each switch: theta <- shrink * theta + perturb * (a fresh initialisation)."""

    shrink: float = 0.8
    perturb: float = 0.2

    def __post_init__(self):
        require_field(self, "shrink", "real", ge=0, le=1)
        require_field(self, "perturb", "real", ge=0)


# %% [markdown]
# ## Where a unit's weights live
#
# ReDo needs, for every hidden unit, the flat positions of its incoming weights (and bias) and of
# its outgoing weights in a member's row. `recycling_layers` reads them off the actor with
# `ParamLayout.indices` (appendix 05b), for the two actor families of notebook 05:
#
# * the **MLP** (`fc1`, `fc2`, `head`): unit $u$ of layer 1 receives `fc1.weight[u, :]` and
#   `fc1.bias[u]` and sends `fc2.weight[:, u]`; unit $u$ of layer 2 receives `fc2.weight[u, :]`,
#   `fc2.bias[u]` and sends `head.weight[:, u]`;
# * the **expert bank** of the MoE and SMoE actors (`w1` of shape (E, in, hidden), computing
#   $x W_1$): unit $u$ of expert $e$'s layer 1 receives `w1[e, :, u]`, `b1[e, u]` and sends
#   `w2[e, u, :]`; in layer 2 it receives `w2[e, :, u]`, `b2[e, u]`.
#
# The experts' last layer feeds the **shared** head, so the head's column $u$ is the outgoing
# weight of unit $u$ of every expert. ReDo zeroes it only when unit $u$ is dormant in every expert;
# otherwise it re-initialises the dormant expert's incoming weights and keeps the column the other
# experts use. That recycled unit then feeds the output at once, the one place where ReDo on a
# mixture does not leave the output unchanged. The routers are left alone: their outputs are the
# experts, not hidden units.

# %%
#| export
def recycling_layers(actor) -> list:
    """Per hidden layer: {"incoming": (E, H, fan_in + 1) flat positions of each unit's incoming
    weights and bias, "outgoing": (E, H, fan_out) of its outgoing weights, "shared": True where the
    outgoing positions are the same for every expert (the mixture's shared head)}. actor: a
    PopulationActor (or anything with .template and .layout) of the MLP or expert-bank kind."""
    template, ix = actor.template, actor.layout.indices
    gate = getattr(template, "gate", None)
    if gate is not None:
        bank = "gate.experts."
        w1, b1, w2, b2 = (ix(bank + n) for n in ("w1", "b1", "w2", "b2"))
        head = ix("head.weight")  # (A, H) shared by the experts, or (E, A, H): each expert its own
        per_expert = head.ndim == 3
        return [
            {"incoming": torch.cat([w1.transpose(1, 2), b1.unsqueeze(-1)], -1), "outgoing": w2, "shared": False},
            {"incoming": torch.cat([w2.transpose(1, 2), b2.unsqueeze(-1)], -1),
             "outgoing": head.transpose(-1, -2) if per_expert else head.T.unsqueeze(0), "shared": not per_expert},
        ]
    if all(hasattr(template, n) for n in ("fc1", "fc2", "head")):
        w1, b1, w2, b2 = (ix(n) for n in ("fc1.weight", "fc1.bias", "fc2.weight", "fc2.bias"))
        return [
            {"incoming": torch.cat([w1, b1.unsqueeze(-1)], -1).unsqueeze(0), "outgoing": w2.T.unsqueeze(0), "shared": False},
            {"incoming": torch.cat([w2, b2.unsqueeze(-1)], -1).unsqueeze(0),
             "outgoing": ix("head.weight").T.unsqueeze(0), "shared": False},
        ]
    raise ValueError(f"ReDo knows the MLP and expert-bank actors (fc1/fc2/head or gate.experts), got {type(template).__name__}")


def dormant_units(act: torch.Tensor, tau: float) -> torch.Tensor:
    """(E, H) bool: units with tau-dormant score <= tau, from post-activations act (E, B, H); a layer
    whose units are all silent is all dormant (as pemamoe.diagnostics.dormant_fraction_tau)."""
    m = act.abs().double().mean(1)
    layer_mean = m.mean(-1, keepdim=True)
    return (layer_mean == 0) | (m / layer_mean <= tau)


# %% [markdown]
# ## ReDo
#
# `recycle(r)` is one member's switch-time action, and returns how many units it recycled, which
# `metrics(r)` logs as `redo/units_recycled` in the iteration of the switch (0 elsewhere). The
# scores come from `probe_batch(r)`, the last rollout's observations that appendix 06b keeps for
# methods that set `probe_rows`; the fresh weights from `fresh_parameters(r)`, a newly initialised
# actor drawn from the member's own generator. Re-initialised entries are written first and zeroed
# ones last, so an `fc2` weight that is both the outgoing weight of a recycled layer-1 unit and an
# incoming weight of a recycled layer-2 unit ends at zero. `RunAdamW.reset(r, mask)` forgets the
# moments of every entry touched and restarts their bias correction (appendix 06d).

# %%
#| export
@register_plasticity
class ReDo(NoPlasticity):
    """ReDo (Sokar et al., 2023) at each switch, per member: recycle the tau-dormant hidden units."""

    name = "redo"
    config = ReDoConfig()

    def __init__(self, configs, actor, critic, actor_opt, critic_opt):
        super().__init__(configs, actor, critic, actor_opt, critic_opt)
        self.probe_rows = self.config.probe_rows
        self.layers = recycling_layers(actor)
        self.recycled = [0] * self.R
        self._switched_at = self._iteration = None
        self._single = None  # a single-run actor to load a member into for its probe

    @torch.no_grad()
    def on_switch(self, iteration: int) -> None:
        self.recycled = [self.recycle(r) for r in range(self.R)]
        self._switched_at = int(iteration)

    def begin_iteration(self, iteration: int):
        self._iteration = int(iteration)
        return super().begin_iteration(iteration)

    def metrics(self, r: int) -> dict:
        return {"redo/units_recycled": self.recycled[r] if self._iteration == self._switched_at else 0}

    @torch.no_grad()
    def recycle(self, r: int) -> int:
        """Recycle member r's tau-dormant units (on probe_batch(r)); returns how many."""
        self._single = self.actor.member(r, self._single)
        acts = self._single.probe(self.probe_batch(r).cpu())["act"]  # per layer (E, B, H)
        reinit, zero, count = [], [], 0
        for layer, act in zip(self.layers, acts):
            dormant = dormant_units(act, self.config.tau)
            count += int(dormant.sum())
            reinit.append(layer["incoming"][dormant].reshape(-1))
            if layer["shared"]:  # the head's column u: only when unit u is dormant in every expert
                zero.append(layer["outgoing"][0][dormant.all(0)].reshape(-1))
            else:
                zero.append(layer["outgoing"][dormant].reshape(-1))
        if count == 0:
            return 0
        reinit, zero = torch.cat(reinit).to(self.device), torch.cat(zero).to(self.device)
        fresh = self.fresh_parameters(r)
        row = self.actor.flat[r]
        row[reinit] = fresh[reinit]
        row[zero] = 0.0
        self.actor_opt.reset(r, torch.cat([reinit, zero]))
        return count


# %% [markdown]
# ## Shrink-and-perturb
#
# `shrink_and_perturb(r)` is one member's switch-time action: every actor parameter but the
# log-std becomes $\lambda\theta + \sigma\varepsilon$, with $\varepsilon$ from
# `fresh_parameters(r)` (a fresh actor's biases are zero, so biases only shrink). The Adam moments
# are kept: the method changes the weights, not the optimiser. It logs nothing of its own, so its
# `metrics.parquet` has exactly the baselines' columns.

# %%
#| export
@register_plasticity
class ShrinkAndPerturb(NoPlasticity):
    """Shrink-and-perturb (Ash & Adams, 2020) at each switch, per member: theta <- shrink * theta +
    perturb * (a fresh initialisation), on every actor parameter except the log-std."""

    name = "shrink_and_perturb"
    config = ShrinkAndPerturbConfig()

    def __init__(self, configs, actor, critic, actor_opt, critic_opt):
        super().__init__(configs, actor, critic, actor_opt, critic_opt)
        self.weights = (~actor.layout.mask(["log_std"])).nonzero().reshape(-1).to(self.device)

    @torch.no_grad()
    def on_switch(self, iteration: int) -> None:
        for r in range(self.R):
            self.shrink_and_perturb(r)

    @torch.no_grad()
    def shrink_and_perturb(self, r: int) -> None:
        fresh = self.fresh_parameters(r)
        idx, cfg = self.weights, self.config
        self.actor.flat[r, idx] = cfg.shrink * self.actor.flat[r, idx] + cfg.perturb * fresh[idx]


# %% [markdown]
# ## Checks on a small population
#
# Two members of each network kind, built as the trainer builds them (appendix 06b's
# `population` recipe). Some Adam state first, from a few steps on random gradients; then we
# silence three units of member 0's first layer (a bias far below zero makes a ReLU unit dead on
# every input), hand the method a rollout's worth of random observations, and recycle member 0.

# %%
import copy
from types import SimpleNamespace

import pandas as pd

from pemamoe.core import by_scale
from pemamoe.diagnostics import dormant_fraction_tau
from pemamoe.nets import PopulationActor, PopulationCritic, make_actor, make_critic
from pemamoe.optim import RunAdamW, group_index
from pemamoe.plasticity import RunSettings

obs_dim, state_dim = by_scale(scale, ci=24, small=64, paper=177), by_scale(scale, ci=32, small=96, paper=240)
base = RunSettings(total_iterations=300, phase_length=100)
members = [SimpleNamespace(seed=s, base_schedule=lambda: base) for s in (seed, seed + 1)]


def population(kind):
    singles = []
    for m in members:
        torch.manual_seed(m.seed)
        singles.append((make_actor(kind, obs_dim), make_critic(kind, state_dim)))
    actor, critic = PopulationActor([a for a, _ in singles]), PopulationCritic([c for _, c in singles])
    group_of, names = group_index(singles[0][0], actor.layout)
    actor_opt = RunAdamW(actor.flat, group_of, len(names), weight_decay=1e-4)
    critic_opt = RunAdamW(critic.flat, torch.zeros(critic.layout.size, dtype=torch.long), 1)
    g = torch.Generator().manual_seed(seed)
    for _ in range(3):  # give Adam some state
        actor.flat.grad = torch.randn(actor.flat.shape, generator=g)
        actor_opt.step(torch.full((len(members),), 1e-3, dtype=torch.float64), torch.ones(len(members), dtype=torch.bool))
    return actor, critic, actor_opt, critic_opt


g = torch.Generator().manual_seed(seed)
rollout_obs = torch.randn(len(members), 64, 3, obs_dim, generator=g)  # (R, N, U, obs_dim), as the trainer hands it
rows = []
for kind in ("mlp", "smoe"):
    actor, critic, actor_opt, critic_opt = population(kind)
    first = "fc1.bias" if kind == "mlp" else "gate.experts.b1"
    with torch.no_grad():  # three dead units in member 0's first layer (expert 0 for the mixture)
        bias = actor.member_param(0, first)
        (bias[:3] if kind == "mlp" else bias[0, :3]).fill_(-1e3)
    method = ReDo(members, actor, critic, actor_opt, critic_opt)
    method.observe_rollout(rollout_obs)
    probe = method.probe_batch(0)
    single = actor.member(0)
    before = dict(flat=actor.flat.detach().clone(), m=actor_opt.exp_avg.clone(), steps=actor_opt.steps.clone(),
                  mean=single.probe(probe)["mean"], tau=[dormant_fraction_tau(a[0]) for a in single.probe(probe)["act"]])
    n = method.recycle(0)
    single = actor.member(0)
    after_act = single.probe(probe)["act"]
    changed = actor.flat[0].detach() != before["flat"][0]
    rows.append({
        "network": kind, "units recycled": n,
        "entries changed": int(changed.sum()),
        "moments reset": int(((actor_opt.exp_avg[0] == 0) & (before["m"][0] != 0)).sum()),
        "dormant (tau) before, layer 1": before["tau"][0],
        "after": dormant_fraction_tau(after_act[0][0]),
        "output moved": float((single.probe(probe)["mean"] - before["mean"]).abs().max()),
        "member 1 untouched": bool(torch.equal(actor.flat[1].detach(), before["flat"][1])
                                   and torch.equal(actor_opt.exp_avg[1], before["m"][1])),
        "step counts kept": bool(torch.equal(actor_opt.steps, before["steps"])),
    })
    assert n >= 3 and rows[-1]["member 1 untouched"] and rows[-1]["step counts kept"]
    assert rows[-1]["after"] < rows[-1]["dormant (tau) before, layer 1"]
print(pd.DataFrame(rows).to_string(index=False))
assert rows[0]["output moved"] == 0.0  # the MLP: recycled units' outgoing weights are zero

# %% [markdown]
# The dead units are recycled (with any other unit that happened to score below $\tau$ on this
# batch), the first layer's dormant fraction drops, member 1's parameters and moments are
# bit-identical, and no step count moved (the reset entries keep clocks of their own). The MLP's
# output did not move at all; the mixture's moved only where a last-layer unit was recycled in
# one expert but not in all (its head column is shared).
#
# **Shrink-and-perturb** on member 0 only: every weight is exactly $\lambda\theta + \sigma\varepsilon$
# with the $\varepsilon$ that `fresh_parameters` gives from the same generator state; member 1 and
# both members' moments are untouched.

# %%
for kind in ("mlp", "smoe"):
    actor, critic, actor_opt, critic_opt = population(kind)
    method = ShrinkAndPerturb(members, actor, critic, actor_opt, critic_opt)
    before, moments = actor.flat.detach().clone(), actor_opt.exp_avg.clone()
    state = method.member_generator(0).get_state()
    method.shrink_and_perturb(0)
    method.member_generator(0).set_state(state)
    eps = method.fresh_parameters(0)
    idx = method.weights
    expected = method.config.shrink * before[0, idx] + method.config.perturb * eps[idx]
    ls = slice(*actor.layout.span("log_std"))
    print(f"{kind:5s} weight norm {float(before[0, idx].norm()):.3f} -> {float(actor.flat[0, idx].detach().norm()):.3f}; "
          f"log-std kept: {torch.equal(actor.flat[0, ls].detach(), before[0, ls])}")
    assert torch.equal(actor.flat[0, idx].detach(), expected)
    assert torch.equal(actor.flat[1].detach(), before[1]) and torch.equal(actor_opt.exp_avg, moments)

# %% [markdown]
# ## In training
#
# A short run of `smoe_redo` through the trainer of notebook 07 (a `ci`-sized run at every scale:
# only the log's columns are shown here). The switch iterations log how many units ReDo recycled.

# %%
from pemamoe.mappo import TrainConfig, train_population

configs = [TrainConfig.for_scale("ci", method="smoe_redo", seed=s) for s in (seed, seed + 1)]
results = train_population(configs, progress=False)
log = pd.DataFrame({f"member {r}": res.metrics.set_index("iteration")["redo/units_recycled"] for r, res in enumerate(results)})
log.insert(0, "switch", results[0].metrics.set_index("iteration")["switch"])
print(log.to_string())
assert (log.loc[~log.switch].drop(columns="switch") == 0).all().all()
