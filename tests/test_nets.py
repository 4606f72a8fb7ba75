"""Tests for pemamoe.nets (notebook 05): architectures, gating, routing replay, cost accounting."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pemamoe.nets import (
    ACTOR_PARAM_GROUPS,
    NETWORKS,
    PAPER_NET,
    PAPER_ACTIVE_PARAMS,
    PAPER_ACTOR_PARAMS,
    PAPER_OBS_DIM,
    ExpertBank,
    MLPActor,
    MLPCritic,
    NetConfig,
    RoutingSample,
    linear_cost,
    load_balance_loss,
    make_actor,
    make_critic,
    register_network,
)

from pemamoe.methods import METHOD_REGISTRY, compared_methods
from pemamoe.netcost import active_parameters, cost_table, count_parameters, macs_per_step

# every method compared by default (make_actor resolves its network); the others reuse these networks
ACTOR_KINDS = compared_methods()
MOE_KINDS = tuple(name for name in ACTOR_KINDS if METHOD_REGISTRY[name].network != "mlp")
IMPLS = ("stacked", "masked", "loop", "auto")


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


# ---------------------------------------------------------------- parameter counts (paper table)


@pytest.mark.parametrize("impl", IMPLS)
def test_paper_parameter_counts_reproduced_exactly(impl):
    cfg = NetConfig(expert_impl=impl, routing_noise="learned", expert_heads="shared")  # PAPER_NET: a noise gate, one head
    for kind in ACTOR_KINDS:
        actor = make_actor(kind, PAPER_OBS_DIM, 2, cfg)
        assert count_parameters(actor) == PAPER_ACTOR_PARAMS[kind]
        assert active_parameters(actor) == PAPER_ACTIVE_PARAMS[kind]
    assert (PAPER_ACTOR_PARAMS["mlp"], PAPER_ACTOR_PARAMS["moe"], PAPER_ACTOR_PARAMS["smoe"]) == (6820, 20858, 21392)
    assert PAPER_ACTIVE_PARAMS["smoe"] == PAPER_ACTIVE_PARAMS["pemamoe"] == 7820


def test_mlp_count_by_hand():
    d, h = PAPER_OBS_DIM, 32
    assert count_parameters(make_actor("mlp", d)) == (d * h + h) + (h * h + h) + (h * 2 + 2) + 2 == 6820


def test_active_parameter_conventions():
    smoe = make_actor("smoe", PAPER_OBS_DIM, 2, PAPER_NET)  # the paper's reading: learned noise
    # paper: router 534 + noise gate 534 + one trunk 6752 (head 66 and log-std 2 left out)
    assert active_parameters(smoe, "paper") == 534 + 534 + 6752
    assert active_parameters(smoe, "sampling") == 7820 + 66 + 2
    assert active_parameters(smoe, "eval") == 534 + 6752 + 66 + 2
    for kind in (n for n, sp in METHOD_REGISTRY.items() if sp.network in ("mlp", "moe")):  # dense networks
        actor = make_actor(kind, PAPER_OBS_DIM)
        for mode in ("paper", "sampling", "eval"):
            assert active_parameters(actor, mode) == count_parameters(actor)


def test_macs_per_step():
    mlp, smoe, moe = (make_actor(k, PAPER_OBS_DIM, 2, PAPER_NET) for k in ("mlp", "smoe", "moe"))
    assert macs_per_step(mlp) == 177 * 32 + 32 * 32 + 32 * 2
    assert macs_per_step(smoe, "sampling") == 2 * 177 * 3 + 177 * 32 + 32 * 32 + 32 * 2
    assert macs_per_step(smoe, "eval") == 177 * 3 + 177 * 32 + 32 * 32 + 32 * 2
    assert macs_per_step(moe) == 177 * 3 + 3 * (177 * 32 + 32 * 32) + 32 * 2
    assert round(macs_per_step(smoe) / macs_per_step(mlp), 2) == 1.16  # the paper's "about 1.16x"


def test_pemamoe_matches_smoe_and_noiseless_smoe_matches_moe():
    assert count_parameters(make_actor("pemamoe", 50)) == count_parameters(make_actor("smoe", 50))
    quiet = make_actor("smoe", PAPER_OBS_DIM, 2, NetConfig(routing_noise="off", expert_heads="shared"))
    assert count_parameters(quiet) == PAPER_ACTOR_PARAMS["moe"]


def test_cost_table_rows():
    table = cost_table({"paper": PAPER_OBS_DIM, "ours": 40}, repeats=1, batch_sizes=(1, 8))
    assert list(table.actor) == list(ACTOR_KINDS) * 2
    paper = table[table.obs == "paper"].set_index("actor")
    for kind in ACTOR_KINDS:
        assert paper.loc[kind, "params"] == PAPER_ACTOR_PARAMS[kind]
        assert paper.loc[kind, "active_params"] == PAPER_ACTIVE_PARAMS[kind]
    assert paper.loc["smoe", "params_vs_mlp"] == 3.14 and paper.loc["moe", "params_vs_mlp"] == 3.06
    assert (table[["latency_us_b1", "latency_us_b8"]] > 0).all().all()


# ---------------------------------------------------------------- routing replay: PPO ratio == 1


@pytest.mark.parametrize("kind", ACTOR_KINDS)
@pytest.mark.parametrize("impl", IMPLS)
def test_replayed_routing_gives_ratio_exactly_one(kind, impl):
    actor = make_actor(kind, 30, 2, NetConfig(expert_impl=impl, masked_min_batch=100))
    obs = torch.randn(300, 30)
    action, logp_old, routing = actor.act(obs, temperature=1.7)
    logp_new, entropy, aux = actor.evaluate(obs, action, routing)
    assert torch.equal(logp_new, logp_old)
    assert torch.equal(torch.exp(logp_new - logp_old), torch.ones(300))
    assert (routing is None) == (kind == "mlp")


@pytest.mark.parametrize("kind", tuple(n for n, sp in METHOD_REGISTRY.items() if sp.network == "smoe"))
def test_noise_matters_without_replay(kind):
    actor = make_actor(kind, 30, 2, PAPER_NET)
    with torch.no_grad():  # make the gate noisy enough that a re-draw changes some routes
        actor.gate.noise_gate.bias.fill_(3.0)
    obs = torch.randn(256, 30)
    action, logp_old, routing = actor.act(obs)
    logp_redraw, _, _ = actor.evaluate(obs, action, None, temperature=1.0)
    assert not torch.equal(logp_redraw, logp_old)
    assert routing.noise.abs().sum() > 0


def test_replay_with_leading_axes_and_minibatches():
    actor = make_actor("smoe", 12)
    obs = torch.randn(5, 4, 12)  # (T, agents, obs)
    temps = torch.linspace(0.5, 2.0, 5).unsqueeze(-1).expand(5, 4)
    action, logp_old, routing = actor.act(obs, temperature=temps)
    assert action.shape == (5, 4, 2) and logp_old.shape == (5, 4)
    assert routing.noise.shape == (5, 4, 3) and routing.experts.shape == (5, 4, 1)
    assert routing.temperature.shape == (5, 4)
    logp_new, _, aux = actor.evaluate(obs, action, routing)
    assert torch.equal(logp_new, logp_old)
    assert aux["router_probs"].shape == (5, 4, 3)
    # flatten as a buffer would, and re-evaluate one minibatch
    flat = routing.reshape(20)
    idx = torch.tensor([3, 7, 11, 19])
    lp_mb, _, _ = actor.evaluate(obs.reshape(20, 12)[idx], action.reshape(20, 2)[idx], flat.select(idx))
    torch.testing.assert_close(lp_mb, logp_old.reshape(20)[idx], rtol=0, atol=1e-5)
    both = RoutingSample.cat([flat.select(idx), flat.select(idx)])
    assert both.noise.shape == (8, 3)


# ---------------------------------------------------------------- gating and load balancing


def test_load_balance_uniform_is_one_and_collapsed_is_larger():
    e = 3
    probs = torch.full((6, e), 1 / e)
    experts = torch.arange(6).remainder(e).unsqueeze(-1)
    assert load_balance_loss(probs, experts, e).item() == pytest.approx(1.0, abs=1e-6)
    collapsed = torch.nn.functional.one_hot(torch.zeros(6, dtype=torch.long), e).float()
    lb = load_balance_loss(collapsed, torch.zeros(6, 1, dtype=torch.long), e)
    assert lb.item() == pytest.approx(3.0) and lb.item() > 1


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 4), st.integers(1, 8), st.integers(0, 10_000))
def test_load_balance_is_one_whenever_dispatch_is_balanced(per_expert, e, seed):
    # f_i = 1/E for every i  =>  E * sum_i P_i / E = 1 whatever the probabilities
    g = torch.Generator().manual_seed(seed)
    probs = torch.softmax(torch.randn(per_expert * e, e, generator=g), -1)
    experts = torch.arange(per_expert * e).remainder(e).unsqueeze(-1)
    assert load_balance_loss(probs, experts, e).item() == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize("kind", tuple(n for n, sp in METHOD_REGISTRY.items() if sp.network == "smoe"))
def test_top1_router_gets_gradient_from_policy_loss(kind):
    actor = make_actor(kind, 20, 2, PAPER_NET)  # learned noise: the noise gate learns too
    obs = torch.randn(64, 20)
    action, _, routing = actor.act(obs)
    logp, _, aux = actor.evaluate(obs, action + 0.3, routing)
    assert torch.equal(aux["gate_weights"], torch.ones(64, 1))  # the paper's renormalised weight
    (-logp.mean()).backward()  # no load-balance term: the gradient comes through the policy
    for layer in (actor.gate.router, actor.gate.noise_gate):
        grad = layer.weight.grad
        assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_top2_weights_renormalised_with_gradient():
    actor = make_actor("smoe", 20, 2, NetConfig(top_k=2))
    obs = torch.randn(32, 20)
    action, _, routing = actor.act(obs)
    logp, _, aux = actor.evaluate(obs, action, routing)
    torch.testing.assert_close(aux["gate_weights"].sum(-1), torch.ones(32))
    assert routing.experts.shape == (32, 2)
    (-logp.mean()).backward()
    assert actor.gate.router.weight.grad.abs().sum() > 0


def test_aux_loss_is_weighted_load_balance():
    actor = make_actor("smoe", 20, 2, NetConfig(load_balance_coef=0.5))
    obs = torch.randn(40, 20)
    action, _, routing = actor.act(obs)
    _, _, aux = actor.evaluate(obs, action, routing)
    torch.testing.assert_close(aux["aux_loss"], 0.5 * aux["load_balance"])
    _, _, aux_mlp = make_actor("mlp", 20).evaluate(obs, action)
    assert aux_mlp["aux_loss"].item() == 0.0 and aux_mlp["router_probs"] is None


def test_temperature_spreads_noisy_top1_routing():
    actor = make_actor("smoe", 20, 2, PAPER_NET)
    with torch.no_grad():
        actor.gate.router.bias.copy_(torch.tensor([2.0, 0.0, 0.0]))  # the router prefers expert 0
    obs = torch.randn(4000, 20)

    def share_of_favourite(tau):
        _, _, r = actor.act(obs, temperature=tau)
        return (r.experts == 0).float().mean().item()

    cold, warm, hot = share_of_favourite(0.25), share_of_favourite(1.0), share_of_favourite(16.0)
    assert cold > 0.97 and cold > warm > hot and hot < 0.45


@pytest.mark.parametrize("bad", [0.0, -1.0, torch.tensor([1.0, 0.0])])
def test_nonpositive_temperature_rejected(bad):
    actor = make_actor("smoe", 5)
    with pytest.raises(ValueError, match="temperature"):
        actor.act(torch.randn(2, 5), temperature=bad)


# ---------------------------------------------------------------- shapes, evaluation mode


@pytest.mark.parametrize("kind", ACTOR_KINDS)
@pytest.mark.parametrize("batch", (1, 64))
def test_shapes(kind, batch):
    actor = make_actor(kind, 17, 2)
    critic = make_critic(kind, 41)
    obs = torch.randn(batch, 17)
    dist, routing = actor(obs)
    assert dist.mean.shape == (batch, 2)
    action, logp, routing = actor.act(obs)
    assert action.shape == (batch, 2) and logp.shape == (batch,)
    logp2, ent, aux = actor.evaluate(obs, action, routing)
    assert logp2.shape == (batch,) and ent.shape == (batch,) and aux["load_balance"].shape == ()
    value, caux = critic(torch.randn(batch, 41))
    assert value.shape == (batch,)
    if kind == "mlp":
        assert routing is None and caux["router_probs"] is None
    else:
        assert routing.noise.shape == (batch, 3)
        assert caux["router_probs"].shape == (batch, 3)
        torch.testing.assert_close(caux["router_probs"].sum(-1), torch.ones(batch))
    probe = actor.probe(torch.randn(batch, 17))
    e = 1 if kind == "mlp" else 3
    assert len(probe["preact"]) == len(probe["act"]) == 2
    for t in (*probe["preact"], *probe["act"]):
        assert t.shape == (e, batch, 32)
    assert probe["mean"].shape == (batch, 2)


@pytest.mark.parametrize("kind", ACTOR_KINDS)
def test_deterministic_evaluation_mode(kind):
    actor = make_actor(kind, 17)
    obs = torch.randn(50, 17)
    torch.manual_seed(1)
    a1, lp1, r1 = actor.act(obs, deterministic=True)
    torch.manual_seed(2)
    a2, lp2, r2 = actor.act(obs, deterministic=True)
    assert torch.equal(a1, a2) and torch.equal(lp1, lp2)
    dist, _ = actor(obs, deterministic_gate=True)
    assert torch.equal(a1, dist.mean)
    if kind != "mlp":
        assert torch.equal(r1.noise, torch.zeros_like(r1.noise))


def test_log_std_initialisation_and_entropy():
    actor = make_actor("mlp", 5, 2, NetConfig(init_log_std=math.log(0.3)))
    torch.testing.assert_close(actor.log_std.detach(), torch.full((2,), math.log(0.3)))
    _, ent, _ = actor.evaluate(torch.randn(3, 5), torch.zeros(3, 2))
    expected = 2 * (0.5 * math.log(2 * math.pi * math.e) + math.log(0.3))
    torch.testing.assert_close(ent, torch.full((3,), expected))


# ---------------------------------------------------------------- expert execution strategies


@pytest.mark.parametrize("kind", MOE_KINDS)
def test_expert_implementations_agree(kind):
    actor = make_actor(kind, 25, 2, NetConfig(top_k=1 if kind != "moe" else 1))
    obs = torch.randn(97, 25)
    action, _, routing = actor.act(obs)
    means, grads = {}, {}
    for impl in IMPLS:
        actor.gate.experts.impl = impl
        actor.zero_grad(set_to_none=True)
        logp, _, _ = actor.evaluate(obs, action, routing)
        (-logp.sum()).backward()
        means[impl] = actor(obs, routing=routing)[0].mean.detach()
        grads[impl] = actor.gate.experts.w1.grad.clone()
    for impl in IMPLS:
        torch.testing.assert_close(means[impl], means["stacked"], rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(grads[impl], grads["stacked"], rtol=1e-4, atol=1e-6)


def test_expert_bank_mixed_top2_agrees():
    bank = ExpertBank(9, 8, 4)
    x = torch.randn(33, 9)
    experts = torch.stack([torch.randperm(4)[:2] for _ in range(33)])
    weights = torch.softmax(torch.randn(33, 2), -1)
    ref = bank.mixed(x, experts, weights, "loop")
    for impl in ("stacked", "masked"):
        torch.testing.assert_close(bank.mixed(x, experts, weights, impl), ref, rtol=1e-5, atol=1e-6)
    all_e = bank.all_experts(x)
    manual = (all_e.transpose(0, 1).gather(1, experts.unsqueeze(-1).expand(-1, -1, 8)) * weights.unsqueeze(-1)).sum(1)
    torch.testing.assert_close(ref, manual, rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------- parameter groups


@pytest.mark.parametrize("kind", ACTOR_KINDS)
def test_param_groups_cover_every_parameter_once(kind):
    actor = make_actor(kind, 14, 2, PAPER_NET)  # with a noise gate, filed under the router
    groups = actor.param_groups()
    assert set(groups) == {"router", "experts", "head", "log_std"}
    ids = [id(p) for ps in groups.values() for p in ps]
    assert len(ids) == len(set(ids))
    assert set(ids) == {id(p) for p in actor.parameters()}
    assert groups["log_std"] == [actor.log_std]
    if METHOD_REGISTRY[kind].network == "smoe":
        assert len(groups["router"]) == 4  # router and noise gate, weight and bias each
    critic = make_critic(kind, 30)
    cgroups = critic.param_groups()
    assert set(cgroups) == {"critic"}
    assert {id(p) for p in cgroups["critic"]} == {id(p) for p in critic.parameters()}
    assert len(cgroups["critic"]) == len(list(critic.parameters()))


@pytest.mark.parametrize("kind", ACTOR_KINDS)
def test_probe_reads_the_network_that_acts(kind):
    # probe derives from features: its features and mean are the deterministic forward's, bit for bit
    actor = make_actor(kind, 14, 2, PAPER_NET)
    obs = torch.randn(40, 14)
    probe = actor.probe(obs)
    with torch.no_grad():
        dist, _ = actor(obs, deterministic_gate=True)
        feat, gate = actor.features(obs, None, None, deterministic_gate=True, with_aux=False)
    assert torch.equal(probe["mean"], dist.mean) and torch.equal(probe["features"], feat)
    if gate is not None:
        assert torch.equal(probe["router_probs"], gate.probs) and torch.equal(probe["selected"], gate.experts)
    assert probe["act"][-1].shape[1:] == (40, 32)


def test_a_new_kind_gets_its_probe_from_its_own_features():
    class Doubled(MLPActor):  # only run_features changes: features, forward and probe follow it
        def run_features(self, p, x, tau=None, noise=None, experts=None):
            h, _ = super().run_features(p, x)
            return 2 * h, None

    register_network("doubled_test", Doubled, MLPCritic)
    try:
        actor, obs = make_actor("doubled_test", 9), torch.randn(16, 9)
        plain = make_actor("mlp", 9)
        plain.load_state_dict(actor.state_dict())
        with torch.no_grad():
            torch.testing.assert_close(actor(obs, deterministic_gate=True)[0].mean, plain.head(2 * plain.probe(obs)["features"]))
            assert torch.equal(actor.probe(obs)["mean"], actor(obs, deterministic_gate=True)[0].mean)
    finally:
        NETWORKS.pop("doubled_test")


def test_param_groups_outside_the_declared_names_are_refused_by_name():
    class Renamed(MLPActor):
        def param_groups(self):
            groups = super().param_groups()
            return {"trunk" if g == "experts" else g: ps for g, ps in groups.items()}

    class Forgetful(MLPActor):
        def param_groups(self):
            return {**super().param_groups(), "head": []}

    for cls, message in ((Renamed, r"group 'trunk'; the groups are router, experts, head, log_std"),
                         (Forgetful, r"leaves out head\.weight, head\.bias")):
        register_network("bad_groups_test", cls, MLPCritic)
        try:
            with pytest.raises(ValueError, match=message):
                make_actor("bad_groups_test", 5)
        finally:
            NETWORKS.pop("bad_groups_test")
    assert ACTOR_PARAM_GROUPS == ("router", "experts", "head", "log_std")


def test_linear_cost_by_hand():
    a, b = torch.nn.Linear(7, 5), torch.nn.Linear(5, 3)
    assert linear_cost(a) == (7 * 5 + 5, 7 * 5)
    assert linear_cost(a, None, b) == (40 + 18, 35 + 15) and linear_cost(None) == (0, 0)


# ---------------------------------------------------------------- validation


def test_unknown_kind_rejected():
    with pytest.raises(ValueError, match=r"'transformer'.*|mlp, moe, smoe, pemamoe"):
        make_actor("transformer", 10)
    with pytest.raises(ValueError, match="mlp, moe, smoe, pemamoe"):
        make_critic("lstm", 10)
    with pytest.raises(ValueError, match="obs_dim"):
        make_actor("mlp", 0)


@pytest.mark.parametrize(
    "field, value",
    [
        ("hidden", 0),
        ("n_experts", 0),
        ("top_k", 4),
        ("top_k", 0),
        ("init_log_std", float("nan")),
        ("load_balance_coef", -0.1),
        ("top1_weight", "st"),
        ("routing_noise", "gaussian"),
        ("noise_std", -0.5),
        ("noise_anneal_portion", 0.0),
        ("critic_gating", "sparse"),
        ("expert_impl", "fused"),
        ("masked_min_batch", 0),
        ("gain_router", 0.0),
    ],
)
def test_invalid_config_names_field_and_value(field, value):
    with pytest.raises(ValueError) as err:
        NetConfig(**{field: value})
    assert f"NetConfig.{field}" in str(err.value) and repr(value) in str(err.value)


def test_invalid_impl_on_bank():
    with pytest.raises(ValueError, match="'fused'"):
        ExpertBank(3, 4, 2).impl = "fused"


def test_cost_modes_validated():
    actor = make_actor("smoe", 10)
    with pytest.raises(ValueError, match="'inference'"):
        active_parameters(actor, "inference")
    with pytest.raises(ValueError, match="'paper'"):
        macs_per_step(actor, "paper")
