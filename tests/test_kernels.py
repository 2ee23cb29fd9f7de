"""The component kernels behind the rotation ops (``jaxquat._arrays``, ``_quaternion``, ``_safe``)
and the one-loop barriers of the integrator steps (``jaxquat._fusion``).

``components`` (a primitive) and ``assemble`` (a custom JVP) carry derivatives chosen for how XLA
on CPU compiles their tangents and transposes, and ``atan2_over_n``/``sinc_cos_of_sq`` carry
closed-form derivatives: each must still be exactly the split, the stack and the derivatives of
the functions they replace, checked here against independent references (NumPy's complex-step
derivatives, finite differences, the Hamilton product in rows).
"""

import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from jax.test_util import check_grads

from helpers import DTYPE, NP_DTYPE, X64, seeds
from jaxquat import _arrays, _fusion, _quaternion, _safe, _trig

EPS = float(np.finfo(NP_DTYPE).eps)


BITS = np.uint64 if X64 else np.uint32  # a float's bits, to compare values to the bit

BARRIERS = {
    "one_loop": _fusion.one_loop,
    "one_loop_backward": _fusion.one_loop_backward,
    "one_loop_both_ways": _fusion.one_loop_both_ways,
}


def _through(barrier, x):
    """A small step with ``barrier`` on its input pair and on its output pair (None: none)."""
    pass_ = (lambda xs: tuple(xs)) if barrier is None else BARRIERS[barrier]
    a, b = pass_((x, jnp.sin(x) * x))
    u = jnp.cos(a) * b + a * a
    return pass_((u * b, u - jnp.exp(-a)))


@pytest.mark.parametrize("barrier", sorted(BARRIERS))
def test_one_loop_barriers_are_the_identity_to_the_bit(barrier):
    """Every float passes unchanged, signed zeros, infinities, NaN and subnormals included
    (``x + (-0.0) == x``), compiled and eager, and the result keeps each input's dtype."""
    tiny = float(np.finfo(NP_DTYPE).smallest_subnormal)
    x = jnp.asarray([0.0, -0.0, 1.5, -2.25, np.inf, -np.inf, np.nan, tiny, -tiny, 3e38], DTYPE)
    y = x[::-1]
    for out in (jax.jit(BARRIERS[barrier])((x, y)), BARRIERS[barrier]((x, y))):
        for got, want in zip(out, (x, y)):
            assert got.dtype == want.dtype
            np.testing.assert_array_equal(np.asarray(got).view(BITS), np.asarray(want).view(BITS))
    half = jax.jit(BARRIERS[barrier])((x.astype(jnp.float16), y))
    assert half[0].dtype == jnp.float16 and half[1].dtype == DTYPE


_both_ways_jit = jax.jit(_fusion.one_loop_both_ways)
_both_ways_grad = jax.jit(
    jax.grad(lambda xs, w: sum(jnp.sum(a * b) for a, b in zip(_fusion.one_loop_both_ways(xs), w)))
)


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_one_loop_passes_any_floats_and_their_cotangents_unchanged(seed):
    """Random finite and non-finite values, three arrays of one fixed shape (one compilation): the
    values pass to the bit, and the cotangents of a weighted sum are the weights, to the bit."""
    rng = np.random.default_rng(seed)
    special = np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 1e-30], NP_DTYPE)
    xs = tuple(
        jnp.asarray(
            np.where(
                rng.random(12) < 0.3, rng.choice(special, 12), rng.normal(size=12) * 10.0 ** rng.integers(-8, 8, 12)
            ),
            DTYPE,
        )
        for _ in range(3)
    )
    w = tuple(jnp.asarray(rng.normal(size=12), DTYPE) for _ in range(3))
    for got, want in zip(_both_ways_jit(xs), xs):
        np.testing.assert_array_equal(np.asarray(got).view(BITS), np.asarray(want).view(BITS))
    for got, want in zip(_both_ways_grad(xs, w), w):
        np.testing.assert_array_equal(got, want)


_through_plain = jax.jit(lambda x: _through(None, x))


@pytest.mark.parametrize("barrier", sorted(BARRIERS))
def test_one_loop_barriers_are_the_identity_to_every_transform(barrier):
    """``grad``, ``jvp``, ``jacfwd``, ``linearize``, the Hessian both ways, a Hessian-vector
    product, the gradient of a ``jvp``, ``vmap`` (with an unbatched operand) and ``jax.checkpoint``
    (nothing saved, and everything saved) through a step with the barriers equal the step without
    them (to a few ulps: the loops' boundaries move where the compiler contracts products into
    fused multiply-adds, measured up to 1.4e-14 in a float64 Hessian), and ``check_grads`` passes.
    Under ``jvp`` values and tangents share one bind, which ``linearize`` and remat must split
    again (the partial-evaluation rules of ``jaxquat._fusion``): the transforms that mix the
    modes are the ones that would fail without them."""
    x = jnp.asarray(np.random.default_rng(2).uniform(0.1, 1.0, size=(5,)), DTYPE)
    dx = jnp.asarray(np.random.default_rng(3).normal(size=(5,)), DTYPE)

    def cost(fn):
        return lambda x: jnp.sum(fn(x)[0] * jnp.arange(5)) + jnp.sum(fn(x)[1] ** 2)

    def step(x):
        return _through(barrier, x)

    tol = dict(rtol=64 * EPS, atol=64 * EPS)
    for transform in (
        lambda f: jax.grad(cost(f))(x),
        lambda f: jax.jvp(f, (x,), (dx,))[1],
        lambda f: jax.jacfwd(cost(f))(x),
        lambda f: jax.hessian(cost(f))(x),
        lambda f: jax.jacrev(jax.jacfwd(cost(f)))(x),
        lambda f: jax.jvp(jax.grad(cost(f)), (x,), (dx,))[1],
        lambda f: jax.grad(lambda x: jax.jvp(cost(f), (x,), (dx,))[1])(x),
        lambda f: jax.linearize(f, x)[1](dx),
        lambda f: jax.grad(jax.checkpoint(cost(f)))(x),
        lambda f: jax.jacfwd(jax.grad(jax.checkpoint(cost(f))))(x),
        lambda f: jax.grad(jax.checkpoint(cost(f), policy=jax.checkpoint_policies.everything_saveable))(x),
        lambda f: jax.vmap(jax.grad(cost(f)))(jnp.stack([x, 2 * x])),
    ):
        got, want = jax.jit(lambda t=transform: t(step))(), jax.jit(lambda t=transform: t(_through_plain))()
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
            np.testing.assert_allclose(a, b, **tol)
    pair = jax.vmap(BARRIERS[barrier], in_axes=((0, None),))((jnp.stack([x, dx]), x))
    np.testing.assert_array_equal(pair[1], jnp.stack([x, x]))
    check_grads(lambda x: step(x)[0], (x,), order=2, modes=["fwd", "rev"])


@pytest.mark.skipif(not X64, reason="a lowering test: its verdict does not depend on the dtype")
def test_one_loop_lowers_to_a_variadic_reduce_on_cpu_only():
    """On CPU ``one_loop`` lowers its values to one variadic ``reduce`` with an operand per array,
    under ``jvp`` its values and tangents together (one ``reduce``, six operands), and
    ``one_loop_backward`` lowers its cotangents so under ``grad``; the other kind lowers to
    nothing. For a GPU (lowered here without one, by ``jax.export``) neither is a ``reduce``."""
    x = jnp.ones((7,), DTYPE)

    def reduces(fn, *args, platform="cpu"):
        text = jax.export.export(jax.jit(fn), platforms=[platform])(*args).mlir_module()
        return text.count("stablehlo.reduce")

    def three(fn):
        return lambda x: fn((x * 2, x + 1, x * x))

    def loss(fn):
        return lambda x: sum(jnp.sum(c * (i + 1)) for i, c in enumerate(three(fn)(x)))

    assert reduces(three(_fusion.one_loop), x) == 1
    assert reduces(three(_fusion.one_loop_backward), x) == 0
    assert reduces(lambda x, d: jax.jvp(three(_fusion.one_loop), (x,), (d,)), x, x) == 1
    jvp_text = jax.export.export(jax.jit(lambda x, d: jax.jvp(three(_fusion.one_loop), (x,), (d,))), platforms=["cpu"])
    assert re.search(r"%\w+:6 = stablehlo\.reduce\(", jvp_text(x, x).mlir_module())  # six results
    assert reduces(lambda x, d: jax.jvp(three(_fusion.one_loop_backward), (x,), (d,)), x, x) == 0
    plain_grad = reduces(jax.grad(loss(lambda xs: tuple(xs))), x)  # the loss's own sums
    assert reduces(jax.grad(loss(_fusion.one_loop_backward)), x) == plain_grad + 1
    assert reduces(jax.grad(loss(_fusion.one_loop)), x) == plain_grad
    assert reduces(three(_fusion.one_loop_both_ways), x, platform="cuda") == 0
    assert reduces(jax.grad(loss(_fusion.one_loop_both_ways)), x, platform="cuda") == plain_grad


def test_one_loop_keeps_only_the_arrays_that_are_used():
    """Dead-code elimination drops an unused array from the bind (its loop computes the rest), and
    a ``vmap`` with one operand unmapped binds it apart and leaves it unmapped (``jacfwd`` maps
    the tangents only, and its value must come out unmapped)."""
    from jax.interpreters import partial_eval as pe

    x = jnp.arange(3.0, dtype=DTYPE)
    for barrier in BARRIERS.values():
        jaxpr = jax.make_jaxpr(lambda a, b, barrier=barrier: barrier((a * 2, b + 1)))(x, x).jaxpr
        kept, used_inputs = pe.dce_jaxpr(jaxpr, [False, True])
        binds = [e for e in kept.eqns if e.primitive.name == "jaxquat_one_loop"]
        assert used_inputs == [False, True]
        assert [len(e.invars) for e in binds] == [1] * len(binds) and binds
        value, batch = jax.vmap(barrier, in_axes=((None, 0),), out_axes=(None, 0))((x, jnp.stack([x, -x])))
        np.testing.assert_array_equal(value, x)
        np.testing.assert_array_equal(batch, jnp.stack([x, -x]))


def test_one_loop_rejects_arrays_of_different_shapes():
    x = jnp.ones((3,), DTYPE)
    expected = r"one_loop: every array must have one shape, got shapes \[\(3,\), \(4,\)\]"
    for barrier in BARRIERS.values():
        with pytest.raises(ValueError, match=expected):
            barrier((x, jnp.ones((4,), DTYPE)))


def _roundtrip(x):
    return _arrays.assemble(*_arrays.components(x))


_roundtrip_jit = jax.jit(_roundtrip)


@pytest.mark.parametrize("cpu", [True, False], ids=["cpu", "other"])
@pytest.mark.parametrize("shape", [(4,), (5, 3), (2, 3, 9)])
def test_components_and_assemble_are_the_split_and_the_stack(cpu, shape, monkeypatch):
    """Values to the bit (sums of products with 0 and 1 are exact for finite values), and as
    derivatives the identity in forward and reverse mode, on the CPU path (products, dot
    tangents) and the other platforms' (a plain stack)."""
    monkeypatch.setattr(_trig, "_cpu", lambda: cpu)
    x = jnp.asarray(np.random.default_rng(0).normal(size=shape), DTYPE)
    f = jax.jit(lambda x: _roundtrip(x))  # a fresh trace per backend setting
    np.testing.assert_array_equal(f(x), x)
    parts = _arrays.components(x)
    assert len(parts) == shape[-1] and all(p.shape == shape[:-1] for p in parts)
    np.testing.assert_array_equal(jnp.stack(parts, axis=-1), x)
    w = jnp.asarray(np.random.default_rng(1).normal(size=shape), DTYPE)
    np.testing.assert_array_equal(jax.grad(lambda x: jnp.sum(f(x) * w))(x), w)
    np.testing.assert_array_equal(jax.jvp(f, (x,), (w,))[1], w)
    check_grads(f, (x,), order=2, modes=["fwd", "rev"], eps=1.0)  # linear: differences exact for any step


@pytest.mark.skipif(not X64, reason="a lowering test: its verdict does not depend on the dtype")
def test_components_tangents_are_a_split_and_their_cotangents_products_on_cpu(monkeypatch):
    """Forward mode takes the tangent's components by the split (no matrix product: with one,
    one ``jvp`` of ``from_euler`` at 10^6 took 95 ms against its value's 2 ms), and ``assemble``
    computes its tangents in one loop (one variadic ``reduce``) before stacking them; reverse
    mode gathers the cotangents through products with the identity on CPU (``dot_general``) and a
    concatenation elsewhere (the choice is made at trace time: ``_trig._cpu`` set to False)."""
    x = jnp.ones((7, 3), DTYPE)

    def count(fn, op):
        return jax.jit(fn).lower(x).as_text().count(op)

    def f(x):
        return _arrays.assemble(*(jnp.sin(c) * c for c in _arrays.components(x)))

    assert count(lambda x: jax.jvp(f, (x,), (x,))[1], "stablehlo.dot_general") == 0
    assert count(lambda x: jax.jvp(f, (x,), (x,))[1], "stablehlo.reduce") == 1
    assert count(jax.grad(lambda x: jnp.sum(f(x) * x)), "stablehlo.dot_general") == 3
    monkeypatch.setattr(_trig, "_cpu", lambda: False)
    assert count(jax.grad(lambda x: jnp.sum(f(x) * x)), "stablehlo.dot_general") == 0


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_components_under_vmap_on_any_axis_and_jacfwd(seed):
    """The primitive's batching rule moves the mapped axis first (the components stay last), for
    values, tangents and cotangents: ``vmap`` over axis 1, and ``jacfwd``/``jacrev`` (a ``vmap``
    of tangents) give the identity."""
    x = jnp.asarray(np.random.default_rng(seed).normal(size=(3, 5, 4)), DTYPE)
    out = jax.vmap(lambda y: jnp.stack(_arrays.components(y), axis=-1), in_axes=1, out_axes=1)(x)
    np.testing.assert_array_equal(out, x)
    out = jax.vmap(lambda y: jnp.stack(_arrays.components(y), axis=-1), in_axes=-1, out_axes=-1)(x[..., :3, :])
    np.testing.assert_array_equal(out, x[..., :3, :])  # the mapped axis last: components of shape (3, 3)
    eye = np.eye(4)
    for jac in (jax.jacfwd, jax.jacrev):  # jacfwd maps the tangents on their last axis
        np.testing.assert_array_equal(jax.jit(jac(lambda y: jnp.stack(_arrays.components(y))))(x[0, 0]), eye)


def test_assemble_nan_fills_the_row_on_cpu():
    """The documented price of the products on CPU: a NaN component makes its whole row NaN.
    Elsewhere (a plain stack) the NaN stays where it was."""
    x = jnp.asarray([[1.0, jnp.nan, 2.0], [1.0, 2.0, 3.0]], DTYPE)
    out = np.asarray(_roundtrip_jit(x))
    row = [True, True, True] if jax.default_backend() == "cpu" else [False, True, False]
    np.testing.assert_array_equal(np.isnan(out[0]), row)
    np.testing.assert_array_equal(out[1], [1.0, 2.0, 3.0])


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_components_vmap_and_batch(seed):
    x = jnp.asarray(np.random.default_rng(seed).normal(size=(3, 4, 4)), DTYPE)
    np.testing.assert_array_equal(jax.vmap(_roundtrip_jit)(x), x)


_multiply = jax.jit(_quaternion.multiply)


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_multiply_components_is_the_hamilton_product(seed):
    """Against the row form, with full quaternions and with exact zeros left out (``None``)."""
    rng = np.random.default_rng(seed)
    p = jnp.asarray(rng.normal(size=(8, 4)), DTYPE)
    q = jnp.asarray(rng.normal(size=(8, 4)), DTYPE)
    want = _multiply(p, q)
    got = jnp.stack(_quaternion.multiply_components(list(p.T), list(q.T)), axis=-1)
    np.testing.assert_allclose(got, want, rtol=0, atol=8 * EPS * 4)
    mask_p, mask_q = rng.random(4) < 0.5, rng.random(4) < 0.5
    sparse = _quaternion.multiply_components(
        [None if m else c for m, c in zip(mask_p, p.T)], [None if m else c for m, c in zip(mask_q, q.T)]
    )
    want = _multiply(p * jnp.asarray(~mask_p, DTYPE)[None, :], q * jnp.asarray(~mask_q, DTYPE)[None, :])
    for c, (got_c, want_c) in enumerate(zip(sparse, want.T)):
        if got_c is None:  # every term of this component had a zero factor
            np.testing.assert_array_equal(want_c, 0.0)
        else:
            np.testing.assert_allclose(got_c, want_c, rtol=0, atol=8 * EPS * 4, err_msg=f"component {c}")


def _atan_over_n_points():
    """``(nsq, w)`` across the series switch (``nsq/w^2 = 1e-3``) on both sides, at ``nsq = 0``,
    ``w`` of both signs and 0, and large ``nsq/w^2``."""
    rng = np.random.default_rng(3)
    w = np.concatenate([rng.uniform(0.05, 2.0, 300), rng.uniform(-2.0, -0.05, 100), np.zeros(20)])
    ratio = np.concatenate([10 ** rng.uniform(-9, 3, 300), 10 ** rng.uniform(-2, 3, 100), 10 ** rng.uniform(-2, 2, 20)])
    ratio[:20] = 1e-3 * (1 + np.linspace(-1e-3, 1e-3, 20))  # straddling the value's switch
    ratio[20:25] = 0.0
    ratio[25:45] = 0.1 * (1 + np.linspace(-1e-3, 1e-3, 20))  # straddling the derivative's
    nsq = ratio * np.where(w == 0, 1.0, w * w)
    return nsq, w


_atan_parts = jax.jit(jax.vmap(jax.value_and_grad(_safe.atan2_over_n, argnums=(0, 1))))


def _atan_over_n_dnsq_reference(nsq, w):
    """``d/dnsq`` of ``atan(n/w)/n`` for ``w > 0``, in float64: below ``nsq/w^2 = 0.1`` its
    power series (``(1/w^3) sum_k>=1 k (-1)^k x^(k-1) / (2k+1)``, ``x = nsq/w^2``, 40 terms),
    above it the complex-step derivative (exact to rounding there; at small ``x`` that formula
    itself cancels, as the direct branch does)."""
    x = nsq / w**2
    series = sum(k * (-1.0) ** k * x ** (k - 1) / (2 * k + 1) for k in range(1, 41)) / w**3
    h = 1e-30
    n_c = np.sqrt((np.maximum(nsq, 1e-300) + 1j * h).astype(complex))
    step = np.imag(np.arctan(n_c / w) / n_c) / h
    return np.where(x < 0.1, series, step)


def test_atan2_over_n_derivatives_against_references():
    """``d/dnsq`` and ``d/dw`` of ``atan2(n, w)/n`` (``n = sqrt(nsq)``) against float64
    references: the series or complex step for ``w > 0``, central differences for ``w <= 0``,
    ``-1/(n^2 + w^2)`` for ``d/dw``."""
    nsq, w = _atan_over_n_points()
    value, (d_nsq, d_w) = _atan_parts(jnp.asarray(nsq, DTYPE), jnp.asarray(w, DTYPE))
    value, d_nsq, d_w = (np.asarray(a, np.float64) for a in (value, d_nsq, d_w))
    pos = w > 0
    # The direct branch just above the derivative's switch (nsq / w^2 = 0.1) loses 1.5 eps / 0.1
    # to cancellation (the docstring's bound): largest errors 16 eps (float32) and 30 eps
    # (float64, against a reference good to a few eps) on this 2-core EPYC.
    tol = 100 * EPS
    np.testing.assert_allclose(d_nsq[pos], _atan_over_n_dnsq_reference(nsq[pos], w[pos]), rtol=tol)
    neg = ~pos & (nsq > 0)
    step = 1e-6 * nsq[neg]
    f = lambda s, ww: np.arctan2(np.sqrt(s), ww) / np.sqrt(s)  # noqa: E731
    fd = (f(nsq[neg] + step, w[neg]) - f(nsq[neg] - step, w[neg])) / (2 * step)
    np.testing.assert_allclose(d_nsq[neg], fd, rtol=1e-7 if DTYPE == jnp.float64 else 1e3 * EPS)
    ok = (nsq + w * w) > 0
    np.testing.assert_allclose(d_w[ok], -1.0 / (nsq[ok] + w[ok] ** 2), rtol=4 * EPS)
    assert np.all(np.isfinite(value)) and np.all(np.isfinite(d_nsq)) and np.all(np.isfinite(d_w))
    # at the identity the series: f = 1/w, df/dnsq = -1/(3 w^3), exactly
    g = jax.grad(_safe.atan2_over_n, argnums=(0, 1))(jnp.asarray(0.0, DTYPE), jnp.asarray(2.0, DTYPE))
    np.testing.assert_allclose(g, (-1.0 / 24.0, -0.25), rtol=EPS)


def test_atan2_over_n_second_derivatives():
    """The custom JVP's own derivative (JAX's, through the branches) against differences."""
    nsq = jnp.asarray([1e-6, 0.5, 3.0, 0.2], DTYPE)
    w = jnp.asarray([0.9, 0.7, -0.4, 1e-1], DTYPE)
    check_grads(
        jax.jit(_safe.atan2_over_n), (nsq, w), order=2, modes=["fwd", "rev"], eps=1e-3 if DTYPE == jnp.float32 else 1e-5
    )


_sinc_parts = jax.jit(jax.vmap(lambda s: jax.jvp(_safe.sinc_cos_of_sq, (s,), (jnp.ones_like(s),))))


_MOSTLY_SMALL_CASES = {
    "all below the switch": np.linspace(0.0, 0.0199, 64),
    "across it": np.concatenate([np.linspace(0.0, 0.0199, 60), [0.02, 0.5, 3.0, 40.0]]),
    "all above it": np.linspace(0.02, 40.0, 64),
}


@pytest.mark.parametrize("name", list(_MOSTLY_SMALL_CASES))
def test_sinc_cos_of_sq_mostly_small_is_sinc_cos_of_sq_with_its_derivatives(name):
    """The integrator step's variant (its derivatives take the series alone when every element is
    below the switch, through a ``lax.cond``) gives :func:`sinc_cos_of_sq`'s values, forward and
    reverse derivatives, and second derivatives, whichever branch the cond takes, also under
    ``vmap`` (rows of one case each: both branches run); to 2 eps (measured: equal)."""
    s = jnp.asarray(_MOSTLY_SMALL_CASES[name], DTYPE)
    weights = jnp.asarray(np.linspace(-1.0, 2.0, s.shape[0]), DTYPE)

    def scalar(f):
        return lambda x: jnp.sum(f(x)[0] * weights[: x.shape[0]]) + jnp.sum(f(x)[1] * weights[::-1][: x.shape[0]])

    new, ref = _safe.sinc_cos_of_sq_mostly_small, _safe.sinc_cos_of_sq
    pairs = [
        (jax.jit(new)(s), jax.jit(ref)(s)),
        (jax.jit(lambda x: jax.jvp(new, (x,), (weights,)))(s), jax.jit(lambda x: jax.jvp(ref, (x,), (weights,)))(s)),
        (jax.jit(jax.grad(scalar(new)))(s), jax.jit(jax.grad(scalar(ref)))(s)),
        (jax.jit(jax.hessian(scalar(new)))(s[:8]), jax.jit(jax.hessian(scalar(ref)))(s[:8])),
        (jax.jit(jax.vmap(new))(jnp.stack([s, s[::-1] * 0.4])), jax.jit(jax.vmap(ref))(jnp.stack([s, s[::-1] * 0.4]))),
    ]
    for got, want in pairs:
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2 * EPS, atol=2 * EPS)
    # a NaN sends the whole array to the direct branch, as the reference's selection does
    nan = jnp.asarray([0.01, jnp.nan], DTYPE)
    for a, b in zip(jax.jit(new)(nan), jax.jit(ref)(nan)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(
        np.asarray(jax.jit(jax.grad(lambda x: new(x)[0].sum()))(nan)),
        np.asarray(jax.jit(jax.grad(lambda x: ref(x)[0].sum()))(nan)),
    )


def test_sinc_cos_of_sq_derivatives_against_references():
    """``d/ds`` of ``sin(x)/x`` and ``cos(x)`` with ``x = sqrt(s)``, across the series switch
    (``s = 0.02``) and at 0, against float64 references: below ``s = 0.5`` the power series
    (``sum_k>=1 k (-1)^k s^(k-1) / (2k+1)!`` and ``/ (2k)!``, 30 terms), above it complex-step
    derivatives."""
    rng = np.random.default_rng(4)
    s = np.concatenate([10 ** rng.uniform(-10, 2, 300), 0.02 * (1 + np.linspace(-1e-3, 1e-3, 20)), [0.0]])
    (sinc, cos), (d_sinc, d_cos) = _sinc_parts(jnp.asarray(s, DTYPE))
    fact = [float(math.factorial(k)) for k in range(64)]
    series_sinc = sum(k * (-1.0) ** k * s ** (k - 1) / fact[2 * k + 1] for k in range(1, 31))
    series_cos = sum(k * (-1.0) ** k * s ** (k - 1) / fact[2 * k] for k in range(1, 31))
    h = 1e-30
    x_c = np.sqrt((np.maximum(s, 1e-300) + 1j * h).astype(complex))
    want_sinc = np.where(s < 0.5, series_sinc, np.imag(np.sin(x_c) / x_c) / h)
    want_cos = np.where(s < 0.5, series_cos, np.imag(np.cos(x_c)) / h)
    tol = 1e-12 if DTYPE == jnp.float64 else 200 * EPS  # float32: the direct branch's cancellation, eps / s = 50 eps
    np.testing.assert_allclose(np.asarray(d_sinc, np.float64), want_sinc, rtol=tol, atol=tol * 1e-2)
    np.testing.assert_allclose(np.asarray(d_cos, np.float64), want_cos, rtol=tol, atol=tol * 1e-2)
    np.testing.assert_allclose(np.asarray(d_cos), -0.5 * np.asarray(sinc), rtol=0, atol=0)
    assert np.all(np.isfinite(np.asarray(cos)))
    check_grads(
        jax.jit(_safe.sinc_cos_of_sq),
        (jnp.asarray([1e-4, 0.3, 5.0], DTYPE),),
        order=2,
        modes=["fwd", "rev"],
        eps=1e-3 if DTYPE == jnp.float32 else 1e-5,
    )
