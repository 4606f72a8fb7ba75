"""`make bench`: run every benchmarks/bench_*.py in turn, print what each measures, and write it
to benchmarks/RESULTS.md.

Each benchmark is a standalone script that prints its own figures. Timing lives here, never in the
unit tests, because the 2-core CI machine is shared and noisy. `python benchmarks/run.py NAME ...`
runs only the named scripts (`bench_records` or `records`) and replaces only their sections of
RESULTS.md; `--results PATH` writes elsewhere, `--no-results` writes nothing.
"""

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from results import RESULTS, provenance, render_section, write_results  # noqa: E402


def select(names) -> list:
    """The bench_*.py scripts named (with or without `bench_` and `.py`), or all of them."""
    scripts = sorted(HERE.glob("bench_*.py"))
    if not names:
        return scripts
    by_name = {s.stem: s for s in scripts}
    chosen = []
    for name in names:
        stem = name.removesuffix(".py")
        stem = stem if stem.startswith("bench_") else f"bench_{stem}"
        if stem not in by_name:
            raise SystemExit(f"bench: no benchmark {name!r}; there are: {', '.join(sorted(by_name))}")
        chosen.append(by_name[stem])
    return chosen


def run_script(script: Path) -> tuple:
    """Run one benchmark, echoing its output as it comes; (exit status, its stdout lines, seconds)."""
    start = time.perf_counter()
    # Lines arrive as printed, not at exit; the scripts import this checkout's package (the one
    # whose commit heads the results), wherever the interpreter's own install points.
    env = {**os.environ, "PYTHONUNBUFFERED": "1",
           "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)}
    with subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, env=env) as proc:
        lines = []
        for line in proc.stdout:
            print(line, end="", flush=True)
            lines.append(line.rstrip("\n"))
    return proc.returncode, lines, time.perf_counter() - start


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("names", nargs="*", help="run only these benchmarks (default: every bench_*.py)")
    parser.add_argument("--results", type=Path, default=RESULTS, help="the file to write (default benchmarks/RESULTS.md)")
    parser.add_argument("--no-results", action="store_true", help="print only; write no results file")
    args = parser.parse_args(argv)
    scripts = select(args.names)
    if not scripts:
        print("bench: no benchmarks/bench_*.py yet")
        return 0
    where = provenance()  # one heading for the whole invocation
    failed, sections = [], {}
    for script in scripts:
        print(f"== {script.name}", flush=True)
        returncode, lines, seconds = run_script(script)
        if returncode != 0:
            failed.append(script.name)
        sections[script.name] = render_section(script.name, lines, seconds=seconds, returncode=returncode,
                                               provenance=where)
        print(f"== {script.name}: {seconds:.1f} s\n", flush=True)
    if not args.no_results:
        print(f"bench: wrote {write_results(sections, args.results)}")
    if failed:
        print(f"bench: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
