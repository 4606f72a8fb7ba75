"""Tests of the MAPPO trainer (notebook 07, pemamoe/mappo.py). Everything runs at the ci scale."""

import json

import numpy as np
import pandas as pd
import pytest
import torch

import pemamoe.mappo as mappo
import pemamoe.populations as populations
from pemamoe.mappo import (
    METHODS,
    TIMING_COLUMNS,
    EpisodeTracker,
    RunningNorm,
    TrainConfig,
    bootstrap_values,
    collect_rollout,
    compute_gae,
    train,
)
from pemamoe.phase_controller import PhaseController, PhaseControllerConfig


pytestmark = pytest.mark.usefixtures("one_thread")


RATIO_ROUNDING = 1e-5  # |log-ratio| allowed before the first step: float rounding, never a routing mismatch


def ci(method="pemamoe", **kw):
    return TrainConfig.for_scale("ci", method=method, seed=3, **kw)


# --- GAE -----------------------------------------------------------------------------------------
def test_gae_hand_computed_with_truncation_and_termination():
    # two environments, gamma 0.9, lambda 0.5
    rewards = torch.tensor([[1.0, 0.0], [2.0, 1.0], [3.0, 1.0]])
    values = torch.tensor([[0.5, 1.0], [1.0, 1.0], [2.0, 1.0]])
    dones = torch.tensor([[1, 0], [0, 0], [1, 0]], dtype=torch.bool)
    # env 0: truncated after step 0 (V(final) = 10), terminated after step 2 (bootstrap 0)
    final = torch.tensor([[10.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    last = torch.tensor([99.0, 4.0])  # env 1 continues: V(s_3) = 4
    nv = bootstrap_values(values, last, dones, final)
    assert nv.tolist() == [[10.0, 1.0], [2.0, 1.0], [0.0, 4.0]]
    adv, ret = compute_gae(rewards, values, nv, dones, gamma=0.9, gae_lambda=0.5)
    # env 0: step 2: 3 - 2 = 1; step 1: (2 + 1.8 - 1) + 0.45 * 1 = 3.25; step 0: 1 + 9 - 0.5 = 9.5 (no carry)
    # env 1: deltas 0 + 0.9 - 1 = -0.1, 1 + 0.9 - 1 = 0.9, 1 + 3.6 - 1 = 3.6
    a2 = 3.6
    a1 = 0.9 + 0.45 * a2
    a0 = -0.1 + 0.45 * a1
    expected = torch.tensor([[9.5, a0], [3.25, a1], [1.0, a2]], dtype=torch.float64)
    assert torch.allclose(adv, expected, atol=1e-12)
    assert torch.allclose(ret, expected + values.double(), atol=1e-12)


def _population_of_one(cfg):
    venv = mappo.UAVVectorEnv(cfg.num_envs, 0, cfg=cfg.env_config())
    return venv, mappo.build_population([cfg])


def test_rollout_bootstraps_truncation_from_final_state():
    # episodes of 3 slots, rollout of 5: truncation at steps 2 of every env; an MLP critic is deterministic
    cfg = ci("mlp", env_overrides={"episode_steps": 3}, rollout_steps=5, num_minibatches=5)
    venv, pop = _population_of_one(cfg)
    critic, norms = pop.critic, pop.norms
    norms.update(torch.tensor([[0.0, 10.0, 20.0]]))
    obs, state, _ = venv.reset()
    sched = pop.plasticity.begin_iteration(0)
    finals = []
    real_step = venv.step

    def spy(actions):
        out = real_step(actions)
        if "final_state" in out[5]:
            finals.append(out[5]["final_state"].copy())
        return out

    venv.step = spy
    ro, *_ = collect_rollout(pop, venv, obs, state, sched, EpisodeTracker(cfg.num_envs), 0)
    assert ro.dones[0, 2].all() and not ro.dones[0, [0, 1, 3, 4]].any()
    with torch.no_grad():
        v, _, _ = critic(torch.from_numpy(finals[0]).unsqueeze(0), sched.value_temperature)
        v_final = norms.denormalize(v.double())
    assert torch.allclose(ro.next_values[0, 2], v_final[0])
    assert torch.equal(ro.next_values[0, :2], ro.values[0, 1:3])


def test_running_norm_matches_batch_statistics():
    norm = RunningNorm(True)
    x = torch.randn(1000, dtype=torch.float64) * 7 + 3
    for chunk in x.split(137):
        norm.update(chunk)
    assert norm.mean == pytest.approx(float(x.mean()), rel=1e-10)
    assert norm.var == pytest.approx(float(x.var(unbiased=False)), rel=1e-10)
    assert torch.allclose(norm.denormalize(norm.normalize(x)), x)
    off = RunningNorm(False)
    off.update(x)
    assert torch.equal(off.normalize(x), x)


# --- every method trains at ci scale -------------------------------------------------------------
EXPECTED = [
    "iteration", "phase", "switch", "env_steps", "episode_return", "coverage", "served_users", "uav_using_rate",
    "energy_rate_kj", "collisions_per_episode", "step/reward", "step/coverage", "approx_kl", "clip_frac",
    "explained_variance", "policy_loss", "value_loss", "entropy", "kl_ref", "lr/head", "lr/critic", "ent_coef",
    "kl_coef", "clip_coef", "temperature/policy", "early_stop_epoch", "sps", "rollout_time", "update_time",
    "rank/stable/mean", "dormant/paper/mean", "router/policy/p0", "action/std_x", "first_ratio_dev",
]


@pytest.mark.parametrize("method", METHODS)
def test_each_method_trains_and_logs(method, tmp_path):
    cfg = ci(method, iterations=3)  # 48 slots: every env finishes one 32-slot episode
    res = train(cfg, tmp_path / method)
    m = res.metrics
    assert len(m) == 3 and m["iteration"].tolist() == [0, 1, 2]
    missing = [c for c in EXPECTED if c not in m.columns]
    assert not missing, missing
    # the ratio is 1 before the first gradient step of every iteration (routing replayed), up to the
    # last bits a CPU's BLAS may change with the row count (see test_first_ratio_is_one_directly)
    assert (m["first_ratio_dev"] <= RATIO_ROUNDING).all()
    assert (m["gradient_steps"] > 0).all()
    assert np.isfinite(m[["policy_loss", "value_loss", "approx_kl", "sps"]].to_numpy()).all()
    assert m["env_steps"].tolist() == [cfg.batch_env_steps * (i + 1) for i in range(3)]
    if method != "mlp":
        assert "router/value/p0" in m.columns
    eps = res.episodes
    assert len(eps) > 0 and {"return", "phase", "served_users", "collisions", "env"} <= set(eps.columns)


def test_build_population_builds_each_member_from_its_own_seed_alone():
    cfgs = [ci("smoe").replace(seed=s) for s in (4, 7)]
    pop = mappo.build_population(cfgs)
    for r, cfg in enumerate(cfgs):  # member r's row holds exactly the networks its config builds alone
        for got, alone in zip(pop.member(r), mappo.member_networks(cfg)):
            assert all(torch.equal(a, b) for a, b in zip(got.state_dict().values(), alone.state_dict().values()))
    assert pop.config is cfgs[0] and pop.group_names[0] == "router" and len(pop.rngs) == len(pop.generators) == 2
    assert pop.frozen_groups(pop.plasticity.begin_iteration(0)) is None  # nothing frozen before a switch
    with pytest.raises(ValueError, match="must share"):
        mappo.build_population([ci("smoe"), ci("mlp")])


def test_first_ratio_is_one_directly():
    # the update's forward pass on a minibatch (other rows, another batch size) replays the
    # rollout's log-probabilities bit for bit, for every member of a population
    for method in METHODS:
        cfgs = [ci(method).replace(seed=s) for s in (0, 1)]
        venv = mappo.UAVVectorEnv(seeds=[x for c in cfgs for x in mappo.vector_seeds(c.seed, c.num_envs)],
                                  cfg=cfgs[0].env_config())
        pop = mappo.build_population(cfgs)
        actor = pop.actor
        obs, state, _ = venv.reset()
        sched = pop.plasticity.begin_iteration(0)
        ro, *_ = collect_rollout(pop, venv, obs, state, sched, EpisodeTracker(venv.num_envs, members=2), 0)
        R, N, U = 2, cfgs[0].batch_env_steps, venv.n_agents
        idx = torch.stack([torch.randperm(N)[: N // 2] for _ in range(R)])
        rows = torch.arange(R).unsqueeze(1)
        route = None
        if ro.routing is not None:
            r = ro.routing.reshape(R, N, U)
            route = mappo.RoutingSample(r.noise[rows, idx].reshape(R, -1, r.noise.shape[-1]),
                                        r.experts[rows, idx].reshape(R, -1, r.experts.shape[-1]),
                                        r.temperature[rows, idx].reshape(R, -1))
        logp, *_ = actor.evaluate(ro.obs.reshape(R, N, U, -1)[rows, idx].reshape(R, -1, venv.obs_dim),
                                  ro.actions.reshape(R, N, U, -1)[rows, idx].reshape(R, -1, 2), route)
        # Bit for bit on many CPUs; on some the BLAS kernel, and so the last bit of a product, depends
        # on the number of rows (the rollout's pass and the minibatch's differ): about 1e-6 seen.
        torch.testing.assert_close(logp, ro.logprobs.reshape(R, N, U)[rows, idx].reshape(R, -1), rtol=0,
                                   atol=RATIO_ROUNDING, msg=method)


# --- phase clock -----------------------------------------------------------------------------------
@pytest.mark.parametrize("L,iters", [(2, 6), (3, 7)])
def test_switch_calls_on_switch_exactly_at_multiples_of_L(L, iters, monkeypatch):
    calls = []
    real = PhaseController.on_switch

    def spy(self, t):
        calls.append(t)
        return real(self, t)

    monkeypatch.setattr(PhaseController, "on_switch", spy)
    res = train(ci(phase_length_iters=L, iterations=iters, diag_every=10))
    assert calls == [t for t in range(1, iters) if t % L == 0]
    m = res.metrics
    assert m.loc[m["switch"], "iteration"].tolist() == calls
    assert m["phase"].tolist() == [(t // L) % 3 for t in range(iters)]
    # the controller acts at the switch: KL anchor on, log-std reset, LR dropped
    first = m[m["iteration"] == L].iloc[0]
    assert first["kl_coef"] > 0 and first["lr/head"] < m["lr/head"].iloc[0]


# --- resume, files, done.json -------------------------------------------------------------------
def _comparable(df):
    return df.drop(columns=[c for c in TIMING_COLUMNS if c in df.columns]).reset_index(drop=True)


@pytest.mark.parametrize("method", ["pemamoe", "mlp"])
def test_resume_continues_exactly(method, tmp_path):
    cfg = ci(method, iterations=6, checkpoint_every=2)
    straight = train(cfg, tmp_path / "straight")
    part = train(cfg, tmp_path / "resumed", max_iterations=3)
    assert not part.finished and not (tmp_path / "resumed" / "done.json").exists()
    ck = torch.load(tmp_path / "resumed" / "checkpoint.pt", weights_only=True)
    assert ck["iteration"] == 3
    resumed = train(cfg, tmp_path / "resumed", resume=True)
    assert resumed.resumed_from == 3 and resumed.finished
    pd.testing.assert_frame_equal(_comparable(straight.metrics), _comparable(resumed.metrics))
    pd.testing.assert_frame_equal(straight.episodes, resumed.episodes)
    for a, b in ((straight.actor, resumed.actor), (straight.critic, resumed.critic)):
        for (na, pa), (nb, pb) in zip(a.state_dict().items(), b.state_dict().items()):
            assert na == nb and torch.equal(pa, pb), na


def test_checkpoints_pack_only_new_log_rows_and_still_resume_from_older_formats(tmp_path):
    """Format 4 stores the log rows as pickled chunks, one per checkpoint, each pickled once (format
    3 pickled every row at every checkpoint, format 2 stored them as lists, which torch.save pickled
    number by number); checkpoints of formats 3 and 2 must still resume to the same run, and the
    finished logs must be the same bytes however the run was checkpointed or resumed."""
    import pickle

    from pemamoe.bookkeeping import RowLog, _pack_rows, _unpack_rows

    cfg = ci("smoe", iterations=6, checkpoint_every=2)
    straight = train(cfg, tmp_path / "straight")
    for old_format in (3, 2):
        folder = tmp_path / f"format{old_format}"
        train(cfg, folder, max_iterations=4)
        path = folder / "checkpoint.pt"
        ck = torch.load(path, weights_only=True)
        assert ck["format"] == 5 and len(ck["metrics_rows"]) == 2  # a chunk per checkpoint: iterations 0-1, 2-3
        assert all(torch.is_tensor(chunk) and chunk.dtype == torch.uint8 for chunk in ck["metrics_rows"])
        rows = _unpack_rows(ck["metrics_rows"])
        assert [r["iteration"] for r in rows] == [0, 1, 2, 3]
        # the unfinished run's log, made from concatenated pieces, holds the same table
        pd.testing.assert_frame_equal(pd.DataFrame(rows), pd.read_parquet(folder / "metrics.parquet"))
        episodes = _unpack_rows(ck["episode_rows"])
        if old_format == 3:
            ck.update(format=3, metrics_rows=_pack_rows(rows), episode_rows=_pack_rows(episodes))
        else:
            ck.update(format=2, metrics_rows=rows, episode_rows=episodes)
        torch.save(ck, path)  # as an earlier trainer wrote it
        resumed = train(cfg, folder, resume=True)
        assert resumed.resumed_from == 4
        pd.testing.assert_frame_equal(_comparable(straight.metrics), _comparable(resumed.metrics))
        pd.testing.assert_frame_equal(straight.episodes, resumed.episodes)
        # episodes carry no timing column: the sealed final log is the straight run's bytes
        assert (folder / "episodes.parquet").read_bytes() == (tmp_path / "straight" / "episodes.parquet").read_bytes()
    log = RowLog(rows[:2])
    first = log.packed()
    log += rows[2:]
    assert log.packed()[0] is first[0] and len(log.packed()) == 2  # earlier chunks are kept as they were
    pd.testing.assert_frame_equal(pd.DataFrame(_unpack_rows(log.packed())), pd.DataFrame(rows))  # (NaN != NaN in dicts)
    pd.testing.assert_frame_equal(log.frame(), pd.DataFrame(rows))
    pd.testing.assert_frame_equal(pd.DataFrame(_unpack_rows(_pack_rows(rows))), pd.DataFrame(rows))
    with pytest.raises(pickle.UnpicklingError, match="only plain data, found numpy"):
        _unpack_rows(pickle.dumps([{"x": np.float32(1.0)}]))
    with pytest.raises(TypeError, match="append-only"):
        log[0] = {}
    with pytest.raises(TypeError, match="append-only"):
        log.pop()
    with pytest.raises(pickle.UnpicklingError, match="only plain data, found numpy"):
        _unpack_rows([torch.frombuffer(bytearray(pickle.dumps([{"x": np.float32(1.0)}])), dtype=torch.uint8)])


def test_a_checkpoint_before_any_episode_ended_resumes(tmp_path):
    """Format 4 with no episode row yet (an empty list of chunks) reads back as no rows."""
    from pemamoe.bookkeeping import RowLog

    cfg = ci("mlp", iterations=3, checkpoint_every=1)
    straight = train(cfg, tmp_path / "straight")
    train(cfg, tmp_path / "cut", max_iterations=1)
    ck = torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=True)
    assert ck["format"] == 5 and ck["episode_rows"] == [] and len(ck["metrics_rows"]) == 1
    assert RowLog.from_checkpoint(ck["episode_rows"]) == []
    resumed = train(cfg, tmp_path / "cut", resume=True)
    assert resumed.resumed_from == 1
    pd.testing.assert_frame_equal(_comparable(straight.metrics), _comparable(resumed.metrics))
    pd.testing.assert_frame_equal(straight.episodes, resumed.episodes)


def test_run_dir_files_are_complete_and_atomic(tmp_path):
    cfg = ci("smoe", iterations=4, checkpoint_every=2)
    res = train(cfg, tmp_path)
    assert TrainConfig.from_dict(json.loads((tmp_path / "config.json").read_text())) == cfg
    m = pd.read_parquet(tmp_path / "metrics.parquet")
    assert len(m) == 4
    pd.testing.assert_frame_equal(m, res.metrics)
    assert len(pd.read_parquet(tmp_path / "episodes.parquet")) == len(res.episodes)
    done = json.loads((tmp_path / "done.json").read_text())
    assert done["finished"] and done["iterations"] == 4 and done["config_hash"] == cfg.config_hash()
    torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert not list(tmp_path.glob("*.tmp")) and not list(tmp_path.glob(".*.tmp"))


def test_done_json_short_circuits(tmp_path, monkeypatch):
    cfg = ci("mlp", iterations=2)
    first = train(cfg, tmp_path)

    def boom(*a, **k):
        raise AssertionError("recomputed a finished run")

    monkeypatch.setattr(populations, "_train_group", boom)
    again = train(cfg, tmp_path, resume=True)
    assert again.from_cache
    pd.testing.assert_frame_equal(again.metrics, first.metrics)
    for (_, a), (_, b) in zip(first.actor.state_dict().items(), again.actor.state_dict().items()):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="different config"):
        train(cfg.replace(seed=4), tmp_path, resume=True)
    # a baseline ignores the phase controller: its settings do not make a different run
    other = cfg.replace(controller=cfg.controller.without("noise_injection"))
    assert other.config_hash() == cfg.config_hash()
    assert train(other, tmp_path, resume=True).from_cache
    pem = cfg.replace(method="pemamoe")
    assert pem.replace(controller=other.controller).config_hash() != pem.config_hash()


def test_config_hash_covers_the_resolved_environment(monkeypatch):
    cfg = TrainConfig.for_scale("ci", "mlp", seed=0)
    assert cfg.identity()["env"]["step_engine"] == "compiled"
    assert cfg.replace(env_overrides={"step_engine": "numpy"}).config_hash() != cfg.config_hash()
    # a changed environment default is a different computation even though no override names it
    before = cfg.config_hash()
    monkeypatch.setattr(TrainConfig, "env_config", lambda self: mappo.EnvConfig(collision_penalty=50.0))
    assert cfg.config_hash() != before


# --- configuration -------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "field,value",
    [("method", "transformer"), ("num_envs", 0), ("rollout_steps", 2.5), ("iterations", -1), ("lr", 0.0),
     ("gamma", 1.5), ("gae_lambda", -0.1), ("clip_coef", 0), ("vf_coef", -1.0), ("target_kl", 0.0),
     ("max_grad_norm", float("nan")), ("num_minibatches", 3), ("adam_betas", (0.9, 1.0)), ("anneal_lr", 1),
     ("phase_length_iters", 0), ("n_phases", 4), ("weight_decay", -1e-4), ("env_overrides", {"phase_clock": "env"}),
     ("device", "tpu")],
)
def test_invalid_config_raises_naming_the_field(field, value):
    with pytest.raises(ValueError, match=f"TrainConfig.{field}"):
        TrainConfig(**{field: value})


def test_presets_and_overrides():
    paper = TrainConfig.for_scale("paper")
    assert paper.total_env_steps == 22_118_400 and paper.iterations == 10_800
    assert paper.phase_length_iters * 9 == paper.iterations
    assert (paper.update_epochs, paper.num_minibatches, paper.lr, paper.clip_coef, paper.vf_coef) == (8, 32, 3e-4, 0.15, 2.0)
    assert paper.controller == PhaseControllerConfig()
    small = TrainConfig.for_scale("small", method="moe", seed=2, noise_gamma=0.01, without="lr_drop")
    assert small.iterations == 9 * small.phase_length_iters
    assert small.controller.noise_gamma == 0.01 and not small.controller.lr_drop
    assert small.controller.lr_warmup_iters < PhaseControllerConfig().lr_warmup_iters
    assert TrainConfig.for_scale("small").config_hash() != small.config_hash()
    assert TrainConfig.from_dict(small.to_dict()) == small
    with pytest.raises(ValueError, match="unknown override"):
        TrainConfig.for_scale("ci", bogus=1)
    with pytest.raises(ValueError, match="scale"):
        TrainConfig.for_scale("huge")


def test_evaluate_policy_is_deterministic():
    cfg = ci("smoe")
    actor, _ = mappo.build_population([cfg]).member(0)
    a = mappo.evaluate_policy(actor, cfg.env_config(), episodes=3, seed=1, phase=2)
    b = mappo.evaluate_policy(actor, cfg.env_config(), episodes=3, seed=1, phase=2)
    assert len(a) == 3 and (a["phase"] == 2).all()
    pd.testing.assert_frame_equal(a, b)


def test_force_controller_runs_noise_only_for_a_baseline():
    from pemamoe.phase_controller import MECHANISMS

    others = [m for m in MECHANISMS if m != "noise_injection"]
    cfg = ci("moe", force_controller=True, without=others, iterations=3)
    assert cfg.controller_enabled and cfg.config_hash() != ci("moe", iterations=3).config_hash()
    m = train(cfg).metrics
    assert m.loc[m["switch"], "noised_experts"].gt(0).all()  # noise after the switch's epochs
    assert (m["kl_coef"] == 0).all() and m["lr/head"].nunique() == 1


def test_paper_preset_and_controller_defaults_agree():
    # RunSettings (notebook 06) repeats the paper's PPO values that TrainConfig (notebook 07) holds;
    # this keeps the two copies from drifting apart.
    from pemamoe.plasticity import RunSettings

    assert TrainConfig.for_scale("paper").base_schedule() == RunSettings()
    assert TrainConfig().base_schedule() == RunSettings()


@pytest.mark.parametrize("reading", ["defaults", "paper"])
def test_pemamoe_trains_as_smoe_bit_for_bit_until_the_first_switch(reading):
    """PE-MAMoE is SMoE plus the phase controller, which acts from the first switch on: before it
    the two runs (same seed, same network reading) are the same numbers, so every difference that
    PE-MAMoE shows against SMoE afterwards is the controller's (the comparison notebook 10 draws)."""
    import dataclasses

    def run(method):
        cfg = TrainConfig.for_scale("ci", method=method, seed=3, phase_length_iters=3, iterations=6)
        if reading == "paper":
            cfg = cfg.replace(net=dataclasses.replace(cfg.net, load_balance_coef=0.0, expert_heads="per_expert",
                                                      update_routing="current"))
        metrics = train(cfg, max_iterations=4, threads=1, progress=False).metrics
        return metrics.filter(regex=r"^(?!.*(_time|sps)).*$")  # all but the clocks

    smoe, pemamoe = run("smoe"), run("pemamoe")
    assert list(smoe.columns) == list(pemamoe.columns)
    before, at_switch = smoe.iteration < 3, smoe.iteration == 3
    numeric = [c for c in smoe.columns if smoe[c].dtype != object]
    for column in numeric:
        assert np.array_equal(smoe.loc[before, column].to_numpy(), pemamoe.loc[before, column].to_numpy(),
                              equal_nan=True), column
    # the switch's iteration is where they part: the controller's resets change the update
    assert any(not np.array_equal(smoe.loc[at_switch, c].to_numpy(), pemamoe.loc[at_switch, c].to_numpy(),
                                  equal_nan=True) for c in numeric)
