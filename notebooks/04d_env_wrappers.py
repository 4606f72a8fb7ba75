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
# # 04d · Appendix: the environments' wrappers, rendering and reference policies
#
# Notebook 04's batched core is the environment's model. This appendix holds the thin layers over
# it that the trainer and outside code use, in the module `pemamoe.env_wrappers`: `UAVVectorEnv`,
# the batched environment the trainer steps, and `UAVParallelEnv`, the PettingZoo environment,
# with the renderer, `compile_step_kernels` and the reference policies (`random`, `hover`,
# `kmeans`) that the learned ones are compared with. Outside code imports them from `pemamoe.env`
# (appendix 04e), which re-exports them with the model.

# %%
#| default_exp env_wrappers

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## The wrappers: the batched environment the trainer uses
#
# `UAVVectorEnv` steps B environments in one process. Episodes of all environments have the same
# length, and an environment whose episode ends (time limit, or an empty battery) starts a new
# one within the same call, so that every call returns usable observations. The last observation of
# the finished episode is returned in `info["final_obs"]` and `info["final_state"]`: the trainer
# bootstraps a truncated episode from the value of that final observation, not from the first
# observation of the next episode.

# %%
#| export
import numpy as np

from pemamoe.env_model import EnvConfig, UAVBatchCore, observation_dim, state_dim
from pemamoe.phases import phase_values


class UAVVectorEnv:
    """B environments stepped together. Arrays: obs (B, U, obs_dim), state (B, state_dim)."""

    def __init__(self, num_envs: int = 16, seed: int | None = 0, cfg: "EnvConfig | None" = None, *, seeds=None,
                 **overrides):
        if cfg is not None and overrides:
            raise ValueError("pass either cfg or keyword overrides, not both")
        self.cfg = cfg or EnvConfig.from_overrides(**overrides)
        if seeds is None:  # explicit per-environment seeds: a population's members side by side
            seeds = vector_seeds(seed, num_envs)
        num_envs = len(seeds)
        self.core = UAVBatchCore(self.cfg, num_envs, seeds)
        self.num_envs = int(num_envs)
        self.n_agents = self.cfg.n_uavs
        self.obs_dim = observation_dim(self.cfg)
        self.state_dim = state_dim(self.cfg)
        self.act_dim = 2

    def reset(self):
        obs, state, info = self.core.reset()
        return obs, state, info

    def set_phase(self, phase: int) -> None:
        self.core.set_phase(phase)

    def state_dict(self) -> dict:
        return self.core.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.core.load_state_dict(state)

    def step(self, actions):
        obs, state, reward, terminated, truncated, info = self.core.step(actions)
        done = terminated | truncated
        if done.any():
            rows = np.flatnonzero(done)
            info["final_obs"], info["final_state"] = obs[rows].copy(), state[rows].copy()
            info["final_rows"] = rows
            new_obs, new_state, _ = self.core.reset(rows)
            obs[rows], state[rows] = new_obs, new_state
        return obs, state, reward, terminated, truncated, info


def vector_seeds(seed, num_envs: int) -> list:
    """Seeds of a vector env's members: environment i of seed s is the env made with seed s + i."""
    if seed is None:
        return [None] * num_envs
    return [int(seed) + i for i in range(num_envs)]


# %% [markdown]
# ## The wrappers: the PettingZoo environment
#
# `make_env(**overrides)` (also `pemamoe.parallel_env`) returns a PettingZoo `ParallelEnv` over the
# same core with B = 1: agents `uav_0 … uav_{U-1}`, Gymnasium `Box` spaces, `state()` for the
# centralised critic and, with `render_mode="rgb_array"`, an RGB `render()` (the default,
# `render_mode=None`, draws nothing). `aec_env(**overrides)` (alias `raw_env`) is the same
# environment as an AEC env, through PettingZoo's own `parallel_to_aec` conversion.
#
# It follows the conventions outside code relies on. The infos of `reset()` carry the same keys,
# with the same types, as those of `step()` (the per-step flags are all `False` at a reset), so a
# library that builds its info spec from `reset()` can read every `step()`. `step()`, `state()` and
# `render()` before the first `reset()` raise an error that says to call `reset()` first. Actions
# outside [-1, 1] are clipped and flagged in `info["action_clipped"]`; a NaN or infinite action, and
# an action for an agent that does not exist, raise an error naming the agent.
#
# PettingZoo and Gymnasium are needed by this environment only. The trainer, the sweeps and the
# benchmarks never build it, so they must import without either package: a GPU machine's own Python
# has torch but neither of them (`benchmarks/device_check.sh` runs there). The class is therefore
# defined in every case, and its base is PettingZoo's `ParallelEnv` where PettingZoo imports, a
# plain `object` where it is not installed; building one without it raises an `ImportError` that
# says what to install. Gymnasium's `Box` spaces are imported when an environment is built. We
# chose this over creating the class on first access (a module `__getattr__`): the class stays one
# object, defined at load, so `pemamoe.env` re-exports it as before, star imports, `isinstance` and
# pickling behave as usual, and there is no second path to keep in step.

# %%
#| export
try:  # PettingZoo (which brings Gymnasium) is optional for everything but this environment
    from pettingzoo import ParallelEnv as _ParallelEnvBase

    _PETTINGZOO_MISSING = None
except ModuleNotFoundError as error:
    if (error.name or "").split(".")[0] not in ("pettingzoo", "gymnasium"):
        raise  # a broken install of something else: say so, do not hide it
    _ParallelEnvBase, _PETTINGZOO_MISSING = object, error

# Info keys that only a step produces, and their value at a reset: (per agent?, value).
_STEP_ONLY_INFO = {"action_clipped": (True, False), "move_infeasible": (True, False),
                   "battery_depleted": (True, False), "phase_switch": (False, False)}


class UAVParallelEnv(_ParallelEnvBase):
    metadata = {"name": "pemamoe_uav_ecn_v0", "render_modes": ["rgb_array", "human"], "is_parallelizable": True,
                "render_fps": 4}

    def __init__(self, cfg: "EnvConfig | None" = None, render_mode: str | None = None):
        if _PETTINGZOO_MISSING is not None:
            raise ImportError("the PettingZoo environment needs pettingzoo and gymnasium "
                              "(pip install pettingzoo gymnasium); the trainer and the vector env "
                              "(make_vector_env) do not") from _PETTINGZOO_MISSING
        from gymnasium import spaces

        if render_mode not in (None, "rgb_array", "human"):
            raise ValueError(f"render_mode must be None, 'rgb_array' or 'human', got {render_mode!r}")
        self.cfg = cfg or EnvConfig()
        self.render_mode = render_mode
        self.possible_agents = [f"uav_{u}" for u in range(self.cfg.n_uavs)]
        self.agents = []
        obs_dim = observation_dim(self.cfg)
        self._obs_space = spaces.Box(-1.0, 1.0, (obs_dim,), np.float32)
        self._act_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self._state_space = spaces.Box(-1.0, 1.0, (state_dim(self.cfg),), np.float32)
        self.core = UAVBatchCore(self.cfg, 1, [None])
        self._seeded = False
        self._state = None  # set by reset(); None means "never reset"

    def observation_space(self, agent):
        return self._obs_space

    def action_space(self, agent):
        return self._act_space

    @property
    def state_space(self):
        return self._state_space

    def _need_reset(self, method: str) -> None:
        if self._state is None:
            raise RuntimeError(f"{method}() called before reset(): call reset() first")

    def reset(self, seed=None, options=None):
        if seed is not None and (isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer))
                                 or not 0 <= int(seed) < 2 ** 63):
            raise ValueError(f"reset(seed=...) must be None or an int in [0, 2**63), got {seed!r}")
        if seed is not None or not self._seeded:
            self.core.rng.reseed(0, seed)
            self._seeded = True
        obs, state, info = self.core.reset()
        self._state = state[0]
        self.agents = list(self.possible_agents)
        U = len(self.agents)
        for key, (per_agent, value) in _STEP_ONLY_INFO.items():  # step()'s keys, with their types
            info.setdefault(key, np.full((1, U) if per_agent else (1,), value))
        infos = _agent_infos(info, 0, self.agents)
        return {a: obs[0, i] for i, a in enumerate(self.agents)}, infos

    def step(self, actions):
        self._need_reset("step")
        if not self.agents:
            raise RuntimeError("step() called on a finished episode: call reset() first")
        unknown = set(actions) - set(self.possible_agents)
        if unknown:
            raise ValueError(f"actions for unknown agent(s) {sorted(unknown, key=str)}; "
                             f"the agents are {self.possible_agents}")
        missing = set(self.agents) - set(actions)
        if missing:
            raise ValueError(f"actions missing for agents {sorted(missing)}")
        try:  # the usual case, one array of 2 numbers per agent, in one call
            stacked = np.array([actions[a] for a in self.possible_agents], dtype=float)
        except (TypeError, ValueError):
            stacked = None
        if stacked is None or stacked.shape != (len(self.possible_agents), 2):
            for a in self.possible_agents:
                if np.shape(actions[a]) != (2,):  # a (1, 2) or (2, 1) array is refused, not reshaped
                    raise ValueError(f"action of {a} must have shape (2,), got shape {np.shape(actions[a])}")
            stacked = np.stack([np.asarray(actions[a], dtype=float).reshape(2) for a in self.possible_agents])
        obs, state, reward, terminated, truncated, info = self.core.step(stacked[None])
        self._state = state[0]
        agents = self.agents
        shared_reward, term, trunc = float(reward[0]), bool(terminated[0]), bool(truncated[0])
        out = (
            {a: obs[0, i] for i, a in enumerate(agents)},
            {a: shared_reward for a in agents},
            {a: term for a in agents},
            {a: trunc for a in agents},
            _agent_infos(info, 0, agents),
        )
        if term or trunc:
            self.agents = []
        return out

    def state(self):
        self._need_reset("state")
        return self._state

    def render(self):
        """rgb_array: the frame (H, W, 3) uint8; human: the frame shown in a matplotlib window
        (nothing visible under a non-interactive backend, as in a headless test), returns None."""
        if self.render_mode is None:
            return None
        self._need_reset("render")
        frame = render_frame(self.core, 0)
        if self.render_mode == "rgb_array":
            return frame
        import matplotlib.pyplot as plt

        if getattr(self, "_window", None) is None or not plt.fignum_exists(self._window[0].number):
            fig, ax = plt.subplots()
            ax.axis("off")
            self._window = (fig, ax.imshow(frame))
        else:
            self._window[1].set_data(frame)
        plt.pause(1 / self.metadata["render_fps"])
        return None

    def close(self):
        window = getattr(self, "_window", None)
        if window is not None:
            import matplotlib.pyplot as plt

            plt.close(window[0])
            self._window = None


def _agent_infos(info: dict, b: int, agents: list) -> dict:
    """Environment b's info as each agent sees it: (B, U) arrays are indexed by agent, (B,) are shared."""
    shared, per_agent = {}, {}
    for key, value in info.items():
        value = value if isinstance(value, np.ndarray) else np.asarray(value)
        # value[b:b + 1].tolist()[0] gives Python numbers, several times faster than value[b].item()
        if value.ndim == 2 and value.shape[1] == len(agents):
            per_agent[key] = value[b:b + 1].tolist()[0]
        else:
            shared[key] = value[b:b + 1].tolist()[0] if value.ndim == 1 else value[b]
    order = list(info)  # every agent's dict keeps info's key order
    return {a: {key: per_agent[key][u] if key in per_agent else shared[key] for key in order}
            for u, a in enumerate(agents)}


def compile_step_kernels() -> None:
    """Compile the compiled engine's kernels in this process, or load them from numba's on-disk
    cache. Call it once before starting parallel workers: they then all load the cached machine
    code instead of compiling it at the same time (about 9 s each, and a race on the cache files)."""
    env = UAVVectorEnv(2, 0, step_engine="compiled")
    env.reset()
    env.step(np.zeros((2, env.n_agents, 2)))


# %% [markdown]
# ## Rendering
#
# `render()` of the PettingZoo environment draws the area from above: users coloured by demand class, UAVs with their service
# circles, and a line from each admitted user to its UAV.

# %%
#| export
CLASS_COLOURS = ("#4daf4a", "#377eb8", "#e41a1c")  # L, M, H


def render_frame(core: "UAVBatchCore", b: int = 0, size_px: int = 480) -> np.ndarray:
    """An RGB frame (H, W, 3) uint8 of environment b."""
    import matplotlib

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    cfg = core.cfg
    fig = Figure(figsize=(size_px / 100, size_px / 100), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_axes([0, 0, 1, 1])
    S = cfg.area_m
    ax.set_xlim(0, S)
    ax.set_ylim(0, S)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    users = core.mobility.user_xy[b]
    uavs = core.uav_xy[b]
    _, _, radius, _ = phase_values(cfg.phases, core.phase[b:b + 1])
    for n, u in enumerate(core.serving[b]):
        if u >= 0:
            ax.plot([users[n, 0], uavs[u, 0]], [users[n, 1], uavs[u, 1]], color="0.6", lw=0.8, zorder=1)
    for u, (x, y) in enumerate(uavs):
        ax.add_patch(matplotlib.patches.Circle((x, y), radius[0], fill=False, ls="--", color="0.3", lw=1))
        ax.plot(x, y, marker="^", ms=12, color="black", zorder=3)
        ax.annotate(f"uav_{u}", (x, y), textcoords="offset points", xytext=(6, 6), fontsize=8)
    ax.scatter(users[:, 0], users[:, 1], c=[CLASS_COLOURS[c] for c in core.demand[b]], s=22, zorder=2)
    ax.set_title(f"phase {core.phase[b]}  step {core.t[b]}", fontsize=9, y=0.95)
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


# %% [markdown]
# ## Reference policies
#
# Three non-learning policies act on the batched observations' underlying state and serve as
# references for the learned ones: `random` (uniform actions), `hover` (stay put) and `kmeans`, the placement a wireless
# engineer would try first. Each slot it runs a few Lloyd iterations of k-means with k = U on the
# user positions, starting from the UAVs' own positions so that each UAV keeps "its" cluster, and
# flies each UAV toward its centroid (at most d_max per slot). It ignores demand classes, overlap and
# separation, which is what makes it a fair classical baseline rather than a tuned one.

# %%
#| export
def random_policy(core: "UAVBatchCore", rng: np.random.Generator):
    return rng.uniform(-1.0, 1.0, size=(core.B, core.cfg.n_uavs, 2))


def hover_policy(core: "UAVBatchCore", rng=None):
    return np.zeros((core.B, core.cfg.n_uavs, 2))


def kmeans_policy(core: "UAVBatchCore", rng=None, iterations: int = 5):
    """Fly each UAV toward the centroid of the user cluster it owns (k-means seeded at the UAVs)."""
    users = core.mobility.user_xy  # (B, N, 2)
    centroids = core.uav_xy.copy()  # (B, U, 2)
    U = centroids.shape[1]
    for _ in range(iterations):
        d = ((users[:, :, None, :] - centroids[:, None, :, :]) ** 2).sum(-1)  # (B, N, U)
        owner = (d.argmin(axis=-1)[..., None] == np.arange(U))  # (B, N, U)
        count = owner.sum(axis=1)  # (B, U)
        total = np.einsum("bnu,bnd->bud", owner.astype(float), users)
        centroids = np.where(count[..., None] > 0, total / np.maximum(count, 1)[..., None], centroids)
    return np.clip((centroids - core.uav_xy) / core.cfg.max_step_m, -1.0, 1.0)


HEURISTICS = {"random": random_policy, "hover": hover_policy, "kmeans": kmeans_policy}


def rollout_heuristic(policy: str, num_envs: int, steps: int, seed: int = 0, phase: int | None = None, **overrides):
    """Run a heuristic in a vector env; return per-step info arrays stacked to (steps, B)."""
    if policy not in HEURISTICS:
        raise ValueError(f"unknown heuristic {policy!r}; choose from {sorted(HEURISTICS)}")
    if phase is not None:
        overrides = {**overrides, "phase_clock": "external"}
    env = UAVVectorEnv(num_envs, seed, **overrides)
    if phase is not None:
        env.set_phase(phase)
    env.reset()
    act_rng = np.random.default_rng(seed)
    rows = []
    for _ in range(steps):
        _, _, _, _, _, info = env.step(HEURISTICS[policy](env.core, act_rng))
        rows.append({k: np.asarray(v) for k, v in info.items() if np.ndim(v) == 1 and k != "final_rows"})
    return {k: np.stack([r[k] for r in rows]) for k in rows[0]}


# %% [markdown]
# ## The wrappers side by side
#
# A PettingZoo episode and environment 2 of a vector env seeded 2 below it (so the same seed) see
# the same observations, rewards and infos step for step; the vector env restarts a finished
# episode in the same call and returns the last observation of the old one; the infos of
# `reset()` carry the keys of `step()`.

# %%
from pemamoe.env import make_env, make_vector_env

pz = make_env()
pz_obs, pz_infos = pz.reset(seed=seed + 2)
venv = make_vector_env(3, seed=seed)
v_obs, _, _ = venv.reset()
assert all(np.array_equal(pz_obs[f"uav_{u}"], v_obs[2, u]) for u in range(3))
wrap_rng = np.random.default_rng(seed)
for step in range(pz.cfg.episode_steps):
    acts = wrap_rng.uniform(-1, 1, (3, 3, 2))
    pz_obs, pz_rew, pz_term, pz_trunc, pz_step_infos = pz.step({f"uav_{u}": acts[2, u] for u in range(3)})
    v_obs, _, v_rew, v_term, v_trunc, v_info = venv.step(acts)
    assert pz_rew["uav_0"] == v_rew[2]
    if v_term[2] or v_trunc[2]:
        break
    assert all(np.array_equal(pz_obs[f"uav_{u}"], v_obs[2, u]) for u in range(3))
assert not pz.agents and 2 in v_info["final_rows"]
row = list(v_info["final_rows"]).index(2)
assert all(np.array_equal(pz_obs[f"uav_{u}"], v_info["final_obs"][row, u]) for u in range(3))
assert set(pz_infos["uav_0"]) == set(pz_step_infos["uav_0"])
print(f"PettingZoo episode of {step + 1} steps = vector env member 2, bit for bit; the vector env restarted it "
      f"in the same call (final_rows {v_info['final_rows'].tolist()})")
