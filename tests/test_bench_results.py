"""benchmarks/RESULTS.md's writer (benchmarks/results.py, called by benchmarks/run.py).

The timed benchmarks never run here (timing lives in `make bench`); the end-to-end case runs the
cheapest one, bench_records.py (a directory listing, about a second), through run.py into a
temporary file.
"""

import importlib.util
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "benchmarks" / "run.py"


def _load_results():
    spec = importlib.util.spec_from_file_location("bench_results", ROOT / "benchmarks" / "results.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


results = _load_results()
WHERE = {"date": "2026-01-01 00:00 UTC", "commit": "abc1234", "machine": "a test machine"}


def test_run_writes_the_figures_it_measured_with_date_commit_and_machine(tmp_path):
    out = tmp_path / "RESULTS.md"
    proc = subprocess.run([sys.executable, str(RUN), "bench_records", "--results", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    printed = [line for line in proc.stdout.splitlines() if line.startswith("records: ")]
    assert printed, proc.stdout
    text = out.read_text()
    assert text.startswith(results.HEADER)
    section = results.read_sections(out)["bench_records.py"]
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    assert f"at `{head}" in section and results.machine() in section and " UTC at " in section
    assert all(line in section.splitlines() for line in printed)  # the very lines printed, nothing else
    assert list(results.read_sections(out)) == ["bench_records.py"]


def test_a_partial_run_replaces_its_own_sections_and_keeps_the_others(tmp_path):
    out = tmp_path / "RESULTS.md"
    results.write_results({name: results.render_section(name, [f"{name}: first"], seconds=1.0, returncode=0, provenance=WHERE)
                           for name in ("bench_b.py", "bench_a.py")}, out)
    later = {**WHERE, "commit": "def5678"}
    results.write_results({"bench_b.py": results.render_section("bench_b.py", ["## not a title", "bench_b.py: second"],
                                                                seconds=2.0, returncode=0, provenance=later)}, out)
    sections = results.read_sections(out)
    assert list(sections) == ["bench_a.py", "bench_b.py"]
    assert "bench_a.py: first" in sections["bench_a.py"] and "`abc1234`" in sections["bench_a.py"]
    assert "bench_b.py: second" in sections["bench_b.py"] and "first" not in sections["bench_b.py"]
    assert "`def5678`" in sections["bench_b.py"] and "## not a title" in sections["bench_b.py"]
    assert out.read_text().count(results.HEADER) == 1
    assert [p.name for p in tmp_path.iterdir()] == ["RESULTS.md"]  # no temporary file left behind


def test_a_failed_script_is_marked_and_a_printed_fence_cannot_end_the_block():
    text = results.render_section("bench_x.py", ["half", "```"], seconds=0.5, returncode=3, provenance=WHERE)
    assert "Failed (exit status 3)" in text
    assert text.count("```") == 2


def test_an_unknown_benchmark_name_is_refused_naming_the_ones_there_are(tmp_path):
    proc = subprocess.run([sys.executable, str(RUN), "bogus", "--results", str(tmp_path / "R.md")],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0 and "bench_records" in proc.stderr
    assert not (tmp_path / "R.md").exists()


def test_bench_nets_runs_to_its_cost_table_for_every_compared_method(tmp_path):
    """`make bench` runs every bench_*.py; the nets benchmark (about 15 s) is run here for its
    exit status and its cost-table rows only, never for its times. It once failed at its last line
    because the registry had gained methods the cost table does not compare."""
    from pemamoe.methods import METHOD_REGISTRY

    proc = subprocess.run([sys.executable, str(RUN), "bench_nets", "--results", str(tmp_path / "RESULTS.md")],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    costed = {line.split()[4] for line in proc.stdout.splitlines() if line.startswith("nets: cost ours")}
    assert costed == {name for name, spec in METHOD_REGISTRY.items() if spec.compared}
