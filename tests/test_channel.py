"""Channel model (notebooks/01_channel.py): hand-computed values, properties, config errors."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pemamoe.channel import (
    ChannelConfig,
    ChannelSample,
    achievable_rate_bps,
    interference_w,
    interference_weights,
    large_scale_gain,
    link_geometry,
    los_probability,
    nakagami_power,
    noise_power_w,
    path_loss_los_db,
    path_loss_nlos_db,
    required_power_w,
    required_sinr,
    reuse_colours,
    rician_power,
    sample_channel,
    shadowing_db,
    sinr,
    user_bandwidth_hz,
)

CFG = ChannelConfig()
PROPS = settings(max_examples=50, deadline=None)

distances = st.floats(1.0, 5000.0, allow_nan=False)
heights = st.floats(-50.0, 300.0, allow_nan=False)
coords = st.floats(0.0, 1000.0, allow_nan=False)
seeds = st.integers(0, 2**32 - 1)


# ---------------------------------------------------------------- hand-computed values


def test_los_path_loss_at_100_m_2_ghz():
    # 28 + 22 * 2 + 20 * log10(2) = 78.0206 dB
    assert path_loss_los_db(100.0, CFG) == pytest.approx(78.0206, abs=1e-4)


def test_nlos_offset_at_known_distances():
    # 13 + 0.1 * r ** 0.25: r = 10_000 m -> 13 + 0.1 * 10 = 14.0 dB; r = 16 m -> 13.2 dB
    assert path_loss_nlos_db(1e4, CFG) - path_loss_los_db(1e4, CFG) == pytest.approx(14.0)
    assert path_loss_nlos_db(16.0, CFG) - path_loss_los_db(16.0, CFG) == pytest.approx(13.2)


def test_los_probability_is_one_inside_breakpoint():
    r = np.array([1.0, 5.0, 17.9, 18.0])
    assert np.all(los_probability(r, 100.0, CFG) == 1.0)
    assert np.all(los_probability(r, 0.0, CFG) == 1.0)


def test_los_probability_hand_values():
    # h = 50 m: C0 = 3.7 ** 1.5 = 7.11709; r = 100 m: 0.18 + e^{-100/36} * 0.82 * 8.11709 = 0.59385
    assert los_probability(100.0, 50.0, CFG) == pytest.approx(0.59385, abs=1e-5)
    # h <= 13 m: no bonus, the plain street-canyon curve: 0.18 + e^{-100/36} * 0.82 = 0.23098
    assert los_probability(100.0, 10.0, CFG) == pytest.approx(0.23098, abs=1e-5)


def test_noise_at_1_mhz_is_minus_114_dbm():
    assert 10 * math.log10(float(noise_power_w(1e6, CFG))) + 30 == pytest.approx(-114.0)


def test_required_power_hand_value():
    # R = 1 Mbit/s on B = 1 MHz, alpha = 0.8: gamma* = 2^1.25 - 1 = 1.378414
    # noise -114 dBm = 3.981072e-15 W, I = 1e-15 W, g = 1e-10: p = 1.378414 * 4.981072e-15 / 1e-10
    assert required_sinr(1e6, 1e6, CFG) == pytest.approx(1.378414, rel=1e-6)
    assert required_power_w(1e6, 1e6, 1e-10, 1e-15, CFG) == pytest.approx(6.865979e-5, rel=1e-6)


def test_zero_target_and_zero_bandwidth_corners():
    assert required_power_w(0.0, 0.0, 1e-10, 0.0, CFG) == 0.0
    assert required_power_w(0.0, 1e6, 0.0, 1e-12, CFG) == 0.0
    assert required_power_w(1e6, 0.0, 1e-10, 0.0, CFG) == np.inf
    assert required_sinr(1e6, 0.0, CFG) == np.inf
    assert achievable_rate_bps(0.0, np.inf, CFG) == 0.0
    assert sinr(0.0, 1e-10, 0.0, 0.0) == 0.0
    assert sinr(1.0, 1e-10, 0.0, 0.0) == np.inf
    with pytest.raises(ValueError, match="target_rate_bps"):
        required_power_w(-1.0, 1e6, 1e-10, 0.0, CFG)
    with pytest.raises(ValueError, match="bandwidth_hz"):
        required_sinr(1e6, -1.0, CFG)


def test_vanishing_gain_uses_epsilon():
    p = required_power_w(1e6, 1e6, 0.0, 0.0, CFG)
    assert np.isfinite(p) and p == pytest.approx(1.378414 * 3.981072e-15 / CFG.min_gain, rel=1e-6)


def test_user_bandwidth():
    cfg = ChannelConfig(reuse_factor=2)
    np.testing.assert_allclose(user_bandwidth_hz([0, 1, 5], cfg), [0.0, 5e6, 1e6])


def test_geometry_shapes_and_values():
    uavs = np.array([[0.0, 0.0, 100.0], [300.0, 400.0, 50.0]])  # (U=2, 3)
    users = np.array([[0.0, 0.0, 1.5], [0.0, 0.0, 0.0], [300.0, 400.0, 50.0]])  # (N=3, 3)
    horizontal, rel_height, distance = link_geometry(uavs, users, CFG)
    assert horizontal.shape == rel_height.shape == distance.shape == (3, 2)
    assert horizontal[1, 1] == pytest.approx(500.0)
    assert rel_height[0, 0] == pytest.approx(98.5)
    assert distance[1, 1] == pytest.approx(math.hypot(500.0, 50.0))
    assert distance[2, 1] == CFG.min_distance_m  # coincident positions: floored


def test_batched_geometry_matches_unbatched():
    rng = np.random.default_rng(1)
    uavs = rng.uniform(0, 1000, (4, 3, 3))
    users = rng.uniform(0, 1000, (4, 7, 3))
    batched = link_geometry(uavs, users, CFG)
    for b in range(4):
        single = link_geometry(uavs[b], users[b], CFG)
        for got, want in zip(batched, single):
            np.testing.assert_allclose(got[b], want)


def test_sample_channel_fields_and_consistency():
    rng = np.random.default_rng(2)
    uavs = rng.uniform(0, 1000, (2, 3, 3))
    uavs[..., 2] = 100.0
    users = rng.uniform(0, 1000, (2, 20, 3))
    users[..., 2] = 1.5
    s = sample_channel(uavs, users, CFG, rng)
    assert isinstance(s, ChannelSample)
    for field in s:
        assert field.shape == (2, 20, 3)
    assert s.los.dtype == bool
    want_pl = np.where(s.los, path_loss_los_db(s.distance_m, CFG), path_loss_nlos_db(s.distance_m, CFG))
    np.testing.assert_allclose(s.path_loss_db, want_pl)
    np.testing.assert_allclose(s.gain, s.fading_power * 10 ** (-(s.path_loss_db + s.shadowing_db) / 10))
    np.testing.assert_allclose(s.expected_gain, large_scale_gain(s.distance_m, s.rel_height_m, CFG))


def test_sample_channel_is_reproducible_with_seed():
    uavs = np.array([[100.0, 100.0, 100.0], [900.0, 900.0, 100.0]])
    users = np.random.default_rng(0).uniform(0, 1000, (10, 3))
    a = sample_channel(uavs, users, CFG, np.random.default_rng(7))
    b = sample_channel(uavs, users, CFG, np.random.default_rng(7))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_los_frequency_matches_probability():
    # 40_000 links at P_LoS ~ 0.59: binomial sd ~ 0.0025, so 0.015 is a 6-sigma bound.
    uav = np.array([[0.0, 0.0, 51.5]])
    users = np.tile([[math.sqrt(100.0**2 - 50.0**2), 0.0, 1.5]], (40_000, 1))
    s = sample_channel(uav, users, CFG, np.random.default_rng(3))
    assert s.los.mean() == pytest.approx(0.59385, abs=0.015)


def test_antenna_gains_scale_the_gain():
    cfg = ChannelConfig(tx_gain_dbi=3.0, rx_gain_dbi=7.0)
    assert large_scale_gain(200.0, 98.5, cfg) == pytest.approx(10 * large_scale_gain(200.0, 98.5, CFG))


# ---------------------------------------------------------------- properties


@PROPS
@given(st.lists(distances, min_size=1, max_size=20), heights)
def test_los_probability_in_unit_interval(r, h):
    p = los_probability(np.array(r), h, CFG)
    assert np.all((p >= 0) & (p <= 1))


@PROPS
@given(distances, distances, heights)
def test_los_probability_non_increasing_in_distance(r1, r2, h):
    lo, hi = sorted((r1, r2))
    assert los_probability(lo, h, CFG) >= los_probability(hi, h, CFG) - 1e-12


@PROPS
@given(distances, st.floats(1e-3, 1000.0))
def test_path_loss_strictly_increasing(r, step):
    for pl in (path_loss_los_db, path_loss_nlos_db):
        assert pl(r + step, CFG) > pl(r, CFG)
    assert path_loss_nlos_db(r, CFG) > path_loss_los_db(r, CFG)


@PROPS
@given(seeds, st.floats(0.0, 20.0))
def test_rician_power_has_unit_mean(seed, k_db):
    # Var|h|^2 = (1 + 2K) / (1 + K)^2 <= 1; with n draws a 6-standard-error band is 6 sqrt(var / n).
    n = 100_000
    k = 10 ** (k_db / 10)
    x = rician_power(n, k_db, np.random.default_rng(seed))
    assert np.all(x >= 0)
    assert abs(x.mean() - 1.0) < 6 * math.sqrt((1 + 2 * k) / (1 + k) ** 2 / n)


@PROPS
@given(seeds, st.floats(0.5, 10.0))
def test_nakagami_power_has_unit_mean(seed, m):
    # Gamma(m, 1/m) has variance 1/m; 6 standard errors of the mean of n draws.
    n = 100_000
    x = nakagami_power(n, m, np.random.default_rng(seed))
    assert np.all(x >= 0)
    assert abs(x.mean() - 1.0) < 6 * math.sqrt(1 / m / n)


def test_shadowing_spread_by_state():
    rng = np.random.default_rng(4)
    n = 100_000  # the sample sd of n normals has relative standard error 1/sqrt(2n) ~ 0.2 %
    los = np.zeros(2 * n, bool)
    los[:n] = True
    x = shadowing_db(los, CFG, rng)
    assert x[:n].std() == pytest.approx(4.0, rel=0.02)
    assert x[n:].std() == pytest.approx(7.82, rel=0.02)
    assert abs(x.mean()) < 0.1


@PROPS
@given(seeds, st.integers(1, 4), st.integers(1, 12), st.integers(1, 3), st.booleans())
def test_rates_non_negative_and_finite(seed, n_uavs, n_users, reuse, coincide):
    rng = np.random.default_rng(seed)
    cfg = ChannelConfig(reuse_factor=reuse)
    uavs = np.column_stack([rng.uniform(0, 1000, (n_uavs, 2)), rng.uniform(0, 150, n_uavs)])
    users = np.column_stack([rng.uniform(0, 1000, (n_users, 2)), np.full(n_users, 1.5)])
    if coincide:  # the first user sits exactly on the first UAV
        users[0] = uavs[0]
    s = sample_channel(uavs, users, cfg, rng)
    assert np.all(np.isfinite(s.gain)) and np.all(s.gain > 0)
    weights = interference_weights(reuse_colours(n_uavs, reuse), cfg.adjacent_leakage)
    interf = interference_w(s.gain, np.full(n_uavs, cfg.max_tx_power_w), weights)
    band = user_bandwidth_hz(rng.integers(0, 6, n_uavs), cfg)
    gamma = sinr(cfg.max_tx_power_w / 5, s.gain, noise_power_w(band, cfg), interf)
    rate = achievable_rate_bps(band, gamma, cfg)
    assert rate.shape == (n_users, n_uavs)
    assert np.all(np.isfinite(rate)) and np.all(rate >= 0)


@PROPS
@given(
    st.floats(1e3, 5e6),  # target rate
    st.floats(1e5, 1e7),  # bandwidth
    st.floats(1e-14, 1e-6),  # gain
    st.floats(0.0, 1e-9),  # interference
)
def test_required_power_reproduces_target_rate(rate, band, gain, interf):
    p = required_power_w(rate, band, gain, interf, CFG)
    achieved = achievable_rate_bps(band, sinr(p, gain, noise_power_w(band, CFG), interf), CFG)
    assert achieved == pytest.approx(rate, rel=1e-9)


def test_required_power_broadcasts_bandwidth_array():
    bands = np.array([1e6, 2e6, 5e6])[:, None]  # (3, 1) against gains (1, 4)
    gains = np.array([[1e-8, 1e-9, 1e-10, 1e-11]])
    p = required_power_w(1e6, bands, gains, 0.0, CFG)
    assert p.shape == (3, 4)
    assert np.all(np.diff(p, axis=0) < 0)  # more band, less power for the same rate
    assert np.all(np.diff(p, axis=1) > 0)  # weaker link, more power


@PROPS
@given(st.integers(1, 8), st.integers(1, 4), st.floats(0.0, 0.999))
def test_interference_matrix_shape_and_zero_self_interference(n_uavs, reuse, leak):
    colours = reuse_colours(n_uavs, reuse)
    w = interference_weights(colours, leak)
    assert w.shape == (n_uavs, n_uavs)
    assert np.all(np.diag(w) == 0)
    same = colours[:, None] == colours[None, :]
    off = ~np.eye(n_uavs, dtype=bool)
    assert np.all(w[same & off] == 1.0) and np.all(w[~same] == leak)
    # A UAV alone in the sky interferes with nobody.
    gain = np.random.default_rng(n_uavs).uniform(1e-12, 1e-8, (5, n_uavs))
    power = np.zeros(n_uavs)
    power[0] = 0.1
    interf = interference_w(gain, power, w)
    assert interf.shape == (5, n_uavs)
    assert np.all(interf[:, 0] == 0)


def test_interference_matches_explicit_sum_batched():
    rng = np.random.default_rng(5)
    gain = rng.uniform(1e-12, 1e-8, (2, 6, 4))  # (batch, N, U)
    power = rng.uniform(0, 0.1, (2, 4))
    w = interference_weights(reuse_colours(4, 2), 1e-3)
    want = np.einsum("uv,bv,bnv->bnu", w, power, gain)
    np.testing.assert_allclose(interference_w(gain, power, w), want)


def test_interference_accepts_scalar_power():
    gain = np.random.default_rng(6).uniform(1e-12, 1e-8, (3, 5, 4))
    w = interference_weights(reuse_colours(4, 1), 1e-3)
    np.testing.assert_allclose(interference_w(gain, 0.1, w), interference_w(gain, np.full(4, 0.1), w))


def test_reuse_factor_two_colours():
    np.testing.assert_array_equal(reuse_colours(5, 2), [0, 1, 0, 1, 0])
    w = interference_weights(reuse_colours(3, 2), 0.01)
    np.testing.assert_allclose(w, [[0, 0.01, 1], [0.01, 0, 0.01], [1, 0.01, 0]])


# ---------------------------------------------------------------- config validation


@pytest.mark.parametrize(
    "field, value, pattern",
    [
        ("bandwidth_hz", -1.0, r"ChannelConfig\.bandwidth_hz must be a finite float > 0, got -1\.0"),
        ("rician_k_db", -3.0, r"ChannelConfig\.rician_k_db must be a finite float >= 0 \(in dB.*got -3\.0"),
        ("nakagami_m", 0.3, r"ChannelConfig\.nakagami_m must be a finite float >= 0\.5, got 0\.3"),
        ("adjacent_leakage", 1.0, r"ChannelConfig\.adjacent_leakage must be a finite float in \[0, 1\), got 1\.0"),
        ("implementation_loss", 0.0, r"ChannelConfig\.implementation_loss must be a finite float in \(0, 1\]"),
        ("max_tx_power_w", float("nan"), r"ChannelConfig\.max_tx_power_w"),
        ("reuse_factor", 0, r"ChannelConfig\.reuse_factor must be an integer >= 1, got 0"),
        ("reuse_factor", 1.5, r"ChannelConfig\.reuse_factor"),
        ("shadowing_nlos_db", -1.0, r"ChannelConfig\.shadowing_nlos_db must be a finite float >= 0"),
        ("min_gain", 0.0, r"ChannelConfig\.min_gain must be a finite float > 0"),
    ],
)
def test_config_rejects_bad_values(field, value, pattern):
    with pytest.raises(ValueError, match=pattern):
        ChannelConfig(**{field: value})


def test_config_properties():
    assert CFG.noise_w_per_hz == pytest.approx(3.981072e-21, rel=1e-6)
    assert CFG.max_tx_power_dbm == pytest.approx(20.0)
    assert CFG.antenna_gain == 1.0
    assert CFG.rician_k == pytest.approx(3.981072, rel=1e-6)
    assert ChannelConfig(reuse_factor=4).colour_bandwidth_hz == 2.5e6
