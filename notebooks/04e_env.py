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
# # 04e · Appendix: `pemamoe.env`, the module outside code imports
#
# The environment's model is notebook 04's (`pemamoe.env_model`), its wrappers appendix 04d's
# (`pemamoe.env_wrappers`), its random streams appendix 04c's (`pemamoe.streams`). Outside code
# imports none of them directly: it imports `pemamoe.env`, which sits on top of all three,
# re-exports them, and builds the two public environments (`make_vector_env` and `make_env`, with
# PettingZoo's `parallel_env`, `aec_env` and `raw_env`). What they return is described in
# notebook 04 ("The environments the trainer and outside code use").

# %%
#| default_exp env

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %%
#| export
from pemamoe.core import require
from pemamoe.env_model import (  # re-export: the model above
    STEP_ENGINES, EnvConfig, Allocation, UAVBatchCore, build_observations, colour_weights, observation_dim,
    observation_layout, pair_distances, realised_rates, reward_terms, schedule_users, slot_draws, state_dim)
from pemamoe.env_wrappers import (  # re-export: the public environments, rendering, reference policies (appendix 04d)
    HEURISTICS, UAVParallelEnv, UAVVectorEnv, compile_step_kernels, hover_policy, kmeans_policy, random_policy,
    render_frame, rollout_heuristic, vector_seeds)
from pemamoe.streams import BatchRandom  # per-environment random streams (appendix 04d)


def make_env(render_mode: str | None = None, **overrides) -> UAVParallelEnv:
    """The PettingZoo ParallelEnv, with any EnvConfig value overridden by keyword."""
    return UAVParallelEnv(EnvConfig.from_overrides(**overrides), render_mode=render_mode)


def parallel_env(render_mode: str | None = None, **overrides) -> UAVParallelEnv:
    """PettingZoo's name for the parallel constructor: the same as make_env."""
    return make_env(render_mode, **overrides)


def aec_env(render_mode: str | None = None, **overrides):
    """The environment as a PettingZoo AEC env (agents act in turn), via PettingZoo's parallel_to_aec."""
    from pettingzoo.utils.conversions import parallel_to_aec  # here, not at load: the trainer needs no PettingZoo

    return parallel_to_aec(make_env(render_mode, **overrides))


raw_env = aec_env  # PettingZoo's usual name for the AEC constructor


def make_vector_env(num_envs: int = 16, seed: int | None = 0, **overrides) -> UAVVectorEnv:
    """B environments in one process; member i behaves as make_env(...) reset with seed + i.

    seed: a non-negative integer, or None for fresh entropy."""
    num_envs = require("make_vector_env", "num_envs", num_envs, "int", ge=1)
    seed = require("make_vector_env", "seed", seed, "int", ge=0, optional=True)
    return UAVVectorEnv(num_envs, seed, **overrides)

# %% [markdown]
# ## Check
#
# The two constructors agree: environment 0 of a vector env seeded `seed` starts where the
# PettingZoo environment reset with `seed` starts.

# %%
import numpy as np

vector_obs = make_vector_env(2, seed=seed).reset()[0]
pz_obs = make_env().reset(seed=seed)[0]
assert all(np.array_equal(pz_obs[f"uav_{u}"], vector_obs[0, u]) for u in range(vector_obs.shape[1]))
print("first observations agree; observation", vector_obs.shape[2:], "per agent")
