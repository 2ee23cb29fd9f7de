"""Lie-group calculus on S^3 / SO(3): retraction ``plus``/``minus``, the Jacobians of the exponential, the adjoint.

Tangent vectors are rotation vectors ``delta`` (``(..., 3)``, radians). With
``Exp(phi) = from_rotvec(phi) = exp((0, phi/2))``:

* body (right) perturbation: ``plus(q, d) = q Exp(d)``, ``minus(q1, q0) = Log(q0* q1)``;
* space (left) perturbation: ``plus(q, d, "space") = Exp(d) q``, ``minus(q1, q0, "space") = Log(q1 q0*)``.

``Log`` is :func:`jaxquat.to_rotvec` (the shortest rotation vector, ``|d| <= pi``),
so ``minus(plus(q, d), q) == d`` for ``|d| < pi``. The Jacobians relate a change
of the exponential coordinates to a body/space rotation:
``Exp(phi + e) ~ Exp(phi) Exp(J_r(phi) e) ~ Exp(J_l(phi) e) Exp(phi)``, so the
body angular velocity of ``Exp(phi(t))`` is ``J_r(phi) phi'`` and the space one
``J_l(phi) phi'``. ``J_l(phi) = J_r(-phi) = R(phi) J_r(phi)``.
"""

from __future__ import annotations

from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _quaternion, _rotation, _safe

__all__ = [
    "plus",
    "minus",
    "right_jacobian",
    "right_jacobian_inverse",
    "left_jacobian",
    "left_jacobian_inverse",
    "adjoint",
]


def plus(
    q: Float[ArrayLike, "*#batch 4"], delta: Float[ArrayLike, "*#batch 3"], frame: str = "body"
) -> Float[Array, "*batch 4"]:
    """Retraction: ``q Exp(delta)`` (``frame="body"``) or ``Exp(delta) q`` (``"space"``).

    ``Exp(delta) = (cos(|delta|/2), sin(|delta|/2) delta/|delta|)`` is the quaternion
    exponential of ``(0, delta/2)`` ([T] eqs. (55)-(56)); smooth at ``delta = 0``.
    Keeps ``|q|``: a unit ``q`` stays unit to rounding, with no renormalisation.
    """
    frame = _checks.frame(frame)
    q, delta = _checks.arguments(q=(q, "quaternion"), delta=(delta, "vector"), shared=True)
    return _arrays.compiled_rows_broadcast(_plus, (1, 1), q, delta, frame=frame)


def _plus(q: Array, delta: Array, frame: str) -> Array:
    e = _rotation.from_rotvec(delta)
    return _quaternion.multiply(q, e) if frame == "body" else _quaternion.multiply(e, q)


def minus(
    q1: Float[ArrayLike, "*#batch 4"], q0: Float[ArrayLike, "*#batch 4"], frame: str = "body"
) -> Float[Array, "*batch 3"]:
    """Inverse retraction: ``Log(q0* q1)`` (body) or ``Log(q1 q0*)`` (space), ``|result| <= pi``.

    The rotation vector that :func:`plus` applies to ``q0`` to reach ``q1``
    (either sign of either quaternion). Scale-invariant in ``q0`` and ``q1``.
    Not differentiable where ``q1`` is exactly 180 degrees from ``q0`` (two
    shortest answers).
    """
    frame = _checks.frame(frame)
    q1, q0 = _checks.arguments(q1=(q1, "quaternion"), q0=(q0, "quaternion"), shared=True)
    return _arrays.compiled_rows_broadcast(_minus, (1, 1), q1, q0, frame=frame)


def _minus(q1: Array, q0: Array, frame: str) -> Array:
    q1, q0 = _safe.rescaled(q1), _safe.rescaled(q0)
    rel = (
        _quaternion.multiply(_quaternion.conjugate(q0), q1)
        if frame == "body"
        else _quaternion.multiply(q1, _quaternion.conjugate(q0))
    )
    return _rotation.to_rotvec(rel)


def right_jacobian(phi: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Right Jacobian of the SO(3) exponential, ``J_r(phi)``.

    ``J_r = I - (1 - cos t)/t^2 hat(phi) + (t - sin t)/t^3 hat(phi)^2`` with
    ``t = |phi|``; the coefficients are Taylor series in ``t^2`` for ``t^2 < 0.5``,
    so every derivative is exact at ``phi = 0`` (where ``J_r = I``). Maps
    exponential-coordinate rates to body angular velocity: ``w_b = J_r(phi) phi'``.
    """
    return _arrays.compiled_rows(_rotation.right_jacobian, (1,), _checks.vec3(phi, "phi"))


def right_jacobian_inverse(phi: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """``J_r(phi)^-1 = I + hat(phi)/2 + (1/t^2 - cot(t/2)/(2 t)) hat(phi)^2``, ``t = |phi|``.

    Written with ``cot(t/2)`` so it is finite at ``t = pi``; singular only at
    ``t = 2 pi`` (outside the range of :func:`minus`). Series in ``t^2`` near 0.
    ``phi' = J_r^-1(phi) w_b``.
    """
    return _arrays.compiled_rows(_rotation.right_jacobian_inverse, (1,), _checks.vec3(phi, "phi"))


def left_jacobian(phi: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Left Jacobian ``J_l(phi) = J_r(-phi) = I + (1 - cos t)/t^2 hat(phi) + (t - sin t)/t^3 hat(phi)^2``.

    Maps exponential-coordinate rates to space angular velocity: ``w_s = J_l(phi) phi'``.
    """
    return _arrays.compiled_rows(_left_jacobian, (1,), _checks.vec3(phi, "phi"))


def left_jacobian_inverse(phi: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """``J_l(phi)^-1 = J_r(-phi)^-1 = I - hat(phi)/2 + (1/t^2 - cot(t/2)/(2 t)) hat(phi)^2``."""
    return _arrays.compiled_rows(_left_jacobian_inverse, (1,), _checks.vec3(phi, "phi"))


def _left_jacobian(phi: Array) -> Array:
    return _rotation.right_jacobian(-phi)


def _left_jacobian_inverse(phi: Array) -> Array:
    return _rotation.right_jacobian_inverse(-phi)


def adjoint(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 3 3"]:
    """Adjoint of SO(3) at ``q``: ``q Exp(d) q* = Exp(Ad_q d)`` with ``Ad_q = to_matrix(q)``.

    Moves a body-frame tangent vector to the space frame:
    ``plus(q, d, "body") == plus(q, adjoint(q) @ d, "space")``. Assumes ``|q| = 1``.
    """
    return _arrays.compiled_rows(_rotation.to_matrix, (1,), _checks.quat(q))
