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
# # 05b · Appendix: the expert bank and the run axis
#
# Notebook 05 builds the actors and critics and writes their gate once, with a leading run axis,
# so that a single network and the trainer's population run the same code. This appendix holds
# the machinery under that code, which changes nothing a network computes, in the module
# `pemamoe.popnets`:
#
# * the **expert bank** (`ExpertBank`): the stacked storage of the $E$ trunks and the two ways a
#   single network can run them besides the batched default: `masked` (genuine conditional
#   computation) and `loop` (the textbook version), and how `"auto"` picks;
# * the **run axis**: the batched building blocks that notebook 05's `run_gate` calls, and R
#   independent networks of one kind held as one set of tensors, which is how the trainer of
#   notebook 07 trains a population of runs in one process.
#
# The registries of methods and network kinds are appendix 05e's (`pemamoe.methods`), the counts,
# latency and the cost table appendix 05f's (`pemamoe.netcost`). Read this one when you add a
# network kind (`run_features`) or need to know why training runs at the speed it does.
#
# **Imports.** `pemamoe.popnets` imports nothing from `pemamoe.nets`, so `pemamoe.nets` imports it
# and re-exports what callers have always taken from it (`from pemamoe.nets import
# PopulationActor, RoutingSample` still works).

# %%
#| default_exp popnets

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## The expert bank: storage, and three ways to run it
#
# The $E$ experts are stored **stacked**: `w1` of shape `(E, obs_dim, hidden)`, `w2` of shape
# `(E, hidden, hidden)`, plus biases. Parameter counts, state dicts, optimiser groups and the phase
# controller's noise injection read this one storage, whichever way the experts are executed.
# `run_gate` (notebook 05) runs every expert on every sample with batched matrix products
# (`run_experts`, below) and picks the selected experts' rows: under top-1 routing that wastes
# $E-1$ of $E$ experts' arithmetic, but it makes only a handful of kernel calls. A single network
# (`NetConfig.expert_impl`, or `bank.impl`) can run its sparse gate's experts two other ways, which
# give the same outputs up to float rounding and the same routing:
#
# * `masked`: for each expert, gather only the rows routed to it (`index_select`), run the two
#   layers on those rows, and add the weighted result back into place (`index_add`). This is the
#   genuine conditional computation the paper describes; it pays for it with more, smaller kernel
#   calls and indexing.
# * `loop`: the textbook version, a Python loop that runs each expert as a pair of ordinary linear
#   layers (`torch.addmm`, what `nn.Linear` does) on the whole batch, then selects.
#
# `benchmarks/bench_nets.py` times the strategies at batch 1 (an agent step), 256 (a typical PPO
# minibatch) and 2048 (a rollout). On our 2-core CPU the batched products win up to a few hundred
# rows, where kernel-call overhead dominates the tiny matrices, and `masked` wins from roughly 512
# rows on, where doing a third of the arithmetic pays for the indexing (forward and backward of the
# top-1 actor at 2048 rows, one thread, both observation sizes: 2.6 to 2.9 ms masked against 3.3 to
# 3.7 ms batched through `run_experts` and 3.8 to 4.6 ms loop, over three runs of
# `benchmarks/bench_nets.py` at `43ae5c1`; `benchmarks/RESULTS.md` holds the latest `make bench`).
# So `"auto"` takes `masked` for sparse mixing at batches of at least `NetConfig.masked_min_batch`
# rows and the batched products otherwise; dense mixing always runs every expert, batched.
# `selected_mixer` hands `run_gate` the strategy as its `mix_selected`. `all_experts` also returns
# each layer's pre-activations and activations for every expert, which the diagnostics read.

# %%
#| export
import copy
import math
from typing import NamedTuple

import torch
import torch.nn as nn
import torch.nn.functional as F

EXPERT_IMPLS = ("auto", "stacked", "masked", "loop")


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


class ExpertBank(nn.Module):
    """E expert trunks in_dim -> hidden -> hidden (ReLU), stored as stacked weights.

    Parameters: w1 (E, in_dim, hidden), b1 (E, hidden), w2 (E, hidden, hidden), b2 (E, hidden).
    `impl` ("auto" | "stacked" | "masked" | "loop") only changes how a single network's sparse
    gate executes its experts (`selected_mixer`); "auto" means "masked" from `masked_min_batch`
    rows on, else "stacked" (run_gate's batched products over every expert).
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

    def selected_mixer(self, x: torch.Tensor):
        """How a single network mixes the selected experts of rows x (B, in_dim) under `impl`, as
        run_gate's `mix_selected`: None (every expert, batched) for "stacked" and for "auto" below
        masked_min_batch rows, else fn(experts (1, B, k), weights (1, B, k)) -> (1, B, hidden)."""
        impl = self.impl
        if impl == "auto":
            impl = "masked" if x.shape[0] >= self.masked_min_batch else "stacked"
        if impl == "stacked":
            return None
        return lambda experts, weights: self.mixed(x, experts[0], weights[0], impl).unsqueeze(0)

    def mixed(self, x: torch.Tensor, experts: torch.Tensor, weights: torch.Tensor, impl: str | None = None):
        """sum_j weights[:, j] * expert_{experts[:, j]}(x) -> (B, hidden).

        x (B, in_dim); experts (B, k) long; weights (B, k).
        """
        impl = impl or self.impl
        if impl == "auto":
            impl = "masked" if x.shape[0] >= self.masked_min_batch else "stacked"
        if impl == "masked":  # each expert on its own rows only
            return masked_mixed(self, x, experts, weights)
        h = self.all_experts(x, impl).transpose(0, 1)  # (B, E, hidden)
        picked = h.gather(1, experts.unsqueeze(-1).expand(-1, -1, self.hidden))  # (B, k, hidden)
        return (picked * weights.unsqueeze(-1)).sum(1)


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
#   `run_features` method (notebook 05, one per actor and critic class) is built from `run_linear`
#   and `run_experts` below and notebook 05's `run_gate`; member r only ever reads row r of the
#   parameters and its own rows of the input. A single network runs the same code at R = 1.
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
# and log-standard-deviations. `RoutingSample` is what a gated pass stores to be replayed (its
# noise, its chosen experts, its temperature), with the indexing a rollout buffer needs;
# `routing_noise_std` is the per-iteration sigma of `fixed` and `annealed` routing noise that the
# trainer hands `act`, and `draw_routing_noise` draws a pass's gate noise as `RoutingSample`
# stores it: the one routing-noise draw, used by `act` here and by notebook 05's single network.

# %%
#| export
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


def routing_noise_std(cfg, iteration: int, iterations: int) -> float:
    """Sigma of the routing noise of NetConfig cfg at `iteration` of a run of `iterations`: cfg.noise_std for
    `fixed`, falling linearly to 0 over the first noise_anneal_portion of the run for `annealed`,
    0 for `off` (and for `learned`, whose scale the network computes)."""
    if cfg.routing_noise == "fixed":
        return float(cfg.noise_std)
    if cfg.routing_noise == "annealed":
        return float(cfg.noise_std * max(0.0, 1.0 - iteration / (cfg.noise_anneal_portion * iterations)))
    return 0.0


def draw_routing_noise(mode: str, rows: int, n_experts: int, sigma, generators=None, dtype=None, device=None):
    """The gate noise of one sampling pass as a RoutingSample stores it, for the single network and the
    population alike: standard-normal draws (rows, E) from torch's global generator when `generators`
    is None (one network, in `dtype`), else (R, rows, E), member r's drawn from generators[r]; times
    sigma for `fixed` and `annealed` routing noise (a number, or one per member (R,)), as drawn for
    `learned` (run_noise_scale multiplies them by the noise gate in the forward pass). Stored already
    scaled, so that a replay needs no sigma."""
    if generators is None:
        noise = torch.randn(rows, n_experts, dtype=dtype, device=device)
    else:
        noise = torch.stack([torch.randn(rows, n_experts, generator=g, device=device) for g in generators])
    if mode == "learned":
        return noise
    if isinstance(sigma, torch.Tensor):
        sigma = sigma.to(noise).reshape(-1, *(1,) * (noise.ndim - 1))
    return noise * sigma


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


def run_experts(x, w1, b1, w2, b2, saved=None):
    """Every expert of every member on that member's rows: x (R, n, in), w1 (R, E, in, h) ->
    (R, E, n, h), the ReLU trunk in -> h -> h, each layer one batched product over R*E. `saved` (a
    dict) keeps what the hand-written backward of appendix 05h reads: the input copied once per
    expert xe (R*E, n, in) and the layer activations a1 (R*E, n, h) and a2 (R, E, n, h)."""
    R, E, d, h = w1.shape
    n = x.shape[1]
    if x.requires_grad and R > 1:
        # Layer 1 as one product over R per expert, on x itself: no E-fold copy of x (about 2x
        # faster at R = 16 on the CPU, forward and backward, where autograd differentiates an input).
        # Each batch entry is the same (n, in) @ (in, h) product as below, so outputs and gradients
        # are the same bits (checked over many shapes, sign of zero included).
        xe = None
        a1 = torch.stack([torch.baddbmm(b1e.unsqueeze(1), x, w1e) for b1e, w1e in zip(b1.unbind(1), w1.unbind(1))], 1)
        a1 = F.relu(a1).reshape(R * E, n, h)
    else:  # E copies of x, then a single call
        xe = x.unsqueeze(1).expand(R, E, n, d).reshape(R * E, n, d)
        a1 = F.relu(torch.baddbmm(b1.reshape(R * E, 1, h), xe, w1.reshape(R * E, d, h)))
    a2 = F.relu(torch.baddbmm(b2.reshape(R * E, 1, h), a1, w2.reshape(R * E, h, h))).reshape(R, E, n, h)
    if saved is not None:
        saved.update(x=x, xe=xe, a1=a1, a2=a2)
    return a2


def routing_counts(experts, probs):
    """(R, E): how many of each member's n*k routing slots chose each expert; experts (R, n, k),
    probs (R, n, E) giving the shape and dtype."""
    slots = experts.reshape(experts.shape[0], -1)
    return torch.zeros_like(probs[:, 0]).scatter_add_(1, slots, torch.ones_like(slots, dtype=probs.dtype))


def run_load_balance(probs, experts, n_experts):
    """Switch balance loss E * sum_i f_i P_i per member: probs (R, n, E), experts (R, n, k) -> (R,);
    f_i the share of the n*k routing slots on expert i (no gradient), P_i the mean of probs[..., i]."""
    counts = routing_counts(experts, probs)
    return (counts * probs.mean(1)).sum(-1) * (n_experts / experts[0].numel())  # f_i = counts_i / (n k)


def run_noise_scale(p, prefix, x, gate):
    """Multiplier of the stored noise draws (R, n, E): softplus of the noise gate for `learned`
    noise; 1 for `fixed` and `annealed`, whose draws are stored already scaled by their sigma;
    0 when noiseless."""
    if gate.noise == "learned":
        return F.softplus(run_linear(x, p[prefix + "noise_gate.weight"], p[prefix + "noise_gate.bias"]))
    return x.new_full((*x.shape[:2], gate.n_experts), 1.0 if gate.noisy else 0.0)


class _Population:
    """R networks of one kind (built as single-run modules) as one flat parameter tensor (R, P)."""

    def __init__(self, members: list):
        if not members:
            raise ValueError("a population needs at least one member")
        self.template = members[0]
        self.layout = ParamLayout(self.template)
        self.R = len(members)
        self.flat = self.layout.flatten(members).requires_grad_(True)
        self._views = None  # (flat, its views), see params
        self._copies = None  # (flat's version, contiguous copies of its views) at R > 1, see params
        self._grad = None  # (gradient buffer, its views), see grad_views
        gate = getattr(self.template, "gate", None)
        self.n_experts = 1 if gate is None else gate.n_experts
        self.k = 0 if gate is None else gate.k
        self.noisy = gate is not None and gate.noisy
        self.noise_mode = "off" if gate is None else gate.noise
        self.gated = gate is not None
        self.lb_coef = self.template.cfg.load_balance_coef
        # the kind's gradient is written out (appendix 05h) when its own class says so; a subclass
        # from a plugin, whose forward may differ, is differentiated by autograd
        self.by_hand = bool(type(self.template).__dict__.get("hand_written_backward", False))

    def to(self, device):
        self.flat = self.flat.detach().to(device).requires_grad_(True)
        return self

    def params(self, flat=None) -> dict:
        """{name: (R, *shape) tensor} of `flat` (default: the population's own parameters): views,
        through which gradients flow back into `flat`.

        Outside autograd, of the population's own tensor, they are made once per change of it and
        are for reading. At R = 1 they are views. At R > 1 a view of one member's row segment is
        strided by P, and every batched product over R*E that reshapes it would copy it each time
        (forward and backward, every minibatch); so they are contiguous copies instead, made in
        one call when `flat`'s version counter shows it was changed in place (an optimizer step,
        a plasticity method's reset, an edit through `member_param`)."""
        if flat is None and not torch.is_grad_enabled():
            if self._views is None or self._views[0] is not self.flat:
                self._views, self._copies = (self.flat, self.layout.views(self.flat)), None
            views = self._views[1]
            if self.flat.shape[0] == 1:
                return views
            if self._copies is None or self._copies[0] != self.flat._version:
                if self._copies is None:
                    self._copies = (None, {n: torch.empty(v.shape, dtype=v.dtype, device=v.device) for n, v in views.items()})
                torch._foreach_copy_(list(self._copies[1].values()), list(views.values()))
                self._copies = (self.flat._version, self._copies[1])
            return self._copies[1]
        return self.layout.views(self.flat if flat is None else flat)

    def grad_views(self) -> tuple:
        """(buffer (R, P), {name: (R, *shape) view of it}): where a hand-written backward (appendix
        05h) writes the members' gradients, one buffer kept for the population's life."""
        if self._grad is None or self._grad[0].shape != self.flat.shape or self._grad[0].device != self.flat.device:
            buffer = torch.zeros_like(self.flat, requires_grad=False)
            self._grad = (buffer, self.layout.views(buffer))
        return self._grad

    def member_param(self, r: int, name: str) -> torch.Tensor:
        """Member r's parameter `name` as a view of the flat row, shaped like the parameter: edit it
        in place under `torch.no_grad()` (`actor.member_param(0, "fc1.weight")[3] = 0.0`)."""
        a, b = self.layout.span(name)
        return self.flat[r, a:b].view(self.layout.shapes[self.layout.index[name]])

    def member(self, r: int, module=None):
        """Member r as a single-run module (a copy; `module` is filled in place if given)."""
        module = module if module is not None else copy.deepcopy(self.template)
        return self.layout.load_member(self.flat[r].detach().cpu(), module)


class ActorStep(NamedTuple):
    """What `PopulationActor.act` returns: the rollout's sample of every member."""

    action: torch.Tensor  # (R, n, A) unclipped Gaussian samples
    log_prob: torch.Tensor  # (R, n) their behaviour log-probabilities
    routing: RoutingSample | None  # leading (R, n): the gate's random choices, None without gates


class ActorEvaluation(NamedTuple):
    """What `PopulationActor.evaluate` returns: the PPO update's pass over stored actions."""

    log_prob: torch.Tensor  # (R, n) of the stored actions under the current parameters
    entropy: torch.Tensor  # (R,) of the Gaussian (state-independent log-std)
    load_balance: torch.Tensor  # (R,) the router's load-balance loss (0 without gates)
    mean: torch.Tensor  # (R, n, A)
    log_std: torch.Tensor  # (R, A)
    experts: torch.Tensor | None  # (R, n, k) the experts chosen in this pass, None without gates


class PopulationActor(_Population):
    """R actors of one kind with batched forward passes."""

    def __init__(self, members: list):
        super().__init__(members)
        self.act_dim = self.template.act_dim
        self.obs_dim = self.template.obs_dim

    def mean_and_gate(self, obs, tau, noise=None, experts=None, flat=None, saved=None):
        """obs (R, n, obs_dim) -> (mean (R, n, A), log_std (R, A), gate or None); `saved` as run_mean."""
        p = self.params(flat)
        if saved is None or not self.by_hand:
            mean, gate = self.template.run_mean(p, obs, tau, noise, experts)
        else:
            mean, gate = self.template.run_mean(p, obs, tau, noise, experts, saved)
        return mean, p["log_std"], gate

    @torch.no_grad()
    def act(self, obs, tau, generators, deterministic: bool = False, noise_std=None):
        """Sample actions for every member. obs (R, n, obs_dim), tau (R,) router temperature,
        generators: one torch.Generator per member (its gate noise, then its action noise),
        noise_std (R,): sigma of `fixed` or `annealed` routing noise (None: the config's noise_std).
        Returns an ActorStep: action (R, n, A), log_prob (R, n), RoutingSample with leading (R, n) or None."""
        R, n, _ = obs.shape
        tau_rows = tau.reshape(R, 1).expand(R, n).contiguous()
        noise = None
        if self.noisy and not deterministic:
            sigma = obs.new_full((R,), self.template.cfg.noise_std) if noise_std is None else noise_std
            noise = draw_routing_noise(self.noise_mode, n, self.n_experts, sigma, generators, device=obs.device)
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
        return ActorStep(action, logp, routing)

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

    @torch.no_grad()
    def reroute_readings(self, obs, routing) -> dict:
        """{"update/reroute_rate": per member, the share of rows whose experts under the current
        parameters (same noise and temperature) differ from those that acted} for a sparse actor
        that routes again in the update (update_routing="current"); {} otherwise. Read after the
        update: how much of the batch PPO moved to another expert. obs (R, ..., obs_dim), routing
        with the same leading axes."""
        if routing is None or not (self.gated and self.k < self.n_experts) \
                or self.template.cfg.update_routing != "current":
            return {}
        R = obs.shape[0]
        rows, stored = obs.reshape(R, -1, obs.shape[-1]), routing.reshape(R, -1)
        _, _, (_, chosen, _) = self.mean_and_gate(rows, stored.temperature, stored.noise if self.noisy else None)
        moved = (chosen.sort(-1).values != stored.experts.sort(-1).values).any(-1).double().mean(1)
        return {"update/reroute_rate": moved.cpu().numpy()}

    def evaluate(self, obs, action, routing=None, flat=None, saved=None):
        """PPO update pass with the stored routing, an ActorEvaluation: log_prob (R, n), entropy (R,),
        load-balance loss (R,), mean (R, n, A), log_std (R, A), experts (R, n, k) or None. The stored noise and
        temperature are always replayed; the stored experts only under update_routing="replay"
        (under "current" the router chooses again, so a changed route shows in the ratio). `saved`:
        a dict that keeps what the hand-written backward reads (appendix 05h), or None."""
        R, n, _ = obs.shape
        if routing is None:
            tau, noise, experts = obs.new_ones(R, n), None, None
        else:
            tau, noise = routing.temperature, (routing.noise if self.noisy else None)
            replay = self.template.cfg.update_routing == "replay"
            experts = routing.experts if replay and self.k and self.k < self.n_experts else None
        if saved is not None:
            saved["inputs"] = (obs, action, routing)
        mean, log_std, gate = self.mean_and_gate(obs, tau, noise, experts, flat, saved)
        logp = gaussian_log_prob(action, mean, log_std, saved)
        entropy = gaussian_entropy(log_std)
        if gate is None:
            return ActorEvaluation(logp, entropy, obs.new_zeros(R), mean, log_std, None)
        probs, chosen, _ = gate
        if chosen is None:  # dense mixing: the balance loss counts each row's top expert
            chosen = probs.argmax(-1, keepdim=True)
        return ActorEvaluation(logp, entropy, run_load_balance(probs, chosen, self.n_experts), mean, log_std, chosen)


class PopulationCritic(_Population):
    """R centralised critics of one kind; noiseless gating (see notebook 07 on why)."""

    def __call__(self, state, tau, saved=None, flat=None):
        """state (R, n, state_dim), tau (R,) -> (value (R, n), load balance (R,), probs or None);
        `saved` and `flat` as PopulationActor.evaluate."""
        R, n, _ = state.shape
        p = self.params(flat)
        if saved is None or not self.by_hand:
            feat, gate = self.template.run_features(p, state, tau.reshape(R, 1).expand(R, n), None, None)
        else:
            feat, gate = self.template.run_features(p, state, tau.reshape(R, 1).expand(R, n), None, None, saved)
            saved["features"] = feat
        if saved is not None:
            saved["inputs"] = (state, tau)
        value = run_linear(feat, p["head.weight"], p["head.bias"]).squeeze(-1)
        if gate is None:
            return value, state.new_zeros(R), None
        probs, chosen, _ = gate
        if chosen is None:
            chosen = probs.argmax(-1, keepdim=True)
        return value, run_load_balance(probs, chosen, self.n_experts), probs


_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


def gaussian_log_prob(action, mean, log_std, saved=None):
    """Diagonal Gaussian log-density summed over the action axis: (R, n, A) -> (R, n); `saved`
    keeps the deviation a - mean and 1 / sigma^2 (R, 1, A), which its gradient reads."""
    inv_var = torch.exp(-2 * log_std).unsqueeze(1)
    diff = action - mean
    if saved is not None:
        saved.update(diff=diff, inv_var=inv_var)
    return (-0.5 * diff * diff * inv_var - log_std.unsqueeze(1) - _HALF_LOG_2PI).sum(-1)


def gaussian_entropy(log_std):
    """Entropy of a diagonal Gaussian per member: log_std (R, A) -> (R,)."""
    return (0.5 + _HALF_LOG_2PI + log_std).sum(-1)


def gaussian_kl(mean, log_std, ref_mean, ref_log_std):
    """KL(N(mean, std) || N(ref_mean, ref_std)) per row, summed over actions -> (R, n)."""
    ls, rls = log_std.unsqueeze(1), ref_log_std.unsqueeze(1)
    var, rvar = torch.exp(2 * ls), torch.exp(2 * rls)
    return (rls - ls + (var + (mean - ref_mean) ** 2) / (2 * rvar) - 0.5).sum(-1)


# %% [markdown]
# ## Demonstration
#
# ### Three expert implementations, one function
#
# The same weights give the same outputs under the three execution strategies; the timing
# comparison is in `benchmarks/bench_nets.py` (`make bench`).

# %%
from pemamoe.methods import METHOD_REGISTRY
from pemamoe.nets import EXPERT_IMPLS, PAPER_OBS_DIM, NetConfig, make_actor, make_critic

torch.manual_seed(seed)
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
# **Read outside autograd, the parameters follow every in-place change.** At R > 1 `params()`
# hands out contiguous copies of the members' parameters, remade whenever `flat` was changed in
# place: here an edit through `member_param` and an optimizer-like step must both show, and the
# copies must equal the views of `flat` itself.

# %%
with torch.no_grad():
    before = actors.params()["log_std"].clone()
    actors.member_param(1, "log_std")[0] = 0.25
    assert actors.params()["log_std"][1, 0] == 0.25 and torch.equal(actors.params()["log_std"][0], before[0])
    actors.flat.mul_(0.5)
    seen, views = actors.params(), actors.layout.views(actors.flat)
    assert seen["log_std"][1, 0] == 0.125 and all(torch.equal(seen[n], views[n]) for n in views)
    assert all(t.is_contiguous() for t in seen.values())
print("params() at R = 3: contiguous, and current after each in-place change of flat")
