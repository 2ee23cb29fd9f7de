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
