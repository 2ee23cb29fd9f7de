"""Rigid-body rotational dynamics: Euler's equations and the Euler-parameter equations of motion.

Conventions. ``inertia`` is always the body-frame tensor (``(..., 3, 3)``, full
symmetric; see :mod:`jaxquat.mechanics.inertia`). Angular velocities, accelerations,
torques and momenta are resolved in the frame named by ``frame`` (``"body"``
or ``"space"``, as in :mod:`jaxquat.mechanics.kinematics`), and results are returned in
that same frame. ``q`` maps body to space and is assumed unit (Euler
parameters); functions that take ``qdot`` assume ``q.qdot = 0``.

Two formulations of the same motion, shown equal in ``tests/test_dynamics.py``:

* Newton-Euler on ``(q, w)``: Euler's equations ``I dw/dt = M - w x I w``
  ([S] eq. (19), [C] eqs. (62), (66)) plus ``qdot = 1/2 q (0, w)``.
* The Euler-parameter equations on ``(q, qdot)``: Chou's closed form for
  ``qddot`` ([C] eqs. (74)-(78)) and Schwab's augmented system with a
  Lagrange multiplier for ``|q| = 1`` ([S] eqs. (20)-(25)).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _fusion, _quaternion, _rates
from .inertia import validated

__all__ = [
    "angular_momentum",
    "kinetic_energy",
    "angular_acceleration",
    "inverse_dynamics",
    "euler_parameter_acceleration",
    "euler_parameter_torque",
    "euler_parameter_mass_matrix",
    "euler_parameter_augmented_system",
    "norm_constraint_multiplier",
    "generalized_force",
    "torque_from_generalized_force",
]


def _checked_with_torque(q, rate_name: str, rate, torque, inertia) -> list[Array | None]:
    """The argument checks of a function of an attitude, its rate (``omega`` a vector or ``qdot`` a
    quaternion), an optional torque (``None`` passed on) and an inertia, in that order (an inertia
    without batch axes is not broadcast to the batch: :func:`jaxquat._checks.broadcast_batch`)."""
    kind = "vector" if rate_name == "omega" else "quaternion"
    return _checks.optional_arguments(
        **{"q": (q, "quaternion"), rate_name: (rate, kind)},
        torque=(torque, "vector?"),
        inertia=(validated(inertia), "inertia"),
        shared=("inertia",),
    )


def angular_momentum(
    q: Float[ArrayLike, "*#batch 4"],
    omega: Float[ArrayLike, "*#batch 3"],
    inertia: Float[ArrayLike, "*#batch 3 3"],
    frame: str = "body",
) -> Float[Array, "*batch 3"]:
    """Angular momentum about the centre of mass, resolved in ``frame``.

    ``H_b = I w_b``; ``H_s = I0 w_s = A I A^T w_s`` ([C] eqs. (60)-(61):
    ``H0 = 2 I0 E_space qdot``, the vector part of ``2 Ihat0 (qdot q*)``).
    ``q`` is only used when ``frame="space"``.
    """
    frame = _checks.frame(frame)
    q, omega, inertia = _checks.arguments(
        q=(q, "quaternion"), omega=(omega, "vector"), inertia=(validated(inertia), "inertia"), shared=("inertia",)
    )
    return _arrays.compiled_rows(_angular_momentum, (1, 1, 2), q, omega, inertia, frame=frame)


def _angular_momentum(q: Array, omega: Array, inertia: Array, frame: str) -> Array:
    qc, w = _arrays.components(q), _arrays.components(omega)
    h = _rates.matvec_parts(_rates.matrix_entries(inertia), _rates.to_body_parts(qc, w, frame))
    return _arrays.stack_in_one_loop(_rates.from_body_parts(qc, h, frame))


# The dynamics are written on components (jaxquat._arrays.components in, one loop and a stack
# out; the kernels are jaxquat._rates' *_parts functions). On rows each stage stacked a vector
# that the next one sliced again (the frame change, I w, the cross product, the solve, the rate
# relations), and reverse mode turned the slices into pads that XLA on CPU fused with the
# backward computation once per component. 10^5 rows, one core, least of 7, the gradient of
# sum(f * W) (tests/test_contract.py's registry, benchmarks/gradient_sweep.py), rows ->
# components, float32 / float64 (session 52 for the first two, session 53 for the others):
# angular_momentum in q (space) 3.2 -> 0.22 / 5.7 -> 0.5 ms; angular_acceleration in q (space)
# 4.7 -> 0.36 / 29.8 -> 0.9 ms, in the inertia 5.2 -> 2.6 / 6.4 -> 2.9 ms;
# euler_parameter_acceleration in q (body) 25.7 -> 1.6 / 60.4 -> 3.2 ms, in qdot (space) 3.2 ->
# 1.0 / 11.5 -> 2.0 ms, in the inertia 8.4 -> 2.7 / 16.5 -> 4.3 ms; euler_parameter_torque 15.5
# -> 1.4 / 30.7 -> 3.0 ms; inverse_dynamics 0.81 -> 0.33 / 1.56 -> 0.57 ms;
# norm_constraint_multiplier 1.25 -> 0.53 / 2.42 -> 1.00 ms.


def kinetic_energy(
    q: Float[ArrayLike, "*#batch 4"],
    omega: Float[ArrayLike, "*#batch 3"],
    inertia: Float[ArrayLike, "*#batch 3 3"],
    frame: str = "body",
) -> Float[Array, "*batch"]:
    """Rotational kinetic energy ``T = 1/2 w_b . I w_b = 1/2 w_s . I0 w_s``.

    In Euler parameters ``T = 1/2 qdot^T (4 Q diag(0, I) Q^T) qdot`` ([S] eq.
    (23)'s mass matrix), and ``2 T`` is Schwab's multiplier ([S] eq. (24)).
    """
    frame = _checks.frame(frame)
    q, omega, inertia = _checks.arguments(
        q=(q, "quaternion"), omega=(omega, "vector"), inertia=(validated(inertia), "inertia"), shared=("inertia",)
    )
    return _arrays.compiled_rows(_kinetic_energy, (1, 1, 2), q, omega, inertia, frame=frame)


def _kinetic_energy(q: Array, omega: Array, inertia: Array, frame: str) -> Array:
    w = _rates.to_body(q, omega, frame)
    return _rates.kinetic_energy(w, _arrays.matvec(inertia, w))


def angular_acceleration(
    q: Float[ArrayLike, "*#batch 4"],
    omega: Float[ArrayLike, "*#batch 3"],
    inertia: Float[ArrayLike, "*#batch 3 3"],
    torque: Float[ArrayLike, "*#batch 3"] | None = None,
    frame: str = "body",
) -> Float[Array, "*batch 3"]:
    """Euler's equations solved for the angular acceleration.

    Body: ``dw_b/dt = I^-1 (M_b - w_b x I w_b)`` ([S] eq. (19), [C] eq. (66)).
    Space: ``dw_s/dt = I0^-1 (M_s - w_s x I0 w_s)`` with ``I0 = A I A^T`` ([C]
    eq. (62), where ``dI0/dt`` of eq. (C4) supplies the gyroscopic term); equal to
    ``A`` times the body result. ``torque=None`` is torque-free motion.
    """
    frame = _checks.frame(frame)
    checked = _checked_with_torque(q, "omega", omega, torque, inertia)
    return _arrays.compiled_rows(_angular_acceleration, (1, 1, 1, 2), *checked, frame=frame)


def _angular_acceleration(q: Array, omega: Array, torque: Array | None, inertia: Array, frame: str) -> Array:
    qc, w = _arrays.components(q), _arrays.components(omega)
    m = _body_torque_parts(qc, torque, frame)
    a = _rates.euler_body_parts(_rates.matrix_entries(inertia), _rates.to_body_parts(qc, w, frame), m)
    return _arrays.stack_in_one_loop(_rates.from_body_parts(qc, a, frame))


def _body_torque_parts(qc: list[Array], torque: Array | None, frame: str) -> list[Array] | None:
    """The body torque's components (None: torque-free) from a torque resolved in ``frame``."""
    return None if torque is None else _rates.to_body_parts(qc, _arrays.components(torque), frame)


def inverse_dynamics(
    q: Float[ArrayLike, "*#batch 4"],
    omega: Float[ArrayLike, "*#batch 3"],
    alpha: Float[ArrayLike, "*#batch 3"],
    inertia: Float[ArrayLike, "*#batch 3 3"],
    frame: str = "body",
) -> Float[Array, "*batch 3"]:
    """Torque that produces a given motion: ``M = I a + w x I w`` in the body frame ([S] eq. (19),
    [C] eq. (66)); ``M_s = I0 a_s + w_s x I0 w_s`` in space ([C] eq. (62))."""
    frame = _checks.frame(frame)
    q, omega, alpha, inertia = _checks.arguments(
        q=(q, "quaternion"),
        omega=(omega, "vector"),
        alpha=(alpha, "vector"),
        inertia=(validated(inertia), "inertia"),
        shared=("inertia",),
    )
    return _arrays.compiled_rows(_inverse_dynamics, (1, 1, 1, 2), q, omega, alpha, inertia, frame=frame)


def _inverse_dynamics(q: Array, omega: Array, alpha: Array, inertia: Array, frame: str) -> Array:
    qc = _arrays.components(q)
    w = _rates.to_body_parts(qc, _arrays.components(omega), frame)
    a = _rates.to_body_parts(qc, _arrays.components(alpha), frame)
    tau = _rates.euler_torque_parts(_rates.matrix_entries(inertia), w, a)
    return _arrays.stack_in_one_loop(_rates.from_body_parts(qc, tau, frame))


def euler_parameter_acceleration(
    q: Float[ArrayLike, "*#batch 4"],
    qdot: Float[ArrayLike, "*#batch 4"],
    inertia: Float[ArrayLike, "*#batch 3 3"],
    torque: Float[ArrayLike, "*#batch 3"] | None = None,
    frame: str = "body",
) -> Float[Array, "*batch 4"]:
    """``qddot`` from the Euler-parameter equations of motion (Chou's closed form).

    Body ([C] eq. (75), second row)::

        qddot = 1/2 E^T I^-1 M_b - |qdot|^2 q - 2 E^T I^-1 (E dE^T/dt) I E qdot

    with ``E`` the body :func:`jaxquat.rate_matrix` (Chou's E-minus). Space
    (first row): the same with Chou's E-plus, ``I0 = A I A^T``, ``M_s``, and
    ``(dE/dt) E^T`` in place of ``E dE^T/dt`` (see ``docs/seed-errata.md`` for the
    dots the transcription lost). Evaluated as
    ``qddot = 1/2 q (0, a_b) - |qdot|^2 q`` with ``w_b = 2 vec(q* qdot)`` and
    ``a_b = I^-1 (M_b - w_b x I w_b)``, the same expression in quaternion
    products. Equal to Schwab's augmented system ([S] eq. (23)) and to
    Newton-Euler. ``torque`` is resolved in ``frame`` (``None``: torque-free).
    The result satisfies ``q.qddot = -|qdot|^2``, the twice-differentiated norm
    constraint.
    """
    frame = _checks.frame(frame)
    checked = _checked_with_torque(q, "qdot", qdot, torque, inertia)
    return _arrays.compiled_rows(_euler_parameter_acceleration, (1, 1, 1, 2), *checked, frame=frame)


def _euler_parameter_acceleration(q: Array, qdot: Array, torque: Array | None, inertia: Array, frame: str) -> Array:
    qc, dc = _arrays.components(q), _arrays.components(qdot)
    m = _body_torque_parts(qc, torque, frame)
    a = _rates.euler_body_parts(_rates.matrix_entries(inertia), _rates.omega_parts(qc, dc, "body"), m)
    return _arrays.stack_in_one_loop(_rates.qddot_parts(qc, dc, a, "body"))


def euler_parameter_torque(
    q: Float[ArrayLike, "*#batch 4"],
    qdot: Float[ArrayLike, "*#batch 4"],
    qddot: Float[ArrayLike, "*#batch 4"],
    inertia: Float[ArrayLike, "*#batch 3 3"],
    frame: str = "body",
) -> Float[Array, "*batch 3"]:
    """Torque from Euler parameters and their derivatives (Euler's equations in Euler parameters).

    Space ([C] eq. (65)): ``M_s = 2 I0 E qddot + 4 (dE/dt) E^T I0 E qdot`` (E-plus).
    Body ([C] eq. (69)): ``M_b = 2 I E qddot + 4 E (dE/dt)^T I E qdot`` (E-minus).
    Evaluated as :func:`inverse_dynamics` of ``w = 2 vec(q* qdot)``,
    ``a = 2 vec(q* qddot)`` (the inverse of :func:`euler_parameter_acceleration`).
    """
    frame = _checks.frame(frame)
    q, qdot, qddot, inertia = _checks.arguments(
        q=(q, "quaternion"),
        qdot=(qdot, "quaternion"),
        qddot=(qddot, "quaternion"),
        inertia=(validated(inertia), "inertia"),
        shared=("inertia",),
    )
    return _arrays.compiled_rows(_euler_parameter_torque, (1, 1, 1, 2), q, qdot, qddot, inertia, frame=frame)


def _euler_parameter_torque(q: Array, qdot: Array, qddot: Array, inertia: Array, frame: str) -> Array:
    qc, dc, ddc = _arrays.components(q), _arrays.components(qdot), _arrays.components(qddot)
    w, a = _rates.omega_parts(qc, dc, "body"), _rates.alpha_parts(qc, dc, ddc, "body")
    tau = _rates.euler_torque_parts(_rates.matrix_entries(inertia), w, a)
    return _arrays.stack_in_one_loop(_rates.from_body_parts(qc, tau, frame))


def _quat_inertia_product(q: Array, inertia: Array) -> Array:
    """``Q diag(0, I) Q^T`` as ``(..., 4, 4)``, with ``Q`` the left-multiplication matrix of ``q``."""
    # Q diag(0, I) Q^T = E^T I E with E = lower three rows of Q^T (the body rate matrix), written
    # out entry by entry, the ten of the upper triangle computed in one loop (jaxquat._fusion) and
    # mirrored. As two batched 3x4 / 3x3 matrix products (until session 52), for 10^5 bodies (one
    # core, least of 7; the gradient of sum(M * W) in q): euler_parameter_mass_matrix float32
    # 2.5 -> 0.73 ms, gradient 82 -> 0.23 ms; float64 3.1 -> 1.8 ms and 27.5 -> 0.65 ms. Stacked
    # without the loop, float64 took 6.3 ms (XLA evaluated the shared products once per entry).
    w, x, y, z = _arrays.components(q)
    e = [[-x, w, z, -y], [-y, -z, w, x], [-z, y, -x, w]]
    m = [[inertia[..., a, b] for b in range(3)] for a in range(3)]
    ie = [[m[a][0] * e[0][j] + m[a][1] * e[1][j] + m[a][2] * e[2][j] for j in range(4)] for a in range(3)]
    keys = [(i, j) for i in range(4) for j in range(i, 4)]
    entries = [e[0][i] * ie[0][j] + e[1][i] * ie[1][j] + e[2][i] * ie[2][j] for i, j in keys]
    upper = dict(zip(keys, _fusion.one_loop(jnp.broadcast_arrays(*entries))))
    rows = [[upper[(min(i, j), max(i, j))] for j in range(4)] for i in range(4)]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def euler_parameter_mass_matrix(
    q: Float[ArrayLike, "*#batch 4"], inertia: Float[ArrayLike, "*#batch 3 3"]
) -> Float[Array, "*batch 4 4"]:
    """Schwab's 4x4 mass matrix ``4 Q diag(0, I) Q^T`` ([S] eq. (23), upper-left block).

    ``1/2 qdot^T M qdot`` is the kinetic energy. ``M`` is singular (``M q = 0``:
    rescaling ``q`` is not a motion); the norm constraint row of
    :func:`euler_parameter_augmented_system` makes the system solvable.
    """
    q, inertia = _checks.arguments(q=(q, "quaternion"), inertia=(validated(inertia), "inertia"), shared=("inertia",))
    return _arrays.compiled_rows(_mass_matrix, (1, 2), q, inertia)


def _mass_matrix(q: Array, inertia: Array) -> Array:
    return 4.0 * _quat_inertia_product(q, inertia)


def generalized_force(
    q: Float[ArrayLike, "*#batch 4"], torque: Float[ArrayLike, "*#batch 3"], frame: str = "body"
) -> Float[Array, "*batch 4"]:
    """Torque -> generalised force dual to the Euler parameters, [S] eq. (25).

    ``f = 2 Q (0, M_b) = 2 q (0, M_b)`` (body) or ``f = 2 Q-bar (0, M_s) = 2 (0, M_s) q``
    (space). Virtual power: ``f . dq = M_b . dw_b`` for every ``dq``, where
    ``dw_b = 2 vec(q* dq)`` (unit ``q``).
    """
    frame = _checks.frame(frame)
    q, torque = _checks.arguments(q=(q, "quaternion"), torque=(torque, "vector"), shared=True)
    return _arrays.compiled_rows_broadcast(_generalized_force, (1, 1), q, torque, frame=frame)


def _generalized_force(q: Array, torque: Array, frame: str) -> Array:
    m = _quaternion.pure(torque)
    return 2.0 * (_quaternion.multiply(q, m) if frame == "body" else _quaternion.multiply(m, q))


def torque_from_generalized_force(
    q: Float[ArrayLike, "*#batch 4"], force: Float[ArrayLike, "*#batch 4"], frame: str = "body"
) -> Float[Array, "*batch 3"]:
    """Generalised Euler-parameter force -> torque: ``M_b = 1/2 vec(q* f)``, ``M_s = 1/2 vec(f q*)``.

    The inverse of :func:`generalized_force` (unit ``q``). The component of ``f``
    along ``q`` (``q.f``, the force on the norm constraint) does no work on a
    rotation and is discarded.
    """
    frame = _checks.frame(frame)
    q, force = _checks.arguments(q=(q, "quaternion"), force=(force, "quaternion"), shared=True)
    return _arrays.compiled_rows_broadcast(_torque_from_generalized_force, (1, 1), q, force, frame=frame)


def _torque_from_generalized_force(q: Array, force: Array, frame: str) -> Array:
    return 0.5 * _rates.vec_rate(q, force, frame)


def euler_parameter_augmented_system(
    q: Float[ArrayLike, "*#batch 4"],
    qdot: Float[ArrayLike, "*#batch 4"],
    inertia: Float[ArrayLike, "*#batch 3 3"],
    torque: Float[ArrayLike, "*#batch 3"] | None = None,
    frame: str = "body",
) -> tuple[Float[Array, "*batch 5 5"], Float[Array, "*batch 5"]]:
    """Schwab's augmented Euler-parameter equations of motion, [S] eq. (23): ``(lhs, rhs)``.

    ::

        [ 4 Q J Q^T   2 q ] [ qddot  ]   [ f + 8 Qdot J Qdot^T q ]
        [ 2 q^T       0   ] [ lambda ] = [ -2 qdot.qdot          ]

    with ``J = diag(0, I)``, ``Q`` = :func:`jaxquat.left_matrix` of ``q``,
    ``f`` = :func:`generalized_force` of ``torque`` (resolved in ``frame``). The
    last row is the norm constraint differentiated twice; the transcription
    prints no right-hand side for it (``docs/seed-errata.md``).
    ``jnp.linalg.solve(lhs, rhs)`` gives ``(qddot, lambda)`` with ``lambda =``
    :func:`norm_constraint_multiplier` ([S] eq. (24)) and ``qddot`` equal to
    :func:`euler_parameter_acceleration`.
    """
    frame = _checks.frame(frame)
    checked = _checked_with_torque(q, "qdot", qdot, torque, inertia)
    return _arrays.compiled_rows(_augmented_system, (1, 1, 1, 2), *checked, frame=frame)


def _augmented_system(q: Array, qdot: Array, torque: Array | None, inertia: Array, frame: str) -> tuple[Array, Array]:
    mass = 4.0 * _quat_inertia_product(q, inertia)
    # The right-hand side on components: Qdot J Qdot^T q = qdot (0, I E(qdot) q) with E(qdot) q =
    # vec(qdot* q), and f = 2 q (0, M_b). As a batched 4x4 product of Qdot diag(0, I) Qdot^T with
    # q (until session 53) the gradient in q at 10^5 took 3.2-5.3 ms (float32, one core), hidden
    # in benchmarks/gradient_sweep.py until then by XLA folding the constant qdot's matrix while
    # compiling (4.7 s).
    qc, dc = _arrays.components(q), _arrays.components(qdot)
    entries = _rates.matrix_entries(inertia)
    gyro = _rates.times_pure_parts(dc, _rates.matvec_parts(entries, _rates.vec_rate_parts(dc, qc, "body")))
    m = _body_torque_parts(qc, torque, frame)
    force = [0.0] * 4 if m is None else _rates.times_pure_parts(qc, m)
    top = [2.0 * f + 8.0 * g for f, g in zip(force, gyro)]
    rhs = _arrays.stack_in_one_loop(top + [-2.0 * _rates.dot_parts(dc, dc)])
    col = 2.0 * q[..., :, None]
    upper = jnp.concatenate([mass, col], axis=-1)
    lower = jnp.concatenate([2.0 * q, jnp.zeros_like(q[..., :1])], axis=-1)[..., None, :]
    return jnp.concatenate([upper, lower], axis=-2), rhs


def norm_constraint_multiplier(
    q: Float[ArrayLike, "*#batch 4"], qdot: Float[ArrayLike, "*#batch 4"], inertia: Float[ArrayLike, "*#batch 3 3"]
) -> Float[Array, "*batch"]:
    """Schwab's Lagrange multiplier of the norm constraint, [S] eq. (24).

    ``lambda = 4 q^T Qdot diag(0, I) Qdot^T q = w_b . I w_b``: twice the
    rotational kinetic energy.
    """
    q, qdot, inertia = _checks.arguments(
        q=(q, "quaternion"), qdot=(qdot, "quaternion"), inertia=(validated(inertia), "inertia"), shared=("inertia",)
    )
    return _arrays.compiled_rows(_norm_constraint_multiplier, (1, 1, 2), q, qdot, inertia)


def _norm_constraint_multiplier(q: Array, qdot: Array, inertia: Array) -> Array:
    w = _rates.omega_parts(_arrays.components(q), _arrays.components(qdot), "body")
    return _rates.dot_parts(w, _rates.matvec_parts(_rates.matrix_entries(inertia), w))
