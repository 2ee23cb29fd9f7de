"""Rotational kinematics in Euler parameters: angular velocity and acceleration <-> quaternion rates.

Frames. ``frame="body"`` means a vector resolved in the body-fixed frame
(Chou's superscript ``i``, Schwab's primed ``w'``, Tasora's ``w_l``);
``frame="space"`` means resolved in the inertial frame (Chou's superscript ``0``,
Schwab's unprimed ``w``, Tasora's ``w_o``). ``q`` maps body to space:
``v_space = rotate(q, v_body)``.

The four binding relations, with ``(0, w)`` the pure quaternion of ``w``::

    body:   qdot = 1/2 q (0, w_b)        w_b = 2 vec(q* qdot)
    space:  qdot = 1/2 (0, w_s) q        w_s = 2 vec(qdot q*)
    body:   qddot = 1/2 q (0, a_b) - |qdot|^2 q       a_b = 2 vec(q* qddot)
    space:  qddot = 1/2 (0, a_s) q - |qdot|^2 q       a_s = 2 vec(qddot q*)

(the forms shown are for ``|q| = 1``; the functions below keep them exact for any
non-zero ``q``, see each docstring). The ``-|qdot|^2 q`` term is the
twice-differentiated norm constraint ``q.qddot + |qdot|^2 = 0`` ([S] eq. (17)).

Source documents: [C] Chou (1992), [S] Schwab (2002), [T] Tasora (2016);
``docs/equations.md`` maps every equation to its function and test.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _rates, _rotation

__all__ = [
    "rate_matrix",
    "qdot_from_omega",
    "omega_from_qdot",
    "qddot_from_alpha",
    "alpha_from_qddot",
    "matrix_rate",
    "matrix_acceleration",
    "point_velocity",
    "point_acceleration",
]


def rate_matrix(q: Float[ArrayLike, "*batch 4"], frame: str = "body") -> Float[Array, "*batch 3 4"]:
    """The 3x4 matrix ``E`` with ``w = 2 E qdot`` and ``qdot = 1/2 E^T w`` (unit ``q``).

    ``frame="body"``: ``E = [-v, q0 I - v~]`` (Chou's E-minus [C] eq. (25),
    Tasora's ``[F(q*)+]`` [T] eqs. (42a), (48b), the lower three rows of
    Schwab's ``Q^T`` [S] eq. (15)). ``frame="space"``: ``E = [-v, q0 I + v~]``
    (Chou's E-plus [C] eq. (26), Tasora's ``[F(q*)-]`` [T] eqs. (43a), (48a),
    Schwab's ``Q-bar^T`` [S] eq. (13)). Here ``q = (q0, v)``.

    For unit ``q``: ``E E^T = I``, ``E^T E = I - q q^T``, ``E q = 0``
    ([C] (A4)-(A5), [T] (38a)-(38b)); ``to_matrix(q) = E_space E_body^T``
    ([C] eq. (34), [T] eq. (29a)); ``hat(w_b) = 2 E_body dE_body^T/dt`` and
    ``hat(w_s) = 2 (dE_space/dt) E_space^T`` ([C] eqs. (45), (51)).
    """
    frame = _checks.frame(frame)
    return _arrays.compiled_rows(_rate_matrix, (1,), _checks.quat(q), frame=frame)


def _rate_matrix(q: Array, frame: str) -> Array:
    w, v = q[..., 0], q[..., 1:]
    skew = _arrays.hat(v)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=q.dtype), skew.shape)
    block = w[..., None, None] * eye + (skew if frame == "space" else -skew)
    return jnp.concatenate([-v[..., :, None], block], axis=-1)


def qdot_from_omega(
    q: Float[ArrayLike, "*#batch 4"], omega: Float[ArrayLike, "*#batch 3"], frame: str = "body"
) -> Float[Array, "*batch 4"]:
    """Quaternion rate from angular velocity.

    ``frame="body"``: ``qdot = 1/2 q (0, w_b)`` ([S] eq. (16), [T] eq. (47b),
    [C] eqs. (70)-(71) second rows). ``frame="space"``: ``qdot = 1/2 (0, w_s) q``
    ([S] eq. (14), [T] eq. (46), [C] eqs. (70)-(71) first rows).

    Any ``q``: the rate is orthogonal to ``q`` (``|q|`` stays constant), and
    ``omega_from_qdot(q, qdot_from_omega(q, w)) == w`` for every non-zero ``q``.
    """
    frame = _checks.frame(frame)
    q, omega = _checks.arguments(q=(q, "quaternion"), omega=(omega, "vector"), shared=True)
    return _arrays.compiled_rows_broadcast(_rates.qdot_from_omega, (1, 1), q, omega, frame=frame)


def omega_from_qdot(
    q: Float[ArrayLike, "*#batch 4"], qdot: Float[ArrayLike, "*#batch 4"], frame: str = "body"
) -> Float[Array, "*batch 3"]:
    """Angular velocity from the quaternion rate.

    ``frame="body"``: ``(0, w_b) = 2 q* qdot`` ([S] eq. (15), [T] eq. (47a),
    [C] eqs. (49)-(50)). ``frame="space"``: ``(0, w_s) = 2 qdot q*`` ([S] eq.
    (13), [T] eq. (45), [C] eqs. (43)-(44)).

    Exact for any non-zero ``q``: the result is divided by ``|q|^2`` and the
    scalar part (``2 q.qdot``, the norm rate) is dropped, so it is the angular
    velocity of the rotation ``q/|q|`` even when an integrator has let ``|q|``
    drift. For unit ``q`` it is exactly the printed formula.
    """
    frame = _checks.frame(frame)
    q, qdot = _checks.arguments(q=(q, "quaternion"), qdot=(qdot, "quaternion"), shared=True)
    return _arrays.compiled_rows_broadcast(_rates.omega_from_qdot_by_components, (1, 1), q, qdot, frame=frame)


def qddot_from_alpha(
    q: Float[ArrayLike, "*#batch 4"],
    qdot: Float[ArrayLike, "*#batch 4"],
    alpha: Float[ArrayLike, "*#batch 3"],
    frame: str = "body",
) -> Float[Array, "*batch 4"]:
    """Quaternion second derivative from angular acceleration.

    For unit ``q`` with ``q.qdot = 0``:
    ``frame="body"``: ``qddot = 1/2 q (0, a_b) - |qdot|^2 q`` (inverse of [S] eq.
    (18), [C] eq. (73) second row; equal to [T] eq. (49b)
    ``1/2 qdot (0, w_b) + 1/2 q (0, a_b)``);
    ``frame="space"``: ``qddot = 1/2 (0, a_s) q - |qdot|^2 q`` (inverse of [S] eq.
    (17), [C] eq. (73) first row; equal to [T] eq. (49a)).

    General non-zero ``q``: returns ``q s / |q|^2`` (body) or ``s q / |q|^2``
    (space) with ``s = (-|qdot|^2, |q|^2 a / 2 + 2 (q.qdot) vec(q* qdot) / |q|^2)``
    (``qdot q*`` in space), so that ``alpha_from_qddot`` of the result returns
    ``alpha`` exactly and ``d^2|q|^2/dt^2 = 0`` (the norm rate is not accelerated).
    """
    frame = _checks.frame(frame)
    q, qdot, alpha = _checks.arguments(
        q=(q, "quaternion"), qdot=(qdot, "quaternion"), alpha=(alpha, "vector"), shared=True
    )
    return _arrays.compiled_rows_broadcast(
        _rates.qddot_from_alpha_by_components, (1, 1, 1), q, qdot, alpha, frame=frame
    )


def alpha_from_qddot(
    q: Float[ArrayLike, "*#batch 4"],
    qdot: Float[ArrayLike, "*#batch 4"],
    qddot: Float[ArrayLike, "*#batch 4"],
    frame: str = "body",
) -> Float[Array, "*batch 3"]:
    """Angular acceleration from the quaternion's first and second derivatives.

    For unit ``q``: ``(0, a_b) = 2 q* qddot + 2 qdot* qdot - 2 (|qdot|^2, 0)``,
    i.e. ``a_b = 2 vec(q* qddot)`` ([S] eq. (18), [T] eq. (50b), [C] eqs.
    (57)-(58)); ``a_s = 2 vec(qddot q*)`` ([S] eq. (17), [T] eq. (50a), [C] eqs.
    (55)-(56)). The scalar part of ``2 q* qddot`` is ``-2|qdot|^2``: that is the
    ``|qdot|^2`` term of [S] (17)-(18).

    General non-zero ``q``: the exact time derivative of :func:`omega_from_qdot`,
    ``a = 2 vec(q* qddot)/|q|^2 - 4 (q.qdot) vec(q* qdot)/|q|^4`` (body; ``qddot q*``
    and ``qdot q*`` in space), the angular acceleration of ``q/|q|``.
    """
    frame = _checks.frame(frame)
    q, qdot, qddot = _checks.arguments(
        q=(q, "quaternion"), qdot=(qdot, "quaternion"), qddot=(qddot, "quaternion"), shared=True
    )
    return _arrays.compiled_rows_broadcast(
        _rates.alpha_from_qddot_by_components, (1, 1, 1), q, qdot, qddot, frame=frame
    )


def matrix_rate(
    q: Float[ArrayLike, "*#batch 4"], omega: Float[ArrayLike, "*#batch 3"], frame: str = "body"
) -> Float[Array, "*batch 3 3"]:
    """Time derivative of the rotation matrix (Poisson's equation).

    ``dA/dt = A hat(w_b)`` (``frame="body"``, [T] eq. (37c), [C] eq. (52)) or
    ``dA/dt = hat(w_s) A`` (``frame="space"``, [T] eq. (37d), [C] eq. (46)),
    with ``A = to_matrix(q)``. Assumes ``|q| = 1`` (as :func:`jaxquat.to_matrix`).
    """
    frame = _checks.frame(frame)
    q, omega = _checks.arguments(q=(q, "quaternion"), omega=(omega, "vector"), shared=True)
    return _arrays.compiled_rows_broadcast(_matrix_rate, (1, 1), q, omega, frame=frame)


def _matrix_rate(q: Array, omega: Array, frame: str) -> Array:
    a = _rotation.to_matrix(q)
    return _arrays.matmul(a, _arrays.hat(omega)) if frame == "body" else _arrays.matmul(_arrays.hat(omega), a)


def matrix_acceleration(
    q: Float[ArrayLike, "*#batch 4"],
    omega: Float[ArrayLike, "*#batch 3"],
    alpha: Float[ArrayLike, "*#batch 3"],
    frame: str = "body",
) -> Float[Array, "*batch 3 3"]:
    """Second time derivative of the rotation matrix.

    ``d2A/dt2 = A (hat(w_b) hat(w_b) + hat(a_b))`` (body; [T] Table 2, whose
    printed ``[A][w~][w~] + [A][a~]`` this is) or
    ``(hat(w_s) hat(w_s) + hat(a_s)) A`` (space). Assumes ``|q| = 1``.
    """
    frame = _checks.frame(frame)
    q, omega, alpha = _checks.arguments(
        q=(q, "quaternion"), omega=(omega, "vector"), alpha=(alpha, "vector"), shared=True
    )
    return _arrays.compiled_rows_broadcast(_matrix_acceleration, (1, 1, 1), q, omega, alpha, frame=frame)


def _matrix_acceleration(q: Array, omega: Array, alpha: Array, frame: str) -> Array:
    a = _rotation.to_matrix(q)
    w = _arrays.hat(omega)
    k = _arrays.matmul(w, w) + _arrays.hat(alpha)
    return _arrays.matmul(a, k) if frame == "body" else _arrays.matmul(k, a)


def point_velocity(
    q: Float[ArrayLike, "*#batch 4"],
    omega: Float[ArrayLike, "*#batch 3"],
    r: Float[ArrayLike, "*#batch 3"],
    r_dot: Float[ArrayLike, "*#batch 3"] | None = None,
    frame: str = "body",
) -> Float[Array, "*batch 3"]:
    """Space-frame velocity of a point with body coordinates ``r`` (relative velocity ``r_dot``).

    ``v = A (w_b x r + r_dot) = w_s x (A r) + A r_dot``: the vector form of [T]
    eq. (33) ``(0, v) = qdot (0,r) q* + q (0,r) qdot* + q (0,r_dot) q*``
    and of [C] eq. (41). ``omega`` is resolved in ``frame``; ``r`` and ``r_dot``
    in the body frame (``r_dot`` defaults to 0, a body-fixed point). Assumes ``|q| = 1``.
    """
    frame = _checks.frame(frame)
    checked = _checks.optional_arguments(
        q=(q, "quaternion"), omega=(omega, "vector"), r=(r, "vector"), r_dot=(r_dot, "vector?")
    )
    return _arrays.compiled_rows(_point_velocity, (1, 1, 1, 1), *checked, frame=frame)


def _point_velocity(q: Array, omega: Array, r: Array, r_dot: Array | None, frame: str) -> Array:
    qc, rc = _arrays.components(q), _arrays.components(r)
    v = _rates.cross_parts(_rates.to_body_parts(qc, _arrays.components(omega), frame), rc)
    v = v if r_dot is None else [x + y for x, y in zip(v, _arrays.components(r_dot))]
    return _arrays.stack_in_one_loop(_rates.rotate_parts(qc, v, inverse=False))


# point_velocity and point_acceleration are written on components, as the dynamics
# (jaxquat.mechanics.dynamics says why). Rows -> components, 10^5 points, one core, least of 7,
# value / gradient of sum(f * W) in q: point_velocity (space frame) float32 0.96 / 3.5 -> 0.40 /
# 0.37 ms, float64 1.9 / 7.0 -> 0.78 / 0.69 ms; point_acceleration (body frame) float32 1.7 / 0.32
# -> 0.45 / 0.30 ms, float64 3.4 / 0.56 -> 0.86 / 0.55 ms.


def point_acceleration(
    q: Float[ArrayLike, "*#batch 4"],
    omega: Float[ArrayLike, "*#batch 3"],
    alpha: Float[ArrayLike, "*#batch 3"],
    r: Float[ArrayLike, "*#batch 3"],
    r_dot: Float[ArrayLike, "*#batch 3"] | None = None,
    r_ddot: Float[ArrayLike, "*#batch 3"] | None = None,
    frame: str = "body",
) -> Float[Array, "*batch 3"]:
    """Space-frame acceleration of a point with body coordinates ``r``.

    ``a = A (a_b x r + w_b x (w_b x r) + 2 w_b x r_dot + r_ddot)``: the vector
    form of [T] eq. (53) (corrected, see ``docs/seed-errata.md``)
    ``qddot p q* + q p qddot* + 2 qdot p qdot* + 2 qdot p' q* + 2 q p' qdot* + q p'' q*``.
    ``omega``, ``alpha`` are resolved in ``frame`` (``a_s = A a_b``);
    ``r``, ``r_dot``, ``r_ddot`` in the body frame (the last two default to 0).
    Assumes ``|q| = 1``.
    """
    frame = _checks.frame(frame)
    checked = _checks.optional_arguments(
        q=(q, "quaternion"),
        omega=(omega, "vector"),
        alpha=(alpha, "vector"),
        r=(r, "vector"),
        r_dot=(r_dot, "vector?"),
        r_ddot=(r_ddot, "vector?"),
    )
    return _arrays.compiled_rows(_point_acceleration, (1, 1, 1, 1, 1, 1), *checked, frame=frame)


def _point_acceleration(
    q: Array, omega: Array, alpha: Array, r: Array, r_dot: Array | None, r_ddot: Array | None, frame: str
) -> Array:
    qc, rc = _arrays.components(q), _arrays.components(r)
    w = _rates.to_body_parts(qc, _arrays.components(omega), frame)
    a = _rates.to_body_parts(qc, _arrays.components(alpha), frame)
    cross = _rates.cross_parts
    acc = [x + y for x, y in zip(cross(a, rc), cross(w, cross(w, rc)))]
    if r_dot is not None:
        acc = [x + 2.0 * y for x, y in zip(acc, cross(w, _arrays.components(r_dot)))]
    if r_ddot is not None:
        acc = [x + y for x, y in zip(acc, _arrays.components(r_ddot))]
    return _arrays.stack_in_one_loop(_rates.rotate_parts(qc, acc, inverse=False))
