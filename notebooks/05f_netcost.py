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
# # 05f · Appendix: parameter and compute counts, latency, the cost table
#
# Notebook 05 explains how the paper counts parameters and multiply-accumulates and reproduces its
# cost table. This appendix holds the code behind those numbers, in the module `pemamoe.netcost`:
# the counting functions in the paper's conventions, the timing of an agent step and of a training
# step, the cost table and the architecture diagram. It builds actors, so it imports
# `pemamoe.nets`, and nothing in `pemamoe.nets` imports it.

# %%
#| default_exp netcost

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## Cost accounting, latency and the cost table
#
# The counting functions implement the conventions notebook 05 explains, from each kind's
# `cost_parts()` (its parts' parameters and multiply-accumulates, built with `nets.linear_cost`):
# `count_parameters` (trainable parameters), `active_parameters(actor, mode)` (what takes part in
# one agent step: `paper`, `sampling` or `eval`) and `macs_per_step(actor, mode)`. `time_forward`
# measures an agent step (`act`, sampling, no gradient) and reports the median over repeats in
# microseconds; `time_train_step` a forward and backward pass of a surrogate loss. `cost_table`
# assembles, for each method and each named observation dimension, the counts and the measured
# latency at batch 1 and batch 2048. `draw_actor_architecture` draws notebook 05's diagram of an
# actor from its modules. All of it lives in module `pemamoe.netcost`, which imports `pemamoe.nets`.

# %%
#| export
import statistics
import time

import torch

from pemamoe.methods import METHOD_REGISTRY
from pemamoe.nets import PAPER_NET, GaussianActor, NetConfig, make_actor

ACTIVE_MODES = ("paper", "sampling", "eval")
MAC_MODES = ("sampling", "eval")


def count_parameters(module: torch.nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def _executed(actor: GaussianActor, mode: str) -> dict:
    # How many copies of each part run in one agent step under `mode`.
    sparse = getattr(actor, "sparse", None)
    if sparse is None:  # MLP
        return {"router": 0, "noise_gate": 0, "one_expert": 1, "head": 1, "log_std": 1}
    gate = actor.gate
    experts = gate.k if sparse else gate.n_experts
    learned = gate.noise == "learned"  # only learned noise runs a noise gate
    noise = 0 if (mode == "eval" or not learned) else 1
    if mode == "paper":
        noise = 1 if learned else 0
    head = 0 if (mode == "paper" and sparse) else 1
    return {"router": 1, "noise_gate": noise, "one_expert": experts, "head": head, "log_std": head}


def active_parameters(actor: GaussianActor, mode: str = "paper") -> int:
    """Parameters taking part in one agent step; mode in ACTIVE_MODES (see notebook 05)."""
    if mode not in ACTIVE_MODES:
        raise ValueError(f"active_parameters mode must be one of {', '.join(ACTIVE_MODES)}, got {mode!r}")
    parts, used = actor.cost_parts(), _executed(actor, mode)
    return sum(parts[name][0] * n for name, n in used.items())


def macs_per_step(actor: GaussianActor, mode: str = "sampling") -> int:
    """Multiply-accumulates of the linear layers for one agent step; mode in MAC_MODES."""
    if mode not in MAC_MODES:
        raise ValueError(f"macs_per_step mode must be one of {', '.join(MAC_MODES)}, got {mode!r}")
    parts, used = actor.cost_parts(), _executed(actor, mode)
    return sum(parts[name][1] * n for name, n in used.items())


def _median_us(fn, repeats: int, warmup: int) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        fn()
        times.append(time.perf_counter_ns() - t0)
    return statistics.median(times) / 1e3


def time_forward(actor: GaussianActor, batch: int, repeats: int = 50, warmup: int = 5, seed: int = 0) -> float:
    """Median microseconds of actor.act(obs) (sampling, no gradient) on a (batch, obs_dim) input."""
    obs = torch.randn(batch, actor.obs_dim, generator=torch.Generator().manual_seed(seed))
    return _median_us(lambda: actor.act(obs), repeats, warmup)


def time_train_step(actor: GaussianActor, batch: int, repeats: int = 20, warmup: int = 3, seed: int = 0) -> float:
    """Median microseconds of evaluate(obs, action, routing) + backward of a PPO-like loss."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(batch, actor.obs_dim, generator=g)
    action, _, routing = actor.act(obs)

    def step():
        logp, ent, aux = actor.evaluate(obs, action, routing)
        loss = -(logp.mean() + 0.01 * ent.mean()) + aux["aux_loss"]
        actor.zero_grad(set_to_none=True)
        loss.backward()

    return _median_us(step, repeats, warmup)


def cost_table(
    obs_dims: dict,
    cfg: NetConfig | None = None,
    act_dim: int = 2,
    repeats: int = 50,
    batch_sizes: tuple = (1, 2048),
    seed: int = 0,
    threads: int | None = 1,
):
    """Per actor kind and per named observation dimension: parameters, ratio to the MLP, active
    parameters (paper / sampling / eval conventions), MACs per agent step, and measured `act`
    latency (median microseconds) at each batch size, timed with `threads` torch threads
    (None: leave the current setting); cfg None: the paper's reading (nets.PAPER_NET, learned
    routing noise), whose counts the paper's table reports. Returns a pandas DataFrame."""
    import pandas as pd

    cfg = cfg or PAPER_NET
    old_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        return pd.DataFrame(_cost_rows(obs_dims, cfg, act_dim, repeats, batch_sizes, seed))
    finally:
        torch.set_num_threads(old_threads)


def _cost_rows(obs_dims, cfg, act_dim, repeats, batch_sizes, seed):
    rows = []
    for label, obs_dim in obs_dims.items():
        torch.manual_seed(seed)
        actors = {name: make_actor(spec.network, obs_dim, act_dim, cfg) for name, spec in METHOD_REGISTRY.items()
                  if spec.compared}
        mlp_params = count_parameters(actors["mlp"])
        mlp_macs = macs_per_step(actors["mlp"])
        for kind, actor in actors.items():
            row = {
                "obs": label,
                "obs_dim": obs_dim,
                "actor": kind,  # the method's name
                "params": count_parameters(actor),
                "params_vs_mlp": round(count_parameters(actor) / mlp_params, 2),
                "active_params": active_parameters(actor, "paper"),
                "active_sampling": active_parameters(actor, "sampling"),
                "active_eval": active_parameters(actor, "eval"),
                "macs_per_step": macs_per_step(actor, "sampling"),
                "macs_vs_mlp": round(macs_per_step(actor, "sampling") / mlp_macs, 3),
                "macs_eval": macs_per_step(actor, "eval"),
            }
            for b in batch_sizes:
                row[f"latency_us_b{b}"] = round(time_forward(actor, b, repeats=repeats, seed=seed), 1)
            row["torch_threads"] = torch.get_num_threads()
            rows.append(row)
    return rows


def _box(ax, x, y, w, h, text, color, fontsize=7.5, style="round,pad=0.02"):
    from matplotlib.patches import FancyBboxPatch  # here: the package does not need matplotlib to load

    ax.add_patch(FancyBboxPatch((x - w / 2, y - h / 2), w, h, boxstyle=style, fc=color, ec="0.25", lw=0.8))
    ax.text(x, y, text, ha="center", va="center", fontsize=fontsize)


def _arrow(ax, x0, y0, x1, y1, dashed=False, color="0.2"):
    ax.annotate(
        "", xy=(x1, y1), xytext=(x0, y0),
        arrowprops=dict(arrowstyle="-|>", lw=0.8, color=color, ls="--" if dashed else "-", shrinkA=1, shrinkB=1),
    )


def draw_actor_architecture(ax, actor, method: str) -> None:
    """Box diagram of `actor` (the network of `method`) on matplotlib axes `ax`: layer shapes and
    parameter counts read off the modules (notebook 05's figure `architecture_actors`)."""
    spec = METHOD_REGISTRY[method]
    parts = actor.cost_parts()
    d, h = actor.obs_dim, actor.cfg.hidden
    ax.set_xlim(0, 11.2), ax.set_ylim(0.2, 10), ax.axis("off")
    title = f"{spec.label} ({actor.kind} network)"
    ax.set_title(f"{title}\n{count_parameters(actor):,} params, {active_parameters(actor):,} active (paper conv.)", fontsize=9)
    _box(ax, 5, 9.4, 3.6, 0.7, f"observation $o$ ({d})", "#eeeeee")
    head_y, out_y = 2.4, 0.9
    if actor.kind == "mlp":
        _box(ax, 5, 6.0, 4.0, 3.2, f"trunk\n{d}→{h}→{h}, ReLU\n{parts['one_expert'][0]:,} params", "#cfe2f3")
        _arrow(ax, 5, 9.05, 5, 7.6)
        _arrow(ax, 5, 4.4, 5, head_y + 0.4)
    else:
        e = actor.gate.n_experts
        xs = [2.2 + i * 2.8 for i in range(e)]
        sparse = actor.gate.sparse
        for i, x in enumerate(xs):
            chosen = (not sparse) or i == 1
            color = "#cfe2f3" if chosen else "#f3f3f3"
            _box(ax, x, 5.6, 2.4, 1.6, f"expert {i + 1}\n{d}→{h}→{h}\n{parts['one_expert'][0]:,}", color, fontsize=7)
            _arrow(ax, 5, 9.05, x, 6.4, dashed=not chosen)
            _arrow(ax, x, 4.8, 5, 4.05, dashed=not chosen)
        lines = [f"router {d}→{e} ({parts['router'][0]})"]
        if actor.gate.noise == "learned":
            lines += [f"noise gate {d}→{e} ({parts['noise_gate'][0]})", "z/τ + ε·softplus(z$_n$)", "softmax, keep top-1"]
        elif actor.gate.noisy:
            lines += [f"z/τ + σε ({actor.gate.noise} σ)", "softmax, keep top-1"]
        elif sparse:
            lines += ["softmax(z/τ)", "keep top-1"]
        else:
            lines += ["softmax(z/τ)", "mix all experts"]
        _box(ax, 9.5, 8.2, 3.1, 1.7, "\n".join(lines), "#fce5cd", fontsize=6.5)
        _arrow(ax, 6.8, 9.4, 7.95, 9.0)
        _box(ax, 5, 3.7, 3.6, 0.7, "Σ$_j$ w$_j$ · features$_j$", "#d9ead3", fontsize=7.5)
        ax.plot([10.6, 10.6], [7.35, 3.7], color="#b45f06", lw=0.8)
        _arrow(ax, 10.6, 3.7, 6.8, 3.7, color="#b45f06")
        ax.text(10.5, 4.9, "gate\nweights", ha="right", va="center", fontsize=6, color="#b45f06")
        _arrow(ax, 5, 3.35, 5, head_y + 0.4)
        if spec.plasticity != "none":
            _box(ax, 9.3, 1.5, 3.1, 1.3, "phase controller\n(0 params): τ, log σ,\nexpert noise, LR, KL", "#ead1dc", fontsize=6)
            ax.plot([9.3, 9.3], [2.15, 7.35], color="#741b47", lw=0.8, ls="--")
            _arrow(ax, 7.75, 1.7, 6.85, head_y, dashed=True, color="#741b47")
    _box(ax, 5, head_y, 3.7, 0.8, f"shared head {h}→2 ({parts['head'][0]})\n+ log σ ({parts['log_std'][0]})", "#d9d2e9", fontsize=7)
    _arrow(ax, 5, head_y - 0.4, 5, out_y + 0.35)
    _box(ax, 5, out_y, 3.4, 0.7, "a ~ N(μ, diag σ²)", "#eeeeee")


# %% [markdown]
# ## Demonstration: timing an agent step
#
# `time_forward` on this machine, at batch 1 (an agent step) and at a rollout-sized batch. The
# numbers depend on the machine and its load; the cost table of notebook 05 reports them beside the
# counts.

# %%
from pemamoe.core import by_scale
from pemamoe.nets import PAPER_OBS_DIM

cfg = NetConfig()
repeats = by_scale(scale, ci=3, small=20, paper=50)
for kind in ("mlp", "smoe"):
    actor = make_actor(kind, PAPER_OBS_DIM, 2, cfg)
    print(f"{kind:<5} act: batch 1 {time_forward(actor, 1, repeats=repeats):8.1f} us, "
          f"batch 2048 {time_forward(actor, 2048, repeats=repeats):9.1f} us; "
          f"train step at 256 rows {time_train_step(actor, 256, repeats=repeats):9.1f} us")
