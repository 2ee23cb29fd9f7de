"""The numerical paths of :func:`jaxquat.simulate`: ``diffeqsolve`` with a Lie or diffrax solver,
the fixed-step scan (struct-of-arrays for ``LieEuler`` and the RKMK tableaus, the solver's own
step otherwise), and the batch in chunks on CPU.

Imported by ``simulate`` on its first numerical solve, not with it: the default torque-free path
(the closed form) needs neither diffrax nor equinox, whose import took 0.35 s of a first call
(this 2-core EPYC; ``docs/benchmarks.md``, session 57)."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.custom_derivatives import SymbolicZero

from .. import _checks, _threads, _trig
from .._threads import at_top_level, cpu_compiler_options, in_shard_map, split_across_devices
from ..mechanics.rigid_body import RigidBody
from ..mechanics.torques import as_body_torque
from . import fixed_step, principal_frame, struct_of_arrays
from .fixed_step import solve_fixed_steps
from .lie_solvers import RKMK45, AbstractLieSolver, AbstractRKMK, BodyRateTerm, LieEuler
from .splitting import AbstractSplitting, EulerPoinsotSplit

__all__ = ["Config", "configure", "solve"]

# The default adjoint's checkpoints per body. Diffrax's own default is O(sqrt(2 max_steps)), 446
# for max_steps=100_000, and each body of the adaptive path's vmap holds its own: their cost
# comes per solve, whatever the number of steps taken. The gradient of 1000 bodies under the PD
# torque for 10 s (55 steps at most in float32, 173 in float64; one core of a 2-core EPYC) took
# 118 ms in float32 and 294 ms in float64 with 446, 57 ms and 232 ms with 64 (16: 58 / 280,
# 32: 57 / 222, 128: 75 / 267, 256: 106 / 295); at 10^4 bodies 1657 ms (1.71 GB peak) and
# 5171 ms (2.21 GB) with 446, 1073 ms (1.09 GB) and 4667 ms (1.18 GB) with 64. Up to
# (64 + 1)(64 + 2)/2 = 2145 steps equinox's online checkpointing recomputes optimally (its bound,
# after Stumm and Walther): 200 s of the PD law plus a sinusoid at 100 bodies, 1754 steps, took
# 367 ms with 446, 375 ms with 64 and 611 ms with 32. Longer solves recompute more than with 446.
_CHECKPOINTS = 64

# The scan path's chunks on CPU: at most this many bytes per component array of a chunk of
# bodies (20 000 bodies in float32, 10 000 in float64), solved one chunk after another
# (_in_chunks). 10^5 torque-free bodies x 1000 RKMK4 steps, one core of this 2-core EPYC, median
# of 3, the gradient (and its peak memory) whole -> in chunks: float32 4103 -> 3639 ms (3.16 ->
# 1.00 GB), float64 11844 -> 6920 ms (5.95 -> 1.03 GB); the forward pass 561 -> 548 ms and
# 1393 -> 1521 ms. Smaller chunks were faster on one core (float32, 2000 bodies: 3006 ms) but
# slower on two, where XLA splits each loop of a step between the threads (the forward pass
# 350 -> 700 ms; 20 000 bodies: 374 ms).
_CHUNK_BYTES = 80_000

# The scan path's chunks on CPU for derivatives (forward and reverse mode): at most this many
# bodies, either dtype; the values keep _CHUNK_BYTES' chunks (_derivatives_in_smaller_chunks). A
# derivative holds more arrays per body than the values (the tangents or cotangents beside the
# states), which overflowed the core's cache at the values' chunks. 10^5 torque-free bodies x 1000
# RKMK4 steps, one core of a 2-core Intel Xeon (2 MiB of L2 per core), least of 3, the whole solve
# in chunks of 20 000 -> 2000 float32 bodies: gradient 5123 -> 2697 ms, one jvp 2542 -> 1241 ms,
# jacfwd with 3 columns 6747 -> 3217 ms (5000: 3794 and 1534 ms; 1000: 3003, 1275 and 3274 ms);
# float64, 10 000 -> 2000: 9213 -> 5470 ms and 4737 -> 2494 ms; at 10^4 float32 bodies (one chunk
# before) 386 -> 269 ms and 175 -> 124 ms. Through _derivatives_in_smaller_chunks (values in the
# larger chunks): float32 2718-2766, 1285 and 3468 ms, float64 5824 and 2659 ms. The forward pass
# takes 607 ms (1324 ms in float64).
# On both cores (XLA splitting each loop between two threads) about even: float32 gradient 4957 ->
# 4784 ms and jvp 2036 -> 2166 ms, float64 8544 -> 7837 ms and 3648 -> 2797 ms. The values in
# chunks of 2000 as well cost the forward pass on both cores (float32 684 -> 1245 ms).
_DERIVATIVE_CHUNK = 2000

# The same where XLA's pool has more than one thread (_threads.pool_threads), which splits each
# loop of a step between them: larger chunks make fewer, longer kernels to split. Session 76, the
# same kind of Xeon, 10^5 torque-free bodies x 1000 RKMK4 steps, least of 3, derivative chunks of
# 2000 -> 10 000 bodies: on both cores float32 gradient 4917-4954 -> 2979 ms, one jvp 2309-2376 ->
# 1290 ms (5000: 3586 and 1609 ms; 20 000: 3229-3317 and 1313-1360 ms), float64 7399 -> 6765 ms
# and 3372 -> 2678 ms; on one pinned core float32 2846 -> 2961 ms and 1354 -> 1525 ms (so 2000
# stays for one thread). With a torque (_TORQUE_CHUNK) chunks of 10 000 cost the forward pass on
# both cores 2665 -> 4619 ms for the same gradient (12424 -> 12515 ms): not there.
_DERIVATIVE_CHUNK_THREADS = 10_000

# The scan path's chunks on CPU with a torque, values and derivatives: at most this many bodies.
# The loops around the torque (struct_of_arrays.EulerEquations) hold more arrays per body than the
# torque-free step, and the values' chunks overflowed the cache as the derivatives' did. 10^5
# bodies under benchmarks/simulation.py's PD law x 1000 RKMK4 steps, the same Intel Xeon, least of
# 3, chunks of 20 000 -> 2000 float32 bodies: forward 2991-3053 -> 1450 ms on one core and 4161 ->
# 2370 ms on both; float64, 10 000 -> 2000: 4770 -> 3021 ms and 6859 -> 3708 ms.
_TORQUE_CHUNK = 2000

# The scan path's chunks on CPU inside a jax.shard_map (each device solving its own shard): this
# many bodies, either dtype. There a device's loops are best kept on one thread (cpu_compiler_options
# with devices > 1), where small chunks win, as they did on one core above. 10^5 torque-free
# bodies x 1000 RKMK4 steps, shard_map over 2 CPU devices of this 2-core EPYC, the pass off, min
# of 3, chunks of 20 000 / 4000 / 2000 / 1000 float32 bodies: forward 293 / 368 / 294 / 317 ms,
# gradient 1821 / 1871 / 1264 / 1501 ms; float64, 10 000 / 2000 / 1000: 620 / 593 / 611 ms and
# 3166 / 2471 / 2536 ms. With XLA's default threads, 20 000 float32 bodies: 2283 and 9261 ms.
_SHARD_MAP_CHUNK = 2000

# The adaptive path's chunks on CPU: at most this many bodies, whose vmapped solves run one chunk
# after another, so that a chunk's arrays stay in cache. 10^4 bodies under the PD torque of
# benchmarks/simulation.py for 10 s, one core of this 2-core EPYC, median of 3, whole -> in
# chunks: float32 forward 79.4 -> 53.5 ms, gradient 723 -> 376 ms; float64 297 -> 217 ms and
# 3373 -> 1703 ms. On two cores (float32, chunks made outside simulate, two runs each) the
# gradient 529-583 -> 304-310 ms, with chunks of 2500 378-383 ms. At 1000 bodies smaller chunks
# gained nothing (one core, float32: 36.0 ms whole, 37.4-38.4 ms in chunks of 100-500). Not
# rematerialised: diffrax's checkpoints are small, and recomputing each chunk cost 12 % more.
_ADAPTIVE_CHUNK = 1000


class Config(NamedTuple):
    """Everything :func:`simulate` decided before solving (static under ``eqx.filter_jit``)."""

    solver: Any
    torque: Callable | None
    torque_frame: str
    principal: bool
    substeps: int | None
    diagonal: bool  # a concrete diagonal tensor (the struct-of-arrays step reads its diagonal only)
    exact: bool
    rtol: float
    atol: float
    max_steps: int
    adjoint: Any
    progress: bool
    # the most bodies per chunk (_in_chunks): the scan path's values, its derivatives, the adaptive path's
    chunks: tuple[int, int, int]
    # the chunks' sizes (and a batch of one chunk) padded to a multiple of this (_threads.batch_multiple)
    multiple: int


def solve(cfg: Config, q0, omega0, inertia, shared_inertia, ts, args, dt0) -> tuple[Array, Array, Any]:
    """The solve behind :func:`simulate`, compiled as one program: called eagerly, the solve
    used to dispatch (and compile) every array operation around ``diffeqsolve`` or the scan on
    its own (the suite's ``test_integrators.py``: 1092 compilations of single operations, 31 s;
    repeated eager calls 0.1-0.8 s each, now microseconds after the first).

    Called eagerly, the program is compiled with :func:`jaxquat.cpu_compiler_options` (on the CPU,
    a float32 batch of up to 1024 bodies: each loop on one thread, which XLA would split between
    threads at a loss; ``jaxquat._threads``). Inside a caller's ``jit``, ``vmap`` or ``grad`` it
    is a plain nested ``jit`` (JAX takes compiler options on a top-level program only): the
    caller's own options decide."""
    arrays = (q0, omega0, inertia, shared_inertia, ts, args, dt0)
    options = cpu_compiler_options(math.prod(q0.shape[:-1]), q0.dtype)
    if options and at_top_level():
        return _one_thread_solve(tuple(sorted(options.items())))(cfg, *arrays)
    return _solve(cfg, *arrays)


@functools.cache
def _one_thread_solve(options: tuple) -> Callable:
    """:func:`solve`'s program compiled with ``options`` (``jax.jit``'s ``compiler_options`` as
    sorted pairs), made on first use and kept."""
    # equinox passes jax.jit's keyword arguments on, though its typed overloads do not list them
    return eqx.filter_jit(_solve_body, compiler_options=dict(options))  # pyright: ignore[reportCallIssue]


def _solve_body(cfg: Config, q0, omega0, inertia, shared_inertia, ts, args, dt0) -> tuple[Array, Array, Any]:
    """:func:`solve`'s program."""
    solver, torque, torque_frame, principal = cfg.solver, cfg.torque, cfg.torque_frame, cfg.principal
    substeps, diagonal, exact, progress = cfg.substeps, cfg.diagonal, cfg.exact, cfg.progress
    rtol, atol, max_steps, adjoint = cfg.rtol, cfg.atol, cfg.max_steps, cfg.adjoint
    # not padded where the batch is split between devices (an Explicit mesh): each device's share is
    # its own, and the concatenation would move bodies between devices
    multiple = 1 if split_across_devices(q0) or split_across_devices(omega0) else cfg.multiple
    adaptive = _has_error_estimate(solver)
    if exact:
        controller = diffrax.StepTo(ts)
    elif adaptive:
        controller = diffrax.ClipStepSizeController(diffrax.PIDController(rtol=rtol, atol=atol), step_ts=ts)
    else:
        controller = diffrax.ConstantStepSize()
    meter = diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter()
    batch = q0.shape[:-1]
    inertia = jnp.broadcast_to(inertia, batch + inertia.shape[-2:])  # simulate passes a shared (3, 3) as it is
    per_body_field = bool(batch) and not adaptive and not isinstance(solver, AbstractSplitting)

    tableau = None if substeps is None else _component_tableau(solver)

    def one_solve(q, w, inertia_1, torque_fn):
        """One solve of a body, or of a whole batch stacked on the leading axis."""
        if tableau is not None and substeps is not None:  # the Lie solvers' scan path, struct-of-arrays form
            # a batch's torque law per body, vmapped over the last axis of the components stacked
            # along the first (EulerEquations' columns); one body's on its rows
            body_torque = None if torque is None else as_body_torque(torque, torque_frame)
            if body_torque is not None and batch:
                body_torque = jax.vmap(body_torque, in_axes=(None, -1, -1, None), out_axes=-1)
            euler = struct_of_arrays.EulerEquations(inertia_1, body_torque, diagonal, columns=bool(batch))
            qs, ws = struct_of_arrays.solve(tableau, euler, ts, q, w, args, substeps)
            return qs, ws, None
        if principal:  # the splittings work in principal axes: rotate there and back
            moments, q_axes, r, q, w = principal_frame.to_principal(inertia_1, q, w)
            inertia_1 = moments[..., None] * jnp.broadcast_to(jnp.eye(3, dtype=moments.dtype), moments.shape + (3,))
        if isinstance(solver, AbstractSplitting):  # the splittings read the RigidBody itself
            term = diffrax.ODETerm(RigidBody(inertia_1, torque_fn, torque_frame))
        else:  # on the scan path in the Lie-algebra form (the body rate on q: no conversion)
            field = _Field(
                inertia_1,
                torque if per_body_field else torque_fn,
                torque_frame,
                per_body_field,
                rates=substeps is not None,
            )
            term = (diffrax.ODETerm if substeps is None else BodyRateTerm)(field)
        if substeps is not None:  # the fixed-step scan driver: the time axis first, as diffrax's
            qs, ws = solve_fixed_steps(solver, term, ts, (q, w), args, substeps=substeps)
            sol = None
        else:
            qs, ws, sol = _diffeqsolve(term, q, w)
        if principal:  # diffrax puts the time axis first
            qs, ws = principal_frame.from_principal(qs, ws, q_axes[None], r[None])
        return qs, ws, sol

    def _diffeqsolve(term, q, w):
        with _saves_by_broadcast():
            return _diffeqsolve_traced(term, q, w)

    def _diffeqsolve_traced(term, q, w):
        sol = diffrax.diffeqsolve(
            term,
            solver,
            ts[0],
            ts[-1],
            dt0,
            (q, w),
            args=args,
            saveat=diffrax.SaveAt(ts=ts),
            stepsize_controller=controller,
            adjoint=adjoint,
            max_steps=max_steps,
            progress_meter=meter,
        )
        qs, ws = sol.ys  # type: ignore[misc]  # diffrax types ys as Optional; SaveAt(ts=...) fills it
        return qs, ws, sol

    if not batch:
        return one_solve(q0, omega0, inertia, torque)
    n = len(ts)
    flat = [x.reshape((-1,) + x.shape[len(batch) :]) for x in (q0, omega0, inertia)]
    if adaptive:  # each body its own step sizes
        qs, ws, sol = _in_chunks(
            jax.vmap(lambda q, w, i: one_solve(q, w, i, torque)),
            cfg.chunks[2],
            *flat,
            remat=False,
            multiple=multiple,
        )
    else:  # fixed steps: one solve of the stacked batch (diffrax's per-step work is shared)
        per_body = None if torque is None else jax.vmap(torque, in_axes=(None, 0, 0, None))
        if shared_inertia is not None and per_body_field:  # one (3, 3) tensor, not carried per body
            flat[2] = shared_inertia
        if substeps is None:  # diffeqsolve
            qs, ws, sol = one_solve(flat[0], flat[1], flat[2], per_body)
            qs, ws = jnp.swapaxes(qs, 0, 1), jnp.swapaxes(ws, 0, 1)
        else:  # the scan drivers

            def batch_first(q, w, i):
                qs, ws, _ = one_solve(q, w, i, per_body)
                return jnp.swapaxes(qs, 0, 1), jnp.swapaxes(ws, 0, 1)

            # A chunk whose steps run in segments (fixed_step.segment_length) is not rematerialised
            # whole: its stored states are the segments' starts already, and a third forward pass
            # cost more than it saved (10^5 float32 bodies x 1000 RKMK4 steps, one core: the gradient
            # 3561 ms unsegmented, 4070 ms segmented and rematerialised, 3358 ms segmented alone).
            def chunked(size):
                state_bytes = 7 * _chunk_size(flat[0].shape[0], size, multiple) * flat[0].dtype.itemsize  # q, w
                remat = not fixed_step.segment_length(substeps, state_bytes)
                return functools.partial(_in_chunks, batch_first, size, remat=remat, multiple=multiple)

            qs, ws = _derivatives_in_smaller_chunks(chunked, cfg.chunks[0], cfg.chunks[1], multiple, *flat)
            sol = None
    return qs.reshape(batch + (n, 4)), ws.reshape(batch + (n, 3)), sol


_solve = eqx.filter_jit(_solve_body)


def _in_chunks(solve: Callable, size: int, q: Array, w: Array, inertia: Array, remat: bool, multiple: int = 1) -> Any:
    """``solve(q, w, inertia)`` of a stacked batch (``q`` ``(n, 4)``, ``w`` ``(n, 3)``, ``inertia``
    ``(3, 3)`` shared or ``(n, 3, 3)``; a pytree of results with the batch axis first), solved
    in chunks of at most ``size`` bodies when ``n`` is larger, one after another (``lax.map``),
    so that the arrays of a step stay in cache. ``remat``: each chunk rematerialised whole in
    reverse mode (``jax.checkpoint``), so that a gradient stores one chunk's states at a time,
    not the whole batch's. The batch is padded to whole chunks with copies of its first body,
    whose results are dropped; each chunk holds a multiple of ``multiple`` bodies
    (:func:`jaxquat._threads.batch_multiple`: XLA's CPU threads split a kernel over an uneven
    count about three times slower), a batch of one chunk too.

    Not ``lax.map(..., batch_size=size)``: it ``vmap``s a one-body function over each chunk (the
    scan path's step is written for a stacked batch; a ``vmap`` of the one-body step took 240 ms
    against its 67 ms, :mod:`jaxquat.integration.struct_of_arrays`), and solves the remainder as
    a second program of another shape (a second compile)."""
    n = q.shape[0]
    size = _chunk_size(n, size, multiple)
    count = -(-n // size)
    if count == 1 and size == n:
        return solve(q, w, inertia)
    per_body = inertia.ndim == 3
    parts = [q, w, inertia] if per_body else [q, w]
    parts = [_threads.with_copies_of_first(x, count * size) for x in parts]
    if count == 1:  # one chunk, padded to the multiple
        return jax.tree.map(lambda x: x[:n], solve(parts[0], parts[1], parts[2] if per_body else inertia))
    # chunk c holds bodies c, c + count, c + 2 count, ...: the batch axis splits as (size, count),
    # so that a batch sharded across devices stays sharded within each chunk
    parts = [jnp.swapaxes(x.reshape((size, count) + x.shape[1:]), 0, 1) for x in parts]

    def one(chunk):
        return solve(chunk[0], chunk[1], chunk[2] if per_body else inertia)

    if remat:
        one = jax.checkpoint(one, prevent_cse=False)  # inside lax.map's scan, CSE cannot cross chunks

    def unchunk(x):
        return jnp.swapaxes(x, 0, 1).reshape((count * size,) + x.shape[2:])[:n]

    return jax.tree.map(unchunk, jax.lax.map(one, parts))


def _derivatives_in_smaller_chunks(
    chunked: Callable[[int], Callable],
    size: int,
    derivative_size: int,
    multiple: int,
    q: Array,
    w: Array,
    inertia: Array,
) -> Any:
    """``chunked(size)(q, w, inertia)`` (the solve in chunks of at most ``size`` bodies,
    :func:`_in_chunks`), whose derivatives (forward mode, and reverse mode by transposing it) are
    those of ``chunked(derivative_size)``: the same per-body arithmetic, so the same values and
    derivatives; only how many bodies a loop of the step covers differs. Where the batch splits
    into the same chunks either way, the first alone.

    Both solves are closure-converted (``eqx.filter_closure_convert``): every array they close
    over (a torque's traced gains, ``ts``) becomes an input of the ``custom_jvp``, whose rule would
    otherwise refuse to differentiate with respect to it."""
    n = q.shape[0]
    if _chunk_size(n, derivative_size, multiple) >= _chunk_size(n, size, multiple):
        return chunked(size)(q, w, inertia)
    values, static = eqx.partition(eqx.filter_closure_convert(chunked(size), q, w, inertia), eqx.is_array)
    derivatives, static_d = eqx.partition(
        eqx.filter_closure_convert(chunked(derivative_size), q, w, inertia), eqx.is_array
    )

    @jax.custom_jvp
    def in_chunks(values, derivatives, *xs):  # the jaxprs closed over (static), their constants inputs
        return eqx.combine(values, static)(*xs)

    @functools.partial(in_chunks.defjvp, symbolic_zeros=True)
    def in_chunks_jvp(primals, tangents):
        # only the perturbed inputs differentiated: a zero tangent made an array of zeros (the
        # inertia's, the constants') cost 10-25 % in arithmetic on them
        leaves, tree = jax.tree.flatten(primals[1:])
        d_leaves = jax.tree.leaves(tangents[1:], is_leaf=lambda t: isinstance(t, SymbolicZero))
        live = [not isinstance(t, SymbolicZero) for t in d_leaves]

        def run(*live_leaves):
            it = iter(live_leaves)
            derivatives, *xs = jax.tree.unflatten(tree, [next(it) if v else x for x, v in zip(leaves, live)])
            return eqx.combine(derivatives, static_d)(*xs)

        pick = lambda xs: [x for x, v in zip(xs, live) if v]  # noqa: E731
        return jax.jvp(run, pick(leaves), pick(d_leaves))

    return in_chunks(values, derivatives, q, w, inertia)


def _chunk_size(n: int, size: int, multiple: int = 1) -> int:
    """Bodies per chunk of :func:`_in_chunks` for ``n`` bodies and chunks of at most ``size``: equal
    chunks, as few as fit, each rounded up to a multiple of ``multiple`` (a chunk may then exceed
    ``size`` by less than ``multiple``)."""
    return _threads.padded_batch(n if n <= size else -(-n // -(-n // size)), multiple)


class _StackOfCopiesAsBroadcast:
    """``jax.numpy`` as diffrax's integrate module sees it, except that ``stack`` of a list
    holding one array ``n`` times is a broadcast. Diffrax 0.6.1-0.7.0 fills ``SaveAt(ts=...)``
    in its (never taken here) ``t0 == t1`` branch by ``jnp.stack([y] * len(ts))``: a
    concatenation of ``len(ts)`` operands that XLA on CPU compiles into one enormous kernel
    (diffrax issue 606, fixed upstream in 0.7.1, which this project cannot use: see
    ``docs/integrators.md``). Measured (this 2-core EPYC, float64, RKMK45 at 1e-10, 6001 saved
    times, ``simulate`` called eagerly): the first call 21.6 s, of it 21.4 s compiling, two
    kernels of 3.5 MB of LLVM IR each; 1.7 s with the broadcast, the same values to the bit."""

    def __init__(self, module):
        self._module = module

    def __getattr__(self, name):
        return getattr(self._module, name)

    def stack(self, arrays, axis=0, *rest, **kwargs):
        arrays = list(arrays)
        if axis == 0 and not rest and not kwargs and len(arrays) > 1 and all(a is arrays[0] for a in arrays):
            first = jnp.asarray(arrays[0])
            return jnp.broadcast_to(first[None], (len(arrays),) + first.shape)
        return self._module.stack(arrays, axis, *rest, **kwargs)


@contextlib.contextmanager
def _saves_by_broadcast():
    """While ``diffeqsolve`` is traced inside :func:`simulate` (at trace time only; nothing of
    diffrax changes outside it), its integrate module's ``jnp`` is
    :class:`_StackOfCopiesAsBroadcast`."""
    import diffrax._integrate as integrate  # private: where the saving code lives (0.6-0.7)

    original = getattr(integrate, "jnp", None)
    if original is None or isinstance(original, _StackOfCopiesAsBroadcast):
        yield  # another layout (a later diffrax), or already in place (a trace in another thread)
        return
    setattr(integrate, "jnp", _StackOfCopiesAsBroadcast(original))  # noqa: B010 (a private name: no typed attribute)
    try:
        yield
    finally:
        setattr(integrate, "jnp", original)  # noqa: B010


class _Field(eqx.Module):
    """The rigid body's vector field, ``(qdot, wdot)``, or ``(w, wdot)`` with ``rates`` (for
    :class:`jaxquat.BodyRateTerm`). ``stacked``: of stacked bodies ``(q (n, 4), w (n, 3))``,
    one body's field vmapped, with a shared ``(3, 3)`` tensor or one per body ``(n, 3, 3)``.
    A module, so the inertia is a leaf every diffrax adjoint differentiates."""

    inertia: Array
    torque: Callable | None
    torque_frame: str = eqx.field(static=True)
    stacked: bool = eqx.field(static=True)
    rates: bool = eqx.field(static=True)

    def _one(self, t, q, w, tensor, args, rates: bool):
        body = RigidBody(tensor, self.torque, self.torque_frame)
        return (w, body.angular_acceleration(t, q, w, args)) if rates else body(t, (q, w), args)

    def _field(self, t, y, args, rates: bool):
        q, w = y
        if not self.stacked:
            return self._one(t, q, w, self.inertia, args, rates)
        axis = None if self.inertia.ndim == 2 else 0
        return jax.vmap(functools.partial(self._one, rates=rates), in_axes=(None, 0, 0, axis, None))(
            t, q, w, self.inertia, args
        )

    def __call__(self, t, y, args):
        return self._field(t, y, args, self.rates)

    def body_rate_field(self, t, y, args):
        """``(w_b, dw_b/dt)``, as :meth:`jaxquat.RigidBody.body_rate_field`."""
        return self._field(t, y, args, True)

    def euler_equations(self):
        """``(inertia, body torque on the state's rows)``, as :meth:`jaxquat.RigidBody.euler_equations`."""
        if self.torque is None:
            return self.inertia, None
        torque = as_body_torque(self.torque, self.torque_frame)
        return self.inertia, jax.vmap(torque, in_axes=(None, 0, 0, None)) if self.stacked else torque


def configure(
    solver, torque, torque_frame, dt0, rtol, atol, max_steps, adjoint, progress, ts_host, n_times, q0, diagonal_given
) -> Config:
    """What :func:`jaxquat.simulate` decides before a numerical solve (its arguments as given there;
    ``ts_host`` the values of a concrete ``ts``, ``n_times`` its length, ``q0`` the checked initial
    attitudes): the solver (its default),
    whether the exact torque-free flow applies (``exact``: then ``simulate`` evaluates the closed
    form), the principal axes, the step limit, the scan path's substeps, the adjoint and the chunks."""
    if solver is None:
        solver = EulerPoinsotSplit() if torque is None else RKMK45()
    adaptive = _has_error_estimate(solver)
    if adaptive and isinstance(solver, AbstractLieSolver):
        # every saved time is a step end (ClipStepSizeController(step_ts=ts), below): the saves are
        # the steps' own ends, and diffrax traces no dense output (_StepEndInterpolation). 1000
        # PD-controlled bodies over 10 s, float32, one core: forward 9.2 -> 6.3 ms, gradient 54.8 ->
        # 41.6 ms (float64: 36 -> 23 ms, 228 -> 166 ms); time to the first gradient 14.1-14.4 ->
        # 11.4 s (trace 6.4 -> 5.3 s, XLA 7.5 -> 6.0 s).
        solver = dataclasses.replace(solver, saves_at_step_ends=True)
    # Torque-free, the exact flow needs no step control: step straight from one saved time to the next.
    exact = getattr(solver, "exact_torque_free", False) and torque is None and dt0 is None
    if not (adaptive or exact) and dt0 is None:
        raise ValueError(f"argument 'dt0' is required with the fixed-step solver {type(solver).__name__}")
    principal = isinstance(solver, AbstractSplitting) and not diagonal_given
    if max_steps is None:
        # numpy, not jnp: inside jit even a concrete ts would be traced by ts[-1] - ts[0]
        span = None if ts_host is None else abs(float(ts_host[-1] - ts_host[0]))
        if exact:
            max_steps = n_times
        elif adaptive or span is None or dt0 is None:  # dt0 is not None here: checked above
            max_steps = 100_000
        else:
            max_steps = math.ceil(span / abs(dt0)) + n_times + 16
    substeps = None if (adjoint is not None or progress) else _scan_substeps(solver, ts_host, dt0, max_steps, q0.dtype)
    adjoint = diffrax.RecursiveCheckpointAdjoint(checkpoints=_CHECKPOINTS) if adjoint is None else adjoint
    diagonal = substeps is not None and diagonal_given
    # a GPU takes the batch whole, and so does a solve with a progress bar (one bar, not one a chunk)
    in_chunks = _trig.is_cpu() and not progress
    scan_chunk = _SHARD_MAP_CHUNK if in_shard_map() else _CHUNK_BYTES // q0.dtype.itemsize
    if torque is not None:
        scan_chunk = min(scan_chunk, _TORQUE_CHUNK)
    derivative_chunk = _DERIVATIVE_CHUNK if _threads.pool_threads() == 1 else _DERIVATIVE_CHUNK_THREADS
    chunks = (scan_chunk, min(scan_chunk, derivative_chunk), _ADAPTIVE_CHUNK) if in_chunks else (q0.size,) * 3
    return Config(
        solver,
        torque,
        torque_frame,
        principal,
        substeps,
        diagonal,
        exact,
        rtol,
        atol,
        max_steps,
        adjoint,
        progress,
        chunks,
        _threads.batch_multiple() if in_chunks else 1,
    )


def _component_tableau(solver) -> struct_of_arrays.Tableau | None:
    """The tableau of a fixed-step Lie solver that the struct-of-arrays step runs exactly
    (``LieEuler``, and ``AbstractRKMK`` subclasses with an explicit tableau that is not
    first-same-as-last and their own ``lie_step``), or None (the solver's own step runs)."""
    if type(solver) is LieEuler:
        return struct_of_arrays.LIE_EULER
    if (
        isinstance(solver, AbstractRKMK)
        and not _has_error_estimate(solver)
        and not solver.tableau.fsal
        and type(solver).lie_step is AbstractRKMK.lie_step
    ):
        order = solver.order(None)
        return None if order is None else struct_of_arrays.Tableau.of(solver.tableau, order)
    return None


def solves_body_by_body(cfg: Config) -> bool:
    """Whether ``diffeqsolve``'s path solves each body of a batch on its own (``vmap``: an
    adaptive solver, each body its own steps), so that every leaf of the solution has the
    (flattened) batch axis first; with fixed steps the batch is one stacked solve."""
    return _has_error_estimate(cfg.solver)


def _has_error_estimate(solver) -> bool:
    """Whether a solver returns an error estimate (so a PID controller can adapt its step)."""
    return isinstance(solver, diffrax.AbstractAdaptiveSolver)


def _scan_substeps(solver, ts_host, dt0, max_steps, dtype) -> int | None:
    """Steps per interval of ``ts`` (its values ``ts_host``, None if traced; the solve steps
    between them rounded to ``dtype``) for the scan path, or None where diffrax must run
    (adaptive solvers, solvers from outside jaxquat).

    An interval that is a whole number of ``dt0`` up to the rounding of the times in ``dtype`` (4
    ulps of the largest ``|t|``) takes that number of steps. Before session 69 the slack was a
    relative 1e-12 whatever the dtype: float32 ``ts = [0, 0.1, 0.2]`` (0.1 rounds up, to
    0.10000000149) with ``dt0=0.05`` took 3 steps an interval, not 2, and ``LieEuler``'s states
    then differed from float64's by 1.1e-3 (``diffeqsolve``'s 2 steps: 1.1e-7)."""
    fixed = isinstance(solver, (AbstractLieSolver, AbstractSplitting)) and not _has_error_estimate(solver)
    if not fixed or dt0 is None or ts_host is None or _checks.is_traced(dt0):
        return None
    times = np.asarray(ts_host, dtype=dtype).astype(np.float64)
    widest = float(np.max(np.abs(np.diff(times))))
    slack = 4 * float(np.finfo(dtype).eps) * float(np.max(np.abs(times))) + 1e-12 * widest
    substeps = max(1, math.ceil((widest - slack) / abs(float(dt0))))
    return None if max_steps is not None and substeps * (len(ts_host) - 1) > max_steps else substeps
