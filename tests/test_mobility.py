"""User mobility: membership, reflection, hotspot motion, batch independence of the streams."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pemamoe.env import BatchRandom
from pemamoe.mobility import (MobilityConfig, hotspot_membership, init_mobility, reflect_into_area,
                              step_mobility)


def test_membership_is_as_even_as_possible():
    m = hotspot_membership(20, 3)
    assert np.bincount(m).tolist() == [7, 7, 6]
    assert np.bincount(hotspot_membership(9, 3)).tolist() == [3, 3, 3]


def test_reflection_by_hand():
    xy = np.array([[-10.0, 1010.0], [500.0, 2050.0], [-1010.0, 0.0]])
    out, flipped = reflect_into_area(xy, 1000.0)
    np.testing.assert_allclose(out, [[10.0, 990.0], [500.0, 50.0], [990.0, 0.0]])
    assert flipped.tolist() == [[True, True], [False, False], [False, False]]


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), speed=st.floats(0.0, 5.0), jitter=st.floats(0.0, 2.0))
def test_users_and_centres_stay_in_the_area(seed, speed, jitter):
    cfg = MobilityConfig()
    rng = np.random.default_rng(seed)
    state = init_mobility(cfg, 2, rng)
    for _ in range(20):
        state = step_mobility(state, np.full(2, speed), np.full(2, jitter), cfg, rng)
    for arr in (state.user_xy, state.centre_xy, state.waypoint_xy):
        assert (arr >= 0).all() and (arr <= cfg.area_m).all()
    assert np.isfinite(state.user_vel).all()


def test_centres_move_toward_waypoints_without_overshoot():
    cfg = MobilityConfig(retarget_every=100)
    rng = np.random.default_rng(0)
    state = init_mobility(cfg, 1, rng)
    before = np.linalg.norm(state.waypoint_xy - state.centre_xy, axis=-1)
    nxt = step_mobility(state, np.array([0.5]), np.array([0.5]), cfg, rng)
    after = np.linalg.norm(nxt.waypoint_xy - nxt.centre_xy, axis=-1)
    step = cfg.centre_speed_factor * 0.5 * cfg.slot_s
    np.testing.assert_allclose(after, np.maximum(before - step, 0.0), atol=1e-9)


def test_retargeting_happens_on_schedule():
    cfg = MobilityConfig(retarget_every=3)
    rng = np.random.default_rng(1)
    state = init_mobility(cfg, 1, rng)
    waypoints = [state.waypoint_xy.copy()]
    for _ in range(6):
        state = step_mobility(state, np.array([0.2]), np.array([0.2]), cfg, rng)
        waypoints.append(state.waypoint_xy.copy())
    changed = [not np.array_equal(a, b) for a, b in zip(waypoints, waypoints[1:])]
    assert changed == [False, False, True, False, False, True]


def test_batched_streams_match_single_environment():
    cfg = MobilityConfig()
    wide, alone = BatchRandom([3, 4], chunk=512), BatchRandom([4], chunk=512)
    a, b = init_mobility(cfg, 2, wide), init_mobility(cfg, 1, alone)
    for _ in range(10):
        a = step_mobility(a, np.array([0.2, 0.8]), np.array([0.2, 0.8]), cfg, wide)
        b = step_mobility(b, np.array([0.8]), np.array([0.8]), cfg, alone)
    np.testing.assert_array_equal(a.user_xy[1], b.user_xy[0])


def test_faster_phase_moves_users_further():
    cfg = MobilityConfig()
    moved = []
    for speed in (0.2, 0.8):
        rng = np.random.default_rng(5)
        state = init_mobility(cfg, 8, rng)
        start = state.user_xy.copy()
        for _ in range(10):
            state = step_mobility(state, np.full(8, speed), np.full(8, 0.2), cfg, rng)
        moved.append(np.linalg.norm(state.user_xy - start, axis=-1).mean())
    assert moved[1] > 2 * moved[0]


@pytest.mark.parametrize("field, value", [("n_users", 2), ("gm_memory", 1.0), ("retarget_every", 0),
                                          ("area_m", -5.0), ("follow_gain", 1.5)])
def test_invalid_mobility_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"MobilityConfig.{field}"):
        MobilityConfig(**{field: value})
