"""Rotary-wing propulsion power, slot energy and battery (notebooks/02_energy.py)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pemamoe.energy import (
    EnergyConfig,
    SlotEnergy,
    battery_update,
    max_range_speed,
    min_power_speed,
    propulsion_power_w,
    slot_energy,
)

CFG = EnergyConfig()
HOVER = 79.86 + 88.63  # 168.49 W


def test_hover_power_is_p0_plus_pi():
    assert propulsion_power_w(0.0, 0.0, CFG) == pytest.approx(168.49, rel=1e-9)
    assert CFG.hover_power_w == pytest.approx(168.49, rel=1e-9)


def test_power_at_10_mps_by_hand():
    # Hand computation at V_h = 10 m/s, V_z = 0:
    #   profile  = 79.86 * (1 + 3*100/120^2)               = 79.86 * 1.0208333   = 81.52375
    #   x        = 100 / (2 * 4.03^2) = 100 / 32.4818       = 3.078647
    #   bracket  = sqrt(1 + x^2) - x = 3.236984 - 3.078647  = 0.158337
    #   induced  = 88.63 * sqrt(0.158337) = 88.63 * 0.397916 = 35.2673
    #   parasite = 0.5 * 0.6 * 1.225 * 0.05 * 0.503 * 10^3  = 9.242625
    #   total                                               = 126.0337 W
    assert propulsion_power_w(10.0, 0.0, CFG) == pytest.approx(126.0337, abs=1e-3)
    # the same value from the textbook (cancellation-prone) form of the bracket
    x = 100.0 / (2 * 4.03**2)
    direct = 79.86 * (1 + 300 / 120**2) + 88.63 * math.sqrt(math.sqrt(1 + x * x) - x) + 9.242625
    assert propulsion_power_w(10.0, 0.0, CFG) == pytest.approx(direct, rel=1e-12)


def test_vertical_speed_enters_like_horizontal_in_induced_term():
    # P(0, Vz) only differs from hover in the induced term, which depends on Vh^2 + Vz^2
    p = propulsion_power_w(0.0, 5.0, CFG)
    assert p == pytest.approx(propulsion_power_w(0.0, -5.0, CFG), rel=1e-15)  # symmetric
    assert p < HOVER  # vertical motion lowers induced power, as forward flight does
    assert p == pytest.approx(142.0422, abs=1e-3)


def test_power_is_vectorised_and_broadcasts():
    v_h = np.linspace(0, 30, 7)[:, None]
    v_z = np.array([0.0, 2.0, -3.0])
    p = propulsion_power_w(v_h, v_z, CFG)
    assert p.shape == (7, 3)
    assert p[3, 1] == pytest.approx(propulsion_power_w(15.0, 2.0, CFG))
    assert isinstance(propulsion_power_w(1.0, 0.0, CFG), float)


def test_characteristic_speeds():
    v_mp, v_mr = min_power_speed(CFG), max_range_speed(CFG)
    assert v_mp == pytest.approx(10.21, abs=0.01)
    assert v_mr == pytest.approx(18.30, abs=0.01)
    # they are minima of P and P/V on a fine grid
    v = np.linspace(0.5, 40, 20001)
    assert abs(v[np.argmin(propulsion_power_w(v, 0.0, CFG))] - v_mp) < 5e-3
    assert abs(v[np.argmin(propulsion_power_w(v, 0.0, CFG) / v)] - v_mr) < 5e-3


def test_hover_slot_energy():
    res = slot_energy(0.0, 0.0, CFG)
    assert isinstance(res, SlotEnergy)
    assert res.energy_j == pytest.approx(168.49 * 60.0, rel=1e-9)
    assert res.hover_time_s == 60.0 and res.move_time_s == 0.0 and not res.infeasible


def test_100m_move_is_10s_flight_plus_50s_hover():
    res = slot_energy(100.0, 0.0, CFG)
    assert res.move_time_s == pytest.approx(10.0)
    assert res.hover_time_s == pytest.approx(50.0)
    expected = propulsion_power_w(10.0, 0.0, CFG) * 10.0 + 168.49 * 50.0  # ~ 9684.84 J
    assert res.energy_j == pytest.approx(expected, rel=1e-12)
    assert res.energy_j == pytest.approx(9684.84, abs=0.01)
    assert not res.infeasible and res.realised_horizontal_m == 100.0


def test_sequential_vertical_leg():
    res = slot_energy(100.0, -20.0, CFG)  # 10 s horizontal + 4 s vertical + 46 s hover
    assert res.move_time_s == pytest.approx(14.0)
    expected = propulsion_power_w(10, 0, CFG) * 10 + propulsion_power_w(0, 5, CFG) * 4 + 168.49 * 46
    assert res.energy_j == pytest.approx(expected, rel=1e-12)
    assert res.realised_vertical_m == -20.0


def test_infeasible_move_is_shrunk_and_flagged():
    # 400 m horizontal (40 s) + 200 m vertical (40 s) = 80 s > 60 s: both legs scaled by 60/80
    res = slot_energy(np.array([400.0, 50.0]), np.array([200.0, 0.0]), CFG)
    assert res.infeasible.tolist() == [True, False]
    assert res.realised_horizontal_m[0] == pytest.approx(300.0)
    assert res.realised_vertical_m[0] == pytest.approx(150.0)
    assert res.move_time_s[0] == pytest.approx(60.0) and res.hover_time_s[0] == 0.0
    expected = propulsion_power_w(10, 0, CFG) * 30 + propulsion_power_w(0, 5, CFG) * 30
    assert res.energy_j[0] == pytest.approx(expected, rel=1e-12)
    assert res.realised_horizontal_m[1] == 50.0


def test_slot_energy_shapes_batch_by_uav():
    rng = np.random.default_rng(0)
    res = slot_energy(rng.uniform(0, 150, (4, 3)), 0.0, CFG)
    for field in res:
        assert np.shape(field) == (4, 3)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -1.0])
def test_slot_energy_rejects_bad_horizontal(bad):
    with pytest.raises(ValueError, match="slot_energy"):
        slot_energy(np.array([10.0, bad]), 0.0, CFG)


@settings(max_examples=50, deadline=None)
@given(
    h=st.lists(st.floats(0, 2000, allow_nan=False), min_size=1, max_size=8),
    v=st.floats(-500, 500, allow_nan=False),
)
def test_slot_energy_properties(h, v):
    res = slot_energy(np.array(h), v, CFG)
    assert np.all(np.isfinite(res.energy_j)) and np.all(res.energy_j > 0)
    assert np.all((res.hover_time_s >= 0) & (res.hover_time_s <= CFG.slot_s))
    assert np.allclose(res.move_time_s + res.hover_time_s, CFG.slot_s)
    assert np.all(res.realised_horizontal_m <= np.array(h) + 1e-9)
    # never more than hovering, since every flight segment here draws less than hover power
    assert np.all(res.energy_j <= HOVER * CFG.slot_s * (1 + 1e-12))


@settings(max_examples=50, deadline=None)
@given(
    battery=st.floats(0, 500e3, allow_nan=False),
    energy=st.floats(0, 1e6, allow_nan=False),
)
def test_battery_never_negative(battery, energy):
    new, depleted = battery_update(battery, energy, CFG)
    assert 0.0 <= new <= CFG.battery_capacity_j
    assert bool(depleted) == (battery - energy <= 0)


def test_battery_update_values():
    new, depleted = battery_update(np.array([500e3, 5e3, 1e3]), np.array([10e3, 5e3, 2e3]), CFG)
    assert new.tolist() == [490e3, 0.0, 0.0]
    assert depleted.tolist() == [False, True, True]


@pytest.mark.parametrize(
    "field, value",
    [("profile_power_w", -1.0), ("cruise_speed_mps", 0.0), ("slot_s", float("nan")),
     ("battery_capacity_j", "500"), ("climb_speed_mps", True)],
)
def test_validation_names_class_and_field(field, value):
    with pytest.raises(ValueError, match=rf"EnergyConfig\.{field} must be a finite float > 0, got"):
        EnergyConfig(**{field: value})
