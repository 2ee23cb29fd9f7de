"""Small fixed-size array kernels: the dot product over a minor axis of 3 or 4, the 3x3
matrix-vector product and the symmetric 3x3 solve, the cross-product matrix and its inverse,
constants broadcast to a batch, and scalars stored before they are broadcast; :func:`compiled`,
through which the public functions run their bodies as one compiled program; and
:func:`rows_at_a_time`, a kernel over blocks of a long batch.

The kernels are written out per component because XLA on CPU compiles a reduction over a minor axis
this short into a slow loop, while the written-out form fuses into the surrounding
expression (measured figures in each docstring). Plain names: the module is private to the
package (see :mod:`jaxquat._quaternion`).
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import operator
from typing import Any

import jax
import jax.numpy as jnp
from jax import Array
from jax.interpreters import ad, batching, mlir

from . import _checks, _fusion, _trig

try:  # jax >= 0.4.36; pyproject allows 0.4.30, where jax.core still held it
    from jax.extend.core import Primitive
except ImportError:  # pragma: no cover
    from jax.core import Primitive  # pyright: ignore[reportAttributeAccessIssue]


def scalars(*xs: Array) -> tuple[Array, ...]:
    """Per-element scalars written to memory before they are broadcast into vectors.

    Left to itself XLA fuses a scalar expression (a ``sincos``, an ``atan2``) into
    every component of the ``(..., 3)`` or ``(..., 4)`` array built from it, so the
    polynomial is evaluated three or four times per element. An optimisation
    barrier makes it one pass that stores the scalars and one cheap pass that
    assembles the vectors. On CPU only (measured there; ``_trig.on_cpu``): other platforms
    get the values as they are and XLA's own fusion. In kernel mode (:func:`jaxquat._trig.kernel_mode`)
    the values as they are: a derivative kernel is one loop, in which each scalar is computed once.
    """
    if _trig.in_kernel():
        return xs
    return _trig.on_cpu(lambda *a: jax.lax.optimization_barrier(a), lambda *a: a, *xs)


def per_row(s: Array, k: int) -> Array:
    """``s[..., None]`` repeated ``k`` times along a new last axis, as a stack of ``k`` copies:
    reverse mode transposes it into ``k`` slices of the cotangent added element by element,
    where the transpose of a broadcast is a ``reduce`` over the minor axis of ``k``, which XLA on
    CPU (jaxlib 0.10.2, its defaults) handed to a YNNPACK fusion: the gradient of
    :func:`jaxquat.inverse` at 10^5 (float32, one core) 2.5 ms with the broadcast, 0.3 ms so.
    Used where it was measured: in a shared kernel the same change moved XLA's fusion elsewhere
    (``omega_from_qdot``'s gradient 2.1 -> 0.5 ms, but ``euler_parameter_acceleration``'s,
    which calls it, 14 -> 31 ms)."""
    return jnp.stack([s] * k, axis=-1)


def stack_in_one_loop(parts: list[Array]) -> Array:
    """``parts`` (broadcast to one shape) stacked along a new last axis after one loop computes them
    all (:func:`jaxquat._fusion.one_loop`): stacked as they are, XLA on CPU evaluates the work they
    share once per component. For kernels written on components."""
    return jnp.stack(_fusion.one_loop(jnp.broadcast_arrays(*parts)), axis=-1)


def components(x: Array) -> list[Array]:
    """The components ``x[..., i]`` of ``x`` as separate arrays (one ``jnp.split``), for kernels
    written on components and assembled by :func:`assemble`.

    A primitive of its own (``jaxquat_components``), for derivatives of two forms. Forward mode
    takes the tangent's components by the same split. Reverse mode gathers the components'
    cotangents back into ``(..., k)`` on CPU as the transpose of products with the columns of
    the identity (``dx @ e_i``), not through the concatenation that transposes a split: XLA on
    CPU fuses that concatenation with the expressions producing the cotangents into one loop over
    the output's elements that branches on the component and re-evaluates every shared
    subexpression once per component. Measured at 10^6 (this 2-core CPU, the gradient of
    ``sum(f(x) * W)``, minimum of 7 x 3 interleaved runs, float32 / float64): ``slerp`` 26 / 58 ms
    against 147 / 186 ms with the split's own transpose, ``from_euler`` 1.1 / 2.7 against 3.0 /
    6.7 ms, ``to_rotvec`` 18 / 33 against 8.6 / 62 ms. Until session 46 the products were the
    tangent itself (a ``custom_jvp``), which forward mode paid: one ``jvp`` at 10^6, float32, one
    core, least of 9, ``to_rotvec`` 29.3 -> 5.9 ms, ``from_rotvec`` 28.5 -> 4.0 ms with the split
    and :func:`assemble`'s tangents in one loop (``docs/benchmarks.md`` has the table).
    Elsewhere (GPU, TPU) both are JAX's own: a split and a concatenation; in kernel mode
    (:func:`jaxquat._trig.kernel_mode`) a plain split, whose transpose stays element-wise."""
    if _trig.in_kernel():
        return next((list(c) for y, c in _STACKED.get() if y is x), None) or list(split(x))
    return list(_components_p.bind(x))


_STACKED: contextvars.ContextVar[tuple[tuple[Array, list[Array]], ...]] = contextvars.ContextVar(
    "jaxquat_stacked", default=()
)


@contextlib.contextmanager
def stacked(parts: list[list[Array]], shapes: list[tuple[int, ...]]):
    """The arrays ``jnp.stack(c, axis=-1)`` of each list of components ``c`` in ``parts``, their
    last axis reshaped to ``shapes`` (``(4,)``, ``(3, 3)``); inside the ``with`` block, in kernel
    mode, :func:`components` of one of them returns its ``c`` themselves. A derivative kernel
    traces its op on these, so that the cotangents reach the components as they are, not through
    the concatenation that transposes a split (which XLA fuses with their producers into one loop
    per component)."""
    arrays = [jnp.stack(c, axis=-1).reshape(c[0].shape + shape) for c, shape in zip(parts, shapes)]
    token = _STACKED.set(_STACKED.get() + tuple(zip(arrays, parts)))
    try:
        yield arrays
    finally:
        _STACKED.reset(token)


def split(x: Array) -> tuple[Array, ...]:
    """The components ``x[..., i]`` of ``x`` by one ``jnp.split``, differentiated by JAX (reverse
    mode transposes the split into a concatenation): for kernels whose own derivative rule is
    written out (``to_euler``). Against :func:`components` as it was until session 46 (its
    tangents by products too), ``to_euler`` at 10^6 (this 2-core CPU, fresh processes): one
    ``jvp`` 5.1 against 21 ms (float32) and 20-22 against 40-43 ms (float64), the value and the
    gradient the same (7.2-7.8 ms, 18.8-20.0 ms float32)."""
    return tuple(c[..., 0] for c in jnp.split(x, x.shape[-1], axis=-1))


_components_p = Primitive("jaxquat_components")
_components_p.multiple_results = True


def _components_transpose(cts, x):
    """The cotangent of ``x`` from its components' cotangents ``cts``: on CPU the transpose of
    ``dx @ e_i`` (see :func:`components`), elsewhere a stack."""
    aval = x.aval
    cts = [ad.instantiate_zeros(c) for c in cts]

    def by_products(*cts):
        eye = jnp.eye(aval.shape[-1], dtype=aval.dtype)
        columns = jax.linear_transpose(
            lambda dx: tuple(matmul(dx, eye[:, i]) for i in range(aval.shape[-1])),
            jax.ShapeDtypeStruct(aval.shape, aval.dtype),
        )
        return columns(tuple(cts))[0]

    return [_trig.on_cpu(by_products, lambda *c: jnp.stack(c, axis=-1), *cts)]


def _components_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    return _components_p.bind(x), _components_p.bind(ad.instantiate_zeros(dx))


def _components_batch(args, dims):
    (x,), (d,) = args, dims
    x = jnp.moveaxis(x, d, 0)  # the mapped axis first, the components last (jacfwd maps the last)
    return _components_p.bind(x), [0] * x.shape[-1]


_components_p.def_impl(split)
_components_p.def_abstract_eval(lambda x: [x.update(shape=x.shape[:-1])] * x.shape[-1])
mlir.register_lowering(_components_p, mlir.lower_fun(split, multiple_results=True))
ad.primitive_jvps[_components_p] = _components_jvp
ad.primitive_transposes[_components_p] = _components_transpose
batching.primitive_batchers[_components_p] = _components_batch


def assemble(*c: Array) -> Array:
    """``jnp.stack(c, axis=-1)``, formed on CPU as ``sum_i c_i e_i^T`` (exact for finite values;
    a NaN or infinite component makes its whole row NaN); in kernel mode
    (:func:`jaxquat._trig.kernel_mode`) a plain stack, which the kernel takes apart again.

    On CPU XLA fuses a stack along the minor axis with the expressions that produce its
    components into one loop over the output's elements that branches on the component and
    evaluates every shared subexpression (a ``sincos``) once per component. The sum of
    products fuses into an element-wise loop over whole rows. Measured on ``from_euler``'s
    kernel (10^6, this 2-core CPU, minimum of 20): 1.4 against 3.3 ms (float32), 3.1 against
    38 ms (float64).

    A linear primitive of its own (``jaxquat_assemble``), the mirror of :func:`components`: its
    tangent is the same sum of products of the components' tangents, fused with the expressions
    that produce them, and its transpose the slices of the cotangent (the transpose of the
    products would be a sum over the minor axis: the gradient of ``sum(f(x) * W)`` took 41
    against 26 ms, ``slerp``, float32). Until session 62 the tangents were computed in one loop
    (:func:`jaxquat._fusion.one_loop`) into arrays of their own and then stacked: a second pass,
    and temporaries that glibc's allocator mapped afresh at many calls (``docs/benchmarks.md``,
    session 62, has the figures). Elsewhere (GPU, TPU) a plain stack."""
    parts = jnp.broadcast_arrays(*c)
    if _trig.in_kernel():
        return jnp.stack(parts, axis=-1)
    dtype = jnp.result_type(*parts)
    return _trig.on_cpu(_assemble_p.bind, lambda *p: jnp.stack(p, axis=-1), *(x.astype(dtype) for x in parts))


_assemble_p = Primitive("jaxquat_assemble")


def _assemble_transpose(ct, *c):
    """The components' cotangents: the slices of the cotangent ``ct`` (a split)."""
    if type(ct) is ad.Zero:
        return [ad.Zero(x.aval) if ad.is_undefined_primal(x) else None for x in c]
    parts = split(ct)
    return [p if ad.is_undefined_primal(x) else None for p, x in zip(parts, c)]


def _assemble_batch(args, dims):
    size = next(a.shape[d] for a, d in zip(args, dims) if d is not None)
    moved = [
        jnp.moveaxis(a, d, 0) if d is not None else jnp.broadcast_to(a, (size,) + a.shape) for a, d in zip(args, dims)
    ]
    return _assemble_p.bind(*moved), 0


def by_products(*c: Array) -> Array:
    """``sum_i c_i e_i^T``: the components ``c`` stacked along a new last axis by products with
    the rows of the identity (exact for finite values), differentiated by JAX."""
    eye = jnp.eye(len(c), dtype=c[0].dtype).reshape((1,) * c[0].ndim + (len(c), len(c)))
    return functools.reduce(operator.add, [x[..., None] * eye[..., i, :] for i, x in enumerate(c)])


_assemble_p.def_impl(by_products)
_assemble_p.def_abstract_eval(lambda *c: c[0].update(shape=c[0].shape + (len(c),)))
mlir.register_lowering(_assemble_p, mlir.lower_fun(by_products, multiple_results=False))
ad.deflinear2(_assemble_p, _assemble_transpose)
batching.primitive_batchers[_assemble_p] = _assemble_batch


# Every matrix product in the library asks for full precision. On a GPU, JAX's default
# precision lets float32 products run on TF32 tensor cores (10-bit mantissa): on an H100,
# ``rotate_inertia``'s Jacobian was 1.8e-3 off and ``mean`` 5.4e-4 rad off scipy in float32
# (session 26). On a CPU the request changes nothing. The optimal-control layer, which runs in
# float64 (where no TF32 applies), keeps plain ``@``.
FULL = jax.lax.Precision.HIGHEST


def matmul(a: Array, b: Array) -> Array:
    """``a @ b`` at full precision (no TF32 on a GPU)."""
    return jnp.matmul(a, b, precision=FULL)


def einsum(spec: str, *operands: Array) -> Array:
    """``jnp.einsum`` at full precision (no TF32 on a GPU)."""
    return jnp.einsum(spec, *operands, precision=FULL)


def outer_sum(a: Array, b: Array | None = None, weights: Array | None = None) -> Array:
    """``sum_n w_n a_n b_n^T`` over the second-last axis: ``a`` ``(..., n, i)``, ``b`` ``(..., n, j)``
    (``None``: ``a`` itself, and only the upper triangle is formed), ``weights`` ``(..., n)`` or
    ``None`` (all ones); returns ``(..., i, j)`` (half-precision inputs summed in float32, the
    result cast back). The products are element-wise and their sums one loop on CPU
    (:func:`jaxquat._fusion.sums`); the cotangents are element-wise too.

    Why not an ``einsum``: XLA on CPU ran it as a matrix product with an inner dimension of ``n``.
    ``align_vectors`` of 10^6 vector pairs (one problem, with the ``rotate`` that makes them; one
    core of this 2-core EPYC, least of 9 runs), einsum -> this: float32 value 9.8 -> 3.4 ms,
    gradient 40 -> 3.9 ms, one ``jvp`` 39 -> 11 ms; float64 11.6 -> 3.6, 26-39 -> 16-24 and 55 ->
    12 ms. ``mean`` of 10^6 quaternions: float32 2.0 -> 1.3, 6.2 -> 2.0 and 7.6 -> 4.4 ms;
    float64 2.7 -> 1.4, 20-32 -> 2.8 and 10.7 -> 4.7 ms."""
    symmetric = b is None
    b = a if b is None else b
    dtype = jnp.result_type(a, b, *([] if weights is None else [weights]))
    work = _checks.working_dtype(dtype)  # half precision: products and sums in float32, as a dot accumulates
    if work != dtype:
        wide = None if weights is None else weights.astype(work)
        return outer_sum(a.astype(work), None if symmetric else b.astype(work), wide).astype(dtype)
    rows = outer_sum_entries(a, None if symmetric else b, weights)
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)


def outer_sum_entries(
    a: Array, b: Array | None = None, weights: Array | None = None, *, unit: bool = False
) -> list[list[Array]]:
    """:func:`outer_sum`'s entries as nested lists of arrays ``(...)``, not stacked (inputs of one
    dtype, at least single precision): for a caller that computes on the entries, whose cotangents
    then reach the sums as they are, where taking them from the stacked matrix transposed each
    slice into a pad that XLA on CPU fused with the whole backward computation once per entry
    (``attitude_covariance``'s gradient at 10^5 problems of 5 vectors, float32: 46 -> 16 ms).
    ``unit`` (with ``b`` None): the sums of ``u u^T`` for the unit vectors ``u = a / |a|``, the
    weights divided by ``|a|^2`` computed from the components (from the rows, the norm's
    cotangent cost ``attitude_covariance``'s gradient 5.8 ms more)."""
    symmetric = b is None
    b = a if b is None else b
    m, k = a.shape[-1], b.shape[-1]
    parts = components(a) if symmetric else components(a) + components(b)
    left, right = parts[:m], parts[-k:]
    if unit:
        if not symmetric:
            raise ValueError("outer_sum_entries: unit=True takes one array")
        nsq = parts[0] * parts[0]
        for x in parts[1:]:
            nsq = nsq + x * x
        weights = 1.0 / nsq if weights is None else weights / nsq
    if weights is not None:
        left = [weights * x for x in left]
    pairs = [(i, j) for i in range(m) for j in range(i if symmetric else 0, k)]
    sums = dict(zip(pairs, _fusion.sums([left[i] * right[j] for i, j in pairs], -1)))
    return [[sums[(i, j) if (i, j) in sums else (j, i)] for j in range(k)] for i in range(m)]


def dot(a: Array, b: Array) -> Array:
    """``sum(a * b)`` over the last axis (size 3 or 4), written out per component: XLA fuses
    it into the surrounding expression, while a reduction over a minor axis that short
    compiles to a slow loop on CPU."""
    total = a[..., 0] * b[..., 0]
    for i in range(1, a.shape[-1]):
        total = total + a[..., i] * b[..., i]
    return total


# At most this many terms are summed written out (sum_last); longer axes go to one reduce.
_SHORT_SUM = 32


def sum_last(x: Array) -> Array:
    """``sum(x, axis=-1)``, written out term by term when the axis has at most 32 entries: XLA's
    CPU backend (jaxlib 0.10.2, its defaults) handed a reduce over a short minor axis, fused
    with the element-wise work before and after it, to a YNNPACK fusion that ran it about 40x
    slower than the element-wise sum. ``quest``'s ``lambda_0 = sum_i w_i |r_i| |b_i|`` for 10^5
    problems of 10 vector pairs (one core of this 2-core EPYC, least of 7): the whole of
    ``quest`` 80.7 -> 26-34 ms in float32, 139 -> 95 ms in float64, the reduce's fusion 40 ms of
    the 82 before (the profiler's figures). Longer axes keep ``jnp.sum``."""
    n = x.shape[-1]
    if n == 0 or n > _SHORT_SUM:
        return jnp.sum(x, axis=-1)
    total = x[..., 0]
    for i in range(1, n):
        total = total + x[..., i]
    return total


def const_like(values, like: Array) -> Array:
    """A constant vector broadcast to ``like``'s batch shape (explicitly, for strict rank promotion)."""
    return jnp.broadcast_to(jnp.asarray(values, dtype=like.dtype), like.shape[:-1] + (len(values),))


def hat(v: Array) -> Array:
    """The cross-product matrix ``[[0, -z, y], [z, 0, -x], [-y, x, 0]]`` of ``v = (x, y, z)``."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], axis=-2)


def matvec(m: Array, v: Array) -> Array:
    """``m @ v`` for stacks of small matrices (3x3, 4x4), written out per component: XLA fuses it,
    while a ``sum`` over the minor axis of size 3 compiles to a slow reduction loop on CPU
    (measured 20x)."""
    return jnp.stack([dot(m[..., i, :], v) for i in range(m.shape[-2])], axis=-1)


def vee(m: Array) -> Array:
    """``(m32 - m23, m13 - m31, m21 - m12) / 2``: the vector of ``m``'s skew part."""
    return 0.5 * jnp.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], axis=-1
    )


def symmetric_solve(inertia: Array, b: Array) -> Array:
    """``I^-1 b`` for symmetric ``I`` by the adjugate (element-wise, so it fuses; no LAPACK call).
    Each component is divided by the determinant before the stack, so a shared tensor ``(3, 3)``
    meets a batch ``b`` ``(n, 3)`` without a rank promotion (``det[..., None]`` had rank 1, which
    ``jax_numpy_rank_promotion="raise"`` refused); the same values."""
    upper = [inertia[..., i, j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))]
    return jnp.stack(symmetric_solve_parts(upper, [b[..., 0], b[..., 1], b[..., 2]]), -1)


def symmetric_solve_parts(upper: list[Array], b: list[Array]) -> list[Array]:
    """:func:`symmetric_solve` on components: ``upper`` the entries ``m00, m01, m02, m11, m12,
    m22``, ``b`` three arrays; returns three."""
    (c00, c01, c02), (_, c11, c12), (_, _, c22), det = _symmetric_cofactors(upper)
    b0, b1, b2 = b
    return [
        (c00 * b0 + c01 * b1 + c02 * b2) / det,
        (c01 * b0 + c11 * b1 + c12 * b2) / det,
        (c02 * b0 + c12 * b1 + c22 * b2) / det,
    ]


def symmetric_inverse_parts(upper: list[Array]) -> list[list[Array]]:
    """The entries of ``m^-1`` (rows of three arrays) for symmetric ``m`` given by ``upper`` (as
    :func:`symmetric_solve_parts`), by its cofactors."""
    *rows, det = _symmetric_cofactors(upper)
    full = [[rows[min(i, j)][max(i, j)] for j in range(3)] for i in range(3)]
    return [[c / det for c in r] for r in full]


def _symmetric_cofactors(upper: list[Array]):
    """The cofactors of a symmetric 3x3 ``m`` (rows, the upper triangle filled) and its determinant."""
    m00, m01, m02, m11, m12, m22 = upper
    c00 = m11 * m22 - m12 * m12
    c01 = m02 * m12 - m01 * m22
    c02 = m01 * m12 - m02 * m11
    c11 = m00 * m22 - m02 * m02
    c12 = m01 * m02 - m00 * m12
    c22 = m00 * m11 - m01 * m01
    det = m00 * c00 + m01 * c01 + m02 * c02
    return (c00, c01, c02), (c01, c11, c12), (c02, c12, c22), det


def symmetric_inverse(inertia: Array) -> Array:
    """``I^-1`` ``(..., 3, 3)`` for symmetric ``I`` by :func:`symmetric_solve` against the unit
    vectors (row ``j`` is ``I^-1 e_j``, which is column ``j`` as ``I^-1`` is symmetric): for
    callers that apply one tensor's inverse many times (each integration step) as products."""
    eye = jnp.broadcast_to(jnp.eye(3, dtype=inertia.dtype), inertia.shape[:-2] + (3, 3))  # explicit ranks
    return symmetric_solve(inertia[..., None, :, :], eye)


def valid_weights(weights: Array) -> Array:
    """Per set: every weight finite and non-negative, and their sum positive."""
    ok = jnp.all(jnp.isfinite(weights) & (weights >= 0), axis=-1)
    return ok & (jnp.sum(weights, axis=-1) > 0)


def nan_where(bad: Array, q: Array) -> Array:
    """NaN in every component of the elements where ``bad`` (the others untouched)."""
    return jnp.where(bad[..., None], jnp.nan, q)


@functools.cache
def _jit(fn, static_argnames: tuple[str, ...], cpu: bool):
    @functools.wraps(fn)
    def body(*args, **kwargs):  # one function per backend choice: JAX keys its traces by the function
        return fn(*args, **kwargs)

    return jax.jit(body, static_argnames=static_argnames)


def compiled(fn, *arrays: Any, **static):
    """``fn(*arrays, **static)`` as one compiled program: ``jax.jit`` of the module-level ``fn``
    (``static`` its static keyword arguments: strings, flags; an argument may be ``None``, an
    empty argument, or a pytree of arrays), made on first use and kept.

    The public functions call their bodies through this after their argument checks. Called
    eagerly (a notebook cell, a script), a body otherwise runs as single operations, each
    compiled on its first use for a shape and dispatched one by one afterwards. Measured
    (float32, 100 rotations, a fresh interpreter per function, this 2-core CPU, XLA's
    defaults, 24 public functions from ``multiply`` to ``right_jacobian_inverse``): the first
    call 0.22-1.29 s as 6-55 single-operation compilations, 0.03-0.31 s as one program; a
    repeated call 1.5-5.5 ms against 0.14-0.45 ms (``docs/benchmarks.md``). Inside a user's
    ``jit``, ``vmap`` or ``grad`` the call is traced into the enclosing program (XLA inlines
    it): the same operations, so the same values. The bodies choose their kernels by the backend
    at trace time (:func:`jaxquat._trig.on_cpu`), so the compiled function is kept per choice."""
    return _jit(fn, tuple(sorted(static)), _trig.is_cpu())(*arrays, **static)


def compiled_rows(fn, cores: tuple[int, ...], *arrays: Any, **static):
    """:func:`compiled` for a function computed row by row: ``arrays[i]`` has ``cores[i]`` core
    axes after its batch axes (a quaternion 1, a matrix 2, a scalar 0; ``None`` for an empty
    argument), and every result the batch axes first. Over a batch of two or more axes the
    arrays go to ``fn`` with the batch flattened to one axis (broadcast first where an array's
    batch is part of it; an array without batch axes as it is), and the results come back shaped.

    Why: XLA's CPU loops vectorise along the last axis of an array. A component ``x[..., i]`` of
    a ``(n, 3, 4)`` batch is ``(n, 3)``, whose inner loop runs over 3 elements; flattened it is
    ``(3 n,)``. Measured (float32, 3 x 10^5 rotations, one core, least of 7, value / gradient of
    ``sum(f * W)``), on ``(10^5, 3, 4)`` against ``(3 x 10^5, 4)``: ``to_rotvec`` 4.9 / 20.9
    against 2.2 / 3.1 ms before, 4.0 / 3.4 ms flattened; ``slerp`` 29.6 / 15.5 against 5.4 / 6.3
    ms before, 5.2 / 8.3 ms flattened. Not recovered: ``multiply`` 1.2 against 0.43 ms and
    ``from_rotvec`` 3.0 against 0.85 ms, though XLA compiles the same fusion (it keeps the entry's
    shape as the fusion's parameter and result). A reshape of contiguous leading axes copies
    nothing; the values are the same to the bit (``docs/benchmarks.md``, session 54)."""
    return compiled(_flattened(fn, cores), *arrays, **static)


def compiled_rows_broadcast(fn, cores: tuple[int, ...], *arrays: Any, **static):
    """:func:`compiled_rows` for a kernel that needs its arrays at one batch shape (one formed from
    rows, such as the quaternion product): an array without batch axes, which the argument checks
    leave as it is (``_checks.arguments(shared=...)``), is broadcast to the batch inside the
    compiled program, where XLA fuses the broadcast into its consumers. Broadcast before the
    program (an eager call), the array was written to memory at the batch's size first. At 10^6
    rows (float32, one core, eager, session 63, two or three processes each): ``multiply(Q, q)``
    with one ``q`` 2.2-3.7 -> 1.0-2.0 ms, ``plus(Q, delta)`` with one ``delta`` 4.5-4.7 -> 1.0-1.1
    ms, ``minus(Q, q)`` 12.2 -> 8.5-8.7 ms, ``from_axis_angle(axis, angles)`` 7.7-7.9 -> 5.7 ms,
    ``qdot_from_omega(Q, w)`` 10.3-10.9 -> 9.2-9.5 ms; under ``jit`` and for the gradients the
    same times (gradients in ``(Q, w)``, three processes each: ``generalized_force`` 15.8-16.6
    against 15.7-16.1 ms, ``qdot_from_omega`` 15.6-16.7 against 15.7-16.7 ms, ``multiply``
    25.6-26.2 against 25.7-26.3 ms). Used by ``multiply``, ``plus``, ``minus``,
    ``from_axis_angle``, the kinematics' rate relations, ``generalized_force``,
    ``torque_from_generalized_force`` and ``inertia_rate``."""
    return compiled(_flattened(fn, cores, True), *arrays, **static)


@functools.cache
def _flattened(fn, cores: tuple[int, ...], broadcast: bool = False):
    """``fn`` with the batch of its arrays flattened to one axis (:func:`compiled_rows`); with
    ``broadcast``, every array at the batch's shape (:func:`compiled_rows_broadcast`)."""

    @functools.wraps(fn)
    def flat(*arrays, **static):
        batches = [a.shape[: a.ndim - c] for a, c in zip(arrays, cores) if a is not None]
        batch = jnp.broadcast_shapes(*batches) if batches else ()

        def full(a, c):  # at the batch's shape
            return jnp.broadcast_to(a, batch + a.shape[a.ndim - c :])

        if len(batch) < 2:
            if broadcast:
                arrays = tuple(a if a is None else full(a, c) for a, c in zip(arrays, cores))
            return fn(*arrays, **static)
        n = functools.reduce(operator.mul, batch, 1)

        def rows(a, c):
            if a is None or (a.ndim == c and not broadcast):
                return a
            return full(a, c).reshape((n,) + a.shape[a.ndim - c :])

        out = fn(*(rows(a, c) for a, c in zip(arrays, cores)), **static)
        return jax.tree.map(lambda x: x.reshape(batch + x.shape[1:]), out)

    return flat


def rows_at_a_time(fn, rows: int, *xs: Array) -> Array:
    """``fn(*xs)`` for arrays of one leading axis (a flattened batch), ``rows`` rows at a time when
    the batch is longer: a ``fori_loop`` over blocks, the last block ending at the last row
    (it overlaps the one before it, whose rows it computes again, to the same values), each
    written into the result by ``dynamic_update_slice``. For a kernel whose temporaries would
    pass glibc's 32 MiB ``mmap`` threshold over the whole batch: XLA on CPU maps such a buffer
    afresh at every call and faults in every page (``from_matrix``'s cotangent at 10^6 in float32:
    36 MB of temporaries, 47 ms whole, 26 ms in blocks of 2^15 rows, 14 ms with glibc's maps
    disabled). ``fn`` maps ``(rows, ...)`` blocks to ``(rows, ...)`` blocks."""
    n = xs[0].shape[0]
    if n <= rows:
        return fn(*xs)
    out = jax.eval_shape(fn, *(jax.ShapeDtypeStruct((rows,) + x.shape[1:], x.dtype) for x in xs))
    blocks = -(-n // rows)

    def body(i, acc):
        start = jnp.minimum(i * rows, n - rows)
        block = fn(*(jax.lax.dynamic_slice_in_dim(x, start, rows) for x in xs))
        return jax.lax.dynamic_update_slice_in_dim(acc, block, start, 0)

    return jax.lax.fori_loop(0, blocks, body, jnp.zeros((n,) + out.shape[1:], out.dtype))
