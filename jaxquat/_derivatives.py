"""Element-wise ops whose forward-mode tangent and reverse-mode cotangent each run as one loop over
the batch on CPU: :func:`derivatives_in_one_loop`; and :func:`forward_and_reverse`, an op whose
value and tangent come from one form and whose cotangent is written out (``from_matrix``), through
the same linear primitive.

JAX differentiates an op by its operations: reverse mode stores the forward pass's intermediates
(each an array over the batch, written and read back) and runs the transposed operations in
kernels of their own. For the rotation ops on CPU that made a gradient at 10^6 elements 5-30
times the time of moving its bytes (``docs/benchmarks.md``): ``to_rotvec``'s gradient took 16
kernels, most of them intermediates of the forward pass with several consumers.

Here an op's tangent ``J(x) dx`` and cotangent ``J(x)^T g`` are two kernels (a primitive,
``jaxquat_linear_kernel``, linear in its last operands, each the other's transpose), each
traced from the op itself by ``jax.jvp`` and ``jax.vjp`` and compiled as a whole: from the op's
inputs, with nothing stored between the forward and the backward pass (reverse mode keeps the
inputs, which it holds anyway). Three things make XLA compile a kernel into one loop:

- its output's components pass through :func:`jaxquat._fusion.one_loop` (a variadic ``reduce``,
  always one loop) before they are stacked;
- it is traced in kernel mode (:func:`jaxquat._trig.kernel_mode`): divisions and square roots
  pass through :func:`jaxquat._fusion.fusible` (XLA's CPU fusion never duplicates a floating
  divide or square root, so each one with two users was an array of its own; until session 65
  they were built from multiplies instead), the scalars' optimisation barriers
  (:func:`jaxquat._arrays.scalars`) are off, and the ops' component splits and stacks are plain;
- the op is written on components (:func:`jaxquat._arrays.components`), so the kernel's
  arithmetic is element-wise.

Measured at 10^6 (float32, one core of this 2-core EPYC): ``to_rotvec``'s cotangent kernel alone
took 24 ms with XLA's divisions and square roots (11 loops: each of them with two users, and their
producers, written out) and 5.3 ms in kernel mode (one loop and the stack). The gradients of the
ops that use it: ``to_rotvec`` 26 -> 6.0 ms, ``slerp`` 44 -> 11.8 ms, ``to_euler`` 32 -> 5.3 ms
(their docstrings have both dtypes and forward mode; ``docs/benchmarks.md`` the tables). Tried
and not kept: ``from_rotvec`` (value 2.0 -> 8.3 ms, gradient 2.3 -> 3.2 ms) and ``from_euler``
(value 2.3 -> 2.9 ms, gradient 2.0 -> 2.2 ms), already within 3x of moving their bytes;
``from_matrix`` (gradient 45 -> 59 ms: XLA wrote the input's nine entries out as arrays of their
own, though one ``jvp`` went 39 -> 8.5 ms). On other platforms than CPU the ops keep JAX's own
derivatives (XLA's GPU compiler fuses many outputs itself).

Second derivatives differentiate the kernels themselves (``jax.jvp`` of the tangent kernel), so
they are exact too, if not fused.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
from jax import Array
from jax.interpreters import ad, batching, mlir

from . import _arrays, _fusion, _trig

try:  # jax >= 0.4.36; pyproject allows 0.4.30, where jax.core still held it
    from jax.extend.core import Primitive
except ImportError:  # pragma: no cover
    from jax.core import Primitive  # pyright: ignore[reportAttributeAccessIssue]


def derivatives_in_one_loop(
    fn: Callable[..., Array], core: Sequence[int], out_core: int, value_in_one_loop: bool = True
) -> Callable[..., Array]:
    """``fn`` (element-wise over leading batch axes, its arrays' last ``core[i]`` axes their
    components, its output's last ``out_core``), differentiated on CPU by one-loop kernels.

    With ``value_in_one_loop`` the value is a kernel too (traced in kernel mode, its components
    computed in one loop before the stack), else ``fn``'s own. Keyword arguments of the result
    are static (``fn``'s options: flags, strings). Elsewhere than on CPU it is ``fn`` itself."""

    @functools.wraps(fn)
    def op(*xs: Array, **static) -> Array:
        if not _trig.is_cpu():
            return fn(*xs, **static)
        return _custom(fn, tuple(core), out_core, value_in_one_loop, tuple(sorted(static.items())))(*xs)

    return op


@functools.cache
def _custom(fn, core: tuple[int, ...], out_core: int, value_in_one_loop: bool, static: tuple):
    f = functools.partial(fn, **dict(static))
    kernels = _Kernels(f, core, out_core)
    return _with_linear_tangent(kernels.value if value_in_one_loop else lambda xs: f(*xs), kernels)


def _with_linear_tangent(value: Callable, kernels) -> Callable[..., Array]:
    """A function of arrays whose value is ``value(xs)`` and whose tangent is the linear primitive
    below, ``kernels.tangent``, with ``kernels.cotangent`` its transpose (a ``custom_jvp``)."""

    @jax.custom_jvp
    def op(*xs):
        return value(xs)

    @op.defjvp
    def _jvp(primals, tangents):
        y = op(*primals)
        out = ((jnp.shape(y), jnp.result_type(y)),)  # the tangent's type: the kernel is not traced for it
        (tangent,) = _linear_p.bind(
            *primals, *tangents, fn=kernels.tangent, transpose=kernels.cotangent, n=len(primals), out=out
        )
        return y, tangent

    return op


class _Kernels:
    """The value, tangent and cotangent kernels of one op (hashable by identity: primitive
    parameters). Each traces the op on its inputs' components (:func:`_flat_parts`), stacked by
    :func:`jaxquat._arrays.stacked`, so the op's own splits hand them back unchanged."""

    def __init__(self, f, core, out_core):
        self.f, self.core, self.out_core = f, core, out_core

    def _on_parts(self, shapes, *flat):
        """``f`` of the arrays whose components are ``flat`` (core shapes ``shapes``)."""
        parts, it = [], iter(flat)
        for shape in shapes:
            parts.append([next(it) for _ in range(math.prod(shape))])
        vectors = [p for p, c in zip(parts, self.core) if c]
        with _arrays.stacked(vectors, [s for s, c in zip(shapes, self.core) if c]) as arrays:
            it = iter(arrays)
            return self.f(*(next(it) if c else p[0] for p, c in zip(parts, self.core)))

    def _traced(self, xs):
        return functools.partial(self._on_parts, [_core_shape(x, c) for x, c in zip(xs, self.core)])

    def _output(self, y):
        """``y``, the op's output or its tangent, with its components computed in one loop."""
        return _in_one_loop(_flat_parts([y], [self.out_core]), [_core_shape(y, self.out_core)])[0]

    def value(self, xs):
        with _trig.kernel_mode():
            return self._output(self._traced(xs)(*_flat_parts(xs, self.core)))

    def tangent(self, xs, dxs):
        with _trig.kernel_mode():
            _, t = jax.jvp(self._traced(xs), tuple(_flat_parts(xs, self.core)), tuple(_flat_parts(dxs, self.core)))
            return (self._output(t),)

    def cotangent(self, xs, cts):
        (ct,) = cts
        batch = jnp.broadcast_shapes(*(jnp.shape(x)[: jnp.ndim(x) - c] for x, c in zip(xs, self.core)))
        full = [jnp.broadcast_to(x, batch + _core_shape(x, c)) for x, c in zip(xs, self.core)]
        with _trig.kernel_mode():
            _, vjp = jax.vjp(self._traced(xs), *_flat_parts(full, self.core))
            dparts = vjp(jnp.broadcast_to(ct, batch + _core_shape(ct, self.out_core)))
        dxs = _in_one_loop(list(dparts), [_core_shape(x, c) for x, c in zip(xs, self.core)])
        return tuple(_unbroadcast(dx, jnp.shape(x)) for dx, x in zip(dxs, xs))


def forward_and_reverse(
    forward: Callable[[Array], Array], cotangent: Callable[[Array, Array], Array], elsewhere: Callable[[Array], Array]
) -> Callable[[Array], Array]:
    """One function of one array written for each mode: ``forward`` gives the value and the
    forward-mode tangent (JAX's ``jvp`` of it), ``cotangent(x, ct)`` the reverse-mode cotangent,
    each the form XLA compiles best for that mode (``from_matrix``: ``jaxquat._rotation``). The
    cotangent must be the transpose of ``forward``'s tangent, branch for branch. The tangent is
    bound through the linear primitive below, whose transpose is the cotangent (second
    derivatives: JAX's derivatives of the two). Elsewhere than on CPU it is ``elsewhere``, the
    same function, differentiated by JAX."""
    return _two_forms(forward, cotangent, elsewhere)


@functools.cache
def _two_forms(forward, cotangent, elsewhere):
    def run(x: Array) -> Array:
        return _two_forms_op(forward, cotangent)(x) if _trig.is_cpu() else elsewhere(x)

    return run


@functools.cache
def _two_forms_op(forward, cotangent):
    return _with_linear_tangent(lambda xs: forward(*xs), _TwoForms(forward, cotangent))


class _TwoForms:
    """The tangent (``forward``'s ``jvp``) and the cotangent of :func:`forward_and_reverse`
    (hashable by identity: primitive parameters)."""

    def __init__(self, forward, cotangent):
        self.forward, self._cotangent = forward, cotangent

    def tangent(self, xs, dxs):
        return [jax.jvp(self.forward, tuple(xs), tuple(dxs))[1]]

    def cotangent(self, xs, cts):
        return [self._cotangent(*xs, *cts)]


def _core_shape(x, c: int) -> tuple[int, ...]:
    return tuple(jnp.shape(x)[jnp.ndim(x) - c :])


def _size(x, c: int) -> int:
    return math.prod(jnp.shape(x)[jnp.ndim(x) - c :])


def _flat_parts(xs, core) -> list[Array]:
    """Every component of every array, in order (an array of no component axes is its own)."""
    out = []
    for x, c in zip(xs, core):
        flat = jnp.reshape(x, jnp.shape(x)[: jnp.ndim(x) - c] + (_size(x, c),))
        out += [flat[..., i] for i in range(flat.shape[-1])] if c else [x]
    return out


def _in_one_loop(parts: list[Array], shapes: list[tuple[int, ...]]) -> list[Array]:
    """The arrays of core shapes ``shapes`` whose components are ``parts`` (in order, of one
    batch shape), the components computed in one loop (:func:`jaxquat._fusion.one_loop`)."""
    looped = iter(_fusion.one_loop(jnp.broadcast_arrays(*parts)))
    out = []
    for shape in shapes:
        comps = [next(looped) for _ in range(math.prod(shape))]
        out.append(_arrays.by_products(*comps).reshape(comps[0].shape + shape) if shape else comps[0])
    return out


def _unbroadcast(x: Array, shape: tuple[int, ...]) -> Array:
    """``x`` summed over the axes that broadcasting added to ``shape``."""
    lead = x.ndim - len(shape)
    axes = tuple(range(lead)) + tuple(lead + i for i, n in enumerate(shape) if n == 1 and x.shape[lead + i] != 1)
    return jnp.sum(x, axis=axes).reshape(shape) if axes else x


_linear_p = Primitive("jaxquat_linear_kernel")
_linear_p.multiple_results = True


def _split(args, n):
    return args[:n], args[n:]


def _abstract(*args, fn, transpose, n, out):
    """The outputs' types, given (``out``): tracing the kernel for them cost each bind (the JVP,
    partial evaluation, the transpose) a trace of the op."""
    return [args[0].update(shape=shape, dtype=dtype) for shape, dtype in out]


def _lower(ctx, *args, fn, transpose, n, out):
    return mlir.lower_fun(lambda *a: fn(*_split(a, n)), multiple_results=True)(ctx, *args)


def _type(y) -> tuple:
    aval = y.aval if ad.is_undefined_primal(y) else y
    return (tuple(jnp.shape(aval)), jnp.dtype(aval.dtype))


def _transpose(cts, *args, fn, transpose, n, out):
    xs, ys = _split(args, n)
    if any(ad.is_undefined_primal(x) for x in xs):
        raise NotImplementedError("jaxquat_linear_kernel is linear in its last operands only")
    cts = [ad.instantiate_zeros(c) for c in cts]
    outs = _linear_p.bind(*xs, *cts, fn=transpose, transpose=fn, n=n, out=tuple(_type(y) for y in ys))
    return [None] * n + [o if ad.is_undefined_primal(y) else None for o, y in zip(outs, ys)]


def _jvp(primals, tangents, *, fn, transpose, n, out):
    """Second derivatives: the kernel differentiated as JAX traces it."""
    tangents = [ad.instantiate_zeros(t) for t in tangents]
    outs = _linear_p.bind(*primals, fn=fn, transpose=transpose, n=n, out=out)
    _, touts = jax.jvp(lambda *a: fn(*_split(a, n)), tuple(primals), tuple(tangents))
    return outs, list(touts)


def _batch(args, dims, *, fn, transpose, n, out):
    size = next(a.shape[d] for a, d in zip(args, dims) if d is not None)
    moved = [
        jnp.moveaxis(a, d, 0) if d is not None else jnp.broadcast_to(a, (size,) + a.shape) for a, d in zip(args, dims)
    ]
    outs = _linear_p.bind(*moved, fn=fn, transpose=transpose, n=n, out=tuple(((size, *s), d) for s, d in out))
    return outs, [0] * len(outs)


_linear_p.def_impl(lambda *args, fn, transpose, n, out: list(fn(*_split(args, n))))
_linear_p.def_abstract_eval(_abstract)
mlir.register_lowering(_linear_p, _lower)
ad.primitive_jvps[_linear_p] = _jvp
ad.primitive_transposes[_linear_p] = _transpose
batching.primitive_batchers[_linear_p] = _batch
