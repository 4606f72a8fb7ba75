"""Theory checks (notebooks 08 and 08b): noise energy, L1 between mixtures, the tracking task, fits, Lipschitz."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import norm

from pemamoe.nets import make_actor
from pemamoe.theory import dynamic_regret, noise_energy, noise_schedule, window_coverage
from pemamoe.toy_tracking import (
    DISTRIBUTIONS,
    TrackerConfig,
    TrackingProblem,
    TrackingProblemConfig,
    fit_power_law,
    gaussian_l1,
    lipschitz_envelope,
    lipschitz_nnls,
    lipschitz_ratio,
    mc_l1_distance,
    mixture_weights,
    moe_components,
    paired_distance,
    perturb_actor,
    run_tracker,
    switch_times,
    tie_states,
    top1_win_probs,
)

# --- noise schedule and energy --------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    K=st.integers(0, 8),
    N=st.integers(0, 20),
    gap=st.integers(0, 10),
    gamma=st.floats(0.0, 1.0, allow_nan=False),
)
def test_energy_identity_disjoint_windows(K, N, gap, gamma):
    starts = [5 + k * (N + gap) for k in range(K)]
    T = 5 + K * (N + gap) + 3
    sched = noise_schedule(T, starts, gamma, N)
    assert noise_energy(sched) == gamma**2 * (K * N)  # bit for bit
    assert np.count_nonzero(sched) == (K * N if gamma > 0 else 0)


@settings(max_examples=60, deadline=None)
@given(
    starts=st.lists(st.integers(0, 60), min_size=0, max_size=8),
    N=st.integers(0, 15),
    gamma=st.floats(1e-4, 1.0),
    T=st.integers(1, 70),
)
def test_energy_with_overlaps_is_union_and_bounded(starts, N, gamma, T):
    sched = noise_schedule(T, starts, gamma, N)
    cover = np.zeros(T, bool)
    for s in starts:
        cover[s : s + N] = True
    assert np.array_equal(window_coverage(T, starts, N), cover)
    assert noise_energy(sched) == gamma**2 * int(cover.sum())
    assert noise_energy(sched) <= gamma**2 * len(starts) * N * (1 + 1e-15)
    assert set(np.unique(sched)) <= {0.0, gamma}  # a level: overlaps never stack


def test_noise_schedule_hand_example_and_validation():
    s = noise_schedule(10, [2, 4], 0.5, 3)
    assert s.tolist() == [0, 0, 0.5, 0.5, 0.5, 0.5, 0.5, 0, 0, 0]
    assert noise_energy(s) == 5 * 0.25
    for bad in (dict(T=-1), dict(window=-2), dict(gamma=-0.1), dict(gamma=float("nan")), dict(switch_times=[-1])):
        kw = dict(T=10, switch_times=[2], gamma=0.1, window=3) | bad
        with pytest.raises(ValueError):
            noise_schedule(**kw)


# --- L1 between Gaussian mixtures -----------------------------------------------------------------


@pytest.mark.parametrize("dmu,sigma", [(0.0, 1.0), (0.05, 0.5), (1.0, 1.0), (2.0, 0.7), (6.0, 1.0)])
def test_mc_l1_matches_closed_form_two_gaussians(dmu, sigma):
    exact = 2 * (2 * norm.cdf(abs(dmu) / (2 * sigma)) - 1)
    assert gaussian_l1([0.0], [dmu], [sigma]) == pytest.approx(exact, abs=1e-12)
    p = (np.ones((1, 1)), np.zeros((1, 1, 1)), np.array([sigma]))
    q = (np.ones((1, 1)), np.full((1, 1, 1), dmu), np.array([sigma]))
    est, se = mc_l1_distance(p, q, np.random.default_rng(0), 40000)
    assert abs(est[0] - exact) <= 4 * se[0] + 1e-3
    if dmu > 0:
        assert abs(est[0] - exact) <= 0.05 * exact + 1e-3  # relative precision even when tiny


def test_mc_l1_mixture_properties():
    rng = np.random.default_rng(1)
    w = np.array([[0.3, 0.7], [1.0, 0.0]])
    mu = rng.standard_normal((2, 2, 2))
    std = np.array([0.4, 0.6])
    same, _ = mc_l1_distance((w, mu, std), (w, mu, std), rng, 512)
    assert np.allclose(same, 0.0)
    # two mixtures with disjoint far-apart supports: L1 = 2
    far, _ = mc_l1_distance((w, mu, std), (w, mu + 100.0, std), rng, 512)
    assert np.allclose(far, 2.0)
    # weights-only change of a mixture of two far-apart components: L1 = ||dw||_1
    mu2 = np.stack([np.zeros(2), np.full(2, 100.0)])[None].repeat(2, 0)
    w2 = np.array([[0.5, 0.5], [0.9, 0.1]])
    est, _ = mc_l1_distance((w, mu2, std), (w2, mu2, std), rng, 4000)
    assert np.allclose(est, np.abs(w - w2).sum(-1), atol=0.05)


# --- the tracking task and the regret accumulator ---------------------------------------------------


def test_tracking_problem_optimum_and_zero_regret():
    prob = TrackingProblem(TrackingProblemConfig(n_phases=3, shift=0.8, init_scale=1.5), seed=3)
    rng = np.random.default_rng(0)
    x = rng.standard_normal((200, 4))
    for k in range(3):
        best = prob.reward(x, prob.optimal_action(x, k), k)
        for _ in range(20):
            a = prob.optimal_action(x, k) + rng.normal(0, 0.3, (200, 2))
            assert np.all(prob.reward(x, a, k) <= best + 1e-12)
        assert np.all(best <= 0)
        opt_means = prob.optimal_action(prob.probe, k)
        assert prob.value(opt_means, k) == prob.optimal_value(k)
    phases = np.array([0, 0, 1, 1, 2])
    opt = [prob.optimal_value(p) for p in phases]
    vals = [prob.value(prob.optimal_action(prob.probe, p), p) for p in phases]
    assert np.array_equal(dynamic_regret(opt, vals), np.zeros(5))
    assert np.allclose(prob.shifts(), 0.8)  # successive optima are `shift` apart in L2(x)
    xt = torch.tensor(x, dtype=torch.float32)
    assert torch.allclose(prob.reward(xt, xt[:, :2], 1), torch.tensor(prob.reward(x, x[:, :2], 1), dtype=torch.float32), atol=1e-5)


def test_dynamic_regret_hand_example():
    assert dynamic_regret([0, 0, 1, 1], [-1, -0.5, 0.5, 1]).tolist() == [1.0, 1.5, 2.0, 2.0]
    with pytest.raises(ValueError):
        dynamic_regret([0, 1], [0])


def test_switch_times_and_configs():
    assert switch_times(300, 2) == [100, 200]
    assert switch_times(10, 0) == []
    with pytest.raises(ValueError, match="TrackerConfig.kind"):
        TrackerConfig(kind="transformer")
    with pytest.raises(ValueError, match="TrackingProblemConfig.shift"):
        TrackingProblemConfig(shift=-1.0)


def test_run_tracker_pairing_and_pulses(one_thread):
    prob = TrackingProblem(TrackingProblemConfig(n_phases=3, probe_size=64), seed=0)
    base = dict(iterations=24, n_switches=2, batch=16, epochs=2, noise_epochs=3)
    clean = run_tracker(prob, TrackerConfig(controller="off", **base), seed=5)
    clean2 = run_tracker(prob, TrackerConfig(controller="noise", noise_gamma=0.0, **base), seed=5)
    noisy = run_tracker(prob, TrackerConfig(controller="noise", noise_gamma=0.05, **base), seed=5)
    assert np.array_equal(clean.values, clean2.values)  # gamma = 0: the twin is reproduced exactly
    assert clean.noise_energy == 0.0
    # pulses: N + 1 per switch, in exactly the slots of noise_schedule with a window of N + 1; gamma
    # at each switch, then each expert gamma x its share of the epoch (the trainer's controller), so
    # a pulse's RMS amplitude over three equal experts lies in [gamma / 3, gamma / sqrt(3)]
    expected = noise_schedule(24 * 2 + 1, [2 * t for t in noisy.switches], 0.05, 3 + 1)
    slots = noisy.noise_slots()
    at_switch = [2 * t for t in noisy.switches]
    assert np.array_equal(slots > 0, expected > 0) and np.all(slots[at_switch] == 0.05)
    epochs = np.delete(slots, at_switch)
    epochs = epochs[epochs > 0]
    assert len(epochs) == 2 * 3 and np.all(epochs >= 0.05 / 3 - 1e-12) and np.all(epochs <= 0.05 / math.sqrt(3) + 1e-12)
    assert noisy.noise_energy == pytest.approx(float(np.sum(slots**2))) and noisy.noise_energy < 0.05**2 * 2 * 4
    # the MLP (one expert, always used) gets gamma after every epoch: noise_schedule itself, bit for bit
    mlp = run_tracker(prob, TrackerConfig(kind="mlp", controller="noise", noise_gamma=0.05, **base), seed=5)
    assert np.array_equal(mlp.noise_slots(), expected) and mlp.noise_energy == 0.05**2 * 2 * 4
    d = paired_distance(clean, noisy)
    assert d["policy_mean"] > 0 and d["energy"] == noisy.noise_energy
    first = noisy.switches[0]
    assert np.array_equal(noisy.values[:first], clean.values[:first])  # identical before any noise
    assert np.all(np.diff(noisy.regret) >= -1e-12)  # instantaneous regret is >= 0


def test_run_tracker_uses_the_trainers_controller(monkeypatch):
    """The theory check's noise comes from the controller class the trainer runs, through its hooks."""
    from pemamoe.phase_controller import PhaseController

    calls = []
    for hook in ("on_switch", "after_epoch"):
        real = getattr(PhaseController, hook)

        def spy(self, *args, _real=real, _hook=hook):
            calls.append(_hook)
            return _real(self, *args)

        monkeypatch.setattr(PhaseController, hook, spy)
    prob = TrackingProblem(TrackingProblemConfig(n_phases=2, probe_size=16), seed=0)
    run = run_tracker(prob, TrackerConfig(iterations=6, n_switches=1, batch=8, epochs=2, noise_epochs=2), seed=1)
    assert calls.count("on_switch") == 1 and calls.count("after_epoch") == 6 * 2
    assert len(run.pulses) == 1 + 2


# --- fits --------------------------------------------------------------------------------------------


def test_fit_power_law_recovers_exponent():
    rng = np.random.default_rng(0)
    x = np.repeat(np.geomspace(10, 1000, 8), 5)
    y = 3.0 * x**0.75 * np.exp(rng.normal(0, 0.1, x.size))
    f = fit_power_law(x, y, np.random.default_rng(1), n_boot=500)
    assert f["ci_low"] <= 0.75 <= f["ci_high"]
    assert abs(f["slope"] - 0.75) < 0.05 and f["ci_high"] - f["ci_low"] < 0.1
    # two regressors, grouped bootstrap
    v = rng.uniform(0.5, 8, x.size)
    y2 = 2.0 * x**0.75 * v**0.25 * np.exp(rng.normal(0, 0.05, x.size))
    f2 = fit_power_law(np.column_stack([x, v]), y2, np.random.default_rng(2), n_boot=300, groups=np.arange(x.size) % 5)
    assert np.allclose(f2["slope"], [0.75, 0.25], atol=0.05)
    assert np.all(f2["ci_low"] <= [0.75, 0.25]) and np.all(f2["ci_high"] >= [0.75, 0.25])
    with pytest.raises(ValueError):
        fit_power_law([1, 2, 3], [1, 0, 2], rng)


def test_lipschitz_estimators_on_linear_map():
    rng = np.random.default_rng(0)
    M = np.array([[3.0, 1.0], [0.0, 2.0]])
    op = np.linalg.norm(M, 2)
    dx = rng.standard_normal((5000, 2))
    dy = dx @ M.T
    est = lipschitz_ratio(dy, dx)
    assert est <= op + 1e-12 and est >= 0.999 * op
    assert lipschitz_ratio(dy, dx, q=0.5) < est
    # envelope and least squares on y = U @ L with known L (some samples strictly inside)
    U = rng.uniform(0, 1, (300, 3))
    L = np.array([2.0, 0.5, 1.5])
    y = U @ L
    y[::2] *= 0.5
    assert np.allclose(lipschitz_envelope(y, U), L, atol=1e-6)
    assert np.allclose(lipschitz_nnls(U @ L, U), L, atol=1e-8)
    with pytest.raises(ValueError):
        lipschitz_ratio([1.0], [0.0])


# --- MoE components, routing ties -------------------------------------------------------------------


def _actor(seed=0, gain_router=1.0):
    from pemamoe.nets import NetConfig

    torch.manual_seed(seed)
    actor = make_actor("pemamoe", 4, 2, NetConfig(gain_router=gain_router))
    with torch.no_grad():
        actor.head.weight.mul_(100.0)  # distinct expert means, as after training
    return actor


def test_components_match_the_actor_and_win_probs():
    actor = _actor()
    x = np.random.default_rng(0).standard_normal((5, 4))
    comp = moe_components(actor, x)
    with torch.no_grad():
        det = actor(torch.tensor(x, dtype=torch.float32), deterministic_gate=True)[0].mean.double().numpy()
    assert np.allclose(comp["means"][np.arange(5), comp["gate"].argmax(-1)], det, atol=1e-6)
    for dist in DISTRIBUTIONS:
        w = mixture_weights(comp, dist)
        assert np.allclose(w.sum(-1), 1.0)
    # quadrature against Monte Carlo of the noisy argmax
    rng = np.random.default_rng(0)
    z, s = rng.normal(0, 1, (3, 3)), rng.uniform(0.3, 1.5, (3, 3))
    eps = rng.standard_normal((200000, 3, 3))
    mc = np.stack([(np.argmax(z + s * eps, -1) == k).mean(0) for k in range(3)], -1)
    assert np.allclose(top1_win_probs(z, s), mc, atol=0.005)


def test_perturbation_sizes_and_ties_break_eval_top1():
    actor = _actor()
    rng = np.random.default_rng(0)
    new, d_router, d_theta = perturb_actor(actor, 0.01, 0.02, rng)
    r_old = torch.cat([p.detach().reshape(-1) for p in actor.gate.router.parameters()])
    r_new = torch.cat([p.detach().reshape(-1) for p in new.gate.router.parameters()])
    assert float((r_new - r_old).norm()) == pytest.approx(d_router, rel=1e-4)
    assert d_router == pytest.approx(0.01 * float(r_old.norm()), rel=1e-6)
    assert d_theta.shape == (3,) and np.all(d_theta > 0)
    from pemamoe.phase_controller import expert_parameters

    one, _, d1 = perturb_actor(actor, 0.0, 0.05, rng, experts=[1])
    assert d1[0] == d1[2] == 0 and d1[1] > 0
    for k in range(3):
        moved = sum(float((a - b).detach().norm() ** 2) for a, b in zip(expert_parameters(one, k), expert_parameters(actor, k)))
        assert math.sqrt(moved) == pytest.approx(d1[k], rel=1e-4, abs=1e-7)
    ties = tie_states(actor, 8, rng)
    g = np.sort(moe_components(actor, ties)["gate"], -1)
    assert np.all(g[:, -1] - g[:, -2] < 1e-6)
    # on a tie, the eval top-1 distribution jumps under a router change that barely moves the gate
    flips = 0
    for _ in range(10):
        new, _, _ = perturb_actor(actor, 1e-3, 0.0, rng)
        a, b = moe_components(actor, ties), moe_components(new, ties)
        flip = a["gate"].argmax(-1) != b["gate"].argmax(-1)
        if flip.any():
            wa, wb = mixture_weights(a, "eval_top1"), mixture_weights(b, "eval_top1")
            l1, _ = mc_l1_distance((wa, a["means"], a["std"]), (wb, b["means"], b["std"]), rng, 256)
            dg = np.abs(a["gate"] - b["gate"]).sum(-1)
            assert np.all(l1[flip] / dg[flip] > 10)
            flips += int(flip.sum())
    assert flips > 0
