"""The prepared GPU check (`benchmarks/device_check.sh`) runs on a lent GPU machine's own python3,
which has torch but no gymnasium and no pettingzoo. These tests make both unimportable in a
subprocess (a `sitecustomize` that puts None in `sys.modules`) and check, cheaply, what the check
needs there: the trainer, the sweeps and the benchmark import, a 1-iteration ci run trains, the
check's tests are collected, and the script itself runs end to end with `CHECK_DEVICE=cpu`.
`benchmarks/device_rehearsal.sh` does the full rehearsal in a fresh venv of the image's packages."""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CHECK = REPO / "benchmarks" / "device_check.sh"
# Not on the GPU image (gymnasium, pettingzoo), or not needed by the trainer (matplotlib, papermill)
MISSING = ("gymnasium", "pettingzoo", "matplotlib", "papermill")


def without_them(tmp_path) -> dict:
    """An environment whose Python cannot import MISSING (and imports this checkout's package)."""
    site = tmp_path / "site"
    site.mkdir(exist_ok=True)
    (site / "sitecustomize.py").write_text(f"import sys\nfor _m in {MISSING!r}:\n    sys.modules[_m] = None\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_", "COV_"))}
    env["PYTHONPATH"] = os.pathsep.join([str(site), str(REPO)])
    return env


def check_test_args() -> list:
    """The pytest arguments device_check.sh runs (read from the script, so the two cannot drift)."""
    line = next(ln for ln in CHECK.read_text().splitlines() if "-m pytest" in ln)
    args = shlex.split(line.split("-m pytest", 1)[1].split("2>&1", 1)[0])
    assert "tests/test_cuda.py" in args, args
    return args


SCRIPT = """
import sys
from pathlib import Path

for name in {missing!r}:
    try:
        __import__(name)
    except ImportError:
        pass
    else:
        sys.exit(f"{{name}} is importable: the test would prove nothing")

import pemamoe.env as E
import pemamoe.mappo as mappo
import pemamoe.experiments  # noqa: F401
import runpy
runpy.run_path("benchmarks/bench_train.py", run_name="bench_train")  # its imports, not its main()

venv = E.make_vector_env(2, seed=0)  # the trainer's environment needs neither package
venv.reset()
try:
    E.make_env()
except ImportError as err:
    assert "pip install pettingzoo gymnasium" in str(err), err
else:
    sys.exit("make_env() built a PettingZoo environment without pettingzoo")

res = mappo.train(mappo.TrainConfig.for_scale("ci", method="pemamoe", seed=0, iterations=1), Path(sys.argv[1]))
assert res.finished and len(res.metrics) == 1, res.metrics

import pytest
rc = pytest.main(["--collect-only", *{args!r}])  # the script's own arguments, -q included
sys.exit(int(rc))
"""


def test_trainer_imports_trains_and_collects_the_checks_tests_without_gymnasium_or_pettingzoo(tmp_path):
    args = check_test_args()
    proc = subprocess.run([sys.executable, "-c", SCRIPT.format(missing=MISSING, args=args), str(tmp_path / "run")],
                          cwd=REPO, env=without_them(tmp_path), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    collected = re.search(r"(\d+)(?:/\d+)? tests? collected", proc.stdout)
    assert collected and int(collected.group(1)) >= 3, proc.stdout[-2000:]
    assert (tmp_path / "run" / "metrics.parquet").is_file()


def test_device_check_script_runs_on_the_cpu_without_gymnasium_or_pettingzoo(tmp_path):
    env = without_them(tmp_path)
    env.update(CHECK_DEVICE="cpu", PY=sys.executable, OUT=str(tmp_path / "out"), BENCH_SCALE="ci", BENCH_SIZES="1 2")
    proc = subprocess.run(["bash", str(CHECK)], cwd=REPO, env=env, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary = proc.stdout.strip().splitlines()[-1]
    assert summary.startswith("device_check cpu (ci preset): tests PASSED") and summary.endswith("OK"), summary
    assert re.search(r"mlp R1=[\d,]+ R2=[\d,]+; pemamoe R1=[\d,]+ R2=[\d,]+;", summary), summary
    assert (tmp_path / "out" / "summary.txt").read_text().strip() == summary
    assert (tmp_path / "out" / "bench_train_cpu.json").is_file()
    machine = (tmp_path / "out" / "machine.txt").read_text()
    assert "gymnasium: not importable" in machine and "pettingzoo: not importable" in machine, machine
