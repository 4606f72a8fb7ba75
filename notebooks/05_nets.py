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
# does not depend on the observation. The four actors differ in how they turn the observation
# into the 32-wide feature vector that feeds the final linear "head" (the gated actors give each
# expert its own head and mix the experts' means, the default since appendix 05d; the parameter
# counts below are the paper's, with one shared head):
#
# | kind | feature extractor | gating |
# |---|---|---|
# | `mlp` | one trunk obs→32→32 (ReLU) | none |
# | `moe` | three trunks obs→32→32, mixed by a softmax router | dense: every expert runs |
# | `smoe` | same three trunks | noisy top-k: one expert runs (k = 1) |
# | `pemamoe` | identical to `smoe` | identical; the plasticity tricks live in the phase controller |
#
# Below: the architecture, read off the paper's parameter counts; the gating (temperature, top-k,
# noise, the gradient for k = 1, load balancing) in the one code path that a single network and
# the trainer's population of networks both run; exact PPO ratios under random routing; the four
# architectures drawn, and the cost table. The machinery around them is in four appendices: the
# expert bank's storage and execution strategies and the population as one set of tensors in
# `05b_popnets.py`, the registries in `05e_methods.py`, counts and latency in `05f_netcost.py`,
# the gate's code in `05g_gating.py`.

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

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.distributions import Independent, Normal

from pemamoe.core import require_field
from pemamoe.methods import METHOD_REGISTRY, load_plugins

# The machinery of appendices 05e (the network-kind registry) and 05b (the expert bank, the batched
# building blocks of the forward, the population), used by the classes below and re-exported here:
from pemamoe.methods import (ACTOR_PARAM_GROUPS, CRITIC_PARAM_GROUPS, NETWORKS, check_param_groups,  # re-export
                             network_kind, register_network)
from pemamoe.popnets import (EXPERT_IMPLS, ActorEvaluation, ActorStep, ExpertBank, ParamLayout,  # re-export  # noqa: F401
                             PopulationActor, PopulationCritic, RoutingSample, draw_routing_noise, gaussian_entropy, gaussian_kl, gaussian_log_prob,
                             loop_experts, masked_mixed, routing_noise_std, run_experts, run_linear, run_load_balance,
                             run_noise_scale)
from pemamoe.gating import (ContiguousGrad, GatedExperts, GateOutput, load_balance_loss, run_gate,  # re-export  # noqa: F401
                            single_member_params, topk_weights)

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
# policy head"), describe deep expert trunks followed by one shared head. We keep the deep trunks
# the counts describe, and give each trunk its own mean head as the equations do
# (`expert_heads="per_expert"`, 66 parameters more per extra expert). That was not always the
# default: until the medium sweep was rerun under it (`benchmarks/HISTORY.md`, session 25), one shared head was, and appendix
# 05d measures what the shared head costs a top-1 actor. `PAPER_NET` keeps the shared head, so the
# cost table below reproduces the paper's counts exactly.
#
# **Where the experts are mixed.** With one shared linear head $h(\cdot)$ and mixing weights
# that sum to one, $h(\sum_j w_j f_j) = \sum_j w_j h(f_j)$ (the head's bias is multiplied by
# $\sum_j w_j = 1$): mixing the 32-wide features and applying the head once is the same policy,
# and cheaper. With a head per expert the experts' means are mixed instead. Either way the mixed
# features are what the plasticity diagnostics (rank, dormant units) look at.

# %% [markdown]
# ## Configuration
#
# One frozen dataclass holds every number of the networks:
#
# * `hidden = 32`, `n_experts = 3`, `top_k = 1`: the paper's values (the dense MoE ignores `top_k`).
# * `init_log_std = log(0.3)`: Algorithm 1 resets the log-std "to $\sigma_{\text{init}}$" at a
#   switch, and the training table lists the reset value 0.3. We read that as $\sigma = 0.3$ at
#   initialisation, so a reset puts the policy back to exactly its initial spread.
# * `load_balance_coef = 0`: the weight of a Switch-style balance loss, reported weighted as
#   `aux_loss`. The paper describes no such loss, so it is off; 0.01 (the value Switch Transformers
#   use) was our default until the medium sweep was rerun, and appendix 05d keeps it as an
#   ablation row.
# * Three gating choices the paper leaves open ("Top-1 gating" below): `top1_weight`,
#   `routing_noise` (`learned`, `fixed`, `annealed` or `off`, with `noise_std` and
#   `noise_anneal_portion`) and `critic_gating` (`dense`, `gated` or `mlp`).
# * Two readings of the sparse actor (appendix 05d compares them): `expert_heads` (`per_expert`,
#   the default: each expert its own head and the experts' means mixed, as the equations say;
#   `shared`: one mean head after the mixed trunk, as the parameter counts say) and
#   `update_routing` (`current`, the default: the update routes each row again with the current
#   router and the stored noise, so a change of route moves the PPO ratio and is clipped like any
#   other change of the policy; `replay`: the update reuses the experts chosen in the rollout).
#   With the balance loss off these are the paper's reading of the sparse actor; the balance loss,
#   a shared head and replayed routes are ours, the defaults until that rerun (`BUDGET_READINGS`,
#   notebook 09, names both).
# * `expert_impl = "auto"` and `masked_min_batch = 512`: how a single network executes its expert
#   bank (next section); speed only.
# * Orthogonal initialisation gains (the usual PPO choices): $\sqrt2$ for hidden layers, 0.01 for
#   the policy mean head (actions start near zero), 1.0 for the value head, and 0.01 for the
#   router, so that every expert starts with nearly equal probability. The noise gate starts at
#   zero weights, i.e. a noise scale of softplus(0) ≈ 0.69 for every expert.

# %%
#| export
TOP1_WEIGHTS = ("straight_through", "switch", "paper")
ROUTING_NOISES = ("learned", "fixed", "annealed", "off")
CRITIC_GATINGS = ("dense", "gated", "mlp")
EXPERT_HEADS = ("shared", "per_expert")
UPDATE_ROUTINGS = ("replay", "current")

# The paper's Table "Computational cost" at observation dimension 177 (hidden 32, 3 experts, 2-D
# action), from the method registry: for comparison with the modules' own counts only.
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
    load_balance_coef: float = 0.0  # the paper describes no balance loss (appendix 05d measures one)
    # the gating readings (chosen by the comparison of appendix 05c; see "Top-1 gating" below)
    top1_weight: str = "straight_through"
    routing_noise: str = "off"
    noise_std: float = 1.0  # sigma of "fixed" routing noise; the starting sigma of "annealed"
    noise_anneal_portion: float = 1.0  # "annealed": sigma reaches 0 after this fraction of the run
    critic_gating: str = "dense"
    # the sparse actor's reading: the paper's equations (appendix 05d measures the alternatives)
    expert_heads: str = "per_expert"  # each expert its own mean head, the experts' means mixed; or "shared"
    update_routing: str = "current"  # PPO's update routes each row with the current router; or "replay"
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
        require_field(self, "expert_heads", "choice", EXPERT_HEADS)
        require_field(self, "update_routing", "choice", UPDATE_ROUTINGS)
        require_field(self, "expert_impl", "choice", EXPERT_IMPLS)
        require_field(self, "masked_min_batch", "int", ge=1)
        for name in ("gain_hidden", "gain_policy", "gain_value", "gain_router"):
            require_field(self, name, "real", gt=0)


# The paper's counts include a noise gate (its SMoE has 534 = 3 x (177 + 1) parameters more than its
# MoE): its network had learned routing noise. Its cost table is reproduced with this configuration.
PAPER_NET = NetConfig(routing_noise="learned", expert_heads="shared")


# %% [markdown]
# ## Gating: temperature, noise, top-k, and a gradient for k = 1
#
# Expert $j$ is the ReLU trunk $f_j(x) = \mathrm{relu}(W^{(j)}_2\,\mathrm{relu}(W^{(j)}_1 x +
# b^{(j)}_1) + b^{(j)}_2)$; the $E$ trunks are stored **stacked** (`ExpertBank`, appendix 05b: `w1`
# of shape `(E, obs_dim, hidden)`, `w2` of `(E, hidden, hidden)`, plus biases), the one storage
# that parameter counts, optimiser groups and the controller's noise injection read. The router is
# one linear map from the observation to $E$ logits $z$ (the paper uses the raw observation, no
# embedding). For the sparse actors a second linear map gives a per-expert noise scale
# $\mathrm{softplus}(z^{\text{noise}})$, and while sampling we draw $\varepsilon \sim \mathcal N(0, I)$:
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
# the Switch Transformer's gradient, by adding $g_j - \mathrm{sg}(g_j)$ (sg: stop gradient), zero
# in value with derivative $\partial g_j$: the router learns how much the chosen expert helped.
# For $k \ge 2$ the renormalised weights already carry a gradient and every setting keeps them.
#
# **Load balancing.** With $f_i$ the fraction of routing slots that went to expert $i$ and $P_i$
# the batch-mean of $g_i$, the Switch loss is $E\sum_i f_i P_i$. It equals 1 when routing is
# uniform and reaches $E$ when one expert takes everything with probability 1; only $P$ carries a
# gradient. For the dense MoE, $f_i$ counts the samples whose largest weight is expert $i$.
#
# **One forward, for one network and for many.** The trainer (notebook 07) trains $R$
# independent runs at once, each member's parameters one row of a tensor; the gate is written once
# with that leading run axis (`run_gate`), and a single network is the population of one. The code
# of the gate, `run_gate`, `topk_weights`, the balance loss and `GatedExperts`, is appendix 05g's
# (`pemamoe.gating`), re-exported here.


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
#   kept probability as the weight), or `paper` (value 1, no gradient: the balance loss alone);
# * `routing_noise`: `learned` (a softplus noise gate per expert), `fixed` (a constant $\sigma$),
#   `annealed` ($\sigma$ falling linearly to 0, `routing_noise_std`) or `off`; fixed and annealed
#   draws are stored already times $\sigma$, so the PPO update replays them without the schedule;
# * `critic_gating` for a gated actor: `dense` (the MoE critic's dense mixture, with its own value
#   router), `gated` (the actor's top-1 gating), or `mlp`.
#
# **What we measured, and chose.** Up to numerics version 1 the code used learned noise, the
# straight-through weight and a gated critic. The straight-through term also hands the noise gate
# a gradient that nothing bounds: its scale grew from 0.69 to about 3 against router logits near
# 0.005, overrode the router on 56-61 % of the rows, and each expert trained on a near-random third
# of the data. Appendix 05c trains twelve readings side by side (`paper_figures/gating_readings.md`):
# turning the noise off is the largest single gain, annealed or fixed noise is no better, the
# Switch weight is no better than straight-through, the paper's literal weight is the worst of
# the noiseless readings (the router needs the task's gradient), and the two critics tie over both
# phases. We chose `straight_through`, `off`, `dense` (the paper's text: the critic "remains
# dense"). Without routing noise a temperature cannot change which expert is largest, so
# PE-MAMoE's temperature schedule no longer moves a routing decision (it still scales the
# straight-through gradient). `NetConfig(routing_noise="learned", critic_gating="gated")` is
# version 1's network, and `PAPER_NET` (learned noise) reproduces the paper's parameter counts.

# %% [markdown]
# ## The actors
#
# **The actor the trainer calls** is a population of these networks, `PopulationActor` (appendix
# 05b): R runs' parameters stacked on a leading axis, one network at R = 1. Its two calls return
# named tuples that notebook 07 reads field by field:
#
# * `actor.act(obs, tau, generators) -> ActorStep(action, log_prob, routing)`: the rollout's sample,
#   obs (R, n, obs_dim), without gradient;
# * `actor.evaluate(obs, action, routing) -> ActorEvaluation(log_prob, entropy, load_balance, mean,
#   log_std, experts)`: the PPO update's pass over stored actions, with the stored routing replayed.
#
# Each kind below is written once, as the single network (an `nn.Module` with a batched
# `run_features`, which the population runs); the single network's own interface is what a
# checkpoint holds, what the diagnostics probe and what a PettingZoo policy acts with. All four
# kinds share it, so nothing asks which kind it holds:
#
# * `dist, routing = actor(obs, temperature=1.0, routing=None, deterministic_gate=False)` returns
#   an `Independent(Normal)` over the action (its `log_prob` and `entropy` sum the action
#   coordinates) and the `RoutingSample` of the pass (`None` for the MLP);
# * `action, log_prob, routing = actor.act(obs, deterministic=False)`: the rollout step, without
#   gradient; `deterministic=True` is evaluation mode (noiseless gating, the mean action);
# * `log_prob, entropy, aux = actor.evaluate(obs, action, routing)`: the PPO update's call; `aux`
#   holds `load_balance`, `aux_loss` (`load_balance_coef` × `load_balance`, zero for the MLP),
#   `router_probs`, `experts` and `gate_weights`;
# * `actor.probe(obs)`: the noiseless pass's features, mean and routing, with per-expert,
#   per-layer pre-activations and activations (`probe_layers`), for the diagnostics;
# * `actor.param_groups()`: the groups of `ACTOR_PARAM_GROUPS`, `router` (router and noise gate),
#   `experts` (the MLP's trunk is its one expert), `head` and `log_std`, scheduled separately.
#
# Observations may carry any leading axes `(..., obs_dim)`; routing tensors follow them.
#
# **What a network kind writes**: the batched `run_features` (what the trainer runs; `features`,
# the single network's pass, is it at $R = 1$ unless the kind has a gate), `trunk_parameters`,
# `param_groups`, `cost_parts` (from `linear_cost`) and, optionally, `probe_layers`. `probe` is
# derived from `features`, so the diagnostics always read the network that acts.
#
# **Exact PPO ratios under random routing.** A noisy router makes the policy itself random: if the
# update re-drew the gate noise, the ratio $\pi_\theta(a|o)/\pi_{\text{old}}(a|o)$ would differ
# from 1 before any learning, just from a different expert being picked. So `act` returns the
# noise and the chosen experts, the buffer stores them, and `evaluate(..., routing=stored)`
# replays them: the policy optimised is the one conditioned on those draws. Under
# `update_routing="current"` only the noise is replayed; the experts are chosen again by the
# current router, so before the first gradient step they are the rollout's. On the same batch the
# replayed log-probabilities are bit-identical to the rollout's (checked below); in other
# minibatch groupings they can differ by float rounding (~1e-7), as for any network.

# %%
#| export
def linear_cost(*layers) -> tuple:
    """(parameters, multiply-accumulates per row) of nn.Linear layers, summed; None counts as
    nothing (an absent noise gate). The building block of every kind's `cost_parts`."""
    present = [layer for layer in layers if layer is not None]
    return (sum(p.numel() for layer in present for p in layer.parameters()),
            sum(layer.in_features * layer.out_features for layer in present))


def _flatten_routing(routing, batch):
    return None if routing is None else routing.reshape(batch)


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

    def run_features(self, p, x, tau=None, noise=None, experts=None, saved=None):
        """R members at once: views p {name: (R, *shape)}, x (R, n, obs_dim) -> ((R, n, hidden),
        (probs, experts, weights) or None); tau (R, n), noise (R, n, E), experts (R, n, k): gated kinds.
        `saved`: a dict to keep what the kind's hand-written backward reads (appendix 05h), or None."""
        raise NotImplementedError

    def run_mean(self, p, x, tau=None, noise=None, experts=None, saved=None):
        """R members at once: (policy mean (R, n, act_dim), gate as run_features); the features
        through the shared head, unless a kind gives each expert its own head."""
        if saved is None:  # (a kind from a plugin may not take `saved`: appendix 05h differentiates it by autograd)
            feat, gate = self.run_features(p, x, tau, noise, experts)
        else:
            feat, gate = self.run_features(p, x, tau, noise, experts, saved)
            saved["features"] = feat
        return run_linear(feat, p["head.weight"], p["head.bias"]), gate

    def features(self, x, temperature=None, routing=None, deterministic_gate=False, with_aux=True):
        """x (B, obs_dim) -> ((B, hidden), GateOutput | None): run_features at R = 1 (gated kinds: their gate)."""
        feat, _ = self.run_features(single_member_params(self), x.unsqueeze(0))
        return feat[0], None

    def mean_of(self, x, feat, gate):
        """The policy mean (B, act_dim) of rows x given their features and gate (from `features`)."""
        return self.head(feat)

    def trunk_parameters(self) -> list:
        """[(parameter name, expert index or None)]: the trunk parameters the plasticity methods
        perturb; index e selects slice e of a stacked (E, ...) parameter."""
        raise NotImplementedError

    def probe_layers(self, x, features) -> tuple:
        """([pre-activation], [activation]) per hidden layer, each (E, B, width), for the rank and
        dormant-unit diagnostics; default: the features as the one layer of one expert."""
        return [features.unsqueeze(0)], [features.unsqueeze(0)]

    @torch.no_grad()
    def probe(self, obs, temperature=None) -> dict:
        """The noiseless pass on probe rows: features, mean, routing, and probe_layers (diagnostics)."""
        x = obs.reshape(-1, self.obs_dim)
        feat, gate = self.features(x, temperature, None, deterministic_gate=True, with_aux=False)
        pre, act = self.probe_layers(x, feat)
        return {"preact": pre, "act": act, "router_probs": None if gate is None else gate.probs,
                "selected": None if gate is None else gate.experts, "features": feat, "mean": self.mean_of(x, feat, gate)}

    def _forward(self, obs, temperature=None, routing=None, deterministic_gate=False, with_aux=False):
        lead = obs.shape[:-1]
        x = obs.reshape(-1, self.obs_dim)
        routing = _flatten_routing(routing, x.shape[0])
        feat, gate = self.features(x, temperature, routing, deterministic_gate, with_aux)
        mean = self.mean_of(x, feat, gate).reshape(*lead, self.act_dim)
        # validate_args=False: the argument checks cost more than the network at batch 1
        dist = Independent(Normal(mean, self.log_std.exp().expand_as(mean), validate_args=False), 1, validate_args=False)
        return dist, gate, lead

    def forward(self, obs, temperature=None, routing: RoutingSample | None = None, deterministic_gate: bool = False):
        """obs (..., obs_dim) -> (Independent Normal over (..., act_dim), RoutingSample | None)."""
        dist, gate, lead = self._forward(obs, temperature, routing, deterministic_gate)
        return dist, (None if gate is None else gate.routing.reshape(*lead))

    @torch.no_grad()
    def act(self, obs, temperature=None, deterministic: bool = False):
        """Rollout step without gradient -> (action, log_prob, routing); deterministic=True:
        noiseless gating and the mean action (evaluation mode)."""
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
            aux = {"load_balance": gate.load_balance, "aux_loss": self.cfg.load_balance_coef * gate.load_balance,
                   "router_probs": gate.probs.reshape(*lead, -1), "experts": gate.experts.reshape(*lead, -1),
                   "gate_weights": gate.weights.reshape(*lead, -1)}
        return dist.log_prob(action), dist.entropy(), aux

    def param_groups(self) -> dict:
        """{group: [parameters]} over ACTOR_PARAM_GROUPS (empty groups allowed): every parameter once."""
        raise NotImplementedError

    def cost_parts(self) -> dict:
        """{part: (params, macs)} for router, noise_gate, one_expert, head, log_std (linear_cost of the modules)."""
        raise NotImplementedError


class MLPActor(GaussianActor):
    """obs -> hidden -> hidden (ReLU) -> mean head; the trunk counts as one expert."""

    kind = "mlp"
    hand_written_backward = True  # appendix 05h differentiates it by hand (read from this class only, not subclasses)

    def __init__(self, obs_dim: int, act_dim: int, cfg: NetConfig):
        super().__init__(obs_dim, act_dim, cfg)
        self.fc1 = nn.Linear(obs_dim, cfg.hidden)
        self.fc2 = nn.Linear(cfg.hidden, cfg.hidden)
        for layer in (self.fc1, self.fc2):
            nn.init.orthogonal_(layer.weight, cfg.gain_hidden)
            nn.init.zeros_(layer.bias)

    def run_features(self, p, x, tau=None, noise=None, experts=None, saved=None):
        h = F.relu(run_linear(x, p["fc1.weight"], p["fc1.bias"]))
        out = F.relu(run_linear(h, p["fc2.weight"], p["fc2.bias"]))
        if saved is not None:
            saved.update(x=x, a1=h, a2=out)
        return out, None

    def trunk_parameters(self) -> list:
        return [(name, None) for name in ("fc1.weight", "fc1.bias", "fc2.weight", "fc2.bias")]

    def probe_layers(self, x, features) -> tuple:
        p1 = self.fc1(x)
        a1 = F.relu(p1)
        p2 = self.fc2(a1)
        return [p1.unsqueeze(0), p2.unsqueeze(0)], [a1.unsqueeze(0), F.relu(p2).unsqueeze(0)]

    def param_groups(self) -> dict:
        return {"router": [], "experts": [*self.fc1.parameters(), *self.fc2.parameters()],
                "head": list(self.head.parameters()), "log_std": [self.log_std]}

    def cost_parts(self) -> dict:
        return {"router": (0, 0), "noise_gate": (0, 0), "one_expert": linear_cost(self.fc1, self.fc2),
                "head": linear_cost(self.head), "log_std": (self.log_std.numel(), 0)}


class ExpertHeads(nn.Module):
    """E linear output layers hidden -> out, stacked like the expert bank: weight (E, out, hidden),
    bias (E, out); each initialised as the shared head would be (orthogonal, `gain`; zero bias)."""

    def __init__(self, n_experts: int, hidden: int, out: int, gain: float):
        super().__init__()
        self.in_features, self.out_features = hidden, out  # one expert's head, for linear_cost
        self.weight = nn.Parameter(torch.stack([nn.init.orthogonal_(torch.empty(out, hidden), gain)
                                                for _ in range(n_experts)]))
        self.bias = nn.Parameter(torch.zeros(n_experts, out))

    def forward(self, h):
        """h (E, B, hidden), every expert's features -> (E, B, out), each through its own head."""
        return torch.baddbmm(self.bias.unsqueeze(1), h, self.weight.transpose(1, 2))


class MoEActor(GaussianActor):
    """Dense mixture: softmax router over E expert trunks, one shared head (the MoE baseline), or
    each expert its own head (`expert_heads="per_expert"`)."""

    kind = "moe"
    sparse = False
    hand_written_backward = True  # appendix 05h differentiates it by hand (read from this class only, not subclasses)

    def __init__(self, obs_dim: int, act_dim: int, cfg: NetConfig):
        super().__init__(obs_dim, act_dim, cfg)
        self.gate = GatedExperts(obs_dim, cfg, sparse=self.sparse)
        if cfg.expert_heads == "per_expert":  # built last: the shared reading draws its initial values as before
            self.head = ExpertHeads(cfg.n_experts, cfg.hidden, act_dim, cfg.gain_policy)

    def features(self, x, temperature=None, routing=None, deterministic_gate=False, with_aux=True):
        out = self.gate(x, temperature, routing, deterministic_gate, with_aux)
        return out.features, out

    def run_features(self, p, x, tau=None, noise=None, experts=None, saved=None):
        return run_gate(p, "gate.", x, tau, noise, experts, self.gate, saved=saved)

    def run_mean(self, p, x, tau=None, noise=None, experts=None, saved=None):
        if self.cfg.expert_heads == "shared":
            return super().run_mean(p, x, tau, noise, experts, saved)
        return run_gate(p, "gate.", x, tau, noise, experts, self.gate, heads=(p["head.weight"], p["head.bias"]),
                        saved=saved)

    def mean_of(self, x, feat, gate):
        if self.cfg.expert_heads == "shared":
            return self.head(feat)
        # the experts' own means, mixed under the routing that made `feat` (replayed at R = 1)
        routing = gate.routing
        mean, _ = self.run_mean(single_member_params(self), x.unsqueeze(0), routing.temperature.unsqueeze(0),
                                routing.noise.unsqueeze(0), gate.experts.unsqueeze(0) if self.sparse else None)
        return mean[0]

    def trunk_parameters(self) -> list:
        return [(f"gate.experts.{n}", e) for e in range(self.gate.n_experts) for n in ("w1", "b1", "w2", "b2")]

    def probe_layers(self, x, features) -> tuple:
        """Every expert on every probe row, (E, B, hidden) per layer."""
        _, pre, act = self.gate.experts.all_experts(x, return_layers=True)
        return pre, act

    def param_groups(self) -> dict:
        return {"router": [p for m in self.gate.gating_modules() for p in m.parameters()],
                "experts": list(self.gate.experts.parameters()), "head": list(self.head.parameters()),
                "log_std": [self.log_std]}

    def cost_parts(self) -> dict:
        bank = self.gate.experts
        return {"router": linear_cost(self.gate.router), "noise_gate": linear_cost(self.gate.noise_gate),
                "one_expert": (bank.params_per_expert(), bank.macs_per_expert()),
                "head": linear_cost(self.head), "log_std": (self.log_std.numel(), 0)}


class SMoEActor(MoEActor):
    """Sparse mixture: noisy top-k gating (k = 1 by default), only the selected experts matter."""

    kind = "smoe"
    sparse = True
    hand_written_backward = True


# %% [markdown]
# ## The critics
#
# The critic reads the global state and returns one scalar per sample: an MLP state→32→32→1, or
# an expert bank with a value head 32→1 and its **own** router (the paper plots the value router's
# probabilities next to the policy router's). Beside a gated actor, `critic_gating` picks `gated`
# (the actor's own gating), `dense` (the MoE critic's dense mixture: the paper's critic "remains
# dense") or `mlp`; the MLP and MoE methods keep their own critics. `value, aux = critic(state,
# temperature=None, deterministic_gate=False)`, with `router_probs`, `experts`, `load_balance` and
# `aux_loss` in `aux`; the trainer computes the values that enter GAE with the noiseless gate.

# %%
#| export
class _Critic(nn.Module):
    """Features (run_features at R = 1, or a gate's) -> value head; subclasses build the layers."""

    features = GaussianActor.features

    def forward(self, state, temperature=None, routing=None, deterministic_gate: bool = False):
        """state (..., state_dim) -> (value (...,), aux with the value router's probabilities, if any)."""
        lead = state.shape[:-1]
        x = state.reshape(-1, self.state_dim)
        feat, out = self.features(x, temperature, _flatten_routing(routing, x.shape[0]), deterministic_gate)
        value = self.head(feat).reshape(lead)
        if out is None:
            zero = value.new_zeros(())
            return value, {"load_balance": zero, "aux_loss": zero, "router_probs": None, "experts": None}
        return value, {"load_balance": out.load_balance, "aux_loss": self.cfg.load_balance_coef * out.load_balance,
                       "router_probs": out.probs.reshape(*lead, -1), "experts": out.experts.reshape(*lead, -1),
                       "routing": out.routing.reshape(*lead)}

    def param_groups(self) -> dict:
        return {"critic": list(self.parameters())}


class MLPCritic(_Critic):
    kind = "mlp"
    hand_written_backward = True

    def __init__(self, state_dim: int, cfg: NetConfig):
        super().__init__()
        self.state_dim, self.cfg = state_dim, cfg
        self.fc1 = nn.Linear(state_dim, cfg.hidden)
        self.fc2 = nn.Linear(cfg.hidden, cfg.hidden)
        self.head = nn.Linear(cfg.hidden, 1)
        for layer, gain in ((self.fc1, cfg.gain_hidden), (self.fc2, cfg.gain_hidden), (self.head, cfg.gain_value)):
            nn.init.orthogonal_(layer.weight, gain)
            nn.init.zeros_(layer.bias)

    run_features = MLPActor.run_features


class MoECritic(_Critic):
    kind = "moe"
    sparse = False
    hand_written_backward = True

    def __init__(self, state_dim: int, cfg: NetConfig):
        super().__init__()
        self.state_dim, self.cfg = state_dim, cfg
        self.gate = GatedExperts(state_dim, cfg, sparse=self.sparse)
        self.head = nn.Linear(cfg.hidden, 1)
        nn.init.orthogonal_(self.head.weight, cfg.gain_value)
        nn.init.zeros_(self.head.bias)

    run_features, features = MoEActor.run_features, MoEActor.features


class SMoECritic(MoECritic):
    kind = "smoe"
    sparse = True
    hand_written_backward = True


# %% [markdown]
# ## Factories and cost accounting
#
# `make_actor` and `make_critic` build a network of a kind registered with `register_network`
# (appendix 05e) and check its parameter groups (`check_param_groups`: every parameter in exactly
# one group, named from `ACTOR_PARAM_GROUPS` or `CRITIC_PARAM_GROUPS`). The cost functions of
# appendix 05f (module `pemamoe.netcost`) read every number off the modules' own shapes:
#
# * `count_parameters(module)`: trainable parameters;
# * `active_parameters(actor, mode)`: parameters that take part in one agent step.
#   `mode="paper"` reproduces the paper's table (dense actors: everything; sparse actors: router,
#   noise gate and the k selected trunks, **without** the head and log-std); `"sampling"` counts
#   everything that executes when an action is sampled; `"eval"` what executes in deterministic
#   evaluation, where the noise gate is skipped;
# * `macs_per_step(actor, mode)`: multiply-accumulates of the linear layers for one agent step
#   (`"sampling"` or `"eval"`); elementwise work (ReLU, softmax, bias adds) is left out;
# * `cost_table`: the counts and the measured latency, per method and observation dimension.

# %%
#| export
register_network("mlp", MLPActor, MLPCritic)
register_network("moe", MoEActor, MoECritic)
register_network("smoe", SMoEActor, SMoECritic)


def _check_dim(name, value):
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
        raise ValueError(f"{name} must be an int >= 1, got {value!r}")


def make_actor(kind: str, obs_dim: int, act_dim: int = 2, cfg: NetConfig | None = None) -> GaussianActor:
    """Actor of network `kind` (or of a method's network) for observations (..., obs_dim) and actions (..., act_dim)."""
    kind = network_kind(kind)
    _check_dim("obs_dim", obs_dim)
    _check_dim("act_dim", act_dim)
    return check_param_groups(NETWORKS[kind][0](obs_dim, act_dim, cfg or NetConfig()), ACTOR_PARAM_GROUPS)


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
    return check_param_groups(NETWORKS[critic_kind(kind, cfg)][1](state_dim, cfg or NetConfig()), CRITIC_PARAM_GROUPS)


# %% [markdown]
# ## Demonstration
#
# Our observation dimension comes from the environment's layout (notebook 04), so the cost table
# follows any change to it or to the number of users.

# %%
import matplotlib.pyplot as plt

from pemamoe.core import by_scale, save_figure, write_table

torch.manual_seed(seed)
if our_obs_dim is None:
    from pemamoe.env import EnvConfig, observation_dim

    our_obs_dim = int(observation_dim(EnvConfig()))
print(f"paper obs_dim = {PAPER_OBS_DIM}, our obs_dim = {our_obs_dim}")

# %% [markdown]
# ### The actor the trainer calls, at R = 1
#
# One SMoE network as a population of one: a rollout sample, then the update's pass over it with
# the stored routing, which scores the sampled actions as the rollout did.

# %%
_population = PopulationActor([make_actor("smoe", our_obs_dim)])
_obs = torch.randn(1, 8, our_obs_dim)
_step = _population.act(_obs, torch.ones(1), [torch.Generator().manual_seed(seed)])
_new = _population.evaluate(_obs, _step.action, _step.routing)
assert torch.allclose(_new.log_prob, _step.log_prob, atol=1e-6)
{name: tuple(value.shape) for name, value in _new._asdict().items() if value is not None}

# %% [markdown]
# ### The four architectures
#
# Drawn from the modules themselves (`draw_actor_architecture`, appendix 05f): the boxes carry the
# layer shapes and parameter counts of freshly built actors at the paper's observation dimension.

# %%
from pemamoe.netcost import active_parameters, count_parameters, draw_actor_architecture, macs_per_step

cfg = PAPER_NET  # the paper's counts: learned routing noise (its noise gate) and one shared mean head
paper_actors = {name: make_actor(spec.network, PAPER_OBS_DIM, 2, cfg) for name, spec in METHOD_REGISTRY.items()
                if spec.compared}
fig, axes = plt.subplots(1, len(paper_actors), figsize=(4.5 * len(paper_actors), 5.6))
for ax, (method, actor) in zip(axes, paper_actors.items()):
    draw_actor_architecture(ax, actor, method)
fig.suptitle(f"Actor architectures at obs_dim {PAPER_OBS_DIM}, hidden {cfg.hidden}, {cfg.n_experts} experts "
             "(solid: executed for a sample routed to expert 2)", fontsize=10)
fig.tight_layout()
save_figure(fig, "architecture_actors", figures_dir)
plt.show()

# %% [markdown]
# ![The four actor architectures at the paper's observation dimension](../paper_figures/architecture_actors.png)

# %% [markdown]
# ### The paper's four numbers, reproduced

# %%
print(f"{'actor':<9} {'paper params':>12} {'ours':>7} {'paper active':>13} {'ours':>7} {'sampling':>9} {'eval':>6}")
for kind, actor in paper_actors.items():
    print(f"{kind:<9} {PAPER_ACTOR_PARAMS[kind]:>12,} {count_parameters(actor):>7,} {PAPER_ACTIVE_PARAMS[kind]:>13,} "
          f"{active_parameters(actor, 'paper'):>7,} {active_parameters(actor, 'sampling'):>9,} "
          f"{active_parameters(actor, 'eval'):>6,}")
    assert count_parameters(actor) == PAPER_ACTOR_PARAMS[kind]
    assert active_parameters(actor, "paper") == PAPER_ACTIVE_PARAMS[kind]
ratio = macs_per_step(paper_actors["smoe"]) / macs_per_step(paper_actors["mlp"])
print(f"SMoE / MLP multiply-accumulates per step (sampling): {ratio:.3f} (paper: about 1.16)")

# %% [markdown]
# ### Routing replay, load balance and the top-1 router's gradient
#
# A rollout batch sampled with noisy gating, re-evaluated with the stored routing as the PPO update
# does: the largest |log-ratio| must be exactly zero (re-drawing the noise instead shows how far
# the ratios would drift). Then the balance loss at its two ends, and the router's gradient from
# the policy loss alone, with top-1 weights that are all exactly 1.

# %%
n_check = by_scale(scale, ci=256, small=2048, paper=2048)
obs = torch.randn(n_check, PAPER_OBS_DIM)
for kind, actor in paper_actors.items():
    action, logp_old, routing = actor.act(obs, temperature=1.5)
    with torch.no_grad():
        exact = (actor.evaluate(obs, action, routing)[0] - logp_old).abs().max().item()
        redraw = (actor.evaluate(obs, action, None, temperature=1.5)[0] - logp_old).abs().max().item()
    print(f"{kind:<8} max|log ratio| replayed = {exact:.1e}   re-drawn noise = {redraw:.2e}")
    assert exact == 0.0

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
print(f"top-1 gate weights all exactly 1: {bool((aux['gate_weights'] == 1).all())}; router grad norm from the policy "
      f"loss alone = {g.norm():.3e}; noise-gate grad norm = {actor.gate.noise_gate.weight.grad.norm():.3e}")
assert torch.isfinite(g).all() and g.abs().sum() > 0
actor.zero_grad(set_to_none=True)

# %% [markdown]
# ### Evaluation mode and the temperature
#
# Evaluation mode (`deterministic=True`) turns the gate noise off and returns the mean action, so
# two calls agree exactly. The plot shows what the controller's temperature does to a noisy sparse
# router given a preference for expert 1 (its bias): with our placement of $\tau$, a hotter router
# hands more decisions to the noise and usage spreads out (applied after the noise, it would not).

# %%
print("deterministic evaluation repeatable:", torch.equal(actor.act(obs, deterministic=True)[0],
                                                         actor.act(obs, deterministic=True)[0]))

demo = make_actor("smoe", PAPER_OBS_DIM, 2, cfg)
with torch.no_grad():
    demo.gate.router.bias.copy_(torch.tensor([2.0, 0.0, 0.0]))
taus = [0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0]
routed = [demo.act(obs, temperature=tau)[2].experts.reshape(-1) for tau in taus]
usage = torch.stack([torch.bincount(r, minlength=E).float() / r.numel() for r in routed])
fig, ax = plt.subplots(figsize=(5.5, 3.2))
for j in range(E):
    ax.plot(taus, usage[:, j], marker="o", label=f"expert {j + 1}")
ax.set(xlabel="router temperature τ", ylabel="fraction of samples routed",
       title="Noisy top-1 routing spreads as τ rises")
ax.set_xscale("log", base=2)
ax.legend(fontsize=8)
fig.tight_layout()
save_figure(fig, "architecture_router_temperature", figures_dir)
plt.show()

# %% [markdown]
# ![Noisy top-1 routing spreads as the router temperature rises](../paper_figures/architecture_router_temperature.png)

# %% [markdown]
# ### The cost table
#
# Counts at the paper's dimension and at ours, with the measured agent-step latency (median of
# repeated `act` calls on one torch thread). Latencies depend on the machine, the counts do not:
# the file written to `paper_figures/` holds the counts only (regenerating it rewrites the same
# bytes), and `make bench` (`benchmarks/bench_nets.py`) prints the latencies.

# %%
from pemamoe.netcost import cost_table

repeats = by_scale(scale, ci=5, small=50, paper=100)
table = cost_table({"paper": PAPER_OBS_DIM, "ours": our_obs_dim}, cfg, repeats=repeats, seed=seed)
write_table(table.drop(columns=[c for c in table.columns if c.startswith("latency_")]), "cost_table", figures_dir)
table

# %% [markdown]
# ### What we found
#
# * The parameter counts pin the architecture to deep expert trunks with one shared head, not the
#   paper's per-expert linear means; its sparse "active" count omits the head and the log-std
#   (68 parameters): 7,820 against 7,888 that actually run when sampling.
# * Under top-1 routing the paper's renormalised weight is constant, so without a
#   straight-through term the router gets no gradient from the policy loss; and a temperature
#   applied to the whole (noisy) logit vector cannot change a top-k decision.
# * On a CPU at these sizes, kernel-call overhead dominates small batches, so batched execution
#   of every expert wins up to a few hundred rows and true conditional computation (`masked`) on
#   rollout-sized ones (appendix 05b; `make bench` reprints the comparison on this machine).
