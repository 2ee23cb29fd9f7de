"""Constrained attitude slews by direct multiple shooting: the public solvers.

``optimal_reorientation`` (any weighted mix of the final time, ``int |u|^2 dt`` and the fuel
``int sum_i |u_i| dt``) and its single-objective cases ``minimum_energy_reorientation``,
``minimum_fuel_reorientation`` and ``constrained_minimum_time``, for the torqued rigid body or a
reaction-wheel spacecraft (``ReactionWheels``), with per-axis torque bounds, body-rate bounds,
wheel momentum bounds and keep-out / keep-in cones. This module validates the arguments, sets
the scales and the configuration, and checks the grid; the transcription, the initial guess
and the result are :mod:`jaxquat.control.transcription`'s.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks
from ..manifold.lie import minus
from ..mechanics.inertia import validated
from . import controlled_model, transcription
from .controlled_model import ControlledModel
from .transcription import Config, ConstrainedReorientation, Data, Warm, guess_config, guesses, solve

__all__ = [
    "ReactionWheels",
    "align_mesh",
    "switch_times",
    "optimal_reorientation",
    "refine_mesh",
    "minimum_energy_reorientation",
    "minimum_fuel_reorientation",
    "constrained_minimum_time",
]


class ReactionWheels(NamedTuple):
    """The reaction wheels that turn the spacecraft in :func:`optimal_reorientation` and its
    single-objective cases (``wheels=``), the model of :class:`jaxquat.ReactionWheelSpacecraft`.

    ``axes`` ``(n, 3)`` the spin axes in the body frame (normalised; ``A`` has them as columns);
    ``torque_limit`` the motor torque bound ``|u_i| <= u_max`` (a scalar or ``(n,)``);
    ``momentum_limit`` the wheel momentum (speed) bound ``|h_i| <= h_max`` at every integration
    step, or ``None``; ``momentum0`` the wheels' axial momenta at the start ``(n,)`` (default 0).
    The body is then driven by the wheels alone: ``J w' = -A u - w x (J w + A h)``, ``h' = u``,
    with ``J`` (the ``inertia`` argument) the spacecraft's inertia without the wheels' axial
    inertias; the final wheel momenta are free (the total momentum ``R(q) (J w + A h)`` is
    conserved, so with ``n = 3`` wheels they are fixed by the boundary states anyway).
    """

    axes: ArrayLike
    torque_limit: ArrayLike
    momentum_limit: ArrayLike | None = None
    momentum0: ArrayLike | None = None


def _cones(keep_out, keep_in, dtype) -> np.ndarray:
    """Rows ``(body axis, inertial direction, cos(half angle), sign, frame)``, unit vectors; the
    constraint is ``sign (s . R(p) a - cos(half)) <= 0``: sign ``+1`` keep-out, ``-1`` keep-in;
    ``p`` the attitude ``q`` (frame 0, a cone given as a triple) or a user model's ``j``-th extra
    quaternion (frame ``j``, a cone given as ``(axis, direction, half_angle, j)``)."""
    rows = []
    for name, sign, cones in (("keep_out", 1.0, keep_out), ("keep_in", -1.0, keep_in)):
        for i, cone in enumerate(cones):
            try:
                axis, direction, half, *frame = cone
            except (TypeError, ValueError):
                frame = [None, None]
            if len(frame) > 1:
                raise ValueError(
                    f"{name}[{i}] must be (body_axis (3,), inertial_direction (3,), half_angle_rad) or that and "
                    f"the frame (0: the body, j >= 1: a model's j-th extra quaternion), got {cone!r}"
                )
            frame = frame[0] if frame else 0
            if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)) or frame < 0:
                raise ValueError(f"{name}[{i}]: the frame must be an int >= 0, got {frame!r}")
            axis, direction = np.asarray(axis, np.float64), np.asarray(direction, np.float64)
            half = float(half)
            if axis.shape != (3,) or direction.shape != (3,):
                raise ValueError(
                    f"{name}[{i}]: body_axis and inertial_direction must be shaped (3,), "
                    f"got {axis.shape} and {direction.shape}"
                )
            if not (np.linalg.norm(axis) > 0 and np.linalg.norm(direction) > 0 and 0 < half < np.pi):
                raise ValueError(f"{name}[{i}]: the axes must be non-zero and 0 < half_angle_rad < pi, got {cone!r}")
            unit = [axis / np.linalg.norm(axis), direction / np.linalg.norm(direction), [np.cos(half), sign, frame]]
            rows.append(np.concatenate(unit))
    return np.asarray(rows, np.float64).reshape(-1, 9).astype(dtype)


def _check_cone_frames(cones: np.ndarray, quaternions: int) -> None:
    """Every cone's frame names the body (0) or one of the model's ``quaternions`` extra ones."""
    frames = np.asarray(cones)[:, 8].astype(int)
    if np.any(frames > quaternions):
        raise ValueError(
            f"arguments 'keep_out'/'keep_in': a cone's frame must be 0 (the body) or 1..{quaternions} (the "
            f"model's extra quaternions), got frames {frames.tolist()}"
        )


def check_grid(intervals, substeps) -> None:
    if not isinstance(intervals, int) or intervals < 2 or not isinstance(substeps, int) or substeps < 1:
        raise ValueError(
            f"need intervals >= 2 and substeps >= 1 (ints), got intervals={intervals!r}, substeps={substeps!r}"
        )


def _mesh(mesh, intervals: int) -> tuple[int, np.ndarray | None]:
    """``(intervals, fractions)``: ``mesh`` (interval lengths, any positive scale) normalised to
    sum 1, or ``None`` for ``intervals`` equal ones."""
    if mesh is None:
        return intervals, None
    m = np.asarray(mesh, np.float64)
    if m.ndim != 1 or m.shape[0] < 2 or not np.all(np.isfinite(m)) or not np.all(m > 0):
        raise ValueError(f"argument 'mesh' must be a 1-D array of >= 2 positive interval lengths, got {m}")
    return int(m.shape[0]), m / np.sum(m)


def refine_mesh(result, *, threshold: float = 1e-3) -> np.ndarray:
    """Interval lengths (fractions of the duration) of ``result``'s mesh with every interval that
    holds a switch halved. In a bang-bang solution each torque component sits on its bound except
    in the intervals where it switches (or on a singular arc), so an interval is split when some
    component is below ``(1 - threshold)`` times that component's largest magnitude. Pass the
    lengths as ``mesh=`` with ``init=result`` to resolve the switches without refining the rest
    (an unbatched result of the multiple-shooting solvers; for smooth, unsaturated torques, as in
    minimum energy, every interval is split)."""
    u, edges = _grid_of(result)
    u = np.abs(u)
    split = np.any(u < (1 - threshold) * np.max(u, axis=0), axis=1)
    lengths = np.diff(edges)
    return np.concatenate([[w / 2, w / 2] if cut else [w] for w, cut in zip(lengths, split)])


def _grid_of(result) -> tuple[np.ndarray, np.ndarray]:
    """An unbatched result's controls ``(N, n)`` and its interval edges as fractions of its time."""
    u = np.asarray(result.controls)
    ts = np.asarray(result.ts)
    if u.ndim != 2 or ts.ndim != 1:
        raise ValueError(f"argument 'result' must be a single (unbatched) result, got controls shaped {u.shape}")
    n = u.shape[0]
    return u, ts[:: (ts.shape[0] - 1) // n] / ts[-1]


# Switches closer than this fraction of an interval (two components switching together) are one:
# a node apart from each would leave an interval too short for its torque to act.
_MERGED = 1e-3


def switch_times(result, *, threshold: float = 1e-3) -> np.ndarray:
    """The switching times of ``result``'s piecewise-constant controls, as sorted fractions of its
    time: a node where a component steps from one held level to another, and inside an interval
    ``k`` whose component is off the levels ``a`` before and ``c`` after it (a level: the
    component's largest magnitude, 0, or a value the neighbouring interval shares, to within
    ``threshold`` times that magnitude), the time ``t_k + f h_k`` with
    ``f = (u_k - c) / (a - c)``: the one switch from ``a`` to ``c`` that gives the interval's
    held value as its average (bang-bang, and bang-off-bang with the level 0). Switches within a
    thousandth of an interval of each other count once."""
    u, edges = _grid_of(result)
    scale = np.max(np.abs(u), axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    flat = np.abs(np.diff(u, axis=0)) <= threshold * scale  # (N - 1, n): k and k + 1 hold one level
    # on a level: on the bound (the largest magnitude), off (0), or shared with a neighbour
    level = (np.abs(u) >= (1 - threshold) * scale) | (np.abs(u) <= threshold * scale)
    level[:-1] |= flat
    level[1:] |= flat
    times = []
    n = u.shape[0]
    for i in range(u.shape[1]):
        for k in range(1, n):
            if level[k - 1, i] and level[k, i] and not flat[k - 1, i]:
                times.append(edges[k])
            if k < n - 1 and not level[k, i] and level[k - 1, i] and level[k + 1, i]:
                a, c = u[k - 1, i], u[k + 1, i]
                if abs(a - c) > threshold * scale[i]:
                    f = (u[k, i] - c) / (a - c)
                    if 0 < f < 1:
                        times.append(edges[k] + f * (edges[k + 1] - edges[k]))
    close = _MERGED / n
    kept: list[float] = []
    for t in np.sort(np.asarray(times, np.float64)):
        if not kept or t - kept[-1] > close:
            kept.append(float(t))
    return np.asarray(kept, np.float64)


def align_mesh(result, *, intervals: int | None = None, threshold: float = 1e-3) -> np.ndarray:
    """Interval lengths (fractions of the duration) of a mesh with a node at each of ``result``'s
    :func:`switch_times`: ``intervals`` of them (default ``result``'s number), each span between
    switches divided into equal intervals, their number in proportion to its length (at least
    one). Solve again with ``mesh=`` it and ``init=result``, and repeat: each solve moves a switch
    that missed its node into the neighbouring interval, whose held value gives the corrected
    time, so the nodes converge to the switches and the held torque resolves the bang-bang
    solution exactly. Unlike :func:`refine_mesh` (halving at the switches) this beats a uniform
    mesh: Bilimoria and Wie's 180 degrees at 14 aligned intervals after three solves 3.2430858,
    against 3.245418 uniform at 14 and 3.243096 at 80 (``docs/optimal-control.md``)."""
    times = switch_times(result, threshold=threshold)
    old = np.asarray(result.controls).shape[0]
    n = old if intervals is None else intervals
    close = _MERGED / old  # a switch this near an end is the end (as near switches are one)
    points = np.concatenate([[0.0], times[(times > close) & (times < 1 - close)], [1.0]])
    spans = np.diff(points)
    if not isinstance(n, int) or n < spans.shape[0]:
        raise ValueError(
            f"argument 'intervals' must be an int of at least the {spans.shape[0]} spans between the "
            f"{spans.shape[0] - 1} switches, got {n!r}"
        )
    share = spans * (n - spans.shape[0])  # the intervals beyond one per span, by length
    counts = 1 + np.floor(share).astype(int)
    counts[np.argsort(np.floor(share) - share, kind="stable")[: n - int(counts.sum())]] += 1
    return np.concatenate([np.full(c, w / c) for w, c in zip(spans, counts)])


def check_starts(starts) -> None:
    if not isinstance(starts, int) or starts < 1:
        raise ValueError(f"argument 'starts' must be an int >= 1, got {starts!r}")


def _options(tol, max_iter, throw, starts, seed, init) -> tuple:
    """The solver options, checked: ``starts`` a positive int; ``init`` a single earlier result."""
    check_starts(starts)
    if init is not None:
        if not all(hasattr(init, f) for f in ("time", "ts", "q", "omega", "torque", "controls")):
            raise TypeError(
                "argument 'init' must be an earlier result (Reorientation or ConstrainedReorientation), "
                f"got {type(init).__name__}"
            )
        if np.ndim(init.time) != 0 or np.ndim(init.controls) != 2:
            raise ValueError(
                f"argument 'init' must be a single (unbatched) result, got time shaped {np.shape(init.time)}"
            )
        h = getattr(init, "wheel_momentum", None)
        h = getattr(init, "extra", None) if h is None else h
        init = Warm(*(jnp.asarray(a) for a in (init.time, init.ts, init.q, init.omega, init.torque)))
        init = init._replace(h=None if h is None else jnp.asarray(h))
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 0:
        raise ValueError(f"argument 'max_iter' must be an int >= 0, got {max_iter!r}")
    return tol, max_iter, throw, starts, int(seed), init


_MAX_STEP_ANGLE = 0.5  # rad the body may turn in one RKMK4 step of the reference profile


def check_resolution(T, q0, qf, w0, wf, intervals: int, substeps: int, widest: float | None = None) -> None:
    """Raise before any work when the grid cannot resolve the motion: the body would turn by
    more than ``_MAX_STEP_ANGLE`` in one integration step of the reference time ``T`` (the larger
    of the boundary rates and the eigenaxis profile's peak rate ``2 theta / T``). Such a problem
    used to run its whole budget (about 40 s at 10 intervals) and return NaN or fail. Checked
    where the values are concrete (eager calls), for the worst problem of a batch; ``widest`` the
    longest interval's share of ``T`` (``1 / intervals`` by default)."""
    values = [_checks.concrete(a) for a in (T, q0, qf, w0, wf)]
    if any(v is None for v in values):
        return
    T, q0, qf, w0, wf = (np.asarray(v, np.float64) for v in values)
    # the angle of q0* qf, in NumPy (these are concrete values: no compilation)
    dot = np.abs(np.sum(q0 * qf, axis=-1))
    cross = qf[..., 1:] * q0[..., :1] - q0[..., 1:] * qf[..., :1] - np.cross(q0[..., 1:], qf[..., 1:])
    theta = 2 * np.arctan2(np.linalg.norm(cross, axis=-1), dot)
    peak = np.where(T > 0, 2 * theta / np.where(T > 0, T, 1.0), 0.0)  # T = 0: already there, at rest
    rate = np.maximum(np.maximum(np.linalg.norm(w0, axis=-1), np.linalg.norm(wf, axis=-1)), peak)
    rate, T = np.broadcast_arrays(rate, T)
    k = np.unravel_index(np.argmax(rate * T), rate.shape) if rate.ndim else ()
    rate, T = float(rate[k]), float(T[k])
    h = T / (intervals * substeps) if widest is None else T * widest / substeps
    if rate * h > _MAX_STEP_ANGLE:
        need = int(np.ceil(rate * T / _MAX_STEP_ANGLE))
        raise ValueError(
            f"the grid cannot resolve this motion: at rate {rate:.3g} rad/s the body turns {rate * h:.3g} rad per "
            f"integration step (reference time {T:.4g}, intervals * substeps = {intervals * substeps}); need "
            f"intervals * substeps >= {need} (a step of at most {_MAX_STEP_ANGLE} rad), or boundary rates "
            "('omega0', 'omegaf') the torque bound can change within a shorter time"
        )


# The smallest tolerance the interior-point solvers accept, in units of the dtype's eps: 1.2e-9
# in float32 (so not the default 1e-9), 2.2e-18 in float64. A float32 solve stalls near a KKT
# error of 1e-7 (the suite's minimum-energy slew, 12 intervals: 7.5e-8) or above it (a
# minimum-time slew: 2e-5).
_TOL_EPS = 1e-2


def check_tolerance(tol, dtype, solver: str, where: str = "") -> None:
    """Raise before any compilation when ``tol`` is below what ``dtype`` can resolve
    (``_TOL_EPS`` eps; a traced ``tol`` is not checked). JAX computes in float32 unless float64
    is enabled, and a float32 solve at the default tol of 1e-9 ran its whole budget (5-10 s, most
    of it compiling) before it raised ``RuntimeError`` without a word of the dtype. ``where``:
    which function takes a ``tol``, when the caller does not."""
    floor = _TOL_EPS * float(np.finfo(dtype).eps)
    tol = _checks.concrete(tol)
    if tol is not None and not float(tol) >= floor:
        raise ValueError(
            f"{solver}: tol = {float(tol):g} is below what {np.dtype(dtype).name} resolves (eps / 100 = {floor:.2g}); "
            "these solvers are written and tested for float64: enable it before making the arrays "
            '(jax.config.update("jax_enable_x64", True), or JAX_ENABLE_X64=1) and pass float64 arguments'
            f", or pass a tol of at least {floor:.2g}{where}"
        )


def float64_hint(dtype) -> str:
    """A sentence for a solver's failure message when ``dtype`` is not float64, else ``""``."""
    if np.dtype(dtype) == np.float64:
        return ""
    return (
        f" The arguments are {np.dtype(dtype).name}: below float64 a solve stalls at a KKT error near 1e-7 (float32) "
        'or above; enable float64 (jax.config.update("jax_enable_x64", True)) and pass float64 arguments.'
    )


def _check_duration(duration) -> float:
    duration = float(duration)
    if not (duration > 0 and np.isfinite(duration)):
        raise ValueError(f"argument 'duration' must be a positive finite float, got {duration}")
    return duration


def _prepare(inertia, q0, qf, omega0, omegaf, torque_bound, rate_bound, keep_out, keep_in):
    """Validated, batch-broadcast arrays (shape errors name the argument)."""
    inertia = validated(inertia)
    if inertia.shape != (3, 3):
        raise ValueError(f"argument 'inertia' must be shaped (3, 3), got shape {tuple(inertia.shape)}")
    q0 = _checks.quat(q0, "q0")
    qf = _checks.quat(qf, "qf")
    dtype = q0.dtype
    w0 = None if omega0 is None else _checks.vec3(omega0, "omega0")
    wf = None if omegaf is None else _checks.vec3(omegaf, "omegaf")
    # rest at the batch shape of the others, made in NumPy: jnp.zeros and its broadcast would be
    # eager compilations of their own (the batch shape checked by broadcast_batch below)
    try:
        batch = np.broadcast_shapes(*(a.shape[:-1] for a in (q0, qf, w0, wf) if a is not None))
    except ValueError:
        batch = ()  # broadcast_batch names the arguments
    rest = jax.device_put(np.zeros(batch + (3,), dtype))
    w0 = rest if w0 is None else w0
    wf = rest if wf is None else wf
    q0, qf, w0, wf = _checks.broadcast_batch([q0, qf, w0, wf], ["q0", "qf", "omega0", "omegaf"], [1, 1, 1, 1])
    for name, x in (("q0", q0), ("qf", qf), ("omega0", w0), ("omegaf", wf)):
        c = _checks.concrete(x)
        if c is not None and name in ("q0", "qf") and not (np.all(np.isfinite(c)) and np.all(np.any(c != 0, -1))):
            raise ValueError(f"argument '{name}' must be a finite non-zero quaternion, got {c}")
        if c is not None and not np.all(np.isfinite(c)):
            raise ValueError(f"argument '{name}' must be finite, got {c}")
    bound = None
    if torque_bound is not None:
        bound = per_axis_bound(torque_bound)
        c = _checks.concrete(bound)
        if bound.ndim != 1 or (c is not None and not (np.all(c > 0) and np.all(np.isfinite(c)))):
            raise ValueError(f"argument 'torque_bound' must be positive and finite, shaped (3,), got {c}")
    if rate_bound is not None:
        rate_bound = float(rate_bound)
        if not (rate_bound > 0 and np.isfinite(rate_bound)):
            raise ValueError(f"argument 'rate_bound' must be a positive finite float, got {rate_bound}")
    cones = _cones(keep_out, keep_in, np.dtype(dtype))
    q0, qf = _arrays.compiled(_units, q0, qf)
    return jnp.asarray(inertia, dtype), q0, qf, w0, wf, bound, rate_bound, cones


def per_axis_bound(torque_bound) -> Array:
    """The body torque bound as ``(3,)``: a scalar bounds all three axes alike (Bilimoria and Wie's
    ``|u_i| <= 1``), a 3-vector each its own; checked as a 3-vector array (shape errors name
    ``torque_bound``)."""
    if np.ndim(torque_bound) == 0 and not isinstance(torque_bound, (str, bytes)):
        c = _checks.concrete(torque_bound)
        torque_bound = np.full(3, c, np.result_type(c, np.float32)) if c is not None else jnp.full(3, torque_bound)
    return _checks.vec3(torque_bound, "torque_bound")


def _units(q0: Array, qf: Array) -> tuple[Array, Array]:
    return q0 / jnp.linalg.norm(q0, axis=-1, keepdims=True), qf / jnp.linalg.norm(qf, axis=-1, keepdims=True)


def _wheels(wheels, dtype) -> tuple | None:
    """The validated ``(axes (n, 3) unit rows, torque_limit (n,), momentum_limit (n,) or None,
    momentum0 (n,))`` of a :class:`ReactionWheels`, or ``None``."""
    if wheels is None:
        return None
    if not isinstance(wheels, ReactionWheels):
        raise TypeError(f"argument 'wheels' must be a jaxquat.ReactionWheels, got {type(wheels).__name__}")
    axes = np.asarray(wheels.axes, np.float64)
    if axes.ndim != 2 or axes.shape[1] != 3 or axes.shape[0] < 1:
        raise ValueError(f"wheels.axes must be the spin axes shaped (n, 3), n >= 1, got shape {axes.shape}")
    norms = np.linalg.norm(axes, axis=1, keepdims=True)
    if not np.all(norms > 0) or not np.all(np.isfinite(axes)):
        raise ValueError(f"wheels.axes must be finite nonzero rows, got {axes.tolist()}")
    axes = axes / norms
    if np.linalg.matrix_rank(axes) < 3:
        raise ValueError("wheels.axes must span the three body axes (the wheels cannot turn the body about all axes)")
    n = axes.shape[0]

    def limit(x, name):
        x = np.asarray(x, np.float64)
        x = np.full(n, x) if x.ndim == 0 else x
        if x.shape != (n,) or not np.all(x > 0) or not np.all(np.isfinite(x)):
            raise ValueError(f"wheels.{name} must be positive and finite, a scalar or shaped ({n},), got {x}")
        return jnp.asarray(x, dtype)

    h0 = np.zeros(n) if wheels.momentum0 is None else np.asarray(wheels.momentum0, np.float64)
    if h0.shape != (n,) or not np.all(np.isfinite(h0)):
        raise ValueError(f"wheels.momentum0 must be finite, shaped ({n},), got {h0}")
    h_limit = None if wheels.momentum_limit is None else limit(wheels.momentum_limit, "momentum_limit")
    if h_limit is not None and np.any(np.abs(h0) > np.asarray(h_limit)):
        raise ValueError(f"wheels.momentum0 {h0} exceeds wheels.momentum_limit {np.asarray(h_limit)}")
    return jnp.asarray(axes, dtype), limit(wheels.torque_limit, "torque_limit"), h_limit, jnp.asarray(h0, dtype)


def _run(
    cfg, inertia, q0, qf, w0, wf, duration, u_ref, w_ref, rate_bound, cones, weights, fractions, options, wheels, model
):
    """Solve, and raise when a problem did not converge (``throw``). ``wheels`` the validated
    ``(axes, torque_limit, momentum_limit or None, momentum0)`` or ``None``; ``model`` the
    validated user model (``controlled_model.Model``) or ``None``."""
    tol, max_iter, throw, starts, seed, init = options
    check_tolerance(
        tol, q0.dtype, "optimal reorientation", " (a minimum-time slew: to jaxquat.constrained_minimum_time)"
    )
    widest = None if fractions is None else float(np.max(fractions))
    check_resolution(duration, q0, qf, w0, wf, cfg.intervals, cfg.substeps, widest)
    batch = q0.shape[:-1]
    args = final = bound = scale = None
    if model is not None:  # the extra states z in the wheel momenta's places
        axes, h0, args, final, bound, scale = None, model.z0, model.args, model.final, model.bound, model.scale
    elif wheels is not None:
        axes, _, bound, h0 = wheels
    else:
        axes = h0 = None
    extra = (axes, h0, bound, scale, args, final)
    boundary = (inertia, q0, qf, w0, wf, duration, u_ref, w_ref)
    data = _arrays.compiled(_data, boundary, rate_bound, cones, weights, fractions, extra, cfg=cfg)
    keys = _arrays.compiled(_keys, seed=seed, starts=starts)
    guess = _arrays.compiled(guesses, data, init, cfg=guess_config(cfg))
    out = solve(data, cfg, tol, np.int32(max_iter), keys, guess, np.asarray(init is not None), batch=batch)
    if throw and not _checks.is_traced(out.violation):
        bad = ~np.asarray(out.converged)
        if np.any(bad):
            raise RuntimeError(
                "optimal reorientation: the interior-point method did not converge"
                f" for {int(bad.sum())} of {bad.size} problems (largest KKT residual "
                f"{float(np.max(np.asarray(out.kkt_residual)[bad])):.3g}, violation "
                f"{float(np.max(np.asarray(out.violation)[bad])):.3g}). Try more intervals, more max_iter or a larger "
                "tol; check that the constraints admit a solution. Pass throw=False to get the last iterate."
                + float64_hint(q0.dtype)
                + _redundancy_hint(cfg, data, out, int(np.flatnonzero(bad.ravel())[0]))
            )
    return out


def _keys(*, seed: int, starts: int) -> Array:
    """The random keys of the starts (start 0 does not use its own)."""
    return jax.vmap(lambda k: jax.random.fold_in(jax.random.PRNGKey(seed), k))(jnp.arange(starts))


def _data(boundary, rate_bound, cones, weights, fractions, extra, *, cfg: Config) -> Data:
    """The solver's :class:`Data`, flat over the batch (leading axis ``B``): ``boundary`` the
    ``(inertia, q0, qf, w0, wf, duration, u_ref, w_ref)`` (batch axes ``batch``), ``extra`` the
    ``(axes, h0, bound, scale, args, final)`` of the wheels (``scale`` None) or of a user model
    (``axes`` None), or all None for the torqued body. Compiled as one program
    (:func:`jaxquat._arrays.compiled`), as are the scales, the unit quaternions and the keys, and
    the results take their batch shape inside the solver's program: eagerly these were 48 to 58
    single-operation compilations on a first call, and compiled the suite's 12-interval slew
    (8 starts) reached its first result 0.7-0.9 s sooner (7.6-7.8 s against 6.9 s, this 2-core
    CPU)."""
    inertia, q0, qf, w0, wf, duration, u_ref, w_ref = boundary
    axes, h0, h_bound, scale, args, final = extra
    dtype = q0.dtype
    inf = jnp.asarray(jnp.inf, dtype)
    if scale is not None:  # a user model: its z in the wheel momenta's places
        axes = jnp.zeros((0, 3), dtype)
        h_bound = inf * jnp.ones_like(h0) if h_bound is None else h_bound
        h_ref = jnp.full_like(w_ref, scale)
    elif axes is None:  # the torqued body
        axes, h0, h_bound = jnp.zeros((0, 3), dtype), jnp.zeros((0,), dtype), jnp.zeros((0,), dtype)
        h_ref = jnp.ones_like(w_ref)
    else:
        h_bound = inf * jnp.ones_like(h0) if h_bound is None else h_bound
        # the momentum the body takes at the reference rate, or the wheels' own, whichever is larger
        h_ref = jnp.maximum(jnp.max(jnp.abs(inertia)) * w_ref, jnp.max(jnp.abs(h0)))
    batch = q0.shape[:-1]

    def data_of(q0_, qf_, w0_, wf_, dur, ur, wr, hr):
        return Data(
            inertia,
            q0_,
            w0_,
            qf_,
            wf_,
            dur,
            ur,
            wr,
            inf if rate_bound is None else jnp.asarray(rate_bound, dtype),
            jnp.asarray(cones, dtype),
            jnp.asarray(weights, dtype),
            jnp.full(cfg.intervals, 1 / cfg.intervals, dtype) if fractions is None else jnp.asarray(fractions, dtype),
            axes,
            h0,
            hr,
            h_bound,
            args,
            final,
        )

    flat = [jnp.reshape(a, (-1,) + a.shape[len(batch) :]) for a in (q0, qf, w0, wf, duration, u_ref, w_ref, h_ref)]
    # Strongly typed leaves: a weak-typed one (e.g. a bound broadcast from a Python float) is
    # another cache key for the jitted solver, and retraced and recompiled it (18 s for the
    # suite's 10-interval problem, whose bound came once as an array and once as a list).
    return jax.tree.map(lambda a: jnp.asarray(a, a.dtype), jax.vmap(data_of)(*flat))


def _redundancy_hint(cfg, data, out, i: int) -> str:
    """For a user model with ``extra_final``: which given entries the dynamics already imply at
    problem ``i``'s last iterate (:func:`transcription.redundant_final`), as a sentence, or ''."""
    if cfg.model is None or not any(cfg.model_fixed):
        return ""
    one = jax.tree.map(lambda a: a[i], data)
    time, controls = (jnp.reshape(a, (-1,) + a.shape[out.time.ndim :])[i] for a in (out.time, out.controls))
    redundant = transcription.redundant_final(cfg, one, time, controls)
    if not redundant:
        return ""
    return (
        f" model.extra_final gives entries {redundant} (an extra quaternion by its first entry) that the "
        "dynamics already imply (a conserved quantity, or a state slaved to q): their terminal conditions "
        "add no rank to the others', which leaves the Newton systems singular; leave them NaN (free)."
    )


def scales(inertia, q0, qf, w0, wf, duration_or_bound, min_time: bool):
    """Per-problem time, torque and rate scales from the eigenaxis profile (one compiled program,
    :func:`jaxquat._arrays.compiled`: eagerly it was 24 single-operation compilations)."""
    return _arrays.compiled(_scales, inertia, q0, qf, w0, wf, duration_or_bound, min_time=min_time)


def _scales(inertia, q0, qf, w0, wf, duration_or_bound, *, min_time: bool):
    theta = jnp.linalg.norm(minus(qf, q0), axis=-1)
    axis = minus(qf, q0) / jnp.maximum(theta, 1e-12)[..., None]
    axis = jnp.where(theta[..., None] > 1e-12, axis, jnp.asarray([1.0, 0.0, 0.0], q0.dtype))
    dw = jnp.linalg.norm(wf - w0, axis=-1)
    if min_time:
        bound = duration_or_bound
        need = jnp.abs(jnp.einsum("ij,...j->...i", inertia, axis))
        bound = jnp.broadcast_to(bound, need.shape)
        accel = jnp.min(jnp.where(need > 1e-12, bound / jnp.maximum(need, 1e-300), jnp.inf), axis=-1)
        T = 2 * jnp.sqrt(theta / accel) + dw / accel
        T = jnp.where(T > 0, T, 1.0)
        u_ref = jnp.broadcast_to(bound, q0.shape[:-1] + (3,))
    else:
        T = jnp.broadcast_to(jnp.asarray(duration_or_bound, q0.dtype), q0.shape[:-1])
        peak = (
            jnp.linalg.norm(jnp.einsum("ij,...j->...i", inertia, axis), axis=-1) * 6 * theta / T**2
            + jnp.max(jnp.abs(inertia)) * dw / T
        )
        u_ref = jnp.broadcast_to(jnp.where(peak > 0, peak, 1.0)[..., None], q0.shape[:-1] + (3,))
    rate = jnp.maximum(jnp.maximum(2 * theta / T, jnp.linalg.norm(w0, axis=-1)), jnp.linalg.norm(wf, axis=-1))
    return T, u_ref, jnp.where(rate > 0, rate, 1.0)


def optimal_reorientation(
    inertia: Float[ArrayLike, "3 3"],
    q0: Float[ArrayLike, "*#batch 4"],
    qf: Float[ArrayLike, "*#batch 4"],
    omega0: Float[ArrayLike, "*#batch 3"] | None = None,
    omegaf: Float[ArrayLike, "*#batch 3"] | None = None,
    *,
    duration: float | None = None,
    time_weight: float = 0.0,
    energy_weight: float = 0.0,
    fuel_weight: float = 0.0,
    torque_bound: Float[ArrayLike, "3"] | None = None,
    rate_bound: float | None = None,
    keep_out: Sequence = (),
    keep_in: Sequence = (),
    intervals: int = 40,
    substeps: int = 4,
    tol: float = 1e-9,
    max_iter: int = 200,
    throw: bool = True,
    starts: int = 1,
    seed: int = 0,
    init=None,
    mesh=None,
    wheels: ReactionWheels | None = None,
    model: ControlledModel | None = None,
) -> ConstrainedReorientation:
    """Least ``time_weight T + energy_weight int |u|^2 dt + fuel_weight int sum_i |u_i| dt`` taking
    ``(q0, omega0)`` to ``(qf, omegaf)``: any weighted mix of the three objectives.

    ``duration=None`` leaves the final time free (then ``time_weight > 0`` and ``torque_bound``
    are required: the torque bound sets the time scale); a ``duration`` fixes it (then
    ``time_weight`` must be 0). ``fuel_weight > 0`` needs ``torque_bound`` (the l1 cost's
    epigraph variables live inside it). ``cost`` is the mix in physical units. Dynamics,
    constraints (``torque_bound``, ``rate_bound``, ``keep_out``, ``keep_in``), batching, starts and
    warm starts as in :func:`minimum_energy_reorientation`; :func:`minimum_energy_reorientation`,
    :func:`minimum_fuel_reorientation` and :func:`constrained_minimum_time` are its single-objective
    cases. Example: ``time_weight=1, energy_weight=rho`` trades the slew time against the energy;
    for a rest-to-rest slew of a body with ``J = I`` whose torque bound does not bind, the energy
    at fixed time is ``c / T^3`` (the dynamics are invariant under ``t -> a t``, ``u -> u / a^2``),
    so the optimum has ``3 rho E = T``.

    Args:
        inertia: body inertia tensor ``(3, 3)``.
        q0: initial attitude ``(..., 4)`` (normalised; leading axes: a batch of problems).
        qf: target attitude ``(..., 4)`` (either sign).
        omega0: initial body rate ``(..., 3)``; default rest.
        omegaf: final body rate ``(..., 3)``; default rest.
        duration: the fixed final time, or ``None`` for a free one.
        time_weight: weight of ``T`` (free final time only).
        energy_weight: weight of ``int |u|^2 dt``.
        fuel_weight: weight of ``int sum_i |u_i| dt`` (needs ``torque_bound``).
        torque_bound: per-axis body torque bound ``(3,)`` (a scalar: the same on each axis), or
            ``None``.
        rate_bound: ``|w_i| <= rate_bound`` at every integration step, or ``None``.
        keep_out: ``(body_axis (3,), inertial_direction (3,), half_angle_rad)`` cones the body
            axis's inertial image stays out of, at every integration step; with a ``model``
            whose ``extra_quaternions`` are ``k``, a fourth entry ``j`` in ``1..k`` puts the cone
            on the ``j``-th extra quaternion's axis instead (a gimballed payload's boresight;
            ``0``, the default, is the body).
        keep_in: cones of the same form it stays in.
        intervals: number of torque intervals ``N`` (ignored when ``mesh`` is given).
        substeps: RKMK4 steps per interval.
        tol: the KKT error at which a start has converged; below eps / 100 of the arguments'
            dtype (1.2e-9 in float32, JAX's default, so the default tol there) it raises
            ``ValueError`` before any work.
        max_iter: interior-point iterations per start.
        throw: raise ``RuntimeError`` when a problem has no converged start (else return the
            last iterate).
        starts: starts solved side by side per problem (the least converged cost wins).
        seed: the random draw of the starts after the first.
        init: an earlier (unbatched) result on any grid to warm-start from.
        mesh: interval lengths (any positive scale) for a non-uniform mesh.
        wheels: a :class:`ReactionWheels`: the body is turned by its reaction wheels (their motor
            torques are the controls, bounded by ``wheels.torque_limit``; ``wheels.momentum_limit``
            bounds their momenta at every integration step) instead of a body torque
            (``torque_bound`` must then be ``None``); ``inertia`` is the spacecraft's without the
            wheels' axial inertias.
        model: a :class:`ControlledModel`: the body follows the user's dynamics ``field(y, u,
            args)`` with its ``model.controls`` inputs (bounded by ``torque_bound``, then shaped
            ``(n,)`` or a scalar) instead of the torqued rigid body; ``inertia`` then sets only
            the scales and the guess (:class:`ControlledModel`). Not with ``wheels``.

    Returns:
        A :class:`ConstrainedReorientation` with leading axes the batch of the boundary states:
        ``time``, ``ts`` ``(N substeps + 1,)``, ``q``, ``omega``, ``torque`` on that grid,
        ``controls`` ``(N, 3)``, ``violation``, ``cost``, the ``costates`` and ``switching``
        function, ``kkt_residual``, ``iterations``, ``converged`` and ``start_costs``.
    """
    check_grid(intervals, substeps)
    intervals, fractions = _mesh(mesh, intervals)
    weights = np.asarray([time_weight, energy_weight, fuel_weight], np.float64)
    if weights.shape != (3,) or not np.all(np.isfinite(weights)) or np.any(weights < 0) or not np.any(weights > 0):
        raise ValueError(
            "arguments 'time_weight', 'energy_weight' and 'fuel_weight' must be finite and >= 0, one of them > 0; "
            f"got {tuple(weights)}"
        )
    free = duration is None
    if wheels is not None and torque_bound is not None:
        raise ValueError("pass either 'torque_bound' (a body torque) or 'wheels' (whose torque_limit bounds them)")
    if wheels is not None and model is not None:
        raise ValueError("pass either 'wheels' or 'model' (a ControlledModel may include the wheels)")
    bounded = torque_bound is not None or wheels is not None
    if free and (weights[0] == 0 or not bounded):
        raise ValueError("a free final time (duration=None) needs time_weight > 0 and a torque_bound")
    if not free and weights[0] != 0:
        raise ValueError(f"argument 'time_weight' must be 0 with a fixed 'duration', got {weights[0]}")
    if weights[2] > 0 and not bounded:
        raise ValueError("argument 'torque_bound' is required with fuel_weight > 0 (the l1 optimum is impulsive)")
    inertia, q0, qf, w0, wf, bound, rate_bound, cones = _prepare(
        inertia, q0, qf, omega0, omegaf, None if model is not None else torque_bound, rate_bound, keep_out, keep_in
    )
    _check_cone_frames(cones, model.extra_quaternions if isinstance(model, ControlledModel) else 0)
    if model is not None:
        boundary = (inertia, q0, qf, w0, wf, rate_bound, cones)
        options = _options(tol, max_iter, throw, starts, seed, init)
        return _model_problem(
            model, torque_bound, duration, boundary, (intervals, substeps, fractions), weights, options
        )
    spec = _wheels(wheels, jnp.result_type(q0))
    if spec is not None:
        # the body torques the wheels can give, per body axis: sum_i u_max_i |a_i|
        bound = jnp.sum(spec[1][:, None] * jnp.abs(spec[0]), axis=0)
    T, u_ref, w_ref = scales(inertia, q0, qf, w0, wf, bound if free else _check_duration(duration), min_time=free)
    if spec is not None:
        u_ref = jnp.broadcast_to(spec[1], jnp.shape(q0)[:-1] + spec[1].shape)
        if init is not None and getattr(init, "wheel_momentum", None) is None:
            raise ValueError("argument 'init' must be a result with wheels (wheel_momentum) when wheels are given")
    elif bound is not None:
        u_ref = jnp.broadcast_to(jnp.asarray(bound), u_ref.shape)
    cfg = _config(
        (intervals, substeps, fractions),
        free,
        bound is not None,
        rate_bound,
        cones,
        weights,
        wheels=0 if spec is None else int(spec[0].shape[0]),
        momentum_bounded=spec is not None and spec[2] is not None,
    )
    options = _options(tol, max_iter, throw, starts, seed, init)
    return _run(
        cfg, inertia, q0, qf, w0, wf, T, u_ref, w_ref, rate_bound, cones, weights, fractions, options, spec, None
    )


def _config(grid, free: bool, bounded: bool, rate_bound, cones, weights, **model) -> Config:
    """The configuration (what the compiled solver depends on) of a problem: ``grid`` ``(intervals,
    substeps, fractions)``; ``model`` the wheels' or a user model's fields of :class:`Config`."""
    intervals, substeps, fractions = grid
    return Config(
        intervals,
        substeps,
        free,
        bounded,
        rate_bound is not None,
        len(cones),
        fuel=bool(weights[2] > 0),
        energy=bool(weights[1] > 0),
        uniform=fractions is None,
        **model,
    )


def _model_bound(torque_bound, n: int, dtype):
    """The controls' bound ``(n,)`` of a user model, checked, or ``None``."""
    if torque_bound is None:
        return None
    b = np.asarray(torque_bound, np.float64)
    b = np.full(n, b) if b.ndim == 0 else b
    if b.shape != (n,) or not (np.all(b > 0) and np.all(np.isfinite(b))):
        raise ValueError(
            f"argument 'torque_bound' must bound the model's {n} controls: positive and finite, a scalar or "
            f"shaped ({n},), got {b}"
        )
    return jnp.asarray(b, dtype)


def _model_problem(model, torque_bound, duration, boundary, grid, weights, options):
    """:func:`optimal_reorientation` for a user model: its scales from the control matrix
    ``B = dw'/du`` at each problem's initial state (the body torques ``J B u`` the controls
    exert), its configuration, the solve. ``boundary`` the validated ``(inertia, q0, qf, omega0,
    omegaf, rate_bound, cones)``, ``grid`` ``(intervals, substeps, fractions)``."""
    inertia, q0, qf, w0, wf, rate_bound, cones = boundary
    fractions = grid[2]
    init = options[-1]
    free = duration is None
    dtype = jnp.result_type(q0)
    spec = controlled_model.validated(model, dtype)
    n = spec.controls
    bound = _model_bound(torque_bound, n, dtype)
    batch = jnp.shape(q0)[:-1]

    def torque_map(q, w):  # (3, n): the body torques per unit control at the initial state
        return inertia @ controlled_model.control_matrix(spec.field, (q, w, spec.z0), spec.args, n)[0]

    flat = jax.vmap(torque_map)(jnp.reshape(q0, (-1, 4)), jnp.reshape(w0, (-1, 3)))
    JB = jnp.reshape(flat, batch + (3, n))
    # the body torque the bounded controls can give per body axis, |J B| b (b for a torqued body)
    body_bound = None if bound is None else jnp.abs(JB) @ bound
    T, u_ref, w_ref = scales(inertia, q0, qf, w0, wf, body_bound if free else _check_duration(duration), min_time=free)
    if bound is not None:
        u_ref = jnp.broadcast_to(bound, batch + (n,))
    else:  # the controls that give the eigenaxis profile's peak torque, at most
        rows = jnp.max(jnp.linalg.norm(jnp.linalg.pinv(JB), axis=-1), axis=-1)
        u_ref = jnp.broadcast_to((u_ref[..., 0] * rows)[..., None], batch + (n,))
    m = spec.z0.shape[0]
    if init is not None and (init.h is None or init.h.shape[-1] != m):
        raise ValueError(
            f"argument 'init' must be a result of a model with {m} extra states (its extra) when model is given"
        )
    cfg = _config(
        grid,
        free,
        bound is not None,
        rate_bound,
        cones,
        weights,
        momentum_bounded=spec.bound is not None,
        model=spec.field,
        model_controls=n,
        model_quaternions=spec.quaternions,
        model_fixed=spec.fixed,
    )
    return _run(
        cfg, inertia, q0, qf, w0, wf, T, u_ref, w_ref, rate_bound, cones, weights, fractions, options, None, spec
    )


_SHARED = (
    "omega0",
    "omegaf",
    "torque_bound",
    "rate_bound",
    "keep_out",
    "keep_in",
    "intervals",
    "substeps",
    "tol",
    "max_iter",
    "throw",
    "starts",
    "seed",
    "init",
    "mesh",
    "wheels",
    "model",
)


def _shared(arguments: dict) -> dict:
    """The arguments a single-objective wrapper passes on to :func:`optimal_reorientation` unchanged."""
    return {name: arguments[name] for name in _SHARED}


def minimum_energy_reorientation(
    inertia: Float[ArrayLike, "3 3"],
    q0: Float[ArrayLike, "*#batch 4"],
    qf: Float[ArrayLike, "*#batch 4"],
    duration: float,
    omega0: Float[ArrayLike, "*#batch 3"] | None = None,
    omegaf: Float[ArrayLike, "*#batch 3"] | None = None,
    *,
    torque_bound: Float[ArrayLike, "3"] | None = None,
    rate_bound: float | None = None,
    keep_out: Sequence = (),
    keep_in: Sequence = (),
    intervals: int = 40,
    substeps: int = 4,
    tol: float = 1e-9,
    max_iter: int = 200,
    throw: bool = True,
    starts: int = 1,
    seed: int = 0,
    init=None,
    mesh=None,
    wheels: ReactionWheels | None = None,
    model: ControlledModel | None = None,
) -> ConstrainedReorientation:
    """Least ``int_0^T |u|^2 dt`` taking ``(q0, omega0)`` to ``(qf, omegaf)`` in the fixed time ``duration``.

    Dynamics ``q' = 1/2 q (0, w)``, ``I w' = u - w x I w`` (body frame, [S] eqs. (16), (19));
    the torque ``u`` is held constant on ``intervals`` equal pieces. Constraints (each
    optional): ``|u_i| <= torque_bound[i]``; ``|w_i| <= rate_bound`` at every integration
    step; ``keep_out``: ``(body_axis, inertial_direction, half_angle_rad)`` triples, the body
    axis's inertial image ``R(q) a`` staying at least the half angle away from the direction at
    every integration step; ``keep_in``: the same triples, the image staying within the half
    angle of the direction (the boundary states must satisfy them). Terminal: ``q(T) = +-qf``,
    ``w(T) = omegaf`` (rates default to rest).
    Direct multiple shooting solved by a primal-dual interior-point method (module docstring);
    leading batch axes on ``q0``, ``qf``, ``omega0``, ``omegaf`` solve in one compiled call.
    ``q0``/``qf`` are normalised. Raises ``RuntimeError`` if a problem does not converge to ``tol``
    (the scaled KKT error) within ``max_iter`` iterations, unless ``throw=False``. Use float64: in
    float32 (JAX's default) the default ``tol`` raises ``ValueError`` at the call.

    Starts: ``starts`` solves run side by side from start 0 (the eigenaxis guess, or ``init``, an
    earlier result on any number of intervals: its torque and trajectory resampled onto this
    grid, e.g. to refine a coarse solution) and from start 0 with its scaled torque perturbed by
    ``0.2 N(0, 1)`` (draws from ``seed``); the result is the converged start of least cost
    (``start_costs`` has them all). Each start is converged to its KKT point, so the choice is
    between converged local optima and does not depend on the CPU's rounding.

    Mesh: ``mesh`` interval lengths (any positive scale; then ``intervals`` is ``len(mesh)``)
    instead of ``intervals`` equal ones; :func:`refine_mesh` halves the intervals next to the
    torque's switches of an earlier result, to solve again with ``init=`` it.

    Args:
        inertia: body inertia tensor ``(3, 3)``.
        q0: initial attitude ``(..., 4)`` (leading axes: a batch of problems).
        qf: target attitude ``(..., 4)`` (either sign).
        duration: the fixed final time ``T``.
        omega0: initial body rate ``(..., 3)``; default rest.
        omegaf: final body rate ``(..., 3)``; default rest.
        torque_bound: per-axis body torque bound ``(3,)`` (a scalar: the same on each axis), or
            ``None``.
        rate_bound: ``|w_i| <= rate_bound`` at every integration step, or ``None``.
        keep_out: ``(body_axis (3,), inertial_direction (3,), half_angle_rad)`` cones (a fourth
            entry ``j >= 1`` puts one on a ``model``'s ``j``-th extra quaternion instead, as in
            :func:`jaxquat.optimal_reorientation`).
        keep_in: cones of the same form the axis stays in.
        intervals: number of torque intervals (ignored when ``mesh`` is given).
        substeps: RKMK4 steps per interval.
        tol: the KKT error at which a start has converged.
        max_iter: interior-point iterations per start.
        throw: raise ``RuntimeError`` when a problem has no converged start.
        starts: starts solved side by side per problem.
        seed: the random draw of the starts after the first.
        init: an earlier (unbatched) result on any grid to warm-start from.
        mesh: interval lengths for a non-uniform mesh.

    Returns:
        A :class:`ConstrainedReorientation` (fields as :func:`optimal_reorientation`'s);
        ``cost`` is ``int |u|^2 dt``.
    """
    return optimal_reorientation(
        inertia,
        q0,
        qf,
        duration=_check_duration(duration),
        energy_weight=1.0,
        **_shared(locals()),
    )


def minimum_fuel_reorientation(
    inertia: Float[ArrayLike, "3 3"],
    q0: Float[ArrayLike, "*#batch 4"],
    qf: Float[ArrayLike, "*#batch 4"],
    duration: float,
    omega0: Float[ArrayLike, "*#batch 3"] | None = None,
    omegaf: Float[ArrayLike, "*#batch 3"] | None = None,
    *,
    torque_bound: Float[ArrayLike, "3"] | None = None,
    rate_bound: float | None = None,
    keep_out: Sequence = (),
    keep_in: Sequence = (),
    intervals: int = 40,
    substeps: int = 4,
    tol: float = 1e-9,
    max_iter: int = 200,
    throw: bool = True,
    starts: int = 1,
    seed: int = 0,
    init=None,
    mesh=None,
    wheels: ReactionWheels | None = None,
    model: ControlledModel | None = None,
) -> ConstrainedReorientation:
    """Least fuel ``int_0^T sum_i |u_i| dt`` taking ``(q0, omega0)`` to ``(qf, omegaf)`` in the fixed
    time ``duration``, with ``|u_i| <= torque_bound[i]`` (required: without a bound the l1
    optimum is impulsive).

    The same transcription, constraints and batching as :func:`minimum_energy_reorientation`;
    the l1 cost is made smooth by an epigraph variable per axis and interval
    (``|u_i| <= sigma_i <= b_i``, cost ``sum h sigma_i``). The optimum is bang-off-bang: torque
    on a bound or zero, except in the intervals that hold a switch. ``cost`` is the fuel.
    ``starts``, ``seed``, ``init`` and ``mesh`` as there."""
    if torque_bound is None and wheels is None:
        raise ValueError("argument 'torque_bound' is required for minimum fuel (the l1 optimum is impulsive)")
    return optimal_reorientation(
        inertia,
        q0,
        qf,
        duration=_check_duration(duration),
        fuel_weight=1.0,
        **_shared(locals()),
    )


def constrained_minimum_time(
    inertia: Float[ArrayLike, "3 3"],
    torque_bound: Float[ArrayLike, "3"] | None,
    q0: Float[ArrayLike, "*#batch 4"],
    qf: Float[ArrayLike, "*#batch 4"],
    omega0: Float[ArrayLike, "*#batch 3"] | None = None,
    omegaf: Float[ArrayLike, "*#batch 3"] | None = None,
    *,
    rate_bound: float | None = None,
    keep_out: Sequence = (),
    keep_in: Sequence = (),
    intervals: int = 40,
    substeps: int = 4,
    tol: float = 1e-9,
    max_iter: int = 200,
    throw: bool = True,
    starts: int = 8,
    seed: int = 0,
    init=None,
    mesh=None,
    wheels: ReactionWheels | None = None,
    model: ControlledModel | None = None,
) -> ConstrainedReorientation:
    """Least final time ``T`` taking ``(q0, omega0)`` to ``(qf, omegaf)`` with ``|u_i| <= torque_bound[i]``.

    The same transcription, constraints and batching as :func:`minimum_energy_reorientation`,
    with ``T`` an unknown (``T >= T_ref / 20``, ``T_ref`` the eigenaxis bang-bang time).
    Time-optimal problems have several local optima (Bilimoria and Wie's 180-degree turn at 10
    intervals: 3.2596 and 3.2765), hence 8 starts by default. :func:`jaxquat.minimum_time_reorientation`
    calls this (its default ``method="interior_point"``)."""
    return optimal_reorientation(
        inertia,
        q0,
        qf,
        time_weight=1.0,
        **_shared(locals()),
    )
