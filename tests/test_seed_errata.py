"""Tasora (2016) section 6-7 relations checked by autodiff along a smooth attitude curve.

Each printed relation is evaluated with q(t), q'(t), q''(t) from jax.jacfwd; the
ones listed in docs/seed-errata.md are shown to fail as printed and to hold as
corrected. Float64 only: these are identities to rounding.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxquat as jq
from helpers import X64

pytestmark = pytest.mark.skipif(not X64, reason="identities checked to rounding in float64")

M, C = jq.multiply, jq.conjugate


def _curve(t):
    return jq.from_rotvec(jnp.stack([0.3 * t + 0.1 * t**2, jnp.sin(t), 0.5 * jnp.cos(2 * t)]))


def _F_plus(q):  # Tasora (29b)
    q0, q1, q2, q3 = q
    return jnp.array([[q1, q0, -q3, q2], [q2, q3, q0, -q1], [q3, -q2, q1, q0]])


def _F_minus(q):  # Tasora (29c)
    q0, q1, q2, q3 = q
    return jnp.array([[q1, q0, q3, -q2], [q2, -q3, q0, q1], [q3, q2, -q1, q0]])


@pytest.fixture(scope="module")
def state():
    t = 0.7
    q = _curve(t)
    qd = jax.jacfwd(_curve)(t)
    qdd = jax.jacfwd(jax.jacfwd(_curve))(t)
    wl = 2 * M(C(q), qd)
    al = jax.jacfwd(lambda s: 2 * M(C(_curve(s)), jax.jacfwd(_curve)(s)))(t)
    ao = jax.jacfwd(lambda s: 2 * M(jax.jacfwd(_curve)(s), C(_curve(s))))(t)
    return q, qd, qdd, wl, al, ao


def test_A_factorisation_and_unit_identities(state):
    q = state[0]
    assert np.allclose(_F_plus(q) @ _F_minus(q).T, jq.to_matrix(q), atol=1e-15)  # (29a)
    assert np.allclose(_F_plus(q) @ _F_plus(q).T, np.eye(3), atol=1e-15)  # (38a)
    qs = C(q)
    assert np.allclose(_F_minus(q).T @ _F_minus(q), np.eye(4) - np.outer(qs, qs), atol=1e-15)  # (38b)


def test_erratum_before_41_F_minus_annihilates_q_conjugate(state):
    q = state[0]
    assert np.abs(_F_minus(q) @ q).max() > 0.1  # printed "[F(q)-] q = 0": false
    assert np.allclose(_F_minus(q) @ C(q), 0.0, atol=1e-15)  # corrected: [F(q)-] q* = 0


def test_angular_velocity_matrix_forms(state):
    q, qd, _, wl, _, _ = state
    assert np.allclose(2 * _F_plus(C(q)) @ qd, wl[1:], atol=1e-15)  # (42a)
    assert np.allclose(-2 * _F_minus(q) @ C(qd), wl[1:], atol=1e-15)  # (42a)
    assert np.allclose(0.5 * _F_plus(C(q)).T @ wl[1:], qd, atol=1e-15)  # (48b)


def test_erratum_table2_alpha_local(state):
    q, qd, qdd, _, al, ao = state
    printed = 2 * M(C(qd), qdd) + 2 * M(C(q), qd)
    corrected = 2 * M(C(qd), qd) + 2 * M(C(q), qdd)  # = eq. (50b)
    assert np.abs(printed - al).max() > 0.1
    assert np.allclose(corrected, al, atol=1e-14)
    assert np.allclose(2 * M(qdd, C(q)) + 2 * M(qd, C(qd)), ao, atol=1e-14)  # (50a) as printed


def test_tasora_algorithm_1_as_printed():
    """Algorithm 1, transcribed literally, agrees with jaxquat.from_matrix on every branch."""

    def algorithm_1(A):
        tr = A[0, 0] + A[1, 1] + A[2, 2]
        q = np.zeros(4)
        if tr >= 0:
            s = np.sqrt(tr + 1)
            q[0] = 0.5 * s
            s = 0.5 / s
            q[1], q[2], q[3] = (A[2, 1] - A[1, 2]) * s, (A[0, 2] - A[2, 0]) * s, (A[1, 0] - A[0, 1]) * s
            return q
        i = 0
        if A[1, 1] > A[0, 0]:
            i = 2 if A[2, 2] > A[1, 1] else 1
        elif A[2, 2] > A[0, 0]:
            i = 2
        if i == 0:
            s = np.sqrt(A[0, 0] - A[1, 1] - A[2, 2] + 1)
            q[1] = 0.5 * s
            s = 0.5 / s
            q[2], q[3], q[0] = (A[0, 1] + A[1, 0]) * s, (A[2, 0] + A[0, 2]) * s, (A[2, 1] - A[1, 2]) * s
        elif i == 1:
            s = np.sqrt(A[1, 1] - A[2, 2] - A[0, 0] + 1)
            q[2] = 0.5 * s
            s = 0.5 / s
            q[3], q[1], q[0] = (A[1, 2] + A[2, 1]) * s, (A[0, 1] + A[1, 0]) * s, (A[0, 2] - A[2, 0]) * s
        else:
            s = np.sqrt(A[2, 2] - A[0, 0] - A[1, 1] + 1)
            q[3] = 0.5 * s
            s = 0.5 / s
            q[1], q[2], q[0] = (A[2, 0] + A[0, 2]) * s, (A[1, 2] + A[2, 1]) * s, (A[1, 0] - A[0, 1]) * s
        return q

    rng = np.random.default_rng(0)
    qs = rng.normal(size=(200, 4))
    qs[:3] = [[0, 1, 0, 0], [0, 0, 1, 0], [0.1, 0, 0, 1]]
    qs /= np.linalg.norm(qs, axis=-1, keepdims=True)
    mats = np.asarray(jq.to_matrix(jnp.asarray(qs)))
    ours = np.asarray(jq.from_matrix(jnp.asarray(mats)))
    for A, o in zip(mats, ours):
        ref = algorithm_1(A)
        assert min(np.abs(ref - o).max(), np.abs(ref + o).max()) < 1e-12


# ------------------------------------------------ Tasora (53): acceleration of a moving point


def test_erratum_tasora_53_point_acceleration():
    """p'' for a point moving in the body frame; both printed versions fail, the corrected one holds."""
    r0 = jnp.asarray([0.4, -1.0, 0.7])

    def p_local(s):
        return jnp.concatenate([jnp.zeros(1), r0 * (1 + 0.5 * s) + jnp.sin(s) * r0[::-1]])

    t = 0.7
    q, qd, qdd = _curve(t), jax.jacfwd(_curve)(t), jax.jacfwd(jax.jacfwd(_curve))(t)
    p, pd, pdd = p_local(t), jax.jacfwd(p_local)(t), jax.jacfwd(jax.jacfwd(p_local))(t)
    truth = jax.jacfwd(jax.jacfwd(lambda s: M(M(_curve(s), p_local(s)), C(_curve(s)))))(t)

    def tri(a, b, c):
        return M(M(a, b), c)

    printed_53 = (
        tri(qdd, p, C(q))
        + tri(q, pdd, C(q))
        + tri(q, p, C(qdd))
        + 2 * tri(qd, pd, C(q))
        + 2 * tri(qd, pd, C(q))
        + 2 * tri(q, pd, C(qd))
    )
    printed_table2 = (
        tri(qdd, p, C(q))
        + tri(q, pdd, C(q))
        + tri(q, pd, C(qd))
        + 2 * tri(qd, p, C(qd))
        + 2 * tri(qd, pd, C(q))
        + 2 * tri(q, pd, C(qd))
    )
    corrected = (
        tri(qdd, p, C(q))
        + tri(q, pdd, C(q))
        + tri(q, p, C(qdd))
        + 2 * tri(qd, pd, C(q))
        + 2 * tri(qd, p, C(qd))
        + 2 * tri(q, pd, C(qd))
    )
    assert np.abs(printed_53 - truth).max() > 0.1
    assert np.abs(printed_table2 - truth).max() > 0.1
    assert np.allclose(corrected, truth, atol=1e-14)
    # and jaxquat.point_acceleration, which is its vector form
    wl = jq.omega_from_qdot(q, qd)
    al = jq.alpha_from_qddot(q, qd, qdd)
    assert np.allclose(jq.point_acceleration(q, wl, al, p[1:], pd[1:], pdd[1:]), truth[1:], atol=1e-14)


# ------------------------------------------------ Chou: the dots the transcription lost


def _chou_state():
    t = 0.7
    q, qd, qdd = _curve(t), jax.jacfwd(_curve)(t), jax.jacfwd(jax.jacfwd(_curve))(t)
    inertia = jnp.asarray([[2.0, 0.3, -0.1], [0.3, 3.0, 0.2], [-0.1, 0.2, 4.0]])
    torque = jnp.asarray([0.3, -0.2, 0.5])
    return q, qd, qdd, inertia, torque


@pytest.mark.parametrize("frame", ["body", "space"])
def test_erratum_chou_45_51_angular_velocity_matrix(frame):
    """Printed '2 E E^T' is the identity times 2; the angular-velocity matrix needs one factor differentiated."""
    q, qd, *_ = _chou_state()
    e, ed = jq.rate_matrix(q, frame), jq.rate_matrix(qd, frame)
    w = jq.omega_from_qdot(q, qd, frame)
    assert np.allclose(2 * e @ e.T, 2 * np.eye(3), atol=1e-15)  # what the undotted print says
    restored = 2 * ed @ e.T if frame == "space" else 2 * e @ ed.T  # (45): dE+ E+^T; (51): E- dE-^T
    assert np.allclose(restored, jq.hat(w), atol=1e-14)


@pytest.mark.parametrize("frame", ["body", "space"])
def test_erratum_chou_75_third_term(frame):
    """(75) as transcribed, '-2 E^T I^-1 (E)(E)^T I E pdot', reduces to -2 pdot: wrong. With
    E dE^T (body) / dE E^T (space) restored it equals the equations of motion."""
    q, qd, _, inertia, torque = _chou_state()
    e, ed = jq.rate_matrix(q, frame), jq.rate_matrix(qd, frame)
    i = inertia if frame == "body" else jq.rotate_inertia(q, inertia)
    ii = jnp.linalg.inv(i)
    head = 0.5 * e.T @ ii @ torque - (qd @ qd) * q
    truth = jq.euler_parameter_acceleration(q, qd, inertia, torque, frame)
    printed = head - 2 * e.T @ ii @ (e @ e.T) @ i @ e @ qd
    middle = e @ ed.T if frame == "body" else ed @ e.T
    restored = head - 2 * e.T @ ii @ middle @ i @ e @ qd
    assert np.abs(printed - truth).max() > 0.1
    assert np.allclose(restored, truth, atol=1e-14)


@pytest.mark.parametrize("frame", ["body", "space"])
def test_erratum_chou_72_four_space_form(frame):
    """(72) as transcribed, 'pddot = 1/2 pbar Wdot - (pbar pbar^T) pdot', has pbar pbar^T = I.
    Restored: the second factor is the matrix of pdot, i.e. -(pbar pdotbar^T) pdot = -|pdot|^2 p."""
    q, qd, qdd, *_ = _chou_state()
    mat = jq.right_matrix if frame == "space" else jq.left_matrix  # pbar (space), p-plus (body)
    a4 = jnp.concatenate([jnp.zeros(1), jq.alpha_from_qddot(q, qd, qdd, frame)])
    printed = 0.5 * mat(q) @ a4 - (mat(q) @ mat(q).T) @ qd
    restored = 0.5 * mat(q) @ a4 - (mat(q) @ mat(qd).T) @ qd
    assert np.abs(printed - qdd).max() > 0.1
    assert np.allclose(restored, qdd, atol=1e-14)


# ------------------------------------------------ Schwab (23): the constraint row's right-hand side


def test_erratum_schwab_23_constraint_row():
    """(23) prints four right-hand-side entries for five unknowns. With the fifth set to 0
    (as an implementer reading it literally might), qddot breaks q.qddot = -|qdot|^2;
    -2 qdot.qdot is right (the norm constraint (20) differentiated twice)."""
    q, qd, _, inertia, torque = _chou_state()
    lhs, rhs = jq.euler_parameter_augmented_system(q, qd, inertia, torque)
    truth = jq.euler_parameter_acceleration(q, qd, inertia, torque)
    zero_row = jnp.linalg.solve(lhs, rhs.at[4].set(0.0))
    assert np.abs(zero_row[:4] - truth).max() > 0.1
    corrected = jnp.linalg.solve(lhs, rhs)
    assert np.allclose(rhs[4], -2 * qd @ qd, atol=0)
    assert np.allclose(corrected[:4], truth, atol=1e-13)
    assert np.isclose(corrected[4], jq.norm_constraint_multiplier(q, qd, inertia), atol=1e-13)  # (24)
