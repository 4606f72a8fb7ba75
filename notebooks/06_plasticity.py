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
# # 06 · Plasticity: the phase controller (paper section IV-B)
#
# PE-MAMoE is the sparse MoE actor of notebook 05 plus a **phase controller**: a piece of
# bookkeeping, with no parameters and no gradient, that reacts to a regime switch. When the
# environment changes phase, the controller
#
# 1. keeps a frozen copy of the pre-switch actor and pulls the new policy towards it with a KL
#    penalty whose weight fades geometrically (**KL anchor**);
# 2. throws away Adam's running moments and step counters (**Adam reset**);
# 3. perturbs the expert trunks with small Gaussian noise, at the switch and after each of the
#    next $N$ update epochs, only on the experts the router actually used (**noise injection**);
# 4. widens the action distribution back to its initial spread (**log-std reset**);
# 5. restarts the entropy bonus at its initial value and anneals it again (**entropy reset**);
# 6. cuts the learning rate and ramps it back (**LR drop and warm-up**);
# 7. makes PPO more careful for a while: tighter clip range and KL budget (**conservative window**);
# 8. leaves the router untouched for a while (**router freeze**);
# 9. heats the router's softmax right after the switch and cools it afterwards (**temperature**).
#
# Each of the nine is behind its own switch in `PhaseControllerConfig`, so that an ablation removes
# exactly one of them and nothing else. With every switch off (or with `enabled=False`, the way the
# MLP, MoE and SMoE baselines run) the controller only reports the baselines' plain schedules.
#
# This notebook gives the mechanisms, their equations and the reference controller for one
# network, with pictures. The appendix `06b_population_plasticity.py` holds the machinery around
# them: the same controller acting on each member of a population of runs (what the trainer of
# notebook 07 calls), AdamW over a population's stacked parameters, the registry of plasticity
# methods, and the **plasticity diagnostics** the paper plots (feature rank, dormant units, router
# probabilities, mean action; `pemamoe/diagnostics.py`).

# %%
#| default_exp phase_controller

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %%
#| export
import copy
import math
from dataclasses import asdict, dataclass, fields

import numpy as np
import torch
from torch.distributions import kl_divergence

from pemamoe.core import require_field

# %% [markdown]
# ## What the paper fixes, and what it leaves open
#
# The numbers come from the "Switch-time schedules" block of the paper's Table II and from
# Algorithm 1; where the paper leaves a choice open, the last column says what we picked:
#
# | mechanism | paper | our value / reading |
# |---|---|---|
# | KL anchor | weight 0.1, × 0.985 per iteration, released "below a threshold" | release when the weight drops under $10^{-3}$, i.e. 305 iterations after the switch |
# | Adam reset | moments set to zero | moments **and** step counts (bias correction restarts); the param groups are kept |
# | noise | $\gamma_0 = 0.005$ for $N = 30$ epochs | at the switch on every expert, then after each update epoch on the experts selected in that epoch's data |
# | log-std reset | "0.3" | $\log\sigma \leftarrow \log 0.3$ (the initial spread, $\sigma = 0.3$) |
# | entropy | 0.01 → 0.003; reset and re-anneal within each phase | linear anneal over the first 30 % of the phase (the table's "anneal portion 0.3" applied to the phase instead of to training) |
# | LR | × 0.3 at the switch, warm back over 200 iterations | linear ramp $0.3 \to 1$ over 200 iterations, on every param group |
# | conservative PPO | "for $K_\text{warm} = 80$ iterations" | clip 0.15 → 0.10, target KL 0.10 → 0.05 |
# | router freeze | 30 iterations | learning rate 0 **and** no gradient for the policy router (and its noise gate) |
# | temperature | $\tau_{\min}, \tau_{\max}$ with a logistic formula | $\tau_{\min} = 1$, $\tau_{\max} = 2$, $\kappa = 20$, $\beta = 0.05$; high after the switch (see below) |
#
# A few readings need a word.
#
# **"Log-std reset 0.3".** Algorithm 1 writes "$\log\sigma \leftarrow \sigma_\text{init}$", which
# mixes the two quantities. Setting the log-std itself to 0.3 would mean $\sigma = e^{0.3} \approx
# 1.35$, a spread larger than the whole action box $[-1, 1]$: a reset to near-uniform random
# actions. Setting $\sigma = 0.3$ matches the actors' initial spread (notebook 05 initialises
# `log_std = log(0.3)`), so the reset returns the policy to the width it started training with,
# which is what "re-open exploration" after a switch asks for. We take $\sigma = 0.3$; the value is
# a config field, so the other reading is one argument away.
#
# **Two windows called "warm".** Algorithm 1 uses one $K_\text{warm}$ for both the LR warm-up
# and the conservative PPO window, while the table gives 80 iterations for the "warm window" and
# 200 for the LR warm-up. We follow the table, which names both windows: 80 for the conservative
# window, 200 for the LR ramp.
#
# **What "LR annealing" means in the ablation.** The ablation text describes resetting the LR
# to its initial value at a switch and annealing it down within the phase; Algorithm 1 and the
# table describe the opposite shape (drop, then warm back up). We implement the table's shape and
# let the ablation's "remove LR annealing" switch it off (`lr_drop=False`: constant LR, as for the
# baselines, whose table entry says "Anneal LR: False").
#
# **The conservative values.** The paper says "conservative" without numbers. We take a clip
# range of 0.10 instead of 0.15 and a target KL of 0.05 instead of 0.10: each about two thirds
# and one half of the base values, so the first post-switch updates move the policy less while
# the KL anchor is strongest, without stopping learning.
#
# **Noise at the switch.** Algorithm 1 perturbs every expert at the switch ($\forall j$) but only
# the selected experts $j \in \mathcal T_k$ after the update epochs. The difference looks
# deliberate (no batch exists at the moment of the switch), so we keep it. "Expert parameters"
# $\theta_j$ means the whole trunk of expert $j$: both layers' weights and biases. The router,
# the noise gate, the shared head and the log-std are never perturbed.
#
# **Router freeze and the critic.** The freeze protects the *policy* router (and its noise
# gate, which shapes the same routing decision). The value router lives in the critic's param
# group and keeps learning; the value function has to track the new rewards immediately.

# %% [markdown]
# ## Contradictions in the paper, and readings it leaves open
#
# **Temperature direction.** The text says the router temperature is raised right after a switch
# and lowered as the phase settles. The formula printed next to it,
# $$\tau(\Delta) = \tau_{\min} + \frac{\tau_{\max}-\tau_{\min}}{1 + \kappa e^{-\beta \Delta}},$$
# with $\Delta$ the time since the switch, does the opposite: it starts near
# $\tau_{\min} + (\tau_{\max}-\tau_{\min})/(1+\kappa)$ and climbs to $\tau_{\max}$. We implement the
# text's intent with the mirror image of the same curve,
# $$\tau(\Delta) = \tau_{\max} - \big(\tau_\text{formula}(\Delta) - \tau_{\min}\big)
#  = \tau_{\min} + \frac{\tau_{\max}-\tau_{\min}}{1 + \kappa^{-1} e^{\beta \Delta}},$$
# which uses the same $\kappa$ and $\beta$, starts at $\tau_{\min} + (\tau_{\max}-\tau_{\min})
# \kappa/(1+\kappa)$ and cools to $\tau_{\min}$, with its midpoint at $\Delta = \ln\kappa/\beta$.
# Why the text wins: the stated goal is diverse routing *while the new regime is being learned*;
# a temperature that is lowest at the switch and highest deep into a stable phase would sharpen
# routing exactly when it should be soft, and blur it once the experts have re-specialised.
# With $\kappa = 20$ and $\beta = 0.05$ the router starts at $\tau \approx 1.95$, crosses the
# midpoint 1.5 at $\Delta \approx 60$ iterations (around the end of the router freeze and the
# conservative window) and is back at 1.0 within about 150 iterations. $\tau_{\min} = 1$ is the
# baselines' temperature, so outside the post-switch transient PE-MAMoE routes exactly like SMoE.
# The same temperature goes to the value router (configurable).
#
# **The learning-rate factor on the noise.** The paper's update equation adds
# $\eta_t \gamma_t \varepsilon_j$ (noise scaled by the learning rate), Algorithm 1 adds
# $\gamma_0 \varepsilon_j$ (no learning rate). The two differ by a factor $\eta \approx 3\cdot
# 10^{-4}$ (or $0.9\cdot 10^{-4}$ during the LR drop): with the factor, noise of standard deviation
# $\approx 10^{-6}$ is far below the Adam step itself and below what could plausibly move the
# ablation's coverage by the reported amounts, and the "noise threshold" sweep
# $\gamma \in \{0.001, 0.005, 0.01\}$ would be a sweep over invisibly small perturbations. Without
# the factor, $\gamma = 0.005$ is a few percent of a typical trunk weight (orthogonal init with
# gain $\sqrt 2$ at width 32 gives weights of size $\approx 0.1$–$0.25$), a real but modest
# shake. We follow Algorithm 1 by default; `noise_lr_factor=True` gives the equation's reading.
#
# **The length of the noise window.** Algorithm 1 injects noise for N = 30 update *epochs* after a
# switch. The paper's cost paragraph counts its ~10,800 training iterations as "epochs" ("N = 30
# epochs out of ~10,800"), which would make the window 30 *iterations* of 8 epochs each, 8 times
# longer. We keep Algorithm 1's reading by default; `noise_window_unit="iterations"` gives the other.
#
# **A dense or a gated critic?** The text says the centralised critic "remains dense", while the
# architecture figure draws a critic MoE encoder and the results plot value-router probabilities.
# We build each method's critic with the actor's network kind (so the gated methods have a gated
# critic with its own router, and the value-router figures exist), and we compute every value the
# advantage estimates use with **noiseless** gating (notebook 07), so that gate noise does not add
# variance to the baseline of the gated methods only.
#
# **Is the phase observable?** In the `cycle` demand mode every user's class one-hot in the
# observation changes with the phase, so an agent can read the regime off its input. The paper
# says the agents infer the regime from demand, which is what this does; the `mix` mode and the
# held-out regime make the inference less direct. We note it because it makes the switches easier
# to detect than a hidden change of dynamics would be.

# %% [markdown]
# ## Configuration
#
# Two frozen dataclasses. `PhaseControllerConfig` holds the switches and the switch-time numbers
# (the PE-MAMoE part). `BaseSchedule` holds what every method shares with PPO (learning rate,
# clip, target KL, entropy schedule, run and phase lengths, the router temperature); the trainer
# builds it from its own PPO config so there is one source for each number.

# %%
#| export
TEMPERATURE_TARGETS = ("policy", "value", "both")
NOISE_WINDOW_UNITS = ("epochs", "iterations")
GROUP_NAMES = ("router", "experts", "head", "log_std", "critic")


@dataclass(frozen=True)
class PhaseControllerConfig:
    """Switch-time mechanisms of PE-MAMoE (paper Algorithm 1); each has its own on/off switch."""

    # KL anchor to the pre-switch actor
    kl_anchor: bool = True
    kl_coef: float = 0.1
    kl_decay: float = 0.985  # per iteration
    kl_release: float = 1e-3  # the reference is dropped once the weight falls below this
    # Adam moments and step counts
    adam_reset: bool = True
    # expert-only Gaussian noise
    noise_injection: bool = True
    noise_gamma: float = 0.005
    noise_epochs: int = 30  # N: update epochs after the switch that get noise
    noise_lr_factor: bool = False  # True: std = gamma * lr (the paper's equation), False: gamma (Algorithm 1)
    noise_window_unit: str = "epochs"  # N counts update epochs (Algorithm 1) or "iterations" (cost paragraph)
    # log-std reset
    log_std_reset: bool = True
    log_std_value: float = math.log(0.3)
    # entropy coefficient reset and re-anneal within the phase
    entropy_reset: bool = True
    entropy_phase_portion: float = 0.3  # fraction of the phase over which it anneals
    # learning-rate drop and linear warm-up
    lr_drop: bool = True
    lr_drop_factor: float = 0.3
    lr_warmup_iters: int = 200
    # conservative PPO window
    conservative_window: bool = True
    conservative_iters: int = 80
    conservative_clip: float = 0.1
    conservative_target_kl: float = 0.05
    # router freeze
    router_freeze: bool = True
    router_freeze_iters: int = 30
    # router temperature (text's reading: hot after the switch, cooling to tau_min)
    temperature_schedule: bool = True
    tau_min: float = 1.0
    tau_max: float = 2.0
    tau_kappa: float = 20.0
    tau_beta: float = 0.05
    temperature_routers: str = "both"

    def __post_init__(self):
        for f in fields(self):
            if f.type in (bool, "bool"):
                require_field(self, f.name, "bool")
        require_field(self, "kl_coef", "real", ge=0)
        require_field(self, "kl_decay", "real", gt=0, le=1)
        require_field(self, "kl_release", "real", ge=0)
        require_field(self, "noise_gamma", "real", ge=0)
        require_field(self, "noise_epochs", "int", ge=0)
        require_field(self, "noise_window_unit", "choice", NOISE_WINDOW_UNITS)
        require_field(self, "log_std_value", "real")
        require_field(self, "entropy_phase_portion", "real", gt=0, le=1)
        require_field(self, "lr_drop_factor", "real", ge=0, le=1)
        for name in ("lr_warmup_iters", "conservative_iters", "router_freeze_iters"):
            require_field(self, name, "int", ge=0)
        require_field(self, "conservative_clip", "real", gt=0)
        require_field(self, "conservative_target_kl", "real", gt=0)
        require_field(self, "tau_min", "real", gt=0)
        require_field(self, "tau_max", "real", ge=self.tau_min)
        require_field(self, "tau_kappa", "real", gt=0)
        require_field(self, "tau_beta", "real", ge=0)
        require_field(self, "temperature_routers", "choice", TEMPERATURE_TARGETS)

    def without(self, mechanism: str) -> "PhaseControllerConfig":
        """The same config with one mechanism switched off (for ablations), e.g. .without("noise_injection")."""
        if mechanism not in MECHANISMS:
            raise ValueError(f"PhaseControllerConfig.without: mechanism must be one of {', '.join(MECHANISMS)}, got {mechanism!r}")
        return PhaseControllerConfig(**{**asdict(self), mechanism: False})


MECHANISMS = (
    "kl_anchor",
    "adam_reset",
    "noise_injection",
    "log_std_reset",
    "entropy_reset",
    "lr_drop",
    "conservative_window",
    "router_freeze",
    "temperature_schedule",
)


@dataclass(frozen=True)
class BaseSchedule:
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


# %% [markdown]
# ## The schedules as pure functions
#
# Every schedule is a function of two clocks: the global iteration $t$ and the time since the
# last switch $\Delta = t - t_s$ (in iterations). They work on scalars and on NumPy arrays, which
# keeps the controller itself small and lets the plots below call the very code the trainer runs.
#
# * **LR multiplier** $m(\Delta) = f + (1-f)\min(\Delta / W, 1)$ with $f = 0.3$, $W = 200$: the
#   iteration of the switch trains at $0.3\,\alpha_0$, iteration $t_s + 100$ at $0.65\,\alpha_0$,
#   and from $t_s + 200$ on at $\alpha_0$ again.
# * **KL weight** $\lambda(\Delta) = 0.1 \cdot 0.985^{\Delta}$ while it is at least $10^{-3}$, then
#   0 (the reference is released): $0.985^{\Delta} < 0.01$ first holds at $\Delta = 305$.
# * **Entropy coefficient**: a linear ramp from 0.01 to 0.003 over the first 30 % of the span being
#   annealed, then flat at 0.003. The span is the whole run for the baselines (the table's
#   "anneal portion 0.3 of training") and the current phase for PE-MAMoE with the reset
#   (0.3 × 1200 = 360 iterations after each switch; the first phase starts at iteration 0).
#   The temperature, too, treats iteration 0 as the start of the first phase; the switch-only
#   mechanisms (KL anchor, LR drop, windows, noise) wait for the first real switch.
# * **Windows**: the conservative PPO values hold for $\Delta < 80$, the router is frozen for
#   $\Delta < 30$.
# * **Temperature**: the two curves of the previous section.

# %%
#| export
def lr_multiplier(since, cfg: PhaseControllerConfig):
    """LR factor at `since` iterations after a switch: drop_factor at 0, linear back to 1 at lr_warmup_iters."""
    since = np.asarray(since, dtype=float)
    if cfg.lr_warmup_iters == 0:
        ramp = np.ones_like(since)
    else:
        ramp = np.clip(since / cfg.lr_warmup_iters, 0.0, 1.0)
    return cfg.lr_drop_factor + (1.0 - cfg.lr_drop_factor) * ramp


def kl_anchor_coef(since, cfg: PhaseControllerConfig):
    """KL-to-reference weight `since` iterations after a switch (0 once released below kl_release)."""
    since = np.asarray(since, dtype=float)
    coef = cfg.kl_coef * cfg.kl_decay**since
    return np.where(coef >= cfg.kl_release, coef, 0.0) if cfg.kl_coef > 0 else np.zeros_like(since)


def temperature_text(since, cfg: PhaseControllerConfig):
    """Router temperature after a switch, the paper's text: hot right after the switch, cooling to tau_min."""
    since = np.asarray(since, dtype=float)
    # tau_min + (tau_max - tau_min) / (1 + exp(beta * since) / kappa), written overflow-free
    z = np.log(cfg.tau_kappa) - cfg.tau_beta * since
    return cfg.tau_min + (cfg.tau_max - cfg.tau_min) * (0.5 * (1.0 + np.tanh(0.5 * z)))


def temperature_formula(since, cfg: PhaseControllerConfig):
    """The paper's printed formula tau_min + (tau_max - tau_min) / (1 + kappa exp(-beta since)): it RISES."""
    since = np.asarray(since, dtype=float)
    z = cfg.tau_beta * since - np.log(cfg.tau_kappa)
    return cfg.tau_min + (cfg.tau_max - cfg.tau_min) * (0.5 * (1.0 + np.tanh(0.5 * z)))


def linear_anneal(step, span, start: float, end: float):
    """start -> end linearly over `span` steps, then flat at `end`."""
    frac = np.clip(np.asarray(step, dtype=float) / span, 0.0, 1.0)
    return start + (end - start) * frac


def entropy_coef(iteration, since_phase, base: BaseSchedule, cfg: PhaseControllerConfig | None):
    """Entropy coefficient: over the run (cfg None or entropy_reset False), or re-annealed within each phase."""
    if cfg is not None and cfg.entropy_reset:
        span = max(cfg.entropy_phase_portion * base.phase_length, 1e-12)
        return linear_anneal(since_phase, span, base.ent_start, base.ent_end)
    span = max(base.ent_anneal_portion * base.total_iterations, 1e-12)
    return linear_anneal(iteration, span, base.ent_start, base.ent_end)


# %% [markdown]
# ## Noise injection on expert trunks
#
# The noise touches the trunk of each chosen expert: in the stacked `ExpertBank` that is slice
# `[j]` of `w1`, `b1`, `w2` and `b2`; for the MLP actor, whose trunk is its single "expert" 0,
# the two hidden layers. Each scalar gets an independent $\mathcal N(0, \sigma^2)$ draw from a
# dedicated `torch.Generator` (so a checkpoint can resume the exact noise sequence, and the noise
# does not disturb the global RNG that drives rollouts). The expected squared size of one
# injection is $\sigma^2$ times the number of perturbed scalars, which is the "noise energy" the
# paper's regret bound accumulates.
#
# `selected` may be anything holding expert indices (a `RoutingSample.experts` tensor of any shape,
# a list) or a boolean mask of length $E$; `None` means every expert.

# %%
#| export
def expert_parameters(actor, expert: int) -> list:
    """Views of the trunk parameters of one expert, as the actor names them (`trunk_parameters`):
    a whole parameter for an unstacked trunk (the MLP's single expert 0), slice `expert` of a
    stacked (E, ...) one."""
    n = n_experts_of(actor)
    if not (isinstance(expert, int) and 0 <= expert < n):
        raise ValueError(f"expert index must be in [0, {n}), got {expert!r}")
    params = dict(actor.named_parameters())
    return [params[name] if e is None else params[name][e]
            for name, e in actor.trunk_parameters() if e is None or e == expert]


def n_experts_of(actor) -> int:
    """Number of experts: the distinct expert indices the actor's trunk names (1 for an unstacked trunk)."""
    return len({0 if e is None else e for _, e in actor.trunk_parameters()})


def selected_expert_ids(selected, n_experts: int) -> list:
    """Sorted distinct expert indices from indices of any shape, a boolean mask of length E, or None (all)."""
    if selected is None:
        return list(range(n_experts))
    sel = torch.as_tensor(selected)
    if sel.dtype == torch.bool:
        if sel.numel() != n_experts:
            raise ValueError(f"a boolean expert mask must have {n_experts} entries, got {sel.numel()}")
        return [int(i) for i in torch.nonzero(sel.reshape(-1)).reshape(-1)]
    ids = sorted({int(i) for i in torch.unique(sel.reshape(-1).long())})
    if ids and (ids[0] < 0 or ids[-1] >= n_experts):
        raise ValueError(f"expert indices must be in [0, {n_experts}), got {ids}")
    return ids


@torch.no_grad()
def inject_expert_noise(actor, experts, std: float, generator: torch.Generator) -> int:
    """Add N(0, std^2) to every trunk parameter of each expert in `experts`; return the number of scalars noised."""
    count = 0
    for e in experts:
        for p in expert_parameters(actor, e):
            noise = torch.randn(p.shape, generator=generator, dtype=p.dtype, device=generator.device)
            p.add_(noise.to(p.device), alpha=std)
            count += p.numel()
    return count


def reset_adam_state(optimizer) -> None:
    """Forget every moment estimate and step count; param groups (and their LRs) stay as they are."""
    optimizer.state.clear()


# %% [markdown]
# ## Freezing the router so that it really does not move
#
# Setting the router's learning rate to zero is not enough on its own with every optimizer
# configuration, and a zero gradient is not enough at all: Adam keeps applying its momentum for
# several steps after the gradient vanishes, and AdamW's decoupled weight decay shrinks a parameter
# every step whether or not it has a gradient. What PyTorch's Adam/AdamW do skip entirely is a
# parameter whose `.grad` is `None`. So during the freeze the controller
#
# * switches `requires_grad` off on the policy router and its noise gate (backward then leaves
#   their `.grad` at `None`, and any stale `.grad` is dropped), and
# * sets the learning rate of the optimizer's `"router"` group to 0 as a second line of defence
#   (for a trainer that zeroes gradients in place instead of setting them to `None`).
#
# The test suite checks bit-identity with a real AdamW (weight decay on) stepping a real actor.
# A frozen router still *routes*: the forward pass is unchanged, only its parameters stay put.

# %% [markdown]
# ## The controller
#
# How one network is trained with it, per iteration $t$ (every call below exists; the comments
# stand for the PPO code of notebook 07). The trainer of notebook 07 runs the population version of
# appendix 06b with the same clock and hooks of the same names.
#
# ```python
# groups = build_param_groups(actor, critic, base.lr)           # named groups
# opt = torch.optim.AdamW(groups, lr=base.lr, betas=(0.9, 0.999), weight_decay=1e-4)
# ctl = PhaseController(cfg, actor, opt, base, enabled=True)    # enabled=False: a baseline
# clock = PhaseSchedule(period=base.phase_length, n_phases=3)   # pemamoe.phases (notebook 03)
# for t in range(base.total_iterations):
#     venv.set_phase(clock.phase_at(t))   # first, so the whole rollout runs in this phase
#     if clock.is_switch(t):              # the phase differs from iteration t - 1's
#         ctl.on_switch(t)
#     s = ctl.begin_iteration(t)          # writes the LRs into opt, applies the router freeze
#     # rollout: action, logp_old, routing = actor.act(obs, temperature=s.policy_temperature);
#     #          values from critic(state, s.value_temperature, deterministic_gate=True); advantages adv
#     for epoch in range(8):
#         for obs, act, logp_old, adv, routing in minibatches:   # routing: the rollout's, replayed
#             logp, ent, aux = actor.evaluate(obs, act, routing)
#             ratio = (logp - logp_old).exp()
#             pg = -torch.min(ratio * adv, ratio.clamp(1 - s.clip_coef, 1 + s.clip_coef) * adv).mean()
#             loss = pg - s.ent_coef * ent.mean() + aux["aux_loss"] + ctl.kl_penalty(obs, routing)  # + value loss
#             opt.zero_grad(set_to_none=True); loss.backward(); opt.step()
#         # (stop the epochs early once the approximate KL exceeds s.target_kl)
#         ctl.after_epoch(rollout_routing.experts)   # noise on the experts the epoch's data used
# ```
#
# `on_switch` runs the switch-time actions in Algorithm 1's order: snapshot (before any
# perturbation, so the anchor is the pre-switch policy), Adam reset, noise on every expert, windows
# start, log-std reset; the entropy, LR, clip and temperature changes follow from the new
# $\Delta = 0$. All state a resume needs is in `state_dict()`: the switch time, the remaining noise
# epochs, the reference actor's weights and the noise generator's state. (The optimizer's state
# and the actor are checkpointed by the trainer as usual.)
#
# **KL to the reference, and routing.** `kl_penalty` evaluates both actors on the same
# minibatch with the *same stored routing* (the gate noise, expert choice and temperature drawn in
# the rollout, replayed through the `routing=` argument). The reference then answers the question
# "what mean and spread would the pre-switch weights give for this observation through this
# expert?", and the KL is the closed form between the two diagonal Gaussians, averaged over the
# batch: $\mathrm{KL}(\pi_\theta \,\|\, \pi_\text{ref})$, with gradient only through $\pi_\theta$.
# Passing `dist=` (the current distribution, if the trainer already has it) saves one forward.

# %%
#| export
@dataclass(frozen=True)
class IterationSettings:
    """What the trainer uses in one iteration (returned by PhaseController.begin_iteration)."""

    iteration: int
    since_switch: int | None  # iterations since the last switch (None before the first)
    lr: dict  # {param group name: learning rate}
    clip_coef: float
    target_kl: float | None
    ent_coef: float
    kl_coef: float  # 0 when off, before the first switch, or once released
    policy_temperature: float
    value_temperature: float
    router_frozen: bool
    conservative: bool
    noise_epochs_left: int


def build_param_groups(actor, critic=None, lr: float = 3e-4) -> list:
    """Optimizer param groups named router/experts/head/log_std (actor) and critic; empty groups are left out."""
    named = dict(actor.param_groups())
    if critic is not None:
        named.update(critic.param_groups())
    return [{"name": name, "params": list(params), "lr": lr} for name, params in named.items() if len(params)]


class PhaseController:
    """Non-gradient switch-time schedules of PE-MAMoE (paper Algorithm 1); enabled=False is the baselines' no-op."""

    def __init__(self, cfg: PhaseControllerConfig, actor, optimizer, base: BaseSchedule | None = None, enabled: bool = True, seed: int = 0):
        self.cfg, self.actor, self.optimizer = cfg, actor, optimizer
        self.base = base or BaseSchedule()
        self.enabled = bool(enabled)
        for group in optimizer.param_groups:
            if "name" not in group:
                raise ValueError("PhaseController needs optimizer param groups with a 'name' key (see build_param_groups)")
        self._router_params = list(actor.param_groups().get("router", []))
        device = next(actor.parameters()).device
        self.generator = torch.Generator(device=device)
        self.generator.manual_seed(int(seed))
        self.last_switch: int | None = None
        self.switches = 0
        self.noise_left = 0
        self.reference = None
        self.settings: IterationSettings | None = None
        self.last_noised: list = []

    # --- switch-time actions -------------------------------------------------------------------
    def on_switch(self, iteration: int) -> None:
        """A phase switch happens at `iteration` (call before begin_iteration of the same iteration)."""
        if self.last_switch is not None and iteration < self.last_switch:
            raise ValueError(f"switch iteration must not go back in time: {iteration} < {self.last_switch}")
        self.last_switch, self.switches = int(iteration), self.switches + 1
        self.last_noised = []
        if not self.enabled:
            return
        cfg = self.cfg
        if cfg.kl_anchor and cfg.kl_coef > 0:
            self.reference = self._snapshot()
        if cfg.adam_reset:
            reset_adam_state(self.optimizer)
        if cfg.noise_injection:
            self.last_noised = list(range(n_experts_of(self.actor)))
            inject_expert_noise(self.actor, self.last_noised, self._noise_std(0), self.generator)
            self.noise_left = cfg.noise_epochs
        if cfg.log_std_reset:
            with torch.no_grad():
                self.actor.log_std.fill_(cfg.log_std_value)

    def _snapshot(self):
        ref = copy.deepcopy(self.actor)
        for p in ref.parameters():
            p.requires_grad_(False)
        return ref.eval()

    def _noise_std(self, since: int) -> float:
        std = self.cfg.noise_gamma
        if self.cfg.noise_lr_factor:
            lr = self.base.lr * (float(lr_multiplier(since, self.cfg)) if self.cfg.lr_drop else 1.0)
            std *= lr
        return std

    # --- per-iteration schedule ----------------------------------------------------------------
    def begin_iteration(self, iteration: int) -> IterationSettings:
        """Settings for `iteration`; also writes the LRs into the optimizer and applies the router freeze."""
        b, cfg = self.base, self.cfg
        since = None if self.last_switch is None else int(iteration) - self.last_switch
        if since is not None and since < 0:
            raise ValueError(f"iteration {iteration} is before the last switch {self.last_switch}")
        since_phase = int(iteration) if since is None else since
        on = self.enabled
        active = on and since is not None

        mult = float(lr_multiplier(since, cfg)) if active and cfg.lr_drop else 1.0
        frozen = active and cfg.router_freeze and since < cfg.router_freeze_iters
        conservative = active and cfg.conservative_window and since < cfg.conservative_iters
        kl = float(kl_anchor_coef(since, cfg)) if active and cfg.kl_anchor else 0.0
        if kl == 0.0:
            self.reference = None  # released (or never taken)
        # inert before the first switch: the base schedule, as without the controller
        ent = float(entropy_coef(iteration, since_phase, b, cfg if active else None))
        tau = float(temperature_text(since_phase, cfg)) if active and cfg.temperature_schedule else b.temperature
        tau_pol = tau if cfg.temperature_routers in ("policy", "both") else b.temperature
        tau_val = tau if cfg.temperature_routers in ("value", "both") else b.temperature

        lrs = {}
        for group in self.optimizer.param_groups:
            lr = 0.0 if (frozen and group["name"] == "router") else b.lr * mult
            group["lr"] = lr
            lrs[group["name"]] = lr
        self._freeze_router(frozen)

        self.settings = IterationSettings(
            iteration=int(iteration),
            since_switch=since,
            lr=lrs,
            clip_coef=cfg.conservative_clip if conservative else b.clip_coef,
            target_kl=cfg.conservative_target_kl if conservative else b.target_kl,
            ent_coef=ent,
            kl_coef=kl,
            policy_temperature=tau_pol,
            value_temperature=tau_val,
            router_frozen=frozen,
            conservative=conservative,
            noise_epochs_left=self.noise_left,
        )
        return self.settings

    def _freeze_router(self, frozen: bool) -> None:
        for p in self._router_params:
            p.requires_grad_(not frozen)
            if frozen:
                p.grad = None

    # --- inside the update ---------------------------------------------------------------------
    def kl_penalty(self, obs, routing=None, dist=None) -> torch.Tensor:
        """kl_coef * mean KL(pi_theta || pi_ref) on `obs` with the stored `routing` replayed; 0 when off or released."""
        coef = 0.0 if self.settings is None else self.settings.kl_coef
        if coef == 0.0 or self.reference is None:
            return self.actor.log_std.new_zeros(())
        if routing is None and getattr(getattr(self.actor, "gate", None), "noisy", False):
            raise ValueError("kl_penalty needs the stored routing for a noisy-gated actor (both actors must route alike)")
        if dist is None:
            dist, _ = self.actor(obs, None, routing)
        with torch.no_grad():
            ref_dist, _ = self.reference(obs, None, routing)
        return coef * kl_divergence(dist, ref_dist).mean()

    def after_epoch(self, selected_experts=None) -> list:
        """End of one update epoch: noise on the selected experts while the N-epoch window lasts. Returns the experts noised."""
        self.last_noised = []
        if not (self.enabled and self.cfg.noise_injection) or self.noise_left <= 0:
            return []
        ids = selected_expert_ids(selected_experts, n_experts_of(self.actor))
        since = 0 if self.settings is None or self.settings.since_switch is None else self.settings.since_switch
        inject_expert_noise(self.actor, ids, self._noise_std(since), self.generator)
        self.noise_left -= 1
        self.last_noised = ids
        return ids

    # --- checkpointing -------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "cfg": asdict(self.cfg),
            "base": asdict(self.base),
            "enabled": self.enabled,
            "last_switch": self.last_switch,
            "switches": self.switches,
            "noise_left": self.noise_left,
            "reference": None if self.reference is None else copy.deepcopy(self.reference.state_dict()),
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        if state["cfg"] != asdict(self.cfg) or state["base"] != asdict(self.base) or state["enabled"] != self.enabled:
            raise ValueError("PhaseController.load_state_dict: the checkpoint was made with a different config")
        self.last_switch, self.switches, self.noise_left = state["last_switch"], state["switches"], state["noise_left"]
        self.generator.set_state(state["generator"])
        if state["reference"] is None:
            self.reference = None
        else:
            self.reference = self._snapshot()
            self.reference.load_state_dict(state["reference"])
        self.settings = None


# %% [markdown]
# ## What the trainer runs
#
# The trainer (notebook 07) trains R runs at once, their parameters stacked on a leading run axis
# (appendix 05b), so it calls the population twin of this controller, `PhaseControllerMethod`
# (appendix 06b): the same config, the same schedule functions and one `IterationSettings` per
# member, acting on each member's row of the parameters and of the optimizer state. The baselines
# run `NoPlasticity` there, the shared PPO schedule and nothing else.
#
# Three of its choices differ from a literal reading of Algorithm 1, which this notebook's
# reference controller follows; each is a documented choice:
#
# * **The critic keeps learning.** The learning-rate drop and the Adam reset act on the actor's
#   parameter groups only. The text above says the critic must keep tracking the new phase's
#   returns; the paper's per-group scheduling allows it, and slowing the critic would slow the
#   very advantage estimates the actor needs after a switch.
# * **The KL anchor does not undo the log-std reset.** The anchor's reference is the pre-switch
#   actor, but with its log-std set to the reset value. Anchored on the narrowed pre-switch sigma,
#   the KL term's pull on log sigma (for sigma_ref = 0.2 about 0.125 per dimension at weight 0.1)
#   is about 12 times the entropy bonus's push, and it undid the reset within tens of iterations
#   (observed with the code before `4233dde`, the commit that fixed it),
#   well inside the anchor window. A test checks that the logged log-std stays at the reset value
#   through the anchor window (up to what the policy gradient itself does).
# * **"Noise only on the selected experts" is weighted by use.** After each update epoch, expert
#   e of a member receives noise with standard deviation gamma x (its share of the epoch's routing
#   slots). With top-1 routing over thousands of rows, the union of the experts selected in an
#   epoch is every expert, so the literal reading perturbs all of them equally; weighting by share
#   perturbs the experts in proportion to how much they were used, and leaves an unused expert
#   alone. The switch-time injection itself still perturbs every expert with the full gamma.

# %% [markdown]
# ## The schedules over three phases
#
# A short run with the paper's values (1,200-iteration phases would flatten the plots, so the
# demonstration uses 400-iteration phases; every window keeps its paper length). The bottom-right
# panel shows both readings of the temperature formula.

# %%
import matplotlib.pyplot as plt

from pemamoe.core import by_scale, save_figure

torch.manual_seed(seed)
demo_phase = 400
demo_base = BaseSchedule(total_iterations=3 * demo_phase, phase_length=demo_phase)
cfg = PhaseControllerConfig()

# %%
from pemamoe.nets import make_actor, make_critic

obs_dim, state_dim = by_scale(scale, ci=24, small=64, paper=177), by_scale(scale, ci=32, small=96, paper=240)


def fresh_controller(enabled=True, config=cfg):
    """A new actor, critic, AdamW over named groups, and a controller on them."""
    a, c = make_actor("smoe", obs_dim), make_critic("smoe", state_dim)
    o = torch.optim.AdamW(build_param_groups(a, c, demo_base.lr), lr=demo_base.lr, weight_decay=1e-4)
    return PhaseController(config, a, o, demo_base, enabled=enabled, seed=seed)


def trace(controller, iterations, phase_length, epochs=8):
    """Drive the controller's clock (no training): settings per iteration."""
    rows = []
    for t in iterations:
        if t > 0 and t % phase_length == 0:
            controller.on_switch(t)
        rows.append(controller.begin_iteration(t))
        for _ in range(epochs):
            controller.after_epoch(None)
    return rows


its = np.arange(demo_base.total_iterations)
pe = trace(fresh_controller(), its, demo_phase)
bl = trace(fresh_controller(enabled=False), its, demo_phase)

fig, axes = plt.subplots(2, 3, figsize=(13, 6.5))
switches = [t for t in its if t > 0 and t % demo_phase == 0]


def mark(ax):
    for t in switches:
        ax.axvline(t, color="0.6", lw=0.8, ls=":")


ax = axes[0, 0]
ax.plot(its, [s.lr["experts"] / demo_base.lr for s in pe], label="experts / head / critic")
ax.plot(its, [s.lr["router"] / demo_base.lr for s in pe], label="policy router", ls="--")
ax.plot(its, [s.lr["experts"] / demo_base.lr for s in bl], label="baselines", color="k", lw=0.8)
ax.set_title("LR multiplier")
ax.legend(fontsize=7)
ax = axes[0, 1]
ax.plot(its, [s.ent_coef for s in pe], label="PE-MAMoE (reset per phase)")
ax.plot(its, [s.ent_coef for s in bl], label="baselines (30 % of run)", color="k", lw=0.8)
ax.set_title("entropy coefficient")
ax.legend(fontsize=7)
ax = axes[0, 2]
ax.plot(its, [s.kl_coef for s in pe])
ax.set_yscale("symlog", linthresh=1e-3)
ax.set_title("KL-to-reference weight (0 = released)")
ax = axes[1, 0]
ax.plot(its, [s.clip_coef for s in pe], label="clip")
ax.plot(its, [s.target_kl for s in pe], label="target KL")
ax.fill_between(its, 0, 0.2, where=[s.router_frozen for s in pe], color="C3", alpha=0.25, label="router frozen")
ax.set_title("conservative PPO window and router freeze")
ax.legend(fontsize=7)
ax = axes[1, 1]
# the noise window is counted in update epochs (8 per iteration): zoom on one switch
zoom = fresh_controller()
zoom.on_switch(0)
epoch_std = [cfg.noise_gamma]  # epoch "0": the injection at the switch itself (every expert)
for t in range(6):
    zoom.begin_iteration(t)
    for _ in range(8):
        epoch_std.append(cfg.noise_gamma if zoom.after_epoch(None) else 0.0)
ax.stem(np.arange(len(epoch_std)), epoch_std, basefmt=" ")
ax.set_title(f"noise std per update epoch after a switch (N = {cfg.noise_epochs})", fontsize=10)
ax.set_xlabel("update epochs since the switch (0 = at the switch)")
ax = axes[1, 2]
ax.plot(its, [s.policy_temperature for s in pe], label="implemented (text: hot, then cools)")
ax.plot(its, [float(temperature_formula(t % demo_phase, cfg)) for t in its], ls="--", label="printed formula (rises)")
ax.set_title("router temperature")
ax.legend(fontsize=7)
for ax in (*axes[0], axes[1, 0], axes[1, 2]):
    mark(ax)
for ax in (axes[1, 0], axes[1, 2]):
    ax.set_xlabel("training iteration")
fig.tight_layout()
save_figure(fig, "plasticity_schedules", figures_dir)

# %% [markdown]
# Hand checks against the formulas above: the LR multiplier is 0.3 at a switch, 0.65 a hundred
# iterations later and 1 after two hundred; the KL weight is released 305 iterations after the
# switch; the temperature starts at $1 + 20/21 \approx 1.952$.

# %%
s0 = pe[demo_phase]
assert s0.since_switch == 0 and math.isclose(s0.lr["experts"], 0.3 * demo_base.lr) and s0.lr["router"] == 0.0
assert math.isclose(pe[demo_phase + 100].lr["experts"], 0.65 * demo_base.lr)
assert pe[demo_phase + 304].kl_coef > 0 and pe[demo_phase + 305].kl_coef == 0
assert math.isclose(s0.policy_temperature, 1 + 20 / 21)
assert all(s.kl_coef == 0 and s.policy_temperature == 1.0 for s in bl)
print("release after", int(np.ceil(np.log(cfg.kl_release / cfg.kl_coef) / np.log(cfg.kl_decay))), "iterations")

# %% [markdown]
# Appendix 06b continues with a switch on a real actor (which parameters move, the router freeze
# through a real optimizer step) and with the plasticity diagnostics before and after it.
