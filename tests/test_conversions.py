"""Conversions: matrix, rotation vector, axis-angle, MRP, against scipy and closed forms."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from scipy.spatial.transform import Rotation

import jaxquat as jq
from helpers import (
    DTYPE,
    TOL,
    X64,
    assert_close,
    assert_same_rotation,
    from_scipy,
    random_quats,
    random_vectors,
    seeds,
    singular_quats,
    to_scipy,
)

to_matrix = jax.jit(jq.to_matrix)
from_matrix = jax.jit(jq.from_matrix)
from_matrix_nearest = jax.jit(lambda m: jq.from_matrix(m, nearest=True))
to_rotvec = jax.jit(jq.to_rotvec)
from_rotvec = jax.jit(jq.from_rotvec)
to_mrp = jax.jit(jq.to_mrp)
from_mrp = jax.jit(jq.from_mrp)
to_axis_angle = jax.jit(jq.to_axis_angle)
from_axis_angle = jax.jit(jq.from_axis_angle)


@given(seeds)
def test_matrix_against_scipy(seed):
    q = random_quats(seed)
    m = to_matrix(q)
    assert m.dtype == DTYPE
    assert_close(m, Rotation.from_quat(to_scipy(q)).as_matrix(), tol=10 * TOL)
    assert_close(m, to_matrix(-q))  # [T] (30): both signs, one matrix
    # orthonormal with det +1
    mm = np.asarray(m, np.float64)
    assert_close(np.einsum("nji,njk->nik", mm, mm), np.broadcast_to(np.eye(3), mm.shape), tol=10 * TOL)
    assert_close(np.linalg.det(mm), np.ones(len(q)), tol=10 * TOL)


@given(seeds)
def test_from_matrix_round_trip_and_canonical(seed):
    q = random_quats(seed)  # includes 180-degree and near-identity rotations
    back = from_matrix(to_matrix(q))
    assert_same_rotation(back, q, tol=20 * TOL)
    assert np.all(np.asarray(back)[:, 0] >= 0), "canonical sign w >= 0"
    assert_close(jq.norm(back), np.ones(len(q)), tol=10 * TOL)
    ref = from_scipy(Rotation.from_matrix(np.asarray(to_matrix(q), np.float64)).as_quat(canonical=True))
    assert_same_rotation(back, ref, tol=20 * TOL)


@given(seeds)
def test_from_matrix_nearest_matches_scipy_orthogonalisation(seed):
    """scipy projects a non-orthogonal matrix onto SO(3) by SVD; nearest=True must agree."""
    rng = np.random.default_rng(seed)
    q = random_quats(seed, with_singular=False).astype(np.float64)
    m = Rotation.from_quat(to_scipy(q)).as_matrix() + 1e-2 * rng.normal(size=(len(q), 3, 3))
    ref = Rotation.from_matrix(m).as_quat(canonical=True)
    out = from_matrix_nearest(m.astype(DTYPE))
    assert_same_rotation(out, from_scipy(ref), tol=1e-9 if X64 else 1e-5)
    # The default Shepperd column is first-order close: error O(1e-2).
    approx = from_matrix(m.astype(DTYPE))
    assert_close(jq.norm(approx), np.ones(len(q)), tol=10 * TOL)
    assert_same_rotation(approx, from_scipy(ref), tol=5e-2)


@given(seeds)
def test_rotvec_against_scipy(seed):
    q = random_quats(seed)
    r = to_rotvec(q)
    ref = Rotation.from_quat(to_scipy(q)).as_rotvec()
    # At exactly 180 degrees +-pi u are the same rotation; compare as rotations there.
    assert_same_rotation(from_rotvec(r), q, tol=10 * TOL)
    near_pi = np.linalg.norm(ref, axis=-1) > np.pi - 1e-6
    assert_close(np.asarray(r)[~near_pi], ref[~near_pi], tol=10 * TOL)
    assert np.all(np.linalg.norm(np.asarray(r, np.float64), axis=-1) <= np.pi + 10 * TOL)
    v = random_vectors(seed) * 2.0
    assert_same_rotation(from_rotvec(v), from_scipy(Rotation.from_rotvec(v.astype(np.float64)).as_quat()), tol=10 * TOL)


def test_rotvec_is_scale_invariant_and_tiny_angles_exact():
    q = jnp.asarray(singular_quats()[2], DTYPE)  # angle 1e-8 about x
    assert_close(jq.to_rotvec(q), [1e-8, 0, 0], tol=1e-15 if X64 else 1e-13)
    assert_close(jq.to_rotvec(3.0 * q), jq.to_rotvec(q), tol=1e-15)
    assert_close(jq.from_rotvec(jnp.asarray([1e-8, 0, 0], DTYPE)), [1.0, 5e-9, 0, 0], tol=1e-16)


@pytest.mark.skipif(not X64, reason="exact derivative checks in float64")
def test_rotvec_jacobians_and_hessians_at_identity():
    e = jnp.asarray([1.0, 0, 0, 0])
    j = jax.jacfwd(jq.to_rotvec)(e)
    assert_close(j[:, 1:], 2 * np.eye(3), tol=0.0)
    assert_close(jax.jacrev(jq.to_rotvec)(e), j, tol=0.0)
    jf = jax.jacfwd(jq.from_rotvec)(jnp.zeros(3))
    assert_close(jf[1:], 0.5 * np.eye(3), tol=0.0)
    assert_close(jf[0], np.zeros(3), tol=0.0)
    # Hessian of w = cos(|r|/2) at 0 is -I/4; of the vector part is 0.
    assert_close(jax.hessian(lambda r: jq.from_rotvec(r)[0])(jnp.zeros(3)), -0.25 * np.eye(3), tol=1e-15)
    assert_close(jax.hessian(lambda r: jq.from_rotvec(r)[1])(jnp.zeros(3)), np.zeros((3, 3)), tol=1e-15)
    # to_rotvec's x-component along the (w, x) plane: 2 atan(x/w); its Hessian at e.
    h = jax.hessian(lambda q: jq.to_rotvec(q)[0])(e)
    # Near e the x-component is 2 x / w to second order: its only non-zero second derivative is d2/dw dx = -2.
    expected = np.zeros((4, 4))
    expected[0, 1] = expected[1, 0] = -2.0
    assert_close(h, expected, tol=1e-12)


@given(seeds)
def test_axis_angle(seed):
    q = random_quats(seed)
    axis, angle = to_axis_angle(q)
    assert np.all((np.asarray(angle) >= 0) & (np.asarray(angle) <= np.pi + 1e-6))
    assert_close(jq.norm(jnp.concatenate([jnp.zeros_like(angle)[:, None], axis], -1)), np.ones(len(q)), tol=10 * TOL)
    assert_same_rotation(from_axis_angle(axis, angle), q, tol=10 * TOL)
    ref = np.linalg.norm(Rotation.from_quat(to_scipy(q)).as_rotvec(), axis=-1)
    assert_close(angle, ref, tol=10 * TOL)
    # An unnormalised axis is normalised.
    assert_same_rotation(from_axis_angle(3.0 * axis, angle), q, tol=10 * TOL)


def test_axis_angle_identity_and_zero_axis():
    axis, angle = jq.to_axis_angle(jnp.asarray([1.0, 0, 0, 0], DTYPE))
    assert_close(axis, [1, 0, 0], tol=0)
    assert angle == 0
    g = jax.grad(lambda q: jq.to_axis_angle(q)[1] + jq.to_axis_angle(q)[0].sum())(jnp.asarray([1.0, 0, 0, 0], DTYPE))
    assert np.all(np.isfinite(np.asarray(g)))
    assert_close(jq.from_axis_angle(jnp.zeros(3, DTYPE), 0.0), [1, 0, 0, 0], tol=0)
    assert np.all(np.isnan(np.asarray(jq.from_axis_angle(jnp.zeros(3, DTYPE), 1.0))[1:]))


@given(seeds)
def test_mrp_against_scipy(seed):
    q = random_quats(seed)
    p = to_mrp(q)
    ref = Rotation.from_quat(to_scipy(q)).as_mrp()
    assert np.all(np.linalg.norm(np.asarray(p, np.float64), axis=-1) <= 1 + 10 * TOL)
    assert_same_rotation(from_mrp(p), q, tol=10 * TOL)
    not_pi = np.abs(np.asarray(q)[:, 0]) > 1e-6  # at 180 degrees p and -p are both valid
    assert_close(np.asarray(p)[not_pi], ref[not_pi], tol=10 * TOL)
    assert_close(to_mrp(2.5 * q), p, tol=10 * TOL)
    # The shadow set: |p| > 1 describes the same rotation.
    shadow = -np.asarray(p, np.float64) / np.maximum(np.sum(np.asarray(p, np.float64) ** 2, -1, keepdims=True), 1e-30)
    ok = np.linalg.norm(np.asarray(p), axis=-1) > 1e-3
    assert_same_rotation(from_mrp(shadow[ok].astype(DTYPE)), np.asarray(q)[ok], tol=100 * TOL)


def test_from_axis_angle_with_a_zero_axis():
    """No axis and a non-zero angle: no rotation exists, so all four components are NaN (eager
    and under jit, element-wise); a zero angle gives the identity whatever the axis."""
    axes = jnp.asarray([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 2.0]], DTYPE)
    angles = jnp.asarray([1.0, 0.0, 1.0], DTYPE)
    for out in (jq.from_axis_angle(axes, angles), from_axis_angle(axes, angles)):
        out = np.asarray(out)
        assert np.all(np.isnan(out[0]))
        np.testing.assert_array_equal(out[1], [1.0, 0.0, 0.0, 0.0])
        assert np.all(np.isfinite(out[2]))


@pytest.mark.skipif(not X64, reason="measures an error of 1e-5 relative: float64 only")
def test_from_matrix_distance_from_the_nearest_rotation_is_as_documented():
    """Default mode: the angle to the polar factor's rotation is about 0.2 |M^T M - I|_F, linear in
    the deviation (the docstring once claimed agreement to first order); nearest=True is the polar
    factor to rounding."""
    from scipy.linalg import polar

    rng = np.random.default_rng(11)
    rot = np.asarray(jq.to_matrix(jnp.asarray(random_quats(11, 64, with_singular=False))))
    ratios = []
    for size in (1e-3, 1e-5):
        m = rot + size * rng.normal(size=rot.shape)
        nearest = np.asarray(jq.from_matrix(jnp.asarray(np.stack([polar(x)[0] for x in m]))))
        deviation = np.linalg.norm(np.einsum("nji,njk->nik", m, m) - np.eye(3), axis=(1, 2))
        ratios.append(np.median(np.asarray(jq.angle_between(from_matrix(jnp.asarray(m)), nearest)) / deviation))
        assert np.all(
            np.asarray(jq.angle_between(from_matrix_nearest(jnp.asarray(m)), nearest)) < 1e-9 * deviation + 1e-14
        )
    assert all(0.1 < r < 0.4 for r in ratios)  # measured 0.20 at both sizes: linear, not quadratic
    assert abs(ratios[0] / ratios[1] - 1) < 0.2
