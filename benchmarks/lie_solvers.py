"""Work-precision of the Lie solvers on a user model (the quadrotor of tests/test_lie_solvers.py)
against diffrax's Tsit5, Dopri5 and Dopri8 on the raw ODE, with and without renormalising q.

Each configuration: ``diffeqsolve`` to t = 10 with a PID controller at rtol = atol = tol,
float64; the error is the largest of the attitude error (rad) and the absolute errors of r, v, w
at t = 10 against scipy DOP853 at rtol = atol = 1e-13; ``| |q| - 1 |`` at t = 10; steps;
vector-field calls; the median wall time of 5 compiled runs (compile time separately).

Run: .venv/bin/python benchmarks/lie_solvers.py [--plot PATH]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

import jaxquat as jq  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent.parent / "tests"))
from test_lie_solvers import MASK, THRUST, _y0, quadrotor  # noqa: E402

T_END = 10.0
KEYS = ("r", "v", "q", "w")


def reference():
    flat0 = np.concatenate([np.asarray(_y0(jnp.float64)[k]) for k in KEYS])

    def rhs(t, x):
        y = {"r": x[:3], "v": x[3:6], "q": x[6:10], "w": x[10:]}
        d = jax.tree.map(np.asarray, quadrotor(np.float64(t), y, THRUST))
        return np.concatenate([d[k] for k in KEYS])

    x = solve_ivp(rhs, (0.0, T_END), flat0, method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
    return {"r": x[:3], "v": x[3:6], "q": x[6:10] / np.linalg.norm(x[6:10]), "w": x[10:]}


def renormalised(t, y, args):
    """The raw field with ``q / |q|`` read inside it: renormalisation as users do it with Tsit5."""
    return quadrotor(t, dict(y, q=y["q"] / jnp.linalg.norm(y["q"])), args)


def run(solver, tol, renorm=False, repeats=5):
    term = diffrax.ODETerm(renormalised if renorm else quadrotor)

    @jax.jit
    def solve():
        sol = diffrax.diffeqsolve(term, solver, 0.0, T_END, 1e-3, _y0(jnp.float64), args=THRUST,
                                  stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol), max_steps=100_000)
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


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--plot", default=None)
    opts = parser.parse_args()
    ref = reference()
    configs = [
        ("RKMK45", jq.RKMK45(quaternions=MASK), False, 6),
        ("RKMKTsit5", jq.RKMKTsit5(quaternions=MASK), False, 6),
        ("RKMK8", jq.RKMK8(quaternions=MASK), False, 13),
        ("Tsit5 (raw ODE)", diffrax.Tsit5(), False, 6),
        ("Dopri5 (raw ODE)", diffrax.Dopri5(), False, 6),
        ("Dopri8 (raw ODE)", diffrax.Dopri8(), False, 13),
        ("Tsit5 (renormalised in f)", diffrax.Tsit5(), True, 6),
    ]
    rows = []
    print("| solver | tol | steps | field calls | wall time, ms | compile, s | error | abs(abs(q) - 1) |")
    print("|---|---|---|---|---|---|---|---|")
    for name, solver, renorm, calls in configs:
        for tol in (1e-6, 1e-8, 1e-10, 1e-12):
            y, steps, wall, comp = run(solver, tol, renorm)
            err = max(max(float(np.abs(np.asarray(y[k]) - ref[k]).max()) for k in ("r", "v", "w")),
                      float(jq.angle_between(y["q"] / jnp.linalg.norm(y["q"]), jnp.asarray(ref["q"]))))
            norm_err = abs(float(jnp.linalg.norm(y["q"])) - 1)
            rows.append((name, tol, steps, wall, err))
            print(f"| {name} | {tol:.0e} | {steps} | {steps * calls} | {wall * 1e3:.2f} | {comp:.2f} | "
                  f"{err:.2e} | {norm_err:.1e} |", flush=True)
    if opts.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
        for name in dict.fromkeys(r[0] for r in rows):
            sub = [r for r in rows if r[0] == name]
            style = "-o" if name.startswith("RKMK") else "--s"
            axes[0].loglog([r[3] * 1e3 for r in sub], [r[4] for r in sub], style, label=name)
            axes[1].loglog([r[2] for r in sub], [r[4] for r in sub], style, label=name)
        axes[0].set_xlabel("wall time, ms (median of 5, compiled)")
        axes[1].set_xlabel("steps")
        for ax in axes:
            ax.set_ylabel("error at t = 10")
            ax.grid(True, which="both", alpha=0.3)
        axes[1].legend(fontsize=8)
        fig.suptitle("Quadrotor {r, v, q, w}, float64: Lie solvers vs diffrax on the raw ODE")
        fig.tight_layout()
        fig.savefig(opts.plot, dpi=110)


if __name__ == "__main__":
    main()
