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
# # A tour of jaxquat
#
# Quaternions are plain `jax.Array`s shaped `(..., 4)`, scalar first `(w, x, y, z)`,
# Hamilton product, active rotation `v' = q v q*`. Every function broadcasts over leading
# axes and works under `jit`, `vmap` and `grad`. The `assert`s make this notebook a test:
# the suite executes it.

# %%
import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation
import jaxquat as jq

# %% [markdown]
# ## Build, compose, rotate
# A rotation by 90 degrees about z takes x to y.

# %%
qz = jq.from_axis_angle(jnp.array([0.0, 0.0, 1.0]), jnp.pi / 2)
print(qz)
print(jq.rotate(qz, jnp.array([1.0, 0.0, 0.0])))
assert np.allclose(jq.rotate(qz, jnp.array([1.0, 0.0, 0.0])), [0, 1, 0])

# %% [markdown]
# `multiply(p, q)` applies `q` first, then `p` (as matrices: `R(p) R(q)`). Check against scipy (scalar last there).

# %%
key = jax.random.PRNGKey(0)
p, q = jq.random(key, (2, 5))
pq = jq.multiply(p, q)
ref = (Rotation.from_quat(np.roll(p, -1, -1)) * Rotation.from_quat(np.roll(q, -1, -1))).as_matrix()
print(np.abs(jq.to_matrix(pq) - ref).max())
assert np.allclose(jq.to_matrix(pq), ref)

# %% [markdown]
# ## Conversions
# Matrices, rotation vectors, Euler angles (24 conventions), each round-tripping.

# %%
r = jq.to_rotvec(p)
assert np.allclose(jq.angle_between(jq.from_rotvec(r), p), 0, atol=1e-7)
assert np.allclose(jq.angle_between(jq.from_matrix(jq.to_matrix(p)), p), 0, atol=1e-7)
angles = jq.to_euler(p, "ZYX")
assert np.allclose(jq.angle_between(jq.from_euler(angles, "ZYX"), p), 0, atol=1e-7)
print(np.degrees(angles[0]))

# %% [markdown]
# ## Interpolation and averaging

# %%
a, b = jq.identity(), qz
mid = jq.slerp(a, b, 0.5)
print(np.degrees(jq.angle(mid)))  # half of 90 degrees
assert np.isclose(jq.angle(mid), jnp.pi / 4)
m = jq.mean(
    jnp.stack(
        [
            p[0],
            jq.multiply(p[0], jq.from_rotvec(jnp.array([0.01, 0, 0]))),
            jq.multiply(p[0], jq.from_rotvec(jnp.array([-0.01, 0, 0]))),
        ]
    )
)
assert jq.angle_between(m, p[0]) < 1e-6

# %% [markdown]
# ## Gradients
# Fit a rotation to vector pairs by gradient descent in the tangent space. The gradient of a loss is finite everywhere, including at the identity.

# %%
target = jq.from_rotvec(jnp.array([0.3, -0.2, 0.5]))
v = jax.random.normal(jax.random.PRNGKey(1), (10, 3))
w = jq.rotate(target, v)


def loss(q):
    return jnp.sum((jq.rotate(q, v) - w) ** 2)


q = jq.identity()
for _ in range(60):
    g = jax.grad(loss)(q)
    q = jq.plus(q, -0.02 * jq.tangent_gradient(q, g))
print(jq.angle_between(q, target))
assert jq.angle_between(q, target) < 1e-6

# %% [markdown]
# `vmap` over a batch and `jit` work on every function:

# %%
batched = jax.jit(jax.vmap(jq.to_matrix))(jq.random(key, (1000,)))
print(batched.shape)
assert batched.shape == (1000, 3, 3)

# %% [markdown]
# ## Dynamics
# Simulate a tumbling asymmetric body. Torque-free, `simulate` uses the exact Euler-Poinsot solution, so energy and angular momentum are conserved to rounding at any time.

# %%
inertia = jnp.diag(jnp.array([1.0, 2.0, 3.0]))
ts = jnp.linspace(0.0, 100.0, 201)
sim = jq.simulate(jq.identity(), jnp.array([0.1, 2.0, 0.05]), inertia, ts)
energy = jq.kinetic_energy(sim.q, sim.omega, inertia)
momentum = jq.rotate(sim.q, jq.angular_momentum(sim.q, sim.omega, inertia))  # body -> space frame
print(np.ptp(energy), np.abs(momentum - momentum[:1]).max())
assert np.ptp(energy) < 1e-10 and np.abs(momentum - momentum[:1]).max() < 1e-10
