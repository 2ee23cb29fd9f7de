"""Interpolation between rotations."""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jaxtyping import Float

from . import _checks, _safe
from .algebra import _conjugate, _multiply

__all__ = ["slerp"]


def slerp(
    p: Float[Array, "*batch 4"], q: Float[Array, "*batch 4"], t: Float[Array, "*batch"] | float
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
    p = _checks.quat(p, "p")
    q = _checks.quat(q, "q")
    t = _checks.scalar_like(t, "t")
    p, q, t = _checks.broadcast_batch([p, q, t], ["p", "q", "t"], [1, 1, 0])
    q = jnp.where((jnp.sum(p * q, axis=-1) < 0)[..., None], -q, q)
    r = _multiply(_conjugate(p), q)
    w, v = r[..., 0], r[..., 1:]
    nsq = _safe.norm_sq(v)
    scale = t * _safe.atan2_over_n(nsq, w)  # t * (half angle) / |v|
    usq = scale * scale * nsq
    step = jnp.concatenate([_safe.cos_of_sq(usq)[..., None], (scale * _safe.sinc_of_sq(usq))[..., None] * v], axis=-1)
    return _multiply(p, step)
