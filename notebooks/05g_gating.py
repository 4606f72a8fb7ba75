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
# # 05g · Appendix: the gate, for one network and for a population
#
# Notebook 05 explains the gate: the router's logits divided by the temperature, the routing
# noise added after, the softmax, the top-k choice and the mixing weights, the gradient for
# k = 1 and the balance loss. This appendix holds the code that computes it, in the module
# `pemamoe.gating`: `run_gate`, the one forward of the gate that the trainer's populations and
# a single network both run, the mixing weights of the kept experts (`topk_weights`), the balance
# loss of one network, and `GatedExperts`, the single network's router, noise gate and expert
# bank. It builds on the batched blocks of appendix 05b (`pemamoe.popnets`); `pemamoe.nets`
# (notebook 05) builds its actors and critics from it and re-exports its names.

# %%
#| default_exp gating

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# **One forward, for one network and for many.** The trainer (notebook 07) trains $R$
# independent runs of one kind at once, each member's parameters one row of a tensor, so the gate
# is written with a leading run axis: inputs `(R, n, in)`, a linear layer's weight `(R, out, in)`,
# the expert bank `(R, E, in, hidden)`; member $r$ reads only its own rows. Read every shape at
# $R = 1$ and it is the single network, which runs exactly so: `GatedExperts` adds an axis of
# length one to its own parameters (`single_member_params`) and calls the same `run_gate`.
#
# ```text
#   x (R, n, in) ─router─► logits (R, n, E) ─/τ, + ε·scale─► softmax g ─top-k─► experts, weights ─┐
#        └─experts─► h (R, E, n, hidden) ──────────────────────────────────── Σ_j w_j h_j ◄─────────┘ ─► features
# ```
#
# `run_gate` reads the `gate` module for its settings only; the numbers come from the parameter
# views `p`, keyed by parameter name after `prefix`. `noise=None` is the noiseless gate; `experts`
# replays stored choices. Its batched building blocks (`run_linear`, `run_experts`,
# `run_noise_scale`) and the balance loss `run_load_balance` are in appendix 05b. By default every
# expert runs on every row, batched, and the selected rows are picked afterwards (under top-1 that
# wastes $E-1$ of $E$ experts' arithmetic in a handful of kernel calls); `mix_selected` lets a
# single network run each expert on its own rows only instead (`NetConfig.expert_impl`: `masked`,
# the conditional computation the paper describes, `loop`, or `auto`; appendix 05b, with the
# timings). It changes speed, never the routing; the trainer never passes it.
#
# `GatedExperts` takes its settings from a `NetConfig` (notebook 05): `n_experts`, `top_k`,
# `routing_noise`, `noise_std`, `top1_weight`, the initialisation gains and how the expert bank
# executes (`expert_impl`, `masked_min_batch`).

# %%
#| export
from typing import NamedTuple

import torch
import torch.nn as nn

from pemamoe.popnets import (ExpertBank, RoutingSample, draw_routing_noise, run_experts, run_linear,
                             run_load_balance, run_noise_scale)


def topk_weights(kept, top1_weight: str):
    """Mixing weights of the k selected experts from their router probabilities kept (..., k):
    renormalised over the k (the paper's equation); at k = 1, exactly 1 with the gradient that
    `top1_weight` names ("straight_through", "switch": the probability itself, "paper": none)."""
    if kept.shape[-1] != 1:
        return kept / kept.sum(-1, keepdim=True)
    if top1_weight == "switch":
        return kept
    ones = torch.ones_like(kept)  # kept / kept, exactly (the top probability is at least 1/E)
    if top1_weight == "straight_through" and torch.is_grad_enabled():
        return ones + (kept - kept.detach())
    return ones


class ContiguousGrad(torch.autograd.Function):
    """The identity, whose backward hands on its gradient in contiguous memory. A gradient that
    reaches a matrix product through views can arrive as a strided view when the population has
    one member and as a copy when it has several; the product's backward then sums in another
    order, and a member's last bits would depend on its population's size."""

    @staticmethod
    def forward(ctx, x):
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad):
        return grad.contiguous()


def run_gate(p, prefix, x, tau, noise, experts, gate, mix_selected=None, heads=None, saved=None):
    """Gated trunk of every member: x (R, n, in), tau (R, n), noise (R, n, E) or None
    (noiseless), experts (R, n, k) to replay or None -> (features (R, n, hidden),
    (probs (R, n, E), experts (R, n, k) or None for dense mixing, weights)).
    mix_selected(experts, weights) -> features: how a single network runs only the selected
    experts of a sparse gate (None: every expert, batched). heads (weight (R, E, out, hidden),
    bias (R, E, out)): each expert's own output layer, applied before the mixing, so that the
    first result is the mixed output (R, n, out) instead of the mixed features. `saved` (a dict)
    keeps what the hand-written backward of appendix 05h reads (the experts' saves, the noise scale,
    probs, experts, weights and every expert's mixed output y)."""
    sparse, k = gate.sparse, gate.k
    logits = run_linear(x, p[prefix + "router.weight"], p[prefix + "router.bias"]) / tau.unsqueeze(-1)
    scale = None
    if gate.noisy and noise is not None:
        scale = run_noise_scale(p, prefix, x, gate)
        logits = logits + noise * scale
    probs = torch.softmax(logits, dim=-1)
    h = None
    if heads is not None or not (sparse and mix_selected is not None):
        h = run_experts(x, p[prefix + "experts.w1"], p[prefix + "experts.b1"], p[prefix + "experts.w2"],
                        p[prefix + "experts.b2"], saved)  # (R, E, n, hidden)
    if heads is not None:  # every expert's own output: (R, E, n, out), mixed below like the features
        (hw, hb), (R, E, n, hid) = heads, h.shape
        # One memory layout whatever R is, forward (the parameters: a reshape of a population's
        # views copies when R > 1 but is a strided view when R = 1, and the product rounds
        # differently on the two) and backward (ContiguousGrad), so a member's bits do not depend
        # on its population's size; the layout is the one populations of several always had.
        h = torch.baddbmm(hb.contiguous().reshape(R * E, 1, -1), h.reshape(R * E, n, hid),
                          hw.transpose(-1, -2).contiguous().reshape(R * E, hid, -1))
        h = ContiguousGrad.apply(h).reshape(R, E, n, -1)
    if sparse:
        if experts is None:
            experts = probs.topk(k, dim=-1).indices
        weights = topk_weights(probs.gather(2, experts), gate.top1_weight)
        if h is None:
            return mix_selected(experts, weights), (probs, experts, weights)
        mix = torch.zeros_like(probs).scatter(2, experts, weights)  # each expert's weight per row, 0 if not chosen
        gate_out = (probs, experts, weights)
    else:
        mix, gate_out = probs, (probs, None, probs)
    # sum_e mix_e h_e, on contiguous weights: a product's memory order follows its operands', and
    # the sum must add in the same order whatever the population's size
    features = (h * mix.transpose(1, 2).contiguous().unsqueeze(-1)).sum(1)
    if saved is not None:
        saved.update(tau=tau, noise=noise, scale=scale, probs=probs, y=h, experts=gate_out[1], weights=gate_out[2],
                     mix=mix)
    return features, gate_out


# The single network's gate: run_gate at R = 1, plus what only a single network does (draw its
# noise from torch's global generator, take any temperature, return a RoutingSample to replay).
class GateOutput(NamedTuple):
    features: torch.Tensor  # (B, hidden) gate-weighted mix of expert features
    probs: torch.Tensor  # (B, E) router probabilities g (noisy while sampling)
    experts: torch.Tensor  # (B, k) selected experts
    weights: torch.Tensor  # (B, k) mixing weights of the selected experts
    load_balance: torch.Tensor | None  # scalar E * sum_i f_i P_i (None when not requested)
    routing: RoutingSample  # what to store to replay this pass


def single_member_params(module: nn.Module) -> dict:
    """{parameter name: (1, *shape) view}: one network as a population of one (gradients flow back)."""
    return {name: p.unsqueeze(0) for name, p in module.named_parameters()}


def load_balance_loss(probs: torch.Tensor, experts: torch.Tensor, n_experts: int) -> torch.Tensor:
    """The Switch balance loss of one network: probs (B, E), experts (B, k) -> scalar (run_load_balance at R = 1)."""
    return run_load_balance(probs.reshape(1, -1, n_experts), experts.reshape(1, -1, experts.shape[-1]), n_experts)[0]


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
    """Router (+ noise gate for learned noise) over an ExpertBank of E trunks: dense softmax mixing
    of every expert (sparse=False, the MoE baseline) or top-k gating (sparse=True)."""

    def __init__(self, in_dim: int, cfg, sparse: bool):
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
        self.experts = ExpertBank(in_dim, cfg.hidden, cfg.n_experts, cfg.expert_impl, cfg.gain_hidden,
                                  cfg.masked_min_batch)

    def gating_modules(self) -> list:
        return [m for m in (self.router, self.noise_gate) if m is not None]

    def forward(self, x, temperature=None, routing: RoutingSample | None = None, deterministic_gate: bool = False,
                with_aux: bool = True):
        """x (B, in_dim) -> GateOutput; `routing` replays stored draws; with_aux=False: no balance loss."""
        batch, n_exp = x.shape[0], self.n_experts
        if temperature is None:
            temperature = routing.temperature if routing is not None else 1.0
        tau = _temperature_column(temperature, batch, x)
        replay = None
        if routing is not None:
            noise = routing.noise.reshape(batch, n_exp).to(x.dtype)
            if self.sparse:
                replay = routing.experts.reshape(1, batch, self.k).long()
        elif self.noisy and not deterministic_gate:
            # the population's routing-noise draw (appendix 05b), from torch's global generator, with the
            # config's sigma (the trainer passes the annealed sigma to the population)
            noise = draw_routing_noise(self.noise, batch, n_exp, self.noise_std, dtype=x.dtype, device=x.device)
        else:
            noise = x.new_zeros(batch, n_exp)
        features, (probs, experts, weights) = run_gate(single_member_params(self), "", x.unsqueeze(0), tau.unsqueeze(0),
                                                       noise.unsqueeze(0), replay, self, self.experts.selected_mixer(x))
        probs, weights = probs[0], weights[0]
        if experts is None:  # dense mixing: every expert, in order; the balance loss counts each row's top one
            experts, counted = torch.arange(n_exp, device=x.device).expand(batch, n_exp), probs.argmax(-1, keepdim=True)
        else:
            experts = counted = experts[0]
        lb = load_balance_loss(probs, counted, n_exp) if with_aux else None
        return GateOutput(features[0], probs, experts, weights, lb, RoutingSample(noise, experts, tau))


# %% [markdown]
# ## Check: the single gate is the population's gate at R = 1
#
# A gate of three experts, top-1, no noise: the mixing weight of the kept expert is exactly 1 with
# the kept probability's gradient, the features `GatedExperts` returns are `run_gate`'s on the
# network's own parameters read as a population of one, and the balance loss of uniform routing
# is 1.

# %%
from types import SimpleNamespace

torch.manual_seed(seed)
kept = torch.tensor([[0.6]], requires_grad=True)
weight = topk_weights(kept, "straight_through")
weight.sum().backward()
assert weight.item() == 1.0 and kept.grad.item() == 1.0

config = SimpleNamespace(n_experts=3, top_k=1, routing_noise="off", top1_weight="straight_through", noise_std=1.0,
                         gain_router=0.01, hidden=8, expert_impl="stacked", gain_hidden=2 ** 0.5, masked_min_batch=512)
gate = GatedExperts(5, config, sparse=True)
x = torch.randn(7, 5)
out = gate(x)
features, (probs, experts, weights) = run_gate(single_member_params(gate), "", x.unsqueeze(0), torch.ones(1, 7),
                                              torch.zeros(1, 7, 3), None, gate)
assert torch.equal(out.features, features[0]) and torch.equal(out.experts, experts[0])
uniform = torch.full((6, 3), 1 / 3)
assert abs(load_balance_loss(uniform, torch.tensor([[0], [1], [2], [0], [1], [2]]), 3).item() - 1.0) < 1e-6
print("the single gate equals run_gate at R = 1; top-1 weight 1 with the kept probability's gradient")
