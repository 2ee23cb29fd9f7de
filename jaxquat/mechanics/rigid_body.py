"""The rigid body as ODEs for diffrax: vector fields on ``(q, w_body)`` and ``(q, qdot)``, and invariants.

``RigidBody(inertia, torque)`` is an ``equinox.Module`` (a pytree: the inertia
is differentiable through every diffrax adjoint) whose call
``rb(t, y, args)`` is the vector field of ``y = (q, w_b)``::

    dq/dt  = 1/2 q (0, w_b)                   ([S] eq. (16), [T] eq. (47b))
    dw_b/dt = I^-1 (M_b(t, q, w_b, args) - w_b x I w_b)   (Euler, [S] eq. (19))

so ``diffrax.ODETerm(RigidBody(I, torque))`` drops into ``diffeqsolve`` with any
diffrax solver, or with the Lie-group solvers of :mod:`jaxquat.integration.lie_solvers` and
:mod:`jaxquat.integration.splitting`.
``EulerParameterBody`` is the same body on ``y = (q, qdot)`` with Chou's
closed-form ``qddot`` (:func:`jaxquat.euler_parameter_acceleration`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _quaternion, _rates
from .inertia import validated
from .torques import as_body_torque

__all__ = ["RigidBody", "EulerParameterBody", "invariants"]


class _Body(eqx.Module):
    """Shared fields: body inertia (validated), body torque function, the frame it was written in."""

    inertia: Array
    torque: Callable | None = None
    torque_frame: str = eqx.field(static=True, default="body")

    def __init__(self, inertia: Any, torque: Callable | None = None, torque_frame: str = "body"):
        self.inertia = validated(inertia)
        self.torque_frame = _checks.frame(torque_frame, "torque_frame")
        self.torque = None if torque is None else as_body_torque(torque, torque_frame)

    def body_torque(self, t, q: Array, w: Array, args) -> Array:
        if self.torque is None:
            return jnp.zeros_like(w)
        return self.torque(t, q, w, args)

    def angular_acceleration(self, t, q: Array, w: Array, args) -> Array:
        """Euler's equations ``I^-1 (M_b - w x I w)`` (body frame)."""
        return _rates.euler_body(self.inertia, w, self.body_torque(t, q, w, args))


class RigidBody(_Body):
    """Vector field of a rigid body on ``y = (q, w_b)``: ``rb(t, y, args) -> (dq/dt, dw_b/dt)``.

    ``inertia``: body-frame tensor ``(3, 3)``. ``torque``: ``None`` (torque-free)
    or a function ``fn(t, q, w, args)`` written in ``torque_frame`` (see
    :func:`jaxquat.as_body_torque`); ``args`` of ``diffeqsolve`` are passed to it.
    """

    def __call__(self, t, y, args):
        w, w_dot = self.body_rate_field(t, y, args)
        return _rates.qdot_from_omega(y[0], w, "body"), w_dot

    def body_rate_field(self, t, y, args):
        """The same field in the Lie-algebra form the Lie solvers step in, ``(w_b, dw_b/dt)``:
        the body rate in place of ``dq/dt = q (0, w_b)/2`` ([S] eq. (16)), body frame, and Euler's
        equations ``dw_b/dt = I^-1 (M_b - w_b x I w_b)`` ([S] eq. (19)); the Lie solvers read the
        rate from here instead of from ``dq/dt``."""
        q, w = y
        return w, self.angular_acceleration(t, q, w, args)

    def euler_equations(self) -> tuple[Array, Callable | None]:
        """``(inertia, torque)``: this field's ``dw_b/dt`` is Euler's equations ([S] eq. (19)) with
        this body-frame tensor and body torque ``fn(t, q, w_b, args)`` (None: torque-free) on the
        state's own shapes. The Lie solvers (``LieEuler``, the RKMK family) read them to step the
        body one array per component (:mod:`jaxquat.integration.struct_of_arrays`) instead of
        running this field on rows: the same method, each stage one loop over the batch."""
        return self.inertia, self.torque


class EulerParameterBody(_Body):
    """Vector field on ``y = (q, qdot)``: ``(qdot, qddot)`` from Chou's closed form [C] eq. (75).

    The same body as :class:`RigidBody`; the norm constraint is kept to second
    order by the ``-|qdot|^2 q`` term (a generic integrator still lets ``|q|`` drift).
    """

    def __call__(self, t, y, args):
        q, qdot = y
        w = _rates.omega_from_qdot(q, qdot, "body")
        return qdot, _rates.qddot_from_alpha(q, qdot, self.angular_acceleration(t, q, w, args), "body")


def invariants(
    q: Float[ArrayLike, "*#batch 4"], omega: Float[ArrayLike, "*#batch 3"], inertia: Float[ArrayLike, "*#batch 3 3"]
) -> dict[str, Array]:
    """Quantities to monitor a run: ``energy`` (1/2 w.Iw, as :func:`jaxquat.kinetic_energy`),
    ``momentum_body`` (I w, as :func:`jaxquat.angular_momentum`), ``momentum_space`` (A I w, with
    ``q`` normalised) and ``norm_error`` (``|q| - 1``). ``omega`` is body-frame.

    For torque-free motion the energy and ``momentum_space`` are conserved
    (``|momentum_body|`` too); ``norm_error`` is 0 for an exact unit-norm integrator.
    """
    inertia = validated(inertia)
    q, omega, inertia = _checks.arguments(
        q=(q, "quaternion"), omega=(omega, "vector"), inertia=(inertia, "inertia"), shared=("inertia",)
    )
    return _arrays.compiled_rows(_invariants, (1, 1, 2), q, omega, inertia)


def _invariants(q: Array, omega: Array, inertia: Array) -> dict[str, Array]:
    norm = jnp.sqrt(jnp.sum(q * q, -1))
    h = _arrays.matvec(inertia, omega)  # body frame, as omega
    return {
        "energy": _rates.kinetic_energy(omega, h),
        "momentum_body": h,
        "momentum_space": _quaternion.rotate(q / norm[..., None], h),
        "norm_error": norm - 1,
    }
