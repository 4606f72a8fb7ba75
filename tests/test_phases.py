"""Phase table, demand classes and the phase schedule."""

import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pemamoe.phases import PhaseConfig, PhaseClock, phase_values, sample_demand_classes


def test_fixed_schedule_by_hand():
    s = PhaseClock(period=3)
    assert [s.phase_at(t) for t in range(10)] == [0, 0, 0, 1, 1, 1, 2, 2, 2, 0]
    assert [s.is_switch(t) for t in range(10)] == [False, False, False, True, False, False, True, False, False, True]
    assert s.switch_ticks(10) == [3, 6, 9]


def test_paper_schedule_has_nine_phases_in_10800_iterations():
    s = PhaseClock(period=1200)
    assert len(s.switch_ticks(10_800)) == 8
    assert s.phase_at(10_799) == 2


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 1000))
def test_random_order_never_repeats_a_phase(seed):
    s = PhaseClock(period=2, order="random", seed=seed)
    seq = [s.phase_at(2 * k) for k in range(200)]
    assert all(a != b for a, b in zip(seq, seq[1:]))
    assert set(seq) == {0, 1, 2}


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 1000), lo=st.integers(1, 5), extra=st.integers(0, 5))
def test_random_durations_in_bounds_and_deterministic(seed, lo, extra):
    hi = lo + extra
    s = PhaseClock(min_period=lo, max_period=hi, seed=seed)
    again = PhaseClock(min_period=lo, max_period=hi, seed=seed)
    switches = [0] + s.switch_ticks(300)
    lengths = np.diff(switches)
    assert (lengths >= lo).all()  # a cyclic order always changes phase, so segments are visible
    assert (lengths <= hi).all()
    assert [s.phase_at(t) for t in range(300)] == [again.phase_at(t) for t in range(300)]


def test_held_out_regime_is_inserted_without_breaking_the_cycle():
    s = PhaseClock(period=2, held_out_every=3)
    assert [s.phase_at(2 * k) for k in range(8)] == [0, 1, 2, 3, 0, 1, 2, 3]
    s = PhaseClock(period=2, held_out_every=2)
    assert [s.phase_at(2 * k) for k in range(9)] == [0, 1, 3, 2, 0, 3, 1, 2, 3]


def test_random_order_never_repeats_far_into_the_schedule():
    s = PhaseClock(period=1, order="random", seed=7)
    seq = [s.phase_at(t) for t in range(10_000)]
    assert all(a != b for a, b in zip(seq, seq[1:]))


def test_schedule_pickles():
    s = PhaseClock(period=4, order="random", min_period=2, max_period=6, seed=3)
    t = pickle.loads(pickle.dumps(s))
    assert [t.phase_at(k) for k in range(100)] == [s.phase_at(k) for k in range(100)]


def test_phase_values_and_held_out():
    cfg = PhaseConfig()
    speed, jitter, radius, overlap = phase_values(cfg, np.array([0, 1, 2, 3]))
    assert speed.tolist() == [0.2, 0.5, 0.8, 1.2]
    assert radius.tolist() == [200.0, 150.0, 150.0, 120.0]
    assert overlap.tolist() == [20.0, 40.0, 80.0, 60.0]
    with pytest.raises(ValueError, match="phase indices"):
        phase_values(cfg, np.array([4]))


def test_cycle_demand_equals_phase():
    rng = np.random.default_rng(0)
    classes = sample_demand_classes(PhaseConfig(), np.array([0, 1, 2]), 20, rng)
    assert (classes == np.array([0, 1, 2])[:, None]).all()


def test_mix_demand_frequencies():
    cfg = PhaseConfig(demand_mode="mix")
    rng = np.random.default_rng(0)
    classes = sample_demand_classes(cfg, np.full(500, 1), 200, rng)
    freq = np.bincount(classes.ravel(), minlength=3) / classes.size
    np.testing.assert_allclose(freq, cfg.mix_probs[1], atol=0.01)  # 100k draws: sd ~ 0.0016


@pytest.mark.parametrize("kwargs, field", [
    ({"demand_mode": "bursty"}, "demand_mode"),
    ({"service_radius_m": (200.0, 0.0, 150.0)}, "service_radius_m"),
    ({"user_speed_mps": (0.2, 0.5)}, "direction_jitter"),
    ({"mix_probs": ((1.0, 0.0, 0.0),) * 2 + ((0.5, 0.5, 0.5),)}, "mix_probs"),
])
def test_invalid_phase_config_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=f"PhaseConfig.{field}"):
        PhaseConfig(**kwargs)


@pytest.mark.parametrize("kwargs, field", [({"period": 0}, "period"), ({"order": "shuffled"}, "order"),
                                           ({"min_period": 3}, "min_period")])
def test_invalid_schedule_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=f"PhaseClock.{field}"):
        PhaseClock(**kwargs)


@pytest.mark.parametrize("kwargs", [
    dict(period=3),  # closed form
    dict(period=4, order="random", seed=2),
    dict(period=5, min_period=2, max_period=7, held_out_every=2),
])
def test_phases_at_agrees_with_phase_at(kwargs):
    s = PhaseClock(**kwargs)
    ticks = np.array([[0, 7, 3], [40, 7, 199]])
    np.testing.assert_array_equal(s.phases_at(ticks), [[s.phase_at(int(t)) for t in row] for row in ticks])
    with pytest.raises(ValueError, match="ticks must be >= 0"):
        s.phases_at([-1])
