"""Issue 57: every config field from the command line (`--set FIELD=VALUE`), and the target-KL
stop's readings (`target_kl_check`: per minibatch, or per epoch as CleanRL checks it)."""

import json

import pytest
import torch

from pemamoe import mappo
from pemamoe.__main__ import main
from pemamoe.commands import sweep_cli
from pemamoe.experiments import experiment_specs
from pemamoe.mappo import TrainConfig, train_population
from pemamoe.populations import check_population, population_key
from pemamoe.train_config import TRAIN_FIELDS_ADDED, parse_setting, parse_settings


# -- parsing ----------------------------------------------------------------------------------
@pytest.mark.parametrize("text, expected", [
    ("controller.log_std_value=0.3", ("controller.log_std_value", 0.3)),
    ("target_kl=none", ("target_kl", None)),
    ("target_kl=1", ("target_kl", 1.0)),  # an int given to a float field is a float
    ("target_kl_check=epoch", ("target_kl_check", "epoch")),
    ("net.top_k=2", ("net.top_k", 2)),
    ("anneal_lr=true", ("anneal_lr", True)),
    ("adam_betas=[0.9, 0.99]", ("adam_betas", (0.9, 0.99))),
    ("env.n_users=30", ("env.n_users", 30)),
])
def test_a_setting_is_read_as_the_field_expects(text, expected):
    assert parse_setting(text) == expected


@pytest.mark.parametrize("text, needles", [
    ("log_std_value", ["'log_std_value'", "FIELD=VALUE"]),
    ("=3", ["'=3'", "FIELD=VALUE"]),
    ("bogus=1", ["'bogus'", "target_kl_check", "controller.FIELD"]),
    ("controller.bogus=1", ["'controller.bogus'", "log_std_value"]),
    ("nets.top_k=2", ["'nets.top_k'", "controller.FIELD, net.FIELD or env.FIELD"]),
    ("method=mlp", ["'method'", "--method"]),
    ("controller=1", ["'controller'"]),
])
def test_a_setting_naming_no_field_is_refused_naming_it_and_what_is_allowed(text, needles):
    with pytest.raises(ValueError) as err:
        parse_setting(text)
    for needle in needles:
        assert needle in str(err.value), (needle, str(err.value))


def test_settings_reach_the_config_through_for_scale_and_its_validators():
    config = TrainConfig.for_scale("ci", "pemamoe", 0, **parse_settings(
        ["controller.log_std_value=0.3", "net.top_k=1", "env.n_users=12", "target_kl=0.15"]))
    assert config.controller.log_std_value == 0.3 and config.env_config().n_users == 12 and config.target_kl == 0.15
    with pytest.raises(ValueError, match="target_kl_check"):
        TrainConfig.for_scale("ci", **parse_settings(["target_kl_check=sometimes"]))
    with pytest.raises(ValueError, match="n_users"):
        TrainConfig.for_scale("ci", **parse_settings(["env.n_users=-3"]))


# -- the command line ---------------------------------------------------------------------------
def test_train_help_lists_set(capsys):
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    out = capsys.readouterr().out
    assert "--set FIELD=VALUE" in out and "controller.log_std_value" in out


def test_sweep_help_lists_set(capsys):
    with pytest.raises(SystemExit):
        sweep_cli(["--help"])
    assert "--set FIELD=VALUE" in capsys.readouterr().out


def test_a_set_run_records_the_field_in_its_config_and_identity(tmp_path):
    """A real ci run: the field is in config.json, and the run's name (hash) is not the default's."""
    out = tmp_path / "run"
    assert main(["train", "--method", "pemamoe", "--scale", "ci", "--out", str(out),
                 "--set", "controller.log_std_value=0.3", "--set", "target_kl_check=epoch"]) == 0
    stored = json.loads((out / "config.json").read_text())
    assert stored["controller"]["log_std_value"] == 0.3 and stored["target_kl_check"] == "epoch"
    config = TrainConfig.from_dict(stored)
    default = TrainConfig.for_scale("ci", "pemamoe", 0)
    assert config.identity()["controller"]["log_std_value"] == 0.3
    assert config.identity()["target_kl_check"] == "epoch"
    assert config.config_hash() != default.config_hash()


def test_a_bad_set_is_one_usage_line_and_nothing_is_written(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--scale", "ci", "--out", str(tmp_path / "run"), "--set", "controller.log_std_value=x"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "log_std_value" in err and "'x'" in err
    assert not (tmp_path / "run").exists()


def test_sweep_set_reaches_every_run_and_its_status(tmp_path, capsys):
    assert sweep_cli(["--experiment", "main", "--scale", "ci", "--seeds", "0", "--methods", "smoe",
                      "--set", "target_kl=none", "--status", "--results-dir", str(tmp_path / "r"),
                      "--records-dir", str(tmp_path / "rec")]) == 0
    specs = experiment_specs("main", "ci", (0,), ("smoe",))
    assert specs[0].with_overrides(parse_settings(["target_kl=none"])).to_config().target_kl is None
    with pytest.raises(SystemExit) as exit_:
        sweep_cli(["--scale", "ci", "--set", "target_kl=-1", "--status", "--results-dir", str(tmp_path / "r")])
    assert exit_.value.code == 2 and "target_kl" in capsys.readouterr().err


# -- identity: a field added after records existed --------------------------------------------
def test_the_added_field_at_its_first_value_leaves_every_earlier_identity_as_it_was():
    config = TrainConfig.for_scale("paper", "smoe", 0)
    assert config.target_kl_check == TRAIN_FIELDS_ADDED["target_kl_check"]
    assert "target_kl_check" not in config.identity()
    old = config.to_dict()
    old.pop("target_kl_check")  # a config.json written before the field existed
    assert TrainConfig.from_dict(old) == config


# -- the two stops, trained ------------------------------------------------------------------
def _tiny(seed=0, **changes):
    return TrainConfig.for_scale("ci", "smoe", seed, iterations=3, update_epochs=3, num_minibatches=4, **changes)


def test_members_may_differ_in_the_stop_and_each_trains_as_it_would_alone():
    configs = [_tiny(target_kl=1e-9), _tiny(target_kl=1e-9, target_kl_check="epoch"), _tiny(target_kl=None)]
    check_population(configs)
    assert len({population_key(c) for c in configs}) == 1
    together = train_population(configs)
    alone = [train_population([c])[0] for c in configs]
    columns = ["policy_loss", "approx_kl", "gradient_steps", "early_stop_epoch", "episode_return"]
    for t, a in zip(together, alone):
        assert t.metrics[columns].equals(a.metrics[columns])
    steps = [r.metrics["gradient_steps"].tolist() for r in together]
    # a tiny target: per minibatch nothing steps once the ratio has moved; per epoch the first
    # epoch's 4 minibatches step and the check after it stops the rest; no target: every step
    assert all(s == 4 for s in steps[1]), steps
    assert all(s == 12 for s in steps[2]), steps
    assert all(s <= 4 for s in steps[0]), steps
    assert together[1].metrics["early_stop_epoch"].eq(0).all()
