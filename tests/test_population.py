"""The run axis: a population of runs trained in one process (notebooks 05-07).

A member's run must be bit-identical whatever population it trains in (the result cache and the
sweeps rely on it), and every per-member action must touch only its own member.
"""

import math

import numpy as np
import pandas as pd
import pytest
import torch

import pemamoe.mappo as mappo
import pemamoe.populations as populations
from pemamoe.bookkeeping import _unpack_rows
from pemamoe.mappo import TIMING_COLUMNS, TrainConfig, train, train_population
from pemamoe.nets import PopulationActor, PopulationCritic, make_actor, make_critic
from pemamoe.optim import RunAdamW, group_index
from pemamoe.phase_controller import PhaseController


pytestmark = pytest.mark.usefixtures("one_thread")


def ci(method="pemamoe", seed=0, **kw):
    return TrainConfig.for_scale("ci", method=method, seed=seed, **kw)


def _comparable(df):
    return df.drop(columns=[c for c in TIMING_COLUMNS if c in df.columns]).reset_index(drop=True)


_PACKED = ("metrics_rows", "episode_rows")
_VOLATILE = ("elapsed", "wall_time", "sps", "sps_total", "rollout_time", "update_time", "diag_time", "population")


def _assert_same(x, y, path=""):
    """Nested checkpoint equality, bit for bit, except how long things took."""
    if isinstance(x, dict):
        assert set(x) == set(y), path
        for k in x:
            if k in _PACKED:  # log rows, chunked as checkpoints fell: compare the rows, timing columns aside
                _assert_same(_unpack_rows(x[k]), _unpack_rows(y[k]), f"{path}/{k}")
            elif k not in _VOLATILE:
                _assert_same(x[k], y[k], f"{path}/{k}")
    elif isinstance(x, (list, tuple)):
        assert len(x) == len(y), path
        for i, (a, b) in enumerate(zip(x, y)):
            _assert_same(a, b, f"{path}[{i}]")
    elif torch.is_tensor(x):
        assert torch.equal(x, y), path
    elif isinstance(x, float) and math.isnan(x):
        assert math.isnan(y), path
    else:
        assert x == y, (path, x, y)


def _assert_same_run(a, b, dir_a=None, dir_b=None):
    pd.testing.assert_frame_equal(_comparable(a.metrics), _comparable(b.metrics))
    pd.testing.assert_frame_equal(a.episodes, b.episodes)
    for net in ("actor", "critic"):
        for (na, ta), (nb, tb) in zip(getattr(a, net).state_dict().items(), getattr(b, net).state_dict().items()):
            assert na == nb and torch.equal(ta, tb), (net, na)
    if dir_a is not None:
        _assert_same(torch.load(dir_a / "checkpoint.pt", weights_only=True),
                     torch.load(dir_b / "checkpoint.pt", weights_only=True))


# The same questions on a GPU (cuBLAS may pick its kernels by batch count, and GPU reductions their
# order by tensor shape: if a cuda case fails, the population layout has to join a CUDA run's
# identity, as notebook 07 explains). Skipped without a GPU, so CI skips them;
# benchmarks/device_check.sh runs them on a lent GPU machine.
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                                 reason="needs a CUDA GPU (CI has none)"))]
# Measured on an H200 (torch 2.11, 2026-12-04): a member's numbers on the GPU depend on its population's
# size from the first update on (policy_loss -0.0016776349 alone, -0.0016776308 in a population of 3),
# for MLP and PE-MAMoE alike. Strict: the day it holds, this test fails and the claim can be made.
GPU_POPULATION_DEPENDENT = pytest.mark.xfail(
    torch.cuda.is_available(), strict=True,
    reason="on a GPU a member's last bits depend on the population size (benchmarks/HISTORY.md)")


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=[DEVICES[1].marks[0], GPU_POPULATION_DEPENDENT])])
@pytest.mark.parametrize("method", ["pemamoe", "mlp", "pemamoe/paper", "moe/paper"])
def test_member_is_bit_identical_alone_and_in_any_population(method, device, tmp_path):
    # members differ in seed, ablation switch, noise gamma, force_controller, learning rate and
    # entropy anneal; orders differ. "/paper": the paper's actor readings (a mean head per expert)
    from pemamoe.experiments import BUDGET_READINGS

    method, _, reading = method.partition("/")
    net = BUDGET_READINGS[reading] if reading else {}
    cfgs = [ci(method, 0, iterations=6, device=device, **net),
            ci(method, 1, iterations=6, device=device, without=("router_freeze",), lr=1e-3, **net),
            ci(method, 2, iterations=6, device=device, noise_gamma=0.05, force_controller=True, ent_start=0.02,
               ent_end=0.006, **net)]
    alone = train(cfgs[0], tmp_path / "alone")
    pop = train_population(cfgs[::-1], [tmp_path / f"p{i}" for i in range(3)])
    pair = train_population([cfgs[1], cfgs[0]], [tmp_path / "q1", tmp_path / "q0"])
    _assert_same_run(alone, pop[2], tmp_path / "alone", tmp_path / "p2")
    _assert_same_run(alone, pair[1], tmp_path / "alone", tmp_path / "q0")
    _assert_same_run(pop[1], pair[0], tmp_path / "p1", tmp_path / "q1")
    for res in pop:  # routing replay holds per member: the ratio is 1 at each first step, up to
        # float rounding: the rollout's pass and the minibatch's see different row counts, and on
        # some CPUs the BLAS kernel (and so the last bit) depends on the count (up to ~1.4e-6 seen)
        assert (res.metrics["first_ratio_dev"] <= 1e-5).all()
        assert (res.metrics["population"] == 3).all()


@pytest.mark.parametrize("device", DEVICES)
def test_killed_population_resumes_bit_identically(device, tmp_path):
    cfgs = [ci("pemamoe", s, iterations=6, checkpoint_every=2, device=device) for s in (0, 1)]
    straight = train_population(cfgs, [tmp_path / "s0", tmp_path / "s1"])
    part = train_population(cfgs, [tmp_path / "r0", tmp_path / "r1"], max_iterations=3)
    assert not any(r.finished for r in part)
    resumed = train_population(cfgs, [tmp_path / "r0", tmp_path / "r1"])
    for r in range(2):
        assert resumed[r].resumed_from == 3 and resumed[r].finished
        _assert_same_run(straight[r], resumed[r], tmp_path / f"s{r}", tmp_path / f"r{r}")


def test_members_at_different_iterations_train_as_subpopulations(tmp_path):
    cfgs = [ci("smoe", s, iterations=4, checkpoint_every=1) for s in (0, 1)]
    train(cfgs[0], tmp_path / "m0", max_iterations=2)
    both = train_population(cfgs, [tmp_path / "m0", tmp_path / "m1"])
    assert both[0].resumed_from == 2 and both[1].resumed_from is None
    _assert_same_run(both[1], train(cfgs[1]))


def test_incompatible_members_are_refused_naming_the_field():
    with pytest.raises(ValueError, match="must share 'method'"):
        check = mappo.check_population
        check([ci("mlp"), ci("moe")])
    with pytest.raises(ValueError, match="must share 'num_envs'"):
        mappo.check_population([ci("mlp"), ci("mlp", num_envs=8)])
    with pytest.raises(ValueError, match="share one run_dir"):
        train_population([ci("mlp", 0), ci("mlp", 1)], ["x", "x"])


# --- per-member actions -------------------------------------------------------------------------------
def _population(cfgs):
    obs_dim, state_dim = 20, 24
    singles = []
    for c in cfgs:
        torch.manual_seed(c.seed)
        kind = c.method_spec().network
        singles.append((make_actor(kind, obs_dim), make_critic(kind, state_dim)))
    actor, critic = PopulationActor([a for a, _ in singles]), PopulationCritic([c for _, c in singles])
    group_of, names = group_index(singles[0][0], actor.layout)
    a_opt = RunAdamW(actor.flat, group_of, len(names), weight_decay=1e-4)
    c_opt = RunAdamW(critic.flat, torch.zeros(critic.layout.size, dtype=torch.long), 1)
    return actor, critic, a_opt, c_opt, names


def test_switch_actions_touch_only_their_member():
    cfgs = [ci("pemamoe", 0), ci("pemamoe", 1, without=("noise_injection", "adam_reset")), ci("smoe", 2)]
    actor, critic, a_opt, c_opt, _ = _population(cfgs)
    ctrl = PhaseController(cfgs, actor, critic, a_opt, c_opt)
    for opt in (a_opt, c_opt):
        opt.exp_avg.fill_(1.0), opt.exp_avg_sq.fill_(1.0), opt.steps.fill_(5.0)
    before = actor.flat.detach().clone()
    ctrl.on_switch(2)
    after = actor.flat.detach()
    ls = slice(*actor.layout.span("log_std"))
    trunk = torch.cat(ctrl.expert_indices())
    # Adam reset: member 0's actor moments only; the critic keeps its moments (it must keep learning)
    assert (a_opt.exp_avg[0] == 0).all() and (a_opt.steps[0] == 0).all()
    assert (a_opt.exp_avg[1:] == 1).all() and (a_opt.steps[1:] == 5).all()
    assert (c_opt.exp_avg == 1).all() and (c_opt.steps == 5).all()
    # noise: member 0's experts only; log-std reset on both controller members, not on the SMoE baseline
    assert not torch.equal(after[0, trunk], before[0, trunk])
    assert torch.equal(after[1, trunk], before[1, trunk]) and torch.equal(after[2], before[2])
    assert torch.allclose(after[:2, ls], torch.full_like(after[:2, ls], math.log(0.3)))
    # the anchor's reference keeps the reset sigma (so it does not pull log-std back)
    assert ctrl.has_reference[0] and torch.allclose(ctrl.reference[0, ls], torch.tensor(math.log(0.3)))
    s = ctrl.begin_iteration(2)
    assert s.router_frozen.tolist() == [True, True, False]
    assert s.lr_critic.tolist() == [cfgs[0].lr] * 3  # no LR drop for the critic
    assert s.lr_actor[0] < cfgs[0].lr and s.lr_actor[2] == cfgs[0].lr


def test_router_freeze_keeps_that_member_bit_identical_while_others_move():
    cfgs = [ci("pemamoe", 0), ci("pemamoe", 1)]
    actor, critic, a_opt, _, names = _population(cfgs)
    router = torch.tensor([names[g] == "router" for g in a_opt.group_of.tolist()])
    before = actor.flat.detach().clone()
    actor.flat.grad = torch.randn_like(actor.flat)
    frozen = torch.zeros(2, len(names), dtype=torch.bool)
    frozen[0, names.index("router")] = True
    a_opt.step(torch.tensor([1e-2, 1e-2], dtype=torch.float64), torch.tensor([True, True]), frozen)
    assert torch.equal(actor.flat[0, router], before[0, router])
    assert not torch.equal(actor.flat[1, router], before[1, router])
    assert not torch.equal(actor.flat[0, ~router], before[0, ~router])
    assert a_opt.steps[0, names.index("router")] == 0 and a_opt.steps[1, names.index("router")] == 1
    # a member that does not step stays bit-identical, moments and step counts included
    snap = (actor.flat.detach().clone(), a_opt.exp_avg.clone(), a_opt.steps.clone())
    actor.flat.grad = torch.randn_like(actor.flat)
    a_opt.step(torch.tensor([1e-2, 1e-2], dtype=torch.float64), torch.tensor([False, True]))
    assert torch.equal(actor.flat[0], snap[0][0]) and torch.equal(a_opt.exp_avg[0], snap[1][0])
    assert torch.equal(a_opt.steps[0], snap[2][0]) and not torch.equal(actor.flat[1], snap[0][1])


def test_epoch_noise_is_weighted_by_each_experts_share():
    cfgs = [ci("pemamoe", 0), ci("pemamoe", 1)]
    actor, critic, a_opt, c_opt, _ = _population(cfgs)
    ctrl = PhaseController(cfgs, actor, critic, a_opt, c_opt)
    ctrl.on_switch(2)
    ctrl.begin_iteration(2)
    idx = ctrl.expert_indices()
    before = actor.flat.detach().clone()
    counts = torch.tensor([[10.0, 0.0, 0.0], [5.0, 5.0, 0.0]])
    noised = ctrl.after_epoch(counts, torch.tensor([True, False]))
    assert noised == [1, 0]
    d = (actor.flat.detach() - before).abs()
    assert d[0, idx[0]].sum() > 0 and d[0, idx[1]].sum() == 0 and d[0, idx[2]].sum() == 0
    assert d[1].sum() == 0  # did not step this epoch: no noise


def test_noise_window_unit_iterations_is_the_longer_reading():
    epochs = ci("pemamoe").controller
    iters = TrainConfig.for_scale("ci", noise_window_unit="iterations").controller
    assert epochs.noise_window_unit == "epochs" and iters.noise_window_unit == "iterations"
    paper_epochs = TrainConfig.for_scale("paper").controller
    assert paper_epochs.noise_epochs == 30
    with pytest.raises(ValueError, match="noise_window_unit"):
        TrainConfig.for_scale("ci", noise_window_unit="weeks")
    m = train(ci("pemamoe", iterations=4, noise_window_unit="iterations", noise_epochs=1)).metrics
    # one iteration of noise after the switch at 2: every epoch of iteration 2 is noised, 3 is not
    assert m.loc[m["iteration"] == 2, "noised_experts"].iloc[0] >= 2
    assert m.loc[m["iteration"] == 3, "noised_experts"].iloc[0] == 0


# --- the paper's order of events --------------------------------------------------------------
def test_first_step_after_a_switch_is_in_the_new_phase(monkeypatch):
    seen = []
    real = mappo.UAVVectorEnv.step

    def spy(self, actions):
        out = real(self, actions)
        if self.num_envs == cfg.num_envs:  # the training environments, not the probe's
            seen.append(int(np.asarray(out[5]["phase"])[0]))
        return out

    cfg = ci("mlp", iterations=4)  # switches at 2; 16 slots per iteration
    monkeypatch.setattr(mappo.UAVVectorEnv, "step", spy)
    res = train(cfg)
    steps = cfg.rollout_steps
    assert seen[2 * steps] == 1 and seen[2 * steps - 1] == 0
    eps = res.episodes
    assert (eps["phase_start"] == eps["phase"]).all()


def test_critic_values_use_noiseless_gating():
    cfg = ci("smoe")
    _, critic, *_ = _population([cfg])
    state = torch.randn(1, 50, 24)
    v1, _, _ = critic(state, torch.ones(1))
    v2, _, _ = critic(state, torch.ones(1))
    assert torch.equal(v1, v2)
    single = critic.member(0)
    with torch.no_grad():
        ref, _ = single(state[0], 1.0, None, deterministic_gate=True)
    assert torch.allclose(v1[0], ref, atol=1e-6)


def test_log_std_reset_survives_the_anchor_window():
    # a policy narrowed to sigma = 0.2 before the switch, reset to 0.3 at the switch: the anchor
    # must not pull log-std back (its gradient on log-std is zero at the reset value), whereas an
    # anchor on the pre-switch sigma pulls with about 12x the entropy bonus's strength
    cfg = ci("pemamoe")
    actor, critic, a_opt, c_opt, _ = _population([cfg])
    ls = slice(*actor.layout.span("log_std"))
    with torch.no_grad():
        actor.flat[0, ls] = math.log(0.2)
    ctrl = PhaseController([cfg], actor, critic, a_opt, c_opt)
    ctrl.on_switch(2)
    assert ctrl.begin_iteration(2).kl_coef[0] > 0

    def log_std_grad():
        obs = torch.randn(1, 64, 20, generator=torch.Generator().manual_seed(0))
        _, _, routing = actor.act(obs, torch.ones(1), [torch.Generator().manual_seed(1)])
        _, _, _, mean, log_std, chosen = actor.evaluate(obs, torch.zeros(1, 64, 2), routing)
        kl = ctrl.extra_loss({"obs": obs, "tau": routing.temperature, "noise": routing.noise, "experts": chosen,
                              "mean": mean, "log_std": log_std})
        (g,) = torch.autograd.grad(kl.sum(), actor.flat)
        return g[0, ls]

    assert log_std_grad().abs().max() < 1e-6
    with torch.no_grad():
        ctrl.reference[0, ls] = math.log(0.2)  # the literal order: snapshot before the reset
    pull = log_std_grad()
    assert (pull > 0.05).all()  # gradient descent lowers log-std back towards the old sigma


@pytest.mark.parametrize("R", [1, 2, 3, 12])
@pytest.mark.parametrize("n,d", [(48, 177), (384, 177), (640, 531), (96, 40)])
def test_first_layer_on_copies_gives_the_bits_of_the_per_expert_products(R, n, d):
    """run_experts computes layer 1 on E copies of an input that needs no gradient and, at R > 1,
    per expert on one that does; outputs and weight/bias gradients must be the same bits."""
    from pemamoe.popnets import run_experts

    g = torch.Generator().manual_seed(R * 1000 + n + d)
    x = torch.randn(R, n, d, generator=g)
    params = [torch.randn(R, 3, d, 32, generator=g), torch.randn(R, 3, 32, generator=g),
              torch.randn(R, 3, 32, 32, generator=g), torch.randn(R, 3, 32, generator=g)]
    upstream = torch.randn(R, 3, n, 32, generator=g)
    results = []
    for input_grad in (False, True):  # False: E copies of x; True: per expert when R > 1
        leaves = [p.clone().requires_grad_() for p in params]
        out = run_experts(x.clone().requires_grad_(input_grad), *leaves)
        (out * upstream).sum().backward()
        results.append([out.detach(), *[p.grad for p in leaves]])
    for copied, narrow in zip(*results):
        assert torch.equal(copied.view(torch.int32), narrow.view(torch.int32))  # the bits, sign of zero included


def test_a_member_behind_catches_up_and_joins_the_population(tmp_path, monkeypatch):
    """Members resumed at different iterations: the laggards train up to the leaders' iteration
    and continue with them as one population; every result is still the run alone, bit for bit."""
    cfgs = [ci("moe", s, iterations=6, checkpoint_every=1) for s in (0, 1, 2)]
    train(cfgs[0], tmp_path / "m0", max_iterations=3)
    calls = []
    real = populations._train_group

    def spy(step, configs, run_dirs, ckpts, max_iterations, *args):
        calls.append((len(configs), None if ckpts[0] is None else int(ckpts[0]["iteration"]), max_iterations))
        return real(step, configs, run_dirs, ckpts, max_iterations, *args)

    monkeypatch.setattr(populations, "_train_group", spy)
    out = train_population(cfgs, [tmp_path / f"m{s}" for s in range(3)])
    assert calls == [(2, None, 3), (3, 3, None)]
    assert [r.resumed_from for r in out] == [3, None, None] and all(r.finished for r in out)
    monkeypatch.setattr(populations, "_train_group", real)
    for s in range(3):
        _assert_same_run(out[s], train(cfgs[s], tmp_path / f"alone{s}"), tmp_path / f"m{s}", tmp_path / f"alone{s}")
