"""Benchmark of the actor networks (notebook 05, pemamoe/nets.py).

Times the three expert-execution strategies of `ExpertBank` ("stacked", "masked", "loop") for
the dense MoE and the noisy top-1 SMoE actor, at batch 1 (one agent step), 256 and 2048 (a PPO
rollout / minibatch), at the paper's observation dimension 177 and at ours, first with one torch
thread and then with torch's default thread count. Then prints the latency columns of the cost
table. Every number is a median over repeats; run with

    python benchmarks/bench_nets.py

It finishes in well under a minute on a 2-core machine.
"""

import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pemamoe.methods import METHOD_REGISTRY  # noqa: E402
from pemamoe.nets import (  # noqa: E402
    PAPER_OBS_DIM,
    NetConfig,
    make_actor,
)
from pemamoe.netcost import cost_table  # noqa: E402

BATCHES = (1, 256, 2048)
EXPERT_IMPLS = ("stacked", "masked", "loop")  # the concrete strategies; "auto" picks among them
KINDS = ("smoe", "moe")
BUDGET_S = 0.08  # time spent per measurement (after warm-up)
MAX_REPEATS = 200


def our_obs_dim() -> int:
    try:  # TODO(env): drop the fallback once pemamoe.env is exported
        from pemamoe.env import EnvConfig, observation_dim

        return int(observation_dim(EnvConfig()))
    except ImportError:
        print("environment module not available; using obs_dim 129")
        return 129


def median_ms(fn) -> float:
    for _ in range(3):
        fn()
    times, start = [], time.perf_counter()
    while len(times) < 5 or (time.perf_counter() - start < BUDGET_S and len(times) < MAX_REPEATS):
        t0 = time.perf_counter_ns()
        fn()
        times.append(time.perf_counter_ns() - t0)
    return statistics.median(times) / 1e6


def bench_impls(kind: str, obs_dim: int, batch: int) -> dict:
    torch.manual_seed(0)
    actor = make_actor(kind, obs_dim, 2, NetConfig())
    obs = torch.randn(batch, obs_dim)
    action, _, routing = actor.act(obs)  # fixed routing: every strategy does the same work
    out = {}
    for impl in EXPERT_IMPLS:
        actor.gate.experts.impl = impl

        def fwd():
            with torch.no_grad():
                actor(obs, routing=routing)

        def fwd_bwd():
            logp, ent, aux = actor.evaluate(obs, action, routing)
            loss = -(logp.mean() + 0.01 * ent.mean()) + aux["aux_loss"]
            actor.zero_grad(set_to_none=True)
            loss.backward()

        out[impl] = (median_ms(fwd), median_ms(fwd_bwd))
    return out


def main() -> int:
    t_start = time.perf_counter()
    default_threads = torch.get_num_threads()
    ours = our_obs_dim()
    print(f"nets: torch {torch.__version__}, default threads = {default_threads}, obs dims paper={PAPER_OBS_DIM} ours={ours}")
    wins = {b: {impl: 0.0 for impl in EXPERT_IMPLS} for b in BATCHES}  # single thread, SMoE
    thread_settings = [1] + ([default_threads] if default_threads != 1 else [])
    for threads in thread_settings:
        torch.set_num_threads(threads)
        for kind in KINDS:
            label = "top1" if kind == "smoe" else "dense"
            for obs_dim in (PAPER_OBS_DIM, ours):
                for batch in BATCHES:
                    res = bench_impls(kind, obs_dim, batch)
                    for what, i in (("fwd", 0), ("fwd+bwd", 1)):
                        cells = " ".join(f"{impl}={res[impl][i]:.3f} ms" for impl in EXPERT_IMPLS)
                        best = min(EXPERT_IMPLS, key=lambda impl: res[impl][i])
                        print(f"nets: {kind} {label} threads={threads} obs={obs_dim} {what} batch={batch} {cells}  -> {best}")
                    if threads == 1 and kind == "smoe":
                        for impl in EXPERT_IMPLS:
                            wins[batch][impl] += res[impl][1]
    torch.set_num_threads(default_threads)
    cfg = NetConfig()
    for batch, tot in wins.items():
        auto = "masked" if batch >= cfg.masked_min_batch else "stacked"
        print(f"nets: smoe top1 threads=1 fwd+bwd batch={batch} summed over obs dims: "
              + " ".join(f"{impl}={ms:.3f} ms" for impl, ms in tot.items())
              + f"  -> fastest: {min(tot, key=tot.get)}; default '{cfg.expert_impl}' uses {auto}")

    table = cost_table({"paper": PAPER_OBS_DIM, "ours": ours}, repeats=20, threads=1)
    print("nets: cost table (act latency, median us, 1 thread)")
    for row in table.itertuples(index=False):
        print(
            f"nets: cost {row.obs:<5} obs={row.obs_dim:<4} {row.actor:<8} params={row.params:>6} "
            f"active={row.active_params:>6} macs={row.macs_per_step:>6} "
            f"latency b1={row.latency_us_b1:>8.1f} us b2048={row.latency_us_b2048:>9.1f} us"
        )
    assert set(table.actor) == {name for name, spec in METHOD_REGISTRY.items() if spec.compared}
    print(f"nets: benchmark finished in {time.perf_counter() - t_start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
