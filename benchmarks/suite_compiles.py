"""Where the test suite's time goes: what each test traces, lowers and compiles, and which
programs a test worker compiles more than once.

The suite is bound by compilation (docs/benchmarks.md, sessions 58, 92 and 93: XLA's compile,
tracing and lowering are about 90 % of a pass's test time), so this is the profile that finds
its time. Two parts:

- A pytest plugin (this module, loaded by ``-p``): it listens to JAX's own timings of tracing,
  lowering and XLA's compile (``jax.monitoring``'s duration events, as ``tests/helpers.py``'s
  ``lowered_programs`` does), wraps JAX's call to XLA (``jax._src.compiler.compile_or_get_cached``)
  to name each program, and writes one JSON line per event, with the test that caused it, to
  ``$JAXQUAT_SUITE_COMPILES`` (default ``/tmp/jaxquat-suite-compiles``), a file per worker and
  dtype. Each program XLA compiles is named by a hash of its MLIR text
  without locations and of its compile options, so a program compiled twice in one worker (a
  closure built again for each parameter of a test, say) shows as a repeat. Hashing costs about
  2 ms a program (10 s over the float64 pass): compare timings only between runs with the
  plugin.
- A report (this module, run as a script): totals per phase, the programs and files that take
  longest, the small programs (eager operations: a program per primitive and shape), and the
  repeated programs with the tests that compiled them.

Run from the repository root, a pass or part of one, then the report::

    rm -rf /tmp/jaxquat-suite-compiles
    JAX_ENABLE_X64=1 PYTHONPATH=benchmarks .venv/bin/python -m pytest -n 2 --dist loadfile -p suite_compiles
    .venv/bin/python benchmarks/suite_compiles.py

The wrapped function is a JAX internal (jax 0.10.2 here); where it is missing the plugin raises
at load, naming it, rather than reporting nothing.
"""

from __future__ import annotations

import collections
import glob
import hashlib
import json
import os
import sys
import time

DIRECTORY = os.environ.get("JAXQUAT_SUITE_COMPILES", "/tmp/jaxquat-suite-compiles")
SMALL = 0.03  # seconds of XLA below which a program counts as small
_PHASES = {
    "jaxpr_trace_duration": "tracing",
    "jaxpr_to_mlir_module_duration": "lowering",
    "backend_compile_duration": "XLA",
}

_test = ["<collection>"]
_records: list[list] = []


def _install() -> None:
    """Listens to JAX's timings and wraps its XLA call (a plugin's import, in each pytest process)."""
    import jax
    from jax._src import compiler

    if not hasattr(compiler, "compile_or_get_cached"):
        raise RuntimeError("suite_compiles: this jax has no jax._src.compiler.compile_or_get_cached to wrap")
    xla = compiler.compile_or_get_cached

    def timed(event: str, duration_secs: float, **kwargs: str | int) -> None:
        phase = _PHASES.get(event.rsplit("/", 1)[-1])
        if phase:
            _records.append([_test[0], phase, str(kwargs.get("fun_name")), duration_secs, None])

    def compiled(backend, computation, devices, compile_options, *args, **kwargs):
        text = computation.operation.get_asm(enable_debug_info=False, large_elements_limit=None)
        key = hashlib.sha1(text.encode() + compile_options.SerializeAsString()).hexdigest()[:16]
        start = time.perf_counter()
        out = xla(backend, computation, devices, compile_options, *args, **kwargs)
        name = computation.operation.attributes["sym_name"].value
        _records.append([_test[0], "program", name, time.perf_counter() - start, key])
        return out

    jax.monitoring.register_event_duration_secs_listener(timed)
    compiler.compile_or_get_cached = compiled


def _flush() -> None:
    if not _records:
        return
    os.makedirs(DIRECTORY, exist_ok=True)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    dtype = "float64" if os.environ.get("JAX_ENABLE_X64", "0") not in ("0", "", "false", "False") else "float32"
    with open(os.path.join(DIRECTORY, f"{worker}-{dtype}.jsonl"), "a") as f:
        f.writelines(json.dumps(r) + "\n" for r in _records)
    _records.clear()


def pytest_runtest_logstart(nodeid, location):
    _flush()
    _test[0] = nodeid


def pytest_runtest_logfinish(nodeid, location):
    _flush()
    _test[0] = "<between tests>"


def pytest_sessionfinish(session, exitstatus):
    _flush()


def report(directory: str = DIRECTORY, top: int = 15) -> str:
    """The report of the records in ``directory``, per dtype."""
    lines = []
    for dtype in ("float64", "float32"):
        files = sorted(glob.glob(os.path.join(directory, f"*-{dtype}.jsonl")))
        if not files:
            continue
        phases, by_name, by_file = collections.Counter(), collections.Counter(), collections.Counter()
        small, small_count, repeats = 0.0, 0, collections.Counter()
        repeat_count, repeat_time = 0, 0.0
        for path in files:  # a worker each: a repeat is a program its own worker compiled before
            seen: dict[str, str] = {}
            for test, phase, name, seconds, key in map(json.loads, open(path)):
                if phase == "program":
                    if seconds < SMALL:
                        small, small_count = small + seconds, small_count + 1
                    if key in seen:
                        repeat_count, repeat_time = repeat_count + 1, repeat_time + seconds
                        repeats[f"{name}: {test} (first: {seen[key]})"] += seconds
                    seen.setdefault(key, test)
                    continue
                phases[phase] += seconds
                by_file[test.split("::")[0]] += seconds
                if phase == "XLA":
                    by_name[name] += seconds
        lines.append(f"== {dtype}: " + ", ".join(f"{p} {s:.1f} s" for p, s in phases.items()))
        lines.append(f"programs under {SMALL * 1e3:.0f} ms of XLA: {small_count}, {small:.1f} s of XLA")
        lines.append(f"programs compiled again in their worker: {repeat_count}, {repeat_time:.1f} s of XLA")
        for title, counter in (("XLA by program", by_name), ("by file (all phases)", by_file), ("repeats", repeats)):
            lines.append(f"-- {title}")
            lines += [f"{seconds:8.2f}  {what}" for what, seconds in counter.most_common(top)]
    return "\n".join(lines) if lines else f"no records in {directory}"


if __name__ == "__main__":
    print(report(sys.argv[1] if len(sys.argv) > 1 else DIRECTORY))
else:
    _install()
