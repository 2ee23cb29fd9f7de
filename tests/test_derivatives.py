"""The one-loop derivative kernels (``jaxquat._derivatives``) of ``to_rotvec``, ``slerp``,
``to_euler`` and the minimal rotation between two directions (``align_vectors`` of one pair): the
tangents, cotangents and second derivatives they give must be JAX's own derivatives of the same op
(the undecorated kernel, differentiated operation by operation through its closed-form scalar
rules), at random and singular points, under every transform; and they must compile as one loop on
CPU and not exist elsewhere. Also ``from_matrix`` on CPU (``forward_and_reverse``): its row form,
its component form and its written-out cotangent are one function, its tangent and cotangent each
other's transpose."""

import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from jax.test_util import check_grads

from helpers import DTYPE, NP_DTYPE, X64, random_quats, seeds
from jaxquat import _derivatives, _rotation, _trig
from jaxquat.rotations import euler_angles

EPS = float(np.finfo(NP_DTYPE).eps)
# Derivatives of O(1) ops: the kernels round differently (another order of operations), a few
# hundred ulp at most near the singular rows in float32.
RTOL = 1e-12 if X64 else 2e-4


def _ops():
    """name -> (decorated op, undecorated kernel, its arguments from a seed)."""

    def quats(seed, n=16):
        return (jnp.asarray(random_quats(seed, n), DTYPE),)

    def slerp_args(seed, n=16):
        rng = np.random.default_rng(seed + 1)
        return (
            jnp.asarray(random_quats(seed, n), DTYPE),
            jnp.asarray(random_quats(seed + 7, n, with_singular=False), DTYPE),
            jnp.asarray(rng.uniform(-0.5, 1.5, n), DTYPE),
        )

    def vector_pairs(seed, n=16):
        """Random pairs, antiparallel ones (three along a coordinate axis, where the axis of the
        half turn switches), parallel ones and one nearly antiparallel."""
        rng = np.random.default_rng(seed + 3)
        a, b = rng.normal(size=(2, max(n, 9), 3))
        b[1:4] = [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
        a[1:6] = -2.0 * b[1:6]
        a[6:8] = 0.5 * b[6:8]
        a[8] = -b[8] + 0.1 * rng.normal(size=3)
        a, b = a[:n], b[:n]  # row 0 and rows from 9 on random pairs
        return jnp.asarray(a, DTYPE), jnp.asarray(b, DTYPE)

    return {
        "minimal_rotation": (_rotation.minimal_rotation, _rotation._minimal_rotation, vector_pairs),
        "to_rotvec": (
            lambda q: _rotation.to_rotvec(q, rescale=True),
            lambda q: _rotation._to_rotvec(q, rescale=True),
            quats,
        ),
        "slerp": (_rotation.slerp, _rotation._slerp, slerp_args),
        "to_euler xyz": (
            lambda q: euler_angles._to_euler(q, seq="xyz"),
            lambda q: euler_angles._to_euler_kernel(q, seq="xyz"),
            quats,
        ),
        "to_euler ZXZ": (
            lambda q: euler_angles._to_euler(q, seq="ZXZ"),
            lambda q: euler_angles._to_euler_kernel(q, seq="ZXZ"),
            quats,
        ),
    }


OPS = _ops()


def _assert_close(got, want, rtol=RTOL):
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    assert got.shape == want.shape
    scale = max(1.0, float(np.max(np.abs(want))))
    assert np.max(np.abs(got - want)) <= rtol * scale, np.max(np.abs(got - want)) / scale


def _cotangent(f, args, seed):
    out = jax.eval_shape(f, *args)
    return jnp.asarray(np.random.default_rng(seed).normal(size=out.shape), DTYPE)


@functools.cache
def _first_order(name: str, which: str):
    """``(value, gradients of sum(f * w) in every input, one jvp)`` of the decorated op or the
    plain kernel, compiled once per op and dtype (hypothesis' examples reuse it)."""
    op, plain, _ = OPS[name]
    f = op if which == "op" else plain

    def run(args, w, tangents):
        grads = jax.grad(lambda a: jnp.sum(f(*a) * w))(args)
        return f(*args), grads, jax.jvp(f, args, tangents)[1]

    return jax.jit(run)


@pytest.mark.parametrize("name", list(OPS))
@settings(max_examples=5, deadline=None)
@given(seed=seeds)
def test_kernels_give_jax_s_own_derivatives(name, seed):
    """Values, one ``jvp``, the gradient of ``sum(f * W)`` with respect to every input, at random
    rows and (``random_quats``) the identity, half turns and tiny angles."""
    op, _, make = OPS[name]
    args = make(seed % 1000)
    w = _cotangent(op, args, seed)
    tangents = tuple(jnp.asarray(np.random.default_rng(seed + 2).normal(size=a.shape), DTYPE) for a in args)
    value, grads, jvp = _first_order(name, "op")(args, w, tangents)
    want, want_grads, want_jvp = _first_order(name, "plain")(args, w, tangents)
    if name.startswith("to_euler"):  # an angle at -pi and at pi is the same (rounding picks one)
        value = want + np.angle(np.exp(1j * (np.asarray(value, np.float64) - np.asarray(want, np.float64))))
    _assert_close(value, want, rtol=64 * EPS)
    for got, expected in zip(grads, want_grads):
        _assert_close(got, expected)
    _assert_close(jvp, want_jvp)


def _transforms(f, args):
    """``jacfwd`` and ``jacrev`` at one row, the Hessian of one output there, a ``vmap`` of a
    gradient over axis 1, ``linearize`` and a rematerialised gradient (``f``'s, or JAX's own
    derivatives for the reference where ``jacrev`` is ``jacfwd``)."""
    one = tuple(a[1] for a in args)
    stacked = tuple(jnp.stack([a, a[::-1]], axis=1) for a in args)  # (4, 2, ...): vmap over axis 1
    return (
        jax.jacfwd(f)(*one),
        jax.jacrev(f)(*one),
        jax.hessian(lambda x: f(x, *one[1:])[0])(one[0]),
        jax.vmap(jax.grad(lambda *a: jnp.sum(f(*a) ** 2)), in_axes=1, out_axes=1)(*stacked),
        jax.linearize(f, *args)[1](*args),
        jax.grad(jax.checkpoint(lambda *a: jnp.sum(f(*a) ** 2)))(*args),
    )


@pytest.mark.skipif(not X64, reason="second derivatives compared in float64")
@pytest.mark.parametrize("name", list(OPS))
def test_kernels_second_derivatives_and_transforms(name):
    """``jacfwd`` (the primal unmapped under ``vmap``), ``jacrev``, the Hessian of one output, a
    ``vmap`` over a non-leading axis, ``linearize`` and a rematerialised gradient, each compiled
    in one program per op."""
    op, plain, make = OPS[name]
    args = make(3, n=4)
    got = jax.jit(lambda a: _transforms(op, a))(args)
    want = jax.jit(lambda a: _transforms(plain, a))(args)
    for g, w in zip(got, want):
        _assert_close(g, w)


def test_slerp_cotangents_sum_over_broadcast_inputs():
    """``slerp(p, q, t)`` with one ``q`` and one ``t`` for a batch of ``p``: their cotangents are
    summed over the batch, as JAX's own."""
    p = jnp.asarray(random_quats(5, 6), DTYPE)
    q = jnp.asarray(random_quats(6, 1, with_singular=False)[0], DTYPE)
    t = jnp.asarray(0.3, DTYPE)
    w = jnp.asarray(np.random.default_rng(0).normal(size=(6, 4)), DTYPE)
    got = jax.jit(jax.grad(lambda *a: jnp.sum(_rotation.slerp(*a) * w), (0, 1, 2)))(p, q, t)
    want = jax.jit(jax.grad(lambda *a: jnp.sum(_rotation._slerp(*a) * w), (0, 1, 2)))(p, q, t)
    for g, x, expected in zip(got, (p, q, t), want):
        assert g.shape == x.shape
        _assert_close(g, expected)


@pytest.mark.skipif(not X64, reason="a lowering test: its verdict does not depend on the dtype")
@pytest.mark.parametrize("cpu", [True, False], ids=["cpu", "other"])
def test_gradient_is_one_linear_kernel_on_cpu_only(cpu, monkeypatch):
    """On CPU the gradient of ``to_rotvec`` is one ``jaxquat_linear_kernel``, compiled into two
    kernels: one variadic ``reduce`` (the one loop, its divisions and square roots inside it,
    through ``_fusion.fusible``: XLA's fusion emitters otherwise give a division with two users a
    kernel of its own) and the stack of its results; elsewhere (the backend test patched) the op
    is its kernel, whose gradient JAX forms (no such primitive)."""
    monkeypatch.setattr(_trig, "_cpu", lambda: cpu)
    q = jnp.asarray(random_quats(1, 8), DTYPE)
    w = jnp.asarray(np.random.default_rng(0).normal(size=(8, 3)), DTYPE)

    def grad(q):  # a fresh function: jit's trace cache is keyed by the function
        return jax.grad(lambda q: jnp.sum(_rotation.to_rotvec(q, rescale=True) * w))(q)

    jaxpr = str(jax.make_jaxpr(grad)(q))
    assert ("jaxquat_linear_kernel" in jaxpr) == cpu
    if cpu:
        hlo = jax.jit(grad).lower(q).compile().as_text()
        reduces = [line for line in hlo.splitlines() if " reduce(" in line]
        assert len(reduces) == 1 and reduces[0].split(" reduce(")[0].count("f64[8]") == 4  # four results
        entry = hlo[hlo.index("ENTRY") :]
        assert len(re.findall(r"^\s+(?:ROOT )?%\S+ = .* fusion\(", entry, re.M)) == 2  # the loop and the stack


def test_kernel_mode_values_are_the_values():
    """Traced in kernel mode (fusible divisions and roots, no barriers, plain splits) each op gives
    its value to a few ulp, and outside the mode ``divide`` and ``sqrt`` are ``/`` and
    ``jnp.sqrt``. Each side is one compiled program, traced inside or outside the mode (a new
    function each, so that jit's cache does not hand one side the other's trace); run eagerly,
    the kernels dispatched about 70 small programs (1.8-2.1 s per pass)."""
    for name, (_, plain, make) in OPS.items():
        args = make(11)
        with _trig.kernel_mode():
            inside = np.asarray(jax.jit(lambda *a, f=plain: f(*a))(*args), np.float64)
        want = np.asarray(jax.jit(lambda *a, f=plain: f(*a))(*args), np.float64)
        if name.startswith("to_euler"):  # -pi and pi
            inside = want + np.angle(np.exp(1j * (inside - want)))
        _assert_close(inside, want, rtol=64 * EPS)
    x = jnp.asarray(np.random.default_rng(3).uniform(0.1, 10.0, 64), DTYPE)
    np.testing.assert_array_equal(_trig.divide(1.0, x), 1.0 / x)
    np.testing.assert_array_equal(_trig.sqrt(x), jnp.sqrt(x))
    assert not _trig.in_kernel()


def test_linear_kernel_refuses_a_nonlinear_transpose():
    """The primitive is linear in its last operands only: transposing it with respect to the
    point it is linearised at is an error, not a silent wrong answer."""
    kernels = _derivatives._Kernels(lambda q: _rotation._to_rotvec(q), (1,), 1)
    q = jnp.asarray(random_quats(2, 3), DTYPE)

    def f(x, dx):
        return _derivatives._linear_p.bind(
            x, dx, fn=kernels.tangent, transpose=kernels.cotangent, n=1, out=(((3, 3), x.dtype),)
        )[0]

    with pytest.raises(NotImplementedError, match="linear in its last operands"):
        jax.linear_transpose(lambda x: f(x, q), q)(jnp.ones((3, 3), DTYPE))


def test_matrix_inputs_and_scalar_outputs():
    """The kernels of an op of ``(..., 3, 3)`` matrices (Shepperd's column, decorated here) and
    of one with a scalar output (the first component of ``to_rotvec``) give JAX's derivatives."""
    from jaxquat import _derivatives as d

    m = jax.vmap(jax.jit(lambda q: _rotation.to_matrix(q)))(jnp.asarray(random_quats(4, 6), DTYPE))
    m = m + 0.01 * jnp.asarray(np.random.default_rng(1).normal(size=m.shape), DTYPE)  # off SO(3) too
    shepperd = d.derivatives_in_one_loop(_rotation._shepperd_components, core=(2,), out_core=1)
    w = jnp.asarray(np.random.default_rng(2).normal(size=(6, 4)), DTYPE)
    first = d.derivatives_in_one_loop(lambda q: _rotation._to_rotvec(q)[..., 0], core=(1,), out_core=0)
    q = jnp.asarray(random_quats(8, 5), DTYPE)

    @jax.jit
    def both(m, q):
        def each(f, g):
            return f(m), jax.grad(lambda m: jnp.sum(f(m) * w))(m), jax.jvp(f, (m,), (m,))[1], g(q)

        return (
            each(shepperd, jax.grad(lambda q: jnp.sum(first(q) ** 2))),
            each(_rotation._shepperd_components, jax.grad(lambda q: jnp.sum(_rotation._to_rotvec(q)[..., 0] ** 2))),
        )

    got, want = both(m, q)
    _assert_close(got[0], want[0], rtol=64 * EPS)
    for g, expected in zip(got[1:], want[1:]):
        _assert_close(g, expected)


def _matrices(seed: int) -> jnp.ndarray:
    """Rotation matrices (random, the identity, half turns), matrices on the boundaries of
    ``from_matrix``'s cases (``R22 = 0``, ``R00 = R11``, ``R00 = -R11``: quarter turns about the
    axes, exact), and all of them perturbed off SO(3)."""
    rotations = np.asarray(jax.jit(_rotation.to_matrix)(jnp.asarray(random_quats(seed, 10), DTYPE)), np.float64)
    quarter = np.array(
        [
            [[1, 0, 0], [0, 0, -1], [0, 1, 0]],  # about x: R22 = 0
            [[0, 0, 1], [0, 1, 0], [-1, 0, 0]],  # about y: R00 = R22 = 0
            [[0, -1, 0], [1, 0, 0], [0, 0, 1]],  # about z: R00 = R11 = -R11 = 0
            [[-1, 0, 0], [0, -1, 0], [0, 0, 1]],  # a half turn about z: R00 = R11
        ],
        np.float64,
    )
    exact = np.concatenate([rotations, quarter])
    off = exact + 0.05 * np.random.default_rng(seed).normal(size=exact.shape)
    return jnp.asarray(np.concatenate([exact, off]), DTYPE)


@functools.cache
def _from_matrix_derivatives():
    """The value, one ``jvp`` and the gradient of ``sum(f * W)`` of ``from_matrix_shepperd`` (its
    two forms) and of its reverse-mode form alone (JAX's derivatives of it), compiled once."""

    def run(f, m, dm, w):
        return f(m), jax.jvp(f, (m,), (dm,))[1], jax.grad(lambda m: jnp.sum(f(m) * w))(m)

    return (
        jax.jit(functools.partial(run, _rotation.from_matrix_shepperd)),
        jax.jit(functools.partial(run, _rotation._shepperd_components)),
    )


@settings(max_examples=5, deadline=None)
@given(seed=seeds)
def test_from_matrix_forms_are_one_function(seed):
    """``_shepperd_rows`` (value, forward mode on CPU) and ``_shepperd_components`` (elsewhere)
    give the same quaternions on and off SO(3), on the cases' boundaries too; the tangent (the
    first form's) and the written-out cotangent (``_shepperd_cotangent``) are each other's
    transpose, ``<J dm, W> = <dm, J^T W>``, and equal JAX's derivatives of the second form."""
    m = _matrices(seed % 1000)
    rng = np.random.default_rng(seed)
    dm = jnp.asarray(rng.normal(size=m.shape), DTYPE)
    w = jnp.asarray(rng.normal(size=m.shape[:-2] + (4,)), DTYPE)
    _assert_close(jax.jit(_rotation._shepperd_rows)(m), jax.jit(_rotation._shepperd_components)(m), rtol=8 * EPS)
    both, reverse = _from_matrix_derivatives()
    value, tangent, cotangent = both(m, dm, w)
    want_value, want_tangent, want_cotangent = reverse(m, dm, w)
    _assert_close(value, want_value, rtol=8 * EPS)
    _assert_close(tangent, want_tangent)
    _assert_close(cotangent, want_cotangent)
    inner = float(jnp.sum(tangent * w)), float(jnp.sum(dm * cotangent))
    assert abs(inner[0] - inner[1]) <= RTOL * max(1.0, abs(inner[0])), inner


def test_from_matrix_cotangent_of_one_matrix_is_that_of_a_batch():
    """One matrix takes its own cotangent form (the nine entries stacked without a loop): the same
    gradient as that matrix's row of a batch, and JAX's derivative of the component form, at the
    identity or a half turn, on the cases' boundaries and at random rotations."""
    m = _matrices(6)
    w = jnp.asarray(np.random.default_rng(6).normal(size=m.shape[:-2] + (4,)), DTYPE)
    both, reverse = _from_matrix_derivatives()
    batch = both(m, m, w)[2]
    for i in range(len(m)):
        one = both(m[i : i + 1], m[i : i + 1], w[i : i + 1])[2]
        _assert_close(one, batch[i : i + 1])
        _assert_close(one, reverse(m[i : i + 1], m[i : i + 1], w[i : i + 1])[2])


@pytest.mark.skipif(not X64, reason="second derivatives compared in float64")
def test_from_matrix_two_forms_under_transforms():
    """``jacfwd`` (the row form's tangents) equals ``jacrev`` (the written-out cotangents) at the
    identity or a half turn and at case boundaries, and second derivatives agree with JAX's of the
    component form."""
    m = _matrices(4)

    @jax.jit  # one program for the three points (eagerly: a program per operation, 19 s of the float64 pass)
    def forms(one):
        return (
            (jax.jacfwd(_rotation.from_matrix_shepperd)(one), jax.jacrev(_rotation.from_matrix_shepperd)(one)),
            (
                jax.hessian(lambda x: _rotation.from_matrix_shepperd(x)[1])(one),
                jax.hessian(lambda x: _rotation._shepperd_components(x)[1])(one),
            ),
        )

    for i in (0, 11, 12):  # the identity or a half turn, R22 = 0, R00 = R22 = 0
        for got, want in forms(m[i]):
            _assert_close(got, want)
    check_grads(jax.jit(_rotation.from_matrix_shepperd), (m[14],), order=2, modes=("fwd", "rev"))


@pytest.mark.parametrize("cpu", [True, False], ids=["cpu", "other"])
def test_from_matrix_forms_on_cpu_only(cpu, monkeypatch):
    """On CPU the tangent is the linear primitive (the two forms); elsewhere (the backend test
    patched) ``from_matrix`` is the reverse-mode form, which JAX differentiates both ways."""
    monkeypatch.setattr(_trig, "_cpu", lambda: cpu)
    m = _matrices(2)

    def jvp(m):  # a fresh function: jit's trace cache is keyed by the function
        return jax.jvp(_rotation.from_matrix_shepperd, (m,), (m,))[1]

    assert ("jaxquat_linear_kernel" in str(jax.make_jaxpr(jvp)(m))) == cpu


def test_from_matrix_cotangent_in_blocks(monkeypatch):
    """The cotangent runs over blocks of rows (``_arrays.rows_at_a_time``), the last block overlapping
    the one before it: the same values as over the whole batch, for a batch of two axes, also with
    the matrix entries through a loop of their own (a long batch's); and a block function over one
    block or fewer rows is called once, unblocked."""
    m = _matrices(6).reshape(4, 7, 3, 3)
    g = jnp.asarray(np.random.default_rng(6).normal(size=(4, 7, 4)), DTYPE)
    whole = jax.jit(lambda m, g: _rotation._shepperd_cotangent(m, g))(m, g)
    monkeypatch.setattr(_rotation, "_COTANGENT_ROWS", 8)  # 28 rows: blocks at 0, 8, 16 and 20
    blocked = jax.jit(lambda m, g: _rotation._shepperd_cotangent(m, g))(m, g)
    _assert_close(blocked, whole, rtol=64 * EPS)  # other loops, other contractions: a few ulp
    monkeypatch.setattr(_rotation, "_ENTRIES_LOOP_ROWS", 1)  # the entries through a loop of their own
    looped = jax.jit(lambda m, g: _rotation._shepperd_cotangent(m, g))(m, g)
    _assert_close(looped, whole, rtol=64 * EPS)
    calls = []
    from jaxquat import _arrays

    _arrays.rows_at_a_time(lambda x: calls.append(x.shape) or x, 8, jnp.zeros((8, 2), DTYPE))
    assert calls == [(8, 2)]
