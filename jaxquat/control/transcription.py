"""The multiple-shooting transcription of the attitude optimal-control problems (the solver
behind :mod:`jaxquat.control.optimal_control`).

Unknowns: the node states ``x_k = (q_k, w_k)`` (``k = 1 .. N``; ``(q_k, w_k, h_k)`` with
reaction wheels), a control held constant on each of ``N`` intervals (the body torque, or the
wheel torques), and (minimum time) the final time. Each interval is integrated by ``substeps``
RKMK4 steps (:mod:`jaxquat.integration.lie_solvers`, ``|q|`` kept to rounding), and its end
must meet the next node (the continuity defects). The NLP is solved by the primal-dual
interior-point method of :mod:`jaxquat.control.interior_point` with exact second derivatives.

Constraints: per-axis torque bounds ``|u_i| <= b_i``; body-rate bounds ``|w_i| <= w_max``;
wheel momentum bounds ``|h_i| <= h_max``; keep-out cones (body axis ``a`` stays at least
``alpha`` from the inertial direction ``s``: ``s . R(q) a <= cos(alpha)``, with ``R(q) a`` the
inertial image of the body axis) and keep-in cones (within ``alpha``: ``s . R(q) a >=
cos(alpha)``, e.g. an antenna kept near the Earth); rate, momentum and cone constraints hold at
every integration step (every substep's end state), not only at the nodes. Terminal
conditions: ``vec(qf* q_N) = 0`` (so ``q_N = +-qf``) and ``w_N = omegaf``; wheel momenta free.

Scaling (the method is not scale invariant; both Bilimoria-Wie's unit body and Betts' 5000
kg m^2 spacecraft are solved with the same settings): torques are divided by the bound
(or, without one, by the eigenaxis profile's peak torque), rates by the eigenaxis profile's peak
rate, wheel momenta by the inertia times that rate, the time by the eigenaxis reference time.

Initial guess: the eigenaxis rotation from ``q0`` to ``qf`` (bang-bang for minimum time, the
cubic minimum-energy profile otherwise), with the boundary rates blended in linearly; its
torque ``I a + w x I w`` is clipped to 90 % of the bound. The nodes need not be continuous: the
solver closes the defects.
"""

from __future__ import annotations

import functools
from importlib.metadata import PackageNotFoundError, version
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import threadpoolctl
from jax import Array

from .. import _arrays, _checks, _quaternion
from ..integration.fixed_step import solve_fixed_steps
from ..integration.lie_solvers import RKMK4, BodyRateTerm, body_rate
from ..manifold.lie import minus, plus
from .controlled_model import join_state, lie_field, rates, renormalised, split_state
from .interior_point import ShootingProblem, solve_shooting

__all__ = ["ConstrainedReorientation"]


class ConstrainedReorientation(NamedTuple):
    """Result of the multiple-shooting solvers (body frame throughout).

    ``time`` the final time; ``ts`` ``(N * substeps + 1,)`` the integration grid; ``q``, ``omega``
    the trajectory on it, re-integrated from ``q0`` with the returned torque (not the nodes);
    ``torque`` ``(len(ts), 3)`` (the last row repeats); ``controls`` ``(N, 3)`` the torque per
    interval; ``violation`` the largest constraint violation of the NLP (defects, terminal
    conditions, path constraints); ``cost`` the objective in physical units (the time, ``int |u|^2
    dt``, the fuel, or their weighted mix);
    ``costates`` ``(N, 7)`` the multipliers of the continuity conditions, in the NLP's scaled
    units (the discrete costates of ``(q, w)``); ``switching`` ``(N, 3)`` the discrete switching
    function ``d(costate . F)/du`` per unit torque; ``kkt_residual``; ``iterations``; ``converged``;
    ``start_costs`` ``(starts,)`` each start's cost where it converged (``inf`` where not): the result
    is the start with the least.

    With ``wheels=`` (a reaction-wheel spacecraft) the controls are the ``n`` wheel motor torques:
    ``torque`` is ``(len(ts), n)``, ``controls`` and ``switching`` ``(N, n)``, ``costates``
    ``(N, 7 + n)``, and ``wheel_momentum`` ``(len(ts), n)`` the wheels' axial momenta on ``ts``
    (``None`` for the rigid body). With ``model=`` (a :class:`jaxquat.ControlledModel`) the
    controls are the model's ``n`` inputs (shapes as with wheels), ``costates`` ``(N, 7 + m)``,
    and ``extra`` ``(len(ts), m)`` its extra states ``z`` on ``ts`` (``None`` otherwise).
    """

    time: Array
    ts: Array
    q: Array
    omega: Array
    torque: Array
    controls: Array
    violation: Array
    cost: Array
    costates: Array
    switching: Array
    kkt_residual: Array
    iterations: Array
    converged: Array
    start_costs: Array
    wheel_momentum: Array | None = None
    extra: Array | None = None


_PERTURBATION = 0.2  # scaled torque perturbation of the initial guess


class Data(NamedTuple):
    inertia: Array
    q0: Array
    w0: Array
    qf: Array
    wf: Array
    duration: Array  # the fixed time, or the reference time T_ref (minimum time)
    u_ref: Array  # (3,) torque scale
    w_ref: Array  # rate scale
    rate_bound: Array  # (inf: none)
    cones: Array  # (n, 9): body axis, inertial direction, cos(half angle), +1 keep-out / -1 keep-in, frame
    weights: Array  # (3,) of the time, int |u|^2 dt and int |u|_1 dt in the cost
    fractions: Array  # (N,) interval lengths over the duration (sum 1; used when not uniform)
    axes: Array  # (n, 3) wheel spin axes ((0, 3): the rigid body, torqued directly)
    h0: Array  # (n,) initial wheel momenta
    h_ref: Array  # wheel momentum scale
    momentum_bound: Array  # (n,) (inf: none)
    model_args: Any = None  # a user model's args (model=): data, so they do not recompile
    model_final: Any = None  # (m,) a user model's z(T) targets where Config.model_fixed


class Config(NamedTuple):
    intervals: int
    substeps: int
    min_time: bool  # a free final time, in the cost
    torque_bounded: bool
    rate_bounded: bool
    n_cones: int
    fuel: bool = False  # int |u|_1 dt in the cost: controls (v, sigma) with |v_i| <= sigma_i <= 1
    energy: bool = False  # int |u|^2 dt in the cost
    uniform: bool = True  # equal intervals (else data.fractions)
    wheels: int = 0  # reaction wheels driving the body (0: a body torque, 3 controls)
    momentum_bounded: bool = False  # |h_i| <= momentum_bound at every integration step
    # A user model (ControlledModel): its field (hashed by identity) and number of controls; the
    # extra states z take the wheel momenta's places in the data (h0, h_ref, momentum_bound).
    model: Any = None
    model_controls: int = 0
    model_quaternions: int = 0  # unit quaternions leading z, advanced on the group
    model_fixed: tuple = ()  # which entries of z(T) are given (extra_final)


def _controls_of(cfg: Config) -> int:
    """The number of physical controls: a user model's, the wheel torques, or the body torque's 3."""
    return cfg.model_controls if cfg.model is not None else (cfg.wheels or 3)


def _grid(n: int, substeps: int, fractions, dtype) -> Array:
    """The normalised integration grid ``(n * substeps + 1,)``: ``substeps`` equal steps in each
    interval, the intervals equal (``fractions=None``) or of lengths ``fractions``."""
    if fractions is None:
        return jnp.linspace(0.0, 1.0, n * substeps + 1, dtype=dtype)
    edges = jnp.concatenate([jnp.zeros(1, dtype), jnp.cumsum(fractions)])
    inner = edges[:-1, None] + fractions[:, None] * (jnp.arange(substeps, dtype=dtype) / substeps)[None]
    return jnp.concatenate([inner.ravel(), edges[-1:]])


def held_torque_states(inertia, q0, w0, time, u, substeps: int, fractions=None):
    """Every state ``(q, w)`` of RKMK4 through the piecewise-constant torque ``u`` ``(n, 3)`` over
    ``[0, time]``, ``substeps`` steps per interval: ``(n * substeps + 1, 4)`` and ``(.., 3)``
    (the first row the initial state); the intervals are equal, or ``fractions`` ``(n,)`` of
    ``time``. Shared by the shooting stages (``n = 1``), the returned
    trajectories and :func:`jaxquat.minimum_time_reorientation`'s rollout.

    One flat grid of ``n * substeps`` steps, each with its interval's torque, not ``n``
    intervals of ``substeps`` steps: the derivatives of nested scans (the Newton-KKT Hessian of
    the single-shooting solver among them) compiled slower, that solver's suite fixture 58.5 s
    against 45.8 s."""

    # I^-1 once, outside the steps, and Euler's equations as 3x3 products: the per-component
    # solve of _rates.euler_body inside a stage took 570 of the 3460 operations of a stage Hessian
    # (the suite's 12-interval minimum-energy slew: 14.3 s from the call to the compiled solver,
    # 10.5 s with this and the switching function from the solver's control Jacobian).
    inverse = _arrays.symmetric_inverse(inertia)

    def field(t, y, u_k):  # the Lie-algebra form: the body rate itself on the quaternion leaf
        return y[1], inverse @ (u_k - jnp.cross(y[1], inertia @ y[1]))

    return _held(RKMK4(layout="rows"), field, (q0, w0), time, u, substeps, fractions)


def held_wheel_states(inertia, axes, q0, w0, h0, time, u, substeps: int, fractions=None):
    """:func:`held_torque_states` for the reaction-wheel spacecraft (the gyrostat of
    :class:`jaxquat.ReactionWheelSpacecraft`): the wheel torques ``u`` ``(n_int, n)`` held per
    interval, ``J w' = -A u - w x (J w + A h)``, ``h' = u``; returns ``(qs, ws, hs)`` on the flat
    grid, RKMK4 on the quaternion leaf."""

    inverse = _arrays.symmetric_inverse(inertia)  # as in held_torque_states

    def field(t, y, u_k):
        q, w, h = y
        total = inertia @ w + h @ axes
        return w, inverse @ (-(u_k @ axes) - jnp.cross(w, total)), u_k

    return _held(
        RKMK4(quaternions=(True, False, False), layout="rows"), field, (q0, w0, h0), time, u, substeps, fractions
    )


def _held(solver, field, y0, time, u, substeps: int, fractions):
    """``solver`` through the Lie-algebra vector field ``field(t, y, u_k)`` from ``y0`` over
    ``[0, time]`` on one flat grid, each step with its interval's control ``u_k``. The solvers
    here hold the quaternion as rows (``layout="rows"``): on the component layout, the Lie
    solvers' default, Bilimoria-Wie at 80 intervals solved in 1.2-1.6 s against 0.92 s and
    reached its first result in 10.0-10.2 s against 8.9-9.0 s (this 2-core CPU, two runs each;
    the same optimum), the second derivatives of these one-interval rollouts being larger.

    Each step is rematerialised in reverse mode (``solve_fixed_steps``' default ``checkpoint``)
    since session 85; before, every step's residuals were stored. The gradient in ``u`` of a
    final-state loss through ``minimum_time_reorientation``'s rollout (80 intervals x 4 steps,
    ``vmap`` over 1000 bodies; one pinned core of a 2-core AMD EPYC, two processes each), stored
    -> rematerialised: float32 308-317 -> 240-248 ms (3.86-3.97x -> 3.04-3.05x the forward pass),
    float64 358-361 -> 199-224 ms (5.65-5.72x -> 3.19-3.52x); the forward pass and forward mode
    are the same program. The interior-point solver's optima are the same to the bit, and its first
    calls no slower (float64, first call and a later solve): Bilimoria-Wie, 30 intervals, 8 starts,
    10.5 -> 9.7 s and 0.95 -> 0.94 s; 20 intervals, 16 starts (reverse-mode Hessians) 12.4-13.0
    -> 10.7-11.8 s and 0.61-0.62 -> 0.56-0.62 s; three reaction wheels, 20 intervals, 4 starts
    10.2 -> 9.0 s and 0.19 -> 0.18 s. ``method="single_shooting"`` (its Lagrangian's gradient runs
    through this rollout in reverse mode), Bilimoria-Wie at 30 intervals: the time within an ulp,
    59.0 -> 59.6 s and 38.6 -> 39.1 s, one run each.

    In float32 the rematerialised steps keep the results of their 3x3 products
    (``jax.checkpoint_policies.dots_with_no_batch_dims_saveable``, session 87). XLA on CPU runs
    these products (8 in the compiled forward pass) as YNNPACK fusions, which cost the float32
    forward pass 113 ms against 86 ms in float64, and each rematerialised step paid them again.
    The same rollout, one pinned core of this 2-core EPYC, two processes each
    alternated, all -> float32 products kept: the gradient in ``u`` 349-350 -> 301-306 ms (3.09x ->
    2.66-2.71x a forward pass of 113 ms), in ``w0`` 346-347 -> 301-304 ms (3.06-3.07x ->
    2.67-2.68x), the gradients the same to the printed nine digits. In float64 the policy measured
    289-295 against 289-292 ms this session and 243-248 against 218-222 ms in session 85, so it
    stays off there. Written as element-wise sums (``_arrays.matvec``), the products took the
    float32 forward pass 113 -> 88 ms but its gradient only to 280-294 ms, 3.2-3.3x, and float64's
    to 305-324 ms."""
    ts = _grid(u.shape[0], substeps, fractions, y0[1].dtype) * time
    return solve_fixed_steps(
        solver,
        BodyRateTerm(field),
        ts,
        y0,
        substeps=1,
        interval_args=jnp.repeat(u, substeps, axis=0),
        checkpoint=jax.checkpoint_policies.dots_with_no_batch_dims_saveable if y0[1].dtype == jnp.float32 else True,
    )


def _states(cfg: Config, data: Data, x0, time, u, substeps: int, fractions=None):
    """``(qs, ws, hs)`` from the physical start ``x0 = (q, w, h)`` through the held controls
    ``u``: the rigid body (``hs`` empty), the wheels, or a user model (``hs`` its ``z``)."""
    q0, w0, h0 = x0
    if cfg.model is not None and cfg.model_quaternions:
        k = cfg.model_quaternions
        field = lie_field(cfg.model, data.model_args, k)
        solver = RKMK4(quaternions=(True, False, True, False), layout="rows")
        qs, ws, Ps, rs = _held(solver, field, (q0, w0, *split_state(h0, k)), time, u, substeps, fractions)
        return qs, ws, join_state(Ps, rs)
    if cfg.model is not None:
        field = lie_field(cfg.model, data.model_args)
        return _held(
            RKMK4(quaternions=(True, False, False), layout="rows"), field, (q0, w0, h0), time, u, substeps, fractions
        )
    if not cfg.wheels:
        qs, ws = held_torque_states(data.inertia, q0, w0, time, u, substeps, fractions)
        return qs, ws, jnp.zeros(ws.shape[:-1] + (0,), ws.dtype)
    return held_wheel_states(data.inertia, data.axes, q0, w0, h0, time, u, substeps, fractions)


def _path(cfg: Config, data: Data, qs, ws, hs, c, p, k):
    """Path constraints ``<= 0`` of one interval (controls ``c``), at every substep's end state."""
    parts = []
    nu = _controls_of(cfg)
    v = c[:nu]
    if cfg.fuel:  # |v_i| <= sigma_i <= 1: sigma is the l1 cost's epigraph variable
        parts += [v - c[nu:], -v - c[nu:], c[nu:] - 1.0]
    elif cfg.torque_bounded:
        parts += [v - 1.0, -v - 1.0]
    if cfg.rate_bounded:
        r = ws / data.rate_bound
        parts += [(r - 1.0).ravel(), (-r - 1.0).ravel()]
    if cfg.momentum_bounded:
        r = hs / data.momentum_bound[None]
        parts += [(r - 1.0).ravel(), (-r - 1.0).ravel()]
    if cfg.n_cones:
        qn = qs / jnp.linalg.norm(qs, axis=-1, keepdims=True)
        if cfg.model_quaternions:  # a cone's frame: q (0) or the j-th extra quaternion (j)
            extra = split_state(hs, cfg.model_quaternions)[0]
            extra = extra / jnp.linalg.norm(extra, axis=-1, keepdims=True)  # as q: the cone, not |p|^2 times it
            frames = jnp.concatenate([qn[:, None], extra], axis=1)
            per_cone = jnp.moveaxis(frames[:, data.cones[:, 8].astype(jnp.int32)], 1, 0)  # (n, substeps, 4)
        else:
            per_cone = jnp.broadcast_to(qn, (data.cones.shape[0], *qn.shape))
        axes = jax.vmap(lambda c, qc: jax.vmap(lambda qq: _quaternion.rotate(qq, c[:3]))(qc))(
            data.cones, per_cone
        )  # (n, substeps, 3)
        cosines = jnp.einsum("csi,ci->cs", axes, data.cones[:, 3:6])
        parts.append((data.cones[:, 7:8] * (cosines - data.cones[:, 6:7])).ravel())
    if cfg.min_time:
        # T >= T_ref / 20, in the first stage only (each copy would add its own barrier term).
        parts.append(jnp.reshape(jnp.where(k == 0, 0.05 - p[0], -1.0), (1,)))
    if not parts:
        return jnp.zeros((0,), qs.dtype)
    return jnp.concatenate(parts)


def _units(data: Data) -> tuple[Array, Array]:
    """The cost terms' units ``(T_ref, T_ref sum u_ref_i^2, T_ref sum u_ref_i)`` (time, energy,
    fuel; ``T_ref`` the fixed time or the eigenaxis reference time) and the cost's unit
    ``S = sum weight_j unit_j``: the NLP minimises ``cost / S`` (a single objective is divided by its
    own unit, as the variables are scaled), and ``S`` times its objective is the cost."""
    units = data.duration * jnp.stack([jnp.ones_like(data.duration), jnp.sum(data.u_ref**2), jnp.sum(data.u_ref)])
    return units, jnp.sum(data.weights * units)


def _problem(cfg: Config) -> ShootingProblem:
    def duration(p, data):
        return data.duration * p[0] if cfg.min_time else data.duration

    nu = _controls_of(cfg)

    def stage(x, c, p, data, k):
        h = duration(p, data) / cfg.intervals if cfg.uniform else duration(p, data) * data.fractions[k]
        u = data.u_ref * c[:nu]
        start = (x[:4], x[4:7] * data.w_ref, x[7:] * data.h_ref)
        qs, ws, hs = _states(cfg, data, start, h, u[None], cfg.substeps)
        x_next = jnp.concatenate([qs[-1], ws[-1] / data.w_ref, hs[-1] / data.h_ref])
        total = _units(data)[1]
        cost = jnp.zeros((), x.dtype)
        if cfg.energy:
            cost = cost + data.weights[1] * h * jnp.sum(u * u) / total
        if cfg.fuel:
            cost = cost + data.weights[2] * h * jnp.sum(data.u_ref * c[nu:]) / total
        return x_next, cost, _path(cfg, data, qs[1:], ws[1:], hs[1:], c, p, k)

    def reached(target, q):  # vec(target* q) = 0: the attitude reached, up to sign
        return _quaternion.multiply(_quaternion.conjugate(target), q)[1:]

    def terminal(xN, data):  # the wheel momenta are free, a model's z where not given
        parts = [reached(data.qf, xN[:4]), xN[4:7] - data.wf / data.w_ref]
        if any(cfg.model_fixed):
            k, fixed = cfg.model_quaternions, cfg.model_fixed
            zN = xN[7:] * data.h_ref
            targets, ends = split_state(data.model_final, k)[0], split_state(zN, k)[0]
            parts += [reached(targets[j], ends[j]) for j in range(k) if fixed[4 * j]]
            rest = [i for i in range(4 * k, len(fixed)) if fixed[i]]
            if rest:
                idx = jnp.asarray(rest)
                parts.append((zN[idx] - data.model_final[idx]) / data.h_ref)
        return jnp.concatenate(parts)

    def objective(p, data):
        units, total = _units(data)
        return data.weights[0] * units[0] / total * p[0] if cfg.min_time else jnp.zeros((), p.dtype)

    return ShootingProblem(stage, terminal, objective)


_PROBLEMS: dict = {}


def _cached_problem(cfg: Config) -> ShootingProblem:
    # One ShootingProblem per configuration: jit hashes the static functions by identity.
    if cfg not in _PROBLEMS:
        _PROBLEMS[cfg] = _problem(cfg)
    return _PROBLEMS[cfg]


def _profile(min_time: bool, s):
    """The eigenaxis reference profile at normalised times ``s``: the angle's fraction, the rate
    and the acceleration (per unit angle, in units of the duration): bang-bang for minimum time,
    the cubic minimum-energy one otherwise."""
    if min_time:
        return (
            jnp.where(s < 0.5, 2 * s * s, 1 - 2 * (1 - s) ** 2),
            jnp.where(s < 0.5, 4 * s, 4 * (1 - s)),
            jnp.where(s < 0.5, 4.0, -4.0),
        )
    return 3 * s * s - 2 * s**3, 6 * s * (1 - s), 6 - 12 * s


def _model_guess(cfg: Config, data: Data, qm, wm, am, fm, fn):
    """A user model's guess along the eigenaxis profile (midpoint attitudes, rates and
    accelerations ``(N, .)``; ``fm``, ``fn`` the midpoints' and the nodes' fractions of the
    duration): per interval the least-squares controls at the midpoint, and ``z`` stepped by
    explicit Euler. An extra quaternion with a given final value (``extra_final``) and a cone on
    its axis follows its geodesic at a constant body rate (its nodes are set there, and its rate
    joins the body's acceleration in the least squares): stepped from its start alone, the
    first Newton step had to carry it the whole way in one linearisation, and a cone on its axis
    jammed the interior point (the gimballed payload of ``tests/test_optimal_control.py``, session
    27: the last substep's cone slack shrank 100x per iteration). Without a cone the plain guess
    stays (that payload's slew: 11 iterations from it, 17 from the geodesic). The controls are
    ``B^+ (target - rows(u = 0))``, ``rows`` the body's ``w'`` and those quaternions' body rates
    (zero rows where not used), ``B`` their Jacobian in ``u``. Returns the node ``z`` ``(N, m)``
    and the controls ``(N, n)``."""
    lengths = data.duration * data.fractions
    k = cfg.model_quaternions
    fixed = [j for j in range(k) if cfg.n_cones and cfg.model_fixed and cfg.model_fixed[4 * j]]
    starts = split_state(data.h0, k)[0]
    turns = {j: minus(split_state(data.model_final, k)[0][j], starts[j]) for j in fixed}
    # 1 where quaternion j has a cone on its axis (cone frame j + 1; the frames are data), else 0
    used = {j: jnp.any(data.cones[:, 8] == j + 1).astype(data.h0.dtype) for j in fixed}

    def on_geodesics(z, f):  # z with each coned, given quaternion at the fraction f of its geodesic
        if not fixed:
            return z
        P, r = split_state(z, k)
        for j in fixed:
            P = P.at[j].set(jnp.where(used[j] > 0, plus(starts[j], f * turns[j]), P[j]))
        return join_state(P, r)

    def interval(z, xs):
        q, w, a, h, f_mid, f_end = xs
        y = (q, w, on_geodesics(z, f_mid))

        def rows(u):  # the value comes out of the Jacobian's own primal pass
            _, dw, dz = rates(cfg.model, y, u, data.model_args)
            P, dP = split_state(y[2], k)[0], split_state(dz, k)[0]
            value = jnp.concatenate([dw, *[used[j] * body_rate(P[j], dP[j]) for j in fixed]])
            return value, value

        B, free = jax.jacfwd(rows, has_aux=True)(jnp.zeros(cfg.model_controls, q.dtype))
        target = jnp.concatenate([a, *[used[j] * turns[j] / data.duration for j in fixed]])
        u = jnp.linalg.pinv(B) @ (target - free)
        z = z + h * rates(cfg.model, y, u, data.model_args)[2]
        if k:  # an Euler step leaves the unit sphere
            z = renormalised(z, k)
        z = on_geodesics(z, f_end)
        return z, (z, u)

    return jax.lax.scan(interval, data.h0, (qm, wm, am, lengths, fm, fn))[1]


def initial_guess(cfg: Config, data: Data):
    """The eigenaxis initial guess: nodes ``(N, 7 + m)``, scaled controls ``(N, n)``."""
    N = cfg.intervals
    dtype = data.q0.dtype
    rotvec = minus(data.qf, data.q0)
    if cfg.uniform:
        s = jnp.arange(1, N + 1, dtype=dtype) / N
        sm = (jnp.arange(N, dtype=dtype) + 0.5) / N
    else:
        s = jnp.cumsum(data.fractions)
        sm = s - data.fractions / 2
    shape, rate_n, _ = _profile(cfg.min_time, s)
    shape_m, rate, accel = _profile(cfg.min_time, sm)
    along = jax.vmap(lambda a: plus(data.q0, a * rotvec))  # the eigenaxis attitudes at angle fractions
    qs = along(shape).at[-1].set(data.qf)
    ws = rate_n[:, None] * rotvec[None] / data.duration + (1 - s)[:, None] * data.w0[None] + s[:, None] * data.wf[None]
    wm = rate[:, None] * rotvec[None] / data.duration + (1 - sm)[:, None] * data.w0[None] + sm[:, None] * data.wf[None]
    am = accel[:, None] * rotvec[None] / data.duration**2 + (data.wf - data.w0)[None] / data.duration
    if cfg.model is not None:
        # the model's own dynamics and control matrix at the profile's midpoints
        hs, u = _model_guess(cfg, data, along(shape_m), wm, am, sm, s)
    elif cfg.wheels:
        # Wheel momenta from the body-frame momentum balance without its rotation,
        # A^T (h - h0) = -J (w - w0), and the wheel torques A^T u = -(J a + w x (J w + A^T h)).
        spread = jnp.linalg.pinv(data.axes.T)  # (n, 3)

        def momenta(w):  # (k, 3) body rates -> (k, n) wheel momenta
            return data.h0[None] - jax.vmap(lambda wk: spread @ (data.inertia @ (wk - data.w0)))(w)

        hs, hm = momenta(ws), momenta(wm)
        u = jax.vmap(lambda w, a, h: -spread @ (data.inertia @ a + jnp.cross(w, data.inertia @ w + h @ data.axes)))(
            wm, am, hm
        )
    else:
        hs = jnp.zeros((N, 0), dtype)
        u = jax.vmap(lambda w, a: data.inertia @ a + jnp.cross(w, data.inertia @ w))(wm, am)
    v = u / data.u_ref[None]
    # A fixed perturbation: on the eigenaxis profile itself the off-axis derivatives vanish,
    # and for symmetric bodies it is a saddle point that Newton's method would converge to.
    v = v + _PERTURBATION * jax.random.normal(jax.random.PRNGKey(0), v.shape, dtype)
    return jnp.concatenate([qs, ws / data.w_ref, hs / data.h_ref], axis=1), v


def _resampled(cfg: Config, data: Data, init):
    """A warm start from a previous result ``init`` (any grid): its torque on each new interval's
    midpoint, its trajectory interpolated at the new nodes (linear in normalised time, ``q``
    and a user model's quaternions renormalised), its time. Scaled as the NLP's unknowns."""
    dtype = data.q0.dtype
    old = jnp.asarray(init.ts, dtype) / jnp.asarray(init.time, dtype)
    torque, q, w = (jnp.asarray(a, dtype) for a in (init.torque, init.q, init.omega))
    edges = _grid(cfg.intervals, 1, None if cfg.uniform else data.fractions, dtype)

    def at(t):  # the grid cell holding t, and t's position in it
        i = jnp.clip(jnp.searchsorted(old, t, side="right") - 1, 0, old.shape[0] - 2)
        return i, ((t - old[i]) / (old[i + 1] - old[i]))[:, None]

    u = torque[at((edges[:-1] + edges[1:]) / 2)[0]]
    i, f = at(edges[1:])
    qs = (1 - f) * q[i] + f * q[i + 1]
    ws = (1 - f) * w[i] + f * w[i + 1]
    hs = (
        (1 - f) * init.h[i] + f * init.h[i + 1]
        if cfg.wheels or cfg.model is not None
        else jnp.zeros((ws.shape[0], 0), dtype)
    )
    if cfg.model_quaternions:  # a user model's quaternions in z, renormalised as q is
        hs = renormalised(hs, cfg.model_quaternions)
    X = jnp.concatenate([qs / jnp.linalg.norm(qs, axis=-1, keepdims=True), ws / data.w_ref, hs / data.h_ref], axis=1)
    p = jnp.reshape(jnp.asarray(init.time, dtype) / data.duration, (1,)) if cfg.min_time else jnp.zeros((0,), dtype)
    return X, u / data.u_ref[None], p


def _controls(cfg: Config, v, clip):
    """Scaled controls of a start: inside the torque bound by the margin ``clip`` (the interior
    point starts strictly inside), and for fuel the epigraph variables ``|v_i| < sigma_i < 1``."""
    v = jnp.clip(v, -clip, clip) if cfg.torque_bounded else v
    if cfg.fuel:
        v = jnp.concatenate([v, jnp.abs(v) + (1 - clip) / 2], axis=1)
    return v


def _start(cfg: Config, data: Data, init):
    """One problem's initial guess ``(X, V, p)``: the eigenaxis profile, or the warm start
    ``init`` resampled onto this grid."""
    if init is None:
        X, V = initial_guess(cfg, data)
        return X, V, jnp.ones((1,), X.dtype) if cfg.min_time else jnp.zeros((0,), X.dtype)
    return _resampled(cfg, data, init)


_REVERSE_HESSIAN_PAIRS = 16  # (problem, start) pairs from which the batch uses hessian="reverse"


def guess_config(cfg: Config) -> Config:
    """``cfg`` with the fields :func:`guesses` does not read at their defaults (the bounds, the cost's
    fuel and energy terms, ``substeps``; the cones and the given final entries unless a user
    model's quaternions read them), so that configurations which differ only there share one
    compiled guess program (its static argument). Measured (float64, one pinned core of a 2-core
    Intel Xeon): the guess program of the 10-interval Bilimoria-Wie slew took 0.47 s to trace and
    compile, once more for the same slew with a rate bound; now once for both."""
    reads_cones = cfg.model is not None and cfg.model_quaternions > 0
    return cfg._replace(
        substeps=1,
        torque_bounded=False,
        rate_bounded=False,
        fuel=False,
        energy=False,
        momentum_bounded=False,
        n_cones=cfg.n_cones if reads_cones else 0,
        model_fixed=cfg.model_fixed if reads_cones else (),
    )


def guesses(data: Data, init=None, *, cfg: Config):
    """Each problem's initial guess ``(X, V, p)`` (leading axis ``B``): the eigenaxis profile, or
    the warm start ``init`` resampled onto this grid; a program of its own, apart from the
    solver's (:func:`solve`), so that a cold and a warm start of one configuration, and warm
    starts from results on any grid, share one compiled solver."""
    return jax.vmap(lambda d: _start(cfg, d, init))(data)


def solve(data: Data, cfg: Config, tol, max_iter, keys, guess, warm, batch: tuple[int, ...] | None = None):
    """:func:`_solve`, jitted (``cfg`` and ``batch`` static) by :func:`solver_jit`, from the
    starts ``guess`` of :func:`guesses` (``warm`` True for a warm start's); ``batch``: the
    problems' batch shape, given to the results' leading axis inside the program (eager reshapes
    compiled one program per result field on a first call), or None to keep the flat axis."""
    return solver_jit(_solve, ("cfg", "batch"))(data, cfg, tol, max_iter, keys, guess, warm, batch)


@functools.cache
def solver_jit(fn, static_argnames: tuple[str, ...] = ()):
    """``jax.jit(fn)`` with :func:`_solver_compiler_options`, made on first use (the options are
    probed by a compile, which ``import jaxquat`` must not wait for) and kept: the jit of the
    package's solver programs, each large and run once per call (this multiple-shooting solver,
    the single-shooting one of :mod:`jaxquat.control.time_optimal`). Called eagerly on the CPU,
    the program runs with LAPACK on one thread (:func:`_one_lapack_thread`) and the call returns
    when it has finished. Inside a caller's ``jit``, ``vmap`` or ``grad`` it is a plain nested
    ``jit``: XLA takes compiler options only for a top-level program (the solvers raised a
    ``ValueError`` under a user's ``jit`` before session 33)."""
    jitted = jax.jit(fn, static_argnames=static_argnames, compiler_options=_solver_compiler_options())
    nested = jax.jit(fn, static_argnames=static_argnames)

    @functools.wraps(fn)
    def run(*args, **kwargs):
        if any(_checks.is_traced(x) for x in jax.tree.leaves((args, kwargs))):
            return nested(*args, **kwargs)
        if jax.default_backend() != "cpu":
            return jitted(*args, **kwargs)
        with _one_lapack_thread():
            return jax.block_until_ready(jitted(*args, **kwargs))

    return run


def _one_lapack_thread():
    """``threadpoolctl.threadpool_limits(1)`` for the BLAS libraries loaded (OpenBLAS: jaxlib's
    CPU LAPACK kernels, ``eigh``, QR, Cholesky, come from scipy's), for the solvers' programs.

    Why: the thread count changes LAPACK's rounding, so the iterates (before session 28, the
    iteration count of the suite's wheel slew: 169 on two threads, 177 on one); on one thread
    every machine computes the same ones. And the solves ran slower on two: OpenBLAS's idle
    workers wait by spinning (its default), the likely cause, taking a core from XLA's threads
    between the LAPACK calls of the small systems here. Measured (float64, one start, this
    2-core EPYC, OpenBLAS's default of two threads against this; best of three after the first
    call): Bilimoria-Wie at 80 intervals 0.91-0.95 s against 0.61 s, Betts asyq01 at 120
    0.73 s against 0.49 s, the 100 slews of 40 intervals in one call 9.95 s against 8.37 s; the
    same iterations and times."""
    return threadpoolctl.threadpool_limits(limits=1, user_api="blas")


@functools.cache
def _solver_compiler_options() -> dict[str, Any] | None:
    """The XLA options of the solvers' programs (:func:`solver_jit`, and the diagnosis of
    :func:`redundant_final`; for these ``jit`` calls only), on the CPU: XLA's older elemental
    emitters (``xla_cpu_use_fusion_emitters`` off) where the installed XLA knows the option, its
    while-loop-invariant code motion pass off, LLVM at optimisation level 1 (XLA's default 2) and
    XLA's fast-compile preset where known; None off the CPU.

    The solver is a large program run once per call, so its compile time is what a first call
    waits for. Measured (float64, one start, this 2-core EPYC, ``OPENBLAS_NUM_THREADS=1``; first
    call then the best of two more), the older emitters: Bilimoria-Wie at 80 intervals, first
    call 10.5 -> 8.5 s and solve 0.93 -> 0.75 s; Betts asyq01 at 120, 11.1 -> 8.9 s and 0.88 ->
    0.72 s; the three-wheel slew at 80, 12.6 -> 9.1 s and 1.02 -> 0.69 s; the same iterations and
    optima (to 1e-15); 100 slews in one call (40 intervals) 11.30 -> 10.86 s. Also tried: LLVM's
    expensive passes off (10.6 s, solve 0.93 s) and backend optimisation level 1 (9.7 s, solve
    1.02 s). Both emitters compute the same IEEE operations; where a fusion evaluates in another
    order the rounding differs. jaxlib 0.11 no longer has the option (its ``XLA_FLAGS`` form
    aborted the process there, session 21), so it is not asked for from 0.11 on.

    The code motion pass (``xla_disable_hlo_passes``): XLA's pass log put 1.1 s of the 3.9 s of
    HLO passes on the suite's payload model there (with the simplification of while loops, 0.9 s
    more, and not removed: it gained nothing more). Without it, on the same slews (runs
    interleaved, two each): first call 7.74-8.04 -> 7.35 s, 7.75-8.02 -> 7.50 s, 8.53-9.12 ->
    7.69-8.58 s, and solves 0.71-0.73 -> 0.65 s, 0.67-0.69 -> 0.60-0.61 s, 0.66-0.67 -> 0.64-0.66 s
    (hoisting out of the Newton loop saves nothing in a body run once per iteration); the same
    iterations and optima to the last digit printed (1e-10). The single-shooting solver's two
    programs (``method="single_shooting"``, the suite's 10-interval asymmetric slew with 4 starts,
    two runs each): first call 19.2-20.7 -> 16.9-17.1 s (compiles 4.5 + 5.1 -> 2.9 + 3.3 s),
    the solve 1.78-1.86 against 1.70-1.90 s, the same time to 1e-12. Only on the CPU: not
    measured on a GPU. One tiny compile decides what the installed XLA accepts.

    Optimisation level 1 (``xla_backend_optimization_level``; session 59, a 2-core Intel Xeon,
    jaxlib 0.10.2, float64, XLA compile and the second call's solve, the two programs side by side
    on one core each, cores swapped): Bilimoria-Wie at 12 intervals with a rate bound, compile 6.90-6.98 -> 5.43-5.44 s
    and solve 0.88-0.93 -> 0.63-0.70 s, the same 13 iterations and time to 1e-15; the minimum-energy
    slew with a keep-out cone 5.40 -> 4.85 s and 0.033 -> 0.030 s; with three wheels 5.95 -> 5.33 s
    and 0.051 -> 0.041 s; a user model (a damped body with a payload quaternion) 13.95 -> 12.97 s and
    0.239 -> 0.215 s, its cost to 2e-16; the single-shooting solver's two programs (10 intervals, 4
    starts) 12.43 -> 11.20 s and 2.62 -> 2.00 s (its best start's time 2.3617159 -> 2.3618372: that
    solver's iterates depend on rounding, ``time_optimal.py``). Level 0 compiled Bilimoria-Wie in
    2.48 s but solved in 5.48 s. Session 20's measurement had level 1 slower (above); XLA's code
    generation has changed since.

    XLA's fast-compile preset (``xla_cpu_opt_preset``, the proto's ``CPU_OPT_PRESET_FAST_COMPILE``;
    session 59, with level 1, the same machine and pairing): it compiles about as fast but runs
    faster, Bilimoria-Wie's solve at 80 intervals (one start) 1.29-1.36 -> 1.00-1.02 s and its
    compile 5.91-6.12 -> 6.00-6.27 s, at 12 intervals 0.80 -> 0.62 s, the same 45 and 13
    iterations and times to the last digit; the suite's optimal-control and time-optimal files
    244.6-253.3 -> 231.9-237.6 s. Its program has 574 fusions against 481 (the same 14 while
    loops); which of the preset's changes makes the difference was not isolated. Each option is
    asked for only where the installed XLA accepts it: the first candidate whose probe compiles."""
    if jax.default_backend() != "cpu":
        return None
    base: dict[str, Any] = {
        "xla_disable_hlo_passes": "while-loop-invariant-code-motion",
        "xla_backend_optimization_level": 1,
    }
    candidates = [{**base, "xla_cpu_opt_preset": "CPU_OPT_PRESET_FAST_COMPILE"}, base]
    try:
        if tuple(int(x) for x in version("jaxlib").split(".")[:2]) < (0, 11):
            candidates = [{**c, "xla_cpu_use_fusion_emitters": False} for c in candidates] + candidates
    except (PackageNotFoundError, ValueError):
        pass
    for options in candidates:
        try:
            jax.jit(lambda x: x + 1, compiler_options=options).lower(np.zeros(())).compile()
        except Exception:  # an XLA that does not know an option, or a jit without compiler_options
            continue
        return options
    return None


def _solve(data: Data, cfg: Config, tol, max_iter, keys, guess, warm, batch: tuple[int, ...] | None = None):
    """A batch of problems (``data`` with a leading axis ``B``), every start of each (one per row
    of ``keys``) solved side by side, then each problem's best start: the least cost among the
    converged starts (the least KKT residual if none converged). Start 0 is ``guess`` (from
    :func:`guesses`: the eigenaxis guess, or with ``warm`` the warm start); start ``s > 0`` adds
    ``_PERTURBATION`` times a standard normal draw (``keys[s]``) to its scaled torque.

    The ``B * S`` (problem, start) pairs are one flat ``vmap`` of the interior point, not a
    ``vmap`` over problems of a ``vmap`` over starts: batching the solver's nested while loops
    twice took the time to a first Bilimoria-Wie result (10 intervals, 8 starts) from 19.9 s to
    24.4 s. ``tol`` and ``max_iter`` are traced: another value reuses the compiled solver (it
    was static, and a new ``max_iter`` recompiled it: 16 s for the suite's 12-interval gimballed
    payload)."""
    problem = _cached_problem(cfg)
    X, V, p = guess
    # A warm start begins nearer the torque bound (the margin clip) and with a smaller barrier
    # parameter: measured 15 iterations against 18 (mu0 = 0.1) for the suite's asymmetric problem
    # from 10 onto 20 intervals, 9 against 12 for Bilimoria-Wie. Both traced (``warm`` is data):
    # a cold and a warm start run one compiled program.
    clip = jnp.where(warm, 0.95, 0.9).astype(X.dtype)
    mu0 = jnp.where(warm, 0.01, 0.1).astype(X.dtype)
    B, S = data.q0.shape[0], keys.shape[0]
    # Large batches form the stage Hessians forward over reverse: each solve twice as fast for a
    # longer compile, which a batch repays (see solve_shooting's ``hessian``); up to the default
    # 8 starts of one problem, forward over forward keeps the first result sooner.
    hessian = "reverse" if B * S >= _REVERSE_HESSIAN_PAIRS else "forward"

    def one(d, X, V, p, key, first):
        kick = _PERTURBATION * jax.random.normal(key, V.shape, V.dtype)
        U = _controls(cfg, jnp.where(first, V, V + kick), clip)
        x0 = jnp.concatenate([d.q0, d.w0 / d.w_ref, d.h0 / d.h_ref])
        return solve_shooting(problem, x0, X, U, p, d, tol=tol, max_iter=max_iter, mu0=mu0, hessian=hessian)

    def pairs(a):  # (B, ...) -> (B * S, ...): each problem once per start
        return jnp.repeat(a, S, axis=0)

    first = jnp.tile(jnp.arange(S) == 0, B)
    flat = _batched(one, *jax.tree.map(pairs, (data, X, V, p)), jnp.tile(keys, (B, 1)), first)
    sols = jax.tree.map(lambda a: jnp.reshape(a, (B, S) + a.shape[1:]), flat)
    out = _batched(lambda d, s: _best(cfg, d, s), data, sols)
    return out if batch is None else jax.tree.map(lambda a: jnp.reshape(a, batch + a.shape[1:]), out)


def _batched(f, *args):
    """``jax.vmap(f)(*args)``, or for a leading axis of length 1 ``f`` on the one row (the axis
    put back): batching the interior point's while loops is most of its trace time, and one
    problem from one start (the default for minimum energy and fuel) needs none of it."""
    if jax.tree.leaves(args)[0].shape[0] != 1:
        return jax.vmap(f)(*args)
    return jax.tree.map(lambda a: a[None], f(*jax.tree.map(lambda a: a[0], args)))


def _best(cfg: Config, data: Data, sols) -> ConstrainedReorientation:
    """One problem's result from its starts' solutions ``sols`` (leading axis: the starts)."""
    costs = _units(data)[1] * sols.objective  # the NLP minimises cost / S: back in physical units
    start_costs = jnp.where(sols.converged, costs, jnp.inf)
    best = jnp.where(jnp.any(sols.converged), jnp.argmin(start_costs), jnp.argmin(sols.kkt))
    sol = jax.tree.map(lambda a: a[best], sols)
    T = data.duration * sol.p[0] if cfg.min_time else data.duration
    nu = _controls_of(cfg)
    u = sol.u[:, :nu] * data.u_ref[None]
    # The trajectory, re-integrated from q0 with the returned torque on one flat grid.
    N, m = cfg.intervals, cfg.substeps
    fractions = None if cfg.uniform else data.fractions
    ts = _grid(N, m, fractions, data.q0.dtype) * T
    qs, ws, hs = _states(cfg, data, (data.q0, data.w0, data.h0), T, u, m, fractions)

    # d(costate . F)/dv for the scaled torque v, from the solver's own Jacobian at the returned
    # point (a reverse pass through the stage here cost 1.1 s of tracing and 1.9 s of compiling);
    # per unit torque: d/du = d/dv / u_ref.
    switching = jnp.einsum("ki,kij->kj", sol.costates, sol.control_jacobian[:, :, :nu]) / data.u_ref[None]
    torque = jnp.concatenate([jnp.repeat(u, m, axis=0), u[-1:]])
    return ConstrainedReorientation(
        T,
        ts,
        qs,
        ws,
        torque,
        u,
        sol.violation,
        costs[best],
        sol.costates,
        switching,
        sol.kkt,
        sol.iterations,
        sol.converged,
        start_costs,
        hs if cfg.wheels else None,
        hs if cfg.model is not None else None,
    )


class Warm(NamedTuple):
    time: Array
    ts: Array
    q: Array
    omega: Array
    torque: Array
    h: Array | None = None  # the wheel momenta of a reaction-wheel result


@functools.cache
def _terminal_jacobians(cfg: Config):
    """``(u, time, data) -> (d/du, d/dtime)`` of the terminal conditions of ``cfg`` through the
    re-integrated trajectory: one compiled program per configuration (and shape), the problem's
    data an argument. Forward mode (as many tangents as controls and the time, 37 on the suite's
    12-interval payload problem, against 9 rows): 2.96 s with its compilation against 5.49 s by
    reverse mode (XLA 1.84 s against 3.66 s; this 2-core CPU, float64), the same redundant entry;
    compiled as one program (op by op, the failed call that runs it took 1.2 s longer: 39.7 s
    against 38.5 s, one run each). Until session 36 the data were constants of the program, so
    every failed solve compiled its own (the suite's four payload tests, two of them failed
    solves: 43.1 s against 37.6 s now)."""
    terminal = _cached_problem(cfg).terminal  # its rows: q's 3, w's 3, then the given z entries in order

    def conditions(u, time, data):
        fractions = None if cfg.uniform else data.fractions
        qs, ws, zs = _states(cfg, data, (data.q0, data.w0, data.h0), time, u, cfg.substeps, fractions)
        return terminal(jnp.concatenate([qs[-1], ws[-1] / data.w_ref, zs[-1] / data.h_ref]), data)

    return jax.jit(jax.jacfwd(conditions, argnums=(0, 1)), compiler_options=_solver_compiler_options())


def redundant_final(cfg: Config, data: Data, time, u) -> list[int]:
    """The given entries of a user model's ``z(T)`` (``extra_final``; an extra quaternion by its
    first index) whose terminal conditions the dynamics already imply, at the controls ``u``
    ``(N, n)`` and final time ``time`` of one problem (NumPy, after a solve).

    The terminal conditions, ``vec(qf* q(T)) = 0``, ``w(T) = wf`` and the given entries of
    ``z(T)`` (``vec(pf* p(T)) = 0`` for a quaternion), are differentiated by forward mode through
    the re-integrated trajectory with respect to the controls (and the time when it is free).
    An entry is redundant when its rows do not raise the rank of that Jacobian (rows scaled to
    unit length, singular values below ``sqrt(eps)`` of the largest counted as zero): a conserved
    quantity, or a state slaved to ``q``, whose condition leaves the Newton-KKT systems singular.
    """
    k = cfg.model_quaternions
    fixed = np.asarray(cfg.model_fixed, bool)
    groups = [(4 * j, 3) for j in range(k) if fixed[4 * j]] + [(i, 1) for i in range(4 * k, fixed.size) if fixed[i]]
    if not groups:
        return []
    jac_u, jac_t = _terminal_jacobians(cfg)(jnp.asarray(u), jnp.asarray(time), data)
    J = np.asarray(jac_u).reshape(jac_u.shape[0], -1)
    if cfg.min_time:
        J = np.concatenate([J, np.asarray(jac_t).reshape(-1, 1)], axis=1)
    if not np.all(np.isfinite(J)):  # a diverged iterate: nothing to say
        return []
    norms = np.linalg.norm(J, axis=1, keepdims=True)
    J = np.where(norms > 0, J / np.where(norms > 0, norms, 1.0), 0.0)

    def rank(rows: np.ndarray) -> int:
        s = np.linalg.svd(rows, compute_uv=False)
        return int(np.sum(s > np.sqrt(np.finfo(rows.dtype).eps) * (float(s[0]) if s.size else 0.0)))

    full = rank(J)
    redundant, offset = [], 6
    for start, size in groups:
        others = np.delete(J, np.arange(offset, offset + size), axis=0)
        if rank(others) + size > full:
            redundant.append(start)
        offset += size
    return redundant
