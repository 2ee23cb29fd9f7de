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
"""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
from jax import Array, lax
from jax.interpreters import ad, batching, mlir

try:  # jax >= 0.4.36; pyproject allows 0.4.30, where jax.core still held it
    from jax.extend.core import Primitive
except ImportError:  # pragma: no cover
    from jax.core import Primitive  # pyright: ignore[reportAttributeAccessIssue]

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
    cts = [ad.instantiate_zeros(c) for c in cts]
    return _one_loop_p.bind(*cts, values=not values)


def _batch(args, dims, *, values: bool):
    size = next(a.shape[d] for a, d in zip(args, dims) if d is not None)
    moved = [jnp.broadcast_to(a, (size, *a.shape)) if d is None else jnp.moveaxis(a, d, 0) for a, d in zip(args, dims)]
    return _one_loop_p.bind(*moved, values=values), [0] * len(moved)


_one_loop_p.def_impl(lambda *xs, values: list(xs))
_one_loop_p.def_abstract_eval(_abstract)
mlir.register_lowering(_one_loop_p, _lower)
mlir.register_lowering(_one_loop_p, _lower_cpu, platform="cpu")
ad.deflinear2(_one_loop_p, _transpose)
batching.primitive_batchers[_one_loop_p] = _batch
