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
# # 08b · Appendix: the toy tracking problems and the instruments of the theory check
#
# Notebook 08 states what section V of the paper predicts and sets each prediction against a
# measurement on toy tracking problems. This appendix holds the problems and the instruments that
# measure them, in the module `pemamoe.toy_tracking`:
#
# * **the tracking task** of notebook 08 as code: `TrackingProblemConfig` and `TrackingProblem`;
# * **the learner**: `TrackerConfig`, `run_tracker` and `run_many`, a compact PPO loop that trains
#   the real actor of notebook 05 on the tracking task with the phase controller the trainer runs
#   (notebook 06, noise injection only), and `paired_distance`, which compares a noisy run with
#   its noise-free twin;
# * **the exponent fit**: `fit_power_law`, a log-log least-squares fit with bootstrap intervals;
# * **distances between action distributions**: `gaussian_l1` (closed form) and `mc_l1_distance`
#   (Monte Carlo, for Gaussian mixtures);
# * **Lipschitz constants from samples**: `lipschitz_ratio`, `lipschitz_nnls`, `lipschitz_envelope`;
# * **probes of the mixture-of-experts actor**: `moe_components`, `top1_win_probs`,
#   `mixture_weights`, `perturb_actor`, `tie_states` and `routing_stability_samples`.
#
# Read it after notebook 08 when a number there looks surprising and you want to know exactly how
# it was measured, or before changing an instrument. Every instrument is checked here on a case
# whose answer is known in advance. `pemamoe.toy_tracking` imports `pemamoe.theory` (the noise
# energy and the dynamic regret); `pemamoe.theory` never imports it back, so notebook 08's
# demonstration cells import the instruments from `pemamoe.toy_tracking` directly. The records
# that keep the measurements (computed once, committed) are appendix 08c's.

# %%
#| default_exp toy_tracking

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %%
#| export
import copy
import math
import multiprocessing
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from pemamoe.core import require_field
from pemamoe.nets import NetConfig, make_actor, network_kind
from pemamoe.phase_controller import (MemberConfig, PhaseController, PhaseControllerConfig, expert_parameters,
                                      n_experts_of)
from pemamoe.plasticity import RunSettings, population_method
from pemamoe.theory import dynamic_regret, noise_energy

# %%
import time

from pemamoe.core import by_scale
from pemamoe.theory import noise_schedule

torch.set_num_threads(1)
T0 = time.perf_counter()

# %% [markdown]
# ## The tracking task
#
# Notebook 08 defines the task: contexts $x \sim \mathcal N(0, I_d)$, the reward
# $r(x, a) = -\|\mathrm{clip}(a) - (A_\phi x + b_\phi)\|^2$ with a hidden phase $\phi$, successive
# phase maps $W = [A \mid b]$ exactly `shift` apart, and values measured on a fixed probe set of
# contexts shared by every run. `TrackingProblem` draws the maps (each step in a random direction
# pulled towards the origin) and the probe set from one seed, and evaluates rewards, optimal
# actions and values on numpy arrays and torch tensors alike (the learner passes tensors).

# %%
#| export
@dataclass(frozen=True)
class TrackingProblemConfig:
    """The contextual tracking task: r = -||clip(a) - (A_phi x + b_phi)||^2 with a hidden phase."""

    obs_dim: int = 4
    act_dim: int = 2
    n_phases: int = 4
    shift: float = 0.6  # ||W_{k+1} - W_k||_F = RMS distance between successive optimal maps
    init_scale: float = 0.5  # ||W_0||_F
    action_bound: float = 1.0
    probe_size: int = 512

    def __post_init__(self):
        for name in ("obs_dim", "act_dim", "n_phases", "probe_size"):
            require_field(self, name, "int", ge=1)
        require_field(self, "shift", "real", ge=0)
        require_field(self, "init_scale", "real", ge=0)
        require_field(self, "action_bound", "real", gt=0)


class TrackingProblem:
    """Phase maps W (P, m, d+1) = [A | b], a fixed probe set (probe_size, d), exact values on it."""

    def __init__(self, cfg: TrackingProblemConfig, seed: int = 0):
        self.cfg = cfg
        rng = np.random.default_rng(seed)
        d, m = cfg.obs_dim, cfg.act_dim
        W = np.zeros((cfg.n_phases, m, d + 1))
        g = rng.standard_normal((m, d + 1))
        W[0] = cfg.init_scale * g / np.linalg.norm(g)
        for k in range(1, cfg.n_phases):
            g = rng.standard_normal((m, d + 1))
            step = g / np.linalg.norm(g) - W[k - 1]  # random direction, pulled towards the origin
            W[k] = W[k - 1] + cfg.shift * step / np.linalg.norm(step)
        self.W = W
        self.probe = rng.standard_normal((cfg.probe_size, d))
        self._W_t = torch.tensor(W, dtype=torch.float32)
        self._opt = np.array([self.value(self.optimal_action(self.probe, k), k) for k in range(cfg.n_phases)])

    def target(self, x, phase: int):
        """A_phi x + b_phi for contexts x (..., d), numpy or torch."""
        if isinstance(x, torch.Tensor):
            W = self._W_t[phase]
            return x @ W[:, :-1].T + W[:, -1]
        W = self.W[phase]
        return np.asarray(x) @ W[:, :-1].T + W[:, -1]

    def reward(self, x, a, phase: int):
        """r(x, a) (...,) for contexts (..., d) and actions (..., m), numpy or torch."""
        c = self.target(x, phase)
        lim = self.cfg.action_bound
        if isinstance(a, torch.Tensor):
            return -((a.clamp(-lim, lim) - c) ** 2).sum(-1)
        return -np.sum((np.clip(a, -lim, lim) - c) ** 2, axis=-1)

    def optimal_action(self, x, phase: int):
        """The maximiser clip(A_phi x + b_phi) of r(x, .)."""
        lim = self.cfg.action_bound
        c = self.target(x, phase)
        return c.clamp(-lim, lim) if isinstance(c, torch.Tensor) else np.clip(c, -lim, lim)

    def value(self, probe_actions, phase: int) -> float:
        """Mean reward of the actions (probe_size, m) taken on the probe contexts."""
        return float(np.mean(self.reward(self.probe, np.asarray(probe_actions, dtype=float), phase)))

    def optimal_value(self, phase: int) -> float:
        """V*_phi on the probe set."""
        return float(self._opt[phase])

    def shifts(self) -> np.ndarray:
        """||W_{k+1} - W_k||_F for each switch (n_phases - 1,)."""
        return np.linalg.norm(np.diff(self.W, axis=0).reshape(self.cfg.n_phases - 1, -1), axis=1)

# %%
check_task = TrackingProblem(TrackingProblemConfig(n_phases=3, shift=0.8), seed=seed)
x_task = np.random.default_rng(seed).standard_normal((200, 4))
for k in range(3):
    best = check_task.reward(x_task, check_task.optimal_action(x_task, k), k)
    worse = check_task.reward(x_task, check_task.optimal_action(x_task, k) + 0.3, k)
    assert np.all(worse <= best + 1e-12) and np.all(best <= 0)
assert np.allclose(check_task.shifts(), 0.8)
print("optimal values per phase:", [round(check_task.optimal_value(k), 4) for k in range(3)],
      "| steps between phase maps:", check_task.shifts().round(6))

# %% [markdown]
# ## The learner and the paired runs
#
# Notebook 08 explains the design: antithetic action pairs under the same routing (an exact,
# critic-free advantage), the phase controller with only noise injection switched on, and a
# random-number layout under which a noisy run and its noise-free twin see the same contexts and
# the same sampling noise. `run_tracker` records, per iteration, the value of the mean-action
# policy on the probe set, the optimal value, the cumulative dynamic regret, and every noise pulse
# with its *pulse slot* (slot 0 of iteration $t$ is its start, where a switch pulse lands; slot
# $e + 1$ follows update epoch $e$). `run_many` runs a list of jobs, in forked worker processes
# when asked, each with one torch thread, and returns the runs in job order.

# %%
#| export
CONTROLLERS = ("off", "noise")


@dataclass(frozen=True)
class TrackerConfig:
    """Learner of the tracking task: actor kind, PPO settings, switches and the noise window."""

    kind: str = "pemamoe"
    iterations: int = 300
    n_switches: int = 3
    batch: int = 64  # contexts per iteration (2 * batch actions, antithetic)
    epochs: int = 2  # PPO epochs per iteration (the noise window counts these)
    lr: float = 3e-3
    clip: float = 0.2
    controller: str = "noise"  # "off": no noise; "noise": only the expert-noise mechanism
    noise_gamma: float = 0.005
    noise_epochs: int = 30
    hidden: int = 32
    n_experts: int = 3
    keep_means: bool = True  # store the probe-set mean actions of every iteration

    def __post_init__(self):
        own = "TrackerConfig"
        try:
            network_kind(self.kind)
        except ValueError as err:
            raise ValueError(f"{own}.kind: {err}") from None
        require_field(self, "iterations", "int", ge=1)
        require_field(self, "n_switches", "int", ge=0)
        for name in ("batch", "epochs", "hidden", "n_experts"):
            require_field(self, name, "int", ge=1)
        require_field(self, "lr", "real", gt=0)
        require_field(self, "clip", "real", gt=0)
        require_field(self, "controller", "choice", CONTROLLERS)
        require_field(self, "noise_gamma", "real", ge=0)
        require_field(self, "noise_epochs", "int", ge=0)
        require_field(self, "keep_means", "bool")


def switch_times(iterations: int, n_switches: int) -> list:
    """K switches evenly spaced in [0, T): round(k T / (K + 1)), k = 1..K (K + 1 equal phases)."""
    return [int(round(k * iterations / (n_switches + 1))) for k in range(1, n_switches + 1)]


@dataclass
class TrackerRun:
    """What run_tracker records. Arrays have one entry per iteration (T,) unless noted."""

    cfg: TrackerConfig
    seed: int
    switches: list
    phase: np.ndarray
    values: np.ndarray  # V(pi_t) of the mean-action policy on the probe set
    optimal: np.ndarray  # V*_phi(t)
    regret: np.ndarray  # cumulative dynamic regret R_t
    pulses: np.ndarray  # (n_pulses, 2): pulse slot (see noise_slots), amplitude (RMS noise std over the trunk)
    means: np.ndarray | None  # (T, probe_size, m) probe mean actions, or None
    log_std: np.ndarray  # (T, m)
    actor: object = field(default=None, repr=False)

    @property
    def noise_energy(self) -> float:
        return noise_energy(self.pulses[:, 1]) if len(self.pulses) else 0.0

    @property
    def total_regret(self) -> float:
        return float(self.regret[-1])

    def noise_slots(self) -> np.ndarray:
        """Realised noise amplitude per pulse slot (iterations * epochs + 1,): slot 0 of iteration t is its
        start (where the switch pulse goes), slot e + 1 follows update epoch e."""
        out = np.zeros(self.cfg.iterations * self.cfg.epochs + 1)
        for slot, std in self.pulses:
            if out[int(slot)] != 0:
                raise ValueError(f"two pulses in slot {int(slot)}")
            out[int(slot)] = std
        return out


def tracker_controller_config(cfg: TrackerConfig) -> PhaseControllerConfig:
    off = dict(
        kl_anchor=False, adam_reset=False, log_std_reset=False, entropy_reset=False, lr_drop=False,
        conservative_window=False, router_freeze=False, temperature_schedule=False,
    )
    return PhaseControllerConfig(
        **off, noise_injection=cfg.controller == "noise", noise_gamma=float(cfg.noise_gamma),
        noise_epochs=cfg.noise_epochs, noise_lr_factor=False,
    )


def _pulse_amplitude(stds, sizes) -> float:
    """RMS noise std over the trunk's scalars of one injection: expert e got stds[e] on sizes[e] scalars."""
    if len(set(stds)) == 1:
        return float(stds[0])  # every expert alike (the switch's pulse, or an ungated trunk): exactly gamma
    return math.sqrt(math.fsum(s * s * n for s, n in zip(stds, sizes)) / sum(sizes))


def run_tracker(problem: TrackingProblem, cfg: TrackerConfig, seed: int = 0, keep_actor: bool = False) -> TrackerRun:
    """Train cfg.kind on `problem` (n_phases must be >= n_switches + 1) and record values and noise.

    The actor is a population of one run, trained as the trainer of notebook 07 trains it (routing
    replayed, Adam over the flat row) and perturbed by its phase controller (notebook 06)."""
    if problem.cfg.n_phases < cfg.n_switches + 1:
        raise ValueError(f"run_tracker needs n_phases >= n_switches + 1, got {problem.cfg.n_phases} < {cfg.n_switches + 1}")
    torch.manual_seed(seed)
    d, m, T = problem.cfg.obs_dim, problem.cfg.act_dim, cfg.iterations
    base = RunSettings(
        lr=cfg.lr, clip_coef=cfg.clip, target_kl=None, ent_start=0.0, ent_end=0.0,
        total_iterations=T, phase_length=max(1, T // (cfg.n_switches + 1)),
    )
    member = MemberConfig(tracker_controller_config(cfg), base, seed=seed + 7912)  # its noise generator: seed + 7919
    single = make_actor(cfg.kind, d, m, NetConfig(hidden=cfg.hidden, n_experts=cfg.n_experts))
    ctrl = population_method(PhaseController.name, [member], [single], eps=1e-8)  # Adam's eps, no weight decay
    actor, opt = ctrl.actor, ctrl.actor_opt
    sparse = actor.gated and actor.k < actor.n_experts
    sizes = [idx.numel() for idx in ctrl.expert_indices()]
    rollout = torch.Generator().manual_seed(seed)  # contexts, gate noise and actions: shared with the twin
    one = torch.ones(1, dtype=torch.bool)
    ls = slice(*actor.layout.span("log_std"))
    switches = switch_times(T, cfg.n_switches)
    switch_set = set(switches)
    probe = torch.tensor(problem.probe, dtype=torch.float32).unsqueeze(0)
    phase_of = np.zeros(T, dtype=np.int64)
    values, optimal = np.zeros(T), np.zeros(T)
    means = np.zeros((T, problem.cfg.probe_size, m), np.float32) if cfg.keep_means else None
    log_std = np.zeros((T, m))
    pulses, epoch, phase = [], 0, 0

    def record(slot):
        stds = ctrl.last_noise[0]
        if stds is not None and max(stds) > 0:
            pulses.append((slot, _pulse_amplitude(stds, sizes)))

    for t in range(T):
        if t in switch_set:
            phase += 1
            ctrl.on_switch(t)
            record(epoch)
        s = ctrl.begin_iteration(t)
        with torch.no_grad():
            x = torch.randn(1, cfg.batch, d, generator=rollout)
            a_plus, _, routing = actor.act(x, s.policy_temperature, [rollout])
            _, _, _, mu, log_sd, _ = actor.evaluate(x, a_plus, routing)
            a_minus = 2 * mu - a_plus  # the antithetic twin: mu - sigma eps under the same routing
            adv = 0.5 * (problem.reward(x[0], a_plus[0], phase) - problem.reward(x[0], a_minus[0], phase))
            obs2, act2 = torch.cat([x, x], 1), torch.cat([a_plus, a_minus], 1)
            adv2 = torch.cat([adv, -adv]).unsqueeze(0)
            adv2 = adv2 / (adv2.std() + 1e-8)
            rout2 = None if routing is None else type(routing).cat([routing, routing], 1)
            logp_old = actor.evaluate(obs2, act2, rout2)[0]
        for _ in range(cfg.epochs):
            logp, _, lb, _, _, chosen = actor.evaluate(obs2, act2, rout2)
            ratio = (logp - logp_old).exp()
            clip = s.clip_coef.unsqueeze(1)
            clipped = ratio.clamp(1.0 - clip, 1.0 + clip)
            loss = -torch.min(ratio * adv2, clipped * adv2).mean(1) + actor.lb_coef * lb
            loss.sum().backward()
            opt.step(s.lr_actor, one)
            counts = F.one_hot(chosen.reshape(1, -1), actor.n_experts).sum(1).float() if sparse else None
            ctrl.after_epoch(counts, one)  # the trainer's rule: each expert's noise weighted by its share
            record(epoch + 1)
            epoch += 1
        with torch.no_grad():
            mp = actor.mean_and_gate(probe, s.policy_temperature.reshape(1, 1).expand(1, probe.shape[1]))[0][0].numpy()
        phase_of[t] = phase
        values[t] = problem.value(mp, phase)
        optimal[t] = problem.optimal_value(phase)
        log_std[t] = actor.flat[0, ls].detach().numpy()
        if means is not None:
            means[t] = mp
    return TrackerRun(
        cfg=cfg, seed=seed, switches=switches, phase=phase_of, values=values, optimal=optimal,
        regret=dynamic_regret(optimal, values), pulses=np.asarray(pulses, dtype=float).reshape(-1, 2),
        means=means, log_std=log_std, actor=actor.member(0) if keep_actor else None,
    )


def _run_job(job):
    torch.set_num_threads(1)
    problem_cfg, tracker_cfg, problem_seed, seed, keep_actor = job
    return run_tracker(TrackingProblem(problem_cfg, problem_seed), tracker_cfg, seed, keep_actor)


def run_many(jobs, workers: int = 1) -> list:
    """run_tracker over jobs (problem_cfg, tracker_cfg, problem_seed, seed, keep_actor), in order.

    workers > 1 forks that many processes (one torch thread each)."""
    jobs = list(jobs)
    if workers <= 1 or len(jobs) <= 1:
        return [_run_job(j) for j in jobs]
    with multiprocessing.get_context("fork").Pool(workers) as pool:
        return pool.map(_run_job, jobs, chunksize=1)


def paired_distance(clean: TrackerRun, noisy: TrackerRun) -> dict:
    """How far a noisy run moved from its noise-free twin (same problem and seed).

    policy_mean / policy_final: mean over iterations / at the end of the probe-mean L2 distance
    E_x ||mu_noisy(x) - mu_clean(x)||; return_gap: |sum_t (J_noisy - J_clean)| (the lemma's
    martingale sum); return_abs: sum_t |J_noisy - J_clean|; excess_regret: R_T(noisy) - R_T(clean).
    """
    if clean.means is None or noisy.means is None:
        raise ValueError("paired_distance needs runs made with keep_means=True")
    if clean.means.shape != noisy.means.shape:
        raise ValueError(f"paired_distance: runs differ in shape, {clean.means.shape} vs {noisy.means.shape}")
    dist_t = np.linalg.norm(noisy.means.astype(float) - clean.means.astype(float), axis=-1).mean(-1)
    dj = noisy.values - clean.values
    return {
        "policy_mean": float(dist_t.mean()),
        "policy_final": float(dist_t[-1]),
        "return_gap": float(abs(dj.sum())),
        "return_abs": float(np.abs(dj).sum()),
        "excess_regret": float(noisy.total_regret - clean.total_regret),
        "energy": noisy.noise_energy - clean.noise_energy,
    }

# %% [markdown]
# A check of the bookkeeping on a short run: with $\gamma = 0$ the "noisy" run reproduces its twin
# exactly; with $\gamma > 0$ the two agree until the first switch, and the pulses fill exactly the
# slots of `noise_schedule` with a window of $N + 1$. A pulse's amplitude is $\gamma$ at the switch;
# after an epoch it is the RMS over the trunk of the share-weighted stds, $\gamma$ for the MLP and
# between $\gamma/E$ and $\gamma/\sqrt E$ for $E$ equal experts, so the energy is at most
# $\gamma^2 K (N + 1)$, with equality for the MLP.

# %%
check_problem = TrackingProblem(TrackingProblemConfig(n_phases=3, probe_size=64), seed=seed)
check_base = dict(iterations=by_scale(scale, ci=24, small=40, paper=40), n_switches=2, batch=16, epochs=2, noise_epochs=3)
clean_run, zero_run, noisy_run, mlp_run = run_many([
    (check_problem.cfg, TrackerConfig(controller="off", **check_base), seed, seed + 5, False),
    (check_problem.cfg, TrackerConfig(controller="noise", noise_gamma=0.0, **check_base), seed, seed + 5, False),
    (check_problem.cfg, TrackerConfig(controller="noise", noise_gamma=0.05, **check_base), seed, seed + 5, False),
    (check_problem.cfg, TrackerConfig(kind="mlp", controller="noise", noise_gamma=0.05, **check_base), seed, seed + 5, False),
])
assert np.array_equal(clean_run.values, zero_run.values)
first = noisy_run.switches[0]
assert np.array_equal(noisy_run.values[:first], clean_run.values[:first])
slots = noise_schedule(check_base["iterations"] * 2 + 1, [2 * t for t in noisy_run.switches], 0.05, 3 + 1)
realised = noisy_run.noise_slots()
assert np.array_equal(realised > 0, slots > 0) and np.all(realised[[2 * t for t in noisy_run.switches]] == 0.05)
epoch_pulses = np.delete(realised, [2 * t for t in noisy_run.switches])
assert np.all(epoch_pulses[epoch_pulses > 0] <= 0.05 / math.sqrt(3) * (1 + 1e-12))
assert np.all(epoch_pulses[epoch_pulses > 0] >= 0.05 / 3 * (1 - 1e-12))
assert np.array_equal(mlp_run.noise_slots(), slots) and mlp_run.noise_energy == 0.05**2 * 2 * (3 + 1)
print(f"switches at {noisy_run.switches}; {len(noisy_run.pulses)} pulses, energy {noisy_run.noise_energy:.4f} "
      f"(MLP {mlp_run.noise_energy:.4f} = gamma^2 K (N + 1))")
print("noisy vs twin:", {k: round(v, 4) for k, v in paired_distance(clean_run, noisy_run).items()})

# %% [markdown]
# ## Fitting exponents
#
# Every scaling of notebook 08 is read off a log-log regression, $\log y = c + \sum_j \alpha_j
# \log x_j$, by least squares. The intervals are percentile bootstrap intervals: the rows (runs)
# are resampled with replacement, or whole groups (e.g. all runs of one seed) when `groups` is
# given, and the fit is repeated; resamples whose design matrix is rank-deficient are skipped.

# %%
#| export
def fit_power_law(x, y, rng: np.random.Generator, n_boot: int = 1000, level: float = 0.95, groups=None) -> dict:
    """Least squares log y = c + sum_j alpha_j log x_j with a bootstrap interval for every alpha_j.

    x (n,) or (n, p) positive; y (n,) positive. Returns {"slope": (p,) or float, "intercept",
    "ci_low", "ci_high", "r2", "n"} (floats when x is 1-D).
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float).reshape(-1)
    one_d = x.ndim == 1
    X = x.reshape(len(y), -1)
    if X.shape[0] != y.shape[0]:
        raise ValueError(f"fit_power_law: x has {X.shape[0]} rows, y has {y.shape[0]}")
    if not (np.all(X > 0) and np.all(y > 0)):
        raise ValueError("fit_power_law: x and y must be > 0 (log-log fit)")
    if not 0 < level < 1:
        raise ValueError(f"fit_power_law: level must be in (0, 1), got {level!r}")
    A = np.column_stack([np.ones(len(y)), np.log(X)])
    ly = np.log(y)

    def solve(idx):
        coef, *_ = np.linalg.lstsq(A[idx], ly[idx], rcond=None)
        return coef

    coef = solve(np.arange(len(y)))
    resid = ly - A @ coef
    r2 = 1.0 - resid.var() / ly.var() if ly.var() > 0 else 1.0
    if groups is None:
        units = [np.array([i]) for i in range(len(y))]
    else:
        g = np.asarray(groups)
        units = [np.flatnonzero(g == u) for u in np.unique(g)]
    boots = []
    for _ in range(n_boot):
        pick = rng.integers(0, len(units), len(units))
        idx = np.concatenate([units[i] for i in pick])
        if np.linalg.matrix_rank(A[idx]) < A.shape[1]:
            continue
        boots.append(solve(idx)[1:])
    boots = np.array(boots).reshape(-1, X.shape[1])
    lo, hi = np.quantile(boots, [(1 - level) / 2, (1 + level) / 2], axis=0) if len(boots) else (np.nan * coef[1:],) * 2
    slope = coef[1:]
    out = {"slope": slope, "intercept": float(coef[0]), "ci_low": lo, "ci_high": hi, "r2": float(r2), "n": int(len(y))}
    if one_d:
        out.update(slope=float(slope[0]), ci_low=float(lo[0]), ci_high=float(hi[0]))
    return out

# %%
rng_check = np.random.default_rng(seed)
x_fit = np.repeat(np.geomspace(10, 1000, 8), 5)
y_fit = 3.0 * x_fit**0.75 * np.exp(rng_check.normal(0, 0.1, x_fit.size))
f_fit = fit_power_law(x_fit, y_fit, rng_check, n_boot=500)
assert f_fit["ci_low"] <= 0.75 <= f_fit["ci_high"]
print(f"y = 3 x^0.75 with 10 % noise: slope {f_fit['slope']:.3f} [{f_fit['ci_low']:.3f}, {f_fit['ci_high']:.3f}], "
      f"R^2 {f_fit['r2']:.3f}")

# %% [markdown]
# ## $L_1$ distances between action distributions
#
# With $m = (p + q)/2$, $\|p - q\|_1 = 2\,\mathbb E_{a \sim m}\big[|p(a) - q(a)|/(p(a) + q(a))\big]
# = 2\,\mathbb E_{a\sim m}\big|\tanh\big(\tfrac12(\log p(a) - \log q(a))\big)\big|$: the integrand lies in $[0, 1]$ and is
# small wherever the densities are close, so the Monte-Carlo error is small *relative* to the
# distance itself, even for tiny perturbations. The closed form for two Gaussians with equal
# spread, $\|\mathcal N(\mu_1, \sigma^2 I) - \mathcal N(\mu_2, \sigma^2 I)\|_1 = 2\,(2\Phi(\delta/2) - 1)$ with
# $\delta = \|\mu_1 - \mu_2\|/\sigma$, is the test case.

# %%
#| export
def gaussian_l1(mu1, mu2, std) -> np.ndarray:
    """Exact ||N(mu1, diag std^2) - N(mu2, diag std^2)||_1 = 2 (2 Phi(delta / 2) - 1), delta the
    Mahalanobis distance. mu1, mu2 (..., D); std (D,) or (..., D) -> (...,)."""
    from scipy.special import ndtr

    delta = np.linalg.norm((np.asarray(mu1, float) - np.asarray(mu2, float)) / np.asarray(std, float), axis=-1)
    return 2.0 * (2.0 * ndtr(delta / 2.0) - 1.0)


def mixture_log_prob(a, weights, means, std) -> np.ndarray:
    """log sum_k w_k N(a; mu_k, diag std^2). a (S, B, D); weights (B, K); means (B, K, D);
    std (D,) or (B, D) -> (S, B). Zero weights are allowed."""
    from scipy.special import logsumexp

    a, w, mu = np.asarray(a, float), np.asarray(weights, float), np.asarray(means, float)
    sd = np.broadcast_to(np.asarray(std, float), (mu.shape[0], mu.shape[-1]))
    z = (a[:, :, None, :] - mu[None]) / sd[None, :, None, :]
    log_norm = -0.5 * mu.shape[-1] * math.log(2 * math.pi) - np.log(sd).sum(-1)  # (B,)
    comp = -0.5 * (z * z).sum(-1) + log_norm[None, :, None]
    with np.errstate(divide="ignore"):
        logw = np.log(w)
    return logsumexp(comp + logw[None], axis=-1)


def _sample_mixture(rng, n, weights, means, std):
    # n samples per row of a mixture: (n, B, D)
    B, K, D = means.shape
    cw = np.cumsum(weights, axis=-1)
    u = rng.random((n, B, 1)) * cw[None, :, -1:]
    k = np.minimum((u > cw[None]).sum(-1), K - 1)  # (n, B)
    mu = np.take_along_axis(means[None].repeat(n, 0), k[..., None, None].repeat(D, -1), axis=2)[:, :, 0]
    sd = np.broadcast_to(np.asarray(std, float), (B, D))
    return mu + sd[None] * rng.standard_normal((n, B, D))


def mc_l1_distance(p, q, rng: np.random.Generator, n_samples: int = 256):
    """Monte-Carlo ||p - q||_1 per row between Gaussian mixtures p, q = (weights (B, K), means (B, K, D),
    std (D,) or (B, D)). Returns (l1 (B,), standard error (B,))."""
    wp, mp, sp = (np.asarray(v, float) for v in p)
    wq, mq, sq = (np.asarray(v, float) for v in q)
    half = n_samples // 2
    a = np.concatenate([_sample_mixture(rng, half, wp, mp, sp), _sample_mixture(rng, n_samples - half, wq, mq, sq)])
    lp, lq = mixture_log_prob(a, wp, mp, sp), mixture_log_prob(a, wq, mq, sq)
    diff = np.where(np.isfinite(lp) | np.isfinite(lq), lp - lq, 0.0)
    f = np.abs(np.tanh(0.5 * diff))  # |p - q| / (p + q), in [0, 1]
    return 2.0 * f.mean(0), 2.0 * f.std(0, ddof=1) / math.sqrt(n_samples)

# %% [markdown]
# The closed form against the Monte-Carlo estimate, from nearly equal distributions to nearly
# disjoint ones; the estimate stays within four standard errors of the exact value.

# %%
import pandas as pd

rng_l1 = np.random.default_rng(seed)
checks = []
for dmu in (0.01, 0.3, 1.0, 3.0):
    p = (np.ones((1, 1)), np.zeros((1, 1, 1)), np.array([0.5]))
    q = (np.ones((1, 1)), np.full((1, 1, 1), dmu), np.array([0.5]))
    est, se = mc_l1_distance(p, q, rng_l1, 20000)
    checks.append({"delta_mu": dmu, "sigma": 0.5, "closed_form": float(gaussian_l1([0.0], [dmu], [0.5])),
                   "monte_carlo": float(est[0]), "mc_se": float(se[0])})
checks = pd.DataFrame(checks)
assert (np.abs(checks.closed_form - checks.monte_carlo) <= 4 * checks.mc_se + 1e-9).all()
checks

# %% [markdown]
# ## Lipschitz constants from samples
#
# Given samples $(y_i, U_i)$ with $y_i$ the measured $L_1$ change and $U_i$ the bound terms
# ($\|\Delta g\|_1$ and $w_k\|\Delta\theta_k\|$ for each expert $k$), three estimates:
#
# * **ratios**: $\max_i y_i / u_i$ (and a high quantile) over samples where only one term moves;
# * **least squares** (non-negative): the constants that explain the *typical* sample;
# * **envelope**: the smallest constants (in mean bound) with $y_i \le U_i L$ for *every* sample,
#   a linear programme. This is the empirical version of A4: if it exists with moderate
#   constants, the samples are consistent with the assumption; if one tie sample forces $L_G$ up
#   by orders of magnitude, they are not.

# %%
#| export
def lipschitz_ratio(dy, dx, q: float = 1.0) -> float:
    """The q-quantile (q = 1: the max) of ||dy_i|| / ||dx_i|| over samples with dx_i != 0.
    dy (n,) or (n, p); dx (n,) or (n, r)."""
    dy = np.asarray(dy, float).reshape(len(dy), -1)
    dx = np.asarray(dx, float).reshape(len(dx), -1)
    ny, nx = np.linalg.norm(dy, axis=1), np.linalg.norm(dx, axis=1)
    ok = nx > 0
    if not ok.any():
        raise ValueError("lipschitz_ratio: every dx is zero")
    return float(np.quantile(ny[ok] / nx[ok], q))


def lipschitz_nnls(y, U) -> np.ndarray:
    """Non-negative least-squares constants L (p,) with y ~ U @ L (U (n, p) >= 0)."""
    from scipy.optimize import nnls

    return nnls(np.asarray(U, float), np.asarray(y, float))[0]


def lipschitz_envelope(y, U) -> np.ndarray:
    """Smallest L >= 0 (minimising the mean bound mean(U @ L)) with U @ L >= y on every sample."""
    from scipy.optimize import linprog

    U, y = np.asarray(U, float), np.asarray(y, float)
    scale = np.maximum(U.mean(0), 1e-300)
    res = linprog(U.mean(0) / scale, A_ub=-(U / scale), b_ub=-y, bounds=[(0, None)] * U.shape[1], method="highs")
    if res.status != 0:
        raise ValueError(f"lipschitz_envelope: no finite envelope ({res.message})")
    return res.x / scale

# %%
U_check = rng_check.uniform(0, 1, (300, 3))
L_true = np.array([2.0, 0.5, 1.5])
y_check = U_check @ L_true
y_check[::2] *= 0.5  # half of the samples lie strictly inside the bound
L_env = lipschitz_envelope(y_check, U_check)
assert np.allclose(L_env, L_true, atol=1e-6)
print("true constants", L_true, "| envelope", L_env.round(6), "| least squares", lipschitz_nnls(y_check, U_check).round(3))

# %% [markdown]
# ## Reading the mixture-of-experts actor
#
# `moe_components` reads, for a batch of states, the tempered router logits $z$, the gating-noise
# scale $s = \mathrm{softplus}(n(s))$, every expert's mean $\mu_k$ and the common $\sigma$; the
# three weightings of notebook 08 (A4 mixture, sampling marginal, evaluation top-1) follow from
# them (`mixture_weights`; `top1_win_probs` integrates the sampling marginal's win probabilities
# by Gauss-Hermite quadrature). `perturb_actor` returns a copy with the router (weights and bias
# of the routing layer; the noise gate is left alone) and/or every expert moved by a random
# direction of *relative* size `scale` (a fraction of that part's norm).
# `tie_states` finds states exactly on a top-1 boundary, by bisecting between two states routed
# to different experts until the two top gate probabilities agree to ~1e-9.

# %%
#| export
DISTRIBUTIONS = ("a4_mixture", "sampling_marginal", "eval_top1")


@torch.no_grad()
def moe_components(actor, obs, temperature: float = 1.0) -> dict:
    """{"logits" (B, E), "noise_scale" (B, E), "gate" (B, E) softmax, "means" (B, E, A), "std" (A,)}."""
    gate = actor.gate
    x = torch.as_tensor(obs, dtype=torch.float32).reshape(-1, actor.obs_dim)
    logits = gate.router(x) / temperature
    scale = F.softplus(gate.noise_gate(x)) if gate.noisy else torch.zeros_like(logits)
    h = gate.experts.all_experts(x, "stacked")  # (E, B, H)
    means = actor.head(h).transpose(0, 1)  # (B, E, A)
    return {
        "logits": logits.double().numpy(),
        "noise_scale": scale.double().numpy(),
        "gate": torch.softmax(logits.double(), -1).numpy(),
        "means": means.double().numpy(),
        "std": actor.log_std.exp().double().numpy(),
    }


def top1_win_probs(logits, noise_scale, n_nodes: int = 96) -> np.ndarray:
    """P(k = argmax_j logits_j + noise_scale_j * eps_j), eps ~ N(0, I), by Gauss-Hermite quadrature.
    logits, noise_scale (B, E) -> (B, E); rows with a zero noise scale fall back to the hard argmax."""
    from scipy.special import log_ndtr

    z, s = np.asarray(logits, float), np.asarray(noise_scale, float)
    B, E = z.shape
    out = np.zeros((B, E))
    hard = (s <= 0).any(-1)
    out[hard, z[hard].argmax(-1)] = 1.0
    if (~hard).any():
        zz, ss = z[~hard], s[~hard]
        u, w = np.polynomial.hermite_e.hermegauss(n_nodes)
        w = w / w.sum()
        arg = (zz[None, :, :, None] + ss[None, :, :, None] * u[:, None, None, None] - zz[None, :, None, :]) / ss[None, :, None, :]
        logphi = log_ndtr(arg)  # (n, B', k, j)
        logphi[..., np.arange(E), np.arange(E)] = 0.0
        pk = np.einsum("n,nbk->bk", w, np.exp(logphi.sum(-1)))
        out[~hard] = pk / pk.sum(-1, keepdims=True)
    return out


def mixture_weights(comp: dict, distribution: str) -> np.ndarray:
    """Mixture weights (B, E) of one of DISTRIBUTIONS, from moe_components output."""
    if distribution == "a4_mixture":
        return comp["gate"]
    if distribution == "sampling_marginal":
        return top1_win_probs(comp["logits"], comp["noise_scale"])
    if distribution == "eval_top1":
        g = comp["gate"]
        return np.eye(g.shape[1])[g.argmax(-1)]
    raise ValueError(f"distribution must be one of {', '.join(DISTRIBUTIONS)}, got {distribution!r}")


def _flat(params):
    return torch.cat([p.detach().reshape(-1) for p in params])


@torch.no_grad()
def perturb_actor(actor, router_scale: float, expert_scale: float, rng: np.random.Generator, experts=None):
    """Copy of `actor` with the router and the experts in `experts` (None: all) moved by random directions
    of relative size router_scale / expert_scale. Returns (copy, ||delta router||, ||delta theta_k|| (E,))."""
    new = copy.deepcopy(actor)
    router = list(new.gate.router.parameters())
    d_router = 0.0
    if router_scale > 0:
        norm = float(_flat(router).norm())
        u = [rng.standard_normal(tuple(p.shape)) for p in router]
        un = math.sqrt(sum(float((v * v).sum()) for v in u))
        for p, v in zip(router, u):
            p.add_(torch.as_tensor(v * router_scale * norm / un, dtype=p.dtype))
        d_router = router_scale * norm
    E = n_experts_of(new)
    d_theta = np.zeros(E)
    if expert_scale > 0:
        for k in range(E) if experts is None else experts:
            params = expert_parameters(new, k)
            norm = float(_flat(params).norm())
            u = [rng.standard_normal(tuple(p.shape)) for p in params]
            un = math.sqrt(sum(float((v * v).sum()) for v in u))
            for p, v in zip(params, u):
                p.add_(torch.as_tensor(v * expert_scale * norm / un, dtype=p.dtype))
            d_theta[k] = expert_scale * norm
    return new, d_router, d_theta


@torch.no_grad()
def tie_states(actor, n: int, rng: np.random.Generator, temperature: float = 1.0, steps: int = 50) -> np.ndarray:
    """n states (n, obs_dim) on a top-1 boundary of the noiseless router (top-two probabilities equal)."""
    d = actor.obs_dim
    found = []
    for _ in range(50):
        x0, x1 = rng.standard_normal((4 * n, d)), rng.standard_normal((4 * n, d))
        arg = lambda x: moe_components(actor, x, temperature)["gate"].argmax(-1)
        k0 = arg(x0)
        ok = k0 != arg(x1)
        x0, x1, k0 = x0[ok], x1[ok], k0[ok]
        lo, hi = np.zeros(len(x0)), np.ones(len(x0))
        for _ in range(steps):
            mid = 0.5 * (lo + hi)
            same = arg(x0 + mid[:, None] * (x1 - x0)) == k0
            lo, hi = np.where(same, mid, lo), np.where(same, hi, mid)
        found.append(x0 + (0.5 * (lo + hi))[:, None] * (x1 - x0))
        if sum(len(f) for f in found) >= n:
            break
    return np.concatenate(found)[:n]


def routing_stability_samples(actor, states, perturbations, rng: np.random.Generator, n_samples: int = 256,
                              temperature: float = 1.0, tie=None):
    """For each (part, scale) in `perturbations`, perturb `actor` once and measure, per state and per
    distribution in DISTRIBUTIONS, the Monte-Carlo L1 distance between the action distributions and
    the bound terms. part: "router", "expert<k>" (one expert), "experts" (all) or "joint" (router and
    all experts). Returns a pandas DataFrame."""
    import pandas as pd

    states = np.asarray(states, float)
    tie = np.zeros(len(states), bool) if tie is None else np.asarray(tie, bool)
    before = moe_components(actor, states, temperature)
    w_before = {d: mixture_weights(before, d) for d in DISTRIBUTIONS}
    top2 = np.sort(before["gate"], -1)[:, -2:]
    gap = top2[:, 1] - top2[:, 0]
    frames = []
    for i, (part, sc) in enumerate(perturbations):
        one = part.startswith("expert") and part[6:].isdigit()
        if not (part in ("router", "experts", "joint") or one):
            raise ValueError(f"perturbation part must be router, expert<k>, experts or joint, got {part!r}")
        rs = sc if part in ("router", "joint") else 0.0
        es = sc if part in ("experts", "joint") or one else 0.0
        new, d_router, d_theta = perturb_actor(actor, rs, es, rng, [int(part[6:])] if one else None)
        after = moe_components(new, states, temperature)
        dg = np.abs(after["gate"] - before["gate"]).sum(-1)
        flipped = after["gate"].argmax(-1) != before["gate"].argmax(-1)
        for dist in DISTRIBUTIONS:
            wa = mixture_weights(after, dist)
            l1, se = mc_l1_distance((w_before[dist], before["means"], before["std"]),
                                    (wa, after["means"], after["std"]), rng, n_samples)
            row = {"draw": i, "part": part, "scale": sc, "distribution": dist, "state": np.arange(len(states)),
                   "tie": tie, "gap": gap, "flipped": flipped, "l1": l1, "l1_se": se, "dG": dg,
                   "dW": np.abs(wa - w_before[dist]).sum(-1), "d_router": d_router}
            for k in range(len(d_theta)):
                row[f"wdtheta_{k}"] = w_before[dist][:, k] * d_theta[k]
            frames.append(pd.DataFrame(row))
    return pd.concat(frames, ignore_index=True)

# %% [markdown]
# Checks on a fresh PE-MAMoE actor whose expert means are spread apart (as after training): the
# evaluation-top-1 mean read off the components is the actor's own deterministic mean; every
# weighting sums to one; the quadrature win probabilities match the routing frequencies of the
# actor's noisy gate; and `tie_states` returns states where the top two gate probabilities agree.

# %%
torch.manual_seed(seed)
probe_actor = make_actor("pemamoe", 4, 2, NetConfig(gain_router=1.0))
with torch.no_grad():
    probe_actor.head.weight.mul_(100.0)
x_probe = np.random.default_rng(seed).standard_normal((6, 4))
comp_probe = moe_components(probe_actor, x_probe)
with torch.no_grad():
    det_probe = probe_actor(torch.tensor(x_probe, dtype=torch.float32), deterministic_gate=True)[0].mean.double().numpy()
assert np.allclose(comp_probe["means"][np.arange(6), comp_probe["gate"].argmax(-1)], det_probe, atol=1e-6)
for dist in DISTRIBUTIONS:
    assert np.allclose(mixture_weights(comp_probe, dist).sum(-1), 1.0)
n_rep = by_scale(scale, ci=4000, small=20000, paper=50000)
with torch.no_grad():
    _, routing = probe_actor(torch.tensor(np.repeat(x_probe, n_rep, 0), dtype=torch.float32))
freq = np.stack([np.bincount(r, minlength=3) for r in routing.experts.reshape(6, n_rep).numpy()]) / n_rep
win = top1_win_probs(comp_probe["logits"], comp_probe["noise_scale"])
assert np.abs(freq - win).max() < 6 * 0.5 / math.sqrt(n_rep)
ties_probe = np.sort(moe_components(probe_actor, tie_states(probe_actor, 8, np.random.default_rng(seed)))["gate"], -1)
assert np.all(ties_probe[:, -1] - ties_probe[:, -2] < 1e-6)
tie_gap = np.max(ties_probe[:, -1] - ties_probe[:, -2])
print(f"win probabilities vs routing frequencies: max |diff| {np.abs(freq - win).max():.4f} "
      f"(sampling s.e. ~ {0.5 / math.sqrt(n_rep):.4f}); largest top-two gap at ties {tie_gap:.1e}")

# %%
print(f"appendix ran in {time.perf_counter() - T0:.1f} s at scale {scale!r}")
