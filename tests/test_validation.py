"""One validator for every configuration (pemamoe.core.require) and the defects it fixed.

Each test below the helper's own tests reproduces a value that the configurations accepted, or
rejected with an unhelpful error, before they all went through `require`.
"""

import dataclasses
import json
import math
import re

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pemamoe import core
from pemamoe import env as E
from pemamoe.channel import ChannelConfig
from pemamoe.core import require
from pemamoe.energy import EnergyConfig
from pemamoe.mobility import MobilityConfig
from pemamoe.phases import PhaseConfig, PhaseClock


# ----------------------------------------------------------------------- the helper itself


@pytest.mark.parametrize(
    "args, rules, message",
    [
        ((math.inf, "real"), dict(gt=0), "Owner.f must be a finite float > 0, got inf"),
        ((True, "int"), dict(ge=1), "Owner.f must be an integer >= 1, got True"),
        (("100", "real"), dict(gt=0), "Owner.f must be a finite float > 0, got '100'"),
        ((1.0, "real"), dict(ge=0, lt=1), "Owner.f must be a finite float in [0, 1), got 1.0"),
        ((0.0, "real"), dict(gt=0, le=1), "Owner.f must be a finite float in (0, 1], got 0.0"),
        ((1.5, "int"), dict(ge=0, optional=True), "Owner.f must be an integer >= 0 or None, got 1.5"),
        (("jax", "choice", ("compiled", "numpy")), {}, "Owner.f must be one of 'compiled', 'numpy', got 'jax'"),
        ((1, "bool"), {}, "Owner.f must be a bool (True or False), got 1"),
        (((0.2, -1.0), "reals"), dict(ge=0, length=2), "Owner.f must be a tuple of 2 finite floats >= 0, got (0.2, -1.0)"),
        ((-1, "int"), dict(ge=0, note="why"), "Owner.f must be an integer >= 0 (why), got -1"),
        ((np.float32(np.nan), "real"), {}, "Owner.f must be a finite float, got nan (float32)"),
    ],
)
def test_require_messages_name_owner_field_value_and_rule(args, rules, message):
    with pytest.raises(ValueError, match=re.escape(message) + "$"):
        require("Owner", "f", *args, **rules)


@given(st.floats(min_value=1e-30, max_value=1e30))
def test_numpy_floats_are_accepted_and_stored_as_python_floats(x):
    for value in (x, np.float64(x), np.float32(x)):
        if float(value) <= 0:  # float32 underflow
            continue
        out = require("Owner", "f", value, "real", gt=0)
        assert type(out) is float and out == float(value)


@given(st.integers(min_value=0, max_value=2**62))
def test_numpy_integers_are_accepted_and_stored_as_python_ints(n):
    for value in (n, np.int64(n), np.uint64(n)):
        out = require("Owner", "f", value, "int", ge=0)
        assert type(out) is int and out == n
    with pytest.raises(ValueError, match="an integer"):
        require("Owner", "f", float(n), "int", ge=0)  # an integral float is still not an integer


@given(st.sampled_from([True, False, np.True_, np.False_, "1", "1.0", b"1", None, [1.0], math.nan, -math.inf]))
def test_bools_strings_and_non_finite_values_are_never_numbers(value):
    for kind in ("int", "real"):
        with pytest.raises(ValueError, match=r"Owner\.f must be"):
            require("Owner", "f", value, kind)


def test_infinity_only_where_a_field_allows_it_and_nan_never():
    assert require("Owner", "f", math.inf, "real", gt=0, allow_inf=True) == math.inf
    with pytest.raises(ValueError, match=r"inf allowed"):
        require("Owner", "f", math.nan, "real", allow_inf=True)


def test_choice_does_not_confuse_bools_with_ints_and_normalises_numpy_strings():
    with pytest.raises(ValueError):
        require("Owner", "f", True, "choice", (1, 2))
    with pytest.raises(ValueError):
        require("Owner", "f", 1, "choice", (True, False))
    out = require("Owner", "f", np.str_("numpy"), "choice", ("compiled", "numpy"))
    assert type(out) is str and out == "numpy"


def test_require_field_stores_the_normalised_value_on_a_frozen_dataclass():
    @dataclasses.dataclass(frozen=True)
    class Demo:
        n: int = 1

        def __post_init__(self):
            core.require_field(self, "n", "int", ge=1)

    assert type(Demo(np.int32(4)).n) is int
    with pytest.raises(ValueError, match=r"^Demo\.n must be an integer >= 1, got 0$"):
        Demo(0)


# ----------------------------------------------------------------------- defects, one test each


@pytest.mark.parametrize(
    "make, value",
    [
        (lambda: ChannelConfig(bandwidth_hz=np.float32(5e6)), lambda c: c.bandwidth_hz),
        (lambda: ChannelConfig(reuse_factor=np.int64(2)), lambda c: c.reuse_factor),
        (lambda: EnergyConfig(battery_capacity_j=np.float32(4e5)), lambda c: c.battery_capacity_j),
        (lambda: MobilityConfig(gm_noise_mps=np.float32(0.1)), lambda c: c.gm_noise_mps),
        (lambda: E.EnvConfig(uav_altitude_m=np.float32(120.0)), lambda c: c.uav_altitude_m),
        (lambda: E.EnvConfig.from_overrides(bandwidth_hz=np.float32(5e6)), lambda c: c.channel.bandwidth_hz),
    ],
)
def test_numpy_scalars_are_stored_as_python_numbers_so_configs_serialise(make, value):
    cfg = make()
    assert type(value(cfg)) in (int, float)
    json.dumps(dataclasses.asdict(cfg), sort_keys=True)  # what TrainConfig.config_hash hashes
    hash(cfg)


def test_numpy_int_n_users_is_accepted():
    cfg = E.EnvConfig.from_overrides(n_users=np.int64(30))
    assert cfg.n_users == 30 and type(cfg.n_users) is int


def test_array_per_phase_values_become_hashable_tuples():
    cfg = PhaseConfig(user_speed_mps=np.array([0.2, 0.5, 0.8]), mix_probs=np.full((3, 3), 1 / 3))
    assert cfg.user_speed_mps == (0.2, 0.5, 0.8) and all(type(v) is float for v in cfg.user_speed_mps)
    hash(cfg)
    json.dumps(dataclasses.asdict(cfg))


@pytest.mark.parametrize(
    "make, field",
    [
        (lambda: E.EnvConfig(episode_steps=True), "EnvConfig.episode_steps"),
        (lambda: E.EnvConfig(n_uavs=True), "EnvConfig.n_uavs"),
        (lambda: E.EnvConfig(max_users_per_uav=True), "EnvConfig.max_users_per_uav"),
        (lambda: E.EnvConfig(phase_period_steps=True), "EnvConfig.phase_period_steps"),
        (lambda: MobilityConfig(n_hotspots=True, n_users=20), "MobilityConfig.n_hotspots"),
        (lambda: MobilityConfig(retarget_every=True), "MobilityConfig.retarget_every"),
        (lambda: PhaseClock(period=True), "PhaseClock.period"),
        (lambda: PhaseClock(held_out_every=True), "PhaseClock.held_out_every"),
        (lambda: ChannelConfig(reuse_factor=True), "ChannelConfig.reuse_factor"),
    ],
)
def test_a_bool_is_never_an_integer_setting(make, field):
    with pytest.raises(ValueError, match=re.escape(field) + r" must be an integer (>= \d+|in \[\d+, \d+\]), got True"):
        make()


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"uav_altitude_m": "100"}, "EnvConfig.uav_altitude_m must be a finite float > 0, got '100'"),
        ({"area_m": "1000"}, "MobilityConfig.area_m must be a finite float > 0, got '1000'"),
        ({"gm_memory": "0.9"}, "MobilityConfig.gm_memory must be a finite float in [0, 1), got '0.9'"),
        ({"collision_penalty": "100"}, "EnvConfig.collision_penalty must be a finite float >= 0, got '100'"),
        ({"user_speed_mps": "fast"}, "PhaseConfig.user_speed_mps must be a non-empty tuple of finite floats >= 0"),
    ],
)
def test_a_string_is_never_a_number_and_the_error_names_the_field(overrides, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        E.make_env(**overrides)


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("area_m", math.inf, "MobilityConfig.area_m must be a finite float > 0, got inf"),
        ("collision_penalty", math.inf, "EnvConfig.collision_penalty must be a finite float >= 0, got inf"),
        ("gm_noise_mps", math.nan, "MobilityConfig.gm_noise_mps must be a finite float >= 0, got nan"),
        ("spawn_spread_m", math.inf, "MobilityConfig.spawn_spread_m must be a finite float >= 0, got inf"),
        ("user_height_m", math.nan, "MobilityConfig.user_height_m must be a finite float >= 0, got nan"),
        ("uav_altitude_m", math.inf, "EnvConfig.uav_altitude_m must be a finite float > 0, got inf"),
        ("overlap_sigma_m", math.inf, "EnvConfig.overlap_sigma_m must be a finite float > 0, got inf"),
        ("held_out_speed_mps", math.nan, "PhaseConfig.held_out_speed_mps must be a finite float >= 0, got nan"),
    ],
)
def test_non_finite_environment_settings_are_rejected(field, value, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        E.EnvConfig.from_overrides(**{field: value})


@pytest.mark.parametrize("seed", [1.5, -1, True, "3", np.float64(2.0)])
def test_make_vector_env_rejects_a_seed_that_is_not_a_non_negative_integer(seed):
    with pytest.raises(ValueError, match=r"make_vector_env\.seed must be an integer >= 0 or None, got"):
        E.make_vector_env(2, seed=seed)


def test_make_vector_env_accepts_numpy_integer_seed_and_num_envs():
    env = E.make_vector_env(np.int64(2), seed=np.int64(3), step_engine="numpy")
    assert env.num_envs == 2
    with pytest.raises(ValueError, match=r"make_vector_env\.num_envs must be an integer >= 1, got 0"):
        E.make_vector_env(0)


@pytest.mark.parametrize("engine", ["compiled", "numpy"])
def test_rng_chunk_advice_is_what_actually_works(engine):
    # 2,000 users: the default chunk (4096) holds neither a compiled slot nor the numpy engine's
    # largest draw (N x U channel numbers). The old error advised step_engine='numpy', which then
    # failed at reset(); now each engine says how large rng_chunk must be, and that size works.
    with pytest.raises(ValueError, match=r"EnvConfig\.rng_chunk must be an integer >= (\d+)") as err:
        E.EnvConfig.from_overrides(n_users=2000, step_engine=engine)
    assert "step_engine" not in str(err.value)
    needed = int(re.search(r">= (\d+)", str(err.value)).group(1))
    assert needed == (4 * 2000 + 3 * 2000 * 3 if engine == "compiled" else 2000 * 3)
    with pytest.raises(ValueError, match="rng_chunk"):
        E.make_vector_env(1, 0, n_users=2000, step_engine=engine, rng_chunk=needed - 1)
    env = E.make_vector_env(1, 0, n_users=2000, step_engine=engine, rng_chunk=needed)
    env.reset()
    env.step(np.zeros((1, env.n_agents, 2)))
    env.step(np.ones((1, env.n_agents, 2)))


def test_config_sections_must_be_their_config_classes():
    with pytest.raises(ValueError, match=r"EnvConfig\.channel must be a ChannelConfig, got \{"):
        E.EnvConfig(channel={"bandwidth_hz": 5e6})


# ----------------------------------------------------------------------- the seed's range (issue 28)


@pytest.mark.parametrize("seed", [2**63, 2**70, 10**20])
def test_train_config_rejects_a_seed_that_torch_cannot_take_naming_value_and_range(seed):
    from pemamoe.train_config import TrainConfig

    with pytest.raises(ValueError, match=rf"TrainConfig\.seed must be an integer in \[0, {2**63}\) .*, got {seed}$"):
        TrainConfig(seed=seed)
    with pytest.raises(ValueError, match=r"TrainConfig\.seed must be an integer in"):
        TrainConfig.for_scale("ci", seed=seed)


def test_the_largest_seed_allowed_trains(tmp_path):
    from pemamoe.mappo import TrainConfig, train

    config = TrainConfig.for_scale("ci", "mlp", seed=2**63 - 1, iterations=1)
    assert train(config, tmp_path / "run").finished
    assert json.loads((tmp_path / "run" / "config.json").read_text())["seed"] == 2**63 - 1


@pytest.mark.parametrize("field, value", [("phase_length_iters", 0), ("update_epochs", 0), ("phase_length_iters", 2.5)])
def test_for_scale_refuses_a_bad_phase_length_or_epoch_count_before_rescaling_the_controller(field, value):
    """for_scale rescales the controller's windows by the phase length and epochs before the
    config validates its fields: a zero must be the validation error, not a ZeroDivisionError."""
    from pemamoe.mappo import TrainConfig

    with pytest.raises(ValueError, match=rf"^TrainConfig\.{field} must be an integer >= 1, got {value!r}$"):
        TrainConfig.for_scale("ci", method="pemamoe", **{field: value})


def test_iterations_and_noise_gamma_are_bounded_in_the_configs():
    """Issue 59: iterations=10**23 trained until stopped; noise_gamma=1e308 crashed at the first switch."""
    from pemamoe.core import ITERATIONS_LIMIT, NOISE_GAMMA_LIMIT
    from pemamoe.mappo import TrainConfig

    with pytest.raises(ValueError, match=rf"^TrainConfig\.iterations must be an integer in \[1, {ITERATIONS_LIMIT}\], "
                                         r"got 99999999999999999999999$"):
        TrainConfig.for_scale("ci", method="mlp", iterations=99999999999999999999999)
    with pytest.raises(ValueError, match=r"PhaseControllerConfig\.noise_gamma must be a finite float in \[0, 10.0\], "
                                         r"got 1e\+308"):
        TrainConfig.for_scale("ci", method="pemamoe", noise_gamma=1e308)
    assert TrainConfig.for_scale("ci", method="pemamoe", noise_gamma=NOISE_GAMMA_LIMIT).controller.noise_gamma == 10.0
