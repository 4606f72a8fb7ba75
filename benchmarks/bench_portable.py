"""What a campaign stop of portable states adds to git (issue 58, item 3; appendix 09d).

Two successive stops of a paper-scale campaign are simulated for 18 and 30 unfinished runs: each
run's checkpoint at iteration 3,600 (stop 1) and 7,200 (stop 2) is packed by `write_portable_state`
into a scratch git repository's records/paper/in_progress/ and committed, and the growth of the
history is read as git counts it (`git rev-list --objects --all | git cat-file --batch-check`, the
sum of the blobs' sizes). Format 1 (one zstd file of the whole checkpoint but its episode rows,
rewritten at every stop) is sized beside it.

The checkpoints are real paper-scale ones where the repository's history holds the campaign's own
format-1 portable states (commit 5eb77f7: SMoE and PE-MAMoE, 3 seeds each, at iterations 7,812 and
9,565 of 10,800): their parameters, optimizer moments, environments (64 per run) and metric rows,
run i taking state i % 6 with one bit of its parameters and its rows' wall clock changed so that no
two runs share a blob. Without that history (a shallow clone), one PE-MAMoE run is trained 2
paper-scale iterations for the state, and the rows are distinct random doubles in its rows' layout:
an upper bound (real rows compress about 3x better).
"""

import io
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from pemamoe.train_config import TRAINING_NUMERICS, TrainConfig  # noqa: E402

HISTORY_COMMIT = "5eb77f7"
HISTORY_STATES = ("smoe-s0-4d546e47ccb3", "smoe-s1-8200c960d70c", "smoe-s2-2aa270cf04a7",
                  "pemamoe-s0-86f1308f58d9", "pemamoe-s1-207cff31548c", "pemamoe-s2-4041e4f4da26")
STOPS = (3600, 7200)  # iterations reached at the two stops: the 10,800 of a paper run in three sessions
RUNS = (18, 30)
BOUND_MB = 30.0  # issue 58: what the portable states of a campaign stage may add to the history


def _git(repo, *args, stdin=None) -> str:
    return subprocess.run(["git", *args], cwd=repo, input=stdin, capture_output=True, text=True, check=True).stdout


def history_checkpoints() -> list:
    """The checkpoints of the campaign's committed format-1 portable states, or [] without them."""
    from pemamoe.records import read_portable_state

    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in HISTORY_STATES:
            blob = subprocess.run(["git", "show", f"{HISTORY_COMMIT}:records/paper/in_progress/{name}.pt.zst"],
                                  cwd=ROOT, capture_output=True)
            if blob.returncode:
                return []
            path = Path(tmp) / f"{name}.pt.zst"
            path.write_bytes(blob.stdout)
            out.append(torch.load(io.BytesIO(read_portable_state(path)), weights_only=True))
    return out


def trained_checkpoint() -> dict:
    """A PE-MAMoE paper-scale checkpoint after 2 iterations, with 7,200 rows of distinct random
    doubles in its rows' layout (a diagnostics row every diag_every)."""
    import random

    from pemamoe.bookkeeping import RowLog
    from pemamoe.mappo import train_population
    from pemamoe.runs import load_checkpoint

    config = TrainConfig.for_scale("paper", method="pemamoe")
    with tempfile.TemporaryDirectory() as tmp:
        train_population([config], [Path(tmp) / "r"], max_iterations=2, progress=False)
        ck = load_checkpoint(Path(tmp) / "r" / "checkpoint.pt", config)
    diag, plain = list(RowLog.from_checkpoint(ck["metrics_rows"]))
    rng = random.Random(0)
    rows = [{k: (v if isinstance(v, bool) else i if isinstance(v, int) else rng.random()) for k, v in
             (diag if i % config.diag_every == 0 else plain).items()} for i in range(STOPS[-1])]
    return {**ck, "metrics_rows": RowLog(rows).packed()}


def run_checkpoint(base: dict, run: int, stop: int) -> tuple:
    """(config, checkpoint) of run `run` at iteration `stop`: `base` with its rows cut at `stop`,
    one bit of every parameter tensor and the rows' wall clock set by run and stop (distinct blobs)."""
    from pemamoe.bookkeeping import RowLog

    config = TrainConfig.for_scale("paper", method="pemamoe", seed=run)
    rows = [dict(row) for row in RowLog.from_checkpoint(base["metrics_rows"])[:stop]]
    for row in rows:
        if "wall_time" in row:
            row["wall_time"] += run * 1e-6
    mark = run * len(STOPS) + STOPS.index(stop) + 1

    def marked(state):
        out = {}
        for key, t in state.items():
            if torch.is_tensor(t) and t.dtype == torch.float32 and t.numel():
                t = t.clone()
                t.view(torch.int32).view(-1)[0] ^= mark  # the last bits of one number
            out[key] = t
        return out

    ck = {**base, "config": config.to_dict(), "iteration": stop, "numerics": TRAINING_NUMERICS,
          "actor": marked(base["actor"]), "critic": marked(base["critic"]),
          "metrics_rows": RowLog(rows).packed(), "episode_rows": []}
    return config, ck


def format_1_bytes(ck: dict) -> int:
    """The size of the format-1 portable state of `ck` (zstd 9 of the checkpoint but its episode rows)."""
    import pyarrow as pa

    buffer = io.BytesIO()
    torch.save({**ck, "episode_rows": []}, buffer)
    return len(pa.Codec("zstd", compression_level=9).compress(buffer.getvalue(), asbytes=True)) + 27


def blob_bytes(repo) -> int:
    objects = _git(repo, "rev-list", "--objects", "--all")
    sizes = _git(repo, "cat-file", "--batch-check=%(objecttype) %(objectsize) %(rest)", stdin=objects)
    return sum(int(fields[1]) for fields in (line.split(maxsplit=2) for line in sizes.splitlines()) if fields[0] == "blob")


def main() -> None:
    from pemamoe.bookkeeping import write_checkpoint
    from pemamoe.core import atomic_write_json
    from pemamoe.records import portable_chunk_files, write_portable_state

    start = time.perf_counter()
    bases = history_checkpoints()
    source = (f"the campaign's own states (commit {HISTORY_COMMIT}): real parameters, environments and rows" if bases
              else "a 2-iteration PE-MAMoE run's state, rows of random doubles (an upper bound)")
    bases = bases or [trained_checkpoint()]
    print(f"portable states: paper scale, {max(RUNS)} runs, stops at iterations {STOPS[0]:,} and {STOPS[1]:,}; "
          f"from {source}")
    with tempfile.TemporaryDirectory() as tmp:
        repo, results = Path(tmp) / "repo", Path(tmp) / "results"
        repo.mkdir()
        _git(repo, "init", "-q")
        _git(repo, "config", "user.email", "bench@pemamoe"), _git(repo, "config", "user.name", "bench")
        (repo / "README").write_text("scratch\n")
        _git(repo, "add", "-A"), _git(repo, "commit", "-qm", "empty")
        v1, state_mb, chunk_mb = {}, {}, {}
        for stop in STOPS:
            before, grown = blob_bytes(repo), {}
            for group in (range(RUNS[0]), range(RUNS[0], RUNS[1])):  # the first 18 runs, then the other 12
                for run in group:
                    config, ck = run_checkpoint(bases[run % len(bases)], run, stop)
                    run_dir = results / config.run_name()
                    run_dir.mkdir(parents=True, exist_ok=True)
                    atomic_write_json(run_dir / "config.json", config.to_dict())
                    write_checkpoint({k: v for k, v in ck.items() if k not in ("format", "numerics")},
                                     run_dir / "checkpoint.pt")
                    path = write_portable_state(run_dir, "paper", repo / "records")
                    if run < len(bases):  # format 1's size: the same for every run of one base
                        v1[stop, run] = format_1_bytes(ck)
                    state_mb[stop, run] = path.stat().st_size / 1e6
                    chunk_mb[stop, run] = max(f.stat().st_size for f in portable_chunk_files(
                        repo / "records", "paper", config.run_name()) if f"-{stop - 1:06d}-" in f.name) / 1e6
                _git(repo, "add", "-A"), _git(repo, "commit", "-qm", f"stop at {stop}: runs to {group.stop - 1}")
                grown[group.stop] = (blob_bytes(repo) - before) / 1e6
            for n, mb in grown.items():
                state, chunk = (sum(d[stop, r] for r in range(n)) / n for d in (state_mb, chunk_mb))
                print(f"stop at iteration {stop:,}, {n} runs: git history +{mb:.2f} MB "
                      f"({'within' if mb <= BOUND_MB else 'OVER'} {BOUND_MB:g} MB; per run: state {state:.2f} MB + "
                      f"chunk of the new rows {chunk:.2f} MB); format 1 would add "
                      f"{sum(v1[stop, r % len(bases)] for r in range(n)) / 1e6:.1f} MB")
        rows_kb = sum(chunk_mb[STOPS[1], r] for r in range(RUNS[1])) / RUNS[1] / (STOPS[1] - STOPS[0]) * 1e3
        state = sum(state_mb[STOPS[1], r] for r in range(RUNS[1])) / RUNS[1]
        print(f"per run and stop: {state:.2f} MB of state + {rows_kb:.3f} kB per iteration of rows; a stop of R runs "
              f"after I iterations adds about R x ({state:.2f} + I x {rows_kb / 1e3:.5f}) MB "
              f"(issue 58's bound: {BOUND_MB:g} MB per stage)")
    print(f"portable states: measured in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
