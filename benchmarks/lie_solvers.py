"""Work-precision of the Lie solvers against diffrax's Tsit5, Dopri5 and Dopri8 on the raw ODE
(q as four numbers), with and without renormalising q, on two models:

- ``quadrotor``: ``jq.Quadrotor`` {r, v, q, w} (thrust along body z, drag, a time-varying
  torque) to t = 10; reference: scipy DOP853 at rtol = atol = 1e-13 on the same field evaluated
  in float64 (``jax.enable_x64``) whatever the run's dtype.
- ``free``: the torque-free asymmetric body ``(q, w)`` of ``jq.RigidBody`` (I = diag(1, 2, 3),
  w0 = (1, 0.3, 0.2)) to t = 100; reference: the exact flow ``jq.euler_poinsot`` in float64.

Each configuration: ``diffeqsolve`` with a PID controller at rtol = atol = tol; the error is the
largest of the attitude error (rad) and the absolute errors of the other leaves at the final
time; ``| |q| - 1 |`` there; steps and vector-field calls; the median wall time of 7 compiled
runs (compile time separately). Prints a markdown table per model.

Run: .venv/bin/python benchmarks/lie_solvers.py [--dtype float32] [--plot PATH]
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax

parser = argparse.ArgumentParser()
parser.add_argument("--dtype", default="float64", choices=["float64", "float32"])
parser.add_argument("--plot", default=None, help="a PNG path: error against wall time and against steps")
OPTS = parser.parse_args()
jax.config.update("jax_enable_x64", OPTS.dtype == "float64")

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

import jaxquat as jq  # noqa: E402

DTYPE = jnp.float64 if OPTS.dtype == "float64" else jnp.float32
TOLS = (1e-6, 1e-8, 1e-10, 1e-12) if OPTS.dtype == "float64" else (1e-3, 1e-4, 1e-5, 1e-6)


def _quad_control(t, y, thrust):
    return thrust, 0.01 * jnp.stack([jnp.sin(3 * t), jnp.cos(2 * t), 0.5 * jnp.ones_like(t)]).astype(y["w"].dtype)


def quadrotor(dtype):
    model = jq.Quadrotor(1.2, jnp.diag(jnp.asarray([0.02, 0.03, 0.05], dtype)), _quad_control, drag=0.3)
    y0 = {
        "r": jnp.zeros(3, dtype),
        "v": jnp.asarray([1.0, 0.0, 0.5], dtype),
        "q": jq.from_rotvec(jnp.asarray([0.3, -0.2, 0.1], dtype)),
        "w": jnp.asarray([2.0, -1.0, 3.0], dtype),
    }
    return model, y0, 12.5, 10.0, jq.Quadrotor.quaternions


def quadrotor_reference():
    with jax.enable_x64(True):
        model, y0, thrust, t_end, _ = quadrotor(jnp.float64)
        keys = tuple(y0)
        sizes = np.cumsum([y0[k].size for k in keys])[:-1]
        field = jax.jit(
            lambda t, x: jnp.concatenate([model(t, dict(zip(keys, jnp.split(x, sizes))), thrust)[k] for k in keys])
        )
        x0 = np.concatenate([np.asarray(y0[k]) for k in keys])
        x = solve_ivp(
            lambda t, x: np.asarray(field(t, x)), (0.0, t_end), x0, method="DOP853", rtol=1e-13, atol=1e-13
        ).y[:, -1]
    return dict(zip(keys, np.split(x, sizes)))


MOMENTS = np.array([1.0, 2.0, 3.0])
W0 = np.array([1.0, 0.3, 0.2])


def free_body(dtype):
    model = jq.RigidBody(jnp.diag(jnp.asarray(MOMENTS, dtype)))
    y0 = (jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype), jnp.asarray(W0, dtype))
    return model, y0, None, 100.0, None


def free_reference():
    with jax.enable_x64(True):
        q, w = jq.euler_poinsot(jnp.asarray([1.0, 0, 0, 0]), jnp.asarray(W0), jnp.asarray(MOMENTS), jnp.asarray(100.0))
    return (np.asarray(q), np.asarray(w))


def _renormalised(model, mask_index):
    """The raw field with ``q / |q|`` read inside it: renormalisation as users do it with Tsit5."""

    def field(t, y, args):
        leaves, tree = jax.tree.flatten(y)
        q = leaves[mask_index]
        leaves[mask_index] = q / jnp.linalg.norm(q)
        return model(t, jax.tree.unflatten(tree, leaves), args)

    return field


def run(term, solver, y0, args, t_end, tol, repeats=7):
    @jax.jit
    def solve():
        sol = diffrax.diffeqsolve(
            term,
            solver,
            0.0,
            t_end,
            1e-3,
            y0,
            args=args,
            stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
            max_steps=200_000,
        )
        return jax.tree.map(lambda x: x[-1], sol.ys), sol.stats["num_steps"]

    start = time.perf_counter()
    y, steps = jax.block_until_ready(solve())
    compile_s = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(solve())
        times.append(time.perf_counter() - start)
    return y, int(steps), statistics.median(times), compile_s


def error(y, ref) -> tuple[float, float]:
    leaves, refs = jax.tree.leaves(y), jax.tree.leaves(ref)
    err, norm_err = 0.0, 0.0
    for leaf, r in zip(leaves, refs):
        leaf = np.asarray(leaf, np.float64)
        if leaf.shape[-1] == 4:
            norm_err = abs(float(np.linalg.norm(leaf)) - 1)
            dot = abs(float(leaf @ r)) / np.linalg.norm(leaf) / np.linalg.norm(r)
            err = max(
                err,
                2 * float(np.arccos(min(1.0, dot)))
                if dot < 1 - 1e-6
                else 2 * float(np.linalg.norm(leaf / np.linalg.norm(leaf) * np.sign(leaf @ r) - r)),
            )
        else:
            err = max(err, float(np.abs(leaf - r).max()))
    return err, norm_err


def study(name, build, reference):
    model, y0, args, t_end, mask = build(DTYPE)
    ref = reference()
    q_index = [i for i, leaf in enumerate(jax.tree.leaves(y0)) if leaf.shape[-1] == 4][0]
    configs = [
        ("RKMK45", jq.RKMK45(quaternions=mask), False, 6),
        ("RKMKTsit5", jq.RKMKTsit5(quaternions=mask), False, 6),
        ("RKMK8", jq.RKMK8(quaternions=mask), False, 13),
        ("Tsit5 (raw ODE)", diffrax.Tsit5(), False, 6),
        ("Dopri5 (raw ODE)", diffrax.Dopri5(), False, 6),
        ("Dopri8 (raw ODE)", diffrax.Dopri8(), False, 13),
        ("Tsit5 (renormalised in f)", diffrax.Tsit5(), True, 6),
        ("Dopri8 (renormalised in f)", diffrax.Dopri8(), True, 13),
    ]
    rows = []
    print(f"\n### {name}, {OPTS.dtype}, t = {t_end:g}\n")
    print("| solver | tol | steps | field calls | wall time, ms | compile, s | error | abs(abs(q) - 1) |")
    print("|---|---|---|---|---|---|---|---|")
    for label, solver, renorm, calls in configs:
        term = diffrax.ODETerm(_renormalised(model, q_index) if renorm else model)
        for tol in TOLS:
            y, steps, wall, comp = run(term, solver, y0, args, t_end, tol)
            err, norm_err = error(y, ref)
            rows.append((label, tol, steps, wall, err))
            print(
                f"| {label} | {tol:.0e} | {steps} | {steps * calls} | {wall * 1e3:.2f} | {comp:.2f} | "
                f"{err:.2e} | {norm_err:.1e} |",
                flush=True,
            )
    return rows


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(results), 2, figsize=(11, 4.2 * len(results)), squeeze=False)
    for row, (name, rows) in zip(axes, results.items()):
        for label in dict.fromkeys(r[0] for r in rows):
            sub = [r for r in rows if r[0] == label]
            style = "-o" if label.startswith("RKMK") else "--s"
            row[0].loglog([r[3] * 1e3 for r in sub], [r[4] for r in sub], style, label=label)
            row[1].loglog([r[2] for r in sub], [r[4] for r in sub], style, label=label)
        row[0].set_xlabel("wall time, ms (median of 7, compiled)")
        row[1].set_xlabel("steps")
        for ax in row:
            ax.set_ylabel(f"{name}: error at the final time")
            ax.grid(True, which="both", alpha=0.3)
        row[1].legend(fontsize=7)
    fig.suptitle(f"Lie solvers vs diffrax on the raw ODE, {OPTS.dtype}")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main():
    results = {
        "quadrotor": study("quadrotor", quadrotor, quadrotor_reference),
        "free rigid body": study("free rigid body", free_body, free_reference),
    }
    if OPTS.plot:
        plot(results, OPTS.plot)


if __name__ == "__main__":
    main()
