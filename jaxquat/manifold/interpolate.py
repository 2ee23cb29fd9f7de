"""Interpolation between rotations: slerp, and Shoemake's squad through a sequence of keys.

Smooth timed splines with continuous angular acceleration are in :mod:`jaxquat.manifold.spline`.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _quaternion, _rotation

__all__ = ["slerp", "squad", "squad_control_points", "squad_segment"]


def slerp(
    p: Float[ArrayLike, "*#batch 4"], q: Float[ArrayLike, "*#batch 4"], t: Float[ArrayLike, "*#batch"] | float
) -> Float[Array, "*batch 4"]:
    """Spherical linear interpolation along the shortest arc: ``p (p* q')^t``, [T] eqs. (59)-(61).

    ``q' = sign(p.q) q`` picks the representative of ``q`` in ``p``'s
    hemisphere, so the path is the geodesic on SO(3) (rotation angle at most pi).
    Written as ``p exp(t log(p* q'))`` with ``log``/``exp`` series near the
    identity, so it is exact and smooth as ``p -> q`` (where the textbook form
    [T] eq. (63), ``sin((1-t)theta)/sin(theta)``, divides by zero). ``t = 0``
    gives ``p``, ``t = 1`` gives ``q'``; ``t`` outside [0, 1] extrapolates.
    Assumes unit ``p`` and ``q``. ``p``, ``q`` and ``t`` broadcast over batch axes.
    """
    p, q, t = _checks.arguments(p=(p, "quaternion"), q=(q, "quaternion"), t=(t, "scalar"), shared=True)
    return _arrays.compiled_rows(_rotation.slerp, (1, 1, 0), p, q, t)


def _control_points(keys: Array) -> Array:
    q = keys[..., 1:-1, :]
    qc = _quaternion.conjugate(q)
    r_next = _rotation.to_rotvec(_quaternion.multiply(qc, keys[..., 2:, :]))
    r_prev = _rotation.to_rotvec(_quaternion.multiply(qc, keys[..., :-2, :]))
    inner = _quaternion.multiply(q, _rotation.from_rotvec(-0.25 * (r_next + r_prev)))
    return jnp.concatenate([keys[..., :1, :], inner, keys[..., -1:, :]], axis=-2)


def squad_control_points(keys: Float[ArrayLike, "*batch n 4"]) -> Float[Array, "*batch n 4"]:
    """Shoemake's intermediate points ``s_i = q_i exp(-(log(q_i* q_(i+1)) + log(q_i* q_(i-1))) / 4)``.

    ``s_0 = q_0`` and ``s_(n-1) = q_(n-1)``. Keys are first sign-aligned (each
    flipped into the hemisphere of its predecessor), so keys given with either
    sign give the same curve; ``log`` of a relative rotation is the shortest one.
    """
    return _arrays.compiled(_aligned_keys_and_controls, _checks.quat(keys, "keys"))[1]


# Compiled whole (the shape check runs while tracing): called eagerly, the squad functions ran
# operation by operation, each compiled again for every new shape (the squad tests of
# test_spline.py and test_contract.py, float32: 32.8 s, now 21.4 s; _arrays.compiled). Inside a user's jit
# they inline.
def _aligned_keys_and_controls(keys: Array) -> tuple[Array, Array]:
    """Sign-aligned keys ``(..., n, 4)``, ``n >= 2``, and their squad control points."""
    if keys.ndim < 2 or keys.shape[-2] < 2:
        raise ValueError(f"argument 'keys' must be shaped (..., n, 4) with n >= 2, got shape {tuple(keys.shape)}")
    aligned = _rotation.align_signs(keys)
    return aligned, aligned if keys.shape[-2] == 2 else _control_points(aligned)


def squad_segment(
    q0: Float[ArrayLike, "*#batch 4"],
    q1: Float[ArrayLike, "*#batch 4"],
    s0: Float[ArrayLike, "*#batch 4"],
    s1: Float[ArrayLike, "*#batch 4"],
    h: Float[ArrayLike, "*#batch"] | float,
) -> Float[Array, "*batch 4"]:
    """One squad segment: ``slerp(slerp(q0, q1, h), slerp(s0, s1, h), 2 h (1 - h))`` for ``h`` in [0, 1]."""
    arrays = [_checks.quat(q0, "q0"), _checks.quat(q1, "q1"), _checks.quat(s0, "s0"), _checks.quat(s1, "s1")]
    h = _checks.scalar_like(h, "h")
    q0, q1, s0, s1, h = _checks.broadcast_batch([*arrays, h], ["q0", "q1", "s0", "s1", "h"], [1, 1, 1, 1, 0])
    return _arrays.compiled_rows(_squad_segment, (1, 1, 1, 1, 0), q0, q1, s0, s1, h)


def _squad_segment(q0: Array, q1: Array, s0: Array, s1: Array, h: Array) -> Array:
    return _rotation.slerp(_rotation.slerp(q0, q1, h), _rotation.slerp(s0, s1, h), 2 * h * (1 - h))


def squad(keys: Float[ArrayLike, "n 4"], u: Float[ArrayLike, "*shape"] | float) -> Float[Array, "*shape 4"]:
    """Shoemake's spherical cubic (squad) through ``keys`` at parameter ``u`` in ``[0, n-1]``.

    Key ``i`` is reached at ``u = i`` (uniform parameterisation); between keys
    ``i`` and ``i+1`` the curve is :func:`squad_segment` with the control points of
    :func:`squad_control_points` and ``h = u - i``. With uniform spacing the
    curve has a continuous first derivative across keys (tested by autodiff).
    ``u`` outside ``[0, n-1]`` extrapolates the end segments. Assumes unit keys.
    For keys at arbitrary times, with continuous angular acceleration, use
    :class:`jaxquat.RotationSpline`.
    """
    keys = _checks.quat(keys, "keys")
    if keys.ndim != 2:
        raise ValueError(f"argument 'keys' must be shaped (n, 4), got shape {tuple(keys.shape)}")
    return _arrays.compiled(_squad, keys, _checks.scalar_like(u, "u").astype(keys.dtype))


def _squad(keys: Array, u: Array) -> Array:
    aligned, controls = _aligned_keys_and_controls(keys)
    n = keys.shape[0]
    i = jnp.clip(jnp.floor(u), 0, n - 2).astype(jnp.int32)
    h = u - i.astype(u.dtype)
    return _squad_segment(aligned[i], aligned[i + 1], controls[i], controls[i + 1], h)
