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
# # 04b · Appendix: the compiled engine
#
# Notebook 04 defines the environment: its dynamics, scheduler, objective, observations and API,
# all as readable numpy. This appendix holds the machinery that makes that environment fast, and
# nothing in it changes what the environment *is*: the compiled engine (module
# `pemamoe.env_kernel`), the same step as notebook 04's numpy reference written as numba-compiled
# loops, and `CompiledStep`, which feeds it from the batched core. `EnvConfig(step_engine=
# "compiled")`, the default, selects it. The random streams are appendix 04c's, the wrappers
# appendix 04d's and the module outside code imports, `pemamoe.env`, appendix 04e's.
#
# Read it when you change the dynamics of notebook 04 (the compiled step must follow, and the tests
# that step both engines side by side will say where it does not), or when you need to know why the
# environment runs at the speed it does. The modules stack without import cycles:
# `pemamoe.streams` and `pemamoe.env_kernel` sit below notebook 04's model (`pemamoe.env_model`),
# the wrappers above it, and `pemamoe.env` on top. The model imports `pemamoe.env_kernel` only when
# a core with the compiled engine is built, so `import pemamoe.env` never loads numba, and it hands
# the engine what the engine needs from it (the observation and state sizes, the random numbers
# one slot draws) as arguments.

# %%
#| default_exp env_kernel

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

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
