"""A reaction-wheel spacecraft slews its star tracker away from the Sun, in least time and then
in least fuel.

The spacecraft (inertia J without the wheels' axial inertias) is turned by three reaction wheels
on its body axes, each with a motor torque limit and a momentum (speed) limit; there is no
external torque, so the total angular momentum R(q) (J w + A h) stays what it was (zero: all at
rest). The body x axis carries a star tracker that must stay at least 20 degrees from the Sun,
and the body rates stay within a gyro limit, at every integration step. The slew is 90 degrees
about z, which would sweep the boresight through the Sun on the eigenaxis path.

`jq.minimum_time_reorientation(..., wheels=jq.ReactionWheels(...))` finds the least-time wheel
torques by direct multiple shooting and a primal-dual interior-point method;
`jq.minimum_fuel_reorientation` then finds the least fuel (sum of |wheel torque| over time) for
the same slew in 1.5 times that time. Both results are re-simulated at 10x finer steps through
`jq.ReactionWheelSpacecraft`'s own vector field to check every constraint, and the script saves
examples/out/wheel_slew.png:
- the boresight path in azimuth and elevation, with the keep-out cone and the eigenaxis path;
- the wheel torques against their limit (least time: on a limit most of the way; least fuel:
  short pulses and a long coast);
- the body rates against their limit;
- the wheel momenta against their limit.

Run: python examples/wheel_slew.py [--intervals 16] [--out examples/out]
"""

from __future__ import annotations

import argparse
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxquat as jq  # noqa: E402
from sun_avoidance import BORESIGHT, HALF, Q0, QF, SUN, plot_sky  # noqa: E402  (the same geometry)

INERTIA = np.diag([1.2, 1.0, 0.8])  # kg m^2, the spacecraft without the wheels' axial inertias
AXES = np.eye(3)  # the wheels' spin axes (rows), one per body axis
WHEEL_TORQUE, WHEEL_MOMENTUM, RATE = 0.1, 0.12, 0.15  # N m, N m s, rad/s
WHEELS = jq.ReactionWheels(AXES, WHEEL_TORQUE, momentum_limit=WHEEL_MOMENTUM)
CONSTRAINTS = dict(rate_bound=RATE, keep_out=[(BORESIGHT, SUN, HALF)], wheels=WHEELS)


def resimulate(r, substeps):
    """The returned wheel torques, held per interval, through the spacecraft model."""
    model = jq.ReactionWheelSpacecraft(INERTIA, AXES, lambda t, y, u: (u, jnp.zeros(3)))
    ts = jnp.linspace(0.0, float(r.time), r.controls.shape[0] + 1)
    y0 = {"q": jnp.asarray(Q0), "w": jnp.zeros(3), "h": jnp.zeros(3)}
    ys = jq.solve_fixed_steps(
        jq.RKMK4(quaternions=model.quaternions),
        diffrax.ODETerm(model),
        ts,
        y0,
        substeps=substeps,
        interval_args=r.controls,
    )
    momentum = jax.vmap(lambda q, w, h: model.momentum({"q": q, "w": w, "h": h}))(ys["q"], ys["w"], ys["h"])
    return {k: np.asarray(v) for k, v in ys.items()}, float(np.max(np.abs(np.asarray(momentum))))


def report(name, r, ys, drift):
    boresight = np.asarray(jax.vmap(lambda q: jq.rotate(q, jnp.asarray(BORESIGHT)))(jnp.asarray(ys["q"])))
    sep = np.degrees(np.arccos(np.clip(boresight @ SUN, -1, 1)))
    error = np.linalg.norm(np.asarray(jq.minus(jnp.asarray(ys["q"][-1]), jnp.asarray(QF))))
    print(
        f"{name}: converged {bool(r.converged)} in {int(r.iterations)} iterations, time {float(r.time):.6f} s, "
        f"cost {float(r.cost):.6f}"
    )
    print(
        f"  re-simulated at 10x finer steps: least Sun angle {sep.min():.4f} deg (limit {np.degrees(HALF):.0f}), "
        f"max rate {np.abs(ys['w']).max():.6f} (limit {RATE}), max wheel momentum {np.abs(ys['h']).max():.6f} "
        f"(limit {WHEEL_MOMENTUM}), max wheel torque {np.abs(np.asarray(r.controls)).max():.6f} (limit {WHEEL_TORQUE})"
    )
    print(f"  final attitude error {error:.2e} rad, inertial momentum (0 at the start) {drift:.1e}")
    return boresight


def solve(intervals):
    """Least time, then least fuel in 1.5 times that time, with every constraint."""
    fast = jq.minimum_time_reorientation(INERTIA, None, Q0, QF, intervals=intervals, **CONSTRAINTS)
    fuel = jq.minimum_fuel_reorientation(INERTIA, Q0, QF, 1.5 * float(fast.time), intervals=intervals, **CONSTRAINTS)
    return fast, fuel


def figure(paths):
    """One row per result ``(name, r, ys, boresight)``: the boresight on the sky with the cone, the
    wheel torques, the body rates and the wheel momenta against their limits."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(len(paths), 4, figsize=(18, 3.75 * len(paths)), squeeze=False)
    for row, (name, r, ys, boresight) in enumerate(paths):
        plot_sky(ax[row, 0], boresight, f"boresight ({name})")
        ax[row, 0].set(xlabel="azimuth (deg)", ylabel="elevation (deg)", title=name, aspect="equal")
        ax[row, 0].legend(fontsize=7, loc="lower left")
        t = np.asarray(r.ts)
        tf = np.linspace(0, float(r.time), len(ys["w"]))
        for i, c in enumerate("rgb"):
            ax[row, 1].step(t, np.asarray(r.torque)[:, i], where="post", color=c, label=f"wheel {i + 1}")
            ax[row, 2].plot(tf, ys["w"][:, i], color=c, label=f"w{i + 1}")
            ax[row, 3].plot(tf, ys["h"][:, i], color=c, label=f"wheel {i + 1}")
        limits = (
            (1, WHEEL_TORQUE, "wheel torque (N m)"),
            (2, RATE, "body rate (rad/s)"),
            (3, WHEEL_MOMENTUM, "wheel momentum (N m s)"),
        )
        for k, lim, label in limits:
            ax[row, k].axhline(lim, color="k", ls="--", lw=0.8)
            ax[row, k].axhline(-lim, color="k", ls="--", lw=0.8)
            ax[row, k].set(xlabel="t (s)", ylabel=label)
            ax[row, k].legend(fontsize=7)
    fig.tight_layout()
    return fig


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--intervals", type=int, default=16)
    ap.add_argument("--out", default="examples/out")
    a = ap.parse_args()
    paths = []
    for name, r in zip(("least time", "least fuel"), solve(a.intervals)):
        ys, drift = resimulate(r, 40)
        paths.append((name, r, ys, report(name, r, ys, drift)))

    import matplotlib

    matplotlib.use("Agg")
    fig = figure(paths)
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "wheel_slew.png", dpi=100)
    print(f"saved {out / 'wheel_slew.png'}")


if __name__ == "__main__":
    main()
