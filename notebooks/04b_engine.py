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
# # 04b · Appendix: the random streams, the compiled engine and the wrappers
#
# Notebook 04 defines the environment: its dynamics, scheduler, objective, observations and API,
# all as readable numpy. This appendix holds the machinery that makes that environment exact and
# fast, and nothing in it changes what the environment *is*:
#
# * `BatchRandom` (module `pemamoe.streams`): one random stream per environment, read as a batch,
#   so that environment b of a batch draws exactly what a lone environment with its seed draws;
# * the compiled engine (module `pemamoe.env_kernel`): the same step as notebook 04's numpy
#   reference, written as numba-compiled loops, and `CompiledStep`, which feeds it from the
#   batched core. `EnvConfig(step_engine="compiled")`, the default, selects it;
# * the wrappers (module `pemamoe.env_wrappers`): `UAVVectorEnv`, the batched environment the
#   trainer steps, and `UAVParallelEnv`, the PettingZoo environment, both thin layers over notebook
#   04's batched core, with the renderer, `compile_step_kernels` and the reference policies
#   (`random`, `hover`, `kmeans`) that the learned ones are compared with.
#
# Read it when you change the dynamics of notebook 04 (the compiled step must follow, and the tests
# that step both engines side by side will say where it does not), when you need to know why the
# environment runs at the speed it does, or when you change what the environments return.
# The modules stack without import cycles: `pemamoe.streams` and `pemamoe.env_kernel` sit below
# notebook 04's model (`pemamoe.env_model`), the wrappers above it, and `pemamoe.env`, which outside
# code imports, on top, re-exporting the model, `BatchRandom` and the wrappers. The model imports
# `pemamoe.env_kernel` only when a core with the compiled engine is built, so `import pemamoe.env`
# never loads numba, and it hands the engine what the engine needs from it (the observation and
# state sizes, the random numbers one slot draws) as arguments.

# %%
#| default_exp env_kernel

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## Per-environment random streams, drawn as one batch
#
# The physics functions of notebooks 01–03 take a random generator and draw arrays whose leading
# axis is the batch. `BatchRandom` is a generator for that purpose: a draw of shape `(B, ...)`
# takes row `b` from environment `b`'s own stream. Each environment has two numpy generators (one
# for normal variates, one for uniforms), read through buffers of `rng_chunk` numbers so that a
# step costs a few array slices rather than B generator calls. Gamma variates come from uniforms
# through the inverse regularised incomplete gamma function, which keeps the count of uniforms per
# draw fixed; every draw of every step consumes a fixed count of numbers, whatever the values.
# Resetting environment b with a seed rebuilds only its streams.

# %%
#| export streams
import math

import numpy as np
from scipy import special


class BatchRandom:
    """Duck-typed numpy Generator whose (B, ...) draws take row b from environment b's stream."""

    def __init__(self, seeds, chunk: int = 4096):
        self.chunk = int(chunk)
        n = len(seeds)
        self._buffers = {"normal": np.empty((n, self.chunk)), "uniform": np.empty((n, self.chunk))}
        self._cursor = {kind: np.full(n, self.chunk) for kind in self._buffers}
        # While every environment has read the same amount (the usual case: whole-batch draws),
        # the shared position lives here and a draw is one slice; None means "use _cursor".
        self._common = {kind: self.chunk for kind in self._buffers}
        self._gens = [None] * n
        self._rows = np.arange(n)
        self._full = True
        for b, s in enumerate(seeds):
            self.reseed(b, s)

    @property
    def batch(self) -> int:
        return len(self._rows)

    def reseed(self, b: int, seed) -> None:
        """Restart environment b's streams from `seed` (an int, a SeedSequence or None)."""
        seq = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        normal_seq, uniform_seq = seq.spawn(2)
        self._gens[b] = {"normal": np.random.default_rng(normal_seq), "uniform": np.random.default_rng(uniform_seq)}
        for kind in self._buffers:
            self._desync(kind)
            self._cursor[kind][b] = self.chunk
            self._resync(kind)

    def select(self, rows) -> "BatchRandom":
        """A view drawing only for environments `rows` (used to reset some environments)."""
        rows = np.asarray(rows, dtype=int)
        if len(rows) == len(self._gens) and np.array_equal(rows, self._rows):
            return self
        view = object.__new__(BatchRandom)
        view.__dict__.update(self.__dict__)  # shares buffers, cursors and generators
        view._rows, view._full = rows, False
        return view

    def _desync(self, kind: str) -> None:
        if self._common[kind] is not None:
            self._cursor[kind][:] = self._common[kind]
            self._common[kind] = None

    def _resync(self, kind: str) -> None:
        cur = self._cursor[kind]
        if self._common[kind] is None and np.all(cur == cur[0]):
            self._common[kind] = int(cur[0])

    def _take(self, kind: str, size) -> np.ndarray:
        size = (size,) if isinstance(size, (int, np.integer)) else tuple(size)
        if not size or size[0] != len(self._rows):
            raise ValueError(f"BatchRandom draws need a leading batch axis of {len(self._rows)}, got size={size}")
        k = math.prod(size[1:])
        if k > self.chunk:
            raise ValueError(f"a draw of {k} numbers per environment exceeds rng_chunk={self.chunk}")
        buf = self._buffers[kind]
        common = self._common[kind]
        if self._full and common is not None:  # fast path: one slice for the whole batch
            if common + k > self.chunk:
                for b in range(len(self._gens)):
                    buf[b] = np.concatenate([buf[b, common:], self._draw(self._gens[b][kind], kind, common)])
                common = 0
            self._common[kind] = common + k
            # A copy, not a view: a later refill rewrites the buffer, and a caller may still be
            # holding this draw (sample_channel draws Rician x, then y, then uses both).
            return np.array(buf[:, common:common + k]).reshape(size)
        self._desync(kind)
        cur, rows = self._cursor[kind], self._rows
        for b in rows[cur[rows] + k > self.chunk]:
            # Refill: keep the unread tail, then append fresh numbers from b's own generator.
            tail = buf[b, cur[b]:].copy()
            fresh = self._draw(self._gens[b][kind], kind, self.chunk - tail.size)
            buf[b] = np.concatenate([tail, fresh])
            cur[b] = 0
        start = cur[rows]
        if np.all(start == start[0]):
            out = buf[rows, start[0]:start[0] + k]
        else:
            out = buf[rows[:, None], start[:, None] + np.arange(k)]
        cur[rows] = start + k
        self._resync(kind)
        return out.reshape(size)

    def state_dict(self) -> dict:
        """Everything needed to continue every stream exactly (numpy arrays and plain dicts)."""
        for kind in self._buffers:
            self._desync(kind)
            self._resync(kind)
        return {
            "buffers": {k: v.copy() for k, v in self._buffers.items()},
            "cursor": {k: v.copy() for k, v in self._cursor.items()},
            "generators": [{k: g.bit_generator.state for k, g in gens.items()} for gens in self._gens],
        }

    def load_state_dict(self, state: dict) -> None:
        if len(state["generators"]) != len(self._gens):
            raise ValueError(f"state holds {len(state['generators'])} streams, this batch has {len(self._gens)}")
        for kind in self._buffers:
            self._buffers[kind][...] = state["buffers"][kind]
            self._common[kind] = None
            self._cursor[kind][...] = state["cursor"][kind]
            self._resync(kind)
        for gens, saved in zip(self._gens, state["generators"]):
            for kind, g in gens.items():
                g.bit_generator.state = saved[kind]

    @staticmethod
    def _draw(gen, kind, n):
        return gen.standard_normal(n) if kind == "normal" else gen.random(n)

    # The subset of numpy.random.Generator's interface that the physics functions use.
    def random(self, size):
        return self._take("uniform", size)

    def uniform(self, low=0.0, high=1.0, size=None):
        return low + (np.asarray(high) - low) * self._take("uniform", size)

    def standard_normal(self, size):
        return self._take("normal", size)

    def normal(self, loc=0.0, scale=1.0, size=None):
        return loc + np.asarray(scale) * self._take("normal", size)

    def integers(self, low, high=None, size=None):
        low, high = (0, low) if high is None else (low, high)
        return (low + np.floor(self._take("uniform", size) * (high - low))).astype(int)

    def gamma(self, shape, scale=1.0, size=None):
        return self.gamma_from_uniform(self._take("uniform", size), shape, scale)

    @staticmethod
    def gamma_from_uniform(u, shape, scale=1.0):
        """Gamma(shape, scale) variates by inversion of the uniforms u."""
        if np.all(np.asarray(shape) == 1.0):  # exponential: the common Nakagami m = 1, and cheap
            return -np.asarray(scale) * np.log1p(-u)
        return np.asarray(scale) * special.gammaincinv(shape, u)


# %% [markdown]
# A batch's streams do not depend on the batch: environment 1 of a batch seeded (5, 6, 7) draws the
# numbers a lone environment seeded 6 draws, across buffer refills.

# %%
wide, alone = BatchRandom([5, 6, 7], chunk=128), BatchRandom([6], chunk=128)
same = all(np.array_equal(wide.standard_normal((3, n))[1], alone.standard_normal((1, n))[0]) for n in (50, 70, 90))
print("environment 1 of the batch draws what a lone environment draws:", same)


# %% [markdown]
# ## The compiled step
#
# The numpy core of notebook 04 is the specification: every formula is one vectorised line that
# can be read against notebooks 01–03 and the paper. It is also slow for this problem's sizes. A step
# at 3 UAVs and 20 users makes about a thousand numpy calls, each on a few dozen numbers, so the
# interpreter's per-call overhead, not arithmetic, sets the pace: about 1.1 ms per PettingZoo step
# and 22,000 environment steps per second at B = 64 (`make bench` at commit `a335d46`, 2-core machine), against the
# 200 µs and 50,000 this project targets.
#
# The compiled engine (`step_engine="compiled"`, the default) runs the same step as explicit loops
# over environments, UAVs and users, compiled once by numba and cached on disk. It is written to
# match the reference operation by operation:
#
# * **Same random numbers.** Python draws a slot's normals and uniforms from `BatchRandom` in one
#   block per stream, in the order the reference draws them (user noise, then the channel; waypoints,
#   LoS states, NLoS fading, demand classes), so every environment reads exactly the numbers it reads
#   under the numpy engine. NLoS fading powers come from their uniforms by the reference's inversion:
#   the kernel computes $-\log(1-u)/m$ itself for the default $m = 1$, and scipy's `gammaincinv`
#   supplies them for any other $m$.
# * **Same constants.** Derived constants (propulsion powers, the LoS height factor, the Rician
#   mixture, the interference weights) are computed by the reference functions and handed in as
#   `KernelParams`.
# * **Same arithmetic order,** written out expression by expression, so results agree to the last
#   bit wherever both sides use the same floating-point operations. They cannot everywhere: numpy
#   sums the interference through a BLAS matrix product and the QoS term pairwise, the kernel in a
#   plain loop, and another machine's numpy may take `exp` or `log10` from a different math library
#   than numba. With the default settings (one frequency colour, integer class rewards) those sums
#   are exact, and on the development machine the two engines' outputs agree bit for bit; with
#   frequency reuse, intermediate interference values differ by an ulp in about one link in eight
#   (measured at `7b4705b`).
#   The motion of UAVs and users never depends on those values, so such differences cannot
#   accumulate along a trajectory. The tests step both engines side by side through episode
#   ends, phase switches, frequency reuse, Nakagami m ≠ 1, the held-out regime and the `mix` demand
#   mode, and require equal discrete outcomes (admissions, served users, collisions, phases) and
#   floats equal to 1e-9 relative.
#
# The compiled step also skips work the reference does for every link: it computes distances for
# all links, the large-scale channel only for users inside a service radius, and this slot's
# realised gain only on the links of admitted users. The random numbers of every link are drawn
# regardless, so no stream changes. Measured with `make bench` over eight runs at commit `81d9b1e`:
# 110–130 µs per PettingZoo step and 63,000–83,000 env-steps/s at B = 64 (47,000–60,000 when every
# user is covered), depending on how busy the shared machine is. (`d2066cc` later moved the demand
# classification to phase switches, which can only make the step cheaper.)
#
# The scheduler is the one place where loops read better than arrays: per UAV, the attached users
# are sorted by (priority, distance) with a stable insertion sort, and admission grows k = 1, 2, …
# until the next user would break the power budget, recomputing the per-user bandwidth B/(F k) and
# every admitted user's power at each k, exactly as the vectorised version evaluates all k at once.


# %%
#| export
import math
from typing import NamedTuple

import numba
import numpy as np

from pemamoe.channel import height_correction, interference_weights, reuse_colours
from pemamoe.energy import propulsion_power_w
from pemamoe.mobility import hotspot_membership
from pemamoe.streams import BatchRandom


# Rows of the kernels' per-environment outputs, named as in the reference's info (float_info and
# int_info are written by _score_env, uav_flags by _move_uavs; the tests compare them by name).
FLOAT_INFO = ("qos", "energy", "collision", "overlap", "reward", "coverage", "uav_using_rate", "energy_rate_kj")
INT_INFO = ("collisions", "served_users", "admitted_users")
UAV_INFO = ("action_clipped", "move_infeasible", "battery_depleted")


class KernelParams(NamedTuple):
    """Every constant the compiled step reads; `kernel_params(cfg)` derives them from an EnvConfig."""

    # UAV motion and energy
    max_step_m: float
    area_m: float
    cruise_speed_mps: float
    slot_s: float
    cruise_power_w: float  # P(V_h, 0)
    climb_power_w: float  # P(0, V_z)
    hover_power_w: float  # P(0, 0)
    battery_capacity_j: float
    # user mobility
    gm_memory: float
    gm_noise_mps: float
    follow_gain: float
    follow_noise_mps: float
    centre_speed_factor: float
    retarget_every: int
    hotspot_of_user: np.ndarray  # (N,)
    # channel
    rel_height_m: float  # UAV altitude minus user height
    min_distance_m: float
    los_breakpoint_m: float
    los_decay_m: float
    los_height_factor: float  # 1 + C0(h)
    pl_intercept_db: float
    pl_distance_slope_db: float
    pl_frequency_term_db: float  # frequency slope x log10(fc)
    nlos_offset_db: float
    nlos_distance_coeff_db: float
    nlos_distance_exponent: float
    antenna_gain: float
    rician_direct: float
    rician_scatter: float
    exponential_fading: bool  # Nakagami m = 1: the kernel turns uniforms into powers itself
    fading_neg_scale: float  # -1/m
    shadowing_los_db: float
    shadowing_nlos_db: float
    colour_bandwidth_hz: float
    max_tx_power_w: float
    noise_w_per_hz: float
    implementation_loss: float
    min_gain: float
    weights: np.ndarray  # (U, U) interference weights
    # scheduler and objective
    max_users_per_uav: int
    energy_weight_per_kj: float
    collision_penalty: float
    min_separation_m: float
    overlap_sigma_m: float
    overlap_cutoff_radii: float
    episode_steps: int
    # phases: per-regime tables, the held-out regime last
    speed_mps: np.ndarray
    jitter: np.ndarray
    radius_m: np.ndarray
    overlap_weight: np.ndarray
    demand_cdf: np.ndarray  # (regimes, 3) cumulative class probabilities
    n_phases: int
    cycle_demand: bool
    rate_threshold_bps: np.ndarray  # (3,) per class
    class_reward: np.ndarray  # (3,) per class


def kernel_params(cfg) -> KernelParams:
    """The compiled step's constants for an EnvConfig, derived with the reference functions."""
    ch, en, mob, ph = cfg.channel, cfg.energy, cfg.mobility, cfg.phases
    rel_height = cfg.uav_altitude_m - mob.user_height_m
    rician_k = 10.0 ** (np.asarray(ch.rician_k_db, dtype=float) / 10.0)  # as channel.rician_power
    return KernelParams(
        max_step_m=float(cfg.max_step_m),
        area_m=float(mob.area_m),
        cruise_speed_mps=float(en.cruise_speed_mps),
        slot_s=float(en.slot_s),
        cruise_power_w=float(propulsion_power_w(en.cruise_speed_mps, 0.0, en)),
        climb_power_w=float(propulsion_power_w(0.0, en.climb_speed_mps, en)),
        hover_power_w=float(en.hover_power_w),
        battery_capacity_j=float(en.battery_capacity_j),
        gm_memory=float(mob.gm_memory),
        gm_noise_mps=float(mob.gm_noise_mps),
        follow_gain=float(mob.follow_gain),
        follow_noise_mps=float(mob.follow_noise_mps),
        centre_speed_factor=float(mob.centre_speed_factor),
        retarget_every=int(mob.retarget_every),
        hotspot_of_user=hotspot_membership(mob.n_users, mob.n_hotspots).astype(np.int64),
        rel_height_m=float(rel_height),
        min_distance_m=float(ch.min_distance_m),
        los_breakpoint_m=float(ch.los_breakpoint_m),
        los_decay_m=float(ch.los_decay_m),
        los_height_factor=float(1.0 + height_correction(np.full(1, rel_height), ch)[0]),
        pl_intercept_db=float(ch.pl_intercept_db),
        pl_distance_slope_db=float(ch.pl_distance_slope_db),
        pl_frequency_term_db=float(ch.pl_frequency_slope_db * math.log10(ch.carrier_ghz)),
        nlos_offset_db=float(ch.nlos_offset_db),
        nlos_distance_coeff_db=float(ch.nlos_distance_coeff_db),
        nlos_distance_exponent=float(ch.nlos_distance_exponent),
        antenna_gain=float(ch.antenna_gain),
        rician_direct=float(np.sqrt(rician_k / (rician_k + 1.0))),
        rician_scatter=float(np.sqrt(0.5 / (rician_k + 1.0))),
        exponential_fading=bool(ch.nakagami_m == 1.0),
        fading_neg_scale=-1.0 / ch.nakagami_m,
        shadowing_los_db=float(ch.shadowing_los_db),
        shadowing_nlos_db=float(ch.shadowing_nlos_db),
        colour_bandwidth_hz=float(ch.colour_bandwidth_hz),
        max_tx_power_w=float(ch.max_tx_power_w),
        noise_w_per_hz=float(ch.noise_w_per_hz),
        implementation_loss=float(ch.implementation_loss),
        min_gain=float(ch.min_gain),
        weights=np.ascontiguousarray(
            interference_weights(reuse_colours(cfg.n_uavs, ch.reuse_factor), ch.adjacent_leakage), dtype=float),
        max_users_per_uav=int(cfg.max_users_per_uav),
        energy_weight_per_kj=float(cfg.energy_weight_per_kj),
        collision_penalty=float(cfg.collision_penalty),
        min_separation_m=float(cfg.min_separation_m),
        overlap_sigma_m=float(cfg.overlap_sigma_m),
        overlap_cutoff_radii=float(cfg.overlap_cutoff_radii),
        episode_steps=int(cfg.episode_steps),
        speed_mps=ph.table("user_speed_mps"),
        jitter=ph.table("direction_jitter"),
        radius_m=ph.table("service_radius_m"),
        overlap_weight=ph.table("overlap_weight"),
        demand_cdf=np.ascontiguousarray(np.cumsum(ph.demand_probs(), axis=-1)),
        n_phases=int(ph.n_phases),
        cycle_demand=ph.demand_mode == "cycle",
        rate_threshold_bps=np.asarray(ph.rate_threshold_bps, dtype=float),
        class_reward=np.asarray(ph.class_reward, dtype=float),
    )


# %% [markdown]
# Motion: UAVs fly their clipped displacement and pay the slot's energy; users take one
# Gauss–Markov/RPGM slot (`mobility.step_mobility`), reflecting at the borders like `np.mod` does.

# %%
#| export
@numba.njit(cache=True)
def _reflect(x, area):
    """Mirror x into [0, area]; returns (position, flipped). See mobility.reflect_into_area."""
    period = 2.0 * area
    folded = x % period  # Python's float modulo, as numpy.mod: the result takes the divisor's sign
    if folded > area:
        return period - folded, True
    return folded, False


@numba.njit(cache=True)
def _move_uavs(p, b, actions, uav_xy, battery_j, energy_j, uav_flags):
    """Clip the actions, fly each UAV, charge the slot's energy (see UAVBatchCore.step)."""
    for u in range(uav_xy.shape[1]):
        a0, a1 = actions[b, u, 0], actions[b, u, 1]
        c0, c1 = min(max(a0, -1.0), 1.0), min(max(a1, -1.0), 1.0)
        uav_flags[0, b, u] = c0 != a0 or c1 != a1
        s0, s1 = c0 * p.max_step_m, c1 * p.max_step_m
        norm = math.sqrt(s0 * s0 + s1 * s1)
        shrink = min(1.0, p.max_step_m / max(norm, 1e-12))
        s0, s1 = s0 * shrink, s1 * shrink
        x0, y0 = uav_xy[b, u, 0], uav_xy[b, u, 1]
        x1, y1 = min(max(x0 + s0, 0.0), p.area_m), min(max(y0 + s1, 0.0), p.area_m)
        dx, dy = x1 - x0, y1 - y0
        moved = math.sqrt(dx * dx + dy * dy)
        uav_xy[b, u, 0], uav_xy[b, u, 1] = x1, y1
        # slot_energy with no vertical leg
        t_h = moved / p.cruise_speed_mps
        t_v = 0.0
        t_move = t_h + t_v
        infeasible = t_move > p.slot_s
        if infeasible:
            t_h = t_h * (p.slot_s / t_move)
        t_move = min(t_h + t_v, p.slot_s)
        t_hover = p.slot_s - t_move
        energy = p.cruise_power_w * t_h + p.climb_power_w * t_v + p.hover_power_w * t_hover
        energy_j[b, u] = energy
        uav_flags[1, b, u] = infeasible
        raw = battery_j[b, u] - energy
        battery_j[b, u] = min(max(raw, 0.0), p.battery_capacity_j)
        uav_flags[2, b, u] = raw <= 0.0


@numba.njit(cache=True)
def _move_users(p, b, i, phase, user_xy, user_vel, centre_xy, waypoint_xy, steps_to_retarget, normals, uniforms):
    """One Gauss-Markov/RPGM slot for environment b (see mobility.step_mobility)."""
    N, G = user_xy.shape[1], centre_xy.shape[1]
    S, dt, eps = p.area_m, p.slot_s, 1e-9
    v0 = p.speed_mps[phase]
    jit = p.jitter[phase]
    countdown = steps_to_retarget[b] - 1
    retarget = countdown <= 0
    for g in range(G):
        tw0 = waypoint_xy[b, g, 0] - centre_xy[b, g, 0]
        tw1 = waypoint_xy[b, g, 1] - centre_xy[b, g, 1]
        dist = math.sqrt(tw0 * tw0 + tw1 * tw1)
        step = min(p.centre_speed_factor * v0 * p.slot_s, dist)
        centre_xy[b, g, 0] = centre_xy[b, g, 0] + step * tw0 / (dist + eps)
        centre_xy[b, g, 1] = centre_xy[b, g, 1] + step * tw1 / (dist + eps)
        if retarget:
            waypoint_xy[b, g, 0] = 0.0 + (S - 0.0) * uniforms[i, 2 * g]
            waypoint_xy[b, g, 1] = 0.0 + (S - 0.0) * uniforms[i, 2 * g + 1]
    steps_to_retarget[b] = p.retarget_every if retarget else countdown
    a, k = p.gm_memory, p.follow_gain
    sigma = p.gm_noise_mps + jit * v0
    noise_scale = math.sqrt(1 - a * a)
    for n in range(N):
        vx, vy = user_vel[b, n, 0], user_vel[b, n, 1]
        speed = math.sqrt(vx * vx + vy * vy)
        g = p.hotspot_of_user[n]
        tc0 = centre_xy[b, g, 0] - user_xy[b, n, 0]
        tc1 = centre_xy[b, g, 1] - user_xy[b, n, 1]
        tc_norm = math.sqrt(tc0 * tc0 + tc1 * tc1) + eps
        for d in range(2):
            v = user_vel[b, n, d]
            xi = normals[i, 2 * n + d]
            eta = normals[i, 2 * N + 2 * n + d]
            v_gm = a * v + (1 - a) * v0 * v / (speed + eps) + noise_scale * sigma * xi
            pull = v0 * (tc0 if d == 0 else tc1) / tc_norm
            v_new = (1 - k) * v_gm + k * pull + p.follow_noise_mps * eta
            pos, flipped = _reflect(user_xy[b, n, d] + v_new * dt, S)
            user_xy[b, n, d] = pos
            user_vel[b, n, d] = -v_new if flipped else v_new


# %% [markdown]
# Channel, scheduler, realised rates and objective of one environment, after the feasibility
# power rule for a single link. Its per-environment outputs go to the rows of `float_info` and
# `int_info` named by `FLOAT_INFO` and `INT_INFO`.

# %%
#| export
@numba.njit(cache=True)
def _required_power(p, rate, band, gain, interference):
    """The feasibility power rule (channel.required_power_w) for one link with rate, band > 0."""
    gamma = math.expm1(rate / (p.implementation_loss * band) * math.log(2.0))
    return gamma * (p.noise_w_per_hz * band + interference) / max(gain, p.min_gain)


@numba.njit(cache=True)
def _score_env(p, b, i, phase, demand, uav_xy, user_xy, energy_j, rand_normal, rand_uniform, nakagami,
               rate_frac, serving, float_info, int_info, scratch):
    """Channel draw, scheduler, realised rates and objective of environment b (see
    sample_channel, schedule_users, realised_rates and reward_terms)."""
    N, U = user_xy.shape[1], uav_xy.shape[1]
    NU = N * U
    horizontal, expected, gain, conservative = scratch[0], scratch[1], scratch[2], scratch[3]
    power, bandwidth = scratch[4], scratch[5]
    p_los, pl_los, pl_nlos = scratch[6], scratch[7], scratch[8]
    radius = p.radius_m[phase]
    # Each quantity is computed only for the links that need it (the random numbers are drawn for
    # every link regardless, so this changes no stream): distances for all links, large-scale
    # terms for covered users, this slot's realised gain for admitted users.
    # -- association: nearest UAV within the service radius
    nearest = np.empty(N, np.int64)
    covered = 0
    for n in range(N):
        for u in range(U):
            horizontal[n, u] = math.hypot(user_xy[b, n, 0] - uav_xy[b, u, 0], user_xy[b, n, 1] - uav_xy[b, u, 1])
        best = 0
        for u in range(1, U):
            if horizontal[n, u] < horizontal[n, best]:
                best = u
        nearest[n] = best if horizontal[n, best] <= radius else -1
        covered += nearest[n] >= 0
    # -- large-scale channel of covered users: LoS probability, both path losses, expected gain,
    #    and the planning interference (every other UAV at full power on the expected channel)
    for n in range(N):
        if nearest[n] < 0:
            continue
        for u in range(U):
            r = max(math.hypot(horizontal[n, u], p.rel_height_m), p.min_distance_m)
            ratio = min(p.los_breakpoint_m / r, 1.0)
            prob = ratio + math.exp(-r / p.los_decay_m) * (1.0 - ratio) * p.los_height_factor
            if r <= p.los_breakpoint_m:
                prob = 1.0
            p_los[n, u] = min(max(prob, 0.0), 1.0)
            pl_los[n, u] = p.pl_intercept_db + p.pl_distance_slope_db * math.log10(r) + p.pl_frequency_term_db
            pl_nlos[n, u] = pl_los[n, u] + p.nlos_offset_db + p.nlos_distance_coeff_db * r ** p.nlos_distance_exponent
            expected[n, u] = p.antenna_gain * (p_los[n, u] * 10.0 ** (-pl_los[n, u] / 10.0)
                                               + (1.0 - p_los[n, u]) * 10.0 ** (-pl_nlos[n, u] / 10.0))
        for u in range(U):
            acc = 0.0
            for v in range(U):
                acc += expected[n, v] * p.max_tx_power_w * p.weights[u, v]
            conservative[n, u] = acc
    # -- admission per UAV: priority (H > M > L), then distance; greedy under the power budget
    cap = min(p.max_users_per_uav, N)
    candidates = np.empty(N, np.int64)
    keys = np.empty(N)
    power[:, :] = 0.0
    bandwidth[:, :] = 0.0
    admitted_of = np.full(N, -1)
    n_admitted_total = 0
    for u in range(U):
        m = 0
        for n in range(N):
            if nearest[n] == u:
                key = (2 - demand[b, n]) * 1e9 + horizontal[n, u]
                pos = m  # stable insertion sort: ties keep the user order
                while pos > 0 and keys[pos - 1] > key:
                    keys[pos] = keys[pos - 1]
                    candidates[pos] = candidates[pos - 1]
                    pos -= 1
                keys[pos] = key
                candidates[pos] = n
                m += 1
        k_admit = 0
        for k in range(1, min(cap, m) + 1):
            band = p.colour_bandwidth_hz / k
            total = 0.0
            for j in range(k):
                total += _required_power(p, p.rate_threshold_bps[demand[b, candidates[j]]], band,
                                         expected[candidates[j], u], conservative[candidates[j], u])
            if total <= p.max_tx_power_w:
                k_admit = k
            else:
                break
        if k_admit > 0:
            band = p.colour_bandwidth_hz / k_admit
            for j in range(k_admit):
                n = candidates[j]
                power[n, u] = _required_power(p, p.rate_threshold_bps[demand[b, n]], band, expected[n, u],
                                              conservative[n, u])
                bandwidth[n, u] = band
                admitted_of[n] = u
        n_admitted_total += k_admit
    # -- this slot's channel (LoS state, fading, shadowing) on every link of an admitted user
    for n in range(N):
        if admitted_of[n] < 0:
            continue
        for u in range(U):
            j = n * U + u
            if rand_uniform[i, j] < p_los[n, u]:  # line of sight: Rician fading
                x = p.rician_direct + p.rician_scatter * rand_normal[i, j]
                y = p.rician_scatter * rand_normal[i, NU + j]
                fading = x * x + y * y
                loss = pl_los[n, u] + p.shadowing_los_db * rand_normal[i, 2 * NU + j]
            else:  # Nakagami-m fading, from the link's second uniform
                if p.exponential_fading:
                    fading = p.fading_neg_scale * math.log1p(-rand_uniform[i, NU + j])
                else:
                    fading = nakagami[i, j]
                loss = pl_nlos[n, u] + p.shadowing_nlos_db * rand_normal[i, 2 * NU + j]
            gain[n, u] = p.antenna_gain * fading * 10.0 ** (-loss / 10.0)
    # -- realised rates, with the power each UAV actually radiates
    radiated = np.zeros(U)
    for n in range(N):
        for u in range(U):
            radiated[u] += power[n, u]
    served_n = 0
    admitted_n = 0
    qos = 0.0
    for n in range(N):
        u = admitted_of[n]
        target = p.rate_threshold_bps[demand[b, n]]
        rate = 0.0
        if u >= 0:
            admitted_n += 1
            interference = 0.0
            for v in range(U):
                interference += gain[n, v] * radiated[v] * p.weights[u, v]
            signal = power[n, u] * gain[n, u]
            disturbance = p.noise_w_per_hz * bandwidth[n, u] + interference
            if disturbance > 0:
                sinr = signal / disturbance
            else:
                sinr = np.inf if signal > 0 else 0.0
            rate = p.implementation_loss * bandwidth[n, u] * math.log2(1.0 + sinr)
            if rate >= target * (1 - 1e-9):
                served_n += 1
                qos += p.class_reward[demand[b, n]]
        rate_frac[b, n] = rate / target
        serving[b, n] = u
    # -- objective: collisions and overlap between UAV pairs, energy
    collisions = 0
    overlap = 0.0
    for u in range(U):
        for v in range(u + 1, U):
            dx = uav_xy[b, u, 0] - uav_xy[b, v, 0]
            dy = uav_xy[b, u, 1] - uav_xy[b, v, 1]
            d = math.sqrt(dx * dx + dy * dy)
            collisions += d < p.min_separation_m
            if d < p.overlap_cutoff_radii * radius:
                overlap += math.exp(-d ** 2 / (2 * p.overlap_sigma_m ** 2))
    overlap = p.overlap_weight[phase] * overlap
    energy_sum = 0.0
    for u in range(U):
        energy_sum += energy_j[b, u]
    energy = p.energy_weight_per_kj * energy_sum / 1e3
    collision = p.collision_penalty * collisions
    float_info[0, i] = qos
    float_info[1, i] = energy
    float_info[2, i] = collision
    float_info[3, i] = overlap
    float_info[4, i] = qos - energy - collision - overlap
    float_info[5, i] = covered / N
    float_info[6, i] = n_admitted_total / U / p.max_users_per_uav
    float_info[7, i] = energy_sum / U / 1e3
    int_info[0, i] = collisions
    int_info[1, i] = served_n
    int_info[2, i] = admitted_n


# %% [markdown]
# Observations and global state (the layout of `build_observations`), then the two entry points:
# a full step of every environment, and the scoring of freshly reset environments.

# %%
#| export
@numba.njit(cache=True)
def _observe_env(p, b, i, t, uav_xy, battery_j, user_xy, rate_frac, serving, demand, obs, state):
    """Write environment b's observations and global state into row i (see build_observations)."""
    U, N = uav_xy.shape[1], user_xy.shape[1]
    S = p.area_m
    for a in range(U):
        obs[i, a, 0] = uav_xy[b, a, 0] / S
        obs[i, a, 1] = uav_xy[b, a, 1] / S
        obs[i, a, 2] = battery_j[b, a] / p.battery_capacity_j
        col = 3
        for o in range(U):
            if o != a:
                obs[i, a, col] = (uav_xy[b, o, 0] - uav_xy[b, a, 0]) / S
                obs[i, a, col + 1] = (uav_xy[b, o, 1] - uav_xy[b, a, 1]) / S
                obs[i, a, col + 2] = battery_j[b, o] / p.battery_capacity_j
                col += 3
        for n in range(N):
            obs[i, a, col] = (user_xy[b, n, 0] - uav_xy[b, a, 0]) / S
            obs[i, a, col + 1] = (user_xy[b, n, 1] - uav_xy[b, a, 1]) / S
            obs[i, a, col + 2] = min(max(rate_frac[b, n], 0.0), 2.0) / 2.0
            obs[i, a, col + 3] = 1.0 if serving[b, n] == a else 0.0
            for c in range(3):
                obs[i, a, col + 4 + c] = 1.0 if demand[b, n] == c else 0.0
            col += 7
    col = 0
    for a in range(U):
        state[i, col] = obs[i, a, 0]
        state[i, col + 1] = obs[i, a, 1]
        state[i, col + 2] = obs[i, a, 2]
        col += 3
    for n in range(N):
        state[i, col] = user_xy[b, n, 0] / S
        state[i, col + 1] = user_xy[b, n, 1] / S
        state[i, col + 2] = min(max(rate_frac[b, n], 0.0), 2.0) / 2.0
        for a in range(U):
            state[i, col + 3 + a] = 1.0 if serving[b, n] == a else 0.0
        for c in range(3):
            state[i, col + 3 + U + c] = 1.0 if demand[b, n] == c else 0.0
        col += 6 + U
    state[i, col] = t[b] / p.episode_steps


@numba.njit(cache=True)
def _draw_demand(p, phase, u):
    """Demand class from one uniform (see phases.sample_demand_classes)."""
    drawn = (u >= p.demand_cdf[phase, 0]) + (u >= p.demand_cdf[phase, 1])
    if p.cycle_demand and phase < p.n_phases:
        return min(phase, 2)
    return drawn


@numba.njit(cache=True)
def step_kernel(p, actions, new_phase, uav_xy, battery_j, user_xy, user_vel, centre_xy, waypoint_xy,
                steps_to_retarget, demand, rate_frac, serving, phase, t, normals, uniforms, nakagami,
                obs, state, float_info, int_info, uav_flags, phase_switch):
    """One slot of every environment, in place; t must already count the new slot.

    normals (B, 4N + 3NU) and uniforms (B, 2G + 2NU + N) are this slot's random numbers in the
    order the numpy reference draws them; nakagami (B, NU) the NLoS fading powers.
    """
    B, U = uav_xy.shape[0], uav_xy.shape[1]
    N, G = user_xy.shape[1], centre_xy.shape[1]
    NU = N * U
    energy_j = np.empty((B, U))
    scratch = np.empty((9, N, U))
    for b in range(B):
        _move_uavs(p, b, actions, uav_xy, battery_j, energy_j, uav_flags)
        _move_users(p, b, b, phase[b], user_xy, user_vel, centre_xy, waypoint_xy, steps_to_retarget,
                    normals, uniforms)
        _score_env(p, b, b, phase[b], demand, uav_xy, user_xy, energy_j, normals[:, 4 * N:],
                   uniforms[:, 2 * G:], nakagami, rate_frac, serving, float_info, int_info, scratch)
        # The phase clock has ticked: new demand classes when the phase changed (their uniforms
        # are drawn every slot regardless, as in the reference).
        phase_switch[b] = new_phase[b] != phase[b]
        if phase_switch[b]:
            for n in range(N):
                demand[b, n] = _draw_demand(p, new_phase[b], uniforms[b, 2 * G + 2 * NU + n])
        phase[b] = new_phase[b]
        _observe_env(p, b, b, t, uav_xy, battery_j, user_xy, rate_frac, serving, demand, obs, state)


@numba.njit(cache=True)
def score_kernel(p, rows, uav_xy, battery_j, user_xy, demand, rate_frac, serving, phase, t, channel_normals,
                 channel_uniforms, nakagami, obs, state, float_info, int_info):
    """Schedule, score and observe environments `rows` after a reset (no motion, no energy)."""
    U, N = uav_xy.shape[1], user_xy.shape[1]
    energy_j = np.zeros((uav_xy.shape[0], U))
    scratch = np.empty((9, N, U))
    for i in range(rows.shape[0]):
        b = rows[i]
        _score_env(p, b, i, phase[b], demand, uav_xy, user_xy, energy_j, channel_normals, channel_uniforms,
                   nakagami, rate_frac, serving, float_info, int_info, scratch)
        _observe_env(p, b, i, t, uav_xy, battery_j, user_xy, rate_frac, serving, demand, obs, state)


# %% [markdown]
# ## Feeding the kernels from the batched core
#
# `UAVBatchCore` (notebook 04) holds a `CompiledStep` when its configuration asks for the compiled
# engine and hands it the reset scoring and every step. `CompiledStep` draws a slot's random numbers
# from the core's `BatchRandom` in one block per stream (`slot_draws` gives the counts, in the
# reference's order), turns NLoS fading uniforms into powers where the kernel cannot, lets the
# kernel update the core's arrays in place, and returns the observations, rewards and `info` with
# the keys in the order the numpy reference produces them.

# %%
#| export
_NOT_NEEDED = np.zeros((1, 1))  # placeholder for the kernel's nakagami argument when m = 1

# The keys of info, in the order the numpy reference's info has them.
_INFO_ORDER = ("qos", "energy", "collision", "overlap", "reward", "collisions", "coverage", "served_users",
               "admitted_users", "uav_using_rate", "energy_rate_kj", "phase", "action_clipped", "move_infeasible",
               "battery_depleted", "phase_switch")


def _info_dict(float_info, int_info, **more) -> dict:
    values = dict(zip(FLOAT_INFO, float_info), **dict(zip(INT_INFO, int_info)), **more)
    return {key: values[key] for key in _INFO_ORDER if key in values}


class CompiledStep:
    """The compiled engine of a UAVBatchCore: the same step, with the same random numbers, as one loop."""

    def __init__(self, cfg, dims: tuple, draws: tuple):
        # dims: (observation_dim(cfg), state_dim(cfg)); draws: slot_draws(cfg), the normals and
        # uniforms one slot takes per environment. The core computes both (notebook 04).
        self.cfg = cfg
        self.params = kernel_params(cfg)
        self.dims = tuple(dims)
        self.draws = tuple(draws)

    def _channel_randoms(self, rng, n):
        """This slot's channel draws, in the reference's order: normals (Rician x, y, shadowing),
        uniforms (LoS state, then the NLoS fading's), and the Nakagami powers (see _nakagami)."""
        NU = self.cfg.n_users * self.cfg.n_uavs
        normals, uniforms = rng.standard_normal((n, 3 * NU)), rng.random((n, 2 * NU))
        return normals, uniforms, self._nakagami(uniforms[:, NU:])

    def _nakagami(self, uniforms):
        """NLoS fading powers from their uniforms. For m = 1 (exponential) the kernel computes them
        itself, and only for the links that need them; other m need scipy's gammaincinv, here."""
        if self.params.exponential_fading:
            return _NOT_NEEDED
        m = np.asarray(self.cfg.channel.nakagami_m, dtype=float)
        return BatchRandom.gamma_from_uniform(uniforms, m, 1.0 / m)

    def _outputs(self, n):
        obs_dim, state_size = self.dims
        return (np.empty((n, self.cfg.n_uavs, obs_dim), np.float32), np.empty((n, state_size), np.float32),
                np.empty((len(FLOAT_INFO), n)), np.empty((len(INT_INFO), n), dtype=np.int64))

    def score(self, core, rows, rng):
        """Schedule, score and observe the freshly reset environments `rows` of `core`."""
        normals, uniforms, nakagami = self._channel_randoms(rng, len(rows))
        obs, state, float_info, int_info = self._outputs(len(rows))
        score_kernel(self.params, rows, core.uav_xy, core.battery_j, core.mobility.user_xy, core.demand,
                     core.rate_frac, core.serving, core.phase, core.t, normals, uniforms, nakagami,
                     obs, state, float_info, int_info)
        info = _info_dict(float_info, int_info, phase=core.phase[rows].copy())
        return obs, state, info

    def step(self, core, actions):
        """Advance every environment of `core` one slot (actions already checked, (B, U, 2) floats)."""
        cfg, B, rng = self.cfg, core.B, core.rng
        N, U, G = cfg.n_users, cfg.n_uavs, cfg.mobility.n_hotspots
        NU = N * U
        # All of a slot's draws at once; per stream this is the reference's order exactly.
        n_normals, n_uniforms = self.draws
        normals, uniforms = rng.standard_normal((B, n_normals)), rng.random((B, n_uniforms))
        nakagami = self._nakagami(uniforms[:, 2 * G + NU:2 * G + 2 * NU])
        old_phase = core.phase.copy()
        core.t += 1
        core.clock += 1
        new_phase = core._current_phase(np.arange(B))
        obs, state, float_info, int_info = self._outputs(B)
        uav_flags, switch = np.empty((len(UAV_INFO), B, U), dtype=bool), np.empty(B, dtype=bool)
        mob = core.mobility
        step_kernel(self.params, actions, new_phase, core.uav_xy, core.battery_j, mob.user_xy, mob.user_vel,
                    mob.centre_xy, mob.waypoint_xy, mob.steps_to_retarget, core.demand, core.rate_frac, core.serving,
                    core.phase, core.t, normals, uniforms, nakagami, obs, state, float_info, int_info, uav_flags,
                    switch)
        info = _info_dict(float_info, int_info, phase=old_phase, **dict(zip(UAV_INFO, uav_flags)), phase_switch=switch)
        terminated = info["battery_depleted"].any(axis=-1)
        truncated = core.t >= cfg.episode_steps
        return obs, state, info["reward"], terminated, truncated, info


# %% [markdown]
# ## The two engines side by side
#
# The same seeds and actions through two episodes give the same trajectories under both engines
# (the test suite checks many more configurations), and the compiled one is faster by an order of
# magnitude. The timing here is only indicative; `make bench` measures the speed properly.

# %%
import time

from pemamoe.core import by_scale
from pemamoe.env import make_vector_env

engine_steps = by_scale(scale, ci=40, small=80, paper=80)
engines = {name: make_vector_env(8, seed=seed, step_engine=name) for name in ("numpy", "compiled")}
engine_actions = np.random.default_rng(seed).uniform(-1, 1, (engine_steps, 8, 3, 2))
outputs, seconds = {}, {}
for name, venv in engines.items():
    venv.reset()
    start = time.perf_counter()
    outputs[name] = [venv.step(a) for a in engine_actions]
    seconds[name] = time.perf_counter() - start
worst = max(float(np.max(np.abs(a[0] - b[0]))) for a, b in zip(outputs["numpy"], outputs["compiled"]))
same_served = all(np.array_equal(a[5]["served_users"], b[5]["served_users"])
                  for a, b in zip(outputs["numpy"], outputs["compiled"]))
print(f"largest observation difference over {engine_steps} steps x 8 envs: {worst:.2e}; "
      f"served users identical: {same_served}")
for name, s in seconds.items():
    print(f"{name:>8}: {engine_steps * 8 / s:,.0f} env-steps/s (first call of the compiled engine may include loading it)")

# %% [markdown]
# ## The wrappers: the batched environment the trainer uses
#
# `UAVVectorEnv` steps B environments in one process. Episodes of all environments have the same
# length, and an environment whose episode ends (time limit, or an empty battery) starts a new
# one within the same call, so that every call returns usable observations. The last observation of
# the finished episode is returned in `info["final_obs"]` and `info["final_state"]`: the trainer
# bootstraps a truncated episode from the value of that final observation, not from the first
# observation of the next episode.

# %%
#| export env_wrappers
import numpy as np

from pemamoe.env_model import EnvConfig, UAVBatchCore, observation_dim, state_dim
from pemamoe.phases import phase_values


class UAVVectorEnv:
    """B environments stepped together. Arrays: obs (B, U, obs_dim), state (B, state_dim)."""

    def __init__(self, num_envs: int = 16, seed: int | None = 0, cfg: "EnvConfig | None" = None, *, seeds=None,
                 **overrides):
        if cfg is not None and overrides:
            raise ValueError("pass either cfg or keyword overrides, not both")
        self.cfg = cfg or EnvConfig.from_overrides(**overrides)
        if seeds is None:  # explicit per-environment seeds: a population's members side by side
            seeds = vector_seeds(seed, num_envs)
        num_envs = len(seeds)
        self.core = UAVBatchCore(self.cfg, num_envs, seeds)
        self.num_envs = int(num_envs)
        self.n_agents = self.cfg.n_uavs
        self.obs_dim = observation_dim(self.cfg)
        self.state_dim = state_dim(self.cfg)
        self.act_dim = 2

    def reset(self):
        obs, state, info = self.core.reset()
        return obs, state, info

    def set_phase(self, phase: int) -> None:
        self.core.set_phase(phase)

    def state_dict(self) -> dict:
        return self.core.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.core.load_state_dict(state)

    def step(self, actions):
        obs, state, reward, terminated, truncated, info = self.core.step(actions)
        done = terminated | truncated
        if done.any():
            rows = np.flatnonzero(done)
            info["final_obs"], info["final_state"] = obs[rows].copy(), state[rows].copy()
            info["final_rows"] = rows
            new_obs, new_state, _ = self.core.reset(rows)
            obs[rows], state[rows] = new_obs, new_state
        return obs, state, reward, terminated, truncated, info


def vector_seeds(seed, num_envs: int) -> list:
    """Seeds of a vector env's members: environment i of seed s is the env made with seed s + i."""
    if seed is None:
        return [None] * num_envs
    return [int(seed) + i for i in range(num_envs)]


# %% [markdown]
# ## The wrappers: the PettingZoo environment
#
# `make_env(**overrides)` (also `pemamoe.parallel_env`) returns a PettingZoo `ParallelEnv` over the
# same core with B = 1: agents `uav_0 … uav_{U-1}`, Gymnasium `Box` spaces, `state()` for the
# centralised critic and, with `render_mode="rgb_array"`, an RGB `render()` (the default,
# `render_mode=None`, draws nothing). `aec_env(**overrides)` (alias `raw_env`) is the same
# environment as an AEC env, through PettingZoo's own `parallel_to_aec` conversion.
#
# It follows the conventions outside code relies on. The infos of `reset()` carry the same keys,
# with the same types, as those of `step()` (the per-step flags are all `False` at a reset), so a
# library that builds its info spec from `reset()` can read every `step()`. `step()`, `state()` and
# `render()` before the first `reset()` raise an error that says to call `reset()` first. Actions
# outside [-1, 1] are clipped and flagged in `info["action_clipped"]`; a NaN or infinite action, and
# an action for an agent that does not exist, raise an error naming the agent.
#
# PettingZoo and Gymnasium are needed by this environment only. The trainer, the sweeps and the
# benchmarks never build it, so they must import without either package: a GPU machine's own Python
# has torch but neither of them (`benchmarks/device_check.sh` runs there). The class is therefore
# defined in every case, and its base is PettingZoo's `ParallelEnv` where PettingZoo imports, a
# plain `object` where it is not installed; building one without it raises an `ImportError` that
# says what to install. Gymnasium's `Box` spaces are imported when an environment is built. We
# chose this over creating the class on first access (a module `__getattr__`): the class stays one
# object, defined at load, so `pemamoe.env` re-exports it as before, star imports, `isinstance` and
# pickling behave as usual, and there is no second path to keep in step.

# %%
#| export env_wrappers
try:  # PettingZoo (which brings Gymnasium) is optional for everything but this environment
    from pettingzoo import ParallelEnv as _ParallelEnvBase

    _PETTINGZOO_MISSING = None
except ModuleNotFoundError as error:
    if (error.name or "").split(".")[0] not in ("pettingzoo", "gymnasium"):
        raise  # a broken install of something else: say so, do not hide it
    _ParallelEnvBase, _PETTINGZOO_MISSING = object, error

# Info keys that only a step produces, and their value at a reset: (per agent?, value).
_STEP_ONLY_INFO = {"action_clipped": (True, False), "move_infeasible": (True, False),
                   "battery_depleted": (True, False), "phase_switch": (False, False)}


class UAVParallelEnv(_ParallelEnvBase):
    metadata = {"name": "pemamoe_uav_ecn_v0", "render_modes": ["rgb_array", "human"], "is_parallelizable": True,
                "render_fps": 4}

    def __init__(self, cfg: "EnvConfig | None" = None, render_mode: str | None = None):
        if _PETTINGZOO_MISSING is not None:
            raise ImportError("the PettingZoo environment needs pettingzoo and gymnasium "
                              "(pip install pettingzoo gymnasium); the trainer and the vector env "
                              "(make_vector_env) do not") from _PETTINGZOO_MISSING
        from gymnasium import spaces

        if render_mode not in (None, "rgb_array", "human"):
            raise ValueError(f"render_mode must be None, 'rgb_array' or 'human', got {render_mode!r}")
        self.cfg = cfg or EnvConfig()
        self.render_mode = render_mode
        self.possible_agents = [f"uav_{u}" for u in range(self.cfg.n_uavs)]
        self.agents = []
        obs_dim = observation_dim(self.cfg)
        self._obs_space = spaces.Box(-1.0, 1.0, (obs_dim,), np.float32)
        self._act_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self._state_space = spaces.Box(-1.0, 1.0, (state_dim(self.cfg),), np.float32)
        self.core = UAVBatchCore(self.cfg, 1, [None])
        self._seeded = False
        self._state = None  # set by reset(); None means "never reset"

    def observation_space(self, agent):
        return self._obs_space

    def action_space(self, agent):
        return self._act_space

    @property
    def state_space(self):
        return self._state_space

    def _need_reset(self, method: str) -> None:
        if self._state is None:
            raise RuntimeError(f"{method}() called before reset(): call reset() first")

    def reset(self, seed=None, options=None):
        if seed is not None and (isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer))
                                 or not 0 <= int(seed) < 2 ** 63):
            raise ValueError(f"reset(seed=...) must be None or an int in [0, 2**63), got {seed!r}")
        if seed is not None or not self._seeded:
            self.core.rng.reseed(0, seed)
            self._seeded = True
        obs, state, info = self.core.reset()
        self._state = state[0]
        self.agents = list(self.possible_agents)
        U = len(self.agents)
        for key, (per_agent, value) in _STEP_ONLY_INFO.items():  # step()'s keys, with their types
            info.setdefault(key, np.full((1, U) if per_agent else (1,), value))
        infos = _agent_infos(info, 0, self.agents)
        return {a: obs[0, i] for i, a in enumerate(self.agents)}, infos

    def step(self, actions):
        self._need_reset("step")
        if not self.agents:
            raise RuntimeError("step() called on a finished episode: call reset() first")
        unknown = set(actions) - set(self.possible_agents)
        if unknown:
            raise ValueError(f"actions for unknown agent(s) {sorted(unknown, key=str)}; "
                             f"the agents are {self.possible_agents}")
        missing = set(self.agents) - set(actions)
        if missing:
            raise ValueError(f"actions missing for agents {sorted(missing)}")
        try:  # the usual case, one array of 2 numbers per agent, in one call
            stacked = np.array([actions[a] for a in self.possible_agents], dtype=float)
        except (TypeError, ValueError):
            stacked = None
        if stacked is None or stacked.shape != (len(self.possible_agents), 2):
            for a in self.possible_agents:
                if np.shape(actions[a]) != (2,):  # a (1, 2) or (2, 1) array is refused, not reshaped
                    raise ValueError(f"action of {a} must have shape (2,), got shape {np.shape(actions[a])}")
            stacked = np.stack([np.asarray(actions[a], dtype=float).reshape(2) for a in self.possible_agents])
        obs, state, reward, terminated, truncated, info = self.core.step(stacked[None])
        self._state = state[0]
        agents = self.agents
        shared_reward, term, trunc = float(reward[0]), bool(terminated[0]), bool(truncated[0])
        out = (
            {a: obs[0, i] for i, a in enumerate(agents)},
            {a: shared_reward for a in agents},
            {a: term for a in agents},
            {a: trunc for a in agents},
            _agent_infos(info, 0, agents),
        )
        if term or trunc:
            self.agents = []
        return out

    def state(self):
        self._need_reset("state")
        return self._state

    def render(self):
        """rgb_array: the frame (H, W, 3) uint8; human: the frame shown in a matplotlib window
        (nothing visible under a non-interactive backend, as in a headless test), returns None."""
        if self.render_mode is None:
            return None
        self._need_reset("render")
        frame = render_frame(self.core, 0)
        if self.render_mode == "rgb_array":
            return frame
        import matplotlib.pyplot as plt

        if getattr(self, "_window", None) is None or not plt.fignum_exists(self._window[0].number):
            fig, ax = plt.subplots()
            ax.axis("off")
            self._window = (fig, ax.imshow(frame))
        else:
            self._window[1].set_data(frame)
        plt.pause(1 / self.metadata["render_fps"])
        return None

    def close(self):
        window = getattr(self, "_window", None)
        if window is not None:
            import matplotlib.pyplot as plt

            plt.close(window[0])
            self._window = None


def _agent_infos(info: dict, b: int, agents: list) -> dict:
    """Environment b's info as each agent sees it: (B, U) arrays are indexed by agent, (B,) are shared."""
    shared, per_agent = {}, {}
    for key, value in info.items():
        value = value if isinstance(value, np.ndarray) else np.asarray(value)
        # value[b:b + 1].tolist()[0] gives Python numbers, several times faster than value[b].item()
        if value.ndim == 2 and value.shape[1] == len(agents):
            per_agent[key] = value[b:b + 1].tolist()[0]
        else:
            shared[key] = value[b:b + 1].tolist()[0] if value.ndim == 1 else value[b]
    order = list(info)  # every agent's dict keeps info's key order
    return {a: {key: per_agent[key][u] if key in per_agent else shared[key] for key in order}
            for u, a in enumerate(agents)}


def compile_step_kernels() -> None:
    """Compile the compiled engine's kernels in this process, or load them from numba's on-disk
    cache. Call it once before starting parallel workers: they then all load the cached machine
    code instead of compiling it at the same time (about 9 s each, and a race on the cache files)."""
    env = UAVVectorEnv(2, 0, step_engine="compiled")
    env.reset()
    env.step(np.zeros((2, env.n_agents, 2)))


# %% [markdown]
# ## Rendering
#
# `render()` of the PettingZoo environment draws the area from above: users coloured by demand class, UAVs with their service
# circles, and a line from each admitted user to its UAV.

# %%
#| export env_wrappers
CLASS_COLOURS = ("#4daf4a", "#377eb8", "#e41a1c")  # L, M, H


def render_frame(core: "UAVBatchCore", b: int = 0, size_px: int = 480) -> np.ndarray:
    """An RGB frame (H, W, 3) uint8 of environment b."""
    import matplotlib

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    cfg = core.cfg
    fig = Figure(figsize=(size_px / 100, size_px / 100), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_axes([0, 0, 1, 1])
    S = cfg.area_m
    ax.set_xlim(0, S)
    ax.set_ylim(0, S)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    users = core.mobility.user_xy[b]
    uavs = core.uav_xy[b]
    _, _, radius, _ = phase_values(cfg.phases, core.phase[b:b + 1])
    for n, u in enumerate(core.serving[b]):
        if u >= 0:
            ax.plot([users[n, 0], uavs[u, 0]], [users[n, 1], uavs[u, 1]], color="0.6", lw=0.8, zorder=1)
    for u, (x, y) in enumerate(uavs):
        ax.add_patch(matplotlib.patches.Circle((x, y), radius[0], fill=False, ls="--", color="0.3", lw=1))
        ax.plot(x, y, marker="^", ms=12, color="black", zorder=3)
        ax.annotate(f"uav_{u}", (x, y), textcoords="offset points", xytext=(6, 6), fontsize=8)
    ax.scatter(users[:, 0], users[:, 1], c=[CLASS_COLOURS[c] for c in core.demand[b]], s=22, zorder=2)
    ax.set_title(f"phase {core.phase[b]}  step {core.t[b]}", fontsize=9, y=0.95)
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


# %% [markdown]
# ## Reference policies
#
# Three non-learning policies act on the batched observations' underlying state and serve as
# references for the learned ones: `random` (uniform actions), `hover` (stay put) and `kmeans`, the placement a wireless
# engineer would try first. Each slot it runs a few Lloyd iterations of k-means with k = U on the
# user positions, starting from the UAVs' own positions so that each UAV keeps "its" cluster, and
# flies each UAV toward its centroid (at most d_max per slot). It ignores demand classes, overlap and
# separation, which is what makes it a fair classical baseline rather than a tuned one.

# %%
#| export env_wrappers
def random_policy(core: "UAVBatchCore", rng: np.random.Generator):
    return rng.uniform(-1.0, 1.0, size=(core.B, core.cfg.n_uavs, 2))


def hover_policy(core: "UAVBatchCore", rng=None):
    return np.zeros((core.B, core.cfg.n_uavs, 2))


def kmeans_policy(core: "UAVBatchCore", rng=None, iterations: int = 5):
    """Fly each UAV toward the centroid of the user cluster it owns (k-means seeded at the UAVs)."""
    users = core.mobility.user_xy  # (B, N, 2)
    centroids = core.uav_xy.copy()  # (B, U, 2)
    U = centroids.shape[1]
    for _ in range(iterations):
        d = ((users[:, :, None, :] - centroids[:, None, :, :]) ** 2).sum(-1)  # (B, N, U)
        owner = (d.argmin(axis=-1)[..., None] == np.arange(U))  # (B, N, U)
        count = owner.sum(axis=1)  # (B, U)
        total = np.einsum("bnu,bnd->bud", owner.astype(float), users)
        centroids = np.where(count[..., None] > 0, total / np.maximum(count, 1)[..., None], centroids)
    return np.clip((centroids - core.uav_xy) / core.cfg.max_step_m, -1.0, 1.0)


HEURISTICS = {"random": random_policy, "hover": hover_policy, "kmeans": kmeans_policy}


def rollout_heuristic(policy: str, num_envs: int, steps: int, seed: int = 0, phase: int | None = None, **overrides):
    """Run a heuristic in a vector env; return per-step info arrays stacked to (steps, B)."""
    if policy not in HEURISTICS:
        raise ValueError(f"unknown heuristic {policy!r}; choose from {sorted(HEURISTICS)}")
    if phase is not None:
        overrides = {**overrides, "phase_clock": "external"}
    env = UAVVectorEnv(num_envs, seed, **overrides)
    if phase is not None:
        env.set_phase(phase)
    env.reset()
    act_rng = np.random.default_rng(seed)
    rows = []
    for _ in range(steps):
        _, _, _, _, _, info = env.step(HEURISTICS[policy](env.core, act_rng))
        rows.append({k: np.asarray(v) for k, v in info.items() if np.ndim(v) == 1 and k != "final_rows"})
    return {k: np.stack([r[k] for r in rows]) for k in rows[0]}


# %% [markdown]
# ## The wrappers side by side
#
# A PettingZoo episode and environment 2 of a vector env seeded 2 below it (so the same seed) see
# the same observations, rewards and infos step for step; the vector env restarts a finished
# episode in the same call and returns the last observation of the old one; the infos of
# `reset()` carry the keys of `step()`.

# %%
from pemamoe.env import make_env

pz = make_env()
pz_obs, pz_infos = pz.reset(seed=seed + 2)
venv = make_vector_env(3, seed=seed)
v_obs, _, _ = venv.reset()
assert all(np.array_equal(pz_obs[f"uav_{u}"], v_obs[2, u]) for u in range(3))
wrap_rng = np.random.default_rng(seed)
for step in range(pz.cfg.episode_steps):
    acts = wrap_rng.uniform(-1, 1, (3, 3, 2))
    pz_obs, pz_rew, pz_term, pz_trunc, pz_step_infos = pz.step({f"uav_{u}": acts[2, u] for u in range(3)})
    v_obs, _, v_rew, v_term, v_trunc, v_info = venv.step(acts)
    assert pz_rew["uav_0"] == v_rew[2]
    if v_term[2] or v_trunc[2]:
        break
    assert all(np.array_equal(pz_obs[f"uav_{u}"], v_obs[2, u]) for u in range(3))
assert not pz.agents and 2 in v_info["final_rows"]
row = list(v_info["final_rows"]).index(2)
assert all(np.array_equal(pz_obs[f"uav_{u}"], v_info["final_obs"][row, u]) for u in range(3))
assert set(pz_infos["uav_0"]) == set(pz_step_infos["uav_0"])
print(f"PettingZoo episode of {step + 1} steps = vector env member 2, bit for bit; the vector env restarted it "
      f"in the same call (final_rows {v_info['final_rows'].tolist()})")
