"""Error versus work for the rigid-body solvers and diffrax's generic solvers on the raw ODE.

Problem (issue 5): I = diag(1, 2, 3), w0 = (1, 0.1, 0.5), q0 = identity, float64, torque-free.
Reference: scipy DOP853 at rtol = atol = 1e-13 on the 7-state ODE. For each configuration:
attitude error at T, |q| error, steps, and wall time of a second (compiled) run.
Run: .venv/bin/python benchmarks/integrators.py [--t-end 100]
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

import jaxquat as jq  # noqa: E402

I_DIAG = np.array([1.0, 2.0, 3.0])
W0 = np.array([1.0, 0.1, 0.5])


def reference(t_end):
    def rhs(t, y):
        q, w = y[:4], y[4:]
        qd = 0.5 * np.array([-q[1:] @ w, *(q[0] * w + np.cross(q[1:], w))])
        return np.concatenate([qd, np.cross(I_DIAG * w, w) / I_DIAG])

    sol = solve_ivp(rhs, (0, t_end), np.concatenate([[1.0, 0, 0, 0], W0]), method="DOP853", rtol=1e-13, atol=1e-13)
    return sol.y[:4, -1]


def raw_field(t, y, args):
    q, w = y
    inertia = jnp.asarray(I_DIAG)
    return 0.5 * jq.multiply(q, jnp.concatenate([jnp.zeros(1), w])), jnp.cross(inertia * w, w) / inertia


def run(t_end, solver, dt=None, tol=None, lie=True):
    term = diffrax.ODETerm(jq.RigidBody(jnp.diag(jnp.asarray(I_DIAG))) if lie else raw_field)
    controller = diffrax.ConstantStepSize() if tol is None else diffrax.PIDController(rtol=tol, atol=tol)
    steps_cap = int(t_end / dt) + 10 if dt else 10_000_000

    @jax.jit
    def solve():
        sol = diffrax.diffeqsolve(term, solver, 0.0, t_end, dt if dt else 1e-2, (jq.identity(), jnp.asarray(W0)),
                                  stepsize_controller=controller, max_steps=steps_cap)
        return sol.ys[0][-1], sol.stats["num_steps"]

    solve()[0].block_until_ready()
    t0 = time.perf_counter()
    q, steps = solve()
    q.block_until_ready()
    return q, int(steps), time.perf_counter() - t0


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--t-end", type=float, default=100.0)
    args = parser.parse_args()
    q_ref = jnp.asarray(reference(args.t_end))
    configs = [
        ("Tsit5 (raw ODE)", diffrax.Tsit5(), None, 1e-8, False),
        ("Tsit5 (raw ODE)", diffrax.Tsit5(), None, 1e-10, False),
        ("Dopri8 (raw ODE)", diffrax.Dopri8(), None, 1e-10, False),
        ("RKMK45", jq.RKMK45(), None, 1e-8, True),
        ("RKMK45", jq.RKMK45(), None, 1e-10, True),
        ("RKMK4", jq.RKMK4(), 0.02, None, True),
        ("RKMK4", jq.RKMK4(), 0.01, None, True),
        ("RigidBodySplit", jq.RigidBodySplit(), 0.01, None, True),
        ("RigidBodySplit4", jq.RigidBodySplit4(), 0.02, None, True),
        ("RigidBodySplit4", jq.RigidBodySplit4(), 0.01, None, True),
        ("LieEuler", jq.LieEuler(), 0.001, None, True),
    ]
    print(f"T = {args.t_end:g}, float64, jax {jax.__version__}, diffrax {diffrax.__version__}")
    print("| solver | setting | steps | wall time, ms | attitude error at T, rad | abs(abs(q) - 1) at T |")
    print("|---|---|---|---|---|---|")
    for name, solver, dt, tol, lie in configs:
        q, steps, wall = run(args.t_end, solver, dt, tol, lie)
        setting = f"dt = {dt:g}" if dt else f"rtol = atol = {tol:g}"
        err = float(jq.angle_between(jq.normalize(q), q_ref))
        print(f"| {name} | {setting} | {steps} | {wall * 1e3:.1f} | {err:.2e} | {abs(float(jq.norm(q)) - 1):.1e} |")


if __name__ == "__main__":
    main()
