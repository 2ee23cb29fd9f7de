# Sourced by benchmarks/gpu_suite.sh and benchmarks/gpu_bench.sh: $OUT made, the wheels in $WHEELS
# (default .whl; packages the GPU machine lacks or has in another version) installed to
# /tmp/site, and PYTHONPATH on them and the repository.
set -u
OUT=${OUT:-gpu-out}
mkdir -p "$OUT"
if [ -d "${WHEELS:-.whl}" ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "${WHEELS:-.whl}"/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
