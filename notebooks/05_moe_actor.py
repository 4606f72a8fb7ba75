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
# # 05 · Actors and critics: MLP, MoE, SMoE, PE-MAMoE (paper section IV-A)
#
# This notebook builds the four policy networks the paper compares, the matching centralised
# critics, and the cost accounting behind the paper's "Computational cost" table.
#
# Every actor is a Gaussian policy over the UAV's 2-D displacement. The mean comes from a network
# of the observation; the spread is one learned log-standard-deviation per action coordinate that
# does not depend on the observation. The four actors differ only in how they turn the
# observation into the 32-wide feature vector that feeds the final linear "head":
#
# | kind | feature extractor | gating |
# |---|---|---|
# | `mlp` | one trunk obs→32→32 (ReLU) | none |
# | `moe` | three trunks obs→32→32, mixed by a softmax router | dense: every expert runs |
# | `smoe` | same three trunks | noisy top-k: one expert runs (k = 1) |
# | `pemamoe` | identical to `smoe` | identical; the plasticity tricks live in the phase controller |
#
# The sections below derive the architecture from the paper's parameter counts, define the
# gating (temperature, top-k, noise, the gradient for k = 1, load balancing), make PPO's
# importance ratio exact under random routing, draw the four architectures and regenerate the
# cost table. The machinery the experiments add on top (the method registry, the faster ways of
# executing the experts, the population of networks trained as one set of tensors, and the
# latency measurements) is in the appendix notebook `05b_population_nets.py`.

# %%
#| default_exp nets

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0
our_obs_dim = None  # None: ask pemamoe.env for the observation dimension of EnvConfig()

# %%
#| export
import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.distributions import Independent, Normal

from pemamoe.core import require_field
from pemamoe.methods import METHOD_REGISTRY, load_plugins
from pemamoe.routing import RoutingSample  # re-export: the random choices of a gated pass (below)

# The batched machinery of appendix 05b, used by the classes below and re-exported from here:
from pemamoe.popnets import (ParamLayout, PopulationActor, PopulationCritic, gaussian_entropy,  # re-export  # noqa: F401
                             gaussian_kl, gaussian_log_prob, loop_experts, masked_mixed, run_experts, run_gate,
                             run_linear, run_load_balance, topk_weights)

# %% [markdown]
# ## Reading the architecture off the paper's parameter counts
#
# The paper gives no layer list for the actors, only a table: 6,820 parameters for the MLP actor,
# 20,858 for the MoE, 21,392 for the sparse MoE and PE-MAMoE, and 7,820 "active at inference" for
# the sparse ones, at observation dimension 177 with hidden width 32, three experts and a 2-D
# action. Those four integers pin the architecture down. Writing a linear layer with $n$ inputs
# and $m$ outputs as $nm + m$ parameters:
#
# * **MLP**: $177\cdot 32+32 = 5696$ (first layer) $+\ 32\cdot 32+32 = 1056$ (second)
#   $+\ 32\cdot 2+2 = 66$ (mean head) $+\ 2$ (log-std) $= 6820$. So the MLP is
#   obs→32→32→2 with a state-independent log-std.
# * **MoE**: each expert trunk obs→32→32 costs $5696+1056 = 6752$; three of them cost 20,256.
#   A linear router obs→3 costs $177\cdot 3+3 = 534$. Then $20256+534+66+2 = 20858$: the mean
#   head (66) and the log-std (2) are counted **once**, so the three experts share a single head.
# * **SMoE**: $20858 + 534 = 21392$, one more obs→3 linear layer. That is exactly the second
#   projection of Shazeer-style noisy gating, which computes a per-expert noise scale from the
#   input.
# * **Active at inference (SMoE)**: router (534) + noise gate (534) + one expert trunk (6752)
#   $= 7820$. The paper's number **leaves out the shared head (66) and the log-std (2)**, which
#   run on every step. Counting everything that executes when an action is sampled gives
#   $7888$; counting what runs in deterministic evaluation (noise gate skipped) gives $7354$.
#   We reproduce the paper's convention exactly (`mode="paper"`) and report the two honest counts
#   beside it.
#
# The paper's ratio "about 1.16× the MLP's multiply-accumulates" is consistent with the sampling
# count: the MLP does $177\cdot32+32\cdot32+32\cdot2 = 6752$ MACs per step, the sparse actor
# $2\cdot 531 + 6688 + 64 = 7814$, ratio 1.157.
#
# **A contradiction in the text.** The paper's equations give every expert its own linear mean
# map of the raw observation ($\mu^{(j)} = W^{(j)}_\mu x + b^{(j)}_\mu$) and mix the means. That
# design would cost $3\,(177\cdot2+2)$ plus router, nowhere near 20,858. The counts, and the
# figure caption ("combine their outputs to form a shared MoE trunk, which parameterizes the
# policy head"), describe deep expert trunks followed by one shared head. We follow the counts.
#
# **Where the experts are mixed.** With one shared linear head $h(\cdot)$ and mixing weights
# that sum to one, mixing features and mixing head outputs are the same function:
# $h(\sum_j w_j f_j) = \sum_j w_j h(f_j)$, since the head's bias is multiplied by
# $\sum_j w_j = 1$. We mix the 32-wide features and apply the head once. It is cheaper, it
# matches the caption's "shared trunk", and the features it produces are what the plasticity
# diagnostics (feature rank, dormant units) look at.

# %% [markdown]
# ## The methods: a network kind plus a plasticity method
#
# A *method* in the experiments pairs a network kind of this notebook with a plasticity method of
# notebook 06: the paper's `mlp`, `moe` and `smoe` train the network of that name with no
# plasticity tricks, and `pemamoe` is the SMoE network with the Phase Controller. The registry
# that names the methods (with their labels, colours and the paper's cost-table numbers) is module
# `pemamoe.methods`, explained in appendix 05b; this notebook reads it for the paper's numbers and
# to build one actor per method.

# %% [markdown]
# ## Configuration
#
# One frozen dataclass holds every number of the networks:
#
# * `hidden = 32`, `n_experts = 3`, `top_k = 1`: the paper's values. The dense MoE ignores
#   `top_k` (it always mixes every expert).
# * `init_log_std = log(0.3)`: Algorithm 1 resets the log-std "to $\sigma_{\text{init}}$" at a
#   switch, and the training table lists the reset value 0.3. We read that as $\sigma = 0.3$ at
#   initialisation, so a reset puts the policy back to exactly its initial spread.
# * `load_balance_coef = 0.01`: the weight of the Switch-style balance loss (the value Switch
#   Transformers use; the paper gives none). The actor reports the weighted term as `aux_loss`.
# * Three gating choices the paper leaves open (the section "Top-1 gating: what the equations
#   leave open" below explains them, and the comparison that chose the defaults):
#   `top1_weight` (how the one kept expert is weighted), `routing_noise` (the Gaussian noise on
#   the router's logits while sampling: `learned`, `fixed`, `annealed` or `off`, with `noise_std`
#   and `noise_anneal_portion`), and `critic_gating` (the centralised critic of a gated method:
#   `dense`, `gated` or `mlp`).
# * `expert_impl = "auto"` and `masked_min_batch = 512`: how the expert bank is executed (next
#   section). It changes speed, never the parameters or the outputs.
# * Orthogonal initialisation gains (the usual PPO choices): $\sqrt2$ for hidden layers, 0.01 for
#   the policy mean head (actions start near zero), 1.0 for the value head, and 0.01 for the
#   router, so that every expert starts with nearly equal probability. The noise gate starts at
#   zero weights, i.e. a noise scale of softplus(0) ≈ 0.69 for every expert.
#
# A bad value raises a `ValueError` that names the field, the value and what is allowed.

# %%
#| export
EXPERT_IMPLS = ("auto", "stacked", "masked", "loop")
TOP1_WEIGHTS = ("straight_through", "switch", "paper")
ROUTING_NOISES = ("learned", "fixed", "annealed", "off")
CRITIC_GATINGS = ("dense", "gated", "mlp")
ACTIVE_MODES = ("paper", "sampling", "eval")
MAC_MODES = ("sampling", "eval")

# What the paper's Table "Computational cost" reports at observation dimension 177 (hidden 32,
# 3 experts, 2-D action): total actor parameters and parameters active at inference. Used only to
# compare against the counts computed from the modules, never in a computation.
# The numbers themselves live in the method registry (pemamoe.methods).
PAPER_OBS_DIM = 177
PAPER_ACTOR_PARAMS = {name: spec.paper_actor_params for name, spec in METHOD_REGISTRY.items()}
PAPER_ACTIVE_PARAMS = {name: spec.paper_active_params for name, spec in METHOD_REGISTRY.items()}


@dataclass(frozen=True)
class NetConfig:
    """Sizes and initialisation of every actor and critic (see notebook 05)."""

    hidden: int = 32
    n_experts: int = 3
    top_k: int = 1
    init_log_std: float = math.log(0.3)
    load_balance_coef: float = 0.01
    # the gating readings (chosen by the comparison of appendix 05c; see "Top-1 gating" below)
    top1_weight: str = "straight_through"
    routing_noise: str = "off"
    noise_std: float = 1.0  # sigma of "fixed" routing noise; the starting sigma of "annealed"
    noise_anneal_portion: float = 1.0  # "annealed": sigma reaches 0 after this fraction of the run
    critic_gating: str = "dense"
    expert_impl: str = "auto"
    masked_min_batch: int = 512
    gain_hidden: float = math.sqrt(2.0)
    gain_policy: float = 0.01
    gain_value: float = 1.0
    gain_router: float = 0.01

    def __post_init__(self):
        require_field(self, "hidden", "int", ge=1)
        require_field(self, "n_experts", "int", ge=1)
        require_field(self, "top_k", "int", ge=1, le=self.n_experts)
        require_field(self, "init_log_std", "real")
        require_field(self, "load_balance_coef", "real", ge=0)
        require_field(self, "top1_weight", "choice", TOP1_WEIGHTS)
        require_field(self, "routing_noise", "choice", ROUTING_NOISES)
        require_field(self, "noise_std", "real", ge=0)
        require_field(self, "noise_anneal_portion", "real", gt=0, le=1)
        require_field(self, "critic_gating", "choice", CRITIC_GATINGS)
        require_field(self, "expert_impl", "choice", EXPERT_IMPLS)
        require_field(self, "masked_min_batch", "int", ge=1)
        for name in ("gain_hidden", "gain_policy", "gain_value", "gain_router"):
            require_field(self, name, "real", gt=0)


# The paper's parameter counts include a noise gate (its SMoE actor has 534 = 3 x (177 + 1) more
# parameters than its dense MoE): the paper's network had learned routing noise. Its cost table
# is reproduced with this configuration, whatever our defaults.
PAPER_NET = NetConfig(routing_noise="learned")


def routing_noise_std(cfg: NetConfig, iteration: int, iterations: int) -> float:
    """Sigma of the routing noise at `iteration` of a run of `iterations`: cfg.noise_std for
    `fixed`, falling linearly to 0 over the first noise_anneal_portion of the run for `annealed`,
    0 for `off` (and for `learned`, whose scale the network computes)."""
    if cfg.routing_noise == "fixed":
        return float(cfg.noise_std)
    if cfg.routing_noise == "annealed":
        return float(cfg.noise_std * max(0.0, 1.0 - iteration / (cfg.noise_anneal_portion * iterations)))
    return 0.0


# %% [markdown]
# ## The expert bank and three ways to run it
#
# The experts are stored **stacked**: the first layers of all $E$ experts form one tensor of
# shape `(E, obs_dim, hidden)`, the second layers one `(E, hidden, hidden)`, plus the biases.
# This storage is the same whichever way we execute the experts, so parameter counts, state
# dicts, optimiser groups and the phase controller's noise injection never depend on the choice:
#
# * `stacked` (the code below): run every expert on every sample with two batched matrix
#   products (`torch.baddbmm`), then pick the selected experts' rows. It wastes $E-1$ of $E$
#   experts' arithmetic under top-1 routing, but makes only a handful of kernel calls.
# * `masked`: run each expert only on the rows routed to it, the genuine conditional computation
#   the paper describes, paid for with more, smaller kernel calls and indexing.
# * `loop`: the textbook version, each expert as a pair of ordinary linear layers on the whole
#   batch, then select.
#
# `masked` and `loop` are written out in appendix 05b (`masked_mixed`, `loop_experts`), with the
# timings behind the default: `"auto"` takes `masked` for sparse mixing at batches of at least
# `NetConfig.masked_min_batch` rows, where doing a third of the arithmetic pays for the indexing,
# and `stacked` otherwise. Each strategy stays selectable with `NetConfig(expert_impl=...)` or by
# setting `bank.impl`.
#
# `ExpertBank.all_experts` also returns each layer's pre-activations and activations for every
# expert; the plasticity diagnostics (feature rank, dormant neurons) read them through
# `probe()`.

# %%
#| export
class ExpertBank(nn.Module):
    """E expert trunks in_dim -> hidden -> hidden (ReLU), stored as stacked weights.

    Parameters: w1 (E, in_dim, hidden), b1 (E, hidden), w2 (E, hidden, hidden), b2 (E, hidden).
    `impl` ("auto" | "stacked" | "masked" | "loop") only changes how the forward pass is executed;
    "auto" means "masked" for sparse mixing of at least `masked_min_batch` rows, else "stacked".
    """

    def __init__(
        self,
        in_dim: int,
        hidden: int,
        n_experts: int,
        impl: str = "auto",
        gain: float = math.sqrt(2.0),
        masked_min_batch: int = 512,
    ):
        super().__init__()
        self.in_dim, self.hidden, self.n_experts = in_dim, hidden, n_experts
        self.masked_min_batch = masked_min_batch
        self.w1 = nn.Parameter(torch.empty(n_experts, in_dim, hidden))
        self.b1 = nn.Parameter(torch.zeros(n_experts, hidden))
        self.w2 = nn.Parameter(torch.empty(n_experts, hidden, hidden))
        self.b2 = nn.Parameter(torch.zeros(n_experts, hidden))
        self.impl = impl
        with torch.no_grad():
            for e in range(n_experts):  # same init as an nn.Linear(out, in) weight, transposed
                self.w1[e].copy_(nn.init.orthogonal_(torch.empty(hidden, in_dim), gain).T)
                self.w2[e].copy_(nn.init.orthogonal_(torch.empty(hidden, hidden), gain).T)

    @property
    def impl(self) -> str:
        return self._impl

    @impl.setter
    def impl(self, value: str):
        if value not in EXPERT_IMPLS:
            raise ValueError(f"ExpertBank.impl must be one of {', '.join(EXPERT_IMPLS)}, got {value!r}")
        self._impl = value

    def params_per_expert(self) -> int:
        return sum(p.numel() for p in self.parameters()) // self.n_experts

    def macs_per_expert(self) -> int:
        return self.w1.shape[1] * self.w1.shape[2] + self.w2.shape[1] * self.w2.shape[2]

    def all_experts(self, x: torch.Tensor, impl: str | None = None, return_layers: bool = False):
        """Every expert on every row of x (B, in_dim) -> (E, B, hidden).

        With return_layers=True returns (out, [pre1, pre2], [act1, act2]), each (E, B, hidden).
        """
        impl = impl or self.impl
        if impl in ("auto", "stacked"):
            xe = x.unsqueeze(0).expand(self.n_experts, *x.shape)
            p1 = torch.baddbmm(self.b1.unsqueeze(1), xe, self.w1)
            a1 = F.relu(p1)
            p2 = torch.baddbmm(self.b2.unsqueeze(1), a1, self.w2)
            a2 = F.relu(p2)
        else:  # "loop" (and "masked", which degenerates to a loop when every expert sees every row)
            p1, a1, p2, a2 = loop_experts(self, x)
        if return_layers:
            return a2, [p1, p2], [a1, a2]
        return a2

    def mixed(self, x: torch.Tensor, experts: torch.Tensor, weights: torch.Tensor, impl: str | None = None):
        """sum_j weights[:, j] * expert_{experts[:, j]}(x) -> (B, hidden).

        x (B, in_dim); experts (B, k) long; weights (B, k).
        """
        impl = impl or self.impl
        if impl == "auto":
            impl = "masked" if x.shape[0] >= self.masked_min_batch else "stacked"
        if impl == "masked":  # each expert on its own rows only (appendix 05b)
            return masked_mixed(self, x, experts, weights)
        h = self.all_experts(x, impl).transpose(0, 1)  # (B, E, hidden)
        picked = h.gather(1, experts.unsqueeze(-1).expand(-1, -1, self.hidden))  # (B, k, hidden)
        return (picked * weights.unsqueeze(-1)).sum(1)


# %% [markdown]
# ## Gating: temperature, noise, top-k, and a gradient for k = 1
#
# The router is one linear map from the observation to $E$ logits $z$ (the paper uses the raw
# observation as router input, no embedding). For the sparse actors a second linear map gives a
# per-expert noise scale $\mathrm{softplus}(z^{\text{noise}})$, and while sampling we draw
# $\varepsilon \sim \mathcal N(0, I)$:
#
# $$ h = z/\tau + \varepsilon \odot \mathrm{softplus}(z^{\text{noise}}), \qquad
#    g = \mathrm{softmax}(h), $$
#
# keep the $k$ largest entries of $g$, and renormalise them to sum to one (the paper's sparse
# weights). A softmax restricted to its top-k entries and renormalised equals the softmax over
# the kept logits alone, so this is the same as Shazeer's "keep top-k logits, then softmax".
#
# **Where the temperature goes.** The paper divides the logits by $\tau$ and then takes the top-k
# of the result. Dividing by a positive number never changes which entry is largest, so under
# the paper's literal formula the temperature cannot change a single routing decision; it would
# only rescale gradients. The phase controller raises $\tau$ precisely to spread traffic over the
# experts after a switch. We therefore divide only the learned logits by $\tau$ and add the noise
# afterwards: a hot router shrinks its own preferences relative to the exploration noise, so
# more samples land on other experts, and at $\tau = 1$ this is exactly Shazeer's noisy top-k.
# The dense MoE has no noise; there $\tau$ flattens or sharpens the mixing weights directly.
#
# **The k = 1 gradient problem.** With one kept expert the renormalised weight is $g_j/g_j = 1$
# for every input, and its derivative is zero: the policy loss would never reach the router,
# which would only learn from the balance loss. The `top1_weight` setting says what to do about
# it (next section); the default keeps the forward value exactly 1 and gives the backward pass
# the Switch Transformer's gradient, by adding $g_j - \mathrm{sg}(g_j)$ (sg: stop gradient). That
# term is exactly zero in value, and its derivative is $\partial g_j$, so the router learns how
# much the chosen expert helped. For $k \ge 2$ the renormalised weights already carry a gradient
# and every setting leaves them alone.
#
# **Load balancing.** With $f_i$ the fraction of routing slots that went to expert $i$ and $P_i$
# the batch-mean of $g_i$, the Switch loss is $E\sum_i f_i P_i$. It equals 1 when routing is
# uniform and reaches $E$ when one expert takes everything with probability 1; only $P$ carries a
# gradient. For the dense MoE, $f_i$ counts the samples whose largest weight is expert $i$.

# %%
#| export routing
from typing import NamedTuple

import torch


class RoutingSample(NamedTuple):
    """The random choices of one gated forward pass, stored in the rollout buffer.

    noise (..., E): the gate noise drawn, per unit of the gate's noise_scale: standard normal for
        `learned` noise, already times sigma for `fixed` and `annealed`, zeros when noiseless;
    experts (..., k): the selected expert indices (all E, in order, for the dense MoE);
    temperature (...,): the router temperature in force.
    Passing it back as `routing=` replays the pass exactly.
    """

    noise: torch.Tensor
    experts: torch.Tensor
    temperature: torch.Tensor

    def select(self, index) -> "RoutingSample":
        """Rows `index` of every field (a minibatch), e.g. routing.select(mb_idx)."""
        return RoutingSample(self.noise[index], self.experts[index], self.temperature[index])

    def reshape(self, *lead) -> "RoutingSample":
        """Give the leading axes the shape `lead` (e.g. flatten (T, N) to (T*N,))."""
        return RoutingSample(
            self.noise.reshape(*lead, self.noise.shape[-1]),
            self.experts.reshape(*lead, self.experts.shape[-1]),
            self.temperature.reshape(*lead),
        )

    def to(self, device) -> "RoutingSample":
        return RoutingSample(*(t.to(device) for t in self))

    @staticmethod
    def cat(samples, dim: int = 0) -> "RoutingSample":
        return RoutingSample(*(torch.cat([getattr(s, f) for s in samples], dim) for f in RoutingSample._fields))


# %%
#| export
class GateOutput(NamedTuple):
    features: torch.Tensor  # (B, hidden) gate-weighted mix of expert features
    probs: torch.Tensor  # (B, E) router probabilities g (noisy while sampling)
    experts: torch.Tensor  # (B, k) selected experts
    weights: torch.Tensor  # (B, k) mixing weights of the selected experts
    load_balance: torch.Tensor | None  # scalar E * sum_i f_i P_i (None when not requested)
    routing: RoutingSample  # what to store to replay this pass


def load_balance_loss(probs: torch.Tensor, experts: torch.Tensor, n_experts: int) -> torch.Tensor:
    """Switch-style balance loss E * sum_i f_i * P_i.

    probs (B, E): router probabilities; experts (B, k): selected indices. f_i is the fraction of
    the B*k routing slots assigned to expert i (no gradient), P_i the batch mean of probs[:, i].
    Equals 1 under uniform routing, n_experts when one expert takes everything with probability 1.
    """
    counts = F.one_hot(experts.reshape(-1), n_experts).to(probs.dtype).sum(0)
    f = counts / counts.sum()
    p = probs.reshape(-1, n_experts).mean(0)
    return n_experts * (f * p).sum()


def _temperature_column(temperature, batch: int, like: torch.Tensor) -> torch.Tensor:
    if isinstance(temperature, (int, float)):  # checked in Python: no tensor op on the hot path
        if not temperature > 0:
            raise ValueError(f"router temperature must be > 0, got {temperature!r}")
        return like.new_full((batch,), float(temperature))
    t = torch.as_tensor(temperature, dtype=like.dtype, device=like.device)
    t = t.expand(batch) if t.ndim == 0 else t.reshape(batch)
    if not bool((t > 0).all()):
        raise ValueError(f"router temperature must be > 0, got {temperature!r}")
    return t


class GatedExperts(nn.Module):
    """Router (+ noise gate for noisy sparse gating) over an ExpertBank of E trunks.

    sparse=False: dense softmax mixing of every expert (the MoE baseline).
    sparse=True: top-k of the (noisy, tempered) router probabilities, renormalised.
    """

    def __init__(self, in_dim: int, cfg: NetConfig, sparse: bool):
        super().__init__()
        self.n_experts, self.sparse = cfg.n_experts, sparse
        self.k = cfg.top_k if sparse else cfg.n_experts
        self.noise = cfg.routing_noise if sparse else "off"  # the dense mixture is never noisy
        self.noisy = self.noise != "off"
        self.top1_weight, self.noise_std = cfg.top1_weight, cfg.noise_std
        self.router = nn.Linear(in_dim, cfg.n_experts)
        nn.init.orthogonal_(self.router.weight, cfg.gain_router)
        nn.init.zeros_(self.router.bias)
        if self.noise == "learned":
            self.noise_gate = nn.Linear(in_dim, cfg.n_experts)
            nn.init.zeros_(self.noise_gate.weight)
            nn.init.zeros_(self.noise_gate.bias)
        else:
            self.noise_gate = None
        self.experts = ExpertBank(
            in_dim, cfg.hidden, cfg.n_experts, cfg.expert_impl, cfg.gain_hidden, cfg.masked_min_batch
        )

    def gating_modules(self) -> list:
        return [m for m in (self.router, self.noise_gate) if m is not None]

    def noise_scale(self, x) -> torch.Tensor:
        """Per-row, per-expert multiplier of a stored noise draw (B, E): softplus of the noise
        gate for `learned`; 1 for `fixed` and `annealed`, whose draws are stored already scaled
        by their sigma; 0 when noiseless."""
        if self.noise == "learned":
            return F.softplus(self.noise_gate(x))
        return x.new_full((x.shape[0], self.n_experts), 1.0 if self.noisy else 0.0)

    def forward(
        self,
        x,
        temperature=None,
        routing: RoutingSample | None = None,
        deterministic_gate: bool = False,
        with_aux: bool = True,
    ):
        """x (B, in_dim) -> GateOutput. `routing` replays stored noise and expert choices;
        with_aux=False skips the load-balance loss (its field is then None)."""
        batch, n_exp = x.shape[0], self.n_experts
        if temperature is None:
            temperature = routing.temperature if routing is not None else 1.0
        tau = _temperature_column(temperature, batch, x)
        logits = self.router(x) / tau.unsqueeze(-1)
        if routing is not None:
            noise = routing.noise.reshape(batch, n_exp).to(x.dtype)
        elif self.noisy and not deterministic_gate:
            noise = torch.randn(batch, n_exp, dtype=x.dtype, device=x.device)
            if self.noise != "learned":  # stored scaled (the trainer passes the annealed sigma to the population)
                noise = noise * self.noise_std
        else:
            noise = x.new_zeros(batch, n_exp)
        if self.noisy:
            logits = logits + noise * self.noise_scale(x)
        probs = torch.softmax(logits, dim=-1)

        if not self.sparse:
            experts = torch.arange(n_exp, device=x.device).expand(batch, n_exp)
            impl = "loop" if self.experts.impl in ("masked", "loop") else "stacked"
            features = torch.einsum("be,ebh->bh", probs, self.experts.all_experts(x, impl))
            lb = load_balance_loss(probs, probs.argmax(-1, keepdim=True), n_exp) if with_aux else None
            return GateOutput(features, probs, experts, probs, lb, RoutingSample(noise, experts, tau))

        if routing is not None:
            experts = routing.experts.reshape(batch, self.k).long()
        else:
            experts = probs.topk(self.k, dim=-1).indices
        weights = topk_weights(probs.gather(1, experts), self.top1_weight)
        features = self.experts.mixed(x, experts, weights)
        lb = load_balance_loss(probs, experts, n_exp) if with_aux else None
        return GateOutput(features, probs, experts, weights, lb, RoutingSample(noise, experts, tau))


# %% [markdown]
# ## Top-1 gating: what the equations leave open, and what we chose
#
# At $k = 1$ the paper's own equations do not pin down a trainable router. Its mixing weight
# $w_j = g_j / \sum_{i \in \mathcal T_k} g_i$ is identically 1 for the one kept expert, so the
# task loss has no path to the router. Its noisy gating ("softplus-scaled Gaussian noise") appears
# only in the discussion, as in Shazeer et al. (2017), who used $k \ge 2$, where the renormalised
# weights do carry a gradient. Switch Transformers (Fedus et al.) made $k = 1$ trainable by scaling
# the expert's output by its probability. And the text says the centralised critic "remains
# dense", while a figure caption mentions a critic MoE encoder. Three choices are therefore ours,
# and `NetConfig` makes each explicit:
#
# * `top1_weight`: `straight_through` (value 1, gradient of the kept probability), `switch` (the
#   kept probability as the weight), or `paper` (value 1, no gradient: only the balance loss moves
#   the router);
# * `routing_noise`: `learned` (a softplus noise gate per expert, trained with everything else),
#   `fixed` (a constant $\sigma$), `annealed` ($\sigma$ falling linearly to 0), or `off`. With
#   fixed or annealed noise the draws are stored already multiplied by $\sigma$, so the PPO update
#   replays them without knowing the schedule;
# * `critic_gating` for a gated actor: `dense` (the dense mixture of the MoE critic, with its own
#   value router), `gated` (the actor's top-1 gating), or `mlp`.
#
# **What went wrong with the first reading.** Up to numerics version 1 the code used learned
# noise, the straight-through weight and a gated critic. The straight-through term also hands
# the noise gate a gradient, and nothing in the loss bounds it: in fixed-phase runs the noise scale
# grew from softplus(0) = 0.69 to about 3, while the router's logits start near 0.005 (gain 0.01).
# The noise then overrode the router's own choice on 56-61 % of the rollout's rows, and an agent's
# selected expert changed between consecutive steps 64-66 % of the time, where uniformly random
# routing over three experts gives 67 %. Each expert trained on a near-random third of the data,
# and top-1 SMoE levelled off well below MLP although one expert is about MLP's size.
#
# **What we measured.** Appendix 05c trains twelve readings side by side (fixed phases 0 and 1, 700k
# environment steps, 2 seeds, MLP beside them) and logs the routing that ran. Its table
# (`paper_figures/gating_readings.md`, from the runs' records: coverage over the last 100k steps, seed mean, phase 0 /
# phase 1; the commit is in `paper_figures/README.md`) says:
#
# * MLP 0.645 / 0.391; the version-1 reading (`st/learned/gated`) 0.566 / 0.369.
# * Turning the noise off is the largest single gain (`st/off/gated`: 0.600 / 0.402, switch rate
#   about 0.2 instead of 0.64-0.66). Annealed noise ends where `off` starts and is no better
#   (0.595 / 0.398); fixed noise learns less than none (σ = 0.3: 0.594 / 0.357; σ = 1:
#   0.587 / 0.361), because the router's logits stay small and even σ = 0.3 overrides a quarter
#   of its choices.
# * The Switch weight is no better than the straight-through one (noise off, dense critic:
#   0.639 / 0.361 against 0.640 / 0.371), and the paper's literal weight, which leaves the router to
#   the balance loss, learns least of the noiseless readings (0.566 / 0.355): the router needs the
#   task's gradient.
# * A dense critic helps in phase 0 and costs in phase 1 (noise off: 0.600 → 0.640 and
#   0.402 → 0.371). Over the two phases the two critics are within 0.005 of each other, which two
#   seeds cannot separate.
# * Evaluated with the router's own choice instead of the noise it trained with, the version-1
#   SMoE loses most of its return in phase 0 (601 → −61; `paper_figures/gating_evaluation.md`):
#   it had come to rely on random routing. The noiseless readings are the same either way.
#
# **What we chose.** `straight_through`, `off`, `dense`. It closes 94 % of the phase-0 gap to MLP
# at 700k steps, where the gated critic closes 42 %; in phase 1 it only matches the version-1
# reading (0.371 against 0.369) while the gated critic beats MLP there (0.402 against 0.391). With
# the two critics tied over both phases, the paper's text ("the centralised critic remains dense")
# decides. Without noise the noise scale cannot grow. One consequence matters for PE-MAMoE:
# without routing noise, dividing the logits by a temperature cannot change which expert is
# largest, so the controller's temperature schedule no longer moves any routing decision (it still
# scales the straight-through gradient); the one reading that would keep it meaningful, bounded
# fixed noise, measurably learns less. The readings are all available:
# `NetConfig(routing_noise="learned", critic_gating="gated")` is version 1's network, and the
# paper's parameter counts (which include a noise gate) are reproduced with `PAPER_NET`, the
# learned-noise reading.

# %% [markdown]
# ## The actors
#
# All four actors share one interface, so the trainer never asks which kind it holds:
#
# * `dist, routing = actor(obs, temperature=1.0, routing=None, deterministic_gate=False)` returns
#   an `Independent(Normal)` over the action (its `log_prob` and `entropy` sum the action
#   coordinates) and the `RoutingSample` of the pass (`None` for the MLP);
# * `action, log_prob, routing = actor.act(obs, deterministic=False)` is the rollout step, run
#   without gradient. `deterministic=True` is evaluation mode: noiseless gating and the mean
#   action;
# * `log_prob, entropy, aux = actor.evaluate(obs, action, routing)` is the PPO update's call;
#   `aux` holds `load_balance`, `aux_loss` (= `load_balance_coef` × `load_balance`, zero for the
#   MLP), `router_probs`, `experts` and `gate_weights`;
# * `actor.probe(obs)` returns per-expert, per-layer pre-activations and activations, the
#   noiseless router probabilities and the selected experts, for the diagnostics;
# * `actor.param_groups()` splits the parameters into `router` (router and noise gate),
#   `experts`, `head` and `log_std`, the groups the phase controller schedules separately. The
#   MLP's trunk is filed under `experts`: it plays the role of a single expert, so the
#   diagnostics treat all four actors alike.
#
# Observations may carry any leading axes `(..., obs_dim)`; routing tensors follow them.
#
# **Exact PPO ratios under random routing.** A noisy router makes the policy itself random: the
# same observation may go to a different expert on a second pass. If the update re-drew the gate
# noise, the ratio $\pi_\theta(a|o)/\pi_{\text{old}}(a|o)$ would differ from 1 before any
# learning, just from a different expert being picked. So `act` returns the noise and the chosen
# experts, the buffer stores them, and `evaluate(..., routing=stored)` replays them: the policy
# being optimised is the one conditioned on those routing draws. On the same batch, the replayed
# log-probabilities are bit-identical to the rollout's (checked below). Re-evaluated in different
# minibatch groupings they can differ by float rounding (~1e-7), as for any network.

# %%
#| exporti
def _flatten_routing(routing, batch):
    return None if routing is None else routing.reshape(batch)


def _linear_macs(layer: nn.Linear) -> int:
    return layer.in_features * layer.out_features


def _count(module) -> int:
    return 0 if module is None else sum(p.numel() for p in module.parameters())


# %%
#| export
class GaussianActor(nn.Module):
    """Base class: feature extractor + shared linear mean head + state-independent log-std."""

    kind = "base"

    def __init__(self, obs_dim: int, act_dim: int, cfg: NetConfig):
        super().__init__()
        self.obs_dim, self.act_dim, self.cfg = obs_dim, act_dim, cfg
        self.head = nn.Linear(cfg.hidden, act_dim)
        nn.init.orthogonal_(self.head.weight, cfg.gain_policy)
        nn.init.zeros_(self.head.bias)
        self.log_std = nn.Parameter(torch.full((act_dim,), float(cfg.init_log_std)))

    # subclasses: features(x (B, obs_dim), temperature, routing, deterministic_gate, with_aux)
    #   -> ((B, hidden) features, GateOutput | None)
    def features(self, x, temperature=None, routing=None, deterministic_gate=False, with_aux=True):
        raise NotImplementedError

    # The run axis (appendix 05b): the same features for R members at
    # once, from parameter views p {name: (R, *shape)} and x (R, n, obs_dim) -> ((R, n, hidden),
    # (probs, experts, weights) or None). tau (R, n), noise (R, n, E) and experts (R, n, k)
    # are the routing inputs of gated kinds (ignored by ungated ones).
    def run_features(self, p, x, tau=None, noise=None, experts=None):
        raise NotImplementedError

    def trunk_parameters(self) -> list:
        """[(parameter name, expert index or None)]: the trunk ("expert") parameters that the
        plasticity methods perturb; index e selects slice e of a stacked (E, ...) parameter."""
        raise NotImplementedError

    @torch.no_grad()
    def probe(self, obs, temperature=None) -> dict:
        """Pre-activations, activations, routing, features and mean on probe rows (diagnostics)."""
        raise NotImplementedError

    def _forward(self, obs, temperature=None, routing=None, deterministic_gate=False, with_aux=False):
        lead = obs.shape[:-1]
        x = obs.reshape(-1, self.obs_dim)
        routing = _flatten_routing(routing, x.shape[0])
        feat, gate = self.features(x, temperature, routing, deterministic_gate, with_aux)
        mean = self.head(feat).reshape(*lead, self.act_dim)
        # validate_args=False: the argument checks cost more than the network at batch 1
        dist = Independent(Normal(mean, self.log_std.exp().expand_as(mean), validate_args=False), 1, validate_args=False)
        return dist, gate, lead

    def forward(self, obs, temperature=None, routing: RoutingSample | None = None, deterministic_gate: bool = False):
        """obs (..., obs_dim) -> (Independent Normal over (..., act_dim), RoutingSample | None)."""
        dist, gate, lead = self._forward(obs, temperature, routing, deterministic_gate)
        return dist, (None if gate is None else gate.routing.reshape(*lead))

    @torch.no_grad()
    def act(self, obs, temperature=None, deterministic: bool = False):
        """Rollout step without gradient -> (action, log_prob, routing).

        deterministic=True: noiseless gating and the mean action (evaluation mode).
        """
        dist, routing = self(obs, temperature, None, deterministic_gate=deterministic)
        action = dist.mean if deterministic else dist.sample()
        return action, dist.log_prob(action), routing

    def evaluate(self, obs, action, routing: RoutingSample | None = None, temperature=None):
        """PPO update: (log_prob (...,), entropy (...,), aux dict) with the stored routing replayed."""
        dist, gate, lead = self._forward(obs, temperature, routing, deterministic_gate=False, with_aux=True)
        if gate is None:
            zero = self.log_std.new_zeros(())
            aux = {"load_balance": zero, "aux_loss": zero, "router_probs": None, "experts": None, "gate_weights": None}
        else:
            aux = {
                "load_balance": gate.load_balance,
                "aux_loss": self.cfg.load_balance_coef * gate.load_balance,
                "router_probs": gate.probs.reshape(*lead, -1),
                "experts": gate.experts.reshape(*lead, -1),
                "gate_weights": gate.weights.reshape(*lead, -1),
            }
        return dist.log_prob(action), dist.entropy(), aux

    def param_groups(self) -> dict:
        """{"router": [...], "experts": [...], "head": [...], "log_std": [...]}: every parameter once."""
        raise NotImplementedError

    def cost_parts(self) -> dict:
        """{part: (params, macs)} for router, noise_gate, one_expert, head, log_std (from the modules)."""
        raise NotImplementedError


class MLPActor(GaussianActor):
    """obs -> hidden -> hidden (ReLU) -> mean head; the trunk counts as one expert."""

    kind = "mlp"

    def __init__(self, obs_dim: int, act_dim: int, cfg: NetConfig):
        super().__init__(obs_dim, act_dim, cfg)
        self.fc1 = nn.Linear(obs_dim, cfg.hidden)
        self.fc2 = nn.Linear(cfg.hidden, cfg.hidden)
        for layer in (self.fc1, self.fc2):
            nn.init.orthogonal_(layer.weight, cfg.gain_hidden)
            nn.init.zeros_(layer.bias)

    def features(self, x, temperature=None, routing=None, deterministic_gate=False, with_aux=True):
        return F.relu(self.fc2(F.relu(self.fc1(x)))), None

    def run_features(self, p, x, tau=None, noise=None, experts=None):
        h = F.relu(run_linear(x, p["fc1.weight"], p["fc1.bias"]))
        return F.relu(run_linear(h, p["fc2.weight"], p["fc2.bias"])), None

    def trunk_parameters(self) -> list:
        return [(name, None) for name in ("fc1.weight", "fc1.bias", "fc2.weight", "fc2.bias")]

    @torch.no_grad()
    def probe(self, obs, temperature=None) -> dict:
        x = obs.reshape(-1, self.obs_dim)
        p1 = self.fc1(x)
        a1 = F.relu(p1)
        p2 = self.fc2(a1)
        a2 = F.relu(p2)
        return {
            "preact": [p1.unsqueeze(0), p2.unsqueeze(0)],
            "act": [a1.unsqueeze(0), a2.unsqueeze(0)],
            "router_probs": None,
            "selected": None,
            "features": a2,
            "mean": self.head(a2),
        }

    def param_groups(self) -> dict:
        return {
            "router": [],
            "experts": [*self.fc1.parameters(), *self.fc2.parameters()],
            "head": list(self.head.parameters()),
            "log_std": [self.log_std],
        }

    def cost_parts(self) -> dict:
        return {
            "router": (0, 0),
            "noise_gate": (0, 0),
            "one_expert": (_count(self.fc1) + _count(self.fc2), _linear_macs(self.fc1) + _linear_macs(self.fc2)),
            "head": (_count(self.head), _linear_macs(self.head)),
            "log_std": (self.log_std.numel(), 0),
        }


class MoEActor(GaussianActor):
    """Dense mixture: softmax router over E expert trunks, one shared head (the MoE baseline)."""

    kind = "moe"
    sparse = False

    def __init__(self, obs_dim: int, act_dim: int, cfg: NetConfig):
        super().__init__(obs_dim, act_dim, cfg)
        self.gate = GatedExperts(obs_dim, cfg, sparse=self.sparse)

    def features(self, x, temperature=None, routing=None, deterministic_gate=False, with_aux=True):
        out = self.gate(x, temperature, routing, deterministic_gate, with_aux)
        return out.features, out

    def run_features(self, p, x, tau=None, noise=None, experts=None):
        return run_gate(p, "gate.", x, tau, noise, experts, self.gate)

    def trunk_parameters(self) -> list:
        return [(f"gate.experts.{n}", e) for e in range(self.gate.n_experts) for n in ("w1", "b1", "w2", "b2")]

    @torch.no_grad()
    def probe(self, obs, temperature=None) -> dict:
        """Every expert on every probe row (E, B, hidden) per layer, plus noiseless routing."""
        x = obs.reshape(-1, self.obs_dim)
        out = self.gate(x, temperature, None, deterministic_gate=True, with_aux=False)
        _, pre, act = self.gate.experts.all_experts(x, return_layers=True)
        return {
            "preact": pre,
            "act": act,
            "router_probs": out.probs,
            "selected": out.experts,
            "features": out.features,
            "mean": self.head(out.features),
        }

    def param_groups(self) -> dict:
        return {
            "router": [p for m in self.gate.gating_modules() for p in m.parameters()],
            "experts": list(self.gate.experts.parameters()),
            "head": list(self.head.parameters()),
            "log_std": [self.log_std],
        }

    def cost_parts(self) -> dict:
        bank = self.gate.experts
        ng = self.gate.noise_gate
        return {
            "router": (_count(self.gate.router), _linear_macs(self.gate.router)),
            "noise_gate": (_count(ng), 0 if ng is None else _linear_macs(ng)),
            "one_expert": (bank.params_per_expert(), bank.macs_per_expert()),
            "head": (_count(self.head), _linear_macs(self.head)),
            "log_std": (self.log_std.numel(), 0),
        }


class SMoEActor(MoEActor):
    """Sparse mixture: noisy top-k gating (k = 1 by default), only the selected experts matter."""

    kind = "smoe"
    sparse = True


# %% [markdown]
# ## The critics
#
# The critic reads the global state and returns one scalar per sample: an MLP state→32→32→1,
# or an expert bank with a value head 32→1 and its **own** router (the paper plots the value
# router's probabilities next to the policy router's). Which one trains beside a gated actor is
# `critic_gating`: `gated` gives the critic the actor's own gating (top-1 for SMoE), `dense` the
# dense softmax mixture of the MoE critic (the paper says the centralised critic "remains dense",
# and still shows a value router), `mlp` the MLP critic. The MLP and MoE methods keep their own
# critics under every setting. `value, aux = critic(state, temperature=None, deterministic_gate=False)`;
# `aux` carries `router_probs`, `experts`, `load_balance` and `aux_loss`. The trainer chooses
# whether the critic's gate is noisy: we suggest noiseless (`deterministic_gate=True`) when
# computing the values that enter GAE, and the default noisy gate in the value-loss update.

# %%
#| export
class MLPCritic(nn.Module):
    kind = "mlp"

    def __init__(self, state_dim: int, cfg: NetConfig):
        super().__init__()
        self.state_dim, self.cfg = state_dim, cfg
        self.fc1 = nn.Linear(state_dim, cfg.hidden)
        self.fc2 = nn.Linear(cfg.hidden, cfg.hidden)
        self.head = nn.Linear(cfg.hidden, 1)
        for layer, gain in ((self.fc1, cfg.gain_hidden), (self.fc2, cfg.gain_hidden), (self.head, cfg.gain_value)):
            nn.init.orthogonal_(layer.weight, gain)
            nn.init.zeros_(layer.bias)

    def forward(self, state, temperature=None, routing=None, deterministic_gate: bool = False):
        """state (..., state_dim) -> (value (...,), aux)."""
        lead = state.shape[:-1]
        x = state.reshape(-1, self.state_dim)
        value = self.head(F.relu(self.fc2(F.relu(self.fc1(x))))).reshape(lead)
        zero = value.new_zeros(())
        return value, {"load_balance": zero, "aux_loss": zero, "router_probs": None, "experts": None}

    def run_features(self, p, x, tau=None, noise=None, experts=None):
        h = F.relu(run_linear(x, p["fc1.weight"], p["fc1.bias"]))
        return F.relu(run_linear(h, p["fc2.weight"], p["fc2.bias"])), None

    def param_groups(self) -> dict:
        return {"critic": list(self.parameters())}


class MoECritic(nn.Module):
    kind = "moe"
    sparse = False

    def __init__(self, state_dim: int, cfg: NetConfig):
        super().__init__()
        self.state_dim, self.cfg = state_dim, cfg
        self.gate = GatedExperts(state_dim, cfg, sparse=self.sparse)
        self.head = nn.Linear(cfg.hidden, 1)
        nn.init.orthogonal_(self.head.weight, cfg.gain_value)
        nn.init.zeros_(self.head.bias)

    def forward(self, state, temperature=None, routing=None, deterministic_gate: bool = False):
        """state (..., state_dim) -> (value (...,), aux with the value router's probabilities)."""
        lead = state.shape[:-1]
        x = state.reshape(-1, self.state_dim)
        out = self.gate(x, temperature, _flatten_routing(routing, x.shape[0]), deterministic_gate)
        value = self.head(out.features).reshape(lead)
        aux = {
            "load_balance": out.load_balance,
            "aux_loss": self.cfg.load_balance_coef * out.load_balance,
            "router_probs": out.probs.reshape(*lead, -1),
            "experts": out.experts.reshape(*lead, -1),
            "routing": out.routing.reshape(*lead),
        }
        return value, aux

    def run_features(self, p, x, tau=None, noise=None, experts=None):
        return run_gate(p, "gate.", x, tau, noise, experts, self.gate)

    def param_groups(self) -> dict:
        return {"critic": list(self.parameters())}


class SMoECritic(MoECritic):
    kind = "smoe"
    sparse = True


# %% [markdown]
# ## Many networks at once
#
# The trainer of notebook 07 trains R independent runs of one kind in one process, their
# parameters stacked on a leading run axis. Each class above therefore has a `run_features`
# method besides `features`: the same features for all R members at once, from per-member
# parameter views, built from batched matrix products (`run_linear`, `run_gate`). Appendix 05b
# explains the run axis (`ParamLayout`, `PopulationActor`, `PopulationCritic`) and checks that a
# member's numbers do not depend on its neighbours.

# %% [markdown]
# ## Factories and cost accounting
#
# `make_actor` and `make_critic` build a network by kind. The cost functions read every number
# off the modules' own shapes, never from a typed constant:
#
# * `count_parameters(module)`: trainable parameters;
# * `active_parameters(actor, mode)`: parameters that take part in one agent step.
#   `mode="paper"` reproduces the paper's table (dense actors: everything; sparse actors: router,
#   noise gate and the k selected trunks, **without** the head and log-std); `"sampling"` counts
#   everything that executes when an action is sampled; `"eval"` what executes in deterministic
#   evaluation, where the noise gate is skipped;
# * `macs_per_step(actor, mode)`: multiply-accumulates of the linear layers for one agent step
#   (`"sampling"` or `"eval"`); elementwise work (ReLU, softmax, bias adds) is left out.
#
# The latency measurements and `cost_table`, which puts the counts and the timings together, are
# in appendix 05b (module `pemamoe.netcost`).

# %%
#| export
NETWORKS: dict = {}  # network kind -> (actor class, critic class)


def register_network(kind: str, actor_cls, critic_cls) -> None:
    """Make a network kind available to make_actor / make_critic (and so to the method registry).
    The actor subclasses GaussianActor (features, run_features, trunk_parameters, probe,
    param_groups, cost_parts); the critic provides forward, run_features and param_groups."""
    if not isinstance(kind, str) or not kind:
        raise ValueError(f"network kind must be a non-empty string, got {kind!r}")
    NETWORKS[kind] = (actor_cls, critic_cls)


register_network("mlp", MLPActor, MLPCritic)
register_network("moe", MoEActor, MoECritic)
register_network("smoe", SMoEActor, SMoECritic)


def network_kind(name: str) -> str:
    """A network kind, or a method name resolved through the method registry."""
    if name not in NETWORKS and name not in METHOD_REGISTRY:
        load_plugins()
    if name in NETWORKS:
        return name
    if name in METHOD_REGISTRY:
        return METHOD_REGISTRY[name].network
    raise ValueError(f"network kind must be one of {', '.join(NETWORKS)} (or a method: {', '.join(METHOD_REGISTRY)}), "
                     f"got {name!r}")


def _check_dim(name, value):
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
        raise ValueError(f"{name} must be an int >= 1, got {value!r}")


def make_actor(kind: str, obs_dim: int, act_dim: int = 2, cfg: NetConfig | None = None) -> GaussianActor:
    """Actor of network `kind` (or of a method's network) for observations (..., obs_dim) and actions (..., act_dim)."""
    kind = network_kind(kind)
    _check_dim("obs_dim", obs_dim)
    _check_dim("act_dim", act_dim)
    return NETWORKS[kind][0](obs_dim, act_dim, cfg or NetConfig())


def critic_kind(kind: str, cfg: NetConfig | None = None) -> str:
    """The network kind of the critic that trains beside an actor of `kind`: its own kind when
    cfg.critic_gating is "gated" (or the kind's critic is not sparse), the dense mixture "moe" for
    a sparse critic under "dense" (the paper: the critic "remains dense"), "mlp" under "mlp"."""
    kind = network_kind(kind)
    gating = (cfg or NetConfig()).critic_gating
    if gating == "mlp":
        return "mlp"
    if gating == "dense" and getattr(NETWORKS[kind][1], "sparse", False):
        return "moe"
    return kind


def make_critic(kind: str, state_dim: int, cfg: NetConfig | None = None) -> nn.Module:
    """Centralised critic for global states (..., state_dim) beside an actor of network `kind`
    (or of a method's network); cfg.critic_gating picks its kind (`critic_kind`)."""
    _check_dim("state_dim", state_dim)
    return NETWORKS[critic_kind(kind, cfg)][1](state_dim, cfg or NetConfig())


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def _executed(actor: GaussianActor, mode: str) -> dict:
    # How many copies of each part run in one agent step under `mode`.
    sparse = getattr(actor, "sparse", None)
    if sparse is None:  # MLP
        return {"router": 0, "noise_gate": 0, "one_expert": 1, "head": 1, "log_std": 1}
    gate = actor.gate
    experts = gate.k if sparse else gate.n_experts
    learned = gate.noise == "learned"  # only learned noise runs a noise gate
    noise = 0 if (mode == "eval" or not learned) else 1
    if mode == "paper":
        noise = 1 if learned else 0
    head = 0 if (mode == "paper" and sparse) else 1
    return {"router": 1, "noise_gate": noise, "one_expert": experts, "head": head, "log_std": head}


def active_parameters(actor: GaussianActor, mode: str = "paper") -> int:
    """Parameters taking part in one agent step; mode in ACTIVE_MODES (see notebook 05)."""
    if mode not in ACTIVE_MODES:
        raise ValueError(f"active_parameters mode must be one of {', '.join(ACTIVE_MODES)}, got {mode!r}")
    parts, used = actor.cost_parts(), _executed(actor, mode)
    return sum(parts[name][0] * n for name, n in used.items())


def macs_per_step(actor: GaussianActor, mode: str = "sampling") -> int:
    """Multiply-accumulates of the linear layers for one agent step; mode in MAC_MODES."""
    if mode not in MAC_MODES:
        raise ValueError(f"macs_per_step mode must be one of {', '.join(MAC_MODES)}, got {mode!r}")
    parts, used = actor.cost_parts(), _executed(actor, mode)
    return sum(parts[name][1] * n for name, n in used.items())


# %% [markdown]
# ## Demonstration
#
# ### Our observation dimension
#
# The environment notebook defines the observation layout (04_environment); we ask it for the
# dimension, so the cost table follows any change to the layout or to the number of users.

# %%
import matplotlib.pyplot as plt
import pandas as pd

from pemamoe.core import by_scale, save_figure, write_table

torch.manual_seed(seed)
if our_obs_dim is None:
    from pemamoe.env import EnvConfig, observation_dim

    our_obs_dim = int(observation_dim(EnvConfig()))
print(f"paper obs_dim = {PAPER_OBS_DIM}, our obs_dim = {our_obs_dim}")

# %% [markdown]
# ### The four architectures
#
# The diagram is drawn from the modules themselves: box labels carry the layer shapes and
# parameter counts of freshly built actors at the paper's observation dimension.

# %%
cfg = PAPER_NET  # the paper's reading: learned routing noise, whose noise gate its counts include
paper_actors = {name: make_actor(spec.network, PAPER_OBS_DIM, 2, cfg) for name, spec in METHOD_REGISTRY.items()
                if spec.compared}


def _box(ax, x, y, w, h, text, color, fontsize=7.5, style="round,pad=0.02"):
    from matplotlib.patches import FancyBboxPatch

    ax.add_patch(FancyBboxPatch((x - w / 2, y - h / 2), w, h, boxstyle=style, fc=color, ec="0.25", lw=0.8))
    ax.text(x, y, text, ha="center", va="center", fontsize=fontsize)


def _arrow(ax, x0, y0, x1, y1, dashed=False, color="0.2"):
    ax.annotate(
        "", xy=(x1, y1), xytext=(x0, y0),
        arrowprops=dict(arrowstyle="-|>", lw=0.8, color=color, ls="--" if dashed else "-", shrinkA=1, shrinkB=1),
    )


def draw_actor(ax, actor, method):
    spec = METHOD_REGISTRY[method]
    parts = actor.cost_parts()
    d, h = actor.obs_dim, actor.cfg.hidden
    ax.set_xlim(0, 11.2), ax.set_ylim(0.2, 10), ax.axis("off")
    title = f"{spec.label} ({actor.kind} network)"
    ax.set_title(f"{title}\n{count_parameters(actor):,} params, {active_parameters(actor):,} active (paper conv.)", fontsize=9)
    _box(ax, 5, 9.4, 3.6, 0.7, f"observation $o$ ({d})", "#eeeeee")
    head_y, out_y = 2.4, 0.9
    if actor.kind == "mlp":
        _box(ax, 5, 6.0, 4.0, 3.2, f"trunk\n{d}→{h}→{h}, ReLU\n{parts['one_expert'][0]:,} params", "#cfe2f3")
        _arrow(ax, 5, 9.05, 5, 7.6)
        _arrow(ax, 5, 4.4, 5, head_y + 0.4)
    else:
        e = actor.gate.n_experts
        xs = [2.2 + i * 2.8 for i in range(e)]
        sparse = actor.gate.sparse
        for i, x in enumerate(xs):
            chosen = (not sparse) or i == 1
            color = "#cfe2f3" if chosen else "#f3f3f3"
            _box(ax, x, 5.6, 2.4, 1.6, f"expert {i + 1}\n{d}→{h}→{h}\n{parts['one_expert'][0]:,}", color, fontsize=7)
            _arrow(ax, 5, 9.05, x, 6.4, dashed=not chosen)
            _arrow(ax, x, 4.8, 5, 4.05, dashed=not chosen)
        lines = [f"router {d}→{e} ({parts['router'][0]})"]
        if actor.gate.noise == "learned":
            lines += [f"noise gate {d}→{e} ({parts['noise_gate'][0]})", "z/τ + ε·softplus(z$_n$)", "softmax, keep top-1"]
        elif actor.gate.noisy:
            lines += [f"z/τ + σε ({actor.gate.noise} σ)", "softmax, keep top-1"]
        elif sparse:
            lines += ["softmax(z/τ)", "keep top-1"]
        else:
            lines += ["softmax(z/τ)", "mix all experts"]
        _box(ax, 9.5, 8.2, 3.1, 1.7, "\n".join(lines), "#fce5cd", fontsize=6.5)
        _arrow(ax, 6.8, 9.4, 7.95, 9.0)
        _box(ax, 5, 3.7, 3.6, 0.7, "Σ$_j$ w$_j$ · features$_j$", "#d9ead3", fontsize=7.5)
        ax.plot([10.6, 10.6], [7.35, 3.7], color="#b45f06", lw=0.8)
        _arrow(ax, 10.6, 3.7, 6.8, 3.7, color="#b45f06")
        ax.text(10.5, 4.9, "gate\nweights", ha="right", va="center", fontsize=6, color="#b45f06")
        _arrow(ax, 5, 3.35, 5, head_y + 0.4)
        if spec.plasticity != "none":
            _box(ax, 9.3, 1.5, 3.1, 1.3, "phase controller\n(0 params): τ, log σ,\nexpert noise, LR, KL", "#ead1dc", fontsize=6)
            ax.plot([9.3, 9.3], [2.15, 7.35], color="#741b47", lw=0.8, ls="--")
            _arrow(ax, 7.75, 1.7, 6.85, head_y, dashed=True, color="#741b47")
    _box(ax, 5, head_y, 3.7, 0.8, f"shared head {h}→2 ({parts['head'][0]})\n+ log σ ({parts['log_std'][0]})", "#d9d2e9", fontsize=7)
    _arrow(ax, 5, head_y - 0.4, 5, out_y + 0.35)
    _box(ax, 5, out_y, 3.4, 0.7, "a ~ N(μ, diag σ²)", "#eeeeee")


fig, axes = plt.subplots(1, len(paper_actors), figsize=(4.5 * len(paper_actors), 5.6))
for ax, (method, actor) in zip(axes, paper_actors.items()):
    draw_actor(ax, actor, method)
fig.suptitle(f"Actor architectures at obs_dim {PAPER_OBS_DIM}, hidden {cfg.hidden}, {cfg.n_experts} experts "
             "(solid: executed for a sample routed to expert 2)", fontsize=10)
fig.tight_layout()
save_figure(fig, "architecture_actors", figures_dir)
plt.show()

# %% [markdown]
# ### The paper's four numbers, reproduced

# %%
print(f"{'actor':<9} {'paper params':>12} {'ours':>7} {'paper active':>13} {'ours':>7} {'sampling':>9} {'eval':>6}")
for kind, actor in paper_actors.items():
    print(
        f"{kind:<9} {PAPER_ACTOR_PARAMS[kind]:>12,} {count_parameters(actor):>7,} "
        f"{PAPER_ACTIVE_PARAMS[kind]:>13,} {active_parameters(actor, 'paper'):>7,} "
        f"{active_parameters(actor, 'sampling'):>9,} {active_parameters(actor, 'eval'):>6,}"
    )
    assert count_parameters(actor) == PAPER_ACTOR_PARAMS[kind]
    assert active_parameters(actor, "paper") == PAPER_ACTIVE_PARAMS[kind]
ratio = macs_per_step(paper_actors["smoe"]) / macs_per_step(paper_actors["mlp"])
print(f"SMoE / MLP multiply-accumulates per step (sampling): {ratio:.3f} (paper: about 1.16)")

# %% [markdown]
# ### Routing consistency: every PPO ratio is exactly 1 before the first update
#
# We sample a rollout batch with noisy gating, then re-evaluate the same samples with the stored
# routing, as the PPO update does. The largest |log-ratio| must be exactly zero. Re-drawing the
# noise instead (no stored routing) shows how far the ratios would drift otherwise.

# %%
n_check = by_scale(scale, ci=256, small=2048, paper=2048)
obs = torch.randn(n_check, PAPER_OBS_DIM)
for kind, actor in paper_actors.items():
    action, logp_old, routing = actor.act(obs, temperature=1.5)
    with torch.no_grad():
        logp_new, _, _ = actor.evaluate(obs, action, routing)
        logp_redraw, _, _ = actor.evaluate(obs, action, None, temperature=1.5)
    exact = (logp_new - logp_old).abs().max().item()
    redraw = (logp_redraw - logp_old).abs().max().item()
    print(f"{kind:<8} max|log ratio| replayed = {exact:.1e}   re-drawn noise = {redraw:.2e}")
    assert exact == 0.0

# %% [markdown]
# ### Load balance and the router's gradient under top-1

# %%
E = cfg.n_experts
uniform = load_balance_loss(torch.full((6, E), 1 / E), torch.arange(6).remainder(E).unsqueeze(-1), E)
collapsed = load_balance_loss(F.one_hot(torch.zeros(6, dtype=torch.long), E).float(), torch.zeros(6, 1, dtype=torch.long), E)
print(f"load balance, uniform routing: {uniform.item():.3f}; everything on expert 1: {collapsed.item():.3f}")

actor = paper_actors["smoe"]
actor.zero_grad(set_to_none=True)
action, _, routing = actor.act(obs)
logp, _, aux = actor.evaluate(obs, action + 0.1, routing)
(-logp.mean()).backward()  # policy loss only, no balance term
g = actor.gate.router.weight.grad
print(f"top-1 gate weights all exactly 1: {bool((aux['gate_weights'] == 1).all())}; "
      f"router grad norm from the policy loss alone = {g.norm():.3e}; "
      f"noise-gate grad norm = {actor.gate.noise_gate.weight.grad.norm():.3e}")
assert torch.isfinite(g).all() and g.abs().sum() > 0
actor.zero_grad(set_to_none=True)

# %% [markdown]
# ### Evaluation mode and the temperature
#
# Evaluation mode (`deterministic=True`) turns the gate noise off and returns the mean action, so
# two calls agree exactly. The plot shows what the phase controller's temperature does to the
# sparse router: with our placement of $\tau$, a hotter router hands more decisions to the noise
# and the expert usage spreads out. (With $\tau$ applied after the noise, the usage would not move
# at all.) Here the router is given a preference for expert 1 through its bias.

# %%
a1, _, _ = actor.act(obs, deterministic=True)
a2, _, _ = actor.act(obs, deterministic=True)
print("deterministic evaluation repeatable:", torch.equal(a1, a2))

demo = make_actor("smoe", PAPER_OBS_DIM, 2, cfg)
with torch.no_grad():
    demo.gate.router.bias.copy_(torch.tensor([2.0, 0.0, 0.0]))
taus = [0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0]
usage = []
for tau in taus:
    _, _, r = demo.act(obs, temperature=tau)
    usage.append(torch.bincount(r.experts.reshape(-1), minlength=E).float() / r.experts.numel())
usage = torch.stack(usage)
fig, ax = plt.subplots(figsize=(5.5, 3.2))
for j in range(E):
    ax.plot(taus, usage[:, j], marker="o", label=f"expert {j + 1}")
ax.set_xscale("log", base=2)
ax.set_xlabel("router temperature τ")
ax.set_ylabel("fraction of samples routed")
ax.set_title("Noisy top-1 routing spreads as τ rises")
ax.legend(fontsize=8)
fig.tight_layout()
save_figure(fig, "architecture_router_temperature", figures_dir)
plt.show()

# %% [markdown]
# ### The cost table
#
# Counts at the paper's dimension and at ours, shown here with the measured agent-step latency
# (median of repeated `act` calls on one torch thread; the timing code is in appendix 05b).
# Latencies depend on the machine and its load, the counts do not: the file written to
# `paper_figures/` holds the counts only, so that regenerating it over the same code rewrites the
# same bytes, and `make bench` (`benchmarks/bench_nets.py`) prints the latencies.

# %%
from pemamoe.netcost import cost_table

repeats = by_scale(scale, ci=5, small=50, paper=100)
table = cost_table({"paper": PAPER_OBS_DIM, "ours": our_obs_dim}, cfg, repeats=repeats, seed=seed)
write_table(table.drop(columns=[c for c in table.columns if c.startswith("latency_")]), "cost_table", figures_dir)
table

# %% [markdown]
# ### What we found
#
# * The parameter counts pin the architecture to deep expert trunks with one shared head; the
#   paper's per-expert linear mean equations do not match them.
# * The paper's "active" count for the sparse actors omits the head and the log-std (68
#   parameters): 7,820 against 7,888 that actually run when sampling.
# * Under top-1 routing the paper's renormalised weight is constant, so without a
#   straight-through term the router gets no gradient from the policy loss; and a temperature
#   applied to the whole (noisy) logit vector cannot change a top-k decision.
# * On a CPU at these sizes, kernel-call overhead dominates small batches (the batched `stacked`
#   execution wins up to a few hundred rows) while true conditional computation (`masked`) wins
#   on rollout-sized batches (`benchmarks/bench_nets.py` at `469129f`); the default `"auto"`
#   switches at 512 rows. `make bench` reprints
#   the comparison on the current machine.
