"""`make bench`: run every benchmarks/bench_*.py in turn and print what each measures.

Each benchmark is a standalone script that prints its own figures. Timing lives here, never in the
unit tests, because the 2-core CI machine is shared and noisy.
"""

import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main() -> int:
    scripts = sorted(HERE.glob("bench_*.py"))
    if not scripts:
        print("bench: no benchmarks/bench_*.py yet")
        return 0
    failed = []
    for script in scripts:
        print(f"== {script.name}", flush=True)
        start = time.perf_counter()
        if subprocess.run([sys.executable, str(script)]).returncode != 0:
            failed.append(script.name)
        print(f"== {script.name}: {time.perf_counter() - start:.1f} s\n", flush=True)
    if failed:
        print(f"bench: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
