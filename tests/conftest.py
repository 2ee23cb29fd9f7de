"""Suite-wide settings: dtype from JAX_ENABLE_X64, strict rank promotion, hypothesis profile,
XLA's cheaper CPU compilation, one OpenBLAS thread for LAPACK, the garbage collector's threshold,
the test workers' cores, each test run from a deep frame (``tests/frames.py``), the workers' exit
without JAX's clean-up and the files' order (the last six below, at their lines).

XLA compilation is most of the suite's time (52 % of the float64 pass, and 16 % more tracing).
``--xla_cpu_use_fusion_emitters=false`` (XLA's older elemental CPU emitters instead of its MLIR
fusion emitters) cuts it by about 40 %: the closed-form torque-free trajectory's ``jacfwd``
compiled in 5.3 s, now 3.3 s (float64, this 2-core CPU). Both emitters compute the same IEEE
operations; what differs is how fast the compiled code runs (the suite is dominated by
compiling; the benchmarks run XLA's defaults) and, where a fusion evaluates in another order,
rounding, on which no assertion may depend. ``--xla_backend_optimization_level=0`` as well
would have saved more (the float64 pass 6m35 instead of 11m02) but together with this flag it
computed wrong float32 results (| |q| - 1 | up to 1.5e-5 in 637 of 10^4 closed-form torque-free
states, against 2.1e-7 with either flag alone), so it is not used. Session 41 found that error
depends on the cores: ``simulate``'s closed form at 10^4 saved times, float32, level 0, 1.5e-5
in 671 states on one core (``taskset``, as a pinned test worker runs) and 3.3e-7 on two, 2.7e-7
at XLA's level on either; a verdict that moves with the core count rules the level out (the
float32 pass at level 0: 156 s against 202-215 s, with that test failing). Session 58: that test
passes at level 0 now, the float64 pass took 9m08 against 11m31, but five others failed, from what
level 0 leaves out (multiply-add contraction, the folding of additions of ``-0.0``): still not used
(``docs/benchmarks.md``).
``--xla_cpu_opt_preset=FAST_COMPILE`` (session 41) compiled the closed form's gradient in 3.6-4.3 s
against 5.4-5.9 s but the whole float32 pass slower (268 s, 370 s of XLA against 243-257 s). The flag also hides
what a user meets under the defaults: the scan path's step with a torque compiled there to
kernels that stalled (an MLP, 0.65 s per backward step of 16 bodies, fixed in session 23;
element-wise laws, the gradient of 1000 bodies x 100 steps in 32-40 s, fixed in session 24), so
``test_gradient_of_a_learned_torque_under_xla_defaults_matches_finite_differences`` runs its
gradients in a subprocess with XLA's defaults. Set
``JAXQUAT_TEST_XLA_DEFAULTS=1`` to run the suite with XLA's default flags (the whole suite passed
with them before the flag was set, and again in session 23: both passes in 13m50 against 9m16
with the flag, on a 2-core EPYC).
``--xla_cpu_parallel_codegen_split_count=1`` (XLA's default 32) compiles each program's LLVM
module as one part instead of splitting it for threads to compile side by side: a test worker
has one core (below), where the parts only add work. ``test_lie_solvers.py``,
``test_kernels.py`` and ``test_torque_free.py`` in float64, one process on each core of this
2-core machine: 143.4 and 136.9 s with the default, 132.9 and 127.5 s with one part (cores
swapped between the two pairs, session 56); ``test_integrators.py``, ``test_contract.py`` and
``test_optimal_control.py`` 427.9 against 400.0 s; the examples', notebooks', spline, derivative
and time-optimal files 186.8 against 177.5 s (the other core). Set on every machine, so that
every machine compiles the same code.
The flags are appended to any ``XLA_FLAGS`` already set, before JAX creates its CPU backend, and
the example and notebook subprocesses inherit it. Only for jaxlib before 0.11: jaxlib 0.11.2's XLA
no longer knows the first flag and aborts the process at start ("Unknown flag in XLA_FLAGS", seen on
the GPU machine of session 21), which would take down every test worker.
"""

import gc
import os
import sys
from importlib.metadata import version

import pytest
from _pytest.runner import runtestprotocol
from frames import deep_frame
from hypothesis import HealthCheck, settings


def _before(dist: str, major: int, minor: int) -> bool:
    return tuple(int(x) for x in version(dist).split(".")[:2]) < (major, minor)


if not os.environ.get("JAXQUAT_TEST_XLA_DEFAULTS") and _before("jaxlib", 0, 11):
    os.environ["XLA_FLAGS"] = " ".join(
        [
            os.environ.get("XLA_FLAGS", ""),
            "--xla_cpu_use_fusion_emitters=false",
            "--xla_cpu_parallel_codegen_split_count=1",
        ]
    ).strip()

# LAPACK on a CPU (``eigh``, QR and the triangular solves of the interior point's Newton step) is
# scipy's OpenBLAS, loaded by jax, whose threaded routines round differently with the number of
# threads it starts (one per core it may run on): the one-start wheel slew of
# ``benchmarks/optimal_control.py`` took 169 interior-point iterations with two threads and 177
# with one (the same optimum to 8e-12), while XLA's own thread count
# (``--xla_cpu_multi_thread_eigen=false``) changed nothing. One thread, so that no verdict depends
# on the cores of the machine; set before jax loads scipy's copy (pytest's plugins load only
# NumPy's own), and inherited by the example and notebook subprocesses.
os.environ["OPENBLAS_NUM_THREADS"] = "1"

# Python's cyclic garbage collector runs a young-generation pass every 700 allocations net of
# frees (its default); tracing and lowering a program allocate millions of short-lived objects,
# and each pass walks the young ones. Every 50 000: test_lie_solvers.py, test_kernels.py and
# test_torque_free.py in float64, one process on each core, 121.6 and 119.7 s against 116.9 and
# 115.5 s (cores swapped between the pairs; the larger process's peak memory 2.10 against
# 2.02 GB); 200 000 gave the same as 50 000 (116.3 s both), and moving everything alive after
# collection to the permanent generation (``gc.freeze``) nothing more (session 56).
gc.set_threshold(50_000, 50, 100)

# Each test worker runs on its own share of the cores (with two workers on two cores: one core
# each), set before XLA starts its threads, which then size their pools to that share: XLA's
# threads of one worker (its runtime's thread pool, its compiler's) otherwise competed with the
# other worker for both cores. Two pytest processes side by side on this 2-core EPYC, each running
# test_torque_free.py and test_spline.py in float64: 76-85 s each when each had a core of its own,
# 83-93 s unpinned (three interleaved pairs, 9-10 % less in each); the float32 pass on two
# workers 196-220 s against 226-238 s (two runs each). The example and notebook subprocesses
# inherit their worker's cores. Only in xdist workers, and only where the system has the call
# (Linux) and allows it.
if os.environ.get("PYTEST_XDIST_WORKER") and hasattr(os, "sched_setaffinity"):
    _cpus = sorted(os.sched_getaffinity(0))
    _n, _i = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")), int(os.environ["PYTEST_XDIST_WORKER"][2:])
    if _n > 1:
        try:
            os.sched_setaffinity(0, set(_cpus[_i::_n]) or {_cpus[_i % len(_cpus)]})
        except OSError:
            pass

import jax  # noqa: E402


@pytest.hookimpl(tryfirst=True)
def pytest_unconfigure(config):
    """A test worker ends here, once it has sent its last report and its exit status (xdist sends
    them at the end of ``pytest_sessionfinish``, before this); the controller decides the run's
    status from them (a failing test still fails the run: checked). What it skips:

    - pytest's own unconfigure and clean-up, which run a full garbage collection each, for
      unraisable exceptions to report, walking the millions of objects a worker holds at the end
      of a pass (0.3-0.5 s each at 0.6-1.0 million objects, after four of the float64 pass's
      files; the float64 pass's last worker ended 5.7 s before the pass did). An exception that
      only a final collection would raise is lost with them.
    - JAX's exit clean-up (``jax._src.api.clean_up``), which frees every compiled program one by
      one: 5-7 s per worker at the end of the float32 pass, with the pass waiting for both (its
      last worker done to the run's end 7.2-8.2 s, 2.7 s without it; 2-core EPYC). What is left is
      memory the process's end returns anyway.

    In the controller and in a run without workers both stay."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_protocol(item, nextitem):
    """pytest's own protocol for one test (set-up, call, tear-down and their reports:
    ``_pytest.runner.runtestprotocol``, between the log start and finish hooks as pytest's default
    does), run from :func:`deep_frame`."""
    item.ihook.pytest_runtest_logstart(nodeid=item.nodeid, location=item.location)
    deep_frame(runtestprotocol, item, nextitem=nextitem)
    item.ihook.pytest_runtest_logfinish(nodeid=item.nodeid, location=item.location)
    return True


# Accidental implicit broadcasting is a bug in library code: make it an error.
jax.config.update("jax_numpy_rank_promotion", "raise")

settings.register_profile(
    "jaxquat",
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    derandomize=True,
)
settings.load_profile("jaxquat")


def pytest_report_header(config):
    return f"jaxquat suite: jax {jax.__version__}, x64={jax.config.jax_enable_x64}"


@pytest.fixture
def x64():
    return bool(jax.config.jax_enable_x64)


# The files that take longest are collected first, the rest in file order. pytest-xdist's --dist
# loadfile hands a worker the next file as it frees up, in this order with --no-loadscope-reorder
# (Makefile; by default xdist sorts the files by their number of tests), so the long files start
# first and the short ones fill the end, instead of one worker finishing a long file alone. The
# order is by the sum of a file's test time in the two passes (seconds, float64 + float32, a
# 2-core Intel Xeon, session 91): the integrators 102 + 66, the contract 67 + 60, optimal control
# 125 + 0, the Lie solvers 64 + 37, the kernels 37 + 32, the sharding subprocess 4 + 43, the
# time-optimal solvers 40 + 0, then 15-33 s each. Until session 90 the sharding file (43 s of the
# float32 pass) and the kernels were left in file order, late: replaying the passes' file times
# on two workers in each order, the float32 pass's longer worker 190 -> 184 s, the float64 pass's
# 341 -> 342 s; run, the float32 pass took 197 s for 365 s of test time before and 197 s for 383 s after
# (a slower minute: at equal work, about 9 s less). Order only: no test depends on another.
_LONGEST_FIRST = (
    "test_integrators.py",
    "test_contract.py",
    "test_optimal_control.py",
    "test_lie_solvers.py",
    "test_kernels.py",
    "test_sharding.py",
    "test_time_optimal.py",
    "test_spline.py",
    "test_derivatives.py",
    "test_examples.py",
    "test_elliptic.py",
    "test_torque_free.py",
    "test_determination.py",
    "test_threads.py",
    "test_notebooks.py",
    "test_examples_optimisation.py",
    "test_kinematics.py",
    "test_euler_angles.py",
    "test_ukf.py",
    "test_dynamics.py",
)


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(_LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
