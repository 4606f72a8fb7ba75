"""How fast the command line answers `--help` and a usage error (issue 41): each subcommand's
`python -m pemamoe COMMAND --help`, and one usage error of each (an unknown option; and train's
--seed 2**63, which used to wait for torch), timed as whole processes, several repeats each.

The target is 0.5 s for every one of them: the parsers are built from light modules only (the
names and checks of pemamoe.core, appendix 00b), and nothing imports torch or the experiments
before the arguments are checked (tests/test_cli_errors.py::test_41i_* checks the imports; the
time is measured here, never in a unit test). PASS or FAIL compares the slowest median with 0.5 s
(the median, because the 2-core machine is often busy with training); the slowest single time is
printed beside it. Exit status 1 on FAIL. `--repeats N` (default 7).
"""

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TARGET_S = 0.5
HELP = (["--help"], ["sweep", "--help"], ["train", "--help"], ["figures", "--help"], ["export", "--help"],
        ["check-export", "--help"])
USAGE_ERRORS = (["sweep", "--bogus"], ["train", "--bogus"], ["figures", "--bogus"], ["export", "--bogus"],
                ["check-export", "--bogus"], ["train", "--seed", str(2**63)], ["sweep", "--workers", "0"])


def timed(argv, repeats: int) -> tuple:
    """(median s, max s, exit statuses seen) of `python -m pemamoe ARGV` run `repeats` times."""
    seconds, codes = [], set()
    for _ in range(repeats):
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, *argv], cwd=ROOT, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
        seconds.append(time.perf_counter() - start)
        codes.add(proc.returncode)
    return statistics.median(seconds), max(seconds), codes


def report(kind: str, rows: list, expected: int) -> bool:
    """Print the rows of one kind and its verdict line; True when it passes."""
    ok = True
    for argv, median, longest, codes in rows:
        wrong = "" if codes == {expected} else f"  UNEXPECTED exit status {sorted(codes)} (expected {expected})"
        ok &= not wrong
        print(f"cli: {kind:12s} {' '.join(argv):34s} median {median:5.3f} s  max {longest:5.3f} s{wrong}")
    argv, median, _, _ = max(rows, key=lambda row: row[1])
    longest = max(row[2] for row in rows)
    ok &= median <= TARGET_S
    print(f"cli: slowest {kind}: {median:.3f} s median ({' '.join(argv)}), {longest:.3f} s max of all: "
          f"{'PASS' if ok else 'FAIL'} against {TARGET_S} s")
    return ok


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=7, help="runs of each command (default 7)")
    args = parser.parse_args(argv)
    base = timed(["-c", "pass"], args.repeats)
    print(f"cli: {args.repeats} runs each; a bare interpreter (python -c pass) takes {base[0]:.3f} s median, "
          f"{base[1]:.3f} s max")
    helps = [(a, *timed(["-m", "pemamoe", *a], args.repeats)) for a in HELP]
    errors = [(a, *timed(["-m", "pemamoe", *a], args.repeats)) for a in USAGE_ERRORS]
    ok = report("help", helps, 0)
    ok &= report("usage error", errors, 2)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
