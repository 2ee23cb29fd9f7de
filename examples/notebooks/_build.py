"""Writes tour.ipynb, slew.ipynb and estimation.ipynb (without outputs) from the cells below: edit here, run, commit both.

Run: python examples/notebooks/_build.py
"""

import pathlib

import nbformat as nbf


def nb(cells):
    n = nbf.v4.new_notebook()
    n.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    n.cells = [nbf.v4.new_markdown_cell(c[1]) if c[0] == "md" else nbf.v4.new_code_cell(c[1]) for c in cells]
    return n


tour = [
    (
        "md",
        """# A tour of jaxquat

Quaternions are plain `jax.Array`s shaped `(..., 4)`, scalar first `(w, x, y, z)`,
Hamilton product, active rotation `v' = q v q*`. Every function broadcasts over leading
axes and works under `jit`, `vmap` and `grad`. The `assert`s make this notebook a test:
the suite executes it.""",
    ),
    (
        "code",
        """import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation
import jaxquat as jq""",
    ),
    ("md", "## Build, compose, rotate\nA rotation by 90 degrees about z takes x to y."),
    (
        "code",
        """qz = jq.from_axis_angle(jnp.array([0.0, 0.0, 1.0]), jnp.pi / 2)
print(qz)
print(jq.rotate(qz, jnp.array([1.0, 0.0, 0.0])))
assert np.allclose(jq.rotate(qz, jnp.array([1.0, 0.0, 0.0])), [0, 1, 0])""",
    ),
    (
        "md",
        "`multiply(p, q)` applies `q` first, then `p` (as matrices: `R(p) R(q)`). Check against scipy (scalar last there).",
    ),
    (
        "code",
        """key = jax.random.PRNGKey(0)
p, q = jq.random(key, (2, 5))
pq = jq.multiply(p, q)
ref = (Rotation.from_quat(np.roll(p, -1, -1)) * Rotation.from_quat(np.roll(q, -1, -1))).as_matrix()
print(np.abs(jq.to_matrix(pq) - ref).max())
assert np.allclose(jq.to_matrix(pq), ref)""",
    ),
    ("md", "## Conversions\nMatrices, rotation vectors, Euler angles (24 conventions), each round-tripping."),
    (
        "code",
        """r = jq.to_rotvec(p)
assert np.allclose(jq.angle_between(jq.from_rotvec(r), p), 0, atol=1e-7)
assert np.allclose(jq.angle_between(jq.from_matrix(jq.to_matrix(p)), p), 0, atol=1e-7)
angles = jq.to_euler(p, "ZYX")
assert np.allclose(jq.angle_between(jq.from_euler(angles, "ZYX"), p), 0, atol=1e-7)
print(np.degrees(angles[0]))""",
    ),
    ("md", "## Interpolation and averaging"),
    (
        "code",
        """a, b = jq.identity(), qz
mid = jq.slerp(a, b, 0.5)
print(np.degrees(jq.angle(mid)))  # half of 90 degrees
assert np.isclose(jq.angle(mid), jnp.pi / 4)
m = jq.mean(jnp.stack([p[0], jq.multiply(p[0], jq.from_rotvec(jnp.array([0.01, 0, 0]))),
                       jq.multiply(p[0], jq.from_rotvec(jnp.array([-0.01, 0, 0])))]))
assert jq.angle_between(m, p[0]) < 1e-6""",
    ),
    (
        "md",
        "## Gradients\nFit a rotation to vector pairs by gradient descent in the tangent space. The gradient of a loss is finite everywhere, including at the identity.",
    ),
    (
        "code",
        """target = jq.from_rotvec(jnp.array([0.3, -0.2, 0.5]))
v = jax.random.normal(jax.random.PRNGKey(1), (10, 3))
w = jq.rotate(target, v)

def loss(q):
    return jnp.sum((jq.rotate(q, v) - w) ** 2)

q = jq.identity()
for _ in range(60):
    g = jax.grad(loss)(q)
    q = jq.plus(q, -0.02 * jq.tangent_gradient(q, g))
print(jq.angle_between(q, target))
assert jq.angle_between(q, target) < 1e-6""",
    ),
    ("md", "`vmap` over a batch and `jit` work on every function:"),
    (
        "code",
        """batched = jax.jit(jax.vmap(jq.to_matrix))(jq.random(key, (1000,)))
print(batched.shape)
assert batched.shape == (1000, 3, 3)""",
    ),
    (
        "md",
        "## Dynamics\nSimulate a tumbling asymmetric body. Torque-free, `simulate` uses the exact Euler-Poinsot solution, so energy and angular momentum are conserved to rounding at any time.",
    ),
    (
        "code",
        """inertia = jnp.diag(jnp.array([1.0, 2.0, 3.0]))
ts = jnp.linspace(0.0, 100.0, 201)
sim = jq.simulate(jq.identity(), jnp.array([0.1, 2.0, 0.05]), inertia, ts)
energy = jq.kinetic_energy(sim.q, sim.omega, inertia)
momentum = jq.rotate(sim.q, jq.angular_momentum(sim.q, sim.omega, inertia))  # body -> space frame
print(np.ptp(energy), np.abs(momentum - momentum[0]).max())
assert np.ptp(energy) < 1e-10 and np.abs(momentum - momentum[0]).max() < 1e-10""",
    ),
]

slew = [
    (
        "md",
        """# Optimising a slew through the simulator

Minimum-energy rest-to-rest slew of a body with `J = I`: rotate by `theta` about a
fixed axis in time `T`, minimising the integral of `|u|^2`. The analytic optimum
is the eigenaxis rotation with a cubic angle profile, cost `12 theta^2 / T^3`.

Here the torque is constant on `N` intervals, the body is simulated with
`jq.simulate` (RKMK4), and the terminal conditions enter a quadratic penalty
with multiplier updates (augmented Lagrangian), minimised by optimistix's L-BFGS.
Gradients flow through the simulation.""",
    ),
    (
        "code",
        """import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
import jaxquat as jq

T, THETA, N = 2.0, np.pi / 2, 20
axis = jnp.array([1.0, 2.0, 2.0]) / 3.0
qf = jq.from_axis_angle(axis, THETA)
""",
    ),
    (
        "md",
        "The torque is held constant on each of the `N` intervals (the cost is then `h sum |u_k|^2`); each interval is one `simulate` call inside a `lax.scan`, so the fixed-step solver never steps across a jump in the torque.",
    ),
    (
        "code",
        """def piece(state, u_k):
    q, w = state
    sim = jq.simulate(q, w, jnp.eye(3), jnp.array([0.0, T / N]), torque=lambda t, q, w, u: u, args=u_k,
                      solver=jq.RKMK4(), dt0=T / (4 * N))
    return (sim.q[-1], sim.omega[-1]), None

def terminal(u):
    (q, w), _ = jax.lax.scan(piece, (jq.identity(), jnp.zeros(3)), u)
    return jnp.concatenate([jq.minus(q, qf), w])

def energy(u):
    return T / N * jnp.sum(u * u)""",
    ),
    ("md", "Augmented Lagrangian: a few outer multiplier updates around a jitted L-BFGS inner loop."),
    (
        "code",
        """import sys
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
    print(f"outer {k}: energy {float(energy(u)):.6f}, violation {float(jnp.linalg.norm(c)):.1e}")""",
    ),
    (
        "md",
        "Compare with the analytic optimum. The best torque held constant on `N` intervals is the linear optimum sampled at the interval midpoints, and it costs `12 theta^2 / (T^3 (1 - 1/N^2))`: 0.25 % more for `N = 20` (derived by the same Lagrange argument as the continuous optimum).",
    ),
    (
        "code",
        """optimum = 12 * THETA**2 / T**3
cost = float(energy(u))
print(f"cost {cost:.6f}, analytic optimum {optimum:.6f}, excess {100 * (cost / optimum - 1):.3f} %")
assert jnp.linalg.norm(terminal(u)) < 1e-5
assert abs(cost / optimum - 1 / (1 - 1 / N**2)) < 1e-5
off_axis = u - jnp.outer(u @ axis, axis)
assert jnp.abs(off_axis).max() < 1e-3  # the optimal torque lies along the eigenaxis""",
    ),
    (
        "code",
        """import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
grid = (np.arange(N) + 0.5) * T / N
plt.step(np.arange(N) * T / N, np.asarray(u @ axis), where="post", label="optimised, along the eigenaxis")
plt.plot(grid, 6 * THETA / T**2 * (1 - 2 * grid / T), "k.", label="analytic optimum at interval midpoints")
plt.xlabel("t"); plt.ylabel("torque"); plt.legend();""",
    ),
]
estimation = [
    (
        "md",
        """# Estimating attitude: TRIAD, QUEST and the MEKF

Static attitude from two star directions, then a multiplicative EKF that fuses a biased gyro
with those stars over time, and finally the filter's noise parameters learned by gradient
through its likelihood. Conventions: `q` rotates body vectors into the reference frame
(`r = R(q) b`); errors are body-frame rotation vectors (`q_true = q Exp(dtheta)`). The
`assert`s make this notebook a test: the suite executes it.""",
    ),
    (
        "code",
        """import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
import optax
import jaxquat as jq

stars = jnp.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])   # reference frame
q_true = jq.from_rotvec(jnp.array([0.4, -1.0, 2.5]))
sigma = 1e-3                                               # rad per vector component
key = jax.random.PRNGKey(0)
body = jq.rotate(jq.conjugate(q_true), stars) + sigma * jax.random.normal(key, (2, 3))""",
    ),
    (
        "md",
        """## Static: TRIAD and QUEST
TRIAD trusts the first vector exactly; QUEST weights both (weights `1/sigma^2`) and
`attitude_covariance` gives Shuster's covariance of its error.""",
    ),
    (
        "code",
        """q_triad = jq.triad(body[0], body[1], stars[0], stars[1])
q_quest = jq.quest(body, stars, jnp.full(2, sigma**-2))
P = jq.attitude_covariance(body, sigma)
print("TRIAD error", float(jq.angle_between(q_triad, q_true)), "rad")
print("QUEST error", float(jq.angle_between(q_quest, q_true)), "rad; 1-sigma bounds", np.sqrt(np.diag(P)))
assert float(jq.angle_between(q_quest, q_true)) < 5 * np.sqrt(np.trace(P))""",
    ),
    (
        "md",
        """## The MEKF
A body turning at a few tens of mrad/s; a 10 Hz gyro with a bias of about 1e-3 rad/s and
angle random walk 1e-3 rad/s^1/2; the stars every sample. `mekf` runs the whole record in
one `lax.scan`; the prior comes from QUEST on the first frame.""",
    ),
    (
        "code",
        """n, dt, sv = 400, 0.1, 1e-3
t = dt * jnp.arange(n)
omega = jnp.stack([0.05 * jnp.sin(0.2 * t), 0.03 * jnp.cos(0.1 * t), 0.02 + 0 * t], -1)
bias = jnp.array([1e-3, -2e-3, 5e-4])

def turn(q, w):
    return jq.plus(q, w * dt), q

_, qs = jax.lax.scan(turn, q_true, omega)
k1, k2 = jax.random.split(jax.random.PRNGKey(1))
gyro = omega + bias + sv / jnp.sqrt(dt) * jax.random.normal(k1, (n, 3))
meas = jq.rotate(jq.conjugate(qs)[:, None], jnp.broadcast_to(stars, (n, 2, 3))) + sigma * jax.random.normal(k2, (n, 2, 3))
P0 = jnp.zeros((6, 6)).at[:3, :3].set(jq.attitude_covariance(meas[0], sigma)).at[3:, 3:].set(1e-5 * jnp.eye(3))
q0 = jq.quest(meas[0], stars, jnp.full(2, sigma**-2))
run = jax.jit(lambda g_noise: jq.mekf(q0, jnp.zeros(3), P0, dt, gyro, meas, stars[None],
                                       vector_noise=sigma, gyro_noise=g_noise, bias_noise=1e-6))
result = run(sv)
err = jq.minus(qs, result.q)
three_sigma = 3 * jnp.sqrt(jnp.diagonal(result.P, axis1=-2, axis2=-1))[:, :3]
inside = float(jnp.mean(jnp.abs(err) < three_sigma))
print("fraction of attitude errors inside 3 sigma:", inside)
print("bias estimate at the end", result.bias[-1], "truth", bias)
assert inside > 0.97
assert float(jnp.max(jnp.abs(result.bias[-1] - bias))) < 5e-4""",
    ),
    (
        "code",
        """import matplotlib.pyplot as plt
fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
ax[0].plot(t, err[:, 0], lw=0.7, label="x error"); ax[0].plot(t, three_sigma[:, 0], "k", t, -three_sigma[:, 0], "k", lw=0.8)
ax[0].set_xlabel("t, s"); ax[0].set_ylabel("rad"); ax[0].legend()
ax[1].plot(t, result.bias); ax[1].plot(t, jnp.broadcast_to(bias, (n, 3)), "k--", lw=0.6)
ax[1].set_xlabel("t, s"); ax[1].set_ylabel("bias estimate, rad/s");""",
    ),
    (
        "md",
        """## Learning the gyro noise by gradient
The innovations' log-likelihood is differentiable in the noise parameters: Adam on
`log(gyro_noise)` from a start 10x too large.""",
    ),
    (
        "code",
        """nll = jax.jit(jax.value_and_grad(lambda x: -jnp.sum(run(jnp.exp(x)).log_likelihood)))
opt = optax.adam(0.1)
x = jnp.log(10 * sv); state = opt.init(x)
for _ in range(60):
    value, g = nll(x)
    updates, state = opt.update(g, state)
    x = optax.apply_updates(x, updates)
print("learned gyro noise / true:", float(jnp.exp(x) / sv))
assert abs(float(jnp.exp(x) / sv) - 1) < 0.3""",
    ),
]
nbf.write(nb(tour), pathlib.Path(__file__).parent / "tour.ipynb")
nbf.write(nb(slew), pathlib.Path(__file__).parent / "slew.ipynb")
nbf.write(nb(estimation), pathlib.Path(__file__).parent / "estimation.ipynb")
