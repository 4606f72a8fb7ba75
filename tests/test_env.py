"""The environment: PettingZoo API, seeding, batched/parallel equivalence, scheduler, objective."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pettingzoo.test import parallel_api_test

from pemamoe import env as E
from pemamoe.channel import ChannelConfig


def random_actions(rng, n_envs, n_uavs):
    return rng.uniform(-1.2, 1.2, size=(n_envs, n_uavs, 2))


# -- API ---------------------------------------------------------------------------------------
def test_parallel_api_test_passes():
    parallel_api_test(E.make_env(), num_cycles=40)


def test_make_env_is_exposed_at_top_level():
    import pemamoe

    assert isinstance(pemamoe.make_env(), E.UAVParallelEnv)


def test_spaces_and_dimensions():
    env = E.make_env()
    obs, _ = env.reset(seed=1)
    cfg = env.cfg
    assert E.observation_dim(cfg) == 3 + 3 * (cfg.n_uavs - 1) + 7 * cfg.n_users == 149
    for a in env.agents:
        assert obs[a].shape == (149,) and obs[a].dtype == np.float32
        assert env.observation_space(a).contains(obs[a])
    assert env.state().shape == (E.state_dim(cfg),)
    assert env.state_space.contains(env.state())


def test_render_returns_rgb_frame():
    env = E.make_env(render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert frame.std() > 0  # something is drawn


# -- seeding and equivalence -------------------------------------------------------------------
def run_parallel(seed, actions, **overrides):
    env = E.make_env(**overrides)
    obs, _ = env.reset(seed=seed)
    trace = [np.stack([obs[a] for a in env.possible_agents])]
    rewards = []
    for act in actions:
        if not env.agents:
            obs, _ = env.reset()
            trace.append(np.stack([obs[a] for a in env.possible_agents]))
        obs, rew, *_ = env.step({a: act[i] for i, a in enumerate(env.possible_agents)})
        trace.append(np.stack([obs[a] for a in env.possible_agents]))
        rewards.append(rew["uav_0"])
    return np.stack(trace), np.array(rewards)


def test_same_seed_same_trajectory_different_seed_different():
    actions = np.random.default_rng(0).uniform(-1, 1, (20, 3, 2))
    a_obs, a_rew = run_parallel(7, actions)
    b_obs, b_rew = run_parallel(7, actions)
    c_obs, _ = run_parallel(8, actions)
    np.testing.assert_array_equal(a_obs, b_obs)
    np.testing.assert_array_equal(a_rew, b_rew)
    assert not np.array_equal(a_obs, c_obs)


@pytest.mark.parametrize("engine", E.STEP_ENGINES)
def test_vector_env_matches_parallel_envs_over_episode_boundaries(engine):
    n_envs, steps = 3, 40  # 40 > 32: crosses an autoreset
    actions = np.random.default_rng(1).uniform(-1, 1, (steps, n_envs, 3, 2))
    venv = E.make_vector_env(n_envs, seed=11, step_engine=engine)
    obs, state, _ = venv.reset()
    v_obs, v_rew = [obs.copy()], []
    for t in range(steps):
        obs, state, rew, term, trunc, info = venv.step(actions[t])
        if (term | trunc).any():
            # the parallel env resets explicitly: record the final obs then the fresh one
            final = obs.copy()
            final[info["final_rows"]] = info["final_obs"]
            v_obs.append(final)
            v_obs.append(obs.copy())
        else:
            v_obs.append(obs.copy())
        v_rew.append(rew.copy())
    v_obs, v_rew = np.stack(v_obs), np.stack(v_rew)
    for i in range(n_envs):
        p_obs, p_rew = run_parallel(11 + i, actions[:, i], step_engine=engine)
        np.testing.assert_array_equal(p_obs, v_obs[:, i])
        np.testing.assert_array_equal(p_rew, v_rew[:, i])


def test_truncation_at_episode_length_returns_final_observation():
    venv = E.make_vector_env(2, seed=0)
    venv.reset()
    for t in range(venv.cfg.episode_steps):
        obs, state, rew, term, trunc, info = venv.step(np.zeros((2, 3, 2)))
    assert trunc.all() and not term.any()
    assert info["final_obs"].shape == (2, 3, venv.obs_dim)
    assert info["final_state"][:, -1] == pytest.approx(1.0)  # elapsed fraction of the finished episode
    assert state[:, -1] == pytest.approx(0.0)  # the new episode starts at 0


# -- bad input ---------------------------------------------------------------------------------
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_action_names_the_agent(bad):
    env = E.make_env()
    env.reset(seed=0)
    actions = {a: np.zeros(2, np.float32) for a in env.agents}
    actions["uav_1"] = np.array([0.0, bad])
    with pytest.raises(ValueError, match="uav_1"):
        env.step(actions)


def test_out_of_range_action_is_clipped_and_reported():
    env = E.make_env()
    env.reset(seed=0)
    before = env.core.uav_xy.copy()
    _, _, _, _, infos = env.step({"uav_0": np.array([5.0, 0.0]), "uav_1": np.zeros(2), "uav_2": np.zeros(2)})
    assert infos["uav_0"]["action_clipped"] is True
    assert infos["uav_1"]["action_clipped"] is False
    moved = np.linalg.norm(env.core.uav_xy - before, axis=-1)[0]
    assert moved[0] <= env.cfg.max_step_m + 1e-9 and moved[1] == 0.0


@pytest.mark.parametrize(
    "overrides, field",
    [
        ({"n_users": 2}, "n_users"),  # fewer users than the 3 hotspots
        ({"service_radius_m": (200.0, -1.0, 150.0)}, "service_radius_m"),
        ({"demand_mode": "bursty"}, "demand_mode"),
        ({"n_uavs": 0}, "n_uavs"),
        ({"bandwidth_hz": -1.0}, "bandwidth_hz"),
        ({"no_such_setting": 1}, "no_such_setting"),
        ({"step_engine": "jax"}, "step_engine"),
    ],
)
def test_invalid_configuration_fails_at_construction_naming_the_field(overrides, field):
    with pytest.raises(ValueError, match=field):
        E.make_env(**overrides)


def test_overrides_route_to_the_owning_section():
    cfg = E.EnvConfig.from_overrides(bandwidth_hz=5e6, n_users=12, channel__reuse_factor=2, slot_s=30.0)
    assert cfg.channel.bandwidth_hz == 5e6 and cfg.channel.reuse_factor == 2
    assert cfg.n_users == 12
    assert cfg.energy.slot_s == cfg.mobility.slot_s == 30.0


# -- scheduler ---------------------------------------------------------------------------------
def one_uav_schedule(distances, priority, cfg=None, gain=1e-9, radius=200.0):
    cfg = cfg or E.EnvConfig()
    d = np.asarray(distances, float)[None, :, None]
    gains = np.full_like(d, gain)
    rate = np.asarray(cfg.phases.rate_threshold_bps)[np.asarray(priority)][None]
    return E.schedule_users(d, gains, rate, np.asarray(priority)[None], np.array([radius]), cfg)


def test_admission_order_is_priority_then_distance_and_capped():
    # 7 users in range: H users first (nearest first), then M, then L; capacity 5.
    distances = [10, 20, 30, 40, 50, 60, 70]
    priority = [0, 2, 1, 2, 0, 1, 2]
    plan = one_uav_schedule(distances, priority)
    admitted = plan.admitted[0, :, 0]
    assert plan.n_admitted[0, 0] == 5
    # H: users 1, 3, 6; M: 2, 5; L (0, 4) left out
    assert admitted.tolist() == [False, True, True, True, False, True, True]


def test_users_beyond_the_service_radius_are_not_associated():
    plan = one_uav_schedule([150, 250], [2, 2], radius=200.0)
    assert plan.covered[0].tolist() == [True, False]
    assert plan.admitted[0, :, 0].tolist() == [True, False]


def test_power_budget_stops_admission_and_holds():
    cfg = E.EnvConfig()
    # A weak gain makes each H user need a lot of power: only a prefix fits into 0.1 W.
    plan = one_uav_schedule([10, 20, 30, 40, 50], [2] * 5, cfg, gain=2e-13)
    assert 0 < plan.n_admitted[0, 0] < 5
    assert plan.power_w[0].sum() <= cfg.channel.max_tx_power_w * (1 + 1e-12)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n_envs=st.integers(1, 4))
def test_schedule_invariants_on_random_states(seed, n_envs):
    venv = E.make_vector_env(n_envs, seed=seed)
    venv.reset()
    rng = np.random.default_rng(seed)
    for _ in range(3):
        obs, state, rew, term, trunc, info = venv.step(random_actions(rng, n_envs, 3))
        assert np.isfinite(obs).all() and np.isfinite(rew).all()
        assert (np.abs(obs) <= 1.0 + 1e-6).all()
        assert (info["served_users"] <= info["admitted_users"]).all()
        assert (info["admitted_users"] <= 5 * 3).all()
        assert ((0 <= info["coverage"]) & (info["coverage"] <= 1)).all()
        assert ((0 <= info["uav_using_rate"]) & (info["uav_using_rate"] <= 1)).all()
    core = venv.core
    assert (core.uav_xy >= 0).all() and (core.uav_xy <= venv.cfg.area_m).all()


# -- objective ---------------------------------------------------------------------------------
def test_reward_terms_by_hand():
    cfg = E.EnvConfig()
    uav_xy = np.array([[[0.0, 0.0], [30.0, 40.0], [500.0, 500.0]]])  # pair (0,1) 50 m apart: no collision
    served = np.array([[True, False, True]])
    weight = np.array([[20.0, 20.0, 10.0]])
    energy = np.array([[10e3, 20e3, 30e3]])
    terms = E.reward_terms(served, weight, energy, uav_xy, np.array([40.0]), np.array([150.0]), cfg)
    assert terms["qos"][0] == 30.0
    assert terms["energy"][0] == pytest.approx(0.1 * 60.0)
    assert terms["collisions"][0] == 0
    # only pair (0,1) at 50 m is within 2 x 150 m
    assert terms["overlap"][0] == pytest.approx(40.0 * np.exp(-50.0 ** 2 / (2 * 150.0 ** 2)))
    closer = uav_xy.copy()
    closer[0, 1] = [10.0, 0.0]
    terms = E.reward_terms(served, weight, energy, closer, np.array([40.0]), np.array([150.0]), cfg)
    assert terms["collisions"][0] == 1 and terms["collision"][0] == 100.0
    assert terms["reward"][0] == pytest.approx(
        terms["qos"][0] - terms["energy"][0] - terms["collision"][0] - terms["overlap"][0])


def test_hover_slot_costs_hover_energy():
    venv = E.make_vector_env(1, seed=0)
    venv.reset()
    *_, info = venv.step(np.zeros((1, 3, 2)))
    hover_kj = venv.cfg.energy.hover_power_w * venv.cfg.energy.slot_s / 1e3
    assert info["energy_rate_kj"][0] == pytest.approx(hover_kj)
    assert info["energy"][0] == pytest.approx(0.1 * 3 * hover_kj)


def test_kmeans_covers_more_users_than_hovering():
    km = E.rollout_heuristic("kmeans", 8, 32, seed=3, phase=1)
    hv = E.rollout_heuristic("hover", 8, 32, seed=3, phase=1)
    assert km["coverage"][-8:].mean() > hv["coverage"][-8:].mean()


def test_env_phase_clock_advances_and_switches_demand():
    venv = E.make_vector_env(1, seed=0, phase_period_steps=5)
    venv.reset()
    phases, switches = [], []
    for _ in range(12):
        *_, info = venv.step(np.zeros((1, 3, 2)))
        phases.append(int(info["phase"][0]))
        switches.append(bool(info["phase_switch"][0]))
    assert phases == [0] * 5 + [1] * 5 + [2] * 2
    assert switches.count(True) == 2
    assert (venv.core.demand == 2).all()  # "cycle" demand: class follows the phase


def test_batch_random_streams_do_not_depend_on_batch_size():
    wide = E.BatchRandom([5, 6, 7], chunk=128)
    alone = E.BatchRandom([6], chunk=128)
    for size in (10, 50, 30, 7):  # crosses refills at different offsets
        np.testing.assert_array_equal(wide.standard_normal((3, size))[1], alone.standard_normal((1, size))[0])
        np.testing.assert_array_equal(wide.random((3, 2, size))[1], alone.random((1, 2, size))[0])
    g = E.BatchRandom([0], chunk=4096).gamma(2.0, 0.5, size=(1, 4000))
    assert g.mean() == pytest.approx(1.0, rel=0.05)


@pytest.mark.parametrize("engine", E.STEP_ENGINES)
def test_state_dict_round_trip_continues_exactly(engine):
    actions = np.random.default_rng(2).uniform(-1, 1, (30, 2, 3, 2))
    a = E.make_vector_env(2, seed=4, step_engine=engine)
    a.reset()
    for t in range(10):
        a.step(actions[t])
    saved = a.state_dict()
    b = E.make_vector_env(2, seed=999, step_engine=engine)  # different seed: everything must come from the state
    b.load_state_dict(saved)
    for t in range(10, 30):  # crosses an episode boundary and random-buffer refills
        oa, sa, ra, *_ = a.step(actions[t])
        ob, sb, rb, *_ = b.step(actions[t])
        np.testing.assert_array_equal(oa, ob)
        np.testing.assert_array_equal(ra, rb)


def test_batch_random_draws_survive_later_refills():
    # Regression: the fast path once returned views of the buffer, which the next refill rewrote
    # while the caller still held them (Rician x was replaced by future numbers of the stream).
    for seeds in ([5], [5, 6, 7]):
        held_rng, fresh_rng = E.BatchRandom(seeds, chunk=100), E.BatchRandom(seeds, chunk=100)
        held = [held_rng.standard_normal((len(seeds), 30)) for _ in range(12)]  # crosses 3 refills
        for draw in held:
            np.testing.assert_array_equal(draw, fresh_rng.standard_normal((len(seeds), 30)))


# -- the compiled engine against the numpy reference --------------------------------------------
def assert_same_step(ref, fast, where):
    """Discrete outcomes equal; floats equal to 1e-9 relative (bit-identical on the dev machine,
    but another CPU's numpy may take exp/log10 from a different math library than numba)."""
    for r, f, name in zip(ref[:5], fast[:5], ("obs", "state", "reward", "terminated", "truncated")):
        assert r.dtype == f.dtype, (where, name)
        if r.dtype.kind == "f":
            np.testing.assert_allclose(f, r, rtol=1e-6 if r.dtype == np.float32 else 1e-9, atol=1e-12,
                                       err_msg=f"{where}: {name}")
        else:
            np.testing.assert_array_equal(f, r, err_msg=f"{where}: {name}")
    assert list(ref[5]) == list(fast[5]), where
    for key, r in ref[5].items():
        r, f = np.asarray(r), np.asarray(fast[5][key])
        assert r.dtype.kind == f.dtype.kind and r.shape == f.shape, (where, key, r.dtype, f.dtype)
        if r.dtype.kind == "f":
            np.testing.assert_allclose(f, r, rtol=1e-9, atol=1e-12, err_msg=f"{where}: info[{key!r}]")
        else:
            np.testing.assert_array_equal(f, r, err_msg=f"{where}: info[{key!r}]")


def run_both_engines(n_envs, steps, seed, action_seed=0, phase=None, **overrides):
    envs = [E.make_vector_env(n_envs, seed=seed, step_engine=e, **overrides) for e in ("numpy", "compiled")]
    if phase is not None:
        for env in envs:
            env.set_phase(phase)
    ref, fast = (env.reset() for env in envs)
    for r, f, name in zip(ref[:2], fast[:2], ("obs", "state")):
        np.testing.assert_allclose(f, r, rtol=1e-6, atol=1e-12, err_msg=f"reset: {name}")
    actions = np.random.default_rng(action_seed).uniform(-1.3, 1.3, (steps, n_envs, envs[0].cfg.n_uavs, 2))
    for t in range(steps):
        assert_same_step(envs[0].step(actions[t]), envs[1].step(actions[t]), f"step {t}")
    for name in ("uav_xy", "battery_j", "demand", "serving", "phase", "clock"):
        np.testing.assert_array_equal(getattr(envs[1].core, name), getattr(envs[0].core, name), err_msg=name)
    return envs


@pytest.mark.parametrize("overrides", [
    {},  # the paper's setting
    {"service_radius_m": (2000.0, 2000.0, 2000.0)},  # every user covered: capacity and budget bind
    {"reuse_factor": 3, "adjacent_leakage": 0.01},  # non-trivial interference weights
    {"nakagami_m": 2.5, "rician_k_db": 0.0},  # the gammaincinv path of the NLoS fading
    {"demand_mode": "mix", "phase_period_steps": 7},  # phase switches with drawn demand classes
    {"n_uavs": 5, "n_users": 31, "n_hotspots": 4, "max_users_per_uav": 7, "min_separation_m": 300.0},
])
def test_compiled_engine_matches_the_numpy_reference(overrides):
    run_both_engines(4, 70, seed=21, **overrides)  # 70 steps: two autoresets, random-buffer refills


def test_compiled_engine_matches_in_the_held_out_regime():
    run_both_engines(3, 40, seed=5, phase=3, phase_clock="external")


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), n_envs=st.integers(1, 3), radius=st.floats(20.0, 1500.0),
       n_users=st.integers(3, 25), max_users=st.integers(1, 6))
def test_compiled_engine_matches_on_random_settings(seed, n_envs, radius, n_users, max_users):
    run_both_engines(n_envs, 6, seed=seed, action_seed=seed, service_radius_m=(radius, radius, radius),
                     n_users=n_users, max_users_per_uav=max_users)


def test_compiled_engine_needs_a_chunk_that_holds_one_slot():
    with pytest.raises(ValueError, match="rng_chunk"):
        E.make_vector_env(1, rng_chunk=64)
    env = E.make_vector_env(1, rng_chunk=64, step_engine="numpy")  # the reference draws in pieces
    env.reset()
    env.step(np.zeros((1, 3, 2)))


def test_integer_rewards_give_float_terms_on_both_engines():
    for engine in E.STEP_ENGINES:
        env = E.make_vector_env(2, seed=0, step_engine=engine, class_reward=(5, 10, 20), collision_penalty=100)
        env.reset()
        *_, info = env.step(np.zeros((2, 3, 2)))
        assert info["qos"].dtype == info["collision"].dtype == np.float64, engine


def test_schedule_must_have_the_configs_phases():
    from pemamoe.phases import PhaseClock

    with pytest.raises(ValueError, match="n_phases=6"):
        E.UAVBatchCore(E.EnvConfig(), 1, [0], schedule=PhaseClock(period=1, n_phases=6))
    two = E.EnvConfig.from_overrides(user_speed_mps=(0.2, 0.5), direction_jitter=(0.2, 0.5),
                                     service_radius_m=(200.0, 150.0), overlap_weight=(20.0, 40.0),
                                     mix_probs=((0.6, 0.3, 0.1), (0.3, 0.5, 0.2)), demand_mode="mix",
                                     phase_period_steps=2)
    core = E.UAVBatchCore(two, 1, [0])  # the default schedule cycles this config's 2 phases
    core.reset()
    phases = [int(core.step(np.zeros((1, 3, 2)))[5]["phase"][0]) for _ in range(8)]
    assert phases == [0, 0, 1, 1, 0, 0, 1, 1]


def test_loading_a_foreign_state_fails_naming_the_array():
    env = E.make_vector_env(1, seed=0)
    env.reset()
    state = env.state_dict()
    state["arrays"]["phase"][:] = 7
    with pytest.raises(ValueError, match="'phase'"):
        E.make_vector_env(1, seed=0).load_state_dict(state)


@pytest.mark.parametrize("engine", E.STEP_ENGINES)
def test_state_arrays_are_updated_in_place_on_both_engines(engine):
    env = E.make_vector_env(2, seed=0, step_engine=engine, phase_period_steps=1)
    env.reset()
    core = env.core
    held = {name: getattr(core, name) for name in ("uav_xy", "battery_j", "demand", "phase")}
    before = {name: array.copy() for name, array in held.items()}
    env.step(np.full((2, 3, 2), 0.5))
    for name, array in held.items():
        assert array is getattr(core, name), name
        assert not np.array_equal(array, before[name]), name  # it moved, and the held array shows it


@pytest.mark.parametrize("overrides, named", [
    (dict(n_users=10**9), r"MobilityConfig\.n_users must be an integer in \[3, 10000\]"),
    (dict(n_hotspots=10**9), r"MobilityConfig\.n_hotspots must be an integer in \[1, 10000\]"),
    (dict(n_uavs=10**6), r"EnvConfig\.n_uavs must be an integer in \[1, 64\]"),
])
def test_a_huge_user_or_uav_count_is_refused_naming_that_field(overrides, named):
    """Issue 59: make_env(n_users=10**9) named rng_chunk, not n_users."""
    import pemamoe

    with pytest.raises(ValueError, match=named):
        pemamoe.make_env(**overrides)
