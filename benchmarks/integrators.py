"""Error versus work for the rigid-body solvers and diffrax's generic solvers on the raw ODE.

Problem (issue 5): I = diag(1, 2, 3), w0 = (1, 0.1, 0.5), q0 = identity, float64, torque-free.
Reference: the exact solution, jaxquat.euler_poinsot (checked against scipy DOP853 at
rtol = 1e-13 to 2e-11 rad in tests/test_torque_free.py). For each configuration: attitude
error at T, | |q| - 1 |, relative energy error, relative drift of the spatial angular
momentum, steps, and the median wall time of 3 compiled runs.

Run: .venv/bin/python benchmarks/integrators.py [--t-end 1000] [--growth] [--plot PATH]
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxquat as jq  # noqa: E402

I_DIAG = np.array([1.0, 2.0, 3.0])
W0 = np.array([1.0, 0.1, 0.5])
INERTIA = jnp.diag(jnp.asarray(I_DIAG))


def raw_field(t, y, args):
    q, w = y
    inertia = jnp.asarray(I_DIAG)
    return 0.5 * jq.multiply(q, jnp.concatenate([jnp.zeros(1), w])), jnp.cross(inertia * w, w) / inertia


def run(t_end, solver, dt=None, tol=None, lie=True, repeats=3):
    if solver == "default":  # jaxquat.simulate with no solver argument
        solve = jax.jit(lambda: jq.simulate(jq.identity(), jnp.asarray(W0), INERTIA, jnp.asarray([0.0, t_end])))
        sim, wall = _timed(solve, repeats)
        return sim.q[-1], sim.omega[-1], int(sim.solution.stats["num_steps"]), wall
    term = diffrax.ODETerm(jq.RigidBody(INERTIA) if lie else raw_field)
    controller = diffrax.ConstantStepSize() if tol is None else diffrax.PIDController(rtol=tol, atol=tol)
    steps_cap = int(round(t_end / dt)) + 10 if dt else 10_000_000

    @jax.jit
    def solve():
        sol = diffrax.diffeqsolve(
            term,
            solver,
            0.0,
            t_end,
            dt if dt else 1e-2,
            (jq.identity(), jnp.asarray(W0)),
            stepsize_controller=controller,
            max_steps=steps_cap,
        )
        return sol.ys[0][-1], sol.ys[1][-1], sol.stats["num_steps"]

    (q, w, steps), wall = _timed(solve, repeats)
    return q, w, int(steps), wall


def _timed(solve, repeats):
    jax.block_until_ready(solve())
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(solve())
        walls.append(time.perf_counter() - t0)
    return out, statistics.median(walls)


def measure(t_end, name, solver, dt, tol, lie):
    q_ref, _ = jq.euler_poinsot(jq.identity(), jnp.asarray(W0), jnp.asarray(I_DIAG), t_end)
    q, w, steps, wall = run(t_end, solver, dt, tol, lie)
    e0 = float(jq.kinetic_energy(jq.identity(), jnp.asarray(W0), INERTIA))
    h0 = np.asarray(jq.rotate(jq.identity(), INERTIA @ jnp.asarray(W0)))
    h1 = np.asarray(jq.rotate(q, INERTIA @ w))
    return dict(
        name=name,
        setting=f"dt = {dt:g}" if dt else (f"rtol = atol = {tol:g}" if tol else "simulate() defaults"),
        steps=steps,
        wall=wall,
        err=float(jq.angle_between(jq.normalize(q), q_ref)),
        norm=abs(float(jq.norm(q)) - 1),
        energy=abs(float(jq.kinetic_energy(q, w, INERTIA)) / e0 - 1),
        momentum=float(np.linalg.norm(h1 - h0) / np.linalg.norm(h0)),
    )


CURVES = [
    ("default (simulate, torque-free)", "default", True, [(None, None)]),
    ("Tsit5 (raw ODE)", diffrax.Tsit5(), False, [(None, 1e-6), (None, 1e-8), (None, 1e-10), (None, 1e-12)]),
    ("Dopri8 (raw ODE)", diffrax.Dopri8(), False, [(None, 1e-8), (None, 1e-10), (None, 1e-12)]),
    ("RKMK45", jq.RKMK45(), True, [(None, 1e-6), (None, 1e-8), (None, 1e-10), (None, 1e-12)]),
    ("RKMK4", jq.RKMK4(), True, [(0.05, None), (0.02, None), (0.01, None)]),
    ("RigidBodySplit", jq.RigidBodySplit(), True, [(0.02, None), (0.01, None), (0.005, None)]),
    ("RigidBodySplit4", jq.RigidBodySplit4(), True, [(0.05, None), (0.02, None), (0.01, None), (0.005, None)]),
    ("EulerPoinsotSplit", jq.EulerPoinsotSplit(), True, [(None, "T"), (1.0, None)]),
    ("LieEuler", jq.LieEuler(), True, [(0.001, None)]),
]


def _configs(t_end):
    for name, solver, lie, points in CURVES:
        for dt, tol in points:
            if tol == "T":
                dt, tol = t_end, None
            yield name, solver, dt, tol, lie


def table(rows):
    out = [
        "| solver | setting | steps | wall time, ms | attitude error, rad | abs(abs(q) - 1) | energy rel. "
        "error | momentum rel. drift |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        out.append(
            f"| {r['name']} | {r['setting']} | {r['steps']} | {r['wall'] * 1e3:.1f} | {r['err']:.2e} | "
            f"{r['norm']:.1e} | {r['energy']:.1e} | {r['momentum']:.1e} |"
        )
    return "\n".join(out)


def plot(rows, path, t_end):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name in dict.fromkeys(r["name"] for r in rows):
        pts = sorted((r["wall"] * 1e3, max(r["err"], 1e-16)) for r in rows if r["name"] == name)
        x, y = zip(*pts)
        style = "--" if "raw" in name else "-"
        ax.loglog(x, y, style, marker="o", label=name)
    ax.axhline(1e-6, color="grey", lw=0.5)
    ax.set_xlabel("wall time of one compiled run, ms (2-core CPU, float64)")
    ax.set_ylabel(f"attitude error at t = {t_end:g}, rad")
    ax.set_title("I = diag(1, 2, 3), w0 = (1, 0.1, 0.5), torque-free")
    ax.legend(fontsize=7)
    ax.grid(True, which="both", lw=0.2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--t-end", type=float, default=1000.0)
    parser.add_argument("--growth", action="store_true", help="also error at 10 T for the fixed-step solvers")
    parser.add_argument("--plot", default=None)
    parser.add_argument("--no-curves", action="store_true", help="skip the error-versus-work table")
    args = parser.parse_args()
    print(f"T = {args.t_end:g}, float64, jax {jax.__version__}, diffrax {diffrax.__version__}")
    rows = [] if args.no_curves else [measure(args.t_end, *c) for c in _configs(args.t_end)]
    if rows:
        print(table(rows))
    if args.plot and rows:
        plot(rows, args.plot, args.t_end)
        print(f"plot written to {args.plot}")
    if args.growth:
        print(
            "\nSplittings, saved every 1 s to T: max relative energy error over [0, T/10] and over"
            " [T/10, T] (bounded: no growth), max relative drift of the spatial angular momentum:"
        )
        print("| solver | setting | energy error, first tenth | energy error, rest | momentum drift |")
        print("|---|---|---|---|---|")
        for name, solver, dt in [
            ("RigidBodySplit", jq.RigidBodySplit(), 0.01),
            ("RigidBodySplit4", jq.RigidBodySplit4(), 0.01),
        ]:
            ts = jnp.linspace(0.0, args.t_end, int(args.t_end) + 1)
            sim = jax.jit(
                lambda s=solver, d=dt, ts=ts: jq.simulate(jq.identity(), jnp.asarray(W0), INERTIA, ts, solver=s, dt0=d)
            )()
            energy = np.asarray(jax.vmap(lambda q, w: jq.kinetic_energy(q, w, INERTIA))(sim.q, sim.omega))
            rel = np.abs(energy / energy[0] - 1)
            h = np.asarray(jq.rotate(sim.q, sim.omega @ INERTIA))
            drift = np.abs(h - h[0]).max() / np.linalg.norm(h[0])
            k = len(ts) // 10
            print(f"| {name} | dt = {dt:g} | {rel[: k + 1].max():.1e} | {rel[k:].max():.1e} | {drift:.1e} |")
        print(f"\nError growth from T = {args.t_end:g} to {10 * args.t_end:g}:")
        print(
            "| solver | setting | error at T | error at 10 T | ratio | energy rel. error at 10 T | momentum "
            "drift at 10 T |"
        )
        print("|---|---|---|---|---|---|---|")
        for name, solver, dt, tol in [
            ("RigidBodySplit4", jq.RigidBodySplit4(), 0.01, None),
            ("RigidBodySplit", jq.RigidBodySplit(), 0.01, None),
            ("RKMK4", jq.RKMK4(), 0.01, None),
            ("RKMK45", jq.RKMK45(), None, 1e-10),
            ("Tsit5 (raw ODE)", diffrax.Tsit5(), None, 1e-10),
        ]:
            lie = "raw" not in name
            a = measure(args.t_end, name, solver, dt, tol, lie)
            b = measure(10 * args.t_end, name, solver, dt, tol, lie)
            print(
                f"| {name} | {a['setting']} | {a['err']:.2e} | {b['err']:.2e} | {b['err'] / a['err']:.1f} | "
                f"{b['energy']:.1e} | {b['momentum']:.1e} |"
            )


if __name__ == "__main__":
    main()
