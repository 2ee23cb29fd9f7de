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
# # Estimating attitude: TRIAD, QUEST and the MEKF
#
# Static attitude from two star directions, then a multiplicative EKF that fuses a biased gyro
# with those stars over time, and finally the filter's noise parameters learned by gradient
# through its likelihood. Conventions: `q` rotates body vectors into the reference frame
# (`r = R(q) b`); errors are body-frame rotation vectors (`q_true = q Exp(dtheta)`). The
# `assert`s make this notebook a test: the suite executes it.

# %%
import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
import optax
import jaxquat as jq

stars = jnp.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])  # reference frame
q_true = jq.from_rotvec(jnp.array([0.4, -1.0, 2.5]))
sigma = 1e-3  # rad per vector component
key = jax.random.PRNGKey(0)
body = jq.rotate(jq.conjugate(q_true), stars) + sigma * jax.random.normal(key, (2, 3))

# %% [markdown]
# ## Static: TRIAD and QUEST
# TRIAD trusts the first vector exactly; QUEST weights both (weights `1/sigma^2`) and
# `attitude_covariance` gives Shuster's covariance of its error.

# %%
q_triad = jq.triad(body[0], body[1], stars[0], stars[1])
q_quest = jq.quest(body, stars, jnp.full(2, sigma**-2))
P = jq.attitude_covariance(body, sigma)
print("TRIAD error", float(jq.angle_between(q_triad, q_true)), "rad")
print("QUEST error", float(jq.angle_between(q_quest, q_true)), "rad; 1-sigma bounds", np.sqrt(np.diag(P)))
assert float(jq.angle_between(q_quest, q_true)) < 5 * np.sqrt(np.trace(P))

# %% [markdown]
# ## The MEKF
# A body turning at a few tens of mrad/s; a 10 Hz gyro with a bias of about 1e-3 rad/s and
# angle random walk 1e-3 rad/s^1/2; the stars every sample. `mekf` runs the whole record in
# one `lax.scan`; the prior comes from QUEST on the first frame.

# %%
n, dt, sv = 400, 0.1, 1e-3
t = dt * jnp.arange(n)
omega = jnp.stack([0.05 * jnp.sin(0.2 * t), 0.03 * jnp.cos(0.1 * t), 0.02 + 0 * t], -1)
bias = jnp.array([1e-3, -2e-3, 5e-4])


def turn(q, w):
    return jq.plus(q, w * dt), q


_, qs = jax.lax.scan(turn, q_true, omega)
k1, k2 = jax.random.split(jax.random.PRNGKey(1))
gyro = omega + bias[None] + sv / jnp.sqrt(dt) * jax.random.normal(k1, (n, 3))
meas = jq.rotate(jq.conjugate(qs)[:, None], jnp.broadcast_to(stars, (n, 2, 3))) + sigma * jax.random.normal(
    k2, (n, 2, 3)
)
P0 = jnp.zeros((6, 6)).at[:3, :3].set(jq.attitude_covariance(meas[0], sigma)).at[3:, 3:].set(1e-5 * jnp.eye(3))
q0 = jq.quest(meas[0], stars, jnp.full(2, sigma**-2))
run = jax.jit(
    lambda g_noise: jq.mekf(
        q0, jnp.zeros(3), P0, dt, gyro, meas, stars[None], vector_noise=sigma, gyro_noise=g_noise, bias_noise=1e-6
    )
)
result = run(sv)
err = jq.minus(qs, result.q)
three_sigma = 3 * jnp.sqrt(jnp.diagonal(result.P, axis1=-2, axis2=-1))[:, :3]
inside = float(jnp.mean(jnp.abs(err) < three_sigma))
print("fraction of attitude errors inside 3 sigma:", inside)
print("bias estimate at the end", result.bias[-1], "truth", bias)
assert inside > 0.97
assert float(jnp.max(jnp.abs(result.bias[-1] - bias))) < 5e-4

# %%
import matplotlib.pyplot as plt

fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
ax[0].plot(t, err[:, 0], lw=0.7, label="x error")
ax[0].plot(t, three_sigma[:, 0], "k", t, -three_sigma[:, 0], "k", lw=0.8)
ax[0].set_xlabel("t, s")
ax[0].set_ylabel("rad")
ax[0].legend()
ax[1].plot(t, result.bias)
ax[1].plot(t, jnp.broadcast_to(bias, (n, 3)), "k--", lw=0.6)
ax[1].set_xlabel("t, s")
ax[1].set_ylabel("bias estimate, rad/s")
# %% [markdown]
# ## Learning the gyro noise by gradient
# The innovations' log-likelihood is differentiable in the noise parameters: Adam on
# `log(gyro_noise)` from a start 10x too large.

# %%
nll = jax.jit(jax.value_and_grad(lambda x: -jnp.sum(run(jnp.exp(x)).log_likelihood)))
opt = optax.adam(0.1)
x = jnp.log(10 * sv)
state = opt.init(x)
for _ in range(60):
    value, g = nll(x)
    updates, state = opt.update(g, state)
    x = optax.apply_updates(x, updates)
print("learned gyro noise / true:", float(jnp.exp(x) / sv))
assert abs(float(jnp.exp(x) / sv) - 1) < 0.3
