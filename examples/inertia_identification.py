"""Inertia identification from noisy attitude measurements of a tumbling body (gyro-free).

A body with an unknown full inertia tensor tumbles freely; we observe only its attitude,
every 0.1 s for 20 s, each measurement rotated by Gaussian noise of a given size (rad per
axis). Torque-free motion does not change if the inertia is scaled, so the tensor is
recovered to scale (normalised to trace 3). Unknowns: the initial attitude (a tangent
correction to the first measurement), the initial body angular velocity, the principal
moments and the principal axes (a rotation vector): 12 parameters, fitted with optimistix's
L-BFGS on the sum of squared attitude residuals over growing time windows, with gradients through the exact
torque-free solution (jaxquat.euler_poinsot). Prints the relative error of the recovered
tensor for each noise level and saves examples/out/inertia_identification.png.

Run: python examples/inertia_identification.py [--iters 300] [--noise 1e-3 1e-2 3e-2]
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
from _lbfgs import minimize  # noqa: E402

TS = jnp.linspace(0.0, 20.0, 201)
TRUE_INERTIA = jnp.asarray([[1.2, 0.15, -0.1], [0.15, 0.9, 0.05], [-0.1, 0.05, 0.9]])
TRUE_W0 = jnp.asarray([0.3, 1.1, -0.4])
TRUE_Q0 = jq.from_rotvec(jnp.asarray([0.4, -0.7, 0.2]))


def normalised(inertia):
    return 3.0 * inertia / jnp.trace(inertia)


def trajectory(q0, w0, moments, axes):
    """Body attitudes at TS for a body with principal moments ``moments`` along the axes
    ``R = Exp(axes)`` (body frame), from ``q0`` and body rate ``w0``."""
    q_axes = jq.from_rotvec(axes)
    r = jq.to_matrix(q_axes)
    q_p, _ = jq.euler_poinsot(jq.multiply(q0, q_axes), r.T @ w0, moments, TS)
    return jq.multiply(q_p, jq.conjugate(q_axes)[None])


def tensor(moments, axes):
    r = jq.to_matrix(jq.from_rotvec(axes))
    return r @ jnp.diag(moments) @ r.T


@jax.jit  # one compiled program; op-by-op (eager) evaluation of the closed form took 9 s
def measurements(noise, seed):
    moments, q_axes = jq.principal_axes(TRUE_INERTIA)
    axes = jq.to_rotvec(q_axes)
    clean = trajectory(TRUE_Q0, TRUE_W0, moments, axes)
    kick = noise * jax.random.normal(jax.random.PRNGKey(seed), (len(TS), 3))
    return jq.multiply(clean, jq.from_rotvec(kick))


def initial_guess(meas):
    dt = TS[1] - TS[0]
    w0 = jq.minus(meas[1], meas[0]) / dt  # body rate from the first two measurements
    return dict(
        dq0=jnp.zeros(3), w0=w0, log_moments=jnp.log(jnp.asarray([0.9, 1.0, 1.1])), axes=jnp.asarray([0.1, 0.1, 0.1])
    )


WINDOWS = (2.0, 6.0, 20.0)


def fit(meas, iters):
    """L-BFGS on growing time windows (continuation: 2 s, 6 s, then all 20 s), so a noisy
    first rate estimate cannot send the fit to a distant local minimum."""

    def loss(p, window):
        q0 = jq.plus(meas[0], p["dq0"])
        model = trajectory(q0, p["w0"], jnp.exp(p["log_moments"]), p["axes"])
        weight = (TS <= window).astype(meas.dtype)
        return jnp.sum(weight[:, None] * jq.minus(model, meas) ** 2)

    @jax.jit
    def run(p, window):
        return minimize(lambda x: loss(x, window), p, iters // len(WINDOWS))

    p, history = initial_guess(meas), []
    for window in WINDOWS:
        p, values = run(p, jnp.asarray(window))
        history.append(values)
    return p, jnp.concatenate(history)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--iters", type=int, default=300)
    ap.add_argument("--noise", type=float, nargs="+", default=[1e-3, 1e-2, 3e-2])
    ap.add_argument("--out", default="examples/out")
    args = ap.parse_args(argv)
    truth = normalised(TRUE_INERTIA)
    print(f"true inertia (trace 3):\n{np.asarray(truth).round(4)}")
    results = []
    for noise in args.noise:
        t0 = time.perf_counter()
        meas = measurements(noise, seed=1)
        p, values = fit(meas, args.iters)
        est = normalised(tensor(jnp.exp(p["log_moments"]), p["axes"]))
        err = float(jnp.linalg.norm(est - truth) / jnp.linalg.norm(truth))
        w_err = float(jnp.linalg.norm(p["w0"] - TRUE_W0))
        results.append((noise, err, values))
        print(
            f"noise {noise:.0e} rad: relative tensor error {err:.2e}, |w0 error| {w_err:.1e} rad/s, "
            f"final loss {float(values[-1]):.3e} ({len(TS)} attitudes), {time.perf_counter() - t0:.1f} s"
        )
    print(f"recovered inertia at noise {args.noise[-1]:.0e} (trace 3):\n{np.asarray(est).round(4)}")

    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for noise, err, values in results:
        ax.semilogy(np.asarray(values), label=f"noise {noise:.0e} rad: tensor error {err:.1e}")
    ax.set_xlabel("L-BFGS iteration")
    ax.set_ylabel("sum of squared attitude residuals")
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = out / "inertia_identification.png"
    fig.savefig(path, dpi=100)
    print(f"figure: {path}")
    return results


if __name__ == "__main__":
    main()
