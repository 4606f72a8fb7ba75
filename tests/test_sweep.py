"""Sweeps: cache keys, skipping finished runs, resuming killed ones, process pool and real Ray."""

import json
import time

import pytest

from pemamoe.mappo import train
from pemamoe.sweep import RunSpec, experiment_specs, noise_specs, run_sweep


def test_spec_resolves_to_config_and_folder(tmp_path):
    spec = RunSpec("pemamoe", 1, "ci", without=("noise_injection",), noise_gamma=0.01)
    cfg = spec.to_config()
    assert cfg.method == "pemamoe" and cfg.seed == 1
    assert cfg.controller.noise_gamma == 0.01 and not cfg.controller.noise_injection
    assert spec.run_dir(tmp_path) == tmp_path / "ci" / cfg.run_name()
    # the tag names the experiment, not the run
    assert RunSpec("mlp", 0, "ci", tag="main") == RunSpec("mlp", 0, "ci", tag="noise")


def test_bad_specs_and_backends_are_named():
    with pytest.raises(ValueError, match="RunSpec.method"):
        RunSpec("transformer")
    with pytest.raises(ValueError, match="scale must be one of"):
        RunSpec("mlp", scale="huge")
    with pytest.raises(ValueError, match="backend must be one of local, ray"):
        run_sweep([], backend="slurm")
    with pytest.raises(ValueError, match="experiment must be one of"):
        experiment_specs("everything", "ci")


def test_noise_sweep_gives_moe_only_the_noise_mechanism():
    moe = [s for s in noise_specs("ci", (0,)) if s.method == "moe"]
    assert len(moe) == 3
    ctrl = moe[0].to_config()
    assert ctrl.controller_enabled
    switches = {name: getattr(ctrl.controller, name) for name in ("noise_injection", "log_std_reset", "lr_drop",
                                                                  "kl_anchor", "router_freeze")}
    assert switches == {"noise_injection": True, "log_std_reset": False, "lr_drop": False,
                        "kl_anchor": False, "router_freeze": False}


def test_finished_runs_are_skipped_and_killed_runs_resume(tmp_path, capsys):
    specs = [RunSpec("mlp", 0, "ci"), RunSpec("smoe", 0, "ci")]
    # "kill" the second run half-way: it leaves a checkpoint and no done.json
    partial = specs[1].run_dir(tmp_path)
    half = train(specs[1].to_config(), partial, max_iterations=3)
    assert not half.finished and not (partial / "done.json").exists()
    folders = run_sweep(specs, "local", workers=1, results_dir=tmp_path)
    assert all((f / "done.json").is_file() for f in folders)
    resumed = train(specs[1].to_config(), partial)  # cached now
    assert resumed.from_cache
    stamps = [(f / "done.json").stat().st_mtime_ns for f in folders]
    capsys.readouterr()
    run_sweep(specs + [RunSpec("mlp", 0, "ci", tag="again")], "local", workers=1, results_dir=tmp_path)
    assert "2 runs, 2 cached, 0 to run" in capsys.readouterr().out
    assert [(f / "done.json").stat().st_mtime_ns for f in folders] == stamps


def test_process_pool_runs_two_runs(tmp_path):
    folders = run_sweep([RunSpec("mlp", 0, "ci"), RunSpec("moe", 0, "ci")], "local", workers=2, results_dir=tmp_path)
    assert all((f / "done.json").is_file() for f in folders)
    assert json.loads((folders[1] / "sweep.json").read_text())["spec"]["method"] == "moe"


def test_two_run_sweep_on_a_real_local_ray(tmp_path):
    ray = pytest.importorskip("ray")
    start = time.perf_counter()
    folders = run_sweep([RunSpec("mlp", 1, "ci"), RunSpec("pemamoe", 1, "ci")], "ray", workers=2,
                        results_dir=tmp_path, verbose=False)
    assert all((f / "done.json").is_file() for f in folders)
    assert not ray.is_initialized()  # the sweep shuts down the Ray instance it started
    # the same runs through the process pool give the same logs (backends do not change results)
    local = run_sweep([RunSpec("mlp", 1, "ci")], "local", workers=1, results_dir=tmp_path / "local", verbose=False)
    import pandas as pd

    cols = ["iteration", "episode_return", "served_users", "approx_kl"]
    pd.testing.assert_frame_equal(pd.read_parquet(folders[0] / "metrics.parquet")[cols],
                                  pd.read_parquet(local[0] / "metrics.parquet")[cols])
    assert time.perf_counter() - start < 300
