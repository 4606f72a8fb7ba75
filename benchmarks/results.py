"""benchmarks/RESULTS.md: what the latest `make bench` measured, written by benchmarks/run.py.

One section per benchmark script: the lines it printed in that invocation, headed by the date, the
commit (`+dirty` when the code had uncommitted changes) and the machine. A run of some scripts only
(`python benchmarks/run.py bench_records`) replaces their sections and keeps the others, each with
its own date and commit, so the file never mixes figures of two runs under one heading. The file is
replaced atomically: an interrupted bench leaves the previous file whole. Older measurements, and
the ones no script makes (sweep and CI wall times), are hand-written in benchmarks/HISTORY.md.
"""

import datetime
import os
import platform
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))  # the repository's own package, as bench_train.py imports it

from pemamoe.core import atomic_write_text  # noqa: E402

RESULTS = HERE / "RESULTS.md"
FENCE = "```"
HEADER = f"""# Benchmark results

Written by `make bench` (`benchmarks/run.py`, through `benchmarks/results.py`); do not edit by
hand. Each section is what one benchmark printed in the invocation named under its title. The
2-core machine's speed drifts by 25 % or more between runs; earlier measurements, with the commits
they were made at, are in `benchmarks/HISTORY.md`.
"""


def _git(*args) -> str:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    except OSError:
        return ""


def current_commit() -> str:
    """The short commit of HEAD, `+dirty` when the measured code has uncommitted changes."""
    commit = _git("rev-parse", "--short", "HEAD") or "unknown"
    dirty = _git("status", "--porcelain", "--", "pemamoe", "notebooks", "benchmarks/*.py")
    return commit + ("+dirty" if dirty else "")


def machine() -> str:
    """The machine in one line: OS and architecture, CPU count and model, memory, Python."""
    from pemamoe.core import cpu_model

    model = f" ({cpu_model()})"
    try:
        memory = f", {os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30:.1f} GiB"
    except (ValueError, OSError, AttributeError):
        memory = ""
    return (f"{platform.system()} {platform.machine()}, {os.cpu_count()} CPUs{model}{memory}, "
            f"Python {platform.python_version()}")


def provenance() -> dict:
    now = datetime.datetime.now(datetime.timezone.utc)
    return {"date": now.strftime("%Y-%m-%d %H:%M UTC"), "commit": current_commit(), "machine": machine()}


def render_section(name: str, lines, *, seconds: float, returncode: int, provenance: dict) -> str:
    """One script's section: title, where and when it ran, and the lines it printed."""
    status = "" if returncode == 0 else f" **Failed (exit status {returncode}): the figures below are incomplete.**"
    body = [line.replace(FENCE, "'''") for line in lines]  # a printed fence would end the block
    return "\n".join([f"## {name}", "",
                      f"Measured {provenance['date']} at `{provenance['commit']}` on {provenance['machine']}; "
                      f"{seconds:.1f} s.{status}", "", FENCE + "text", *body, FENCE, ""])


def read_sections(path) -> dict:
    """{script name: section text} of an existing RESULTS.md ({} if there is none). A `## ` line
    starts a section only outside a fenced block."""
    path = Path(path)
    if not path.is_file():
        return {}
    sections, name, in_fence = {}, None, False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith(FENCE):
            in_fence = not in_fence
        elif not in_fence and line.startswith("## "):
            name = line[3:].strip()
            sections[name] = []
        if name is not None:
            sections[name].append(line)
    return {k: "\n".join(v).rstrip("\n") + "\n" for k, v in sections.items()}


def write_results(sections: dict, path=RESULTS) -> Path:
    """Merge `sections` ({script name: rendered section}) into `path`, replacing those scripts'
    earlier sections and keeping the rest, in script order; write the file atomically."""
    merged = {**read_sections(path), **sections}
    text = HEADER + "".join("\n" + merged[name] for name in sorted(merged))
    return atomic_write_text(path, text)
