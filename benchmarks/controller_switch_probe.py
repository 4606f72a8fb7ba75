"""Why PE-MAMoE learns less than SMoE after a switch at the paper scale: a probe of the first switch.

PE-MAMoE and SMoE are the same network and train bit for bit alike until the first phase switch
(iteration 1,200 at the paper scale), where the phase controller acts. The committed paper-scale
records show PE-MAMoE learning the first phase-1 visit worse than SMoE (notebook 10). This probe
retrains runs up to `--iterations` (the first switch and part of the visit after it) and sets them
beside the committed records of SMoE and PE-MAMoE over the same iterations:

* `SMoE (retrained)`, `PE-MAMoE (retrained)`: the two methods as committed;
* `no log-std reset`: the controller without its log-std reset (every other mechanism on);
* `log-std reset to 0.3`: the other reading of the paper's "log-std reset 0.3" (log sigma = 0.3,
  sigma = 1.35, where our default resets sigma to 0.3, log sigma = -1.20; notebook 06);
* `SMoE, stop on kept rows` and `PE-MAMoE, stop on kept rows`: the retrained runs continued from the
  switch with the target-KL stop reading only the rows whose expert is the rollout's.

The committed records' first stretch was trained on a processor whose float kernels differ from
this machine's, so SMoE and PE-MAMoE are retrained here too; every retrained log before the switch
must equal the others' bit for bit (the controller is inert before it): the probe checks that.
Per variant, mean over seeds: coverage over the visit so far, the policy's log-std just before and
after the switch, and the gradient steps per iteration the target-KL early stop lets through (of
8 x 32 = 256). Then, with `--kl-split`, where the stopping estimate comes from: each minibatch's
KL estimate beside the part of it carried by the rows whose expert did not change since the rollout.

`python benchmarks/controller_switch_probe.py [--iterations 1800] [--variant ...]
[--stop-on-kept-rows ...]` trains into results/switch_probe/ (resumable, one population of 3 seeds
per variant) and writes benchmarks/CONTROLLER_SWITCH.md from every variant trained so far. A
variant to iteration 1,800 takes about an hour on one core of the 2-core machine (2-3 s per
iteration before the switch, under 1 s after it: benchmarks/HISTORY.md, session 29).
"""

import argparse
import dataclasses
import subprocess
import sys
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
SWITCH = 1200  # the first phase switch at the paper scale
RECORD_BLOCK = 20  # iterations per row of a paper-scale record (its marker's "block")
# name: (method, change to its paper-scale config). The first two retrain the committed methods on
# this machine: the records' first stretch was trained on a processor whose float kernels differ
# ("not recorded" in their timing), so their logs differ from a retraining here from iteration 0.
VARIANTS = {
    "SMoE (retrained)": ("smoe", lambda cfg: cfg),
    "PE-MAMoE (retrained)": ("pemamoe", lambda cfg: cfg),
    "no log-std reset": ("pemamoe", lambda cfg: cfg.without("log_std_reset")),
    "log-std reset to 0.3": ("pemamoe", lambda cfg: cfg.replace(
        controller=dataclasses.replace(cfg.controller, log_std_value=0.3))),
}
# name: the retrained run it continues from its checkpoint at the first switch (which training it
# keeps in results/switch_probe_snap/), with the target-KL stop reading a minibatch's KL estimate
# over the rows whose expert is the rollout's only: the same runs, the same switch, one reading of
# the stop changed (their logged approx_kl is that estimate too).
STOP_ON_KEPT_ROWS = {
    "SMoE, stop on kept rows": "SMoE (retrained)",
    "PE-MAMoE, stop on kept rows": "PE-MAMoE (retrained)",
}
RECORDED = {"SMoE (record)": "smoe", "PE-MAMoE (record)": "pemamoe"}


def record_log(method: str, seed: int) -> pd.DataFrame:
    """The committed paper-scale record's log of `method`, `seed` (verified against its marker)."""
    from pemamoe.mappo import TrainConfig
    from pemamoe.records import RECORDS_DIR, read_record, record_files

    run_name = TrainConfig.for_scale("paper", method, seed).run_name()
    return read_record(record_files(RECORDS_DIR, "paper", run_name)["marker"])[1]


def probe_dir(name: str, seed: int, folder: str = "switch_probe") -> Path:
    """The run folder of one seed of a probe run, under results/`folder`/."""
    return ROOT / "results" / folder / f"{''.join(c for c in name.replace(' ', '_') if c not in '.(),')}-s{seed}"


def variant_configs(name: str, seeds) -> list:
    from pemamoe.mappo import TrainConfig

    method, change = VARIANTS[name]
    return [change(TrainConfig.for_scale("paper", method, seed)) for seed in seeds]


def copy_run(source: Path, target: Path) -> Path:
    """A copy of a run folder to resume elsewhere (without its writer's lock file)."""
    import shutil

    return shutil.copytree(source, target, ignore=shutil.ignore_patterns(".lock"))


def last_iteration(run_dir: Path) -> int:
    return int(pd.read_parquet(run_dir / "metrics.parquet").iteration.max())


def train_variant(name: str, seeds, iterations: int) -> list:
    from pemamoe.mappo import train_population

    configs, dirs = variant_configs(name, seeds), [probe_dir(name, seed) for seed in seeds]
    if name in STOP_ON_KEPT_ROWS.values():  # keep a copy at the first switch to continue from
        train_population(configs, dirs, max_iterations=SWITCH)
        for seed, run_dir in zip(seeds, dirs):
            snapshot = probe_dir(name, seed, "switch_probe_snap")
            if last_iteration(run_dir) == SWITCH - 1 and not snapshot.exists():
                copy_run(run_dir, snapshot)
    train_population(configs, dirs, max_iterations=iterations)
    return dirs


def kl_stop_split(name: str, seeds, iterations: int, extra: int) -> dict:
    """Where the target-KL stop's estimate comes from, `extra` iterations after `iterations`: the
    variant's runs resumed on a copy of their folders, every minibatch's KL estimate split into the
    rows the router sent to another expert than the rollout's (the PPO ratio is taken on the current
    routes) and the rest. Mean over minibatches and seeds, of those whose estimate is over the member's
    target (the minibatch that stops it) and of those under it."""
    import tempfile

    import torch

    import pemamoe.mappo as mappo

    configs = variant_configs(name, seeds)
    rows, latest, original, original_check = [], [], mappo._minibatch_loss, mappo._KLStop.check

    def split_loss(population, coef, batch):
        loss, stats = original(population, coef, batch)
        per_row, moved = _estimate_terms(population, batch)
        n = per_row.shape[1]
        latest[:] = [{"KL estimate": float(per_row[r].mean()),
                      "kept rows' part": float(torch.where(moved[r], 0.0, per_row[r]).sum() / n),
                      "rerouted share of rows": float(moved[r].float().mean())} for r in range(len(per_row))]
        return loss, stats

    def check(stop, approx_kl, epoch):  # keep the minibatches of members still stepping before this one
        live = (~stop.stopped).tolist()
        stepping = original_check(stop, approx_kl, epoch)
        rows.extend({**latest[r], "over target": not stepping[r].item()} for r in range(len(live)) if live[r])
        return stepping

    with tempfile.TemporaryDirectory() as tmp:
        dirs = [copy_run(probe_dir(name, seed), Path(tmp) / probe_dir(name, seed).name) for seed in seeds]
        mappo._minibatch_loss, mappo._KLStop.check = split_loss, check
        try:
            mappo.train_population(configs, dirs, max_iterations=iterations + extra)
        finally:
            mappo._minibatch_loss, mappo._KLStop.check = original, original_check
    frame = pd.DataFrame(rows)
    over, under = frame[frame["over target"]], frame[~frame["over target"]]
    target = configs[0].target_kl
    return {"run": name, "minibatches": len(frame), "over target": len(over),
            "over target on the kept rows alone": int((over["kept rows' part"] > target).sum()),
            "KL estimate, median (over)": over["KL estimate"].median(),
            "kept rows' part, mean (over)": over["kept rows' part"].mean(),
            "rerouted rows (over)": over["rerouted share of rows"].mean(),
            "KL estimate, mean (under)": under["KL estimate"].mean(),
            "kept rows' part, mean (under)": under["kept rows' part"].mean(),
            "rerouted rows (under)": under["rerouted share of rows"].mean()}


def gradient_steps_by_visit(seeds) -> pd.DataFrame:
    """Thousands of gradient steps in each phase visit, mean over seeds, for every method of the
    committed paper-scale campaign (the records' per-iteration `gradient_steps`; 1,200 x 256 =
    307.2 thousand when no update stops early)."""
    methods = sorted({p.name.split("-s")[0] for p in (ROOT / "records" / "paper").glob("*-s*.parquet")})
    rows = []
    for method in methods:
        per_seed = []
        for seed in seeds:
            log = record_log(method, seed)
            per_seed.append((log.gradient_steps * log.iterations).groupby(log.iteration // SWITCH).sum() / 1000)
        rows.append({"method": method, **{f"visit {v}": steps for v, steps in pd.concat(per_seed, axis=1)
                                          .mean(axis=1).items()}})
    return pd.DataFrame(rows)


def _estimate_terms(population, batch) -> tuple:
    """The target-KL estimate's per-row terms (R, rows), computed as the trainer computes them
    (from the log-ratio, so finite where the ratio underflows), and (R, rows) bool: the rows whose
    experts under the current parameters differ from the rollout's. A second, gradient-free pass
    of the actor over the minibatch (the same numbers as the loss's pass)."""
    import torch

    with torch.no_grad():
        R, steps, U = batch.logprobs.shape  # a minibatch of the trainer's Batch: its m*U agent rows
        n = steps * U
        routing = batch.routing.reshape(R, n)
        new_logp, _, _, _, _, chosen = population.actor.evaluate(batch.obs.reshape(R, n, -1),
                                                                 batch.actions.reshape(R, n, -1), routing)
        logratio = new_logp - batch.logprobs.reshape(R, n)
        moved = (chosen.reshape(R, n, -1).sort(-1).values
                 != routing.experts.reshape(R, n, -1).sort(-1).values).any(-1)
        return (logratio.exp() - 1) - logratio, moved


def train_stop_on_kept_rows(name: str, seeds, iterations: int) -> None:
    """Continue the retrained runs from their snapshot at the first switch with the early stop
    reading the KL estimate over the rows that kept their expert (the loss itself unchanged)."""
    import torch

    import pemamoe.mappo as mappo

    base = STOP_ON_KEPT_ROWS[name]
    configs = variant_configs(base, seeds)
    dirs = []
    for seed in seeds:
        source, target = probe_dir(base, seed, "switch_probe_snap"), probe_dir(name, seed)
        if not target.exists():
            if not (source / "checkpoint.pt").is_file() or last_iteration(source) != SWITCH - 1:
                raise SystemExit(f"{name}: no snapshot at the first switch in {source}; train it with "
                                 f"--variant {base!r} (which keeps one)")
            copy_run(source, target)
        dirs.append(target)
    original = mappo._minibatch_loss

    def kept_rows_loss(population, coef, batch):
        loss, stats = original(population, coef, batch)
        per_row, moved = _estimate_terms(population, batch)
        stats["approx_kl"] = torch.where(moved, 0.0, per_row).sum(1) / per_row.shape[1]  # also what is logged
        return loss, stats

    mappo._minibatch_loss = kept_rows_loss
    try:
        mappo.train_population(configs, dirs, max_iterations=iterations)
    finally:
        mappo._minibatch_loss = original


def summarise(logs: dict, iterations: int) -> pd.DataFrame:
    rows = []
    for name, per_seed in logs.items():
        visit = [log[(log.iteration >= SWITCH) & (log.iteration < iterations)] for log in per_seed]
        rows.append({
            "run": name, "seeds": len(per_seed),
            "coverage, visit so far": sum(v.coverage.mean() for v in visit) / len(visit),
            "coverage, its last 100 iterations": sum(v[v.iteration >= iterations - 100].coverage.mean()
                                                     for v in visit) / len(visit),
            # a row is a block of 20 iterations: the last block before the switch, and the switch's own
            "log-std, 20 iterations before the switch": sum(log[log.iteration < SWITCH].log_std_mean.iloc[-1]
                                                            for log in per_seed) / len(per_seed),
            "log-std, 20 after it": sum(log[log.iteration == SWITCH].log_std_mean.iloc[0]
                                        for log in per_seed) / len(per_seed),
            "gradient steps per iteration": sum(v.gradient_steps.mean() for v in visit) / len(visit),
            "by seed (coverage, visit so far)": ", ".join(f"{v.coverage.mean():.3f}" for v in visit),
        })
    return pd.DataFrame(rows)


def main() -> int:
    from pemamoe.records import record_frame

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--iterations", type=int, default=1800)
    parser.add_argument("--variant", choices=tuple(VARIANTS), action="append",
                        help="train this variant (repeatable; default: report only what is trained)")
    parser.add_argument("--stop-on-kept-rows", choices=tuple(STOP_ON_KEPT_ROWS), action="append",
                        help="continue this retrained method from the first switch with the early stop on the "
                             "rows that kept their expert (repeatable)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--kl-split", type=int, default=4, metavar="N",
                        help="iterations each trained variant is resumed for (on a copy) to split the target-KL "
                             "stop's estimate (0: skip)")
    args = parser.parse_args()
    if args.iterations <= SWITCH:
        parser.error(f"--iterations must be above the first switch ({SWITCH}), got {args.iterations}")
    for name in args.variant or ():
        train_variant(name, args.seeds, args.iterations)
    for name in args.stop_on_kept_rows or ():
        train_stop_on_kept_rows(name, args.seeds, args.iterations)
    logs = {name: [record_log(method, s) for s in args.seeds] for name, method in RECORDED.items()}
    for name in (*VARIANTS, *STOP_ON_KEPT_ROWS):
        paths = [probe_dir(name, s) / "metrics.parquet" for s in args.seeds]
        if not all(p.is_file() for p in paths):
            continue
        runs = [pd.read_parquet(p) for p in paths]
        if min(int(r.iteration.max()) for r in runs) < args.iterations - 1:
            continue  # not trained this far yet
        # averaged over blocks of 20 iterations as the records are, so that the two compare like for like
        runs = [record_frame(run[run.iteration < args.iterations], RECORD_BLOCK) for run in runs]
        logs[name] = runs
    trained = [name for name in VARIANTS if name in logs]
    # the controller is inert before the switch: every retraining is equal there, in every logged column
    for name in [*trained[1:], *(n for n in STOP_ON_KEPT_ROWS if n in logs)]:
        for seed, run, first in zip(args.seeds, logs[name], logs[trained[0]]):
            if not run[run.iteration < SWITCH].equals(first[first.iteration < SWITCH]):
                print(f"{name}, seed {seed}: its log before the switch differs from {trained[0]}'s", file=sys.stderr)
                return 1
    table = summarise(logs, args.iterations)
    split = pd.DataFrame([kl_stop_split(name, args.seeds, args.iterations, args.kl_split)
                          for name in trained]) if args.kl_split and trained else None
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    from pemamoe.core import _markdown_table, atomic_write_text

    text = (f"# The first switch at the paper scale (`benchmarks/controller_switch_probe.py`)\n\n"
            f"Written by `python benchmarks/controller_switch_probe.py --iterations {args.iterations}` at commit "
            f"`{commit}`: iterations {SWITCH:,} to {args.iterations - 1:,} (of the first visit of phase 1, "
            f"iterations {SWITCH:,} to {2 * SWITCH - 1:,}), mean over "
            f"seeds {', '.join(map(str, args.seeds))}. The runs retrained here are equal bit for bit before the "
            f"switch; the committed records differ from them from the first iteration on (their first "
            f"stretch was trained on another processor's float kernels), so compare retrained with retrained."
            f"\n\n{_markdown_table(table, '.3g')}\n")
    text += ("\n## Gradient steps per phase visit in the committed records\n\nThousands, mean over seeds "
             f"{', '.join(map(str, args.seeds))}, from `records/paper/` (visit v is phase v mod 3; 307 is every "
             "minibatch of every epoch, no early stop).\n\n"
             f"{_markdown_table(gradient_steps_by_visit(args.seeds), '.3g')}\n")
    if split is not None:
        text += (f"\n## What stops the updates\n\nEach trained variant resumed for {args.kl_split} iterations "
                 f"after iteration {args.iterations - 1:,} (on a copy), every minibatch a member stepped on or "
                 f"stopped at split into the rows the router sent to another expert than the rollout's and the "
                 f"rest (`--kl-split`). Over: the minibatches whose KL estimate passed the member's target "
                 f"(each stops its member's update); under: the rest. The kept rows' part is the estimate's "
                 f"sum over the rows that kept their expert, divided by all rows.\n\n"
                 f"{_markdown_table(split, '.3g')}\n")
    atomic_write_text(ROOT / "benchmarks" / "CONTROLLER_SWITCH.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
