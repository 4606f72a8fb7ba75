#!/usr/bin/env bash
# The GPU checks of the project, as one prepared call for a session that is lent a GPU machine
# (it runs there on the machine's own python3, which has torch with CUDA, numpy, pandas, pyarrow,
# numba and scipy; the package is used from the working tree, nothing is installed):
#   1. what the machine is;
#   2. tests/test_cuda.py and the cuda cases of tests/test_population.py: a CUDA run trains, is its
#      own run and reads back on the CPU; member independence and resume, bit for bit, on the GPU;
#   3. the population benchmark on the GPU (benchmarks/bench_train.py --device cuda).
# Logs go to $OUT (the device tool's output folder) or build/device_check/. About 5 minutes.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-build/device_check}
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
PY=${PY:-python3}
status=0
{ nvidia-smi; "$PY" -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name(0))"; } \
    2>&1 | tee "$OUT/machine.txt" || status=1
timeout 240 "$PY" -m pytest -q -p no:cacheprovider tests/test_cuda.py tests/test_population.py -k cuda 2>&1 | tee "$OUT/test_cuda.log" || status=1
timeout 300 "$PY" benchmarks/bench_train.py --device cuda --methods mlp pemamoe --sizes 1 16 64 2>&1 \
    | tee "$OUT/bench_cuda.log" || status=1
cp build/bench_train_cuda.json "$OUT/" 2>/dev/null || true
exit $status
