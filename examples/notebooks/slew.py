# ---
# jupyter:
#   jupytext:
#     cell_metadata_filter: -all
#     notebook_metadata_filter: kernelspec
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.17.3
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Optimising a slew through the simulator
#
# Minimum-energy rest-to-rest slew of a body with `J = I`: rotate by `theta` about a
# fixed axis in time `T`, minimising the integral of `|u|^2`. The analytic optimum
# is the eigenaxis rotation with a cubic angle profile, cost `12 theta^2 / T^3`.
#
# Here the torque is constant on `N` intervals, the body is simulated with
# `jq.simulate` (RKMK4), and the terminal conditions enter a quadratic penalty
# with multiplier updates (augmented Lagrangian), minimised by optimistix's L-BFGS.
# Gradients flow through the simulation.

# %%
import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
import jaxquat as jq

T, THETA, N = 2.0, np.pi / 2, 20
axis = jnp.array([1.0, 2.0, 2.0]) / 3.0
qf = jq.from_axis_angle(axis, THETA)


# %% [markdown]
# The torque is held constant on each of the `N` intervals (the cost is then `h sum |u_k|^2`); each interval is one `simulate` call inside a `lax.scan`, so the fixed-step solver never steps across a jump in the torque.


# %%
def piece(state, u_k):
    q, w = state
    sim = jq.simulate(
        q,
        w,
        jnp.eye(3),
        jnp.array([0.0, T / N]),
        torque=lambda t, q, w, u: u,
        args=u_k,
        solver=jq.RKMK4(),
        dt0=T / (4 * N),
    )
    return (sim.q[-1], sim.omega[-1]), None


def terminal(u):
    (q, w), _ = jax.lax.scan(piece, (jq.identity(), jnp.zeros(3)), u)
    return jnp.concatenate([jq.minus(q, qf), w])


def energy(u):
    return T / N * jnp.sum(u * u)


# %% [markdown]
# Augmented Lagrangian: a few outer multiplier updates around a jitted L-BFGS inner loop.

# %%
import sys

sys.path.insert(0, "..")  # examples/_lbfgs.py: optimistix L-BFGS steps in one lax.scan
from _lbfgs import minimize


@jax.jit
def inner(u, lam, mu):
    def f(x):
        c = terminal(x)
        return energy(x) + lam @ c + 0.5 * mu * c @ c

    u, values = minimize(f, u, 40)
    return u, values[-1]


u = 0.1 * jax.random.normal(jax.random.PRNGKey(0), (N, 3))
lam, mu = jnp.zeros(6), 100.0
for k in range(5):
    u, value = inner(u, lam, mu)
    c = terminal(u)
    lam = lam + mu * c
    print(f"outer {k}: energy {float(energy(u)):.6f}, violation {float(jnp.linalg.norm(c)):.1e}")

# %% [markdown]
# Compare with the analytic optimum. The best torque held constant on `N` intervals is the linear optimum sampled at the interval midpoints, and it costs `12 theta^2 / (T^3 (1 - 1/N^2))`: 0.25 % more for `N = 20` (derived by the same Lagrange argument as the continuous optimum).

# %%
optimum = 12 * THETA**2 / T**3
cost = float(energy(u))
print(f"cost {cost:.6f}, analytic optimum {optimum:.6f}, excess {100 * (cost / optimum - 1):.3f} %")
assert jnp.linalg.norm(terminal(u)) < 1e-5
assert abs(cost / optimum - 1 / (1 - 1 / N**2)) < 1e-5
off_axis = u - jnp.outer(u @ axis, axis)
assert jnp.abs(off_axis).max() < 1e-3  # the optimal torque lies along the eigenaxis

# %%
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

grid = (np.arange(N) + 0.5) * T / N
plt.step(np.arange(N) * T / N, np.asarray(u @ axis), where="post", label="optimised, along the eigenaxis")
plt.plot(grid, 6 * THETA / T**2 * (1 - 2 * grid / T), "k.", label="analytic optimum at interval midpoints")
plt.xlabel("t")
plt.ylabel("torque")
plt.legend()
