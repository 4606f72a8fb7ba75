"""Sanity checks of the sparse actor (issues 38 and 40): the readings of appendix 05d against hand
computations and against the networks they must reduce to.

* one expert: a top-1 SMoE with a single expert computes what an MLP with the same weights does;
* top-k = number of experts: a sparse gate that keeps every expert is the dense mixture (MoE);
* per-expert heads: each expert has its own mean head, and the mean is the chosen expert's;
* the router gets the task's gradient at top-1 (straight-through and Switch weights; none under the
  paper's literal weight);
* update_routing="current": PPO's update uses the routes the current parameters choose, so a
  change of route moves the ratio; "replay" keeps the stored routes;
* sampling and evaluation route alike when there is no routing noise.
"""

import dataclasses

import pytest
import torch

from pemamoe.nets import NetConfig, PopulationActor, RoutingSample, make_actor, single_member_params

OBS, ACT, HID = 7, 2, 8


# Our first reading of the sparse actor (a balance loss, one shared head, replayed routes): the
# tests below start from it whatever the defaults are, and each names the readings it changes.
OURS = {"load_balance_coef": 0.01, "expert_heads": "shared", "update_routing": "replay"}


def cfg(**kw) -> NetConfig:
    return NetConfig(hidden=HID, **{**OURS, **kw})


def obs(n=64, seed=0):
    return torch.randn(n, OBS, generator=torch.Generator().manual_seed(seed))


def spread(actor):
    """Make the experts' means and the router visibly different (as after training)."""
    with torch.no_grad():
        actor.head.weight.mul_(100)
        if hasattr(actor, "gate"):
            actor.gate.router.weight.mul_(300)
    return actor


def mean(actor, x):
    return actor(x, 1.0, None, deterministic_gate=True)[0].mean


@pytest.mark.parametrize("heads", ["shared", "per_expert"])
def test_one_expert_smoe_computes_what_an_mlp_with_its_weights_does(heads):
    torch.manual_seed(0)
    mlp = spread(make_actor("mlp", OBS, ACT, cfg()))
    smoe = make_actor("smoe", OBS, ACT, cfg(n_experts=1, expert_heads=heads))
    bank = smoe.gate.experts
    with torch.no_grad():  # the bank stores w (E, in, out); nn.Linear stores (out, in)
        bank.w1.copy_(mlp.fc1.weight.T.unsqueeze(0))
        bank.b1.copy_(mlp.fc1.bias.unsqueeze(0))
        bank.w2.copy_(mlp.fc2.weight.T.unsqueeze(0))
        bank.b2.copy_(mlp.fc2.bias.unsqueeze(0))
        smoe.head.weight.copy_(mlp.head.weight.reshape(smoe.head.weight.shape))
        smoe.head.bias.copy_(mlp.head.bias.reshape(smoe.head.bias.shape))
    x = obs()
    torch.testing.assert_close(mean(smoe, x), mean(mlp, x), rtol=1e-6, atol=1e-6)
    # with one expert the router's probability is 1 whatever it computes: no gradient reaches it
    logp, _, _ = smoe.evaluate(x, torch.zeros(len(x), ACT), smoe(x, 1.0)[1])
    logp.sum().backward()
    assert smoe.gate.router.weight.grad is None or not smoe.gate.router.weight.grad.any()


@pytest.mark.parametrize("heads", ["shared", "per_expert"])
def test_top_k_equal_to_the_number_of_experts_is_the_dense_mixture(heads):
    torch.manual_seed(1)
    moe = spread(make_actor("moe", OBS, ACT, cfg(expert_heads=heads)))
    smoe = make_actor("smoe", OBS, ACT, cfg(top_k=3, routing_noise="off", expert_heads=heads))
    smoe.load_state_dict(moe.state_dict())
    x = obs()
    torch.testing.assert_close(mean(smoe, x), mean(moe, x), rtol=1e-5, atol=1e-5)


def test_per_expert_heads_give_the_chosen_experts_own_mean():
    torch.manual_seed(2)
    actor = spread(make_actor("smoe", OBS, ACT, cfg(expert_heads="per_expert")))
    assert tuple(actor.head.weight.shape) == (3, ACT, HID) and tuple(actor.head.bias.shape) == (3, ACT)
    shared = make_actor("smoe", OBS, ACT, cfg())
    assert sum(p.numel() for p in actor.parameters()) - sum(p.numel() for p in shared.parameters()) == 2 * (HID * ACT + ACT)
    x = obs()
    chosen = actor.gate.router(x).argmax(-1)  # noiseless top-1 at temperature 1
    h = actor.gate.experts.all_experts(x, "stacked")  # (E, B, hidden)
    own = torch.stack([h[e, i] @ actor.head.weight[e].T + actor.head.bias[e] for i, e in enumerate(chosen.tolist())])
    torch.testing.assert_close(mean(actor, x), own, rtol=1e-5, atol=1e-5)
    assert len(set(chosen.tolist())) > 1  # the rows really went to different experts


@pytest.mark.parametrize("heads", ["shared", "per_expert"])
@pytest.mark.parametrize("routing", ["replay", "current"])
def test_the_single_network_is_the_population_at_r1(heads, routing):
    torch.manual_seed(3)
    actor = spread(make_actor("smoe", OBS, ACT, cfg(expert_heads=heads, update_routing=routing)))
    pop = PopulationActor([actor])
    x = obs()
    single = mean(actor, x)
    batched, _, _ = pop.mean_and_gate(x.unsqueeze(0), torch.ones(1, len(x)))
    assert torch.equal(single, batched[0])


@pytest.mark.parametrize("weight,reaches", [("straight_through", True), ("switch", True), ("paper", False)])
@pytest.mark.parametrize("heads", ["shared", "per_expert"])
def test_the_router_gets_the_task_gradient_at_top1(weight, reaches, heads):
    torch.manual_seed(4)
    actor = spread(make_actor("smoe", OBS, ACT, cfg(top1_weight=weight, expert_heads=heads)))
    x = obs()
    action, _, routing = actor.act(x, 1.0)
    logp, _, aux = actor.evaluate(x, action + 0.3, routing)  # the balance loss left out: the task's gradient only
    logp.sum().backward()
    grad = actor.gate.router.weight.grad
    assert (grad is not None and bool(grad.abs().sum() > 0)) == reaches


def _stored_routing_moved(actor, x):
    """The routing a rollout would store, with each row's expert moved to another one."""
    _, _, routing = actor.act(x, 1.0)
    moved = (routing.experts + 1) % actor.gate.n_experts
    return routing, RoutingSample(routing.noise, moved, routing.temperature)


@pytest.mark.parametrize("heads", ["shared", "per_expert"])
def test_rerouting_counts_in_the_ratio_under_current_routing(heads):
    torch.manual_seed(5)
    base = spread(make_actor("smoe", OBS, ACT, cfg(expert_heads=heads)))
    x = obs()
    acted, moved = _stored_routing_moved(base, x)
    action = base.act(x, 1.0, deterministic=True)[0]
    out = {}
    for routing in ("replay", "current"):
        actor = make_actor("smoe", OBS, ACT, cfg(expert_heads=heads, update_routing=routing))
        actor.load_state_dict(base.state_dict())
        pop = PopulationActor([actor])
        r = moved.reshape(1, len(x))
        logp, _, _, _, _, chosen = pop.evaluate(x.unsqueeze(0), action.unsqueeze(0), r)
        out[routing] = (logp[0], chosen[0])
    # replay: the stored (moved) experts act; current: the router's own choice acts again
    assert torch.equal(out["replay"][1], moved.experts)
    assert torch.equal(out["current"][1], acted.experts)
    own = PopulationActor([base]).evaluate(x.unsqueeze(0), action.unsqueeze(0), acted.reshape(1, len(x)))[0][0]
    torch.testing.assert_close(out["current"][0], own)
    assert not torch.allclose(out["replay"][0], own)  # the moved routes give other means, so another ratio
    # the share of rows the current parameters route elsewhere than the stored routes
    pop = PopulationActor([make_actor("smoe", OBS, ACT, cfg(expert_heads=heads, update_routing="current"))])
    pop.flat.data.copy_(PopulationActor([base]).flat.data)
    rate = pop.reroute_readings(x.unsqueeze(0), moved.reshape(1, len(x)))["update/reroute_rate"]
    assert rate[0] == pytest.approx(1.0)
    assert pop.reroute_readings(x.unsqueeze(0), acted.reshape(1, len(x)))["update/reroute_rate"][0] == 0.0
    replayed = make_actor("smoe", OBS, ACT, cfg(expert_heads=heads, update_routing="replay"))
    assert PopulationActor([replayed]).reroute_readings(x.unsqueeze(0), acted.reshape(1, len(x))) == {}  # not logged


def test_sampling_and_evaluation_route_alike_without_routing_noise():
    torch.manual_seed(6)
    actor = spread(make_actor("smoe", OBS, ACT, cfg(routing_noise="off")))
    x = obs()
    for tau in (0.5, 1.0, 3.0):  # a temperature rescales the logits: it never changes the largest
        _, _, sampled = actor.act(x, tau)
        _, _, evaluated = actor.act(x, tau, deterministic=True)
        assert torch.equal(sampled.experts, evaluated.experts)


def test_the_readings_are_validated_by_name():
    for field in ("expert_heads", "update_routing"):
        with pytest.raises(ValueError, match=field):
            NetConfig(**{field: "bogus"})
    assert dataclasses.replace(NetConfig(), expert_heads="per_expert").expert_heads == "per_expert"
