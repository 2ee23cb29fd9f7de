"""Lie-group solvers for any diffrax model whose state holds unit quaternions.

``quaternions=`` names the quaternion leaves of the ODE state: a pytree prefix of the
state with ``True`` on each leaf that is a unit quaternion ``(..., 4)``, e.g.
``{"r": False, "v": False, "q": True, "w": False}`` for a quadrotor or
``(True, False, False)`` for a spacecraft ``(q, w, wheel_rates)``. Without it the state
must be the rigid body's ``(q, w)`` (its first leaf is the quaternion).

The user's vector field is an ordinary diffrax one: on a quaternion leaf it returns
``qdot``, e.g. ``1/2 q (0, w_b)``. The solver reads the body rate from it,
``w_b = 2 vec(q* qdot)`` (the component of ``qdot`` along ``q``, which only changes
``|q|``, is dropped: a model may return any ``qdot`` whose tangential part is right), or
takes it from the model's ``body_rate_field(t, y, args)`` where the vector field has one
(the same field with ``w_b`` on each quaternion leaf: jaxquat's ``RigidBody``, ``Quadrotor``
and ``ReactionWheelSpacecraft``, or a user's model), and
advances the leaf on the group: on each step ``q = q_n Exp(theta)`` with
``theta' = J_r(theta)^-1 w_b`` (``dexp^-1``, truncated after the terms the order needs),
the other leaves ``z`` with the same stages, and ``q_(n+1) = q_n Exp(theta_1)``
(Runge-Kutta-Munthe-Kaas; Munthe-Kaas 1999; Hairer, Lubich and Wanner IV.8).
``|q| = 1`` to rounding without a projection step; one Newton step on ``|q|``
(``q (3 - |q|^2) / 2``, a few multiplies) then keeps float32 rounding from walking.

================  =====  =================  =======================================
solver            order  stages (f calls)   error estimate
================  =====  =================  =======================================
LieEuler          1      1                  no (fixed steps)
RKMK4             4      4                  no (fixed steps)
RKMK45            5(4)   7 (6, FSAL)        Dormand-Prince, for ``PIDController``
RKMKTsit5         5(4)   7 (6, FSAL)        Tsitouras; smaller error constant
RKMK8             8(7)   14 (13, FSAL)      Dormand-Prince 8(7), for tight tolerances
================  =====  =================  =======================================

Every one is a ``diffrax.AbstractSolver`` driven by a ``diffrax.ButcherTableau`` (the
adaptive ones reuse diffrax's own tableaus, and are ``AbstractAdaptiveSolver``s), so
``PIDController``, ``ConstantStepSize``, ``SaveAt``, ``Event``,
``RecursiveCheckpointAdjoint`` and ``BacksolveAdjoint`` (its backward solve uses the
same Lie solver on the augmented state) all work. A new method is a subclass of
:class:`AbstractRKMK` with a tableau and an order; anything else a subclass of
:class:`AbstractLieSolver` implementing ``lie_step``. Dense output: for the first-same-as-last
tableaus (``RKMK45``, ``RKMKTsit5``, ``RKMK8``) a quartic in the step's local coordinates
through the tableau's own midpoint (:class:`LocalPolynomialInterpolation`, unit norm); for
the others slerp on the quaternion leaves, linear on the rest (:class:`SlerpInterpolation`).
"""

from __future__ import annotations

import abc
import functools
from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple, cast

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .. import _arrays, _fusion, _quaternion, _rates, _rotation, _safe
from . import struct_of_arrays

__all__ = [
    "AbstractLeafInterpolation",
    "SlerpInterpolation",
    "LocalPolynomialInterpolation",
    "BodyRateTerm",
    "AbstractLieSolver",
    "AbstractRKMK",
    "LieEuler",
    "RKMK4",
    "RKMK45",
    "RKMKTsit5",
    "RKMK8",
]

_RESULTS = diffrax.RESULTS


class QuaternionMask:
    """The ``quaternions=`` prefix, stored hashably (solvers are static data under ``jit``)."""

    def __init__(self, prefix: Any):
        leaves, self.treedef = jax.tree.flatten(prefix)
        bad = [x for x in leaves if not isinstance(x, (bool, np.bool_))]
        if bad or not leaves:
            raise TypeError(
                "argument 'quaternions' must be a pytree prefix of the ODE state with a bool on every leaf "
                f"(True where the leaf is a unit quaternion (..., 4)), got {prefix!r}"
            )
        self.leaves = tuple(bool(x) for x in leaves)

    @classmethod
    def of(cls, prefix: Any) -> QuaternionMask | None:
        return prefix if prefix is None or isinstance(prefix, cls) else cls(prefix)

    def __hash__(self):
        return hash((self.treedef, self.leaves))

    def __eq__(self, other):
        return isinstance(other, QuaternionMask) and (self.treedef, self.leaves) == (other.treedef, other.leaves)

    def __repr__(self):
        return repr(jax.tree.unflatten(self.treedef, self.leaves))

    def broadcast(self, y) -> tuple[bool, ...] | None:
        """One flag per leaf of ``y``, or None if the mask is not a prefix of ``y``."""
        prefix = jax.tree.unflatten(self.treedef, self.leaves)
        try:
            full = jax.tree.map(lambda flag, sub: [flag] * len(jax.tree.leaves(sub)), prefix, y)
        except (ValueError, TypeError):
            return None
        return tuple(jax.tree.leaves(full))


def _is_rigid_body_state(y) -> bool:
    ok = isinstance(y, tuple) and len(y) == 2 and all(hasattr(x, "shape") for x in y)
    return ok and y[0].shape[-1:] == (4,) and y[1].shape[-1:] == (3,)


def leaf_flags(mask: QuaternionMask | None, y, solver: str = "solver") -> tuple[bool, ...]:
    """Which leaves of the state ``y`` are quaternions, checked: ``quaternions`` must be a
    prefix of ``y`` and each flagged leaf a floating array ``(..., 4)``. Without a mask, ``y``
    must be the rigid body's ``(q (..., 4), w (..., 3))``. ``diffrax.BacksolveAdjoint``'s
    backward solve passes the augmented state ``(y, a_y, a_args, a_terms)``: the mask then
    applies to ``y`` and the adjoints are vectors."""
    if mask is None:
        if _is_rigid_body_state(y):
            return (True, False)
        if isinstance(y, tuple) and len(y) == 4 and _is_rigid_body_state(y[0]):
            return (True, False) + (False,) * len(jax.tree.leaves(y[1:]))
        raise TypeError(
            f"{solver} without quaternions= advances the rigid-body state (q (..., 4), w (..., 3)) only; for any "
            "other state name its quaternion leaves, e.g. quaternions={'r': False, 'v': False, 'q': True, 'w': False}"
        )
    flags = mask.broadcast(y)
    if flags is None and isinstance(y, tuple) and len(y) == 4:
        inner = mask.broadcast(y[0])
        if inner is not None:
            flags = inner + (False,) * len(jax.tree.leaves(y[1:]))
    if flags is None:
        raise ValueError(
            f"argument 'quaternions' ({mask!r}) must be a pytree prefix of the ODE state, whose structure is "
            f"{jax.tree.structure(y)}"
        )
    for flag, leaf in zip(flags, jax.tree.leaves(y)):
        if flag and (
            not hasattr(leaf, "shape")
            or leaf.shape[-1:] != (4,)
            or not jnp.issubdtype(jnp.result_type(leaf), jnp.floating)
        ):
            raise ValueError(
                "argument 'quaternions' flags a leaf that is not a floating quaternion array shaped (..., 4): "
                f"got shape {getattr(leaf, 'shape', None)} and dtype {getattr(leaf, 'dtype', type(leaf).__name__)}"
            )
    return flags


class AbstractLeafInterpolation(diffrax.AbstractLocalInterpolation):
    """Dense output over one step, leaf by leaf: a subclass gives :meth:`leaves_at`, the leaves
    at the step fraction ``s = (t - t0)/(t1 - t0)``; this base gives diffrax's ``evaluate``
    (the difference form for two times included) and the leaves' quaternion flags."""

    # each subclass also declares ``mask: QuaternionMask | None`` (static, default None) as its
    # last field; an abstract declaration here would order it before the subclass's own fields
    t0: eqx.AbstractVar[Any]
    t1: eqx.AbstractVar[Any]
    y0: eqx.AbstractVar[Any]

    @abc.abstractmethod
    def leaves_at(self, s, flags: tuple[bool, ...], leaves0: list) -> list:
        """The state's leaves at step fraction ``s``; ``leaves0`` are ``y0``'s."""

    def evaluate(self, t0, t1=None, left: bool = True):
        del left
        if t1 is not None:
            return jax.tree.map(lambda a, b: b - a, self.evaluate(t0), self.evaluate(t1))
        leaves0, tree = jax.tree.flatten(self.y0)
        mask = self.mask  # pyright: ignore[reportAttributeAccessIssue]  # each subclass's last field
        flags = leaf_flags(mask, self.y0, type(self).__name__)
        s = (t0 - self.t0) / jnp.where(self.t1 == self.t0, 1, self.t1 - self.t0)
        return jax.tree.unflatten(tree, self.leaves_at(s, flags, leaves0))


class SlerpInterpolation(AbstractLeafInterpolation):
    """Dense output between two steps: slerp on the quaternion leaves (stays unit), linear
    on the others. ``mask`` None: the rigid body's ``(q, w)``."""

    t0: Any
    t1: Any
    y0: Any
    y1: Any
    mask: QuaternionMask | None = eqx.field(static=True, default=None)

    def leaves_at(self, s, flags, leaves0):
        out = []
        for flag, a, b in zip(flags, leaves0, jax.tree.leaves(self.y1)):
            si = jnp.asarray(s, a.dtype)
            out.append(_rotation.slerp(a, b, jnp.broadcast_to(si, a.shape[:-1])) if flag else a + si * (b - a))
        return out


class LocalPolynomialInterpolation(AbstractLeafInterpolation):
    """Dense output of the first-same-as-last RKMK solvers, in the step's local coordinates:
    ``q(s) = q0 Exp(p(s))`` on quaternion leaves (unit norm) and ``y0 + p(s)`` elsewhere, with
    ``p`` the quartic through ``p(0) = 0``, ``p(1/2) = mid`` and ``p(1) = incr`` with the end
    slopes ``d0``, ``d1`` (``s = (t - t0)/(t1 - t0)``; the form of diffrax's Dopri5 dense output).
    ``incr`` is the step's increment (``theta_1`` on quaternions), ``d0``, ``d1`` the step times
    the local-coordinate slopes at both ends (the first and last stages) and ``mid`` the
    tableau's own continuous extension at ``s = 1/2`` (``h sum_i b_i(1/2) k_i``: in local
    coordinates RKMK is a classical Runge-Kutta method, so its dense output carries over). Without
    ``mid`` (a tableau with no continuous extension), the cubic Hermite through the ends.
    Measured on the quadrotor (``tests/test_lie_solvers.py``, PID at 1e-9, 37 times against
    DOP853): attitude error 4.4e-9 rad for ``RKMK45`` (the cubic Hermite: 1.7e-7), 9.1e-10 for
    ``RKMKTsit5``; on the quadrotor example at 1e-10, 201 saved times, 1.0e-10 (cubic 8.2e-9).
    A quartic is below ``RKMK8``'s order: with its long steps the dense error is 1.5e-6 there
    (``SaveAt(ts=...)`` interpolates too; where that matters, make the saved times step ends
    with ``diffrax.PIDController(..., step_ts=ts)``)."""

    t0: Any
    t1: Any
    y0: Any
    y1: Any
    incr: Any
    d0: Any
    d1: Any
    mid: Any = None
    mask: QuaternionMask | None = eqx.field(static=True, default=None)

    def leaves_at(self, s, flags, leaves0):
        mids = [None] * len(leaves0) if self.mid is None else jax.tree.leaves(self.mid)
        out = []
        for flag, y, d, a, b, m in zip(
            flags, leaves0, *(jax.tree.leaves(x) for x in (self.incr, self.d0, self.d1)), mids
        ):
            si = jnp.asarray(s, y.dtype)
            if m is None:  # cubic Hermite
                c4, c3, c2 = 0.0, a + b - 2 * d, 3 * d - 2 * a - b
            else:  # quartic through the midpoint
                c4 = 2 * (b - a) - 8 * d + 16 * m
                c3 = 5 * a - 3 * b + 14 * d - 32 * m
                c2 = b - 4 * a - 5 * d + 16 * m
            p = (((c4 * si + c3) * si + c2) * si + a) * si
            out.append(unit(_quaternion.multiply(y, _rotation.from_rotvec(p))) if flag else y + p)
        return out


class _Interpolation(eqx.Module):
    """``interpolation_cls`` of a masked solver: a hashable factory diffrax calls with the dense info."""

    mask: QuaternionMask | None = eqx.field(static=True)
    local: bool = eqx.field(static=True, default=False)
    ends: bool = eqx.field(static=True, default=False)

    def __call__(self, *, t0, t1, y0, y1, **slopes):
        if self.ends:
            return _StepEndInterpolation(t0=t0, t1=t1, y0=y0, y1=y1)
        if self.local:
            return LocalPolynomialInterpolation(t0=t0, t1=t1, y0=y0, y1=y1, mask=self.mask, **slopes)
        return SlerpInterpolation(t0=t0, t1=t1, y0=y0, y1=y1, mask=self.mask)


class _StepEndInterpolation(diffrax.AbstractLocalInterpolation):
    """Dense output that knows only the step's two ends: ``y0`` at ``t0``, ``y1`` at ``t1`` (each
    to 16 units of rounding of the times), NaN between (so that a time inside a step cannot pass
    unnoticed). For a solve whose saved times are all step ends (``SaveAt(ts=ts)`` with
    ``diffrax.ClipStepSizeController(..., step_ts=ts)``, as ``simulate``'s adaptive path runs): a
    Lie solver with ``saves_at_step_ends=True``. The saved states are then the steps' own ends,
    and diffrax's saving traces no polynomial. The rounding margin: a step that ends one unit of
    rounding short of a saved time is not clipped, and the next step, which starts there, saves
    it (seen at ``t = 4.2``, the step ending at 4.199999999999999)."""

    t0: Any
    t1: Any
    y0: Any
    y1: Any

    def evaluate(self, t0, t1=None, left: bool = True):
        del left
        if t1 is not None:
            return jax.tree.map(lambda a, b: b - a, self.evaluate(t0), self.evaluate(t1))

        t = jnp.asarray(t0)
        margin = 16 * jnp.finfo(jnp.result_type(t, self.t0, self.t1, float)).eps
        margin = margin * jnp.maximum(jnp.abs(self.t0), jnp.abs(self.t1))
        at_start, at_end = jnp.abs(t - self.t0) <= margin, jnp.abs(t - self.t1) <= margin

        def pick(a, b):
            return jnp.where(at_end, b, jnp.where(at_start, a, jnp.full_like(b, jnp.nan)))

        return jax.tree.map(pick, self.y0, self.y1)


def unit(q: Array) -> Array:
    """One Newton step towards ``|q| = 1``: ``q (3 - |q|^2) / 2``.

    A product of unit quaternions is unit only to rounding, and over many steps the
    rounding errors of ``|q|`` add up (in float32 to ``| |q| - 1 |`` of about 3e-5 after
    1000 steps). With ``|q|^2 = 1 + e`` the step leaves ``1 + O(e^2)``, so the norm stays
    at rounding level for good, at the cost of a few multiplies (no square root or division).
    """
    return q * (1.5 - 0.5 * _safe.norm_sq(q))[..., None]


def body_rate(q: Array, qdot: Array) -> Array:
    """``w_b = 2 vec(q* qdot)`` for a unit ``q``: the body rate of a quaternion velocity; the
    component of ``qdot`` along ``q`` (a change of ``|q|`` only) drops out."""
    return 2 * _rates.vec_rate(q, qdot, "body")


def dexpinv(theta: Array, w: Array, order: int) -> Array:
    """``J_r(theta)^-1 w`` truncated for an RKMK method of ``order`` p: the terms
    ``B_k/k! ad^k`` with ``k <= p - 1`` (Munthe-Kaas 1999; ``theta = O(h)``, so the rest
    is ``O(h^(p+1))`` per step). In so(3) ``ad^(2j+2) = (-|theta|^2)^j ad^2``, so this is
    ``w + 1/2 theta x w + c theta x (theta x w)`` with ``c = 1/12`` (p = 3, 4),
    ``+ |theta|^2/720`` (p = 5, 6), ``+ |theta|^4/30240`` (p >= 7): polynomial, no division."""
    if order <= 1:
        return w
    cross = jnp.cross(theta, w)
    if order == 2:
        return w + 0.5 * cross
    coef = _safe.jacobian_inverse_coeff_truncated(order, _safe.norm_sq(theta)[..., None] if order >= 5 else None)
    return w + 0.5 * cross + coef * jnp.cross(theta, cross)


def _exp_rows(theta: Array) -> Array:
    """The rows of ``Exp(theta) = (cos(|theta|/2), sin(|theta|/2) theta / |theta|)``, its two
    scalars ``cos`` and ``sinc/2`` (:func:`jaxquat._safe.sinc_cos_of_sq`) written by one loop
    (:func:`jaxquat._fusion.one_loop`) before the product that takes them.

    Why: XLA on CPU (jaxlib 0.10.2) otherwise fused the exponential, both of its branches and
    the range reduction, into every component of ``q Exp(theta)``, and the step's end state
    into each of its two users (the scan's carry and the stored state): the profile of
    ``minimum_time_reorientation``'s rollout showed two kernels of 72 us per step at 1000
    bodies, and its compiled program three range reductions where one is needed. An
    ``optimization_barrier`` (``_arrays.scalars``) did not stop it. Measured on that rollout (80
    intervals x 4 RKMK4 steps, ``vmap`` over 1000 bodies, one pinned core of a 2-core AMD EPYC,
    least of 9, processes alternated, session 88), before -> after: float32 forward pass 113 ->
    70 ms, gradient in ``u`` 303-307 -> 223-228 ms; float64 86 -> 39-40 ms and 291-292 ->
    206-212 ms; the gradients agree to ten digits in float64, six in float32. The gradient's ratio to the
    forward pass rises (float64 3.4 -> 5.3x) because the forward pass gained more. Writing all
    four components in the loop gave the same times. The interior-point solver's small problems
    (float64, interleaved fresh processes): Bilimoria-Wie at 80 intervals, first call 7.4-8.2 ->
    7.5-7.8 s, a solve 0.78 -> 0.77-0.78 s; three reaction wheels at 20 intervals, 4 starts,
    8.8-9.1 -> 9.1-10.0 s and 0.93-1.01 -> 0.98-1.16 s (this hour's spread is as large);
    ``minimum_time_reorientation`` at 30 intervals, 8 starts, 10.4-10.8 -> 10.4-10.9 s and
    1.49-1.57 -> 1.52-1.73 s. The same optima to twelve digits."""
    r0, r1, r2 = _arrays.components(theta)
    sinc, cos = _safe.sinc_cos_of_sq(0.25 * (r0 * r0 + r1 * r1 + r2 * r2))
    cos, h = _fusion.one_loop((cos, 0.5 * sinc))
    return _arrays.assemble(cos, h * r0, h * r1, h * r2)


class _RowLeaves:
    """A quaternion leaf as its ``(..., 4)`` rows (``layout="rows"``): every value of a leaf is a
    1-tuple holding the array, the local coordinates and slopes ``(..., 3)``."""

    @staticmethod
    def split(q: Array) -> tuple[Array, ...]:
        return (q,)

    @staticmethod
    def point(q: tuple, theta: tuple) -> Array:
        """The rows of ``q Exp(theta)`` (a stage's argument of the vector field)."""
        return _quaternion.multiply(q[0], _exp_rows(theta[0]))

    @staticmethod
    def rate(w: Array, computed: bool) -> tuple[Array, ...]:
        """The parts of a body rate ``(..., 3)``, the tangent field's value on the leaf (``computed``:
        read from ``qdot`` by the solver or a term's own expression, not a model's
        ``body_rate_field``)."""
        return (w,)

    @staticmethod
    def dexpinv(theta: tuple, w: tuple, order: int) -> tuple[Array, ...]:
        return (dexpinv(theta[0], w[0], order),)

    @staticmethod
    def advance(q: tuple, theta: tuple) -> tuple[tuple, Array]:
        """``q Exp(theta)`` with one Newton step on its norm: its parts and its rows."""
        q1 = unit(_quaternion.multiply(q[0], _exp_rows(theta[0])))
        return (q1,), q1

    @staticmethod
    def error(q1: tuple, e: tuple) -> Array:
        """``q1 (0, e/2)``, the first-order difference ``q1 - q_n Exp(theta_1 - e)``."""
        return _quaternion.multiply(q1[0], jnp.concatenate([jnp.zeros_like(e[0][..., :1]), 0.5 * e[0]], -1))

    @staticmethod
    def rows(c: tuple) -> Array:
        return c[0]


class _ComponentLeaves:
    """A quaternion leaf as one array per component (``layout="components"``, the default): the
    Lie part of a step (``Exp``, the products, ``dexp^-1``, the norm step) written out on them as
    in :mod:`jaxquat.integration.struct_of_arrays`, element-wise over the batch. The vector field
    still takes and returns rows: its argument is assembled and then multiplied by ``I_4``, and a
    rate the solver read from ``qdot`` is split by
    :func:`jaxquat.integration.struct_of_arrays.columns_by_products` (a model's own rates plainly:
    :class:`_ModelRates`); XLA on CPU fuses neither product, so the field runs as row kernels of
    its own and the step's Lie part as element-wise ones. Measured (``diffeqsolve`` with
    ``RKMK4``, a ``RigidBody`` read through ``qdot``, 1000 bodies x 1000 steps, float32, this
    2-core CPU, one run each): the forward pass 333 ms without the two products (XLA fused the
    field's rows into each component of every stage's slope), 365 ms with the first alone, 110 ms
    with the second alone, 85 ms with both; the row layout 600 ms."""

    @staticmethod
    def split(q: Array) -> tuple[Array, ...]:
        return tuple(_arrays.components(q))

    @staticmethod
    def point(q: tuple, theta: tuple) -> Array:
        rows = _arrays.assemble(*struct_of_arrays.multiply(q, struct_of_arrays.exp(theta)))
        return _arrays.matmul(rows, jnp.eye(4, dtype=rows.dtype))

    @staticmethod
    def rate(w: Array, computed: bool) -> tuple[Array, ...]:
        return struct_of_arrays.columns_by_products(w) if computed else tuple(_arrays.components(w))

    @staticmethod
    def dexpinv(theta: tuple, w: tuple, order: int) -> tuple[Array, ...]:
        return struct_of_arrays.dexpinv(theta, w, order)

    @staticmethod
    def advance(q: tuple, theta: tuple) -> tuple[tuple, Array]:
        q1 = struct_of_arrays.unit(struct_of_arrays.multiply(q, struct_of_arrays.exp(theta)))
        return q1, _arrays.assemble(*q1)

    @staticmethod
    def error(q1: tuple, e: tuple) -> Array:
        return _arrays.assemble(*cast(list[Array], _quaternion.multiply_components(q1, (None, *(0.5 * x for x in e)))))

    @staticmethod
    def rows(c: tuple) -> Array:
        return _arrays.assemble(*c)


_LAYOUTS = {"components": _ComponentLeaves, "rows": _RowLeaves}


def _as_parts(x: Array) -> tuple[tuple[Array], Array]:
    """A leaf that is not a quaternion as ``(parts, rows)``: one part, the array itself."""
    return (x,), x


def _layout(value: str) -> str:
    if value not in _LAYOUTS:
        raise ValueError(f"argument 'layout' must be one of {sorted(_LAYOUTS)}, got {value!r}")
    return value


def _model_body_rates(terms) -> tuple[Callable, Any] | None:
    """``(body_rate_field, time direction)`` of a plain ``diffrax.ODETerm`` whose vector field has
    that method, as ``solve_fixed_steps`` hands it or inside the time-direction wrapper that
    ``diffeqsolve`` puts around every term (``WrapTerm``, not public in diffrax: recognised by
    its name and fields, and any other term takes the generic path); otherwise None."""
    direction = None
    if type(terms).__name__ == "WrapTerm" and hasattr(terms, "term") and hasattr(terms, "direction"):
        terms, direction = terms.term, terms.direction
    if type(terms) is not diffrax.ODETerm:
        return None
    field = getattr(terms.vector_field, "body_rate_field", None)
    return None if field is None else (field, direction)


class _ModelRates:
    """A tangent field made from a model's ``body_rate_field``: called as the function it wraps;
    its type tells a step that the rates are the model's own values (in the rigid body's case
    the state's ``w`` itself), so the component layout splits them plainly: XLA fuses the split
    with whatever formed them, cheap here, while a rate the solver computed from ``qdot`` is
    split through products (``columns_by_products``) that keep that computation out of every
    component's kernel. Measured (``solve_fixed_steps``, ``RKMK4``, 1000 bodies x 1000 steps,
    one core, float32 / float64): ``RigidBody``'s own rates split plainly 22 / 42 ms forward and
    0.27 / 0.44 s gradient, through products 33 / 49 ms and 0.38 / 0.50 s; rates read from
    ``qdot`` split plainly 298 / 334 ms and 1.42 / 1.65 s, through products 83 / 115 ms and
    0.79 / 1.01 s."""

    def __init__(self, fn: Callable, rigid_body: _RigidBodyParts | None = None):
        self.fn = fn
        self.rigid_body = rigid_body

    def __call__(self, t, y) -> list:
        return self.fn(t, y)


class _RigidBodyParts(NamedTuple):
    """What a model's ``euler_equations()`` gives (its inertia and body torque), with the time
    direction and ``args`` of the solve: enough for :func:`_rigid_body_step`."""

    inertia: Array
    torque: Callable | None
    direction: Any
    args: Any


def _rigid_body_parts(field: Callable, direction, args, flags: tuple[bool, ...]) -> _RigidBodyParts | None:
    """The parts of a model whose state is the rigid body's ``(q, w_b)`` and whose method
    ``euler_equations()`` returns ``(inertia, body_torque or None)`` (``RigidBody``, ``simulate``'s
    field): its body rates are ``w_b`` and its ``dw_b/dt`` Euler's equations with that torque."""
    model = getattr(field, "__self__", None)
    parts = getattr(model, "euler_equations", None)
    if flags != (True, False) or not callable(parts):
        return None
    inertia, torque = cast(tuple[Array, Callable | None], parts())
    return _RigidBodyParts(inertia, torque, direction, args)


def _rigid_body_step(tab: _SoATableau, parts: _RigidBodyParts, tangent, t0, t1, h, y0, solver_state, made_jump):
    """A Lie solver's step on a rigid-body model, in components
    (:func:`jaxquat.integration.struct_of_arrays.lie_step`, each stage one loop over the batch on
    CPU): the same method as the generic step, which runs the model's vector field on rows (the
    figures in :class:`AbstractLieSolver`'s ``layout``). ``simulate`` with a torque (its default
    ``RKMK45``, a ``vmap`` of one-body solves; the PD law of ``benchmarks/simulation.py`` on 1000
    bodies over 10 s, one core, float32 / float64): forward 23.5 / 67.6 -> 9.1-10.9 / 35.6-39.1
    ms, gradient 177 / 459 -> 111-116 / 288-313 ms. The carried first stage of a
    first-same-as-last tableau goes through the input barrier with ``(q, w)``: left out, its
    cotangents were reductions over the backward step of their own, which XLA's CPU fusion
    emitters compiled into code re-evaluating the step's subgraphs (the gradient of 10 bodies
    through ``RKMK45`` took 1.3 s instead of 0.6 ms)."""
    soa = struct_of_arrays
    leaves, tree = jax.tree.flatten(y0)
    q, w = leaves
    euler = soa.EulerEquations(parts.inertia, parts.torque, False)

    first = None
    if tab.fsal_state and solver_state is not None:
        g0 = jax.lax.cond(made_jump, lambda: tangent(t0, y0), lambda: solver_state)
        first = (soa.split(g0[0]), soa.split(g0[1]))

    # The step as a jitted function of its arrays: one equation in the caller's jaxpr, whose
    # transformations JAX caches on it. Diffrax's checkpointed adjoint transforms the loop's body
    # several times over (linearize, vjp, vmap); inlined, the component step's 2442 equations
    # (937 in rows) were transformed anew each time. Time to the first gradient of 1000 bodies
    # through simulate with the PD torque (benchmarks/simulation.py; adaptive RKMK45, float32):
    # 19.5 s inlined (11.4 s tracing, 8.0 s XLA), 14.1-14.4 s so (6.4-6.5 s, 7.5-7.9 s); the row layout
    # 11.9 s (5.0 s, 6.7 s).
    dynamic, static = eqx.partition(parts.args, eqx.is_array)

    def step(direction, t0, dt, h, q, w, dynamic, first, entries):
        def field(t, qc, wc, args, entries):
            return wc, euler.with_entries(entries)(t if direction is None else t * direction, qc, wc, args)

        args = eqx.combine(dynamic, static)
        return soa.lie_step(
            tab.soa,
            field,
            t0,
            dt,
            h,
            q,
            w,
            args,
            parts.torque is not None,
            tab.b_error,
            tab.mid_weights,
            first,
            entries,
            tab.dense,
            tab.fsal_state,
        )

    out = jax.jit(step)(parts.direction, t0, t1 - t0, h, soa.split(q), soa.split(w), dynamic, first, euler.entries())

    def rows(pair):
        return jax.tree.unflatten(tree, [soa.stack(pair[0]), soa.stack(pair[1])])

    y1 = rows((out.q1, out.z1))
    y_error = None if out.error is None else rows(out.error)
    if not tab.fsal_state:
        return y1, y_error, None, None
    assert out.last is not None  # carried: tab.fsal_state
    last = [soa.stack(out.last[0]), soa.stack(out.last[1])]
    if not tab.dense:
        return y1, y_error, None, last
    assert out.theta is not None and out.dz is not None and out.start is not None and out.end is not None
    dense = dict(y0=y0, y1=y1, incr=rows((out.theta, out.dz)), d0=rows(out.start), d1=rows(out.end))
    dense["mid"] = None if out.mid is None else rows(out.mid)
    return y1, y_error, dense, last


class _SoATableau(NamedTuple):
    """A Lie solver's tableau for :func:`_rigid_body_step`: as Python floats, whether the step
    carries its last stage (first-same-as-last), the error and midpoint weights (None: none), and
    whether it computes the dense output's slopes."""

    soa: struct_of_arrays.Tableau
    fsal_state: bool
    b_error: list[float] | None = None
    mid_weights: list[float] | None = None
    dense: bool = False  # a first-same-as-last tableau that does not save at step ends


def _body_rate_form(field: Callable, direction, args, flags: tuple[bool, ...], t, y) -> list:
    """The leaves of ``field(t, y, args)``, a model's ``body_rate_field`` (at ``t * direction``
    inside ``diffeqsolve``'s wrapper), each broadcast and cast to its state leaf as
    ``diffrax.ODETerm.vf`` does (the body rate ``(..., 3)`` on a quaternion leaf ``(..., 4)``)."""
    out = field(t if direction is None else t * direction, y, args)
    if jax.tree.structure(out) != jax.tree.structure(y):
        raise ValueError(
            f"body_rate_field must return a pytree with the structure of the state, {jax.tree.structure(y)}"
        )
    return [
        jnp.broadcast_to(v, x.shape[:-1] + (3,) if f else x.shape).astype(x.dtype)
        for f, x, v in zip(flags, jax.tree.leaves(y), jax.tree.leaves(out))
    ]


class BodyRateTerm(diffrax.ODETerm):
    """An ``ODETerm`` whose vector field returns, on each quaternion leaf, the body rate
    ``w_b`` ``(..., 3)`` instead of ``qdot`` (the Lie-algebra form ``q' = q (0, w_b)/2``): the
    Lie solvers then use it as it is, with no conversion and no rounding from one. For
    :func:`jaxquat.solve_fixed_steps` (``diffeqsolve`` wants a vector field shaped like the
    state); ``simulate``'s and ``minimum_time_reorientation``'s fixed-step paths use it."""

    def vf(self, t, y, args):
        return self.vector_field(t, y, args)


class AbstractLieSolver(diffrax.AbstractSolver):
    """Base of the Lie-group solvers: subclass it and implement :meth:`lie_step`.

    ``quaternions``: see the module docstring. :meth:`step` (diffrax's) turns the user's
    vector field into the *tangent* field ``tangent(t, y)``, which holds the body rate
    ``w_b`` (``(..., 3)``) on each quaternion leaf and the vector field on the others, and
    calls ``lie_step``. ``simulate`` and ``minimum_time_reorientation`` drive every solver
    through ``init`` and ``step`` only (:func:`jaxquat.solve_fixed_steps`).

    Every Lie solver (``LieEuler``, ``RKMK4``, ``RKMK45``, ``RKMKTsit5``, ``RKMK8``) is built
    the same way, e.g. ``RKMK45(quaternions={"q": True, "w": False})``, and passed to
    ``diffrax.diffeqsolve`` as its ``solver``.

    Attributes:
        quaternions: which leaves of the ODE state are unit quaternions ``(..., 4)``: a pytree
            prefix of the state with ``True`` on each (e.g. ``(True, False, False)`` for
            ``(q, w, wheel_rates)``). ``None``: the state is the rigid body's ``(q, w)``.
        layout: how the built-in steps (``LieEuler``, ``AbstractRKMK``) hold a quaternion leaf
            inside a step: ``"components"`` (default), one array per component, the step's Lie
            part element-wise over the batch; ``"rows"``, the ``(..., 4)`` rows. The same method
            and values to rounding. Measured (``diffeqsolve`` with ``RKMK4``, ``RigidBody``,
            1000 bodies x 1000 steps, float32, this 2-core CPU): the forward pass 25 against
            92 ms, the gradient 0.31 against 0.61 s (diffrax's default adjoint), a ``vmap`` of
            one-body solves 123 against 211 ms (with a vector field read through ``qdot``, as
            before ``body_rate_field``: 85 against 600 ms, 0.83 against 3.8 s). ``"rows"`` for
            the optimal-control transcription's small per-interval rollouts under second
            derivatives (Bilimoria-Wie, 80 intervals: solve 0.92 against 1.2-1.6 s, first call
            8.9 against 10.1 s). On a model whose state is ``(q, w_b)`` and which has
            ``euler_equations()`` (``RigidBody``, ``simulate``'s field), ``"components"`` steps
            the whole body one array per component, Euler's equations included, each stage one
            loop over the batch on CPU (:func:`jaxquat.integration.struct_of_arrays.lie_step`):
            ``diffeqsolve`` with ``RKMK4``, 1000 bodies x 1000 steps, one core, float32 /
            float64: forward 15.0 / 27.7 -> 7.4 / 12.7 ms, gradient 177 / 304 -> 56 / 106 ms
            (diffrax's default adjoint; 28 / 72 ms with a checkpoint per step,
            ``RecursiveCheckpointAdjoint(checkpoints=max_steps)``). Its first gradient takes
            longer to compile: through ``simulate`` with a torque (adaptive ``RKMK45``, 1000
            bodies, float32) 14.1-14.4 s to the first result against 11.9 s in rows, whose
            later gradients are slower.
        saves_at_step_ends: the dense output knows only each step's two ends (``y0`` at ``t0``,
            ``y1`` at ``t1``, NaN inside a step): for a solve that saves at step ends only,
            ``SaveAt(ts=ts)`` with ``diffrax.ClipStepSizeController(..., step_ts=ts)``, as
            ``simulate``'s adaptive path sets it. Diffrax's saving then traces no dense
            output, and a first-same-as-last step computes no slopes for one: ``simulate``
            of 1000 PD-controlled bodies (``RKMK45``, float32, one core) 9.2 -> 6.3 ms forward,
            54.8 -> 41.6 ms gradient, 14.1-14.4 -> 11.4 s to the first gradient.
    """

    quaternions: Any = eqx.field(static=True, default=None, converter=QuaternionMask.of)
    layout: str = eqx.field(static=True, default="components", converter=_layout)
    saves_at_step_ends: bool = eqx.field(static=True, default=False)
    term_structure: ClassVar = diffrax.AbstractTerm

    @property
    def interpolation_cls(self) -> Callable[..., diffrax.AbstractLocalInterpolation]:  # type: ignore[override]
        return _Interpolation(self.quaternions, ends=self.saves_at_step_ends)

    @abc.abstractmethod
    def lie_step(self, tangent, t0, t1, h, y0, flags, solver_state, made_jump) -> tuple[Any, Any, Any, Any]:
        """One step from ``(t0, y0)`` to ``t1``: returns ``(y1, y_error or None, dense_info or
        None, solver_state)``. ``tangent`` is evaluated at times in ``[t0, t1]``; ``h`` (diffrax's
        control ``contr(t0, t1)``) scales the increments; the two differ in sign when diffrax
        solves backwards in time (it flips the time variable and wraps the term). ``flags`` is
        one bool per leaf of ``y0`` (True: a unit quaternion). ``dense_info`` None means
        ``dict(y0=y0, y1=y1)`` for :class:`SlerpInterpolation`."""

    def init(self, terms, t0, t1, y0, args):
        leaf_flags(self.quaternions, y0, type(self).__name__)
        return None

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    def tangent_field(self, terms, args, flags) -> Callable:
        """``tangent(t, y)``: the vector field with each quaternion leaf's ``qdot`` read as its
        body rate ``w_b = 2 vec(q* qdot)``. A vector field may return the body rate ``(..., 3)``
        itself on a quaternion leaf (the Lie-algebra form, :class:`BodyRateTerm`: no conversion,
        no rounding from it). A plain ``diffrax.ODETerm`` whose vector field has a method
        ``body_rate_field(t, y, args)`` (the same field in that form: ``RigidBody``, ``Quadrotor``,
        ``ReactionWheelSpacecraft``) is evaluated through it: the rates the field turned into
        ``qdot = q (0, w_b)/2`` are not read back from it. Measured (``solve_fixed_steps``,
        ``RKMK4``, ``RigidBody``, 1000 bodies x 1000 steps, float32, this 2-core CPU): forward
        88 against 51 ms, gradient 1.07 against 0.58 s."""
        lie_form = _model_body_rates(terms)
        if lie_form is not None:
            parts = _rigid_body_parts(*lie_form, args, flags) if self.layout == "components" else None
            return _ModelRates(functools.partial(_body_rate_form, *lie_form, args, flags), parts)

        def tangent(t, y):
            out = jax.tree.leaves(terms.vf(t, y, args))
            return [
                body_rate(q, v) if flag and v.shape[-1] == 4 else v
                for flag, q, v in zip(flags, jax.tree.leaves(y), out)
            ]

        return tangent

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        flags = leaf_flags(self.quaternions, y0, type(self).__name__)
        h = terms.contr(t0, t1)
        y1, y_error, dense, solver_state = self.lie_step(
            self.tangent_field(terms, args, flags), t0, t1, h, y0, flags, solver_state, made_jump
        )
        dense = dict(y0=y0, y1=y1) if dense is None or self.saves_at_step_ends else dense
        return y1, y_error, dense, solver_state, _RESULTS.successful


class AbstractRKMK(AbstractLieSolver):
    """Runge-Kutta-Munthe-Kaas with an explicit ``diffrax.ButcherTableau``: give a subclass a
    ``tableau`` and an ``order`` (the ``dexp^-1`` series is truncated for it). First-same-as-last
    tableaus (Dormand-Prince, Tsitouras) reuse the last stage's tangent as the next step's
    first, carried as the solver state. The stages run in a ``lax.fori_loop``, so the vector
    field is traced and compiled once whatever the number of stages (unrolled, the fast
    variant of the slew example took 48 s instead of 29 s, nearly all compilation, for at most
    10 % more throughput)."""

    tableau: ClassVar[diffrax.ButcherTableau]
    #: ``b_i(1/2)``, the tableau's continuous extension at the step's midpoint (None: none; the
    #: dense output is then the cubic Hermite); see :func:`midpoint_weights`. The subclasses
    #: here give them as literals (``midpoint_weights`` at import cost 1.2 s of ``import
    #: jaxquat``'s 1.8 s, in eager float64 compilations); ``tests/test_lie_solvers.py`` checks
    #: them against ``midpoint_weights`` of diffrax's own solvers to the last bit.
    mid_weights: ClassVar[np.ndarray | None] = None

    @property
    def interpolation_cls(self) -> Callable[..., diffrax.AbstractLocalInterpolation]:  # type: ignore[override]
        return _Interpolation(self.quaternions, local=self.tableau.fsal, ends=self.saves_at_step_ends)

    def init(self, terms, t0, t1, y0, args):
        flags = leaf_flags(self.quaternions, y0, type(self).__name__)
        if not self.tableau.fsal:
            return None
        return self.tangent_field(terms, args, flags)(t0, y0)

    def lie_step(self, tangent, t0, t1, h, y0, flags, solver_state, made_jump):
        tab = self.tableau
        order = self.order(None)
        if order is None:
            raise TypeError(f"{type(self).__name__}.order must return the method's order, got None")
        if isinstance(tangent, _ModelRates) and tangent.rigid_body is not None:
            soa_tab = _SoATableau(
                struct_of_arrays.Tableau.of(tab, order),
                bool(tab.fsal),
                np.asarray(tab.b_error).tolist() if isinstance(self, diffrax.AbstractAdaptiveSolver) else None,
                None if self.mid_weights is None else np.asarray(self.mid_weights).tolist(),
                bool(tab.fsal) and not self.saves_at_step_ends,
            )
            return _rigid_body_step(soa_tab, tangent.rigid_body, tangent, t0, t1, h, y0, solver_state, made_jump)
        stages = tab.num_stages
        a = np.zeros((stages, stages))
        for i, row in enumerate(tab.a_lower):
            a[i + 1, : len(row)] = row
        c = np.concatenate([[0.0], tab.c])
        lay = _LAYOUTS[self.layout]
        leaves, tree = jax.tree.flatten(y0)
        # every value of a leaf is a tuple: the layout's parts on a quaternion leaf (q = q_n Exp(theta),
        # theta its local coordinates), the array itself (a 1-tuple) elsewhere
        parts = [lay.split(x) if f else (x,) for f, x in zip(flags, leaves)]

        def point(incr):
            return jax.tree.unflatten(
                tree, [lay.point(qp, d) if f else x + d[0] for f, x, qp, d in zip(flags, leaves, parts, incr)]
            )

        computed = not isinstance(tangent, _ModelRates)

        def rates(g):
            return [lay.rate(v, computed) if f else (v,) for f, v in zip(flags, g)]

        def slope(theta, w):
            return [lay.dexpinv(th, wi, order) if f else wi for f, th, wi in zip(flags, theta, w)]

        def weigh(weights, ks):
            return [
                tuple(
                    jnp.tensordot(jnp.asarray(weights, k.dtype), k, axes=1, precision=_arrays.FULL) * h.astype(k.dtype)
                    for k in kk
                )
                for kk in ks
            ]

        def rows(values):
            return jax.tree.unflatten(tree, [lay.rows(v) if f else v[0] for f, v in zip(flags, values)])

        h = jnp.asarray(h)
        if tab.fsal and solver_state is not None:
            g0 = jax.lax.cond(made_jump, lambda: tangent(t0, y0), lambda: solver_state)
        else:
            g0 = tangent(t0, y0)
        k0 = rates(g0)  # dexp^-1 at theta = 0 is the identity
        ks = [tuple(jnp.zeros((stages,) + x.shape, x.dtype).at[0].set(x) for x in k) for k in k0]
        a_arr, c_arr = jnp.asarray(a), jnp.asarray(c)

        def stage(i, carry):
            ks, _ = carry
            incr = weigh(a_arr[i], ks)
            g = tangent(t0 + c_arr[i].astype(jnp.result_type(t0, t1)) * (t1 - t0), point(incr))
            k = slope(incr, rates(g))
            return [tuple(b.at[i].set(x) for b, x in zip(kk, ki)) for kk, ki in zip(ks, k)], g

        ks, g_last = jax.lax.fori_loop(1, stages, stage, (ks, g0))
        incr = weigh(tab.b_sol, ks)
        # (parts, rows) of each leaf at the step's end
        ends = [lay.advance(qp, d) if f else _as_parts(x + d[0]) for f, x, qp, d in zip(flags, leaves, parts, incr)]
        y1 = jax.tree.unflatten(tree, [y for _, y in ends])
        y_error = None
        if isinstance(self, diffrax.AbstractAdaptiveSolver):
            err = weigh(tab.b_error, ks)
            # on a quaternion leaf q1 - q_n Exp(theta_1 - e) = q1 (0, e/2) + O(|e|^2): no second Exp
            y_error = jax.tree.unflatten(
                tree, [lay.error(p, e) if f else e[0] for f, (p, _), e in zip(flags, ends, err)]
            )
        if not tab.fsal:
            return y1, y_error, None, None
        # FSAL: the last stage is the tangent at y1, so the end slopes of the local polynomial come free
        k1 = slope(incr, rates(g_last))
        dense = dict(
            y0=y0,
            y1=y1,
            incr=rows(incr),
            d0=rows([tuple(x * h.astype(x.dtype) for x in k) for k in k0]),
            d1=rows([tuple(x * h.astype(x.dtype) for x in k) for k in k1]),
            mid=None if self.mid_weights is None else rows(weigh(self.mid_weights, ks)),
        )
        return y1, y_error, dense, g_last


def midpoint_weights(solver_cls: type[diffrax.AbstractRungeKutta]) -> np.ndarray:
    """``b_i(1/2)``: the weights of a diffrax Runge-Kutta solver's own dense output at the middle
    of a step, read through its public ``interpolation_cls`` (linear in the stages: evaluated with
    ``y0 = y1 = 0`` and the stages set to the identity). Dopri5, Tsit5 and Dopri8 give weights
    independent of ``y1``. Computed in float64 whatever JAX's precision mode, so a float64 run
    never meets float32-rounded weights."""
    tableau = solver_cls.tableau
    if not isinstance(tableau, diffrax.ButcherTableau):
        raise TypeError(f"{solver_cls.__name__} has no single Butcher tableau")
    n = tableau.num_stages
    x64 = getattr(jax, "enable_x64", None)
    if x64 is None:  # jax < 0.6
        from jax.experimental import enable_x64 as x64  # pyright: ignore[reportAttributeAccessIssue]
    with x64(True), jax.ensure_compile_time_eval():
        zero = jnp.zeros(n, jnp.float64)
        interp = solver_cls.interpolation_cls(t0=0.0, t1=1.0, y0=zero, y1=zero, k=jnp.eye(n, dtype=jnp.float64))
        return np.asarray(interp.evaluate(0.5), dtype=np.float64)


def _tableau(c, a_lower, b_sol, b_error=None) -> diffrax.ButcherTableau:
    b_sol = np.asarray(b_sol, dtype=np.float64)
    return diffrax.ButcherTableau(
        c=np.asarray(c, dtype=np.float64),
        a_lower=tuple(np.asarray(r, dtype=np.float64) for r in a_lower),
        b_sol=b_sol,
        b_error=np.zeros_like(b_sol) if b_error is None else np.asarray(b_error, dtype=np.float64),
    )


class LieEuler(AbstractLieSolver):
    """First-order Lie-Euler: ``q <- q Exp(h w_b)``, ``z <- z + h f(t, y)``. Fixed steps.

    Explicit and first order: ``|q| = 1`` is kept, but the energy is not. Euler's equations
    stepped explicitly gain energy, roughly like ``exp(c h t) - 1``; measured for
    ``I = diag(1, 2, 3)``, ``w0 = (0.1, 1, 0.1)``: +11 % at ``h = 0.01, t = 100``, +312 % at
    ``t = 1000``, +1 % at ``h = 1e-3, t = 100``, and NaN (overflow) after about 10^6 steps
    of ``h = 0.01``. Keep ``h t`` below about 0.1 for a 1 % energy error; for long runs use
    :class:`RKMK4`, :class:`RKMK45` or the splittings (see ``docs/integrators.md``).
    """

    def order(self, terms):
        return 1

    def lie_step(self, tangent, t0, t1, h, y0, flags, solver_state, made_jump):
        if isinstance(tangent, _ModelRates) and tangent.rigid_body is not None:
            tab = _SoATableau(struct_of_arrays.LIE_EULER, False)
            return _rigid_body_step(tab, tangent.rigid_body, tangent, t0, t1, h, y0, None, made_jump)
        # written out: diffrax's ButcherTableau needs two stages or more
        lay = _LAYOUTS[self.layout]
        leaves, tree = jax.tree.flatten(y0)
        g = tangent(t0, y0)
        y1 = []
        for f, x, gi in zip(flags, leaves, g):
            if f:
                q = lay.split(x)
                w = lay.rate(gi, not isinstance(tangent, _ModelRates))
                y1.append(lay.advance(q, tuple(h * wi for wi in w))[1])
            else:
                y1.append(x + h * gi)
        return jax.tree.unflatten(tree, y1), None, None, None


class RKMK4(AbstractRKMK):
    """RKMK with the classical fourth-order Runge-Kutta tableau. Fixed steps, 4 stages."""

    tableau: ClassVar = _tableau([0.5, 0.5, 1.0], [[0.5], [0.0, 0.5], [0.0, 0.0, 1.0]], [1 / 6, 1 / 3, 1 / 3, 1 / 6])

    def order(self, terms):
        return 4


class RKMK45(AbstractRKMK, diffrax.AbstractAdaptiveSolver):
    """RKMK on diffrax's Dormand-Prince 5(4) tableau: order 5, embedded order-4 error estimate
    (in the local coordinates) for ``PIDController``. 7 stages, 6 vector-field calls a step (FSAL)."""

    tableau: ClassVar = diffrax.Dopri5.tableau
    mid_weights: ClassVar = np.array(
        [
            0.10013431883002388,
            0.0,
            0.39183217941842585,
            -0.029824601765948172,
            0.05893268337240795,
            -0.04497888809104361,
            0.023904308236133986,
        ]
    )

    def order(self, terms):
        return 5


class RKMKTsit5(AbstractRKMK, diffrax.AbstractAdaptiveSolver):
    """RKMK on diffrax's Tsitouras 5(4) tableau: order 5 at the cost of :class:`RKMK45` (6 calls a
    step, FSAL), with a smaller principal error constant (Tsitouras 2011); see the
    work-precision figures in ``docs/integrators.md``."""

    tableau: ClassVar = diffrax.Tsit5.tableau
    mid_weights: ClassVar = np.array(
        [
            0.10741235230096871,
            0.01135625,
            0.39560903056045305,
            -0.34475214352593553,
            1.3161853649581645,
            -1.0170608542936508,
            0.031249999999999993,
        ]
    )

    def order(self, terms):
        return 5


class RKMK8(AbstractRKMK, diffrax.AbstractAdaptiveSolver):
    """RKMK on diffrax's Dormand-Prince 8(7) tableau: order 8 (``dexp^-1`` to ``ad^7``),
    14 stages, 13 calls a step (FSAL); for tolerances near float64 rounding."""

    tableau: ClassVar = diffrax.Dopri8.tableau
    mid_weights: ClassVar = np.array(
        [
            0.04103130360739393,
            0.0,
            0.0,
            0.0,
            0.0,
            0.05100562801991382,
            0.2388930677412202,
            0.3096870143996103,
            -0.2172325471755352,
            0.07833405679331928,
            -0.0018614369715579948,
            0.007072844202678841,
            0.00690847373200576,
            -0.013838404349047373,
        ]
    )

    def order(self, terms):
        return 8
