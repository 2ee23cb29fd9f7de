"""Minimum-time slews: jaxquat's multiple-shooting interior point against CasADi + IPOPT.

Both solve the same transcription: direct multiple shooting, torque held on N intervals, 4
integration steps per interval (jaxquat: RKMK4 on the group; CasADi: classical RK4 on the
quaternion ODE, the setup of the issue), free final time, terminal conditions
``vec(qf* q_N) = 0, w_N = 0``, the same eigenaxis initial guess, KKT tolerance 1e-9 (IPOPT's
``tol``). Problems: Bilimoria & Wie's 180 degrees about x (J = I, |u_i| <= 1; continuous optimum
3.24308) and Betts' asyq01 (J = diag(5621, 4547, 2364), |u_i| <= 50, 150 degrees about x;
28.6304). Times are medians after compilation; jaxquat's compile time is reported apart.
A third problem turns Bilimoria & Wie's body by three reaction wheels whose momenta are bounded
at every integration step. Then 100 different slews (random axes, 150 degrees, asyq01's body)
in one batched call.

Run: python benchmarks/optimal_control.py [--write docs/benchmarks.md]   (casadi: `make bench`)
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxquat as jq  # noqa: E402
from _report import machine, median_time, write_section  # noqa: E402

PROBLEMS = {
    "Bilimoria-Wie 180 deg": (np.eye(3), np.ones(3), np.pi, 80, 3.24308),
    "Betts asyq01": (np.diag([5621.0, 4547.0, 2364.0]), np.full(3, 50.0), np.deg2rad(150.0), 120, 28.6304),
}
# Bilimoria-Wie turned by three reaction wheels on the body axes (wheel torque |u_i| <= 1, the
# body torque being -u) whose momenta must stay within 1.5 at every integration step (the free
# optimum's wheels reach 1.63): (momentum limit, intervals). No published value.
WHEEL_PROBLEM = ("Bilimoria-Wie by 3 wheels, momentum <= 1.5", 1.5, 80)


def _guess(inertia, bound, theta, n):
    """jaxquat's own initial guess (the perturbed eigenaxis bang-bang profile), in physical units,
    so that both solvers start from the same point: ``(T, X (n+1, 7), U (n, 3))``."""
    from jaxquat.control import optimal_control as oc
    from jaxquat.control import transcription as tr

    q0, qf = jnp.asarray([1.0, 0, 0, 0]), jnp.asarray([np.cos(theta / 2), np.sin(theta / 2), 0, 0])
    zero = jnp.zeros(3)
    T, u_ref, w_ref = oc.scales(jnp.asarray(inertia), q0, qf, zero, zero, jnp.asarray(bound), min_time=True)
    cfg = tr.Config(n, 4, True, True, False, 0)
    data = tr.Data(
        jnp.asarray(inertia),
        q0,
        zero,
        qf,
        zero,
        T,
        u_ref,
        w_ref,
        jnp.asarray(jnp.inf),
        jnp.zeros((0, 8)),
        jnp.asarray([1.0, 0.0, 0.0]),
        jnp.full(n, 1.0 / n),
        jnp.zeros((0, 3)),
        jnp.zeros(0),
        jnp.asarray(1.0),
        jnp.zeros(0),
    )
    X, V = tr.initial_guess(cfg, data)
    X = np.concatenate([[[1.0, 0, 0, 0, 0, 0, 0]], np.asarray(X)])
    X[:, 4:] *= float(w_ref)
    return float(T), X, np.asarray(V) * np.asarray(u_ref)


def casadi_solve(inertia, bound, theta, n, substeps=4, momentum_limit=None):
    """IPOPT on the same transcription; with ``momentum_limit`` the spacecraft is turned by three
    wheels on its body axes (state ``(q, w, h)``, ``J w' = -u - w x (J w + h)``, ``h' = u``, the
    wheel momenta bounded at every RK4 step's end, the final ones free)."""
    import casadi as ca

    J, Jinv = ca.DM(inertia), ca.DM(np.linalg.inv(inertia))
    wheels = momentum_limit is not None
    nx = 10 if wheels else 7

    def f(x, u):
        q, w = x[:4], x[4:7]
        qdot = 0.5 * ca.vertcat(-ca.dot(q[1:], w), q[0] * w + ca.cross(q[1:], w))
        if not wheels:
            return ca.vertcat(qdot, Jinv @ (u - ca.cross(w, J @ w)))
        h = x[7:]
        return ca.vertcat(qdot, Jinv @ (-u - ca.cross(w, J @ w + h)), u)

    opti = ca.Opti()
    X, U, T = opti.variable(nx, n + 1), opti.variable(3, n), opti.variable()
    h = T / n / substeps
    for k in range(n):
        x = X[:, k]
        for _ in range(substeps):
            k1 = f(x, U[:, k])
            k2 = f(x + h / 2 * k1, U[:, k])
            k3 = f(x + h / 2 * k2, U[:, k])
            k4 = f(x + h * k3, U[:, k])
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            if wheels:
                opti.subject_to(opti.bounded(-momentum_limit, x[7:], momentum_limit))
        opti.subject_to(X[:, k + 1] == x)
    qf = np.array([np.cos(theta / 2), np.sin(theta / 2), 0, 0])
    opti.subject_to(X[:, 0] == np.zeros(nx) + np.eye(nx)[0])
    qN = X[:4, n]
    opti.subject_to(ca.vertcat(qf[0] * qN[1:] - qN[0] * qf[1:] - ca.cross(qf[1:], qN[1:]), X[4:7, n]) == 0)
    opti.subject_to(opti.bounded(-bound[0], U, bound[0]))
    opti.subject_to(T >= 0.05)
    opti.minimize(T)
    T0, X0, U0 = _guess(inertia, bound, theta, n)
    if wheels:  # at rest the total momentum J w + h stays 0: the wheels carry -J w and torque -u
        X0 = np.concatenate([X0, -X0[:, 4:7] @ np.asarray(inertia).T], axis=1)
        U0 = -U0
    opti.set_initial(T, T0)
    opti.set_initial(X, X0.T)
    opti.set_initial(U, U0.T)
    opti.solver("ipopt", {"print_time": False}, {"print_level": 0, "tol": 1e-9, "sb": "yes"})

    def run():
        return float(opti.solve().value(T))

    return run


def jaxquat_solve(inertia, bound, theta, n, momentum_limit=None):
    # starts=1: IPOPT solves from one start, the same eigenaxis guess (the default is 8 starts).
    qf = jnp.asarray([np.cos(theta / 2), np.sin(theta / 2), 0, 0])
    if momentum_limit is None:
        return lambda: jq.constrained_minimum_time(inertia, bound, jq.identity(), qf, intervals=n, starts=1)
    wheels = jq.ReactionWheels(np.eye(3), bound[0], momentum_limit=momentum_limit)
    return lambda: jq.constrained_minimum_time(inertia, None, jq.identity(), qf, intervals=n, starts=1, wheels=wheels)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--write", help="markdown file whose 'optimal-control' section to rewrite")
    ap.add_argument("--no-batch", action="store_true", help="skip the 100-slew batch")
    a = ap.parse_args()
    rows, ipopt_seconds = [], []
    try:
        import casadi  # noqa: F401

        have_casadi = True
    except ImportError:
        have_casadi = False
    wheel_name, limit, wheel_n = WHEEL_PROBLEM
    cases = [(name, *spec, None) for name, spec in PROBLEMS.items()]
    cases.append((wheel_name, *PROBLEMS["Bilimoria-Wie 180 deg"][:3], wheel_n, None, limit))
    for name, inertia, bound, theta, n, published, momentum_limit in cases:
        fn = jaxquat_solve(inertia, bound, theta, n, momentum_limit)
        t0 = time.perf_counter()
        r = jax.block_until_ready(fn())
        first = time.perf_counter() - t0
        t_jq = median_time(fn, repeats=5, warmup=1, max_seconds=20)
        row = [name, str(n), f"{float(r.time):.6f}", f"{int(r.iterations)}", f"{t_jq:.2f} s", f"{first:.1f} s"]
        if have_casadi:
            cs = casadi_solve(inertia, bound, theta, n, momentum_limit=momentum_limit)
            t_cs_first = time.perf_counter()
            T_cs = cs()
            t_cs_first = time.perf_counter() - t_cs_first
            times = []
            for _ in range(3):
                t0 = time.perf_counter()
                cs()
                times.append(time.perf_counter() - t0)
            t_cs = float(np.median(times))
            ipopt_seconds.append(t_cs)
            row += [f"{T_cs:.6f}", f"{t_cs:.2f} s", f"{t_cs / t_jq:.1f}x"]
        else:
            row += ["not installed"] * 3
        row.insert(3, "-" if published is None else f"{abs(float(r.time) / published - 1) * 100:.3f} %")
        rows.append(row)
        print(" | ".join(row), flush=True)

    # IPOPT's figure for the same accuracy: its uniform 80-interval Bilimoria-Wie solve (the first row).
    aligned_line = _aligned(ipopt_seconds[0] if have_casadi else None)
    batch_line = ""
    if not a.no_batch:
        batch_line = _batch()
    header = (
        "| problem | N | jaxquat T | vs published | iterations | jaxquat solve | jaxquat first call (compile) "
        "| IPOPT T | IPOPT solve | IPOPT / jaxquat |\n|" + "---|" * 10
    )
    md = (
        f"Machine: {machine()}.\n\n"
        + header
        + "\n"
        + "\n".join("| " + " | ".join(r) + " |" for r in rows)
        + "\n\n"
        + aligned_line
        + "\n\n"
        + batch_line
        + "\n"
    )
    if a.write:
        write_section(a.write, "optimal-control", "## Minimum-time slews against CasADi + IPOPT\n\n" + md)


def _aligned(ipopt_uniform: float | None = None) -> str:
    # Bilimoria-Wie on a mesh aligned with its switches (jq.align_mesh): the 10-interval optimum
    # (8 starts: from one start the 10-interval solve reaches another local optimum, whose aligned
    # refinement converged to 3.2432145), then three solves on 14 intervals with a node at each
    # switch.
    inertia, bound, theta, _, published = PROBLEMS["Bilimoria-Wie 180 deg"]
    qf = jnp.asarray([np.cos(theta / 2), np.sin(theta / 2), 0, 0])

    def pipeline():
        r = jq.constrained_minimum_time(inertia, bound, jq.identity(), qf, intervals=10, starts=8)
        for _ in range(3):
            mesh = jq.align_mesh(r, intervals=14)
            r = jq.constrained_minimum_time(inertia, bound, jq.identity(), qf, mesh=mesh, starts=1, init=r)
        return r

    t0 = time.perf_counter()
    r = jax.block_until_ready(pipeline())
    first = time.perf_counter() - t0
    t = median_time(pipeline, repeats=3, warmup=0, max_seconds=20)
    line = (
        f"Bilimoria-Wie on a mesh aligned with its switches (`align_mesh`: 10 uniform intervals, 8 starts, then "
        f"three solves on 14 with a node at each switch): T = {float(r.time):.7f} "
        f"({abs(float(r.time) / published - 1) * 100:.4f} % from the published value), all four solves "
        f"{t:.2f} s after compilation (first call {first:.1f} s: three configurations)."
    )
    if ipopt_uniform is not None:
        line += (
            f" IPOPT in this run needed 80 uniform intervals for 3.243096 (0.0005 %), in {ipopt_uniform:.2f} s: "
            f"{ipopt_uniform / t:.1f}x the aligned pipeline's time."
        )
    print(line)
    return line


def _batch() -> str:
    # 100 different slews in one batched call (asyq01's body and bound, 150 degrees about random axes).
    inertia, bound, theta, _, _ = PROBLEMS["Betts asyq01"]
    n = 40
    axes = np.random.default_rng(0).normal(size=(100, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    qfs = jnp.asarray(np.concatenate([np.full((100, 1), np.cos(theta / 2)), np.sin(theta / 2) * axes], axis=1))

    def batch():
        return jq.constrained_minimum_time(
            inertia, bound, jnp.asarray([1.0, 0, 0, 0]), qfs, intervals=n, throw=False, starts=1
        )

    def one():
        return jq.constrained_minimum_time(inertia, bound, jnp.asarray([1.0, 0, 0, 0]), qfs[0], intervals=n, starts=1)

    t_one = median_time(one, repeats=3, warmup=1, max_seconds=20)
    rb = jax.block_until_ready(batch())
    t_batch = median_time(batch, repeats=2, warmup=0, max_seconds=60)
    conv = int(np.sum(np.asarray(rb.converged)))
    batch_line = (
        f"100 slews in one call (asyq01 body, 150 deg about random axes, {n} intervals): {t_batch:.2f} s "
        f"against {t_one:.2f} s for one ({t_batch / t_one:.1f}x); {conv} of 100 converged, "
        f"iterations {int(np.min(rb.iterations))}-{int(np.max(rb.iterations))}."
    )
    print(batch_line)
    return batch_line


if __name__ == "__main__":
    main()
