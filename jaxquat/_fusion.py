"""One loop for many outputs on CPU: :func:`one_loop`, :func:`one_loop_backward`,
:func:`one_loop_both_ways`.

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
    the same for their tangents in forward mode. All of one shape."""
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


def _check(shapes) -> None:
    if len(set(shapes)) > 1:
        raise ValueError(f"one_loop: every array must have one shape, got shapes {sorted(set(shapes))}")


def _abstract(*avals, values: bool):
    del values
    return list(avals)


def _merged(*xs: Array) -> list[Array]:
    """A variadic ``reduce`` over a new last axis of ``(x, -0.0)``, one per floating dtype (XLA
    refuses a ``reduce`` of mixed precisions); other arrays pass as they are."""
    out = list(xs)
    nd = xs[0].ndim
    for dtype in dict.fromkeys(x.dtype for x in xs if jnp.issubdtype(x.dtype, jnp.floating)):
        idx = [i for i, x in enumerate(xs) if x.dtype == dtype]
        zero = jnp.array(-0.0, dtype)
        pads = [lax.pad(xs[i][..., None], zero, [(0, 0, 0)] * nd + [(0, 1, 0)]) for i in idx]
        summed = lax.reduce(pads, [zero] * len(idx), lambda a, b: tuple(u + v for u, v in zip(a, b)), (nd,))
        for i, y in zip(idx, summed):
            out[i] = y
    return out


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


def _partial_eval(trace, *tracers, values: bool):
    """``JaxprTrace`` (``linearize``): the known operands bound apart from the unknown ones."""
    known = [t.pval.is_known() for t in tracers]
    if all(known) or not any(known):
        return trace.default_process_primitive(_one_loop_p, tracers, dict(values=values))
    a, b = _parts(known, tracers)
    out_a = iter(trace.default_process_primitive(_one_loop_p, a, dict(values=values)))
    out_b = iter(trace.default_process_primitive(_one_loop_p, b, dict(values=values)))
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


def _batch(args, dims, *, values: bool):
    """Mapped and unmapped operands bound apart, so an unmapped value stays unmapped (``jacfwd``
    maps the tangents only)."""
    mapped = [d is not None for d in dims]
    a, b = _parts(mapped, [jnp.moveaxis(x, d, 0) if d is not None else x for x, d in zip(args, dims)])
    out_a = iter(_one_loop_p.bind(*a, values=values))
    out_b = iter(_one_loop_p.bind(*b, values=values) if b else [])
    return [next(out_a) if m else next(out_b) for m in mapped], [0 if m else None for m in mapped]


_one_loop_p.def_impl(lambda *xs, values: list(xs))
_one_loop_p.def_abstract_eval(_abstract)
mlir.register_lowering(_one_loop_p, _lower)
mlir.register_lowering(_one_loop_p, _lower_cpu, platform="cpu")
ad.primitive_jvps[_one_loop_p] = _jvp
ad.primitive_transposes[_one_loop_p] = _transpose
batching.primitive_batchers[_one_loop_p] = _batch
pe.custom_partial_eval_rules[_one_loop_p] = _partial_eval
pe.partial_eval_jaxpr_custom_rules[_one_loop_p] = _partial_eval_custom
pe.dce_rules[_one_loop_p] = _dce
