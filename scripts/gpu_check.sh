#!/usr/bin/env bash
# Every GPU figure of issue 26 in one go, in under 5 minutes on a lent H100 / H200: one JSON line per
# figure on stdout (scripts/gpu_figures.py: the card, the same machine's CPU measured in the same run,
# the bar and whether it is met), then the gpu-marked tests, then a short table. Full logs go to $OUT.
#
#   bash scripts/gpu_check.sh                  # on the lent machine, with .whl/ carried (see below)
#   bash scripts/gpu_check.sh --cpu-dry-run    # here: every step on the CPU at small sizes (checks the script)
#
# The machine has torch, numpy, scipy, matplotlib, safetensors, yaml, tqdm, pytest and triton but not
# pytorch-kinematics, yourdfpy or trimesh: their wheels (and arm-pytorch-utilities, pytorch-seed) lie in
# .whl/ (not committed; python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 ...),
# installed below into /tmp/site without the network.
# Each figure runs in its own process under its own time limit, and all of them under one budget
# (BUDGET seconds, default 285): a figure that fails or runs out of time prints a JSON line with
# "error" and the next one goes on.
set -u
DRY=""
[ "${1:-}" = "--cpu-dry-run" ] && DRY="--cpu-dry-run"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD || exit 1
PY=${PYTHON:-python3}
OUT=${OUT:-/tmp/gpu_check_out}
mkdir -p "$OUT"
LOG="$OUT/gpu_check.log"; JSONL="$OUT/figures.jsonl"
: > "$LOG"; : > "$JSONL"
START=$(date +%s)
BUDGET=${BUDGET:-285}
export TORCHCAL_TEST_THREADS=1 PYTHONUNBUFFERED=1

{ date -u; nvidia-smi -L 2>&1; nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv 2>&1
  $PY -c "import torch, platform; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'python', platform.python_version())" 2>&1
  $PY -c "import triton; print('triton', triton.__version__)" 2>&1
  $PY -c "import pytorch_kinematics, yourdfpy, trimesh; print('pytorch_kinematics', pytorch_kinematics.__file__)" 2>&1
  nproc; grep -m1 'model name' /proc/cpuinfo; } > "$OUT/env.txt"

error_line() {  # figure, message
  $PY -c 'import json, sys; print(json.dumps({"figure": sys.argv[1], "error": sys.argv[2]}))' "$1" "$2" | tee -a "$JSONL"
}

left() { echo $(( BUDGET - ($(date +%s) - START) )); }

figure() {  # name, time limit (s)
  local name=$1 limit=$2 rem t rc
  rem=$(left)
  t=$(( limit < rem ? limit : rem ))
  if [ "$t" -lt 10 ]; then error_line "$name" "skipped: the ${BUDGET} s budget is spent"; return; fi
  echo "=== $name (limit ${t} s) $(date -u +%T)" >> "$LOG"
  timeout -k 5 "$t" $PY scripts/gpu_figures.py "$name" $DRY 2>> "$LOG" | tee -a "$JSONL"
  rc=${PIPESTATUS[0]}
  if [ "$rc" -ne 0 ]; then
    if [ "$rc" -eq 124 ] || [ "$rc" -eq 137 ]; then error_line "$name" "timed out after ${t} s (log: gpu_check.log)"
    else error_line "$name" "exit $rc: $(grep -v '^\s*$' "$LOG" | tail -n 1 | cut -c1-300)"; fi
  fi
}

gpu_tests() {  # time limit (s): the gpu-marked tests, one JSON line
  local rem t rc summary
  rem=$(left); t=$(( $1 < rem ? $1 : rem ))
  if [ "$t" -lt 15 ]; then error_line pytest_gpu "skipped: the ${BUDGET} s budget is spent"; return; fi
  timeout -k 5 "$t" $PY -m pytest -m gpu -q -p no:cacheprovider -rs tests/structure/test_gpu_matches_cpu.py > "$OUT/pytest_gpu.log" 2>&1
  rc=$?
  summary=$(grep -E '(passed|failed|skipped|error|no tests ran)' "$OUT/pytest_gpu.log" | tail -n 1 | tr -d '=' | sed 's/^ *//')
  [ "$rc" -eq 124 ] && summary="timed out after ${t} s; $summary"
  $PY -c 'import json, sys; print(json.dumps({"figure": "pytest_gpu", "summary": sys.argv[1], "met": sys.argv[2] == "0", "exit": int(sys.argv[2])}))' \
    "$summary" "$rc" | tee -a "$JSONL"
}

# most wanted first: whatever the budget cuts comes last
figure fk 80
figure pop240 60
figure pop10000 40
figure calibrate 40
figure loop 70
gpu_tests 100
figure fleet 90
figure pop240_cudagraph 45

echo "--- $(( $(date +%s) - START )) s; logs in $OUT (env.txt, gpu_check.log, figures.jsonl, pytest_gpu.log)"
$PY scripts/gpu_figures.py table --jsonl "$JSONL"
