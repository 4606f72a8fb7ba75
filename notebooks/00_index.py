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
# # 00 · Index: the paper, notebook by notebook
#
# `pemamoe` rebuilds *PE-MAMoE* (a plasticity-enhanced multi-agent mixture of experts for
# UAV-assisted emergency networks) as a sequence of notebooks that follow the paper's order.
# Each notebook explains one part of the method, implements it, and exports its code into the
# importable package `pemamoe/`. Nothing in `pemamoe/` is written by hand except the package's
# `__init__.py`, the exporter and the command line's entry point (`CONTRIBUTING.md`): the notebooks
# are the source.
#
# **Where to start.** A first pass reads the numbered notebooks in order: 01 to 04 build the
# environment (channel, energy, mobility, the objective), 05 the actors, 06 the phase controller,
# 07 the training loop, 08 the theory check, 09 and 10 the results. A notebook with a letter after
# its number (03b, 05c, ...) is an appendix: the machinery or a side study its main notebook
# points to; 00b, the shared utilities, can wait until last. Words used throughout: a *scale* is a
# training budget (`ci` tiny, `small`, `medium`, `paper` the paper's own); SMoE is the top-1
# sparse network alone, PE-MAMoE the same network with the phase controller, MoE the dense mixture
# (every expert weighted by its gate) and MLP the plain actor; the *phase controller* is PE-MAMoE's
# reaction to a phase switch (a KL anchor to the old policy, an optimizer reset, noise on the used
# experts, log-std and entropy resets, a learning-rate drop; notebook 06); ReDo and
# shrink-and-perturb are two published plasticity baselines, an MLP whose dormant units are
# re-initialised, or whose weights are shrunk towards a fresh initialisation, at each switch; an
# *IQM* is the interquartile mean (the mean of the middle half: within a run over its episodes,
# then across runs), given with a 95 % bootstrap interval (rliable, appendix 09g); a *reading* is
# one way of filling in what the paper leaves open (the sparse actor's two are "ours" and "the
# paper's"); a *population* is several runs trained together along a leading axis; a *record* is the
# committed data of a finished run, which every figure reads.
#
# **What we found.** At the `medium` scale PE-MAMoE does not reproduce the paper's headline
# claims: its return IQM is 13 % below the dense MoE's where the paper reports 26 % above the best
# baseline, and it does no better than its own sparse network without the phase controller
# (notebook 10). That verdict is on the sparse actor as the paper describes it (a mean head per
# expert, no balance loss, the PPO ratio on the current routes), the default since our first
# reading, with three settings of ours, was found to learn even a single fixed phase 0.11 worse
# than the MLP because its routing split states between experts whose actions disagreed
# (appendix 05d). Built the paper's way the same actor levels off with the MLP in every fixed
# phase (within 0.013 coverage) and with the dense MoE in phase 0, about 0.03 below it in phases 1
# and 2 (appendix 09b), so the gap that remains on the cycling runs is not the sparse network's
# plateau. Every method was tuned alike; a top-2 arm (notebook 10) shows that keeping two experts
# does not change the medium verdict.
#
# ![Normalised IQM across five system metrics, medium scale (notebook 09)](../paper_figures/results_normalised_iqm.png)
#
# At the paper's own scale (its campaign: 18 committed runs of 22M steps, the four methods and two
# plasticity baselines on the MLP) the claims are contradicted more plainly: PE-MAMoE's return
# IQM is 48 % below the best baseline's, MLP + shrink-and-perturb, and 34 % below SMoE's, the same
# network without the controller (notebook 10). The premise, plasticity loss, shows faintly in an
# MLP, clearly in the dense MoE and late in SMoE (which trains with far fewer updates after the
# first switch); shrink-and-perturb removes the MLP's (notebook 09). A probe of the first switch
# (notebook 10) points to two readings there: our log-std reset to σ = 0.3 narrows a
# policy that had widened to σ ≈ 0.86, and that makes the controller's whole gap over the first
# 600 iterations after it; and with top-1 routing and the PPO ratio on the current routes, the few
# rows the router moves tripped every target-KL stop the probe examined: after the first switch
# the sparse networks take a fraction of the gradient steps an MLP takes (letting the update run
# on is worse).
#
# ![Normalised IQM across five system metrics, paper scale: the campaign's 18 runs (notebook 09)](../paper_figures/paper_scale/results_normalised_iqm.png)
#
# ## Map from the paper to the code
#
# Section numbers are the paper's: III problem statement, IV method, V theory, VI results
# (VI-A simulation setup and the parameter table, VI-B baselines, VI-C effectiveness, VI-D expert
# selection, VI-E system performance, VI-F internal states, VI-G ablation).
#
# | paper | notebook | module(s) | regenerates |
# |---|---|---|---|
# | III-B channel model | `01_channel.py` | `pemamoe/channel.py` | `channel_*` figures |
# | III-C energy model | `02_energy.py` | `pemamoe/energy.py` | `energy_power_vs_speed` |
# | III-D mobility and phases | `03_mobility.py` | `pemamoe/mobility.py` | `mobility_*`, `phases_schedules` |
# | (appendix to III-D) the phase table and the phase clock in code | `03b_phases.py` | `pemamoe/phases.py` | |
# | III-E objective, "environment-side heuristics" | `04_env_model.py` | `pemamoe/env_model.py` | reward anatomy table |
# | (appendix to III-E) the compiled step engine | `04b_env_kernel.py` | `pemamoe/env_kernel.py` | |
# | (appendix to III-E) one random stream per environment, read as a batch | `04c_streams.py` | `pemamoe/streams.py` | |
# | (appendix to III-E) the vector and PettingZoo wrappers, rendering, reference policies | `04d_env_wrappers.py` | `pemamoe/env_wrappers.py` | |
# | (appendix to III-E) `pemamoe.env`, the module outside code imports | `04e_env.py` | `pemamoe/env.py` | |
# | IV-A MoE architecture, Table "Computational cost" | `05_nets.py` | `pemamoe/nets.py` | `architecture_*`, `cost_table` |
# | (appendix to IV-A) the expert bank's execution strategies, the run axis | `05b_popnets.py` | `pemamoe/popnets.py` | |
# | (appendix to IV-A) top-1 gating readings compared: the kept expert's weight, the routing noise, the critic | `05c_gating_readings.py` | | `gating_readings*`, `gating_evaluation` |
# | (appendix to IV-A) the sparse actor's readings (per-expert heads, balance loss, re-routed ratio, top-2) and why top-1 plateaus lower | `05d_sparse_actor.py` | | `sparse_actor*` |
# | (appendix to IV-A) the registries of methods and network kinds | `05e_methods.py` | `pemamoe/methods.py` | |
# | (appendix to IV-A) parameter and compute counts, latency, the cost table's code | `05f_netcost.py` | `pemamoe/netcost.py` | |
# | (appendix to IV-A) the gate's code, for one network and for a population | `05g_gating.py` | `pemamoe/gating.py` | |
# | (appendix to IV-A) the networks' gradients, written out | `05h_backprop.py` | `pemamoe/backprop.py` | |
# | IV-B plasticity injection, Algorithm 1 (phase controller) | `06_phase_controller.py` | `pemamoe/phase_controller.py` | schedule figures |
# | (appendix) plasticity methods for a population of runs (the shared schedule, the interface, the registry) | `06b_plasticity.py` | `pemamoe/plasticity.py` | |
# | (appendix) two plasticity baselines, ReDo and shrink-and-perturb, on the MLP and the SMoE network | `06c_plasticity_baselines.py` | `pemamoe/plasticity_baselines.py` | |
# | (appendix) AdamW over the run axis: per-member learning rates, moments, resets and freezes | `06d_optim.py` | `pemamoe/optim.py` | |
# | (appendix) the plasticity diagnostics (VI-F): feature rank, dormant units, routers, mean action | `06e_diagnostics.py` | `pemamoe/diagnostics.py` | |
# | IV-B training (MAPPO: PPO + GAE under CTDE, total loss, Algorithm 1's loop); VI-A training table | `07_mappo.py` | `pemamoe/mappo.py` | training curves |
# | (appendix to IV-B) run folders you can trust: locks, sealed results, named errors | `07b_runs.py` | `pemamoe/runs.py` | |
# | (appendix to IV-B) the run's configuration: its fields and checks, its identity, the presets; VI-A's parameter table | `07c_train_config.py` | `pemamoe/train_config.py` | `table_parameters` |
# | (appendix to IV-B) populations of runs, resuming and catching up, reading a run back, deterministic evaluation | `07d_populations.py` | `pemamoe/populations.py` | |
# | (appendix to IV-B) the trainer's bookkeeping: episodes, the log row, the return normaliser, checkpoint encoding | `07e_bookkeeping.py` | `pemamoe/bookkeeping.py` | |
# | V theoretical analysis | `08_theory.py` | `pemamoe/theory.py` | `theory_*` |
# | (appendix of V) the toy tracking problems and the theory check's instruments | `08b_toy_tracking.py` | `pemamoe/toy_tracking.py` | |
# | (appendix of V) the theory check's records: computed once, committed, read back | `08c_theory_records.py` | `pemamoe/theory_records.py` | |
# | VI-B to VI-F results | `09_experiments.py` | `pemamoe/experiments.py` | every results figure |
# | (appendix to VI) the learning-budget study: how many steps a phase needs, which fixes the `medium` scale | `09b_budget.py` | `pemamoe/budget.py` | `learning_budget*` |
# | (appendix to VI) executing a sweep: a run's spec, the run cache, process pool, Ray, stopping | `09c_sweep_runner.py` | `pemamoe/sweep_runner.py` | |
# | (appendix to VI) run records: the published data of a finished run, which the figures read | `09d_records.py` | `pemamoe/records.py` | |
# | (appendix to VI) a portable state's codecs: log rows in columns, random buffers as where they were drawn | `09h_portable_codecs.py` | `pemamoe/portable_codecs.py` | |
# | (appendix to VI) the commands: `python -m pemamoe sweep` and `make figures` | `09e_commands.py` | `pemamoe/commands.py` | |
# | (appendix to VI) the results store: run folders in a local folder or at a URL (`s3://...`), leased and synced | `09f_store.py` | `pemamoe/store.py` | |
# | (appendix to VI) reading results: the IQM and its bootstrap intervals, the heuristics' levels, curves over training | `09g_analysis.py` | `pemamoe/analysis.py` | |
# | VI-G ablations; the headline claims against the paper's numbers | `10_ablations.py` | | noise sweep, tricks ablation, `headline_*` tables |
# | the settings the paper leaves open that move the paper-scale verdict (Algorithm 1, training table) | `10b_readings.py` | | `readings`, `log_std_reset_direction`, `update_budget` tables (paper scale) |
# | (appendix, no paper section) shared machinery | `00b_core.py` | `pemamoe/core.py` | |
#
# `paper_figures/README.md` lists every regenerated file with its paper counterpart, the notebook,
# the scale, the command and a digest of the notebook's code (`paper_figures/paper_scale/README.md`
# the same for the paper scale's files).
#
# ## How to run everything
#
# * `make test` builds the pinned environment in `.venv` (first run only), checks that
#   `pemamoe/` matches the notebooks, runs the unit and property tests, and executes every
#   notebook at the `ci` scale.
# * `make figures` (default `SCALE=medium`, whose runs are committed as records) executes every
#   notebook headlessly with papermill and writes the figures and tables into `paper_figures/`,
#   printing which notebook of how many is running, the time spent, and the notebooks' own
#   progress output. `SCALE=ci` is a smoke run (every notebook, a few minutes); `SCALE=small` is short training
#   (committed too); `SCALE=medium` trains each phase long enough to learn in (notebook 09b says
#   why this length); `SCALE=paper` uses the paper's training budget for its campaign, the main
#   comparison with two plasticity baselines, and draws only what reads it (notebooks 09 and 10,
#   into `paper_figures/paper_scale/`, a folder that run creates). The README gives the measured cost of each.
# * `make lab` opens JupyterLab, where these `.py` files open as notebooks. A notebook run there
#   (kernel in `notebooks/`) writes its figures into the repository's `paper_figures/` at its own
#   parameters' scale (`small` unless changed), over the committed `medium` files: set `figures_dir`
#   in its parameters cell to another folder, or `git checkout paper_figures` afterwards.
# * `python -m pemamoe sweep --experiment campaign --scale paper --backend ray --address auto` runs the
#   training behind the figures on a Ray cluster; `make figures SCALE=paper BACKEND=ray` then
#   plots from the cached runs (or trains what is missing, on Ray). The campaign's 18 runs are
#   committed records, so on a fresh clone `make figures SCALE=paper` trains nothing and takes
#   minutes (`python -m pemamoe sweep --experiment campaign --scale paper --status` says so).
#
# The utilities every notebook shares (scales, the configuration validator, atomic file writes,
# figure and table saving, the headless notebook runner) are explained in the appendix notebook
# `00b_core.py`, which exports `pemamoe/core.py`.

# %% [markdown]
# ## Reading list
#
# * **CleanRL** (Huang et al., 2022): single-file PPO implementations; notebook 07 follows its PPO
#   details wherever the paper is silent (advantage normalisation, AdamW epsilon, KL estimator).
# * **MAPPO** (Yu et al., 2022, "The Surprising Effectiveness of PPO in Cooperative Multi-Agent
#   Games"): PPO with a centralised critic and shared actor weights, the training recipe the paper
#   builds on.
# * **Switch Transformer** (Fedus, Zoph and Shazeer, 2022): top-1 routing, the gating of the SMoE
#   and PE-MAMoE actors; its load-balancing loss, which the paper does not use, is an ablation row
#   of appendix 05d.
# * **Dormant neurons** (Sokar et al., 2023, "The Dormant Neuron Phenomenon in Deep RL"): the
#   τ-dormant score that appendix 06e measures as the plasticity indicator.
# * **rliable** (Agarwal et al., 2021, "Deep RL at the Edge of the Statistical Precipice"): IQM
#   with stratified-bootstrap intervals, how notebooks 09 and 10 compare methods across seeds.

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## A quick look
#
# Running this cell lists the notebooks `make figures` executes, in order, and where the figures
# of this session go.

# %%
from pemamoe.core import check_scale, figure_notebooks, repo_path

for path in figure_notebooks():
    print(path.name)
print(f"scale={check_scale(scale)!r}; figures go to {repo_path(figures_dir)}")
