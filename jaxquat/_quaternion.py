"""Quaternion kernels: the Hamilton product, conjugate, rotation of vectors, the canonical sign
and component packing, on arrays already validated and broadcast.

The public functions of :mod:`jaxquat.rotations.algebra` (and every other module) check their
arguments once and then call these; inside the package the kernels are called directly, so
validation runs once per entry point. Names here are plain: the module's leading underscore
says "not public API", a name's says "only used in this module". Element-wise on the four
components throughout, so XLA fuses a whole expression into one loop over the batch.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import cast

import jax
import jax.numpy as jnp
from jax import Array


def split(q: Array):
    """The four components ``(w, x, y, z)`` of ``q``."""
    return q[..., 0], q[..., 1], q[..., 2], q[..., 3]


def _pack(w, x, y, z) -> Array:
    """The quaternion ``(..., 4)`` stacked from four component arrays."""
    return jnp.stack([w, x, y, z], axis=-1)


def scaled(scale: Array, v: Array) -> Array:
    """``scale[..., None] * v`` for ``v`` ``(..., 3)``, per component (see :func:`scalar_vector`)."""
    return jnp.stack([scale * v[..., 0], scale * v[..., 1], scale * v[..., 2]], axis=-1)


def scalar_vector(s: Array, v: Array, scale: Array | None = None) -> Array:
    """The quaternion ``(s, scale v)`` from ``(...)``, ``(..., 3)`` and an optional ``(...)``.

    Stacked from components: XLA on CPU compiles ``concatenate([s[..., None], v], -1)``
    into a slower, branching loop. (Multiplying each component by ``scale`` separately
    instead of ``scale[..., None] * v`` made slerp 10x slower at 10^6: keep the broadcast.)
    """
    if scale is not None:
        v = scale[..., None] * v
    return _pack(s, v[..., 0], v[..., 1], v[..., 2])


def _permuted(x: Array, k: int) -> Array:
    """The components of ``x`` in the orders (0123), (1032), (2301), (3210): no reversal,
    reversal within pairs, of the pairs, of all four (cheap strided copies, unlike a gather)."""
    if k == 0:
        return x
    if k == 3:
        return x[..., ::-1]
    pairs = x.reshape(x.shape[:-1] + (2, 2))
    return (pairs[..., ::-1] if k == 1 else pairs[..., ::-1, :]).reshape(x.shape)


# p q = sum_k p_k (L_k q) = sum_k q_k (R_k p), with L_k, R_k = signs * _permuted(., k). The signs
# follow from (p0, p) (q0, q) = (p0 q0 - p.q,  p0 q + q0 p + p x q).
_LEFT_SIGNS = ((1.0, 1.0, 1.0, 1.0), (-1.0, 1.0, -1.0, 1.0), (-1.0, 1.0, 1.0, -1.0), (-1.0, -1.0, 1.0, 1.0))
_RIGHT_SIGNS = ((1.0, 1.0, 1.0, 1.0), (-1.0, 1.0, 1.0, -1.0), (-1.0, -1.0, 1.0, 1.0), (-1.0, 1.0, -1.0, 1.0))


def _weighted_permutations(weights: Array, x: Array, signs) -> Array:
    """``sum_k weights_k (signs_k * _permuted(x, k))``: linear in ``x`` through whole rows."""
    table = jnp.asarray(signs, x.dtype).reshape((4,) + (1,) * (x.ndim - 1) + (4,))
    terms = [weights[..., k : k + 1] * (table[k] * _permuted(x, k)) for k in range(4)]
    return ((terms[0] + terms[1]) + terms[2]) + terms[3]  # sum()'s order


@jax.custom_jvp
def multiply(p: Array, q: Array) -> Array:
    """Hamilton product without argument checks (inputs already broadcast).

    Written as ``sum_k p_k (L_k q)`` where ``L_k q`` permutes and signs the components
    of ``q``: every term is a whole ``(..., 4)`` row, so XLA emits one vectorised loop
    (splitting into components and stacking them back ran about 3x slower on CPU).
    The JVP is ``p dq + dp q`` with the second term written as ``sum_k q_k (R_k dp)``,
    so both tangents enter through permutations of whole rows, and reverse mode
    transposes them into permutations again. (The transpose of the broadcast ``p_k``
    would be a reduction over the minor axis, which XLA on CPU runs about 20x slower:
    74 ms against 5.7 ms for the gradient at 10^6 in float32.)
    """
    return _weighted_permutations(p, q, _LEFT_SIGNS)


@multiply.defjvp
def _multiply_jvp(primals, tangents):
    (p, q), (dp, dq) = primals, tangents
    return multiply(p, q), _weighted_permutations(p, dq, _LEFT_SIGNS) + _weighted_permutations(q, dp, _RIGHT_SIGNS)


# The Hamilton product's components: w = p0 q0 - p1 q1 - p2 q2 - p3 q3, etc., as
# (sign, index in p, index in q) per term.
_PRODUCT_TERMS = (
    ((1, 0, 0), (-1, 1, 1), (-1, 2, 2), (-1, 3, 3)),
    ((1, 0, 1), (1, 1, 0), (1, 2, 3), (-1, 3, 2)),
    ((1, 0, 2), (-1, 1, 3), (1, 2, 0), (1, 3, 1)),
    ((1, 0, 3), (1, 1, 2), (-1, 2, 1), (1, 3, 0)),
)


def multiply_components(p: Sequence[Array | None], q: Sequence[Array | None]) -> list[Array | None]:
    """The Hamilton product ``p q`` on components (lists of four arrays), ``None`` standing
    for an exact zero: the terms with a zero factor are left out instead of multiplied (XLA
    cannot drop them, as ``0 * x`` is not 0 for every float), so a product of elementary
    rotations costs what its written-out formula does. For kernels written on components
    (:func:`jaxquat._arrays.components`); a component of the result is ``None`` only when
    every term of it has a zero factor."""
    out: list[Array | None] = []
    for terms in _PRODUCT_TERMS:
        total = None
        for sign, i, j in terms:
            a, b = p[i], q[j]
            if a is None or b is None:
                continue
            term = a * b
            total = (term if sign > 0 else -term) if total is None else (total + term if sign > 0 else total - term)
        out.append(total)
    return out


def multiply_dense(p: Sequence[Array], q: Sequence[Array]) -> list[Array]:
    """:func:`multiply_components` of two quaternions given as four component arrays each."""
    return cast(list[Array], multiply_components(p, q))


def conjugate(q: Array) -> Array:
    """``q* = (q0, -q)``."""
    return jnp.stack([q[..., 0], -q[..., 1], -q[..., 2], -q[..., 3]], axis=-1)


def rotate(q: Array, v: Array) -> Array:
    """``v + 2 w (u x v) + 2 u x (u x v)`` for ``q = (w, u)``: the rotation of ``v`` by unit ``q``."""
    return jnp.stack(rotate_components(split(q), (v[..., 0], v[..., 1], v[..., 2])), axis=-1)


def rotate_components(q: Sequence[Array], v: Sequence[Array]) -> list[Array]:
    """:func:`rotate` on components (four arrays and three)."""
    w, ux, uy, uz = q
    vx, vy, vz = v
    # t = 2 u x v ;  v' = v + w t + u x t
    tx = 2.0 * (uy * vz - uz * vy)
    ty = 2.0 * (uz * vx - ux * vz)
    tz = 2.0 * (ux * vy - uy * vx)
    return [
        vx + w * tx + (uy * tz - uz * ty),
        vy + w * ty + (uz * tx - ux * tz),
        vz + w * tz + (ux * ty - uy * tx),
    ]


def canonical_sign(w, x, y, z) -> Array:
    """+1 or -1: the sign that puts ``(w, x, y, z)`` in the canonical hemisphere."""
    flip = (w < 0) | ((w == 0) & ((x < 0) | ((x == 0) & ((y < 0) | ((y == 0) & (z < 0))))))
    return jnp.where(flip, -1.0, 1.0).astype(w.dtype)


def canonicalize(q: Array) -> Array:
    """``q`` or ``-q``, whichever is in the canonical hemisphere (see :func:`canonical_sign`)."""
    return q * canonical_sign(*split(q))[..., None]


def pure(v: Array) -> Array:
    """The pure quaternion ``(0, v)``."""
    return scalar_vector(jnp.zeros_like(v[..., 0]), v)
