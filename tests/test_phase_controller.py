"""Phase controller (notebook 06): every mechanism of Algorithm 1, each behind its own switch.

The controller under test is the one the trainer runs (`pemamoe.phase_controller.PhaseController`),
driven here for one run (a population of R = 1), its update steps made as the trainer makes them.
"""

import copy
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pemamoe.nets import NetConfig, PopulationActor, make_actor, make_critic
from pemamoe.optim import group_index
from pemamoe.phase_controller import (
    MECHANISMS,
    MemberConfig,
    PhaseController,
    PhaseControllerConfig,
    entropy_coef,
    expert_parameters,
    kl_anchor_coef,
    lr_multiplier,
    temperature_formula,
    temperature_text,
)
from pemamoe.plasticity import RunSettings, plasticity_method, population_method

OBS, STATE = 10, 14
BASE = RunSettings(total_iterations=3000, phase_length=1000)
ONE = torch.ones(1, dtype=torch.bool)


def setup(kind="pemamoe", cfg=None, enabled=True, base=BASE, seed=0, weight_decay=1e-4, net=None):
    torch.manual_seed(seed)
    actor, critic = make_actor(kind, OBS, 2, net), make_critic(kind, STATE, net)
    member = MemberConfig(cfg or PhaseControllerConfig(), base, controller_enabled=enabled, seed=seed)
    return population_method("phase_controller", [member], [actor], [critic], weight_decay=weight_decay)


def group_names(ctl):
    return group_index(ctl.actor.template, ctl.actor.layout)[1]


def router_mask(ctl):
    names = group_names(ctl)
    return torch.tensor([names[g] == "router" for g in ctl.actor_opt.group_of.tolist()])


def batch(ctl, sched, obs):
    _, _, routing = ctl.actor.act(obs, sched.policy_temperature, [torch.Generator().manual_seed(1)])
    return routing


def extra(ctl, obs, routing):
    _, _, _, mean, log_std, chosen = ctl.actor.evaluate(obs, torch.zeros(*obs.shape[:2], 2), routing)
    return ctl.extra_loss({"obs": obs, "tau": routing.temperature, "noise": routing.noise, "experts": chosen,
                           "mean": mean, "log_std": log_std})


def train_step(ctl, sched, n=32, seed=0, zero_grad_in_place=False):
    """One trainer-like step of member 0 (PPO stand-in loss, KL anchor, router freeze); returns counts."""
    g = torch.Generator().manual_seed(seed)
    obs, state, target = torch.randn(1, n, OBS, generator=g), torch.randn(1, n, STATE, generator=g), torch.randn(1, n, 2, generator=g)
    actor, critic = ctl.actor, ctl.critic
    _, _, routing = actor.act(obs, sched.policy_temperature, [g])
    logp, ent, lb, mean, log_std, chosen = actor.evaluate(obs, target, routing)
    value, c_lb, _ = critic(state, sched.value_temperature)
    loss = -logp.mean(1) - sched.ent_coef * ent + actor.lb_coef * lb + value.pow(2).mean(1) + critic.lb_coef * c_lb
    kl = ctl.extra_loss({"obs": obs, "tau": None if routing is None else routing.temperature,
                         "noise": None if routing is None else routing.noise, "experts": chosen,
                         "mean": mean, "log_std": log_std})
    if kl is not None:
        loss = loss + kl
    loss.sum().backward()
    frozen = None
    if bool(sched.router_frozen[0]):  # as the trainer: the router group masked in the step, its gradient zeroed
        frozen = torch.tensor([[name == "router" for name in group_names(ctl)]])
        actor.flat.grad.masked_fill_(router_mask(ctl), 0.0)
    ctl.actor_opt.step(sched.lr_actor, ONE, frozen)
    ctl.critic_opt.step(sched.lr_critic, ONE)
    ctl.after_minibatch(ONE)
    if chosen is None or not (actor.gated and actor.k < actor.n_experts):
        return None
    return F.one_hot(chosen.reshape(1, -1), actor.n_experts).sum(1).float()


def row(ctl):
    return ctl.actor.flat[0].detach().clone()


def span(ctl, name):
    return slice(*ctl.actor.layout.span(name))


# --- config ----------------------------------------------------------------------------------------

@pytest.mark.parametrize(
    "field, value",
    [
        ("kl_coef", -0.1),
        ("kl_decay", 1.5),
        ("noise_gamma", -1.0),
        ("noise_epochs", 2.5),
        ("lr_drop_factor", 1.2),
        ("conservative_clip", 0.0),
        ("tau_min", 0.0),
        ("tau_max", 0.5),
        ("temperature_routers", "critic"),
        ("noise_injection", 1),
        ("log_std_value", float("nan")),
    ],
)
def test_invalid_config_names_field(field, value):
    with pytest.raises(ValueError, match=rf"PhaseControllerConfig\.{field} must be .*got"):
        PhaseControllerConfig(**{field: value})


@pytest.mark.parametrize("field, value", [("lr", 0.0), ("target_kl", -1.0), ("phase_length", 0), ("ent_anneal_portion", 0.0)])
def test_invalid_base_names_field(field, value):
    with pytest.raises(ValueError, match=rf"RunSettings\.{field} must be"):
        RunSettings(**{field: value})


def test_without_switches_one_mechanism_off():
    cfg = PhaseControllerConfig()
    for m in MECHANISMS:
        off = cfg.without(m)
        assert getattr(off, m) is False
        assert all(getattr(off, o) for o in MECHANISMS if o != m)
    with pytest.raises(ValueError, match="mechanism"):
        cfg.without("coffee")


def test_param_group_names_and_the_registry():
    names = group_index(make_actor("mlp", OBS), PopulationActor([make_actor("mlp", OBS)]).layout)[1]
    assert names == ["experts", "head", "log_std"]  # the MLP has no router group
    assert group_names(setup()) == ["router", "experts", "head", "log_std"]
    assert plasticity_method("phase_controller") is PhaseController


# --- schedules -------------------------------------------------------------------------------------

def test_lr_drop_and_warmup_values():
    cfg = PhaseControllerConfig()
    assert lr_multiplier(0, cfg) == pytest.approx(0.3)
    assert lr_multiplier(50, cfg) == pytest.approx(0.3 + 0.7 * 0.25)
    assert lr_multiplier(100, cfg) == pytest.approx(0.65)
    assert lr_multiplier(200, cfg) == pytest.approx(1.0)
    assert lr_multiplier(1000, cfg) == pytest.approx(1.0)
    ctl = setup()
    ctl.on_switch(1000)
    for since, mult in [(0, 0.3), (100, 0.65), (150, 0.825), (200, 1.0), (500, 1.0)]:
        s = ctl.begin_iteration(1000 + since)
        assert float(s.lr_actor[0]) == pytest.approx(BASE.lr * mult)
        assert s.members[0].lr["router"] == (0.0 if since < 30 else pytest.approx(BASE.lr * mult))
        assert float(s.lr_critic[0]) == BASE.lr  # the critic keeps learning at the base rate


def test_kl_anchor_decays_and_releases():
    cfg = PhaseControllerConfig()
    for n in (0, 1, 10, 100, 304):
        assert kl_anchor_coef(n, cfg) == pytest.approx(0.1 * 0.985**n)
    assert kl_anchor_coef(305, cfg) == 0.0  # 0.1 * 0.985^305 < 1e-3
    ctl = setup()
    obs = torch.randn(1, 4, OBS)
    assert float(ctl.begin_iteration(0).kl_coef[0]) == 0.0 and not ctl.has_reference[0]  # nothing before a switch
    assert extra(ctl, obs, batch(ctl, ctl.begin_iteration(1), obs)) is None
    ctl.on_switch(1000)
    prev = None
    for t in range(1000, 1010):
        k = float(ctl.begin_iteration(t).kl_coef[0])
        if prev is not None:
            assert k == pytest.approx(prev * 0.985, rel=1e-6)
        prev = k
    assert ctl.has_reference[0]
    assert float(ctl.begin_iteration(1304).kl_coef[0]) > 0 and ctl.has_reference[0]
    s = ctl.begin_iteration(1305)
    assert float(s.kl_coef[0]) == 0.0 and not ctl.has_reference[0]
    assert extra(ctl, obs, batch(ctl, s, obs)) is None  # released: nothing added


def test_kl_penalty_is_zero_right_after_snapshot_and_grows_with_change():
    cfg = PhaseControllerConfig(noise_injection=False, log_std_reset=False)
    ctl = setup(cfg=cfg, net=NetConfig(routing_noise="learned"))  # noisy gating: the routing is replayed
    ctl.on_switch(1000)
    s = ctl.begin_iteration(1000)
    obs = torch.randn(1, 16, OBS)
    routing = batch(ctl, s, obs)
    assert float(extra(ctl, obs, routing).detach()[0]) == pytest.approx(0.0, abs=1e-10)
    with torch.no_grad():
        ctl.actor.flat[0, span(ctl, "log_std")] += 0.5
    pen = extra(ctl, obs, routing)
    # KL(N(m, s1) || N(m, s0)) per dim = log(s0/s1) + s1^2/(2 s0^2) - 1/2 with s1 = e^0.5 s0
    per_dim = -0.5 + math.exp(1.0) / 2 - 0.5
    assert float(pen.detach()[0]) == pytest.approx(0.1 * 2 * per_dim, rel=1e-5)
    (g,) = torch.autograd.grad(pen.sum(), ctl.actor.flat)
    assert (g[0, span(ctl, "log_std")] != 0).all()
    assert not ctl.reference.requires_grad  # the reference gets no gradient


def test_entropy_reset_and_reanneal():
    cfg = PhaseControllerConfig()
    # baselines: 0.01 -> 0.003 over 30 % of 3000 = 900 iterations
    assert entropy_coef(450, 450, BASE, None) == pytest.approx(0.0065)
    assert entropy_coef(2000, 0, BASE, None) == pytest.approx(0.003)
    # PE-MAMoE: over 30 % of the 1000-iteration phase
    assert entropy_coef(1000, 0, BASE, cfg) == pytest.approx(0.01)
    assert entropy_coef(1150, 150, BASE, cfg) == pytest.approx(0.0065)
    assert entropy_coef(1400, 400, BASE, cfg) == pytest.approx(0.003)
    ctl = setup()

    def ent(c, t):
        return c.begin_iteration(t).members[0].ent_coef

    # before the first switch the controller is inert: the baselines' run-long schedule
    assert ent(ctl, 150) == pytest.approx(entropy_coef(150, 150, BASE, None))
    assert ent(ctl, 450) == pytest.approx(0.0065)
    assert ent(ctl, 999) == pytest.approx(0.003)
    ctl.on_switch(1000)
    assert ent(ctl, 1000) == pytest.approx(0.01)
    assert ent(ctl, 1150) == pytest.approx(0.0065)
    # switched off: the run-long baseline schedule
    off = setup(cfg=cfg.without("entropy_reset"))
    off.on_switch(1000)
    assert ent(off, 1000) == pytest.approx(0.003)


def test_temperature_curves_run_in_opposite_directions():
    cfg = PhaseControllerConfig()
    d = np.arange(0, 400)
    hot, cold = temperature_text(d, cfg), temperature_formula(d, cfg)
    assert hot[0] == pytest.approx(1 + 20 / 21) and cold[0] == pytest.approx(1 + 1 / 21)
    assert np.all(np.diff(hot) <= 0) and np.all(np.diff(cold) >= 0)
    assert hot[-1] == pytest.approx(1.0, abs=1e-6) and cold[-1] == pytest.approx(2.0, abs=1e-6)
    np.testing.assert_allclose(hot + cold, 3.0)  # mirror images
    assert temperature_text(math.log(20) / 0.05, cfg) == pytest.approx(1.5)
    ctl = setup()
    ctl.on_switch(1000)
    s = ctl.begin_iteration(1000)
    assert float(s.policy_temperature[0]) == float(s.value_temperature[0]) == pytest.approx(1 + 20 / 21)


def test_conservative_window_and_freeze_window_lengths():
    ctl = setup()
    ctl.on_switch(1000)
    s = ctl.begin_iteration(1079).members[0]
    assert (s.clip_coef, s.target_kl, s.conservative) == (0.1, 0.05, True)
    s = ctl.begin_iteration(1080).members[0]
    assert (s.clip_coef, s.target_kl, s.conservative) == (0.15, 0.1, False)
    assert bool(ctl.begin_iteration(1080).router_frozen[0]) is False
    ctl2 = setup()
    ctl2.on_switch(1000)
    assert bool(ctl2.begin_iteration(1029).router_frozen[0]) and not bool(ctl2.begin_iteration(1030).router_frozen[0])


def test_disabled_controller_reports_base_schedule_and_does_nothing():
    ctl = setup(enabled=False)
    for t in range(3):
        train_step(ctl, ctl.begin_iteration(t), seed=t)
    before, moments, steps = row(ctl), ctl.actor_opt.exp_avg.clone(), ctl.actor_opt.steps.clone()
    ctl.on_switch(1000)
    sched = ctl.begin_iteration(1000)
    assert ctl.after_epoch(None, ONE) == [0]
    assert torch.equal(before, row(ctl))
    assert torch.equal(moments, ctl.actor_opt.exp_avg) and torch.equal(steps, ctl.actor_opt.steps)
    s = sched.members[0]
    assert s.kl_coef == 0 and s.clip_coef == 0.15 and s.target_kl == 0.1 and not s.router_frozen
    assert s.policy_temperature == s.value_temperature == 1.0
    assert float(sched.lr_actor[0]) == float(sched.lr_critic[0]) == BASE.lr
    assert s.ent_coef == pytest.approx(entropy_coef(1000, 0, BASE, None))
    assert ctl.state_dict(0) == {}


SCHEDULE_FIELDS = ("lr_actor", "lr_critic", "router_frozen", "clip_coef", "target_kl", "ent_coef", "kl_coef",
                   "policy_temperature", "value_temperature")


def test_all_mechanisms_off_equals_disabled():
    off = PhaseControllerConfig(**{m: False for m in MECHANISMS})
    a, b = setup(cfg=off), setup(enabled=False)
    for ctl in (a, b):
        ctl.on_switch(1000)
    assert torch.equal(a.actor.flat, b.actor.flat)
    for t in (1000, 1010, 1100, 1500):
        sa, sb = a.begin_iteration(t), b.begin_iteration(t)
        assert all(torch.equal(getattr(sa, f), getattr(sb, f)) for f in SCHEDULE_FIELDS), t


# --- optimizer state and router freeze -------------------------------------------------------------

def test_adam_reset_clears_moments_and_step_counts():
    ctl = setup()
    for t in range(3):
        train_step(ctl, ctl.begin_iteration(t), seed=t)
    opt, c_opt = ctl.actor_opt, ctl.critic_opt
    assert (opt.exp_avg != 0).any() and (opt.steps == 3).all()
    ctl.on_switch(1000)
    assert (opt.exp_avg == 0).all() and (opt.exp_avg_sq == 0).all() and (opt.steps == 0).all()
    assert (c_opt.steps == 3).all() and (c_opt.exp_avg != 0).any()  # the critic keeps its moments
    train_step(ctl, ctl.begin_iteration(1000))
    assert opt.steps[0, [group_names(ctl).index(n) for n in ("experts", "head", "log_std")]].tolist() == [1, 1, 1]
    # switched off: moments survive the switch
    ctl = setup(cfg=PhaseControllerConfig(adam_reset=False))
    train_step(ctl, ctl.begin_iteration(0))
    ctl.on_switch(1000)
    assert (ctl.actor_opt.exp_avg != 0).any() and (ctl.actor_opt.steps == 1).all()


@pytest.mark.parametrize("adam_reset, weight_decay", [(True, 1e-4), (False, 0.1)])
def test_router_is_bit_identical_during_freeze_and_moves_after(adam_reset, weight_decay):
    # without the Adam reset and with strong weight decay, stale momentum and the decay would move a
    # router whose gradient were merely zero
    ctl = setup(cfg=PhaseControllerConfig(router_freeze_iters=4, adam_reset=adam_reset), weight_decay=weight_decay)
    for t in range(3):  # build up Adam momentum on the router first
        train_step(ctl, ctl.begin_iteration(t), seed=t)
    ctl.on_switch(1000)
    mask, trunk = router_mask(ctl), torch.cat(ctl.expert_indices())
    router, experts = row(ctl)[mask], row(ctl)[trunk]
    for t in range(1000, 1004):
        s = ctl.begin_iteration(t)
        assert bool(s.router_frozen[0]) and s.members[0].lr["router"] == 0.0
        train_step(ctl, s, seed=t)
        assert torch.equal(row(ctl)[mask], router)
    assert not torch.equal(row(ctl)[trunk], experts)  # the rest did train
    assert ctl.actor_opt.steps[0, group_names(ctl).index("router")] == (0 if adam_reset else 3)
    s = ctl.begin_iteration(1004)
    assert not bool(s.router_frozen[0])
    for t in range(1004, 1007):
        train_step(ctl, ctl.begin_iteration(t), seed=t)
    assert not torch.equal(row(ctl)[mask], router)


# --- noise injection -------------------------------------------------------------------------------

def test_noise_touches_only_selected_expert_trunks():
    ctl = setup()
    idx = ctl.expert_indices()
    before = row(ctl)
    assert ctl.perturb_experts(0, [0.0, 0.01, 0.0], torch.Generator().manual_seed(0)) == 1
    d = row(ctl) - before
    assert (d[idx[1]] != 0).all()
    untouched = torch.ones_like(d, dtype=torch.bool)
    untouched[idx[1]] = False
    assert (d[untouched] == 0).all()  # other experts, router, noise gate, head, log_std
    # the flat indices are the actor's own trunk slices
    single = ctl.actor.member(0)
    assert sum(p.numel() for p in expert_parameters(single, 1)) == idx[1].numel()


def test_noise_energy_matches_gamma_squared_times_count():
    torch.manual_seed(0)
    ctl = population_method("phase_controller", [MemberConfig()], [make_actor("pemamoe", 40)])
    gamma = 0.005
    idx = ctl.expert_indices()
    per_expert = 40 * 32 + 32 + 32 * 32 + 32
    assert [i.numel() for i in idx] == [per_expert] * 3
    before = row(ctl)
    ctl.perturb_experts(0, [gamma, 0.0, gamma], torch.Generator().manual_seed(3))
    n = 2 * per_expert
    energy = float((row(ctl) - before).double().pow(2).sum())
    # chi-square with n dof: relative std sqrt(2 / n) ~ 2.9 %; allow 5 sigma
    assert energy == pytest.approx(gamma**2 * n, rel=5 * math.sqrt(2 / n))


def test_noise_on_mlp_trunk():
    actor = make_actor("mlp", OBS)
    assert len(expert_parameters(actor, 0)) == 4
    with pytest.raises(ValueError):
        expert_parameters(actor, 1)
    ctl = setup("mlp")
    assert len(ctl.expert_indices()) == 1
    before = row(ctl)
    ctl.perturb_experts(0, [0.01], torch.Generator().manual_seed(0))
    d = row(ctl) - before
    assert (d[span(ctl, "head.weight")] == 0).all() and (d[span(ctl, "fc1.weight")] != 0).all()


def test_noise_window_at_switch_then_used_experts_for_n_epochs():
    cfg = PhaseControllerConfig(noise_epochs=3)
    ctl = setup(cfg=cfg)
    idx = ctl.expert_indices()
    before = row(ctl)
    ctl.on_switch(1000)
    assert ctl.last_noise[0] == [0.005] * 3  # every expert, full gamma, at the switch
    assert all((row(ctl)[i] != before[i]).any() for i in idx)
    ctl.begin_iteration(1000)
    before = row(ctl)
    assert ctl.after_epoch(torch.tensor([[1.0, 0.0, 2.0]]), ONE) == [2]
    assert ctl.last_noise[0] == pytest.approx([0.005 / 3, 0.0, 0.01 / 3])  # weighted by each expert's share
    assert torch.equal(row(ctl)[idx[1]], before[idx[1]]) and not torch.equal(row(ctl)[idx[2]], before[idx[2]])
    before = row(ctl)
    assert ctl.after_epoch(torch.tensor([[0.0, 4.0, 0.0]]), torch.zeros(1, dtype=torch.bool)) == [0]  # no step: no noise
    assert torch.equal(row(ctl), before) and ctl.noise_left[0] == 2  # ... and the window is not used up
    assert ctl.after_epoch(torch.tensor([[0.0, 4.0, 0.0]]), ONE) == [1]
    assert ctl.after_epoch(None, ONE) == [3]  # an ungated reading: every expert, full gamma
    before = row(ctl)
    assert ctl.after_epoch(None, ONE) == [0]  # window of 3 epochs is over
    assert torch.equal(row(ctl), before) and ctl.last_noise[0] is None


def test_noise_lr_factor_scales_std():
    cfg = PhaseControllerConfig(noise_lr_factor=True)
    assert setup(cfg=cfg)._noise_std(0, 0) == pytest.approx(0.005 * 0.3 * BASE.lr)
    assert setup()._noise_std(0, 0) == 0.005


# --- each switch removes exactly its mechanism -----------------------------------------------------

def switch_effects(cfg):
    ctl = setup(cfg=cfg)
    for t in range(2):
        train_step(ctl, ctl.begin_iteration(t), seed=t)
    with torch.no_grad():
        ctl.actor.flat[0, span(ctl, "log_std")] = -2.0
    before, had_moments = row(ctl), bool((ctl.actor_opt.exp_avg != 0).any())
    ctl.on_switch(1000)
    sched = ctl.begin_iteration(1000)
    s = sched.members[0]
    d = row(ctl) - before
    trunk = torch.cat(ctl.expert_indices())
    return {
        "kl_anchor": s.kl_coef > 0 and ctl.has_reference[0],
        "adam_reset": bool((ctl.actor_opt.exp_avg == 0).all()) and had_moments,
        "noise_injection": bool((d[trunk] != 0).any()),
        "log_std_reset": bool((d[span(ctl, "log_std")] != 0).all()),
        "entropy_reset": s.ent_coef == pytest.approx(0.01),
        "lr_drop": float(sched.lr_actor[0]) == pytest.approx(0.3 * BASE.lr),
        "conservative_window": s.conservative and s.clip_coef == 0.1,
        "router_freeze": s.router_frozen and s.lr["router"] == 0.0,
        "temperature_schedule": s.policy_temperature > 1.9,
    }


def test_each_switch_disables_exactly_its_mechanism():
    full = switch_effects(PhaseControllerConfig())
    assert all(full.values()), full
    for m in MECHANISMS:
        eff = switch_effects(PhaseControllerConfig().without(m))
        assert eff[m] is False, m
        assert all(v for k, v in eff.items() if k != m), (m, eff)


# --- checkpointing ---------------------------------------------------------------------------------

def test_state_dict_round_trip_reproduces_settings_and_noise():
    ctl = setup()
    for t in range(2):
        train_step(ctl, ctl.begin_iteration(t), seed=t)
    ctl.on_switch(1000)
    s = ctl.begin_iteration(1000)
    counts = train_step(ctl, s)
    ctl.after_epoch(counts, ONE)
    ctl.after_epoch(torch.tensor([[0.0, 3.0, 1.0]]), ONE)
    state = copy.deepcopy(ctl.state_dict(0))
    flat, opt_state = row(ctl), ctl.actor_opt.member_state(0)

    # a fresh process: new networks (different init), new optimizer, then load everything
    ctl2 = setup(seed=7)
    ctl2.load_state_dict(0, state)
    with torch.no_grad():
        ctl2.actor.flat[0] = flat
    ctl2.actor_opt.load_member_state(0, opt_state)
    a, b = ctl.begin_iteration(1001), ctl2.begin_iteration(1001)
    assert a.members == b.members and all(torch.equal(getattr(a, f), getattr(b, f)) for f in SCHEDULE_FIELDS)
    assert ctl2.noise_left[0] == ctl.noise_left[0] == 28
    c = torch.tensor([[2.0, 0.0, 2.0]])
    assert ctl.after_epoch(c, ONE) == ctl2.after_epoch(c, ONE)
    assert torch.equal(row(ctl), row(ctl2))
    obs = torch.randn(1, 8, OBS)
    routing = batch(ctl, a, obs)
    assert torch.equal(extra(ctl, obs, routing), extra(ctl2, obs, routing))
    with pytest.raises(ValueError, match="different config"):
        setup(cfg=PhaseControllerConfig(noise_gamma=0.01)).load_state_dict(0, state)
    with pytest.raises(ValueError, match="controller on"):
        setup(enabled=False).load_state_dict(0, state)
