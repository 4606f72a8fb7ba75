"""Analysis (notebook 09, pemamoe.analysis): labels from each run's own config.json, methods from the
registry, experts ordered by usage per seed, cached heuristic reference levels."""

import json
import shutil

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402

from pemamoe import analysis  # noqa: E402
from pemamoe.core import atomic_write_json  # noqa: E402
from pemamoe.mappo import TrainConfig, train  # noqa: E402
from pemamoe.methods import METHOD_REGISTRY, MethodSpec, proposed_method, register_method  # noqa: E402
from pemamoe.records import write_record  # noqa: E402


@pytest.fixture(scope="module")
def ablated_run(tmp_path_factory):
    cfg = TrainConfig.for_scale("ci", proposed_method(), 0, without=("lr_drop",), iterations=4)
    folder = tmp_path_factory.mktemp("runs") / "ablated"
    train(cfg, folder)
    return cfg, folder


def test_load_runs_labels_come_from_the_runs_own_config(ablated_run, tmp_path):
    cfg, folder = ablated_run
    d = shutil.copytree(folder, tmp_path / "run")
    # a marker left by another experiment (or another run) must not relabel the run
    atomic_write_json(d / "sweep.json", {"spec": {"method": "mlp", "seed": 7, "without": [], "tag": "noise"}})
    metrics, episodes = analysis.load_runs([write_record(d, "ci", tmp_path / "records")])
    for frame in (metrics, episodes):
        row = frame.iloc[0]
        assert set(analysis.RUN_COLUMNS) <= set(frame.columns)
        assert (row.method, row.seed, row.without) == (cfg.method, 0, "lr_drop")
        assert row.label == cfg.label() and row.variant == "w/o lr_drop" and not row.force_controller
        assert row.noise_gamma == cfg.controller.noise_gamma
        assert frame[list(analysis.RUN_COLUMNS)].drop_duplicates().shape[0] == 1
    scores = analysis.run_scores(episodes)
    assert len(scores) == 1 and scores.label.iloc[0] == cfg.label()


def test_run_labels_of_a_baseline_with_the_controller_and_of_a_plain_baseline():
    forced = TrainConfig.for_scale("ci", "moe", 1, force_controller=True, noise_gamma=0.01,
                                   without=tuple(m for m in analysis_mechanisms() if m != "noise_injection"))
    lab = analysis.run_labels(forced.to_dict(), "r")
    assert lab["variant"] == "+ noise_injection" and lab["force_controller"] and lab["noise_gamma"] == 0.01
    assert lab["label"] == forced.label() and lab["method"] == "moe" and lab["seed"] == 1
    plain = analysis.run_labels(TrainConfig.for_scale("ci", "mlp", 0).to_dict())
    assert (plain["without"], plain["variant"], plain["label"]) == ("none", "", "MLP")


def analysis_mechanisms():
    from pemamoe.phase_controller import MECHANISMS

    return MECHANISMS


@pytest.fixture
def plugin_method():
    spec = register_method(MethodSpec("zz_plugin", network="mlp", label="Plugin", colour="#123456"))
    yield spec
    del METHOD_REGISTRY["zz_plugin"]


def test_method_order_follows_the_registry_and_keeps_unknown_names(plugin_method):
    assert analysis.method_order() == [m for m, spec in METHOD_REGISTRY.items() if spec.compared]
    assert analysis.method_order()[-1] == "zz_plugin" and "smoe_redo" not in analysis.method_order()
    assert analysis.method_order({"smoe_redo", "mlp"}) == ["mlp", "smoe_redo"]  # named, it takes its place
    assert analysis.method_order({"zz_plugin", "unknown", proposed_method(), "mlp"}) == [
        "mlp", proposed_method(), "zz_plugin", "unknown"]
    assert analysis.is_proposed(proposed_method()) and not analysis.is_proposed("zz_plugin")


def synthetic_metrics(method_probs: dict) -> pd.DataFrame:
    """method_probs: {(method, seed): (T, E) probabilities}; every other iteration has no diagnostics."""
    frames = []
    for (method, seed), p in method_probs.items():
        T, E = p.shape
        f = pd.DataFrame({"iteration": np.arange(T), "phase": (np.arange(T) // 4) % 3,
                          "switch": np.r_[False, np.diff((np.arange(T) // 4) % 3) != 0],
                          "served_users": np.linspace(0, 1, T)})
        for j in range(E):
            col = p[:, j].astype(float).copy()
            col[1::2] = np.nan
            f[f"router/policy/p{j}"] = col
        frames.append(f.assign(run=f"{method}-{seed}", method=method, seed=seed))
    return pd.concat(frames, ignore_index=True)


def test_experts_are_ordered_by_usage_within_each_seed():
    T = 12
    heavy0 = np.tile([0.6, 0.3, 0.1], (T, 1))  # seed 0 uses expert 0 most
    heavy2 = np.tile([0.1, 0.3, 0.6], (T, 1))  # seed 1 uses expert 2 most
    mlp = np.ones((T, 1))
    m = synthetic_metrics({("smoe", 0): heavy0, ("smoe", 1): heavy2, ("mlp", 0): mlp})
    ranked = analysis.experts_by_usage(m, "policy")
    assert set(ranked.method) == {"smoe"}  # one expert: nothing to order
    assert ranked.p.notna().all() and set(ranked.iteration) == set(range(0, T, 2))
    top = ranked[ranked.usage_rank == 1].groupby("seed").expert.first().to_dict()
    assert top == {0: 0, 1: 2}
    mean_by_rank = ranked.groupby("usage_rank").p.mean()
    np.testing.assert_allclose(mean_by_rank.to_numpy(), [0.6, 0.3, 0.1])  # not 0.35, 0.3, 0.35 by raw index
    # ties go to the lower index, so the order is deterministic
    tied = analysis.experts_by_usage(synthetic_metrics({("moe", 0): np.full((T, 2), 0.5)}), "policy")
    assert tied[tied.usage_rank == 1].expert.unique().tolist() == [0]
    assert analysis.experts_by_usage(synthetic_metrics({("mlp", 0): mlp}), "policy").empty


def test_reference_levels_are_cached_and_named_as_the_training_curves(tmp_path):
    levels = analysis.reference_levels("ci", tmp_path)
    path = tmp_path / "ci" / "reference_levels.csv"
    first = path.read_bytes()
    assert set(analysis.CURVE_COLUMNS.values()) <= set(levels.columns)
    assert sorted(zip(levels.policy, levels.phase)) == sorted((p, k) for p in analysis.REFERENCE_POLICIES for k in range(3))
    again = analysis.reference_levels("ci", tmp_path)
    pd.testing.assert_frame_equal(levels, again)
    assert path.read_bytes() == first
    # a stale table (another environment) is recomputed
    stale = levels.assign(key="0" * 16)
    path.write_text(stale.to_csv(index=False))
    pd.testing.assert_frame_equal(analysis.reference_levels("ci", tmp_path), levels)


def test_plot_over_training_draws_any_method_and_the_reference_levels(plugin_method):
    m = synthetic_metrics({("zz_plugin", 0): np.ones((12, 1)), ("unregistered", 0): np.ones((12, 1))})
    levels = pd.DataFrame([{"policy": p, "phase": k, "served_users": 0.1 * k + (p == "kmeans")}
                           for p in analysis.REFERENCE_POLICIES for k in range(3)])
    fig, ax = plt.subplots()
    analysis.plot_over_training(ax, m, "served_users", reference=levels)
    labels = [line.get_label() for line in ax.get_lines()]
    assert labels[:2] == ["Plugin", "unregistered"]
    assert ax.get_lines()[0].get_color() == "#123456"
    segments = [c for c in ax.collections if c.get_label() and "per phase" in c.get_label()]
    assert len(segments) == 2  # one legend entry per heuristic
    from matplotlib.collections import LineCollection

    assert analysis.phase_blocks(m) == [(0, 4, 0), (4, 8, 1), (8, 11, 2)]
    hlines = [c for c in ax.collections if isinstance(c, LineCollection)]
    assert len(hlines) == 2 * 3  # each heuristic, each phase block
    plt.close(fig)


def test_phase_visits_are_inclusive_and_phase_blocks_join_them():
    import pandas as pd

    from pemamoe.analysis import phase_blocks, phase_visits

    phases = [0, 0, 0, 1, 1, 2, 2, 2, 0]
    frame = pd.DataFrame({"run": "a", "iteration": range(len(phases)), "phase": phases})
    assert phase_visits(frame) == [(0, 2, 0), (3, 4, 1), (5, 7, 2), (8, 8, 0)]
    assert phase_blocks(frame) == [(0, 3, 0), (3, 5, 1), (5, 8, 2), (8, 8, 0)]


def test_claim_verdict_needs_an_interval_on_the_papers_side_of_zero():
    from pemamoe.analysis import claim_verdict

    assert claim_verdict(2.0, 9.0, 26.3).startswith("reproduced")
    assert claim_verdict(-80.0, -10.0, -75.0).startswith("reproduced")
    assert claim_verdict(-30.0, -1.0, 26.3).startswith("contradicted")
    assert claim_verdict(-5.0, 4.0, 26.3).startswith("not resolved (interval contains 0)")
    assert claim_verdict(-28.0, -28.0, 26.3) == "not resolved (no interval: one seed)"
    assert claim_verdict(float("nan"), float("nan"), -75.0).startswith("undefined")
    assert claim_verdict(2.0, 9.0, 0.0).startswith("undefined")


def test_bootstrap_intervals_do_not_depend_on_numpys_global_generator():
    # rliable draws resampling indices from np.random; the analysis seeds it for each call and
    # puts the caller's state back, so a second `make figures` writes the same intervals
    rng = np.random.default_rng(3)
    rows = [{"method": m, **{k: rng.random() for k in analysis.SUMMARY_METRICS}} for m in ("a", "b") for _ in range(5)]
    norm = pd.DataFrame(rows)
    results = []
    for global_seed in (1, 2):
        np.random.seed(global_seed)
        before = np.random.get_state()[1].copy()
        poi = analysis.probability_of_improvement(norm, "a", ["b"], reps=200)
        iqm = analysis.bootstrap_iqm(norm, ["a", "b"], reps=200)
        assert np.array_equal(np.random.get_state()[1], before)  # the caller's generator is untouched
        results.append((poi.to_numpy().tolist(), [iqm[m][1].tolist() for m in ("a", "b")]))
    assert results[0] == results[1]
