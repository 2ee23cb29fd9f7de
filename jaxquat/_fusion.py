"""One loop for many outputs on CPU: :func:`one_loop`, :func:`one_loop_backward`,
:func:`one_loop_both_ways`; :func:`sums`, many sums over one axis in one loop;
:func:`spread`, many broadcasts along a new axis whose cotangents are those sums; and
:func:`fusible`, an identity that lets XLA fuse an expensive operation with several users.

XLA's CPU compiler (jaxlib 0.10.2, its defaults) gives every output array of an element-wise
computation a kernel of its own and copies into each kernel every producer it needs: a step
that ends in seven arrays (``simulate``'s struct-of-arrays RKMK4 step, ``(q, w_b)`` on
components) became seven loops, each evaluating most of the step again (3260 HLO operations in
the step's kernels). Its multi-output fusion is off by default and global when switched on (a
flag: session 41 measured a 98.9 s compile of one gradient with it). But one HLO operation
with many outputs is always one loop: a variadic ``reduce``. So :func:`one_loop` passes the
arrays through a ``reduce`` over a new axis of two, each array and a pad of ``-0.0`` (``x +
(-0.0) == x`` for every ``x``: signed zeros, infinities and NaN included), which XLA compiles
into one loop that evaluates the shared work once and writes every array.

Measured on ``simulate``'s scan path (1000 torque-free bodies x 1000 RKMK4 steps, float32,
one core of this 2-core EPYC, median of 7): the forward pass 26.8 -> 6.1 ms with the step's
outputs in one loop, and with its cotangents in one loop too, the gradient 70.8 -> 33.4 ms
(:mod:`jaxquat.integration.struct_of_arrays` has the figures of the final form).

A primitive of its own (``jax.extend.core.Primitive``, with the rules of
``jax.interpreters.ad``, ``batching`` and ``mlir``) rather than a function, for its
derivatives: it is linear (the identity), its tangent passes through the same kind and its
cotangent through the other. ``one_loop`` puts the values and the forward-mode tangents in one
loop, ``one_loop_backward`` the cotangents of reverse mode: the first on a step's outputs and
the second on its inputs, and the forward pass, a ``jvp`` and the backward pass of ``grad``
each end in one loop over the batch. A ``custom_jvp`` cannot give the cotangents a form of
their own, and ``jax.custom_derivatives.linear_call``, which can, has no ``vmap`` rule (jax
0.10.2). Elsewhere than on CPU (XLA's GPU compiler fuses multiple outputs itself) both lower
to the identity.

Under ``jvp`` a ``one_loop`` binds its values and their tangents together, so the loop that
computes the tangents (which needs the values' intermediates anyway) writes the values too,
instead of a second loop recomputing them: one ``jvp`` through the scan path (1000 bodies x
1000 RKMK4 steps, one core, median of 7, two runs) 15.3-15.8 -> 12.6-12.9 ms in float32,
torque-free, and 73.9-76.6 -> 62.3-64.1 ms in float64 with a PD torque. Where the two are
evaluated apart, the bind is split again: ``linearize`` (and so ``grad``) partially evaluates
the ``jvp`` with the values known and the tangents not, and remat (``jax.checkpoint``) does
the same through ``partial_eval_jaxpr_custom``; without the two rules below the values would
come out unknown and the transpose would fail (``tests/test_kernels.py`` runs both modes
mixed). ``vmap`` binds mapped and unmapped operands apart (``jacfwd`` maps only the tangents,
and its values must stay unmapped; binding all with the values broadcast, 3-column
``jacfwd`` took 36.9 against 34.1 ms). The rules use JAX's extension points for primitives
(``jax.interpreters.partial_eval``'s rule tables), not its private modules.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import jax.numpy as jnp
from jax import Array, lax
from jax.interpreters import ad, batching, mlir
from jax.interpreters import partial_eval as pe

try:  # jax >= 0.4.36; pyproject allows 0.4.30, where jax.core still held them
    from jax.extend.core import Literal, Primitive
except ImportError:  # pragma: no cover
    from jax.core import Literal, Primitive  # pyright: ignore[reportAttributeAccessIssue]

_one_loop_p = Primitive("jaxquat_one_loop")
_one_loop_p.multiple_results = True


def one_loop(xs: Sequence[Array]) -> tuple[Array, ...]:
    """``xs`` unchanged, computed on CPU in one XLA loop (with any element-wise work they share);
    the same for their tangents in forward mode. All of one shape; floating arrays in one loop per
    dtype, integer and boolean ones (no tangents) in one loop per dtype of their own."""
    _check([jnp.shape(x) for x in xs])
    return tuple(_one_loop_p.bind(*xs, values=True))


def one_loop_backward(xs: Sequence[Array]) -> tuple[Array, ...]:
    """``xs`` unchanged; in reverse mode their cotangents are computed on CPU in one XLA loop.
    All of one shape."""
    _check([jnp.shape(x) for x in xs])
    return tuple(_one_loop_p.bind(*xs, values=False))


def one_loop_both_ways(xs: Sequence[Array]) -> tuple[Array, ...]:
    """``xs`` unchanged: their values and tangents in one loop (:func:`one_loop`), and their
    cotangents in one loop (:func:`one_loop_backward`)."""
    return one_loop_backward(one_loop(xs))


def fusible(x: Array) -> Array:
    """``x`` unchanged (``lax.reduce_precision`` to ``x``'s own format, which rounds nothing), as
    the one user of the expensive operation that made it, so that XLA fuses that operation into
    the loop of its consumers.

    Why: XLA's CPU compiler with its fusion emitters (jaxlib 0.10.2's default) does not duplicate
    an expensive producer (a floating division, a square root, a transcendental) and leaves one
    with several users out of its consumers' loop, even when all those users end up in the same
    loop: a kernel of its own, writing an array that the next kernel reads back (``a / b``
    feeding three outputs of one :func:`one_loop` compiled as two kernels; the older emitters,
    which the test suite runs, fuse it). After ``fusible`` the operation has one user, and the
    reduction to the same precision is cheap, so XLA copies it into each consumer: where those
    are one loop, the operation is computed there once; where they are several loops, the
    operation is left out as before. A chain of cheap operations that several loops read, which
    XLA had made a kernel of its own, ending in ``fusible`` is copied into each of those loops
    instead (the scan path's rematerialised step: ``integration.struct_of_arrays._recomputed``).
    XLA keeps the ``reduce_precision`` (``tests/test_kernels.py`` checks that the division above
    is fused, which would fail if a later XLA dropped it).
    Non-floating arrays are returned as they are. Its derivatives are the same identity on the
    tangent and the cotangent.

    Measured on ``simulate``'s default path (the closed form, 1000 bodies x 101 saved times,
    float32, jaxlib 0.10.2, a 2-core AMD EPYC), with the per-body quantities, the unit pairs, the
    minimal rotation, the AGM and Carlson steps and ``atan2``'s ratio through it (session 65):
    the forward program 71 -> 47 compiled kernels, the first eager call 1.42 -> 1.12-1.25 s (XLA
    1.07 -> 0.79-0.89 s; three fresh processes each, alternated); later calls on one core
    15.6-16.8 -> 14.3-14.5 ms, one ``jvp`` 25.5-26.0 -> 22.6-22.9 ms, the gradient 77-80 -> 76-77
    ms (float64, three runs: 39.0-40.7 -> 38.6-39.5, 80-83 -> 72-79 and 184-200 -> 172-180 ms).
    The gradient's program 197 -> 187 kernels; its first call (one Adam step) 3.54-3.69 ->
    3.35-3.60 s (three processes each, alternated, in a quiet hour). The same identity after every
    division, square root and transcendental of the whole program (a probe that patched JAX's
    primitives) reached 46 and 183 kernels; ``simulate``'s scan path and the optimal-control solvers' first calls did
    not change under that probe (their kernels have no expensive operation with several users)."""
    dtype = jnp.result_type(x)
    if not jnp.issubdtype(dtype, jnp.floating):
        return x
    info = jnp.finfo(dtype)
    return lax.reduce_precision(x, exponent_bits=info.nexp, mantissa_bits=info.nmant)


def _check(shapes, name: str = "one_loop") -> None:
    if len(set(shapes)) > 1:
        raise ValueError(f"{name}: every array must have one shape, got shapes {sorted(set(shapes))}")


def _abstract(*avals, values: bool):
    del values
    return list(avals)


def _merged(*xs: Array) -> list[Array]:
    """A variadic ``reduce`` over a new last axis of ``(x, pad)``, one per dtype (XLA refuses a
    ``reduce`` of mixed types): the pad ``-0.0`` for floating arrays, ``0`` for integers and
    ``False`` for booleans (combined by ``or``), each of which leaves ``x`` unchanged. Arrays whose
    last axis is shorter than ``_SHORT_BELOW`` pass with their last two axes swapped (a transpose
    that XLA fuses into the loop's reads and writes), so the loop is vectorised along the longer
    axis (the constant has why)."""
    out = list(xs)
    shape = xs[0].shape
    swap = len(shape) > 1 and shape[-1] < _SHORT_BELOW
    for kind, pad, combine in _PADS:
        idx = [i for i, x in enumerate(xs) if jnp.issubdtype(x.dtype, kind)]
        parts = [jnp.swapaxes(xs[i], -1, -2) if swap else xs[i] for i in idx]
        pads = [lax.pad(x[..., None], jnp.array(pad, x.dtype), [(0, 0, 0)] * x.ndim + [(0, 1, 0)]) for x in parts]
        for i, y in zip(idx, _reduce_by_dtype(pads, len(shape), pad, combine)):
            out[i] = jnp.swapaxes(y, -1, -2) if swap else y
    return out


# Arrays whose last axis is shorter than this pass through one_loop's reduce with their last two
# axes swapped. XLA's CPU loop emitter vectorises a reduce's output along its last axis only: on a
# (10^5, 2) array (10^5 bodies at 2 saved times) the loop ran a vector lane or two wide. Session 83
# flattened such arrays instead (elliptic.rd's 16-step loop over (10^5, 2) 15.2 -> 2.9 ms, one core
# of a 2-core AMD EPYC with AVX-512, float32; carlson's 90 -> 13 ms; simulate's closed form at 10^5
# bodies x 2 times, one jvp 126-140 -> 115-119 ms and the gradient 182-191 -> 167-179 ms). But a
# flattened loop reads an operand broadcast along the times (a per-body quantity) at index i // 2,
# and under jacfwd one broadcast along the columns at i % (2 x 10^5): LLVM vectorised none of the
# closed form's 3-column kernels that read one. Swapped, such an operand is read along the loop (per
# body) or held for it (per time or per column). Session 84, the same machine, simulate's closed
# form (benchmarks/simulation.py's loss, float32, one core, least of 7 or 20, two processes each at
# 10^5 and 1000 bodies, one at 2 x 10^4), flattened -> swapped, forward / grad / jvp / 3-column
# jacfwd: 10^5 bodies x 2 times 55.0-59.5 / 108-114 / 84-87 / 133-134 -> 48.7-51.5 / 103-108 / 71-73
# / 97-101 ms; 2 x 10^4 x 2 10.6 / 19.2 / 15.3 / 24.7 -> 9.3 / 18.3 / 13.4 / 17.0 ms, x 3 times 11.0
# / 23.5 / 16.2 / 27.5 -> 10.2 / 21.3 / 14.4 / 20.5 ms; 1000 x 2 0.55 / 0.74-0.78 / 0.77-0.79 /
# 1.13-1.18 -> 0.47-0.49 / 0.68-0.73 / 0.62-0.66 / 0.78-0.82 ms; float64 at 10^5 x 2 135-139 /
# 231-234 / - / 265-269 -> 128-134 / 229-231 / - / 241-249 ms. The programs have 0-3 more fusions
# (the transposes fuse into the loops); compiling at 1000 x 2 took 1.22-1.35 -> 1.34-1.39 s forward,
# 3.07-3.50 -> 3.08-3.54 s for the jacfwd. Arrays whose last axis is 4 or more are reduced in their
# own shape, as before.
_SHORT_BELOW = 4


def _identity(*xs: Array) -> list[Array]:
    return list(xs)


def _lower_cpu(ctx, *xs, values: bool):
    return mlir.lower_fun(_merged if values else _identity, multiple_results=True)(ctx, *xs)


def _lower(ctx, *xs, values: bool):
    del values
    return mlir.lower_fun(_identity, multiple_results=True)(ctx, *xs)


def _transpose(cts, *xs, values: bool):
    linear = [ad.is_undefined_primal(x) for x in xs]
    cts = [ad.instantiate_zeros(c) for c, lin in zip(cts, linear) if lin]
    out = iter(_one_loop_p.bind(*cts, values=not values))
    return [next(out) if lin else None for lin in linear]


def _jvp(primals, tangents, *, values: bool):
    """Values and their nonzero tangents in one bind (one loop on CPU); the partial-evaluation rules
    below split it again wherever the two are evaluated apart (``linearize``, ``grad``, remat)."""
    nonzero = [type(t) is not ad.Zero for t in tangents]
    given = [t for t, nz in zip(tangents, nonzero) if nz]
    if values:
        outs = _one_loop_p.bind(*primals, *given, values=True)
        out, rest = list(outs[: len(primals)]), iter(outs[len(primals) :])
    else:
        out = _one_loop_p.bind(*primals, values=False)
        rest = iter(_one_loop_p.bind(*given, values=False) if given else [])
    return out, [next(rest) if nz else t for t, nz in zip(tangents, nonzero)]


def _parts(flags, xs):
    return [x for x, f in zip(xs, flags) if f], [x for x, f in zip(xs, flags) if not f]


def _partial_eval(primitive, trace, *tracers, **params):
    """``JaxprTrace`` (``linearize``): the known operands bound apart from the unknown ones (each
    output of these primitives is a function of its own operand alone)."""
    known = [t.pval.is_known() for t in tracers]
    if all(known) or not any(known):
        return trace.default_process_primitive(primitive, tracers, params)
    a, b = _parts(known, tracers)
    out_a = iter(trace.default_process_primitive(primitive, a, params))
    out_b = iter(trace.default_process_primitive(primitive, b, params))
    return [next(out_a) if k else next(out_b) for k in known]


def _partial_eval_custom(saveable, unks_in, inst_in, eqn):
    """``partial_eval_jaxpr_custom`` (remat): the known operands are bound on the known side and
    recomputed on the staged side (the values pass unchanged, so recomputing costs a copy), the
    unknown ones staged."""
    del saveable
    if all(unks_in):
        return None, eqn, [True] * len(unks_in), [True] * len(unks_in), []
    known = [not u for u in unks_in]
    ins, _ = _parts(known, eqn.invars)
    outs, _ = _parts(known, eqn.outvars)
    eqn_known = eqn.replace(invars=ins, outvars=outs)
    residuals = [v for v, k, inst in zip(eqn.invars, known, inst_in) if k and not inst and not isinstance(v, Literal)]
    return eqn_known, eqn, list(unks_in), [True] * len(unks_in), residuals


def _dce(used_outs, eqn):
    if not any(used_outs):
        return [False] * len(used_outs), None
    ins, _ = _parts(used_outs, eqn.invars)
    outs, _ = _parts(used_outs, eqn.outvars)
    return list(used_outs), eqn.replace(invars=ins, outvars=outs)


def _bind_apart(primitive, args, dims, mapped_params: dict, unmapped_params: dict):
    """A batching rule's bind: the mapped operands (their axis moved first) and the unmapped ones
    bound apart, so an unmapped value stays unmapped (``jacfwd`` maps the tangents only)."""
    mapped = [d is not None for d in dims]
    a, b = _parts(mapped, [jnp.moveaxis(x, d, 0) if d is not None else x for x, d in zip(args, dims)])
    out_a = iter(primitive.bind(*a, **mapped_params))
    out_b = iter(primitive.bind(*b, **unmapped_params) if b else [])
    return [next(out_a) if m else next(out_b) for m in mapped], [0 if m else None for m in mapped]


def _batch(args, dims, *, values: bool):
    return _bind_apart(_one_loop_p, args, dims, dict(values=values), dict(values=values))


def _register(primitive, impl, abstract, lower, lower_cpu, jvp, transpose, batch) -> None:
    """The rules of a primitive of this module (the partial-evaluation ones shared)."""
    primitive.def_impl(impl)
    primitive.def_abstract_eval(abstract)
    mlir.register_lowering(primitive, lower)
    mlir.register_lowering(primitive, lower_cpu, platform="cpu")
    ad.primitive_jvps[primitive] = jvp
    ad.primitive_transposes[primitive] = transpose
    batching.primitive_batchers[primitive] = batch
    pe.custom_partial_eval_rules[primitive] = functools.partial(_partial_eval, primitive)
    pe.partial_eval_jaxpr_custom_rules[primitive] = _partial_eval_custom
    pe.dce_rules[primitive] = _dce


_register(_one_loop_p, lambda *xs, values: list(xs), _abstract, _lower, _lower_cpu, _jvp, _transpose, _batch)


# Many sums over one axis in one loop ----------------------------------------------------------

_sums_p = Primitive("jaxquat_sums")
_sums_p.multiple_results = True


def sums(xs: Sequence[Array], axis: int) -> tuple[Array, ...]:
    """``jnp.sum(x, axis)`` of each of ``xs`` (broadcast to one shape), computed on CPU in one
    loop: a variadic ``reduce`` (one per dtype), which reads the arrays once and takes
    with it the element-wise work that forms them. A linear primitive: its tangent is itself, its
    cotangent each cotangent broadcast back along ``axis``. Elsewhere than on CPU, one ``reduce``
    per array (XLA's GPU compiler fuses sibling reductions itself).

    Why: the nine sums of Davenport's ``B = sum_n w_n a_n b_n^T`` over 10^6 vector pairs
    (:func:`jaxquat._arrays.outer_sum`; one core of this 2-core EPYC, least of 9 runs) took 9.3 ms
    in float32 and 10.4 ms in float64 as an ``einsum`` (XLA on CPU ran it as a matrix product
    with an inner dimension of 10^6), 4.2 and 28 ms as nine ``jnp.sum`` (nine loops, or one,
    as XLA's fusion chose by dtype), 1.5 and 1.7 ms as this loop.

    Where the summed axis is longer than 1024 it is summed in rows of about its square root
    (zero-padded), then the rows' sums: XLA on CPU adds a many-operand ``reduce`` in order, and
    ``mean``'s ten sums over 2^20 float32 quaternions were 3.8e-4 off the exact sums (relative to
    the largest) in one row, 7.1e-7 in rows of 1024 (an ``einsum``'s 2.7e-7), in the same time."""
    arrays = jnp.broadcast_arrays(*xs)
    ndim = arrays[0].ndim
    if not -ndim <= axis < ndim:
        raise ValueError(f"sums: axis {axis} out of range for arrays of {ndim} dimensions")
    return tuple(_sums_p.bind(*arrays, axis=axis % ndim))


def _sums_abstract(*avals, axis: int):
    return [a.update(shape=a.shape[:axis] + a.shape[axis + 1 :]) for a in avals]


def _sums_one_loop(*xs: Array, axis: int) -> list[Array]:
    """The sums as variadic ``reduce``s, one per dtype; past 1024 elements in rows (:func:`sums`)."""
    length = xs[0].shape[axis]
    if length <= 1024:
        return _reduce_by_dtype(xs, axis)
    row = 2 ** ((length - 1).bit_length() + 1 >> 1)
    rows = -(-length // row)
    pad = [(0, 0, 0)] * axis + [(0, rows * row - length, 0)] + [(0, 0, 0)] * (xs[0].ndim - axis - 1)
    shape = xs[0].shape[:axis] + (rows, row) + xs[0].shape[axis + 1 :]
    blocks = [lax.pad(x, jnp.array(0, x.dtype), pad).reshape(shape) for x in xs]
    return _reduce_by_dtype(_reduce_by_dtype(blocks, axis + 1), axis)


def _add_pairs(a, b):
    return tuple(u + v for u, v in zip(a, b))


def _or_pairs(a, b):
    return tuple(u | v for u, v in zip(a, b))


# (dtype kind, the pad that leaves an element unchanged, how a reduce combines two) for _merged.
_PADS = ((jnp.floating, -0.0, _add_pairs), (jnp.integer, 0, _add_pairs), (jnp.bool_, False, _or_pairs))


def _reduce_by_dtype(xs: Sequence[Array], axis: int, init: float = 0.0, combine=_add_pairs) -> list[Array]:
    """The reductions of ``xs`` over ``axis`` from ``init`` by ``combine`` (sums by default), as
    one variadic ``reduce`` per dtype (XLA refuses a ``reduce`` of mixed precisions)."""
    out = list(xs)
    for dtype in dict.fromkeys(x.dtype for x in xs):
        idx = [i for i, x in enumerate(xs) if x.dtype == dtype]
        # The start passes an optimization barrier: with every operand a constant (arrays a user's
        # jit closes over), XLA would evaluate the reduce while compiling, and its size guard
        # skips a variadic reduce (a tuple): one_loop of ten entries of 10^5 constant rows took
        # 2.3 s to fold (4.7 s in euler_parameter_augmented_system's gradient), 0.26 s now.
        start = lax.optimization_barrier(jnp.array(init, dtype))
        summed = lax.reduce([xs[i] for i in idx], [start] * len(idx), combine, (axis,))
        for i, y in zip(idx, summed):
            out[i] = y
    return out


def _sums_apart(*xs: Array, axis: int) -> list[Array]:
    return [jnp.sum(x, axis=axis) for x in xs]


def _sums_jvp(primals, tangents, *, axis: int):
    """The values and the nonzero tangents summed in one bind (one loop reads both); the
    partial-evaluation rules split it again where they are evaluated apart (as for ``one_loop``)."""
    nonzero = [type(t) is not ad.Zero for t in tangents]
    outs = _sums_p.bind(*primals, *[t for t, nz in zip(tangents, nonzero) if nz], axis=axis)
    out, given = list(outs[: len(primals)]), iter(outs[len(primals) :])
    return out, [
        next(given) if nz else ad.Zero(_sums_abstract(t.aval, axis=axis)[0]) for t, nz in zip(tangents, nonzero)
    ]


def _sums_transpose(cts, *xs, axis: int):
    out = []
    for ct, x in zip(cts, xs):
        if not ad.is_undefined_primal(x):
            out.append(None)
        elif type(ct) is ad.Zero:
            out.append(ad.Zero(x.aval))
        else:
            shape = x.aval.shape
            out.append(lax.broadcast_in_dim(ct, shape, tuple(d for d in range(len(shape)) if d != axis)))
    return out


def _sums_batch(args, dims, *, axis: int):
    return _bind_apart(_sums_p, args, dims, dict(axis=axis + 1), dict(axis=axis))


_register(
    _sums_p,
    lambda *xs, axis: _sums_apart(*xs, axis=axis),
    _sums_abstract,
    mlir.lower_fun(_sums_apart, multiple_results=True),
    mlir.lower_fun(_sums_one_loop, multiple_results=True),
    _sums_jvp,
    _sums_transpose,
    _sums_batch,
)


# Many broadcasts along a new last axis, their cotangents summed in one loop -------------------

_spread_p = Primitive("jaxquat_spread")
_spread_p.multiple_results = True


def spread(xs: Sequence[Array], length: int) -> tuple[Array, ...]:
    """Each of ``xs`` (all of one shape) broadcast along a new last axis of ``length``: the
    values as ``jnp.broadcast_to(x[..., None], x.shape + (length,))``, and in reverse mode the
    cotangents summed back over that axis by :func:`sums`, in one loop instead of one reduction
    (one kernel) each. A linear primitive: its tangent is itself.

    Why: the closed-form torque-free solution broadcasts 44 per-body arrays to every saved time
    (``jaxquat.mechanics.torque_free._Motion.at_times``), and reverse mode summed each cotangent
    in a reduction of its own: ``simulate``'s default gradient program (1000 bodies x 101 times)
    had 413 fusions, 338 with this (``_Motion.at_times`` has the times; session 60)."""
    _check([jnp.shape(x) for x in xs], "spread")
    return tuple(_spread_p.bind(*xs, length=length))


def _spread_abstract(*avals, length: int):
    return [a.update(shape=a.shape + (length,)) for a in avals]


def _spread_apart(*xs: Array, length: int) -> list[Array]:
    return [jnp.broadcast_to(x[..., None], x.shape + (length,)) for x in xs]


def _spread_jvp(primals, tangents, *, length: int):
    nonzero = [type(t) is not ad.Zero for t in tangents]
    given = iter(_spread_p.bind(*[t for t, nz in zip(tangents, nonzero) if nz], length=length) if any(nonzero) else [])
    zeros = [ad.Zero(a) for a in _spread_abstract(*(t.aval for t in tangents), length=length)]
    return _spread_p.bind(*primals, length=length), [next(given) if nz else z for nz, z in zip(nonzero, zeros)]


def _spread_transpose(cts, *xs, length: int):
    linear = [ad.is_undefined_primal(x) for x in xs]
    cts = [ad.instantiate_zeros(c) for c, lin in zip(cts, linear) if lin]
    out = iter(_sums_p.bind(*cts, axis=cts[0].ndim - 1) if cts else [])
    return [next(out) if lin else None for lin in linear]


def _spread_batch(args, dims, *, length: int):
    return _bind_apart(_spread_p, args, dims, dict(length=length), dict(length=length))


_spread_lowering = mlir.lower_fun(_spread_apart, multiple_results=True)
_register(
    _spread_p,
    lambda *xs, length: _spread_apart(*xs, length=length),
    _spread_abstract,
    _spread_lowering,
    _spread_lowering,
    _spread_jvp,
    _spread_transpose,
    _spread_batch,
)
