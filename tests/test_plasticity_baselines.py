"""ReDo and shrink-and-perturb (appendix 06c), the hooks they use (appendix 06b: probe batches,
logged metrics, fresh parameters, partial Adam resets) and their runs through the trainer."""
import copy
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch

from pemamoe.methods import METHOD_REGISTRY, compared_methods, method_spec
from pemamoe.nets import PopulationActor, PopulationCritic, make_actor, make_critic
from pemamoe.plasticity_baselines import ReDo, ShrinkAndPerturb, dormant_units, recycling_layers
from pemamoe.optim import RunAdamW, group_index
from pemamoe.plasticity import RunSettings, plasticity_method
from pemamoe.train_config import METHODS, TIMING_COLUMNS

OBS, STATE = 10, 14
BASE = RunSettings(total_iterations=30, phase_length=10)
MEMBERS = [SimpleNamespace(seed=s, base_schedule=lambda: BASE) for s in (0, 1)]


def population(kind, steps=3):
    singles = []
    for m in MEMBERS:
        torch.manual_seed(m.seed)
        singles.append((make_actor(kind, OBS), make_critic(kind, STATE)))
    actor, critic = PopulationActor([a for a, _ in singles]), PopulationCritic([c for _, c in singles])
    group_of, names = group_index(singles[0][0], actor.layout)
    actor_opt = RunAdamW(actor.flat, group_of, len(names), weight_decay=1e-4)
    critic_opt = RunAdamW(critic.flat, torch.zeros(critic.layout.size, dtype=torch.long), 1)
    g = torch.Generator().manual_seed(5)
    for _ in range(steps):
        actor.flat.grad = torch.randn(actor.flat.shape, generator=g)
        actor_opt.step(torch.full((2,), 1e-3, dtype=torch.float64), torch.ones(2, dtype=torch.bool))
    return actor, critic, actor_opt, critic_opt


def snapshot(actor, opt):
    return [t.detach().clone() for t in (actor.flat, opt.exp_avg, opt.exp_avg_sq, opt.steps)]


def test_the_baselines_are_registered_and_outside_the_default_comparison():
    for name, plasticity, network in (("mlp_redo", "redo", "mlp"), ("smoe_redo", "redo", "smoe"),
                                      ("mlp_snp", "shrink_and_perturb", "mlp"), ("smoe_snp", "shrink_and_perturb", "smoe")):
        spec = method_spec(name)
        assert (spec.plasticity, spec.network, spec.compared) == (plasticity, network, False)
        assert name not in METHODS and name not in compared_methods()
    assert plasticity_method("redo") is ReDo and plasticity_method("shrink_and_perturb") is ShrinkAndPerturb
    assert METHODS == ("mlp", "moe", "smoe", "pemamoe")
    assert set(METHOD_REGISTRY) >= {"mlp_redo", "smoe_snp"}


# -- RunAdamW: a masked reset ------------------------------------------------------------------
def _torch_adamw(values, grads, lr, wd):
    """torch.optim.AdamW run over `grads` from `values` (one parameter vector) -> values after."""
    p = torch.nn.Parameter(values.clone())
    opt = torch.optim.AdamW([p], lr=lr, eps=1e-5, weight_decay=wd)
    for g in grads:
        p.grad = g.clone()
        opt.step()
    return p.detach()


def test_a_masked_reset_restarts_only_the_masked_entries_as_a_fresh_adamw():
    P, lr, wd = 12, 1e-2, 1e-4
    group_of = torch.tensor([0] * 6 + [1] * 6)  # two groups of six
    g = torch.Generator().manual_seed(0)
    start = torch.randn(2, P, generator=g)
    grads = [torch.randn(2, P, generator=g) for _ in range(9)]
    flat = start.clone().requires_grad_(True)
    opt = RunAdamW(flat, group_of, 2, eps=1e-5, weight_decay=wd)
    lrs, every = torch.full((2,), lr, dtype=torch.float64), torch.ones(2, dtype=torch.bool)
    for grad in grads[:4]:
        flat.grad = grad.clone()
        opt.step(lrs, every)
    at_reset = flat.detach().clone()
    other = snapshot(SimpleNamespace(flat=flat), opt)
    mask = torch.zeros(P, dtype=torch.bool)
    mask[[1, 2, 7]] = True  # part of each group
    opt.reset(0, mask)
    assert torch.equal(opt.steps, other[3])  # no group is covered whole: no step count moves
    assert (opt.exp_avg[0, mask] == 0).all() and (opt.exp_avg_sq[0, mask] == 0).all()
    assert torch.equal(opt.exp_avg[0, ~mask], other[1][0, ~mask]) and torch.equal(opt.exp_avg[1], other[1][1])
    for grad in grads[4:]:
        flat.grad = grad.clone()
        opt.step(lrs, every)
    # hand check: the masked entries move as a fresh AdamW started at the reset, the others (and
    # member 1) as one AdamW over all nine steps
    fresh = _torch_adamw(at_reset[0], [g_[0] for g_ in grads[4:]], lr, wd)
    kept = _torch_adamw(start[0], [g_[0] for g_ in grads], lr, wd)
    assert torch.allclose(flat[0, mask].detach(), fresh[mask], atol=1e-6, rtol=0)
    assert torch.allclose(flat[0, ~mask].detach(), kept[~mask], atol=1e-6, rtol=0)
    assert torch.allclose(flat[1].detach(), _torch_adamw(start[1], [g_[1] for g_ in grads], lr, wd), atol=1e-6, rtol=0)
    # the first step after a reset that kept the count would be ~3x a fresh one: not what happened
    assert not torch.allclose(fresh[mask], kept[mask], atol=1e-4)


def test_a_mask_covering_a_whole_group_zeroes_that_groups_count_only():
    group_of = torch.tensor([0, 0, 0, 1, 1, 1])
    flat = torch.randn(2, 6).requires_grad_(True)
    opt = RunAdamW(flat, group_of, 2)
    for _ in range(3):
        flat.grad = torch.randn(2, 6)
        opt.step(torch.full((2,), 1e-3, dtype=torch.float64), torch.ones(2, dtype=torch.bool))
    opt.reset(0, torch.tensor([True, True, True, False, True, False]))
    assert opt.steps.tolist() == [[0.0, 3.0], [3.0, 3.0]]
    assert opt.clock_offset[0].tolist() == [0, 0, 0, 0, 3, 0] and opt.clock_offset[1].tolist() == [0] * 6
    opt.reset(0, torch.tensor([3, 5]))  # flat indices work too; the rest of group 1, but each call is partial
    assert opt.steps.tolist() == [[0.0, 3.0], [3.0, 3.0]]
    opt.reset(0)  # the full reset clears every count and clock
    assert opt.steps[0].sum() == 0 and opt.clock_offset[0].sum() == 0


def test_optimizer_state_with_clocks_round_trips_and_old_states_still_load():
    actor, _, opt, _ = population("mlp")
    old = opt.member_state(0)
    assert "clock_offset" not in old  # no partial reset yet: the checkpoint keys of every existing run
    opt.reset(0, torch.tensor([0, 1, 2]))
    state = opt.member_state(0)
    other = RunAdamW(actor.flat, opt.group_of, opt.n_groups)
    other.load_member_state(0, state)
    assert torch.equal(other.clock_offset[0], opt.clock_offset[0])
    other.load_member_state(0, old)
    assert other.clock_offset[0].sum() == 0


# -- ReDo ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["mlp", "smoe"])
def test_redo_recycles_the_dormant_units_of_its_own_member_only(kind):
    actor, critic, actor_opt, critic_opt = population(kind)
    method = ReDo(MEMBERS, actor, critic, actor_opt, critic_opt)
    first = "fc1.bias" if kind == "mlp" else "gate.experts.b1"
    with torch.no_grad():  # two dead first-layer units in member 0
        bias = actor.member_param(0, first)
        (bias if kind == "mlp" else bias[0])[[3, 5]] = -1e3
    obs = torch.randn(2, 40, 3, OBS, generator=torch.Generator().manual_seed(1))
    method.observe_rollout(obs)
    probe = method.probe_batch(0)
    assert probe.shape == (min(method.probe_rows, 120), OBS)
    acts = actor.member(0).probe(probe)["act"]
    want = [dormant_units(a, method.config.tau) for a in acts]
    assert want[0][0, 3] and want[0][0, 5]
    before = snapshot(actor, actor_opt)
    critic_before = critic.flat.detach().clone()
    n = method.recycle(0)
    assert n == sum(int(d.sum()) for d in want)
    after = snapshot(actor, actor_opt)
    for b, a in zip(before, after):  # member 1: parameters, moments and step counts bit-identical
        assert torch.equal(b[1], a[1])
    assert torch.equal(before[3], after[3])  # no group count moved in member 0 either
    assert torch.equal(critic_before, critic.flat.detach())
    layer = recycling_layers(actor)[0]
    fresh_in = layer["incoming"][want[0]].reshape(-1)
    out = layer["outgoing"][want[0]].reshape(-1)
    assert (actor.flat[0, out] == 0).all()  # outgoing weights zeroed
    assert (actor.flat[0, fresh_in] != before[0][0, fresh_in]).any()  # incoming weights re-initialised
    assert (actor_opt.exp_avg[0, fresh_in] == 0).all() and (actor_opt.exp_avg[0, out] == 0).all()
    assert actor_opt.clock_offset[0, fresh_in].eq(actor_opt.steps[0, 0]).all()
    untouched = torch.ones(actor.layout.size, dtype=torch.bool)
    for lay, d in zip(recycling_layers(actor), want):
        untouched[lay["incoming"][d].reshape(-1)] = False
        untouched[(lay["outgoing"][0][d.all(0)] if lay["shared"] else lay["outgoing"][d]).reshape(-1)] = False
    assert torch.equal(actor.flat[0, untouched].detach(), before[0][0, untouched])
    assert torch.equal(actor_opt.exp_avg[0, untouched], before[1][0, untouched])
    assert dormant_units(actor.member(0).probe(probe)["act"][0], method.config.tau)[0, [3, 5]].logical_not().all()


def test_redo_on_the_mlp_leaves_the_output_unchanged_when_the_recycled_units_were_silent():
    actor, critic, actor_opt, critic_opt = population("mlp")
    method = ReDo(MEMBERS, actor, critic, actor_opt, critic_opt)
    with torch.no_grad():
        actor.member_param(0, "fc1.bias")[:4] = -1e3
        actor.member_param(0, "fc2.bias")[:2] = -1e3
    method.observe_rollout(torch.randn(2, 40, 3, OBS, generator=torch.Generator().manual_seed(2)))
    probe = method.probe_batch(0)
    mean = actor.member(0).probe(probe)["mean"]
    assert method.recycle(0) >= 6
    assert torch.equal(actor.member(0).probe(probe)["mean"], mean)


def test_probe_batches_need_a_rollout_and_methods_without_probe_rows_keep_none():
    actor, critic, actor_opt, critic_opt = population("mlp", steps=0)
    method = ReDo(MEMBERS, actor, critic, actor_opt, critic_opt)
    with pytest.raises(RuntimeError, match="no rollout observed"):
        method.probe_batch(0)
    snp = ShrinkAndPerturb(MEMBERS, actor, critic, actor_opt, critic_opt)
    snp.observe_rollout(torch.zeros(2, 4, 3, OBS))
    assert "recent_obs" not in snp.state_dict(0) and snp.metrics(0) == {}


def test_fresh_parameters_leave_the_global_generator_alone():
    actor, critic, actor_opt, critic_opt = population("smoe", steps=0)
    method = ShrinkAndPerturb(MEMBERS, actor, critic, actor_opt, critic_opt)
    torch.manual_seed(123)
    state = torch.get_rng_state()
    a = method.fresh_parameters(0)
    assert torch.equal(torch.get_rng_state(), state)
    b = method.fresh_parameters(0)
    assert not torch.equal(a, b) and a.shape == (actor.layout.size,)


# -- shrink-and-perturb --------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["mlp", "smoe"])
def test_shrink_and_perturb_shrinks_its_own_member_only(kind):
    actor, critic, actor_opt, critic_opt = population(kind)
    method = ShrinkAndPerturb(MEMBERS, actor, critic, actor_opt, critic_opt)
    before = snapshot(actor, actor_opt)
    state = method.member_generator(0).get_state()
    method.shrink_and_perturb(0)
    method.member_generator(0).set_state(state)
    eps = method.fresh_parameters(0)
    idx = method.weights
    cfg = method.config
    assert torch.equal(actor.flat[0, idx].detach(), cfg.shrink * before[0][0, idx] + cfg.perturb * eps[idx])
    ls = slice(*actor.layout.span("log_std"))
    assert torch.equal(actor.flat[0, ls].detach(), before[0][0, ls])
    assert actor.flat[0, idx].detach().norm() < 0.9 * before[0][0, idx].norm()
    after = snapshot(actor, actor_opt)
    assert torch.equal(after[0][1], before[0][1])
    for b, a in zip(before[1:], after[1:]):  # the optimizer state of both members is kept
        assert torch.equal(b, a)


# -- through the trainer -------------------------------------------------------------------------
def _frame(result):
    return result.metrics.drop(columns=[c for c in TIMING_COLUMNS if c in result.metrics.columns])


def test_redo_logs_units_recycled_and_resumes_bit_for_bit_at_a_switch(tmp_path):
    from pemamoe.mappo import TrainConfig, train_population

    cfgs = [TrainConfig.for_scale("ci", method="smoe_redo", seed=s) for s in (0, 1)]
    whole = train_population(cfgs, run_dirs=[tmp_path / "a0", tmp_path / "a1"], progress=False)
    m = whole[0].metrics
    assert m.loc[m.switch, "redo/units_recycled"].gt(0).all() and m.loc[~m.switch, "redo/units_recycled"].eq(0).all()
    assert pd.read_parquet(tmp_path / "a0" / "metrics.parquet")["redo/units_recycled"].equals(m["redo/units_recycled"])
    dirs = [tmp_path / "b0", tmp_path / "b1"]
    train_population(cfgs, run_dirs=dirs, max_iterations=2, progress=False)  # stops just before the first switch
    resumed = train_population(cfgs, run_dirs=dirs, progress=False)
    alone = train_population(cfgs[1:], progress=False)[0]  # a member trains as it would alone
    for w, r in zip(whole, resumed):
        pd.testing.assert_frame_equal(_frame(w), _frame(r))
        assert torch.equal(w.actor.gate.experts.w1, r.actor.gate.experts.w1)
    pd.testing.assert_frame_equal(_frame(whole[1]), _frame(alone))


def test_a_sweep_runs_both_baselines_on_both_networks(tmp_path):
    from pemamoe.analysis import load_runs
    from pemamoe.experiments import RunSpec, sweep_records

    names = ("mlp_redo", "smoe_redo", "mlp_snp", "smoe_snp")
    records = sweep_records([RunSpec(n, 0, "ci") for n in names], "local", workers=1, results_dir=tmp_path / "results",
                            records_dir=tmp_path / "records", verbose=False)
    metrics, _ = load_runs(records)
    assert set(metrics.method) == set(names)
    for name in names:
        rows = metrics[metrics.method == name]
        assert rows.switch.any() and np.isfinite(rows.episode_return).any()
        logged = rows["redo/units_recycled"].notna().any() if "redo/units_recycled" in rows else False
        assert logged == name.endswith("redo")  # only ReDo's runs have the column
