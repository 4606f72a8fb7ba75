"""Benchmark of the MAPPO trainer (notebook 07, pemamoe/mappo.py).

For each method at the `small` preset, runs a few training iterations (one torch thread, the way
the sweep workers run) and prints environment steps per second, the split of an iteration into
rollout / update / diagnostics, and the projected wall time of one full small-scale run and of
the whole small sweep (about 40 runs on 2 worker processes). Then runs two PE-MAMoE trainings
at once in two processes, to see what sharing the 2 cores costs. Run with

    python benchmarks/bench_train.py

It finishes in about a minute on a 2-core machine.
"""

import multiprocessing as mp
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pemamoe.mappo import METHODS, TrainConfig, train  # noqa: E402

ITERS = 6  # timed iterations per method (the first one, with its warm-up, is dropped)
SWEEP_RUNS = 40  # 4 methods x 3 seeds + 4 ablations x 3 seeds + noise sweep: about 40 runs
WORKERS = 2


def measure(method: str, iters: int = ITERS) -> dict:
    cfg = TrainConfig.for_scale("small", method=method, seed=0)
    t0 = time.perf_counter()
    res = train(cfg, None, max_iterations=iters, threads=1)
    total = time.perf_counter() - t0
    m = res.metrics.iloc[1:]  # drop the first iteration (allocations, caches)
    roll, upd = statistics.median(m["rollout_time"]), statistics.median(m["update_time"])
    diag = m.loc[m["diag_time"] > 0.0005, "diag_time"]
    diag_t = statistics.median(diag) if len(diag) else 0.0
    n_diag = len([t for t in range(cfg.iterations)
                  if t % cfg.diag_every == 0 or t % cfg.phase_length_iters == 0 or t == cfg.iterations - 1])
    setup = total - res.metrics[["rollout_time", "update_time", "diag_time"]].to_numpy().sum()
    run_s = cfg.iterations * (roll + upd) + n_diag * diag_t + setup
    return {"method": method, "sps": cfg.batch_env_steps / (roll + upd), "rollout_s": roll, "update_s": upd,
            "diag_s": diag_t, "setup_s": setup, "run_s": run_s, "cfg": cfg}


def _worker(method, iters, queue):
    out = measure(method, iters)
    out.pop("cfg")
    queue.put(out)


def main() -> int:
    cfg = TrainConfig.for_scale("small")
    print(f"small preset: {cfg.num_envs} envs x {cfg.rollout_steps} slots = {cfg.batch_env_steps} env steps/iteration, "
          f"{cfg.iterations} iterations (L = {cfg.phase_length_iters}), {cfg.update_epochs} epochs x "
          f"{cfg.num_minibatches} minibatches, 1 torch thread")
    print(f"{'method':8s} {'SPS':>7s} {'rollout s':>10s} {'update s':>9s} {'diag s':>7s} {'setup s':>8s} {'run (min)':>10s}")
    rows = []
    for method in METHODS:
        r = measure(method)
        rows.append(r)
        print(f"{method:8s} {r['sps']:7.0f} {r['rollout_s']:10.3f} {r['update_s']:9.3f} {r['diag_s']:7.3f} "
              f"{r['setup_s']:8.2f} {r['run_s'] / 60:10.2f}", flush=True)
    mean_run = statistics.mean(r["run_s"] for r in rows)
    print(f"projected: one small run {mean_run / 60:.2f} min (mean over methods); {SWEEP_RUNS} runs on {WORKERS} "
          f"workers {SWEEP_RUNS * mean_run / WORKERS / 60:.1f} min if two runs share the cores without slowdown")

    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    procs = [ctx.Process(target=_worker, args=("pemamoe", ITERS, queue)) for _ in range(WORKERS)]
    for p in procs:
        p.start()
    outs = [queue.get() for _ in procs]
    for p in procs:
        p.join()
    solo = next(r for r in rows if r["method"] == "pemamoe")
    par = statistics.mean(o["sps"] for o in outs)
    print(f"{WORKERS} concurrent pemamoe runs: {par:.0f} SPS each (alone: {solo['sps']:.0f}); "
          f"projected sweep {SWEEP_RUNS * mean_run * solo['sps'] / par / WORKERS / 60:.1f} min")
    return 0


if __name__ == "__main__":
    sys.exit(main())
