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
# # 05b · Appendix: the machinery behind the networks
#
# Notebook 05 builds the actors and critics as single networks: what each computes, and why. The
# experiments need more than that, and nothing in this appendix changes what a network computes:
#
# * the **method registry** (module `pemamoe.methods`): a method pairs a network kind of notebook 05
#   with a plasticity method of notebook 06 and gives them the label and colour every figure uses;
# * two more **ways to execute the expert bank** besides notebook 05's `stacked` one: `masked`
#   (genuine conditional computation) and `loop` (the textbook version), and how `"auto"` picks;
# * the **run axis** (module `pemamoe.popnets`): R independent networks of one kind held as one set of
#   tensors, which is how the trainer of notebook 07 trains a population of runs in one process;
# * **latency and the cost table** (module `pemamoe.netcost`): timing an agent step, and the
#   function that assembles the cost table regenerated at the end of notebook 05.
#
# Read it when you add a method or a network kind (the registry and `run_features`), or when you
# need to know why training runs at the speed it does.
#
# **Imports.** `pemamoe.methods` and `pemamoe.popnets` import nothing from `pemamoe.nets` while
# loading, so `pemamoe.nets` imports them and re-exports what callers have always taken from it
# (`from pemamoe.nets import PopulationActor, gaussian_kl` still works). The one thing
# `pemamoe.popnets` needs from notebook 05, the `RoutingSample` that `PopulationActor.act` returns,
# is imported inside that method. `pemamoe.netcost` builds actors, so it imports `pemamoe.nets`,
# and nothing in `pemamoe.nets` imports it.

# %%
#| default_exp popnets

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## The methods: a network kind plus a plasticity method
#
# A *method* in the experiments is a pair: the network kind that computes the policy (notebook 05)
# and the plasticity method that acts at phase switches (notebook 06). The registry below is the one
# place that names the methods; the trainer, the sweeps, the figures and the tests read names,
# labels, colours and dispatch from it. PE-MAMoE is the SMoE network with the Phase Controller;
# any other pairing (an MLP with the controller's switch-time mechanisms, say) is one more entry
# with its own label. The paper's cost-table numbers ride along in each entry, for comparison only
# (notebook 05 reads them as `PAPER_ACTOR_PARAMS` and `PAPER_ACTIVE_PARAMS`).

# %%
#| export methods
from dataclasses import dataclass


@dataclass(frozen=True)
class MethodSpec:
    """One comparable method: what it trains (network kind) and how it treats plasticity."""

    name: str
    network: str  # a kind of pemamoe.nets.make_actor / make_critic
    plasticity: str = "none"  # a name in pemamoe.population_plasticity.PLASTICITY_METHODS
    label: str = ""  # display label in figures and tables
    colour: str = "#333333"
    proposed: bool = False  # the paper's method (the headline comparisons are against it)
    paper_actor_params: int | None = None  # the paper's cost table, for comparison only
    paper_active_params: int | None = None
    # the plasticity method's preset: (field, value) pairs applied to the run's PhaseControllerConfig
    # before the scale's rescaling and any override (empty: the defaults of notebook 06)
    plasticity_preset: tuple = ()
    # in the experiments' default comparison (`compared_methods()`: the paper's four and, unless
    # they say otherwise, a plug-in's); False: registered and run by name, in a sweep only when named
    compared: bool = True


METHOD_REGISTRY: dict = {}


def register_method(spec: MethodSpec) -> MethodSpec:
    """Add a method (or replace one of the same name); returns it."""
    if not isinstance(spec, MethodSpec):
        raise ValueError(f"register_method needs a MethodSpec, got {type(spec).__name__}")
    if not spec.name or not isinstance(spec.name, str):
        raise ValueError(f"MethodSpec.name must be a non-empty string, got {spec.name!r}")
    METHOD_REGISTRY[spec.name] = spec if spec.label else MethodSpec(**{**spec.__dict__, "label": spec.name})
    return METHOD_REGISTRY[spec.name]


def load_plugins() -> None:
    """Import the modules named in $PEMAMOE_PLUGINS (comma-separated), once: how methods, network
    kinds and plasticity methods defined outside the package reach every process of a sweep."""
    import importlib
    import os

    for module in filter(None, (m.strip() for m in os.environ.get("PEMAMOE_PLUGINS", "").split(","))):
        if module not in _LOADED_PLUGINS:
            _LOADED_PLUGINS.add(module)
            importlib.import_module(module)


_LOADED_PLUGINS: set = set()


def method_spec(name: str) -> MethodSpec:
    if name not in METHOD_REGISTRY:
        load_plugins()
    if name not in METHOD_REGISTRY:
        raise ValueError(f"method must be one of {', '.join(METHOD_REGISTRY)}, got {name!r}")
    return METHOD_REGISTRY[name]


def method_names(proposed_last: bool = True) -> tuple:
    """Registered method names in registration order (the figures' order)."""
    return tuple(METHOD_REGISTRY)


def compared_methods() -> tuple:
    """The methods the experiments compare unless told otherwise, in registration order (every
    registered method except those registered with compared=False)."""
    return tuple(name for name, spec in METHOD_REGISTRY.items() if spec.compared)


def method_label(name: str) -> str:
    return METHOD_REGISTRY[name].label if name in METHOD_REGISTRY else name


def method_colour(name: str) -> str:
    return METHOD_REGISTRY[name].colour if name in METHOD_REGISTRY else "#333333"


def proposed_method() -> str:
    return next(name for name, spec in METHOD_REGISTRY.items() if spec.proposed)


# The paper's four methods, in the order the figures use.
register_method(MethodSpec("mlp", network="mlp", label="MLP", colour="#7f7f7f",
                           paper_actor_params=6820, paper_active_params=6820))
register_method(MethodSpec("moe", network="moe", label="MoE", colour="#1f77b4",
                           paper_actor_params=20858, paper_active_params=20858))
register_method(MethodSpec("smoe", network="smoe", label="SMoE", colour="#ff7f0e",
                           paper_actor_params=21392, paper_active_params=7820))
register_method(MethodSpec("pemamoe", network="smoe", plasticity="phase_controller", label="PE-MAMoE",
                           colour="#d62728", proposed=True, paper_actor_params=21392, paper_active_params=7820))
# Two plasticity baselines from the literature (appendix 06c), each on the MLP and on the SMoE
# network: run by name (`--methods smoe_redo`), outside the default comparison.
register_method(MethodSpec("mlp_redo", network="mlp", plasticity="redo", label="MLP + ReDo", colour="#9467bd",
                           compared=False))
register_method(MethodSpec("smoe_redo", network="smoe", plasticity="redo", label="SMoE + ReDo", colour="#8c564b",
                           compared=False))
register_method(MethodSpec("mlp_snp", network="mlp", plasticity="shrink_and_perturb",
                           label="MLP + shrink-and-perturb", colour="#e377c2", compared=False))
register_method(MethodSpec("smoe_snp", network="smoe", plasticity="shrink_and_perturb",
                           label="SMoE + shrink-and-perturb", colour="#17becf", compared=False))


# %% [markdown]
# ## Executing the expert bank: stacked, masked, loop
#
# Notebook 05 stores the $E$ experts **stacked** (`w1` of shape `(E, obs_dim, hidden)`, `w2` of
# shape `(E, hidden, hidden)`, plus biases) and runs them the `stacked` way: every expert on every
# sample with two batched matrix products, then the selected experts' rows are picked. Under top-1
# routing that wastes $E-1$ of $E$ experts' arithmetic, but it makes only a handful of kernel calls.
# The same stored weights can be run two other ways, which give the same outputs:
#
# * `masked`: for each expert, gather only the rows routed to it (`index_select`), run the two
#   layers on those rows, and add the weighted result back into place (`index_add`). This is the
#   genuine conditional computation the paper describes; it pays for it with more, smaller kernel
#   calls and indexing.
# * `loop`: the textbook version, a Python loop that runs each expert as a pair of ordinary linear
#   layers (`torch.addmm`, what `nn.Linear` does) on the whole batch, then selects.
#
# `benchmarks/bench_nets.py` times the three at batch 1 (an agent step), 256 (a typical PPO
# minibatch) and 2048 (a rollout). On our 2-core CPU, `stacked` wins up to a few hundred rows,
# where kernel-call overhead dominates the tiny matrices, and `masked` wins from roughly 512 rows
# on, where doing a third of the arithmetic pays for the indexing (forward and backward of the
# top-1 actor at 2048 rows, one thread: 4.6 to 6.7 ms masked against 6.0 to 8.8 ms stacked and
# 7.0 to 10.3 ms loop over our runs at `469129f`). No single strategy is fastest everywhere, so the default
# `"auto"` takes `masked` for sparse mixing at batches of at least `NetConfig.masked_min_batch`
# rows and `stacked` otherwise (dense mixing always runs every expert, so it uses `stacked`).
# `ExpertBank` (notebook 05) calls the two functions below for `masked` and `loop`; each strategy
# stays selectable with `NetConfig(expert_impl=...)` or by setting `bank.impl`.

# %%
#| export
import copy
import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from pemamoe.routing import RoutingSample  # notebook 05


def loop_experts(bank, x):
    """Every expert of an ExpertBank on every row of x (B, in_dim), one expert at a time, as two
    ordinary linear layers -> [pre1, act1, pre2, act2], each (E, B, hidden)."""
    p1s, a1s, p2s, a2s = [], [], [], []
    for e in range(bank.n_experts):
        p1 = torch.addmm(bank.b1[e], x, bank.w1[e])
        a1 = F.relu(p1)
        p2 = torch.addmm(bank.b2[e], a1, bank.w2[e])
        p1s.append(p1), a1s.append(a1), p2s.append(p2), a2s.append(F.relu(p2))
    return [torch.stack(t) for t in (p1s, a1s, p2s, a2s)]


def masked_mixed(bank, x, experts, weights):
    """sum_j weights[:, j] * expert_{experts[:, j]}(x) -> (B, hidden), each expert run only on the
    rows routed to it. x (B, in_dim); experts (B, k) long; weights (B, k)."""
    batch, k = experts.shape
    out = x.new_zeros(batch, bank.hidden)
    flat_e = experts.reshape(-1)
    flat_w = weights.reshape(-1, 1)
    rows = torch.arange(batch, device=x.device).repeat_interleave(k)
    for e in range(bank.n_experts):
        slot = (flat_e == e).nonzero(as_tuple=True)[0]
        if slot.numel() == 0:
            continue
        r = rows.index_select(0, slot)
        h = F.relu(torch.addmm(bank.b1[e], x.index_select(0, r), bank.w1[e]))
        h = F.relu(torch.addmm(bank.b2[e], h, bank.w2[e]))
        out = out.index_add(0, r, h * flat_w.index_select(0, slot))
    return out


# %% [markdown]
# ## A population of networks: the run axis
#
# Training one small network at a time wastes the CPU: a PPO minibatch step on 192 rows costs
# mostly fixed per-call overhead (Python, dispatch, allocation), not arithmetic. So the trainer
# trains R independent runs ("members": different seeds, ablation switches or noise levels) in
# one process, as one set of tensors with a leading run axis, the way PureJaxRL vectorises seeds.
#
# * Each member's parameters are one row of a flat `(R, P)` tensor. `ParamLayout` knows where
#   every named parameter of the single-run module lives in that row, and `views` hands out
#   `(R, *shape)` views, so gradients, the optimizer, gradient clipping and noise injection are
#   a handful of tensor operations for all members together.
# * Each network kind computes its features for all members with batched matrix products: its
#   `run_features` method (notebook 05, one per actor and critic class) is built from `run_linear`,
#   `run_experts` and `run_gate` below; member r only ever reads row r of the parameters and its
#   own rows of the input.
# * Members are built as single-run modules (same constructor, same seed, so the same
#   initialisation as a run trained alone) and stacked; `member(r)` copies row r back into a
#   single-run module for diagnostics, evaluation and checkpoints. A checkpoint of a member is
#   therefore the same file whether it trained alone or in a population.
#
# Why a member's numbers do not depend on its neighbours: every operation is either
# elementwise, a reduction within one member's slice, or a batched matrix product whose batch
# entries are computed independently (checked bit for bit in the tests, and by training the same
# member alone and in populations of different sizes).
#
# `PopulationActor` and `PopulationCritic` hold the flat parameters and run the batched passes the
# trainer needs: `act` (one torch generator per member, which draws first the member's gate noise,
# then its action noise), `evaluate` (the PPO update's pass with the stored routing replayed, as
# notebook 05's `GaussianActor.evaluate` does for one network) and the critic's call. The Gaussian
# helpers at the end compute log-densities, entropies and KL divergences per member from the means
# and log-standard-deviations.

# %%
#| export
class ParamLayout:
    """Where each parameter of one member lives in a flat vector of length P.

    A population of R members stores its parameters as one (R, P) tensor; `views(flat)` gives
    each named parameter as an (R, *shape) view of it, so one optimizer step, one gradient-norm
    and one noise draw act on all members at once, and member r's numbers are row r.
    """

    def __init__(self, module: nn.Module):
        self.names, self.shapes, self.offsets = [], [], []
        offset = 0
        for name, p in module.named_parameters():
            self.names.append(name)
            self.shapes.append(tuple(p.shape))
            self.offsets.append(offset)
            offset += p.numel()
        self.size = offset
        self.index = {n: i for i, n in enumerate(self.names)}

    def span(self, name: str) -> tuple:
        i = self.index[name]
        return self.offsets[i], self.offsets[i] + math.prod(self.shapes[i])

    def flatten(self, modules) -> torch.Tensor:
        """(R, P) from R modules of the same architecture (parameters copied)."""
        rows = []
        for m in modules:
            params = dict(m.named_parameters())
            rows.append(torch.cat([params[n].detach().reshape(-1) for n in self.names]))
        return torch.stack(rows)

    def views(self, flat: torch.Tensor) -> dict:
        """{name: (R, *shape) view of flat (R, P)} (gradients flow back into flat).

        One `split` rather than a slice per parameter: its backward is a single concatenation,
        where slices would each allocate a full (R, P) gradient."""
        R = flat.shape[0]
        sizes = [math.prod(s) for s in self.shapes]
        parts = flat.split(sizes, dim=1)
        return {n: part.reshape(R, *s) for n, s, part in zip(self.names, self.shapes, parts)}

    def load_member(self, row: torch.Tensor, module: nn.Module) -> nn.Module:
        """Copy one member's flat parameters (P,) into a single-run module; returns it."""
        params = dict(module.named_parameters())
        with torch.no_grad():
            for n, s, o in zip(self.names, self.shapes, self.offsets):
                params[n].copy_(row[o:o + math.prod(s)].reshape(s))
        return module

    def mask(self, names) -> torch.Tensor:
        """(P,) bool: True on the parameters named."""
        m = torch.zeros(self.size, dtype=torch.bool)
        for n in names:
            a, b = self.span(n)
            m[a:b] = True
        return m

    def indices(self, name: str) -> torch.Tensor:
        """The flat positions of parameter `name`, shaped like it: `indices("fc1.weight")[u]` are
        where row u of that weight lives in a member's row, for partial edits and optimizer masks."""
        a, b = self.span(name)
        return torch.arange(a, b).reshape(self.shapes[self.index[name]])

    def expert_index(self, name: str, expert: int) -> torch.Tensor:
        """Flat indices of slice `expert` along the leading axis of parameter `name` (E, ...)."""
        a, b = self.span(name)
        shape = self.shapes[self.index[name]]
        per = math.prod(shape[1:])
        return torch.arange(a + expert * per, a + (expert + 1) * per)


def run_linear(x, weight, bias):
    """Member-wise linear layer: x (R, n, in), weight (R, out, in), bias (R, out) -> (R, n, out)."""
    if weight.shape[1] == 1:
        # A single output (the value head): torch takes a different matrix-vector path for one
        # batch entry than for several, and the results differ in the last bit, which would make
        # a member's values depend on the population size. A product and a row sum do not.
        return (x * weight[:, :, :].transpose(1, 2).reshape(x.shape[0], 1, -1)).sum(-1, keepdim=True) + bias.unsqueeze(1)
    return torch.baddbmm(bias.unsqueeze(1), x, weight.transpose(1, 2))


def run_experts(x, w1, b1, w2, b2):
    """Every expert of every member on that member's rows: x (R, n, in), w1 (R, E, in, h) ->
    (R, E, n, h), the ReLU trunk in -> h -> h (layer 1: one wide product per member when x needs
    no gradient, else per expert; layer 2: one batched product over R*E)."""
    R, E, d, h = w1.shape
    n = x.shape[1]
    if not x.requires_grad:
        # Layer 1 of all E experts as one (n, in) @ (in, E*h) product per member: a wide product
        # runs about 1.6x faster than E narrow ones (forward and backward). Every output column is
        # the same dot product over `in`, so outputs and the weight and bias gradients are the same
        # bits as the narrow products below (checked over many shapes in tests/test_population.py);
        # the input's gradient would be summed in another order, hence only for inputs without one.
        wide = w1.permute(0, 2, 1, 3).reshape(R, d, E * h)
        a1 = torch.baddbmm(b1.reshape(R, 1, E * h), x, wide).reshape(R, n, E, h).transpose(1, 2)
        a1 = F.relu(a1).reshape(R * E, n, h)
    elif R > 1:
        # Layer 1 as one product over R per expert, on x itself: no E-fold copy of x (about 2x
        # faster at R = 16 on the CPU, forward and backward). Each batch entry is the same
        # (n, in) @ (in, h) product as below, so outputs and gradients are the same bits (checked
        # over many shapes, sign of zero included); `unbind` backward stacks, it adds nothing.
        a1 = torch.stack([torch.baddbmm(b1e.unsqueeze(1), x, w1e) for b1e, w1e in zip(b1.unbind(1), w1.unbind(1))], 1)
        a1 = F.relu(a1).reshape(R * E, n, h)
    else:  # one member: a single call on E copies of x is cheaper than E calls
        xe = x.unsqueeze(1).expand(R, E, n, d).reshape(R * E, n, d)
        a1 = F.relu(torch.baddbmm(b1.reshape(R * E, 1, h), xe, w1.reshape(R * E, d, h)))
    a2 = F.relu(torch.baddbmm(b2.reshape(R * E, 1, h), a1, w2.reshape(R * E, h, h)))
    return a2.reshape(R, E, n, h)


def run_load_balance(probs, experts, n_experts):
    """Switch balance loss per member: probs (R, n, E), experts (R, n, k) -> (R,)."""
    onehot = F.one_hot(experts.reshape(experts.shape[0], -1), n_experts).to(probs.dtype)
    counts = onehot.sum(1)
    f = counts / counts.sum(-1, keepdim=True)
    return n_experts * (f * probs.mean(1)).sum(-1)


def topk_weights(kept, top1_weight: str):
    """Mixing weights of the k selected experts from their router probabilities kept (..., k):
    renormalised over the k (the paper's equation). At k = 1 that is exactly 1 and `top1_weight`
    says what trains the router through it (notebook 05): "straight_through" keeps the value 1
    with the gradient of the kept probability, "switch" uses the probability itself as the weight
    (Switch Transformers), "paper" keeps 1 with no gradient (the balance loss alone trains the
    router)."""
    weights = kept / kept.sum(-1, keepdim=True)
    if kept.shape[-1] != 1:
        return weights
    if top1_weight == "straight_through":
        return weights.detach() + (kept - kept.detach())
    if top1_weight == "switch":
        return kept
    return weights.detach()


def run_noise_scale(p, prefix, x, gate):
    """Multiplier of the stored noise draws (R, n, E), the batched GatedExperts.noise_scale."""
    if gate.noise == "learned":
        return F.softplus(run_linear(x, p[prefix + "noise_gate.weight"], p[prefix + "noise_gate.bias"]))
    return x.new_full((*x.shape[:2], gate.n_experts), 1.0 if gate.noisy else 0.0)


def run_gate(p, prefix, x, tau, noise, experts, gate):
    """Gated trunk of every member (the batched GatedExperts): x (R, n, in), tau (R, n),
    noise (R, n, E) or None (noiseless), experts (R, n, k) to replay or None ->
    (features (R, n, hidden), (probs (R, n, E), experts (R, n, k) or None, weights))."""
    sparse, k = gate.sparse, gate.k
    logits = run_linear(x, p[prefix + "router.weight"], p[prefix + "router.bias"]) / tau.unsqueeze(-1)
    if gate.noisy and noise is not None:
        logits = logits + noise * run_noise_scale(p, prefix, x, gate)
    probs = torch.softmax(logits, dim=-1)
    h = run_experts(x, p[prefix + "experts.w1"], p[prefix + "experts.b1"], p[prefix + "experts.w2"],
                    p[prefix + "experts.b2"])  # (R, E, n, hidden)
    if not sparse:
        features = torch.einsum("rne,renh->rnh", probs, h)
        return features, (probs, None, probs)
    if experts is None:
        experts = probs.topk(k, dim=-1).indices
    weights = topk_weights(probs.gather(2, experts), gate.top1_weight)
    R, E, n, hid = h.shape
    picked = h.permute(0, 2, 1, 3).gather(2, experts.unsqueeze(-1).expand(R, n, k, hid))  # (R, n, k, hidden)
    features = (picked * weights.unsqueeze(-1)).sum(2)
    return features, (probs, experts, weights)


class _Population:
    """R networks of one kind (built as single-run modules) as one flat parameter tensor (R, P)."""

    def __init__(self, members: list):
        if not members:
            raise ValueError("a population needs at least one member")
        self.template = members[0]
        self.layout = ParamLayout(self.template)
        self.R = len(members)
        self.flat = self.layout.flatten(members).requires_grad_(True)
        gate = getattr(self.template, "gate", None)
        self.n_experts = 1 if gate is None else gate.n_experts
        self.k = 0 if gate is None else gate.k
        self.noisy = gate is not None and gate.noisy
        self.noise_mode = "off" if gate is None else gate.noise
        self.gated = gate is not None
        self.lb_coef = self.template.cfg.load_balance_coef

    def to(self, device):
        self.flat = self.flat.detach().to(device).requires_grad_(True)
        return self

    def params(self, flat=None) -> dict:
        return self.layout.views(self.flat if flat is None else flat)

    def member_param(self, r: int, name: str) -> torch.Tensor:
        """Member r's parameter `name` as a view of the flat row, shaped like the parameter: edit it
        in place under `torch.no_grad()` (`actor.member_param(0, "fc1.weight")[3] = 0.0`)."""
        a, b = self.layout.span(name)
        return self.flat[r, a:b].view(self.layout.shapes[self.layout.index[name]])

    def member(self, r: int, module=None):
        """Member r as a single-run module (a copy; `module` is filled in place if given)."""
        module = module if module is not None else copy.deepcopy(self.template)
        return self.layout.load_member(self.flat[r].detach().cpu(), module)


class PopulationActor(_Population):
    """R actors of one kind with batched forward passes."""

    def __init__(self, members: list):
        super().__init__(members)
        self.act_dim = self.template.act_dim
        self.obs_dim = self.template.obs_dim

    def mean_and_gate(self, obs, tau, noise=None, experts=None, flat=None):
        """obs (R, n, obs_dim) -> (mean (R, n, A), log_std (R, A), gate or None)."""
        p = self.params(flat)
        feat, gate = self.template.run_features(p, obs, tau, noise, experts)
        return run_linear(feat, p["head.weight"], p["head.bias"]), p["log_std"], gate

    @torch.no_grad()
    def act(self, obs, tau, generators, deterministic: bool = False, noise_std=None):
        """Sample actions for every member. obs (R, n, obs_dim), tau (R,) router temperature,
        generators: one torch.Generator per member (its gate noise, then its action noise),
        noise_std (R,): sigma of `fixed` or `annealed` routing noise (None: the config's noise_std).
        Returns (action (R, n, A), log_prob (R, n), RoutingSample with leading (R, n) or None)."""
        R, n, _ = obs.shape
        tau_rows = tau.reshape(R, 1).expand(R, n).contiguous()
        noise = None
        if self.noisy and not deterministic:
            noise = torch.stack([torch.randn(n, self.n_experts, generator=g, device=obs.device) for g in generators])
            if self.noise_mode != "learned":  # stored already scaled, so that replay needs no sigma
                sigma = obs.new_full((R,), self.template.cfg.noise_std) if noise_std is None else noise_std
                noise = noise * sigma.to(noise).reshape(R, 1, 1)
        mean, log_std, gate = self.mean_and_gate(obs, tau_rows, noise)
        if deterministic:
            action = mean
        else:
            eps = torch.stack([torch.randn(n, self.act_dim, generator=g, device=obs.device) for g in generators])
            action = mean + log_std.exp().unsqueeze(1) * eps
        logp = gaussian_log_prob(action, mean, log_std)
        routing = None
        if gate is not None:
            if noise is None:
                noise = obs.new_zeros(R, n, self.n_experts)
            experts = gate[1] if gate[1] is not None else torch.arange(self.n_experts, device=obs.device).expand(R, n, -1)
            routing = RoutingSample(noise, experts, tau_rows)
        return action, logp, routing

    @torch.no_grad()
    def routing_readings(self, obs, routing, dones, noise_std=None) -> dict:
        """The routing that ran in a rollout, per member, for a sparse gated actor ({} otherwise).
        obs (R, T, B, U, obs_dim), routing with leading (R, T, B, U), dones (R, T, B) ->
        {"rollout/switch_rate": share of an agent's consecutive steps (within an episode) whose
        selected experts differ, "rollout/override_rate": share of rows where the noise changed
        the noiseless choice, "rollout/noise_scale": mean std of the noise added to the logits
        (noise_std (R,) as passed to `act`)}."""
        if routing is None or not (self.gated and self.k < self.n_experts):
            return {}
        R, T, B, U, d = obs.shape
        rows = obs.reshape(R, -1, d)
        experts = routing.experts.reshape(R, T, B, U, -1).sort(-1).values
        changed = (experts[:, 1:] != experts[:, :-1]).any(-1).double()  # (R, T-1, B, U)
        same_episode = (~dones[:, :-1].bool()).to(changed).unsqueeze(-1).expand_as(changed)
        steps = same_episode.sum((1, 2, 3)).clamp(min=1)
        tau = routing.temperature.reshape(R, -1)
        _, _, (_, quiet, _) = self.mean_and_gate(rows, tau)
        chosen = routing.experts.reshape(R, -1, self.k).sort(-1).values
        override = (quiet.sort(-1).values != chosen).any(-1).double().mean(1)
        if self.noise_mode == "learned":
            noise_scale = run_noise_scale(self.params(), "gate.", rows, self.template.gate).mean((1, 2))
        elif self.noise_mode == "off":
            noise_scale = rows.new_zeros(R)
        else:
            noise_scale = rows.new_full((R,), self.template.cfg.noise_std) if noise_std is None else noise_std
        return {"rollout/switch_rate": ((changed * same_episode).sum((1, 2, 3)) / steps).cpu().numpy(),
                "rollout/override_rate": override.cpu().numpy(),
                "rollout/noise_scale": noise_scale.double().cpu().numpy()}

    def evaluate(self, obs, action, routing=None, flat=None):
        """PPO update pass with the stored routing replayed: (log_prob (R, n), entropy (R,),
        load-balance loss (R,), mean (R, n, A), log_std (R, A), experts (R, n, k) or None)."""
        R, n, _ = obs.shape
        if routing is None:
            tau, noise, experts = obs.new_ones(R, n), None, None
        else:
            tau, noise = routing.temperature, (routing.noise if self.noisy else None)
            experts = routing.experts if self.k and self.k < self.n_experts else None
        mean, log_std, gate = self.mean_and_gate(obs, tau, noise, experts, flat)
        logp = gaussian_log_prob(action, mean, log_std)
        entropy = gaussian_entropy(log_std)
        if gate is None:
            return logp, entropy, obs.new_zeros(R), mean, log_std, None
        probs, chosen, _ = gate
        if chosen is None:  # dense mixing: the balance loss counts each row's top expert
            chosen = probs.argmax(-1, keepdim=True)
        return logp, entropy, run_load_balance(probs, chosen, self.n_experts), mean, log_std, chosen


class PopulationCritic(_Population):
    """R centralised critics of one kind; noiseless gating (see notebook 07 on why)."""

    def __call__(self, state, tau):
        """state (R, n, state_dim), tau (R,) -> (value (R, n), load balance (R,), probs or None)."""
        R, n, _ = state.shape
        p = self.layout.views(self.flat)
        feat, gate = self.template.run_features(p, state, tau.reshape(R, 1).expand(R, n), None, None)
        value = run_linear(feat, p["head.weight"], p["head.bias"]).squeeze(-1)
        if gate is None:
            return value, state.new_zeros(R), None
        probs, chosen, _ = gate
        if chosen is None:
            chosen = probs.argmax(-1, keepdim=True)
        return value, run_load_balance(probs, chosen, self.n_experts), probs


_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


def gaussian_log_prob(action, mean, log_std):
    """Diagonal Gaussian log-density summed over the action axis: (R, n, A) -> (R, n)."""
    log_std = log_std.unsqueeze(1)
    return (-((action - mean) ** 2) / (2 * torch.exp(2 * log_std)) - log_std - _HALF_LOG_2PI).sum(-1)


def gaussian_entropy(log_std):
    """Entropy of a diagonal Gaussian per member: log_std (R, A) -> (R,)."""
    return (0.5 + _HALF_LOG_2PI + log_std).sum(-1)


def gaussian_kl(mean, log_std, ref_mean, ref_log_std):
    """KL(N(mean, std) || N(ref_mean, ref_std)) per row, summed over actions -> (R, n)."""
    ls, rls = log_std.unsqueeze(1), ref_log_std.unsqueeze(1)
    var, rvar = torch.exp(2 * ls), torch.exp(2 * rls)
    return (rls - ls + (var + (mean - ref_mean) ** 2) / (2 * rvar) - 0.5).sum(-1)


# %% [markdown]
# ## Latency and the cost table
#
# `time_forward` measures an agent step (`act`, sampling, no gradient) and reports the median
# over repeats in microseconds; `time_train_step` measures a forward and backward pass of a
# surrogate loss. `cost_table` assembles, for each method and each named observation dimension,
# the counts of notebook 05 (`count_parameters`, `active_parameters` in its three conventions,
# `macs_per_step`) and the measured latency at batch 1 and batch 2048. The counting functions stay
# in notebook 05 beside the conventions they implement; the timing is machinery, so it lives here,
# in module `pemamoe.netcost`, which imports `pemamoe.nets`.

# %%
#| export netcost
import statistics
import time

import torch

from pemamoe.methods import METHOD_REGISTRY
from pemamoe.nets import (PAPER_NET, GaussianActor, NetConfig, active_parameters, count_parameters, macs_per_step,
                          make_actor)


def _median_us(fn, repeats: int, warmup: int) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        fn()
        times.append(time.perf_counter_ns() - t0)
    return statistics.median(times) / 1e3


def time_forward(actor: GaussianActor, batch: int, repeats: int = 50, warmup: int = 5, seed: int = 0) -> float:
    """Median microseconds of actor.act(obs) (sampling, no gradient) on a (batch, obs_dim) input."""
    obs = torch.randn(batch, actor.obs_dim, generator=torch.Generator().manual_seed(seed))
    return _median_us(lambda: actor.act(obs), repeats, warmup)


def time_train_step(actor: GaussianActor, batch: int, repeats: int = 20, warmup: int = 3, seed: int = 0) -> float:
    """Median microseconds of evaluate(obs, action, routing) + backward of a PPO-like loss."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(batch, actor.obs_dim, generator=g)
    action, _, routing = actor.act(obs)

    def step():
        logp, ent, aux = actor.evaluate(obs, action, routing)
        loss = -(logp.mean() + 0.01 * ent.mean()) + aux["aux_loss"]
        actor.zero_grad(set_to_none=True)
        loss.backward()

    return _median_us(step, repeats, warmup)


def cost_table(
    obs_dims: dict,
    cfg: NetConfig | None = None,
    act_dim: int = 2,
    repeats: int = 50,
    batch_sizes: tuple = (1, 2048),
    seed: int = 0,
    threads: int | None = 1,
):
    """Per actor kind and per named observation dimension: parameters, ratio to the MLP, active
    parameters (paper / sampling / eval conventions), MACs per agent step, and measured `act`
    latency (median microseconds) at each batch size, timed with `threads` torch threads
    (None: leave the current setting); cfg None: the paper's reading (nets.PAPER_NET, learned
    routing noise), whose counts the paper's table reports. Returns a pandas DataFrame."""
    import pandas as pd

    cfg = cfg or PAPER_NET
    old_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        return pd.DataFrame(_cost_rows(obs_dims, cfg, act_dim, repeats, batch_sizes, seed))
    finally:
        torch.set_num_threads(old_threads)


def _cost_rows(obs_dims, cfg, act_dim, repeats, batch_sizes, seed):
    rows = []
    for label, obs_dim in obs_dims.items():
        torch.manual_seed(seed)
        actors = {name: make_actor(spec.network, obs_dim, act_dim, cfg) for name, spec in METHOD_REGISTRY.items()
                  if spec.compared}
        mlp_params = count_parameters(actors["mlp"])
        mlp_macs = macs_per_step(actors["mlp"])
        for kind, actor in actors.items():
            row = {
                "obs": label,
                "obs_dim": obs_dim,
                "actor": kind,  # the method's name
                "params": count_parameters(actor),
                "params_vs_mlp": round(count_parameters(actor) / mlp_params, 2),
                "active_params": active_parameters(actor, "paper"),
                "active_sampling": active_parameters(actor, "sampling"),
                "active_eval": active_parameters(actor, "eval"),
                "macs_per_step": macs_per_step(actor, "sampling"),
                "macs_vs_mlp": round(macs_per_step(actor, "sampling") / mlp_macs, 3),
                "macs_eval": macs_per_step(actor, "eval"),
            }
            for b in batch_sizes:
                row[f"latency_us_b{b}"] = round(time_forward(actor, b, repeats=repeats, seed=seed), 1)
            row["torch_threads"] = torch.get_num_threads()
            rows.append(row)
    return rows


# %% [markdown]
# ## Demonstration
#
# ### The registered methods
#
# The paper's four methods, in the order the figures use, with their network kind, plasticity
# method and the paper's counts.

# %%
import pandas as pd

from pemamoe.methods import METHOD_REGISTRY, method_names, proposed_method
from pemamoe.nets import EXPERT_IMPLS, PAPER_OBS_DIM, NetConfig, make_actor, make_critic

torch.manual_seed(seed)
registry = pd.DataFrame([{k: v for k, v in spec.__dict__.items() if k != "plasticity_preset"}
                         for spec in METHOD_REGISTRY.values()]).set_index("name")
print(registry.to_string())
assert method_names()[:4] == ("mlp", "moe", "smoe", "pemamoe") and proposed_method() == "pemamoe"

# %% [markdown]
# ### Three expert implementations, one function
#
# The same weights give the same outputs under the three execution strategies; the timing
# comparison is in `benchmarks/bench_nets.py` (`make bench`).

# %%
cfg = NetConfig()
x = torch.randn(64, PAPER_OBS_DIM)
for kind in [m for m, spec in METHOD_REGISTRY.items() if spec.network != "mlp" and spec.plasticity == "none"]:
    net = make_actor(kind, PAPER_OBS_DIM, 2, cfg)
    _, _, r = net.act(x)
    means = {}
    for impl in EXPERT_IMPLS:
        net.gate.experts.impl = impl
        d, _ = net(x, routing=r)
        means[impl] = d.mean
    same = {impl: bool(torch.allclose(m, means["stacked"], atol=1e-6)) for impl, m in means.items()}
    print(kind, same)
    assert all(same.values())

# %% [markdown]
# ### The run axis: a member does not notice its neighbours
#
# We build three SMoE actors and critics as single networks (seeds 0, 1, 2), stack them into a
# population, and check three things: `member(r)` gives back exactly the network that went in; a
# member's batched actions, log-probabilities and routing are those the same member draws in a
# population of one (bit for bit, with the same generator seed); and the batched mean of member r
# is what the single network computes on the same rows with the same routing.

# %%
obs_dim, state_dim, n_rows = 12, 20, 32


def build(kind, r):
    torch.manual_seed(r)
    return make_actor(kind, obs_dim, 2, cfg), make_critic(kind, state_dim, cfg)


singles = [build("smoe", r) for r in range(3)]
actors = PopulationActor([a for a, _ in singles])
critics = PopulationCritic([c for _, c in singles])
print(f"R = {actors.R} members, P = {actors.layout.size} actor parameters each, flat {tuple(actors.flat.shape)}")
for r, (a, _) in enumerate(singles):
    assert all(torch.equal(p, q) for p, q in zip(actors.member(r).parameters(), a.parameters()))

obs = torch.randn(3, n_rows, obs_dim)
tau = torch.tensor([1.0, 2.0, 0.5])
old = torch.get_num_threads()
torch.set_num_threads(1)  # the bit-for-bit claim is about one thread, as the trainer's members run
try:
    gens = [torch.Generator().manual_seed(100 + r) for r in range(3)]
    action, logp, routing = actors.act(obs, tau, gens)
    for r in range(3):
        alone = PopulationActor([singles[r][0]])
        a1, lp1, rt1 = alone.act(obs[r:r + 1], tau[r:r + 1], [torch.Generator().manual_seed(100 + r)])
        assert torch.equal(a1[0], action[r]) and torch.equal(lp1[0], logp[r]) and torch.equal(rt1.experts[0], routing.experts[r])
finally:
    torch.set_num_threads(old)

with torch.no_grad():
    logp_new, entropy, lb, mean, log_std, chosen = actors.evaluate(obs, action, routing)
    for r, (a, _) in enumerate(singles):
        dist, _ = a(obs[r], routing=routing.select(r))
        assert torch.allclose(dist.mean, mean[r], atol=1e-6)
        assert torch.allclose(dist.log_prob(action[r]), logp_new[r], atol=1e-5)
    value, value_lb, probs = critics(torch.randn(3, n_rows, state_dim), tau)
print("PPO ratios before any update, max |log ratio| =", f"{(logp_new - logp).abs().max().item():.1e}")
print("member load-balance losses:", [round(v, 3) for v in lb.tolist()], "; values", tuple(value.shape))

# %% [markdown]
# ### Timing an agent step
#
# `time_forward` on this machine, at batch 1 (an agent step) and at a rollout-sized batch. The
# numbers depend on the machine and its load; the cost table of notebook 05 reports them beside the
# counts.

# %%
from pemamoe.core import by_scale
from pemamoe.netcost import time_forward, time_train_step

repeats = by_scale(scale, ci=3, small=20, paper=50)
for kind in ("mlp", "smoe"):
    actor = make_actor(kind, PAPER_OBS_DIM, 2, cfg)
    print(f"{kind:<5} act: batch 1 {time_forward(actor, 1, repeats=repeats):8.1f} us, "
          f"batch 2048 {time_forward(actor, 2048, repeats=repeats):9.1f} us; "
          f"train step at 256 rows {time_train_step(actor, 256, repeats=repeats):9.1f} us")
