"""Phase controller (notebook 06): every mechanism of Algorithm 1, each behind its own switch."""

import copy
import math

import numpy as np
import pytest
import torch

from pemamoe.nets import NetConfig, make_actor, make_critic
from pemamoe.phase_controller import (
    MECHANISMS,
    BaseSchedule,
    PhaseController,
    PhaseControllerConfig,
    build_param_groups,
    entropy_coef,
    expert_parameters,
    inject_expert_noise,
    kl_anchor_coef,
    lr_multiplier,
    temperature_formula,
    temperature_text,
)

OBS, STATE = 10, 14
BASE = BaseSchedule(total_iterations=3000, phase_length=1000)


def setup(kind="pemamoe", cfg=None, enabled=True, base=BASE, seed=0, weight_decay=1e-4, net=None):
    torch.manual_seed(seed)
    actor, critic = make_actor(kind, OBS, 2, net), make_critic(kind, STATE, net)
    opt = torch.optim.AdamW(build_param_groups(actor, critic, base.lr), lr=base.lr, weight_decay=weight_decay)
    ctl = PhaseController(cfg or PhaseControllerConfig(), actor, opt, base, enabled=enabled, seed=seed)
    return actor, critic, opt, ctl


def train_step(actor, critic, opt, ctl, settings, n=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    obs, state = torch.randn(n, OBS, generator=g), torch.randn(n, STATE, generator=g)
    action, _, routing = actor.act(obs, temperature=settings.policy_temperature)
    target = torch.randn(n, 2, generator=g)
    logp, ent, aux = actor.evaluate(obs, target, routing)
    value, vaux = critic(state, settings.value_temperature)
    loss = -logp.mean() - settings.ent_coef * ent.mean() + aux["aux_loss"] + value.pow(2).mean() + vaux["aux_loss"]
    loss = loss + ctl.kl_penalty(obs, routing)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return routing


def params(module):
    return {n: p.detach().clone() for n, p in module.named_parameters()}


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
    with pytest.raises(ValueError, match=rf"BaseSchedule\.{field} must be"):
        BaseSchedule(**{field: value})


def test_without_switches_one_mechanism_off():
    cfg = PhaseControllerConfig()
    for m in MECHANISMS:
        off = cfg.without(m)
        assert getattr(off, m) is False
        assert all(getattr(off, o) for o in MECHANISMS if o != m)
    with pytest.raises(ValueError, match="mechanism"):
        cfg.without("coffee")


def test_param_groups_need_names():
    actor = make_actor("pemamoe", OBS)
    with pytest.raises(ValueError, match="name"):
        PhaseController(PhaseControllerConfig(), actor, torch.optim.Adam(actor.parameters()))
    names = [g["name"] for g in build_param_groups(make_actor("mlp", OBS), make_critic("mlp", STATE))]
    assert names == ["experts", "head", "log_std", "critic"]  # the MLP has no router group


# --- schedules -------------------------------------------------------------------------------------

def test_lr_drop_and_warmup_values():
    cfg = PhaseControllerConfig()
    assert lr_multiplier(0, cfg) == pytest.approx(0.3)
    assert lr_multiplier(50, cfg) == pytest.approx(0.3 + 0.7 * 0.25)
    assert lr_multiplier(100, cfg) == pytest.approx(0.65)
    assert lr_multiplier(200, cfg) == pytest.approx(1.0)
    assert lr_multiplier(1000, cfg) == pytest.approx(1.0)
    actor, critic, opt, ctl = setup()
    ctl.on_switch(1000)
    for since, mult in [(0, 0.3), (100, 0.65), (150, 0.825), (200, 1.0), (500, 1.0)]:
        s = ctl.begin_iteration(1000 + since)
        for g in opt.param_groups:
            expected = 0.0 if (g["name"] == "router" and since < 30) else BASE.lr * mult
            assert g["lr"] == pytest.approx(expected) and s.lr[g["name"]] == g["lr"]


def test_kl_anchor_decays_and_releases():
    cfg = PhaseControllerConfig()
    for n in (0, 1, 10, 100, 304):
        assert kl_anchor_coef(n, cfg) == pytest.approx(0.1 * 0.985**n)
    assert kl_anchor_coef(305, cfg) == 0.0  # 0.1 * 0.985^305 < 1e-3
    actor, critic, opt, ctl = setup()
    assert ctl.begin_iteration(0).kl_coef == 0.0 and ctl.reference is None  # nothing before a switch
    ctl.on_switch(1000)
    prev = None
    for t in range(1000, 1010):
        k = ctl.begin_iteration(t).kl_coef
        if prev is not None:
            assert k == pytest.approx(prev * 0.985)
        prev = k
    assert ctl.reference is not None
    assert ctl.begin_iteration(1304).kl_coef > 0 and ctl.reference is not None
    assert ctl.begin_iteration(1305).kl_coef == 0.0 and ctl.reference is None
    assert float(ctl.kl_penalty(torch.randn(4, OBS))) == 0.0


def test_kl_penalty_is_zero_right_after_snapshot_and_grows_with_change():
    cfg = PhaseControllerConfig(noise_injection=False, log_std_reset=False)
    actor, critic, opt, ctl = setup(cfg=cfg, net=NetConfig(routing_noise="learned"))  # noisy gating
    ctl.on_switch(1000)
    ctl.begin_iteration(1000)
    obs = torch.randn(16, OBS)
    _, _, routing = actor.act(obs)
    assert float(ctl.kl_penalty(obs, routing).detach()) == pytest.approx(0.0, abs=1e-12)
    with torch.no_grad():
        actor.log_std.add_(0.5)
    pen = ctl.kl_penalty(obs, routing)
    # KL(N(m, s1) || N(m, s0)) per dim = log(s0/s1) + s1^2/(2 s0^2) - 1/2 with s1 = e^0.5 s0
    per_dim = -0.5 + math.exp(1.0) / 2 - 0.5
    assert float(pen.detach()) == pytest.approx(0.1 * 2 * per_dim, rel=1e-5)
    pen.backward()
    assert actor.log_std.grad is not None
    with pytest.raises(ValueError, match="routing"):
        ctl.kl_penalty(obs)  # noisy gating: the reference must replay the same routing
    assert all(p.grad is None for p in ctl.reference.parameters())


def test_entropy_reset_and_reanneal():
    cfg = PhaseControllerConfig()
    # baselines: 0.01 -> 0.003 over 30 % of 3000 = 900 iterations
    assert entropy_coef(450, 450, BASE, None) == pytest.approx(0.0065)
    assert entropy_coef(2000, 0, BASE, None) == pytest.approx(0.003)
    # PE-MAMoE: over 30 % of the 1000-iteration phase
    assert entropy_coef(1000, 0, BASE, cfg) == pytest.approx(0.01)
    assert entropy_coef(1150, 150, BASE, cfg) == pytest.approx(0.0065)
    assert entropy_coef(1400, 400, BASE, cfg) == pytest.approx(0.003)
    actor, critic, opt, ctl = setup()
    # before the first switch the controller is inert: the baselines' run-long schedule
    assert ctl.begin_iteration(150).ent_coef == pytest.approx(entropy_coef(150, 150, BASE, None))
    assert ctl.begin_iteration(450).ent_coef == pytest.approx(0.0065)
    assert ctl.begin_iteration(999).ent_coef == pytest.approx(0.003)
    ctl.on_switch(1000)
    assert ctl.begin_iteration(1000).ent_coef == pytest.approx(0.01)
    assert ctl.begin_iteration(1150).ent_coef == pytest.approx(0.0065)
    # switched off: the run-long baseline schedule
    _, _, _, off = setup(cfg=cfg.without("entropy_reset"))
    off.on_switch(1000)
    assert off.begin_iteration(1000).ent_coef == pytest.approx(0.003)


def test_temperature_curves_run_in_opposite_directions():
    cfg = PhaseControllerConfig()
    d = np.arange(0, 400)
    hot, cold = temperature_text(d, cfg), temperature_formula(d, cfg)
    assert hot[0] == pytest.approx(1 + 20 / 21) and cold[0] == pytest.approx(1 + 1 / 21)
    assert np.all(np.diff(hot) <= 0) and np.all(np.diff(cold) >= 0)
    assert hot[-1] == pytest.approx(1.0, abs=1e-6) and cold[-1] == pytest.approx(2.0, abs=1e-6)
    np.testing.assert_allclose(hot + cold, 3.0)  # mirror images
    assert temperature_text(math.log(20) / 0.05, cfg) == pytest.approx(1.5)


def test_conservative_window_and_freeze_window_lengths():
    actor, critic, opt, ctl = setup()
    ctl.on_switch(1000)
    s = ctl.begin_iteration(1079)
    assert (s.clip_coef, s.target_kl, s.conservative) == (0.1, 0.05, True)
    s = ctl.begin_iteration(1080)
    assert (s.clip_coef, s.target_kl, s.conservative) == (0.15, 0.1, False)
    assert ctl.begin_iteration(1029).router_frozen and not ctl.begin_iteration(1030).router_frozen


def test_disabled_controller_reports_base_schedule_and_does_nothing():
    actor, critic, opt, ctl = setup(enabled=False)
    for t in range(3):
        train_step(actor, critic, opt, ctl, ctl.begin_iteration(t))
    before, n_state = params(actor), len(opt.state)
    ctl.on_switch(1000)
    s = ctl.begin_iteration(1000)
    assert ctl.after_epoch(None) == []
    after = params(actor)
    assert all(torch.equal(before[n], after[n]) for n in before)
    assert len(opt.state) == n_state
    assert s.kl_coef == 0 and s.clip_coef == 0.15 and s.target_kl == 0.1 and not s.router_frozen
    assert s.policy_temperature == s.value_temperature == 1.0
    assert set(s.lr.values()) == {BASE.lr}
    assert s.ent_coef == pytest.approx(entropy_coef(1000, 0, BASE, None))


def test_all_mechanisms_off_equals_disabled():
    off = PhaseControllerConfig(**{m: False for m in MECHANISMS})
    _, _, _, a = setup(cfg=off)
    _, _, _, b = setup(enabled=False)
    for ctl in (a, b):
        ctl.on_switch(1000)
    for t in (1000, 1010, 1100, 1500):
        assert a.begin_iteration(t) == b.begin_iteration(t)


# --- optimizer state and router freeze -------------------------------------------------------------

def test_adam_reset_clears_moments_and_step_counts():
    actor, critic, opt, ctl = setup()
    groups_before = [(g["name"], len(g["params"])) for g in opt.param_groups]
    for t in range(3):
        train_step(actor, critic, opt, ctl, ctl.begin_iteration(t), seed=t)
    assert len(opt.state) > 0 and all(float(st["step"]) == 3 for st in opt.state.values())
    ctl.on_switch(1000)
    assert len(opt.state) == 0
    assert [(g["name"], len(g["params"])) for g in opt.param_groups] == groups_before
    train_step(actor, critic, opt, ctl, ctl.begin_iteration(1000))
    steps = {float(st["step"]) for st in opt.state.values()}
    assert steps == {1.0}
    # switched off: moments survive the switch
    actor, critic, opt, ctl = setup(cfg=PhaseControllerConfig(adam_reset=False))
    train_step(actor, critic, opt, ctl, ctl.begin_iteration(0))
    ctl.on_switch(1000)
    assert len(opt.state) > 0


@pytest.mark.parametrize("optim", ["adam", "adamw"])
def test_router_is_bit_identical_during_freeze_and_moves_after(optim):
    torch.manual_seed(0)
    actor, critic = make_actor("pemamoe", OBS), make_critic("pemamoe", STATE)
    groups = build_param_groups(actor, critic, BASE.lr)
    opt = (torch.optim.Adam(groups, lr=BASE.lr, weight_decay=1e-4) if optim == "adam"
           else torch.optim.AdamW(groups, lr=BASE.lr, weight_decay=1e-2))
    cfg = PhaseControllerConfig(router_freeze_iters=4)
    ctl = PhaseController(cfg, actor, opt, BASE)
    for t in range(3):  # build up Adam momentum on the router first
        train_step(actor, critic, opt, ctl, ctl.begin_iteration(t), seed=t)
    ctl.on_switch(1000)
    router = [p.detach().clone() for p in actor.param_groups()["router"]]
    experts = actor.gate.experts.w1.detach().clone()
    for t in range(1000, 1004):
        s = ctl.begin_iteration(t)
        assert s.router_frozen
        train_step(actor, critic, opt, ctl, s, seed=t)
        assert all(torch.equal(a, b) for a, b in zip(router, actor.param_groups()["router"]))
    assert not torch.equal(experts, actor.gate.experts.w1)  # the rest did train
    s = ctl.begin_iteration(1004)
    assert not s.router_frozen and all(p.requires_grad for p in actor.param_groups()["router"])
    for t in range(1004, 1007):
        train_step(actor, critic, opt, ctl, ctl.begin_iteration(t), seed=t)
    assert not torch.equal(router[0], actor.param_groups()["router"][0])


def test_router_freeze_survives_stale_momentum_and_in_place_zero_grad():
    # no Adam reset, gradients zeroed in place (not set to None): momentum and weight decay would move
    # the router if only its gradient were zero
    torch.manual_seed(1)
    actor, critic = make_actor("pemamoe", OBS), make_critic("pemamoe", STATE)
    opt = torch.optim.AdamW(build_param_groups(actor, critic, BASE.lr), lr=BASE.lr, weight_decay=0.1)
    ctl = PhaseController(PhaseControllerConfig(adam_reset=False), actor, opt, BASE)
    for t in range(3):
        train_step(actor, critic, opt, ctl, ctl.begin_iteration(t), seed=t)
    ctl.on_switch(1000)
    router = [p.detach().clone() for p in actor.param_groups()["router"]]
    for t in range(1000, 1005):
        s = ctl.begin_iteration(t)
        obs = torch.randn(16, OBS)
        action, _, routing = actor.act(obs, temperature=s.policy_temperature)
        logp, ent, aux = actor.evaluate(obs, torch.randn(16, 2), routing)
        opt.zero_grad(set_to_none=False)
        (-logp.mean() + aux["aux_loss"]).backward()
        opt.step()
    assert all(torch.equal(a, b) for a, b in zip(router, actor.param_groups()["router"]))


# --- noise injection -------------------------------------------------------------------------------

def test_noise_touches_only_selected_expert_trunks():
    actor = make_actor("pemamoe", OBS)
    before = params(actor)
    g = torch.Generator().manual_seed(0)
    inject_expert_noise(actor, [1], 0.01, g)
    after = params(actor)
    for name in before:
        d = after[name] - before[name]
        if name.startswith("gate.experts."):
            assert torch.equal(d[0], torch.zeros_like(d[0])) and torch.equal(d[2], torch.zeros_like(d[2]))
            assert (d[1] != 0).all()
        else:  # router, noise gate, head, log_std
            assert torch.equal(d, torch.zeros_like(d)), name


def test_noise_energy_matches_gamma_squared_times_count():
    actor = make_actor("pemamoe", 40)
    gamma = 0.005
    before = params(actor)
    n = inject_expert_noise(actor, [0, 2], gamma, torch.Generator().manual_seed(3))
    per_expert = 40 * 32 + 32 + 32 * 32 + 32
    assert n == 2 * per_expert
    after = params(actor)
    energy = sum(float((after[k] - before[k]).double().pow(2).sum()) for k in before)
    # chi-square with n dof: relative std sqrt(2 / n) ~ 2.9 %; allow 5 sigma
    assert energy == pytest.approx(gamma**2 * n, rel=5 * math.sqrt(2 / n))


def test_noise_on_mlp_trunk():
    actor = make_actor("mlp", OBS)
    assert len(expert_parameters(actor, 0)) == 4
    with pytest.raises(ValueError):
        expert_parameters(actor, 1)
    head = actor.head.weight.detach().clone()
    fc1 = actor.fc1.weight.detach().clone()
    inject_expert_noise(actor, [0], 0.01, torch.Generator().manual_seed(0))
    assert torch.equal(head, actor.head.weight) and not torch.equal(fc1, actor.fc1.weight)


def test_noise_window_at_switch_then_selected_experts_for_n_epochs():
    cfg = PhaseControllerConfig(noise_epochs=3)
    actor, critic, opt, ctl = setup(cfg=cfg)
    w = actor.gate.experts.w1.detach().clone()
    ctl.on_switch(1000)
    assert ctl.last_noised == [0, 1, 2]  # every expert at the switch
    assert all(not torch.equal(w[j], actor.gate.experts.w1[j]) for j in range(3))
    ctl.begin_iteration(1000)
    w = actor.gate.experts.w1.detach().clone()
    assert ctl.after_epoch(torch.tensor([[2], [2], [0]])) == [0, 2]
    assert torch.equal(w[1], actor.gate.experts.w1[1]) and not torch.equal(w[2], actor.gate.experts.w1[2])
    assert ctl.after_epoch(torch.tensor([False, True, False])) == [1]
    assert ctl.after_epoch(None) == [0, 1, 2]
    w = actor.gate.experts.w1.detach().clone()
    assert ctl.after_epoch(None) == []  # window of 3 epochs is over
    assert torch.equal(w, actor.gate.experts.w1)


def test_noise_lr_factor_scales_std():
    cfg = PhaseControllerConfig(noise_lr_factor=True)
    _, _, _, ctl = setup(cfg=cfg)
    assert ctl._noise_std(0) == pytest.approx(0.005 * 0.3 * BASE.lr)
    assert setup()[3]._noise_std(0) == 0.005


# --- each switch removes exactly its mechanism -----------------------------------------------------

def switch_effects(cfg):
    actor, critic, opt, ctl = setup(cfg=cfg)
    for t in range(2):
        train_step(actor, critic, opt, ctl, ctl.begin_iteration(t), seed=t)
    with torch.no_grad():
        actor.log_std.fill_(-2.0)
    before, n_state = params(actor), len(opt.state)
    ctl.on_switch(1000)
    s = ctl.begin_iteration(1000)
    after = params(actor)
    moved = {n for n in before if not torch.equal(before[n], after[n])}
    return {
        "kl_anchor": s.kl_coef > 0 and ctl.reference is not None,
        "adam_reset": len(opt.state) == 0 and n_state > 0,
        "noise_injection": any(n.startswith("gate.experts") for n in moved),
        "log_std_reset": "log_std" in moved,
        "entropy_reset": s.ent_coef == pytest.approx(0.01),
        "lr_drop": s.lr["experts"] == pytest.approx(0.3 * BASE.lr),
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
    actor, critic, opt, ctl = setup()
    for t in range(2):
        train_step(actor, critic, opt, ctl, ctl.begin_iteration(t), seed=t)
    ctl.on_switch(1000)
    s = ctl.begin_iteration(1000)
    train_step(actor, critic, opt, ctl, s)
    ctl.after_epoch(None)
    ctl.after_epoch(torch.tensor([1]))
    state = copy.deepcopy(ctl.state_dict())
    actor_state, opt_state = copy.deepcopy(actor.state_dict()), copy.deepcopy(opt.state_dict())

    # a fresh process: new networks (different init), new optimizer, then load everything
    actor2, critic2, opt2, ctl2 = setup(seed=7)
    actor2.load_state_dict(actor_state)
    opt2.load_state_dict(opt_state)
    ctl2.load_state_dict(state)
    assert ctl2.begin_iteration(1001) == ctl.begin_iteration(1001)
    assert ctl2.noise_left == ctl.noise_left == 28
    assert ctl.after_epoch(torch.tensor([0, 2])) == ctl2.after_epoch(torch.tensor([0, 2]))
    assert all(torch.equal(a, b) for a, b in zip(actor.parameters(), actor2.parameters()))
    obs = torch.randn(8, OBS)
    _, _, routing = actor.act(obs)
    assert torch.equal(ctl.kl_penalty(obs, routing), ctl2.kl_penalty(obs, routing))
    with pytest.raises(ValueError, match="different config"):
        setup(cfg=PhaseControllerConfig(noise_gamma=0.01))[3].load_state_dict(state)
