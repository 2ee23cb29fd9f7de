"""Skew-symmetric matrices of 3-vectors: ``hat`` (vector -> matrix) and ``vee`` (back).

``hat(w) @ v == cross(w, v)``. The angular-velocity matrices of the source
documents ([C] eqs. (45), (51); [T] eq. (37c)-(37d); [S] eq. (4)) are ``hat`` of
the angular velocity.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jaxtyping import Float

from . import _checks

__all__ = ["hat", "vee"]


def _hat(v: Array) -> Array:
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], axis=-2)


def hat(v: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """The skew-symmetric cross-product matrix ``v~`` with ``v~ x = v x x``.

    ``[[0, -v3, v2], [v3, 0, -v1], [-v2, v1, 0]]``: [S] eq. (4), [C] ``a~`` under
    eq. (9), [T] ``[w~]`` in eq. (37c).
    """
    return _hat(_checks.vec3(v))


def _matvec(m: Array, v: Array) -> Array:
    """``m @ v`` for stacks of 3x3 matrices, written out per component: XLA fuses it, while a
    ``sum`` over the minor axis of size 3 compiles to a slow reduction loop on CPU (measured 20x)."""
    return jnp.stack(
        [m[..., i, 0] * v[..., 0] + m[..., i, 1] * v[..., 1] + m[..., i, 2] * v[..., 2] for i in range(3)], axis=-1
    )


def _vee(m: Array) -> Array:
    return 0.5 * jnp.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], axis=-1
    )


def vee(m: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """The vector of the skew-symmetric part of ``m``: ``vee(hat(v)) == v``.

    ``vee(m) = (m32 - m23, m13 - m31, m21 - m12) / 2``. Averaging both
    off-diagonal entries makes ``vee`` the orthogonal projection onto skew
    matrices, so a rounding-perturbed ``R^T dR/dt`` still gives the best vector.
    """
    return _vee(_checks.mat3(m))
