"""Benchmark of the population trainer (notebook 07, pemamoe/mappo.py): the run as a tensor axis.

For each method at the paper preset, trains populations of R = 1, 4 and 16 members for a few
iterations (one torch thread, as the sweep workers run) and prints, measured in this invocation:

* throughput: member environment steps per second, summed over the members
  (R x 2048 / seconds per iteration), and its ratio to R = 1;
* per-run speed: environment steps per second of one member (2048 / seconds per iteration);
* the split of an iteration into rollout and update;

then projects the 39-run sweeps (paper, small and medium scale) from the measured rates and the
sweep's own grouping of runs into populations, profiles a 16-member MLP and PE-MAMoE iteration for
the share of its time inside matrix-product kernels (and the throughput those kernels alone would
allow), and measures the peak resident memory of a 16-member paper-preset population in a child
process. Diagnostics are switched off while timing (they run every 50 iterations in a real run;
their cost is printed separately at R = 1).

Run with `python benchmarks/bench_train.py` (about 8 minutes on the 2-core machine);
`--device cuda [--methods ..] [--sizes ..]` measures only the rates, on a GPU, and `--rates-only`
does the same on the CPU (benchmarks/device_check.sh and its CPU rehearsal,
benchmarks/device_rehearsal.sh). The rates go to build/bench_train_<device>.json as
{"<method>/R<R>": {"throughput": member env steps/s, "per_run_sps": ..., "iteration_s": ...}}.
"""

import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from pemamoe.mappo import METHODS, TrainConfig, train_population  # noqa: E402

SIZES = (1, 4, 16)
TIMED = 2  # iterations timed after one warm-up iteration
TARGET_THROUGHPUT = 10_000  # member env steps / s for PE-MAMoE at R = 16 (paper preset)
TARGET_SMALL_SWEEP_MIN = 8.0
TARGET_MEDIUM_SWEEP_MIN = 120.0  # the whole medium sweep (issue: at most 2 hours)
TARGET_RSS_GIB = 4.0


def measure(method: str, R: int, scale: str = "paper", device: str = "cpu") -> dict:
    cfgs = [TrainConfig.for_scale(scale, method=method, seed=s, diag_every=10**9, device=device) for s in range(R)]
    res = train_population(cfgs, max_iterations=1 + TIMED, threads=1, progress=False)
    m = res[0].metrics.iloc[1:]
    roll, upd = statistics.median(m["rollout_time"]), statistics.median(m["update_time"])
    it_s = roll + upd
    steps = cfgs[0].batch_env_steps
    return {"method": method, "R": R, "rollout_s": roll, "update_s": upd, "iteration_s": it_s,
            "throughput": R * steps / it_s, "per_run_sps": steps / it_s}


MATMUL_OPS = ("aten::bmm", "aten::baddbmm", "aten::mm", "aten::addmm", "aten::mv", "aten::addmv")


def matmul_ceiling(method: str, R: int) -> dict:
    """Share of one paper-preset iteration spent inside matrix-product kernels, from the profiler's
    self time of those kernels in a real iteration, and the throughput if everything else were
    free: an upper bound that no removal of overhead can beat without fewer or faster products."""
    from torch.profiler import ProfilerActivity, profile

    cfgs = [TrainConfig.for_scale("paper", method=method, seed=s, diag_every=10**9) for s in range(R)]
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        res = train_population(cfgs, max_iterations=2, threads=1, progress=False)
    m = res[0].metrics
    # both iterations are in the profile; the first also builds and warms up, so count the kernels
    # of both against the logged time of both
    total = float(m["rollout_time"].sum() + m["update_time"].sum())
    mm = sum(e.self_cpu_time_total for e in prof.key_averages() if e.key in MATMUL_OPS) / 1e6
    steps = cfgs[0].batch_env_steps * len(m)
    return {"matmul_s": mm, "iteration_s": total, "share": mm / total, "ceiling": R * steps / mm}


TARGET_OPS_PER_MINIBATCH = 200  # torch operations dispatched per PPO minibatch step (issue 43)


def ops_per_minibatch(method: str, scale: str = "paper") -> float:
    """Torch operations dispatched (forward, backward, optimizer, statistics; views included) per
    minibatch step of PPO's update, counted with a dispatch mode around ppo_update in one iteration
    (one epoch of 8 minibatches of the preset's size: the count per step does not depend on how many)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    import pemamoe.mappo as mappo

    class Count(TorchDispatchMode):
        n = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            Count.n += 1
            return func(*args, **(kwargs or {}))

    update, steps = mappo.ppo_update, []

    def counted(*args, **kwargs):
        with Count():
            out = update(*args, **kwargs)
        steps.append(sum(out["gradient_steps"]))
        return out

    cfg = TrainConfig.for_scale(scale, method=method, seed=0, diag_every=10**9, update_epochs=1, num_minibatches=8)
    cfg = cfg.replace(num_envs=cfg.num_envs // 4)  # minibatches of a quarter: the same ops, less waiting
    mappo.ppo_update = counted
    try:
        train_population([cfg], max_iterations=1, threads=1, progress=False)
    finally:
        mappo.ppo_update = update
    return Count.n / sum(steps)


def fill_ratio(method: str, R: int, rounds: int = 3) -> dict:
    """Seconds per paper-preset iteration with deterministic mode's NaN fill of new tensors on (as
    before) and off (the trainer's setting), in interleaved rounds: (median on, median off, ratio)."""
    import pemamoe.bookkeeping as bk

    times = {True: [], False: []}
    try:
        for _ in range(rounds):
            for fill in (True, False):
                bk.FILL_UNINITIALIZED_MEMORY = fill
                times[fill].append(measure(method, R)["iteration_s"])
    finally:
        bk.FILL_UNINITIALIZED_MEMORY = False
    on, off = statistics.median(times[True]), statistics.median(times[False])
    return {"on": on, "off": off, "ratio": on / off, "ratios": [a / b for a, b in zip(times[True], times[False])]}


def report_update_ops() -> None:
    """The update's cost in operations and the fill's share, measured in this invocation."""
    for method in ("mlp", "pemamoe"):
        ops = ops_per_minibatch(method)
        verdict = "met" if ops <= TARGET_OPS_PER_MINIBATCH else "NOT met"
        print(f"{method}: {ops:.0f} torch operations per PPO minibatch step (target <= {TARGET_OPS_PER_MINIBATCH}: {verdict})",
              flush=True)
    for R in (1, 16):
        f = fill_ratio("pemamoe", R)
        print(f"pemamoe R = {R}: paper-preset iteration {f['on']:.3f} s with the NaN fill of new tensors, "
              f"{f['off']:.3f} s without ({f['ratio']:.2f}x; rounds {', '.join(f'{r:.2f}' for r in f['ratios'])})",
              flush=True)


def diagnostics_cost(method: str) -> float:
    cfg = TrainConfig.for_scale("paper", method=method, seed=0, diag_every=1)
    m = train_population([cfg], max_iterations=2, threads=1, progress=False)[0].metrics
    return float(m["diag_time"].iloc[1])


def rss_child(R: int) -> float:
    """Peak RSS (GiB) of a process that trains an R-member paper-preset PE-MAMoE population."""
    # VmHWM is the peak of the child's own address space. getrusage's ru_maxrss is not: Linux
    # carries the parent's resident size over the fork and exec, so after the timed populations
    # above it reported this benchmark's own 5.4 GiB instead of the child's.
    code = ("import resource; from pemamoe.mappo import TrainConfig, train_population; "
            f"cfgs=[TrainConfig.for_scale('paper', method='pemamoe', seed=s) for s in range({R})]; "
            "train_population(cfgs, max_iterations=2, threads=1, progress=False); "
            "hwm=[l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM:')]; "
            "print(hwm[0] if hwm else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[1])
    return int(out.stdout.strip().splitlines()[-1]) / 2**20  # KiB -> GiB


def sweep_groups(scale: str) -> list:
    """[(method, members)] of the 39-run sweep as run_sweep groups it (population cap 16)."""
    from pemamoe.experiments import experiment_specs, group_specs

    unique = {}
    for spec in experiment_specs("all", scale):  # as run_sweep does: one run per folder
        unique.setdefault(spec.to_config().config_hash(), spec)
    return [(g[0].method, len(g)) for g in group_specs(list(unique.values()), 16, 2)]


def rate_table(methods, sizes, device: str, scale: str = "paper") -> dict:
    """Measure and print each method at each population size; {(method, R): measure(...)}."""
    print(f"{'method':8s} {'R':>3s} {'rollout s':>9s} {'update s':>9s} {'throughput':>11s} {'x R=1':>6s} {'per-run SPS':>11s}")
    rates = {}
    for method in methods:
        base = None
        for R in sizes:
            r = measure(method, R, scale, device=device)
            base = base or r["throughput"]
            rates[(method, R)] = r
            print(f"{method:8s} {R:3d} {r['rollout_s']:9.2f} {r['update_s']:9.2f} {r['throughput']:11.0f} "
                  f"{r['throughput'] / base:6.2f} {r['per_run_sps']:11.0f}", flush=True)
    return rates


def report_target(rates: dict, json_name: str, where: str = "", scale: str = "paper") -> None:
    """Print the PE-MAMoE R = 16 throughput against the target (a paper-preset figure, so only
    there, and only where it was measured); keep the rates in build/."""
    if scale == "paper" and ("pemamoe", 16) in rates:
        thr = rates[("pemamoe", 16)]["throughput"]
        print(f"target: PE-MAMoE throughput at R = 16 >= {TARGET_THROUGHPUT}: {thr:.0f} "
              f"({'met' if thr >= TARGET_THROUGHPUT else 'NOT met'}){where}")
    out = Path(__file__).resolve().parents[1] / "build" / json_name
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps({f"{m}/R{R}": v for (m, R), v in rates.items()}, indent=1))


def rates_main(sizes, methods, device: str = "cuda", scale: str = "paper") -> int:
    """`--device cuda` (or `--rates-only`): the per-member rates alone, with the networks and the
    update on `device` (the environment stays on the CPU, one torch thread). No projections or
    CPU-only figures. Writes build/bench_train_<device>.json."""
    torch.set_num_threads(1)
    name = torch.cuda.get_device_name(0) if device == "cuda" else "cpu"
    print(f"device: {name}; {scale} preset, 1 CPU torch thread for the environment side")
    rates = rate_table(methods, sizes, device, scale)
    if device == "cuda":
        print(f"peak GPU memory: {torch.cuda.max_memory_allocated() / 2**30:.2f} GiB")
    report_target(rates, f"bench_train_{device}.json", " on the GPU" if device == "cuda" else "", scale)
    return 0


def checkpoint_cost(scale: str) -> dict:
    """Seconds one member spends writing its last checkpoint of a `scale` run (the checkpoint
    holds every log row so far), with the rows stored as lists (checkpoint format 2), packed
    into one pickled bytes object (format 3) and as a RowLog's chunks, of which only the last
    checkpoint's rows are new (format 4), and the two parquet logs written beside it, converting
    every row (as the final, sealed write does) or only the new ones (every other write). The rows
    have the shape and types of real ones: the keys of a real ci run's rows, distinct numbers."""
    import io
    import random
    import tempfile

    import pandas as pd

    from pemamoe.bookkeeping import RowLog, _pack_rows, write_rows_parquet
    from pemamoe.mappo import train

    cfg = TrainConfig.for_scale(scale)
    with tempfile.TemporaryDirectory() as tmp:
        ci = train(TrainConfig.for_scale("ci", method="pemamoe"), Path(tmp) / "ci", progress=False)
        metric_row, episode_row = ci.metrics.iloc[-1].to_dict(), ci.episodes.iloc[-1].to_dict()
    rng = random.Random(0)

    def rows(template, n):
        template = {k: (v.item() if hasattr(v, "item") else v) for k, v in template.items()}  # numpy -> python
        out = []
        for i in range(n):
            row = {}
            for k, v in template.items():  # same types as the template: python floats, ints, bools
                row[k] = (v if isinstance(v, bool) else i if isinstance(v, int) else rng.random()) \
                    if isinstance(v, (bool, int, float)) else v
            out.append(row)
        return out

    episodes_per_iteration = cfg.num_envs * cfg.rollout_steps / cfg.env_config().episode_steps
    metrics = rows(metric_row, cfg.iterations)
    episodes = rows(episode_row, int(cfg.iterations * episodes_per_iteration))
    out = {"metric_rows": len(metrics), "episode_rows": len(episodes), "checkpoints": cfg.iterations // cfg.checkpoint_every}
    for name, pack in (("lists", lambda r: r), ("packed", _pack_rows)):
        start = time.perf_counter()
        torch.save({"metrics_rows": pack(metrics), "episode_rows": pack(episodes)}, io.BytesIO())
        out[name] = time.perf_counter() - start
    # RowLogs that have encoded every row but the last checkpoint's (as they have in a run)
    new_metrics, new_episodes = cfg.checkpoint_every, int(cfg.checkpoint_every * episodes_per_iteration)
    logs = [RowLog(metrics[:-new_metrics]), RowLog(episodes[:-new_episodes])]
    for log in logs:
        log.packed(), log.frame()
    logs[0] += metrics[-new_metrics:]
    logs[1] += episodes[-new_episodes:]
    start = time.perf_counter()
    torch.save({"metrics_rows": logs[0].packed(), "episode_rows": logs[1].packed()}, io.BytesIO())
    out["chunks"] = time.perf_counter() - start
    with tempfile.TemporaryDirectory() as tmp:
        for name, final in (("parquet", True), ("parquet_new_rows", False)):
            start = time.perf_counter()
            write_rows_parquet(logs[0], Path(tmp) / "metrics.parquet", final)
            write_rows_parquet(logs[1], Path(tmp) / "episodes.parquet", final)
            out[name] = time.perf_counter() - start
    return out


CAMPAIGN_BASELINES = ("mlp_redo", "mlp_snp")  # the paper-scale campaign's plasticity baselines (issue 38)
CAMPAIGN_POPULATION = 5  # seeds per method of campaign v2 (issue 57), trained as one population


def report_campaign(iteration_s) -> None:
    """Campaign v2 at the paper scale (the main comparison and the two plasticity baselines, one
    population of 5 seeds each, every update at its full 8 x 32 steps as this benchmark times it)
    projected from this invocation's rates, beside what campaign v1's committed records measured
    (their timing files: each member's share of its population's compute; v1's sparse networks took
    a fraction of their steps after the first switch, so they cost less than a full update).
    The baselines run at MLP's measured rate: their own work is a few operations per phase switch."""
    iters = TrainConfig.for_scale("paper").iterations
    populations = [*METHODS, *CAMPAIGN_BASELINES]
    hours = {m: iteration_s(m if m in METHODS else "mlp", CAMPAIGN_POPULATION) * iters / 3600 for m in populations}
    print(f"projected paper campaign v2: {len(populations) * CAMPAIGN_POPULATION} runs in {len(populations)} populations "
          f"of {CAMPAIGN_POPULATION}: {sum(hours.values()):.1f} core-hours "
          f"({', '.join(f'{m} {h:.1f}' for m, h in hours.items())})", flush=True)
    recorded = {}
    for timing in (Path(__file__).resolve().parents[1] / "records" / "paper").glob("*.timing.json"):
        method = timing.name.split("-s")[0]
        recorded[method] = recorded.get(method, 0.0) + json.loads(timing.read_text())["member_compute_s"] / 3600
    if recorded:
        print("campaign v1's committed paper records measured (3 seeds each): " + ", ".join(
            f"{m} {h:.1f} worker-hours (projected here {hours[m]:.1f})" for m, h in sorted(recorded.items()) if m in hours))


def main() -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                        help="cuda: the population rates on a GPU only (benchmarks/device_check.sh)")
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="population sizes (cuda or --rates-only; default 1 4 16)")
    parser.add_argument("--methods", nargs="+", default=None, choices=METHODS, help="methods (cuda or --rates-only; default all)")
    parser.add_argument("--rates-only", action="store_true",
                        help="only the population rates, as --device cuda does (on the CPU: the device check's rehearsal)")
    parser.add_argument("--update-ops", action="store_true",
                        help="only the update's operations per minibatch step and the NaN-fill ratio")
    parser.add_argument("--scale", default="paper", choices=("ci", "small", "medium", "paper"),
                        help="preset of the rates with --device cuda or --rates-only (default paper)")
    args = parser.parse_args()
    if args.device == "cuda" or args.rates_only:
        if args.device == "cuda" and not torch.cuda.is_available():
            parser.error("--device cuda: torch sees no CUDA device on this machine")
        return rates_main(args.sizes or list(SIZES), args.methods or list(METHODS), args.device, args.scale)
    torch.set_num_threads(1)
    if args.update_ops:
        report_update_ops()
        return 0
    print("paper preset: 64 envs x 32 slots = 2048 env steps/iteration, 8 epochs x 32 minibatches, 1 torch thread")
    rates = rate_table(METHODS, SIZES, "cpu")
    print(f"diagnostics (every 50 iterations at the paper preset): {diagnostics_cost('pemamoe'):.2f} s per call (pemamoe, R = 1)")

    # Projections: each population's iterations at the measured rate of the nearest measured size,
    # two worker processes sharing the two cores.
    def iteration_s(method, R):
        near = min(SIZES, key=lambda s: (abs(s - R), s))
        return rates[(method, near)]["iteration_s"] * (R / near if R > near else 1.0)

    small_rates = {}  # iteration seconds at the small update settings (the small and medium presets)
    for scale in ("paper", "small", "medium"):
        try:
            groups = sweep_groups(scale)
        except Exception as err:  # the grouping lives in the sweep module
            print(f"{scale} sweep projection unavailable: {err}")
            continue
        iters = TrainConfig.for_scale(scale).iterations
        if scale in ("small", "medium"):  # rates at the small preset, measured here for each group size used
            for method, R in groups:
                if (method, R) not in small_rates:
                    small_rates[(method, R)] = measure(method, R, "small")["iteration_s"]
            seconds = [small_rates[(m, R)] * iters for m, R in groups]
        else:
            seconds = [iteration_s(m, R) * iters for m, R in groups]
        workers = [0.0, 0.0]  # the pool hands populations, in order, to whichever worker is free
        for sec in seconds:
            workers[workers.index(min(workers))] += sec
        runs = sum(R for _, R in groups)
        print(f"projected {scale} sweep: {runs} runs in {len(groups)} populations "
              f"({', '.join(f'{m}x{R}' for m, R in groups)}): {max(workers) / 60:.1f} min on 2 workers "
              f"({sum(seconds) / 3600:.2f} core-hours)", flush=True)
        if scale == "small":
            verdict = "met" if max(workers) / 60 <= TARGET_SMALL_SWEEP_MIN else "NOT met"
            print(f"target: small sweep <= {TARGET_SMALL_SWEEP_MIN:.0f} min: {verdict}")
        if scale == "medium":
            verdict = "met" if max(workers) / 60 <= TARGET_MEDIUM_SWEEP_MIN else "NOT met"
            print(f"target: medium sweep <= {TARGET_MEDIUM_SWEEP_MIN:.0f} min: {verdict}")

    report_campaign(iteration_s)

    for method in ("mlp", "pemamoe"):
        c = matmul_ceiling(method, 16)
        print(f"{method} R = 16: matrix products take {c['share']:.0%} of an iteration (profiled); with every "
              f"other cost removed the throughput would be at most {c['ceiling']:.0f} member env steps/s", flush=True)

    for scale in ("medium", "paper"):
        c = checkpoint_cost(scale)
        # the rows grow linearly over a run, so the whole run's checkpoints cost about half the last one's, times their number
        run = {k: c[k] * c["checkpoints"] / 2 for k in ("lists", "packed", "parquet")}
        # format 4: the rows' chunk costs the same at every checkpoint; the parquet write of the new
        # rows still writes the whole table, which grows (half its last cost on average, an upper
        # bound: the conversion part does not grow); plus one final write converting every row
        chunked = c["checkpoints"] * (c["chunks"] + c["parquet_new_rows"] / 2) + c["parquet"]
        print(f"checkpoint of one member at the end of a {scale} run ({c['metric_rows']:,} metric rows, "
              f"{c['episode_rows']:,} episode rows): rows as lists {c['lists']:.2f} s, packed {c['packed']:.2f} s "
              f"({c['lists'] / c['packed']:.1f}x less), new rows only {c['chunks']:.3f} s; parquet logs "
              f"{c['parquet']:.2f} s converting every row, {c['parquet_new_rows']:.2f} s converting the new ones "
              f"({c['parquet'] / c['parquet_new_rows']:.1f}x less); over the run's {c['checkpoints']} checkpoints about "
              f"{(run['lists'] + run['parquet']) / 60:.1f} min per member with lists, "
              f"{(run['packed'] + run['parquet']) / 60:.1f} min packed, {chunked / 60:.1f} min with new rows only", flush=True)

    report_update_ops()
    gib = rss_child(16)
    print(f"peak RSS of a 16-member paper-preset PE-MAMoE population: {gib:.2f} GiB "
          f"(target <= {TARGET_RSS_GIB:.0f} GiB: {'met' if gib <= TARGET_RSS_GIB else 'NOT met'})")
    report_target(rates, "bench_train.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
