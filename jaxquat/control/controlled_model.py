"""A user's spacecraft model for the optimal-control solvers (``model=``): any attitude dynamics with
a control input, solved by the same multiple-shooting transcription and RKMK4 step as the built-in
rigid body and reaction wheels.

The state is ``y = (q, w, z)``: the attitude ``q`` ``(4,)`` (body to inertial, the quaternion leaf
the Lie solver advances on the group), the body rate ``w`` ``(3,)`` (the boundary conditions
``omega0``/``omegaf`` and ``rate_bound`` apply to it) and ``m >= 0`` further states ``z`` ``(m,)``
(wheel momenta, a stored momentum, an energy meter, ...): ``z(0) = extra0``, ``z(T)`` free (or
``extra_final``, NaN entries free), ``|z_i| <= extra_bound_i`` at every integration step if given.
The controls ``u`` ``(n,)`` are held constant on each interval, bounded by the solvers'
``torque_bound`` (``(n,)`` or a scalar); the energy and fuel costs are ``int |u|^2 dt`` and ``int
sum_i |u_i| dt`` over them. The first ``4 k`` entries of ``z`` may be ``k`` further unit
quaternions (``extra_quaternions=k``: a gimballed payload's attitude, a second body's), advanced
on the group by the same RKMK4 step as ``q``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike

from ..integration.lie_solvers import body_rate

__all__ = ["ControlledModel"]


class ControlledModel(NamedTuple):
    """Any attitude model the optimal-control solvers drive (their ``model=`` argument).

    ``field(y, u, args) -> (q', w', z')`` the time-invariant vector field of the state
    ``y = (q (4,), w (3,), z (m,))`` under the controls ``u`` ``(n,)``: an ordinary one, e.g.
    ``q' = 1/2 q (0, w)`` ([S] eq. (16)) on the quaternion leaf (only its part tangent to the
    unit sphere is used, the body rate ``2 vec(q* q')``), ``J w' = u - w x J w`` for a torqued
    body ([S] eq. (19)). ``controls`` the number ``n`` of inputs; ``extra0`` ``z(0)`` (default
    ``None``: no extra states); ``extra_bound`` ``|z_i| <= extra_bound_i`` at every integration step (a
    scalar or ``(m,)``), or ``None``; ``extra_scale`` the unit the solver measures ``z`` in (the
    interior point is not scale invariant; default the largest of 1, ``|extra0|`` and the finite
    bounds); ``args`` a pytree of arrays handed to ``field`` as data: problems that differ only
    in ``args`` (or in the boundary states) share one compiled solver, whereas each new
    ``field`` function is compiled anew (it is part of the configuration, compared by identity).
    ``extra_quaternions`` ``k``: the first ``4 k`` entries of ``z`` are ``k`` unit quaternions
    (``extra0``'s must have unit norm), whose rates in ``z'`` are ordinary quaternion derivatives
    like ``q'``; the Lie step advances them on the group (their body rates ``2 vec(p* p')``), so
    they stay unit. A bound in ``extra_bound`` applies to their components as to any entry.
    ``extra_final`` ``(m,)``: ``z(T)`` where given (NaN entries stay free); a quaternion's four
    entries are all given (a unit quaternion, reached up to sign: ``vec(pf* p(T)) = 0``) or all
    NaN. Leave free what the dynamics already fix (a conserved momentum, a state slaved to
    ``q``): a redundant final condition makes the Newton systems singular (a failed solve's error
    names such entries).

    The solvers' ``inertia`` is still needed: with the control matrix ``B = dw'/du`` at the
    initial state it gives the body torques the controls can exert, ``|J B| b``, from which the
    eigenaxis time, torque and rate scales are set as for the built-in models. The initial
    guess takes the eigenaxis profile's rates and accelerations ``a`` and, per interval, the
    least-squares controls ``u = B^+ (a - w'(u = 0))`` at its midpoint (the built-in guesses for
    the rigid body and the wheels are this formula's special cases), with ``z`` stepped along by
    explicit Euler.
    """

    field: Callable[..., Any]
    controls: int
    extra0: ArrayLike | None = None
    extra_bound: ArrayLike | None = None
    extra_scale: float | None = None
    args: Any = None
    extra_quaternions: int = 0
    extra_final: ArrayLike | None = None


class Model(NamedTuple):
    """A validated :class:`ControlledModel`: ``z0`` ``(m,)`` and ``bound`` ``(m,)`` (or ``None``)
    in the problem's dtype, ``scale`` a float, ``args`` arrays, ``quaternions`` the ``k`` unit
    quaternions leading ``z``."""

    field: Callable[..., Any]
    controls: int
    z0: Array
    bound: Array | None
    scale: float
    args: Any
    quaternions: int = 0
    final: Array | None = None  # (m,) z(T) targets, 0 where free
    fixed: tuple[bool, ...] = ()  # which entries of z(T) are given (static)


def validated(model: Any, dtype) -> Model:
    """The checked model (errors name the field at fault)."""
    if not isinstance(model, ControlledModel):
        raise TypeError(f"argument 'model' must be a jaxquat.ControlledModel, got {type(model).__name__}")
    if not callable(model.field):
        raise TypeError(f"model.field must be callable field(y, u, args), got {type(model.field).__name__}")
    if not isinstance(model.controls, int) or isinstance(model.controls, bool) or model.controls < 1:
        raise ValueError(f"model.controls must be an int >= 1 (the number of inputs), got {model.controls!r}")
    z0 = np.zeros(0) if model.extra0 is None else np.asarray(model.extra0, np.float64)
    if z0.ndim != 1 or not np.all(np.isfinite(z0)):
        raise ValueError(f"model.extra0 must be finite, shaped (m,) (None: no extra states), got {z0}")
    m = z0.shape[0]
    k = model.extra_quaternions
    if not isinstance(k, int) or isinstance(k, bool) or k < 0 or 4 * k > m:
        raise ValueError(
            f"model.extra_quaternions must be an int k >= 0 with 4 k <= {m} (the first 4 k entries of z), got {k!r}"
        )
    norms = np.linalg.norm(split_state(z0, k)[0], axis=-1)
    if np.any(np.abs(norms - 1) > 1e-6):
        raise ValueError(f"model.extra0's first {4 * k} entries must be {k} unit quaternions, got norms {norms}")
    final, fixed = None, ()
    if model.extra_final is not None:
        zf = np.asarray(model.extra_final, np.float64)
        if zf.shape != (m,) or np.any(np.isinf(zf)):
            raise ValueError(f"model.extra_final must be shaped ({m},) like extra0, finite or NaN (free), got {zf}")
        given, targets = ~np.isnan(zf), np.where(np.isnan(zf), 0.0, zf)
        blocks = split_state(given, k)[0]
        if np.any(blocks.any(axis=-1) != blocks.all(axis=-1)):
            raise ValueError("model.extra_final must give all four entries of an extra quaternion or none (NaN)")
        norms = np.linalg.norm(split_state(targets, k)[0], axis=-1)
        if np.any(blocks.all(axis=-1) & (np.abs(norms - 1) > 1e-6)):
            raise ValueError(f"model.extra_final's extra quaternions must be unit, got norms {norms}")
        final, fixed = jnp.asarray(targets, dtype), tuple(bool(g) for g in given)
    bound = None
    if model.extra_bound is not None:
        bound = np.asarray(model.extra_bound, np.float64)
        bound = np.full(m, bound) if bound.ndim == 0 else bound
        if bound.shape != (m,) or m == 0 or not np.all(bound > 0):
            raise ValueError(f"model.extra_bound must be positive, a scalar or shaped ({m},), got {bound}")
        if np.any(np.abs(z0) > bound):
            raise ValueError(f"model.extra0 {z0} exceeds model.extra_bound {bound}")
    scale = model.extra_scale
    if scale is None:
        finite = [] if bound is None else bound[np.isfinite(bound)].tolist()
        scale = max([1.0, *np.abs(z0).tolist(), *finite])
    scale = float(scale)
    if not (scale > 0 and np.isfinite(scale)):
        raise ValueError(f"model.extra_scale must be a positive finite float, got {model.extra_scale!r}")
    args = jax.tree.map(lambda a: _as_data(a, dtype), model.args)
    return Model(
        model.field,
        model.controls,
        jnp.asarray(z0, dtype),
        None if bound is None else jnp.asarray(bound, dtype),
        scale,
        args,
        k,
        final,
        fixed,
    )


def _as_data(a: Any, dtype) -> Array:
    """An ``args`` leaf as an array: floating ones in the problem's dtype."""
    return jnp.asarray(a, dtype) if np.issubdtype(np.result_type(a), np.floating) else jnp.asarray(a)


def rates(field: Callable[..., Any], y: tuple, u: Array, args: Any) -> tuple[Array, Array, Array]:
    """``field(y, u, args)`` checked against the state's shapes: ``(q', w', z')``."""
    out = field(y, u, args)
    try:
        dq, dw, dz = out
    except (TypeError, ValueError):
        raise ValueError(f"model.field must return the tuple (q', w', z'), got {type(out).__name__}") from None
    want = tuple(jnp.shape(a) for a in y)
    got = tuple(jnp.shape(a) for a in (dq, dw, dz))
    if got != want:
        raise ValueError(f"model.field must return (q', w', z') shaped {want} like the state (q, w, z), got {got}")
    return dq, dw, dz


def lie_field(field: Callable[..., Any], args: Any, quaternions: int = 0) -> Callable:
    """The Lie-algebra form of ``field`` that RKMK4 advances: ``(t, (q, w, z), u) -> (w_b, w',
    z')``, or with ``k = quaternions > 0`` on the split state ``(q, w, P (k, 4), r)`` (``z = (P,
    r)`` flattened) ``-> (w_b, w', P's body rates (k, 3), r')``."""
    k = quaternions

    def lie(t, y, u):
        dq, dw, dz = rates(field, y, u, args)
        return body_rate(y[0], dq), dw, dz

    def split(t, y, u):
        q, w, P, r = y
        dq, dw, dz = rates(field, (q, w, join_state(P, r)), u, args)
        dP, dr = split_state(dz, k)
        return body_rate(q, dq), dw, body_rate(P, dP), dr

    return split if k else lie


def split_state(z: Any, quaternions: int) -> tuple[Any, Any]:
    """``z (..., m) -> (P (..., k, 4), r (..., m - 4 k))``: the leading ``k = quaternions``
    quaternions and the rest (NumPy or JAX arrays)."""
    k = quaternions
    return z[..., : 4 * k].reshape(z.shape[:-1] + (k, 4)), z[..., 4 * k :]


def join_state(P: Array, r: Array) -> Array:
    """The inverse of :func:`split_state`: ``(P (..., k, 4), r (..., m - 4 k)) -> z (..., m)``."""
    return jnp.concatenate([P.reshape(P.shape[:-2] + (4 * P.shape[-2],)), r], axis=-1)


def renormalised(z: Array, quaternions: int) -> Array:
    """``z`` ``(..., m)`` with its leading ``quaternions`` quaternions scaled to unit norm."""
    P, r = split_state(z, quaternions)
    return join_state(P / jnp.linalg.norm(P, axis=-1, keepdims=True), r)


def control_matrix(field: Callable[..., Any], y: tuple, args: Any, n: int) -> tuple[Array, Array]:
    """``(B, w'(u = 0))``: ``B = dw'/du`` ``(3, n)`` at the state ``y`` (exact for dynamics affine
    in ``u``, the linearisation otherwise)."""
    dtype = y[1].dtype

    def wdot(u):  # the value comes out of the Jacobian's own primal pass
        value = rates(field, y, u, args)[1]
        return value, value

    return jax.jacfwd(wdot, has_aux=True)(jnp.zeros(n, dtype))
