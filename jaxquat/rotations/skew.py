"""Skew-symmetric matrices of 3-vectors: ``hat`` (vector -> matrix) and ``vee`` (back).

``hat(w) @ v == cross(w, v)``. The angular-velocity matrices of the source
documents ([C] eqs. (45), (51); [T] eq. (37c)-(37d); [S] eq. (4)) are ``hat`` of
the angular velocity.
"""

from __future__ import annotations

from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks

__all__ = ["hat", "vee"]


def hat(v: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """The skew-symmetric cross-product matrix ``v~`` with ``v~ x = v x x``.

    ``[[0, -v3, v2], [v3, 0, -v1], [-v2, v1, 0]]``: [S] eq. (4), [C] ``a~`` under
    eq. (9), [T] ``[w~]`` in eq. (37c).
    """
    return _arrays.compiled_rows(_arrays.hat, (1,), _checks.vec3(v))


def vee(m: Float[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
    """The vector of the skew-symmetric part of ``m``: ``vee(hat(v)) == v``.

    ``vee(m) = (m32 - m23, m13 - m31, m21 - m12) / 2``. Averaging both
    off-diagonal entries makes ``vee`` the orthogonal projection onto skew
    matrices, so a rounding-perturbed ``R^T dR/dt`` still gives the best vector.
    """
    return _arrays.compiled_rows(_arrays.vee, (2,), _checks.mat3(m))
