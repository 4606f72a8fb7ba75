"""Diagnostics formulas on matrices whose answers are known by hand (appendix notebook 06b)."""

import math

import numpy as np
import pytest
import torch

from pemamoe import diagnostics as dg
from pemamoe.methods import METHOD_REGISTRY
from pemamoe.nets import make_actor, make_critic


@pytest.mark.parametrize("n", [1, 5, 32, 64])
def test_identity_has_full_rank_in_every_measure(n):
    eye = np.eye(n)
    assert dg.stable_rank(eye) == pytest.approx(n)
    assert dg.effective_rank(eye) == pytest.approx(n)
    assert dg.srank(eye) == n  # n < 100: dropping one of n equal values loses more than delta = 1 %


def test_srank_of_identity_above_100_drops_one():
    # 99 of 100 equal singular values hold exactly 99 % of the total
    assert dg.srank(np.eye(100)) == 99


def test_rank_one_matrix():
    rng = np.random.default_rng(0)
    a = np.outer(rng.normal(size=50), rng.normal(size=8))
    assert dg.stable_rank(a) == pytest.approx(1.0)
    assert dg.effective_rank(a) == pytest.approx(1.0, abs=1e-6)
    assert dg.srank(a) == 1


def test_diagonal_with_known_singular_values():
    s = np.array([4.0, 2.0, 1.0, 1.0])
    a = np.diag(s)
    assert dg.stable_rank(a) == pytest.approx((16 + 4 + 1 + 1) / 16)  # 1.375
    p = s / s.sum()  # 0.5, 0.25, 0.125, 0.125
    entropy = -(0.5 * math.log(0.5) + 0.25 * math.log(0.25) + 2 * 0.125 * math.log(0.125))
    assert dg.effective_rank(a) == pytest.approx(math.exp(entropy))  # 2^1.75 = 3.3636
    assert dg.effective_rank(a) == pytest.approx(2**1.75)
    # cumulative sums 4, 6, 7, 8 of total 8: 0.99 * 8 = 7.92 -> k = 4; delta 0.2 -> 6.4 -> k = 3
    assert dg.srank(a) == 4
    assert dg.srank(a, delta=0.2) == 3
    assert dg.srank(a, delta=0.5) == 1  # 4 >= 4
    # the order of rows and signs does not matter
    assert dg.stable_rank(-a[::-1]) == pytest.approx(1.375)


def test_zero_matrix_has_rank_zero_and_tensors_accepted():
    z = torch.zeros(10, 4)
    assert dg.stable_rank(z) == 0.0
    assert dg.effective_rank(z) == 0.0
    assert dg.srank(z) == 0
    assert dg.stable_rank(torch.eye(3)) == pytest.approx(3.0)
    with pytest.raises(ValueError, match="2-D"):
        dg.stable_rank(np.zeros(3))
    with pytest.raises(ValueError, match="delta"):
        dg.srank(np.eye(3), delta=1.0)


def test_dormant_paper_threshold_on_mean_abs_preactivation():
    # 4 units over a batch of 2: mean |a| = 0.005, 0.5, 0.0, 0.02 -> units 0 and 2 are below 0.01
    pre = torch.tensor([[0.01, 1.0, 0.0, -0.02], [0.0, 0.0, 0.0, 0.02]])
    assert dg.dormant_fraction_paper(pre) == pytest.approx(0.5)
    assert dg.dormant_fraction_paper(pre, delta=0.6) == pytest.approx(1.0)
    # a "dead ReLU" with strongly negative pre-activations is NOT dormant under the paper's rule
    assert dg.dormant_fraction_paper(torch.full((5, 1), -3.0)) == 0.0


def test_dormant_tau_score():
    # E|h| per unit: 1, 1, 1, 0.02, 0 -> layer mean 0.604; scores 1.656, ..., 0.0331, 0
    act = torch.tensor([[1.0, 2.0, 0.0, 0.04, 0.0], [1.0, 0.0, 2.0, 0.0, 0.0]])
    assert dg.dormant_fraction_tau(act) == pytest.approx(1 / 5)  # only the silent unit (0.0331 > 0.025)
    assert dg.dormant_fraction_tau(act, tau=0.04) == pytest.approx(2 / 5)
    # exactly at tau counts as dormant (s <= tau): unit means 3, 3, 1, 1 -> layer mean 2 -> s = 1.5, 1.5, 0.5, 0.5
    act2 = torch.tensor([[3.0, 3.0, 1.0, 1.0]])
    assert dg.dormant_fraction_tau(act2, tau=0.5) == pytest.approx(0.5)
    assert dg.dormant_fraction_tau(act2, tau=0.49) == 0.0
    assert dg.dormant_fraction_tau(torch.zeros(3, 4)) == 1.0
    assert dg.dormant_fraction_tau(torch.ones(3, 4)) == 0.0


@pytest.mark.parametrize("kind", tuple(METHOD_REGISTRY))
def test_plasticity_diagnostics_names_and_values(kind):
    torch.manual_seed(0)
    obs_dim, state_dim, n = 12, 16, 64
    actor, critic = make_actor(kind, obs_dim), make_critic(kind, state_dim)
    g = torch.Generator().manual_seed(0)
    obs, state = torch.randn(n, obs_dim, generator=g), torch.randn(n, state_dim, generator=g)
    d = dg.plasticity_diagnostics(actor, critic, obs, state)
    n_exp = 1 if METHOD_REGISTRY[kind].network == "mlp" else 3
    assert all(isinstance(v, float) for v in d.values())
    for name in ("stable", "effective", "srank"):
        assert f"rank/{name}/mean" in d
        vals = [d[f"rank/{name}/expert{j}"] for j in range(n_exp)]
        assert d[f"rank/{name}/mean"] == pytest.approx(np.mean(vals))
    for which in ("paper", "tau"):
        for layer in (1, 2):
            assert 0.0 <= d[f"dormant/{which}/layer{layer}"] <= 1.0
        assert f"dormant/{which}/mean" in d
    for which in ("policy", "value"):
        probs = [d[f"router/{which}/p{j}"] for j in range(n_exp)]
        tops = [d[f"router/{which}/top{j}"] for j in range(n_exp)]
        assert sum(probs) == pytest.approx(1.0) and sum(tops) == pytest.approx(1.0)
    assert d["action/std_x"] == pytest.approx(0.3) and d["action/std_y"] == pytest.approx(0.3)
    # rank of expert 0 equals the formula on the probe's last-layer activations
    acts = actor.probe(obs)["act"][-1][0]
    assert d["rank/stable/expert0"] == pytest.approx(dg.stable_rank(acts))
    mean = actor.probe(obs)["mean"]
    assert d["action/mean_x"] == pytest.approx(float(mean[:, 0].mean()), abs=1e-7)
    # without a critic / probe state there are no value-router keys
    assert not any(k.startswith("router/value") for k in dg.plasticity_diagnostics(actor, None, obs))


def test_same_keys_for_every_moe_kind():
    keys = [set(dg.plasticity_diagnostics(make_actor(k, 6), make_critic(k, 7), torch.randn(8, 6), torch.randn(8, 7))) for k in (n for n, sp in METHOD_REGISTRY.items() if sp.network != "mlp")]
    assert keys[0] == keys[1] == keys[2]
