#!/bin/bash
# The simulation and gradient benchmarks on a machine with a GPU, in one call, each part under its
# own time limit so that what finished comes back: the float64 forward-mode test with its whole
# traceback (it failed there in session 26), benchmarks/simulation.py (throughput, the autodiff
# table, compile and import times) and benchmarks/gradient_sweep.py (every public function's
# value and gradient). Logs in $OUT. Wheels in $WHEELS (diffrax 0.7.0 where the machine has
# 0.7.1-0.7.2, beartype) are installed to /tmp/site first.
#   bash benchmarks/gpu_bench.sh
#   SIM_ARGS="--batches 1000 --grad-batches 1000" SWEEP_ROWS=100000 bash benchmarks/gpu_bench.sh
source "$(dirname "$0")/gpu_setup.sh"
export PYTHONUNBUFFERED=1 JAXQUAT_TEST_XLA_DEFAULTS=1
start=$(date +%s)
nvidia-smi -L
python3 -c "import jax, diffrax, equinox, optax; print('jax', jax.__version__, jax.devices(), 'diffrax', diffrax.__version__, 'equinox', equinox.__version__, 'optax', optax.__version__)"
timeout "${SIM_LIMIT:-330}" python3 benchmarks/simulation.py ${SIM_ARGS:---batches 1000 100000 1000000 --grad-batches 1000 100000 1000000 --repeats 3} > "$OUT/simulation.log" 2>&1
echo "simulation rc=$? at $(( $(date +%s) - start )) s" | tee -a "$OUT/simulation.log"
grep -E "body-steps|forward .* grad|Compile|Import" "$OUT/simulation.log" | grep -v "^|"
JAX_ENABLE_X64=1 timeout "${TEST_LIMIT:-100}" python3 -m pytest -p no:randomly --tb=long -rfE \
  tests/test_integrators.py -k "forward_mode_through_simulate" > "$OUT/forward_mode_x64.log" 2>&1
echo "forward-mode test (float64) rc=$? at $(( $(date +%s) - start )) s" | tee -a "$OUT/forward_mode_x64.log"
grep -E "^E |Error|passed|failed" "$OUT/forward_mode_x64.log" | head -30
ROWS=${SWEEP_ROWS:-1000000} timeout "${SWEEP_LIMIT:-110}" python3 benchmarks/gradient_sweep.py float32 > "$OUT/sweep_float32.log" 2>&1
echo "sweep rc=$? at $(( $(date +%s) - start )) s" | tee -a "$OUT/sweep_float32.log"
sort -k3 -n -r "$OUT/sweep_float32.log" | head -25
