"""Static attitude determination: TRIAD and QUEST against scipy's Wahba solver and closed forms,
QUEST's custom JVP against finite differences, Shuster's covariance against a Monte Carlo, and
align_vectors' sensitivity against scipy."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.test_util import check_grads
import numpy as np
import pytest
from hypothesis import given
from scipy.spatial.transform import Rotation

import jaxquat as jq
from helpers import DTYPE, X64, assert_close, assert_same_rotation, from_scipy, random_quats, seeds, to_scipy

N = 16  # batch of problems
M = 5  # vectors per problem
quest_jit = jax.jit(jq.quest)
triad_jit = jax.jit(jq.triad)
align_jit = jax.jit(jq.align_vectors)


def _problem(seed, noise=0.01, m=M):
    """Random attitudes (singular rows first), body vectors, and reference vectors r = R b + noise."""
    rng = np.random.default_rng(seed)
    q = random_quats(seed, N, dtype=np.float64)
    b = rng.normal(size=(N, m, 3))
    b /= np.linalg.norm(b, axis=-1, keepdims=True)
    r = np.einsum("nij,nmj->nmi", Rotation.from_quat(to_scipy(q)).as_matrix(), b) + noise * rng.normal(size=b.shape)
    w = rng.uniform(0.5, 2.0, (N, m))
    return q, b, r, w


@given(seeds)
def test_quest_solves_wahba_as_scipy_does(seed):
    _, b, r, w = _problem(seed)
    got = quest_jit(jnp.asarray(b, DTYPE), jnp.asarray(r, DTYPE), jnp.asarray(w, DTYPE))
    ref = np.stack([from_scipy(Rotation.align_vectors(r[i], b[i], w[i])[0].as_quat()) for i in range(N)])
    assert_same_rotation(got, ref, tol=1e-10 if X64 else 2e-5)
    assert np.all(np.asarray(got)[:, 0] >= 0)


@given(seeds)
def test_quest_is_exact_on_noise_free_data_including_180_degrees(seed):
    q, b, r, w = _problem(seed, noise=0.0)
    assert_same_rotation(
        quest_jit(jnp.asarray(b, DTYPE), jnp.asarray(r, DTYPE), jnp.asarray(w, DTYPE)), q, tol=1e-12 if X64 else 2e-6
    )


def test_quest_matches_the_eigh_solution_when_the_top_eigenvalues_are_close():
    """Three nearly parallel vectors, so lambda_max and the next eigenvalue are close: 1e-6 apart in
    float64 (where Newton's root alone was 1.4e-5 rad off), 1e-3 in float32 (a 1e-6 gap is ten
    rounding errors of |K| = 3 there: no solver resolves it). In float64 against eigh. In float32
    both against scipy's float64 answer, within ten times the problem's own sensitivity to
    rounding, eps |K| / gap (2.1e-4 rad here; measured: QUEST 5.1e-4, eigh 2.7e-5). An earlier
    QUEST refined from Newton's root of the quartic, which float32 rounding can put nearer the
    second eigenvalue: 2.4e-4 rad from eigh under the suite's XLA flags on an AMD EPYC (4e-5 on
    an Intel Xeon), and 3.13 rad (the second eigenvector) under XLA's default flags. Run with
    JAXQUAT_TEST_XLA_DEFAULTS=1 as well."""
    rng = np.random.default_rng(3)
    sep = 1e-3 if X64 else 3e-2
    b = np.array([[1.0, 0.0, 0.0], [1.0, sep, 0.0], [1.0, 0.0, sep]])
    q = jq.random(jax.random.PRNGKey(0), (), DTYPE)
    r = np.asarray(jq.rotate(q, jnp.asarray(b, DTYPE)), np.float64) + 1e-5 * rng.normal(size=b.shape)
    got = jq.quest(jnp.asarray(b, DTYPE), jnp.asarray(r, DTYPE))
    want = jq.align_vectors(jnp.asarray(r, DTYPE), jnp.asarray(b, DTYPE))
    if X64:
        assert float(jq.angle_between(got, want)) < 1e-9  # measured 8e-11
        return
    m = b.T @ r  # Davenport's K of the equal-weight problem (float64): its top eigenvalue gap
    z = np.array([m[1, 2] - m[2, 1], m[2, 0] - m[0, 2], m[0, 1] - m[1, 0]])
    k = np.block([[np.trace(m), z[None]], [z[:, None], m + m.T - np.trace(m) * np.eye(3)]])
    eigenvalues = np.linalg.eigvalsh(k)
    sensitivity = np.finfo(np.float32).eps * np.abs(eigenvalues).max() / (eigenvalues[-1] - eigenvalues[-2])
    assert 1e-4 < sensitivity < 1e-3, sensitivity  # the problem this test is about
    reference = jnp.asarray(from_scipy(Rotation.align_vectors(r, b)[0].as_quat()), DTYPE)
    for name, x in (("quest", got), ("align_vectors", want)):
        assert float(jq.angle_between(x, reference)) < 10 * sensitivity, name


def test_quest_gradient_matches_finite_differences():
    """Custom JVP (dlambda = q^T dK q, a 4x4 solve for dq) against central differences, forward and reverse."""
    _, b, r, w = _problem(5, noise=0.05)
    b, r, w = (jnp.asarray(x[:4], DTYPE) for x in (b, r, w))
    if not X64:
        pytest.skip("finite differences need float64; float32 runs the same code in the contract tests")
    check_grads(jq.quest, (b, r, w), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-6, rtol=1e-6)


def test_triad_closed_form_properties():
    """R(q) b1 is exactly along r1, and R(q) (b1 x b2) along r1 x r2, with noisy data; exact without noise."""
    q, b, r, _ = _problem(11, noise=0.02)
    b1, b2, r1, r2 = (jnp.asarray(x, DTYPE) for x in (b[:, 0], b[:, 1], 2.0 * r[:, 0], r[:, 1]))
    got = triad_jit(b1, b2, r1, r2)
    tol = 1e-12 if X64 else 3e-6
    unit = lambda v: v / jnp.linalg.norm(v, axis=-1, keepdims=True)  # noqa: E731
    assert_close(jq.rotate(got, unit(b1)), unit(r1), tol=tol, what="R b1 = r1 direction")
    assert_close(jq.rotate(got, unit(jnp.cross(b1, b2))), unit(jnp.cross(r1, r2)), tol=tol, what="R (b1 x b2)")
    _, b, r, _ = _problem(11, noise=0.0)
    exact = triad_jit(*(jnp.asarray(x, DTYPE) for x in (b[:, 0], b[:, 1], r[:, 0], r[:, 1])))
    assert_same_rotation(exact, q, tol=1e-12 if X64 else 3e-6)


def test_triad_and_quest_jit_vmap_batching_and_gradients_at_180_degrees():
    q, b, r, w = _problem(2, noise=0.0)
    args = [jnp.asarray(x, DTYPE) for x in (b[:, 0], b[:, 1], r[:, 0], r[:, 1])]
    assert_close(jax.vmap(jq.triad)(*args), jq.triad(*args), tol=1e-12 if X64 else 1e-6)
    nested = jq.triad(*(a.reshape(4, 4, 3) for a in args))
    assert nested.shape == (4, 4, 4) and nested.dtype == DTYPE
    qb = [jnp.asarray(x, DTYPE) for x in (b, r, w)]
    assert_close(jax.vmap(jq.quest)(*qb), quest_jit(*qb), tol=1e-12 if X64 else 1e-6)
    assert jq.quest(*(a.reshape(4, 4, *a.shape[1:]) for a in qb)).shape == (4, 4, 4)
    # Rows 0..3 of random_quats hold singular attitudes (180 degrees among them): finite gradients.
    g = jax.grad(lambda r: jnp.sum(quest_jit(qb[0], r, qb[2]) ** 2 * jnp.arange(4.0, dtype=DTYPE)[None]))(qb[1])
    assert np.all(np.isfinite(np.asarray(g)))
    g = jax.grad(lambda r1: jnp.sum(triad_jit(args[0], args[1], r1, args[3]) * jnp.arange(4.0, dtype=DTYPE)[None]))(
        args[2]
    )
    assert np.all(np.isfinite(np.asarray(g)))


def test_attitude_covariance_against_a_monte_carlo_of_quest():
    """Shuster's P = (sum s_i^-2 (I - b_i b_i^T))^-1 against the sample covariance of QUEST's error
    (weights 1/s_i^2) over 4000 draws of tangential noise: within 10 % (the sampling error of a
    variance from 4000 draws is 2.2 %; measured 0.984, 1.007, 0.995, correlations below 0.03)."""
    rng = np.random.default_rng(0)
    b = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.6, 0.0, 0.8]])
    s = np.array([1e-3, 3e-3, 2e-3])
    q = np.asarray(jq.from_rotvec(jnp.asarray([0.3, -0.2, 1.0])), np.float64)
    r = np.asarray(jq.rotate(jnp.asarray(q), jnp.asarray(b)), np.float64)
    draws = 4000
    # Measured body vectors: the true ones turned by a small rotation of s_i per tangent axis.
    noise = rng.normal(size=(draws, 3, 3)) * s[None, :, None]
    noise -= np.einsum("dmi,mi->dm", noise, b)[..., None] * b
    measured = np.asarray(jq.plus(jnp.asarray([1.0, 0, 0, 0]), jnp.asarray(noise)), np.float64)
    bm = np.asarray(jq.rotate(jnp.asarray(measured), jnp.broadcast_to(jnp.asarray(b), (draws, 3, 3))))
    est = quest_jit(
        jnp.asarray(bm, DTYPE), jnp.asarray(np.broadcast_to(r, bm.shape), DTYPE), jnp.asarray(1 / s**2, DTYPE)
    )
    err = np.asarray(jq.minus(jnp.asarray(q), est.astype(jnp.float64) if X64 else est), np.float64)
    sample = err.T @ err / draws
    p = np.asarray(jq.attitude_covariance(jnp.asarray(b, DTYPE), jnp.asarray(s, DTYPE)), np.float64)
    info = np.einsum("n,nij->ij", s**-2.0, np.eye(3) - b[:, :, None] * b[:, None, :])
    assert np.allclose(p @ info, np.eye(3), atol=1e-10 if X64 else 1e-4)
    # Compare in the frame of P's eigenvectors: each variance within 10 %, the correlations small.
    vals, vecs = np.linalg.eigh(p)
    rotated = vecs.T @ sample @ vecs
    assert np.all(np.abs(np.diag(rotated) / vals - 1) < 0.1), np.diag(rotated) / vals
    off = rotated / np.sqrt(np.outer(vals, vals))
    assert np.abs(off - np.diag(np.diag(off))).max() < 0.1


# One compiled program for every example (a jit of a new lambda in each example compiled 25 times:
# the test took 4.3 s alone against 0.7 s now, float64 on a 2-core EPYC; 7 s of each pass).
_align_with_sensitivity = jax.jit(lambda a, b, w: jq.align_vectors(a, b, w, return_sensitivity=True))


@given(seeds)
def test_align_vectors_sensitivity_matches_scipy(seed):
    _, b, r, w = _problem(seed, noise=0.05)
    q, sens = _align_with_sensitivity(jnp.asarray(r, DTYPE), jnp.asarray(b, DTYPE), jnp.asarray(w, DTYPE))
    for i in range(N):
        rot, _, ref = Rotation.align_vectors(r[i], b[i], w[i], return_sensitivity=True)
        assert_same_rotation(q[i], from_scipy(rot.as_quat()), tol=1e-10 if X64 else 2e-5)
        assert_close(sens[i], ref, tol=1e-9 if X64 else 1e-4, what="sensitivity")


def test_bad_input():
    v = jnp.ones((5, 3))
    with pytest.raises(ValueError, match=r"'vectors_body'.*n >= 2"):
        jq.quest(jnp.ones((1, 3)), jnp.ones((1, 3)))
    with pytest.raises(ValueError, match="same n"):
        jq.quest(v, jnp.ones((4, 3)))
    with pytest.raises(ValueError, match=r"'vectors_ref'.*\(\.\.\., 3\)"):
        jq.quest(v, jnp.ones((5, 4)))
    with pytest.raises(ValueError, match="'weights'"):
        jq.quest(v, v, jnp.ones(4))
    with pytest.raises(ValueError, match="non-negative"):
        jq.quest(v, v, -jnp.ones(5))
    with pytest.raises(ValueError, match=r"'r2'.*\(\.\.\., 3\)"):
        jq.triad(v[0], v[1], v[2], jnp.ones(4))
    with pytest.raises(TypeError, match="'b1'.*floating"):
        jq.triad(jnp.ones(3, int), v[1], v[2], v[3])
    with pytest.raises(ValueError, match="'noise'"):
        jq.attitude_covariance(v, jnp.ones(4))
    with pytest.raises(ValueError, match="single vector pair"):
        jq.align_vectors(jnp.ones((1, 3)), jnp.ones((1, 3)), return_sensitivity=True)


_BATCH = 1024  # _rotation._JACOBI_FROM: from here on the top eigenvector comes from Jacobi rotations


def _align_and_mean(a, b, quats, weights):
    """``align_vectors(a, b)``, ``mean(quats)`` and the gradients of weighted sums of them in ``a``
    and ``quats``."""
    q = jq.align_vectors(a, b)
    m = jq.mean(quats)
    ga = jax.grad(lambda x: jnp.sum(jq.align_vectors(x, b) * weights))(a)
    gm = jax.grad(lambda x: jnp.sum(jq.mean(x) * weights))(quats)
    return q, m, ga, gm


def test_a_batch_of_1024_problems_is_solved_by_jacobi_rotations_as_one_problem_by_eigh(monkeypatch):
    """From 1024 problems on, on CPU, ``align_vectors`` and ``mean`` take their top eigenvector from
    Jacobi rotations (``_jacobi.eigh4``), below from LAPACK's ``eigh``: the batch gives, values
    and gradients, what the same problems give one at a time (``lax.map``), among them noise-free
    problems (a triple lower eigenvalue) and half turns."""
    from jaxquat import _jacobi

    calls = []
    original = _jacobi.eigh4
    monkeypatch.setattr(_jacobi, "eigh4", lambda k: calls.append(k.shape) or original(k))
    rng = np.random.default_rng(5)
    b = rng.normal(size=(_BATCH, 4, 3))
    turns = rng.normal(size=(_BATCH, 4))
    turns /= np.linalg.norm(turns, axis=-1, keepdims=True)
    turns[:8] = [0.0, 1.0, 0.0, 0.0]  # half turns about x
    a = np.array(jq.rotate(jnp.asarray(turns)[:, None], jnp.asarray(b)))
    a[_BATCH // 2 :] += 0.05 * rng.normal(size=(_BATCH // 2, 4, 3))  # half of them noisy
    quats = np.asarray(jq.normalize(jnp.asarray(turns[:, None] + 0.1 * rng.normal(size=(_BATCH, 5, 4)))))
    weights = jnp.asarray(rng.normal(size=(_BATCH, 4)), DTYPE)
    args = tuple(jnp.asarray(x, DTYPE) for x in (a, b, quats)) + (weights,)
    batch = jax.jit(_align_and_mean)(*args)
    assert calls and all(shape[0] == _BATCH for shape in calls)
    calls.clear()
    one = jax.jit(lambda *xs: jax.lax.map(lambda x: _align_and_mean(*x), xs))(*args)
    assert not calls
    # at a half turn w is 0 but for rounding, which picks the canonical sign: compared up to q ~ -q
    signs = [jnp.where(jnp.sum(batch[i] * one[i], axis=-1) < 0, -1.0, 1.0) for i in (0, 1)]
    # measured: values 2.9e-15 and 1.0e-15, gradients (entries up to 1) 6.7e-15 and 2.3e-15 in
    # float64; 2.0e-6, 4.8e-7, 3.8e-6 and 9.5e-7 in float32
    tol = (1e-13, 1e-13) if X64 else (2e-5, 4e-5)
    for got, want, sign, t in zip(batch, one, signs + signs, (tol[0], tol[0], tol[1], tol[1])):
        assert_close(got * sign.reshape(sign.shape + (1,) * (got.ndim - 1)), want, tol=t)


def test_quest_s_small_solve_is_numpy_s():
    """The 4x4 solve in ``quest``'s derivative (Gaussian elimination with partial pivoting written
    out) against NumPy's LU solve in float64: random matrices (condition up to about 5000), a zero
    leading entry and a tiny one (a pivot must be taken from below), to ``8 eps cond`` relative
    to the solution's largest entry; and a batch of two shapes."""
    from jaxquat.rotations.determination import _solve

    rng = np.random.default_rng(8)
    m = rng.normal(size=(256, 4, 4))
    m[:8, 0, 0] = 0.0
    m[8:16, :, 0] = [1e-12, 1.0, 0.0, 0.0]
    b = rng.normal(size=(256, 4))
    m_, b_ = (np.asarray(x, np.dtype(DTYPE)).astype(np.float64) for x in (m, b))
    got = np.asarray(jax.jit(_solve)(jnp.asarray(m_, DTYPE), jnp.asarray(b_, DTYPE)), np.float64)
    want = np.linalg.solve(m_, b_[..., None])[..., 0]
    eps = float(jnp.finfo(DTYPE).eps)
    scale = np.abs(want).max(-1) * np.linalg.cond(m_)
    assert np.all(np.abs(got - want).max(-1) < 8 * eps * scale)  # measured 0.68 (float64), 0.42 (float32)
    batch = jax.jit(_solve)(jnp.asarray(m_[:6].reshape(2, 3, 4, 4), DTYPE), jnp.asarray(b_[:6].reshape(2, 3, 4), DTYPE))
    assert batch.shape == (2, 3, 4)


def test_quest_s_value_has_no_matrix_product():
    """``quest``'s Rayleigh quotients and the rest of its value are written out on the entries: its
    jaxpr holds no ``dot_general`` (an ``einsum`` there ran a batched 4x4 product per quotient on
    CPU, ``docs/benchmarks.md``). The gradient keeps its ``einsum``s (written out, they were
    slower). The values themselves are checked against scipy and ``eigh`` above."""
    b = jnp.ones((8, 10, 3), DTYPE)
    assert "dot_general" not in str(jax.make_jaxpr(lambda r, b: jq.quest(b, r))(b, b))
