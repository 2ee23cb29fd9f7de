"""RotationSpline against scipy's RotationSpline, its rates against autodiff, continuity across
keys, the double cover, gradients with respect to keys and times; squad's key passage, C1
continuity and the great-circle closed form."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from scipy.spatial.transform import Rotation
from scipy.spatial.transform import RotationSpline as ScipySpline

import jaxquat as jq
from helpers import DTYPE, X64, assert_close, assert_same_rotation, central_difference_jacobian, seeds, to_scipy

SCIPY_TOL = 1e-10 if X64 else 2e-3  # float32 keys vs scipy's float64 construction


def _keys(seed, n):
    rng = np.random.default_rng(seed)
    times = np.cumsum(rng.uniform(0.2, 2.0, n)) - 1.0
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return times, q


@jax.jit
def _evaluate(times, q, ts):
    s = jq.RotationSpline(times, q)
    return s(ts), s(ts, 1), s(ts, 2)


@pytest.mark.parametrize("n", [2, 3, 5, 12])
@given(seed=seeds)
def test_agrees_with_scipy_rotation_spline(n, seed):
    times, q = _keys(seed, n)
    q = q.astype(np.float32 if not X64 else np.float64).astype(np.float64)  # what our dtype sees
    ref = ScipySpline(times, Rotation.from_quat(to_scipy(q)))
    ts = np.concatenate([np.linspace(times[0] - 0.5, times[-1] + 0.5, 41), times])
    att, rate, acc = _evaluate(jnp.asarray(times, DTYPE), jnp.asarray(q, DTYPE), jnp.asarray(ts, DTYPE))
    scale = max(1.0, np.abs(ref(ts, 2)).max())
    assert_same_rotation(att, ref(ts).as_quat()[:, [3, 0, 1, 2]], tol=SCIPY_TOL)
    assert_close(np.asarray(rate) / scale, ref(ts, 1) / scale, tol=SCIPY_TOL, what="angular rate vs scipy")
    assert_close(
        np.asarray(acc) / scale,
        ref(ts, 2) / scale,
        tol=SCIPY_TOL * (10 if not X64 else 1),
        what="angular acceleration vs scipy",
    )


def test_passes_through_the_keys_and_ignores_their_signs():
    """Five keys and the times of ``test_agrees_with_scipy_rotation_spline`` (41 across the keys
    and beyond them, then the keys): its compiled program for five keys serves this test too (six
    keys at 50 and at 6 times compiled two of their own, 1.8 s each in float64, session 41)."""
    times, q = _keys(1, 5)
    flipped = q * np.array([1, -1, -1, 1, -1])[:, None]
    ts = jnp.asarray(np.concatenate([np.linspace(times[0] - 0.5, times[-1] + 0.5, 41), times]), DTYPE)
    a = _evaluate(jnp.asarray(times, DTYPE), jnp.asarray(q, DTYPE), ts)
    b = _evaluate(jnp.asarray(times, DTYPE), jnp.asarray(flipped, DTYPE), ts)
    tol = 1e-12 if X64 else 1e-5
    assert_same_rotation(a[0], b[0], tol=tol)
    assert_close(a[1], b[1], tol=tol)
    assert_close(a[2], b[2], tol=100 * tol)
    assert_same_rotation(a[0][-len(times) :], q, tol=10 * tol)  # at the keys


def test_rates_are_the_derivatives_of_the_attitude_and_continuous():
    times, q = _keys(2, 5)
    s = jq.RotationSpline(jnp.asarray(times, DTYPE), jnp.asarray(q, DTYPE))
    ts = jnp.asarray([0.3, 1.1, 2.2, 3.3], DTYPE) * (times[-1] - times[0]) / 3.5 + times[0] + 0.01

    @jax.jit
    def derived(t):
        qq, qd, qdd = [f(t) for f in (s, jax.jacfwd(s), jax.jacfwd(jax.jacfwd(s)))]
        return jq.omega_from_qdot(qq, qd), jq.alpha_from_qddot(qq, qd, qdd)

    w, a = jax.vmap(derived)(ts)
    tol = 1e-10 if X64 else 1e-3
    scale = max(1.0, float(jnp.abs(a).max()))
    assert_close(s(ts, 1) / scale, w / scale, tol=tol, what="order 1 = omega of d/dt spline")
    assert_close(s(ts, 2) / scale, a / scale, tol=tol, what="order 2 = alpha of d2/dt2 spline")


@pytest.mark.skipif(not X64, reason="a jump test needs a time step far below float32 resolution")
def test_rate_and_acceleration_are_continuous_across_keys():
    times, q = _keys(2, 5)
    s = jq.RotationSpline(jnp.asarray(times), jnp.asarray(q))
    eps = 1e-8  # the smooth change over 2 eps is ~1e-7; a kink would show as O(1)
    for k in range(1, 4):
        for order in (1, 2):
            jump = float(jnp.abs(s(times[k] + eps, order) - s(times[k] - eps, order)).max())
            assert jump < 1e-5, (k, order, jump)


@pytest.mark.skipif(not X64, reason="finite differences need float64")
def test_gradients_with_respect_to_keys_and_times():
    """Reverse mode through the spline's construction and its three orders, in the keys and the
    times at once, against central differences. (One spline of both: until session 36 one of the
    keys and one of the times, two fits in each compiled program; the test alone took 15.1 s against
    8.7 s then, float64 on a 2-core EPYC.)"""
    times, q = _keys(4, 4)
    t_eval = jnp.asarray(np.linspace(times[0] + 0.1, times[-1] - 0.1, 7))
    w = jnp.asarray(np.random.default_rng(0).normal(size=(7, 3)))

    def loss(x):  # keys and times in one vector, one spline: one compiled gradient and one loss
        s = jq.RotationSpline(x[16:], jq.normalize(x[:16].reshape(4, 4)))
        return jnp.sum((s(t_eval, 1) + s(t_eval, 2)) * w) + jnp.sum(s(t_eval)[:, 1:] ** 2)

    x = np.concatenate([np.asarray(q).ravel(), np.asarray(times)])
    # one compiled program for the gradient and every central difference's value (a loss of
    # its own compiled in 1.2 s more, float64, session 56)
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    g = np.asarray(value_and_grad(jnp.asarray(x))[1])
    fd = central_difference_jacobian(lambda y: value_and_grad(y)[0], x, h=1e-6)
    assert np.all(np.isfinite(g))
    for part, what in ((slice(0, 16), "keys"), (slice(16, None), "times")):
        scale = max(1.0, float(np.abs(fd[part]).max()))
        assert_close(g[part] / scale, fd[part] / scale, tol=1e-6, what=f"d/d {what} vs central differences")


def test_vmap_over_key_sets_and_jit():
    times, _ = _keys(5, 4)
    qs = np.stack([_keys(s, 4)[1] for s in range(3)])
    ts = jnp.linspace(times[0], times[-1], 9, dtype=DTYPE)
    batched = jax.vmap(lambda qq: jq.RotationSpline(jnp.asarray(times, DTYPE), qq)(ts, 1))(jnp.asarray(qs, DTYPE))
    for i in range(3):
        single = _evaluate(jnp.asarray(times, DTYPE), jnp.asarray(qs[i], DTYPE), ts)[1]
        assert_close(batched[i], single, tol=1e-12 if X64 else 1e-5)
    spline = jq.RotationSpline(jnp.asarray(times, DTYPE), jnp.asarray(qs[0], DTYPE))
    assert_close(jax.jit(lambda s, t: s(t, 2))(spline, ts), spline(ts, 2), tol=1e-12 if X64 else 1e-4)


@pytest.mark.skipif(X64, reason="half precision does not depend on the x64 flag: checked once, in the float32 pass")
@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16])
def test_half_precision_builds_in_float32_and_returns_the_input_dtype(dtype):
    """(NotImplementedError before: XLA has no half-precision LU for the rate solve.)"""
    times, q = _keys(5, 4)
    ts = np.linspace(times[0], times[-1], 9)
    for order in (0, 1, 2):
        out = jq.RotationSpline(jnp.asarray(times, dtype), jnp.asarray(q, dtype))(jnp.asarray(ts, dtype), order)
        ref = jq.RotationSpline(jnp.asarray(times, jnp.float32), jnp.asarray(q, jnp.float32))(
            jnp.asarray(ts, jnp.float32), order
        )
        assert out.dtype == dtype
        out, ref = np.asarray(out, np.float32), np.asarray(ref, np.float32)
        assert np.all(np.isfinite(out))
        assert_close(out, ref, tol=0.1 * max(1.0, float(np.abs(ref).max())), what=f"order {order} {dtype}")


def test_bad_input():
    with pytest.raises(ValueError, match="argument 'times' must be strictly increasing"):
        jq.RotationSpline(jnp.asarray([0.0, 1.0, 1.0]), jq.identity(3))
    with pytest.raises(ValueError, match=r"argument 'quats' must be shaped \(n, 4\) with n >= 2"):
        jq.RotationSpline(jnp.asarray([0.0]), jq.identity(1))
    with pytest.raises(ValueError, match=r"argument 'times' must be shaped \(n,\) with n = 3"):
        jq.RotationSpline(jnp.asarray([0.0, 1.0]), jq.identity(3))
    with pytest.raises(ValueError, match=r"argument 'quats' must be a quaternion array shaped \(\.\.\., 4\)"):
        jq.RotationSpline(jnp.asarray([0.0, 1.0]), jnp.zeros((2, 3)))
    with pytest.raises(ValueError, match="argument 'order' must be 0, 1 or 2"):
        jq.RotationSpline(jnp.asarray([0.0, 1.0]), jq.identity(2))(0.5, order=3)


# ------------------------------------------------------------------ squad


def test_squad_on_a_great_circle_is_uniform_rotation():
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    keys = jq.from_rotvec(jnp.asarray(np.outer(np.arange(5) * 0.6, axis), DTYPE))
    u = jnp.linspace(0.0, 4.0, 33, dtype=DTYPE)
    expected = jq.from_rotvec(jnp.asarray(np.outer(np.asarray(u) * 0.6, axis), DTYPE))
    assert_same_rotation(jq.squad(keys, u), expected, tol=1e-12 if X64 else 1e-5)


@jax.jit
def _squad_joins(keys):
    """Squad at the keys, and its derivative at the end of segment i-1 and the start of segment i."""
    controls = jq.squad_control_points(keys)
    aligned = jq.squad(keys, jnp.arange(keys.shape[0], dtype=keys.dtype))  # the sign-aligned keys

    def derivative(h):  # d/dh of every segment at parameter h, one batched forward-mode pass
        seg = lambda x: jq.squad_segment(aligned[:-1], aligned[1:], controls[:-1], controls[1:], x)  # noqa: E731
        x = jnp.full(keys.shape[:1][0] - 1, h, keys.dtype)
        return jax.jvp(seg, (x,), (jnp.ones_like(x),))[1]

    return aligned, derivative(1.0)[:-1], derivative(0.0)[1:]


@given(seed=seeds)
def test_squad_passes_through_keys_and_is_C1(seed):
    _, q = _keys(seed, 6)
    keys = jnp.asarray(q, DTYPE)
    at_keys, left, right = _squad_joins(keys)
    assert_same_rotation(at_keys, q, tol=1e-12 if X64 else 1e-5)
    assert_close(left, right, tol=1e-11 if X64 else 1e-4, what="squad derivative across keys")
    flipped = keys * jnp.asarray([1, -1, 1, -1, -1, 1], DTYPE)[:, None]
    assert_same_rotation(_squad_joins(flipped)[0], at_keys, tol=1e-12 if X64 else 1e-5)


def test_squad_bad_input():
    with pytest.raises(ValueError, match=r"argument 'keys' must be shaped \(n, 4\)"):
        jq.squad(jq.identity((2, 3)), 0.5)
    with pytest.raises(ValueError, match=r"argument 'keys' must be shaped \(\.\.\., n, 4\) with n >= 2"):
        jq.squad_control_points(jq.identity(1))
