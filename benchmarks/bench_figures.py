"""What `make figures` costs a reader: the medium scale regenerated on a fresh clone of this commit.

Clones the repository's committed HEAD into a temporary folder (this checkout's .venv linked in, so
the time is the figures' alone: the environment build is CI's to measure), runs the command that
`make figures SCALE=medium` runs there, and prints, measured in this invocation:

* the wall time of the whole regeneration and of each notebook (from the command's own lines);
* how many runs it trained (run folders under the clone's results/; a fresh clone must train none,
  every figure reads the committed records);
* how many theory records notebook 08 computed instead of reading ("[theory record] ...: computing"
  lines; a fresh clone must compute none, the toy problems' results are committed records too);
* which files of paper_figures/ differ from the committed ones (the README of paper_figures/
  itself names the commit, so it always does).

`python benchmarks/bench_figures.py [--scale medium] [--install]`: --install copies the regenerated
paper_figures/ over this checkout's (the way to refresh the committed figures from a clean tree).
Takes about 15 minutes at medium on the 2-core machine.
"""

import argparse
import filecmp
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def changed_files(new: Path, old: Path) -> list:
    """Paths (relative) that differ between two figure folders, or exist in one only."""
    names = {p.relative_to(new) for p in new.rglob("*") if p.is_file()} | {
        p.relative_to(old) for p in old.rglob("*") if p.is_file()}
    return sorted(str(n) for n in names if not ((new / n).is_file() and (old / n).is_file()
                                                and filecmp.cmp(new / n, old / n, shallow=False)))


def trained_runs(results: Path) -> list:
    """Run folders the regeneration left under results/ (a run it trained, even part way)."""
    return sorted(str(p.relative_to(results)) for p in results.glob("*/*") if p.is_dir()) if results.is_dir() else []


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scale", default="medium", choices=("ci", "small", "medium", "paper"))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--install", action="store_true", default=os.environ.get("PEMAMOE_INSTALL_FIGURES") == "1",
                        help="copy the regenerated paper_figures/ into this checkout (also PEMAMOE_INSTALL_FIGURES=1, "
                             "the way through benchmarks/run.py)")
    args = parser.parse_args()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="pemamoe-figures-") as tmp:
        clone = Path(tmp) / "clone"
        subprocess.run(["git", "clone", "--quiet", str(ROOT), str(clone)], check=True)
        (clone / ".venv").symlink_to(ROOT / ".venv")
        command = [str(ROOT / ".venv" / "bin" / "python"), "-m", "pemamoe", "figures", "--scale", args.scale,
                   "--workers", str(args.workers)]
        print(f"figures: fresh clone of {commit}; {' '.join(command[1:])}", flush=True)
        start = time.perf_counter()
        proc = subprocess.run(command, cwd=clone, capture_output=True, text=True)
        seconds = time.perf_counter() - start
        for index, name, clock in re.findall(r"\[figures\] (\d+/\d+) (\S+) done in (\d+:\d+:\d+)", proc.stdout):
            print(f"figures: {index} {name} {clock}")
        if proc.returncode != 0:
            print((proc.stdout + proc.stderr)[-3000:])
            print(f"figures: FAILED (exit {proc.returncode}) after {seconds:.0f} s")
            return 1
        trained = trained_runs(clone / "results")
        computed = re.findall(r"\[theory record\] (\S+): computing", proc.stdout + proc.stderr)
        changed = changed_files(clone / "paper_figures", ROOT / "paper_figures")
        print(f"figures: make figures SCALE={args.scale} on a fresh clone took {seconds:.0f} s "
              f"({seconds / 60:.1f} min, {args.workers} workers)")
        print(f"figures: runs trained: {len(trained)}" + (f" ({', '.join(trained[:8])}{' ...' if len(trained) > 8 else ''})"
                                                       if trained else " (every figure read the committed records)"))
        print(f"figures: theory records computed: {len(computed)}"
              + (f" ({', '.join(computed)})" if computed else " (notebook 08 read every one)"))
        print(f"figures: files of paper_figures/ that differ from this checkout's: {len(changed)}"
              + (f" ({', '.join(changed[:12])}{' ...' if len(changed) > 12 else ''})" if changed else ""))
        if args.install:
            shutil.rmtree(ROOT / "paper_figures")
            shutil.copytree(clone / "paper_figures", ROOT / "paper_figures")
            print("figures: installed the regenerated paper_figures/ into this checkout")
    return 1 if trained or computed else 0


if __name__ == "__main__":
    sys.exit(main())
