"""One call to simulate rigid bodies: ``simulate(q0, omega0, inertia, ts, ...)``."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, NamedTuple, NoReturn, cast

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.sharding import NamedSharding, PartitionSpec

from .. import _arrays, _checks, _threads
from .._threads import split_across_devices
from ..mechanics.inertia import validated
from ..mechanics.torque_free import propagate
from . import principal_frame

if TYPE_CHECKING:
    import diffrax

__all__ = ["Simulation", "simulate"]


class Simulation(NamedTuple):
    """Result of :func:`simulate`: attitudes ``q`` ``(*batch, len(ts), 4)``, body angular
    velocities ``omega`` ``(*batch, len(ts), 3)`` and diffrax's ``solution`` (batched;
    ``None`` when the fixed-step scan ran instead of ``diffeqsolve``)."""

    q: Array
    omega: Array
    solution: Any


def simulate(
    q0: Any,
    omega0: Any,
    inertia: Any,
    ts: Any,
    *,
    torque: Callable | None = None,
    torque_frame: str = "body",
    args: Any = None,
    solver: diffrax.AbstractSolver | None = None,
    dt0: float | None = None,
    rtol: float = 1e-8,
    atol: float = 1e-8,
    max_steps: int | None = None,
    adjoint: diffrax.AbstractAdjoint | None = None,
    progress: bool = False,
) -> Simulation:
    """Integrate the rigid body ``(q, w_b)`` from ``ts[0]`` and return the state at every ``ts``.

    ``q0`` ``(..., 4)`` (unit), ``omega0`` ``(..., 3)`` body angular velocity,
    ``inertia`` ``(..., 3, 3)`` body tensor; their leading axes broadcast. A batch is
    solved as one stacked state with fixed steps or the exact flow, and with ``vmap``
    (a step size per body) with an adaptive solver, on CPU in chunks of at most 1000 bodies
    one after another (10^4 PD-controlled bodies, one core: the gradient 1.9-2.0x faster).
    ``torque``: ``fn(t, q, w, args)`` in ``torque_frame``, written for one body (``q`` ``(4,)``,
    ``w`` ``(3,)``; it is vmapped over a batch, ``args`` shared).

    ``solver`` defaults to :class:`jaxquat.EulerPoinsotSplit` when there is no
    torque: the exact Euler-Poinsot flow, one step from each saved time to the
    next (``diffrax.StepTo(ts)``), error at rounding level at any ``t``. With a
    torque it defaults to :class:`jaxquat.RKMK45` with a PID controller
    (``rtol``, ``atol``) made to step exactly onto every ``ts`` (so saved
    states are step ends, not interpolants: a step that ends within rounding of a
    saved time saves its end, and a Lie solver computes no dense output,
    ``saves_at_step_ends``). A fixed-step solver
    (``LieEuler``, ``RKMK4``, the splittings, or any diffrax solver without an
    error estimate) needs ``dt0``. The splitting solvers (``RigidBodySplit*``,
    ``EulerPoinsotSplit*``) work in principal axes: a full (or traced) tensor
    is diagonalised with :func:`jaxquat.principal_axes` and the results are
    rotated back (its derivative needs distinct principal moments). ``adjoint`` defaults to diffrax's
    ``RecursiveCheckpointAdjoint`` with 64 checkpoints per body (diffrax's own default for
    ``max_steps=100_000``, 446, made reverse mode through a batch 1.3-2x slower, with up to 1.9x
    the memory; see ``numerical_solve._CHECKPOINTS``); ``progress=True`` shows a tqdm bar.

    Torque-free with the default solver, no ``dt0``, ``adjoint`` or ``progress``: no
    ``diffeqsolve`` runs; every saved state is the closed-form flow
    (:func:`jaxquat.euler_poinsot`) from ``(q0, omega0)`` over ``ts[i] - ts[0]``, so
    rounding does not carry from one saved time to the next, and ``solution`` is ``None``.

    Autodiff: reverse mode everywhere. Forward mode (``jax.jvp``, ``jax.jacfwd``) works on
    the closed-form and scan paths as they are; through ``diffeqsolve`` pass
    ``adjoint=diffrax.ForwardMode()`` (without it a clear ``TypeError`` says so).
    In float32 give ``rtol``/``atol`` above float32 rounding (e.g. 1e-5): the defaults
    (1e-8) are float64 tolerances.

    Fast path: every fixed-step jaxquat solver (``LieEuler``, ``RKMK4``, the splittings)
    with concrete ``ts`` and ``dt0``, no ``adjoint`` or ``progress``, and ``max_steps`` (if
    given) not exceeded, runs on a ``lax.scan`` over the steps instead of ``diffeqsolve`` (1.5x
    the throughput at 10^5 bodies, see ``docs/benchmarks.md``): ``LieEuler`` and the RKMK
    tableaus as the same method written on one array per state component
    (:mod:`jaxquat.integration.struct_of_arrays`, whose reverse pass is element-wise too, each
    stage one loop over the batch on CPU: 1000 torque-free bodies x 1000 RKMK4 steps take 5.9 ms
    and their gradient 25 ms in float32 on one core; the same step inside ``diffeqsolve``, as the
    Lie solvers run it on a ``RigidBody`` or this function's own field, 7.4 ms and 56 ms, or 28 ms
    with a checkpoint per step; the generic Lie step, which runs a model's field on rows, 13.8 ms
    and 174 ms), the splittings through their own
    ``init``/``step`` (:func:`jaxquat.solve_fixed_steps`). Every interval
    ``[ts[i], ts[i+1]]`` is split into the same number
    ``ceil(max_i |ts[i+1] - ts[i]| / |dt0|)`` of equal steps, so no step exceeds
    ``dt0`` and every saved state is a step end, not an interpolant; each step is
    rematerialised in the backward pass (``jax.checkpoint``), so reverse mode stores
    one state per step. On CPU, a batch of more than 20 000 bodies in float32 (10 000 in float64) is
    solved in chunks of at most that size (inside a ``jax.shard_map``, each device's shard in
    chunks of 2000 bodies: docs/integrators.md, "Many bodies on a multi-core CPU"), one after
    another, each chunk rematerialised
    whole in reverse mode: a gradient then stores one chunk's states per step, not the whole
    batch's (10^5 torque-free bodies x 1000 RKMK4 steps, one core: float32 gradient 4.10 ->
    3.64 s with a peak of 3.2 -> 1.0 GB; float64 11.8 -> 6.9 s, 5.9 -> 1.0 GB; 10^6 bodies,
    which needed 28 GB, fit). Derivatives (``grad``, ``jvp``, ``jacfwd``) run in chunks of at
    most 2000 bodies, and so do the values with a torque acting (their arrays then stay in
    cache: at 10^5 bodies, one core, float32, the torque-free gradient 5.1 -> 2.7 s, a PD law's
    forward pass 3.0 -> 1.45 s; docs/integrators.md, "Large batches on CPU").
    ``solution`` is then ``None``. A batch sharded over a mesh of
    several devices runs on this path as one SPMD program, each step's branches chosen per
    element. On an Explicit mesh (``jax.make_mesh``'s default) the closed form runs each
    device's shard in a ``jax.shard_map`` of its own, and so does the adaptive path for a batch
    with one axis (reverse mode through a ``custom_vjp`` whose backward pass runs the whole
    batch on every device, as diffrax's adjoint fails inside a ``shard_map``; forward mode is
    not available there); the fixed-step ``diffeqsolve`` path (an ``adjoint`` given), a
    progress bar and several batch axes refuse the batch with a ``ValueError`` (JAX's explicit
    sharding fails inside diffrax's loop): run those in a ``jax.shard_map``
    (``check_vma=False``), or shard over ``AxisType.Auto`` axes.

    Args:
        q0: initial attitude ``(..., 4)``, unit, scalar first (body to space).
        omega0: initial body angular velocity ``(..., 3)``.
        inertia: body inertia tensor ``(..., 3, 3)``, symmetric positive definite (values
            checked when concrete: eagerly, or a NumPy array under ``jit``). A concrete diagonal
            tensor is known to be diagonal, under ``jit`` too, and takes the faster paths (the
            closed form without diagonalising, the fixed-step scan reading the moments only:
            ``np.diag(...)``, not ``jnp.diag(...)`` inside a jitted function).
        ts: the times to save at ``(n,)``, strictly increasing, ``n >= 2``; the solve starts
            at ``ts[0]``.
        torque: ``fn(t, q, w, args) -> (3,)`` for one body, or ``None`` (torque-free).
        torque_frame: ``"body"`` or ``"space"``: the frame ``torque`` returns its torque in.
        args: passed to ``torque`` (shared by a batch).
        solver: any jaxquat or diffrax solver; default as above.
        dt0: the step (required by fixed-step solvers; the first step of adaptive ones).
        rtol: relative tolerance of an adaptive solver.
        atol: absolute tolerance of an adaptive solver.
        max_steps: diffrax's step limit (default: 100 000 for adaptive solvers, the number
            of steps plus a margin for fixed ones).
        adjoint: a diffrax adjoint (``ForwardMode()`` for ``jax.jvp``/``jacfwd`` through
            ``diffeqsolve``).
        progress: show a tqdm progress bar (needs ``tqdm``).

    Returns:
        A :class:`Simulation`: ``q`` ``(..., n, 4)``, ``omega`` ``(..., n, 3)`` at every ``ts``,
        and diffrax's ``solution`` (``None`` on the closed-form and scan paths).
    """
    # the values of a concrete ts, taken before any jnp op (under jit those return tracers)
    ts_host = None if _checks.is_traced(ts) else np.asarray(ts, dtype=np.float64)
    # whether it is diagonal, asked of the tensor as given (a NumPy array under a user's jit is
    # concrete; jnp.asarray, and so validated, makes it a tracer there; broadcast to the batch
    # below it is one anyway). 1000 bodies x 101 saved times, torque-free, float32, one core: a
    # diagonal tensor taken as full was diagonalised per body, and the gradient took 298 ms.
    given = inertia
    inertia = validated(inertia)  # values too, wherever they are concrete: every path trusts them after this
    diagonal_given = _is_concrete_diagonal(given)
    ts = _checks.scalar_like(ts, "ts")
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"argument 'ts' must be shaped (n,) with n >= 2, got shape {tuple(ts.shape)}")
    shared_inertia = inertia if inertia.ndim == 2 else None  # one tensor for every body
    # A shared tensor is not broadcast to the batch here: the closed form takes it as it is, and
    # the broadcast was an eager operation of its own (a first call 24 ms longer, for an array it
    # did not use); the numerical paths broadcast it inside their compiled program.
    q0, omega0, inertia = _checks.arguments(
        q0=(q0, "quaternion"), omega0=(omega0, "vector"), inertia=(inertia, "inertia"), shared=("inertia",)
    )
    ts = ts.astype(q0.dtype)
    ts = _check_times(ts, ts_host, dt0, solver)
    if progress:
        _checks.require_tqdm("simulate")
    tensor = inertia if shared_inertia is None else shared_inertia
    if solver is None and torque is None and dt0 is None and adjoint is None and not progress:
        # The default torque-free path, the closed form (EulerPoinsotSplit's exact flow), decided
        # here without importing diffrax and equinox (numerical_solve's docstring).
        return _closed_form(q0, omega0, tensor, ts, principal=not diagonal_given)
    from . import numerical_solve  # diffrax and equinox, on the first numerical solve

    cfg = numerical_solve.configure(
        solver,
        torque,
        torque_frame,
        dt0,
        rtol,
        atol,
        max_steps,
        adjoint,
        progress,
        ts_host,
        len(ts),
        q0,
        diagonal_given,
    )
    if cfg.exact and adjoint is None and not progress:
        return _closed_form(q0, omega0, tensor, ts, principal=cfg.principal)
    split = None if cfg.substeps is not None else _split_argument(q0, omega0, "diffeqsolve path")
    if split is not None:
        batch = jnp.broadcast_shapes(q0.shape[:-1], omega0.shape[:-1])
        if progress or not numerical_solve.solves_body_by_body(cfg) or len(batch) != 1:
            _refuse_split_batch(
                "diffeqsolve path with a fixed step (an adjoint given), a progress bar or several batch axes"
            )
    try:
        if split is not None:
            return _numerical_in_shards(cfg, q0, omega0, tensor, ts, args, dt0, split=split)
        return Simulation(*numerical_solve.solve(cfg, q0, omega0, inertia, shared_inertia, ts, args, dt0))
    except TypeError as err:  # jvp of a custom_vjp: diffrax's adjoint, or the split batch's solve
        if "custom_vjp" not in str(err):
            raise
        if split is None:
            raise TypeError(
                "forward-mode autodiff (jax.jvp, jax.jacfwd) through simulate's diffeqsolve path needs "
                "adjoint=diffrax.ForwardMode(); the default RecursiveCheckpointAdjoint supports reverse mode only"
            ) from err
        raise TypeError(
            "forward-mode autodiff (jax.jvp, jax.jacfwd) through simulate's adaptive path on a batch split "
            "between devices by an Explicit mesh is not available (reverse mode is): take the scan path (a "
            "fixed-step solver with dt0, no adjoint) or the closed form (torque-free, no solver), or an "
            "unsplit batch with adjoint=diffrax.ForwardMode(); docs/integrators.md, 'Many bodies on a "
            "multi-core CPU'"
        ) from err


def _closed_form(q0: Array, omega0: Array, tensor: Array, ts: Array, principal: bool) -> Simulation:
    """:func:`_exact_simulate`, compiled; a batch split between devices by an Explicit mesh
    (:func:`jaxquat._threads.split_across_devices`) as the body of a ``jax.shard_map`` over the
    batch's mesh axes (:func:`_in_shards`). JAX's explicit sharding fails inside the closed form
    (jax 0.10.2: a reshape of a sharded axis raised ``ShardingTypeError``), and each body's flow
    is its own, so each device solves its shard."""
    split = _split_argument(q0, omega0, "closed form")
    if split is None:
        return _arrays.compiled(
            _exact_simulate, q0, omega0, tensor, ts, principal=principal, multiple=_threads.batch_multiple()
        )
    return _closed_form_in_shards(q0, omega0, tensor, ts, principal=principal, split=split)


def _split_argument(q0: Array, omega0: Array, path: str) -> int | None:
    """Which of ``(q0, omega0)`` holds the whole batch split between devices by an Explicit mesh
    (:func:`jaxquat._threads.split_across_devices`), or ``None`` where neither is split. Where only
    a smaller, broadcast argument is split, :func:`_refuse_split_batch` raises."""
    if not (split_across_devices(q0) or split_across_devices(omega0)):
        return None
    batch = jnp.broadcast_shapes(q0.shape[:-1], omega0.shape[:-1])
    whole = [i for i, x in enumerate((q0, omega0)) if x.shape[:-1] == batch and split_across_devices(x)]
    if not whole:
        _refuse_split_batch(f"{path} (a batch split only in a broadcast argument)")
    return whole[0]


@functools.partial(jax.jit, static_argnames=("principal", "split"))
def _closed_form_in_shards(
    q0: Array, omega0: Array, tensor: Array, ts: Array, principal: bool, split: int
) -> Simulation:
    """:func:`_closed_form`'s ``shard_map``, compiled (an eager call places the shared tensor
    and ``ts`` on the mesh inside the program)."""
    return _in_shards(
        lambda q0, omega0, tensor, ts, _: _exact_simulate(q0, omega0, tensor, ts, principal, _threads.batch_multiple()),
        q0,
        omega0,
        tensor,
        ts,
        None,
        split,
    )


def _numerical_in_shards(cfg, q0: Array, omega0: Array, tensor: Array, ts: Array, args, dt0, split: int) -> Simulation:
    """``diffeqsolve``'s adaptive path (each body solved on its own) for a batch split between
    devices by an Explicit mesh: each device solves its shard (:func:`_in_shards`), the torque's
    ``args`` and ``dt0`` replicated. JAX's explicit sharding fails inside diffrax (jax 0.10.2,
    diffrax 0.7: its term check raised ``ShardingTypeError`` and its loop under ``vmap`` a
    ``ValueError``), and each body's adaptive steps are its own, so a device needs nothing from
    the others. Compiled by ``eqx.filter_jit`` as :func:`numerical_solve.solve` is: ``cfg``,
    ``split`` and the leaves of ``args`` that are not arrays are static."""
    return _numerical_in_shards_program()(cfg, q0, omega0, tensor, ts, args, dt0, split)


@functools.cache
def _numerical_in_shards_program() -> Callable:
    """:func:`_numerical_in_shards`' program, made on first use (equinox is imported with the
    numerical paths, not with this module)."""
    import equinox as eqx

    return eqx.filter_jit(_numerical_in_shards_body)


def _numerical_in_shards_body(cfg, q0, omega0, tensor, ts, args, dt0, split: int) -> Simulation:
    """:func:`_numerical_in_shards`' program: the array leaves of ``(args, dt0)`` pass the
    ``shard_map`` replicated, the others are put back beside them on each device.

    Reverse mode through a ``custom_vjp`` whose backward pass is the whole batch's ``jax.vjp`` on
    every device (:func:`_pullback_whole`), not JAX's transpose of the forward ``shard_map``,
    inside which diffrax's adjoint fails (jax 0.10.2, diffrax 0.7: equinox's closure conversion
    sees other argument types). Forward mode is not available: a ``custom_vjp`` has none (nor has
    diffrax's default adjoint on the unsplit path)."""
    import equinox as eqx

    from . import numerical_solve

    arrays, static = eqx.partition((args, dt0), eqx.is_array)

    def solve(q0, omega0, tensor, ts, arrays):
        args, dt0 = eqx.combine(arrays, static)
        shared = tensor if tensor.ndim == 2 else None
        return Simulation(*numerical_solve.solve(cfg, q0, omega0, tensor, shared, ts, args, dt0))

    layout = _ShardLayout.of(q0, omega0, tensor, split)

    @jax.custom_vjp
    def run(q0, omega0, tensor, ts, arrays):
        return layout.shard_map(solve, q0, omega0, tensor, ts, arrays)

    def run_forward(q0, omega0, tensor, ts, arrays):
        return run(q0, omega0, tensor, ts, arrays), (q0, omega0, tensor, ts, arrays)

    def run_backward(primals, cotangent):
        return _pullback_whole(solve, primals, cotangent)

    run.defvjp(run_forward, run_backward)
    return run(*layout.placed(q0, omega0, tensor, ts, arrays))


class _ShardLayout(NamedTuple):
    """How :func:`_in_shards` splits a batch: the mesh, the batch's partition spec entries ``b``
    (those of ``(q0, omega0)[split]``'s batch axes), the batch shape, and whether the tensor is
    per body (split as the batch is) or shared (replicated)."""

    mesh: Any
    b: tuple
    batch: tuple
    per_body_tensor: bool

    @classmethod
    def of(cls, q0: Array, omega0: Array, tensor: Array, split: int) -> _ShardLayout:
        sharding = jax.typeof((q0, omega0)[split]).sharding
        batch = jnp.broadcast_shapes(q0.shape[:-1], omega0.shape[:-1])
        return cls(sharding.mesh, tuple(sharding.spec)[:-1], batch, tensor.ndim > 2)

    def _place(self, x: Array, spec: tuple) -> Array:
        return jax.sharding.reshard(x, NamedSharding(self.mesh, PartitionSpec(*spec)))

    def placed(self, q0: Array, omega0: Array, tensor: Array, ts: Array, shared: Any) -> tuple:
        """The arguments broadcast to the batch (the tensor too, if per body) and placed: the
        batch arguments split as the batch is, ``ts`` and ``shared`` replicated."""
        row = (*self.b, None)
        q0, omega0 = (self._place(jnp.broadcast_to(x, self.batch + x.shape[-1:]), row) for x in (q0, omega0))
        if self.per_body_tensor:
            tensor = jnp.broadcast_to(tensor, self.batch + tensor.shape[-2:])
        tensor = self._place(tensor, self.tensor_spec)
        shared = jax.tree.map(lambda x: self._place(jnp.asarray(x), ()), shared)
        return q0, omega0, tensor, self._place(ts, ()), shared

    @property
    def tensor_spec(self) -> tuple:
        return (*self.b, None, None) if self.per_body_tensor else ()

    @property
    def in_specs(self) -> tuple:
        return (
            PartitionSpec(*self.b, None),
            PartitionSpec(*self.b, None),
            PartitionSpec(*self.tensor_spec),
            PartitionSpec(),
            PartitionSpec(),
        )

    def shard_map(self, fn: Callable, *placed: Any) -> Any:
        """``fn(q0, omega0, tensor, ts, shared)`` as the body of a ``jax.shard_map`` over the
        batch's mesh axes, on arguments from :meth:`placed`; every leaf of the result split along
        its leading batch axes as the batch is. ``check_vma=False``: the cotangents of the closed
        form's custom derivative rules carry no varying mesh axes, and diffrax's loop carries a
        flag, both of which JAX's check refuses (diffrax issue #735)."""
        out_specs = PartitionSpec(*self.b)
        body = jax.shard_map(fn, mesh=self.mesh, in_specs=self.in_specs, out_specs=out_specs, check_vma=False)
        return body(*placed)


def _pullback_whole(fn: Callable, primals: tuple, cotangent: Any) -> tuple:
    """The cotangents of ``fn``'s arguments ``primals`` (placed by :meth:`_ShardLayout.placed`)
    for the ``cotangent`` of its sharded result: ``jax.vjp`` of ``fn`` on the whole batch,
    replicated on every device of the mesh (its axes made Auto, ``jax.sharding.auto_axes``), the
    cotangents then placed as their primals are. So a split batch's gradient costs about one
    device's gradient of the whole batch, and needs its memory on every device.

    Why not split: a ``vjp`` per shard inside a ``shard_map`` fails in diffrax's checkpointed
    adjoint (equinox's closure conversion refuses its own arguments: constants typed without the
    manual mesh when converted, with it when called; jax 0.10.2, equinox 0.13, diffrax issue
    #765), and the same ``vjp`` kept split on Auto axes stops each of its loops on a flag reduced
    across the devices at every iteration: on 2 and 4 host devices of a 2-core CPU (64 bodies,
    ``diffrax.Heun``, float32) 13.3 and 20.4 s a gradient against 0.94-1.09 s unsplit, and 1.06
    and 2.09 s replicated (``docs/integrators.md``). Integer and boolean leaves are not
    differentiated (their cotangents are ``float0`` zeros), nor are the result's."""
    leaves, tree = jax.tree.flatten(primals)
    floating = [jnp.issubdtype(x.dtype, jnp.inexact) for x in leaves]
    ct_leaves = jax.tree.leaves(cotangent)
    ct_floating = [jnp.issubdtype(c.dtype, jnp.inexact) for c in ct_leaves]

    def pulled(inputs):  # every array an argument: one closed over would keep its Explicit type
        diff, fixed, cts = inputs

        def of_floating(*xs):
            it, rest = iter(xs), iter(fixed)
            full = jax.tree.unflatten(tree, [next(it) if f else next(rest) for f in floating])
            out = jax.tree.leaves(fn(*full))
            return [o for o, f in zip(out, ct_floating) if f]

        _, pull = jax.vjp(of_floating, *diff)
        return tuple(pull(list(cts)))

    diff = [x for x, f in zip(leaves, floating) if f]
    fixed = [x for x, f in zip(leaves, floating) if not f]
    cts = [c for c, f in zip(ct_leaves, ct_floating) if f]
    shardings = tuple(jax.typeof(x).sharding for x in diff)
    replicated = NamedSharding(shardings[0].mesh, PartitionSpec())
    inputs = jax.tree.map(lambda x: jax.sharding.reshard(x, replicated), (diff, fixed, cts))
    on_auto_axes = cast(Callable[[Any], tuple], jax.sharding.auto_axes(pulled, out_sharding=replicated))
    grads = iter(jax.sharding.reshard(g, s) for g, s in zip(on_auto_axes(inputs), shardings))
    out = [next(grads) if f else np.zeros(x.shape, jax.dtypes.float0) for x, f in zip(leaves, floating)]
    return tuple(jax.tree.unflatten(tree, out))


def _in_shards(fn: Callable, q0: Array, omega0: Array, tensor: Array, ts: Array, shared: Any, split: int) -> Any:
    """``fn(q0, omega0, tensor, ts, shared)`` as the body of a ``jax.shard_map`` over the mesh axes
    that split the batch of ``(q0, omega0)[split]``: the other batch arguments (a per-body
    ``tensor`` too) take its sharding, ``ts`` and ``shared`` (a pytree of arrays) are replicated,
    and every leaf of the result is split along its leading batch axes as the batch is
    (:class:`_ShardLayout`)."""
    layout = _ShardLayout.of(q0, omega0, tensor, split)
    return layout.shard_map(fn, *layout.placed(q0, omega0, tensor, ts, shared))


def _refuse_split_batch(path: str) -> NoReturn:
    """A clear error where a batch split between devices by its type (an Explicit mesh,
    :func:`jaxquat._threads.split_across_devices`) reaches a path that JAX's explicit sharding
    fails inside (session 70, jax 0.10.2: diffrax's term check and its loop under ``vmap`` raised
    ``ShardingTypeError`` or ``ValueError`` from deep in the solve). The scan path, the closed
    form (:func:`_closed_form`) and the adaptive path (:func:`_numerical_in_shards`) take such a
    batch (``tests/test_sharding.py``). Called where the batch is known to be split
    (:func:`_split_argument`)."""
    raise ValueError(
        f"simulate's {path} does not take a batch split between devices by an Explicit mesh "
        "(arguments 'q0', 'omega0'): run simulate as the body of jax.shard_map(..., check_vma=False) "
        "over the mesh, shard over AxisType.Auto axes, or take the scan path (a fixed-step solver "
        "with dt0, no adjoint) or the closed form (torque-free, no solver); docs/integrators.md, "
        "'Many bodies on a multi-core CPU'"
    )


def _exact_simulate(q0, omega0, inertia, ts, principal: bool, multiple: int = 1) -> Simulation:
    """The torque-free flow evaluated in closed form at every ``ts`` from the initial state.

    No ``diffeqsolve``: each saved state is :func:`jaxquat.euler_poinsot` of ``(q0, omega0)``
    over ``ts[i] - ts[0]``, so rounding does not accumulate from one saved time to the next
    (float32, 10^4 saved times: ``| |q| - 1 |`` 2.2e-4 when chained, rounding level here), and
    forward and reverse mode both work (no ``custom_vjp`` from diffrax's adjoint). Each body's
    part of the solution is formed once for all its saved times (:func:`propagate` with a time
    axis): 1000 bodies x 101 saved times on this 2-core CPU, a call 31-39 ms against 96-99 ms when
    it was formed at every time (float32; float64 60 against 207 ms), its gradient 162-174 ms
    against 467-524 ms (float64 280 against 1042 ms), a ``jvp`` 131-144 against 245-252 ms. Compiled
    as one program (an eager first call at 11 saved times took 6.0 s as single operations, 3.0 s
    compiled; a repeated call 0.77 s and 5 ms).

    The bodies are solved as a batch of a multiple of ``multiple``
    (:func:`jaxquat._threads.batch_multiple`), padded with copies of the first body whose states
    are dropped: XLA's CPU threads split a kernel over an uneven count of bodies about three
    times slower (1000 -> 1001 bodies x 101 saved times, float32, in a caller's ``jit`` on a 2-core
    Intel Xeon: 10.5 -> 33.8 ms unpadded, 10.5 ms padded to 1002)."""
    bodies = jnp.broadcast_shapes(q0.shape[:-1], omega0.shape[:-1], inertia.shape[:-2])
    n = math.prod(bodies)  # shapes are static: an int
    total = _threads.padded_batch(int(n), multiple)
    if total != n:

        def flat(x: Array, core: int) -> Array:  # the bodies on one axis, then the copies of the first
            x = jnp.broadcast_to(x, bodies + x.shape[x.ndim - core :]).reshape((n,) + x.shape[x.ndim - core :])
            return _threads.with_copies_of_first(x, total)

        tensors = flat(inertia, 2) if inertia.ndim > 2 else inertia
        sim = _exact_simulate(flat(q0, 1), flat(omega0, 1), tensors, ts, principal)
        qs, ws = (x[:n].reshape(bodies + x.shape[1:]) for x in (sim.q, sim.omega))
        return Simulation(qs, ws, None)
    if principal:  # rotate to principal axes and back
        moments, q_axes, r, q0, omega0 = principal_frame.to_principal(inertia, q0, omega0)
    else:
        moments = jnp.diagonal(inertia, axis1=-2, axis2=-1)
    bodies = jnp.broadcast_shapes(q0.shape[:-1], omega0.shape[:-1], moments.shape[:-1])
    q0, omega0, moments = (jnp.broadcast_to(x, bodies + x.shape[-1:]) for x in (q0, omega0, moments))
    qs, ws = propagate(q0, omega0, moments, jnp.broadcast_to(ts - ts[0], bodies + ts.shape))
    if principal:  # the time axis is last among the batch axes here
        qs, ws = principal_frame.from_principal(qs, ws, q_axes[..., None, :], r[..., None, :, :])
    return Simulation(qs, ws, None)


def _check_times(ts, ts_host, dt0, solver):
    """``ts`` finite and strictly increasing, ``dt0`` finite and positive, ``solver`` a diffrax
    solver: ``ValueError``/``TypeError`` naming the argument where the values are known (an
    eager call or a concrete ``ts``); a traced ``ts`` is checked at run time (``eqx.error_if``)."""
    if solver is not None:
        import diffrax  # a solver was given: its caller has imported diffrax already

        if not isinstance(solver, diffrax.AbstractSolver):
            raise TypeError(
                f"argument 'solver' must be a diffrax solver instance (e.g. jaxquat.RKMK4()), got {solver!r}"
            )
    if dt0 is not None and not _checks.is_traced(dt0):
        value = np.asarray(dt0)
        if value.shape != () or not np.isfinite(value) or value <= 0:
            raise ValueError(f"argument 'dt0' must be a finite positive step size, got {dt0!r}")
    message = "argument 'ts' must be finite and strictly increasing"
    if ts_host is not None:
        if not np.all(np.isfinite(ts_host)) or not np.all(np.diff(ts_host) > 0):
            raise ValueError(f"{message}, got {ts_host}")
        return ts
    import equinox as eqx  # a traced ts: checked at run time

    return eqx.error_if(ts, ~(jnp.all(jnp.isfinite(ts)) & jnp.all(ts[1:] > ts[:-1])), message)


def _is_concrete_diagonal(inertia) -> bool:
    """A concrete tensor with zero off-diagonal entries (traced values count as full)."""
    if _checks.is_traced(inertia):
        return False
    return not np.any(np.asarray(inertia) * (1 - np.eye(3)) != 0)
