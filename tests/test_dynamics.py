"""Dynamics: Euler's equations, the Euler-parameter equations of motion (Chou's closed form,
Schwab's augmented system), generalised forces. References are independent: autodiff of the
angular momentum along a curve, a Lagrangian derived by autodiff, the symmetric top in closed
form, and literal transcriptions of the printed matrix equations (with the corrections of
docs/seed-errata.md)."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given

import jaxquat as jq
from helpers import (
    DTYPE,
    X64,
    assert_close,
    attitude_curve,
    curve_coefficients,
    random_inertias,
    seeds,
    time_derivatives,
)

FRAMES = ["body", "space"]
TOL_D = 1e-10 if X64 else 2e-4  # relative to the largest entry of the compared quantity
mv = lambda m, v: jnp.einsum("...ij,...j->...i", m, v)  # noqa: E731
T = lambda m: jnp.swapaxes(m, -1, -2)  # noqa: E731


def _close(a, b, what, tol=TOL_D, scale=None):
    """|a - b| <= tol * scale, scale defaulting to max(1, max|b|) (pass the size of the terms when b is 0)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    scale = max(1.0, float(np.abs(b).max())) if scale is None else scale
    assert_close(a / scale, b / scale, tol=tol, what=what)


@jax.jit
def _curve(c, inertia):
    """Along q(t): q, qdot, qddot, w and alpha in both frames, and dH/dt (space) by autodiff."""
    t = jnp.asarray(0.41, DTYPE)
    q, qd, qdd = time_derivatives(lambda s: attitude_curve(c, s), t, 2)
    wb = jq.omega_from_qdot(q, qd)
    ab = jq.alpha_from_qddot(q, qd, qdd)

    def h_space(s):
        qs, qds = attitude_curve(c, s), jax.jacfwd(lambda u: attitude_curve(c, u))(s)
        return jq.rotate(qs, mv(inertia, jq.omega_from_qdot(qs, qds)))  # A I w_b

    hdot = jax.jacfwd(h_space)(t)
    return dict(
        q=q,
        qd=qd,
        qdd=qdd,
        w={"body": wb, "space": jq.rotate(q, wb)},
        al={"body": ab, "space": jq.rotate(q, ab)},
        hdot_space=hdot,
    )


def _data(seed):
    inertia = jnp.asarray(random_inertias(seed), DTYPE)
    return _curve(jnp.asarray(curve_coefficients(seed), DTYPE), inertia), inertia


def _random_state(seed):
    """Unit q, tangent qdot, a physical full inertia and a torque."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(16, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    qd = rng.normal(size=(16, 4))
    qd -= (qd * q).sum(-1, keepdims=True) * q
    return (
        jnp.asarray(q, DTYPE),
        jnp.asarray(qd, DTYPE),
        jnp.asarray(random_inertias(seed), DTYPE),
        jnp.asarray(rng.normal(size=(16, 3)), DTYPE),
    )


# ------------------------------------------------------------------ Euler's equations


@pytest.mark.parametrize("frame", FRAMES)
def test_torque_is_the_rate_of_angular_momentum(frame):
    """Newton's law dH_s/dt = M_s, with dH_s/dt from autodiff: checks inverse_dynamics, and
    angular_acceleration as its inverse ([S] (19), [C] (62), (66))."""
    s, inertia = _data(1)
    m = jq.inverse_dynamics(s["q"], s["w"][frame], s["al"][frame], inertia, frame)
    m_space = m if frame == "space" else jq.rotate(s["q"], m)
    _close(m_space, s["hdot_space"], f"M = dH/dt ({frame})")
    _close(jq.angular_acceleration(s["q"], s["w"][frame], inertia, m, frame), s["al"][frame], f"Euler {frame}")


def test_symmetric_top_in_closed_form():
    """Torque-free axisymmetric body: w = (a cos(lt), -a sin(lt), w3), l = (It - I3) w3 / It."""
    it, i3, a, w3 = 2.0, 3.5, 0.7, 1.3
    lam = (it - i3) * w3 / it
    ts = jnp.linspace(0.0, 5.0, 16, dtype=DTYPE)
    w = jnp.stack([a * jnp.cos(lam * ts), -a * jnp.sin(lam * ts), jnp.full_like(ts, w3)], -1)
    wdot = jnp.stack([-a * lam * jnp.sin(lam * ts), -a * lam * jnp.cos(lam * ts), jnp.zeros_like(ts)], -1)
    inertia = jnp.broadcast_to(jnp.diag(jnp.asarray([it, it, i3], DTYPE)), (16, 3, 3))
    _close(jq.angular_acceleration(jq.identity(16, DTYPE), w, inertia), wdot, "symmetric top")


@given(seed=seeds)
def test_torque_free_motion_conserves_energy_and_momentum_magnitude(seed):
    q, qd, inertia, _ = _random_state(seed)
    w = jq.omega_from_qdot(q, qd)
    a = jq.angular_acceleration(q, w, inertia)
    h = mv(inertia, w)
    size = float(jnp.abs(h).max() * jnp.abs(mv(inertia, a)).max())
    _close(jnp.sum(w * mv(inertia, a), -1), np.zeros(16), "dT/dt = w.I a = 0", scale=size)
    _close(jnp.sum(h * mv(inertia, a), -1), np.zeros(16), "d|H|^2/dt = 2 H.I a = 0", scale=10 * size)


def test_angular_momentum_and_energy_in_both_frames():
    q, qd, inertia, _ = _random_state(3)
    wb = jq.omega_from_qdot(q, qd)
    ws = jq.omega_from_qdot(q, qd, "space")
    hb = jq.angular_momentum(q, wb, inertia)
    _close(hb, mv(inertia, wb), "H_b = I w_b")
    _close(jq.angular_momentum(q, ws, inertia, "space"), jq.rotate(q, hb), "H_s = A H_b")
    # [C] (60)-(61): four-space H0 = 2 Ihat0 (qdot q*); scalar part 2 k q.qdot = 0
    i0 = jq.rotate_inertia(q, inertia)
    h4 = 2 * mv(jq.quaternion_inertia(i0), jq.multiply(qd, jq.conjugate(q)))
    _close(h4[..., 0], np.zeros(16), "scalar part of Chou (61)")
    _close(h4[..., 1:], jq.angular_momentum(q, ws, inertia, "space"), "Chou (60)-(61)")
    _close(2 * mv(i0, mv(jq.rate_matrix(q, "space"), qd)), h4[..., 1:], "H0 = 2 I0 E+ qdot")
    t = jq.kinetic_energy(q, wb, inertia)
    _close(jq.kinetic_energy(q, ws, inertia, "space"), t, "T frame-independent")
    _close(0.5 * jnp.sum(wb * mv(inertia, wb), -1), t, "T = w.Iw/2")


# ------------------------------------------------------------------ Euler-parameter equations


@pytest.mark.parametrize("frame", FRAMES)
def test_euler_parameter_acceleration_reproduces_the_curve(frame):
    """The torque that drives q(t) (from dH/dt), fed to the EOM, gives back q(t)'s qddot."""
    s, inertia = _data(2)
    m_space = s["hdot_space"]
    m = m_space if frame == "space" else jq.rotate(jq.conjugate(s["q"]), m_space)
    _close(jq.euler_parameter_acceleration(s["q"], s["qd"], inertia, m, frame), s["qdd"], f"qddot {frame}")
    _close(jq.euler_parameter_torque(s["q"], s["qd"], s["qdd"], inertia, frame), m, f"torque {frame}")


@pytest.mark.parametrize("frame", FRAMES)
@given(seed=seeds)
def test_newton_euler_chou_and_schwab_agree(frame, seed):
    q, qd, inertia, torque = _random_state(seed)
    qdd = jq.euler_parameter_acceleration(q, qd, inertia, torque, frame)
    # Newton-Euler on (q, w): qddot = 1/2 qdot (0, w_b) + 1/2 q (0, a_b)  ([T] (49b))
    wb = jq.omega_from_qdot(q, qd)
    mb = torque if frame == "body" else jq.rotate(jq.conjugate(q), torque)
    ab = jq.angular_acceleration(q, wb, inertia, mb)
    pure = lambda v: jnp.concatenate([jnp.zeros_like(v[..., :1]), v], -1)  # noqa: E731
    _close(qdd, 0.5 * jq.multiply(qd, pure(wb)) + 0.5 * jq.multiply(q, pure(ab)), "vs Newton-Euler")
    # Schwab (23): solve the augmented 5x5 system
    lhs, rhs = jq.euler_parameter_augmented_system(q, qd, inertia, torque, frame)
    sol = jnp.linalg.solve(lhs, rhs[..., None])[..., 0]
    _close(sol[..., :4], qdd, "vs Schwab (23)", tol=100 * TOL_D)
    _close(sol[..., 4], jq.norm_constraint_multiplier(q, qd, inertia), "lambda vs (24)", tol=100 * TOL_D)


@pytest.mark.parametrize("frame", FRAMES)
def test_chou_75_and_78_as_transcribed_with_dots_restored(frame):
    q, qd, inertia, torque = _random_state(5)
    e, ed = jq.rate_matrix(q, frame), jq.rate_matrix(qd, frame)
    i = inertia if frame == "body" else jq.rotate_inertia(q, inertia)
    ii = jnp.linalg.inv(i)
    speed = jnp.sum(qd * qd, -1)[..., None]
    middle = e @ T(ed) if frame == "body" else ed @ T(e)  # hat(w)/2 in three-space
    chou75 = 0.5 * mv(T(e) @ ii, torque) - speed * q - 2 * mv(T(e) @ ii @ middle @ i @ e, qd)
    sign78 = 1.0 if frame == "body" else -1.0  # (78) prints + for body, - for space: both right
    chou78 = 0.5 * mv(T(e) @ ii, torque) - speed * q + sign78 * 2 * mv((T(e) @ ii @ e) @ (T(ed) @ i @ ed), q)
    ours = jq.euler_parameter_acceleration(q, qd, inertia, torque, frame)
    _close(chou75, ours, f"Chou (75) {frame}", tol=100 * TOL_D)
    _close(chou78, ours, f"Chou (78) {frame}", tol=100 * TOL_D)
    # (65)/(69): T = 2 I E qddot + 4 [hat(w)/2] I E qdot
    chou65 = 2 * mv(i @ e, ours) + 4 * mv(middle @ i @ e, qd)
    _close(chou65, torque, f"Chou (65)/(69) {frame}", tol=100 * TOL_D)


def test_lagrangian_derivation_by_autodiff():
    """Independent derivation: L(q, qdot) = 1/2 qdot^T M(q) qdot with M from the mass matrix;
    d/dt dL/dqdot - dL/dq - f must be parallel to q (the constraint force) along our qddot."""
    q, qd, inertia, torque = _random_state(7)
    qdd = jq.euler_parameter_acceleration(q, qd, inertia, torque)

    def lagrangian(qq, qqd):
        return 0.5 * jnp.sum(qqd * mv(jq.euler_parameter_mass_matrix(qq, inertia), qqd))

    dl_dq = jax.grad(lagrangian, 0)(q, qd)
    p = lambda qq, qqd: jax.grad(lagrangian, 1)(qq, qqd)  # noqa: E731
    _, pdot = jax.jvp(p, (q, qd), (qd, qdd))
    resid = pdot - dl_dq - jq.generalized_force(q, torque)
    tangential = resid - jnp.sum(resid * q, -1)[..., None] * q
    _close(
        tangential,
        np.zeros((16, 4)),
        "Lagrange equations up to the constraint force",
        scale=float(jnp.abs(pdot).max() + jnp.abs(dl_dq).max()),
    )
    # and the kinetic energy of the mass matrix is the rigid-body kinetic energy
    t_mass = 0.5 * jnp.sum(qd * mv(jq.euler_parameter_mass_matrix(q, inertia), qd), -1)
    _close(t_mass, jq.kinetic_energy(q, jq.omega_from_qdot(q, qd), inertia), "1/2 qdot M qdot = T")
    _close(mv(jq.euler_parameter_mass_matrix(q, inertia), q), np.zeros((16, 4)), "M q = 0")


def test_schwab_24_multiplier_literal_form():
    q, qd, inertia, _ = _random_state(8)
    qdm = jq.left_matrix(qd)
    j4 = jnp.zeros((16, 4, 4), DTYPE).at[:, 1:, 1:].set(inertia)
    literal = 4 * jnp.sum(q * mv(qdm @ j4 @ T(qdm), q), -1)
    lam = jq.norm_constraint_multiplier(q, qd, inertia)
    _close(literal, lam, "4 q^T Qd J Qd^T q")
    _close(lam, 2 * jq.kinetic_energy(q, jq.omega_from_qdot(q, qd), inertia), "lambda = 2T")


@pytest.mark.parametrize("frame", FRAMES)
@given(seed=seeds)
def test_generalized_force_virtual_power(frame, seed):
    """[S] (25): f . dq = M . dw for every virtual dq, with dw = 2 vec(q* dq) (body) or 2 vec(dq q*)."""
    q, _, _, torque = _random_state(seed)
    dq = jnp.asarray(np.random.default_rng(seed + 1).normal(size=(16, 4)), DTYPE)
    f = jq.generalized_force(q, torque, frame)
    dw = jq.omega_from_qdot(q, dq, frame)  # the linear map dq -> dw (scalar part dropped)
    _close(jnp.sum(f * dq, -1), jnp.sum(torque * dw, -1), "virtual power")
    _close(jq.torque_from_generalized_force(q, f, frame), torque, "round trip")
    # body and space forms give the same generalised force for the same physical torque
    other = "space" if frame == "body" else "body"
    conv = jq.rotate(q, torque) if frame == "body" else jq.rotate(jq.conjugate(q), torque)
    _close(jq.generalized_force(q, conv, other), f, "frame independence")


def test_schwab_23_left_hand_side_is_nonsingular_where_mass_matrix_is_not():
    q, qd, inertia, torque = _random_state(9)
    lhs, _ = jq.euler_parameter_augmented_system(q, qd, inertia, torque)
    sv = np.linalg.svd(np.asarray(lhs, np.float64), compute_uv=False)
    assert sv.min() > 1e-3 * sv.max()
    mass_sv = np.linalg.svd(np.asarray(jq.euler_parameter_mass_matrix(q, inertia), np.float64), compute_uv=False)
    assert np.all(mass_sv[:, 2] > 1e-2 * mass_sv[:, 0])  # rank 3 ...
    assert np.all(mass_sv[:, 3] < (1e-12 if X64 else 1e-5) * mass_sv[:, 0])  # ... and singular


@pytest.mark.skipif(not X64, reason="a lowering test: its verdict does not depend on the dtype")
def test_one_inertia_for_a_batch_is_read_as_it_is_not_broadcast_to_the_batch():
    """A tensor ``(3, 3)`` shared by a batch of 1000 bodies reaches the kernels as it is (its
    entries broadcast inside their loops): no broadcast to ``(1000, 3, 3)`` in the programs, where
    the broadcast tensor was written to memory and read back (``angular_momentum`` at 10^6,
    float32: 16.9 -> 5.0 ms); the same for ``invariants``, ``gravity_gradient_torque`` and
    ``rotate_inertia``. The values are those of a tensor per body."""
    q = jnp.ones((1000, 4), DTYPE)
    w = jnp.ones((1000, 3), DTYPE)
    shared = jnp.asarray([[2.0, 0.1, 0.2], [0.1, 3.0, 0.3], [0.2, 0.3, 4.0]], DTYPE)
    per_body_tensors = jnp.broadcast_to(shared, (1000, 3, 3))
    calls = {
        "angular_momentum": lambda j: jq.angular_momentum(q, w, j, frame="space"),
        "kinetic_energy": lambda j: jq.kinetic_energy(q, w, j),
        "angular_acceleration": lambda j: jq.angular_acceleration(q, w, j, w, frame="space"),
        "inverse_dynamics": lambda j: jq.inverse_dynamics(q, w, w, j),
        "euler_parameter_acceleration": lambda j: jq.euler_parameter_acceleration(q, q, j, w),
        "euler_parameter_torque": lambda j: jq.euler_parameter_torque(q, q, q, j),
        "euler_parameter_mass_matrix": lambda j: jq.euler_parameter_mass_matrix(q, j),
        "euler_parameter_augmented_system": lambda j: jq.euler_parameter_augmented_system(q, q, j, w),
        "norm_constraint_multiplier": lambda j: jq.norm_constraint_multiplier(q, q, j),
        "invariants": lambda j: jq.invariants(q, w, j),
        "rotate_inertia": lambda j: jq.rotate_inertia(q, j),
        "gravity_gradient_torque": lambda j: jq.gravity_gradient_torque(q, w + 5.0, j),
        "gravity_gradient_torque, mu an array": lambda j: jq.gravity_gradient_torque(q, w + 5.0, j, jnp.ones(1000)),
    }
    broadcast = re.compile(r"broadcast_in_dim[^\n]*-> tensor<1000x3x3")
    for name, call in calls.items():
        assert not broadcast.search(jax.jit(call).lower(shared).as_text()), name
        for a, b in zip(jax.tree.leaves(jax.jit(call)(shared)), jax.tree.leaves(call(per_body_tensors))):
            np.testing.assert_allclose(a, b, rtol=1e-13, err_msg=name)
