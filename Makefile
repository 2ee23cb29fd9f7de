# The two commands a newcomer types: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
BENCH_STAMP := $(VENV)/.installed-bench

.PHONY: demo test test64 test32 lint docs bench clean

# Let Python cache the bytecode of what it imports (some machines export PYTHONDONTWRITEBYTECODE=1,
# this one among them): the install skips precompiling (--no-compile, below), so without this
# every process of a run (test workers, notebook kernels, subprocesses) compiled jax, scipy,
# diffrax, ... from source again: 4.3 s against 2.5 s to import what a test worker imports.
unexport PYTHONDONTWRITEBYTECODE

$(PY):
	$(PYTHON) -m venv $(VENV)

# --no-compile: Python compiles the modules it imports on first import (and caches them: see
# unexport above); precompiling every installed file took 27 s of the 40 s install on a 2-core CPU.
# The docs extra (mkdocs, pure Python) comes with the first install: one resolver run instead of
# a second one for `make docs`.
$(STAMP): $(PY) pyproject.toml
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet --no-compile -e ".[test,docs]"
	touch $(STAMP)

# The peers the benchmarks compare against (MuJoCo MJX among them): only `make bench` needs them.
# brax without its dependencies (flax, orbax, ...): the benchmark loads only its jax-only math.py.
$(BENCH_STAMP): $(STAMP)
	$(PY) -m pip install --quiet --no-compile -e ".[test,bench]"
	$(PY) -m pip install --quiet --no-compile --no-deps "brax==0.14.2"
	touch $(BENCH_STAMP)

demo: $(STAMP)
	$(PY) examples/demo.py

# The whole suite, once in float64 and once in float32, on two worker processes
# (pytest-xdist; a test file stays on one worker so its jitted functions compile once).
# --no-loadscope-reorder: the files go out in the order tests/conftest.py collects them (the
# longest first); xdist's default reorders them by their number of tests, which left one worker
# finishing alone: the float32 pass's workers ended 13 s apart, 1.6 s apart in this order (one
# run each, 2-core EPYC).
PYTEST := $(PY) -m pytest -n 2 --dist loadfile --no-loadscope-reorder
# No persistent compilation cache (JAX's is off unless asked for). From session 35 to 77 each run
# made one for its two passes, caching compilations of 0.5 s or more, for the notebook kernel and
# the other worker to reuse; session 78 found 4 of the 270 programs it wrote read again, each
# within 3 s of its write, while its keys and writes cost 31.7 s of the float64 pass's 1240 s of
# test time (2-core Intel Xeon; JAX's compile call timed with and without its backend compile).

test: $(STAMP)
	JAX_ENABLE_X64=1 $(PYTEST) && JAX_ENABLE_X64=0 $(PYTEST)

test64: $(STAMP)
	JAX_ENABLE_X64=1 $(PYTEST)

test32: $(STAMP)
	JAX_ENABLE_X64=0 $(PYTEST)

# ruff's lint rules and its formatter (--check: `ruff format` rewrites; [tool.ruff]) and the type checker ([tool.basedpyright], pyright's basic
# rules on the package), both from pyproject.toml; .ci/run runs them before the tests, and
# .pre-commit-config.yaml runs the same two commands on each commit.
lint: $(STAMP)
	$(PY) -m ruff check jaxquat tests examples benchmarks
	$(PY) -m ruff format --check jaxquat tests examples benchmarks
	$(VENV)/bin/basedpyright --project pyproject.toml

# The site (docs/ and the API reference generated from the docstrings by mkdocstrings) into
# site/; --strict (mkdocs.yml) turns every warning, a docstring griffe cannot parse or a broken
# link among them, into an error. .ci/run builds it after the lint.
docs: $(STAMP)
	$(VENV)/bin/mkdocs build --strict --quiet

# Rewrites the generated sections of docs/benchmarks.md (the text around them stays).
# glibc maps each allocation of 32 MiB or more afresh and faults its 4 KiB pages in at every call:
# at 10^6 rotations in float64 `to_matrix` took 36.9 ms, 30 of them in 17,579 page faults per call
# (docs/benchmarks.md, session 64). The benchmark processes raise the threshold (for allocations
# up to 64 MiB, reused from the heap) and give the larger ones transparent huge pages (512 times
# fewer faults): the tables are then repeatable, with every contender and the roofline under the
# same setting, which each table's first line names. Raising the threshold alone made some
# float64 gradients slower (from_rotvec's 7.2 -> 26.3 ms: 9,766 faults per call against none).
BENCH_ENV := GLIBC_TUNABLES=glibc.malloc.hugetlb=1:glibc.malloc.mmap_threshold=1073741824:glibc.malloc.trim_threshold=1073741824

bench: $(BENCH_STAMP)
	$(BENCH_ENV) $(PY) benchmarks/ops.py --write docs/benchmarks.md
	$(BENCH_ENV) $(PY) benchmarks/simulation.py --write docs/benchmarks.md
	$(BENCH_ENV) $(PY) benchmarks/batch.py --write docs/benchmarks.md
	$(BENCH_ENV) $(PY) benchmarks/estimation.py --write docs/benchmarks.md
	$(BENCH_ENV) $(PY) benchmarks/optimal_control.py --write docs/benchmarks.md

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis site
