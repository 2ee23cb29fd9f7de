"""Euler angles: all 24 conventions, spelled as scipy spells them.

Lower case (``"xyz"``) is *extrinsic*: rotate about the fixed x axis by
``angles[0]``, then the fixed y axis, then the fixed z axis, so ``R = Rz Ry Rx``.
Upper case (``"XYZ"``) is *intrinsic*: about x, then the new Y, then the new Z,
so ``R = RX RY RZ``. Angles in radians.

Extraction follows Bernardes & Viollet, "Quaternion to Euler angles conversion:
A direct, general and computationally efficient method", PLoS ONE 17(11), 2022:
every angle comes from ``atan2``/``hypot`` of linear combinations of the
quaternion, never from ``arcsin``, so it keeps full precision next to gimbal lock
in float32 as well as float64.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _derivatives, _quaternion, _safe, _trig

__all__ = ["from_euler", "to_euler"]

_AXIS = {"x": 0, "y": 1, "z": 2}


def _elementary(axis: int, s: Array, c: Array) -> list[Array | None]:
    """The components of ``(cos(t/2), sin(t/2) e_axis)``; ``None`` for the two that are zero."""
    comps: list[Array | None] = [c, None, None, None]
    comps[1 + axis] = s
    return comps


def from_euler(angles: Float[ArrayLike, "*batch 3"], seq: str) -> Float[Array, "*batch 4"]:
    """Unit quaternion of three successive elementary rotations.

    Extrinsic ``"abc"``: ``q = q_c(angles[2]) q_b(angles[1]) q_a(angles[0])``;
    intrinsic ``"ABC"``: ``q = q_A(angles[0]) q_B(angles[1]) q_C(angles[2])``,
    with ``q_x(t) = (cos(t/2), sin(t/2), 0, 0)`` etc. ([T] eq. (31) and the
    composition rule [T] eq. (24)). Matches ``scipy``'s ``Rotation.from_euler``
    up to the sign of ``q``. Smooth in the angles everywhere.
    """
    seq = _checks.euler_seq(seq)
    return _arrays.compiled_rows(_from_euler, (1,), _checks.vec3(angles, "angles"), seq=seq)


def _from_euler(angles: Array, seq: str) -> Array:
    axes = [_AXIS[c] for c in seq.lower()]
    # In components (one split, three sincos, the product written out without its zero terms,
    # one assembly): at 10^6 (this 2-core CPU, minimum of 7 x 3 interleaved runs, float32 /
    # float64) the value took 1.2 / 3.6 ms and the gradient of sum(f(x) * W) 1.1 / 2.6 ms,
    # against 21 / 27 and 23 / 42 ms as products of (..., 4) elementary quaternions.
    halves = [_trig.sincos(0.5 * a) for a in _arrays.components(angles)]
    q0, q1, q2 = (_elementary(axis, s, c) for axis, (s, c) in zip(axes, halves))
    q = (
        _quaternion.multiply_components(q2, _quaternion.multiply_components(q1, q0))
        if seq.islower()
        else _quaternion.multiply_components(q0, _quaternion.multiply_components(q1, q2))
    )
    zero = jnp.zeros_like(halves[0][0])
    return _arrays.assemble(*(zero if c is None else c for c in q))


def _gimbal_tolerance(dtype) -> float:
    return 10.0 * float(jnp.finfo(dtype).eps)


class _Plan(NamedTuple):
    """How a sequence reads the quaternion (Bernardes & Viollet): the extrinsic axis order
    ``(i, j, k)`` (``k`` the third axis for symmetric sequences) and the permutation's sign."""

    extrinsic: bool
    symmetric: bool
    i: int
    j: int
    k: int
    sign: float


def _plan(seq: str) -> _Plan:
    extrinsic = seq.islower()
    i, j, k = (_AXIS[c] for c in (seq.lower() if extrinsic else seq.lower()[::-1]))
    symmetric = i == k
    if symmetric:
        k = 3 - i - j
    return _Plan(extrinsic, symmetric, i, j, k, float((i - j) * (j - k) * (k - i) // 2))


def _abcd(plan: _Plan, w, x, y, z) -> tuple:
    """The permuted quaternion ``(a, b, c, d)`` (linear in ``q``, so also its tangent's)."""
    v = (x, y, z)
    qi, qj, qk = v[plan.i], v[plan.j], v[plan.k] * plan.sign
    if plan.symmetric:
        return w, qi, qj, qk
    return w - qj, qi + qk, qj + w, qk - qi


def _outer(plan: _Plan, half_sum, half_diff, middle, at_zero, regular) -> tuple:
    """``(first, middle, third)`` from ``atan2(b, a)``, ``atan2(d, c)`` and the middle angle; at
    gimbal lock the first angle carries the rotation and the third is 0 (also for tangents,
    which this combines the same way: the map is linear in its first three arguments)."""
    locked = jnp.where(at_zero, 2.0 * half_sum, 2.0 * half_diff * (-1.0 if plan.extrinsic else 1.0))
    outer_sign = 1.0 if plan.symmetric else plan.sign
    if plan.extrinsic:
        first = jnp.where(regular, half_sum - half_diff, locked)
        third = jnp.where(regular, half_sum + half_diff, 0.0) * outer_sign
    else:
        first = jnp.where(regular, half_sum + half_diff, locked) * outer_sign
        third = jnp.where(regular, half_sum - half_diff, 0.0)
    return first, middle, third


def _angle_parts(seq: str, w, x, y, z) -> tuple:
    plan = _plan(seq)
    a, b, c, d = _abcd(plan, w, x, y, z)
    ab, cd = a * a + b * b, c * c + d * d
    r_ab, r_cd = _safe.safe_sqrt(ab), _safe.safe_sqrt(cd)
    middle = 2.0 * _trig.atan2(r_cd, r_ab)
    half_sum = _safe.safe_atan2(b, a)
    half_diff = _safe.safe_atan2(d, c)
    # |middle| <= tol and |middle - pi| <= tol written as cd <= (tol/2)^2 ab and ab <= (tol/2)^2 cd
    # (atan2(r_cd, r_ab) <= tol/2, and tan(tol/2) = tol/2 far below a rounding), so that the
    # derivatives, which read these flags and not the middle angle, compute no atan2. At 10^6 (one
    # pinned core of a 2-core Intel Xeon, least of 21, three or four processes each, alternated),
    # float32 / float64: gradient of sum(to_euler(q, "xyz")) 5.35-5.77 -> 4.43-4.78 / 12.4-13.1 ->
    # 9.0-9.9 ms, one jvp 5.24-5.54 -> 4.01-4.29 / 10.6-11.2 -> 8.0-8.7 ms; the value 5.17-5.51 ->
    # 5.51-5.90 / 12.3-13.0 -> 12.4-12.7 ms (the same operations less three; session 75)
    tol_sq = (0.5 * _gimbal_tolerance(w.dtype)) ** 2
    at_zero = cd <= tol_sq * ab
    regular = ~(at_zero | (ab <= tol_sq * cd))
    return plan, (a, b, c, d, ab, cd, r_ab, r_cd), (half_sum, half_diff, middle, at_zero, regular)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _angles(seq: str, w, x, y, z) -> tuple:
    """``(first, middle, third)`` (the middle angle before the shift of asymmetric sequences) of
    the quaternion's components ``(w, x, y, z)``; differentiated by the closed-form JVP below."""
    plan, _, parts = _angle_parts(seq, w, x, y, z)
    return _outer(plan, *parts)


@_angles.defjvp
def _angles_jvp(seq, primals, tangents):
    """``d atan2(b, a) = (a db - b da) / (a^2 + b^2)``, likewise ``atan2(d, c)``, and
    ``d middle = 2 (r_ab / r_cd (c dc + d dd) - r_cd / r_ab (a da + b db)) / (r_ab^2 + r_cd^2)``
    (``r_ab = hypot(a, b)``, ``r_cd = hypot(c, d)``); each term 0 where its denominator is (the
    zero subgradients of ``safe_atan2`` and ``safe_sqrt``, as JAX's derivative of the value's
    expression gives). Hand-written because the gradient JAX formed through the three ``atan2``
    and two ``hypot`` took longer: measured in ``_angles``' caller."""
    plan, (a, b, c, d, ab, cd, r_ab, r_cd), (half_sum, half_diff, middle, at_zero, regular) = _angle_parts(
        seq, *primals
    )
    da, db, dc, dd = _abcd(plan, *tangents)
    both = (ab > 0) & (cd > 0)
    u = jnp.where(ab > 0, _trig.divide(1.0, jnp.where(ab > 0, ab, 1.0)), 0.0)
    v = jnp.where(cd > 0, _trig.divide(1.0, jnp.where(cd > 0, cd, 1.0)), 0.0)
    scale = _trig.divide(2.0, jnp.where(both, r_ab * r_cd * (ab + cd), 1.0))
    m_ab = jnp.where(both, scale * cd, 0.0)  # 2 r_cd / (r_ab (r_ab^2 + r_cd^2))
    m_cd = jnp.where(both, scale * ab, 0.0)  # 2 r_ab / (r_cd (r_ab^2 + r_cd^2))
    d_half_sum = u * (a * db - b * da)
    d_half_diff = v * (c * dd - d * dc)
    d_middle = m_cd * (c * dc + d * dd) - m_ab * (a * da + b * db)
    return _outer(plan, half_sum, half_diff, middle, at_zero, regular), _outer(
        plan, d_half_sum, d_half_diff, d_middle, at_zero, regular
    )


def to_euler(q: Float[ArrayLike, "*batch 4"], seq: str) -> Float[Array, "*batch 3"]:
    """Euler angles of ``q`` for the sequence ``seq`` (inverse of :func:`from_euler`).

    Ranges (as scipy): first and third angles in ``[-pi, pi]``; the middle angle
    in ``[0, pi]`` for symmetric sequences (``"zxz"``) and ``[-pi/2, pi/2]`` for
    asymmetric ones (``"xyz"``). Scale-invariant, so any non-zero ``q`` works.

    Method (Bernardes & Viollet 2022): with ``(i, j, k)`` the extrinsic axis
    order, permute the quaternion into ``(a, b, c, d)`` and take
    ``theta2 = 2 atan2(hypot(c, d), hypot(a, b))``,
    ``theta1, theta3 = atan2(b, a) -+ atan2(d, c)``.

    Gimbal lock (middle angle within ``10 eps`` of 0 or pi, for asymmetric
    sequences of +-pi/2): only the sum or difference of the outer angles is
    determined. The third angle is then set to 0 (as scipy does) and the
    first carries the whole rotation, so ``from_euler(to_euler(q))`` reproduces
    ``q``'s rotation there too, and all angles are finite. The angles are not
    differentiable at gimbal lock; the gradient returned there is that of this
    branch (third angle constant, its gradient 0; the middle angle gets the zero
    subgradient of ``hypot`` at the origin). Everywhere else gradients are exact.
    """
    seq = _checks.euler_seq(seq)
    return _arrays.compiled_rows(_to_euler, (1,), _checks.quat(q), seq=seq)


def _to_euler_kernel(q: Array, seq: str) -> Array:
    # In components (one split, the scale taken on the components, one stack) with a closed-form
    # JVP (_angles), which replaced a row form (docs/benchmarks.md). _to_euler is this kernel with
    # its value, tangent and cotangent as one-loop kernels on CPU (_derivatives; elsewhere JAX
    # differentiates it through _angles' rule). At 10^6 (one core of this 2-core EPYC, least of 9
    # runs, three processes each, float32 / float64): value 5.6 / 25-26 against 13-15 / 62-67 ms,
    # gradient of sum(f(q)) 5.3 / 15-25 against 32-33 / 67-84 ms, one jvp 4.6 / 20-22 against
    # 7.6-8.9 / 34-36 ms.
    w, x, y, z = _safe.rescaled_components(*_arrays.components(q))
    first, middle, third = _angles(seq, w, x, y, z)
    if not _plan(seq).symmetric:
        middle = middle - 0.5 * jnp.pi
    first, middle, third = _arrays.scalars(first, middle, third)
    # (t + pi) mod 2 pi - pi, by floor: jnp.remainder is a scalar fmod call on CPU
    wrap = lambda t: t - (2.0 * jnp.pi) * jnp.floor((t + jnp.pi) / (2.0 * jnp.pi))  # noqa: E731
    return _arrays.assemble(wrap(first), middle, wrap(third))


_to_euler = _derivatives.derivatives_in_one_loop(_to_euler_kernel, core=(1,), out_core=1)
