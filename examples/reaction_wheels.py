"""A spacecraft slewed by four reaction wheels, integrated on the quaternion group.

The model is `jq.ReactionWheelSpacecraft` (a gyrostat; state {q, w, h} with h the wheels'
axial momenta) with four wheels in a pyramid, wheel torque and wheel momentum limits. The
controller is a PD law on the quaternion error with gyroscopic compensation, mapped to the
wheels by the pseudo-inverse of the axis matrix; the limits clip what it asks for. No external
torque acts, so the total angular momentum in the inertial frame, R(q) (J w + A h), must stay
constant whatever the wheels do. Integrated with `jq.RKMK45(quaternions=...)` and diffrax's PID
step control, against scipy's DOP853 at rtol = atol = 1e-13 on the raw ODE (q as four numbers).
Saves a figure of the slew (attitude error, rates, wheel torques and momenta against their
limits, momentum drift) to examples/out/reaction_wheels.png.

Run: python examples/reaction_wheels.py [--t-end 120] [--out examples/out]
"""

from __future__ import annotations

import argparse
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

import jaxquat as jq  # noqa: E402

J = jnp.asarray([[120.0, 2.0, -1.0], [2.0, 100.0, 1.5], [-1.0, 1.5, 80.0]])  # kg m^2, wheels' axial part removed
TILT = np.arccos(1 / np.sqrt(3))  # pyramid: each axis 54.7 deg from the body z axis
AXES = jnp.asarray(
    [
        [np.sin(TILT) * np.cos(a), np.sin(TILT) * np.sin(a), np.cos(TILT)]
        for a in np.radians([45.0, 135.0, 225.0, 315.0])
    ]
)
TORQUE_LIMIT, MOMENTUM_LIMIT = 0.2, 2.2  # N m, N m s per wheel
TARGET = jq.from_axis_angle(jnp.asarray([1.0, -1.0, 0.5]), jnp.radians(120.0))
KP, KD = 0.6, 6.0
TOL = 1e-10
KEYS = ("q", "w", "h")


def control(t, y, args):
    """Body torque wanted: ``-KP vec(q_err) - KD w + w x (J w + A h)`` (the last term cancels the
    gyroscopic coupling); the wheels supply ``-A u``, so ``u = -A^+ tau``."""
    err = jq.multiply(jq.conjugate(TARGET), y["q"])
    err = jnp.where(err[0] < 0, -err, err)
    total = J @ y["w"] + y["h"] @ AXES
    tau = -KP * err[1:] - KD * y["w"] + jnp.cross(y["w"], total)
    u = -jnp.linalg.pinv(AXES.T) @ tau
    return u, jnp.zeros(3)


MODEL = jq.ReactionWheelSpacecraft(
    J, AXES, control, wheel_torque_limit=TORQUE_LIMIT, wheel_momentum_limit=MOMENTUM_LIMIT
)
Y0 = {"q": jnp.asarray([1.0, 0.0, 0.0, 0.0]), "w": jnp.asarray([0.01, -0.02, 0.015]), "h": jnp.zeros(4)}


@jax.jit
def slew(ts):
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(MODEL),
        jq.RKMK45(quaternions=MODEL.quaternions),
        0.0,
        ts[-1],
        0.1,
        Y0,
        stepsize_controller=diffrax.PIDController(rtol=TOL, atol=TOL),
        saveat=diffrax.SaveAt(ts=ts),
        max_steps=100_000,
    )
    return sol.ys, sol.stats["num_steps"]


def reference(ts):
    """DOP853 on the raw ODE (the same field, q as a plain 4-vector), rtol = atol = 1e-13."""
    field = jax.jit(
        lambda t, x: jnp.concatenate([MODEL(t, dict(zip(KEYS, jnp.split(x, [4, 7]))), None)[k] for k in KEYS])
    )
    x0 = np.concatenate([np.asarray(Y0[k]) for k in KEYS])
    sol = solve_ivp(
        lambda t, x: np.asarray(field(t, x)),
        (0.0, float(ts[-1])),
        x0,
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
        t_eval=np.asarray(ts),
    )
    return dict(zip(KEYS, np.split(sol.y.T, [4, 7], axis=1)))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--t-end", type=float, default=120.0)
    ap.add_argument("--out", default="examples/out")
    opts = ap.parse_args(argv)
    ts = jnp.linspace(0.0, opts.t_end, 601)
    ys, steps = slew(ts)
    ref = reference(ts)
    momentum = jax.vmap(lambda q, w, h: MODEL.momentum({"q": q, "w": w, "h": h}))(ys["q"], ys["w"], ys["h"])
    drift = float(jnp.max(jnp.linalg.norm(momentum - momentum[:1], axis=-1)) / jnp.linalg.norm(momentum[0]))
    q_ref = jnp.asarray(ref["q"] / np.linalg.norm(ref["q"], axis=-1, keepdims=True))
    att = float(jnp.max(jq.angle_between(ys["q"], q_ref)))
    wheel = float(np.max(np.abs(np.asarray(ys["h"]) - ref["h"])))
    u = jax.vmap(lambda t, q, w, h: MODEL(t, {"q": q, "w": w, "h": h}, None)["h"])(ts, ys["q"], ys["w"], ys["h"])
    pointing = np.degrees(np.asarray(jq.angle_between(ys["q"], jnp.broadcast_to(TARGET, ys["q"].shape))))
    print(f"slew of 120 deg to t = {opts.t_end:g} s, RKMK45 at rtol = atol = {TOL:g}: {int(steps)} steps")
    print(f"pointing error at the end {pointing[-1]:.2e} deg (start {pointing[0]:.1f} deg)")
    print(f"against DOP853 at 1e-13: attitude error {att:.2e} rad, wheel momentum error {wheel:.2e} N m s")
    print(f"relative drift of the inertial angular momentum {drift:.2e}")
    print(f"max ||q| - 1| {float(jnp.max(jnp.abs(jq.norm(ys['q']) - 1))):.1e}")
    print(
        f"max wheel torque {float(jnp.max(jnp.abs(u))):.9f} N m (limit {TORQUE_LIMIT}), "
        f"max wheel momentum {float(jnp.max(jnp.abs(ys['h']))):.9f} N m s (limit {MOMENTUM_LIMIT})"
    )
    out = pathlib.Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    axes[0, 0].semilogy(ts, pointing + 1e-12)
    axes[0, 0].set_ylabel("angle to target, deg")
    axes[0, 1].plot(ts, ys["w"], label=["w_x", "w_y", "w_z"])
    axes[0, 1].set_ylabel("body rate, rad/s")
    axes[0, 1].legend()
    axes[1, 0].plot(ts, u)
    axes[1, 0].axhline(TORQUE_LIMIT, color="k", ls="--", lw=0.8)
    axes[1, 0].axhline(-TORQUE_LIMIT, color="k", ls="--", lw=0.8)
    axes[1, 0].set_ylabel("wheel torque, N m")
    axes[1, 1].plot(ts, ys["h"])
    axes[1, 1].axhline(MOMENTUM_LIMIT, color="k", ls="--", lw=0.8)
    axes[1, 1].axhline(-MOMENTUM_LIMIT, color="k", ls="--", lw=0.8)
    axes[1, 1].set_ylabel("wheel momentum, N m s")
    for ax in axes[1]:
        ax.set_xlabel("t, s")
    fig.suptitle(f"Reaction-wheel slew; inertial momentum drift {drift:.1e} (relative)")
    fig.tight_layout()
    fig.savefig(out / "reaction_wheels.png", dpi=110)
    print(f"figure: {out / 'reaction_wheels.png'}")


if __name__ == "__main__":
    main()
