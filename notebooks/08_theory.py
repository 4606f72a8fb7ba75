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
# # 08 · What the theory section predicts, and what can be seen of it (paper section V)
#
# Section V of the paper states a dynamic-regret bound for PE-MAMoE of the shape
#
# $$\mathrm{DynRegret}_T \;\lesssim\; T^{3/4} V_T^{1/4} \;+\; \sqrt{\textstyle\sum_t \gamma_t^2} \;+\; \text{(critic error)},$$
#
# built from three ingredients: a drift term governed by the variation budget $V_T$ (how far the
# per-phase optimum moves in total), a noise term governed by the **noise energy**
# $\sum_t \gamma_t^2$ of the switch-aware perturbation, and a Lipschitz assumption (A4) saying
# that a small change of the router or of one expert changes the action distribution by a
# proportionally small amount in $L_1$. None of the constants is given, and the argument leans on
# outside results (trust-region bounds, non-stationary MDP bounds) whose conditions are not
# checked for this architecture. A bound with unknown constants cannot be confirmed by experiment,
# but each of its *scalings* can be measured on a problem small enough to run in seconds. This
# notebook does that, and reports honestly where the measurements agree and where they do not.
#
# 1. **Noise energy.** The pulse schedule's energy identity, then how far a noisy run drifts from
#    its noise-free twin (same seed) as the amplitude $\gamma$, the window $N$ and the number of
#    switches $K$ vary, with the real actor and the real phase controller.
# 2. **Routing stability (A4).** Random perturbations of the router and of the experts of a
#    trained PE-MAMoE actor, the exact $L_1$ distance between the action distributions before and
#    after (Monte Carlo), and the smallest Lipschitz constants that explain the samples, including
#    at routing ties, where hard top-1 selection breaks the assumption.
# 3. **Dynamic regret.** A contextual tracking problem with a hidden, switching optimum known in
#    closed form, learned by a compact PPO loop; the measured growth of the regret in $T$, in
#    $V_T$ and in the noise energy, with fitted exponents and bootstrap intervals.
#
# The quantities the claims are about, the noise schedule with its energy and the dynamic regret,
# are defined here and exported to `pemamoe/theory.py`. The instruments that measure them (the
# tracking task's code, the learner and its paired runs, the fits of exponents, the $L_1$ distances
# between action distributions, the Lipschitz estimates and the probes of the actor) live in the
# appendix notebook `08b_toy_tracking.py` (module `pemamoe.toy_tracking`), each checked there on a
# case with a known answer; this notebook only calls them. The records (below) are appendix 08c's.
#
# **Where the numbers come from.** The three experiments are computed once and kept as records,
# like the training runs of notebook 09: `records/<scale>/theory/`, one per section (`noise`,
# `routing`, `regret`), each carrying the parameters that produced it. The notebook reads a record
# whose parameters are its own and computes one otherwise (and then writes it); the committed
# records are those of `medium`, which in this notebook has the sizes of `small`, so at either
# scale `make figures` trains nothing here. To compute them again, run the notebook with
# `retrain=True` (`python -m pemamoe figures --scale medium --notebook 08_theory --retrain`,
# about eight minutes on two cores) and commit the rewritten records. Computing is not
# reproducible across processors, while reading a record is: appendix 08c explains why, and
# describes the records.

# %%
#| default_exp theory

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0
records_dir = "records"
retrain = False  # True: ignore the theory records, compute every experiment again and rewrite its record

# %%
#| export
import math

import numpy as np

# %%
import time

import matplotlib.pyplot as plt
import pandas as pd
import torch

from pemamoe.core import by_scale, repo_path, save_figure, write_table
from pemamoe.theory_records import round_reported, theory_parameters, theory_record
from pemamoe.toy_tracking import (
    DISTRIBUTIONS,
    TrackerConfig,
    TrackingProblemConfig,
    fit_power_law,
    lipschitz_envelope,
    lipschitz_nnls,
    lipschitz_ratio,
    moe_components,
    paired_distance,
    routing_stability_samples,
    run_many,
    tie_states,
    top1_win_probs,
)

torch.set_num_threads(1)
T0 = time.perf_counter()
records_root = repo_path(records_dir)

# %% [markdown]
# ## 1 · Noise energy
#
# ### The schedule and its energy
#
# Section IV-B switches the expert noise on at a constant amplitude $\gamma$ for $N$ update epochs
# after each phase switch, and off otherwise. Over a run with $K$ switches the energy
# $\sum_t \gamma_t^2$ is therefore $\gamma^2$ times the number of epochs covered by some window. If
# the $K$ windows are disjoint and all end before the run does, that number is $KN$ and the
# energy is $\gamma^2 K N$, the quantity in the noise-energy lemma.
#
# Two situations break the product form, and the code below makes a choice for each:
#
# * **Overlapping windows** (two switches less than $N$ epochs apart). The amplitude is a level,
#   not a count: a second switch inside a running window restarts the window (this is what the
#   phase controller of notebook 06 does, it resets its counter to $N$), so an epoch covered by two
#   windows still gets $\gamma$, not $2\gamma$. The energy is $\gamma^2\,|\bigcup_k W_k|$, strictly
#   less than $\gamma^2 K N$.
# * **A window cut by the end of the run** contributes only its epochs before $T$.
#
# In both cases $\gamma^2 KN$ remains an upper bound, which is all the lemma needs.
#
# `noise_energy` sums the squares with `math.fsum`, which rounds the exact sum once; since
# $\gamma^2\cdot(KN)$ with an integer $KN$ is also rounded once, the identity holds bit for bit.

# %%
#| export
def _int_ok(v, low=0):
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= low


def window_coverage(T: int, switch_times, window: int) -> np.ndarray:
    """Boolean (T,) mask: epoch t lies in [t_s, t_s + window) for at least one switch t_s."""
    if not _int_ok(T):
        raise ValueError(f"noise_schedule T must be an int >= 0, got {T!r}")
    if not _int_ok(window):
        raise ValueError(f"noise_schedule window must be an int >= 0, got {window!r}")
    starts = np.asarray(list(switch_times), dtype=np.int64).reshape(-1)
    if starts.size and (starts.min() < 0):
        raise ValueError(f"noise_schedule switch_times must be >= 0, got {starts.tolist()}")
    starts = starts[starts < T]
    edges = np.zeros(T + 1, dtype=np.int64)
    np.add.at(edges, starts, 1)
    np.add.at(edges, np.minimum(starts + window, T), -1)
    return np.cumsum(edges)[:T] > 0


def noise_schedule(T: int, switch_times, gamma: float, window: int) -> np.ndarray:
    """gamma_t for t = 0..T-1 (shape (T,)): gamma inside the window of any switch, else 0.

    Overlapping windows merge (the amplitude is a level, not a count); windows are cut at T.
    """
    if not (isinstance(gamma, (int, float)) and not isinstance(gamma, bool) and math.isfinite(gamma) and gamma >= 0):
        raise ValueError(f"noise_schedule gamma must be a finite float >= 0, got {gamma!r}")
    return np.where(window_coverage(T, switch_times, window), float(gamma), 0.0)


def noise_energy(schedule) -> float:
    """Cumulative noise energy sum_t gamma_t^2, correctly rounded (math.fsum)."""
    g = np.asarray(schedule, dtype=float).reshape(-1)
    return math.fsum((g * g).tolist())

# %%
sched = noise_schedule(100, [10, 50, 70], 0.005, 15)
print("disjoint windows:  energy", noise_energy(sched), " gamma^2 K N =", 0.005**2 * (3 * 15))
sched = noise_schedule(100, [10, 20, 90], 0.005, 15)
print("overlap + cut:     energy", noise_energy(sched), " = gamma^2 *", int(window_coverage(100, [10, 20, 90], 15).sum()),
      "covered epochs < gamma^2 K N =", 0.005**2 * 45)

# %% [markdown]
# ### A phase-switching problem with a known optimum
#
# To see what the noise does to learning we need a learner, a problem, and an exact measure of
# how good a policy is. The problem is a **contextual tracking task**: at every step a context
# $x \sim \mathcal N(0, I_d)$ arrives, the agent answers with an action $a \in \mathbb R^m$, and
# the reward is
#
# $$ r(x, a) = -\big\| \mathrm{clip}(a) - (A_\phi x + b_\phi) \big\|^2 ,$$
#
# where $\mathrm{clip}$ clips each coordinate to $[-1, 1]$ (the action box of the UAV actor) and
# the phase $\phi$ is **hidden** from the agent, as a regime switch is when it first happens. For a
# given $x$ the best action is $\mathrm{clip}(A_\phi x + b_\phi)$, so the optimal value $V^*_\phi$
# and the value of any deterministic policy are expectations of closed-form quantities; we
# evaluate them on a fixed probe set of contexts, the same for every run (common random numbers).
#
# Successive phases differ by a step of exactly `shift` in the stacked matrix $W = [A \mid b]$:
# because $\mathbb E[xx^\top] = I$, that is also the root-mean-square distance between the two
# optimal action maps (before clipping). The **variation budget** of a run with $K$ switches is
# therefore $V_T = K\cdot\text{shift}$: the path length of the optimum. Each step is taken in a
# random direction pulled towards the origin, so the optimum stays near the box.
#
# We value the learner's *mean* action (deterministic gating, as at evaluation): exploration noise
# of the Gaussian policy would add a constant $\sum_i \sigma_i^2$ per step that has nothing to do
# with tracking.
#
# The task's code (`TrackingProblemConfig`, `TrackingProblem`) is in appendix 08b. The quantity
# it serves is defined here: the cumulative dynamic regret of a run against the moving optimum.

# %%
#| export
def dynamic_regret(optimal_values, values) -> np.ndarray:
    """Cumulative dynamic regret R_t = sum_{s <= t} (V*_{phi(s)} - V(pi_s)), shape (T,)."""
    opt = np.asarray(optimal_values, dtype=float)
    val = np.asarray(values, dtype=float)
    if opt.shape != val.shape:
        raise ValueError(f"dynamic_regret: shapes differ, {opt.shape} vs {val.shape}")
    return np.cumsum(opt - val)

# %% [markdown]
# ### The learner: the real actor, a compact PPO loop, the real noise injection
#
# `run_tracker` trains an actor from `pemamoe.nets` (MLP, SMoE or PE-MAMoE) with a PPO-clip
# update. Each iteration draws a batch of contexts and answers each with an **antithetic pair**
# of actions $\mu \pm \sigma\varepsilon$ sampled under the *same* routing; half the reward
# difference is an unbiased advantage that needs no critic (the critic-error term of the theorem
# is then zero by construction). The stored routing is replayed in the update, as in notebook 07.
#
# The noise comes from the phase controller the experiments run, `PhaseController` of notebook 06,
# on the actor as a population of one run and configured with **only** noise injection switched
# on: every other switch-time mechanism (KL anchor, LR drop, router freeze, temperature, resets)
# is off, so that a noisy run and its noise-free twin differ in the noise and in nothing else. The
# controller perturbs every expert with $\gamma$ at the switch itself and then, after each of the
# next $N$ update epochs, each expert with $\gamma$ times its share of the epoch's routing slots:
# $N + 1$ pulses per switch, not $N$. We record every pulse with its amplitude, the RMS of the noise
# std over the trunk's scalars: $\gamma$ at the switch and after every epoch for the MLP (one
# expert, always used); after an epoch of a three-expert actor between $\gamma/3$ (even use) and
# $\gamma/\sqrt 3$ (one expert takes every slot). The fits use the **realised** energy, the sum of
# the squared amplitudes: $\gamma^2 K (N+1)$ for the MLP, less for the gated actors.
#
# Randomness is arranged for pairing: the context and action draws use the global torch
# generator seeded by `seed`, while the noise has the controller's own generator. A noisy run
# consumes exactly the same stream of context and sampling noise as its twin, so every
# difference between them is caused by the perturbations.
#
# `run_tracker` (one run), `run_many` (a list of runs, in worker processes when asked) and
# `paired_distance` (a noisy run against its twin) are in appendix 08b.

# %% [markdown]
# ### Fitting exponents
#
# Every scaling below is read off a log-log regression, $\log y = c + \sum_j \alpha_j \log x_j$
# (`fit_power_law`, appendix 08b).
# The intervals are percentile bootstrap intervals: the rows (runs) are resampled with
# replacement, or whole groups (e.g. all runs of one seed) when `groups` is given, and the fit is
# repeated. They quantify the sampling spread of the slope on *these* runs; they say nothing
# about the asymptotic regime a bound refers to.

# %% [markdown]
# ### Noise energy against drift, on paired runs
#
# Three sweeps around a reference point ($\gamma = 0.01$, $N = 30$ epochs, $K = 3$ switches):
# the amplitude $\gamma$ alone, the window $N$ alone, and the number of switches $K$ alone. For
# each setting and seed, a noisy run and its noise-free twin are compared on three distances:
# the probe-set $L_2$ distance of the mean actions (averaged over training), the signed
# cumulative return gap $|\sum_t (J_t^{\text{noisy}} - J_t^{\text{clean}})|$ (the martingale sum
# of the noise-energy lemma, with the twin standing in for the conditional mean), and the
# unsigned $\sum_t |J_t^{\text{noisy}} - J_t^{\text{clean}}|$. The lemma says the return gap grows
# no faster than $\sqrt{\sum_t\gamma_t^2}$: slope at most 1 on a log-log plot against
# $\sqrt{\text{energy}}$.

# %%
NOISE_T = by_scale(scale, ci=120, small=200, paper=400)
NOISE_SEEDS = by_scale(scale, ci=2, small=3, paper=6)
WORKERS = by_scale(scale, ci=1, small=2, paper=2)
REF = dict(gamma=0.01, window=30, K=3)
GAMMAS = by_scale(scale, ci=[0.005, 0.02], small=[0.0025, 0.005, 0.01, 0.02, 0.04], paper=[0.0025, 0.005, 0.01, 0.02, 0.04, 0.08])
WINDOWS = by_scale(scale, ci=[10, 30], small=[8, 15, 30, 60], paper=[4, 8, 15, 30, 60])
KS = by_scale(scale, ci=[1, 3], small=[1, 2, 3, 5], paper=[1, 2, 3, 5, 8])
BATCH = by_scale(scale, ci=32, small=64, paper=64)

noise_settings = {}
for g in GAMMAS:
    noise_settings.setdefault((g, REF["window"], REF["K"]), set()).add("gamma")
for n in WINDOWS:
    noise_settings.setdefault((REF["gamma"], n, REF["K"]), set()).add("window N")
for k in KS:
    noise_settings.setdefault((REF["gamma"], REF["window"], k), set()).add("switches K")
Kmax = max(k for _, _, k in noise_settings)
noise_problem = TrackingProblemConfig(n_phases=Kmax + 1)


def tcfg(**kw):
    return TrackerConfig(batch=BATCH, **kw)


# the same gamma sweep with the MLP actor (no routing), to see what top-1 routing adds
settings_by_kind = {("pemamoe", key): sw for key, sw in noise_settings.items()}
settings_by_kind.update({("mlp", (g, REF["window"], REF["K"])): {"gamma (mlp)"} for g in GAMMAS})
jobs, keys = [], []
for kind, k in sorted({(kind, key[2]) for kind, key in settings_by_kind}):
    for s in range(NOISE_SEEDS):
        jobs.append((noise_problem, tcfg(kind=kind, iterations=NOISE_T, n_switches=k, controller="off"), seed, seed + s, False))
        keys.append((kind, "clean", k, s))
for kind, (g, n, k) in settings_by_kind:
    for s in range(NOISE_SEEDS):
        jobs.append((noise_problem, tcfg(kind=kind, iterations=NOISE_T, n_switches=k, noise_gamma=g, noise_epochs=n), seed, seed + s, False))
        keys.append((kind, (g, n, k), k, s))


def compute_noise():
    """The paired runs: one row per (setting, seed), noisy run against its twin; and the reference
    distances between clean runs of different seeds."""
    t_start = time.perf_counter()
    runs = dict(zip(keys, run_many(jobs, WORKERS)))
    print(f"{len(jobs)} runs of {NOISE_T} iterations in {time.perf_counter() - t_start:.1f} s")
    rows = []
    for (kind, (g, n, k)), sweeps in settings_by_kind.items():
        for s in range(NOISE_SEEDS):
            clean, noisy = runs[(kind, "clean", k, s)], runs[(kind, (g, n, k), k, s)]
            d = paired_distance(clean, noisy)
            rows.append({"kind": kind, "gamma": g, "window": n, "K": k, "seed": s, "sweeps": "+".join(sorted(sweeps)),
                         "schedule_matches": bool(np.array_equal(noisy.noise_slots() > 0, window_coverage(
                             NOISE_T * 2 + 1, [2 * t for t in noisy.switches], n + 1))),
                         "clean_regret": clean.total_regret, **d})
    # Reference level: how far two noise-free runs with *different* seeds are from each other.
    ref = []
    for kind in ("pemamoe", "mlp"):
        for s in range(1, NOISE_SEEDS):
            a, b = runs[(kind, "clean", REF["K"], 0)], runs[(kind, "clean", REF["K"], s)]
            ref.append({"kind": kind, "seed_pair": f"0-{s}", **paired_distance(a, b)})
    return {"pairs": pd.DataFrame(rows), "seed_pairs": pd.DataFrame(ref)}, {"runs": len(jobs)}


noise_parameters = theory_parameters(dict(NOISE_T=NOISE_T, NOISE_SEEDS=NOISE_SEEDS, REF=REF, GAMMAS=GAMMAS, WINDOWS=WINDOWS,
                                          KS=KS, BATCH=BATCH, seed=seed), jobs)
noise_tables, _ = theory_record(records_root, scale, "noise", noise_parameters, compute_noise, retrain)
noise_df, ref = noise_tables["pairs"], noise_tables["seed_pairs"]
full = noise_df["gamma"] ** 2 * noise_df["K"] * (noise_df["window"] + 1)
mlp_rows = noise_df["kind"] == "mlp"
assert np.allclose(noise_df.loc[mlp_rows, "energy"], full[mlp_rows]) and (noise_df["energy"] <= full * (1 + 1e-12)).all()
assert noise_df["schedule_matches"].all()
print("pulses in exactly the slots of noise_schedule(window N+1) in every run; energy = gamma^2 K (N+1) for the MLP,",
      f"{(noise_df.energy / full)[~mlp_rows].mean():.2f} of it (mean) for PE-MAMoE")
noise_df.groupby(["kind", "gamma", "window", "K"])[["energy", "policy_mean", "return_gap", "return_abs", "excess_regret"]].mean()

# %%
# Reference level: how far two noise-free runs with *different* seeds are from each other.
print("seed-to-seed distance of clean runs (mean):", ref.groupby("kind")[["policy_mean", "policy_final", "return_abs"]].mean().round(4).to_dict("index"))
print("noisy-vs-twin distance at the largest gamma (mean):",
      noise_df[noise_df.gamma == max(GAMMAS)].groupby("kind")[["policy_mean", "policy_final", "return_abs"]].mean().round(4).to_dict("index"))

# %% [markdown]
# The check above also confirms the bookkeeping: counting the controller's pulses on a grid of
# *pulse slots* (the start of each iteration, where the switch pulse lands, and the end of each
# update epoch), the realised noise fills exactly the window of $N + 1$ slots of `noise_schedule`,
# opened at slot $2t$ for a switch at iteration $t$ (two update epochs per iteration here), and
# for the MLP it is `noise_schedule` itself, amplitude included.

# %%
rng_fit = np.random.default_rng(seed)
noise_fit_rows = []
root_e = np.sqrt(noise_df["energy"].to_numpy())
for metric in ("policy_mean", "policy_final", "return_gap", "return_abs"):
    for sweep in ("all", "gamma", "window N", "switches K", "gamma (mlp)"):
        pe = (noise_df["kind"] == "pemamoe").to_numpy()
        if sweep == "all":
            sel = pe
        elif sweep == "gamma (mlp)":
            sel = ~pe
        else:
            sel = pe & noise_df["sweeps"].str.split("+").apply(lambda v: sweep in v).to_numpy()
        yv = noise_df[metric].to_numpy()[sel]
        xv = root_e[sel]
        keep = yv > 0
        if keep.sum() < 3 or len(np.unique(xv[keep])) < 2:
            continue
        f = fit_power_law(xv[keep], yv[keep], rng_fit, n_boot=1000)
        noise_fit_rows.append({"metric": metric, "sweep": "all (pemamoe)" if sweep == "all" else sweep, "slope": f["slope"], "ci_low": f["ci_low"],
                               "ci_high": f["ci_high"], "r2": f["r2"], "n": f["n"], "lemma_slope_at_most": 1.0})
noise_fit = round_reported(pd.DataFrame(noise_fit_rows))
write_table(noise_fit, "theory_noise_fit", figures_dir)
print(noise_fit.to_string(index=False, float_format=lambda v: f"{v:.3f}"))

# %%
fig, axes = plt.subplots(1, 2, figsize=(10, 4))
colors = {"gamma": "C0", "window N": "C1", "switches K": "C2", "gamma (mlp)": "0.5"}
for ax, metric, label in ((axes[0], "policy_mean", "mean probe distance of mean actions"),
                          (axes[1], "return_gap", r"$|\sum_t (J_t^{noisy} - J_t^{clean})|$")):
    for sweep, c in colors.items():
        sel = noise_df["sweeps"].str.split("+").apply(lambda v: sweep in v)
        ax.scatter(np.sqrt(noise_df.loc[sel, "energy"]), noise_df.loc[sel, metric].clip(lower=1e-8), s=14, c=c,
                   label=f"vary {sweep}" + ("" if "mlp" in sweep else " (pemamoe)"), alpha=0.7,
                   marker="x" if "mlp" in sweep else "o")
    f = noise_fit[(noise_fit.metric == metric) & (noise_fit.sweep == "all (pemamoe)")]
    if len(f):
        f = f.iloc[0]
        sel = (noise_df[metric] > 0) & (noise_df["kind"] == "pemamoe")
        xs = np.geomspace(root_e.min(), root_e.max(), 20)  # noqa: F841
        c0 = np.exp(np.mean(np.log(noise_df.loc[sel, metric]) - f.slope * np.log(np.sqrt(noise_df.loc[sel, "energy"]))))
        ax.plot(xs, c0 * xs ** f.slope, "k-", lw=1, label=f"fit slope {f.slope:.2f} [{f.ci_low:.2f}, {f.ci_high:.2f}]")
        c1 = np.exp(np.mean(np.log(noise_df.loc[sel, metric]) - np.log(np.sqrt(noise_df.loc[sel, "energy"]))))
        ax.plot(xs, c1 * xs, "k:", lw=1, label="slope 1 (lemma)")
    ax.set_xscale("log"), ax.set_yscale("log")
    ax.set_xlabel(r"$\sqrt{\sum_t \gamma_t^2}$ (realised)"), ax.set_ylabel(label)
    ax.legend(fontsize=7)
fig.suptitle("Noisy run vs its noise-free twin (same seed), PE-MAMoE actor")
fig.tight_layout()
save_figure(fig, "theory_noise_energy", figures_dir)
plt.show()

# %% [markdown]
# ![Noisy run against its noise-free twin, PE-MAMoE actor](../paper_figures/theory_noise_energy.png)

# %% [markdown]
# ## 2 · Routing stability (assumption A4)
#
# ### Which action distribution?
#
# A4 writes the policy as the gate-weighted mixture $\sum_k G_k(s)\,\pi_{\theta_k}(\cdot\mid s)$.
# The PE-MAMoE actor of notebook 05 (noisy top-1 gating, one shared linear head, a
# state-independent $\sigma$) has expert means $\mu_k(s) = \text{head}(h_k(s))$ and can be read as
# three different distributions, and we measure all three, because they behave differently:
#
# * **A4 mixture**: $\sum_k g_k(s)\,\mathcal N(\mu_k(s), \sigma^2)$ with $g$ the noiseless softmax of
#   the tempered router logits. This is the paper's formal object. It is not what the network
#   samples.
# * **Sampling marginal**: what the actor *does* sample. A top-1 pass picks expert $k$ when
#   $z_k + \varepsilon_k\,\mathrm{softplus}(n_k(s))$ is the largest noisy logit and then acts with
#   $\mathcal N(\mu_k, \sigma^2)$ (the top-1 weight is exactly 1). Averaged over the gating
#   noise, the action distribution is the mixture $\sum_k p_k(s)\,\mathcal N(\mu_k, \sigma^2)$,
#   with $p_k$ the probability that $k$ wins. We compute $p_k$ by Gauss-Hermite quadrature of
#   $\int \varphi(u) \prod_{j \ne k} \Phi\big((z_k + s_k u - z_j)/s_j\big)\,du$ and check it against
#   the actor's own routing frequencies.
# * **Evaluation top-1**: deterministic gating, $\mathcal N(\mu_{k^*(s)}, \sigma^2)$ with
#   $k^* = \arg\max_k g_k(s)$. This is the policy that is deployed, and it jumps when the argmax
#   changes.
#
# (The dense MoE baseline is different again: it averages *features*, so its action distribution
# is one Gaussian with mean $\sum_k g_k\mu_k$. We do not study it here.)
#
# For two mixtures with shared $\sigma$, the triangle inequality gives
# $\|\pi' - \pi\|_1 \le \|w' - w\|_1 + \sum_k w_k \|\mathcal N(\mu_k', \sigma^2) - \mathcal N(\mu_k, \sigma^2)\|_1$,
# where $w$ are the mixture weights: A4 holds with $L_G = 1$ *if the gate change is measured on the
# mixture weights themselves*. For the sampling marginal those weights are $p$, a smooth function of
# the router that moves more slowly than $g$ when the gating noise is large; for evaluation top-1
# they are a one-hot vector, which can jump by 2 while $g$ barely moves. The interesting question is
# thus A4 as written, with $\|\Delta G\| = \|\Delta g\|_1$, the change of the router's softmax.
#
# Every $L_1$ distance below is a Monte-Carlo estimate between Gaussian mixtures, with an error
# small relative to the distance itself (`mc_l1_distance`, checked against the closed form for two
# Gaussians in appendix 08b). `moe_components` reads the router logits, gating-noise scales and
# expert means off the actor; `perturb_actor` moves the router and/or the experts by random
# directions of a given relative size; `tie_states` finds states exactly on a top-1 boundary.

# %% [markdown]
# ### The actor under test
#
# A PE-MAMoE actor straight from initialisation has an almost flat router (gain 0.01), so every
# state is a near-tie. We use instead an actor **trained** on the tracking task for a few hundred
# iterations. Before perturbing anything, two checks that the three distributions are read
# correctly off the network: the evaluation-top-1 mean equals the actor's deterministic mean, and
# the quadrature win probabilities match the routing frequencies of the actor's own noisy gate.
#
# The cell below trains the actor, makes these checks and runs the perturbation sweep of the next
# subsection, or reads all of it from its record: the checks' numbers and one row per
# (perturbation, state, distribution) of the sweep.

# %%
RS_T = by_scale(scale, ci=150, small=400, paper=800)
rs_problem = TrackingProblemConfig(n_phases=4)
rs_job = (rs_problem, TrackerConfig(iterations=RS_T, n_switches=3, batch=BATCH, keep_means=False), seed, seed, True)
N_STATES = by_scale(scale, ci=128, small=384, paper=1024)
N_TIES = by_scale(scale, ci=32, small=96, paper=256)
N_REP = by_scale(scale, ci=4000, small=20000, paper=50000)
SCALES = by_scale(scale, ci=[1e-3, 1e-2, 1e-1], small=[1e-3, 3e-3, 1e-2, 3e-2, 1e-1], paper=[1e-3, 3e-3, 1e-2, 3e-2, 1e-1])
DRAWS = by_scale(scale, ci=1, small=2, paper=4)
MC_SAMPLES = by_scale(scale, ci=128, small=256, paper=512)


def compute_routing():
    """Train the actor; the checks of its three distributions; the perturbation sweep."""
    trained = run_many([rs_job])[0].actor
    rng_rs = np.random.default_rng(seed + 1)
    states = rng_rs.standard_normal((N_STATES, trained.obs_dim))
    ties = tie_states(trained, N_TIES, rng_rs)
    comp = moe_components(trained, states)
    with torch.no_grad():
        det_mean = trained(torch.tensor(states, dtype=torch.float32), deterministic_gate=True)[0].mean.double().numpy()
    top1_mean = comp["means"][np.arange(N_STATES), comp["gate"].argmax(-1)]
    xs_check = torch.tensor(np.repeat(states[:6], N_REP, 0), dtype=torch.float32)
    with torch.no_grad():
        _, routing = trained(xs_check)
    freq = np.stack([np.bincount(r, minlength=trained.gate.n_experts) for r in routing.experts.reshape(6, N_REP).numpy()]) / N_REP
    wp = top1_win_probs(comp["logits"][:6], comp["noise_scale"][:6])
    gt = np.sort(moe_components(trained, ties)["gate"], -1)
    gaps_all = np.diff(np.sort(comp["gate"], -1)[:, -2:], axis=-1)[:, 0]
    values = {
        "n_experts": trained.gate.n_experts, "top1_mean_diff": np.abs(det_mean - top1_mean).max(),
        "win_prob_diff": np.abs(freq - wp).max(), "logits_std": comp["logits"].std(0),
        "noise_scale_mean": comp["noise_scale"].mean(0), "gap_median": np.median(gaps_all),
        "gap_q05": np.quantile(gaps_all, 0.05), "tie_gap_max": np.max(gt[:, -1] - gt[:, -2]),
        "win_prob_mean": top1_win_probs(comp["logits"], comp["noise_scale"]).mean(0), "gate_mean": comp["gate"].mean(0),
    }
    parts = ["router", *[f"expert{k}" for k in range(trained.gate.n_experts)], "joint"]
    perturbations = [(part, sc) for part in parts for sc in SCALES for _ in range(DRAWS)]
    is_tie = np.r_[np.zeros(N_STATES, bool), np.ones(N_TIES, bool)]
    t_start = time.perf_counter()
    samples = routing_stability_samples(trained, np.concatenate([states, ties]), perturbations, rng_rs,
                                        n_samples=MC_SAMPLES, tie=is_tie)
    print(f"{len(samples)} samples in {time.perf_counter() - t_start:.1f} s")
    return {"samples": samples}, values


routing_parameters = theory_parameters(dict(RS_T=RS_T, BATCH=BATCH, N_STATES=N_STATES, N_TIES=N_TIES, N_REP=N_REP,
                                            SCALES=SCALES, DRAWS=DRAWS, MC_SAMPLES=MC_SAMPLES, seed=seed), [rs_job])
routing_tables, checks = theory_record(records_root, scale, "routing", routing_parameters, compute_routing, retrain)
rs = routing_tables["samples"]
print(f"eval top-1 mean vs actor deterministic mean: max |diff| = {checks['top1_mean_diff']:.2e}")
print(f"win probabilities: quadrature vs routing frequency, max |diff| = {checks['win_prob_diff']:.4f} "
      f"(sampling s.e. ~ {0.5 / math.sqrt(N_REP):.4f})")
print(f"router logits spread (std over states): {np.round(checks['logits_std'], 3)}, gating-noise scale: "
      f"{np.round(checks['noise_scale_mean'], 3)}")
print(f"top-2 softmax gap on random states: median {checks['gap_median']:.3f}, 5% {checks['gap_q05']:.4f}; "
      f"on tie states: max {checks['tie_gap_max']:.1e}")
print("mean win probabilities p (sampling marginal):", np.round(checks["win_prob_mean"], 3),
      " vs softmax g:", np.round(checks["gate_mean"], 3))

# %% [markdown]
# ### Perturbation sweep
#
# The router alone, each expert alone, and everything at once (joint), at relative scales from
# $10^{-3}$ to $10^{-1}$, on random states and on tie states. The constants are estimated from
# the **single-factor** perturbations on random states only: $L_G$ as the largest ratio
# $\|\Delta\pi\|_1 / \|\Delta g\|_1$ over router-only samples, $L_k$ as the largest ratio
# $\|\Delta\pi\|_1 / (w_k\|\Delta\theta_k\|)$ over samples that moved expert $k$ only. The additive
# bound $L_G\|\Delta g\|_1 + \sum_k w_k L_k\|\Delta\theta_k\|$ is then **tested** on the joint
# perturbations, which were not used to fit it, and on the tie states. A sample counts as a
# violation when it exceeds the bound by more than three Monte-Carlo standard errors. For
# reference the table also gives the least-squares constants and the LP envelope fitted on all
# random-state samples.

# %%
E = checks["n_experts"]
U_cols = ["dG"] + [f"wdtheta_{k}" for k in range(E)]
lip_rows, consts = [], {}
for dist in DISTRIBUTIONS:
    sub = rs[rs.distribution == dist]
    rnd = sub[~sub.tie]
    r_only = rnd[rnd.part == "router"]
    L = [lipschitz_ratio(r_only.l1, r_only.dG, 1.0)]
    for k in range(E):
        e_only = rnd[rnd.part == f"expert{k}"]
        used = (e_only[f"wdtheta_{k}"] > 0).any()  # eval top-1 may never select an expert on these states
        L.append(lipschitz_ratio(e_only.l1, e_only[f"wdtheta_{k}"], 1.0) if used else np.nan)
    L = np.nan_to_num(np.array(L), nan=0.0)
    consts[dist] = L
    bound = sub[U_cols].to_numpy() @ L
    viol = sub.l1.to_numpy() > bound + 3 * sub.l1_se.to_numpy()
    env = lipschitz_envelope(rnd.l1.to_numpy(), rnd[U_cols].to_numpy())
    ls = lipschitz_nnls(rnd.l1.to_numpy(), rnd[U_cols].to_numpy())
    joint = (sub.part == "joint").to_numpy()
    tie = sub.tie.to_numpy()
    t_router = sub[sub.tie & (sub.part == "router")]
    lip_rows.append({
        "distribution": dist,
        "L_G": L[0], **{f"L_{k}": L[k + 1] for k in range(E)},
        "L_G_q95": lipschitz_ratio(r_only.l1, r_only.dG, 0.95),
        "L_G_at_ties": lipschitz_ratio(t_router.l1, t_router.dG, 1.0),
        "joint_tightness_median": float(np.median(sub.l1.to_numpy()[joint & ~tie] / bound[joint & ~tie])),
        "violations_joint_random": f"{int(viol[joint & ~tie].sum())}/{int((joint & ~tie).sum())}",
        "violations_ties": f"{int(viol[tie].sum())}/{int(tie.sum())}",
        "L_G_lsq": ls[0], "L_theta_lsq_mean": ls[1:].mean(),
        "L_G_envelope": env[0], "L_theta_envelope_mean": env[1:].mean(),
    })
    rs.loc[sub.index, "bound"] = bound
lip = round_reported(pd.DataFrame(lip_rows))
write_table(lip, "theory_lipschitz", figures_dir)
print(lip.T.to_string())
tie_flips = rs[(rs.distribution == "eval_top1") & rs.tie & (rs.part == "router")]
print(f"\nrouter-only perturbations at tie states: the chosen expert flipped in {int(tie_flips.flipped.sum())}/{len(tie_flips)} "
      f"cases; there the eval-top-1 L1 change is {tie_flips.l1[tie_flips.flipped].median():.3f} (median) for a gate change "
      f"||dg||_1 of {tie_flips.dG[tie_flips.flipped].median():.2e} (median)")

# %%
fig, axes = plt.subplots(1, 3, figsize=(14, 4.3))
markers = {"router": "o", "expert": "s", "joint": "^"}
for ax, dist in zip(axes, DISTRIBUTIONS):
    sub = rs[rs.distribution == dist]
    for part, mk in markers.items():
        s2 = sub[sub.part.str.startswith(part) & ~sub.tie]
        ax.scatter(s2.bound.clip(lower=1e-7), s2.l1.clip(lower=1e-7), s=4, marker=mk, alpha=0.25, label=f"{part} (random states)")
    s3 = sub[sub.tie]
    ax.scatter(s3.bound.clip(lower=1e-7), s3.l1.clip(lower=1e-7), s=10, c="red", marker="x", alpha=0.6, label="tie states")
    lim = [1e-7, 3]
    ax.plot(lim, lim, "k--", lw=1, label="measured = bound")
    ax.set_xscale("log"), ax.set_yscale("log"), ax.set_xlim(lim), ax.set_ylim(lim)
    ax.set_xlabel(r"bound $L_G\|\Delta g\|_1 + \sum_k w_k L_k \|\Delta\theta_k\|$")
    ax.set_ylabel(r"measured $\|\pi' - \pi\|_1$ (Monte Carlo)")
    ax.set_title(dist)
axes[0].legend(fontsize=7, loc="upper left")
fig.suptitle("A4 on a trained PE-MAMoE actor: points above the diagonal violate the bound")
fig.tight_layout()
save_figure(fig, "theory_routing_stability", figures_dir)
plt.show()

# %% [markdown]
# ![Assumption A4 on a trained PE-MAMoE actor: measured distance against the bound](../paper_figures/theory_routing_stability.png)

# %% [markdown]
# ## 3 · Dynamic regret
#
# Three sweeps on the tracking task, each over several seeds:
#
# * **$T$ at a fixed number of switches** ($K = 3$, so $V_T$ is fixed): the shape
#   $T^{3/4}V_T^{1/4}$ predicts an exponent of at most $3/4$ in $T$. Run for the PE-MAMoE actor
#   with noise, the same network without noise (the SMoE baseline) and the MLP.
# * **$T$ at a fixed phase length**: $K$ and therefore $V_T$ grow in proportion to $T$, so the shape
#   predicts at most exponent $1$, i.e. nothing beyond linear regret.
# * **$V_T$ at fixed $T$**, varied both through the number of switches $K$ and through the size of
#   each step (`shift`): exponent at most $1/4$ *if* the bound were tight in $V_T$.
#
# A joint fit $\log R_T = c + \alpha\log T + \beta\log V_T$ over all runs with $V_T > 0$ gives
# $(\alpha, \beta)$ to set against $(3/4, 1/4)$. The noise term is read off the paired runs of
# section 1: the excess regret $R_T(\text{noisy}) - R_T(\text{clean})$ against
# $\sqrt{\sum_t\gamma_t^2}$. We also report the **steady-state regret**, the mean instantaneous
# regret over the last fifth of each phase, to separate what the learner cannot track from what
# it never learns at all.

# %%
TS = by_scale(scale, ci=[60, 120, 240], small=[100, 200, 400, 800], paper=[100, 200, 400, 800, 1600])
REG_SEEDS = by_scale(scale, ci=2, small=3, paper=5)
PHASE_LEN = TS[0]
KINDS = by_scale(scale, ci=[("pemamoe", "noise")], small=[("pemamoe", "noise"), ("smoe", "off"), ("mlp", "off")],
                 paper=[("pemamoe", "noise"), ("smoe", "off"), ("mlp", "off")])
V_T = by_scale(scale, ci=240, small=400, paper=800)
V_KS = by_scale(scale, ci=[1, 3], small=[1, 3, 7], paper=[1, 3, 7, 15])
V_SHIFTS = by_scale(scale, ci=[0.3, 1.2], small=[0.3, 0.6, 1.2], paper=[0.3, 0.6, 1.2])
reg_jobs, reg_keys = [], []
for kind, ctl in KINDS:
    for T in TS:
        for s in range(REG_SEEDS):
            reg_jobs.append((TrackingProblemConfig(n_phases=4), TrackerConfig(kind=kind, controller=ctl, iterations=T, n_switches=3,
                             batch=BATCH, noise_gamma=0.01, keep_means=False), seed, seed + s, False))
            reg_keys.append(("fixed K", kind, T, 3, 0.6, s))
for T in TS:
    K = T // PHASE_LEN - 1
    for s in range(REG_SEEDS):
        reg_jobs.append((TrackingProblemConfig(n_phases=K + 1), TrackerConfig(iterations=T, n_switches=K, batch=BATCH, noise_gamma=0.01,
                         keep_means=False), seed, seed + s, False))
        reg_keys.append(("fixed phase length", "pemamoe", T, K, 0.6, s))
for K in V_KS:
    for sh in V_SHIFTS:
        for s in range(REG_SEEDS):
            reg_jobs.append((TrackingProblemConfig(n_phases=K + 1, shift=sh), TrackerConfig(iterations=V_T, n_switches=K, batch=BATCH,
                             noise_gamma=0.01, keep_means=False), seed, seed + s, False))
            reg_keys.append(("fixed T", "pemamoe", V_T, K, sh, s))


def steady_state(run):
    inst = run.optimal - run.values
    tails = []
    bounds = [0, *run.switches, len(inst)]
    for a, b in zip(bounds[:-1], bounds[1:]):
        tails.append(inst[b - max(1, (b - a) // 5):b].mean())
    return float(np.mean(tails))


def compute_regret():
    """One row per regret run; and the regret curves R_t of the fixed-T runs at the largest shift
    (seed 0), which the figure draws."""
    t_start = time.perf_counter()
    reg_runs = run_many(reg_jobs, WORKERS)
    print(f"{len(reg_jobs)} regret runs in {time.perf_counter() - t_start:.1f} s")
    runs = pd.DataFrame([{
        "sweep": k[0], "kind": k[1], "T": k[2], "K": k[3], "shift": k[4], "seed": k[5],
        "V_T": float(k[3] * k[4]), "R_T": r.total_regret, "steady_state": steady_state(r),
        "energy": r.noise_energy, "bound_shape": k[2] ** 0.75 * (k[3] * k[4]) ** 0.25,
    } for k, r in zip(reg_keys, reg_runs)])
    curves = pd.concat([pd.DataFrame({"K": k[3], "shift": k[4], "iteration": np.arange(len(r.regret)), "regret": r.regret})
                        for k, r in sorted(zip(reg_keys, reg_runs), key=lambda kr: kr[0][3])
                        if k[0] == "fixed T" and k[4] == V_SHIFTS[-1] and k[5] == 0], ignore_index=True)
    return {"runs": runs, "curves": curves}, {"runs": len(reg_jobs)}


regret_parameters = theory_parameters(dict(TS=TS, REG_SEEDS=REG_SEEDS, PHASE_LEN=PHASE_LEN, KINDS=KINDS, V_T=V_T, V_KS=V_KS,
                                           V_SHIFTS=V_SHIFTS, BATCH=BATCH, seed=seed), reg_jobs)
regret_tables, _ = theory_record(records_root, scale, "regret", regret_parameters, compute_regret, retrain)
reg_df, reg_curves = regret_tables["runs"], regret_tables["curves"]
reg_df.groupby(["sweep", "kind", "T", "K", "shift"])[["V_T", "R_T", "steady_state", "energy"]].mean()

# %%
rng_reg = np.random.default_rng(seed + 2)
fit_rows = []


def add_fit(name, sel, cols, paper, groups=None):
    sub = reg_df[sel]
    f = fit_power_law(sub[cols].to_numpy() if len(cols) > 1 else sub[cols[0]].to_numpy(), sub.R_T.to_numpy(), rng_reg, n_boot=2000)
    slopes = np.atleast_1d(f["slope"])
    los, his = np.atleast_1d(f["ci_low"]), np.atleast_1d(f["ci_high"])
    for c, a, lo, hi, pe in zip(cols, slopes, los, his, paper):
        fit_rows.append({"fit": name, "regressor": c, "exponent": a, "ci_low": lo, "ci_high": hi,
                         "paper_shape_exponent": pe, "exceeds_shape": bool(lo > pe), "r2": f["r2"], "n_runs": f["n"]})


for kind, _ in KINDS:
    add_fit(f"fixed K=3, {kind}", (reg_df.sweep == "fixed K") & (reg_df.kind == kind), ["T"], [0.75])
add_fit("fixed phase length", (reg_df.sweep == "fixed phase length") & (reg_df.K > 0), ["T"], [1.0])
add_fit("fixed T, vary K and shift", reg_df.sweep == "fixed T", ["V_T"], [0.25])
for sh in V_SHIFTS:
    add_fit(f"fixed T, shift={sh}, vary K", (reg_df.sweep == "fixed T") & (reg_df["shift"] == sh), ["V_T"], [0.25])
add_fit("joint (pemamoe, V_T > 0)", (reg_df.kind == "pemamoe") & (reg_df.V_T > 0), ["T", "V_T"], [0.75, 0.25])
# noise term: excess regret of the paired runs of section 1
pe_noise = noise_df[noise_df.kind == "pemamoe"]
pos = pe_noise.excess_regret > 0
if pos.sum() >= 3 and pe_noise.loc[pos, "energy"].nunique() >= 2:
    f = fit_power_law(np.sqrt(pe_noise.loc[pos, "energy"]), pe_noise.loc[pos, "excess_regret"], rng_reg, n_boot=2000)
    fit_rows.append({"fit": f"noise: excess regret, pemamoe ({int(pos.sum())}/{len(pe_noise)} pairs > 0)", "regressor": "sqrt(energy)",
                     "exponent": f["slope"], "ci_low": f["ci_low"], "ci_high": f["ci_high"], "paper_shape_exponent": 1.0,
                     "exceeds_shape": bool(f["ci_low"] > 1.0), "r2": f["r2"], "n_runs": f["n"]})
regret_fit = round_reported(pd.DataFrame(fit_rows))
write_table(regret_fit, "theory_regret_fit", figures_dir)
print(regret_fit.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
ss = reg_df.groupby(["sweep", "kind", "T", "K", "shift"]).steady_state.mean()
print(f"\nsteady-state regret (mean instantaneous regret over the last fifth of each phase): "
      f"{ss.min():.4f} .. {ss.max():.4f}; first-iteration regret after a switch is typically ~0.1-1")
ratio = reg_df[reg_df.V_T > 0].assign(C=lambda d: d.R_T / d.bound_shape)
print("\nimplied constant C = R_T / (T^3/4 V_T^1/4), by sweep and T (mean over seeds):")
print(ratio.groupby(["sweep", "kind", "T"]).C.mean().round(3).to_string())
for kind, grp in noise_df.groupby("kind"):
    ex, rel = grp.excess_regret, grp.excess_regret / grp.clean_regret
    print(f"excess regret of noisy runs ({kind}): mean {ex.mean():+.3f}, positive in {int((ex > 0).sum())}/{len(ex)} pairs, "
          f"relative to the clean R_T: median {rel.median():+.2%}, range {rel.min():+.2%} .. {rel.max():+.2%}")

# %%
fig, axes = plt.subplots(1, 4, figsize=(18, 4.2))
for (K, sh), curve in reg_curves.groupby(["K", "shift"], sort=True):
    axes[0].plot(curve.iteration, curve.regret, label=f"K={K}, shift={sh}")
axes[0].set_xlabel("iteration t"), axes[0].set_ylabel(r"cumulative regret $R_t$"), axes[0].legend(fontsize=7)
axes[0].set_title("regret accumulates at switches")
for (kind, _), c in zip(KINDS, ("C0", "C1", "C2")):
    sub = reg_df[(reg_df.sweep == "fixed K") & (reg_df.kind == kind)]
    axes[1].scatter(sub["T"], sub.R_T, s=12, c=c, label=f"fixed K=3, {kind}")
sub = reg_df[(reg_df.sweep == "fixed phase length") & (reg_df.K > 0)]
axes[1].scatter(sub["T"], sub.R_T, s=12, c="C3", marker="^", label="fixed phase length (pemamoe)")
tt = np.array(TS, float)
base_r = reg_df[(reg_df.sweep == "fixed K") & (reg_df["T"] == TS[0])].R_T.mean()
axes[1].plot(tt, base_r * (tt / tt[0]) ** 0.75, "k:", label=r"$\propto T^{3/4}$")
axes[1].plot(tt, base_r * (tt / tt[0]), "k--", lw=0.8, label=r"$\propto T$")
axes[1].set_xscale("log"), axes[1].set_yscale("log"), axes[1].set_xlabel("T"), axes[1].set_ylabel(r"$R_T$")
axes[1].legend(fontsize=7), axes[1].set_title("growth in T")
sub = reg_df[reg_df.sweep == "fixed T"]
for sh, c in zip(V_SHIFTS, ("C0", "C1", "C2", "C3")):
    s2 = sub[sub["shift"] == sh]
    axes[2].scatter(s2.V_T, s2.R_T, s=12, c=c, label=f"shift {sh}, vary K")
vv = np.geomspace(sub.V_T.min(), sub.V_T.max(), 10)
axes[2].plot(vv, sub.R_T.min() * (vv / vv[0]) ** 0.25, "k:", label=r"$\propto V_T^{1/4}$")
axes[2].plot(vv, sub.R_T.min() * (vv / vv[0]), "k--", lw=0.8, label=r"$\propto V_T$")
axes[2].set_xscale("log"), axes[2].set_yscale("log"), axes[2].set_xlabel(r"$V_T = K\cdot$shift"), axes[2].set_ylabel(r"$R_T$")
axes[2].legend(fontsize=7), axes[2].set_title(f"growth in the variation budget (T={V_T})")
for kind, mk in (("pemamoe", "o"), ("mlp", "x")):
    grp = noise_df[noise_df.kind == kind]
    axes[3].scatter(np.sqrt(grp.energy), grp.excess_regret / grp.clean_regret, s=12, marker=mk,
                    c=[colors[s.split("+")[0]] for s in grp.sweeps], label=kind)
axes[3].legend(fontsize=7)
axes[3].axhline(0, color="k", lw=0.8)
axes[3].set_xscale("log"), axes[3].set_xlabel(r"$\sqrt{\sum_t\gamma_t^2}$")
axes[3].set_ylabel(r"$(R_T^{noisy} - R_T^{clean}) / R_T^{clean}$")
axes[3].set_title("noise term (paired runs)")
fig.tight_layout()
save_figure(fig, "theory_dynamic_regret", figures_dir)
plt.show()

# %% [markdown]
# ![Dynamic regret sweeps on the tracking task](../paper_figures/theory_dynamic_regret.png)

# %%
print(f"notebook ran in {time.perf_counter() - T0:.1f} s at scale {scale!r}")

# %% [markdown]
# ## 4 · What these checks show, and what they cannot
#
# *(The numbers quoted here are those of the committed `medium` records, which serve `small` too:
# this notebook uses the same sizes at both. Slopes, intervals and Lipschitz constants are those of
# the tables the notebook writes from the records (`theory_noise_fit.md`, `theory_regret_fit.md`
# and `theory_lipschitz.md`); the rest (twin distances, gate spreads, steady-state and excess
# regret) are read from the cells' output. The cells above print the values of whatever scale the
# notebook was run at.)*
#
# **Noise energy.** The identity $\sum_t\gamma_t^2 = \gamma^2KN$ is exact for disjoint windows
# (bit for bit, tested), and an upper bound otherwise. The shipped controller adds one pulse at the
# switch itself, so the MLP's realised energy is $\gamma^2K(N+1)$, and the recorded pulses fill the
# window of $N+1$ slots in every run. The gated actor's epoch pulses are weighted by how much each
# expert is used, so PE-MAMoE's energy is 0.17 of the MLP's on average. The drift of a noisy run
# from its same-seed twin grows with the energy but **much more slowly than**
# $\sqrt{\text{energy}}$. In the $\gamma$ sweep the probe-distance slope against
# $\sqrt{\sum\gamma^2}$ is 0.26 [0.19, 0.32] for PE-MAMoE and 0.62 [0.59, 0.64] for the MLP, and
# $\sum_t|\Delta J_t|$ has slope 0.20 [0.07, 0.30].
#
# The reference line shows why. At $\gamma = 0.04$ the MLP's twin is as far away (0.094) as a run
# with a *different seed* (0.094), and PE-MAMoE's is at 0.072 against 0.124. A paired PPO run
# amplifies any small perturbation until it reaches the learner's own seed-to-seed spread, so this
# distance saturates and does not isolate the conditional mean that the lemma's martingale sum is
# centred on. The lemma's own quantity, the signed sum $|\sum_t \Delta J_t|$, is dominated by
# cancellations ($R^2 = 0.13$, slope 0.58 with an interval from 0.23 to 1.10): these runs place
# its slope at or below the lemma's 1, but pin it down poorly.
#
# Read literally, a slope below 1 means that the ratio deviation$/\sqrt{\text{energy}}$ grows as
# $\gamma \to 0$. That conflicts with a uniform $O(\sqrt{\sum\gamma^2})$ constant if one takes the
# twin distance as the deviation. It does not refute the lemma, which is about a differently
# centred quantity. The $K$ sweep (slope 1.8) is confounded: more switches also means an earlier
# first pulse, so the noise acts for longer.
#
# **Routing stability (A4).** With the gating defaults of notebook 05c the trained actor has no
# routing noise (its gating-noise scale is 0). Its sampling policy therefore routes top-1 like the
# evaluation policy, and the "sampling marginal" is the same one-hot choice. The softmax gate is
# nearly flat: the top-two gap has a median of 0.036, and the logits spread by 0.06 to 0.16 over
# states.
#
# For the A4 mixture, the constants fitted on single-factor perturbations bound every held-out
# joint perturbation (0/3840 violations, median tightness 0.11) and every tie (0/4800). The
# constants are $L_G = 0.95$ and $L_k \approx 0.67$ to $0.83$ per unit of $w_k\|\Delta\theta_k\|$.
# $L_G \approx 1$ is what the triangle inequality predicts.
#
# For the **top-1 policies the assumption fails**, in sampling and in evaluation alike:
# * Router-only perturbations already need $L_G \approx 1.4\times10^3$ on random states, some of
#   which lie close to a boundary.
# * At exact ties the ratio reaches $1.3\times10^5$, and 273 (sampling) and 292 (evaluation) of
#   4800 tie samples break the bound with these constants (as does 1 of the 3840 held-out joint
#   perturbations on random states).
# * A router change that moves the gate by $\|\Delta g\|_1 \approx 5\times10^{-4}$ flips the
#   chosen expert in half the tie cases (463 of 960), and moves the action distribution by 0.30
#   in $L_1$ (median).
#
# A4 holds for the smooth mixture. For the hard top-1 policy that is trained and deployed it holds
# only piecewise, away from the boundaries. The paper's phrase "piecewise smooth" concedes this;
# its Lipschitz inequality does not.
#
# **Dynamic regret.** With $V_T$ fixed ($K = 3$) the regret grows like $T^{0.25}$ [0.22, 0.28]
# for PE-MAMoE (SMoE and MLP 0.24), far below $T^{3/4}$. The implied constant
# $R_T/(T^{3/4}V_T^{1/4})$ falls from 0.25 to 0.09 between $T = 100$ and $800$, so in $T$ the
# bound is loose, and more so as $T$ grows. With a fixed phase length the regret is linear (1.03
# [0.95, 1.18]), as the shape allows.
#
# In $V_T$ at fixed $T$, the measured growth is **steeper than $V_T^{1/4}$**:
# * 0.88 [0.71, 1.03] over all $(K, \text{shift})$;
# * 0.57 to 0.61 when only $K$ varies, at shift 0.6 or 1.2 (0.30 at shift 0.3);
# * the joint fit gives $(\alpha, \beta) = (0.18\;[0.01, 0.29],\; 0.83\;[0.68, 0.95])$ against
#   $(3/4, 1/4)$.
#
# This does not break the bound, since every run sits under $0.55\,T^{3/4}V_T^{1/4}$. It does mean
# the shape misdescribes how this learner's regret depends on drift. Each switch costs a transient
# roughly proportional to the size of the jump, while steady-state regret is only 0.002 to 0.02 per
# step. So regret is close to additive in the switches, and the $T^{3/4}$ slack absorbs the steeper
# $V_T$ dependence.
#
# The noise term is not detectable in the regret:
# * The excess regret of PE-MAMoE's noisy runs is −1.1 % of the clean regret (median, range
#   −6 % to +8 %), positive in 12 of 33 pairs, which a sign test does not tell from half
#   ($p = 0.16$). Fitted on those 12 pairs, its slope against $\sqrt{\text{energy}}$ is 0.66,
#   with an interval from −0.01 to 2.31.
# * The MLP's noisy runs are at −2.3 % (median, range −10 % to +9 %, positive in 5 of 15).
#
# In this toy, noise neither helps (no plasticity has been lost in a few hundred iterations) nor
# measurably hurts.
#
# **What this cannot show.** A fitted slope over one decade of $T$ or $\gamma$ is not an
# asymptotic rate, and an upper bound with hidden constants can only be *falsified* by a
# measurement growing faster than its shape in the regime it claims, which none of ours does in
# $T$. The bootstrap intervals cover the spread of these seeds and settings, not model error. The
# toy problem has a hidden but piecewise-constant optimum, one agent, no transition dynamics, an
# exact advantage and none of the other switch-time mechanisms. It says nothing direct about the
# UAV environment, the multi-agent critic (assumption A3) or the trust-region conditions (A2) that
# the proof borrows. It checks the *ingredients* (energy bookkeeping, Lipschitz routing,
# regret scaling) on the paper's real actor and real noise injection, and shows where they are
# loose or fail.
