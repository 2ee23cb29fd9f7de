"""Plot a RotationSpline through timed keys: attitude (ZYX Euler angles), body angular velocity
and body angular acceleration, with squad through the same keys for comparison.

Run: .venv/bin/python examples/spline_plot.py [--out DIR]   (default examples/out/)
Writes DIR/rotation_spline.png and prints the largest jumps of the rate and acceleration
across the keys (zero up to the finite-difference step: the spline is C2).
"""

from __future__ import annotations

import argparse
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jaxquat as jq  # noqa: E402

TIMES = np.array([0.0, 1.0, 2.5, 3.0, 5.0, 6.0])
EULER_DEG = np.array([[0, 0, 0], [40, 10, -20], [90, -30, 10], [100, -20, 60], [30, 45, 120], [0, 0, 90]], float)


def build():
    keys = jq.from_euler(jnp.asarray(np.deg2rad(EULER_DEG)), "ZYX")
    return jq.RotationSpline(jnp.asarray(TIMES), keys), keys


def key_jumps(spline, eps: float = 1e-8):
    """Largest change of rate and acceleration over [t_k - eps, t_k + eps] at interior keys."""
    jumps = {}
    for order in (1, 2):
        diffs = [jnp.abs(spline(t + eps, order) - spline(t - eps, order)).max() for t in TIMES[1:-1]]
        jumps[order] = float(max(diffs))
    return jumps


def plot(out: pathlib.Path) -> pathlib.Path:
    spline, keys = build()
    t = jnp.linspace(TIMES[0], TIMES[-1], 601)
    att = spline(t)
    euler = np.rad2deg(np.unwrap(np.asarray(jq.to_euler(att, "ZYX")), axis=0))
    rate, acc = np.asarray(spline(t, 1)), np.asarray(spline(t, 2))
    u = jnp.interp(t, jnp.asarray(TIMES), jnp.arange(len(TIMES), dtype=t.dtype))  # squad parameter
    squad_euler = np.rad2deg(np.unwrap(np.asarray(jq.to_euler(jq.squad(keys, u), "ZYX")), axis=0))

    fig, axes = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    labels = ("yaw (Z)", "pitch (Y)", "roll (X)")
    for k in range(3):
        line = axes[0].plot(t, euler[:, k], label=f"spline {labels[k]}")[0]
        axes[0].plot(t, squad_euler[:, k], "--", color=line.get_color(), alpha=0.5, lw=1)
        axes[0].plot(TIMES, EULER_DEG[:, k], "o", color=line.get_color())
    axes[0].set_ylabel("ZYX Euler angles, deg")
    axes[0].set_title("RotationSpline through 6 timed keys (dashed: squad, uniform in key index)")
    axes[0].legend(fontsize=8)
    for k, name in enumerate("xyz"):
        axes[1].plot(t, rate[:, k], label=f"w_{name}")
        axes[2].plot(t, acc[:, k], label=f"a_{name}")
    axes[1].set_ylabel("body angular velocity, rad/s")
    axes[2].set_ylabel("body angular acceleration, rad/s^2")
    axes[2].set_xlabel("time, s")
    for ax in axes[1:]:
        ax.legend(fontsize=8)
    for ax in axes:
        for tk in TIMES:
            ax.axvline(tk, color="0.85", lw=0.8, zorder=0)
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    path = out / "rotation_spline.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "out"))
    args = parser.parse_args()
    path = plot(pathlib.Path(args.out))
    jumps = key_jumps(build()[0])
    print(
        f"max jump across keys over 2e-8 s: angular velocity {jumps[1]:.1e} rad/s, "
        f"angular acceleration {jumps[2]:.1e} rad/s^2"
    )
    print(f"figure: {path}")


if __name__ == "__main__":
    main()
