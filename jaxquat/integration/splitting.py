"""Splitting solvers for the rigid body ``(q, w_b)`` of :class:`jaxquat.RigidBody`, as diffrax solvers.

Splitting (Dullweber, Leimkuhler and McLachlan 1997; Reich; Touma-Wisdom): the
kinetic energy ``T = sum_i m_i^2 / (2 I_i)`` in principal axes (``m = I w``) is
split into three exactly solvable rotations about the body axes, composed
symmetrically ``R1(h/2) R2(h/2) R3(h) R2(h/2) R1(h/2)``; a torque enters as
half kicks ``m += h/2 M`` before and after (Strang), the second one the adjoint
(implicit) of the first so the step stays symmetric for torques that depend on
``w``; ``EulerPoinsotSplit`` replaces the five rotations by the exact
torque-free flow. Each sub-flow is an exact
rotation, so the spatial angular momentum of a torque-free body is conserved to
rounding and the energy error stays bounded (the map is symplectic). Cost per
step: 5 axis rotations (plus 2 torque evaluations when forced);
``RigidBodySplit4`` composes three of them with Yoshida's weights (order 4). The
splitting solvers need the inertia in principal axes (a diagonal tensor);
rotate the attitude to principal axes first for a full tensor.

The solvers are siblings under :class:`AbstractSplitting` (the Strang composition, the
torque kicks, Yoshida's triple jump and the invariant projection); each concrete one
names its free flow and its weights.

====================  =====  ==========================================================
solver                order  conserves (to rounding)
====================  =====  ==========================================================
RigidBodySplit        2      ``|q|``, spatial momentum when torque-free; energy error
                             bounded (symplectic)
RigidBodySplit4       4      as RigidBodySplit (Yoshida triple jump)
EulerPoinsotSplit     2      ``|q|``; exact (any step) when torque-free (momentum and
                             energy to rounding)
EulerPoinsotSplit4    4      as EulerPoinsotSplit (Yoshida triple jump)
====================  =====  ==========================================================
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array

from .. import _arrays, _quaternion, _safe, _trig
from .lie_solvers import SlerpInterpolation, leaf_flags, unit
from ..mechanics.rigid_body import RigidBody
from ..mechanics.torque_free import propagate

__all__ = ["AbstractSplitting", "RigidBodySplit", "RigidBodySplit4", "EulerPoinsotSplit", "EulerPoinsotSplit4"]

_RESULTS = diffrax.RESULTS
_CBRT2 = 2.0 ** (1.0 / 3.0)
_W1 = 1.0 / (2.0 - _CBRT2)
_YOSHIDA = (_W1, 1.0 - 2.0 * _W1, _W1)  # triple-jump weights: order 2 -> 4


class AbstractSplitting(diffrax.AbstractSolver):
    """Base of the splittings: Strang's half kick, free flow, half kick, composed with
    ``weights`` (``(1,)``: order 2; Yoshida's triple jump: order 4). A subclass gives
    ``free_flow`` (the torque-free motion over ``h`` in principal axes), ``weights``,
    ``exact_energy`` (whether the free flow keeps the energy exactly, so that its rounding is
    projected away in every dtype) and ``exact_torque_free`` (whether one step of any size
    is exact without a torque: then :func:`jaxquat.simulate` steps from one saved time to
    the next). Torque-free, each step ends on the initial ``|m|`` (``m = I w``) and, where
    ``exact_energy`` or below float64, on the initial energy (:func:`_onto_invariants`;
    float32 drift over 10^5 steps 7.7e-3 -> 2.4e-7, see ``docs/integrators.md``).

    The four splittings take the rigid body's state ``(q, w)`` and the terms of
    ``diffrax.ODETerm(RigidBody(inertia, torque))`` in principal axes (:func:`jaxquat.simulate`
    rotates a full tensor there), e.g. ``EulerPoinsotSplit4()``.

    Attributes:
        kick_iterations: fixed-point sweeps of the torque kick's implicit (adjoint) half, for a
            torque that depends on the rates; ``0`` suffices for one of ``(t, q)`` alone.
    """

    term_structure: ClassVar = diffrax.AbstractTerm
    interpolation_cls: ClassVar = SlerpInterpolation
    weights: eqx.AbstractClassVar[tuple[float, ...]]
    exact_energy: eqx.AbstractClassVar[bool]
    exact_torque_free: eqx.AbstractClassVar[bool]
    kick_iterations: int = eqx.field(static=True, default=3)

    @abc.abstractmethod
    def free_flow(self, q: Array, w: Array, moments: Array, h) -> tuple[Array, Array]:
        """Torque-free motion of ``(q, w)`` over ``h`` with principal ``moments``."""

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    def _strang(self, rb: RigidBody, t, h, q, w, args):
        """Half kick, free flow, half kick. The first kick is explicit and the second is its
        adjoint (implicit, by ``kick_iterations`` fixed-point sweeps), so the step is
        symmetric also when the torque depends on ``w`` (a damper); for torques of
        ``(t, q)`` only the first sweep is already exact and ``kick_iterations=0`` saves
        the extra torque evaluations."""
        moments = jnp.diagonal(rb.inertia, axis1=-2, axis2=-1)
        if rb.torque is not None:
            w = w + 0.5 * h * rb.body_torque(t, q, w, args) / moments
        q, w = self.free_flow(q, w, moments, h)
        if rb.torque is not None:
            w_free = w

            def sweep(_, w_new):
                return w_free + 0.5 * h * rb.body_torque(t + h, q, w_new, args) / moments

            w = jax.lax.fori_loop(0, self.kick_iterations + 1, sweep, w_free)
        return q, w

    def init(self, terms, t0, t1, y0, args):
        """Torque-free, the solver state is the initial invariants ``(|m|^2, 2 E)`` (``m = I w``),
        onto which every step projects (see :func:`_onto_invariants`); with a torque, none."""
        leaf_flags(None, y0, type(self).__name__)
        rb, _ = self._body(terms)
        if rb.torque is not None:
            return None
        return _invariants(jnp.diagonal(rb.inertia, axis1=-2, axis2=-1), y0[1])

    def _body(self, terms) -> tuple[RigidBody, Any]:
        """The user's RigidBody and the time direction of diffrax's wrappers (``-1`` when it solves
        backwards in time: it then flips the time variable, and the torque needs the real time)."""
        inner, direction = terms, 1
        while not hasattr(inner, "vector_field") and hasattr(inner, "term"):
            direction = direction * getattr(inner, "direction", 1)
            inner = inner.term  # diffrax wraps the user's term (WrapTerm)
        rb = getattr(inner, "vector_field", None)
        if not isinstance(rb, RigidBody):
            raise TypeError(
                f"{type(self).__name__} needs diffrax.ODETerm(jaxquat.RigidBody(...)), got {type(rb).__name__}"
            )
        return rb, direction

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        rb, direction = self._body(terms)
        h = terms.contr(t0, t1)  # in real time: negative backwards
        t0 = direction * t0
        q, w = y0
        weights = jnp.asarray(self.weights, w.dtype)
        offsets = jnp.concatenate([jnp.zeros(1, w.dtype), jnp.cumsum(weights)[:-1]])

        def sub(carry, wt):
            qq, ww = carry
            weight, offset = wt
            return self._strang(rb, t0 + offset * h, weight * h, qq, ww, args), None

        (q1, w1), _ = jax.lax.scan(sub, (q, w), (weights, offsets))
        q1 = unit(q1)  # as the RKMK solvers: float32 rounding of |q| must not walk over 1e5 steps
        if solver_state is not None:
            # Below float64, rounding drift (5e-4 after 10^5 float32 steps) dwarfs the splitting's
            # bounded O(h^2) energy error (7e-7 there), so the energy is restored too.
            energy = bool(self.exact_energy or jnp.finfo(w1.dtype).eps > 1e-10)
            w1 = _onto_invariants(jnp.diagonal(rb.inertia, axis1=-2, axis2=-1), w1, solver_state, energy)
        # A run-time check (under jit the inertia's values are unknown at trace time).
        off_diagonal = jnp.any(
            rb.inertia * jnp.broadcast_to(1 - jnp.eye(3, dtype=rb.inertia.dtype), rb.inertia.shape) != 0
        )
        q1 = eqx.error_if(
            q1,
            off_diagonal,
            f"{type(self).__name__} needs the inertia in principal axes (a diagonal tensor): use "
            "jaxquat.principal_axes, or jaxquat.simulate, which rotates to principal axes itself",
        )
        y1 = (q1, w1)
        return y1, None, dict(y0=y0, y1=y1), solver_state, _RESULTS.successful


class RigidBodySplit(AbstractSplitting):
    """Symmetric splitting for ``RigidBody`` terms (principal axes): order 2, fixed steps.
    Free flow: ``R1(h/2) R2(h/2) R3(h) R2(h/2) R1(h/2)``, five exact axis rotations. It keeps
    ``|m|`` exactly but the energy only within its bounded O(h^2) error, so in float64 only
    ``|m|`` is restored (projecting the energy would cost the exact spatial momentum)."""

    weights: ClassVar[tuple[float, ...]] = (1.0,)
    exact_energy: ClassVar[bool] = False
    exact_torque_free: ClassVar[bool] = False

    def order(self, terms):
        return 2

    def free_flow(self, q, w, moments, h):
        return _axis_splitting(q, w, moments, h)


class RigidBodySplit4(AbstractSplitting):
    """Yoshida's fourth-order triple jump of :class:`RigidBodySplit`: weights ``(w1, w0, w1)``,
    ``w1 = 1/(2 - 2^(1/3))``, ``w0 = 1 - 2 w1``. Fixed steps; 3 Strang steps per step."""

    weights: ClassVar[tuple[float, ...]] = _YOSHIDA
    exact_energy: ClassVar[bool] = False
    exact_torque_free: ClassVar[bool] = False

    def order(self, terms):
        return 4

    def free_flow(self, q, w, moments, h):
        return _axis_splitting(q, w, moments, h)


class EulerPoinsotSplit(AbstractSplitting):
    """Torque kicks around the exact torque-free flow (:func:`jaxquat.euler_poinsot`).

    ``m += h/2 M``, exact Euler-Poinsot motion for ``h``, ``m += h/2 M`` (Strang):
    order 2 when a torque acts, and *exact for any step* when none does (one step
    may span the whole run). Conserves ``|q|`` and, torque-free, the spatial
    momentum and the energy to rounding: each step ends on the initial ``|m|`` and energy
    (:func:`_onto_invariants`), so rounding does not accumulate. Cost per step: one closed-form
    evaluation (AGM, Landen and Carlson loops, about 20 vector-field costs) plus
    2 torque evaluations. Needs principal axes, as :class:`RigidBodySplit`.
    """

    weights: ClassVar[tuple[float, ...]] = (1.0,)
    exact_energy: ClassVar[bool] = True
    exact_torque_free: ClassVar[bool] = True

    def order(self, terms):
        return 2

    def free_flow(self, q, w, moments, h):
        return propagate(q, w, moments, jnp.broadcast_to(h, q.shape[:-1]).astype(q.dtype))


class EulerPoinsotSplit4(AbstractSplitting):
    """Yoshida's triple jump of :class:`EulerPoinsotSplit`: order 4 with torques, exact without."""

    weights: ClassVar[tuple[float, ...]] = _YOSHIDA
    exact_energy: ClassVar[bool] = True
    exact_torque_free: ClassVar[bool] = True

    def order(self, terms):
        return 4

    def free_flow(self, q, w, moments, h):
        return propagate(q, w, moments, jnp.broadcast_to(h, q.shape[:-1]).astype(q.dtype))


def _axis_rotation(q: list, m: list, inv_inertia: list, axis: int, tau) -> tuple[list, list]:
    """Exact flow of ``H_i = m_i^2 / (2 I_i)`` for time ``tau``, on components (lists of arrays):
    ``q <- q Exp(phi e_i)`` with ``phi = tau m_i / I_i`` about body axis ``i``, and the body
    momentum turned by ``-phi`` about ``e_i`` (``dm/dt = m x (phi' e_i)``).

    One ``sincos`` of ``phi/2`` gives both: ``Exp(phi e_i) = (c, s e_i)``, whose product with
    ``q`` takes two terms per component (its zero components left out by
    :func:`jaxquat._quaternion.multiply_components`), and ``sin phi = 2 s c``, ``cos phi =
    c^2 - s^2``."""
    phi = tau * m[axis] * inv_inertia[axis]
    s, c = _trig.sincos(0.5 * phi)
    rotation: list = [c, None, None, None]
    rotation[1 + axis] = s
    q = _quaternion.multiply_components(q, rotation)
    j, k = (axis + 1) % 3, (axis + 2) % 3
    sin, cos = 2.0 * s * c, c * c - s * s
    m = list(m)
    m[j], m[k] = cos * m[j] + sin * m[k], cos * m[k] - sin * m[j]
    return q, m


def _axis_splitting(q, w, moments, h):
    """Torque-free flow for ``h``: ``R1(h/2) R2(h/2) R3(h) R2(h/2) R1(h/2)``, on components
    (:func:`jaxquat._arrays.components`) from the rows ``q`` ``(..., 4)`` and ``w`` ``(..., 3)``.

    Why components and one half-angle ``sincos`` per rotation: before session 89 each rotation
    took ``from_rotvec`` of ``(0, .., phi, .., 0)`` (a norm, both of its branches and a Hamilton
    product with three zero components), a second ``sincos`` of ``phi``, and updated the rows of
    ``m`` by ``.at[..., j].set``. ``simulate`` with ``RigidBodySplit`` (1000 torque-free bodies x
    1000 steps, one pinned core of a 2-core AMD EPYC, least of 7, two processes each,
    alternated), before -> after: the forward pass 297 -> 67 ms in float32 and 337 -> 132 ms in
    float64, the gradient of a final-attitude loss in ``w0`` 2.72-2.77 -> 0.32-0.33 s and
    3.20-3.23 -> 0.60 s (9.3x -> 4.8x and 9.5x -> 4.5x the forward pass). The float64 results
    agree to 1e-13 relative; in float32, after 1000 steps, the sum of the final quaternions is
    8.5e-4 (before) and 3.5e-4 (after) from float64's. Session 90 wrote the product with
    ``Exp(phi e_i)`` through ``multiply_components`` instead of a table of signed components of
    its own: the same terms, one ulp apart where XLA fuses a multiply-add differently, the same
    times (one pinned core of a 2-core Intel Xeon, least of 7, two processes each)."""
    inv = 1 / moments
    m = moments * w
    inv_c = _arrays.components(jnp.broadcast_to(inv, m.shape))
    q_c, m_c = _arrays.components(q), _arrays.components(m)
    for axis, frac in ((0, 0.5), (1, 0.5), (2, 1.0), (1, 0.5), (0, 0.5)):
        q_c, m_c = _axis_rotation(q_c, m_c, inv_c, axis, frac * h)
    return _arrays.assemble(*q_c), _arrays.assemble(*m_c) * inv


def _invariants(moments: Array, w: Array) -> tuple[Array, Array]:
    """``(|m|^2, 2 E)`` of the body momentum ``m = I w`` (principal axes)."""
    m = moments * w
    return _safe.norm_sq(m), _arrays.dot(m, w)


def _onto_invariants(moments: Array, w: Array, invariants, energy: bool = True) -> Array:
    """``w`` moved the least distance in ``m = I w`` onto ``|m|^2 = C``, ``m . w = 2 E``.

    Torque-free, both are invariants of the exact flow, and the splittings keep them up to
    rounding per step; but rounding does not average out: near a steady spin the step's
    rotation angle is the same every step, so is its rounding, and the invariants drift
    linearly (float32, ``h = 0.01``, ``I = (1, 2, 3)``, ``w0 = (0.05, 0.02, 1)``: 7.7e-3
    relative after 10^5 steps). Projecting onto the initial values (a projection method,
    Hairer, Lubich and Wanner, Geometric Numerical Integration, IV.4; the order is kept) leaves
    an error that does not accumulate. One Gauss-Newton step with the constraint gradients
    ``(2 m, 2 m / I)``; where they are nearly parallel (``m`` within about 2 degrees of a
    principal axis, or a spherical body) the two constraints are nearly one and only the norm
    is restored, by scaling, which then also restores the energy to ``O(angle^2)``.
    """
    c0, e0 = invariants
    m = moments * w
    n2 = _safe.norm_sq(m)
    g1, g2 = 2 * m, 2 * w  # gradients of |m|^2 and of m . w = sum m^2 / I, in m
    r1, r2 = n2 - c0, _arrays.dot(m, w) - e0
    a, b, c = _safe.norm_sq(g1), _arrays.dot(g1, g2), _safe.norm_sq(g2)
    det = a * c - b * b
    general = (det > 1e-3 * a * c) & energy
    det = jnp.where(general, det, 1.0)
    x1 = (c * r1 - b * r2) / det  # (J J^T)^-1 r
    x2 = (a * r2 - b * r1) / det
    m_gn = m - x1[..., None] * g1 - x2[..., None] * g2
    moving = n2 > 0  # at rest nothing moves (and the square root stays away from 0)
    scale = jnp.sqrt(jnp.where(moving, c0 / jnp.where(moving, n2, 1.0), 1.0))
    return jnp.where(general[..., None], m_gn, m * scale[..., None]) / moments
