#!/usr/bin/env bash
# The rounding-sensitive test files under several numerical modes (issue 34): a test may not depend
# on which kernel rounds last, so each mode must pass.
#   MKL_CBWR=AVX2 / COMPATIBLE   MKL's conditional numerical reproducibility: other BLAS/LAPACK
#                                kernels (AVX2 is what an AMD EPYC or an older Intel CPU gets)
#   ATEN_CPU_CAPABILITY=avx2     torch's own vectorised kernels as an AVX2 machine runs them
#   OMP_NUM_THREADS=1 / 2        one or two threads in torch (and in torchcal's entry points)
# Usage: scripts/rounding_check.sh [pytest args...]   (e.g. -x, or -m "not slow" for a quick pass)
# Prints one line per mode and exits 1 if any mode fails; each mode's log is in $OUT (default
# out/rounding).
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
OUT=${OUT:-out/rounding}
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"

# Files whose tests compare results across batch shapes, solvers, shards or code paths, or
# count iterations: where a kernel that rounds differently would show first.
FILES=(
  tests/fleet/test_fleet.py
  tests/optim/test_optim_restarts.py
  tests/optim/test_optim_pso.py
  tests/optim/test_optim_evolution.py
  tests/optim/test_optim_gradient.py
  tests/optim/test_lm_host_syncs.py
  tests/seeds/test_elm.py
  tests/kinematics/test_robot_kinematics.py
  tests/kinematics/test_fk_compact.py
  tests/deploy/test_command_correction.py
  tests/deploy/test_persist.py
  tests/measure/test_measurement_models.py
  tests/calibrate/test_calibrate.py
  tests/problems/test_identifiability.py
  tests/problems/test_pseudo_inverse.py
  tests/loop/test_batched_folds.py
  tests/loop/test_linear_mode_selection.py
  tests/loop/test_schur_solves.py
  tests/optim/test_lm_checkpoint.py
  tests/calibrate/test_creeping_fit.py
  tests/loop/test_prune_together.py
)

# MKL is what these modes act on: say whether torch uses it, and show that the mode changes the
# bits of a matrix product and a least-squares solve (a hash per mode; equal hashes would mean
# the variable had no effect).
probe='import hashlib, torch
torch.manual_seed(0)
A = torch.randn(257, 311, dtype=torch.float64); B = torch.randn(311, 263, dtype=torch.float64)
h = lambda t: hashlib.sha1(t.numpy().tobytes()).hexdigest()[:10]
x = torch.linalg.lstsq(A[:, :40], A[:, 40:41], driver="gelsd").solution
print(f"mkl={torch.backends.mkl.is_available()} capability={torch.backends.cpu.get_cpu_capability()} "
      f"threads={torch.get_num_threads()} mm={h(A @ B)} lstsq={h(x)}")'

MODES=(
  "MKL_CBWR=AVX2"
  "MKL_CBWR=COMPATIBLE"
  "ATEN_CPU_CAPABILITY=avx2"
  "OMP_NUM_THREADS=1 TORCHCAL_TEST_THREADS=1 TORCHCAL_THREADS=1"
  "OMP_NUM_THREADS=2 TORCHCAL_TEST_THREADS=2 TORCHCAL_THREADS=2"
)
fail=0
for mode in "${MODES[@]}"; do
  tag=$(echo "$mode" | cut -d' ' -f1 | tr '=' '_')
  start=$(date +%s)
  # threads stay at 1 unless the mode says otherwise
  env OMP_NUM_THREADS=1 TORCHCAL_TEST_THREADS=1 $mode "$PY" -c "$probe" > "$OUT/$tag.log" 2>&1
  env OMP_NUM_THREADS=1 TORCHCAL_TEST_THREADS=1 $mode "$PY" -m pytest -q -p no:cacheprovider "${FILES[@]}" "$@" \
    >> "$OUT/$tag.log" 2>&1
  rc=$?
  [ $rc -eq 0 ] || fail=1
  echo "$mode: $(head -1 "$OUT/$tag.log") | $(tail -1 "$OUT/$tag.log") | rc=$rc, $(( $(date +%s) - start )) s"
done
exit $fail
