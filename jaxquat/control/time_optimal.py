"""Minimum-time reorientation of a rigid body under per-axis torque bounds.

:func:`minimum_time_reorientation` solves it by direct multiple shooting and the interior-point
method of :mod:`jaxquat.control.optimal_control` (the default), or by the single-shooting solver of this
module (``method="single_shooting"``), described here.

Problem: find the final time ``T`` and a body torque ``u(t)`` with ``|u_i| <= b_i`` that
take ``(q0, w0)`` to ``(qf, wf)`` in least time, for the rigid body
``q' = 1/2 q (0, w)``, ``I w' = u - w x I w`` (body frame; [S] eqs. (16), (19)).

Transcription (direct, single shooting): time runs on ``s in [0, 1]`` with
``t = T s``; the torque is constant on ``intervals`` equal pieces,
``u_i = b_i sin(p_i)`` (smooth, bounded, and saturation is a stationary point at
``p = +-pi/2``, so bang-bang arcs are reachable without infinite parameters);
``T = T_ref exp(sigma)``. Each piece is integrated with ``substeps`` RKMK4 steps
(:mod:`jaxquat.integration.lie_solvers`; ``|q| = 1`` to rounding). The six terminal conditions
``c = (minus(q(T), qf), w(T) - wf)`` enter an augmented Lagrangian
``T + lambda . c + mu/2 |c|^2``, minimised over ``(sigma, p)`` by optimistix's L-BFGS; the
multipliers are updated after each inner solve and ``mu`` grows by 10 when ``|c|``
has not fallen by 4. After each inner solve a copy of the iterate is projected onto
``c = 0`` by a few Gauss-Newton minimum-norm steps (``J`` by forward mode, 6 rows),
which changes ``T`` by ``O(|c|)``; each start keeps its shortest projected iterate with
``|c| <= tol`` (the last penalty iterations can oscillate). Several starts run side
by side (``vmap``). Each start's best iterate is then converged by Newton's method on the
KKT conditions (SQP with the exact Hessian of the Lagrangian, ``refine`` steps); the
result is the shortest feasible start among those whose KKT residual fell below 1e-8
(among all feasible ones if none did).

Reproducibility: XLA's CPU code, and so the rounding, depends on the vector ISA (AVX2,
AVX-512, ...), not on the thread count, and the fixed-budget L-BFGS phase amplifies
rounding into differences of 1e-3 in the time. A start converged to its KKT point no
longer depends on its path: the suite's 180-degree problem gives the same time to 2e-16
under XLA's AVX-512, AVX2 and SSE4.2 code. Where the discrete problem has several local
optima close together (the suite's asymmetric 10-interval problem has KKT points at
1.918171, 1.918318 and 1.918498), which one a start reaches can still depend on the ISA:
FAST settings (10 intervals, 4 starts) give 1.9182356290060518 under AVX-512 and
1.9181217122804963 under AVX2 and SSE4.2 (``benchmarks/reproducibility.py``; the earlier
optax L-BFGS gave 1.9181217 under AVX-512 and 1.9186739 under AVX2). Hence the interior-point
default, whose starts all converge by Newton steps (the same problem: 1.918121717830074 under
every ISA and thread count tried).

Starts: start 0 is the eigenaxis rest-to-rest bang-bang profile (the rotation
about the fixed axis of ``q0* qf``), scaled to 80 % of the bound and perturbed, since
exactly on it the off-axis gradients vanish; the other starts are generic:
``p ~ N(0, 1)`` per axis and interval. ``init=`` a previous result warm-starts
from its time and its torque, resampled onto the new intervals (use it to refine
the discretisation).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import equinox as eqx
import numpy as np
import optimistix as optx
from jax import Array
from jax.flatten_util import ravel_pytree
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _trig
from ..mechanics.inertia import validated
from ..manifold.lie import minus
from .optimal_control import (
    ReactionWheels,
    check_grid,
    check_resolution,
    check_starts,
    constrained_minimum_time,
    float64_hint,
    per_axis_bound,
)
from .controlled_model import ControlledModel
from .transcription import ConstrainedReorientation, held_torque_states, solver_jit

__all__ = ["Reorientation", "minimum_time_reorientation"]

_MEMORY = 20  # L-BFGS history
_MU_MAX = 1e5  # penalty cap; the multipliers do the rest
_POLISH_STEPS = 4  # Gauss-Newton projection steps onto the terminal conditions
_CONVERGED = 1e-8  # KKT residual below which a refined start counts as a converged local optimum


class Reorientation(NamedTuple):
    """Result of :func:`minimum_time_reorientation` (body frame throughout).

    ``time`` the final time; ``ts`` ``(intervals * substeps + 1,)`` the integrator's
    grid; ``q`` ``(len(ts), 4)`` and ``omega`` ``(len(ts), 3)`` the trajectory on it;
    ``torque`` ``(len(ts), 3)`` the torque on ``[ts[k], ts[k+1])`` (the last row repeats);
    ``controls`` ``(intervals, 3)`` the torque per interval; ``violation`` the norm of
    the terminal residual ``(minus(q(T), qf), w(T) - wf)``; ``start_times``
    ``(starts,)`` each start's refined time where it is a candidate (``inf`` if not);
    ``history`` one ``(time, violation)`` row per outer iteration for the best start;
    ``multipliers`` ``(6,)`` the KKT multipliers ``lam`` of the terminal conditions;
    ``switching`` ``(intervals, 3)`` the discrete switching function
    ``sigma = d(lam . c)/du`` (stationarity ``sigma b cos(p) = 0``: a control with
    ``sigma != 0`` is on a bound); ``kkt_residual`` ``|(grad T + J^T lam, c)|``.
    """

    time: Array
    ts: Array
    q: Array
    omega: Array
    torque: Array
    controls: Array
    violation: Array
    start_times: Array
    history: Array
    multipliers: Array
    switching: Array
    kkt_residual: Array


def _rollout(inertia, q0, w0, time, u, substeps: int):
    """The final state of :func:`jaxquat.control.transcription.held_torque_states` (RKMK4 through the
    piecewise-constant torque ``u`` ``(n, 3)`` over ``[0, time]``)."""
    qs, ws = held_torque_states(inertia, q0, w0, time, u, substeps)
    return qs[-1], ws[-1]


def _trajectory(x, pr: _Problem, *, substeps: int):
    """The returned trajectory of the chosen start ``x``: ``(time, u, ts, qs, ws, torque,
    violation)``, the states on the flat grid (the first row ``(q0, w0)``), the torque held per
    interval (its last value repeated at ``ts[-1]``), the final state's residual norm. One compiled
    program: formed eagerly, a first call ran 88 compilations in all, now 27 (10 intervals, 4 starts,
    float64, the same time to the bit)."""
    time, u = _unpack(x, pr)
    qs, ws = held_torque_states(pr.inertia, pr.q0, pr.w0, time, u, substeps)
    ts = jnp.linspace(0.0, 1.0, u.shape[0] * substeps + 1, dtype=qs.dtype) * time
    torque = jnp.repeat(u, substeps, axis=0)
    torque = jnp.concatenate([torque, torque[-1:]])
    violation = jnp.linalg.norm(_residual(qs[-1], ws[-1], pr.qf, pr.wf))
    return time, u, ts, qs, ws, torque, violation


def _residual(q, w, qf, wf):
    return jnp.concatenate([minus(q, qf), w - wf])


def _lbfgs(f, x0, iters: int):
    """``iters`` optimistix L-BFGS steps (history ``_MEMORY``, backtracking Armijo line search)
    on the scalar ``f`` from ``x0`` (any pytree) in one ``lax.scan``, with no stopping test.

    Why optimistix and not optax's L-BFGS (this solver's earlier choice): optax's zoom line search
    traces ``f`` and its gradient at three call sites (the state's cached value, the bracketing
    and the zoom phases), so the rollout and its adjoint compiled three times, and under the
    starts' ``vmap`` every branch of the ``lax.cond`` between them ran. optimistix evaluates
    ``f`` once per step. Measured on the suite's 10-interval problem (4 starts, 80 steps, this
    2-core CPU): the inner solve traced in 2.9 s against 6.9 s and compiled in 6.0 s against
    10.5 s."""
    solver = optx.LBFGS(rtol=0.0, atol=0.0, history_length=_MEMORY)

    def fn(y, _):
        return f(y), None

    f_struct = jax.ShapeDtypeStruct((), jnp.result_type(*jax.tree_util.tree_leaves(x0)))
    state = solver.init(fn, x0, None, {}, f_struct, None, frozenset())
    arrays, static = eqx.partition(state, eqx.is_array)  # the state holds functions: carry its arrays

    def body(carry, _):
        y, arrays = carry
        y, state, _ = solver.step(fn, y, None, {}, eqx.combine(arrays, static), frozenset())
        return (y, eqx.partition(state, eqx.is_array)[0]), None

    (x, _), _ = jax.lax.scan(body, (x0, arrays), None, length=iters)
    return x


def _eigenaxis(q0, qf) -> tuple[float, np.ndarray]:
    """Angle and unit axis of the rotation from ``q0`` to ``qf`` (body frame; x if none)."""
    rotvec = np.asarray(minus(qf, q0))
    theta = float(np.linalg.norm(rotvec))
    return theta, (rotvec / theta if theta > 0 else np.array([1.0, 0.0, 0.0]))


def _reference_time(inertia, bound, theta, axis, w0, wf) -> float:
    """Eigenaxis rest-to-rest bang-bang time ``2 sqrt(theta / a)`` plus ``|wf - w0| / a``, with
    ``a`` the largest angular acceleration about the eigenaxis that the bounds allow."""
    need = np.abs(np.asarray(inertia, np.float64) @ axis)
    accel = float(np.min(np.where(need > 1e-12, np.asarray(bound, np.float64) / np.maximum(need, 1e-300), np.inf)))
    return 2.0 * math.sqrt(theta / accel) + float(np.linalg.norm(np.asarray(wf) - np.asarray(w0))) / accel


def _initial_controls(key, starts, intervals, bound, axis, init):
    """Torque parameters ``p`` ``(starts, intervals, 3)``."""
    keys = jax.random.split(key, 2)
    if init is not None:  # warm start: hold the previous torque on the new grid, small perturbations
        held = _held_controls(init, intervals, bound, 0.999)
        p = held[None] + 0.01 * np.array(jax.random.normal(keys[0], (starts, intervals, 3)))
        p[0] = held
        return p
    sign = np.where(np.arange(intervals) < intervals / 2, 1.0, -1.0)[:, None]
    eigen = np.arcsin(0.8 * np.clip(sign * axis / np.max(np.abs(axis)), -1, 1))
    p = np.array(jax.random.normal(keys[1], (starts, intervals, 3)))
    p[0] = eigen + 0.3 * p[0]
    return p


def _held_controls(init, intervals: int, bound, limit: float) -> np.ndarray:
    """The torque parameters ``p = arcsin(u / b)`` ``(intervals, 3)`` of an earlier result's torque
    held on a grid of ``intervals``, ``u / b`` clipped to ``[-limit, limit]`` (below 1 for a start
    of the augmented-Lagrangian phase: at ``p = +-pi/2`` the torque's derivative is 0)."""
    old = np.asarray(init.controls)
    idx = np.minimum((np.arange(intervals) + 0.5) * old.shape[0] // intervals, old.shape[0] - 1).astype(int)
    return np.arcsin(np.clip(old[idx] / np.asarray(bound), -limit, limit))


class _Problem(NamedTuple):
    inertia: Array
    bound: Array
    q0: Array
    w0: Array
    qf: Array
    wf: Array
    t_ref: Array


def _unpack(x, pr: _Problem):
    return pr.t_ref * jnp.exp(x["sigma"]), pr.bound[None, :] * _trig.sin(x["p"])


def _terminal_residual(x, pr: _Problem, substeps: int):
    time, u = _unpack(x, pr)
    q, w = _rollout(pr.inertia, pr.q0, pr.w0, time, u, substeps)
    return _residual(q, w, pr.qf, pr.wf)


def _polish(x, pr: _Problem, substeps: int):
    """Gauss-Newton projection onto ``c = 0``: minimum-norm steps ``-J^T (J J^T)^-1 c`` (6
    constraints; ``J`` by forward mode), which move the time and the torque by ``O(|c|)``."""
    flat, unravel = ravel_pytree(x)

    def residual(z):
        return _terminal_residual(unravel(z), pr, substeps)

    def newton(z, _):
        jac = jax.jacfwd(residual)(z)
        gram = jac @ jac.T + 1e-12 * jnp.eye(6, dtype=z.dtype)
        return z - jac.T @ jnp.linalg.solve(gram, residual(z)), None

    flat, _ = jax.lax.scan(newton, flat, None, length=_POLISH_STEPS)
    return unravel(flat)


def _switching(x, lam, pr: _Problem, substeps: int):
    """The discrete switching function ``sigma = d(lam . c)/du`` ``(intervals, 3)`` at fixed time:
    stationarity in ``p`` is ``sigma b cos(p) = 0``, so a control with ``sigma != 0`` is on a bound."""
    time, u = _unpack(x, pr)
    return jax.grad(lambda uu: lam @ _residual(*_rollout(pr.inertia, pr.q0, pr.w0, time, uu, substeps), pr.qf, pr.wf))(
        u
    )


def _refine(x, pr: _Problem, substeps: int, iters: int):
    """Newton's method on the KKT conditions of ``min T s.t. c = 0`` (SQP with the exact Hessian),
    one start at a time (vmapped): ``[[H, J^T], [J, 0]] (dz, lam) = -(grad T, c)``, the first
    step from the least-squares multipliers ``lam = -(J J^T)^-1 J grad T``.

    Why: the augmented-Lagrangian phase stops where its fixed iteration budget ends, and where
    that is depends on rounding, so on the CPU's vector ISA (XLA's AVX2 and AVX-512 code gave
    times 1.6e-3 apart on the suite's 180-degree problem). At the KKT point the answer no longer
    depends on the path. Full Newton steps (the residual may rise before it falls
    quadratically; a merit line search and a Hessian shift were tried and stalled every start
    of the suite's problems); each start returns the iterate with the least KKT residual
    ``|(grad T + J^T lam, c)|`` met on the way, so it never ends worse than it began.
    ``grad T`` is ``T`` in the slot of ``sigma`` (``T = T_ref exp(sigma)``); ``J`` by reverse mode
    (6 rows).
    Returns per start: the iterate, its multipliers, KKT residual, time, ``|c|`` and
    switching function."""
    flat0, unravel = ravel_pytree(jax.tree_util.tree_map(lambda a: a[0], x))
    n = flat0.shape[0]
    eye6 = jnp.eye(6, dtype=flat0.dtype)

    def residual(z):
        return _terminal_residual(unravel(z), pr, substeps)

    def step(carry, k):
        z, mult, best = carry
        c = residual(z)
        time = lambda y: _unpack(unravel(y), pr)[0]  # noqa: E731
        grad_t = jax.grad(time)(z)  # (0, ..., T) in sigma's slot
        # The constraints' Hessians (6, n, n) forward over forward, their Jacobian J coming with
        # them: _refine compiled in 8.7 s against 12.1 s for forward over reverse (the suite's
        # 10-interval problem, 4 starts, this 2-core CPU).
        hess_c, jac = jax.jacfwd(lambda y: (jax.jacfwd(residual)(y),) * 2, has_aux=True)(z)
        mult = jnp.where(k == 0, -jnp.linalg.solve(jac @ jac.T + 1e-14 * eye6, jac @ grad_t), mult)
        g = grad_t + jac.T @ mult
        res = jnp.sqrt(g @ g + c @ c)
        best = jax.tree_util.tree_map(lambda a, b: jnp.where(res < best[2], a, b), (z, mult, res), best)
        hess = jax.hessian(time)(z) + jnp.einsum("i,izw->zw", mult, hess_c)
        kkt = jnp.block([[hess, jac.T], [jac, jnp.zeros((6, 6), z.dtype)]])
        sol = jnp.linalg.solve(kkt, -jnp.concatenate([grad_t, c]))
        ok = jnp.all(jnp.isfinite(sol))  # a singular system leaves the iterate where it is
        return (jnp.where(ok, z + sol[:n], z), jnp.where(ok, sol[n:], mult), best), None

    def one(z):
        zero, inf = jnp.zeros(6, z.dtype), jnp.asarray(jnp.inf, z.dtype)
        # iters + 1 evaluations: the last one only scores the final iterate (its step is dropped).
        (_, _, (z, mult, res)), _ = jax.lax.scan(step, (z, zero, (z, zero, inf)), jnp.arange(iters + 1))
        xi = unravel(z)
        violation = jnp.linalg.norm(_terminal_residual(xi, pr, substeps))
        return xi, mult, res, _unpack(xi, pr)[0], violation, _switching(xi, mult, pr, substeps)

    return jax.vmap(one)(jax.vmap(lambda xi: ravel_pytree(xi)[0])(x))


def _solve(x, lam, mu, pr: _Problem, substeps: int, inner: int):
    """One augmented-Lagrangian inner solve per start (vmapped), then the projected copy."""

    def one(x1, lam1, mu1):
        def lagrangian(z):
            c = _terminal_residual(z, pr, substeps)
            return _unpack(z, pr)[0] + lam1 @ c + 0.5 * mu1 * c @ c

        x1 = _lbfgs(lagrangian, x1, inner)
        x_pol = _polish(x1, pr, substeps)
        return (
            x1,
            _terminal_residual(x1, pr, substeps),
            x_pol,
            _terminal_residual(x_pol, pr, substeps),
            _unpack(x_pol, pr)[0],
        )

    return jax.vmap(one)(x, lam, mu)


def minimum_time_reorientation(
    inertia: Float[ArrayLike, "3 3"],
    torque_bound: Float[ArrayLike, "3"] | None,
    q0: Float[ArrayLike, "4"],
    qf: Float[ArrayLike, "4"],
    omega0: Float[ArrayLike, "3"] | None = None,
    omegaf: Float[ArrayLike, "3"] | None = None,
    *,
    intervals: int = 30,
    substeps: int = 4,
    starts: int = 8,
    seed: int = 0,
    init: Reorientation | ConstrainedReorientation | None = None,
    outer: int | None = None,
    inner: int | None = None,
    mu: float | None = None,
    tol: float | None = None,
    refine: int | None = None,
    progress: bool | None = None,
    throw: bool = True,
    rate_bound: float | None = None,
    keep_out: Sequence = (),
    keep_in: Sequence = (),
    mesh=None,
    method: str = "interior_point",
    wheels: ReactionWheels | None = None,
    model: ControlledModel | None = None,
) -> Reorientation | ConstrainedReorientation:
    """Shortest time ``T`` and bounded body torque taking ``(q0, omega0)`` to ``(qf, omegaf)``.

    Minimises ``T`` subject to ``q' = 1/2 q (0, w)``, ``I w' = u - w x I w``
    (body frame, [S] eqs. (16), (19)), ``|u_i(t)| <= torque_bound[i]``,
    ``q(T) = +-qf`` and ``w(T) = omegaf``; rates default to rest. ``q0`` and ``qf``
    are normalised. The torque is held constant on ``intervals`` equal pieces, each integrated
    by ``substeps`` RKMK4 steps. Use float64 (``jax_enable_x64``).

    ``method="interior_point"`` (the default): direct multiple shooting solved by the
    interior-point method of :func:`jaxquat.constrained_minimum_time`, ``starts`` starts side by
    side (``seed``; ``init`` an earlier result to warm-start from, e.g. to refine ``intervals``, or
    ``mesh`` from :func:`jaxquat.refine_mesh` to refine near the switches),
    each converged to a KKT error of 1e-9; returns a :class:`jaxquat.ConstrainedReorientation`
    (``time``, ``ts``, ``q``, ``omega``, ``torque``, ``controls``, ``violation``, ``switching``,
    ``start_costs``, ...). Also takes ``rate_bound`` (``|w_i| <= rate_bound``), ``keep_out`` and
    ``keep_in`` (``(body_axis (3,), inertial_direction (3,), half_angle_rad)`` triples: cones the
    body axis's inertial image must stay out of, or in). Its result does not
    depend on the CPU's vector instructions or thread count (measured: the same time to the last
    digit or to 1e-15 under XLA's AVX-512, AVX2 and SSE4.2 code, 1 to 4 host devices, one core).

    ``method="single_shooting"``: this module's solver (module docstring), torque bounds only:
    torque ``b sin(p)``, augmented Lagrangian with ``outer`` multiplier updates of ``inner``
    L-BFGS iterations, ``starts`` starts in parallel (start 0 the perturbed eigenaxis profile,
    the others random with ``seed``) or ``init`` (a previous result), then ``refine``
    Newton-KKT steps per start. Returns the shortest converged start with violation ``<= tol``
    (or the shortest feasible one) as a :class:`Reorientation`. With ``init``, the earlier torque
    held on this grid is one of the candidates where it meets ``tol`` (in the place of the start
    that ended longest), so a warm start from a converged result on its own grid never returns a
    longer time (on a finer grid the held torque is a candidate only where it still meets
    ``tol``, and a converged start is preferred to it). Which local optimum its
    fixed-budget L-BFGS phase reaches can depend on the CPU's rounding (the module docstring);
    ``tol`` (1e-6), ``outer`` (10), ``inner`` (200), ``mu`` (10), ``refine`` (20) and ``progress``
    apply to it only (given with the interior-point method they raise ``ValueError``). If no
    start meets ``tol``, raises ``RuntimeError`` naming the least violation (as optimistix does
    with ``throw=True``: an infeasible answer is not returned as a plausible time); with
    ``throw=False`` the least violating start is returned instead, for inspection. Before any
    solve, a grid too coarse for the motion raises ``ValueError`` (the body would turn more than
    0.5 rad per integration step at the reference time, e.g. ``omega0 = (100, 0, 0)`` with unit
    torque; the message gives the ``intervals * substeps`` needed). With no feasible start, the
    outer loop stops early once the least violation stalls (falls by less than 10 % in two outer
    iterations while above ``100 tol``) or reaches rounding level (``10 eps`` of the dtype, so
    with a ``tol`` below it). ``progress=True`` shows a tqdm bar with the time and violation.
    Runs eagerly (the inner solves are jitted).

    The discrete optimum approaches the continuous one from above as ``intervals``
    grows; compare two discretisations to see how far it has converged.

    Args:
        inertia: body inertia tensor ``(3, 3)``.
        torque_bound: per-axis body torque bound ``(3,)``, positive (a scalar: the same on each
            axis).
        q0: initial attitude ``(..., 4)`` (normalised; leading axes: a batch, interior point only).
        qf: target attitude ``(..., 4)`` (either sign).
        omega0: initial body rate ``(..., 3)``; default rest.
        omegaf: final body rate ``(..., 3)``; default rest.
        intervals: number of torque intervals ``N``.
        substeps: RKMK4 steps per interval.
        starts: starts solved side by side.
        seed: the random draw of the starts after the first.
        init: an earlier result (any grid) to warm-start from.
        outer: single shooting only: augmented-Lagrangian multiplier updates (10).
        inner: single shooting only: L-BFGS iterations per update (200).
        mu: single shooting only: the penalty weight (10).
        tol: single shooting only: the terminal tolerance of an accepted start (1e-6).
        refine: single shooting only: Newton-KKT steps per start (20).
        progress: single shooting only: a tqdm bar.
        throw: raise ``RuntimeError`` when no start converges (else return the best).
        rate_bound: ``|w_i| <= rate_bound`` at every integration step (interior point).
        keep_out: ``(body_axis, inertial_direction, half_angle_rad)`` cones to stay out of.
        keep_in: cones of the same form to stay in.
        mesh: interval lengths for a non-uniform mesh (e.g. :func:`jaxquat.refine_mesh`).
        method: ``"interior_point"`` or ``"single_shooting"``.
        wheels: a :class:`jaxquat.ReactionWheels` turning the body instead of a body torque
            (then ``torque_bound=None``; interior point only; see
            :func:`jaxquat.optimal_reorientation`).
        model: a :class:`jaxquat.ControlledModel`, the user's dynamics with its own controls
            (bounded by ``torque_bound``, ``(n,)`` or a scalar; interior point only).

    Returns:
        A :class:`jaxquat.ConstrainedReorientation` (interior point) or a
        :class:`Reorientation` (single shooting): ``time``, ``ts`` ``(N substeps + 1,)``,
        ``q``, ``omega``, ``torque`` on that grid, ``controls`` ``(N, 3)``, ``violation`` and
        the method's certificate fields.
    """
    if method not in ("interior_point", "single_shooting"):
        raise ValueError(f"argument 'method' must be 'interior_point' or 'single_shooting', got {method!r}")
    single = dict(outer=outer, inner=inner, mu=mu, tol=tol, refine=refine, progress=progress)
    if method == "single_shooting" and mesh is not None:
        raise ValueError("argument 'mesh' needs method='interior_point' (the default)")
    if method == "interior_point":
        given = [name for name, v in single.items() if v is not None]
        if given:
            raise ValueError(
                f"argument(s) {', '.join(repr(n) for n in given)} apply to method='single_shooting' only "
                "(the interior-point method converges every start to a KKT error of 1e-9; for its own "
                "tol and max_iter call jaxquat.constrained_minimum_time)"
            )
        return constrained_minimum_time(
            inertia,
            torque_bound,
            q0,
            qf,
            omega0,
            omegaf,
            rate_bound=rate_bound,
            keep_out=keep_out,
            keep_in=keep_in,
            intervals=intervals,
            substeps=substeps,
            throw=throw,
            starts=starts,
            seed=seed,
            init=init,
            mesh=mesh,
            wheels=wheels,
            model=model,
        )
    for name, given in (("wheels", wheels), ("model", model)):
        if given is not None:
            raise ValueError(f"argument '{name}' needs method='interior_point' (the default)")
    if rate_bound is not None or len(keep_out) > 0 or len(keep_in) > 0:
        raise ValueError(
            "method='single_shooting' handles torque bounds only; rate_bound, keep_out and keep_in need "
            "method='interior_point' (the default)"
        )
    inertia = validated(inertia)
    if inertia.shape != (3, 3):
        raise ValueError(f"argument 'inertia' must be shaped (3, 3), got shape {tuple(inertia.shape)}")
    bound = per_axis_bound(torque_bound)
    q0 = _checks.quat(q0, "q0")
    qf = _checks.quat(qf, "qf")
    for name, x in (("torque_bound", bound), ("q0", q0), ("qf", qf)):
        if x.ndim != 1:
            raise ValueError(f"argument '{name}' must be a single value shaped ({x.shape[-1]},), got {tuple(x.shape)}")
    if not np.all(np.asarray(bound) > 0) or not np.all(np.isfinite(np.asarray(bound))):
        raise ValueError(f"argument 'torque_bound' must be positive and finite, got {np.asarray(bound)}")
    for name, x in (("q0", q0), ("qf", qf)):
        if not np.all(np.isfinite(np.asarray(x))) or not np.any(np.asarray(x) != 0):
            raise ValueError(f"argument '{name}' must be a finite non-zero quaternion, got {np.asarray(x)}")
    dtype = q0.dtype
    zeros = jnp.zeros(3, dtype)
    w0 = zeros if omega0 is None else _checks.vec3(omega0, "omega0")
    wf = zeros if omegaf is None else _checks.vec3(omegaf, "omegaf")
    if w0.shape != (3,) or wf.shape != (3,):
        raise ValueError("arguments 'omega0' and 'omegaf' must be shaped (3,)")
    for name, x in (("omega0", w0), ("omegaf", wf)):
        if not np.all(np.isfinite(np.asarray(x))):
            raise ValueError(f"argument '{name}' must be finite, got {np.asarray(x)}")
    check_grid(intervals, substeps)
    check_starts(starts)
    outer = 10 if outer is None else outer
    inner = 200 if inner is None else inner
    mu = 10.0 if mu is None else mu
    tol = 1e-6 if tol is None else tol
    refine = 20 if refine is None else refine
    q0 = q0 / jnp.linalg.norm(q0)
    qf = qf / jnp.linalg.norm(qf)
    inertia, bound, w0, wf = (jnp.asarray(x, dtype) for x in (inertia, bound, w0, wf))
    theta, axis = _eigenaxis(q0, qf)
    t_ref = float(init.time) if init is not None else _reference_time(inertia, bound, theta, axis, w0, wf)
    check_resolution(t_ref, q0, qf, w0, wf, intervals, substeps)
    p = _initial_controls(jax.random.PRNGKey(seed), starts, intervals, bound, axis, init)

    problem = _Problem(inertia, bound, jnp.asarray(q0), w0, jnp.asarray(qf), wf, jnp.asarray(t_ref, dtype))

    x = {"sigma": jnp.zeros(starts, dtype), "p": jnp.asarray(p, dtype)}  # every start at T = T_ref
    lam = jnp.zeros((starts, 6), dtype)
    mus = np.full(starts, float(mu))
    prev = np.full(starts, np.inf)
    best_time = np.full(starts, np.inf)
    best_x = jax.tree_util.tree_map(np.array, x)
    least = np.full(starts, np.inf)
    held = None
    if init is not None:  # the earlier result held exactly on this grid (the torque on its bounds)
        held = {"sigma": jnp.zeros((), dtype), "p": jnp.asarray(_held_controls(init, intervals, bound, 1.0), dtype)}
        held_violation = float(jnp.linalg.norm(_arrays.compiled(_terminal_residual, held, problem, substeps=substeps)))
    least_seen = [np.inf]
    history = []
    bar = None
    if progress:
        _checks.require_tqdm("minimum_time_reorientation")
        from tqdm.auto import tqdm

        bar = tqdm(total=outer, desc="minimum time", leave=False)
    for _ in range(outer):
        x, c, x_pol, c_pol, times = solver_jit(_solve, ("substeps", "inner"))(
            x, lam, jnp.asarray(mus, dtype), problem, substeps, inner
        )
        c = np.asarray(c)
        lam = lam + jnp.asarray(mus[:, None] * c, dtype)
        mus = np.where(np.linalg.norm(c, axis=-1) > 0.25 * prev, np.minimum(10 * mus, _MU_MAX), mus)
        prev = np.linalg.norm(c, axis=-1)
        # Candidates are the polished iterates (the AL iterate itself stays as it is).
        times, viol = np.asarray(times), np.linalg.norm(np.asarray(c_pol), axis=-1)
        better = ((viol <= tol) & (times < best_time)) | ((best_time == np.inf) & (viol < least))
        least = np.minimum(least, viol)
        for key in best_x:
            best_x[key] = np.where(
                better.reshape((-1,) + (1,) * (best_x[key].ndim - 1)), np.asarray(x_pol[key]), best_x[key]
            )
        best_time = np.where(better & (viol <= tol), times, best_time)
        k = (
            int(np.argmin(np.where(best_time < np.inf, best_time, np.inf)))
            if np.any(best_time < np.inf)
            else int(np.argmin(viol))
        )
        history.append((float(times[k]), float(viol[k])))
        # Stalled with no feasible start: the least violation over the starts fell by less than
        # 10 % in two outer iterations while above 100 tol, or it is at rounding level (10 eps,
        # reached only when tol is below it), where it moves by rounding noise whose size
        # depends on how XLA compiled the rollout. Stop and let the Newton phase try.
        if (
            len(history) >= 3
            and not np.any(best_time < np.inf)
            and (
                least.min() <= 10 * np.finfo(dtype).eps
                or (least.min() > 100 * tol and least.min() > 0.9 * least_seen[-2])
            )
        ):
            break
        least_seen.append(float(least.min()))
        if bar is not None:
            bar.set_postfix(
                time=f"{times[k]:.6f}", violation=f"{viol[k]:.1e}", feasible=int(np.sum(best_time < np.inf))
            )
            bar.update()
    if bar is not None:
        bar.close()
    if held is not None and held_violation <= tol:
        # The init, where it meets the terminal conditions on this grid, takes the place of the
        # start that ended longest (or infeasible) and is converged and chosen between as the
        # others are: from a converged init on its own grid (a KKT point, where the Newton steps
        # stay) a warm start never returns a longer time. Full
        # Newton steps from an augmented-Lagrangian iterate can reach a KKT point of a longer time
        # (session 61: the suite's asymmetric slew warm-started on its own grid, 1.9185 -> 1.9345
        # s, where derivatives changed at rounding level had moved the iterates).
        worst = int(np.argmax(best_time))
        for key in best_x:
            best_x[key][worst] = np.asarray(held[key])
    # Converge every start to its KKT point, then take the shortest feasible one: the choice is
    # made between converged optima, not between wherever each start's budget ran out.
    x_ref, mults, kkt_res, t_ref_all, viol_ref, sigmas = (
        jax.tree_util.tree_map(np.asarray, out)
        for out in solver_jit(_refine, ("substeps", "iters"))(
            {key: jnp.asarray(v) for key, v in best_x.items()}, problem, substeps, refine
        )
    )
    converged = kkt_res <= _CONVERGED
    feasible = (viol_ref <= tol) & (converged if np.any(converged & (viol_ref <= tol)) else True)
    best_time = np.where(feasible, t_ref_all, np.inf)
    if throw and not np.any(feasible):
        raise RuntimeError(
            f"minimum_time_reorientation: no start met the terminal conditions to tol = {tol:g} "
            f"(least violation {float(np.min(viol_ref)):.3g}, time {float(t_ref_all[np.argmin(viol_ref)]):.6g}). "
            "Try more outer/inner iterations, starts or intervals, and check that the torque bound can "
            "reach omegaf from omega0. Pass throw=False to get the least violating start." + float64_hint(dtype)
        )
    k = int(np.argmin(best_time)) if np.any(feasible) else int(np.argmin(viol_ref))
    xk = {key: jnp.asarray(v[k]) for key, v in x_ref.items()}
    multipliers = jnp.asarray(mults[k])
    time, u, ts, qs, ws, torque, violation = _arrays.compiled(_trajectory, xk, problem, substeps=substeps)
    switching = jnp.asarray(sigmas[k])
    return Reorientation(
        time,
        ts,
        qs,
        ws,
        torque,
        u,
        violation,
        jnp.asarray(best_time),
        jnp.asarray(history),
        multipliers,
        switching,
        jnp.asarray(kkt_res[k]),
    )
