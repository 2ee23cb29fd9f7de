"""Kinematic and dynamic kernels: the Euler-parameter rate relations between ``q``, ``qdot``,
``qddot`` and the angular velocity and acceleration in either frame, frame changes of vectors,
Euler's equations solved for the acceleration, and the kinetic energy, on arrays already
validated and broadcast.

The public functions of :mod:`jaxquat.mechanics.kinematics` and :mod:`jaxquat.mechanics.dynamics` check their
arguments and call these; the vector fields, solvers and filters call them directly. Plain
names: the module is private to the package (see :mod:`jaxquat._quaternion`).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
from jax import Array

from . import _arrays, _fusion, _quaternion


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


def vec_rate_parts(qc: list[Array], dc: list[Array], frame: str) -> list[Array]:
    """:func:`vec_rate` on components (lists of four arrays)."""
    conj = [qc[0], -qc[1], -qc[2], -qc[3]]
    prod = _quaternion.multiply_dense(conj, dc) if frame == "body" else _quaternion.multiply_dense(dc, conj)
    return prod[1:]


def dot_parts(a: list[Array], b: list[Array]) -> Array:
    """``a . b`` for vectors given as components."""
    total = a[0] * b[0]
    for x, y in zip(a[1:], b[1:]):
        total = total + x * y
    return total


# The public kinematics functions (jaxquat.mechanics.kinematics) run the three kernels below:
# the same formulas written on components (jaxquat._arrays.components in, one loop and a stack
# out). On rows, the broadcasts of the per-row scalars (|q|^2, q.qdot) had cotangents summed over
# the minor axis, which XLA on CPU handed to YNNPACK fusions, and the slices' pads were fused
# with the backward computation once per component. 10^5 rows, one core, least of 7, the gradient
# of sum(f * W) in q (body frame), rows -> components: omega_from_qdot float32 2.1 -> 0.15 ms,
# float64 3.5 -> 0.34 ms; qddot_from_alpha 10.2 -> 0.34 ms and 33-39 -> 0.77 ms; alpha_from_qddot
# 3.2 -> 0.37 ms and 6.3-7.2 -> 1.1 ms; the values 0.09-0.48 ms either way. The vector fields keep
# the row kernels above. The dynamics (jaxquat.mechanics.dynamics, the gravity-gradient torque)
# are written on components end to end with the *_parts functions below: swapping in only the
# stacked kernels made their float64 gradients in qdot slower (euler_parameter_acceleration 3.8
# -> 19.7 ms, norm_constraint_multiplier 0.9 -> 14.6 ms), since each consumer took the stacked
# result's components again.


def omega_parts(qc: list[Array], dc: list[Array], frame: str) -> list[Array]:
    """:func:`omega_from_qdot` on components (four arrays each in, three out)."""
    scale = 2.0 / dot_parts(qc, qc)
    return [scale * r for r in vec_rate_parts(qc, dc, frame)]


def qddot_parts(qc: list[Array], dc: list[Array], ac: list[Array], frame: str) -> list[Array]:
    """:func:`qddot_from_alpha` on components."""
    nsq = dot_parts(qc, qc)
    rate = vec_rate_parts(qc, dc, frame)
    # s = q* qddot (body) or qddot q* (space), solved from the alpha relation;
    # its scalar part q.qddot = -|qdot|^2 keeps d^2|q|^2/dt^2 = 0.
    half, lift = 0.5 * nsq, 2.0 * dot_parts(qc, dc) / nsq
    s = [-dot_parts(dc, dc)] + [half * a + lift * r for a, r in zip(ac, rate)]
    out = _quaternion.multiply_dense(qc, s) if frame == "body" else _quaternion.multiply_dense(s, qc)
    inv = 1.0 / nsq
    return [x * inv for x in out]


def alpha_parts(qc: list[Array], dc: list[Array], ddc: list[Array], frame: str) -> list[Array]:
    """:func:`alpha_from_qddot` on components."""
    nsq = dot_parts(qc, qc)
    acc = vec_rate_parts(qc, ddc, frame)
    rate = vec_rate_parts(qc, dc, frame)
    a_scale, r_scale = 2.0 / nsq, 4.0 * dot_parts(qc, dc) / (nsq * nsq)
    return [a_scale * a - r_scale * r for a, r in zip(acc, rate)]


def omega_from_qdot_by_components(q: Array, qdot: Array, frame: str) -> Array:
    """:func:`omega_from_qdot` on components."""
    qc, dc = _arrays.components(q), _arrays.components(qdot)
    return _arrays.stack_in_one_loop(omega_parts(qc, dc, frame))


def qddot_from_alpha_by_components(q: Array, qdot: Array, alpha: Array, frame: str) -> Array:
    """:func:`qddot_from_alpha` on components."""
    qc, dc, ac = _arrays.components(q), _arrays.components(qdot), _arrays.components(alpha)
    return _arrays.stack_in_one_loop(qddot_parts(qc, dc, ac, frame))


def alpha_from_qddot_by_components(q: Array, qdot: Array, qddot: Array, frame: str) -> Array:
    """:func:`alpha_from_qddot` on components."""
    qc, dc, ddc = _arrays.components(q), _arrays.components(qdot), _arrays.components(qddot)
    return _arrays.stack_in_one_loop(alpha_parts(qc, dc, ddc, frame))


# Euler's equations and frame changes on components, for the dynamics written on components
# (jaxquat.mechanics.dynamics, jaxquat.mechanics.torques).


def rotate_parts(qc: list[Array], v: list[Array], inverse: bool) -> list[Array]:
    """``v`` rotated by ``q`` (or by ``q*``: into the body frame), on components (unit ``q``)."""
    return _quaternion.rotate_components([qc[0], -qc[1], -qc[2], -qc[3]] if inverse else qc, v)


def to_body_parts(qc: list[Array], v: list[Array], frame: str) -> list[Array]:
    """:func:`to_body` on components."""
    return v if frame == "body" else rotate_parts(qc, v, inverse=True)


def from_body_parts(qc: list[Array], v: list[Array], frame: str) -> list[Array]:
    """A body-frame vector expressed in ``frame``, on components (unit ``q``)."""
    return v if frame == "body" else rotate_parts(qc, v, inverse=False)


def cross_parts(a: Sequence[Array], b: Sequence[Array]) -> list[Array]:
    """``a x b`` on components."""
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def times_pure_parts(p: list[Array], u: list[Array]) -> list[Array]:
    """The product ``p (0, u)`` on components: ``(-p_v . u, p_0 u + p_v x u)``."""
    return [-dot_parts(p[1:], u)] + [p[0] * x + c for x, c in zip(u, cross_parts(p[1:], u))]


def matrix_entries(m: Array) -> list[list[Array]]:
    """The nine entries of ``m`` ``(..., 3, 3)`` as components (their cotangents gathered by
    :func:`jaxquat._arrays.components`, not pads of slices: ``angular_acceleration``'s gradient in
    the inertia at 10^5, one core, float32 / float64, 2.6 / 2.9 ms, against 7.5 / 8.3 ms sliced),
    the cotangents computed in one loop (:func:`jaxquat._fusion.one_loop_backward`; session 53,
    the same gradient measured 3.9 -> 2.7 ms and 5.1 -> 4.4 ms, ``euler_parameter_acceleration``'s
    in the inertia 4.0 -> 2.7 and 5.3 -> 4.3 ms)."""
    flat = list(_fusion.one_loop_backward(_arrays.components(m.reshape(m.shape[:-2] + (9,)))))
    return [flat[3 * i : 3 * i + 3] for i in range(3)]


def matvec_parts(m: list[list[Array]], v: list[Array]) -> list[Array]:
    """``m v`` for ``m``'s entries and ``v`` given as components."""
    return [r[0] * v[0] + r[1] * v[1] + r[2] * v[2] for r in m]


def euler_body_parts(entries: list[list[Array]], w: list[Array], torque: list[Array] | None) -> list[Array]:
    """:func:`euler_body` on components: ``I^-1 (M - w x I w)`` for the inertia's entries (symmetric),
    ``torque`` None for torque-free motion."""
    gyro = cross_parts(w, matvec_parts(entries, w))
    rhs = [-g for g in gyro] if torque is None else [x - g for x, g in zip(torque, gyro)]
    upper = [entries[i][j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))]
    return _arrays.symmetric_solve_parts(upper, rhs)


def euler_torque_parts(entries: list[list[Array]], w: list[Array], alpha: list[Array]) -> list[Array]:
    """Euler's equations solved for the torque, ``I a + w x I w``, on components (body frame)."""
    gyro = cross_parts(w, matvec_parts(entries, w))
    return [x + g for x, g in zip(matvec_parts(entries, alpha), gyro)]


def to_body(q: Array, v: Array, frame: str) -> Array:
    """Resolve a vector given in ``frame`` in the body frame (unit ``q``)."""
    return v if frame == "body" else _quaternion.rotate(_quaternion.conjugate(q), v)


def euler_body(inertia: Array, w: Array, torque: Array) -> Array:
    """Euler's equations solved for the acceleration, ``I^-1 (M - w x I w)``, all body frame."""
    return _arrays.symmetric_solve(inertia, torque - jnp.cross(w, _arrays.matvec(inertia, w)))


def kinetic_energy(w: Array, h: Array) -> Array:
    """``1/2 w . h`` from the body rate and the body angular momentum ``h = I w``."""
    return 0.5 * _arrays.dot(w, h)
