"""One call to simulate rigid bodies: ``simulate(q0, omega0, inertia, ts, ...)``."""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from . import _checks
from .algebra import _conjugate, _multiply
from .conversions import _to_matrix
from .integrators import RKMK45, EulerPoinsotSplit, RigidBodySplit, _RKMK
from .rigid_body import RigidBody
from .skew import _matvec
from .torque_free import principal_axes

__all__ = ["Simulation", "simulate"]


class Simulation(NamedTuple):
    """Result of :func:`simulate`: attitudes ``q`` ``(*batch, len(ts), 4)``, body angular
    velocities ``omega`` ``(*batch, len(ts), 3)`` and diffrax's ``solution`` (batched)."""

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
    (a step size per body) with an adaptive solver. ``torque``: ``fn(t, q, w, args)`` in
    ``torque_frame``, written for one body (``q`` ``(4,)``, ``w`` ``(3,)``; it is vmapped
    over a batch, ``args`` shared).

    ``solver`` defaults to :class:`jaxquat.EulerPoinsotSplit` when there is no
    torque: the exact Euler-Poinsot flow, one step from each saved time to the
    next (``diffrax.StepTo(ts)``), error at rounding level at any ``t``. With a
    torque it defaults to :class:`jaxquat.RKMK45` with a PID controller
    (``rtol``, ``atol``) made to step exactly onto every ``ts`` (so saved
    states are step ends, not interpolants). A fixed-step solver
    (``LieEuler``, ``RKMK4``, the splittings, or any diffrax solver without an
    error estimate) needs ``dt0``. The splitting solvers (``RigidBodySplit*``,
    ``EulerPoinsotSplit*``) work in principal axes: a full (or traced) tensor
    is diagonalised with :func:`jaxquat.principal_axes` and the results are
    rotated back (its derivative needs distinct principal moments). ``adjoint`` defaults to diffrax's
    ``RecursiveCheckpointAdjoint``; ``progress=True`` shows a tqdm bar.
    """
    q0 = _checks.quat(q0, "q0")
    omega0 = _checks.vec3(omega0, "omega0")
    inertia = _checks.inertia(inertia)
    ts = _checks.scalar_like(ts, "ts")
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"argument 'ts' must be shaped (n,) with n >= 2, got shape {tuple(ts.shape)}")
    q0, omega0, inertia = _checks.broadcast_batch([q0, omega0, inertia], ["q0", "omega0", "inertia"], [1, 1, 2])
    ts = ts.astype(q0.dtype)
    if solver is None:
        solver = EulerPoinsotSplit() if torque is None else RKMK45()
    adaptive = _has_error_estimate(solver)
    # Torque-free, the exact flow needs no step control: step straight from one saved time to the next.
    exact = isinstance(solver, EulerPoinsotSplit) and torque is None and dt0 is None
    if not (adaptive or exact) and dt0 is None:
        raise ValueError(f"argument 'dt0' is required with the fixed-step solver {type(solver).__name__}")
    principal = isinstance(solver, RigidBodySplit) and not _is_concrete_diagonal(inertia)
    if max_steps is None:
        # numpy, not jnp: inside jit even a concrete ts would be traced by ts[-1] - ts[0]
        span = None if isinstance(ts, jax.core.Tracer) else abs(float(np.asarray(ts)[-1] - np.asarray(ts)[0]))
        if exact:
            max_steps = len(ts)
        else:
            max_steps = 100_000 if (adaptive or span is None) else math.ceil(span / abs(dt0)) + len(ts) + 16
    if exact:
        controller = diffrax.StepTo(ts)
    elif adaptive:
        controller = diffrax.ClipStepSizeController(diffrax.PIDController(rtol=rtol, atol=atol), step_ts=ts)
    else:
        controller = diffrax.ConstantStepSize()
    adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint
    meter = diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter()

    def solve(q, w, inertia_1, torque_fn):
        """One diffeqsolve of a body, or of a whole batch stacked on the leading axis."""
        if principal:  # the splittings work in principal axes: rotate there and back
            moments, q_axes = principal_axes(inertia_1)
            r = _to_matrix(q_axes)
            q, w = _multiply(q, q_axes), _matvec(jnp.swapaxes(r, -1, -2), w)
            inertia_1 = moments[..., None] * jnp.eye(3, dtype=moments.dtype)
        term = diffrax.ODETerm(RigidBody(inertia_1, torque_fn, torque_frame))
        sol = diffrax.diffeqsolve(
            term, solver, ts[0], ts[-1], dt0, (q, w), args=args, saveat=diffrax.SaveAt(ts=ts),
            stepsize_controller=controller, adjoint=adjoint, max_steps=max_steps, progress_meter=meter,
        )
        qs, ws = sol.ys
        if principal:
            qs, ws = _multiply(qs, _conjugate(q_axes)[None]), _matvec(r[None], ws)
        return qs, ws, sol

    batch = q0.shape[:-1]
    if not batch:
        return Simulation(*solve(q0, omega0, inertia, torque))
    n = len(ts)
    flat = [x.reshape((-1,) + x.shape[len(batch):]) for x in (q0, omega0, inertia)]
    if adaptive:  # each body its own step sizes
        qs, ws, sol = jax.vmap(lambda q, w, i: solve(q, w, i, torque))(*flat)
    else:  # fixed steps: one solve of the stacked batch (diffrax's per-step work is shared)
        per_body = None if torque is None else jax.vmap(torque, in_axes=(None, 0, 0, None))
        qs, ws, sol = solve(*flat, per_body)
        qs, ws = jnp.swapaxes(qs, 0, 1), jnp.swapaxes(ws, 0, 1)
    return Simulation(qs.reshape(batch + (n, 4)), ws.reshape(batch + (n, 3)), sol)


def _is_concrete_diagonal(inertia) -> bool:
    """A concrete tensor with zero off-diagonal entries (traced values count as full)."""
    if isinstance(inertia, jax.core.Tracer):
        return False
    return not np.any(np.asarray(inertia) * (1 - np.eye(3)) != 0)


def _has_error_estimate(solver) -> bool:
    """Whether a solver returns an error estimate (so a PID controller can adapt its step)."""
    if isinstance(solver, _RKMK):
        return len(solver.tableau[3]) > 0
    return isinstance(solver, diffrax.AbstractAdaptiveSolver)
