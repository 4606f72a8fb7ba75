#!/usr/bin/env bash
# The CPU rehearsal of benchmarks/device_check.sh, for any machine without a GPU.
# A lent GPU machine runs that check on its own python3, whose packages are not ours: what we count
# on there is torch (CUDA), numpy, pandas, pyarrow, numba, scipy, pytest, hypothesis and tqdm; it
# has no gymnasium and no pettingzoo, and nothing can be installed there. Device time is short, so a
# check that dies there at an import is a lost call. This script brings that package set here: a
# fresh venv (python3.11) holding only those packages, pinned to environment.lock (torch's CPU
# build), checks that gymnasium, pettingzoo, matplotlib and papermill are not importable in it (the
# trainer needs none of them), and then runs the very
# same device_check.sh with CHECK_DEVICE=cpu (same tests collected, same benchmark, same summary
# line). tests/test_device_check.py keeps the cheap half of this (imports, a 1-iteration run, the
# collection) passing in CI. About 2-4 minutes on the 2-core machine, most of it the install.
# Knobs: OUT (build/device_rehearsal), PYTHON (python3.11), BENCH_SCALE (ci here: the rates only
# prove the path on a CPU; paper as on the GPU), REUSE_VENV=1 keeps the venv of the last run.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-build/device_rehearsal}
PYTHON=${PYTHON:-python3.11}
VENV=${VENV:-build/device_rehearsal_venv}
PACKAGES=(torch numpy pandas pyarrow numba scipy pytest hypothesis tqdm)
mkdir -p "$OUT"
start=$SECONDS

if [ "${REUSE_VENV:-0}" != 1 ] || [ ! -x "$VENV/bin/python" ]; then
    rm -rf "$VENV"
    "$PYTHON" -m venv "$VENV" || exit 1
    # each package at its environment.lock pin; their own dependencies pinned by the same file
    pins=()
    for name in "${PACKAGES[@]}"; do
        pin=$(grep -i -E "^$name==" environment.lock) || { echo "no pin for $name in environment.lock"; exit 1; }
        pins+=("$pin")
    done
    "$VENV/bin/python" -m pip install --quiet -c environment.lock "${pins[@]}" > "$OUT/pip_install.log" 2>&1 \
        || { echo "device_rehearsal: the install failed (see $OUT/pip_install.log)"; exit 1; }
fi
"$VENV/bin/python" -m pip list 2>/dev/null > "$OUT/pip_list.txt"
installed=$(($SECONDS - start))
if ! "$VENV/bin/python" - <<'EOF'
import importlib.util, sys
present = [m for m in ("gymnasium", "pettingzoo", "matplotlib", "papermill") if importlib.util.find_spec(m)]
if present:
    sys.exit(f"device_rehearsal: the venv must not hold {present}: it would hide the imports that fail on the GPU machine")
EOF
then exit 1; fi

CHECK_DEVICE=cpu PY="$VENV/bin/python" OUT="$OUT" BENCH_SCALE=${BENCH_SCALE:-ci} bash benchmarks/device_check.sh
rc=$?
echo "device_rehearsal: venv ready in ${installed} s, whole rehearsal $((SECONDS - start)) s, device_check rc $rc"
exit $rc
