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
# # 01 · Channel model (paper section III-B)
#
# This notebook turns the paper's air-to-ground radio model into vectorised numpy code. Every
# function works on whole arrays of links at once: positions come in as `(..., U, 3)` for the
# UAVs and `(..., N, 3)` for the users, and every per-link quantity comes out as `(..., N, U)`
# (user index first, UAV index second). The leading `...` can be a batch of environments, so one
# call evaluates every link of every environment, with no Python loop over users or UAVs.
#
# The chain we build, from positions to rates:
#
# 1. **geometry**: horizontal distance, height difference, 3-D distance;
# 2. **line of sight**: a probability that depends on distance and height, then one random
#    LoS/NLoS state per link;
# 3. **path loss** for each state, plus **shadowing** (log-normal) and **small-scale fading**
#    (Rician when the direct ray exists, Nakagami-m when it does not);
# 4. **interference** between UAVs sharing a frequency colour, with leakage between colours;
# 5. **noise, SINR and Shannon-type rate**, and the inverse problem the scheduler solves: the
#    power a user needs to reach a target rate.
#
# Randomness always enters through an explicit `numpy.random.Generator`, so a seed fixes every
# draw. All constants live in one frozen `ChannelConfig`.

# %%
#| default_exp channel

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %%
#| export
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from pemamoe.core import require_field

# %% [markdown]
# ## The configuration
#
# One frozen dataclass carries every number of the channel. The defaults are the values every
# experiment here uses: 2 GHz carrier, 10 MHz of spectrum, one frequency colour (reuse factor 1,
# as in the paper) with a leakage of $10^{-3}$ between colours, 0.1 W (20 dBm) per UAV, thermal noise
# of $-174$ dBm/Hz, isotropic antennas, an implementation-loss factor $\alpha = 0.8$ on the
# Shannon rate, Rician $K = 6$ dB for LoS links, Nakagami $m = 1$ (Rayleigh) for NLoS links, and
# shadowing spreads of 4 dB / 7.82 dB (the 3GPP UMi values).
#
# The coefficients of the LoS-probability and path-loss formulas are fields too (the paper's
# numbers are the defaults), so a study can swap in, say, the 3GPP UMa variants without touching
# code.
#
# Two guards keep the arithmetic finite: `min_distance_m` floors the 3-D distance (a UAV exactly
# above a user at the user's height would otherwise give $\log_{10} 0$), and `min_gain` is the
# $\varepsilon$ of the power rule, so a vanishing gain asks for a huge but finite power.
#
# **Why we forbid $K < 0$ dB.** The Rician $K$ factor is the power ratio of the direct ray to the
# scattered rays. Below 0 dB the direct ray is weaker than the scatter, and the link behaves
# almost like a Rayleigh (NLoS) link. In this model that situation is already represented by the
# NLoS branch (Nakagami-m fading on top of the NLoS path loss), so a LoS link with $K < 0$ dB
# would describe the same physics twice with contradicting path losses. We therefore reject it.
#
# A bad value raises a `ValueError` naming the class, the field, the value and the allowed
# range, at construction time rather than deep inside a training run.

# %%
#| export
@dataclass(frozen=True)
class ChannelConfig:
    """Every constant of the air-to-ground channel (units in the field names)."""

    carrier_ghz: float = 2.0
    bandwidth_hz: float = 10e6  # total spectrum B, split into `reuse_factor` colours
    reuse_factor: int = 1  # F: number of frequency colours
    adjacent_leakage: float = 1e-3  # rho_adj: share of a different colour's power that leaks in
    max_tx_power_w: float = 0.1  # P_max per UAV (20 dBm)
    noise_dbm_per_hz: float = -174.0  # one-sided N0
    tx_gain_dbi: float = 0.0
    rx_gain_dbi: float = 0.0
    implementation_loss: float = 0.8  # alpha: rate = alpha * B * log2(1 + SINR)
    rician_k_db: float = 6.0  # LoS fading
    nakagami_m: float = 1.0  # NLoS fading (m = 1 is Rayleigh)
    shadowing_los_db: float = 4.0
    shadowing_nlos_db: float = 7.82
    los_breakpoint_m: float = 18.0  # P_LoS = 1 up to this 3-D distance
    los_decay_m: float = 36.0  # decay length of the exponential LoS term
    min_gain: float = 1e-20  # epsilon of the feasibility power rule
    min_distance_m: float = 1.0  # 3-D distances are floored here
    # Coefficients of the paper's formulas (defaults = the paper's numbers).
    los_height_offset_m: float = 13.0  # C0(h) = (max(h - offset, 0) / scale) ** exponent
    los_height_scale_m: float = 10.0
    los_height_exponent: float = 1.5
    pl_intercept_db: float = 28.0  # PL_LoS = intercept + dist_slope log10(r) + freq_slope log10(fc)
    pl_distance_slope_db: float = 22.0
    pl_frequency_slope_db: float = 20.0
    nlos_offset_db: float = 13.0  # PL_NLoS = PL_LoS + offset + coeff * r ** exponent
    nlos_distance_coeff_db: float = 0.1
    nlos_distance_exponent: float = 0.25

    def __post_init__(self):
        # Every field is a finite real number (no constant of this model is meaningfully
        # infinite), except reuse_factor, an integer; see pemamoe.core.require.
        for name, bounds in {
            "carrier_ghz": dict(gt=0),
            "bandwidth_hz": dict(gt=0),
            "adjacent_leakage": dict(ge=0, lt=1),
            "max_tx_power_w": dict(gt=0),
            "noise_dbm_per_hz": {},
            "tx_gain_dbi": {},
            "rx_gain_dbi": {},
            "implementation_loss": dict(gt=0, le=1),
            "rician_k_db": dict(ge=0, note="in dB: a LoS ray weaker than its scatter is what the NLoS branch models"),
            "nakagami_m": dict(ge=0.5),
            "shadowing_los_db": dict(ge=0),
            "shadowing_nlos_db": dict(ge=0),
            "los_breakpoint_m": dict(gt=0),
            "los_decay_m": dict(gt=0),
            "min_gain": dict(gt=0),
            "min_distance_m": dict(gt=0),
            "los_height_offset_m": {},
            "los_height_scale_m": dict(gt=0),
            "los_height_exponent": dict(gt=0),
            "pl_intercept_db": {},
            "pl_distance_slope_db": dict(gt=0),
            "pl_frequency_slope_db": {},
            "nlos_offset_db": dict(ge=0),
            "nlos_distance_coeff_db": dict(ge=0),
            "nlos_distance_exponent": dict(ge=0),
        }.items():
            require_field(self, name, "real", **bounds)
        require_field(self, "reuse_factor", "int", ge=1)

    @property
    def noise_w_per_hz(self) -> float:
        """N0 in W/Hz (-174 dBm/Hz is about 3.98e-21 W/Hz)."""
        return 10.0 ** ((self.noise_dbm_per_hz - 30.0) / 10.0)

    @property
    def antenna_gain(self) -> float:
        """G_TX * G_RX as a linear factor."""
        return 10.0 ** ((self.tx_gain_dbi + self.rx_gain_dbi) / 10.0)

    @property
    def rician_k(self) -> float:
        """Rician K as a linear power ratio."""
        return 10.0 ** (self.rician_k_db / 10.0)

    @property
    def colour_bandwidth_hz(self) -> float:
        """B / F: the spectrum of one frequency colour."""
        return self.bandwidth_hz / self.reuse_factor

    @property
    def max_tx_power_dbm(self) -> float:
        return 10.0 * math.log10(self.max_tx_power_w) + 30.0


# %% [markdown]
# ## Geometry
#
# For user $n$ at $\mathbf s_n = (x_n, y_n, z_n)$ and UAV $u$ at $\mathbf q_u = (x_u, y_u, h_u)$:
#
# * horizontal distance $d_{n,u} = \lVert (x_n - x_u,\; y_n - y_u) \rVert$,
# * relative height $h_{n,u} = h_u - z_n$ (the UAV's altitude above the user, not above ground),
# * 3-D distance $r_{n,u} = \sqrt{d_{n,u}^2 + h_{n,u}^2}$, floored at `min_distance_m`.
#
# Broadcasting does the pairing: users get a new UAV axis and UAVs a new user axis, so the result
# is `(..., N, U)` with no loop.

# %%
#| export
def link_geometry(uav_xyz, user_xyz, cfg: ChannelConfig):
    """Per-link geometry.

    uav_xyz:  (..., U, 3) UAV positions [m]; user_xyz: (..., N, 3) user positions [m].
    Returns (horizontal_m, rel_height_m, distance_3d_m), each (..., N, U). The 3-D distance is
    floored at cfg.min_distance_m so coincident positions stay finite.
    """
    uav = np.asarray(uav_xyz, dtype=float)
    user = np.asarray(user_xyz, dtype=float)
    if uav.shape[-1:] != (3,) or user.shape[-1:] != (3,):
        raise ValueError(
            f"link_geometry expects uav_xyz (..., U, 3) and user_xyz (..., N, 3); "
            f"got {uav.shape} and {user.shape}"
        )
    delta_xy = user[..., :, None, :2] - uav[..., None, :, :2]  # (..., N, U, 2)
    horizontal = np.hypot(delta_xy[..., 0], delta_xy[..., 1])
    rel_height = uav[..., None, :, 2] - user[..., :, None, 2]
    distance = np.maximum(np.hypot(horizontal, rel_height), cfg.min_distance_m)
    return horizontal, rel_height, distance


# %% [markdown]
# ## Line-of-sight probability
#
# The paper starts from the 3GPP street-canyon (UMi) expression, which is 1 up to 18 m and then
# mixes a $18/r$ term with an exponentially decaying term of length 36 m, and multiplies the
# exponential term by an altitude bonus $1 + C_0(h)$ with
#
# $$C_0(h) = \Big(\frac{\max(h - 13,\,0)}{10}\Big)^{1.5},$$
#
# $$P_\text{LoS}(r, h) = \begin{cases} 1 & r \le 18\,\text{m} \\
# \dfrac{18}{r} + e^{-r/36}\Big(1 - \dfrac{18}{r}\Big)\big(1 + C_0(h)\big) & r > 18\,\text{m}
# \end{cases}$$
#
# clipped to $[0, 1]$. Here $r$ is the 3-D distance and $h$ the relative height. The bonus grows
# quickly with altitude ($C_0 \approx 25$ at a relative height of 98.5 m), so near the UAV the
# raw expression exceeds 1 and the clip makes the link certainly LoS; far away the exponential has
# died out and only $18/r$ remains, whatever the altitude. The figure below shows both regimes.

# %%
#| export
def height_correction(rel_height_m, cfg: ChannelConfig):
    """C0(h) = (max(h - 13, 0) / 10) ** 1.5 with the config's coefficients; same shape as h."""
    excess = np.maximum(np.asarray(rel_height_m, dtype=float) - cfg.los_height_offset_m, 0.0)
    return (excess / cfg.los_height_scale_m) ** cfg.los_height_exponent


def los_probability(distance_m, rel_height_m, cfg: ChannelConfig):
    """P_LoS(r, h) in [0, 1]; r = 3-D distance [m], h = relative height [m], broadcast together."""
    r = np.maximum(np.asarray(distance_m, dtype=float), cfg.min_distance_m)
    ratio = np.minimum(cfg.los_breakpoint_m / r, 1.0)  # = 1 inside the breakpoint
    p = ratio + np.exp(-r / cfg.los_decay_m) * (1.0 - ratio) * (1.0 + height_correction(rel_height_m, cfg))
    # Inside the breakpoint (1 - ratio) is 0, so p is exactly 1 there even before the clip.
    return np.clip(np.where(r <= cfg.los_breakpoint_m, 1.0, p), 0.0, 1.0)


# %% [markdown]
# ## Path loss
#
# For a LoS link the loss in dB is $28 + 22\log_{10} r + 20\log_{10} f_c$ with $r$ in metres and
# $f_c$ in GHz; an NLoS link pays $13 + 0.1\,r^{0.25}$ dB more. (The second term is small: 0.3 dB
# at 100 m, 0.56 dB at 1 km; the 13 dB offset does the work.) At 100 m and 2 GHz the LoS loss is
# $28 + 44 + 6.02 = 78.02$ dB.

# %%
#| export
def path_loss_los_db(distance_m, cfg: ChannelConfig):
    """LoS path loss [dB] at 3-D distance r [m] (floored at cfg.min_distance_m)."""
    r = np.maximum(np.asarray(distance_m, dtype=float), cfg.min_distance_m)
    return (
        cfg.pl_intercept_db
        + cfg.pl_distance_slope_db * np.log10(r)
        + cfg.pl_frequency_slope_db * math.log10(cfg.carrier_ghz)
    )


def path_loss_nlos_db(distance_m, cfg: ChannelConfig):
    """NLoS path loss [dB] = LoS loss + 13 + 0.1 r^0.25 (paper's coefficients by default)."""
    r = np.maximum(np.asarray(distance_m, dtype=float), cfg.min_distance_m)
    return path_loss_los_db(r, cfg) + cfg.nlos_offset_db + cfg.nlos_distance_coeff_db * r ** cfg.nlos_distance_exponent


# %% [markdown]
# ## What the scheduler knows: large-scale CSI
#
# The scheduler decides admissions and powers before the slot's fading and shadowing are known,
# so it plans on the **expected large-scale gain**: the LoS and NLoS path-loss gains averaged with
# the LoS probability, times the antenna gains,
#
# $$\bar g = G_\text{TX} G_\text{RX}\Big(P_\text{LoS}\,10^{-\text{PL}_\text{LoS}/10} + (1 - P_\text{LoS})\,10^{-\text{PL}_\text{NLoS}/10}\Big).$$
#
# Fading has unit mean, so leaving it out does not bias $\bar g$. Shadowing is zero-mean *in dB*,
# which makes its linear median 1 but its linear mean larger than 1 ($e^{(\sigma\ln 10/10)^2/2}$:
# 1.53 for 4 dB, 5.1 for 7.82 dB); $\bar g$ leaves it out, so the planner works with the median
# shadowing. The realised SINR then differs from the planned one, which is the point: a user the
# scheduler admits can still miss its rate in a deep fade.

# %%
#| export
def large_scale_gain(distance_m, rel_height_m, cfg: ChannelConfig):
    """Expected linear gain (antenna gains included, no fading or shadowing), shape of r and h."""
    p_los = los_probability(distance_m, rel_height_m, cfg)
    return _expected_gain(p_los, path_loss_los_db(distance_m, cfg), path_loss_nlos_db(distance_m, cfg), cfg)


def _expected_gain(p_los, pl_los_db, pl_nlos_db, cfg: ChannelConfig):
    g_los = 10.0 ** (-pl_los_db / 10.0)
    g_nlos = 10.0 ** (-pl_nlos_db / 10.0)
    return cfg.antenna_gain * (p_los * g_los + (1.0 - p_los) * g_nlos)


# %% [markdown]
# ## Small-scale fading and shadowing
#
# Both fading laws are normalised so that the power $|h|^2$ has mean 1: fading then scatters the
# gain around the path-loss value without shifting its average.
#
# * **Rician (LoS).** A fixed direct component of power $K/(K+1)$ plus a complex Gaussian scatter
#   of power $1/(K+1)$: $h = \sqrt{K/(K+1)} + \sqrt{1/(2(K+1))}\,(x + jy)$ with $x, y \sim
#   \mathcal N(0,1)$. With $K = 6$ dB ($\approx 3.98$) most of the power is in the direct ray and
#   deep fades are rare.
# * **Nakagami-m (NLoS).** The power is Gamma distributed with shape $m$ and scale $1/m$. $m = 1$ is
#   Rayleigh fading (exponential power); larger $m$ means milder fading; $m = 0.5$ is the most
#   severe case the Nakagami family allows.
# * **Shadowing.** A Gaussian in dB, zero mean, spread $\sigma_\text{LoS}$ or $\sigma_\text{NLoS}$
#   by the link's state, added to the path loss.

# %%
#| export
def rician_power(los_shape, k_db, rng: np.random.Generator):
    """Rician fading power |h|^2 with unit mean; k_db is a scalar or broadcasts to los_shape."""
    k = 10.0 ** (np.asarray(k_db, dtype=float) / 10.0)
    direct = np.sqrt(k / (k + 1.0))
    scatter = np.sqrt(0.5 / (k + 1.0))
    x = rng.standard_normal(los_shape)
    y = rng.standard_normal(los_shape)
    return (direct + scatter * x) ** 2 + (scatter * y) ** 2


def nakagami_power(shape, m, rng: np.random.Generator):
    """Nakagami-m fading power ~ Gamma(shape=m, scale=1/m): unit mean, variance 1/m."""
    m = np.asarray(m, dtype=float)
    if np.any(m < 0.5):
        raise ValueError(f"nakagami_power: m must be >= 0.5, got {m}")
    return rng.gamma(m, 1.0 / m, shape)


def shadowing_db(los_mask, cfg: ChannelConfig, rng: np.random.Generator):
    """Zero-mean Gaussian shadowing [dB], spread by link state; same shape as los_mask."""
    los_mask = np.asarray(los_mask, dtype=bool)
    sigma = np.where(los_mask, cfg.shadowing_los_db, cfg.shadowing_nlos_db)
    return sigma * rng.standard_normal(los_mask.shape)


# %% [markdown]
# ## One random channel realisation
#
# `sample_channel` draws, independently for every link: the LoS state (a Bernoulli trial with
# $P_\text{LoS}$), the fading power of that state's law, and the shadowing. The realised linear
# gain is
#
# $$g = G_\text{TX} G_\text{RX}\;|h|^2\;10^{-(\text{PL}_\text{state} + X_\sigma)/10}.$$
#
# The LoS state is redrawn at every call (every slot): the paper gives no correlation model
# across slots, so we do not invent one. The sample also carries `expected_gain` (the
# large-scale CSI above), so the environment can plan on one and realise on the other.

# %%
#| export
class ChannelSample(NamedTuple):
    """One draw of every link's channel; every field is (..., N, U)."""

    distance_m: np.ndarray  # 3-D distance, floored at cfg.min_distance_m
    rel_height_m: np.ndarray  # UAV altitude minus user height
    horizontal_m: np.ndarray
    los: np.ndarray  # bool: the drawn LoS state
    path_loss_db: np.ndarray  # path loss of the drawn state (shadowing not included)
    fading_power: np.ndarray  # |h|^2, unit mean
    shadowing_db: np.ndarray  # extra loss [dB] added to path_loss_db
    gain: np.ndarray  # realised linear gain, antenna gains included
    expected_gain: np.ndarray  # large_scale_gain: what the scheduler plans on


def sample_channel(uav_xyz, user_xyz, cfg: ChannelConfig, rng: np.random.Generator) -> ChannelSample:
    """Draw LoS states, fading and shadowing for every (user, UAV) link; see ChannelSample."""
    horizontal, rel_height, distance = link_geometry(uav_xyz, user_xyz, cfg)
    p_los = los_probability(distance, rel_height, cfg)
    pl_los, pl_nlos = path_loss_los_db(distance, cfg), path_loss_nlos_db(distance, cfg)
    los = rng.random(distance.shape) < p_los
    path_loss = np.where(los, pl_los, pl_nlos)
    # Both laws are drawn for every link and the state picks one. The count of random numbers a
    # call consumes is then fixed by the shapes alone, whatever the LoS states, so a batch of
    # environments with one stream each can share one call (the environment relies on this).
    fading = np.where(
        los,
        rician_power(distance.shape, cfg.rician_k_db, rng),
        nakagami_power(distance.shape, cfg.nakagami_m, rng),
    )
    shadow = shadowing_db(los, cfg, rng)
    gain = cfg.antenna_gain * fading * 10.0 ** (-(path_loss + shadow) / 10.0)
    return ChannelSample(
        distance_m=distance,
        rel_height_m=rel_height,
        horizontal_m=horizontal,
        los=los,
        path_loss_db=path_loss,
        fading_power=fading,
        shadowing_db=shadow,
        gain=gain,
        expected_gain=_expected_gain(p_los, pl_los, pl_nlos, cfg),  # = large_scale_gain, reusing the parts
    )


# %% [markdown]
# ## Frequency reuse and interference
#
# The spectrum is cut into $F$ colours of width $B/F$ and UAV $u$ gets colour $c(u) = u \bmod F$.
# A user served by UAV $u$ is disturbed by every other UAV $u'$: fully if $u'$ has the same
# colour, and through a leakage factor $\rho_\text{adj} < 1$ if not. We write this as a weight
# matrix $W$ with $W_{u,u} = 0$, $W_{u,u'} = 1$ for a shared colour and $\rho_\text{adj}$
# otherwise, so that
#
# $$I_{n,u} = \sum_{u'} W_{u,u'}\,P_{u'}\,g_{n,u'},$$
#
# a single matrix product over the last axis for every user (and every batch element) at once.
# $I_{n,u}$ is computed for *every* candidate server $u$, which is what the scheduler needs to
# compare UAVs. We make the conservative assumption that every interferer transmits at full power,
# $P_{u'} = P_\text{max}$.
#
# A modelling note: the formula charges the interferer's *total* power against a user that only
# occupies a slice $B_u$ of the colour. If the interferer spreads its power evenly over its
# colour, only the fraction $B_u/(B/F)$ of it falls into the victim's slice. The functions here
# take whatever power the caller passes; the paper's reading is the total power.

# %%
#| export
def reuse_colours(n_uavs: int, reuse_factor: int):
    """Colour c(u) = u mod F of each UAV; shape (U,), dtype int."""
    if int(n_uavs) != n_uavs or n_uavs < 0:
        raise ValueError(f"reuse_colours: n_uavs must be an integer >= 0, got {n_uavs!r}")
    if int(reuse_factor) != reuse_factor or reuse_factor < 1:
        raise ValueError(f"reuse_colours: reuse_factor must be an integer >= 1, got {reuse_factor!r}")
    return np.arange(int(n_uavs)) % int(reuse_factor)


def interference_weights(colours, adjacent_leakage: float):
    """(U, U) weights: 0 on the diagonal, 1 for a shared colour, adjacent_leakage otherwise."""
    if not 0.0 <= adjacent_leakage < 1.0:
        raise ValueError(f"interference_weights: adjacent_leakage must be in [0, 1), got {adjacent_leakage!r}")
    colours = np.asarray(colours)
    weights = np.where(colours[:, None] == colours[None, :], 1.0, float(adjacent_leakage))
    np.fill_diagonal(weights, 0.0)
    return weights


def interference_w(gain, uav_power_w, weights):
    """Interference [W] at user n if served by UAV u: I[..., n, u] = sum_u' W[u, u'] P[..., u'] g[..., n, u'].

    gain: (..., N, U) linear gains; uav_power_w: (..., U) or scalar; weights: (U, U).
    Returns (..., N, U).
    """
    gain = np.asarray(gain, dtype=float)
    power = np.asarray(uav_power_w, dtype=float)
    # A per-UAV power vector gets a user axis; a scalar (every UAV at the same power) broadcasts.
    received = gain * (power if power.ndim == 0 else power[..., None, :])  # (..., N, U')
    return received @ np.asarray(weights, dtype=float).T


# %% [markdown]
# ## Noise, SINR and rate
#
# Noise in the user's band is $N_0 B_u$; the SINR is $p\,g / (N_0 B_u + I)$; the achievable rate
# is $\alpha B_u \log_2(1 + \text{SINR})$. In the paper a UAV with $K_u$ users gives each
# $B_u = B/(F K_u)$ (`user_bandwidth_hz`).
#
# Edge cases, decided once here: a user with zero bandwidth gets rate 0; an SINR with zero noise
# and zero interference is $+\infty$ if the received power is positive and 0 otherwise.

# %%
#| export
def noise_power_w(bandwidth_hz, cfg: ChannelConfig):
    """Thermal noise N0 * B [W]; -174 dBm/Hz over 1 MHz is -114 dBm."""
    return cfg.noise_w_per_hz * np.asarray(bandwidth_hz, dtype=float)


def user_bandwidth_hz(n_served, cfg: ChannelConfig):
    """Per-user bandwidth B / (F * K_u) for K_u served users; 0 where K_u == 0."""
    k = np.asarray(n_served, dtype=float)
    with np.errstate(divide="ignore"):
        return np.where(k > 0, cfg.colour_bandwidth_hz / np.maximum(k, 1.0), 0.0)


def sinr(power_w, gain, noise_w, interference_w):
    """p g / (noise + I), broadcast over all arguments; 0/0 -> 0 and x/0 -> inf for x > 0."""
    signal = np.asarray(power_w, dtype=float) * np.asarray(gain, dtype=float)
    disturbance = np.asarray(noise_w, dtype=float) + np.asarray(interference_w, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = signal / disturbance
    return np.where(disturbance > 0, ratio, np.where(signal > 0, np.inf, 0.0))


def achievable_rate_bps(bandwidth_hz, sinr, cfg: ChannelConfig):
    """alpha * B * log2(1 + SINR) [bit/s]; 0 where the bandwidth is 0."""
    bandwidth = np.asarray(bandwidth_hz, dtype=float)
    with np.errstate(invalid="ignore"):
        rate = cfg.implementation_loss * bandwidth * np.log2(1.0 + np.asarray(sinr, dtype=float))
    return np.where(bandwidth > 0, rate, 0.0)


# %% [markdown]
# ## The feasibility rule: how much power a target rate costs
#
# Inverting the rate formula gives the SINR a target rate $R^*$ needs on a band $B_u$,
# $\gamma^* = 2^{R^*/(\alpha B_u)} - 1$, and from it the transmit power under a given (here
# conservative) interference:
#
# $$p = \frac{\gamma^*\,(N_0 B_u + I)}{\max(g, \varepsilon)}.$$
#
# The required SINR grows *exponentially* with the spectral efficiency $R^*/B_u$: halving the band
# of a user more than doubles the SINR it needs. Conventions for the corners:
#
# * a target of 0 costs 0 W, whatever the band;
# * a positive target on a zero band is impossible: the required SINR and power are `np.inf`
#   (so a comparison with the power budget simply fails; no NaN ever appears);
# * negative targets or bandwidths are errors.
#
# By construction, plugging $p$ back into `sinr` and `achievable_rate_bps` returns $R^*$ (up to
# rounding) whenever $g \ge \varepsilon$.

# %%
#| export
def required_sinr(target_rate_bps, bandwidth_hz, cfg: ChannelConfig):
    """gamma* = 2^(R / (alpha B)) - 1; 0 where R == 0, inf where R > 0 and B == 0."""
    rate, bandwidth = _nonnegative_rate_and_band(target_rate_bps, bandwidth_hz)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        efficiency = rate / (cfg.implementation_loss * bandwidth)
        gamma = np.expm1(efficiency * math.log(2.0))  # accurate for small efficiencies
    return np.where(rate == 0, 0.0, np.where(bandwidth == 0, np.inf, gamma))


def required_power_w(target_rate_bps, bandwidth_hz, gain, interference_w, cfg: ChannelConfig):
    """Transmit power [W] reaching target_rate_bps: gamma* (N0 B + I) / max(g, eps).

    All arguments broadcast (typically (..., N, U)). 0 where the target is 0; inf where the
    target is positive and the bandwidth is 0.
    """
    rate, bandwidth = _nonnegative_rate_and_band(target_rate_bps, bandwidth_hz)
    gamma = required_sinr(rate, bandwidth, cfg)
    disturbance = noise_power_w(bandwidth, cfg) + np.asarray(interference_w, dtype=float)
    effective_gain = np.maximum(np.asarray(gain, dtype=float), cfg.min_gain)
    with np.errstate(invalid="ignore", over="ignore"):
        power = gamma * disturbance / effective_gain
    return np.where(rate == 0, 0.0, np.where(bandwidth == 0, np.inf, power))


# %%
#| exporti
def _nonnegative_rate_and_band(target_rate_bps, bandwidth_hz):
    rate = np.asarray(target_rate_bps, dtype=float)
    bandwidth = np.asarray(bandwidth_hz, dtype=float)
    if np.any(rate < 0) or np.any(np.isnan(rate)):
        raise ValueError(f"target_rate_bps must be >= 0, got {rate}")
    if np.any(bandwidth < 0) or np.any(np.isnan(bandwidth)):
        raise ValueError(f"bandwidth_hz must be >= 0, got {bandwidth}")
    return rate, bandwidth


# %% [markdown]
# ---
# ## Demonstrations
#
# The cells below are not exported. They draw the model's curves, check a few numbers, and
# print a link budget. Sizes follow `scale`: `ci` uses coarse grids so the notebook runs in
# seconds.

# %%
import matplotlib.pyplot as plt

from pemamoe.core import by_scale, save_figure

cfg = ChannelConfig()
rng = np.random.default_rng(seed)
user_height_m = 1.5  # project default
uav_altitude_m = 100.0  # project default
n_curve = by_scale(scale, ci=200, small=1000, paper=2000)
n_grid = by_scale(scale, ci=41, small=151, paper=301)
n_draws = by_scale(scale, ci=20_000, small=200_000, paper=1_000_000)
print(cfg)
print(f"N0 = {cfg.noise_w_per_hz:.3e} W/Hz; P_max = {cfg.max_tx_power_dbm:.1f} dBm")

# %% [markdown]
# ### LoS probability against horizontal distance
#
# Near the UAV the altitude bonus pushes the raw expression above 1 and the clip holds it there;
# past a few hundred metres every curve collapses onto $18/r$. Note the 150 m curve: directly
# under the UAV its 3-D distance is already 148.5 m, the exponential term has faded, and the
# probability is *below* that of a 100 m UAV, although a higher UAV sees the ground at steeper
# angles. This is a property of the paper's formula (it measures distance in 3-D and keeps the
# street-level decay length), not of the code.

# %%
horizontal = np.linspace(0.0, 1000.0, n_curve)
fig, ax = plt.subplots(figsize=(6, 3.8))
for altitude in (30.0, 60.0, 100.0, 150.0):
    h = altitude - user_height_m
    r = np.hypot(horizontal, h)
    ax.plot(horizontal, los_probability(r, h, cfg), label=f"UAV at {altitude:.0f} m")
ax.plot(horizontal, los_probability(np.hypot(horizontal, 0.0), 0.0, cfg), "k:", label="ground level (no bonus)")
ax.set(xlabel="horizontal distance [m]", ylabel="$P_\\mathrm{LoS}$", ylim=(0, 1.02), xlim=(0, 1000))
ax.grid(alpha=0.3)
ax.legend()
save_figure(fig, "channel_los_probability", figures_dir)

# %% [markdown]
# ![LoS probability against horizontal distance, four UAV altitudes](../paper_figures/channel_los_probability.png)

# %% [markdown]
# ### Path loss
#
# LoS and NLoS losses against 3-D distance, the expected gain the scheduler plans with (as an
# equivalent loss, for a UAV at 100 m), and, as grey dots, realised losses including fading and
# shadowing from one `sample_channel` draw along the same line.

# %%
r = np.geomspace(10.0, 1500.0, n_curve)
h = uav_altitude_m - user_height_m
line_users = np.stack([horizontal, np.zeros_like(horizontal), np.full_like(horizontal, user_height_m)], axis=-1)
draw = sample_channel(np.array([[0.0, 0.0, uav_altitude_m]]), line_users, cfg, rng)

fig, ax = plt.subplots(figsize=(6, 3.8))
ax.scatter(draw.distance_m[:, 0], -10 * np.log10(draw.gain[:, 0]), s=3, c="0.6", label="one realisation")
ax.plot(r, path_loss_los_db(r, cfg), label="LoS")
ax.plot(r, path_loss_nlos_db(r, cfg), label="NLoS")
r_h = r[r >= h]
ax.plot(r_h, -10 * np.log10(large_scale_gain(r_h, h, cfg)), "k--", label="expected (UAV at 100 m)")
ax.set(xlabel="3-D distance [m]", ylabel="path loss [dB]", xscale="log")
ax.grid(alpha=0.3, which="both")
ax.legend()
save_figure(fig, "channel_path_loss", figures_dir)

# %% [markdown]
# ![Path loss against 3-D distance: LoS, NLoS, the expected loss and one realisation](../paper_figures/channel_path_loss.png)

# %% [markdown]
# ### Fading and shadowing sanity check
#
# Empirical means of the two fading laws (should be 1) and of the shadowing in dB (should be 0).

# %%
for name, draws in {
    "Rician K=6 dB": rician_power(n_draws, cfg.rician_k_db, rng),
    "Nakagami m=1": nakagami_power(n_draws, cfg.nakagami_m, rng),
    "Nakagami m=0.5": nakagami_power(n_draws, 0.5, rng),
}.items():
    print(f"{name:15s} mean {draws.mean():.4f}  var {draws.var():.3f}  P(|h|^2 < 0.1) {np.mean(draws < 0.1):.4f}")
x = shadowing_db(np.zeros(n_draws, bool), cfg, rng)
print(f"NLoS shadowing: mean {x.mean():+.3f} dB, std {x.std():.3f} dB")

# %% [markdown]
# ### Rate map for three UAVs
#
# Three UAVs at 100 m over the 1 km x 1 km area. At each ground point a test user associates with
# the UAV of largest expected gain, which serves it alongside four other users: it gets $B/(5F)$
# of spectrum and $P_\text{max}/5$ of power, while the other two UAVs transmit at $P_\text{max}$
# (conservative interference). Left: one colour for all (reuse 1, the paper's setting). Right:
# three colours, so the interference shrinks to the $10^{-3}$ leakage but each user gets a third
# of the band. White contours mark the L/M/H demand thresholds 0.5 / 1 / 2 Mbps.

# %%
uavs = np.array([[250.0, 250.0, uav_altitude_m], [750.0, 300.0, uav_altitude_m], [480.0, 760.0, uav_altitude_m]])
axis = np.linspace(0.0, 1000.0, n_grid)
gx, gy = np.meshgrid(axis, axis)
grid_users = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, user_height_m)], axis=-1)
_, rel_h, dist = link_geometry(uavs, grid_users, cfg)
g_bar = large_scale_gain(dist, rel_h, cfg)  # (points, U)
users_per_uav = 5


def rate_map(reuse_factor):
    c = ChannelConfig(reuse_factor=reuse_factor)
    weights = interference_weights(reuse_colours(len(uavs), reuse_factor), c.adjacent_leakage)
    interf = interference_w(g_bar, np.full(len(uavs), c.max_tx_power_w), weights)
    band = user_bandwidth_hz(users_per_uav, c)
    gamma = sinr(c.max_tx_power_w / users_per_uav, g_bar, noise_power_w(band, c), interf)
    best = np.argmax(g_bar, axis=-1)
    best_sinr = np.take_along_axis(gamma, best[:, None], axis=-1)[:, 0]
    return achievable_rate_bps(band, best_sinr, c).reshape(gx.shape) / 1e6


maps = {F: rate_map(F) for F in (1, 3)}
vmax = max(m.max() for m in maps.values())
fig, axes = plt.subplots(1, 2, figsize=(10, 4.2), sharey=True, constrained_layout=True)
for ax, (F, rates) in zip(axes, maps.items()):
    im = ax.pcolormesh(gx, gy, rates, shading="auto", vmin=0, vmax=vmax, cmap="viridis")
    cs = ax.contour(gx, gy, rates, levels=[0.5, 1.0, 2.0], colors="white", linewidths=0.8)
    ax.clabel(cs, fmt="%.1f")
    ax.plot(uavs[:, 0], uavs[:, 1], "r^", ms=9)
    served = [np.mean(rates >= t) for t in (0.5, 1.0, 2.0)]
    ax.set(title=f"reuse F={F}: area >= 0.5/1/2 Mbps: " + "/".join(f"{s:.0%}" for s in served),
           xlabel="x [m]", aspect="equal")
    ax.title.set_fontsize(9)
axes[0].set_ylabel("y [m]")
fig.colorbar(im, ax=axes, label="rate of a user with B/(5F), P_max/5 [Mbps]")
save_figure(fig, "channel_rate_map", figures_dir)

# %% [markdown]
# ![Rate map for three UAVs at 100 m, reuse 1 (left) and reuse 3 (right)](../paper_figures/channel_rate_map.png)

# %% [markdown]
# ### Link budget: does the 0.1 W budget bind?
#
# A user walks from under its UAV (at 100 m) toward a co-channel neighbour 500 m away (the
# typical spacing of three UAVs in this area), with a third UAV 500 m away on the other side.
# Both neighbours transmit at $P_\text{max}$ (conservative interference, reuse 1). The user gets
# $B/5 = 2$ MHz. We print the expected gain, the interference, and the power each demand class
# needs; the budget binds when five such users together need more than 0.1 W.

# %%
serving = np.array([0.0, 0.0, uav_altitude_m])
neighbours = np.array([[500.0, 0.0, uav_altitude_m], [-250.0, 433.0, uav_altitude_m]])
walk = np.array([0.0, 50.0, 100.0, 150.0, 200.0, 250.0])
walk_users = np.stack([walk, np.zeros_like(walk), np.full_like(walk, user_height_m)], axis=-1)
_, rel_h, dist = link_geometry(np.vstack([serving, neighbours]), walk_users, cfg)
g_walk = large_scale_gain(dist, rel_h, cfg)
W = interference_weights(reuse_colours(3, cfg.reuse_factor), cfg.adjacent_leakage)
interf_walk = interference_w(g_walk, np.full(3, cfg.max_tx_power_w), W)[:, 0]
band = cfg.bandwidth_hz / users_per_uav
targets = np.array([0.5e6, 1e6, 2e6])
p_noise = required_power_w(targets, band, g_walk[:, :1], 0.0, cfg)
p_conservative = required_power_w(targets, band, g_walk[:, :1], interf_walk[:, None], cfg)

print(f"B_u = {band / 1e6:.0f} MHz, noise {10 * np.log10(noise_power_w(band, cfg)) + 30:.1f} dBm, "
      f"gamma* for 0.5/1/2 Mbps = " + ", ".join(f"{x:.3f}" for x in required_sinr(targets, band, cfg)))
print(f"{'d [m]':>6} {'r [m]':>6} {'P_LoS':>6} {'PL_LoS':>7} {'PL_NLoS':>8} {'E[g] dB':>8} {'I dBm':>7} "
      f"| {'noise-only p [mW] 0.5/1/2 Mbps':>32} | {'conservative p [mW] 0.5/1/2 Mbps':>34}")
for i, d in enumerate(walk):
    r0, h0 = dist[i, 0], rel_h[i, 0]
    print(
        f"{d:6.0f} {r0:6.1f} {float(los_probability(r0, h0, cfg)):6.3f} {float(path_loss_los_db(r0, cfg)):7.2f} "
        f"{float(path_loss_nlos_db(r0, cfg)):8.2f} {10 * np.log10(g_walk[i, 0]):8.2f} "
        f"{10 * np.log10(interf_walk[i]) + 30:7.1f} | "
        + " ".join(f"{1e3 * x:10.4f}" for x in p_noise[i]) + " | "
        + " ".join(f"{1e3 * x:10.3f}" for x in p_conservative[i])
    )
print(f"budget per user if 5 users share P_max: {1e3 * cfg.max_tx_power_w / users_per_uav:.0f} mW")

# %% [markdown]
# Reading the table: thermal noise alone never binds (micro- to milliwatts at any distance in the
# area). The conservative interference does: once the user is a couple of hundred metres from
# its UAV the neighbour's signal is only a few dB weaker than the server's, and high-demand users
# need more than their fifth of the budget. That is what makes UAV placement matter in this
# problem, and why the scheduler admits users greedily until the power runs out.
