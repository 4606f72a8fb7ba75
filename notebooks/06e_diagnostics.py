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
# # 06e · Appendix: the plasticity diagnostics
#
# The paper reads plasticity off the rank of the expert features and the fraction of dormant
# units, and plots the routers' expert probabilities and the mean action around phase switches.
# This appendix holds those measurements, in the module `pemamoe.diagnostics`; the trainer of
# notebook 07 logs them on a fixed probe batch, and notebook 06b shows them around one switch.

# %%
#| default_exp diagnostics

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## Plasticity diagnostics
#
# The paper reads plasticity off two signals, the rank of the expert features and the fraction
# of dormant units, and it plots the routers' expert probabilities and the mean action around the
# switches. All are computed on a **fixed probe batch** (the same observations every time), so a
# change in a curve is a change in the network, not in the data.
#
# **Feature rank.** For expert $j$, stack its last hidden layer (post-ReLU, the 32 features it
# hands to the head) over the $B$ probe observations into $A \in \mathbb R^{B\times 32}$, with
# singular values $\sigma_1 \ge \sigma_2 \ge \dots$. Every expert sees every probe row, whether or
# not the router would pick it, so that the rank measures what the expert *can* represent. Three
# summaries:
#
# * stable rank $\|A\|_F^2 / \|A\|_2^2 = \sum_i \sigma_i^2 / \sigma_1^2$: smooth, dominated by the
#   largest directions;
# * effective rank (Roy & Vetterli, 2007) $\exp\big(-\sum_i p_i \log p_i\big)$ with
#   $p_i = \sigma_i / \sum_k \sigma_k$;
# * $\mathrm{srank}_\delta$ (Kumar et al., 2021): the smallest $k$ with
#   $\sum_{i\le k}\sigma_i \ge (1-\delta)\sum_i \sigma_i$, $\delta = 0.01$.
#
# All three equal $n$ for an $n\times n$ identity and 1 for a rank-one matrix (for srank with
# $\delta = 0.01$, the identity reaches $n$ only while $n < 100$: beyond, dropping one of $n$ equal
# values keeps 99 % of the sum). A zero matrix gets rank 0. The features are not centred.
#
# **Dormant units.** Two definitions, per layer of each expert:
#
# * *the paper's DNF*: unit $u$ is dormant when its mean absolute **pre-activation** over the
#   batch is below a small $\delta$. The paper gives no $\delta$; we use $\delta = 0.01$, about 1 %
#   of a typical pre-activation at initialisation. Note what this does and does not catch: a unit
#   whose pre-activation sits near zero for every input, yes; a ReLU unit that is "dead" because its
#   pre-activation is strongly *negative* for every input, no (its mean $|a|$ is large). So the
#   paper's DNF is a measure of collapsed units rather than of dead ReLUs.
# * *the $\tau$-dormant score* (Sokar et al., 2023), on the **post-activation** $h_u$:
#   $s_u = \mathbb E|h_u| \,/\, \big(\tfrac1d\sum_k \mathbb E|h_k|\big)$, dormant when
#   $s_u \le \tau = 0.025$. A dead ReLU has $s_u = 0$ and counts; the score is scale-free. A layer
#   whose units are all silent counts as fully dormant.
#
# **Routers and actions.** Mean router probability per expert over the probe batch (noiseless
# gating), for the policy router and, given probe global states, for the value router; also the
# share of probe rows whose top choice is each expert. The MLP has one "expert" with probability 1.
# The mean action is the policy mean $\mu(o)$ averaged over the probe batch (before the
# environment clips actions to $[-1,1]$), per coordinate, with the policy's standard deviation
# beside it.

# %%
#| export
import math

import numpy as np
import torch

DORMANT_PAPER_DELTA = 0.01
DORMANT_TAU = 0.025
SRANK_DELTA = 0.01
_AXES = ("x", "y", "z")


def singular_values(a) -> np.ndarray:
    """Singular values (descending, float64) of a 2-D matrix (tensor or array)."""
    if isinstance(a, torch.Tensor):
        a = a.detach().cpu().double().numpy()
    a = np.asarray(a, dtype=float)
    if a.ndim != 2:
        raise ValueError(f"rank measures need a 2-D matrix (batch, features), got shape {a.shape}")
    return np.linalg.svd(a, compute_uv=False)


def stable_rank(a) -> float:
    """||A||_F^2 / ||A||_2^2 (0 for a zero matrix)."""
    s = singular_values(a)
    return 0.0 if s.size == 0 or s[0] == 0 else float(np.sum(s**2) / s[0] ** 2)


def effective_rank(a) -> float:
    """Roy & Vetterli: exp of the entropy of the normalised singular values (0 for a zero matrix)."""
    s = singular_values(a)
    total = s.sum()
    if total == 0:
        return 0.0
    p = s[s > 0] / total
    return float(np.exp(-np.sum(p * np.log(p))))


def srank(a, delta: float = SRANK_DELTA) -> int:
    """Kumar et al.: smallest k with sum of the top-k singular values >= (1 - delta) * their total."""
    if not 0 <= delta < 1:
        raise ValueError(f"srank delta must be in [0, 1), got {delta!r}")
    s = singular_values(a)
    total = s.sum()
    if total == 0:
        return 0
    cum = np.cumsum(s)
    return int(np.searchsorted(cum, (1 - delta) * total * (1 - 1e-12)) + 1)


def dormant_fraction_paper(preact, delta: float = DORMANT_PAPER_DELTA) -> float:
    """The paper's DNF: share of units whose mean |pre-activation| over the batch is < delta. preact (B, d)."""
    m = torch.as_tensor(preact).abs().double().mean(0)
    return float((m < delta).double().mean())


def dormant_fraction_tau(act, tau: float = DORMANT_TAU) -> float:
    """Sokar et al.: share of units with E|h_u| / mean_k E|h_k| <= tau. act (B, d) post-activation."""
    m = torch.as_tensor(act).abs().double().mean(0)
    layer_mean = m.mean()
    if layer_mean == 0:
        return 1.0
    return float((m / layer_mean <= tau).double().mean())


def _axis(i: int, n: int) -> str:
    return _AXES[i] if n <= len(_AXES) else str(i)


@torch.no_grad()
def plasticity_diagnostics(actor, critic=None, probe_obs=None, probe_state=None, temperature=None) -> dict:
    """Flat {name: float} of rank, dormant, router and action statistics on fixed probe batches.

    probe_obs (B, obs_dim) for the actor; probe_state (B, state_dim) for the value router (optional).
    Names: rank/{stable,effective,srank}/expert{j} and /mean; dormant/{paper,tau}/expert{j}/layer{l},
    /layer{l} (mean over experts) and /mean; router/policy/p{j}, router/policy/top{j};
    router/value/p{j}, router/value/top{j}; action/mean_{x,y}, action/std_{x,y}.
    """
    if probe_obs is None:
        raise ValueError("plasticity_diagnostics needs probe_obs")
    out = {}
    probe = actor.probe(probe_obs, temperature)
    acts, pres = probe["act"], probe["preact"]  # per layer (E, B, hidden)
    n_exp, n_layers = acts[0].shape[0], len(acts)
    for name, fn in (("stable", stable_rank), ("effective", effective_rank), ("srank", srank)):
        vals = [float(fn(acts[-1][j])) for j in range(n_exp)]
        for j, v in enumerate(vals):
            out[f"rank/{name}/expert{j}"] = v
        out[f"rank/{name}/mean"] = float(np.mean(vals))
    for name, fn, layers in (("paper", dormant_fraction_paper, pres), ("tau", dormant_fraction_tau, acts)):
        per = np.array([[fn(layers[l][j]) for l in range(n_layers)] for j in range(n_exp)])
        for j in range(n_exp):
            for l in range(n_layers):
                out[f"dormant/{name}/expert{j}/layer{l + 1}"] = float(per[j, l])
        for l in range(n_layers):
            out[f"dormant/{name}/layer{l + 1}"] = float(per[:, l].mean())
        out[f"dormant/{name}/mean"] = float(per.mean())
    _router_stats(out, "policy", probe["router_probs"], n_exp)
    if critic is not None and probe_state is not None:
        _, aux = critic(probe_state, temperature, None, deterministic_gate=True)
        _router_stats(out, "value", aux["router_probs"], 1 if aux["router_probs"] is None else aux["router_probs"].shape[-1])
    mean = probe["mean"].reshape(-1, probe["mean"].shape[-1])
    std = actor.log_std.exp()
    for i in range(mean.shape[-1]):
        out[f"action/mean_{_axis(i, mean.shape[-1])}"] = float(mean[:, i].mean())
        out[f"action/std_{_axis(i, mean.shape[-1])}"] = float(std[i])
    return out


def _router_stats(out: dict, which: str, probs, n_exp: int) -> None:
    if probs is None:  # MLP: a single "expert" takes every row
        out[f"router/{which}/p0"] = 1.0
        out[f"router/{which}/top0"] = 1.0
        return
    probs = probs.reshape(-1, probs.shape[-1]).double()
    mean = probs.mean(0)
    top = torch.bincount(probs.argmax(-1), minlength=n_exp).double() / probs.shape[0]
    for j in range(n_exp):
        out[f"router/{which}/p{j}"] = float(mean[j])
        out[f"router/{which}/top{j}"] = float(top[j])


# %% [markdown]
# Hand checks of the rank measures and dormant fractions against the statements above: an identity
# has every rank equal to its size, a rank-one matrix 1, a zero matrix 0; a unit whose
# pre-activation is strongly negative is not dormant for the paper's DNF but is for the
# $\tau$-dormant score.

# %%
from pemamoe import diagnostics as dg

eye, one = np.eye(8), np.outer(np.arange(1.0, 7.0), np.ones(5))
for f in (dg.stable_rank, dg.effective_rank, dg.srank):
    assert math.isclose(f(eye), 8) and math.isclose(f(one), 1) and f(np.zeros((4, 3))) == 0
pre = torch.tensor([[-5.0, 1.0], [-4.0, 2.0]])  # unit 0: dead ReLU (always negative)
print("dead ReLU unit -> paper DNF", dg.dormant_fraction_paper(pre), " tau-dormant", dg.dormant_fraction_tau(pre.relu()))
assert dg.dormant_fraction_paper(pre) == 0.0 and dg.dormant_fraction_tau(pre.relu()) == 0.5


# %% [markdown]
# ## Every network kind
#
# The diagnostics return the same kind of keys for every network kind (the MLP as a single expert).

# %%
from pemamoe.nets import NETWORKS, make_actor, make_critic

obs_dim, state_dim, n_probe = 24, 32, 256
g = torch.Generator().manual_seed(seed)
probe_obs, probe_state = torch.randn(n_probe, obs_dim, generator=g), torch.randn(n_probe, state_dim, generator=g)

from pemamoe.nets import NETWORKS

for kind in NETWORKS:
    a, c = make_actor(kind, obs_dim), make_critic(kind, state_dim)
    d = dg.plasticity_diagnostics(a, c, probe_obs, probe_state)
    print(f"{kind:8s} {len(d):3d} metrics  stable rank {d['rank/stable/mean']:.2f}  effective {d['rank/effective/mean']:.2f}"
          f"  srank {d['rank/srank/mean']:.1f}  dormant(paper) {d['dormant/paper/mean']:.3f}  dormant(tau) {d['dormant/tau/mean']:.3f}")
