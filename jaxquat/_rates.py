"""Kinematic and dynamic kernels: the Euler-parameter rate relations between ``q``, ``qdot``,
``qddot`` and the angular velocity and acceleration in either frame, frame changes of vectors,
Euler's equations solved for the acceleration, and the kinetic energy, on arrays already
validated and broadcast.

The public functions of :mod:`jaxquat.mechanics.kinematics` and :mod:`jaxquat.mechanics.dynamics` check their
arguments and call these; the vector fields, solvers and filters call them directly. Plain
names: the module is private to the package (see :mod:`jaxquat._quaternion`).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array

from . import _arrays, _quaternion


def vec_rate(q: Array, qdot: Array, frame: str) -> Array:
    """``vec(q* qdot)`` (body) or ``vec(qdot q*)`` (space): half the angular velocity times ``|q|^2``."""
    prod = (
        _quaternion.multiply(_quaternion.conjugate(q), qdot)
        if frame == "body"
        else _quaternion.multiply(qdot, _quaternion.conjugate(q))
    )
    return prod[..., 1:]


def qdot_from_omega(q: Array, omega: Array, frame: str) -> Array:
    """``qdot = q (0, w) / 2`` (body) or ``(0, w) q / 2`` (space)."""
    w = _quaternion.pure(omega)
    return 0.5 * (_quaternion.multiply(q, w) if frame == "body" else _quaternion.multiply(w, q))


def omega_from_qdot(q: Array, qdot: Array, frame: str) -> Array:
    """``w = 2 vec(q* qdot) / |q|^2`` (body) or ``2 vec(qdot q*) / |q|^2`` (space)."""
    return 2.0 * vec_rate(q, qdot, frame) / _arrays.dot(q, q)[..., None]


def qddot_from_alpha(q: Array, qdot: Array, alpha: Array, frame: str) -> Array:
    """The ``qddot`` whose angular acceleration is ``alpha``, keeping ``d^2 |q|^2 / dt^2 = 0``."""
    nsq = _arrays.dot(q, q)[..., None]
    rate = vec_rate(q, qdot, frame)
    # s = q* qddot (body) or qddot q* (space), solved from the alpha relation;
    # its scalar part q.qddot = -|qdot|^2 keeps d^2|q|^2/dt^2 = 0.
    s_vec = 0.5 * nsq * alpha + 2.0 * _arrays.dot(q, qdot)[..., None] * rate / nsq
    s = _quaternion.scalar_vector(-_arrays.dot(qdot, qdot), s_vec)
    return (_quaternion.multiply(q, s) if frame == "body" else _quaternion.multiply(s, q)) / nsq


def alpha_from_qddot(q: Array, qdot: Array, qddot: Array, frame: str) -> Array:
    """The angular acceleration of ``(q, qdot, qddot)``: the derivative of :func:`omega_from_qdot`."""
    nsq = _arrays.dot(q, q)[..., None]
    acc = vec_rate(q, qddot, frame)
    rate = vec_rate(q, qdot, frame)
    return 2.0 * acc / nsq - 4.0 * _arrays.dot(q, qdot)[..., None] * rate / (nsq * nsq)


def to_body(q: Array, v: Array, frame: str) -> Array:
    """Resolve a vector given in ``frame`` in the body frame (unit ``q``)."""
    return v if frame == "body" else _quaternion.rotate(_quaternion.conjugate(q), v)


def from_body(q: Array, v: Array, frame: str) -> Array:
    """Express a body-frame vector in ``frame`` (unit ``q``)."""
    return v if frame == "body" else _quaternion.rotate(q, v)


def euler_body(inertia: Array, w: Array, torque: Array) -> Array:
    """Euler's equations solved for the acceleration, ``I^-1 (M - w x I w)``, all body frame."""
    return _arrays.symmetric_solve(inertia, torque - jnp.cross(w, _arrays.matvec(inertia, w)))


def kinetic_energy(w: Array, h: Array) -> Array:
    """``1/2 w . h`` from the body rate and the body angular momentum ``h = I w``."""
    return 0.5 * _arrays.dot(w, h)
