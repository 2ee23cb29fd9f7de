"""Jacobi elliptic functions and Carlson integrals: against scipy, the m -> 1 limit
(tanh/sech and the first-order expansion in 1 - m), identities, derivatives, batching
and bad input."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special as sp
from hypothesis import given
from jax.test_util import check_grads  # eps=1e-6: its default 1e-4 step is too coarse for K near m = 1

from jaxquat.mechanics import elliptic as el
from jaxquat import ellipj, ellipk, elliprf, elliprj
from helpers import DTYPE, NP_DTYPE, X64, assert_close, seeds

N = 64
TOL = 1e-13 if X64 else 3e-5
_ellipj = jax.jit(ellipj)
_jacobi = jax.jit(el._jacobi)
_am_rate = jax.jit(jax.vmap(jax.grad(lambda a, b: ellipj(a, b)[3])))


def _draw(seed):
    rng = np.random.default_rng(seed)
    u = rng.uniform(-25, 25, N)
    m = np.concatenate([rng.uniform(0, 0.99, N - 8), [0.0, 1e-12, 0.5, 0.9, 0.99, 0.999, 1e-3, 0.25]])
    return u.astype(NP_DTYPE), m.astype(NP_DTYPE)


@given(seeds)
def test_ellipj_matches_scipy(seed):
    u, m = _draw(seed)
    ours = _ellipj(jnp.asarray(u), jnp.asarray(m))
    ref = sp.ellipj(u.astype(np.float64), m.astype(np.float64))
    # |u| up to 25 carries the phase error eps * |u| (a few float32 ulps of 25 in float32).
    tol = TOL * 25
    for name, a, b in zip(["sn", "cn", "dn", "am"], ours, ref):
        assert a.dtype == DTYPE
        assert_close(a, b, tol=tol * (np.abs(b).max() if name == "am" else 1), what=name)


@given(seeds)
def test_identities(seed):
    u, m = _draw(seed)
    sn, cn, dn, am = _ellipj(jnp.asarray(u), jnp.asarray(m))
    assert_close(sn * sn + cn * cn, np.ones(N), tol=TOL, what="sn^2 + cn^2")
    assert_close(dn * dn + m * sn * sn, np.ones(N), tol=TOL, what="dn^2 + m sn^2")
    # d am / du = dn, by autodiff through the Landen recurrence.
    dam = _am_rate(jnp.asarray(u), jnp.asarray(m))
    assert_close(dam, dn, tol=10 * TOL, what="d am/du")


def test_separatrix_limit():
    """m -> 1: tanh/sech at m = 1, and A&S 16.15's first-order expansion in mc = 1 - m
    (its error is O(mc^2)), with mc formed exactly (it never passes through 1 - m)."""
    u = jnp.linspace(-12.0, 12.0, 49, dtype=DTYPE)
    sn, cn, dn, am = _jacobi(u, jnp.ones_like(u), jnp.zeros_like(u))
    assert_close(sn, np.tanh(u), tol=TOL, what="sn(u|1)")
    assert_close(cn, 1 / np.cosh(u), tol=TOL, what="cn(u|1)")
    assert_close(dn, 1 / np.cosh(u), tol=TOL, what="dn(u|1)")
    mc = 1e-12
    u64 = np.asarray(u, np.float64)
    sn, cn, dn, _ = _jacobi(u, jnp.full_like(u, 1 - mc), jnp.full_like(u, mc))
    ch, th, k = np.cosh(u64), np.tanh(u64), mc / 4 * (np.sinh(u64) * np.cosh(u64) - u64)
    assert_close(sn, th + k / ch**2, tol=TOL, what="sn near m = 1")
    assert_close(cn, 1 / ch - k * th / ch, tol=TOL, what="cn near m = 1")


def test_complete_and_carlson_against_scipy():
    rng = np.random.default_rng(3)
    m = np.concatenate([rng.uniform(0, 1, 40), 1 - 10.0 ** -np.arange(1, 9 if X64 else 6)])
    assert_close(ellipk(jnp.asarray(m, DTYPE)) / sp.ellipk(m), np.ones_like(m), tol=TOL * 10, what="K")
    # The domain the propagator uses: z = 1, x in [0, 1], y in (0, 1], p >= 1; and generic positive triples.
    x = np.concatenate([rng.uniform(0, 1, 30), [0.0, 1e-300 if X64 else 1e-37]])
    y = np.concatenate([10.0 ** rng.uniform(-12, 0, 30), [1e-30, 0.5]])
    p = rng.uniform(1, 6, 32)
    z = np.ones_like(x)
    assert_close(
        elliprf(*(jnp.asarray(v, DTYPE) for v in (x, y, z))) / sp.elliprf(x, y, z),
        np.ones(32),
        tol=TOL * 10,
        what="R_F",
    )
    assert_close(
        elliprj(*(jnp.asarray(v, DTYPE) for v in (x, y, z, p))) / sp.elliprj(x, y, z, p),
        np.ones(32),
        tol=TOL * 10,
        what="R_J",
    )
    a, b, c, d = rng.uniform(0.01, 10, (4, 32))
    assert_close(
        elliprj(*(jnp.asarray(v, DTYPE) for v in (a, b, c, d))) / sp.elliprj(a, b, c, d),
        np.ones(32),
        tol=TOL * 10,
        what="R_J generic",
    )
    # R_D (the amplitude's derivative in m; internal): the domain it is used on, x = cos^2 r and
    # z = dn^2 in (0, 1] or x = tiny and z = 1 - m, and generic positive triples.
    rd_x, rd_z = np.concatenate([x, a]), np.concatenate([y, c])
    assert_close(
        jax.jit(el.rd)(*(jnp.asarray(v, DTYPE) for v in (rd_x, np.ones(64), rd_z))) / sp.elliprd(rd_x, 1.0, rd_z),
        np.ones(64),
        tol=TOL * 10,
        what="R_D",
    )


def test_incomplete_integrals_unwrap():
    """F and Pi of an amplitude beyond pi/2 add whole complete integrals (checked against
    scipy's ellipkinc and a scipy R_F/R_J reference)."""
    rng = np.random.default_rng(4)
    phi = rng.uniform(-9, 9, 24)
    m, n = rng.uniform(0, 0.95, 24), -rng.uniform(0, 4, 24)
    # The amplitude goes in as whole turns plus (sin, cos), as the torque-free flow passes it.
    turns = np.round(phi / (2 * np.pi))
    h, s, c = el.reduced_amplitude(jnp.asarray(np.sin(phi), DTYPE), jnp.asarray(np.cos(phi), DTYPE))
    j_in = 2 * turns + h
    m_, mc_, n_ = (jnp.asarray(x, DTYPE) for x in (m, 1 - m, n))
    # As the torque-free flow forms them: the integrals at the reduced amplitude r, the complete
    # ones (s = 1, c = tiny_cos, y = complete_y), and 2 j of the complete ones added.
    f_r, pi_r = el.legendre(s, c, el.partial_y(c, m_, mc_), n_)
    f_k, pi_k = el.legendre(*el.complete_arguments(mc_), n_)
    f, pi = 2 * j_in * f_k + f_r, 2 * j_in * pi_k + pi_r
    j = np.round(phi / np.pi)
    r = phi - j * np.pi
    np.testing.assert_array_equal(np.asarray(j_in), j)
    assert_close(f, 2 * j * sp.ellipk(m) + sp.ellipkinc(r, m), tol=TOL * 20, what="F")

    def pi_ref(phi_):
        s, c = np.sin(phi_), np.cos(phi_)
        return s * sp.elliprf(c * c, 1 - m * s * s, 1) + n / 3 * s**3 * sp.elliprj(
            c * c, 1 - m * s * s, 1, 1 - n * s * s
        )

    assert_close(pi, 2 * j * pi_ref(np.pi / 2) + pi_ref(r), tol=TOL * 20, what="Pi")


def _legendre_each(a, b):
    return el.legendre(*a), el.legendre(*b)


_legendre_apart = jax.jit(_legendre_each)
_legendre_joint = jax.jit(lambda a, b: tuple(el.legendre_joint(a, b)))


@pytest.mark.parametrize("times", [2, 10])
def test_amplitude_of_per_body_agm_is_that_of_the_agm_at_every_time(times):
    """``amplitude`` with an AGM per body shared by its times (rank-aligned, as the torque-free
    flow passes it) is the amplitude with the AGM broadcast to every time; from 4 times on the loop
    runs with the times' axis first (``_shared_axes_first``), at 2 times in the given order, and
    both ways agree with ``ellipj`` (scipy's convention) to rounding."""
    rng = np.random.default_rng(times)
    bodies = 40
    m = jnp.asarray(rng.uniform(0, 0.99, bodies), DTYPE)
    u = jnp.asarray(rng.uniform(-25, 25, (bodies, times)), DTYPE)
    steps, a_last = el.agm(m, 1 - m)
    shared = jax.jit(el.amplitude)(u, tuple(x[..., None] for x in steps), a_last[..., None])
    full = tuple(jnp.broadcast_to(x[..., None], x.shape + (times,)) for x in steps)
    each = jax.jit(el.amplitude)(u, full, jnp.broadcast_to(a_last[..., None], u.shape))
    assert el._shared_axes_first(u.shape, (bodies, 1)) == (None if times < 4 else (1, 0))
    assert el._shared_axes_first(u.shape, (bodies, times)) is None
    assert shared.shape == u.shape
    assert_close(shared, each, tol=TOL * 25, what="amplitude, shared AGM")
    assert_close(shared, _ellipj(u, jnp.broadcast_to(m[:, None], u.shape))[3], tol=TOL * 25 * 25, what="am")


def test_shared_axes_first_orders_the_longer_axes_last():
    """The loop order of ``amplitude``: shared axes (size 1 in the AGM) first where they are at
    least 4 long, not a multiple of 16 and shorter than the rest; otherwise the order as given."""
    order = el._shared_axes_first
    assert order((1000, 101), (1000, 1)) == (1, 0)
    assert order((1000, 3), (1000, 1)) is None  # under 4 times
    assert order((1000, 256), (1000, 1)) is None  # whole vectors of 16 lanes
    assert order((1000, 250), (1000, 1)) == (1, 0)
    assert order((10, 101), (10, 1)) is None  # more times than bodies
    assert order((70, 5, 6), (70, 1, 1)) == (1, 2, 0)
    assert order((7, 5, 6), (7, 1, 1)) is None  # 30 times, 7 bodies
    assert order((8, 1, 6), (8, 1, 1)) == (2, 0, 1)  # a size-1 axis counts with the bodies'
    assert order((5,), (5,)) is None


def test_legendre_of_several_sets_in_one_loop_is_legendre_of_each():
    """``legendre_joint`` (one Carlson loop for sets of different shapes, as the torque-free flow
    takes its per-body and per-time integrals) gives each set's ``legendre``, values and
    gradients, in the set's own shape (a ``(2, 5)`` set with a broadcast ``n`` and a ``(7, 5)``
    one)."""
    rng = np.random.default_rng(11)
    m = rng.uniform(0, 0.95, 5)

    def args(rows):
        phi = rng.uniform(-1.5, 1.5, (rows, 5))
        s, c = np.sin(phi), np.cos(phi)
        return tuple(jnp.asarray(v, DTYPE) for v in (s, c, 1 - m * s * s, -rng.uniform(0, 3, (rows, 5))))

    a, b = args(2), args(7)
    a = (*a[:3], a[3][:1])  # n broadcast over the set, as the flow's -nu[None]
    joint, apart = _legendre_joint(a, b), _legendre_apart(a, b)
    assert [x.shape for pair in joint for x in pair] == [(2, 5), (2, 5), (7, 5), (7, 5)]
    for got, want in zip(jax.tree.leaves(joint), jax.tree.leaves(apart)):
        assert_close(got, want, tol=TOL, what="legendre_joint")

    def total(fn):
        return lambda a, b: sum(jnp.sum(x * (1 + i)) for i, x in enumerate(jax.tree.leaves(fn(a, b))))

    grads = [jax.jit(jax.grad(total(fn), argnums=(0, 1)))(a, b) for fn in (el.legendre_joint, _legendre_each)]
    for got, want in zip(*(jax.tree.leaves(g) for g in grads)):
        assert_close(got, want, tol=TOL, what="legendre_joint's gradient")


def _legendre_through_the_loop(s, c, y, n):
    """``legendre`` differentiated by JAX through Carlson's duplication loop (its form before the
    closed-form derivatives of ``_carlson_unit_z``)."""
    r_f, r_j = el.carlson(c * c, y, jnp.ones_like(c), 1 - n * s * s)
    return s * r_f, s * r_f + n / 3 * s * (s * s) * r_j


def _legendre_points():
    """Amplitudes, parameters and characteristics as the torque-free flow passes them (``n <= 0 <=
    m < 1``), with the points where ``_carlson_unit_z``'s gaps vanish or nearly (``s = 0``, small
    ``s``, ``n = 0``, ``m = n = 0``, ``m`` near 1), partial (``c = cos r``) and complete (``s = 1``,
    ``c = tiny_cos``) integrals: 2 x 96 points."""
    rng = np.random.default_rng(12)
    r, m, n = rng.uniform(-1.57, 1.57, 96), rng.uniform(0, 0.99, 96), -rng.uniform(0, 5, 96)
    r[:8], r[8:16], n[16:24], m[24:32], n[24:32], m[32:40] = 0.0, 1e-3, 0.0, 0.0, 0.0, 1 - 1e-5
    r[40:48], m[48:56], n[48:56] = np.pi / 2, 1e-4, -1e-4
    s, c = np.sin(r).astype(NP_DTYPE), np.cos(r).astype(NP_DTYPE)
    m_, mc_, n_ = (jnp.asarray(v, DTYPE) for v in (m, 1 - m, n))
    s_, c_ = jnp.asarray(s), jnp.asarray(c)
    partial = (s_, c_, el.partial_y(c_, m_, mc_), n_)
    complete = (*el.complete_arguments(mc_), n_)
    return tuple(jnp.concatenate([a, b]) for a, b in zip(partial, complete))


@functools.partial(jax.jit, static_argnums=0)
def _legendre_grads(fn, a):
    """The gradients of ``fn``'s ``F`` and ``Pi`` in each of its four arguments, element by element."""
    return [jax.vmap(jax.grad(lambda *z, k=k: fn(*z)[k], argnums=(0, 1, 2, 3)))(*a) for k in range(2)]


_legendre_jvps = jax.jit(lambda fn, a, t: jax.jvp(fn, a, t)[1], static_argnums=0)


def test_legendre_s_closed_form_derivatives_are_those_of_the_carlson_loop():
    """``legendre``'s derivatives (``_carlson_unit_z``: ``R_D`` with each argument distinguished,
    taken in the value's loop, then partial fractions and ``R_J``'s homogeneity) are JAX's
    derivatives through the duplication loop, in ``s, c, y, n``, both modes, finite at every point,
    including the 0/0 gaps at ``s = 0`` and ``m = n = 0``. Measured: 9.3e-15 (float64) and 4e-6
    (float32, where the closed form is the closer of the two to float64's) relative to ``1 + |d|``."""
    a = _legendre_points()
    got, want = _legendre_grads(el.legendre, a), _legendre_grads(_legendre_through_the_loop, a)
    for k, name in enumerate(("F", "Pi")):
        for i, arg in enumerate("scyn"):
            g, w = np.asarray(got[k][i], np.float64), np.asarray(want[k][i], np.float64)
            assert np.all(np.isfinite(g)), (name, arg)
            assert_close(g / (1 + np.abs(w)), w / (1 + np.abs(w)), tol=TOL, what=f"d{name}/d{arg} (reverse)")
    t = tuple(jnp.asarray(np.random.default_rng(13).normal(size=x.shape), DTYPE) for x in a)
    for g, w in zip(_legendre_jvps(el.legendre, a, t), _legendre_jvps(_legendre_through_the_loop, a, t)):
        g, w = np.asarray(g, np.float64), np.asarray(w, np.float64)
        assert_close(g / (1 + np.abs(w)), w / (1 + np.abs(w)), tol=TOL, what="legendre's jvp")


@pytest.mark.skipif(not X64, reason="second differences need float64")
def test_legendre_s_second_derivatives_are_those_of_the_carlson_loop():
    """The closed-form rule is differentiable again (its loop and the element-wise partials): the
    Hessian of ``Pi`` in ``(s, y, n)`` (forward over forward) at generic points (away from the 0/0
    gaps, where the rule's guard is a constant) is the loop's."""
    rng = np.random.default_rng(14)
    r, m, n = rng.uniform(0.2, 1.4, 4), rng.uniform(0.1, 0.9, 4), -rng.uniform(0.5, 3, 4)
    s, c = np.sin(r), np.cos(r)
    a = [jnp.asarray(v) for v in (s, c, 1 - m * s * s, n)]

    def hessian(fn):
        pi = lambda s, y, n, c: fn(s, c, y, n)[1]  # noqa: E731
        return np.asarray(
            jax.vmap(jax.jacfwd(jax.jacfwd(pi, argnums=(0, 1, 2)), argnums=(0, 1, 2)))(a[0], a[2], a[3], a[1])
        )

    assert_close(hessian(el.legendre), hessian(_legendre_through_the_loop), tol=1e-11, what="Pi's Hessian")


def test_derivative_in_m_at_and_near_one():
    """d/dm of sn, cn, dn at m = 1 (and 1 - 1e-12 in float64), both modes, against the
    m -> 1- limit from A&S 16.15: d sn/dm = -(sinh cosh - u) sech^2 / 4, d cn/dm =
    (sinh cosh - u) tanh sech / 4, d dn/dm = -(sinh cosh + u) tanh sech / 4. Through the
    Landen loop this was NaN at m = 1 and wrong near it; the amplitude's own derivative
    rule is regular there. At 1 - 1e-12 the derivative itself has moved by
    O(1e-12 d2/dm2) (measured 2.5e-9 at |u| <= 6)."""
    u = jnp.linspace(-6.0, 6.0, 25, dtype=DTYPE)
    u64 = np.asarray(u, np.float64)
    ch, th, sh = np.cosh(u64), np.tanh(u64), np.sinh(u64)
    ref = np.stack([-(sh * ch - u64) / (4 * ch**2), (sh * ch - u64) * th / (4 * ch), -(sh * ch + u64) * th / (4 * ch)])
    for m, tol in [(1.0, 10 * TOL)] + ([(1 - 1e-12, 1e-8)] if X64 else []):
        mm = jnp.full_like(u, m)
        _, fwd = _jvp_m(u, mm)
        rev = np.stack([_grad_m(u, mm, i) for i in range(3)])
        for got, mode in ((np.asarray(fwd), "fwd"), (rev, "rev")):
            assert np.all(np.isfinite(got))
            assert_close(
                got / np.maximum(1.0, np.abs(ref)),
                ref / np.maximum(1.0, np.abs(ref)),
                tol=tol,
                what=f"d/dm at m = {m} ({mode})",
            )


_jvp_m = jax.jit(lambda u, m: jax.jvp(lambda x: jnp.stack(ellipj(u, x)[:3]), (m,), (jnp.ones_like(m),)))
_grad_m = jax.jit(lambda u, m, i: jax.grad(lambda x: jnp.sum(jnp.stack(ellipj(u, x)[:3])[i]))(m))


@pytest.mark.skipif(not X64, reason="finite differences need float64")
def test_gradients():
    u = jnp.asarray([0.3, -2.0, 7.5])
    for m in (jnp.asarray([0.2, 0.7, 0.95]), jnp.asarray([0.0, 0.0, 0.0])):
        # m = 0 is smooth: the AGM's first step is written without sqrt(m).
        check_grads(
            lambda a, b: jnp.stack(ellipj(a, b)), (u, m), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6, eps=1e-6
        )
    # Second order: the amplitude's rule takes K'(m) as an input (R_D(0, 1, 1 - m), formed once per
    # m); formed differentiably, its own derivative enters the second one (u = 7.5, 12 turn whole
    # half-periods; with K'(m) held constant the d2/dm2 of am is off by a factor of 2). Forward
    # over forward only: reverse mode transposes the same rule (1.1 s against 3.4 s for both).
    u2, m2 = jnp.asarray([0.3, -2.0, 7.5, 12.0]), jnp.asarray([0.2, 0.7, 0.95, 0.5])
    check_grads(lambda a, b: jnp.stack(ellipj(a, b)), (u2, m2), order=2, modes=("fwd",), atol=1e-5, rtol=1e-5, eps=1e-5)
    x, y, p = jnp.asarray([0.2, 0.9]), jnp.asarray([0.5, 0.01]), jnp.asarray([1.5, 3.0])
    check_grads(
        lambda a, b, c: elliprj(a, b, 1.0, c), (x, y, p), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6, eps=1e-6
    )
    check_grads(lambda a, b: elliprf(a, b, 1.0), (x, y), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6, eps=1e-6)


def test_jit_vmap_and_broadcasting():
    u, m = _draw(9)
    eager = ellipj(jnp.asarray(u), jnp.asarray(m))
    mapped = jax.vmap(ellipj)(jnp.asarray(u), jnp.asarray(m))
    nested = ellipj(jnp.asarray(u).reshape(8, 8), jnp.asarray(m).reshape(8, 8))
    for e, a, b in zip(eager, mapped, nested):
        assert_close(a, e, tol=TOL, what="vmap")
        assert_close(b.reshape(-1), e, tol=TOL, what="nested")
    assert ellipj(jnp.asarray(u), 0.5)[0].shape == (N,)  # scalar m broadcasts


def test_bad_input():
    with pytest.raises(TypeError, match="argument 'm' must have a floating dtype"):
        ellipj(jnp.ones(3), jnp.ones(3, jnp.int32))
    with pytest.raises(TypeError, match="argument 'p'"):
        elliprj(1.0, 1.0, 1.0, jnp.ones(2, jnp.int32))
    with pytest.raises(ValueError, match="broadcast"):
        ellipj(jnp.ones(3), jnp.ones(4))


def test_outside_the_domain_gives_nan_as_scipy_does():
    m = jnp.asarray([1.5, 2.0, np.inf, np.nan], DTYPE)
    assert np.all(np.isnan(np.asarray(ellipk(m)))) and np.all(np.isnan(sp.ellipk(np.asarray(m))))
    for out in ellipj(jnp.full(4, 0.3, DTYPE), m):
        assert np.all(np.isnan(np.asarray(out)))
    # negative m is inside the domain
    assert_close(ellipk(jnp.asarray(-3.0, DTYPE)), sp.ellipk(-3.0), tol=1e-12 if X64 else 1e-5)
