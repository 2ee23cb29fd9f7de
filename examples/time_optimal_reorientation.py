"""Time-optimal 180-degree rest-to-rest reorientation of an inertially symmetric spacecraft.

The problem of Bilimoria and Wie (J. Guidance, Control, and Dynamics 16(3), 1993):
J = I, independent torque bounds |u_i| <= 1 on the body axes, a rest-to-rest rotation
by 180 degrees about the body x axis. The eigenaxis manoeuvre (bang-bang about x)
takes 2 sqrt(pi); the time-optimal one is not an eigenaxis rotation and is shorter.

Solved with jaxquat.minimum_time_reorientation (free final time, torque held on equal
intervals, RKMK4 steps; by default direct multiple shooting and a primal-dual interior-point
method, 8 starts side by side: the perturbed eigenaxis bang-bang profile and 7 further
perturbations of it; the 180-degree problem has several local optima). The shortest converged
start is then refined by warm starts on 2x and 4x as many intervals, to show the time has
converged. `--method single_shooting` runs the augmented-Lagrangian L-BFGS solver instead
(`--outer`, `--inner`). No published value is used anywhere.

Prints each level's time, terminal violation and change, then the violation and, as
its last line, `minimum time: <T>`. The certificate line checks the discrete minimum
principle (every control with a non-zero switching function on its bound, at -b sign(sigma)).
Saves examples/out/time_optimal_reorientation.png (torque, rates, and the switching function
against the torque).

Run: python examples/time_optimal_reorientation.py [--intervals 30] [--levels 3] [--starts 8]
     [--method interior_point|single_shooting] [--outer 10] [--inner 200] [--no-progress]
     [--out examples/out]
"""

from __future__ import annotations

import argparse
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxquat as jq  # noqa: E402

THETA = np.pi
AXIS = np.array([1.0, 0.0, 0.0])


def saturated_fraction(result, bound=1.0, level=0.99):
    """Fraction of (interval, axis) torque values at the bound: bang-bang structure."""
    u = np.abs(np.asarray(result.controls)) / bound
    return float(np.mean(u > level))


def certificate(result, bound=1.0, level=1e-6):
    """The discrete minimum principle on the converged solution: every control whose switching
    function sigma = d(costate . F)/du is non-zero sits on its bound, at u = -b sign(sigma) for
    the multiple-shooting KKT conditions. Returns (non-zero sigma, of those on the bound, of those
    with the sign of -sigma)."""
    sigma, u = np.asarray(result.switching), np.asarray(result.controls) / bound
    active = np.abs(sigma) > level * np.max(np.abs(sigma))
    on_bound = np.abs(np.abs(u[active]) - 1) < level
    signs = np.sign(u[active]) == -np.sign(sigma[active])
    return int(active.sum()), int(on_bound.sum()), int(signs.sum())


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--intervals", type=int, default=30)
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--starts", type=int, default=8)
    ap.add_argument("--method", default="interior_point", choices=["interior_point", "single_shooting"])
    ap.add_argument("--outer", type=int, default=10)
    ap.add_argument("--inner", type=int, default=200)
    ap.add_argument("--refine-outer", type=int, default=6)
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--out", default="examples/out")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    inertia, bound = jnp.eye(3), jnp.ones(3)
    q0, qf = jq.identity(), jq.from_axis_angle(jnp.asarray(AXIS), THETA)
    eigenaxis = 2 * np.sqrt(THETA)  # bang-bang about x: theta/2 = (T/2)^2 / 2 with unit acceleration
    progress = not args.no_progress
    single = args.method == "single_shooting"
    options = dict(outer=args.outer, inner=args.inner, progress=progress) if single else {}

    result = jq.minimum_time_reorientation(
        inertia, bound, q0, qf, intervals=args.intervals, starts=args.starts, method=args.method, **options
    )
    times = np.asarray(result.start_times if single else result.start_costs)
    feasible = times[np.isfinite(times)]
    print(
        f"{args.starts} starts on {args.intervals} intervals ({args.method}): {feasible.size} converged; "
        f"times {np.array2string(np.sort(feasible), precision=5, separator=', ')}"
    )
    if single:
        options["outer"] = args.refine_outer
    levels = [result]
    for k in range(1, args.levels):
        n = args.intervals * 2**k
        refined = jq.minimum_time_reorientation(
            inertia, bound, q0, qf, intervals=n, starts=1, init=levels[-1], method=args.method, **options
        )
        levels.append(refined)
    wall = time.perf_counter() - t0

    print(f"eigenaxis bang-bang time 2 sqrt(pi) = {eigenaxis:.6f}")
    print("intervals  time        violation  change from previous  saturated")
    for k, r in enumerate(levels):
        change = "" if k == 0 else f"{100 * (float(r.time) / float(levels[k - 1].time) - 1):+.4f} %"
        print(
            f"{args.intervals * 2**k:9d}  {float(r.time):.8f}  {float(r.violation):.1e}  {change:>20}  "
            f"{100 * saturated_fraction(r):.0f} %"
        )
    best = levels[-1]
    print(
        f"{100 * (1 - float(best.time) / eigenaxis):.2f} % shorter than the eigenaxis manoeuvre; wall time {wall:.1f} s"
    )

    active, on_bound, signs = certificate(best)
    print(
        f"certificate: {active} of {best.switching.size} controls have a non-zero switching function; "
        f"{on_bound} of them on the bound" + ("" if single else f", {signs} at -b sign(sigma)")
    )

    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ts = np.asarray(best.ts)
    fig, (a1, a2, a3) = plt.subplots(1, 3, figsize=(14, 3.5))
    edges = ts[:: (ts.shape[0] - 1) // best.controls.shape[0]]
    sigma = np.asarray(best.switching) / np.max(np.abs(np.asarray(best.switching)))
    for i, name in enumerate("xyz"):
        a1.step(ts, np.asarray(best.torque)[:, i], where="post", label=f"u_{name}")
        a2.plot(ts, np.asarray(best.omega)[:, i], label=f"omega_{name}")
        line = a3.step(edges, np.append(-sigma[:, i], -sigma[-1, i]), where="post", label=f"-sigma_{name}")
        a3.step(
            edges, np.append(best.controls[:, i], best.controls[-1, i]), where="post", ls=":", c=line[0].get_color()
        )
    a1.set_xlabel("t")
    a1.set_ylabel("body torque")
    a1.legend(fontsize=7)
    a2.set_xlabel("t")
    a2.set_ylabel("body rate")
    a2.legend(fontsize=7)
    a3.set_xlabel("t")
    a3.set_ylabel("-sigma / max|sigma| (solid), u / b (dotted)")
    a3.legend(fontsize=7)
    fig.suptitle(f"time-optimal 180 deg reorientation, J = I: T = {float(best.time):.5f}")
    fig.tight_layout()
    path = out / "time_optimal_reorientation.png"
    fig.savefig(path, dpi=100)
    print(f"figure: {path}")
    print(f"terminal constraint violation: {float(best.violation):.2e}")
    print(f"minimum time: {float(best.time):.6f}")
    return levels


if __name__ == "__main__":
    main()
