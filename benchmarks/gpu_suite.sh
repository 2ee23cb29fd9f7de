#!/bin/bash
# The test suite on a machine with a GPU, both passes side by side (8 workers each), one line per
# test in $OUT/x64_1.log and $OUT/x64_0.log (kept even when a pass is stopped at its limit), and
# JUnit XML for a pass that finishes. XLA's defaults (JAXQUAT_TEST_XLA_DEFAULTS=1); no memory
# preallocation, since 16 processes share the GPU. The notebook, docs and example files are left
# out (their packages, Jupyter and mkdocs, are rarely on such a machine).
#   bash benchmarks/gpu_suite.sh                 # the whole suite, 400 s per pass
#   LIMIT=200 TESTS="tests/test_kernels.py" bash benchmarks/gpu_suite.sh
# Wheels in $WHEELS (packages the machine lacks: diffrax 0.7.0 where it has 0.7.1-0.7.2, beartype,
# numpy-quaternion) are installed to /tmp/site first. Session 26 used it on an H100
# (docs/benchmarks.md, "The test suite on a GPU").
source "$(dirname "$0")/gpu_setup.sh"
nvidia-smi -L
python3 -c "import jax, diffrax, equinox, optimistix, lineax, optax; print('jax', jax.__version__, jax.devices(), 'diffrax', diffrax.__version__, 'equinox', equinox.__version__, 'optimistix', optimistix.__version__, 'lineax', lineax.__version__, 'optax', optax.__version__)"
export XLA_PYTHON_CLIENT_PREALLOCATE=false JAXQUAT_TEST_XLA_DEFAULTS=1 PYTHONUNBUFFERED=1
LIMIT=${LIMIT:-400}
IGNORE="--ignore=tests/test_notebooks.py --ignore=tests/test_docs.py --ignore=tests/test_examples.py --ignore=tests/test_examples_optimisation.py"
for x in 1 0; do
  # -vv: the configuration's -q and one -v cancel; at +1 xdist prints each test's outcome as it ends
  (JAX_ENABLE_X64=$x timeout "$LIMIT" python3 -m pytest -n 8 --dist loadfile -vv -rfE --tb=short $IGNORE \
     --junitxml="$OUT/x64_$x.xml" --durations=15 ${TESTS:-tests} > "$OUT/x64_$x.log" 2>&1
   echo "rc=$?" >> "$OUT/x64_$x.log") &
done
wait
for x in 1 0; do
  echo "== JAX_ENABLE_X64=$x: $(grep -c " PASSED " "$OUT/x64_$x.log") passed"
  grep -E "(FAILED|ERROR) " "$OUT/x64_$x.log" | grep -v "^FAILED\|^ERROR"
  tail -2 "$OUT/x64_$x.log"
done
