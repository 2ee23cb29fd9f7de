"""jaxquat showcase: exact values and gradients where naive formulas break (float32), the
Dzhanibekov flip from the exact torque-free solution, and a minimum-energy slew optimised
with optax through a simulation (float64).

Run with `make demo`. Prints a summary table and writes its figures to examples/out/;
takes well under two minutes on a 2-core CPU.
"""

import pathlib
import sys

import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxquat as jq


def naive_pitch(q):
    """Textbook arcsin extraction of the middle angle of "xyz" (what many codes do)."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.arcsin(jnp.clip(2 * (w * y - x * z), -1, 1))


def main():
    rows = []
    # 1. Euler angles 1e-4 degrees from gimbal lock, float32.
    ang = jnp.asarray([[0.7, np.pi / 2 - np.deg2rad(1e-4), -0.4]], jnp.float32)
    q = jq.from_euler(ang, "xyz")
    back = jq.from_euler(jq.to_euler(q, "xyz"), "xyz")
    rows.append(("Euler round trip 1e-4 deg from gimbal lock (float32), rad", float(jq.angle_between(back, q)[0])))
    naive = jq.from_euler(jnp.stack([ang[:, 0], naive_pitch(q), ang[:, 2]], -1), "xyz")
    rows.append(("  same with arcsin pitch and true outer angles, rad", float(jq.angle_between(naive, q)[0])))

    # 2. Jacobian of the rotation vector at the identity: exactly [0 | 2 I].
    J = jax.jacfwd(jq.to_rotvec)(jq.identity(dtype=jnp.float32))
    rows.append(("max |d to_rotvec/dq - [0|2I]| at the identity", float(jnp.abs(J[:, 1:] - 2 * jnp.eye(3)).max())))

    # 3. Gradient of a loss through slerp as p -> q (textbook slerp divides 0 by 0).
    p = jq.from_rotvec(jnp.asarray([0.3, -0.2, 0.1], jnp.float32))
    g = jax.grad(lambda x: jq.slerp(p, x, 0.5)[1])(p)
    rows.append(("slerp(p, q, 1/2) gradient at q = p is finite", bool(jnp.all(jnp.isfinite(g)))))

    # 4. from_matrix at a 180-degree rotation: finite gradient.
    m = jq.to_matrix(jnp.asarray([0.0, 0.0, 1.0, 0.0], jnp.float32))
    gm = jax.grad(lambda m: jq.from_matrix(m)[2])(m)
    rows.append(("from_matrix gradient finite at 180 degrees", bool(jnp.all(jnp.isfinite(gm)))))

    # 5. Batched throughput.
    key = jax.random.PRNGKey(0)
    qs = jq.random(key, (1_000_000,))
    vs = jax.random.normal(key, (1_000_000, 3))
    rot = jax.jit(jq.rotate)
    rot(qs, vs).block_until_ready()
    t0 = time.perf_counter()
    for _ in range(10):
        rot(qs, vs).block_until_ready()
    dt = (time.perf_counter() - t0) / 10
    rows.append(("rotate 10^6 vectors (float32, jit), ms", dt * 1e3))

    # 6. Mean and Wahba.
    truth = jq.from_rotvec(jnp.asarray([0.2, 0.5, -0.3]))
    b = jax.random.normal(jax.random.PRNGKey(1), (10, 3))
    a = jq.rotate(truth, b) + 1e-3 * jax.random.normal(jax.random.PRNGKey(2), (10, 3))
    rows.append(
        ("align_vectors error, 10 vectors, 1e-3 noise, rad", float(jq.angle_between(jq.align_vectors(a, b), truth)))
    )

    # 7. The Euler-parameter equations of motion, three ways (float32): Chou's closed
    #    form, Schwab's augmented system with its multiplier, Newton-Euler on (q, w).
    inertia = jnp.asarray([[2.0, 0.1, 0.0], [0.1, 3.0, 0.2], [0.0, 0.2, 4.0]], jnp.float32)
    qb = jq.random(jax.random.PRNGKey(3), (1000,))
    wb = jax.random.normal(jax.random.PRNGKey(4), (1000, 3))
    mb = jax.random.normal(jax.random.PRNGKey(5), (1000, 3))
    qd = jq.qdot_from_omega(qb, wb)
    chou = jq.euler_parameter_acceleration(qb, qd, inertia, mb)
    lhs, rhs = jq.euler_parameter_augmented_system(qb, qd, inertia, mb)
    schwab = jnp.linalg.solve(lhs, rhs[..., None])[..., 0]
    newton = jq.qddot_from_alpha(qb, qd, jq.angular_acceleration(qb, wb, inertia, mb))
    rows.append(("EOM, 1000 states: max |Chou - Schwab (23)| qddot", float(jnp.abs(chou - schwab[:, :4]).max())))
    rows.append(("  max |Chou - Newton-Euler| qddot", float(jnp.abs(chou - newton).max())))
    lam = jq.norm_constraint_multiplier(qb, qd, inertia)
    rows.append(
        ("  Schwab's multiplier vs w.Iw (eq. 24), max rel. error", float(jnp.abs(schwab[:, 4] / lam - 1).max()))
    )

    # 8-9. The two dynamics examples (they switch float64 on: run them after the float32 part).
    sys.path.insert(0, str(pathlib.Path(__file__).parent))
    import dzhanibekov
    import min_energy_slew

    print("--- Dzhanibekov flip (examples/dzhanibekov.py) ---")
    measured, formula = dzhanibekov.main(["--t-end", "40"])
    rows.append(("Dzhanibekov flip interval, measured vs 2K(m)/lambda, rel.", abs(measured / formula - 1)))
    print("--- minimum-energy slew (examples/min_energy_slew.py, short run) ---")
    cost, optimum, c = min_energy_slew.main(["--outer", "5", "--inner", "40", "--steps", "100"])
    rows.append(("min-energy slew: cost / (12 theta^2 / T^3) - 1", cost / optimum - 1))
    rows.append(("  terminal constraint violation", float(jnp.linalg.norm(c))))

    width = max(len(r[0]) for r in rows)
    print("jaxquat demo".center(width + 14, "="))
    for name, val in rows:
        val = f"{val:.3e}" if isinstance(val, float) else str(val)
        print(f"{name:<{width}}  {val:>12}")
    print("=" * (width + 14))
    print("figures: examples/out/dzhanibekov.png, examples/out/min_energy_slew.png")


if __name__ == "__main__":
    main()
