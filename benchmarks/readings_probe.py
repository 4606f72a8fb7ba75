"""The readings probe (issue 57): the paper scale's first three phase visits under each candidate
reading of the two settings the paper leaves open and whose reading moves results.

* The target-KL stop (TrainConfig `target_kl`, `target_kl_check`): checked before every
  minibatch's step (campaign v1's reading), after every epoch on its last minibatch (CleanRL's
  continuous PPO, whose names the paper's training table uses), or never (Algorithm 1's update loop
  draws no stop; PE-MAMoE's conservative window keeps its own target, which Algorithm 1 sets).
* PE-MAMoE's log-std reset value "0.3" (`controller.log_std_value`): sigma = 0.3 (v1's reading,
  log sigma = -1.20, which narrows a widened policy) or log sigma = 0.3 (sigma = 1.35).

Each method trains as one population whose members are its readings x seeds (members may differ
in these fields: notebook 07d), to `--iterations` (3,600: phases 0, 1, 2 once each) of the paper
preset. Runs train into results/readings_probe/<run name>/ and resume there; `--hours` stops every
population with a checkpoint and packs each unfinished member's portable state into
benchmarks/readings_probe/paper/in_progress/ (commit it: `unpack` restores it on another machine,
then `train` goes on bit for bit). `report` writes benchmarks/READINGS_PROBE.md from the run folders:
per method, reading and phase visit, mean coverage and return over the visit so far, gradient steps
per iteration, and the policy's sigma just before and after each switch; and the same per member in
records/paper/probes/readings_probe.csv, which notebook 10b reads for the readings table.

    python benchmarks/readings_probe.py train --methods smoe --hours 2.5
    python benchmarks/readings_probe.py unpack     # on a fresh machine, before train
    python benchmarks/readings_probe.py report

The probe trains under TRAINING_NUMERICS 2, the arithmetic it started with (commit 21bf770): a
member's run is named by that version (`PROBE_NUMERICS`) whatever the checkout, and `train` runs
only from a checkout whose code computes that version (`git worktree add ../probe a9bbb68`, the last
commit before the bump to 3, which also reads the portable states `unpack` restores),
since a checkpoint is never resumed under another arithmetic. `unpack` and `report` work anywhere.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results" / "readings_probe"
STATES = ROOT / "benchmarks" / "readings_probe"  # its own records folder: portable states only
REPORT = ROOT / "benchmarks" / "READINGS_PROBE.md"
SUMMARY = ROOT / "records" / "paper" / "probes" / "readings_probe.csv"  # per member and visit, for notebook 10b
ITERATIONS = 3600  # the first three phase visits at the paper scale (L = 1,200)
SEEDS = (0, 1)
KL_READINGS = {
    "stop per minibatch (v1)": {},
    "stop per epoch (CleanRL)": {"target_kl_check": "epoch"},
    "no stop": {"target_kl": None},
}
LOG_STD_READINGS = {
    "sigma <- 0.3 (v1)": {},
    "log sigma <- 0.3": {"controller.log_std_value": 0.3},
}
METHODS = ("smoe", "pemamoe", "moe", "mlp")
PROBE_NUMERICS = 2  # the training arithmetic the probe was started under (see the docstring)


def readings(method: str) -> dict:
    """{reading label: for_scale settings} of `method`: the stops, and for PE-MAMoE x the log-std values."""
    if method != "pemamoe":
        return dict(KL_READINGS)
    return {f"{kl}, {ls}": {**kl_set, **ls_set} for kl, kl_set in KL_READINGS.items()
            for ls, ls_set in LOG_STD_READINGS.items()}


def members(method: str, seeds=SEEDS) -> list:
    """[(reading, seed, TrainConfig)] of `method`'s population."""
    from pemamoe.mappo import TrainConfig

    return [(label, seed, TrainConfig.for_scale("paper", method, seed, **settings))
            for label, settings in readings(method).items() for seed in seeds]


def train(methods, hours: float | None, iterations: int) -> None:
    from pemamoe.mappo import train_population
    from pemamoe.records import write_portable_state
    from pemamoe.train_config import training_numerics

    if training_numerics() != PROBE_NUMERICS:
        raise SystemExit(f"error: the probe's runs compute TRAINING_NUMERICS {PROBE_NUMERICS}, this checkout "
                         f"{training_numerics()}: train from a checkout at version {PROBE_NUMERICS} "
                         "(git worktree add ../probe a9bbb68); unpack and report work from this one")
    deadline = None if hours is None else time.time() + hours * 3600
    for method in methods:
        configs = [c for _, _, c in members(method)]
        dirs = [RESULTS / c.run_name(PROBE_NUMERICS) for c in configs]
        start = time.time()
        train_population(configs, dirs, max_iterations=iterations, deadline=deadline)
        print(f"[probe] {method}: {len(configs)} members trained for {time.time() - start:.0f} s", flush=True)
        for run_dir in dirs:
            path = write_portable_state(run_dir, "paper", STATES)
            if path is not None:
                print(f"[probe] packed {path.relative_to(ROOT)} ({path.stat().st_size / 1e6:.2f} MB)", flush=True)
        if deadline is not None and time.time() >= deadline:
            break


def unpack(methods) -> None:
    from pemamoe.records import restore_portable_state

    for method in methods:
        for _, _, config in members(method):
            if restore_portable_state(RESULTS / config.run_name(PROBE_NUMERICS), "paper", STATES):
                print(f"[probe] restored {config.run_name(PROBE_NUMERICS)}", flush=True)


def visit_rows(method: str, iterations: int) -> pd.DataFrame:
    """One row per member and phase visit of what the member logged so far (its run folder)."""
    rows = []
    for label, seed, config in members(method):
        path = RESULTS / config.run_name(PROBE_NUMERICS) / "metrics.parquet"
        if not path.exists():
            continue
        m = pd.read_parquet(path)
        m = m[m.iteration < iterations]
        L = config.phase_length_iters
        sigma = np.exp(m["log_std_mean"].to_numpy())
        for visit, g in m.groupby(m.iteration // L):
            first = int(g.index[0])
            rows.append({"method": method, "reading": label, "seed": seed, "run": config.run_name(PROBE_NUMERICS),
                         "visit": int(visit), "phase": int(g.phase.iloc[0]), "iterations": len(g),
                         "coverage": g.coverage.mean(), "return": g.episode_return.mean(),
                         "gradient_steps": int(g.gradient_steps.sum()),
                         "sigma_before": float(sigma[first - 1]) if first > 0 else np.nan,
                         "sigma_first": float(sigma[first]), "sigma_last": float(sigma[int(g.index[-1])])})
    return pd.DataFrame(rows)


def visit_table(rows: pd.DataFrame) -> pd.DataFrame:
    """Means over the seeds, one row per reading and visit."""
    table = (rows.assign(steps_per_iteration=rows.gradient_steps / rows.iterations)
             .groupby(["reading", "visit", "phase"], sort=False)
             .agg(seeds=("seed", "nunique"), iterations=("iterations", "min"), coverage=("coverage", "mean"),
                  ret=("return", "mean"), steps=("steps_per_iteration", "mean"), sigma_before=("sigma_before", "mean"),
                  sigma_first=("sigma_first", "mean"), sigma_last=("sigma_last", "mean"))
             .reset_index())
    return table.rename(columns={"ret": "return", "steps": "gradient steps/iter", "sigma_before": "sigma before",
                                 "sigma_first": "sigma at visit start", "sigma_last": "sigma at visit end"})


def report(methods, iterations: int) -> Path:
    import subprocess

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    lines = ["# Readings probe: the first three phase visits at the paper scale", "",
             f"Written by `python benchmarks/readings_probe.py report` at `{commit}` from the run folders in "
             "results/readings_probe/ (do not edit by hand). Means over the seeds trained so far; a visit "
             "still in progress counts the iterations logged so far (column `iterations`: the fewest of any seed). "
             f"Gradient steps per iteration are out of 8 x 32 = 256. See the script's docstring for the readings.", ""]
    frames = [visit_rows(method, iterations) for method in methods]
    frames = [f for f in frames if not f.empty]
    for rows in frames:
        lines += [f"## {rows.method.iloc[0]}", "", "```text", visit_table(rows).round(3).to_string(index=False), "```", ""]
    if frames:  # what notebook 10b reads (committed): one row per member and visit
        SUMMARY.parent.mkdir(parents=True, exist_ok=True)
        pd.concat(frames).to_csv(SUMMARY, index=False, float_format="%.6g")
    REPORT.write_text("\n".join(lines))
    return REPORT


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("command", choices=("train", "unpack", "report"))
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    parser.add_argument("--hours", type=float, default=None)
    parser.add_argument("--iterations", type=int, default=ITERATIONS)
    args = parser.parse_args()
    if args.command == "train":
        train(args.methods, args.hours, args.iterations)
    elif args.command == "unpack":
        unpack(args.methods)
    else:
        print(report(args.methods, args.iterations))
    return 0


if __name__ == "__main__":
    sys.exit(main())
