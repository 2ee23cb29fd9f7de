"""The component kernels behind the rotation ops (``jaxquat._arrays``, ``_quaternion``, ``_safe``)
and the one-loop barriers of the integrator steps (``jaxquat._fusion``).

``components`` (a primitive) and ``assemble`` (a custom JVP) carry derivatives chosen for how XLA
on CPU compiles their tangents and transposes, and ``atan2_over_n``/``sinc_cos_of_sq`` carry
closed-form derivatives: each must still be exactly the split, the stack and the derivatives of
the functions they replace, checked here against independent references (NumPy's complex-step
derivatives, finite differences, the Hamilton product in rows).
"""

import functools
import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from jax.test_util import check_grads

from helpers import DTYPE, NP_DTYPE, X64, XLA_CHOOSES_EMITTERS, seeds
import jaxquat as jq
from jaxquat import _arrays, _fusion, _jacobi, _quaternion, _rotation, _safe, _trig

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


def test_one_loop_passes_integers_and_booleans_unchanged_in_a_loop_per_dtype():
    """Integer and boolean arrays (the torque-free roles and mask) pass to the bit, the extremes of
    each integer type included, beside floats whose gradient is unchanged; on CPU each dtype is
    one variadic ``reduce`` (floats, int32 and bool: three)."""
    ints = jnp.asarray([0, 1, -1, 2, np.iinfo(np.int32).max, np.iinfo(np.int32).min], jnp.int32)
    flags = jnp.asarray([True, False, False, True, True, False])
    x = jnp.linspace(-1.0, 2.0, 6, dtype=DTYPE)

    def through(x, ints, flags):
        return _fusion.one_loop_both_ways((x * x, ints, flags, ints * 2, ~flags))

    got = jax.jit(through)(x, ints, flags)
    for a, b in zip(got[1:], (ints, flags, ints * 2, ~flags)):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    grad = jax.jit(jax.grad(lambda x: jnp.sum(through(x, ints, flags)[0] * jnp.where(flags, 1.0, 2.0))))(x)
    np.testing.assert_allclose(grad, 2 * x * jnp.where(flags, 1.0, 2.0), rtol=EPS)
    text = jax.jit(through).lower(x, ints, flags).as_text()
    assert text.count("stablehlo.reduce") == (3 if jax.default_backend() == "cpu" else 0)


_through_plain = jax.jit(lambda x: _through(None, x))


@functools.cache
def _barrier_point():
    x = jnp.asarray(np.random.default_rng(2).uniform(0.1, 1.0, size=(5,)), DTYPE)
    return x, jnp.asarray(np.random.default_rng(3).normal(size=(5,)), DTYPE)


def _barrier_transforms(f):
    """The barrier test's transforms of ``f``, at its point."""
    x, dx = _barrier_point()

    def cost(fn):
        return lambda x: jnp.sum(fn(x)[0] * jnp.arange(5)) + jnp.sum(fn(x)[1] ** 2)

    transforms = (
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
    )
    return [t(f) for t in transforms]


@functools.cache
def _barrier_plain():
    """The transforms without a barrier: one program for the three barriers' tests (each
    compiled its own, the same one)."""
    return jax.jit(lambda: _barrier_transforms(_through_plain))()


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
    x, dx = _barrier_point()

    def step(x):
        return _through(barrier, x)

    # every transform in one program per form (a program per transform: 24 compilations)
    got = jax.jit(lambda: _barrier_transforms(step))()
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(_barrier_plain()), strict=True):
        np.testing.assert_allclose(a, b, rtol=64 * EPS, atol=64 * EPS)
    pair = jax.vmap(BARRIERS[barrier], in_axes=((0, None),))((jnp.stack([x, dx]), x))
    np.testing.assert_array_equal(pair[1], jnp.stack([x, x]))
    check_grads(jax.jit(lambda x: step(x)[0]), (x,), order=2, modes=["fwd", "rev"])


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


@pytest.mark.parametrize("shape", [(5, 1), (5, 2), (3, 4, 3), (5, 4), (2, 7)])
def test_one_loop_swaps_a_short_last_axis(shape):
    """Arrays whose last axis is shorter than 4 reach ``one_loop``'s ``reduce`` with their last two
    axes swapped (XLA's CPU loop emitter vectorises along the last axis), the others in their own
    shape; either way the values, their tangents and their cotangents pass unchanged to the bit."""
    x = jnp.asarray(np.random.default_rng(0).normal(size=shape), DTYPE)

    def pair(fn):
        return lambda x: tuple(fn((jnp.sin(x) * x, x * x - 1.0)))

    text = jax.export.export(jax.jit(pair(_fusion.one_loop_both_ways)), platforms=["cpu"])(x).mlir_module()
    swapped = shape[-1] < 4 and len(shape) > 1
    padded = [*shape[:-2], shape[-1], shape[-2], 2] if swapped else [*shape, 2]
    assert "tensor<" + "x".join(map(str, padded)) + "x" in text, text[-2000:]
    plain, looped = jax.jit(pair(tuple)), jax.jit(pair(_fusion.one_loop_both_ways))
    for a, b in zip(plain(x), looped(x)):
        np.testing.assert_array_equal(np.asarray(a).view(BITS), np.asarray(b).view(BITS))
    d = jnp.ones_like(x) * 0.5
    for a, b in zip(jax.jvp(plain, (x,), (d,))[1], jax.jvp(looped, (x,), (d,))[1]):
        np.testing.assert_array_equal(np.asarray(a).view(BITS), np.asarray(b).view(BITS))

    def loss(fn):
        return lambda x: sum(jnp.sum(c * (i + 2)) for i, c in enumerate(fn(x)))

    np.testing.assert_array_equal(np.asarray(jax.grad(loss(plain))(x)), np.asarray(jax.grad(loss(looped))(x)))


_fusible_jit = jax.jit(_fusion.fusible)


def test_fusible_is_the_identity_to_the_bit_and_to_every_transform():
    """``fusible`` passes every float unchanged (signed zeros, infinities, NaN, subnormals and the
    largest finite value included), compiled and eager, in each float dtype, and integers and
    booleans as they are; its tangent and cotangent are the identity (exact ones), also under
    ``vmap`` and ``jacfwd``."""
    for dtype in (DTYPE, jnp.float16, jnp.bfloat16):
        info = jnp.finfo(dtype)
        special = [0.0, -0.0, 1.5, -2.25, np.inf, -np.inf, np.nan, float(info.smallest_subnormal), float(info.max)]
        x = jnp.asarray(special, dtype)
        bits = {2: np.uint16, 4: np.uint32, 8: np.uint64}[x.dtype.itemsize]
        for out in (_fusible_jit(x), _fusion.fusible(x)):
            assert out.dtype == x.dtype
            np.testing.assert_array_equal(np.asarray(out).view(bits), np.asarray(x).view(bits))
    ints, flags = jnp.arange(5), jnp.arange(5) > 2
    assert _fusion.fusible(ints) is ints and _fusion.fusible(flags) is flags
    x = jnp.linspace(-2.0, 3.0, 6, dtype=DTYPE)
    _, tangent = jax.jvp(_fusion.fusible, (x,), (x * 3,))
    np.testing.assert_array_equal(tangent, x * 3)
    np.testing.assert_array_equal(jax.grad(lambda v: jnp.sum(_fusion.fusible(v) * x))(x), x)
    np.testing.assert_array_equal(jax.jacfwd(jax.vmap(_fusion.fusible))(x), np.eye(6, dtype=NP_DTYPE))


@pytest.mark.skipif(not X64, reason="a compiling test: its verdict does not depend on the dtype")
@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the loops are reduces on CPU only")
def test_fusible_puts_a_division_with_several_users_into_their_loop():
    """The reason for ``fusible``: XLA's CPU fusion emitters (jaxlib's default, which the suite
    otherwise turns off: ``tests/conftest.py``) leave a division that feeds several outputs of one
    ``one_loop`` out of that loop (a kernel of its own, writing an array); through ``fusible`` it
    is computed in the loop, and the compiled program has one kernel fewer, with the same values.
    (The older emitters fuse it either way.)"""
    x = jnp.linspace(1.0, 2.0, 1000, dtype=DTYPE)
    emitters = {"xla_cpu_use_fusion_emitters": True} if XLA_CHOOSES_EMITTERS else None  # later: the only ones

    def outputs(wrap):
        def f(a, b, c):
            m = wrap(a / b)
            return _fusion.one_loop((m * c, m + c, m * m))

        return jax.jit(f, compiler_options=emitters)

    def kernels(fn):
        text = fn.lower(x, x + 1, x + 2).compile().as_text()
        return len(re.findall(r"^\s+(?:ROOT )?%\S+ = .* fusion\(", text[text.index("ENTRY") :], re.M))

    plain, fused = outputs(lambda m: m), outputs(_fusion.fusible)
    assert kernels(plain) == 2 and kernels(fused) == 1
    for got, want in zip(fused(x, x + 1, x + 2), plain(x, x + 1, x + 2)):
        np.testing.assert_array_equal(got, want)


@pytest.mark.skipif(not X64, reason="a lowering test: its verdict does not depend on the dtype")
@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the loops are reduces on CPU only")
def test_one_loop_and_sums_of_constants_are_not_evaluated_while_compiling():
    """Arrays a jitted function closes over are constants of its program. XLA folds an operation
    whose operands are all constants while compiling, and its size guard skips a variadic reduce
    (a tuple): ten entries of 10^5 constant rows took 2.3 s to fold. The reduces' start passes an
    optimization barrier, so the compiled program keeps them (folded, it holds none)."""
    c = jnp.asarray(np.linspace(0.5, 1.5, 12).reshape(4, 3), DTYPE)

    def compiled_reduces(fn):
        return jax.jit(fn).lower(jnp.asarray(2.0, DTYPE)).compile().as_text().count(" reduce(")

    assert compiled_reduces(lambda s: sum(_fusion.one_loop([c * 2.0, c + 1.0, c * c])) * s) == 1
    assert compiled_reduces(lambda s: sum(_fusion.sums([c * 2.0, c + 1.0], axis=-1)) * s) == 1


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


def _sums_reference(xs, axis):
    return tuple(jnp.sum(x, axis=axis) for x in jnp.broadcast_arrays(*xs))


_sums_jit = jax.jit(lambda xs: _fusion.sums(xs, -1))
_outer_sum_jit = jax.jit(_arrays.outer_sum)
_sums_reference_jit = jax.jit(lambda xs: _sums_reference(xs, -1))


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_sums_are_the_sums_in_rows_and_past_1024_elements(seed):
    """``sums`` equals one ``jnp.sum`` per array (broadcast first), for axes summed in one row
    (5, 1024 elements) and in zero-padded rows (1025, 3000), to the rounding of a different
    order of addition (a bound of length * eps * sum |x|)."""
    rng = np.random.default_rng(seed)
    for length in (5, 1024, 1025, 3000):
        xs = (
            jnp.asarray(rng.normal(size=(2, length)), DTYPE),
            jnp.asarray(rng.normal(size=(1, length)) * 1e3, DTYPE),
            jnp.asarray(rng.normal(size=(length,)), DTYPE),
        )
        got, want = _sums_jit(xs), _sums_reference_jit(xs)
        for g, w, x in zip(got, want, jnp.broadcast_arrays(*xs)):
            assert g.shape == w.shape == (2,)
            bound = length * EPS * np.sum(np.abs(np.asarray(x, np.float64)), axis=-1)
            np.testing.assert_array_less(np.abs(np.asarray(g, np.float64) - np.asarray(w, np.float64)), bound)


def test_sums_past_1024_elements_are_accurate():
    """``mean``'s ``sum q q^T`` over 2^20 quaternions (ten sums in one ``reduce``), normal and
    near-constant components: within 128 eps of the exact sums of the same values, relative to
    the largest. XLA adds a ten-operand ``reduce`` in order, and in one row the error was
    3.8e-4 and 9.7e-4 in float32 (over 3000 eps); in rows of 1024, 7.1e-7 and 2.7e-6, as an
    ``einsum``'s (2.7e-7, 5.6e-6)."""
    rng = np.random.default_rng(5)
    for q in (rng.normal(size=(2**20, 4)), 1.0 + 1e-3 * rng.uniform(size=(2**20, 4))):
        q = q.astype(NP_DTYPE)
        q64 = q.astype(np.float64)  # float32 products exact in float64; fsum exact sums
        exact = np.array([[math.fsum(q64[:, min(i, j)] * q64[:, max(i, j)]) for j in range(4)] for i in range(4)])
        got = np.asarray(_outer_sum_jit(jnp.asarray(q)), np.float64)
        assert np.abs(got - exact).max() / np.abs(exact).max() < 128 * EPS


def _sums_step(summed):
    """A small function of ``x`` through sums over each axis of products (``summed``: ``sums`` or
    the reference), for the derivative tests."""

    def step(x):
        a, b, d = summed((x * x, jnp.sin(x) * x[:1], x), 1)
        (c,) = summed((a[:, None] * x * b[:, None],), 0)
        return jnp.sum(c * c) + jnp.sum(a * b * d)

    return step


def _assert_the_same_under_every_transform(step, plain, x, dx):
    """``step`` (a scalar function of ``x`` through a primitive of ``jaxquat._fusion``) and
    ``plain`` (the same through JAX's own operations) equal to rounding under ``grad``, ``jvp``,
    ``jacfwd``, the Hessian both ways, the gradient of a ``jvp``, ``linearize``,
    ``jax.checkpoint`` (nothing saved, everything saved, and under ``jacfwd``) and ``vmap``, every
    transform in one program per form (a program per transform: 22 compilations); and
    ``check_grads`` to order 2 through ``step``."""
    transforms = (
        lambda f: jax.grad(f)(x),
        lambda f: jax.jvp(f, (x,), (dx,))[1],
        lambda f: jax.jacfwd(f)(x),
        lambda f: jax.hessian(f)(x),
        lambda f: jax.jacrev(jax.jacfwd(f))(x),
        lambda f: jax.grad(lambda x: jax.jvp(f, (x,), (dx,))[1])(x),
        lambda f: jax.linearize(f, x)[1](dx),
        lambda f: jax.grad(jax.checkpoint(f))(x),
        lambda f: jax.grad(jax.checkpoint(f, policy=jax.checkpoint_policies.everything_saveable))(x),
        lambda f: jax.jacfwd(jax.grad(jax.checkpoint(f)))(x),
        lambda f: jax.vmap(jax.grad(f))(jnp.stack([x, 2 * x])),
    )
    got, want = (jax.jit(lambda f=f: [t(f) for t in transforms])() for f in (step, plain))
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        np.testing.assert_allclose(a, b, rtol=64 * EPS, atol=64 * EPS)
    check_grads(jax.jit(step), (x,), order=2, modes=["fwd", "rev"])


def test_sums_derivatives_are_those_of_the_sums():
    """``grad``, ``jvp``, ``jacfwd``, ``linearize``, the Hessian both ways, the gradient of a
    ``jvp``, ``vmap`` (with an unbatched operand), ``jax.checkpoint`` (nothing saved, everything
    saved): through ``sums`` the same as through ``jnp.sum``, to rounding (the loops add in
    another order); ``check_grads`` to order 2. Under ``jvp`` the values and the tangents share
    one bind, which ``linearize`` and remat split again (the partial-evaluation rules of
    ``jaxquat._fusion``)."""
    x = jnp.asarray(np.random.default_rng(2).uniform(0.1, 1.0, size=(3, 5)), DTYPE)
    dx = jnp.asarray(np.random.default_rng(3).normal(size=(3, 5)), DTYPE)
    step = _sums_step(_fusion.sums)
    _assert_the_same_under_every_transform(step, _sums_step(_sums_reference), x, dx)
    tol = dict(rtol=64 * EPS, atol=64 * EPS)
    mapped, unmapped = jax.vmap(lambda a, b: _fusion.sums((a, b), 0), in_axes=(0, None), out_axes=(0, None))(x, x[0])
    np.testing.assert_allclose(mapped, jnp.sum(x, axis=1), **tol)
    np.testing.assert_allclose(unmapped, jnp.sum(x[0]), **tol)


@pytest.mark.skipif(not X64, reason="a lowering test: its verdict does not depend on the dtype")
def test_sums_lower_to_one_variadic_reduce_on_cpu_only():
    """On CPU three sums are one ``reduce`` with three results (past 1024 elements two: the rows,
    then their sums), under ``jvp`` the values and the tangents one ``reduce`` with six; for a GPU
    (lowered here without one, by ``jax.export``) one ``reduce`` per sum."""

    def module(fn, *args, platform="cpu"):
        return jax.export.export(jax.jit(fn), platforms=[platform])(*args).mlir_module()

    def three(x):
        return _fusion.sums((x * 2, x + 1, x * x), 0)

    x, long = jnp.ones((7,), DTYPE), jnp.ones((3000,), DTYPE)
    assert module(three, x).count("stablehlo.reduce") == 1
    assert re.search(r"%\w+:3 = stablehlo\.reduce\(", module(three, x))
    assert module(three, long).count("stablehlo.reduce") == 2
    assert re.search(r"%\w+:6 = stablehlo\.reduce\(", module(lambda x, d: jax.jvp(three, (x,), (d,)), x, x))
    assert module(three, x, platform="cuda").count("stablehlo.reduce") == 3
    assert not re.search(r"%\w+:\d+ = stablehlo\.reduce\(", module(three, x, platform="cuda"))


def _spread_step(spread):
    """A small function of ``x`` (3 elements) through broadcasts of three functions of it along a
    new axis of 4 (``spread``: ``_fusion.spread`` or ``jnp.broadcast_to``), for the derivative tests."""

    def step(x):
        t = jnp.linspace(0.5, 2.0, 4, dtype=x.dtype)[None]
        a, b, c = spread((x * x, jnp.sin(x), x), 4)
        return jnp.sum(jnp.cos(a * t) * b + c * c * t)

    return step


def _spread_reference(xs, length):
    return tuple(jnp.broadcast_to(x[..., None], x.shape + (length,)) for x in xs)


def test_spread_is_the_broadcast_to_every_transform():
    """``grad``, ``jvp``, ``jacfwd``, ``linearize``, the Hessian both ways, the gradient of a
    ``jvp``, ``vmap`` (with an unbatched operand), ``jax.checkpoint`` (nothing saved, everything
    saved): through ``spread`` the same as through ``jnp.broadcast_to``, to rounding (its
    cotangents are summed in one loop, in another order); ``check_grads`` to order 2; on CPU the
    cotangents of three broadcasts are one ``reduce`` with three results."""
    x = jnp.asarray(np.random.default_rng(4).uniform(0.1, 1.0, size=(3,)), DTYPE)
    dx = jnp.asarray(np.random.default_rng(5).normal(size=(3,)), DTYPE)
    step = _spread_step(_fusion.spread)
    _assert_the_same_under_every_transform(step, _spread_step(_spread_reference), x, dx)
    mapped, unmapped = jax.vmap(lambda a, b: _fusion.spread((a, b), 2), in_axes=(0, None), out_axes=(0, None))(
        jnp.stack([x, 2 * x]), x
    )
    np.testing.assert_array_equal(mapped, jnp.broadcast_to(jnp.stack([x, 2 * x])[..., None], (2, 3, 2)))
    np.testing.assert_array_equal(unmapped, jnp.broadcast_to(x[:, None], (3, 2)))
    with pytest.raises(ValueError, match="spread: every array must have one shape"):
        _fusion.spread((x, x[:2]), 4)
    if jax.default_backend() == "cpu":
        backward = jax.jit(jax.grad(step)).lower(x).as_text()
        assert re.search(r"%\w+:3 = stablehlo\.reduce\(", backward), backward


def test_sums_reject_an_axis_out_of_range_and_keep_dtypes():
    x = jnp.ones((3, 4), DTYPE)
    with pytest.raises(ValueError, match="sums: axis 2 out of range for arrays of 2 dimensions"):
        _fusion.sums((x,), 2)
    half, full = jax.jit(lambda a, b: _fusion.sums((a, b), 1))(x.astype(jnp.float16), x)
    assert half.dtype == jnp.float16 and full.dtype == DTYPE
    np.testing.assert_array_equal(half, 4.0)
    np.testing.assert_array_equal(full, 4.0)


@settings(max_examples=10, deadline=None)
@given(seeds)
def test_outer_sum_is_the_weighted_sum_of_outer_products(seed):
    """``sum_n w_n a_n b_n^T`` against NumPy's ``einsum`` in float64: with and without weights,
    ``b`` given or ``a`` itself (the symmetric form, only its upper triangle summed), a batch of
    problems and a single vector pair; its derivatives by ``check_grads``."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(2, 5, 4)).astype(NP_DTYPE)
    b = rng.normal(size=(2, 5, 3)).astype(NP_DTYPE)
    w = rng.uniform(0.1, 2.0, size=(2, 5)).astype(NP_DTYPE)
    a64, b64, w64 = (x.astype(np.float64) for x in (a, b, w))
    cases = [
        (_outer_sum_jit(a, b, w), np.einsum("...n,...ni,...nj->...ij", w64, a64, b64)),
        (_outer_sum_jit(a, b), np.einsum("...ni,...nj->...ij", a64, b64)),
        (_outer_sum_jit(a, None, w), np.einsum("...n,...ni,...nj->...ij", w64, a64, a64)),
        (_outer_sum_jit(a), np.einsum("...ni,...nj->...ij", a64, a64)),
        (_outer_sum_jit(a[:, :1], b[:, :1]), np.einsum("...ni,...nj->...ij", a64[:, :1], b64[:, :1])),
    ]
    for got, want in cases:
        assert got.shape == want.shape and got.dtype == DTYPE
        np.testing.assert_allclose(got, want, rtol=16 * EPS, atol=16 * EPS * np.abs(want).max())
    symmetric = np.asarray(cases[3][0])
    np.testing.assert_array_equal(symmetric, np.swapaxes(symmetric, -1, -2))


@pytest.mark.parametrize("n", [1, 10, 32, 33])
def test_sum_last_is_the_sum_over_the_last_axis(n):
    """``_arrays.sum_last`` equals ``jnp.sum(x, -1)`` (to ``n`` eps of the sum of ``|x|``) with its
    derivative; up to 32 terms it is written out, with no ``reduce`` in the lowered program (the
    YNNPACK fusion it avoids), past that it is one ``reduce``."""
    x = jnp.asarray(np.random.default_rng(n).normal(size=(3, 2, n)), DTYPE)
    got, want = jax.jit(_arrays.sum_last)(x), jnp.sum(x, axis=-1)
    assert got.shape == (3, 2) and got.dtype == DTYPE
    np.testing.assert_allclose(got, want, rtol=0, atol=n * EPS * float(jnp.abs(x).sum(-1).max()))
    weights = jnp.arange(1.0, 7.0, dtype=DTYPE).reshape(3, 2)
    np.testing.assert_array_equal(
        jax.jit(jax.grad(lambda x: jnp.sum(_arrays.sum_last(x) * weights)))(x),
        jnp.broadcast_to(weights[..., None], x.shape),
    )
    text = jax.jit(_arrays.sum_last).lower(x).as_text()
    assert text.count("stablehlo.reduce") == (0 if n <= 32 else 1)


_eigh4 = jax.jit(_jacobi.eigh4)


def test_jacobi_eigh4_against_numpy():
    """``_jacobi.eigh4`` on symmetric 4x4 matrices: eigenvalues within ``16 eps |K|`` of NumPy's
    ``eigvalsh`` (float64), residuals ``|K v - lambda v|`` and ``|V^T V - I|`` within ``16 eps
    |K|`` and ``16 eps`` (``|K|`` its largest entry). Random matrices, Davenport spectra with a triple eigenvalue
    (``3, -1, -1, -1``, an exact rotation's ``K``), a close pair, entries of size 1e-30 and
    1e30, diagonal ones (no rotation needed), zero matrices, and a NaN matrix (NaN, the rest of
    the batch unaffected)."""
    rng = np.random.default_rng(12)
    m = rng.normal(size=(64, 4, 4))
    q, _ = np.linalg.qr(rng.normal(size=(64, 4, 4)))
    turned = lambda d: q @ np.diag(d) @ np.swapaxes(q, -1, -2)  # noqa: E731
    cases = [
        m + np.swapaxes(m, -1, -2),
        turned([3.0, -1.0, -1.0, -1.0]),
        turned([1.0, 1.0 + 1e-7, -0.5, 2.0]),
        1e-30 * (m + np.swapaxes(m, -1, -2)),
        1e30 * (m + np.swapaxes(m, -1, -2)),
        np.broadcast_to(np.diag([4.0, -2.0, 1.0, 0.5]), (64, 4, 4)),
        np.zeros((64, 4, 4)),
    ]
    for k in cases:
        k = np.asarray(k, NP_DTYPE).astype(np.float64)
        lam, vecs = (np.asarray(x, np.float64) for x in _eigh4(jnp.asarray(k, DTYPE)))
        size = np.abs(k).max(axis=(-2, -1))[:, None] + 1e-300
        error = np.abs(np.sort(lam, -1) - np.linalg.eigvalsh(k)) / size
        residual = np.abs(np.einsum("bij,bjk->bik", k, vecs) - vecs * lam[:, None, :]).max(-2) / size
        orthogonality = np.abs(np.einsum("bij,bik->bjk", vecs, vecs) - np.eye(4))
        # measured at most 8.7, 4.3 and 6 eps in float64, 3.1, 3.7 and 4.4 in float32
        assert error.max() < 16 * EPS and residual.max() < 16 * EPS and orthogonality.max() < 16 * EPS
    k = jnp.asarray(cases[0], DTYPE).at[3, 1, 2].set(jnp.nan)
    lam, vecs = _eigh4(k)
    assert np.isnan(np.asarray(lam[3])).all() and np.isfinite(np.asarray(lam[:3])).all()
    np.testing.assert_array_equal(np.asarray(lam[4:]), np.asarray(_eigh4(jnp.asarray(cases[0], DTYPE))[0][4:]))


def test_outer_sum_derivatives():
    """First and second derivatives, both modes, equal those of the ``einsum`` it replaced (to
    rounding), with and without weights and in the symmetric form; ``check_grads`` in float64
    (in float32 the finite differences of this cubic round at the tolerance)."""
    rng = np.random.default_rng(7)
    a, b, w = (jnp.asarray(rng.normal(size=s), DTYPE) for s in ((3, 4), (3, 3), (3,)))
    pairs = [
        (lambda a, b, w: _arrays.outer_sum(a, b, w), lambda a, b, w: jnp.einsum("n,ni,nj->ij", w, a, b)),
        (lambda a, b, w: _arrays.outer_sum(a, b), lambda a, b, w: jnp.einsum("ni,nj->ij", a, b)),
        (lambda a, b, w: _arrays.outer_sum(a, None, w), lambda a, b, w: jnp.einsum("n,ni,nj->ij", w, a, a)),
    ]
    tol = dict(rtol=64 * EPS, atol=64 * EPS)
    args = (0, 1, 2)
    transforms = (
        lambda f: jax.jacfwd(f, args),
        lambda f: jax.jacrev(f, args),
        lambda f: jax.jacfwd(jax.jacrev(f, args), args),
        lambda f: jax.jacrev(jax.jacfwd(f, args), args),
    )
    for fn, ref in pairs:
        # each pair's eight derivatives in one program (eight of their own: the test took 6.8 s against
        # 6.0 s in float64, 4.7 s against 3.7 s in float32, one core, session 56)
        got, want = jax.jit(lambda *x, f=fn, r=ref: [[t(g)(*x) for t in transforms] for g in (f, r)])(a, b, w)
        for g, r in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
            np.testing.assert_allclose(g, r, **tol)
        if X64:
            check_grads(fn, (a, b, w), order=2, modes=["fwd", "rev"])


def _roundtrip(x):
    return _arrays.assemble(*_arrays.components(x))


_roundtrip_jit = jax.jit(_roundtrip)


def _flat_and_nested(q, p, v, t):
    """``to_rotvec``, ``slerp`` (``p`` without batch axes, ``t`` per element) and ``rotate`` with
    the gradient of a weighted sum of them in ``q``."""

    def f(q):
        return jq.to_rotvec(q), jq.slerp(q, p, t), jq.rotate(q, v)

    def loss(q):
        return sum(jnp.sum(x * jnp.arange(x.size, dtype=x.dtype).reshape(x.shape)) for x in f(q))

    return (*f(q), jax.grad(loss)(q))


_flat_and_nested_jit = jax.jit(_flat_and_nested)


def test_public_functions_flatten_a_batch_of_several_axes():
    """A row-wise public function (``_arrays.compiled_rows``) computes a batch of several axes as
    one axis: the kernel receives ``(n, 4)`` rows (an ``(n // 3, 3)`` batch's components would
    be ``(n // 3, 3)`` arrays, along whose last axis of 3 XLA's CPU loops ran: ``to_rotvec``'s
    gradient at 10^5 x 3 rotations 21.2 ms against 3.1 ms flat). The values are those of the flat
    batch to the bit (the gradient of a sum of three to rounding), an operand without batch axes
    broadcasts, and a batch of one axis or none is passed as it is."""
    rng = np.random.default_rng(3)
    q = jnp.asarray(rng.normal(size=(12, 4)), DTYPE)
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    v = jnp.asarray(rng.normal(size=(12, 3)), DTYPE)
    t = jnp.asarray(rng.uniform(size=12), DTYPE)
    p = jnp.asarray([0.5, 0.5, -0.5, 0.5], DTYPE)
    flat = _flat_and_nested_jit(q, p, v, t)
    nested = _flat_and_nested_jit(q.reshape(4, 3, 4), p, v.reshape(4, 3, 3), t.reshape(4, 3))
    for a, b in zip(flat[:3], nested[:3]):
        np.testing.assert_array_equal(np.asarray(b).reshape(a.shape), np.asarray(a))
    # the three functions' cotangents of q add in another order: measured 3 eps in 2 of 48 entries
    np.testing.assert_allclose(np.asarray(nested[3]).reshape(12, 4), flat[3], rtol=16 * EPS, atol=16 * EPS)
    jaxpr = str(jax.make_jaxpr(jq.to_rotvec)(q.reshape(2, 2, 3, 4)))
    assert re.search(r"reshape\[[^\]]*new_sizes=\(12, 4\)", jaxpr), jaxpr
    for one_or_none, flattened in ((q, "(12, 4)"), (q[0], "(1, 4)")):
        assert f"new_sizes={flattened}" not in str(jax.make_jaxpr(jq.to_rotvec)(one_or_none))


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
    forms its tangent as its value, by products with the rows of the identity (no ``reduce``, no
    concatenation: a stack fused with the tangents' expressions evaluates their shared work once
    per component); reverse mode gathers the cotangents through products with the identity on
    CPU (``dot_general``) and a concatenation elsewhere (the choice is made at trace time:
    ``_trig._cpu`` set to False)."""
    x = jnp.ones((7, 3), DTYPE)

    def count(fn, op):
        return jax.jit(fn).lower(x).as_text().count(op)

    def f(x):
        return _arrays.assemble(*(jnp.sin(c) * c for c in _arrays.components(x)))

    for op in ("stablehlo.dot_general", "stablehlo.reduce", "stablehlo.concatenate"):
        assert count(lambda x: jax.jvp(f, (x,), (x,))[1], op) == 0, op
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


def _mostly_small_side(f, scalar, vmapped):
    """One compiled program per function ``f`` (one side of the two tests below): its value, a
    JVP, the gradient and the Hessian (on a slice) of ``scalar``, a weighted sum of its outputs,
    and ``vmapped`` under ``vmap``. The three cases of each test have the same shapes, so the
    program compiles once for all three (each case compiled its own ten or eight programs, the
    same ones: about 4 s a pass for the two tests)."""

    def side(x, dx, small, stack):
        return f(x), jax.jvp(f, (x,), (dx,)), jax.grad(scalar)(x), jax.hessian(scalar)(small), jax.vmap(vmapped)(stack)

    return jax.jit(side)


@functools.cache
def _sinc_small_batch_sides():
    weights = jnp.asarray(np.linspace(-1.0, 2.0, 64), DTYPE)

    def scalar(f):  # a weighting of each of the two outputs
        def weighted(x):
            sinc, cos = f(x)
            return jnp.sum(sinc * weights[: x.shape[0]]) + jnp.sum(cos * weights[::-1][: x.shape[0]])

        return weighted

    new, ref = _safe.sinc_cos_of_sq_small_batch, _safe.sinc_cos_of_sq
    sides = [_mostly_small_side(f, scalar(f), f) for f in (new, ref)]
    nan_grads = [jax.jit(jax.grad(lambda x, f=f: f(x)[0].sum())) for f in (new, ref)]
    return weights, sides, nan_grads


@pytest.mark.parametrize("name", list(_MOSTLY_SMALL_CASES))
def test_sinc_cos_of_sq_small_batch_is_sinc_cos_of_sq_with_its_derivatives(name):
    """The integrator step's variant (its value and derivatives take the series alone when every
    element is below the switch, through a ``lax.cond``) gives
    :func:`sinc_cos_of_sq`'s values, forward and reverse derivatives, and second derivatives,
    whichever branch the cond takes, also under ``vmap`` (rows of one case each: both branches
    run); to 2 eps (measured: equal)."""
    s = jnp.asarray(_MOSTLY_SMALL_CASES[name], DTYPE)
    weights, (new, ref), nan_grads = _sinc_small_batch_sides()
    args = (s, weights, s[:8], jnp.stack([s, s[::-1] * 0.4]))
    for got, want in zip(new(*args), ref(*args), strict=True):
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2 * EPS, atol=2 * EPS)
    # a NaN sends the whole array to the direct branch, as the reference's selection does
    nan = jnp.asarray([0.01, jnp.nan], DTYPE)
    for a, b in zip(jax.jit(_safe.sinc_cos_of_sq_small_batch)(nan), jax.jit(_safe.sinc_cos_of_sq)(nan)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(nan_grads[0](nan)), np.asarray(nan_grads[1](nan)))


@functools.cache
def _exp_by_batch_sides():
    def of(branches):
        return lambda x: jnp.stack(_rotation.exp_components([x[..., 0], x[..., 1], x[..., 2]], branches), axis=-1)

    weights = jnp.asarray(np.linspace(-1.0, 2.0, 4), DTYPE)

    def scalar(f):
        def weighted(x):
            out = f(x)
            return jnp.sum(out * jnp.broadcast_to(weights, out.shape))

        return weighted

    fs = of("derivatives by batch"), of("per element")
    values = [jax.jit(f) for f in fs]
    sides = [_mostly_small_side(f, scalar(f), jax.grad(scalar(f))) for f in fs]
    return values, sides


@pytest.mark.parametrize("name", list(_MOSTLY_SMALL_CASES))
def test_exp_derivatives_by_batch_is_exp_per_element_with_its_derivatives(name):
    """``exp_components(r, "derivatives by batch")`` (the last exponential of an RKMK step, whose
    JVP rule computes ``r`` and ``|r|^2/4`` in one loop before the batch's cond) against
    ``"per element"``: the same values to the bit, and forward, reverse and second derivatives
    to 4 eps, whichever branch the cond takes, at ``r = 0`` too, and under ``vmap``."""
    s = np.asarray(_MOSTLY_SMALL_CASES[name])
    directions = np.random.default_rng(7).normal(size=(s.shape[0], 3))
    r = jnp.asarray(2.0 * np.sqrt(s)[:, None] * directions / np.linalg.norm(directions, axis=-1, keepdims=True), DTYPE)
    dr = jnp.asarray(np.random.default_rng(8).normal(size=r.shape), DTYPE)
    (new_value, ref_value), (new, ref) = _exp_by_batch_sides()
    np.testing.assert_array_equal(np.asarray(new_value(r)), np.asarray(ref_value(r)))
    args = (r, dr, r[-3:], r)
    for got, want in zip(new(*args), ref(*args), strict=True):
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=4 * EPS, atol=4 * EPS)


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
