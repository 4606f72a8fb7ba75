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
# # 03 · User mobility and the phase model
#
# The environment is non-stationary on purpose. A *phase* is a regime of the disaster scene: how
# fast and how erratically people move, how far a UAV can serve, how much crowding of UAVs is
# penalised, and what data rate each user asks for. Phases switch abruptly, and the agents are
# never told which phase they are in; they can only notice its consequences.
#
# This notebook builds the two halves of that:
#
# * `pemamoe/mobility.py`: users grouped around a few hotspots whose centres wander across the
#   area (reference-point group mobility, RPGM), each user following its group with a
#   Gauss–Markov velocity of its own;
# * the phases: the per-phase parameter table, the demand classes, and one `PhaseClock` object
#   that says which phase is active at any tick, whether the ticks are training iterations (the
#   trainer) or environment steps (a standalone environment). Their code is the module
#   `pemamoe/phases.py`, in appendix `03b_phases.py`; this notebook describes them and draws them.

# %%
#| default_exp mobility

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## The phase table
#
# The paper gives three phases, 0/1/2, with rising user speed (0.2, 0.5, 0.8 m/s) and direction
# jitter (0.2, 0.5, 0.8), a service radius of 200 m in the calm phase and 150 m in the others, and
# a growing penalty on overlapping UAVs (20, 40, 80). Demand comes in three classes, L, M and H,
# asking for 0.5, 1 and 2 Mbit/s and worth 5, 10 and 20 when met.
#
# **Demand modes.** In the paper's `cycle` mode every user holds the class of the phase: everybody
# is L in phase 0, M in phase 1, H in phase 2. We also offer a `mix` mode in which each user draws
# its class from the phase's probabilities (by default mostly L in phase 0, mostly M in phase 1,
# mostly H in phase 2), which makes the regimes overlap and the class mix itself informative.
#
# **A held-out regime.** The paper names randomised and unseen phases as future work. They cost
# little here: `PhaseConfig` carries a fourth regime (index 3) with parameters outside the training
# range (faster users, 1.2 m/s; more jitter; a 120 m radius; a mixed demand leaning to H). A
# schedule can insert it every k-th segment, or an evaluation can set it directly, to measure
# generalisation rather than re-adaptation.

# %%
import pandas as pd

from pemamoe.phases import PhaseConfig

_table = PhaseConfig()
print("demand classes L, M, H:", [f"{r / 1e6:g} Mbit/s worth {w:g}" for r, w in
                                  zip(_table.rate_threshold_bps, _table.class_reward)])
pd.DataFrame({"user speed (m/s)": _table.user_speed_mps, "direction jitter": _table.direction_jitter,
              "service radius (m)": _table.service_radius_m, "overlap weight": _table.overlap_weight},
             index=pd.RangeIndex(len(_table.user_speed_mps), name="phase"))

# %% [markdown]
# Which phase is active when is one object, `PhaseClock`: in the paper the phase advances every
# L = 1200 training iterations (3 phases x 3 cycles); a standalone environment can use it with
# its own step counter. It can also draw a random order (no phase follows itself), random
# durations, or insert the held-out regime every k-th segment (pictured at the end). The table's
# and the clock's code are appendix `03b_phases.py` (`pemamoe.phases`).


# %% [markdown]
# ## Hotspots and users
#
# Users are split into G hotspots (20 users in 3 groups: 7, 7 and 6), and the membership never
# changes. A hotspot's centre walks straight toward a waypoint at 1.2 times the phase's user speed
# and draws a new waypoint every 10 steps. Each user's velocity has two parts:
#
# 1. a **Gauss–Markov** update that keeps most of the previous velocity (memory α = 0.9), pulls its
#    magnitude toward the nominal speed v₀, and adds Gaussian noise;
# 2. an **RPGM blend** that mixes in a pull toward the group centre (follow gain κ = 0.3) plus a
#    small follow noise (0.15 m/s).
#
# Positions then advance one slot (60 s) and reflect off the borders of the area (the velocity
# component that crossed a border changes sign).
#
# **Direction jitter.** The paper tabulates both a fixed GM noise (0.08 m/s) and a phase-dependent
# "direction jitter" (0.2/0.5/0.8) without saying how they combine. We read the jitter as a noise
# level *relative to the phase's nominal speed*: the GM noise standard deviation is
# `gm_noise + jitter × v₀`. Calm phases then move nearly in straight lines (0.08 + 0.04 m/s of noise
# at 0.2 m/s), and the evacuation phase is erratic (0.08 + 0.64 m/s at 0.8 m/s), which is the
# qualitative contrast the paper describes.
#
# **Batches and randomness.** Every array has a leading batch axis B, and one step draws a fixed
# count of random numbers (B×N×2 GM normals, B×N×2 follow normals, B×G×2 waypoint uniforms),
# whether or not a hotspot retargets. A generator whose row b is environment b's own stream (the
# environment's `BatchRandom`) therefore makes environment b's motion independent of the batch.

# %%
#| export
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from pemamoe.core import require_field

USERS_LIMIT = 10_000  # ground users at most (the paper has 20 to 100): every slot is O(users x UAVs)


@dataclass(frozen=True)
class MobilityConfig:
    area_m: float = 1000.0
    n_users: int = 20
    n_hotspots: int = 3
    slot_s: float = 60.0
    user_height_m: float = 1.5
    gm_memory: float = 0.9
    gm_noise_mps: float = 0.08
    follow_gain: float = 0.3
    follow_noise_mps: float = 0.15
    centre_speed_factor: float = 1.2
    retarget_every: int = 10
    spawn_spread_m: float = 60.0  # users start around their centre with this standard deviation
    centre_margin: float = 0.15  # centres start at least this fraction of the side from a border

    def __post_init__(self):
        require_field(self, "area_m", "real", gt=0)
        require_field(self, "n_hotspots", "int", ge=1, le=USERS_LIMIT)
        require_field(self, "n_users", "int", ge=self.n_hotspots, le=USERS_LIMIT, note="every hotspot needs a user")
        require_field(self, "slot_s", "real", gt=0)
        require_field(self, "user_height_m", "real", ge=0)
        require_field(self, "gm_memory", "real", ge=0, lt=1)
        require_field(self, "follow_gain", "real", ge=0, le=1)
        for name in ("gm_noise_mps", "follow_noise_mps", "centre_speed_factor", "spawn_spread_m"):
            require_field(self, name, "real", ge=0)
        require_field(self, "retarget_every", "int", ge=1)
        require_field(self, "centre_margin", "real", ge=0, lt=0.5)


class MobilityState(NamedTuple):
    user_xy: np.ndarray  # (B, N, 2)
    user_vel: np.ndarray  # (B, N, 2) m/s
    centre_xy: np.ndarray  # (B, G, 2)
    waypoint_xy: np.ndarray  # (B, G, 2)
    steps_to_retarget: np.ndarray  # (B,) int


def hotspot_membership(n_users: int, n_hotspots: int) -> np.ndarray:
    """(N,) hotspot of each user, groups as even as possible (20 users, 3 hotspots: 7, 7, 6)."""
    sizes = [n_users // n_hotspots + (g < n_users % n_hotspots) for g in range(n_hotspots)]
    return np.repeat(np.arange(n_hotspots), sizes)


def reflect_into_area(xy, area_m: float):
    """Fold positions back into [0, area] like a mirror; return (positions, flipped-sign mask)."""
    period = 2.0 * area_m
    folded = np.mod(xy, period)
    flipped = folded > area_m
    # An odd number of reflections (folded position in the upper half-period) reverses the motion.
    return np.where(flipped, period - folded, folded), flipped


def init_mobility(cfg: MobilityConfig, batch: int, rng) -> MobilityState:
    """Hotspot centres away from the borders, users scattered around them, waypoints anywhere."""
    S, G, N = cfg.area_m, cfg.n_hotspots, cfg.n_users
    margin = cfg.centre_margin * S
    centre = rng.uniform(margin, S - margin, size=(batch, G, 2))
    waypoint = rng.uniform(0.0, S, size=(batch, G, 2))
    member = hotspot_membership(N, G)
    user, _ = reflect_into_area(centre[:, member] + cfg.spawn_spread_m * rng.standard_normal((batch, N, 2)), S)
    heading = rng.standard_normal((batch, N, 2))
    vel = 0.1 * heading  # a small initial drift in a random direction; GM rescales it to v0
    return MobilityState(user, vel, centre, waypoint, np.full(batch, cfg.retarget_every))


def step_mobility(state: MobilityState, speed_mps, jitter, cfg: MobilityConfig, rng) -> MobilityState:
    """Advance every environment one slot; speed_mps and jitter are (B,) phase values."""
    S, dt, eps = cfg.area_m, cfg.slot_s, 1e-9
    B, N, _ = state.user_xy.shape
    G = state.centre_xy.shape[1]
    v0 = np.asarray(speed_mps, dtype=float)[:, None, None]
    jit = np.asarray(jitter, dtype=float)[:, None, None]
    xi = rng.standard_normal((B, N, 2))
    eta = rng.standard_normal((B, N, 2))
    new_waypoints = rng.uniform(0.0, S, size=(B, G, 2))

    # Hotspot centres: straight toward the waypoint, without overshooting it; retarget on schedule.
    to_wp = state.waypoint_xy - state.centre_xy
    dist = np.linalg.norm(to_wp, axis=-1, keepdims=True)
    step = np.minimum(cfg.centre_speed_factor * v0 * dt, dist)
    centre = state.centre_xy + step * to_wp / (dist + eps)
    countdown = state.steps_to_retarget - 1
    retarget = countdown <= 0
    waypoint = np.where(retarget[:, None, None], new_waypoints, state.waypoint_xy)
    countdown = np.where(retarget, cfg.retarget_every, countdown)

    # Users: Gauss-Markov velocity, blended with a pull toward the group centre (RPGM).
    a = cfg.gm_memory
    v = state.user_vel
    speed = np.linalg.norm(v, axis=-1, keepdims=True)
    sigma = cfg.gm_noise_mps + jit * v0
    v_gm = a * v + (1 - a) * v0 * v / (speed + eps) + math.sqrt(1 - a * a) * sigma * xi
    member = hotspot_membership(N, G)
    to_centre = centre[:, member] - state.user_xy
    pull = v0 * to_centre / (np.linalg.norm(to_centre, axis=-1, keepdims=True) + eps)
    k = cfg.follow_gain
    v_new = (1 - k) * v_gm + k * pull + cfg.follow_noise_mps * eta
    user, flipped = reflect_into_area(state.user_xy + v_new * dt, S)
    v_new = np.where(flipped, -v_new, v_new)
    return MobilityState(user, v_new, centre, waypoint, countdown)

# %% [markdown]
# ## Pictures
#
# User trajectories under each phase's mobility (one panel per regime, same seed), and the drift
# of the hotspot centres.

# %%
import matplotlib.pyplot as plt

from pemamoe.core import by_scale, save_figure
from pemamoe.phases import PhaseConfig, PhaseClock, phase_values

mob_cfg, phase_cfg = MobilityConfig(), PhaseConfig()
steps = by_scale(scale, ci=16, small=32, paper=64)
regimes = list(range(phase_cfg.n_regimes))
fig, axes = plt.subplots(1, len(regimes), figsize=(4 * len(regimes), 4), sharey=True)
drift = {}
for ax, regime in zip(axes, regimes):
    rng = np.random.default_rng(seed)
    state = init_mobility(mob_cfg, 1, rng)
    speed, jitter, _, _ = phase_values(phase_cfg, np.array([regime]))
    path, centres = [state.user_xy[0]], [state.centre_xy[0]]
    for _ in range(steps):
        state = step_mobility(state, speed, jitter, mob_cfg, rng)
        path.append(state.user_xy[0])
        centres.append(state.centre_xy[0])
    path, centres = np.stack(path), np.stack(centres)
    drift[regime] = centres
    member = hotspot_membership(mob_cfg.n_users, mob_cfg.n_hotspots)
    for n in range(mob_cfg.n_users):
        ax.plot(path[:, n, 0], path[:, n, 1], lw=0.8, color=f"C{member[n]}", alpha=0.8)
    ax.scatter(path[-1, :, 0], path[-1, :, 1], s=10, color="black", zorder=3)
    name = "held-out" if regime == phase_cfg.n_phases else f"phase {regime}"
    ax.set_title(f"{name}: v0={speed[0]:.1f} m/s, jitter={jitter[0]:.1f}")
    ax.set_xlim(0, mob_cfg.area_m)
    ax.set_ylim(0, mob_cfg.area_m)
    ax.set_aspect("equal")
fig.suptitle(f"User trajectories over {steps} slots of {mob_cfg.slot_s:.0f} s (colour: hotspot)")
save_figure(fig, "mobility_trajectories", figures_dir)
plt.show()

# %% [markdown]
# ![User trajectories under each regime's mobility](../paper_figures/mobility_trajectories.png)

# %%
fig, ax = plt.subplots(figsize=(5, 5))
for regime, centres in drift.items():
    for g in range(mob_cfg.n_hotspots):
        ax.plot(centres[:, g, 0], centres[:, g, 1], color=f"C{regime}", lw=1.2,
                label=f"regime {regime}" if g == 0 else None)
        ax.scatter(*centres[0, g], color=f"C{regime}", marker="o", s=15)
ax.set_xlim(0, mob_cfg.area_m)
ax.set_ylim(0, mob_cfg.area_m)
ax.set_aspect("equal")
ax.legend(fontsize=8)
ax.set_title("Hotspot-centre drift (dots: start)")
save_figure(fig, "mobility_hotspot_drift", figures_dir)
plt.show()

# %% [markdown]
# ![Hotspot-centre drift in each regime](../paper_figures/mobility_hotspot_drift.png)

# %% [markdown]
# And the schedule variants over 60 ticks: the paper's fixed cycle, random durations, a random
# order, and the fixed cycle with the held-out regime inserted after every third segment.

# %%
variants = {
    "fixed cycle (paper)": PhaseClock(period=5),
    "random durations 3-8": PhaseClock(period=5, min_period=3, max_period=8, seed=seed),
    "random order": PhaseClock(period=5, order="random", seed=seed),
    "held-out after every 3": PhaseClock(period=5, held_out_every=3),
}
ticks = np.arange(60)
fig, ax = plt.subplots(figsize=(9, 3))
for i, (name, sched) in enumerate(variants.items()):
    ax.step(ticks, [sched.phase_at(int(t)) + 5 * i for t in ticks], where="post", label=name)
ax.set_yticks([5 * i + 1.5 for i in range(len(variants))], list(variants))
ax.set_xlabel("tick (training iteration or environment step)")
ax.set_title("Phase schedules (each trace: phase 0-2, 3 = held-out)")
save_figure(fig, "phases_schedules", figures_dir)
plt.show()

# %% [markdown]
# ![Phase schedule variants: fixed cycle, random durations, random order, held-out inserted](../paper_figures/phases_schedules.png)
