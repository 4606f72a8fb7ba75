"""The learning-budget study (notebook 09b): fixed-phase runs, the per-environment phase of the
environment, the study's run list and its read-out (plateau, steps to 85 %)."""

import numpy as np
import pandas as pd
import pytest
import torch

from pemamoe.budget import plateau_table, reading_gaps, seconds_to_reach, with_fixed_phase_twins
from pemamoe.env import EnvConfig, UAVVectorEnv
from pemamoe.mappo import TrainConfig, check_population, population_key, train, train_population
from pemamoe.experiments import BUDGET_READINGS, RunSpec, budget_specs, default_reading, group_specs

from test_population import _assert_same_run


pytestmark = pytest.mark.usefixtures("one_thread")


def fixed(method="mlp", seed=0, phase=0, **kw):
    return TrainConfig.for_scale("ci", method=method, seed=seed, fixed_phase=phase, iterations=4,
                                 phase_length_iters=4, **kw)


def test_env_takes_one_phase_or_one_per_environment():
    cfg = EnvConfig(phase_clock="external")
    env = UAVVectorEnv(seeds=[0, 1, 2], cfg=cfg)
    env.set_phase([2, 0, 1])
    env.reset()
    assert env.core.phase.tolist() == [2, 0, 1]
    other = UAVVectorEnv(seeds=[0, 1, 2], cfg=cfg)
    other.load_state_dict(env.state_dict())
    for _ in range(3):
        other.step(np.zeros((3, other.n_agents, other.act_dim), dtype=np.float32))
    assert other.core.phase.tolist() == [2, 0, 1]  # the per-environment phase survives a save/restore and steps
    env.set_phase(1)
    env.reset()
    assert env.core.phase.tolist() == [1, 1, 1]
    for bad in ([0, 1], [0, 1, 9], -1, 1.5, [[0, 1, 2]]):
        with pytest.raises(ValueError, match="phase must be an integer in"):
            env.set_phase(bad)


def test_fixed_phase_member_is_identical_alone_and_next_to_other_phases(tmp_path):
    cfgs = [fixed(seed=0, phase=2), fixed(seed=1, phase=0), fixed(seed=2, phase=1)]
    pop = train_population(cfgs, [tmp_path / f"p{i}" for i in range(3)])
    alone = train(cfgs[0], tmp_path / "alone")
    _assert_same_run(alone, pop[0], tmp_path / "alone", tmp_path / "p0")
    for cfg, res in zip(cfgs, pop):
        assert (res.metrics.phase == cfg.fixed_phase).all() and not res.metrics.switch.any()
        assert (res.episodes.phase == cfg.fixed_phase).all()


def test_fixed_phase_is_validated_and_cannot_mix_with_cycling_members():
    with pytest.raises(ValueError, match=r"TrainConfig.fixed_phase must be an integer in \[0, 3\) or None.*got 3"):
        TrainConfig(fixed_phase=3)
    with pytest.raises(ValueError, match="fixed_phase"):
        check_population([fixed(phase=0), TrainConfig.for_scale("ci", method="mlp", seed=1)])
    # a cycling run's identity (its cache folder) does not mention the new field
    assert "fixed_phase" not in TrainConfig.for_scale("ci").identity()
    assert population_key(fixed(phase=0)) == population_key(fixed(seed=3, phase=2))
    assert population_key(fixed(phase=0)) != population_key(TrainConfig.for_scale("ci", method="mlp", iterations=4,
                                                                                   phase_length_iters=4))


def test_budget_specs_cover_every_method_phase_and_seed_and_group_by_method():
    specs = budget_specs("small", seeds=(0, 1, 2), methods=("mlp", "pemamoe"))
    cfgs = [s.to_config() for s in specs]
    small = [c for c in cfgs if c.num_envs == 16]
    assert {(c.method, c.fixed_phase, c.seed) for c in small} == {
        (m, p, s) for m in ("mlp", "pemamoe") for p in (0, 1, 2) for s in (0, 1, 2)}
    assert all(c.total_env_steps >= 2_000_000 and c.phase_length_iters == c.iterations for c in cfgs)
    paper = [c for c in cfgs if c.num_envs == 64]
    assert [(c.method, c.fixed_phase, c.update_epochs, c.num_minibatches) for c in paper] == [("mlp", 0, 8, 32)] * 3
    sizes = sorted(len(g) for g in group_specs(specs, 16, 2))
    assert sizes == [3, 9, 9, 9]  # one population per method, actor reading and update setting
    with pytest.raises(ValueError, match="steps must be an integer >= 1"):
        budget_specs("small", steps=0)


def test_the_study_runs_the_gated_methods_under_each_actor_reading_and_mlp_once():
    specs = budget_specs("small", seeds=(0,), methods=("mlp", "smoe"), phases=(0,))
    assert [(s.method, s.tag) for s in specs] == [
        ("mlp", "budget/small"), ("smoe", "budget/small"), ("smoe", "budget/small/paper"), ("mlp", "budget/paper")]
    nets = {s.tag: s.to_config().net for s in specs if s.method == "smoe"}
    for tag, reading in (("budget/small", "ours"), ("budget/small/paper", "paper")):
        assert all(getattr(nets[tag], k) == v for k, v in BUDGET_READINGS[reading].items())
    # ours is the committed study: the same runs (identities) as before the reading axis existed
    ours = budget_specs("small", seeds=(0,), methods=("smoe",), phases=(0,), readings=("ours",))
    unpinned = [spec for spec in ours if spec.method == "smoe"][0]
    plain = RunSpec("smoe", 0, "small", overrides=tuple((k, v) for k, v in unpinned.overrides if k not in BUDGET_READINGS["ours"]),
                    tag="budget/small")
    if default_reading() == "ours":
        assert unpinned.to_config().run_name() == plain.to_config().run_name()
    with pytest.raises(ValueError, match=r"budget reading must be one of ours, paper, got 'top-3'"):
        budget_specs("small", readings=("top-3",))


def test_default_reading_names_the_reading_the_netconfig_defaults_are(monkeypatch):
    import pemamoe.experiments as sweep

    assert default_reading() in BUDGET_READINGS
    for name, fields in BUDGET_READINGS.items():
        monkeypatch.setitem(sweep.BUDGET_READINGS, name, {**fields, "top_k": 3})
    with pytest.raises(ValueError, match="match none of the study's readings"):
        default_reading()


def test_the_defaults_are_the_papers_reading_and_their_study_lends_pemamoe_smoes_runs():
    """After issue 40 the NetConfig defaults are the paper's reading; its study runs SMoE only (in a
    fixed phase PE-MAMoE trains as SMoE), so PE-MAMoE's yardstick rows are SMoE's, renamed, and a
    method with runs of its own (or no twin: MLP, MoE) is left as it is."""
    assert default_reading() == "paper"
    paper = budget_specs("ci", readings=("paper",))
    assert {s.method for s in paper} == {"mlp", "moe", "smoe"}
    rows = pd.DataFrame({"method": ["smoe", "smoe", "mlp"], "run": ["s0", "s1", "m0"], "coverage": [0.5, 0.6, 0.7]})
    out = with_fixed_phase_twins(rows)
    twin = out[out.method == "pemamoe"]
    assert list(twin.coverage) == [0.5, 0.6] and list(twin.run) == ["s0", "s1"]
    assert sorted(out.method) == ["mlp", "pemamoe", "pemamoe", "smoe", "smoe"]
    own = pd.concat([rows, rows[rows.method == "smoe"].assign(method="pemamoe", coverage=0.1)], ignore_index=True)
    assert with_fixed_phase_twins(own).equals(own)


def test_a_member_of_a_learning_rate_and_entropy_grid_trains_as_it_would_alone(tmp_path):
    net = BUDGET_READINGS["paper"]
    cfgs = [fixed("smoe", seed=0, **net), fixed("smoe", seed=0, lr=1e-3, ent_start=0.02, ent_end=0.006, **net),
            fixed("smoe", seed=1, lr=1e-4, **net)]
    assert len({population_key(c) for c in cfgs}) == 1  # one population for the tuning grid of a method
    pop = train_population(cfgs, [tmp_path / f"p{i}" for i in range(3)])
    alone = train(cfgs[1], tmp_path / "alone")
    _assert_same_run(alone, pop[1], tmp_path / "alone", tmp_path / "p1")
    assert pop[0].metrics.ent_coef.iloc[0] != pop[1].metrics.ent_coef.iloc[0]


def test_pemamoe_in_a_fixed_phase_trains_as_smoe_bit_for_bit(tmp_path):
    from pemamoe.experiments import fixed_phase_twin

    assert fixed_phase_twin("pemamoe", ("mlp", "smoe", "pemamoe")) == "smoe"
    assert fixed_phase_twin("pemamoe", ("mlp", "pemamoe")) is None and fixed_phase_twin("smoe_redo", ("smoe",)) is None
    net = BUDGET_READINGS["paper"]
    smoe = train(fixed("smoe", phase=1, **net), tmp_path / "smoe")
    pemamoe = train(fixed("pemamoe", phase=1, **net), tmp_path / "pemamoe")
    pd.testing.assert_frame_equal(smoe.episodes, pemamoe.episodes)
    shared = [c for c in smoe.metrics.columns if c in pemamoe.metrics.columns and "time" not in c and "sps" not in c]
    pd.testing.assert_frame_equal(smoe.metrics[shared], pemamoe.metrics[shared])
    for net_name in ("actor", "critic"):
        for (na, ta), (nb, tb) in zip(getattr(smoe, net_name).state_dict().items(),
                                      getattr(pemamoe, net_name).state_dict().items()):
            assert na == nb and torch.equal(ta, tb), (net_name, na)
    # the study runs PE-MAMoE under the committed reading only
    assert {s.tag for s in budget_specs("small", seeds=(0,), methods=("smoe", "pemamoe"), phases=(0,))
            if s.method == "pemamoe"} == {"budget/small"}


def test_reading_gaps_from_hand_made_curves():
    steps = np.arange(1, 11) * 100_000
    rows = []
    for method, reading, level in (("mlp", "none", 0.8), ("smoe", "ours", 0.68), ("smoe", "paper", 0.76)):
        for seed, jitter in ((0, -0.02), (1, 0.02)):
            rows += [{"method": method, "reading": reading, "phase": 0, "seed": seed, "env_steps": x,
                      "coverage": (level + jitter) if x > 900_000 else 0.1} for x in steps]
    table = reading_gaps(pd.DataFrame(rows)).set_index(["method", "reading"])
    assert table.loc[("mlp", "none"), "gap_to_mlp"] == pytest.approx(0.0)
    assert table.loc[("smoe", "ours"), "plateau"] == pytest.approx(0.68)  # the last 10 %: the final block
    assert table.loc[("smoe", "ours"), "gap_to_mlp"] == pytest.approx(0.12)
    assert table.loc[("smoe", "paper"), "gap_to_mlp"] == pytest.approx(0.04)
    assert table.loc[("smoe", "paper"), ["lowest", "highest", "seeds"]].tolist() == pytest.approx([0.74, 0.78, 2])
    with pytest.raises(ValueError, match="the baseline 'moe' has no runs"):
        reading_gaps(pd.DataFrame(rows), baseline="moe")


def test_plateau_and_steps_to_85_percent_from_hand_made_curves():
    steps = np.arange(1, 11) * 100_000
    rise = np.array([0.2, 0.4, 0.5, 0.6, 0.7, 0.75, 0.78, 0.8, 0.8, 0.8])
    rows = [{"method": "mlp", "settings": "small", "phase": 0, "seed": s, "run": f"r{s}", "env_steps": x,
             "coverage": y + d, "compute_s": x / 1000} for s, d in ((0, -0.01), (1, 0.01)) for x, y in zip(steps, rise)]
    curves = pd.DataFrame(rows)
    table = plateau_table(curves)
    row = table.iloc[0]
    assert row.plateau == pytest.approx(0.8)  # last 10 % of 1M steps: the final block only
    assert row.steps_to_85pct == 500_000  # 0.7 >= 0.85 * 0.8 = 0.68, 0.6 is not
    assert row.first_block == pytest.approx(0.2)
    hit = seconds_to_reach(curves, 0.75).iloc[0]
    assert hit.env_steps == 600_000 and hit.compute_s == pytest.approx(600.0)
    assert np.isnan(seconds_to_reach(curves, 0.9).iloc[0].env_steps)


def test_phase_learning_reads_the_last_tenth_of_each_visit_against_the_plateau():
    from pemamoe.budget import phase_learning

    rows = []
    for seed, shift in ((0, -0.05), (1, 0.05)):
        for it in range(40):  # 4 visits of 10 iterations: phases 0, 1, 2, 0
            phase = (it // 10) % 3
            rows.append({"run": f"mlp-s{seed}", "method": "mlp", "seed": seed, "iteration": it, "phase": phase,
                         "episodes": 2 if it % 10 == 9 else 1, "coverage": 0.1 * phase + it / 100 + shift})
    plateaus = pd.DataFrame({"method": "mlp", "phase": [0, 1, 2], "plateau": [0.5, 0.4, 0.5]})
    out = phase_learning(pd.DataFrame(rows), plateaus)
    assert out.visit.tolist() == [0, 1, 2, 3] and out.phase.tolist() == [0, 1, 2, 0]
    assert out.iterations.tolist() == ["0-9", "10-19", "20-29", "30-39"]
    # the last tenth of a 10-iteration visit is its last iteration: coverage it / 100 + 0.1 * phase
    assert out.coverage_last_10pct.tolist() == pytest.approx([0.09, 0.29, 0.49, 0.39])
    assert out.seed_min.tolist() == pytest.approx([0.04, 0.24, 0.44, 0.34])
    assert out.fraction_of_plateau.tolist() == pytest.approx([0.18, 0.725, 0.98, 0.78])


def test_budget_curves_weight_iterations_by_episodes_and_drop_the_last_partial_block():
    from pemamoe.budget import budget_curves

    steps = np.arange(1, 12) * 10  # 10 .. 110 steps; blocks of 20 end at 20, 40, ..., 100, and 120 (partial)
    m = pd.DataFrame({"method": "mlp", "settings": "small", "phase": 0, "seed": 0, "run": "r", "env_steps": steps,
                      "episodes": [1, 3] * 5 + [1], "coverage": np.linspace(0.1, 0.6, 11),
                      "member_seconds": 2.0})
    c = budget_curves(m, block_steps=20)
    assert c.env_steps.tolist() == [20, 40, 60, 80, 100]
    cov = np.linspace(0.1, 0.6, 11)
    assert c.coverage.iloc[0] == pytest.approx((cov[0] * 1 + cov[1] * 3) / 4)
    assert c.compute_s.tolist() == pytest.approx([4.0, 8.0, 12.0, 16.0, 20.0])


# --- the tuning grid (issue 38: every method tuned alike) ------------------------------------------
def test_tuning_grid_gives_every_method_the_same_settings_and_shares_its_centre_with_the_study():
    from pemamoe.experiments import BUDGET_READINGS, TUNING_ENTROPY, TUNING_LRS, tuning_specs

    specs = tuning_specs("small")
    cfgs = [s.to_config() for s in specs]
    # PE-MAMoE is SMoE in a fixed phase (its twin): three methods are run
    assert len({c.run_name() for c in cfgs}) == len(specs) == 3 * len(TUNING_LRS) * len(TUNING_ENTROPY) * 2
    grids = {}
    for c in cfgs:
        grids.setdefault(c.method, set()).add((c.lr, c.ent_start, c.ent_end, c.seed))
    assert sorted(grids) == ["mlp", "moe", "smoe"] and all(g == grids["mlp"] for g in grids.values())
    assert all(c.fixed_phase == 0 and c.total_env_steps >= 2_000_000 and c.num_envs == 16 for c in cfgs)
    for c in cfgs:
        if c.method != "mlp":  # the gated methods run the paper's actor readings
            assert all(getattr(c.net, k) == v for k, v in BUDGET_READINGS["paper"].items()), c.run_name()
    centre = {c.run_name() for c in cfgs if c.lr == 3e-4 and c.ent_start == 0.01}
    study = {s.to_config().run_name() for s in budget_specs("small", seeds=(0, 1), methods=("mlp", "moe", "smoe"))
             if dict(s.overrides)["fixed_phase"] == 0 and "num_envs" not in dict(s.overrides)
             and (s.method == "mlp" or s.tag.endswith("/paper"))}
    assert centre == study and len(centre) == 6  # the study's runs (MLP; MoE, SMoE read as the paper), not new ones
    with pytest.raises(ValueError, match="learning rate must be a float > 0, got 0"):
        tuning_specs("small", lrs=(0,))
    with pytest.raises(ValueError, match=r"\(ent_start, ent_end\) pairs >= 0, got \(0.01, -1\)"):
        tuning_specs("small", entropy=((0.01, -1),))


def test_tuning_table_reads_each_runs_last_tenth_and_marks_each_methods_best_setting():
    from pemamoe.budget import tuning_table

    steps = np.arange(1, 11) * 100
    rows, grid = [], {}
    for method, lr, seed, level in (("mlp", 1e-4, 0, 0.5), ("mlp", 1e-4, 1, 0.7), ("mlp", 3e-4, 0, 0.65),
                                    ("mlp", 3e-4, 1, 0.65), ("smoe", 1e-4, 0, 0.4)):
        run = f"{method}-{lr}-{seed}"
        grid[run] = (lr, 0.01, 0.003)
        for x in steps:  # the level only in the last block: the plateau reads the last tenth alone
            rows.append({"run": run, "method": method, "seed": seed, "env_steps": x,
                         "coverage": level if x == 1000 else 0.0, "member_seconds": 36.0})
    table = tuning_table(pd.DataFrame(rows), grid, centre=(1e-4, 0.01, 0.003)).set_index(["method", "lr"])
    assert table.loc[("mlp", 1e-4), "plateau"] == pytest.approx(0.6)
    assert table.loc[("mlp", 1e-4), "spread"] == pytest.approx(np.std([0.5, 0.7], ddof=1))
    assert table.loc[("mlp", 3e-4), "best"] and not table.loc[("mlp", 1e-4), "best"]  # 0.65 > 0.6
    assert table.loc[("smoe", 1e-4), "best"] and table.loc[("smoe", 1e-4), "seeds"] == 1
    assert table.loc[("mlp", 1e-4), "member_hours"] == pytest.approx(2 * 10 * 36 / 3600)
    # 0.65 vs the centre's 0.6 +- 0.141 (2 seeds): a lead of 0.05 < 2 x 0.1 standard errors, the centre stays
    assert table.loc[("mlp", 1e-4), "chosen"] and not table.loc[("mlp", 3e-4), "chosen"]
    assert table.loc[("smoe", 1e-4), "chosen"]  # its best is its centre


def test_tuning_moves_off_the_centre_only_when_the_lead_exceeds_the_seed_noise():
    from pemamoe.budget import TUNING_MARGIN, tuning_table

    def table(levels):  # lr -> the plateaus of its two seeds
        rows, grid = [], {}
        for lr, plateaus in levels.items():
            for seed, level in enumerate(plateaus):
                run = f"mlp-{lr}-{seed}"
                grid[run] = (lr, 0.01, 0.003)
                rows += [{"run": run, "method": "mlp", "seed": seed, "env_steps": x, "coverage": level,
                          "member_seconds": 1.0} for x in (1, 2)]
        return tuning_table(pd.DataFrame(rows), grid, centre=(3e-4, 0.01, 0.003)).set_index("lr")

    # spread 0.01 each: standard error of the difference 0.01; a lead of 0.03 > 2 x 0.01 moves
    moved = table({3e-4: (0.70, 0.70 + 0.01 * np.sqrt(2)), 1e-3: (0.73, 0.73 + 0.01 * np.sqrt(2))})
    assert moved.loc[1e-3, "chosen"] and not moved.loc[3e-4, "chosen"]
    kept = table({3e-4: (0.70, 0.70 + 0.01 * np.sqrt(2)), 1e-3: (0.715, 0.715 + 0.01 * np.sqrt(2))})
    assert TUNING_MARGIN == 2.0 and kept.loc[1e-3, "best"] and kept.loc[3e-4, "chosen"]
    with pytest.raises(ValueError, match=r"mlp has no run at the centre setting \(0.001, 0.02, 0.006\)"):
        tuning_table(pd.DataFrame([{"run": "a", "method": "mlp", "seed": 0, "env_steps": 1, "coverage": 0.5,
                                    "member_seconds": 1.0}]), {"a": (3e-4, 0.01, 0.003)}, centre=(1e-3, 0.02, 0.006))


def _cycling_run(levels, steps_per_iteration=100, iterations_per_visit=10):
    """One seed of a hand-made cycling run: visits of phases 0, 1, 0 at constant coverage `levels`."""
    rows, it = [], 0
    for phase, level in zip((0, 1, 0), levels):
        for _ in range(iterations_per_visit):
            rows.append({"method": "mlp", "run": "r0", "seed": 0, "iteration": it, "phase": phase,
                         "env_steps": (it + 1) * steps_per_iteration, "episodes": 1, "coverage": level})
            it += 1
    return pd.DataFrame(rows)


def _fresh_run(level, iterations, steps_per_iteration=100):
    return pd.DataFrame({"method": "mlp", "seed": 0, "phase": 0, "iteration": range(iterations),
                         "env_steps": [(i + 1) * steps_per_iteration for i in range(iterations)],
                         "episodes": 1, "coverage": level})


def test_revisit_learning_sets_a_revisit_against_its_first_visit_and_a_fresh_network_by_hand():
    from pemamoe.budget import revisit_learning

    plateaus = pd.DataFrame({"method": ["mlp"], "phase": [0], "plateau": [0.8]})
    out = revisit_learning(_cycling_run((0.6, 0.3, 0.5)), _fresh_run(0.7, 12), plateaus, bin_steps=100)
    row = out.iloc[0]
    assert len(out) == 1 and (row.phase, row.visit, row.first_visit, row.steps) == (0, 2, 0, 1000)
    assert row.revisit_minus_first_mean == pytest.approx(-0.1) and row.revisit_minus_fresh_mean == pytest.approx(-0.2)
    assert np.isnan(row.revisit_steps_to_target) and row.fresh_steps_to_target == 100  # 0.68 = 85 % of 0.8


def test_a_fresh_network_shorter_than_the_visit_is_not_compared():
    """Its mean over fewer steps is not the same area (the paper scale: a 2.46M-step visit against
    the study's 2M-step runs), so the revisit-minus-fresh differences are NaN, not a mean over less."""
    from pemamoe.budget import revisit_learning

    plateaus = pd.DataFrame({"method": ["mlp"], "phase": [0], "plateau": [0.8]})
    out = revisit_learning(_cycling_run((0.6, 0.3, 0.5)), _fresh_run(0.7, 8), plateaus, bin_steps=100)
    assert np.isnan(out.revisit_minus_fresh_mean.iloc[0]) and np.isnan(out.fresh_end.iloc[0])
    assert out.revisit_minus_first_mean.iloc[0] == pytest.approx(-0.1)
    exactly = revisit_learning(_cycling_run((0.6, 0.3, 0.5)), _fresh_run(0.7, 10), plateaus, bin_steps=100)
    assert exactly.revisit_minus_fresh_mean.iloc[0] == pytest.approx(-0.2)  # as long as the visit: compared


def test_the_figures_read_study_runs_of_the_compared_methods_only():
    """At the paper scale the campaign adds MLP + ReDo and MLP + shrink-and-perturb, which the study
    never ran: notebooks 09 and 10 ask for no run of theirs (it would train 2M-step runs inside
    `make figures SCALE=paper`), only runs the figures command's own sweep of "budget" covers."""
    from pemamoe.budget import study_specs
    from pemamoe.experiments import CAMPAIGN_BASELINES, campaign_methods, experiment_specs

    specs = study_specs("paper", None, campaign_methods("paper"))
    assert specs and not {s.method for s in specs} & set(CAMPAIGN_BASELINES)
    covered = {s.to_config().run_name() for s in experiment_specs("budget", "paper")}
    assert {s.to_config().run_name() for s in specs} <= covered
