"""A star-tracker slew that keeps the boresight out of the Sun, within rate and torque limits.

The body x axis carries a star tracker. The slew is 90 degrees about z in 3 s (unit inertia),
so the eigenaxis rotation would sweep the boresight through the Sun direction, 45 degrees along
the way in the xy plane. `jq.minimum_energy_reorientation` finds the least-energy torque that
keeps the boresight at least 20 degrees from the Sun, the body rates within 0.7 rad/s and each
torque within 1.2, all at every integration step, by direct multiple shooting and a primal-dual
interior-point method.

The result is re-simulated at 10x finer steps to check every constraint. The script prints the
cost against the eigenaxis slew's closed-form 12 theta^2 / T^3 and saves
examples/out/sun_avoidance.png. The figure shows three panels:
- the boresight path in azimuth and elevation, with the keep-out cone and the eigenaxis path;
- the torque against its limit;
- the rates against their limit.

Run: python examples/sun_avoidance.py [--intervals 12] [--out examples/out]
"""

from __future__ import annotations

import argparse
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxquat as jq  # noqa: E402

Q0 = np.array([1.0, 0.0, 0.0, 0.0])
QF = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])  # 90 degrees about z
DURATION = 3.0
BORESIGHT = np.array([1.0, 0.0, 0.0])
SUN = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
HALF = np.deg2rad(20.0)
RATE, TORQUE = 0.7, np.array([1.2, 1.2, 1.2])


def resimulate(controls, time, substeps):
    def field(t, y, u):
        return y[1], u - jnp.cross(y[1], y[1])  # unit inertia

    ts = jnp.linspace(0.0, time, controls.shape[0] + 1)
    return jq.solve_fixed_steps(
        jq.RKMK4(),
        jq.BodyRateTerm(field),
        ts,
        (jnp.asarray(Q0), jnp.zeros(3)),
        substeps=substeps,
        interval_args=controls,
    )


def plot_sky(ax, boresight, label):
    """The boresight path in azimuth and elevation, the eigenaxis path (the equator from 0 to 90
    degrees) and the Sun keep-out cone, filled (shared with examples/wheel_slew.py)."""
    az, el = np.degrees(np.arctan2(boresight[:, 1], boresight[:, 0])), np.degrees(np.arcsin(boresight[:, 2]))
    ax.plot(az, el, label=label)
    ax.plot([0, 90], [0, 0], "k:", label="eigenaxis path")
    # The cone boundary: directions at HALF from the Sun.
    e1 = np.array([0.0, 0.0, 1.0])
    e2 = np.cross(SUN, e1)
    phi = np.linspace(0, 2 * np.pi, 200)
    ring = np.cos(HALF) * SUN[None] + np.sin(HALF) * (np.cos(phi)[:, None] * e1[None] + np.sin(phi)[:, None] * e2[None])
    ax.fill(
        np.degrees(np.arctan2(ring[:, 1], ring[:, 0])),
        np.degrees(np.arcsin(ring[:, 2])),
        color="orange",
        alpha=0.4,
        label=f"Sun keep-out ({np.degrees(HALF):.0f} deg)",
    )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--intervals", type=int, default=12)
    ap.add_argument("--out", default="examples/out")
    a = ap.parse_args()
    r = jq.minimum_energy_reorientation(
        np.eye(3),
        Q0,
        QF,
        DURATION,
        torque_bound=TORQUE,
        rate_bound=RATE,
        keep_out=[(BORESIGHT, SUN, HALF)],
        intervals=a.intervals,
    )
    qs, ws = (np.asarray(x) for x in resimulate(r.controls, float(r.time), 40))
    boresight = np.asarray(jax.vmap(lambda q: jq.rotate(q, jnp.asarray(BORESIGHT)))(jnp.asarray(qs)))
    sep = np.degrees(np.arccos(np.clip(boresight @ SUN, -1, 1)))
    print(f"converged {bool(r.converged)} in {int(r.iterations)} iterations, KKT residual {float(r.kkt_residual):.1e}")
    print(f"energy {float(r.cost):.10f} (eigenaxis slew through the Sun: {12 * (np.pi / 2) ** 2 / DURATION**3:.6f})")
    print(
        f"re-simulated at 10x finer steps: least Sun angle {sep.min():.4f} deg (limit {np.degrees(HALF):.1f}), "
        f"max rate {np.abs(ws).max():.6f} rad/s (limit {RATE}), max torque {np.abs(np.asarray(r.controls)).max():.6f} "
        f"(limit {TORQUE[0]})"
    )
    print(f"final attitude error {np.linalg.norm(np.asarray(jq.minus(jnp.asarray(qs[-1]), jnp.asarray(QF)))):.2e} rad")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    plot_sky(ax[0], boresight, "boresight (optimal)")
    ax[0].set(xlabel="azimuth (deg)", ylabel="elevation (deg)", title="boresight on the sky", aspect="equal")
    ax[0].legend(fontsize=8, loc="lower left")
    t = np.asarray(r.ts)
    for i, c in enumerate("rgb"):
        ax[1].step(t, np.asarray(r.torque)[:, i], where="post", color=c, label=f"u{i + 1}")
        ax[2].plot(np.linspace(0, float(r.time), len(ws)), ws[:, i], color=c, label=f"w{i + 1}")
    for axis, lim, name in ((ax[1], TORQUE[0], "torque"), (ax[2], RATE, "rate (rad/s)")):
        axis.axhline(lim, color="k", ls="--", lw=0.8)
        axis.axhline(-lim, color="k", ls="--", lw=0.8)
        axis.set(xlabel="t (s)", ylabel=name)
        axis.legend(fontsize=8)
    fig.tight_layout()
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "sun_avoidance.png", dpi=110)
    print(f"saved {out / 'sun_avoidance.png'}")


if __name__ == "__main__":
    main()
