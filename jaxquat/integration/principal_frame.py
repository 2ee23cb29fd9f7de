"""A rigid body's state in the principal axes of its inertia tensor, and back (the closed form and
the splitting solvers work there)."""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array

from .. import _arrays, _quaternion, _rotation
from ..mechanics.inertia import principal_axes

__all__ = ["from_principal", "to_principal"]


def to_principal(inertia: Array, q: Array, w: Array) -> tuple[Array, Array, Array, Array, Array]:
    """Diagonalise ``inertia`` (``I = A diag(moments) A^T``, ``A`` of ``q_axes``) and express the
    state in principal axes: ``(moments, q_axes, A, q q_axes, A^T w)``."""
    moments, q_axes = principal_axes(inertia)
    q_axes = jnp.broadcast_to(q_axes, q.shape[:-1] + (4,))
    r = _rotation.to_matrix(q_axes)
    return moments, q_axes, r, _quaternion.multiply(q, q_axes), _arrays.matvec(jnp.swapaxes(r, -1, -2), w)


def from_principal(qs: Array, ws: Array, q_axes: Array, r: Array) -> tuple[Array, Array]:
    """Back from principal axes: ``(q q_axes*, A w)``, ``q_axes`` and ``A`` broadcast onto the states."""
    q_axes = jnp.broadcast_to(q_axes, qs.shape)
    return _quaternion.multiply(qs, _quaternion.conjugate(q_axes)), _arrays.matvec(
        jnp.broadcast_to(r, ws.shape + (3,)), ws
    )
