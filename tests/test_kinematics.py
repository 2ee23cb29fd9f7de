"""Kinematics against autodiff: every relation is evaluated on q(t) from a smooth curve,
with qdot, qddot, angular velocity and acceleration obtained by differentiating in t."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given

import jaxquat as jq
from helpers import (
    DTYPE,
    TOL,
    X64,
    assert_close,
    attitude_curve,
    curve_coefficients,
    on_device,
    seeds,
    time_derivatives,
)

FRAMES = ["body", "space"]
T0 = 0.37


@jax.jit
def _curve_state(c, scale):
    """q, qdot, qddot and the true body/space angular velocity and acceleration (from R(t))."""
    t = jnp.asarray(T0, DTYPE)
    q, qd, qdd = time_derivatives(lambda s: attitude_curve(c, s, scale), t, 2)
    a, ad, add = time_derivatives(lambda s: jq.to_matrix(jq.normalize(attitude_curve(c, s, scale))), t, 2)
    at = jnp.swapaxes(a, -1, -2)
    wb = jq.vee(at @ ad)  # R^T dR/dt = hat(w_b)
    ws = jq.vee(ad @ at)  # dR/dt R^T = hat(w_s)
    ab = jq.vee(at @ add - (at @ ad) @ (at @ ad))  # d/dt (R^T dR) = R^T d2R - (R^T dR)^2
    as_ = jnp.einsum("...ij,...j->...i", a, ab)
    return dict(q=q, qd=qd, qdd=qdd, a=a, ad=ad, add=add, w={"body": wb, "space": ws}, al={"body": ab, "space": as_})


def _jit_state(seed, scale):
    """One compiled function for every seed (the seed only changes the coefficients)."""
    return _curve_state(jnp.asarray(curve_coefficients(seed), DTYPE), jnp.asarray(float(scale), DTYPE))


TOL_K = 1e-11 if X64 else 5e-5  # quantities of O(1)-O(10) on the test curves


def _close(a, b, what, tol=TOL_K):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    scale = max(1.0, float(np.abs(b).max()))
    assert_close(a / scale, b / scale, tol=tol, what=what)


@pytest.mark.parametrize("frame", FRAMES)
@given(seed=seeds)
def test_omega_and_qdot_against_autodiff(frame, seed):
    s = _jit_state(seed % 97, False)
    _close(jq.omega_from_qdot(s["q"], s["qd"], frame), s["w"][frame], f"omega_from_qdot {frame}")
    _close(jq.qdot_from_omega(s["q"], s["w"][frame], frame), s["qd"], f"qdot_from_omega {frame}")


@pytest.mark.parametrize("frame", FRAMES)
@given(seed=seeds)
def test_alpha_and_qddot_against_autodiff(frame, seed):
    s = _jit_state(seed % 97, False)
    _close(jq.alpha_from_qddot(s["q"], s["qd"], s["qdd"], frame), s["al"][frame], f"alpha_from_qddot {frame}")
    _close(jq.qddot_from_alpha(s["q"], s["qd"], s["al"][frame], frame), s["qdd"], f"qddot_from_alpha {frame}")


@pytest.mark.parametrize("frame", FRAMES)
def test_non_unit_quaternion_curve_gives_the_rotation_rates(frame):
    """A curve s(t) q(t) with varying |q|: omega and alpha are those of the rotation q/|q|."""
    s = _jit_state(5, True)
    _close(jq.omega_from_qdot(s["q"], s["qd"], frame), s["w"][frame], f"omega {frame} non-unit")
    _close(jq.alpha_from_qddot(s["q"], s["qd"], s["qdd"], frame), s["al"][frame], f"alpha {frame} non-unit")


@pytest.mark.parametrize("frame", FRAMES)
@given(seed=seeds)
def test_round_trips_for_any_nonzero_q(frame, seed):
    rng = np.random.default_rng(seed)
    q = jnp.asarray(rng.normal(size=(16, 4)) * rng.uniform(0.2, 3.0, (16, 1)), DTYPE)  # not unit
    qd = jnp.asarray(rng.normal(size=(16, 4)), DTYPE)  # not tangent either
    w = jnp.asarray(rng.normal(size=(16, 3)), DTYPE)
    a = jnp.asarray(rng.normal(size=(16, 3)), DTYPE)
    _close(jq.omega_from_qdot(q, jq.qdot_from_omega(q, w, frame), frame), w, "omega(qdot(w))", 20 * TOL)
    _close(jq.alpha_from_qddot(q, qd, jq.qddot_from_alpha(q, qd, a, frame), frame), a, "alpha(qddot(a))", 50 * TOL)
    # qdot_from_omega is tangent; qddot_from_alpha keeps d2|q|^2/dt2 = 2 q.qddot + 2|qdot|^2 = 0.
    assert_close(jnp.sum(q * jq.qdot_from_omega(q, w, frame), -1), np.zeros(16), tol=20 * TOL)
    qdd = jq.qddot_from_alpha(q, qd, a, frame)
    _close(jnp.sum(q * qdd, -1), -jnp.sum(qd * qd, -1), "norm constraint twice differentiated", 50 * TOL)


def test_body_and_space_are_related_by_the_rotation():
    s = _jit_state(11, False)
    _close(jq.rotate(s["q"], s["w"]["body"]), s["w"]["space"], "w_s = A w_b [C] (53)")
    _close(jq.rotate(s["q"], s["al"]["body"]), s["al"]["space"], "a_s = A a_b [C] (59)")


# ------------------------------------------------------------ 3x4 rate matrices


@pytest.mark.parametrize("frame", FRAMES)
def test_rate_matrix_maps_and_identities(frame):
    s = _jit_state(3, False)
    q, qd = s["q"], s["qd"]
    e = jq.rate_matrix(q, frame)
    eye3 = np.eye(3)
    _close(2 * jnp.einsum("...ij,...j->...i", e, qd), s["w"][frame], "w = 2 E qdot")
    _close(0.5 * jnp.einsum("...ji,...j->...i", e, s["w"][frame]), qd, "qdot = 1/2 E^T w")
    _close(e @ jnp.swapaxes(e, -1, -2), np.broadcast_to(eye3, e.shape[:-2] + (3, 3)), "E E^T = I ([T] 38a)")
    qqT = q[..., :, None] * q[..., None, :]
    _close(jnp.swapaxes(e, -1, -2) @ e, np.eye(4) - np.asarray(qqT), "E^T E = I - q q^T ([T] 38b)")
    _close(jnp.einsum("...ij,...j->...i", e, q), np.zeros(e.shape[:-1]), "E q = 0")
    # [C] (A4)/(A11): E(qdot) q = -E(q) qdot (E is linear in q and E(q) q = 0 for all t)
    ed = jq.rate_matrix(qd, frame)
    _close(jnp.einsum("...ij,...j->...i", ed, q), -jnp.einsum("...ij,...j->...i", e, qd), "E(qdot) q = -E(q) qdot")
    # [C] (45)/(51): hat(w_s) = 2 (dE+/dt) E+^T, hat(w_b) = 2 E- (dE-/dt)^T
    lhs = 2 * (ed @ jnp.swapaxes(e, -1, -2) if frame == "space" else e @ jnp.swapaxes(ed, -1, -2))
    _close(lhs, jq.hat(s["w"][frame]), "angular-velocity matrix")


def test_rate_matrices_factor_the_rotation_matrix():
    s = _jit_state(4, False)
    eb, es = jq.rate_matrix(s["q"], "body"), jq.rate_matrix(s["q"], "space")
    _close(es @ jnp.swapaxes(eb, -1, -2), jq.to_matrix(s["q"]), "A = E+ E-^T ([C] 34, [T] 29a)")


def test_rate_matrix_entries_are_chou_25_26_and_tasora_F():
    q = jnp.asarray([0.5, -0.1, 0.7, 0.3], DTYPE)
    a0, a1, a2, a3 = np.asarray(q, np.float64)
    e_minus = np.array([[-a1, a0, a3, -a2], [-a2, -a3, a0, a1], [-a3, a2, -a1, a0]])  # [C] (25)
    e_plus = np.array([[-a1, a0, -a3, a2], [-a2, a3, a0, -a1], [-a3, -a2, a1, a0]])  # [C] (26)
    assert_close(jq.rate_matrix(q, "body"), e_minus, tol=0)
    assert_close(jq.rate_matrix(q, "space"), e_plus, tol=0)
    # Tasora (29b)/(29c) evaluated at q*: F(q*)+ is body, F(q*)- is space ([T] 42a, 43a).
    c0, c1, c2, c3 = a0, -a1, -a2, -a3
    f_plus = np.array([[c1, c0, -c3, c2], [c2, c3, c0, -c1], [c3, -c2, c1, c0]])
    f_minus = np.array([[c1, c0, c3, -c2], [c2, -c3, c0, c1], [c3, c2, -c1, c0]])
    assert_close(f_plus, e_minus, tol=0)
    assert_close(f_minus, e_plus, tol=0)


# ------------------------------------------------------------ rotation matrix and points


@pytest.mark.parametrize("frame", FRAMES)
def test_poisson_equation_and_second_derivative(frame):
    s = _jit_state(6, False)
    _close(jq.matrix_rate(s["q"], s["w"][frame], frame), s["ad"], f"dA/dt {frame}")
    _close(jq.matrix_acceleration(s["q"], s["w"][frame], s["al"][frame], frame), s["add"], f"d2A/dt2 {frame}")


@pytest.mark.parametrize("frame", FRAMES)
def test_point_velocity_and_acceleration_against_autodiff(frame):
    v, acc, v_fixed, a_fixed, r, rd, rdd, r0 = _point_references()
    st = _jit_state(8, False)
    w, al = st["w"][frame], st["al"][frame]
    _close(jq.point_velocity(st["q"], w, r, rd, frame=frame), v, "point velocity")
    _close(jq.point_acceleration(st["q"], w, al, r, rd, rdd, frame=frame), acc, "point acceleration")
    # body-fixed point (defaults)
    _close(jq.point_velocity(st["q"], w, r0, frame=frame), v_fixed, "fixed point velocity")
    _close(jq.point_acceleration(st["q"], w, al, r0, frame=frame), a_fixed, "fixed point acceleration")


@functools.cache
def _point_references():
    """The references of the point test, which do not depend on the frame: computed once for both
    parameters (each parameter compiled the same two programs: 1.4-1.7 s a pass). The space-frame
    velocity and acceleration of a point moving in the body frame, and of a body-fixed point, by
    forward-mode autodiff through the attitude curve, in one program; the point's own body-frame
    derivatives."""
    c = jnp.asarray(curve_coefficients(8), DTYPE)
    t = jnp.asarray(T0, DTYPE)
    r0 = jnp.asarray(np.random.default_rng(9).normal(size=(16, 3)), DTYPE)

    def r_body(s):  # a point moving in the body frame
        return r0 * (1 + 0.5 * s) + jnp.sin(s) * r0[:, ::-1]

    def references(s):
        _, v, acc = time_derivatives(lambda u: jq.rotate(attitude_curve(c, u), r_body(u)), s, 2)
        _, v_fixed, a_fixed = time_derivatives(lambda u: jq.rotate(attitude_curve(c, u), r0), s, 2)
        return v, acc, v_fixed, a_fixed, *time_derivatives(r_body, s, 2)

    return (*jax.jit(references)(t), r0)


def test_hat_and_vee():
    rng = np.random.default_rng(0)
    v = jnp.asarray(rng.normal(size=(16, 3)), DTYPE)
    x = jnp.asarray(rng.normal(size=(16, 3)), DTYPE)
    assert_close(jnp.einsum("...ij,...j->...i", jq.hat(v), x), np.cross(np.asarray(v), np.asarray(x)), tol=10 * TOL)
    assert_close(jq.vee(jq.hat(v)), v, tol=0)
    assert_close(jq.hat(v) + jnp.swapaxes(jq.hat(v), -1, -2), np.zeros((16, 3, 3)), tol=0)
    m = jnp.asarray(rng.normal(size=(16, 3, 3)), DTYPE)
    # vee of a non-skew matrix is the vector of its skew part
    assert_close(jq.vee(m), jq.vee(0.5 * (m - jnp.swapaxes(m, -1, -2))), tol=10 * TOL)


@pytest.mark.parametrize(
    "call",
    [
        lambda: jq.qdot_from_omega(jnp.zeros(4), jnp.zeros(3), frame="world"),
        lambda: jq.omega_from_qdot(jnp.zeros(4), jnp.zeros(4), frame="Body"),
        lambda: jq.rate_matrix(jnp.zeros(4), frame=None),
    ],
)
def test_bad_frame_raises(call):
    with pytest.raises(ValueError, match="argument 'frame' must be 'body' or 'space'"):
        call()


@pytest.mark.parametrize("frame", FRAMES)
def test_the_public_kernels_on_components_are_the_row_kernels(frame):
    """``omega_from_qdot``, ``qddot_from_alpha`` and ``alpha_from_qddot`` run kernels written on
    components (``jaxquat._rates.*_by_components``, faster gradients); the vector fields and the
    dynamics run the row kernels. The two forms must stay one formula: values and the gradients of
    ``sum(f * W)`` in every argument, on non-unit ``q`` (the ``|q|^2`` scaling) of 64 rows, to a
    few eps (measured: at most 3.0e-16 float64, 3.2e-7 float32, relative to the largest entry).
    Each form's value and gradients are one compiled program (run eagerly, the private kernels
    and their gradients dispatched about 100 small programs per frame: 4.1-4.6 s per pass)."""
    from jaxquat import _rates

    rng = np.random.default_rng(11)
    q, qd, qdd = (on_device(rng.normal(size=(64, 4)), DTYPE) for _ in range(3))
    alpha = on_device(rng.normal(size=(64, 3)), DTYPE)
    cases = [
        (_rates.omega_from_qdot, _rates.omega_from_qdot_by_components, (q, qd)),
        (_rates.qddot_from_alpha, _rates.qddot_from_alpha_by_components, (q, qd, alpha)),
        (_rates.alpha_from_qddot, _rates.alpha_from_qddot_by_components, (q, qd, qdd)),
    ]
    tol = 1e-14 if X64 else 5e-6
    for rows, comps, args in cases:
        shape = jax.eval_shape(lambda *a, f=rows: f(*a, frame), *args).shape  # traced, not run
        w = on_device(rng.normal(size=shape), DTYPE)
        want, got = _value_and_gradients(rows, args, frame, w), _value_and_gradients(comps, args, frame, w)
        for g, h in zip(got, want):
            error = np.max(np.abs(np.asarray(g) - np.asarray(h))) / np.max(np.abs(np.asarray(h)))
            assert error <= tol, (rows.__name__, error)


def _value_and_gradients(f, args, frame, w):
    """``f(*args, frame)`` and the gradients of ``sum(f * w)`` in every argument, in one program."""

    def both(*a):
        grads = jax.grad(lambda *b: jnp.sum(f(*b, frame) * w), argnums=tuple(range(len(a))))(*a)
        return (f(*a, frame), *grads)

    return jax.jit(both)(*args)
