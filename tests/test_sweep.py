"""Sweeps: cache keys, skipping finished runs, resuming killed ones, process pool and real Ray."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import psutil
import pytest
import torch

from pemamoe.mappo import train
from pemamoe.methods import METHOD_REGISTRY
from pemamoe.commands import sweep_cli
from pemamoe.sweep_runner import status_summary, sweep_status
from pemamoe.experiments import RunSpec, experiment_specs, main_specs, noise_specs, run_sweep

ROOT = Path(__file__).resolve().parent.parent
BASELINES = tuple(n for n, sp in METHOD_REGISTRY.items() if sp.compared and not sp.proposed)  # three runs without the controller


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
    folders = run_sweep([RunSpec("mlp", 1, "ci"), RunSpec("pemamoe", 1, "ci")], "ray", workers=2,
                        results_dir=tmp_path, verbose=False)
    assert all((f / "done.json").is_file() for f in folders)
    assert not ray.is_initialized()  # the sweep shuts down the Ray instance it started
    # the same runs through the process pool give the same logs (backends do not change results)
    local = run_sweep([RunSpec("mlp", 1, "ci")], "local", workers=1, results_dir=tmp_path / "local", verbose=False)
    import pandas as pd

    from pemamoe.runs import read_parquet

    cols = ["iteration", "episode_return", "served_users", "approx_kl"]
    pd.testing.assert_frame_equal(read_parquet(folders[0] / "metrics.parquet")[cols],
                                  read_parquet(local[0] / "metrics.parquet")[cols])


# --- reliability: verified done check, numpy seeds, CLI, progress, interrupts ---------------------
@pytest.fixture(scope="module")
def finished_mlp(tmp_path_factory):
    """A finished ci run of mlp seed 0, and one stopped at iteration 5 of 6 (copy before use)."""
    base = tmp_path_factory.mktemp("sweep_runs")
    spec = RunSpec("mlp", 0, "ci")
    train(spec.to_config(), base / "done")
    train(RunSpec("moe", 0, "ci").to_config(), base / "partial", max_iterations=5)
    return base


def test_numpy_seeds_work_in_a_sweep(tmp_path, finished_mlp):
    specs = main_specs("ci", seeds=np.arange(1), methods=("mlp",))
    folder = tmp_path / "ci" / RunSpec("mlp", 0, "ci").to_config().run_name()
    shutil.copytree(finished_mlp / "done", folder)
    assert run_sweep(specs, "local", workers=1, results_dir=tmp_path, verbose=False) == [folder]  # failed: int64 JSON
    assert type(specs[0].seed) is int and specs[0] == RunSpec("mlp", 0, "ci")
    with pytest.raises(ValueError, match="RunSpec.seed must be an int >= 0"):
        RunSpec("mlp", 1.5)
    with pytest.raises(ValueError, match="results store must be a folder path or a URL such as s3://bucket/prefix, got ''"):
        run_sweep(specs, "local", workers=1, results_dir="")


def test_a_corrupt_or_foreign_done_marker_stops_the_sweep(tmp_path, finished_mlp):
    spec = RunSpec("mlp", 0, "ci")
    folder = Path(shutil.copytree(finished_mlp / "done", spec.run_dir(tmp_path)))
    (folder / "done.json").write_text("garbage")
    with pytest.raises(ValueError, match=r"done.json is not valid JSON"):
        run_sweep([spec], "local", workers=1, results_dir=tmp_path, verbose=False)
    shutil.copy(finished_mlp / "partial" / "config.json", folder / "config.json")  # another run's folder
    (folder / "done.json").write_text((finished_mlp / "done" / "done.json").read_text())
    with pytest.raises(ValueError, match=r"config.json holds a run with a different config \(method: stored 'moe'"):
        run_sweep([spec], "local", workers=1, results_dir=tmp_path, verbose=False)


@pytest.mark.parametrize("argv", [["--methods"], ["--seeds"], ["--seeds", "-1"], ["--methods", "gpt"],
                                  ["--workers", "0"], ["--scale", "huge"]])
def test_cli_rejects_empty_or_bad_lists(argv, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        sweep_cli(["--scale", "ci", "--results-dir", str(tmp_path), *argv])
    assert exit_.value.code == 2
    assert "error" in capsys.readouterr().err


def test_progress_bar_counts_cached_runs_and_is_off_without_a_terminal(tmp_path, finished_mlp, capsys):
    specs = [RunSpec("mlp", 0, "ci"), RunSpec("moe", 0, "ci")]
    shutil.copytree(finished_mlp / "done", specs[0].run_dir(tmp_path))
    shutil.copytree(finished_mlp / "partial", specs[1].run_dir(tmp_path))  # one iteration left
    run_sweep(specs, "local", workers=1, results_dir=tmp_path, verbose=False, progress=True)
    err = capsys.readouterr().err
    assert "1/2" in err and "2/2" in err and "run" in err  # cached run counted from the start
    run_sweep(specs, "local", workers=1, results_dir=tmp_path, verbose=False)  # stderr is not a terminal here
    assert capsys.readouterr().err == ""


def _wait_for(predicate, timeout, what):
    import time as _time

    end = _time.monotonic() + timeout
    while _time.monotonic() < end:
        if predicate():
            return
        _time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def test_sigint_stops_the_workers_and_starts_nothing_queued(tmp_path):
    specs = [RunSpec(m, 0, "ci") for m in BASELINES]
    folders = [s.run_dir(tmp_path) for s in specs]
    proc = subprocess.Popen([sys.executable, "-m", "pemamoe", "sweep", "--experiment", "main", "--scale", "ci",
                             "--seeds", "0", "--methods", *BASELINES, "--workers", "2",
                             "--results-dir", str(tmp_path), "--records-dir", str(tmp_path / "records"),
                             "--no-progress"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        _wait_for(lambda: all((f / "config.json").exists() for f in folders[:2]) or proc.poll() is not None,
                  240, "two runs to start")
        assert proc.poll() is None, proc.stdout.read()
        tree = psutil.Process(proc.pid).children(recursive=True)
        start = time.monotonic()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
        stopped = time.monotonic() - start
    finally:
        if proc.poll() is None:
            proc.kill()
    gone, alive = psutil.wait_procs(tree, timeout=10)
    assert not alive, f"left running: {alive}"
    assert not folders[2].exists(), "a queued run started after the interrupt"
    assert stopped < 15, f"took {stopped:.1f} s to stop"
    assert proc.returncode == 128 + signal.SIGINT, out
    assert "stopped by SIGINT" in out and "rerun the same command to resume" in out


def test_ray_sweep_is_cancelled_by_sigint(tmp_path):
    ray = pytest.importorskip("ray")
    import threading

    specs = [RunSpec(m, 2, "ci") for m in BASELINES]
    folders = [s.run_dir(tmp_path) for s in specs]

    def interrupt():
        _wait_for(lambda: any((f / "config.json").exists() for f in folders), 240, "a Ray task to start")
        os.kill(os.getpid(), signal.SIGINT)

    before = {p.pid for p in psutil.Process().children(recursive=True)}  # e.g. multiprocessing's resource tracker
    threading.Thread(target=interrupt, daemon=True).start()
    from pemamoe.experiments import SweepInterrupted

    start = time.monotonic()
    with pytest.raises(SweepInterrupted, match="SIGINT"):
        run_sweep(specs, "ray", workers=1, results_dir=tmp_path, verbose=False)
    assert time.monotonic() - start < 240
    assert not ray.is_initialized()
    assert sum(f.exists() for f in folders) == 1, "a queued Ray task started after the interrupt"
    new = [p for p in psutil.Process().children(recursive=True) if p.pid not in before]
    gone, alive = psutil.wait_procs(new, timeout=15)
    assert not alive, f"left running: {alive}"


def test_a_large_compatible_set_splits_into_near_equal_populations():
    from pemamoe.experiments import group_specs

    specs = experiment_specs("all", "small")
    unique = list({s.to_config().run_name(): s for s in reversed(specs)}.values())[::-1]  # one spec per run
    groups = group_specs(unique, 16, 2)
    by_method = {}
    for g in groups:
        assert len({s.method for s in g}) == 1
        by_method.setdefault(g[0].method, []).append(len(g))
    assert by_method == {"mlp": [3], "moe": [12], "smoe": [3], "pemamoe": [11, 10]}
    assert [s for g in groups for s in g if s.method == "pemamoe"] == [s for s in unique if s.method == "pemamoe"]
    assert [len(g) for g in group_specs([s for s in unique if s.method == "pemamoe"], 4, 1)] == [4, 4, 4, 3, 3, 3]


def test_status_reports_where_a_sweep_stands_and_trains_nothing(tmp_path, capsys):
    specs = [RunSpec("mlp", 0, "ci"), RunSpec("smoe", 0, "ci"), RunSpec("smoe", 1, "ci"), RunSpec("moe", 0, "ci")]
    train(specs[0].to_config(), specs[0].run_dir(tmp_path))  # finished
    train(specs[1].to_config(), specs[1].run_dir(tmp_path), max_iterations=4)  # stopped after a checkpoint
    train(specs[2].to_config(), specs[2].run_dir(tmp_path), max_iterations=2)
    before = sorted((p, p.stat().st_mtime_ns) for p in tmp_path.rglob("*"))
    table = sweep_status(specs, tmp_path, workers=2)
    assert (table.attrs["finished"], table.attrs["runs"], table.attrs["timed"]) == (1, 4, 0)
    assert np.isnan(table.attrs["spent_hours"])  # no records folder: nothing measured to report
    smoe, moe = (table[table.methods == m].iloc[0] for m in ("smoe", "moe"))
    # the two SMoE runs form one population that resumes from the lagging member's iteration
    assert (smoe.members, smoe.iteration, smoe.of) == (2, 2, 6)
    assert smoe.s_per_iteration > 0 and smoe.hours_left == pytest.approx(4 * smoe.s_per_iteration / 3600)
    assert (moe.members, moe.iteration) == (1, 0) and np.isnan(moe.s_per_iteration)
    text = status_summary(table, workers=2)
    assert text.startswith("1 of 4 runs finished; 2 populations to run (3 runs)") and "1 population with no rate yet" in text
    with pytest.raises(ValueError, match="workers must be an integer >= 1, got 0"):
        sweep_status(specs, tmp_path, workers=0)
    assert sorted((p, p.stat().st_mtime_ns) for p in tmp_path.rglob("*")) == before  # nothing trained or written
    assert sweep_cli(["--experiment", "main", "--scale", "ci", "--seeds", "0", "--methods", "mlp", "smoe", "moe",
                      "--results-dir", str(tmp_path), "--records-dir", str(tmp_path / "records"),
                      "--status"]) == 0
    assert "1 of 3 runs finished" in capsys.readouterr().out


def test_status_sums_the_compute_the_finished_runs_records_measured(tmp_path):
    from pemamoe.records import record_timing, write_record

    specs = [RunSpec("mlp", 0, "ci"), RunSpec("smoe", 0, "ci")]
    train(specs[0].to_config(), specs[0].run_dir(tmp_path))
    marker = write_record(specs[0].run_dir(tmp_path), "ci", tmp_path / "records")
    measured = record_timing(marker)["member_compute_s"]
    assert measured > 0
    # the main PE-MAMoE run shared by two experiments counts once: here, a spec given twice
    table = sweep_status([specs[0], specs[0], specs[1]], tmp_path, workers=1, records_dir=tmp_path / "records")
    assert table.attrs["spent_hours"] == pytest.approx(measured / 3600)
    assert table.attrs["timed"] == 1
    assert f"1 of 2 runs finished (1 record measured {measured / 3600:.2f} worker-hours of training)" in \
        status_summary(table, 1)


def test_status_rate_counts_checkpoints_but_not_pauses(tmp_path):
    """The rate is the logged wall clock per iteration: checkpoint steps count (they are work), a
    step far longer than the typical checkpoint step (a paused process) does not."""
    import pandas as pd

    from pemamoe.sweep_runner import _logged_progress

    steps = [1.0] * 200
    steps[99] = steps[199] = 41.0  # two checkpoints
    steps[150] = 590.0  # the sweep paused for ten minutes in the middle of an iteration
    wall = np.cumsum([0.0] + steps)
    pd.DataFrame({"iteration": range(len(wall)), "wall_time": wall}).to_parquet(tmp_path / "metrics.parquet")
    n, rate = _logged_progress(tmp_path, checkpoint_every=100)
    assert n == 201 and rate == pytest.approx((197 * 1.0 + 2 * 41.0) / 199)  # 199 working steps, the pause left out
    assert _logged_progress(tmp_path / "missing", 100) == (0, None)


# --- sweeps that advance a few hours at a time (--hours) ------------------------------------------
def _comparable_metrics(result):
    from pemamoe.mappo import TIMING_COLUMNS

    return result.metrics.drop(columns=[c for c in TIMING_COLUMNS if c in result.metrics.columns])


def test_a_deadline_checkpoints_every_member_and_the_resume_is_bit_identical(tmp_path):
    from pemamoe.mappo import TrainConfig, train_population
    from pemamoe.runs import verify_done

    cfgs = [TrainConfig.for_scale("ci", method="smoe", seed=s, iterations=5) for s in (0, 1)]
    whole = train_population(cfgs, [tmp_path / "w0", tmp_path / "w1"])
    dirs = [tmp_path / "d0", tmp_path / "d1"]
    cut = train_population(cfgs, dirs, deadline=time.time())  # already passed: one iteration, then stop
    assert all(not r.finished and len(r.metrics) == 1 for r in cut)
    assert not any(verify_done(d) for d in dirs) and all((d / "checkpoint.pt").exists() for d in dirs)
    resumed = train_population(cfgs, dirs)
    for a, b in zip(whole, resumed):
        assert b.finished and b.resumed_from == 1
        pd.testing.assert_frame_equal(_comparable_metrics(a), _comparable_metrics(b))
        for (na, ta), (nb, tb) in zip(a.actor.state_dict().items(), b.actor.state_dict().items()):
            assert torch.equal(ta, tb), na


def test_sweep_hours_stops_starts_nothing_after_the_deadline_and_a_rerun_finishes(tmp_path, capsys):
    from pemamoe.runs import verify_done

    specs = [RunSpec("mlp", 0, "ci"), RunSpec("smoe", 0, "ci")]  # two populations
    run_sweep(specs, workers=1, results_dir=tmp_path, hours=1e-9)
    out = capsys.readouterr().out
    assert "0 of 2 runs finished, 2 left" in out and "rerun the same command" in out
    assert not any(verify_done(s.run_dir(tmp_path)) for s in specs)
    run_sweep(specs, workers=1, results_dir=tmp_path, hours=1.0)
    assert "finished 2 runs" in capsys.readouterr().out
    assert all(verify_done(s.run_dir(tmp_path)) for s in specs)
    with pytest.raises(ValueError, match="hours must be a number > 0"):
        run_sweep(specs, results_dir=tmp_path, hours=0)


def test_sweep_cli_hours_prints_what_is_left(tmp_path, capsys):
    code = sweep_cli(["--experiment", "main", "--scale", "ci", "--methods", "mlp", "--workers", "1",
                      "--results-dir", str(tmp_path), "--records-dir", str(tmp_path / "records"),
                      "--hours", "0.0000001", "--no-progress"])
    out = capsys.readouterr().out
    assert code == 0 and "1 left" in out and "0 of 1 runs finished" in out and "hours_left" in out


def test_sweep_help_describes_the_command_and_every_option(capsys):
    """sweep --help says what the command does, and each option what it means and its default."""
    with pytest.raises(SystemExit) as exit_:
        sweep_cli(["--help"])
    assert exit_.value.code == 0
    out = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    assert "Train the runs of one experiment" in out
    for shown in ("{ci,small,medium,paper}", "(default: main)", "(default: small)", "(default: local)",
                  "(default: 2)", "(default: results/)", "(default: records/)"):
        assert shown in out, shown


def test_the_top2_arm_runs_the_sparse_methods_with_two_experts_under_the_papers_reading(tmp_path):
    from pemamoe.experiments import BUDGET_READINGS, TOP2_METHODS

    specs = experiment_specs("top2", "medium")
    configs = [s.to_config() for s in specs]
    assert sorted({c.method for c in configs}) == sorted(TOP2_METHODS) == ["pemamoe", "smoe"]
    assert len(specs) == 6 and all(s.tag == "top2" for s in specs)
    for c in configs:
        assert c.net.top_k == 2 and c.fixed_phase is None and c.iterations == configs[0].iterations
        assert all(getattr(c.net, k) == v for k, v in BUDGET_READINGS["paper"].items() if k != "top_k")
    main = {s.to_config().run_name() for s in main_specs("medium")}
    assert not main & {c.run_name() for c in configs}  # runs of their own, not top-1's
    run_sweep(experiment_specs("top2", "ci", seeds=(0,)), "local", workers=1, results_dir=tmp_path, progress=False)
    assert all((s.run_dir(tmp_path) / "done.json").is_file() for s in experiment_specs("top2", "ci", seeds=(0,)))


def test_campaign_v2_is_the_campaign_under_its_readings_with_five_seeds_at_the_paper_scale():
    from pemamoe.experiments import CAMPAIGN_V2_READINGS

    v1, v2 = experiment_specs("campaign", "paper"), experiment_specs("campaign_v2", "paper")
    assert len(v2) == 30 and sorted({s.seed for s in v2}) == [0, 1, 2, 3, 4]
    assert sorted({s.method for s in v2}) == sorted({s.method for s in v1})
    by_run = {(s.method, s.seed): s.to_config() for s in v1}
    for spec in v2:
        config = spec.to_config()
        assert config.controller.log_std_value == CAMPAIGN_V2_READINGS["controller.log_std_value"] == 0.3
        assert config.target_kl_check == CAMPAIGN_V2_READINGS["target_kl_check"] == "epoch"
        if (spec.method, spec.seed) in by_run:  # v1's run of the same method and seed: only the readings differ
            old = by_run[spec.method, spec.seed]
            assert config.run_name() != old.run_name()
            assert config.replace(target_kl_check=old.target_kl_check,
                                  controller=old.controller).config_hash() == old.config_hash()
    assert len(experiment_specs("campaign_v2", "ci")) == 4  # the four compared methods, one seed


@pytest.mark.parametrize("reading", ["ours", "paper"])
def test_a_pinned_reading_sets_the_gated_actors_and_leaves_mlp_and_the_rest_of_the_run(reading):
    """--reading pins the sparse actor of the gated methods only; pinning the defaults' own reading
    renames no run (so runs trained pinned are the unpinned experiment's once the defaults are that
    reading)."""
    import dataclasses

    from pemamoe.mappo import NetConfig
    from pemamoe.methods import method_spec
    from pemamoe.experiments import BUDGET_READINGS

    plain, pinned = experiment_specs("all", "ci"), experiment_specs("all", "ci", reading=reading)
    assert [s.tag for s in plain] == [s.tag for s in pinned]
    for before, after in zip(plain, pinned):
        a, b = before.to_config(), after.to_config()
        if method_spec(a.method).network == "mlp":
            assert after == before and b.run_name() == a.run_name()
            continue
        assert all(getattr(b.net, k) == v for k, v in BUDGET_READINGS[reading].items())
        assert dataclasses.replace(b, net=a.net) == a  # nothing else moved (noise, ablations, seeds)
        defaults = NetConfig()
        if all(getattr(defaults, k) == v for k, v in BUDGET_READINGS[reading].items()):
            assert b.run_name() == a.run_name()
        else:
            assert b.run_name() != a.run_name()


def test_a_reading_outside_the_cycling_experiments_is_refused_naming_them(capsys):
    with pytest.raises(ValueError, match="main, tricks, noise, all, campaign.*'budget'"):
        experiment_specs("budget", "ci", reading="paper")
    with pytest.raises(ValueError, match="reading must be one of ours, paper, got 'theirs'"):
        experiment_specs("main", "ci", reading="theirs")
    with pytest.raises(SystemExit) as exit_:
        sweep_cli(["--experiment", "tuning", "--reading", "paper", "--status"])
    assert exit_.value.code == 2
    assert "--reading applies to the experiments main, tricks, noise, all, campaign; 'tuning'" in capsys.readouterr().err
