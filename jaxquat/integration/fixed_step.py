"""The fixed-step driver: any diffrax solver stepped by ``lax.scan``, without ``diffeqsolve``.

``solve_fixed_steps`` is the fast path of :func:`jaxquat.simulate` for the splittings and the
rollout of :func:`jaxquat.minimum_time_reorientation`; ``scan_steps`` is its scan for any step
function (the struct-of-arrays Lie steps of ``simulate`` run on it). ``solve_fixed_steps``
drives the solver only through diffrax's public solver interface (``init`` once, then
``step``), so it serves every model and every fixed-step solver (the Lie solvers, the
splittings, diffrax's own). Against
``diffeqsolve`` with ``ConstantStepSize`` it drops the step-size controller, the event and
save bookkeeping and the while loop, which a reverse pass must otherwise checkpoint:
1.5x the throughput at 10^5 bodies (``docs/benchmarks.md``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array

from .. import _trig

__all__ = ["solve_fixed_steps"]

# Reverse mode stores one state per step. Past this many bytes per interval, the steps run in
# segments of about sqrt(substeps), each rematerialised (two-level checkpointing): XLA on CPU puts
# a program's temporaries in one buffer, and above glibc's 32 MiB mmap threshold that buffer is
# mapped afresh and faulted in at every call. Measured (simulate's scan path, 1000 RKMK4 steps,
# one core of this 2-core EPYC; docs/integrators.md, "Large batches on CPU"): the gradient at 1000
# bodies in float64 77-79 -> 60-62 ms (56 -> 4 MB of temporaries), at 10^4 bodies 773 -> 724 ms in
# float64 and 385-391 -> 309-389 ms in float32. Below it one pass more would cost more than it
# saves (1000 bodies, float32, 28 MB: 29 -> 30-31 ms). CPU only: a GPU has no such allocator.
_SEGMENT_BYTES = 32 * 2**20


def solve_fixed_steps(
    solver: diffrax.AbstractSolver,
    terms: diffrax.AbstractTerm,
    ts: Array,
    y0: Any,
    args: Any = None,
    *,
    substeps: int = 1,
    interval_args: Any = None,
    checkpoint: bool | Callable = True,
) -> Any:
    """The state at every ``ts``, each interval ``[ts[i], ts[i+1]]`` split into ``substeps``
    equal steps of ``solver``; returns ``y`` with a leading axis ``len(ts)`` (``ys[0] = y0``).

    ``interval_args``: a pytree whose leaves have a leading axis ``len(ts) - 1``; interval
    ``i`` sees ``args = interval_args[i]`` (a piecewise-constant control), and its first step is
    flagged ``made_jump`` so first-same-as-last solvers re-evaluate the vector field there.
    ``checkpoint``: rematerialise each step in the backward pass (``jax.checkpoint``), so
    reverse mode stores one state per step; a policy of ``jax.checkpoint_policies`` instead of
    ``True`` keeps the residuals it names as well. ``ts`` may be traced (only its values are used);
    ``substeps`` must be a Python int. Called outside ``jit`` it runs as one compiled program
    (``equinox.filter_jit``): the arrays of its arguments, the terms' and the solver's included,
    are the program's inputs and the rest is static, so a later call with arrays of the same
    shapes reuses it (a new vector-field function, or a Python number in ``args``, compiles
    again).

    Args:
        solver: any diffrax solver (a jaxquat Lie solver or splitting, or diffrax's own), driven
            through its ``init`` and ``step`` only.
        terms: the solver's terms, e.g. ``diffrax.ODETerm(RigidBody(inertia))``.
        ts: the times ``(n,)``, ``n >= 2``, increasing; the state is returned at each.
        y0: the state at ``ts[0]`` (any pytree).
        args: passed to the vector field (unless ``interval_args`` is given).
        substeps: equal solver steps per interval of ``ts``.
        interval_args: per-interval ``args``, leaves with a leading axis ``n - 1``.
        checkpoint: rematerialise each step in reverse mode (memory: one state per step);
            ``False`` stores every step's residuals; a ``jax.checkpoint_policies`` policy
            (e.g. ``jax.checkpoint_policies.dots_with_no_batch_dims_saveable``) stores those it
            saves.

    Returns:
        ``y0``'s pytree with a leading axis ``n`` on every leaf: the state at each of ``ts``.
    """
    if not isinstance(substeps, int) or substeps < 1:
        raise ValueError(f"argument 'substeps' must be a positive int, got {substeps!r}")
    ts = jnp.asarray(ts)
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"argument 'ts' must be shaped (n,) with n >= 2, got shape {tuple(ts.shape)}")
    return _compiled_steps(solver, terms, ts, y0, args, substeps, interval_args, checkpoint)


@eqx.filter_jit
def _compiled_steps(solver, terms, ts, y0, args, substeps: int, interval_args, checkpoint):
    """:func:`solve_fixed_steps` after its checks, as one compiled program: the arrays in its
    arguments (the terms' and the solver's too) are the program's inputs, everything else (the
    vector field's function, ``substeps``, ``checkpoint``) is static, so a second eager call with
    new arrays of the same shapes reuses the program. Called eagerly, the driver otherwise traced
    and compiled its scan at every call (a new closure each time) and ran the solver's ``init``
    op by op: a rigid body, 100 ``RKMK4`` steps, float64, one core of this 2-core CPU, three eager
    calls 0.71, 0.50 and 0.50 s, now 0.61, 0.001 and 0.001 s (the same states). Inside a
    caller's ``jit``, ``vmap`` or ``grad`` it is a nested ``jit``, traced into the caller's
    program."""
    if interval_args is not None:
        args = jax.tree.map(lambda x: x[0], interval_args)
    state = solver.init(terms, ts[0], ts[0] + (ts[1] - ts[0]) / substeps, y0, args)

    def step(carry, t0, t1, step_args, jump):
        y, s = carry
        y1, _, _, s1, _ = solver.step(terms, t0, t1, y, step_args, s, jump)
        return y1, s1

    return scan_steps(
        step,
        ts,
        (y0, state),
        args,
        substeps=substeps,
        interval_args=interval_args,
        checkpoint=checkpoint,
        saved=lambda carry: carry[0],
    )


def scan_steps(
    step: Callable,
    ts: Array,
    y0: Any,
    args: Any = None,
    *,
    substeps: int,
    interval_args: Any = None,
    checkpoint: bool | Callable = True,
    saved: Callable = lambda y: y,
) -> Any:
    """The ``lax.scan`` behind :func:`solve_fixed_steps`, for any step function
    ``step(y, t0, t1, args, jump) -> y`` on a pytree state: ``substeps`` equal steps per interval
    of ``ts``, the state at every ``ts`` stacked on a leading axis (``ys[0] = y0``). ``jump`` is
    True on each interval's first step when ``interval_args`` is given. ``checkpoint``:
    rematerialise each step in reverse mode (a ``jax.checkpoint_policies`` policy: keeping what
    it saves). ``saved(y)``: the part of the state kept at each
    of ``ts`` (all of it by default)."""
    if checkpoint is True:
        one_step = jax.checkpoint(step)
    elif callable(checkpoint):
        one_step = jax.checkpoint(step, policy=checkpoint)
    elif checkpoint is False:
        one_step = step
    else:
        raise TypeError(f"argument 'checkpoint' must be a bool or a jax.checkpoint_policies policy, got {checkpoint!r}")
    state_bytes = sum(jnp.size(x) * jnp.result_type(x).itemsize for x in jax.tree.leaves(y0))
    segment = segment_length(substeps, state_bytes) if checkpoint else 0

    def interval(carry, xs):
        t0, t1, step_args = xs
        step_args = args if interval_args is None else step_args
        h = (t1 - t0) / substeps

        def inner(c, k):
            jump = False if interval_args is None else k == 0
            return one_step(c, t0 + k * h, t0 + (k + 1) * h, step_args, jump), None

        if substeps == 1:  # no scan of length 1: each transform of a scan retraces its body
            carry, _ = inner(carry, jnp.zeros((), ts.dtype))
        elif segment:
            carry = _in_segments(inner, carry, jnp.arange(substeps, dtype=ts.dtype), segment)
        else:
            carry, _ = jax.lax.scan(inner, carry, jnp.arange(substeps, dtype=ts.dtype))
        return carry, saved(carry)

    # One interval (``ts`` of two times, as in a simulation saved only at its end): no scan of
    # length 1 around the steps' scan. Each transform of a scan traces its body again, so the
    # extra level cost reverse mode its tracing: the first optax Adam step through ``simulate``
    # (batch 1000, 1000 RKMK4 steps, float32, this 2-core CPU; before and after interleaved, three
    # fresh processes each) 1.78-2.11 s before, 1.53-1.60 s after (tracing and lowering 0.61-0.75
    # -> 0.40 s, XLA 1.08-1.25 -> 1.05-1.10 s); values and gradients bit-identical.
    if ts.shape[0] == 2:
        _, y1 = interval(y0, jax.tree.map(lambda x: x[0], (ts[:-1], ts[1:], interval_args)))
        ys = jax.tree.map(lambda a: jnp.asarray(a)[None], y1)
    else:
        _, ys = jax.lax.scan(interval, y0, (ts[:-1], ts[1:], interval_args))
    return jax.tree.map(lambda a, b: jnp.concatenate([jnp.asarray(a)[None], b]), saved(y0), ys)


def segment_length(substeps: int, state_bytes: int) -> int:
    """Steps per segment of an interval of ``substeps`` steps on a state of ``state_bytes``
    (:data:`_SEGMENT_BYTES`), 0 for none: about ``sqrt(substeps)``, so the states stored in reverse
    mode are the segments' starts plus one segment's steps."""
    if substeps > 1 and substeps * state_bytes > _SEGMENT_BYTES and _trig.is_cpu():
        return max(2, round(substeps**0.5))
    return 0


def _in_segments(inner: Callable, carry: Any, ks: Array, length: int) -> Any:
    """``lax.scan(inner, carry, ks)``'s final carry, the steps grouped in segments of ``length``
    (each rematerialised in reverse mode), the remainder after them."""
    whole = ks.shape[0] // length * length
    segment = jax.checkpoint(lambda c, kk: (jax.lax.scan(inner, c, kk)[0], None), prevent_cse=False)
    carry, _ = jax.lax.scan(segment, carry, ks[:whole].reshape(-1, length))
    if whole < ks.shape[0]:
        carry, _ = jax.lax.scan(inner, carry, ks[whole:])
    return carry
