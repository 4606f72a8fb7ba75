"""The environment as outside code uses it: PettingZoo's own API and seed tests, the AEC conversion,
reset/step infos of one spec, render_mode, and errors for misuse (step/state before reset, unknown agents)."""

import numpy as np
import pytest
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test

import pemamoe
from pemamoe import env as E


# -- PettingZoo's own tests --------------------------------------------------------------------
@pytest.mark.parametrize("engine", E.STEP_ENGINES)
def test_parallel_api_test(engine):
    parallel_api_test(E.parallel_env(step_engine=engine), num_cycles=40)


def test_parallel_seed_test():
    parallel_seed_test(E.parallel_env, num_cycles=40)


def test_api_test_on_the_aec_conversion():
    api_test(E.aec_env(), num_cycles=40)


def test_module_level_constructors():
    assert pemamoe.parallel_env is E.parallel_env
    env = pemamoe.parallel_env(n_users=12)
    assert isinstance(env, E.UAVParallelEnv) and env.cfg.n_users == 12
    aec = E.raw_env(n_users=12)
    aec.reset(seed=0)
    assert aec.agents == env.possible_agents
    assert aec.unwrapped.cfg.n_users == 12


def test_make_env_is_a_pettingzoo_parallel_env_where_pettingzoo_is_installed():
    # its base class falls back to object only where pettingzoo is missing (tests/test_device_check.py)
    from pettingzoo import ParallelEnv

    assert issubclass(E.UAVParallelEnv, ParallelEnv)
    assert isinstance(pemamoe.make_env(), ParallelEnv) and isinstance(E.aec_env().unwrapped, ParallelEnv)


# -- infos -------------------------------------------------------------------------------------
def _spec(infos):
    """Per agent: key -> (Python type, shape, numpy dtype) of each info value."""
    return {agent: {key: (type(v), np.shape(v), np.asarray(v).dtype) for key, v in info.items()}
            for agent, info in infos.items()}


@pytest.mark.parametrize("engine", E.STEP_ENGINES)
def test_reset_and_step_infos_have_identical_keys_shapes_and_dtypes(engine):
    env = E.make_env(step_engine=engine)
    _, reset_infos = env.reset(seed=3)
    reset_spec = _spec(reset_infos)
    assert set(reset_spec) == set(env.possible_agents)
    rng = np.random.default_rng(0)
    for _ in range(5):
        _, _, _, _, step_infos = env.step({a: rng.uniform(-1.5, 1.5, 2) for a in env.agents})
        step_spec = _spec(step_infos)
        for agent in env.possible_agents:
            assert list(reset_spec[agent]) == list(step_spec[agent])  # same keys, same order
            assert reset_spec[agent] == step_spec[agent]


def test_reset_infos_mark_no_step_events():
    env = E.make_env()
    _, infos = env.reset(seed=0)
    for info in infos.values():
        assert info["action_clipped"] is False and info["move_infeasible"] is False
        assert info["battery_depleted"] is False and info["phase_switch"] is False


# -- render_mode -------------------------------------------------------------------------------
def test_render_mode_defaults_to_none():
    for env in (E.make_env(), E.parallel_env(), E.UAVParallelEnv()):
        assert env.render_mode is None
        env.reset(seed=0)
        assert env.render() is None


def test_rgb_array_on_request():
    env = E.make_env(render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3


def test_unknown_render_mode_is_rejected():
    with pytest.raises(ValueError, match=r"None, 'rgb_array' or 'human', got 'ansi'"):
        E.make_env(render_mode="ansi")


def test_pettingzoos_render_test_passes_with_human_and_rgb_array(monkeypatch):
    import matplotlib

    matplotlib.use("Agg")  # headless: "human" draws into a figure nobody sees
    from pettingzoo.test import render_test

    render_test(lambda render_mode=None: E.aec_env(render_mode=render_mode))
    env = E.make_env(render_mode="human")
    env.reset(seed=0)
    assert env.render() is None and env.render() is None  # the second frame reuses the window
    env.close()


@pytest.mark.parametrize("seed", [-1, "a", 1.5, True, 2 ** 63])
def test_reset_names_a_bad_seed(seed):
    env = E.make_env()
    with pytest.raises(ValueError, match=r"reset\(seed=\.\.\.\) must be None or an int in \[0, 2\*\*63\), got"):
        env.reset(seed=seed)


@pytest.mark.parametrize("shape", [(1, 2), (2, 1), (3,)])
def test_an_action_of_another_shape_is_refused_not_reshaped(shape):
    env = E.make_env()
    env.reset(seed=0)
    actions = {a: np.zeros(2, np.float32) for a in env.agents}
    actions[env.agents[1]] = np.zeros(shape, np.float32)
    with pytest.raises(ValueError, match=rf"action of {env.agents[1]} must have shape \(2,\), got shape"):
        env.step(actions)


# -- misuse ------------------------------------------------------------------------------------
@pytest.mark.parametrize("call", ["state", "step", "render"])
def test_use_before_reset_says_to_call_reset(call):
    env = E.make_env(render_mode="rgb_array")
    args = ({a: np.zeros(2) for a in env.possible_agents},) if call == "step" else ()
    with pytest.raises(RuntimeError, match=r"call reset\(\) first"):
        getattr(env, call)(*args)


@pytest.mark.parametrize("bad", ["uav_9", "uav0", 0])
def test_action_for_unknown_agent_names_it_and_the_valid_agents(bad):
    env = E.make_env()
    env.reset(seed=0)
    actions = {a: np.zeros(2, np.float32) for a in env.agents}
    actions[bad] = np.zeros(2, np.float32)
    with pytest.raises((ValueError, KeyError), match=rf"{bad!r}.*uav_0.*uav_1.*uav_2"):
        env.step(actions)
