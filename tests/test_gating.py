"""Top-1 gating choices (notebook 05): the weight of the kept expert, the routing noise, the critic
beside a gated actor. A single network's gate is the population's run_gate read at R = 1 (bit for
bit), and its whole pass, head and log-density included, equals its one-member population's; the
controller inert without a switch; the routing that ran, as the trainer logs it."""

import itertools

import numpy as np
import pandas as pd
import pytest
import torch

from pemamoe.mappo import TrainConfig, evaluate_policy, train
from pemamoe.nets import (CRITIC_GATINGS, ROUTING_NOISES, TOP1_WEIGHTS, MLPCritic, MoECritic, NetConfig,
                          PopulationActor, PopulationCritic, RoutingSample, SMoECritic, critic_kind, make_actor,
                          make_critic, routing_noise_std, topk_weights)


pytestmark = pytest.mark.usefixtures("one_thread")


def test_top1_weight_values_and_gradients_by_hand():
    for mode, value, grad in (("straight_through", 1.0, 1.0), ("switch", 0.7, 1.0), ("paper", 1.0, None)):
        kept = torch.tensor([[0.7]], requires_grad=True)
        w = topk_weights(kept, mode)
        assert w.item() == pytest.approx(value)
        if grad is None:
            assert not w.requires_grad  # the router learns from the balance loss only
        else:
            w.sum().backward()
            assert kept.grad.item() == pytest.approx(grad)
    kept = torch.tensor([[0.6, 0.2]])
    for mode in TOP1_WEIGHTS:  # k > 1: the paper's renormalised weights whatever the top-1 reading
        torch.testing.assert_close(topk_weights(kept, mode), torch.tensor([[0.75, 0.25]]))


def test_routing_noise_sigma_schedules():
    assert routing_noise_std(NetConfig(routing_noise="fixed", noise_std=0.4), 900, 1000) == pytest.approx(0.4)
    ann = NetConfig(routing_noise="annealed", noise_std=1.0, noise_anneal_portion=0.5)
    assert [routing_noise_std(ann, i, 1000) for i in (0, 250, 500, 900)] == pytest.approx([1.0, 0.5, 0.0, 0.0])
    for mode in ("learned", "off"):
        assert routing_noise_std(NetConfig(routing_noise=mode), 10, 100) == 0.0


def test_critic_gating_picks_the_critic():
    expect = {("smoe", "gated"): SMoECritic, ("smoe", "dense"): MoECritic, ("smoe", "mlp"): MLPCritic,
              ("pemamoe", "dense"): MoECritic, ("moe", "gated"): MoECritic, ("moe", "dense"): MoECritic,
              ("mlp", "gated"): MLPCritic, ("mlp", "dense"): MLPCritic}
    for (kind, gating), cls in expect.items():
        cfg = NetConfig(critic_gating=gating)
        assert type(make_critic(kind, 12, cfg)) is cls, (kind, gating)
        assert critic_kind(kind, cfg) == cls.kind


CHOICES = list(itertools.product(TOP1_WEIGHTS, ROUTING_NOISES))


@pytest.mark.parametrize("kind", ["smoe", "moe"])
@pytest.mark.parametrize("top1_weight, noise", CHOICES)
def test_the_single_gate_is_run_gate_at_r1_bit_for_bit(kind, top1_weight, noise):
    cfg = NetConfig(top1_weight=top1_weight, routing_noise=noise, noise_std=0.8, critic_gating="gated")
    torch.manual_seed(0)
    for net in (make_actor(kind, 20, 2, cfg), make_critic(kind, 20, cfg)):
        pop = (PopulationActor if hasattr(net, "log_std") else PopulationCritic)([net])
        obs = torch.randn(48, 20)
        out = net.gate(obs, 1.3)  # sampling: the single network draws its own noise
        r = out.routing
        feat, (probs, experts, weights) = net.run_features(pop.params(), obs.unsqueeze(0), r.temperature.unsqueeze(0),
                                                           r.noise.unsqueeze(0), r.experts.unsqueeze(0) if net.gate.sparse else None)
        assert torch.equal(feat[0], out.features) and torch.equal(probs[0], out.probs)
        assert torch.equal(weights[0], out.weights)
        assert experts is None if kind == "moe" else torch.equal(experts[0], out.experts)
        replayed = net.gate(obs, None, r)
        assert torch.equal(replayed.features, out.features) and torch.equal(replayed.load_balance, out.load_balance)


@pytest.mark.parametrize("top1_weight, noise", CHOICES)
def test_each_gating_choice_at_r1_equals_its_population_form(top1_weight, noise):
    cfg = NetConfig(top1_weight=top1_weight, routing_noise=noise, noise_std=0.8)
    torch.manual_seed(0)
    single = make_actor("smoe", 20, 2, cfg)
    with torch.no_grad():  # a router far from its zero-gain start, so that the weights matter
        single.gate.router.weight.mul_(100)
    pop = PopulationActor([single])
    obs = torch.randn(48, 20)
    action, logp_single, routing = single.act(obs, temperature=1.3)
    if noise in ("fixed", "annealed"):  # stored already scaled by sigma
        assert routing.noise.std().item() == pytest.approx(0.8, rel=0.25)
    elif noise == "off":
        assert torch.equal(routing.noise, torch.zeros_like(routing.noise))
    # the population replays the single module's routing: same log-probabilities and gradients
    logp_s, _, aux = single.evaluate(obs, action, routing)
    (-logp_s.mean()).backward()
    batched = RoutingSample(routing.noise.unsqueeze(0), routing.experts.unsqueeze(0), routing.temperature.unsqueeze(0))
    logp_p, _, _, _, _, chosen = pop.evaluate(obs.unsqueeze(0), action.unsqueeze(0), batched)
    (-logp_p.mean()).backward()
    torch.testing.assert_close(logp_p[0], logp_s, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(logp_s, logp_single, rtol=1e-6, atol=1e-6)
    assert torch.equal(chosen[0], routing.experts)
    grads = pop.layout.views(pop.flat.grad)
    for name, p in single.named_parameters():  # None: no path from the loss (the paper's weight)
        expected = torch.zeros_like(p) if p.grad is None else p.grad
        torch.testing.assert_close(grads[name][0], expected, rtol=1e-5, atol=1e-7, msg=name)
    g = single.gate.router.weight.grad
    router_grad = 0.0 if g is None else g.abs().sum().item()
    assert (router_grad == 0.0) == (top1_weight == "paper")  # the policy loss alone trains the router unless "paper"


@pytest.mark.parametrize("noise", ["fixed", "annealed", "learned"])
def test_population_noise_draws_are_per_member(noise):
    cfg = NetConfig(routing_noise=noise, noise_std=0.5)
    members = [make_actor("smoe", 10, 2, cfg) for _ in range(2)]
    obs = torch.randn(2, 30, 10)
    gens = lambda: [torch.Generator().manual_seed(s) for s in (3, 4)]  # noqa: E731
    sigma = torch.tensor([0.5, 0.25])
    pair = PopulationActor(members).act(obs, torch.ones(2), gens(), noise_std=sigma)
    alone = PopulationActor(members[1:]).act(obs[1:], torch.ones(1), gens()[1:], noise_std=sigma[1:])
    for a, b in zip(pair[:2], alone[:2]):
        assert torch.equal(a[1], b[0])
    assert torch.equal(pair[2].noise[1], alone[2].noise[0])
    if noise != "learned":  # stored scaled by each member's own sigma
        assert pair[2].noise[0].std().item() == pytest.approx(0.5, rel=0.3)
        assert pair[2].noise[1].std().item() == pytest.approx(0.25, rel=0.3)


def test_routing_readings_by_hand():
    actor = PopulationActor([make_actor("smoe", 4, 2, NetConfig(routing_noise="off"))])
    obs = torch.zeros(1, 4, 1, 1, 4)  # one env, one agent, 4 steps
    experts = torch.tensor([0, 1, 1, 2]).reshape(1, 4, 1, 1, 1)
    routing = RoutingSample(torch.zeros(1, 4, 1, 1, 3), experts, torch.ones(1, 4, 1, 1))
    dones = torch.tensor([[[False], [True], [False], [False]]])  # the episode ends at step 1
    out = actor.routing_readings(obs, routing, dones)
    # steps 0->1 change (same episode), 1->2 crosses the episode end (not counted), 2->3 change
    assert out["rollout/switch_rate"][0] == pytest.approx(1.0)
    # the router maps the zero observation to one expert: 3 of the 4 stored choices differ from it
    quiet = int(actor.mean_and_gate(obs.reshape(1, 4, 4), torch.ones(1, 4))[2][1][0, 0, 0])
    assert out["rollout/override_rate"][0] == pytest.approx(float((experts.reshape(-1) != quiet).float().mean()))
    assert out["rollout/noise_scale"][0] == 0.0
    assert PopulationActor([make_actor("mlp", 4)]).routing_readings(obs, None, dones) == {}


def _fixed(method, **kw):
    return TrainConfig.for_scale("ci", method=method, seed=3, fixed_phase=1, iterations=4, phase_length_iters=4, **kw)


def test_pemamoe_trains_bit_for_bit_as_smoe_without_a_switch():
    a, b = train(_fixed("smoe")), train(_fixed("pemamoe"))
    for net in ("actor", "critic"):
        for (na, ta), (nb, tb) in zip(getattr(a, net).state_dict().items(), getattr(b, net).state_dict().items()):
            assert na == nb and torch.equal(ta, tb), (net, na)
    pd.testing.assert_frame_equal(a.episodes, b.episodes)
    same = ["episode_return", "coverage", "policy_loss", "value_loss", "approx_kl", "ent_coef", "temperature/policy",
            "temperature/value", "rollout/switch_rate", "log_std_mean"]
    pd.testing.assert_frame_equal(a.metrics[same], b.metrics[same])
    assert (b.metrics["temperature/policy"] == 1.0).all()  # the schedule waits for the first switch


def test_the_noise_scale_of_the_defaults_stays_bounded_in_a_ci_run():
    cfg = TrainConfig.for_scale("ci", method="smoe", seed=0, iterations=6)
    m = train(cfg).metrics
    scale = m["rollout/noise_scale"].to_numpy()
    bound = {"off": 0.0, "fixed": cfg.net.noise_std, "annealed": cfg.net.noise_std}.get(cfg.net.routing_noise)
    assert bound is not None, f"the default routing noise {cfg.net.routing_noise!r} has no bound"
    assert np.isfinite(scale).all() and (scale <= bound + 1e-12).all()
    if cfg.net.routing_noise == "annealed":
        assert (np.diff(scale) <= 0).all()


def test_evaluation_reports_noiseless_and_trained_routing():
    from pemamoe.env import EnvConfig, UAVVectorEnv
    obs_dim = UAVVectorEnv(1, 0, cfg=EnvConfig()).obs_dim
    actor = make_actor("smoe", obs_dim, 2, NetConfig(routing_noise="fixed", noise_std=3.0))
    with torch.no_grad():
        actor.gate.router.weight.mul_(30)
    state = torch.get_rng_state()
    quiet = evaluate_policy(actor, episodes=2, seed=0)
    noisy = evaluate_policy(actor, episodes=2, seed=0, routing="trained")
    again = evaluate_policy(actor, episodes=2, seed=0, routing="trained")
    assert torch.equal(state, torch.get_rng_state())  # the global generator is left alone
    assert (quiet.routing == "noiseless").all() and (noisy.routing == "trained").all()
    pd.testing.assert_frame_equal(noisy, again)  # seeded
    assert not np.allclose(quiet["return"], noisy["return"])
    with pytest.raises(ValueError, match="'sampled'"):
        evaluate_policy(actor, episodes=1, routing="sampled")
