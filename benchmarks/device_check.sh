#!/usr/bin/env bash
# The GPU checks of the project, as one prepared call for a session that is lent a GPU machine.
# It runs there on the machine's own python3 (torch with CUDA, numpy, pandas, pyarrow, numba, scipy,
# pytest, hypothesis, tqdm; no gymnasium, no pettingzoo, which the trainer does not need), using
# the package from the working tree; nothing is installed:
#   1. what the machine is;
#   2. tests/test_cuda.py and the cuda cases of tests/test_population.py: a CUDA run trains, is its
#      own run and reads back on the CPU; member independence and resume, bit for bit, on the GPU;
#   3. the population benchmark (benchmarks/bench_train.py --rates-only, MLP and PE-MAMoE at
#      R = 1, 16, 64), whose rates land in build/bench_train_<device>.json;
#   4. one summary line: the tests' verdict and the member env-steps/s of each method and size.
# CHECK_DEVICE=cuda (default) | cpu; cpu is the rehearsal (benchmarks/device_rehearsal.sh runs this
# very script in a venv holding only the GPU image's packages). Also PY (python3), BENCH_SCALE
# (paper), BENCH_SIZES ("1 16 64"). Logs go to $OUT (the device tool's output folder) or
# build/device_check/. About 130 s on one H200 (first run: benchmarks/HISTORY.md, "The CUDA path");
# each step has its own timeout; exits non-zero if any step failed.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-build/device_check}
DEVICE=${CHECK_DEVICE:-cuda}
PY=${PY:-python3}
BENCH_SCALE=${BENCH_SCALE:-paper}
read -r -a SIZES <<< "${BENCH_SIZES:-1 16 64}"
mkdir -p "$OUT" build
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
status=0
start=$SECONDS

# 1. the machine
{
    if [ "$DEVICE" = cuda ]; then nvidia-smi; fi
    "$PY" - "$DEVICE" <<'EOF'
import platform, sys
import torch
device = sys.argv[1]
print("python", platform.python_version(), sys.executable)
print("torch", torch.__version__, "cuda", torch.version.cuda, "available", torch.cuda.is_available())
if device == "cuda":
    print("gpu", torch.cuda.get_device_name(0))  # fails, and so fails the check, without a GPU
for name in ("numpy", "pandas", "pyarrow", "numba", "scipy", "pytest", "hypothesis", "tqdm", "gymnasium", "pettingzoo"):
    try:
        print(f"{name}: {getattr(__import__(name), '__version__', '?')}")
    except ImportError:  # gymnasium and pettingzoo are not on the GPU image
        print(f"{name}: not importable")
EOF
} 2>&1 | tee "$OUT/machine.txt" || status=1

# 2. the tests (without a GPU they are collected, so every module they import is loaded, and skipped)
timeout 240 "$PY" -m pytest -q -p no:cacheprovider tests/test_cuda.py tests/test_population.py -k cuda 2>&1 \
    | tee "$OUT/test_$DEVICE.log"
test_rc=${PIPESTATUS[0]}
[ "$test_rc" = 0 ] || status=1

# 3. the benchmark
rm -f "build/bench_train_$DEVICE.json"
timeout 300 "$PY" benchmarks/bench_train.py --device "$DEVICE" --rates-only --scale "$BENCH_SCALE" \
    --methods mlp pemamoe --sizes "${SIZES[@]}" 2>&1 | tee "$OUT/bench_$DEVICE.log" || status=1
cp "build/bench_train_$DEVICE.json" "$OUT/" 2>/dev/null || status=1

# 4. the summary (also in $OUT/summary.txt)
tests=$(grep -E '(passed|failed|skipped|error|no tests ran)' "$OUT/test_$DEVICE.log" | tail -n 1 | tr -d '=' | xargs)
if [ "$test_rc" != 0 ]; then verdict="tests FAILED rc $test_rc (${tests:-?})"
elif [ "$DEVICE" = cuda ] && [[ "$tests" == *skipped* ]]; then verdict="tests SKIPPED, so not run (${tests})"; status=1
else verdict="tests PASSED (${tests:-?})"; fi  # on the cpu rehearsal they are all skipped: collected, imported
rates=$("$PY" - "build/bench_train_$DEVICE.json" "${SIZES[@]}" <<'EOF' 2>/dev/null || echo "bench FAILED: no rates"
import json, sys
rates = json.load(open(sys.argv[1]))
parts = []
for method in ("mlp", "pemamoe"):
    got = [f"R{R}={rates[f'{method}/R{R}']['throughput']:,.0f}" if f"{method}/R{R}" in rates else f"R{R}=missing"
           for R in sys.argv[2:]]
    parts.append(f"{method} " + " ".join(got))
print("member env-steps/s: " + "; ".join(parts))
EOF
)
line="device_check $DEVICE ($BENCH_SCALE preset): $verdict; $rates; $((SECONDS - start)) s; $([ $status = 0 ] && echo OK || echo FAILED)"
echo "$line" | tee "$OUT/summary.txt"
exit $status
