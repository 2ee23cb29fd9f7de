"""Torque models: user torque functions in either frame, and the gravity-gradient torque as a
worked example (against the potential's derivative, and the pitch libration frequency)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxquat as jq
from helpers import DTYPE, X64, assert_close, random_inertias, random_quats


def test_gravity_gradient_is_minus_the_gradient_of_the_potential():
    """M_b . dtheta = -dV for a body-frame rotation q -> q exp(dtheta/2)."""
    q = jnp.asarray(random_quats(4, 8), DTYPE)
    inertia = jnp.asarray(random_inertias(4, 8), DTYPE)
    r = jnp.asarray(np.random.default_rng(4).normal(size=(8, 3)) * 3.0, DTYPE)
    mu = 2.5

    def potential(dtheta, qi, ii, ri):
        rb = jq.rotate(jq.conjugate(jq.multiply(qi, jq.from_rotvec(dtheta))), ri)
        rr = jnp.sum(ri * ri)
        return -mu / (2 * rr**1.5) * (jnp.trace(ii) - 3 * rb @ ii @ rb / rr)

    grad = jax.jit(jax.vmap(jax.grad(potential), (None, 0, 0, 0)))(jnp.zeros(3, DTYPE), q, inertia, r)
    m = jq.gravity_gradient_torque(q, r, inertia, mu)
    assert_close(m / jnp.abs(m).max(), -grad / jnp.abs(m).max(), tol=1e-12 if X64 else 1e-5)


def test_equilibrium_attitude_has_no_torque():
    inertia = jnp.diag(jnp.asarray([1.0, 2.0, 1.5], DTYPE))
    torque = jq.circular_orbit_gravity_gradient(inertia, 0.7)
    ts = jnp.linspace(0.0, 10.0, 7, dtype=DTYPE)
    lvlh = jq.from_rotvec(jnp.stack([0 * ts, 0 * ts, 0.7 * ts], -1))
    m = torque(ts, lvlh, jnp.zeros((7, 3), DTYPE), None)
    assert_close(m, np.zeros((7, 3)), tol=1e-14 if X64 else 1e-6)


def _rk4_pitch(theta0, n, inertia, dt, steps):
    torque = jq.circular_orbit_gravity_gradient(inertia, n)

    def rhs(t, y):
        q, w = y
        return jq.qdot_from_omega(q, w), jq.angular_acceleration(q, w, inertia, torque(t, q, w, None))

    def step(carry, _):
        t, y = carry
        k1 = rhs(t, y)
        k2 = rhs(t + dt / 2, jax.tree.map(lambda a, k: a + dt / 2 * k, y, k1))
        k3 = rhs(t + dt / 2, jax.tree.map(lambda a, k: a + dt / 2 * k, y, k2))
        k4 = rhs(t + dt, jax.tree.map(lambda a, k: a + dt * k, y, k3))
        y = jax.tree.map(lambda a, b, c, d, e: a + dt / 6 * (b + 2 * c + 2 * d + e), y, k1, k2, k3, k4)
        return (t + dt, y), (t + dt, y[0])

    y0 = (jq.from_rotvec(jnp.asarray([0.0, 0.0, theta0], DTYPE)), jnp.asarray([0.0, 0.0, n], DTYPE))
    _, (ts, qs) = jax.lax.scan(step, (jnp.asarray(0.0, DTYPE), y0), None, length=steps)
    rel = jq.multiply(jq.conjugate(jq.from_rotvec(jnp.stack([0 * ts, 0 * ts, n * ts], -1))), qs)
    return ts, jq.to_rotvec(rel)  # attitude relative to the orbit frame


def test_pitch_libration_frequency_of_the_worked_example():
    """Small pitch oscillation about the orbit normal: omega_p = n sqrt(3 (Iyy - Ixx) / Izz)."""
    n = 1.0
    inertia = jnp.diag(jnp.asarray([1.0, 2.0, 1.5], DTYPE))
    expected_period = 2 * np.pi / (n * np.sqrt(3 * (2.0 - 1.0) / 1.5))
    ts, rel = jax.jit(_rk4_pitch, static_argnums=(3, 4))(0.01, n, inertia, 0.01, 1400)
    pitch = np.asarray(rel[:, 2], np.float64)
    t = np.asarray(ts, np.float64)
    i = np.nonzero(np.sign(pitch[1:]) != np.sign(pitch[:-1]))[0]
    crossings = t[i] - pitch[i] * (t[i + 1] - t[i]) / (pitch[i + 1] - pitch[i])
    period = 2 * np.mean(np.diff(crossings))
    assert len(crossings) >= 5
    # amplitude 0.01 rad shifts the period by ~theta0^2/16 = 6e-6; RK4 at dt = 0.01 by ~1e-9
    assert abs(period / expected_period - 1) < (1e-4 if X64 else 2e-3), (period, expected_period)
    assert np.abs(np.asarray(rel[:, :2])).max() < 1e-6  # roll and yaw stay unexcited


@pytest.mark.parametrize("frame", ["body", "space"])
def test_user_torque_in_either_frame(frame):
    """A torque fixed in space (e.g. a thruster aligned with an inertial axis) written both ways."""
    q = jnp.asarray(random_quats(6, 8), DTYPE)
    w = jnp.asarray(np.random.default_rng(6).normal(size=(8, 3)), DTYPE)
    m_space = jnp.asarray([0.3, -0.1, 0.2], DTYPE)

    def space_fn(t, qq, ww, args):
        return jnp.broadcast_to(args * m_space, ww.shape) + 0.1 * ww  # depends on w_s too

    def body_fn(t, qq, ww, args):
        ws = jq.rotate(qq, ww)
        return jq.rotate(jq.conjugate(qq), jnp.broadcast_to(args * m_space, ws.shape) + 0.1 * ws)

    fn = jq.as_body_torque(space_fn if frame == "space" else body_fn, frame)
    ref = body_fn(0.0, q, w, 2.0)
    assert_close(jax.jit(fn)(0.0, q, w, 2.0), ref, tol=1e-12 if X64 else 1e-5)
    # differentiable in its parameters through the wrapper
    g = jax.grad(lambda a: jnp.sum(fn(0.0, q, w, a)))(2.0)
    assert np.isfinite(float(g))


def test_torque_function_with_a_wrong_output_shape_is_named():
    def thruster(t, q, w, args):
        return jnp.zeros(q.shape)  # (..., 4): wrong

    with pytest.raises(
        ValueError, match=r"argument 'thruster\(t, q, omega, args\)' must be a 3-vector array shaped \(\.\.\., 3\)"
    ):
        jq.as_body_torque(thruster)(0.0, jq.identity((), DTYPE), jnp.zeros(3, DTYPE), None)
    with pytest.raises(ValueError, match="argument 'frame'"):
        jq.as_body_torque(thruster, "inertial")
    with pytest.raises(TypeError, match="torque function"):
        jq.as_body_torque(3.0)
