"""A quadrotor flown by a simple attitude controller, integrated on the quaternion group.

The model is `jq.Quadrotor` (thrust along body z, linear drag, state {r, v, q, w}); the
controller holds a yawing attitude schedule with a PD law on the quaternion error, sets the
thrust to climb to 1 m, and a time-varying gust torque pushes the body about. The whole state
is integrated by `jq.RKMK45(quaternions=jq.Quadrotor.quaternions)` (a Lie solver: q advances
by Exp of the body rate, |q| = 1 to rounding) with diffrax's PID step control, and compared
with scipy's DOP853 at rtol = atol = 1e-13 on the raw 13-dimensional ODE (q as four numbers)
and with diffrax's Tsit5 on that raw ODE at the same tolerance (|q| drifts there).

Run: python examples/quadrotor.py [--t-end 10] [--out examples/out]
"""

from __future__ import annotations

import argparse
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

import jaxquat as jq  # noqa: E402

MASS = 1.2
INERTIA = jnp.diag(jnp.asarray([0.02, 0.03, 0.05]))
KEYS = ("r", "v", "q", "w")
TOL = 1e-10


def control(t, y, args):
    """Yaw schedule psi(t) = 0.6 sin(0.5 t) with small roll/pitch commands; PD on the
    quaternion error (body frame); thrust for a 1 m climb, divided by the tilt cosine; gust
    torque 0.02 (sin 3t, cos 2t, 0.5 sin t)."""
    target = jq.from_euler(jnp.stack([0.6 * jnp.sin(0.5 * t), 0.15 * jnp.sin(t), 0.1 * jnp.cos(0.7 * t)]), "ZYX")
    err = jq.multiply(jq.conjugate(target), y["q"])  # body relative to the target
    err = jnp.where(err[0] < 0, -err, err)
    torque = -0.8 * err[1:] - 0.12 * y["w"]
    gust = 0.02 * jnp.stack([jnp.sin(3 * t), jnp.cos(2 * t), 0.5 * jnp.sin(t)])
    up = jq.rotate(y["q"], jnp.asarray([0.0, 0.0, 1.0]))[2]
    climb = 9.81 + 2.0 * (1.0 - y["r"][2]) - 1.6 * y["v"][2]
    thrust = MASS * climb / jnp.clip(up, 0.5, 1.0)
    return thrust, torque + gust


MODEL = jq.Quadrotor(MASS, INERTIA, control, drag=0.3)
Y0 = {
    "r": jnp.zeros(3),
    "v": jnp.asarray([1.0, 0.0, 0.5]),
    "q": jq.from_rotvec(jnp.asarray([0.3, -0.2, 0.1])),
    "w": jnp.asarray([2.0, -1.0, 3.0]),
}


def solve(solver, t_end, ts):
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(MODEL),
        solver,
        0.0,
        t_end,
        1e-3,
        Y0,
        stepsize_controller=diffrax.PIDController(rtol=TOL, atol=TOL),
        saveat=diffrax.SaveAt(ts=ts),
        max_steps=200_000,
    )
    return sol.ys, sol.stats["num_steps"]


def reference(t_end, ts):
    """DOP853 on the raw ODE (the same field, q as a plain 4-vector), rtol = atol = 1e-13."""
    field = jax.jit(
        lambda t, x: jnp.concatenate([MODEL(t, dict(zip(KEYS, jnp.split(x, [3, 6, 10]))), None)[k] for k in KEYS])
    )
    x0 = np.concatenate([np.asarray(Y0[k]) for k in KEYS])
    sol = solve_ivp(
        lambda t, x: np.asarray(field(t, x)),
        (0.0, t_end),
        x0,
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
        t_eval=np.asarray(ts),
    )
    return dict(zip(KEYS, np.split(sol.y.T, [3, 6, 10], axis=1)))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--t-end", type=float, default=10.0)
    ap.add_argument("--out", default="examples/out")
    opts = ap.parse_args(argv)
    ts = jnp.linspace(0.0, opts.t_end, 201)
    runs = {}
    for name, solver in (
        ("RKMK45 (Lie)", jq.RKMK45(quaternions=jq.Quadrotor.quaternions)),
        ("Tsit5 (raw ODE)", diffrax.Tsit5()),
    ):
        run = jax.jit(lambda s=solver: solve(s, opts.t_end, ts))
        ys, steps = jax.block_until_ready(run())
        start = time.perf_counter()
        jax.block_until_ready(run())
        runs[name] = (ys, int(steps), time.perf_counter() - start)
    ref = reference(opts.t_end, ts)
    q_ref = jnp.asarray(ref["q"] / np.linalg.norm(ref["q"], axis=-1, keepdims=True))
    print(f"quadrotor to t = {opts.t_end:g}, PID rtol = atol = {TOL:g}, against DOP853 at 1e-13 on the raw ODE")
    for name, (ys, steps, wall) in runs.items():
        att = float(jnp.max(jq.angle_between(ys["q"] / jq.norm(ys["q"])[:, None], q_ref)))
        pos = float(np.max(np.abs(np.asarray(ys["r"]) - ref["r"])))
        rate = float(np.max(np.abs(np.asarray(ys["w"]) - ref["w"])))
        drift = float(jnp.max(jnp.abs(jq.norm(ys["q"]) - 1)))
        print(
            f"{name:16s} steps {steps:5d}  {wall * 1e3:7.2f} ms  attitude error {att:.2e} rad  "
            f"position error {pos:.2e} m  rate error {rate:.2e} rad/s  max ||q| - 1| {drift:.1e}"
        )
    lie = runs["RKMK45 (Lie)"][0]
    print(f"final altitude {float(lie['r'][-1, 2]):.4f} m")
    out = pathlib.Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    axes[0].plot(lie["r"][:, 0], lie["r"][:, 1], label="ground track")
    axes[0].set_xlabel("x, m")
    axes[0].set_ylabel("y, m")
    axes[0].set_title("path (altitude in the inset colour)")
    sc = axes[0].scatter(lie["r"][::10, 0], lie["r"][::10, 1], c=lie["r"][::10, 2], s=12)
    fig.colorbar(sc, ax=axes[0], label="z, m")
    axes[1].plot(ts, np.degrees(np.asarray(jq.to_euler(lie["q"], "ZYX"))), label=["yaw", "pitch", "roll"])
    axes[1].set_xlabel("t, s")
    axes[1].set_ylabel("deg")
    axes[1].legend()
    axes[1].set_title("attitude (ZYX Euler angles)")
    for name, (ys, _, _) in runs.items():
        axes[2].semilogy(ts[1:], np.abs(np.asarray(jq.norm(ys["q"]))[1:] - 1) + 1e-17, label=name)
    axes[2].set_xlabel("t, s")
    axes[2].set_ylabel("| |q| - 1 |")
    axes[2].set_title("unit norm")
    axes[2].legend()
    fig.tight_layout()
    fig.savefig(out / "quadrotor.png", dpi=110)
    print(f"figure: {out / 'quadrotor.png'}")


if __name__ == "__main__":
    main()
