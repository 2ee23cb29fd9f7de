"""Python frames for the suite's long call stacks (standard library only, so that a subprocess's
script can use it before it imports JAX: :func:`script_in_deep_frame`)."""

from __future__ import annotations

import pathlib
import types


def deep_frame(f, *args, **kwargs):
    """``f(*args, **kwargs)`` called from a frame that reserves about 1 MiB of CPython's frame stack.

    CPython 3.11+ keeps its Python frames on per-thread stack chunks of 16 KiB, allocates a chunk
    with ``mmap`` when a call does not fit in the current one and unmaps it when the call that
    opened it returns. A call stack that goes up and down across a chunk's end (tracing and
    lowering a JAX program, tens of frames deep under pytest's own) maps and unmaps a chunk each
    time, and faults its pages in afresh: 43 % of the page faults of ``test_kernels.py`` were
    ``_PyThreadState_BumpFramePointerSlow``'s (``perf record -e page-faults``, one process,
    float64). This frame's code claims a value stack of 140 000 slots (``co_stacksize``, of which
    its one call uses a few), so calling it opens one 2 MiB chunk and every frame above it fits in
    the rest (about 0.9 MiB: a stack thousands of frames deep). Measured (session 79, 2-core Intel
    Xeon, float64 pass on two workers, one run each): its tests' minor page faults 6.23 -> 2.47
    million and their system time 129 -> 101 s, the pass 10m12 -> 9m43; the float32 sharding
    script 501 000 -> 256 000 faults and 83.2 -> 81.8 s; a clean clone's ``.ci/run`` 3m49-3m52 ->
    2m45-3m17 of system time (``docs/benchmarks.md``, session 79); the learned-torque script
    (session 80, one pinned core) 252 000 -> 163 000 faults and 19.5 -> 18.4-18.5 s. Nothing
    computed changes: only where CPython puts its frames."""
    return _DEEP(f, *args, **kwargs)


def _call(f, *args, **kwargs):
    return f(*args, **kwargs)


_DEEP = types.FunctionType(_call.__code__.replace(co_stacksize=140_000), {})


def script_in_deep_frame(script: str) -> str:
    """Python source (for ``python -c``) that runs ``script`` as ``__main__`` from :func:`deep_frame`."""
    here = str(pathlib.Path(__file__).parent)
    return (
        f"import sys; sys.path.insert(0, {here!r}); from frames import deep_frame; "
        f"deep_frame(exec, compile({script!r}, '<script>', 'exec'), {{'__name__': '__main__'}})"
    )
