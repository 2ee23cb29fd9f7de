"""Algebra: product, conjugate, inverse, norm, normalize, exp/log/power, product matrices, rotate."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import quaternion as npq  # numpy-quaternion, an independent reference
from hypothesis import given
from scipy.spatial.transform import Rotation

import jaxquat as jq
from helpers import (
    DTYPE,
    TOL,
    X64,
    assert_close,
    random_quats,
    random_vectors,
    seeds,
    to_scipy,
)

multiply = jax.jit(jq.multiply)
exp = jax.jit(jq.exp)
log = jax.jit(jq.log)
power = jax.jit(jq.power)
rotate = jax.jit(jq.rotate)
inverse = jax.jit(jq.inverse)
normalize = jax.jit(jq.normalize)


def _general(seed, n=16):
    """Non-unit quaternions with scale spread over 1e-2 .. 1e2."""
    rng = np.random.default_rng(seed + 7)
    q = random_quats(seed, n).astype(np.float64) * 10 ** rng.uniform(-2, 2, size=(n, 1))
    return q.astype(DTYPE)


def _npq(q):
    return npq.as_quat_array(np.asarray(q, dtype=np.float64))


# ---------------------------------------------------------------- values against references


@given(seeds)
def test_multiply_matches_numpy_quaternion(seed):
    p, q = _general(seed), _general(seed + 1)
    ref = npq.as_float_array(_npq(p) * _npq(q))
    scale = np.abs(ref).max(-1, keepdims=True)
    assert_close(np.asarray(multiply(p, q)) / scale, ref / scale)


def test_hamilton_units():
    one, i, j, k = np.eye(4, dtype=DTYPE)
    assert_close(jq.multiply(i, j), k)
    assert_close(jq.multiply(j, k), i)
    assert_close(jq.multiply(k, i), j)
    assert_close(jq.multiply(jq.multiply(i, j), k), -one)  # i j k = -1, Tasora (2d)
    assert_close(jq.multiply(j, i), -k)


@given(seeds)
def test_product_matrices(seed):
    p, q = _general(seed), _general(seed + 1)
    pq = np.asarray(multiply(p, q))
    left = np.einsum("nij,nj->ni", np.asarray(jq.left_matrix(p)), q)
    right = np.einsum("nij,nj->ni", np.asarray(jq.right_matrix(q)), p)
    scale = np.abs(pq).max(-1, keepdims=True)
    assert_close(left / scale, pq / scale)
    assert_close(right / scale, pq / scale)
    # Schwab: Q and P-bar commute; the matrices of q* are the transposes.
    lq, rp = np.asarray(jq.left_matrix(q)), np.asarray(jq.right_matrix(p))
    s = np.abs(lq).max() * np.abs(rp).max()
    assert_close((lq @ rp - rp @ lq) / s, np.zeros_like(lq), what="Q Pbar = Pbar Q")
    assert_close(np.asarray(jq.left_matrix(jq.conjugate(q))), np.swapaxes(lq, -1, -2))


@given(seeds)
def test_rotate_matches_scipy_and_matrix(seed):
    q, v = random_quats(seed), random_vectors(seed)
    ref = Rotation.from_quat(to_scipy(q)).apply(np.asarray(v, dtype=np.float64))
    out = rotate(q, v)
    assert out.dtype == DTYPE
    assert_close(out, ref, tol=10 * TOL)
    assert_close(out, np.einsum("nij,nj->ni", np.asarray(jq.to_matrix(q)), v), tol=10 * TOL)
    # As the sandwich product q (0, v) q*.
    pure = np.concatenate([np.zeros((len(v), 1), DTYPE), v], -1)
    sandwich = multiply(multiply(q, pure), jq.conjugate(q))
    assert_close(sandwich[:, 1:], out, tol=10 * TOL)
    assert_close(sandwich[:, 0], np.zeros(len(v)), tol=10 * TOL)


@given(seeds)
def test_exp_log_match_numpy_quaternion(seed):
    q = _general(seed) / 4.0
    ref_exp = npq.as_float_array(np.exp(_npq(q)))
    assert_close(exp(q) / np.abs(ref_exp).max(-1, keepdims=True), ref_exp / np.abs(ref_exp).max(-1, keepdims=True))
    ref_log = npq.as_float_array(np.log(_npq(q)))
    lg = np.asarray(log(q))
    # numpy-quaternion differs on the negative real axis only (where log is not unique).
    mask = ~((np.abs(q[:, 1:]).max(-1) == 0) & (q[:, 0] < 0))
    assert_close(lg[mask], ref_log[mask], tol=10 * TOL)


@given(seeds)
def test_exp_log_inverse(seed):
    q = _general(seed)
    back = exp(log(q))
    assert_close(
        back / jnp.linalg.norm(q, axis=-1, keepdims=True), q / jnp.linalg.norm(q, axis=-1, keepdims=True), tol=10 * TOL
    )


def test_log_negative_real_axis_is_a_logarithm():
    q = jnp.asarray([[-2.0, 0, 0, 0]], DTYPE)
    lg = jq.log(q)
    assert_close(lg, [[np.log(2.0), np.pi, 0, 0]])
    assert_close(jq.exp(lg), q, tol=10 * TOL)


@given(seeds)
def test_power(seed):
    q = random_quats(seed)
    t = np.random.default_rng(seed).uniform(-2, 2, size=len(q)).astype(DTYPE)
    out = power(q, t)
    ref = npq.as_float_array(np.array([a**b for a, b in zip(_npq(q), t.astype(np.float64))]))
    assert_close(out, ref, tol=20 * TOL)
    # q^(1/2) squared is q; q^1 is q; q^0 is the identity.
    half = power(q, jnp.full(len(q), 0.5, DTYPE))
    assert_close(multiply(half, half), q, tol=10 * TOL)
    assert_close(power(q, jnp.ones(len(q), DTYPE)), q, tol=10 * TOL)
    assert_close(power(q, jnp.zeros(len(q), DTYPE)), jq.identity(len(q), DTYPE))


def test_power_is_exp_of_t_log_in_rows_and_on_components():
    """``power`` runs ``exp(t log q)`` on components (``_log_parts``, ``_exp_parts``: faster
    gradients); the public ``exp`` and ``log`` keep the row kernels. The two forms must stay one
    formula: ``power`` against ``exp(t * log(q))`` in rows, values and the gradients of
    ``sum(f * W)`` in ``q`` and ``t``, on non-unit ``q`` of 64 rows with the identity and a real
    negative among them (measured in one jitted program: values equal to the bit, gradients at
    most 1.6e-16 float64, 1.5e-7 float32, relative to the largest entry; eagerly 2.9e-16 and
    1.2e-7; a NaN anywhere fails the comparison)."""
    from jaxquat.rotations import algebra

    rng = np.random.default_rng(5)
    q = jnp.asarray(rng.normal(size=(64, 4)), DTYPE).at[0].set(jnp.asarray([1.0, 0, 0, 0], DTYPE))
    q = q.at[1].set(jnp.asarray([-2.0, 0, 0, 0], DTYPE))
    t = jnp.asarray(rng.uniform(-2, 2, 64), DTYPE)
    w = jnp.asarray(rng.normal(size=(64, 4)), DTYPE)

    def rows(q, t):
        return algebra._exp(t[:, None] * algebra._log(q))

    @jax.jit  # one program for both forms (eagerly: a program per operation, 2x the test's time)
    def both(q, t):
        return [
            (f(q, t), *jax.grad(lambda q, t, f=f: jnp.sum(f(q, t) * w), (0, 1))(q, t)) for f in (algebra._power, rows)
        ]

    tol = 1e-14 if X64 else 5e-6
    got, want = both(q, t)
    for g, h in zip(got, want):
        g, h = np.asarray(g), np.asarray(h)
        error = float(np.max(np.abs(g - h))) / float(np.max(np.abs(h)))
        assert error <= tol, error


def test_power_scalar_t_broadcasts():
    q = random_quats(3)
    assert_close(jq.power(q, 2.0), jq.multiply(q, q), tol=10 * TOL)


# ---------------------------------------------------------------- group properties


@given(seeds)
def test_group_axioms(seed):
    p, q, r = _general(seed), _general(seed + 1), _general(seed + 2)
    lhs, rhs = multiply(multiply(p, q), r), multiply(p, multiply(q, r))
    scale = np.abs(np.asarray(lhs)).max(-1, keepdims=True)
    assert_close(lhs / scale, rhs / scale, what="associativity")
    e = jq.identity(len(p), DTYPE)
    assert_close(multiply(e, p), p)
    assert_close(multiply(p, e), p)
    ident = multiply(p, inverse(p))
    assert_close(ident, e, tol=10 * TOL, what="p p^-1")
    assert_close(multiply(inverse(p), p), e, tol=10 * TOL)
    # |p q| = |p| |q| and (p q)* = q* p*
    n = jq.norm(multiply(p, q))
    assert_close(n / (jq.norm(p) * jq.norm(q)), np.ones(len(p)), tol=10 * TOL)
    assert_close(jq.conjugate(multiply(p, q)) / scale, multiply(jq.conjugate(q), jq.conjugate(p)) / scale)


@given(seeds)
def test_normalize(seed):
    q = _general(seed)
    u = normalize(q)
    assert_close(jq.norm(u), np.ones(len(q)), tol=10 * TOL)
    assert_close(u * jq.norm(q)[:, None], q, tol=10 * TOL * np.abs(q).max())


def test_zero_quaternion_in_a_jitted_batch():
    """Zero has no direction and no inverse: NaN for that element, the rest untouched."""
    q = jnp.asarray([[0.0, 0, 0, 0], [2.0, 0, 0, 0]], DTYPE)
    n = normalize(q)
    assert np.all(np.isnan(np.asarray(n[0])))
    assert_close(n[1], [1.0, 0, 0, 0])
    inv = inverse(q)
    assert np.all(np.isnan(np.asarray(inv[0])))
    assert_close(inv[1], [0.5, 0, 0, 0])
    # Gradients of the healthy element stay finite.
    g = jax.grad(lambda x: jq.normalize(x)[1, 0] + jq.inverse(x)[1, 0])(q)
    assert np.all(np.isfinite(np.asarray(g[1])))
    assert jq.norm(q)[0] == 0
    assert np.all(np.isfinite(np.asarray(jax.grad(lambda x: jq.norm(x).sum())(q))))


def test_identity():
    e = jq.identity((2, 3), DTYPE)
    assert e.shape == (2, 3, 4) and e.dtype == DTYPE
    assert_close(e[1, 2], [1, 0, 0, 0])
    assert jq.identity().shape == (4,)
    with pytest.raises(TypeError, match="dtype"):
        jq.identity(dtype=jnp.int32)


# ---------------------------------------------------------------- derivatives at the identity


@pytest.mark.skipif(not X64, reason="exact derivative checks in float64")
def test_exp_log_derivatives_at_identity():
    zero = jnp.zeros(4, DTYPE)
    jac = jax.jacfwd(jq.exp)(zero)
    assert_close(jac, np.eye(4), tol=1e-14)
    jac_log = jax.jacrev(jq.log)(jnp.asarray([1.0, 0, 0, 0], DTYPE))
    assert_close(jac_log, np.eye(4), tol=1e-14)
    # Hessian of exp's scalar part at 0: d^2 cos|v| / dv^2 = -I on the vector block.
    hess = jax.hessian(lambda q: jq.exp(q)[0])(zero)
    expected = np.diag([1.0, -1.0, -1.0, -1.0])
    assert_close(hess, expected, tol=1e-12)
