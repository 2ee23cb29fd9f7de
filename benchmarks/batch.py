"""Many bodies on a multi-core CPU: one device against the batch split over one CPU device per core.

10^5 torque-free asymmetric bodies (random attitudes and rates, principal moments in [1, 2]),
``jaxquat.simulate``'s scan path with RKMK4 at dt = 0.01 for 1000 steps, float32 and float64.
The CPU is given one device per core (``jax_num_cpu_devices``) and the same function runs three
ways:

- one device: ``jax.jit`` of the whole batch, XLA's defaults (XLA splits a large kernel between
  the threads of its pool);
- sharded ``jit``: the batch on an Explicit mesh over the devices (``jax.make_mesh``'s default),
  one SPMD program;
- ``shard_map``: ``simulate`` as the body of a ``jax.shard_map`` over the devices, compiled with
  ``jq.cpu_compiler_options(batch, dtype, devices=n)`` (each device on one thread), the recipe
  of ``docs/integrators.md``, "Many bodies on a multi-core CPU".

For each: the forward pass (the final attitudes) and the gradient of a final-attitude loss in
``w0``, least of ``--repeats`` calls after compiling, with the compile times apart, and the largest
difference from the one-device results. Beside them, the one-device run's attitude error at the
final time against the exact solution (``jaxquat.euler_poinsot`` in float64).

Run: python benchmarks/batch.py [--bodies 100000] [--steps 1000] [--devices N (default: the cores)]
                                [--dtypes float32 float64] [--repeats 3] [--write docs/benchmarks.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax

if __name__ == "__main__":  # the devices before JAX starts its CPU backend (main() parses the rest)
    _early = argparse.ArgumentParser(add_help=False)
    _early.add_argument("--devices", type=int)
    jax.config.update("jax_num_cpu_devices", _early.parse_known_args()[0].devices or os.cpu_count() or 1)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import NamedSharding  # noqa: E402
from jax.sharding import PartitionSpec as P  # noqa: E402

import jaxquat as jq  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from _report import machine, write_section  # noqa: E402


def bodies(n, seed=0):
    rng = np.random.default_rng(seed)
    q0 = rng.normal(size=(n, 4))
    q0 /= np.linalg.norm(q0, axis=-1, keepdims=True)
    moments = np.sort(rng.uniform(1.0, 2.0, (n, 3)), axis=-1)
    return q0, rng.normal(size=(n, 3)), moments


def functions(steps, dt, dtype):
    """The final attitudes of a batch, and the loss's weights per component."""
    ts = np.asarray([0.0, steps * dt], dtype)

    def final(q0, w0, moments):
        sim = jq.simulate(q0, w0, jax.vmap(jnp.diag)(moments), ts, solver=jq.RKMK4(), dt0=dt, max_steps=steps + 4)
        return sim.q[:, -1]

    return final, jnp.asarray([0.5, 1.0, -1.0, 2.0], dtype)


def least_time(fn, args, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return min(times)


def compiled(fn, args, options=None):
    """``fn`` compiled for ``args`` (``jax.jit``, with ``options`` as its compiler options) and the
    seconds that took (tracing, lowering and XLA)."""
    t0 = time.perf_counter()
    out = jax.jit(fn, compiler_options=options or None).lower(*args).compile()
    return out, time.perf_counter() - t0


def setups(final, weights, n_devices, batch, dtype):
    """``(name, forward, gradient, shard the inputs, compiler options)`` for each way to run; the
    gradient's arguments are ``(w0, q0, moments)``."""
    mesh = jax.make_mesh((n_devices,), ("b",))
    spec = NamedSharding(mesh, P("b"))

    def shard(xs):
        return [jax.device_put(x, spec) for x in xs]

    mapped = jax.shard_map(final, mesh=mesh, in_specs=(P("b"),) * 3, out_specs=P("b"))

    def gradient(fn):
        return jax.grad(lambda w0, q0, moments: jnp.sum(fn(q0, w0, moments) * weights))

    one = ("one device, `jit`", final, gradient(final), lambda xs: xs, None)
    spmd = (f"{n_devices} devices, sharded `jit`", final, gradient(final), shard, None)
    options = jq.cpu_compiler_options(batch, dtype, devices=n_devices)
    by_map = (f"{n_devices} devices, `shard_map`, one thread each", mapped, gradient(mapped), shard, options)
    return [one, spmd, by_map] if n_devices > 1 else [one]


def run(bodies_, steps, dt, dtype, repeats):
    q0, w0, moments = bodies(bodies_)
    final, weights = functions(steps, dt, dtype)
    host = [np.asarray(x, dtype) for x in (q0, w0, moments)]
    rows, reference = [], None
    for name, fwd, grad, shard, options in setups(final, weights, len(jax.devices()), bodies_, dtype):
        q_args = shard([jnp.asarray(x) for x in host])
        g_args = [q_args[1], q_args[0], q_args[2]]
        fwd_c, fwd_compile = compiled(fwd, q_args, options)
        grad_c, grad_compile = compiled(grad, g_args, options)
        q, g = fwd_c(*q_args), grad_c(*g_args)
        t_fwd = least_time(fwd_c, q_args, repeats)
        t_grad = least_time(grad_c, g_args, repeats)
        q, g = np.asarray(q), np.asarray(g)
        if reference is None:
            reference = (q, g, t_fwd, t_grad)
        diff = max(float(np.max(np.abs(q - reference[0]))), float(np.max(np.abs(g - reference[1]))))
        rows.append((name, t_fwd, t_grad, fwd_compile, grad_compile, diff))
        print(dtype.__name__, name, f"{t_fwd * 1e3:.0f} ms / {t_grad * 1e3:.0f} ms", flush=True)
    with jax.enable_x64(True):
        q_ref, _ = jq.euler_poinsot(
            jnp.asarray(q0), jnp.asarray(w0), jnp.asarray(moments), jnp.full(bodies_, steps * dt)
        )
        err = np.asarray(jq.angle_between(jnp.asarray(reference[0], jnp.float64), q_ref))
    return rows, (float(np.median(err)), float(np.max(err)))


def markdown(results, bodies_, steps, dt, repeats):
    n = len(jax.devices())
    lines = [
        f"{bodies_:,} torque-free bodies x {steps} RKMK4 steps of {dt} (`simulate`'s scan path); {machine()}, "
        f"{n} CPU devices (`jax_num_cpu_devices`). Least of {repeats} calls after compiling; gradient: "
        "`jax.grad` of a final-attitude loss in `w0`; compile: `jax.jit(...).lower(...).compile()`, "
        "tracing included; the last column: the largest difference from the one-device attitudes and "
        "gradient.",
        "",
        "| dtype | setup | forward | body-steps/s | gradient | gradient / forward | vs one device, forward / gradient "
        "| compile, forward / gradient | difference |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    errors = []
    for dtype, (rows, err) in results.items():
        base = rows[0]
        for name, t_fwd, t_grad, c_fwd, c_grad, diff in rows:
            lines.append(
                f"| {dtype} | {name} | {t_fwd * 1e3:.0f} ms | {bodies_ * steps / t_fwd:.2e} | {t_grad * 1e3:.0f} ms "
                f"| {t_grad / t_fwd:.2f}x | {base[1] / t_fwd:.2f}x / {base[2] / t_grad:.2f}x "
                f"| {c_fwd:.2f} / {c_grad:.2f} s | {diff:.1e} |"
            )
        errors.append(f"{dtype} median {err[0]:.1e}, max {err[1]:.1e} rad")
    lines += ["", "Attitude error at the final time against `euler_poinsot` (float64): " + "; ".join(errors) + "."]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bodies", type=int, default=100_000)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--devices", type=int, help="CPU devices (default: the cores); read before JAX starts")
    ap.add_argument("--dtypes", nargs="+", default=["float32", "float64"], choices=["float32", "float64"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--write", help="markdown file whose 'batch' section to rewrite")
    a = ap.parse_args(argv)
    results = {}
    for name in a.dtypes:
        with jax.enable_x64(name == "float64"):
            results[name] = run(a.bodies, a.steps, a.dt, np.dtype(name).type, a.repeats)
    md = markdown(results, a.bodies, a.steps, a.dt, a.repeats)
    print(md)
    if a.write:
        write_section(a.write, "batch", "### Many bodies on the cores of one CPU (`benchmarks/batch.py`)\n\n" + md)


if __name__ == "__main__":
    main()
