# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 05d · The sparse actor, measured: why top-1 SMoE plateaus below MLP and MoE
#
# In the learning-budget study (notebook 09b), built as we first read the paper, the top-1 sparse
# actor levelled off clearly below the MLP and the dense MoE in every fixed phase (0.680 against
# 0.793 in phase 0), with no phase switch and no plasticity mechanism involved. Every verdict about PE-MAMoE, which is that sparse actor plus a phase controller,
# inherits this gap, so it has to be explained before it is blamed on sparse routing itself.
#
# The sparse actor of notebook 05, as it was when the gap was found ("ours" in `BUDGET_READINGS`,
# notebook 09), differed from what the paper's equations write in three places, each a choice we
# made where the paper is silent or contradicts itself (this appendix is why the defaults are now
# the paper's three, end of the notebook):
#
# * **One shared mean head.** The paper's parameter counts say one head after the mixed trunk; its
#   equations give every expert its own mean and mix the means (`expert_heads`).
# * **A load-balancing loss (coefficient 0.01).** The paper's prose names a Switch-style balance
#   term, but its loss equations (the actor objective and the total loss) have no such term and
#   it gives no coefficient (`load_balance_coef`).
# * **Replayed routes in PPO's ratio.** The update recomputes each row's action probability with
#   the expert that acted in the rollout, so when the router would now pick another expert, the
#   ratio never sees it and the clip never holds it (`update_routing`: `replay`, or `current`,
#   which routes each row again with the current router and the stored noise).
#
# Each reading below changes one of these, or all three at once (`smoe/paper`), beside the
# sanity checks: one expert (routing removed: the network is an MLP with a router that cannot
# matter) and the paper's readings with the two best experts kept (`top-2`). MLP and MoE, with
# and without the paper's readings, are the references. Every run learns a single fixed phase 0
# for 1.5 million environment steps (2,930 iterations of the small update settings), 2 seeds.
# Besides the coverage (the study's yardstick) we read, from each run's final actor, how its
# deterministic policy moves: the mean distance between an agent's consecutive mean actions when
# its expert changed and when it did not, and the share of mean actions outside the action box
# (the environment clips them), with `action_switch_readings` (appendix 07d).
#
# The runs are a sweep, `python -m pemamoe sweep --experiment sparse` (small preset; the records
# are committed); this notebook reads their records and trains only runs that have none (at `ci`,
# a few iterations, so that CI executes it).

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seeds = None  # None: 2 (1 at the ci scale)
backend = "local"
workers = 2
ray_address = None
results_dir = "results"
records_dir = "records"  # the published records (appendix 09d); runs without one are trained
retrain = False  # True: ignore the records, train into results_dir and write the records again

# %%
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from pemamoe.budget import PLATEAU_TAIL, block_steps, budget_curves, load_budget, plateau_table
from pemamoe.core import save_figure, write_table
from pemamoe.populations import action_switch_readings
from pemamoe.records import read_record_actor
from pemamoe.experiments import SPARSE_READINGS, sparse_specs, sweep_records

specs = sparse_specs(scale, seeds)
records = sweep_records(specs, backend, workers, results_dir, ray_address, records_dir, retrain)
metrics = load_budget(records)
metrics["method"] = metrics.run.map({Path(r).stem: spec.tag.split("/", 1)[1] for spec, r in zip(specs, records)})
readings = list(SPARSE_READINGS)
print(f"{len(records)} runs of {metrics.env_steps.max():,} environment steps, {len(readings)} readings")

# %% [markdown]
# ## The table
#
# Per reading: coverage over the last 10 % of the steps (seed mean, lowest and highest seed); the
# share of the gap between the sparse actor as it was (`smoe`) and MLP that the reading closes;
# over the same window, the switch rate of the selected expert in the rollouts, the share of the
# rollouts' routing slots that the busiest expert takes (`top_expert_share`: 1 when one expert
# does everything, 1/3 when the three share alike) and, for the readings that route again in the
# update, the share of the batch the update moved to another expert (`reroute_rate`); and from the
# final actors (200 steps of 16 environments in phase 0,
# noiseless routing, mean action) the action jumps and the share of mean actions outside the box.

# %%
def tail_mean(frame: pd.DataFrame, column: str) -> pd.Series:
    """Per reading: seed mean of each run's mean of `column` over its last PLATEAU_TAIL of iterations."""
    if column not in frame:
        return pd.Series(dtype=float)
    last = frame.groupby("run").iteration.transform("max")
    window = frame[frame.iteration > last - np.maximum(1, np.round(PLATEAU_TAIL * (last + 1)))]
    return window.groupby(["method", "seed"])[column].mean().groupby("method").mean()


curves = budget_curves(metrics, block_steps=block_steps(scale))
table = plateau_table(curves).rename(columns={"method": "reading", "plateau": "coverage"})
table = table[["reading", "seeds", "steps", "coverage"]].set_index("reading")
per_seed = curves[curves.env_steps > (1 - PLATEAU_TAIL) * curves.groupby("run").env_steps.transform("max")]
per_seed = per_seed.groupby(["method", "seed"]).coverage.mean()
table["seed_min"] = per_seed.groupby("method").min()
table["seed_max"] = per_seed.groupby("method").max()
gap = table.coverage["mlp"] - table.coverage["smoe"]
table["gap_closed"] = (table.coverage - table.coverage["smoe"]) / gap if abs(gap) > 1e-9 else np.nan
table["switch_rate"] = tail_mean(metrics, "rollout/switch_rate")
table["reroute_rate"] = tail_mean(metrics, "update/reroute_rate")
shares = [tail_mean(metrics, c) for c in metrics.columns if c.startswith("rollout/expert_frac")]
table["top_expert_share"] = pd.concat(shares, axis=1).max(axis=1) if shares else np.nan  # 1: one expert does all

rows = []
for spec, record in zip(specs, records):
    config = spec.to_config()
    readings_of_actor = action_switch_readings(read_record_actor(record), config.env_config(),
                                               steps=20 if scale == "ci" else 200, seed=1000 + spec.seed, phase=0)
    rows.append({"reading": spec.tag.split("/", 1)[1], "seed": spec.seed, **readings_of_actor})
behaviour = pd.DataFrame(rows).groupby("reading")[["jump_at_switch", "jump_otherwise", "outside_box"]].mean()
table = table.join(behaviour).reindex(readings).reset_index()
write_table(table.round(4), "sparse_actor", figures_dir)
table.round(3)

# %% [markdown]
# ## Over training
#
# Coverage per 100k-step block (seed mean; MLP in grey, MoE in black), and the final actors'
# action jumps at an expert switch against the other steps.

# %%
colours = dict(zip(readings, ["#7f7f7f", "#000000", "#444444", *plt.cm.tab10(np.arange(len(readings) - 3))]))
fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4), gridspec_kw={"width_ratios": [1.4, 1]})
for reading in readings:
    g = curves[curves.method == reading].groupby("env_steps").coverage.mean()
    ax.plot(g.index / 1e6, g.to_numpy(), color=colours[reading], lw=2.2 if reading in ("mlp", "moe") else 1.2,
            ls="--" if reading == "moe/paper" else "-", label=reading)
ax.set(title="coverage, phase 0 only", xlabel="environment steps (millions)", ylabel="coverage")
ax.legend(fontsize=7, loc="lower right")
t = table.set_index("reading")
x = np.arange(len(readings))
bx.bar(x - 0.2, t.jump_otherwise.reindex(readings), 0.4, color="#bbbbbb", label="expert unchanged")
bx.bar(x + 0.2, t.jump_at_switch.reindex(readings).fillna(0), 0.4, color="#d62728", label="expert changed")
bx.set_xticks(x, readings, rotation=60, ha="right", fontsize=7)
bx.set(title="mean-action jump between consecutive steps", ylabel="distance in the action box")
bx.legend(fontsize=7)
fig.suptitle(f"The sparse actor's readings in fixed phase 0 ({t.seeds.max():.0f} seed(s), "
             f"{metrics.env_steps.max():,} steps per run)", fontsize=9)
fig.tight_layout()
save_figure(fig, "sparse_actor", figures_dir)

# %% [markdown]
# ![The sparse actor's readings in fixed phase 0: coverage and mean-action jumps](../paper_figures/sparse_actor.png)

# %% [markdown]
# ## The study's actors, read the same way
#
# The same behaviour readings for the final actors of the committed learning-budget study
# under our reading (notebook 09b: 2 million steps in phase 0, 3 seeds), so the jumps at
# expert switches are seen where the plateau gap was measured, not only in the shorter runs above.
# (PE-MAMoE in a fixed phase is SMoE: the controller never acts, so it is left out.)

# %%
from pemamoe.experiments import budget_specs

study_specs = [s for s in budget_specs(scale, None, ("mlp", "moe", "smoe"), readings=("ours",))
               if s.tag == "budget/small" and dict(s.overrides)["fixed_phase"] == 0]
study_records = sweep_records(study_specs, backend, workers, results_dir, ray_address, records_dir, retrain)
rows = [{"method": spec.method, "seed": spec.seed,
         **action_switch_readings(read_record_actor(record), spec.to_config().env_config(),
                                  steps=20 if scale == "ci" else 200, seed=1000 + spec.seed, phase=0)}
        for spec, record in zip(study_specs, study_records)]
study_behaviour = (pd.DataFrame(rows).groupby("method", sort=False)
                   [["jump_at_switch", "jump_otherwise", "switch_rate", "outside_box"]].agg(["mean", "min", "max"]))
study_behaviour.columns = [f"{a}_{b}" for a, b in study_behaviour.columns]
study_behaviour = study_behaviour.reset_index()
write_table(study_behaviour.round(4), "sparse_actor_study", figures_dir)
study_behaviour.round(3)

# %% [markdown]
# ## What the numbers say
#
# The cell below states the comparison from the table of this run.

# %%
def _describe(t: pd.DataFrame) -> str:
    t = t.set_index("reading")
    c = t.coverage
    lines = [f"* Coverage over the last 10 % of the steps: MLP {c['mlp']:.3f}, MoE {c['moe']:.3f}, "
             f"the sparse actor as it was (`smoe`) {c['smoe']:.3f}: a gap of {c['mlp'] - c['smoe']:.3f} to MLP "
             f"(busiest expert's share {t.top_expert_share['smoe']:.2f})."]
    lines.append(f"* One expert (no routing): {c['smoe/1 expert']:.3f} "
                 f"({t.gap_closed['smoe/1 expert']:.0%} of the gap closed).")
    for reading in ("smoe/no balance", "smoe/expert heads", "smoe/re-routed ratio", "smoe/paper", "smoe/paper top-2"):
        lines.append(f"* `{reading}`: {c[reading]:.3f} ({t.gap_closed[reading]:.0%} of the gap closed; "
                     f"seeds {t.seed_min[reading]:.3f}-{t.seed_max[reading]:.3f}; switch rate {t.switch_rate[reading]:.2f}; "
                     f"busiest expert's share {t.top_expert_share[reading]:.2f}).")
    lines.append(f"* MoE with the paper's readings: {c['moe/paper']:.3f} (MoE as it was: {c['moe']:.3f}).")
    lines.append(f"* Mean-action jump at an expert switch against other steps: `smoe` {t.jump_at_switch['smoe']:.2f} "
                 f"vs {t.jump_otherwise['smoe']:.2f}; `smoe/paper` {t.jump_at_switch['smoe/paper']:.2f} vs "
                 f"{t.jump_otherwise['smoe/paper']:.2f}; MLP {t.jump_otherwise['mlp']:.2f}. Mean actions outside "
                 f"the box: `smoe` {t.outside_box['smoe']:.0%}, `smoe/paper` {t.outside_box['smoe/paper']:.0%}, "
                 f"MLP {t.outside_box['mlp']:.0%}.")
    return "\n".join(lines)


from IPython.display import Markdown  # noqa: E402

Markdown(_describe(table))

# %% [markdown]
# ## The cause, in plain words, and what the defaults become
#
# The numbers below are those of `paper_figures/sparse_actor.md` and `sparse_actor_study.md`
# (1.5 million steps, 2 seeds; the study's actors 2 million steps, 3 seeds).
#
# * **The gating code is sound; splitting an agent's states between experts is what costs.** With
#   a single expert the sparse actor learns as well as the MLP (0.765 against 0.760); with three it
#   ends 0.059 below. Its final policy is a patchwork: where the selected expert changes from one
#   step to the next, the mean action moves 1.59 on average (0.64 elsewhere; the study's actors
#   1.56 against 0.71), and 26 % of its mean actions fall outside the action box (MLP 7 %). Expert
#   means that disagree by that much give neighbouring states inconsistent actions.
# * **The balance loss keeps that split in place.** It holds the three experts near equal traffic
#   (the busiest takes 0.37). Without it the router gives one expert 99 % of the traffic and the
#   actor learns almost like an MLP (0.753), which closes the gap by ceasing to be a mixture.
# * **Per-expert heads alone, or re-routing alone, do not help** (0.693 and 0.668).
# * **The paper's three readings together close two thirds of the gap to MLP** (0.740, both
#   seeds at 0.740): each expert's own head, no balance term, and the ratio of the policy as it
#   now routes. Two experts stay in use (the busiest takes 0.50), and the jump at a switch falls to
#   0.62 against 0.53 elsewhere, with 9 % of mean actions outside the box: the experts' means now
#   agree where their regions meet.
# * **What is left is top-1 routing itself.** The same readings help the dense MoE just as much
#   (0.772 to 0.811), so against the dense mixture the sparse actor still trails by 0.07 under
#   either reading. Keeping the two best experts (`top-2`) recovers about three quarters of it
#   (0.792 against the dense MoE's 0.811).
#
# So the readings that follow the paper's equations (`expert_heads="per_expert"`,
# `load_balance_coef=0`, `update_routing="current"`) close more than half of the gap, and they
# are now the defaults of every gated actor, the dense MoE included so that the methods stay
# alike; top-2 is an arm of its own beside top-1 (`sweep --experiment top2`), since the paper's
# actor is top-1. A default changes the identity of every gated run, so the switch landed only
# once the runs it requires had been trained under the pinned reading (the learning-budget study
# and the medium runs of MoE, SMoE and PE-MAMoE; the plan and its cost are in
# `benchmarks/HISTORY.md`, which also keeps the verdicts of the earlier defaults). At the study's
# horizon, 2 million steps, the 1.5M comparison's remaining gap is gone as well: under these
# readings SMoE levels off at 0.796 in phase 0, as do MLP (0.793) and the dense MoE (0.796)
# (`learning_budget_readings`, appendix 09b). This appendix keeps our earlier reading as its
# baseline (`readings=("ours",)` above), since that is the actor whose gap it explains.
