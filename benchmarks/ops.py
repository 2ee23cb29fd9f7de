"""Rotation-op throughput: jaxquat against jaxlie and scipy (on JAX arrays), as ratios.

Every contender runs in this process on the same inputs, jitted (scipy 1.17's
``Rotation`` traces under ``jax.jit`` with ``SCIPY_ARRAY_API=1``), timed after
compilation with ``block_until_ready()``; the figure is the median of repeated
runs. The roofline is a jitted element-wise ``a + b`` over two ``(N, 4)``
arrays, the memory-traffic floor for an op that reads two quaternion arrays and
writes one.

    python benchmarks/ops.py [--n 1000000] [--dtype float32] [--write docs/benchmarks.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

os.environ.setdefault("SCIPY_ARRAY_API", "1")  # must precede the scipy import

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import jaxlie  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

import jaxquat as jq  # noqa: E402


def _time(fn, *args, repeats: int) -> float:
    jax.block_until_ready(fn(*args))  # compile and warm up
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _xyzw(q):
    return jnp.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def _wxyz(q):
    return jnp.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def contenders():
    """op -> {library: function of (p, q, v, m, t)} (each picks the inputs it needs)."""

    def sp(q):
        return Rotation.from_quat(_xyzw(q))

    def lie(q):
        return jaxlie.SO3(wxyz=q)

    return {
        "multiply": {
            "jaxquat": lambda p, q, v, m, t: jq.multiply(p, q),
            "jaxlie": lambda p, q, v, m, t: (lie(p) @ lie(q)).wxyz,
            "scipy": lambda p, q, v, m, t: _wxyz((sp(p) * sp(q)).as_quat()),
        },
        "rotate": {
            "jaxquat": lambda p, q, v, m, t: jq.rotate(p, v),
            "jaxlie": lambda p, q, v, m, t: lie(p) @ v,
            "scipy": lambda p, q, v, m, t: sp(p).apply(v),
        },
        "to_matrix": {
            "jaxquat": lambda p, q, v, m, t: jq.to_matrix(p),
            "jaxlie": lambda p, q, v, m, t: lie(p).as_matrix(),
            "scipy": lambda p, q, v, m, t: sp(p).as_matrix(),
        },
        "from_matrix": {
            "jaxquat": lambda p, q, v, m, t: jq.from_matrix(m),
            "jaxlie": lambda p, q, v, m, t: jaxlie.SO3.from_matrix(m).wxyz,
            "scipy": lambda p, q, v, m, t: _wxyz(Rotation.from_matrix(m).as_quat()),
        },
        "slerp": {
            "jaxquat": lambda p, q, v, m, t: jq.slerp(p, q, t),
            # Neither peer has an element-wise slerp; this is how each spells it.
            "jaxlie": lambda p, q, v, m, t: (
                lie(p) @ jaxlie.SO3.exp(t[:, None] * (lie(p).inverse() @ lie(q)).log())
            ).wxyz,
            "scipy": lambda p, q, v, m, t: _wxyz(
                (sp(p) * Rotation.from_rotvec(t[:, None] * (sp(p).inv() * sp(q)).as_rotvec())).as_quat()
            ),
        },
        "to_rotvec": {
            "jaxquat": lambda p, q, v, m, t: jq.to_rotvec(p),
            "jaxlie": lambda p, q, v, m, t: lie(p).log(),
            "scipy": lambda p, q, v, m, t: sp(p).as_rotvec(),
        },
        "from_rotvec": {
            "jaxquat": lambda p, q, v, m, t: jq.from_rotvec(v),
            "jaxlie": lambda p, q, v, m, t: jaxlie.SO3.exp(v).wxyz,
            "scipy": lambda p, q, v, m, t: _wxyz(Rotation.from_rotvec(v).as_quat()),
        },
        "to_euler (xyz)": {
            "jaxquat": lambda p, q, v, m, t: jq.to_euler(p, "xyz"),
            "jaxlie": None,  # jaxlie has only roll/pitch/yaw (as_rpy_radians); not the same quantity set
            "scipy": lambda p, q, v, m, t: sp(p).as_euler("xyz"),
        },
    }


def run(n: int, dtype, repeats: int):
    key = jax.random.PRNGKey(0)
    k1, k2, k3, k4 = jax.random.split(key, 4)
    p = jq.random(k1, (n,), dtype)
    q = jq.random(k2, (n,), dtype)
    v = jax.random.normal(k3, (n, 3), dtype)
    t = jax.random.uniform(k4, (n,), dtype)
    m = jax.jit(jq.to_matrix)(p)
    args = (p, q, v, m, t)
    roof = _time(jax.jit(lambda a, b: a + b), p, q, repeats=repeats)
    rows = []
    for op, libs in contenders().items():
        times = {}
        for lib, fn in libs.items():
            if fn is None:
                times[lib] = None
                continue
            times[lib] = _time(jax.jit(fn), *args, repeats=repeats)
        rows.append((op, times))
    return roof, rows


def table(n, dtype, roof, rows) -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    dev = jax.devices()[0]
    lines = [
        f"Batch {n:,} {jnp.dtype(dtype).name} quaternions; {dev.platform.upper()} `{dev.device_kind}`, "
        f"{os.cpu_count()} cores ({cpu}); jax {jax.__version__}, jaxlie {getattr(jaxlie, '__version__', '?')}, "
        f"scipy {__import__('scipy').__version__}. Median of repeated jitted runs after compilation.",
        "",
        f"Roofline (jitted `a + b` on two `({n}, 4)` arrays): {roof * 1e3:.2f} ms.",
        "",
        "| op | jaxquat (ms) | jaxlie (ms) | scipy on JAX (ms) | jaxlie / jaxquat | scipy / jaxquat | jaxquat / roofline |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for op, tm in rows:
        ours = tm["jaxquat"]

        def ms(x):
            return "n/a" if x is None else f"{x * 1e3:.2f}"

        def ratio(x):
            return "n/a" if x is None else f"{x / ours:.1f}x"

        lines.append(
            f"| {op} | {ms(ours)} | {ms(tm['jaxlie'])} | {ms(tm['scipy'])} | {ratio(tm['jaxlie'])} | "
            f"{ratio(tm['scipy'])} | {ours / roof:.2f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--write", help="markdown file to (re)write with the table")
    a = ap.parse_args(argv)
    if a.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    roof, rows = run(a.n, jnp.dtype(a.dtype), a.repeats)
    md = table(a.n, a.dtype, roof, rows)
    print(md)
    if a.write:
        header = (
            "# Benchmarks\n\n"
            "Written by `make bench` (`python benchmarks/ops.py --write docs/benchmarks.md`). "
            "Ratios are peer time / jaxquat time measured in the same run; absolute times depend on the machine.\n\n"
            "## Rotation ops\n\n"
        )
        with open(a.write, "w") as f:
            f.write(header + md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
