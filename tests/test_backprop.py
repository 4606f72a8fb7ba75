"""The hand-written gradients of appendix 05h (pemamoe/backprop.py) against autograd's on the same
forward pass: every network kind and gate setting, at several population sizes."""

import itertools

import pytest
import torch

from pemamoe.backprop import actor_grads, critic_grads
from pemamoe.nets import (CRITIC_GATINGS, EXPERT_HEADS, NETWORKS, ROUTING_NOISES, TOP1_WEIGHTS, MLPActor, MLPCritic,
                          NetConfig, PopulationActor, PopulationCritic, make_actor, make_critic, register_network)

OBS, STATE, ACT, ROWS = 11, 17, 2, 24


def _close(manual, auto):
    scale = auto.abs().max().clamp(min=1e-6)
    torch.testing.assert_close(manual / scale, auto / scale, rtol=0, atol=2e-6)


def _actor_case(kind, R, cfg, seed=0):
    torch.manual_seed(seed)
    actor = PopulationActor([make_actor(kind, OBS, ACT, cfg) for _ in range(R)])
    with torch.no_grad():  # give every parameter a size that makes its gradient non-trivial
        actor.flat.add_(0.3 * torch.randn_like(actor.flat))
    obs = torch.randn(R, ROWS, OBS)
    gens = [torch.Generator().manual_seed(seed + r) for r in range(R)]
    step = actor.act(obs, torch.full((R,), 0.7), gens)
    return actor, obs, step


def _actor_autograd(actor, obs, step, g_mean, g_log_std):
    flat = actor.flat.detach().requires_grad_(True)
    new = actor.evaluate(obs, step.action, step.routing, flat=flat)
    total = (new.mean * g_mean).sum() + (new.log_std * g_log_std).sum() + actor.lb_coef * new.load_balance.sum()
    return torch.autograd.grad(total, flat, allow_unused=True)[0]


# every (top-k, top-1 weight) reading against every routing noise; the heads, the update's routing
# and the balance loss alternate across them, so that each value meets several of the others
GATE_CASES = [dict(top_k=k, top1_weight=w, routing_noise=noise, expert_heads=EXPERT_HEADS[i % 2],
                   update_routing=("current", "replay")[(i // 2) % 2], load_balance_coef=(0.0, 0.05)[(i // 4) % 2])
              for i, ((k, w), noise) in enumerate(itertools.product(
                  ((1, "straight_through"), (1, "switch"), (1, "paper"), (2, "straight_through")), ROUTING_NOISES))]


@pytest.mark.parametrize("kind", ["mlp", "moe", "smoe"])
@pytest.mark.parametrize("R", [1, 3])
def test_actor_gradients_match_autograd_for_every_gate_setting(kind, R):
    cases = GATE_CASES if kind != "mlp" else [{}]
    for i, case in enumerate(cases):
        cfg = NetConfig(hidden=8, n_experts=3, **case)
        actor, obs, step = _actor_case(kind, R, cfg, seed=i)
        g_mean, g_log_std = torch.randn(R, ROWS, ACT), torch.randn(R, ACT)
        saved = {}
        with torch.no_grad():
            actor.evaluate(obs, step.action, step.routing, saved=saved)
            manual = actor_grads(actor, saved, g_mean, g_log_std)
        auto = _actor_autograd(actor, obs, step, g_mean, g_log_std)
        assert manual.shape == auto.shape
        try:
            _close(manual, auto)
        except AssertionError as err:
            raise AssertionError(f"{kind} R={R} {case}: {err}") from None


def test_the_balance_loss_gradient_matches_autograd():
    for kind, R in (("smoe", 2), ("moe", 1)):
        cfg = NetConfig(hidden=8, n_experts=3, load_balance_coef=0.3)
        actor, obs, step = _actor_case(kind, R, cfg)
        g_mean, g_log_std = torch.randn(R, ROWS, ACT), torch.randn(R, ACT)
        saved = {}
        with torch.no_grad():
            actor.evaluate(obs, step.action, step.routing, saved=saved)
            manual = actor_grads(actor, saved, g_mean, g_log_std)
        flat = actor.flat.detach().requires_grad_(True)
        new = actor.evaluate(obs, step.action, step.routing, flat=flat)
        total = (new.mean * g_mean).sum() + (new.log_std * g_log_std).sum() + actor.lb_coef * new.load_balance.sum()
        _close(manual, torch.autograd.grad(total, flat)[0])


@pytest.mark.parametrize("kind", ["mlp", "moe", "smoe"])
@pytest.mark.parametrize("gating", CRITIC_GATINGS)
@pytest.mark.parametrize("R", [1, 4])
def test_critic_gradients_match_autograd(kind, gating, R):
    cfg = NetConfig(hidden=8, n_experts=3, critic_gating=gating, top_k=2, load_balance_coef=0.1)
    torch.manual_seed(R)
    critic = PopulationCritic([make_critic(kind, STATE, cfg) for _ in range(R)])
    with torch.no_grad():
        critic.flat.add_(0.3 * torch.randn_like(critic.flat))
    state, tau, g_value = torch.randn(R, ROWS, STATE), torch.full((R,), 1.3), torch.randn(R, ROWS)
    saved = {}
    with torch.no_grad():
        critic(state, tau, saved=saved)
        manual = critic_grads(critic, saved, g_value)
    flat = critic.flat.detach().requires_grad_(True)
    value, lb, _ = critic(state, tau, flat=flat)
    auto = torch.autograd.grad((value * g_value).sum() + critic.lb_coef * lb.sum(), flat)[0]
    _close(manual, auto)


def test_a_plugin_kind_without_a_written_backward_is_differentiated_by_autograd():
    class Doubled(MLPActor):  # a subclass: it does not inherit hand_written_backward
        def run_features(self, p, x, tau=None, noise=None, experts=None):
            h, _ = super().run_features(p, x)
            return 2 * h, None

    register_network("doubled_backprop_test", Doubled, MLPCritic)
    try:
        actor, obs, step = _actor_case("doubled_backprop_test", 2, NetConfig(hidden=8))
        assert not actor.by_hand
        g_mean, g_log_std = torch.randn(2, ROWS, ACT), torch.randn(2, ACT)
        saved = {}
        with torch.no_grad():
            actor.evaluate(obs, step.action, step.routing, saved=saved)
            grads = actor_grads(actor, saved, g_mean, g_log_std)
        _close(grads, _actor_autograd(actor, obs, step, g_mean, g_log_std))
    finally:
        NETWORKS.pop("doubled_backprop_test")


def _captured_update(monkeypatch, method, **settings):
    """(population, settings, flattened batch) of a ci-scale run's first update."""
    import pemamoe.mappo as mappo
    from pemamoe.mappo import TrainConfig, train_population

    cap, update = {}, mappo.ppo_update

    def grab(pop, sets, batch):
        cap.update(pop=pop, settings=sets, batch=batch)
        return update(pop, sets, batch)

    monkeypatch.setattr(mappo, "ppo_update", grab)
    train_population([TrainConfig.for_scale("ci", method, 0, **settings)], max_iterations=1, threads=1, progress=False)
    pop = cap["pop"]
    return pop, cap["settings"], cap["batch"].for_update(pop.norms, pop.device)


def _reference_loss_grads(pop, settings, b):
    """PPO's loss of notebook 07 written with autograd (the reading before appendix 05h), its gradients."""
    actor, critic, config = pop.actor, pop.critic, pop.config
    R, steps, U = b.logprobs.shape
    rows, clip = steps * U, settings.clip_coef.unsqueeze(1)
    route = None if b.routing is None else b.routing.reshape(R, rows)
    fa, fc = actor.flat.detach().requires_grad_(True), critic.flat.detach().requires_grad_(True)
    new = actor.evaluate(b.obs.reshape(R, rows, -1), b.actions.reshape(R, rows, -1), route, flat=fa)
    ratio = (new.log_prob - b.logprobs.reshape(R, rows)).exp()
    adv = b.advantages.unsqueeze(2).expand(R, steps, U).reshape(R, rows)
    adv = (adv - adv.mean(1, keepdim=True)) / (adv.std(1, keepdim=True) + 1e-8)
    pg = torch.max(-adv * ratio, -adv * torch.clamp(ratio, 1 - clip, 1 + clip)).mean(1)
    v, c_lb, _ = critic(b.states, settings.value_temperature, flat=fc)
    if config.clip_vloss:
        vc = b.values + torch.clamp(v - b.values, -clip, clip)
        vl = torch.max((v - b.returns) ** 2, (vc - b.returns) ** 2).mean(1)
    else:
        vl = ((v - b.returns) ** 2).mean(1)
    sparse = actor.gated and actor.k < actor.n_experts
    kl = pop.plasticity.extra_loss({"obs": b.obs.reshape(R, rows, -1), "tau": None if route is None else route.temperature,
                                    "noise": None if route is None else route.noise,
                                    "experts": new.experts if sparse else None, "mean": new.mean, "log_std": new.log_std})
    loss = pg + config.vf_coef * vl - settings.ent_coef * new.entropy + actor.lb_coef * new.load_balance + critic.lb_coef * c_lb
    loss = loss if kl is None else loss + kl
    return loss, torch.autograd.grad(loss.sum(), (fa, fc))


@pytest.mark.parametrize("method,settings", [("mlp", {}), ("moe", {}), ("smoe", {"clip_vloss": True}),
                                             ("pemamoe", {}), ("pemamoe", {"clip_vloss": True})])
def test_the_minibatch_gradient_is_autograds_of_the_loss(monkeypatch, method, settings):
    import pemamoe.mappo as mappo

    pop, sets, steps = _captured_update(monkeypatch, method, **settings)
    if method == "pemamoe":  # a switch: the KL anchor's term joins the loss
        pop.plasticity.on_switch(1)
        sets = pop.plasticity.begin_iteration(1)
        with torch.no_grad():
            pop.actor.flat.add_(0.05 * torch.randn_like(pop.actor.flat))
    b = steps.take(torch.randperm(steps.logprobs.shape[0])[:48], 1)
    loss, _, (g_actor, g_critic) = mappo._minibatch_loss(pop, sets, b)
    ref_loss, (ref_actor, ref_critic) = _reference_loss_grads(pop, sets, b)
    if method == "pemamoe":
        assert pop.plasticity.has_reference[0] and pop.plasticity.settings[0].kl_coef > 0
    torch.testing.assert_close(loss, ref_loss.detach())
    _close(g_actor, ref_actor)
    _close(g_critic, ref_critic)
