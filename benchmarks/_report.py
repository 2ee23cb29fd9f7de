"""Shared by the benchmark scripts: timing after compilation, the machine line, and
rewriting one generated section of docs/benchmarks.md (hand-written text around it stays)."""

from __future__ import annotations

import os
import pathlib
import platform
import statistics
import time

import jax


def samples(fn, *args, repeats: int, warmup: int = 2, max_seconds: float = 3.0) -> list[float]:
    """Wall times of ``fn(*args)`` after ``warmup`` untimed calls (compile, warm up).

    Samples stop after ``repeats`` or once ``max_seconds`` have been spent timing (at least
    one sample): a contender that takes seconds per call (NumPy at 10^6) is timed once or
    twice rather than holding up the run.
    """
    for _ in range(warmup):
        jax.block_until_ready(fn(*args))
    times = []
    while len(times) < repeats and (not times or sum(times) < max_seconds):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return times


def median_time(fn, *args, repeats: int, warmup: int = 2, max_seconds: float = 3.0) -> float:
    """The median of :func:`samples`."""
    return statistics.median(samples(fn, *args, repeats=repeats, warmup=warmup, max_seconds=max_seconds))


def least_time(fn, *args, repeats: int, warmup: int = 2, max_seconds: float = 3.0) -> float:
    """The least of :func:`samples`: the figure a disturbance of the machine (another process,
    this VM's neighbours) leaves alone unless it lasts through every sample."""
    return min(samples(fn, *args, repeats=repeats, warmup=warmup, max_seconds=max_seconds))


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), cpu)
    except OSError:
        pass
    dev = jax.devices()[0]
    tunables = os.environ.get("GLIBC_TUNABLES")
    env = f"; `GLIBC_TUNABLES={tunables}`" if tunables else ""
    return f"{dev.platform.upper()} `{dev.device_kind}`, {os.cpu_count()} cores ({cpu}); jax {jax.__version__}{env}"


def write_section(path: str, name: str, markdown: str) -> None:
    """Replace the text between ``<!-- name:begin -->`` and ``<!-- name:end -->`` (appended if absent)."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    p = pathlib.Path(path)
    text = p.read_text() if p.exists() else "# Benchmarks\n"
    block = f"{begin}\n{markdown.rstrip()}\n{end}"
    if text.count(begin) > 1 or text.count(end) > 1:  # a stray marker would survive every rewrite
        raise ValueError(f"{path} has more than one {begin} or {end}: remove the extra marker")
    if begin in text and end in text:
        text = text[: text.index(begin)] + block + text[text.index(end) + len(end) :]
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    p.write_text(text)
