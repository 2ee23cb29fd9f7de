"""Angles, mean, align_vectors, random sampling and slerp."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from jax.test_util import check_grads
from scipy.spatial.transform import Rotation, Slerp

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
    to_scipy,
)

angle = jax.jit(jq.angle)
angle_between = jax.jit(jq.angle_between)
mean = jax.jit(jq.mean)
align = jax.jit(jq.align_vectors)
slerp = jax.jit(jq.slerp)


@given(seeds)
def test_angle_and_distance(seed):
    p, q = random_quats(seed), random_quats(seed + 1)
    ref = Rotation.from_quat(to_scipy(p)).magnitude()
    assert_close(angle(p), ref, tol=10 * TOL)
    assert_close(angle(-3.0 * p), ref, tol=10 * TOL)  # sign and scale invariant
    d = angle_between(p, q)
    ref_d = (Rotation.from_quat(to_scipy(p)).inv() * Rotation.from_quat(to_scipy(q))).magnitude()
    assert_close(d, ref_d, tol=100 * TOL)
    assert_close(d, angle_between(q, -p), tol=10 * TOL)
    # triangle inequality of the metric
    r = random_quats(seed + 2)
    assert np.all(np.asarray(angle_between(p, r)) <= np.asarray(d + angle_between(q, r)) + 10 * TOL)


def test_angle_gradients_at_identity_and_pi():
    g = jax.grad(jq.angle)(jnp.asarray([1.0, 0, 0, 0], DTYPE))
    assert_close(g, np.zeros(4), tol=0)
    g = jax.grad(jq.angle)(jnp.asarray([0.0, 1.0, 0, 0], DTYPE))
    assert np.all(np.isfinite(np.asarray(g)))
    assert g[0] == 0


@given(seeds)
def test_mean_against_scipy(seed):
    rng = np.random.default_rng(seed)
    q = random_quats(seed, n=32, with_singular=False).reshape(2, 16, 4)
    # Flip random signs: the mean must not care.
    flips = np.where(rng.random((2, 16, 1)) < 0.5, -1.0, 1.0).astype(DTYPE)
    w = rng.uniform(0.1, 2.0, size=(2, 16)).astype(DTYPE)
    out = mean(q * flips, w)
    assert out.shape == (2, 4)
    for b in range(2):
        ref = Rotation.from_quat(to_scipy(q[b])).mean(weights=w[b].astype(np.float64)).as_quat(canonical=True)
        assert_same_rotation(out[b], from_scipy(ref), tol=1e-8 if X64 else 1e-4)
    assert np.all(np.asarray(out)[:, 0] >= 0)
    # Mean of one repeated rotation is that rotation; unweighted call works.
    rep = jnp.broadcast_to(jnp.asarray(q[0, 0]), (5, 4))
    assert_same_rotation(jq.mean(rep), q[0, 0], tol=10 * TOL)


def test_mean_of_clustered_rotations_is_the_center():
    rng = np.random.default_rng(0)
    center = jq.from_rotvec(jnp.asarray([0.3, -0.2, 0.9], DTYPE))
    eps = rng.normal(size=(200, 3)) * 0.05
    eps -= eps.mean(0)  # symmetric cloud: chordal mean equals the center to second order
    cloud = jq.multiply(center, jq.from_rotvec(jnp.asarray(eps, DTYPE)))
    assert float(jq.angle_between(jq.mean(cloud), center)) < 1e-3


@given(seeds)
def test_align_vectors_against_scipy(seed):
    rng = np.random.default_rng(seed)
    q = random_quats(seed, n=1, with_singular=False)[0]
    b = random_vectors(seed, n=8)
    a = np.asarray(jq.rotate(jnp.asarray(q), b)) + (1e-3 * rng.normal(size=b.shape)).astype(DTYPE)
    w = rng.uniform(0.5, 2.0, 8).astype(DTYPE)
    out = align(a, b, w)
    ref, _ = Rotation.align_vectors(a.astype(np.float64), b.astype(np.float64), weights=w.astype(np.float64))
    assert_same_rotation(out, from_scipy(ref.as_quat()), tol=1e-8 if X64 else 1e-4)
    # Noise-free: exact recovery.
    exact = align(np.asarray(jq.rotate(jnp.asarray(q), b)), b, np.ones(8, DTYPE))
    assert_same_rotation(exact, q, tol=1e-8 if X64 else 1e-4)


def test_align_single_pair_is_the_minimal_rotation():
    a = jnp.asarray([[[0.0, 2.0, 0.0]], [[-1.0, 0.0, 0.0]], [[1.0, 1.0, 1.0]]], DTYPE)
    b = jnp.asarray([[[1.0, 0.0, 0.0]], [[1.0, 0.0, 0.0]], [[1.0, 1.0, 1.0]]], DTYPE)
    q = jq.align_vectors(a, b)
    for i in range(3):
        ref, _ = Rotation.align_vectors(np.asarray(a[i], np.float64), np.asarray(b[i], np.float64))
        assert_close(jq.angle(q[i]), ref.magnitude(), tol=10 * TOL)
        rb = jq.rotate(q[i], b[i, 0])
        assert_close(rb / jnp.linalg.norm(rb), a[i, 0] / jnp.linalg.norm(a[i, 0]), tol=10 * TOL)


@given(seeds)
def test_align_single_pairs_rotate_b_onto_a_by_the_angle_between_them(seed):
    """A batch of single pairs (one problem each): random, antiparallel (along the axes too, where
    the half turn's axis switches) and parallel. ``R(q) b`` has ``a``'s direction and the angle of
    ``q`` is the angle between the vectors (pi for the antiparallel ones, about an axis normal to
    ``b``)."""
    rng = np.random.default_rng(seed)
    a, b = rng.normal(size=(2, 32, 3))
    b[:3] = np.eye(3)
    a[:6] = -rng.uniform(0.5, 2.0, (6, 1)) * b[:6]
    a[6:8] = 3.0 * b[6:8]
    a, b = jnp.asarray(a, DTYPE), jnp.asarray(b, DTYPE)
    q = align(a[:, None], b[:, None])
    rb = np.asarray(jq.rotate(q, b), np.float64)
    a64, b64 = np.asarray(a, np.float64), np.asarray(b, np.float64)
    unit = lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True)  # noqa: E731
    assert_close(unit(rb), unit(a64), tol=100 * TOL)
    between = np.arctan2(np.linalg.norm(np.cross(a64, b64), axis=-1), np.sum(a64 * b64, -1))
    assert_close(angle(q), between, tol=100 * TOL)
    assert_close(np.sum(np.asarray(q, np.float64)[:6, 1:] * b64[:6], -1), np.zeros(6), tol=10 * TOL)


@pytest.mark.skipif(not X64, reason="finite differences in float64")
def test_align_single_pair_gradients_against_finite_differences():
    rng = np.random.default_rng(5)
    a, b = (jnp.asarray(x, DTYPE) for x in rng.normal(size=(2, 4, 1, 3)))
    check_grads(jq.align_vectors, (a, b), order=1, modes=("fwd", "rev"), eps=1e-6)


def test_random_is_uniform():
    q = jq.random(jax.random.PRNGKey(0), (20000,), DTYPE)
    assert q.shape == (20000, 4) and q.dtype == DTYPE
    assert_close(jq.norm(q), np.ones(20000), tol=10 * TOL)
    # Haar measure: E[R] = 0, E[w^2] = 1/4 for each component, rotation angle density (1 - cos)/pi.
    m = np.asarray(jq.to_matrix(q), np.float64)
    assert np.abs(m.mean(0)).max() < 0.03
    assert np.abs((np.asarray(q, np.float64) ** 2).mean(0) - 0.25).max() < 0.01
    ang = np.asarray(jq.angle(q), np.float64)
    assert abs(np.mean(ang) - (np.pi / 2 + 2 / np.pi)) < 0.02  # E[phi] = pi/2 + 2/pi
    with pytest.raises(TypeError, match="dtype"):
        jq.random(jax.random.PRNGKey(0), 3, jnp.int32)


@given(seeds)
def test_slerp_against_scipy(seed):
    p, q = random_quats(seed), random_quats(seed + 1)
    t = np.random.default_rng(seed).uniform(0, 1, len(p)).astype(DTYPE)
    out = slerp(p, q, t)
    # Where p* q is a 180-degree rotation (p.q = 0) there are two shortest arcs;
    # scipy may take the other one, so compare with it only where the arc is unique.
    unique = np.abs(np.sum(np.asarray(p, np.float64) * q, -1)) > 1e-6
    for i in np.flatnonzero(unique):
        s = Slerp([0.0, 1.0], Rotation.from_quat(to_scipy(np.stack([p[i], q[i]]))))
        assert_same_rotation(out[i], from_scipy(s([float(t[i])]).as_quat())[0], tol=100 * TOL)
    assert_same_rotation(slerp(p, q, jnp.zeros(len(p), DTYPE)), p)
    assert_same_rotation(slerp(p, q, jnp.ones(len(p), DTYPE)), q, tol=10 * TOL)
    # Shortest path: constant angular speed, the angle to p grows linearly in t.
    d = np.asarray(angle_between(p, q))
    assert_close(angle_between(p, out), d * t, tol=1e-3 if not X64 else 1e-9)
    assert_close(angle_between(out, q), d * (1 - t), tol=1e-3 if not X64 else 1e-9)


def test_slerp_stable_as_p_approaches_q():
    p = jq.from_rotvec(jnp.asarray([0.4, 0.1, -0.3], DTYPE))
    for eps in (1e-3, 1e-8, 0.0):
        q = jq.multiply(p, jq.from_rotvec(jnp.asarray([eps, 0, 0], DTYPE)))
        out = jq.slerp(p, q, 0.5)
        assert np.all(np.isfinite(np.asarray(out)))
        ref = jq.multiply(p, jq.from_rotvec(jnp.asarray([eps / 2, 0, 0], DTYPE)))
        assert_close(out, ref, tol=10 * TOL)
        g = jax.jacrev(lambda x: jq.slerp(p, x, 0.3))(q)
        assert np.all(np.isfinite(np.asarray(g)))


# ------------------------------------------------------------------ bad input: empty sets, weights, no information


def test_mean_rejects_an_empty_set_and_bad_weights():
    with pytest.raises(ValueError, match=r"'q' must hold at least one rotation.*\(0, 4\)"):
        jq.mean(jnp.zeros((0, 4), DTYPE))
    with pytest.raises(ValueError, match=r"'q' must hold at least one rotation"):
        jax.jit(jq.mean)(jnp.zeros((3, 0, 4), DTYPE))  # at trace time
    q = jnp.asarray(random_quats(3, 4), DTYPE)
    for w, match in [
        ([1.0, -1.0, 1.0, 1.0], "non-negative"),
        ([0.0] * 4, "positive sum"),
        ([1.0, np.nan, 1.0, 1.0], "finite"),
        ([1.0, np.inf, 1.0, 1.0], "finite"),
    ]:
        with pytest.raises(ValueError, match=f"'weights' must.*{match}"):
            jq.mean(q, jnp.asarray(w, DTYPE))


def test_mean_under_jit_gives_nan_only_for_sets_with_bad_weights():
    q = jnp.asarray(random_quats(4, 12), DTYPE).reshape(3, 4, 4)
    w = jnp.asarray([[1.0, 2.0, 1.0, 1.0], [1.0, -1.0, 1.0, 1.0], [0.0, 0.0, 0.0, 0.0]], DTYPE)
    out = np.asarray(jax.jit(jq.mean)(q, w))
    assert np.all(np.isfinite(out[0])) and np.all(np.isnan(out[1:]))
    assert_same_rotation(out[0], jq.mean(q[0], w[0]))


def test_align_vectors_without_information_gives_nan_and_empty_sets_raise():
    with pytest.raises(ValueError, match=r"'a' must hold at least one vector pair.*\(0, 3\)"):
        jq.align_vectors(jnp.zeros((0, 3), DTYPE), jnp.zeros((0, 3), DTYPE))
    one = jnp.asarray([[1.0, 2.0, 3.0]], DTYPE)
    zero = jnp.zeros((1, 3), DTYPE)
    for a, b in [(zero, one), (one, zero)]:
        assert np.all(np.isnan(np.asarray(jq.align_vectors(a, b))))
        assert np.all(np.isnan(np.asarray(jax.jit(jq.align_vectors)(a, b))))
    a = jnp.asarray(random_vectors(5, 4), DTYPE)
    assert np.all(np.isnan(np.asarray(jq.align_vectors(jnp.zeros_like(a), a))))
    with pytest.raises(ValueError, match="'weights' must.*non-negative"):
        jq.align_vectors(a, a, jnp.asarray([1.0, -1.0, 1.0, 1.0], DTYPE))
    # Batched under jit: only the element without information is NaN.
    batch_a = jnp.stack([a, jnp.zeros_like(a)])
    out = np.asarray(jax.jit(jq.align_vectors)(batch_a, jnp.stack([a, a])))
    assert_same_rotation(out[0], [1.0, 0.0, 0.0, 0.0], tol=1e-6 if not X64 else 1e-12)
    assert np.all(np.isnan(out[1]))
