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
# # 03b · Appendix: the phase table and the phase clock in code
#
# Notebook 03 describes the phases: the paper's three regimes of the disaster scene, the demand
# classes, our held-out regime, and how the phase switches. This appendix holds their code, in the
# module `pemamoe.phases`: `PhaseConfig` (the per-phase parameter table), the demand classes and
# how a user's class is drawn, and `PhaseClock`, the one phase clock that the trainer (its
# ticks are iterations) and a standalone environment (its ticks are steps) share.

# %%
#| default_exp phases

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## The phase table
#
# The paper's values, with our `mix` demand mode and the held-out regime (notebook 03 explains them).

# %%
#| export
import bisect
import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from pemamoe.core import config_error, require, require_field

CLASS_NAMES = ("L", "M", "H")
DEMAND_MODES = ("cycle", "mix")


@dataclass(frozen=True)
class PhaseConfig:
    """Per-phase parameters (index 0, 1, 2: the paper's phases; index 3: the held-out regime)."""

    user_speed_mps: tuple = (0.2, 0.5, 0.8)
    direction_jitter: tuple = (0.2, 0.5, 0.8)
    service_radius_m: tuple = (200.0, 150.0, 150.0)
    overlap_weight: tuple = (20.0, 40.0, 80.0)
    rate_threshold_bps: tuple = (0.5e6, 1.0e6, 2.0e6)  # demand classes L, M, H
    class_reward: tuple = (5.0, 10.0, 20.0)
    demand_mode: str = "cycle"
    mix_probs: tuple = ((0.6, 0.3, 0.1), (0.3, 0.5, 0.2), (0.1, 0.3, 0.6))
    held_out_speed_mps: float = 1.2
    held_out_jitter: float = 1.0
    held_out_radius_m: float = 120.0
    held_out_overlap_weight: float = 60.0
    held_out_demand_probs: tuple = (0.2, 0.3, 0.5)

    def __post_init__(self):
        # Per-phase tuples are stored as tuples of floats (hashable, JSON-ready); see core.require.
        n = len(require_field(self, "user_speed_mps", "reals", ge=0))
        per_phase = "one per phase, like user_speed_mps"
        for name in ("direction_jitter", "overlap_weight"):
            require_field(self, name, "reals", ge=0, length=n, note=per_phase)
        require_field(self, "service_radius_m", "reals", gt=0, length=n, note=per_phase)
        require_field(self, "rate_threshold_bps", "reals", gt=0, length=3, note="classes L, M, H")
        require_field(self, "class_reward", "reals", ge=0, length=3, note="classes L, M, H")
        require_field(self, "demand_mode", "choice", DEMAND_MODES)
        if self.demand_mode == "cycle" and n > 3:
            raise config_error("PhaseConfig", "demand_mode", self.demand_mode,
                               "'mix' when there are more than 3 phases (cycle gives phase p class p)")
        _require_distributions(self, "mix_probs", n)
        _require_distributions(self, "held_out_demand_probs", None)
        for name in ("held_out_speed_mps", "held_out_jitter", "held_out_overlap_weight"):
            require_field(self, name, "real", ge=0)
        require_field(self, "held_out_radius_m", "real", gt=0)

    @property
    def n_phases(self) -> int:
        """The training phases (3 in the paper)."""
        return len(self.user_speed_mps)

    @property
    def n_regimes(self) -> int:
        """Training phases plus the held-out regime (its index is n_phases)."""
        return self.n_phases + 1

    def table(self, name: str) -> np.ndarray:
        """Values of a per-phase field for every regime, the held-out one last."""
        held = {"user_speed_mps": self.held_out_speed_mps, "direction_jitter": self.held_out_jitter,
                "service_radius_m": self.held_out_radius_m, "overlap_weight": self.held_out_overlap_weight}[name]
        return np.array([*getattr(self, name), held], dtype=float)

    def demand_probs(self) -> np.ndarray:
        """(n_regimes, 3) class probabilities per regime, as used in `mix` mode."""
        return np.array([*self.mix_probs, self.held_out_demand_probs], dtype=float)


def _require_distributions(cfg, name: str, count: int | None) -> None:
    """Check cfg.<name>: a probability triple (L, M, H) summing to 1 (count None), or a tuple of
    `count` such triples; store it as (tuples of) floats."""
    value = getattr(cfg, name)
    allowed = ("a probability triple (L, M, H) summing to 1" if count is None
               else f"{count} probability triples (L, M, H), one per phase, each summing to 1")
    rows = [value] if count is None else value
    try:
        if isinstance(rows, (str, bytes)) or len(rows) != (1 if count is None else count):
            raise ValueError
        rows = tuple(require("PhaseConfig", name, p, "reals", ge=0, le=1, length=3) for p in rows)
    except (TypeError, ValueError):
        raise config_error("PhaseConfig", name, value, allowed) from None
    if any(abs(sum(p) - 1.0) >= 1e-9 for p in rows):
        raise config_error("PhaseConfig", name, value, allowed)
    object.__setattr__(cfg, name, rows[0] if count is None else rows)


def phase_values(cfg: PhaseConfig, phase):
    """(speed, jitter, radius, overlap_weight) arrays for a phase index array (B,)."""
    phase = np.asarray(phase, dtype=int)
    if phase.size and (phase.min() < 0 or phase.max() >= cfg.n_regimes):
        raise ValueError(f"phase indices must be in [0, {cfg.n_regimes}), got {np.unique(phase).tolist()}")
    return tuple(cfg.table(name)[phase] for name in
                 ("user_speed_mps", "direction_jitter", "service_radius_m", "overlap_weight"))


def sample_demand_classes(cfg: PhaseConfig, phase, n_users: int, rng) -> np.ndarray:
    """(B, N) demand classes (0=L, 1=M, 2=H) for environments in phases `phase` (B,).

    Draws B x N uniforms in every mode, so the random numbers consumed do not depend on the mode
    or the phase. In `cycle` mode a training phase p gives every user class p; the held-out regime
    always draws from its probabilities.
    """
    phase = np.asarray(phase, dtype=int)
    u = rng.random((phase.shape[0], n_users))
    cdf = np.cumsum(cfg.demand_probs()[phase], axis=-1)  # (B, 3)
    drawn = (u[..., None] >= cdf[:, None, :2]).sum(-1)
    if cfg.demand_mode == "cycle":
        cyclic = np.broadcast_to(np.minimum(phase, 2)[:, None], drawn.shape)
        return np.where((phase < cfg.n_phases)[:, None], cyclic, drawn)
    return drawn


# %% [markdown]
# ## One phase clock for the trainer and the environment
#
# `PhaseClock` maps a tick to a phase. In the paper's setting the ticks are training iterations
# and the phase advances every L = 1200 of them (3 phases × 3 cycles over 10,800 iterations); a
# standalone environment can use the same object with its own step counter as the tick. Options:
#
# * `order="random"`: a seeded random order in which no phase follows itself;
# * `min_period`/`max_period`: seeded random durations, uniform in that range;
# * `held_out_every=k`: the held-out regime is inserted after every k regular segments.
#
# The fixed cyclic schedule is a closed formula. The others draw their segments from the seed,
# lazily and in order, as far as the ticks asked for; `phase_at` is then a binary search, and the
# same seed always gives the same sequence however far it is read.

# %%
#| export
@dataclass(frozen=True)
class PhaseClock:
    """Which phase is active at each tick (iteration or env step); see the notebook for options."""

    period: int = 1200
    n_phases: int = 3
    order: str = "cyclic"  # "cyclic" | "random"
    min_period: int | None = None  # with max_period: random durations in [min_period, max_period]
    max_period: int | None = None
    held_out_every: int = 0  # insert the held-out regime (index n_phases) after every k regular segments
    seed: int = 0
    # Segments of randomised schedules, generated lazily from the seed as far as ticks are asked for.
    _segments: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        require_field(self, "period", "int", ge=1)
        require_field(self, "n_phases", "int", ge=1)
        require_field(self, "order", "choice", ("cyclic", "random"))
        if self.order == "random" and self.n_phases < 2:
            raise config_error("PhaseClock", "n_phases", self.n_phases,
                               "an integer >= 2 for a random order that never repeats a phase")
        if (self.min_period is None) != (self.max_period is None):
            raise config_error("PhaseClock", "min_period", self.min_period,
                               f"set together with max_period (here {self.max_period!r}), or both None")
        if self.min_period is not None:
            require_field(self, "min_period", "int", ge=1)
            require_field(self, "max_period", "int", ge=self.min_period, note="max_period >= min_period")
        require_field(self, "held_out_every", "int", ge=0)
        require_field(self, "seed", "int", ge=0)
        self._segments.update(starts=[0], phases=[], regular=0, previous=-1,
                              rng=np.random.default_rng(self.seed))

    @property
    def closed_form(self) -> bool:
        """The paper's fixed cycle needs no segment list: phase = (tick // period) mod n_phases."""
        return self.order == "cyclic" and self.min_period is None and not self.held_out_every

    def _extend_to(self, tick: int) -> None:
        seg = self._segments
        while seg["starts"][-1] <= tick:
            if self.held_out_every and seg["regular"] and seg["regular"] % self.held_out_every == 0 \
                    and seg["phases"] and seg["phases"][-1] != self.n_phases:
                phase = self.n_phases
            else:
                if self.order == "random":
                    choices = [p for p in range(self.n_phases) if p != seg["previous"]]
                    phase = int(choices[seg["rng"].integers(len(choices))])
                else:
                    phase = seg["regular"] % self.n_phases
                seg["regular"] += 1
                seg["previous"] = phase
            length = self.period if self.min_period is None else int(
                seg["rng"].integers(self.min_period, self.max_period + 1))
            seg["phases"].append(phase)
            seg["starts"].append(seg["starts"][-1] + length)

    def phase_at(self, tick: int) -> int:
        if tick < 0:
            raise ValueError(f"tick must be >= 0, got {tick}")
        if self.closed_form:
            return (tick // self.period) % self.n_phases
        self._extend_to(tick)
        return self._segments["phases"][bisect.bisect_right(self._segments["starts"], tick) - 1]

    def phases_at(self, ticks) -> np.ndarray:
        """phase_at for an array of ticks (one vectorised step for the paper's fixed cycle)."""
        ticks = np.asarray(ticks, dtype=np.int64)
        if ticks.size and ticks.min() < 0:
            raise ValueError(f"ticks must be >= 0, got min {ticks.min()}")
        if self.closed_form:
            return (ticks // self.period) % self.n_phases
        uniq, inverse = np.unique(ticks, return_inverse=True)
        return np.array([self.phase_at(int(t)) for t in uniq], dtype=np.int64)[inverse].reshape(ticks.shape)

    def is_switch(self, tick: int) -> bool:
        """True at a tick where the phase differs from the previous tick's (never at tick 0)."""
        return tick > 0 and self.phase_at(tick) != self.phase_at(tick - 1)

    def switch_ticks(self, horizon: int) -> list:
        """Every switch tick in [1, horizon)."""
        return [t for t in range(1, horizon) if self.is_switch(t)]

# %% [markdown]
# ## Check
#
# The paper's fixed cycle with L = 4: phases 0, 1, 2, 0, ... in blocks of 4 ticks, switches at
# every multiple of 4; a random order never repeats a phase.

# %%
fixed = PhaseClock(period=4)
assert [fixed.phase_at(t) for t in range(13)] == [0] * 4 + [1] * 4 + [2] * 4 + [0]
assert fixed.switch_ticks(13) == [4, 8, 12]
shuffled = PhaseClock(period=4, order="random", seed=seed)
phases = [shuffled.phase_at(t) for t in range(0, 200, 4)]
assert all(a != b for a, b in zip(phases, phases[1:]))
print("fixed:", [fixed.phase_at(t) for t in range(13)], "| random order:", phases[:10])
